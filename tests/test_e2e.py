"""End to end: a drive emulator streams healthy, then faulty (gear_severe_wear) phase data to the
agent, which runs as its own process (``pmsm-agent run --config``); a PLC client (Modbus TCP) and
a zenoh subscriber in this test process watch it.

Per transport:

* ``serial``: ``SerialBridgeEmulator`` on a pty (this process writes the master side, the agent
  opens the pty's path as its serial port). **The short form runs only this one.**
* ``can``: ``CanEmulator`` on the python-can ``virtual`` bus. That bus exists only inside one
  process, so the emulator runs in the agent's process: a small launcher starts it, then calls
  ``pmsm-agent run`` in the same interpreter (the agent is still a process of its own, apart from
  the observers here). Full form only (``PMSM_SLOW=full``).
* ``modbus``: ``DriveModbusEmulator`` (TCP) in this process; the agent triggers and reads 4 s
  snapshots (a whole span, 100 000 samples each), about 6 s apiece, so this takes ~1 min.
  Full form only.

Each scenario: the agent starts with a baseline already in its library (identified here from 12
simulated healthy 4 s records, so it needs no learning); both observers see quality good/state
normal; the emulator switches to the fault; both see caution or warning; SIGKILL of the agent
makes its zenoh liveliness token disappear (DELETE); a restarted agent keeps the journal (the
first run's events are listed by ``pmsm-agent events --state-dir D --json``); SIGTERM stops it
cleanly (exit 0, ``stop`` journalled). Before SIGKILL the emulator stops: quality goes stale on
both channels (last values kept) while the heartbeat goes on. The full form also streams 20 s
more of healthy data before the fault (no false alarm).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh

from agent.modelfile import save_baseline
from firmware_if import plc_registers
from protocols.zenoh_sink import zenoh_config
from runtime_support import (PROFILE_PATH, RATE, RELAXED_GROSS, ROOT, PlcPoller, Samples, condition_stream, free_port,
                             healthy_baseline, sim, wait_for)

pytestmark = [pytest.mark.slow, pytest.mark.timeout(600)]

PMSM_AGENT = str(ROOT / ".venv" / "bin" / "pmsm-agent")
PREFIX = "e2e/pmsm"
DRIVE = "drive1"
TRANSPORTS = ("serial", "can", "modbus")
SHORT_FORM = ("serial",)
CAN_CHANNEL = "pmsm-e2e"
ALARM = ("caution", "warning")


@pytest.fixture(scope="module")
def drive_records():
    """12 s healthy and 12 s faulty of the same seed (the switch continues at the same sample: the
    fault appears without a jump), played in a loop by the emulators with a gap at each restart."""
    return {"healthy": sim("healthy", 80.0, 12.0, 301), "fault": sim("gear_severe_wear", 80.0, 12.0, 301)}


CAN_LAUNCHER = """
# the CAN drive emulator and the agent in one process (python-can's virtual bus is in-process)
import json, sys, threading, time
from types import SimpleNamespace
import can, numpy as np
sys.path.insert(0, {tests!r})
from runtime_support import condition_stream
from protocols.can_bus import CanEmulator
from pathlib import Path

spec = json.loads(Path(sys.argv[1]).read_text())
data = np.load(spec["records"])
records = {{k: SimpleNamespace(v_abc=data[k + "_v"], i_abc=data[k + "_i"]) for k in ("healthy", "fault")}}
flag, quiet = Path(spec["flag"]), Path(spec["quiet"])

def device():
    emu = None
    bus = can.Bus(interface="virtual", channel=spec["channel"], fd=True, ignore_config=True)
    from can.interfaces import virtual
    while True:  # frames sent before the agent's bus exists would be lost
        with virtual.channels_lock:
            if len(virtual.channels.get(spec["channel"], [])) >= 2:
                break
        time.sleep(0.02)
    stream = condition_stream(records, flag.exists, stop=quiet.exists, on_wrap=lambda: emu.drop_frames(100))
    emu = CanEmulator(bus, stream, rate_hz=spec["rate"], speed=1.0)
    emu.start()

threading.Thread(target=device, daemon=True).start()
from agent.cli import main
sys.exit(main(["run", "--config", spec["config"]]))
"""


class Agent:
    """The agent process; its stdout/stderr go to ``log``."""

    def __init__(self, argv: list[str], log: Path):
        self.argv, self.log = argv, log
        self.proc: subprocess.Popen | None = None

    def start(self) -> None:
        env = {k: v for k, v in os.environ.items() if k not in ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID")}
        env.update(PYTHONUNBUFFERED="1", PYTHONFAULTHANDLER="1")
        with open(self.log, "ab") as f:
            f.write(f"--- start {' '.join(self.argv)}\n".encode())
            self.proc = subprocess.Popen(self.argv, stdout=f, stderr=subprocess.STDOUT, env=env, cwd=self.log.parent)

    def signal(self, sig) -> None:
        self.proc.send_signal(sig)

    def wait(self, timeout: float) -> int:
        return self.proc.wait(timeout)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)

    def tail(self, n: int = 40) -> str:
        lines = self.log.read_text(errors="replace").splitlines() if self.log.exists() else []
        return "\n".join(lines[-n:])


def agent_config(tmp: Path, source: str, mb_port: int, z_port: int) -> Path:
    state = tmp / "state"
    save_baseline(healthy_baseline(), state / "library" / f"{DRIVE}_80pct.json")
    path = tmp / "agent.toml"
    path.write_text(f"""
schema_version = 1
agent_id = "e2e"
state_dir = "{state}"

[[drives]]
name = "{DRIVE}"
profile = "{PROFILE_PATH}"

[drives.source]
{textwrap.dedent(source).strip()}

[pipeline]
window_s = 2.0
hop_s = 0.5
persist_hops = 2
alarm_hold_s = 10.0
stale_after_s = 3.0
auto_learn = false
gross_false_alarms_per_month = {RELAXED_GROSS}

[modbus_server]
host = "127.0.0.1"
port = {mb_port}

[zenoh]
mode = "peer"
listen = []
connect = ["tcp/127.0.0.1:{z_port}"]
prefix = "{PREFIX}"
period_s = 0.5

[zenoh.inline]
"scouting/delay" = 0
""")
    return path


def events(state: Path) -> list[dict]:
    r = subprocess.run([PMSM_AGENT, "events", "--state-dir", str(state), "--json", "--limit", "10000"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)["events"]  # oldest first, as `events` lists them


def docs(samples: Samples, since: float = 0.0) -> list[dict]:
    return [json.loads(p) | {"_t": t} for _, p, _, t in samples.snapshot() if t >= since]


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_drive_to_plc_and_zenoh(transport, tmp_path, drive_records, full_form):
    if transport not in SHORT_FORM and not full_form:
        pytest.skip("full form only (PMSM_SLOW=full)")
    mb_port, z_port = free_port(), free_port()
    flag, quiet_flag = tmp_path / "fault.flag", tmp_path / "quiet.flag"
    switch = flag.exists
    device = {}
    cleanup = []  # run last-in first-out
    scada = zenoh.open(zenoh_config("peer", [f"tcp/127.0.0.1:{z_port}"], [], {"scouting/delay": 0}))
    cleanup.append(scada.close)
    states, alive = Samples(), Samples()
    subs = [scada.declare_subscriber(f"{PREFIX}/{DRIVE}/state", states),
            scada.liveliness().declare_subscriber(f"{PREFIX}/agent/**", alive, history=True)]
    cleanup.extend(s.undeclare for s in subs)
    token = f"{PREFIX}/agent/e2e/alive"
    start_device = None
    try:
        if transport == "serial":
            from protocols.ptyutil import Pty
            from protocols.serial_bridge import SerialBridgeEmulator

            pty = Pty()
            cleanup.append(pty.close)
            source = f'kind = "serial"\nport = "{pty.path}"\nbaud = 4000000'

            def start_device():
                stream = condition_stream(drive_records, switch, on_wrap=lambda: emu.drop_frames(8))
                emu = SerialBridgeEmulator(pty.master, stream, rate_hz=RATE, speed=1.0)
                cleanup.append(emu.stop)
                device["quiet"] = emu.stop
                emu.start()
            argv_extra = None
        elif transport == "can":
            source = (f'kind = "can"\ninterface = "virtual"\nchannel = "{CAN_CHANNEL}"\n'
                      'base_id = 0x0A500000\nextended = true')
            npz = tmp_path / "records.npz"
            np.savez(npz, **{f"{k}_{c}": getattr(r, f"{c}_abc") for k, r in drive_records.items() for c in "vi"})
            launcher = tmp_path / "can_launcher.py"
            launcher.write_text(CAN_LAUNCHER.format(tests=str(Path(__file__).parent)))
            argv_extra = [sys.executable, str(launcher), str(tmp_path / "spec.json")]
            device["quiet"] = quiet_flag.touch
        else:
            from protocols.modbus_drive import DriveModbusEmulator

            offset = [0]

            def snapshot(first, n):  # the next contiguous n samples of the current condition's record
                rec = drive_records["fault" if switch() else "healthy"]
                a = offset[0] if offset[0] + n <= rec.n else 0
                offset[0] = a + n
                return np.vstack([rec.v_abc[:, a:a + n], rec.i_abc[:, a:a + n]])

            emu = DriveModbusEmulator(snapshot, rate_hz=RATE, scales=(0.05, 0.05, 0.05, 0.002, 0.002, 0.002))
            emu.start()
            cleanup.append(emu.close)
            device["quiet"] = emu.stop
            source = (f'kind = "modbus"\nhost = "127.0.0.1"\nport = {emu.address[1]}\n'
                      'poll_interval_s = 0.05\ntimeout_s = 2.0')
            argv_extra = None
        cfg = agent_config(tmp_path, source, mb_port, z_port)
        if transport == "can":
            (tmp_path / "spec.json").write_text(json.dumps({"records": str(npz), "flag": str(flag), "rate": RATE,
                                                            "quiet": str(quiet_flag), "channel": CAN_CHANNEL,
                                                            "config": str(cfg)}))
        agent = Agent(argv_extra or [PMSM_AGENT, "run", "--config", str(cfg)], tmp_path / "agent.log")
        cleanup.append(agent.stop)
        t0 = time.monotonic()
        agent.start()
        alive.wait(lambda k, p, kind: k == token and kind == zenoh.SampleKind.PUT, 60, "the agent's liveliness token")
        t_up = time.monotonic() - t0
        if start_device is not None:
            start_device()
        plc = PlcPoller(mb_port)
        cleanup.append(plc.close)

        # 1. healthy: quality good, state normal on both channels
        try:
            states.wait(lambda k, p, kind: json.loads(p)["quality"] == "good", 60, "quality good on zenoh")
            wait_for(lambda: any(d == [0, 0] for _, _, d in plc.reads), 10, what="good/normal on Modbus")
        except AssertionError as err:
            raise AssertionError(f"{err}\n{agent.tail()}") from None
        good = [d for d in docs(states) if d["quality"] == "good"]
        assert good[0]["state"] == "normal" and abs(good[0]["fe_hz"] - 100.0) < 1.0
        assert {"state", "quality", "spectrum_state", "cluster_state", "fe_hz", "load_pct", "t"} <= good[0].keys()
        g = plc.reads[-1][1]
        assert g[0] == plc_registers.MAP_VERSION and g[2] == 1

        # 2. the fault: caution or warning on both channels (the full form first streams 20 s more
        # of healthy data: no false alarm meanwhile, checked below)
        time.sleep(20.0 if full_form else 1.0)
        t_fault = time.monotonic()
        flag.touch()
        limit = 90 if transport == "modbus" else 30
        try:
            states.wait(lambda k, p, kind: json.loads(p)["state"] in ALARM, limit, "an alarm on zenoh")
            wait_for(lambda: any(d[0] in (1, 2) for _, _, d in plc.reads), 10, what="an alarm on Modbus")
        except AssertionError as err:
            raise AssertionError(f"{err}\n{agent.tail()}") from None
        before = [d for d in docs(states) if d["_t"] < t_fault]
        assert before and all(d["state"] == "normal" for d in before), [d["state"] for d in before]
        first_alarm = [d for d in docs(states) if d["state"] in ALARM][0]
        t_alarm = first_alarm["_t"] - t_fault
        assert first_alarm["quality"] == "good"
        if transport == "modbus":  # every snapshot held a whole span: 2 windows of 2 s
            assert {c.raw.shape[1] for c in emu.stats.history} == {int(4.0 * RATE)}
        beats = [(t, g[1]) for t, g, _ in plc.reads]
        assert (beats[-1][1] - beats[0][1]) % 65536 >= int(beats[-1][0] - beats[0][0]) - 1  # heartbeat lives

        # 3. the drive goes quiet: quality stale with the last values kept, the heartbeat goes on
        last = docs(states)[-1]
        t_quiet = time.monotonic()
        monitored = [d["quality"] for d in docs(states, good[0]["_t"])]
        assert set(monitored) == {"good"}, f"quality flapped while the drive was streaming: {monitored}"
        device["quiet"]()
        try:
            wait_for(lambda: [d for d in docs(states, t_quiet) if d["quality"] == "stale"], 30,
                     what="quality stale on zenoh")
            wait_for(lambda: any(d[1] == 3 for t, _, d in plc.reads if t > t_quiet), 10, what="stale on Modbus")
        except AssertionError as err:
            raise AssertionError(f"{err}\n{agent.tail()}") from None
        stale = [d for d in docs(states, t_quiet) if d["quality"] == "stale"][0]
        assert stale["fe_hz"] is not None and abs(stale["fe_hz"] - last["fe_hz"]) < 1.0
        t_stale = stale["_t"] - t_quiet
        time.sleep(1.2)
        quiet_beats = [g[1] for t, g, _ in plc.reads if t > t_quiet]
        assert quiet_beats[-1] != quiet_beats[0], "the heartbeat must go on while the data is stale"

        # 4. SIGKILL: the liveliness token goes
        n_before = len(alive.snapshot())
        t_kill = time.monotonic()
        agent.signal(signal.SIGKILL)
        agent.wait(10)
        alive.wait(lambda k, p, kind: k == token and kind == zenoh.SampleKind.DELETE, 15, "liveliness DELETE")
        t_delete = [t for k, _, kind, t in alive.snapshot()[n_before:] if kind == zenoh.SampleKind.DELETE][0] - t_kill
        first_run = events(tmp_path / "state")

        # 5. restart: the journal keeps the first run's events
        agent.start()
        wait_for(lambda: [kind for k, _, kind, _ in alive.snapshot()].count(zenoh.SampleKind.PUT) >= 2, 60,
                 what="the restarted agent's liveliness token")
        wait_for(lambda: [e for e in events(tmp_path / "state") if e["kind"] == "start"][1:], 10,
                 what="the second start in the journal")
        listed = events(tmp_path / "state")
        starts = [e["id"] for e in listed if e["kind"] == "start"]
        assert len(starts) == 2
        kept = [e for e in listed if e["id"] < starts[1]]
        assert [e["id"] for e in kept] == [e["id"] for e in first_run]  # nothing of the first run lost
        alarms = [e for e in kept if e["kind"] == "state" and e["state"] in ALARM]
        assert alarms and alarms[0]["drive"] == DRIVE
        assert any(e["kind"] == "quality" and e["quality"] == "good" for e in kept)
        assert any(e["kind"] == "quality" and e["quality"] == "stale" for e in kept)

        # 6. SIGTERM: a clean stop
        agent.signal(signal.SIGTERM)
        assert agent.wait(30) == 0, agent.tail()
        assert events(tmp_path / "state")[-1]["kind"] == "stop"
        print(f"\n{transport}: agent up {t_up:.1f} s, alarm {t_alarm:.1f} s after the switch, "
              f"stale {t_stale:.1f} s after the drive stopped, "
              f"liveliness DELETE {1000 * t_delete:.0f} ms after SIGKILL")
    finally:
        for fn in reversed(cleanup):
            try:
                fn()
            except Exception:  # noqa: BLE001
                pass
