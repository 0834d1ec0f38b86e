"""Records: three-phase voltage and current samples, measured or simulated (CONTRACT section 3).

A record is read from CSV, NPZ or TDMS into a :class:`Record`; every problem a user can fix
(missing column, non-uniform time, NaN, sample rate that disagrees with the profile, too few
samples) raises :class:`agent.errors.InputError` naming the file and the problem.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Required channels, in the order of ``Record`` arrays.
VOLTAGES = ("va", "vb", "vc")
CURRENTS = ("ia", "ib", "ic")
OPTIONAL = ("theta_e", "omega_e")
#: Relative tolerance on the uniformity of the time column.
TIME_TOLERANCE = 1e-6


@dataclass
class Record:
    """One record.

    ``v_abc`` and ``i_abc`` are ``(3, N)`` arrays in V and A (phase-to-neutral); ``theta_e``
    (rad) and ``omega_e`` (rad/s) are the electrical rotor angle and speed when the drive
    provides them, else ``None``. ``meta`` holds free-form string/number annotations
    (simulator condition, load, seed...) that round-trip through NPZ and TDMS.
    """

    t: np.ndarray
    v_abc: np.ndarray
    i_abc: np.ndarray
    theta_e: np.ndarray | None = None
    omega_e: np.ndarray | None = None
    source: str = "<memory>"
    meta: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        return int(self.t.size)

    @property
    def rate_hz(self) -> float:
        """Sample rate from the time column, Hz."""
        return 1.0 / float(np.mean(np.diff(self.t))) if self.n > 1 else float("nan")

    @property
    def duration_s(self) -> float:
        return self.n / self.rate_hz
