"""Windowed amplitude spectrum and peak search (Alg. 3), against scipy and analytic values."""

import numpy as np
import pytest
from scipy.signal import periodogram

from agent.spectrum import SPLIT, WINDOWS, _window, amplitude_spectrum, envelope, peak_near

SCIPY_NAMES = {"hann": "hann", "flattop": "flattop", "rect": "boxcar"}


@pytest.mark.parametrize("window", list(WINDOWS))
@pytest.mark.parametrize("n", [8, 1001, 4096])
def test_windows_equal_scipy(window, n):
    from scipy.signal import get_window

    np.testing.assert_allclose(_window(window, n), get_window(SCIPY_NAMES[window], n), atol=1e-12)

FS, N = 25_000.0, 25_000  # 1 Hz bins
DF = FS / N
T = np.arange(N) / FS


@pytest.mark.parametrize("window", list(WINDOWS))
def test_on_bin_tone_reads_its_amplitude_and_dc_is_not_doubled(window):
    x = 0.7 + 3.0 * np.cos(2 * np.pi * 100.0 * T + 0.4) + 0.5 * np.cos(np.pi * FS * T)  # DC, tone, Nyquist
    f, a = amplitude_spectrum(x, FS, window)
    np.testing.assert_allclose(f, np.fft.rfftfreq(N, 1 / FS))
    assert a[100] == pytest.approx(3.0, rel=1e-9)
    assert a[0] == pytest.approx(0.7, rel=1e-9)
    assert a[-1] == pytest.approx(0.5, rel=1e-9)


@pytest.mark.parametrize("window", list(WINDOWS))
@pytest.mark.parametrize("n", [1000, 1001])
def test_matches_scipy_periodogram(window, n):
    x = np.random.default_rng(1).normal(size=n)
    f, a = amplitude_spectrum(x, FS, window)
    fp, p = periodogram(x, FS, window=SCIPY_NAMES[window], detrend=False, scaling="spectrum")
    doubled = np.ones(p.size, dtype=bool)  # periodogram doubles the power of all but DC (and Nyquist, n even)
    doubled[0] = False
    doubled[-1] = n % 2 == 1
    np.testing.assert_allclose(f, fp)
    np.testing.assert_allclose(a, np.sqrt(p * np.where(doubled, 2.0, 1.0)), rtol=1e-9, atol=1e-15)


def test_rows_are_vectorised():
    rng = np.random.default_rng(2)
    x = rng.normal(size=(4, 512))
    f, a = amplitude_spectrum(x, 1000.0)
    assert a.shape == (4, 257)
    for row, xr in zip(a, x):
        np.testing.assert_allclose(row, amplitude_spectrum(xr, 1000.0)[1], rtol=1e-12)


@pytest.mark.parametrize("bins", [1, 2, 6251, 6252])
def test_low_bins_equal_the_whole_transform(bins):
    """With few ``bins`` (a multiple of SPLIT samples, at most n / (2 SPLIT) + 1 bins) the bins
    come from the interleaved subsequences' transforms: the whole transform's to rounding."""
    x = np.random.default_rng(3).normal(size=(2, 50_000))
    assert (bins <= 50_000 // (2 * SPLIT) + 1) == (bins < 6252)  # 6252: the whole transform's path
    f, a = amplitude_spectrum(x, FS, bins=bins)
    f_all, a_all = amplitude_spectrum(x, FS)
    np.testing.assert_array_equal(f, f_all[:bins])
    np.testing.assert_allclose(a, a_all[:, :bins], rtol=0, atol=1e-14 * a_all.max())


def test_scalloping_between_bins():
    """A tone half-way between bins: Hann reads 8/(3 pi) of A, flat-top within 0.2 % (0.02 dB)."""
    x = 2.0 * np.cos(2 * np.pi * 100.5 * T)
    f, a = amplitude_spectrum(x, FS, "hann")
    assert a[100] == pytest.approx(a[101], rel=1e-6)
    assert a[100] == pytest.approx(2.0 * 8 / (3 * np.pi), rel=1e-4)
    f, a = amplitude_spectrum(x, FS, "flattop")
    assert a[100] == pytest.approx(2.0, rel=2e-3)


def test_unknown_window():
    with pytest.raises(ValueError, match="unknown window 'kaiser'.*hann, flattop, rect"):
        amplitude_spectrum(np.zeros(8), 1.0, "kaiser")


def test_peak_near_tolerates_bin_spacing():
    x = np.cos(2 * np.pi * 87.3 * T) + 5.0 * np.cos(2 * np.pi * 92.0 * T)  # big tone 4.7 bins away
    f, a = amplitude_spectrum(x, FS)
    i, fi, m = peak_near(f, a, 87.5)  # target 0.2 bins off the tone, tone 0.3 bins off bin 87
    assert (i, fi) == (87, 87.0) and isinstance(i, int) and isinstance(m, float)
    assert m == pytest.approx(a[87]) and 0.85 < m < 1.0
    assert peak_near(f, a, 88.4)[0] == 87  # nearest bin 88, one bin either side reaches 87
    assert peak_near(f, a, 88.6)[0] in (88, 89, 90)  # nearest bin 89: 87 is out of reach
    assert peak_near(f, a, 89.0, half_width=3)[0] == 92  # a wider search reaches the big tone
    assert peak_near(f, a, 89.0)[0] in (88, 89, 90)


def test_envelope_is_the_peak_statistic_per_bin():
    rng = np.random.default_rng(0)
    a = rng.random((3, 200))
    env = envelope(a, 1)
    for f_hz in (0.0, 10.4, 57.5, 199.0):
        c = int(round(f_hz))
        np.testing.assert_allclose(peak_near(np.arange(200.0), a, f_hz)[2], env[:, c])
    np.testing.assert_allclose(env[:, 50], a[:, 49:52].max(axis=1))


def test_peak_near_rows():
    rates = np.array([1.0, 2.0, 3.0])[:, None]
    x = rates * np.cos(2 * np.pi * np.array([[74.0], [75.0], [76.0]]) * T)
    f, a = amplitude_spectrum(x, FS)
    i, fi, m = peak_near(f, a, 75.0)
    np.testing.assert_array_equal(i, [74, 75, 76])
    np.testing.assert_array_equal(fi, [74.0, 75.0, 76.0])
    np.testing.assert_allclose(m, [1.0, 2.0, 3.0], rtol=1e-9)


def test_peak_near_outside_spectrum():
    f, a = amplitude_spectrum(np.cos(np.pi * np.arange(100)), 100.0, "rect")  # a tone at Nyquist
    assert peak_near(f, a, 50.5)[0] == 50  # just past Nyquist, within the search
    with pytest.raises(ValueError, match="outside the spectrum"):
        peak_near(f, a, 60.0)


def test_peak_near_many_frequencies_equals_one_at_a_time():
    rng = np.random.default_rng(5)
    a = rng.random((3, 400))
    f = np.arange(400.0)
    targets = np.array([0.2, 10.4, 57.5, 123.0, 399.0])
    idx, fr, mag = peak_near(f, a, targets, 2)
    assert idx.shape == (3, 5)
    for j, t in enumerate(targets):
        i1, f1, m1 = peak_near(f, a, t, 2)
        np.testing.assert_array_equal(idx[:, j], i1)
        np.testing.assert_array_equal(mag[:, j], m1)
