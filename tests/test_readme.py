"""The README works verbatim: its shell blocks run in a fresh folder (the project's config/ and
.venv beside them, nothing else), exit 0, and the offline tour ends at the diagnosis it promises;
so does docs/workbench.md's walkthrough."""

from __future__ import annotations

import os
import re
import shutil
import subprocess

import pytest

from runtime_support import ROOT, free_port

pytestmark = pytest.mark.timeout(300)

#: commands that run until stopped (the service): run for RUN_S seconds, then SIGTERM
LONG_RUNNING = re.compile(r"pmsm-agent run --config ")
RUN_S = 10


def shell_blocks(doc: str = "README.md") -> list[str]:
    return re.findall(r"```sh\n(.*?)```", (ROOT / doc).read_text(), flags=re.S)


@pytest.fixture
def fresh(tmp_path):
    """A fresh folder with the project's config/ (the shipped agent config's fixed Modbus and zenoh
    ports moved to free ones, so the test collides with nothing) and the .venv."""
    shutil.copytree(ROOT / "config", tmp_path / "config")
    cfg = tmp_path / "config" / "agent.toml"
    cfg.write_text(cfg.read_text().replace("port = 5020", f"port = {free_port()}")
                   .replace("tcp/127.0.0.1:7447", f"tcp/127.0.0.1:{free_port()}"))
    (tmp_path / ".venv").symlink_to(ROOT / ".venv")
    return tmp_path


def run_block(block: str, cwd) -> subprocess.CompletedProcess:
    lines = [f"timeout -s TERM {RUN_S} {re.sub(r'[ ]+#.*$', '', line)} || test $? -eq 124"
             if LONG_RUNNING.search(line) else line for line in block.splitlines()]
    script = "set -e\n" + ("" if lines and lines[0].startswith(". .venv") else ". .venv/bin/activate\n") + "\n".join(lines)
    env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "STATE_DIRECTORY")}
    return subprocess.run(["bash", "-c", script], cwd=cwd, capture_output=True, text=True, env=env, timeout=280)


#: a load figure as the commands print it: "load 82.7 %", "load 61-105 %", "drive1_100hz_83pct"
LOAD_FIGURES = re.compile(r"load (\d+(?:\.\d+)?)(?:-(\d+(?:\.\d+)?))? %|_(\d+)pct\b")


def requested_loads(block: str, default: float = 80.0) -> set[float]:
    """The loads a block's commands ask the simulator for (``--load``, else the default)."""
    asked = {float(x) for x in re.findall(r"--load\s+(\d+(?:\.\d+)?)", block)}
    return asked or {default}


def assert_loads_match(text: str, requested: set[float], tolerance: float = 5.0) -> None:
    """Every load figure printed (load is torque over rated torque) lies within ``tolerance``
    %-points of a load that was asked for; a range's ends of the lowest and highest asked."""
    figures = []
    for lo, hi, name in LOAD_FIGURES.findall(text):
        if hi:
            assert abs(float(lo) - min(requested)) <= tolerance and abs(float(hi) - max(requested)) <= tolerance, \
                (lo, hi, requested)
        figures += [float(x) for x in (lo, hi, name) if x]
    assert figures, text[-2000:]
    far = [f for f in figures if min(abs(f - r) for r in requested) > tolerance]
    assert not far, (far, requested)


def test_the_offline_tour_ends_at_the_promised_diagnosis(fresh):
    tour = shell_blocks()[0]
    assert "diagnose" in tour and "gear_severe_wear" in tour
    r = run_block(tour, fresh)
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr
    assert "runs/severe.csv: WARNING" in r.stdout, r.stdout[-2000:]
    assert "verdict: gear_driven most likely at fault" in r.stdout, r.stdout[-2000:]
    assert_loads_match(r.stdout, requested_loads(tour))
    assert (fresh / "runs" / "gear80.json").is_file() and len(list((fresh / "runs").glob("healthy_*.npz"))) == 30


def test_every_other_block_runs(fresh):
    """The agent block: check the config, run the agent for a while, list its journal."""
    for block in shell_blocks()[1:]:
        r = run_block(block, fresh)
        assert r.returncode == 0, (block, r.stderr)
        assert "Traceback" not in r.stderr
        if "events" in block:
            assert " start " in r.stdout and "learning" in r.stdout, r.stdout
            asked = re.search(r"^load_pct = (\S+)", (fresh / "config" / "agent.toml").read_text(), flags=re.M)
            if LOAD_FIGURES.search(r.stdout):
                assert_loads_match(r.stdout, {float(asked.group(1))})


def test_the_workbench_walkthrough_finds_the_offset_it_hides(fresh):
    walk = shell_blocks("docs/workbench.md")[0]
    r = run_block(walk, fresh)
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr
    assert_loads_match(r.stdout + r.stderr, requested_loads(walk))
    first = next(line for line in r.stdout.splitlines() if "explains" in line)
    assert first.split()[0] == "current_offset" and "SIGNIFICANT" in first, r.stdout[-2000:]
    assert (fresh / "runs" / "report" / "index.html").is_file() and (fresh / "runs" / "m2.json").is_file()


def test_the_demo_prints_the_load_it_runs_at(demo_ports):
    """``pmsm-agent demo``: the baseline it learns is named and printed at the simulated drive's load
    (config/agent.toml, load as torque over rated torque), within 5 %-points."""
    from agent.demo import DEFAULT_CONFIG, run_demo

    lines: list[str] = []
    run_demo(say=lines.append, until_learned=True)  # it learns within about 20 s of wall time on an idle machine
    text = "\n".join(lines)
    assert "baseline learned at fe" in text, text
    asked = float(re.search(r"^load_pct = (\S+)", DEFAULT_CONFIG.read_text(), flags=re.M).group(1))
    assert_loads_match(text, {asked})
