"""Sources that play records: recorded files (CSV/NPZ/TDMS) and the embedded simulated drive.

They live beside the records (:mod:`agent.records`), not among the transports: they read files,
not links. Both cut records into blocks of ``block_s`` and pace them at ``speedup`` x real time;
``speedup = 0`` plays as fast as the pipeline takes them, and such a source is ``lossless``: the
service waits for the pipeline instead of dropping blocks (a live link never waits). Files are
streamed from disk a chunk at a time (:func:`agent.records.stream_record`), so a day of records
costs one chunk of memory. Consecutive records are separate streams: ``Block.first_sample``
jumps between them so the pipeline restarts its windows, exactly as it does after a gap on a
real link. A finished source reports ``finished`` (the service then idles, it does not spin).
"""

from __future__ import annotations

import itertools
import logging

import numpy as np
import time
from collections.abc import Callable, Iterable, Iterator

from agent.records import Record, stream_record
from protocols.base import Block, SourceStats

log = logging.getLogger(__name__)


class RecordSource:
    """Plays records as blocks of one drive: ``records()`` yields, per record, an iterable of its
    consecutive chunks (:class:`Record` s; one chunk for a record held in memory)."""

    def __init__(self, name: str, drive: str, records: Callable[[], Iterable[Iterable[Record]]], rate_hz: float,
                 block_s: float = 0.1, speedup: float = 1.0):
        self.name, self.drive, self.rate_hz = name, drive, rate_hz
        self.block = max(1, int(round(block_s * rate_hz)))
        self.speedup = speedup
        self.lossless = speedup == 0  #: as fast as the pipeline takes it: wait, never drop
        self._records = records
        self.stats = SourceStats()
        self._blocks: Iterator[Block] | None = None
        self._t0 = 0.0
        self._played = 0.0  # seconds of signal handed out

    def open(self) -> None:
        self._blocks = self._generate()
        self._t0 = time.monotonic()
        self._played = 0.0

    def _generate(self) -> Iterator[Block]:
        first = 0
        for chunks in self._records():
            pending, pos = None, first  # samples carried to the next chunk (less than a block)
            for rec in chunks:
                rows = [rec.v_abc, rec.i_abc] + [x[None, :] for x in (rec.theta_e, rec.omega_e) if x is not None]
                data = np.vstack(rows)
                if pending is not None:
                    data = np.hstack((pending, data))
                n = data.shape[1] - data.shape[1] % self.block
                for start in range(0, n, self.block):
                    yield self._block(data[:, start:start + self.block], pos, rec.theta_e is not None,
                                      rec.omega_e is not None)
                    pos += self.block
                pending = data[:, n:]
            first = pos + self.block  # a jump: the next record is a new stream

    def _block(self, data: np.ndarray, first: int, theta: bool, omega: bool) -> Block:
        return Block(self.drive, self.rate_hz, data[0:3], data[3:6], first, self.stats.blocks,
                     data[6] if theta else None, data[6 + theta] if omega else None)

    def read(self, timeout: float) -> Block | None:
        if self._blocks is None:
            return None
        if self.speedup > 0:
            due = self._t0 + self._played / self.speedup
            wait = due - time.monotonic()
            if wait > timeout:
                time.sleep(timeout)
                return None
            if wait > 0:
                time.sleep(wait)
        block = next(self._blocks, None)
        if block is None:
            self._blocks = None  # finished: behaves like a link that went quiet
            return None
        self._played += block.n / self.rate_hz
        self.stats.blocks += 1
        self.stats.samples += block.n
        return block

    def close(self) -> None:
        self._blocks = None

    @property
    def finished(self) -> bool:
        return self._blocks is None


def replay_source(files: list[str], drive: str, profile, *, block_s: float = 0.1, speedup: float = 1.0,
                  loop: bool = False, chunk_s: float = 0.2) -> RecordSource:
    """Replay recorded files (validated against ``profile`` chunk by chunk of ``chunk_s``: what a
    replayed drive holds besides its pipeline, ~0.3 MB at 25 kS/s), once or in a loop."""
    chunk = max(1, int(round(chunk_s * profile.sampling.rate_hz)))

    def records():
        paths = itertools.cycle(files) if loop else files
        for path in paths:
            yield stream_record(path, profile, chunk)
    return RecordSource(f"replay:{drive}", drive, records, profile.sampling.rate_hz, block_s, speedup)


def simulated_source(profile, schedule: list[tuple], drive: str = "drive1", *, load_pct: float = 80.0,
                     segment_s: float = 8.0, seed: int = 1, block_s: float = 0.1, speedup: float = 1.0,
                     loop: bool = False) -> RecordSource:
    """The embedded simulated drive: ``schedule`` is [(condition, seconds[, load_pct[, severity]]), ...]
    played in order, repeated when ``loop``. Each phase is cut into records of at most
    ``segment_s``; every record is a new operating session of the rig (its own small load and
    temperature spread), so learning sees the record-to-record variation a plant has."""
    from agent.simulator import simulate

    def records():
        seeds = itertools.count(seed)
        for phase in itertools.cycle(schedule) if loop else schedule:
            condition, seconds, load, severity = (tuple(phase) + (load_pct, 1.0))[:4]
            left = seconds
            while left > 1e-9:
                part = min(segment_s, left)
                yield [simulate(profile, condition, load, part, seed=next(seeds), severity=severity)]
                left -= part
    return RecordSource(f"simulated:{drive}", drive, records, profile.sampling.rate_hz, block_s, speedup)
