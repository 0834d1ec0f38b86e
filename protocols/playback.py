"""Sources that play records: recorded files (CSV/NPZ/TDMS) and the embedded simulated drive.

Both cut records into blocks of ``block_s`` and pace them at ``speedup`` x real time
(``speedup = 0``: as fast as the reader takes them). Consecutive records are separate streams:
``Block.first_sample`` jumps between them so the pipeline restarts its windows, exactly as it
does after a gap on a real link.
"""

from __future__ import annotations

import itertools
import logging
import time
from collections.abc import Callable, Iterable, Iterator

from agent.records import Record, load_record
from protocols.base import Block, SourceStats

log = logging.getLogger(__name__)


class RecordSource:
    """Plays an iterable of records as blocks of one drive."""

    def __init__(self, name: str, drive: str, records: Callable[[], Iterable[Record]], rate_hz: float,
                 block_s: float = 0.1, speedup: float = 1.0):
        self.name, self.drive, self.rate_hz = name, drive, rate_hz
        self.block = max(1, int(round(block_s * rate_hz)))
        self.speedup = speedup
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
        for rec in self._records():
            for start in range(0, rec.n - self.block + 1, self.block):
                cut = slice(start, start + self.block)
                yield Block(self.drive, self.rate_hz, rec.v_abc[:, cut], rec.i_abc[:, cut], first + start,
                            self.stats.blocks,
                            None if rec.theta_e is None else rec.theta_e[cut],
                            None if rec.omega_e is None else rec.omega_e[cut])
            first += rec.n + self.block  # a jump: the next record is a new stream

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
                  loop: bool = False) -> RecordSource:
    """Replay recorded files (validated against ``profile``), once or in a loop."""
    def records():
        paths = itertools.cycle(files) if loop else files
        for path in paths:
            yield load_record(path, profile)
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
                yield simulate(profile, condition, load, part, seed=next(seeds), severity=severity)
                left -= part
    return RecordSource(f"simulated:{drive}", drive, records, profile.sampling.rate_hz, block_s, speedup)
