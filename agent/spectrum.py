"""Windowed single-sided amplitude spectrum and peak search near a frequency (paper Alg. 3).

The spectrum is scaled so that ``A cos(2 pi f t)`` with ``f`` on a bin reads ``A`` at that bin
(coherent-gain correction: ``2 |X_k| / sum(w)``; DC and Nyquist are not doubled). Windows are
periodic (DFT-even), as :func:`scipy.signal.get_window` makes them by default.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy.signal import get_window

#: Supported window names -> scipy.signal names.
WINDOWS = {"hann": "hann", "flattop": "flattop", "rect": "boxcar"}


@lru_cache(maxsize=32)
def _window(name: str, n: int) -> np.ndarray:
    if name not in WINDOWS:
        raise ValueError(f"unknown window '{name}' (known: {', '.join(WINDOWS)})")
    w = get_window(WINDOWS[name], n)
    w.flags.writeable = False
    return w


def amplitude_spectrum(x, rate_hz: float, window: str = "hann") -> tuple[np.ndarray, np.ndarray]:
    """Single-sided amplitude spectrum of real ``x`` along its last axis (``(N,)`` or ``(m, N)``).

    Returns ``(freqs_hz (N//2+1,), amplitude (..., N//2+1))`` in the units of ``x`` (peak, not rms).
    """
    x = np.asarray(x, dtype=float)
    n = x.shape[-1]
    w = _window(window, n)
    amp = np.abs(np.fft.rfft(x * w, axis=-1)) * (2.0 / w.sum())
    amp[..., 0] *= 0.5
    if n % 2 == 0:
        amp[..., -1] *= 0.5
    return np.fft.rfftfreq(n, 1.0 / rate_hz), amp


def peak_near(freqs, amplitude, f_hz: float, tol_hz: float | None = None):
    """Largest bin within ``max(tol_hz, 1.5 bin spacings)`` of ``f_hz`` (Hz).

    ``freqs`` is the uniform bin grid of :func:`amplitude_spectrum`. Returns ``(index, freq_hz,
    magnitude)``: scalars for ``amplitude`` shaped ``(nbins,)``, arrays ``(m,)`` for ``(m, nbins)``.
    Raises ``ValueError`` when no bin lies within the tolerance.
    """
    freqs = np.asarray(freqs, dtype=float)
    amplitude = np.asarray(amplitude)
    tol = max(tol_hz or 0.0, 1.5 * (freqs[1] - freqs[0]))
    lo = int(np.searchsorted(freqs, f_hz - tol, side="left"))
    hi = int(np.searchsorted(freqs, f_hz + tol, side="right"))
    if hi <= lo:
        raise ValueError(f"no spectrum bin within {tol:g} Hz of {f_hz:g} Hz (bins {freqs[0]:g}..{freqs[-1]:g} Hz)")
    seg = amplitude[..., lo:hi]
    idx, mag = lo + seg.argmax(axis=-1), seg.max(axis=-1)
    if amplitude.ndim == 1:
        return int(idx), float(freqs[idx]), float(mag)
    return idx, freqs[idx], mag
