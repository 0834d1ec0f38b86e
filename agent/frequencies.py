"""Gear and chain fault characteristic frequencies (paper eqs. 19-22).

Base frequencies (Hz), with ``f_r = fe / n_p`` the driving shaft rotation frequency (the paper's
``n_p`` is the pole-pair count: fe = 100 Hz, 4 pole pairs -> f_gm = 25 Hz):

* ``gear_driving``: ``f_gm = fe / n_p`` (eq. 19)
* ``gear_driven``:  ``f_gl = fe / (g_r n_p)``, ``g_r`` = driven / driving teeth (eq. 20)
* ``chain``:        ``f_ch = 2 pi r_m f_r / l_ch``, ``r_m`` = driving pitch radius, ``l_ch`` =
  chain length (eq. 21); a chain profile also gets the two sprocket families above.

Each family's signatures are the sidebands ``fe +- k f`` for ``k = 1..K`` (eqs. 19, 20, 22).
"""

from __future__ import annotations

import math
import numbers

from agent.errors import InputError
from agent.profile import DriveProfile


def _fe(profile: DriveProfile, fe_hz) -> float:
    fe = profile.rated_fe_hz if fe_hz is None else float(fe_hz)
    if not (math.isfinite(fe) and fe > 0):
        raise InputError(f"electrical frequency fe must be positive, got {fe_hz}")
    return fe


def base_frequencies(profile: DriveProfile, fe_hz: float | None = None) -> dict[str, float]:
    """Family -> base frequency (Hz): ``gear_driving`` f_gm, ``gear_driven`` f_gl, ``chain`` f_ch.

    ``fe_hz`` defaults to the rated electrical frequency; ``chain`` only for a chain profile.
    """
    tr = profile.transmission
    f_r = _fe(profile, fe_hz) / profile.motor.pole_pairs
    out = {"gear_driving": f_r, "gear_driven": f_r / tr.ratio}
    if tr.kind == "chain":
        out["chain"] = math.pi * tr.driving_pitch_diameter_mm * f_r / tr.chain_length_mm  # 2 pi r_m f_r / l_ch
    return out


def fault_frequencies(profile: DriveProfile, fe_hz: float | None = None, k_max: int = 3) -> dict[str, list[dict]]:
    """Family -> ``[{"k": k, "freq_hz": fe -+ k f}, ...]`` for k = 1..k_max, sorted by frequency.

    Sidebands at or below 0 Hz (``k f >= fe``) are dropped.
    """
    if isinstance(k_max, bool) or not isinstance(k_max, numbers.Integral) or k_max < 1:
        raise InputError(f"k must be a positive integer, got {k_max!r}")
    fe = _fe(profile, fe_hz)
    return {
        family: sorted(({"k": k, "freq_hz": fe + s * k * f} for k in range(1, int(k_max) + 1) for s in (-1, 1)
                        if fe + s * k * f > 0), key=lambda p: p["freq_hz"])
        for family, f in base_frequencies(profile, fe).items()
    }
