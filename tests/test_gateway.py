"""The gateway install: the agent learns and monitors from recorded files with scipy, numba and
matplotlib made unimportable (what `make gateway` leaves out), and the workbench's commands
say what to install instead of failing with a traceback."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from agent.records import save_record
from runtime_support import PROFILE_PATH, RELAXED_GROSS, ROOT, sim

pytestmark = pytest.mark.timeout(300)

BLOCK_WORKBENCH = "import sys\nfor m in ('scipy', 'numba', 'matplotlib', 'llvmlite'):\n    sys.modules[m] = None\n"


def test_learning_and_monitoring_need_no_workbench_library(tmp_path):
    files = [str(save_record(sim("healthy", 80.0, 8.0, 900 + j), tmp_path / f"h{j}.npz")) for j in range(14)]
    fault = str(save_record(sim("gear_severe_wear", 80.0, 8.0, 950), tmp_path / "severe.npz"))
    code = BLOCK_WORKBENCH + f"""
import json, tempfile
from agent.evidence import AlarmConfig
from agent.library import ModelLibrary
from agent.pipeline import DriveMonitor, PipelineConfig
from agent.playback import replay_source
from agent.profile import load_profile
profile = load_profile({str(PROFILE_PATH)!r})
lib = ModelLibrary(tempfile.mkdtemp())
alarm = AlarmConfig(stretch_s=4.0, gross_false_alarms_per_month={RELAXED_GROSS})
cfg = PipelineConfig(learn_windows=6, learn_stretches=8, learn_min_s=0.0, alarm=alarm)
mon = DriveMonitor("d1", profile, lib, cfg)
mon.start_learning("b80")
def play(paths):
    src = replay_source(paths, "d1", profile, speedup=0.0)
    src.open()
    out = []
    while not src.finished:
        b = src.read(0.1)
        if b is not None:
            out += mon.process(b)
    return out
play({files!r})
states = [s.state for s in play([{fault!r}])]
import numpy as np
from agent.identify import FitResult, constrain
from agent.model import DQModel, lumped_params
d, q = lumped_params("lumped", 4e-5, -0.5, 0.015, 0.028, 0.25, 2 * np.pi * 100)  # negative R: implausible
fit = FitResult(DQModel("lumped", 4e-5, d, q, (), (), fe_hz=100.0), np.zeros(2), np.eye(3) * 1e6, np.eye(4) * 1e6)
constrain(fit, 0.25)
constrained = all(fit.model.physical()[k] > 0 for k in ("Rs_d", "Rs_q", "Ld", "Lq"))
print(json.dumps({{"learned": sorted(lib.baselines), "constrained": constrained,
                  "states": states, "workbench": [m for m in ("scipy", "numba", "matplotlib") if sys.modules.get(m)]}}))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=str(ROOT), timeout=240)
    assert out.returncode == 0, out.stderr[-2000:]
    doc = json.loads(out.stdout.strip().splitlines()[-1])
    assert doc["learned"] == ["b80"] and doc["workbench"] == []
    assert doc["constrained"]  # an implausible fit is constrained with numpy alone
    assert "warning" in doc["states"]


def test_workbench_commands_name_the_missing_install(tmp_path):
    code = BLOCK_WORKBENCH + ("from agent.cli import main\n"
                              f"raise SystemExit(main(['simulate', '--profile', {str(PROFILE_PATH)!r}, '--out', "
                              f"{str(tmp_path / 'x.npz')!r}]))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=str(ROOT), timeout=60)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1 and "pmsm-agent[workbench]" in out.stderr
