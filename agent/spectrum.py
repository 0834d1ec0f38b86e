"""Windowed single-sided amplitude spectrum and peak search near a frequency (paper Alg. 3).

The spectrum is scaled so that ``A cos(2 pi f t)`` with ``f`` on a bin reads ``A`` at that bin
(coherent-gain correction: ``2 |X_k| / sum(w)``; DC and Nyquist are not doubled). Windows are
periodic (DFT-even), as :func:`scipy.signal.get_window` makes them by default; they are computed
here from their cosine-sum coefficients so the agent does not load scipy.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

#: Supported windows -> cosine-sum coefficients a_k of w[n] = sum_k (-1)^k a_k cos(2 pi k n / N)
#: (scipy.signal.windows' values for "hann", "flattop" and "boxcar").
WINDOWS = {"hann": (0.5, 0.5), "flattop": (0.21557895, 0.41663158, 0.277263158, 0.083578947, 0.006947368),
           "rect": (1.0,)}


@lru_cache(maxsize=32)
def _window(name: str, n: int) -> np.ndarray:
    if name not in WINDOWS:
        raise ValueError(f"unknown window '{name}' (known: {', '.join(WINDOWS)})")
    phase = 2 * np.pi * np.arange(n) / n
    w = sum((-1) ** k * a * np.cos(k * phase) for k, a in enumerate(WINDOWS[name]))
    w.flags.writeable = False
    return w


#: The low bins of a long transform come from the transforms of this many interleaved
#: subsequences (:func:`_low_bins`)
SPLIT = 4


@lru_cache(maxsize=8)
def _twiddles(n: int, bins: int) -> np.ndarray:
    """(SPLIT, bins): exp(-2 pi i r k / n), subsequence r, bin k."""
    w = np.exp(-2j * np.pi * np.outer(np.arange(SPLIT), np.arange(bins)) / n)
    w.flags.writeable = False
    return w


def _low_bins(x: np.ndarray, bins: int) -> np.ndarray:
    """The first ``bins`` bins of ``rfft(x)`` (last axis, its length n a multiple of SPLIT, bins at
    most n / (2 SPLIT) + 1) by decimation in time: X_k = sum_r exp(-2 pi i r k / n) R_k with R the
    rfft of x[r::SPLIT]; the same values to rounding, about 2.5x faster at n = 50 000 (pocketfft runs
    the SPLIT short transforms side by side)."""
    sub = np.fft.rfft(x.reshape(*x.shape[:-1], -1, SPLIT).swapaxes(-1, -2), axis=-1)[..., :bins]
    return (sub * _twiddles(x.shape[-1], bins)).sum(axis=-2)


def amplitude_spectrum(x, rate_hz: float, window: str = "hann", bins: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Single-sided amplitude spectrum of real ``x`` along its last axis (``(N,)`` or ``(m, N)``).

    Returns ``(freqs_hz (N//2+1,), amplitude (..., N//2+1))`` in the units of ``x`` (peak, not rms);
    with ``bins``, only the first ``bins`` of them (the magnitudes above are not computed).
    """
    x = np.asarray(x, dtype=float)
    n = x.shape[-1]
    w = _window(window, n)
    if bins is not None and n % SPLIT == 0 and bins <= n // (2 * SPLIT) + 1:
        spectrum = _low_bins(x * w, bins)
    else:
        spectrum = np.fft.rfft(x * w, axis=-1)[..., :bins]
    amp = np.abs(spectrum) * _gain(window, n)
    amp[..., 0] *= 0.5
    if n % 2 == 0 and amp.shape[-1] == n // 2 + 1:
        amp[..., -1] *= 0.5
    return _freqs(n, float(rate_hz), amp.shape[-1]), amp


@lru_cache(maxsize=32)
def _gain(window: str, n: int) -> float:
    """2 / sum(w): the coherent-gain correction of a single-sided amplitude."""
    return 2.0 / _window(window, n).sum()


@lru_cache(maxsize=32)
def _freqs(n: int, rate_hz: float, bins: int) -> np.ndarray:
    """The first ``bins`` of ``numpy.fft.rfftfreq(n, 1 / rate_hz)``, the same values (read-only)."""
    f = np.fft.rfftfreq(n, 1.0 / rate_hz)[:bins].copy()
    f.flags.writeable = False
    return f


def peak_near(freqs, amplitude, f_hz, half_width: int = 1):
    """Largest bin among the bin nearest ``f_hz`` (Hz) and ``half_width`` bins either side.

    Tolerant of bin spacing: a line between bins, or a target off by up to half a bin plus
    ``half_width`` bins, is still found. ``freqs`` is the uniform grid of :func:`amplitude_spectrum`.
    ``f_hz`` is one frequency or an array of them (shape ``L``); ``amplitude`` is ``(nbins,)`` or
    ``(m, nbins)``. Returns ``(index, freq_hz, magnitude)`` shaped ``amplitude.shape[:-1] + L``
    (plain scalars for one spectrum and one frequency). Raises ``ValueError`` when a frequency is
    off the grid by more than ``half_width`` bins. The same statistic per bin is :func:`envelope`.
    """
    freqs = np.asarray(freqs, dtype=float)
    amplitude = np.asarray(amplitude)
    targets = np.atleast_1d(f_hz)
    centre = nearest_bin(freqs, targets.ravel(), half_width)
    around = np.clip(centre[:, None] + np.arange(-half_width, half_width + 1), 0, freqs.size - 1)
    near = amplitude[..., around]  # (..., lines, search)
    mag = near.max(axis=-1)
    idx = around[np.arange(centre.size), near.argmax(axis=-1)]
    shape = amplitude.shape[:-1] + np.shape(f_hz)
    idx, mag = idx.reshape(shape), mag.reshape(shape)
    if not shape:
        return int(idx), float(freqs[idx]), float(mag)
    return idx, freqs[idx], mag


def nearest_bin(freqs, f_hz, half_width: int = 0):
    """Index of the bin nearest ``f_hz`` (Hz; one frequency, or an array: an index array shaped as
    it); ``ValueError`` if one lies more than ``half_width`` + 1/2 bins off the grid."""
    df = freqs[1] - freqs[0]
    pos = (np.asarray(f_hz, dtype=float) - freqs[0]) / df
    off = ~((-half_width - 0.5 <= pos) & (pos <= freqs.size - 0.5 + half_width))
    if off.any():
        f = np.asarray(f_hz, dtype=float)[off] if pos.ndim else f_hz
        raise ValueError(f"{float(np.ravel(f)[0]):g} Hz is outside the spectrum ({freqs[0]:g}..{freqs[-1]:g} Hz)")
    idx = np.clip(np.rint(pos), 0, freqs.size - 1).astype(int)
    return int(idx) if idx.ndim == 0 else idx


def envelope(amplitude, half_width: int = 1) -> np.ndarray:
    """Per bin, the largest amplitude within ``half_width`` bins: the statistic :func:`peak_near`
    reads at a line, so thresholds learned on it match the decision (last axis)."""
    a = np.asarray(amplitude)
    out = a.copy()
    for shift in range(1, half_width + 1):  # edges repeat the end bins ("nearest")
        np.maximum(out[..., shift:], a[..., :-shift], out=out[..., shift:])
        np.maximum(out[..., :-shift], a[..., shift:], out=out[..., :-shift])
    return out
