"""The one contract every transport implements.

A *source* delivers blocks of phase samples of one drive; a *sink* receives drive status.
Sources and sinks never raise out of ``read``/``publish`` for transport trouble: they count it
in ``stats`` and log it, reconnect with backoff, and return ``None`` (source) or drop the update
(sink). The runtime owns threads, retries of ``open`` and lifecycle.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, Self, runtime_checkable

import numpy as np


@dataclass
class Block:
    """Consecutive samples of one drive.

    ``v_abc``/``i_abc`` are ``(3, N)`` float64 in V and A; ``theta_e``/``omega_e`` (rad, rad/s)
    only when the drive sends its encoder angle. ``seq`` is the source's block counter and
    ``first_sample`` the index of the block's first sample since the source started, so the
    pipeline can detect gaps (``first_sample`` jumps) and restart its windows.
    """

    drive: str
    rate_hz: float
    v_abc: np.ndarray
    i_abc: np.ndarray
    first_sample: int
    seq: int = 0
    theta_e: np.ndarray | None = None
    omega_e: np.ndarray | None = None

    @property
    def n(self) -> int:
        return int(self.i_abc.shape[1])


@dataclass
class SourceStats:
    """Counters every source keeps (exported in diagnostics)."""

    blocks: int = 0
    samples: int = 0
    frames: int = 0
    bad_frames: int = 0  #: CRC errors, malformed frames, unknown ids
    resyncs: int = 0
    gaps: int = 0  #: sequence jumps (lost frames)
    reconnects: int = 0
    last_error: str = ""
    opened_at: float = 0.0  #: wall time (time.time()) the source last opened, s

    def as_dict(self) -> dict:
        return dict(self.__dict__)


class OpenClose:
    """Mixin for sources and sinks: ``with x:`` calls ``x.open()`` and ``x.close()``."""

    def __enter__(self) -> Self:
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@runtime_checkable
class Source(Protocol):
    """A producer of :class:`Block` for one drive."""

    name: str
    stats: SourceStats

    def open(self) -> None: ...

    def read(self, timeout: float) -> Block | None:
        """Next block, or ``None`` when nothing arrived within ``timeout`` s (or the link is down)."""

    def close(self) -> None:
        """Release the transport; safe to call twice."""


@dataclass
class DriveStatus:
    """What the agent publishes per drive (CONTRACT section 6).

    ``state``/``spectrum_state``/``cluster_state``: "normal" | "caution" | "warning" (codes 0/1/2);
    ``quality``: "good" | "no_model" | "learning" | "stale" | "bad_input" (codes 0..4).
    """

    drive: str
    state: str = "normal"
    quality: str = "no_model"
    spectrum_state: str = "normal"
    cluster_state: str = "normal"
    fe_hz: float = float("nan")
    load_pct: float = float("nan")
    t: float = 0.0  #: Unix time of the window's end, s
    model: str = ""  #: id of the scheduled baseline
    peaks: list[dict] = field(default_factory=list)
    cluster_distance2: float = float("nan")
    window: int = 0  #: windows processed
    extra: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        def num(x):
            return None if x != x else x  # NaN -> null
        return {"drive": self.drive, "state": self.state, "quality": self.quality,
                "spectrum_state": self.spectrum_state, "cluster_state": self.cluster_state,
                "fe_hz": num(self.fe_hz), "load_pct": num(self.load_pct), "t": self.t, "model": self.model,
                "peaks": self.peaks, "cluster_distance2": num(self.cluster_distance2), "window": self.window,
                **self.extra}


STATE_CODES = {"normal": 0, "caution": 1, "warning": 2}
QUALITY_CODES = {"good": 0, "no_model": 1, "learning": 2, "stale": 3, "bad_input": 4}


@runtime_checkable
class Sink(Protocol):
    """A consumer of :class:`DriveStatus` (zenoh, the PLC's Modbus server)."""

    name: str

    def open(self) -> None: ...

    def publish(self, status: DriveStatus) -> None:
        """Hand over one update; must return quickly and never block the pipeline."""

    def close(self) -> None: ...
