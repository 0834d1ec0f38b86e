"""config/pmsm-agent.service: `systemd-analyze verify` passes and the hardening keys are there."""

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from agent.runtime.config import MEMORY_LIMIT_MB

UNIT = Path(__file__).resolve().parent.parent / "config" / "pmsm-agent.service"


def sections(text):
    out, cur = {}, None
    for line in text.splitlines():
        if line.startswith("["):
            cur = out.setdefault(line.strip("[]"), [])
        elif line and not line.startswith("#") and cur is not None:
            cur.append(tuple(line.split("=", 1)))
    return out


def test_unit_keys():
    text = UNIT.read_text()
    s = sections(text)
    svc = dict(s["Service"])
    assert svc["Type"] == "notify" and svc["NotifyAccess"] == "main" and svc["Restart"] == "on-failure"
    assert svc["WatchdogSec"] and svc["ExecReload"] == "/bin/kill -HUP $MAINPID"
    assert "run --config" in svc["ExecStart"]
    for key, value in {"DynamicUser": "yes", "StateDirectory": "pmsm-agent", "ConfigurationDirectory": "pmsm-agent",
                       "ProtectSystem": "strict", "NoNewPrivileges": "yes", "SupplementaryGroups": "dialout",
                       "RestrictAddressFamilies": "AF_UNIX AF_INET AF_INET6 AF_CAN AF_NETLINK"}.items():
        assert svc[key] == value, key
    # the rule in the unit's comments: MemoryHigh is the largest estimate check-config accepts, MemoryMax 25 % more
    assert svc["MemoryHigh"] == f"{MEMORY_LIMIT_MB:.0f}M" and svc["MemoryMax"] == f"{1.25 * MEMORY_LIMIT_MB:.0f}M"
    assert svc["CPUQuota"] == "170%"
    assert "OPENBLAS_NUM_THREADS=1" in " ".join(v for k, v in s["Service"] if k == "Environment")
    assert ("DeviceAllow", "char-ttyUSB rw") in s["Service"] and ("DeviceAllow", "char-ttyACM rw") in s["Service"]
    assert {"StartLimitIntervalSec", "StartLimitBurst"} <= {k for k, _ in s["Unit"]}
    assert not {"StartLimitIntervalSec", "StartLimitBurst"} & set(svc)
    assert not re.search(r"^[^#\n][^\n]*=[^\n]*[ \t]#", text, re.M), "systemd has no trailing comments"


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_systemd_analyze_verify_and_security(tmp_path):
    unit = tmp_path / UNIT.name  # ExecStart must name an existing binary for verify
    unit.write_text(re.sub(r"^ExecStart=\S+", f"ExecStart={sys.executable}", UNIT.read_text(), flags=re.M))
    r = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and not r.stderr.strip(), r.stderr
    r = subprocess.run(["systemd-analyze", "security", "--offline=true", str(unit)], capture_output=True,
                       text=True, timeout=60)
    m = re.search(r"Overall exposure level for \S+: ([0-9.]+) (\w+)", r.stdout)
    assert m, r.stdout + r.stderr
    print(f"\nsystemd-analyze security --offline=true: {m.group(1)} {m.group(2)}")
    assert float(m.group(1)) <= 3.0
