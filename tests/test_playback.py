"""Record playback (agent.playback): files streamed from disk in chunks, cut into blocks exactly as
the record, played losslessly at speedup 0 through the real service, idle when finished."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from agent.playback import replay_source
from agent.records import load_record, save_record
from runtime_support import PROFILE_PATH, profile, sim

pytestmark = pytest.mark.timeout(120)


def drain(src, limit=10_000):
    src.open()
    blocks = []
    while not src.finished and len(blocks) < limit:
        b = src.read(timeout=0.1)
        if b is not None:
            blocks.append(b)
    return blocks


@pytest.mark.parametrize("fmt", [".npz", ".csv", ".tdms"])
def test_replay_streams_the_files_block_for_block(tmp_path, fmt):
    """Chunks of 0.13 s, blocks of 0.1 s (neither divides the other): the blocks are the records'
    samples in order; each file is a stream of its own (first_sample jumps between files)."""
    recs = [sim("healthy", 80.0, 1.0, 31), sim("healthy", 80.0, 1.0, 32)]
    paths = [str(save_record(r, tmp_path / f"r{j}{fmt}")) for j, r in enumerate(recs)]
    src = replay_source(paths, "d1", profile(), block_s=0.1, speedup=0.0, chunk_s=0.13)
    assert src.lossless
    blocks = drain(src)
    per_file = len(blocks) // 2
    assert len(blocks) == 2 * per_file == 2 * (recs[0].n // 2500)
    for j, path in enumerate(paths):
        part = blocks[j * per_file:(j + 1) * per_file]
        whole = load_record(path)
        np.testing.assert_array_equal(np.hstack([b.i_abc for b in part]), whole.i_abc[:, :per_file * 2500])
        np.testing.assert_array_equal(np.hstack([b.v_abc for b in part]), whole.v_abc[:, :per_file * 2500])
        firsts = [b.first_sample for b in part]
        assert np.all(np.diff(firsts) == 2500)
    assert blocks[per_file].first_sample > blocks[per_file - 1].first_sample + 2500  # a new stream


def test_speedup_zero_through_the_service_loses_no_block(tmp_path, monkeypatch):
    """A pipeline ten times slower than the reader: at speedup 0 the reader waits, every block of
    the files reaches the pipeline, none is dropped; when the files end the reader idles."""
    from agent.pipeline import DriveMonitor
    from agent.runtime.config import check_config
    from agent.runtime.service import Service

    paths = [str(save_record(sim("healthy", 80.0, 2.0, 40 + j), tmp_path / f"r{j}.npz")) for j in range(3)]
    cfg_path = tmp_path / "agent.toml"
    files = ", ".join(f'"{p}"' for p in paths)
    cfg_path.write_text(f"""
schema_version = 1
agent_id = "replay"
state_dir = "{tmp_path / 'state'}"
[[drives]]
name = "drive1"
profile = "{PROFILE_PATH}"
[drives.source]
kind = "replay"
files = [{files}]
speedup = 0
block_s = 0.02
[pipeline]
auto_learn = false
[modbus_server]
enabled = false
[zenoh]
enabled = false
""")
    seen = []
    real = DriveMonitor.process

    def slow(self, block):
        seen.append(block.first_sample)
        time.sleep(0.002)
        return real(self, block)

    monkeypatch.setattr(DriveMonitor, "process", slow)
    service = Service(check_config(cfg_path))
    runner = threading.Thread(target=service.run, kwargs={"max_seconds": 60}, daemon=True)
    runner.start()
    expected = 3 * (50_000 // 500)
    t_end = time.monotonic() + 50
    while len(seen) < expected and time.monotonic() < t_end:
        time.sleep(0.05)
    d = service.drives["drive1"]
    assert len(seen) == expected and d.dropped == 0
    assert d.source.finished
    # finished: the reader idles (no busy loop), the process stays nearly idle
    cpu0, t0 = time.process_time(), time.monotonic()
    time.sleep(1.0)
    assert (time.process_time() - cpu0) / (time.monotonic() - t0) < 0.3
    service.stop_event.set()
    runner.join(10)
    assert not runner.is_alive()
