"""The per-sample recursions of the agent's runtime path, in C (``agent/_kernels.c``) through ctypes.

The PLL loop, the dq model's free-run simulation and the streaming pipeline's per-block pass
(:func:`block_rows`, :func:`ltv_residuals`) are the sample-by-sample loops the running agent
needs. They are plain C so that the agent never imports numba: numba and its LLVM cost about
120 MB of resident memory, most of the agent's 150 MB budget. The shared object is built in
place by ``make setup`` (``pip install -e .``, a setuptools extension declared in pyproject.toml)
and sits next to this file. The development tools (``agent.simulator``,
``agent.workbench``) keep numba.
"""

from __future__ import annotations

import ctypes
import importlib.machinery
from pathlib import Path

import numpy as np
from numpy.ctypeslib import ndpointer

_NAME = "_kernels"


_ABI = 6  #: the interface of agent/_kernels.c this module calls (its kernels_abi())


def _load() -> ctypes.CDLL:
    here = Path(__file__).resolve().parent
    for suffix in importlib.machinery.EXTENSION_SUFFIXES:
        path = here / (_NAME + suffix)
        if path.is_file():
            lib = ctypes.CDLL(str(path))
            if not hasattr(lib, "kernels_abi") or lib.kernels_abi() != _ABI:
                raise ImportError(f"the agent's C kernels ({path}) were built from an older agent/_kernels.c: "
                                  "run `make setup` (or `pip install --no-build-isolation -e .`) again")
            return lib
    missing = here / (_NAME + importlib.machinery.EXTENSION_SUFFIXES[0])
    raise ImportError(f"the agent's C kernels are not built ({missing} is missing): run `make setup` "
                      "(or `pip install --no-build-isolation -e .`) in the project directory")


_lib = _load()
_IN = ndpointer(np.float64, flags="C_CONTIGUOUS")
_OUT = ndpointer(np.float64, flags=("C_CONTIGUOUS", "WRITEABLE"))

_lib.pll_run.restype = None
_lib.pll_run.argtypes = [_IN, ctypes.c_ssize_t, _IN, _IN, _OUT, _OUT, _OUT, _OUT]
_lib.pll_series.restype = None
_lib.pll_series.argtypes = [_IN, _IN, _IN, ctypes.c_ssize_t, _OUT]
_lib.simulate_ltv.restype = None
_lib.simulate_ltv.argtypes = [_IN, _IN, _IN, _IN, _IN, ctypes.c_ssize_t, _OUT]
_lib.ltv_residuals.restype = None
_lib.ltv_residuals.argtypes = [_IN, _IN, _IN, _IN, ctypes.c_void_p, ctypes.c_ssize_t, _IN, ctypes.c_ssize_t,
                               ctypes.c_ssize_t, _OUT, _OUT]
_lib.block_rows.restype = ctypes.c_int
_lib.block_rows.argtypes = [ctypes.c_void_p, ctypes.c_ssize_t, ctypes.c_void_p, ctypes.c_ssize_t, ctypes.c_ssize_t,
                            ctypes.c_void_p, ctypes.c_void_p, ctypes.c_double, ctypes.c_void_p, ctypes.c_void_p,
                            ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_ssize_t, ctypes.c_int,
                            ctypes.c_void_p]

#: The rows :func:`block_rows` writes (agent.pipeline's signal ring).
ROWS = ("va", "vb", "vc", "ia", "ib", "ic", "omega_e", "i_d", "i_q", "v_d", "v_q")
#: A hop's sums as :func:`block_rows` carries them (:func:`new_sums`): the angle they are taken
#: about (rad), sums of power (W, v.i of the phases), omega, i_q, i_d i_q, i_d^2 + i_q^2; minima of
#: i_d, i_q and maxima (NaN once a sample is NaN); sums of dth = angle - ref, dth^2, dth omega,
#: dth power, omega^2, omega power; sum of i_d.
SUMS = ("ref", "power", "omega", "i_q", "i_dq", "i_sq", "i_d_min", "i_q_min", "i_d_max", "i_q_max",
        "dth", "dth_sq", "dth_omega", "dth_power", "omega_sq", "omega_power", "i_d")

LTV_RUNS = 8  #: the most free runs :func:`ltv_residuals` takes at once (agent/_kernels.c's)
#: Length of the PLL's parameter vector and of its state vector.
PLL_N_PAR, PLL_N_STATE = 10, 9


def _f64(a, shape: tuple[int | None, ...], name: str) -> np.ndarray:
    """``a`` as a C-contiguous float64 array (no copy when it already is one) of ``shape``
    (None: any length)."""
    a = np.ascontiguousarray(a, dtype=np.float64)
    if a.shape != shape and (a.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, a.shape))):
        want = str(tuple("N" if s is None else s for s in shape)).replace("'", "")
        raise ValueError(f"{name} must be shaped {want}, got {a.shape}")
    return a


def pll_run(x_abc, clarke, par, zi, cos_sin: bool = False):
    """Run the SRF-PLL over ``x_abc`` ``(3, N)`` from state ``zi`` (9,); returns theta, omega, zf,
    and with ``cos_sin`` also ``(4, N)``: cos and sin of theta and of theta + Ts omega / 2.

    ``clarke`` ``(2, 3)``: the Clarke rows giving alpha, beta. ``par`` = (Ts, wn_track, wn_acq,
    taper per sample, lock-filter coefficient, lock threshold, unlock threshold, lock samples,
    min amplitude, damping); ``zi``/``zf`` = (angle, integrator omega, filtered error, samples
    below threshold, locked 0/1, natural frequency wn, the angle's phasor cos and sin, its steps
    since exact: 0 in a new state). ``zi`` is not modified. See :mod:`agent.pll` for the loop.
    """
    x = _f64(x_abc, (3, None), "x_abc")
    n = x.shape[1]
    theta, omega, cs = np.empty(n), np.empty(n), np.empty((4, n))
    zf = np.array(zi, dtype=np.float64)  # a copy: the kernel updates the state in place
    _lib.pll_run(x, n, _f64(clarke, (2, 3), "clarke"), _f64(par, (PLL_N_PAR,), "par"),
                 _f64(zf, (PLL_N_STATE,), "zi"), theta, omega, cs)
    return (theta, omega, zf, cs) if cos_sin else (theta, omega, zf)


def pll_series(x, d, q) -> np.ndarray:
    """The series the PLL's loop takes in place of libm (for tests): ``(4, N)`` = cos and sin of
    ``x`` (|x| <= 0.4 rad), the phase error atan2(-d, q) and 1 where it came from the series."""
    x = _f64(x, (None,), "x")
    out = np.empty((4, x.size))
    _lib.pll_series(x, _f64(d, x.shape, "d"), _f64(q, x.shape, "q"), x.size, out)
    return out


def simulate_ltv(a0, a1, omega, u, x0) -> np.ndarray:
    """Free-run ``x(k+1) = (a0 + omega(k) a1) x(k) + u(k)`` from ``x(0) = x0``; returns x ``(2, N)``.

    ``a0``, ``a1`` ``(2, 2)``; ``omega`` ``(N,)``; ``u`` ``(2, N)``; ``x0`` ``(2,)``.
    Diverging output is returned as is (inf/NaN).
    """
    w = _f64(omega, (None,), "omega")
    n = w.size
    x = np.empty((2, n))
    _lib.simulate_ltv(_f64(a0, (2, 2), "a0"), _f64(a1, (2, 2), "a1"), w, _f64(u, (2, n), "u"),
                      _f64(x0, (2,), "x0"), n, x)
    return x


def ltv_residuals(a0, a1, omega, u, i_dq, theta, x0) -> tuple[np.ndarray, np.ndarray]:
    """The phase-a residuals of m free runs of :func:`simulate_ltv` over the same samples, each
    from its own state ``x0`` ``(2, m)``: ``(i_d - x_d) cos(theta) - (i_q - x_q) sin(theta)``,
    ``(m, N)`` (units of ``i_dq``; m <= :data:`LTV_RUNS`), and the states after the last sample ``(2, m)`` (a stream cut
    into blocks continues exactly). ``omega`` ``(N,)``; ``u``, ``i_dq`` ``(2, N)`` (``i_dq``'s rows
    are read in place when each is contiguous); ``theta`` ``(N,)``, rad."""
    w = _f64(omega, (None,), "omega")
    n = w.size
    x = np.array(x0, dtype=np.float64)  # a copy: the kernel updates the states in place
    m = x.shape[1] if x.ndim == 2 else 0
    if m > LTV_RUNS:
        raise ValueError(f"ltv_residuals: at most {LTV_RUNS} runs at once, got {m}")
    r = np.empty((m, n))
    i, i_stride = _f64_rows(i_dq, 2, "i_dq")
    if i.shape[1] != n:
        raise ValueError(f"i_dq must be shaped (2, {n}), got {i.shape}")
    _lib.ltv_residuals(_f64(a0, (2, 2), "a0"), _f64(a1, (2, 2), "a1"), w, _f64(u, (2, n), "u"), i.ctypes.data,
                       i_stride, _f64(theta, (n,), "theta"), n, m, _f64(x, (2, m), "x0"), r)
    return r, x


def _row_stride(a: np.ndarray) -> int | None:
    """The distance between the rows of the 2-D ``a`` in elements, when each row is contiguous (a
    C-contiguous array, or a span of columns of one); else None."""
    size = a.itemsize
    return a.strides[0] // size if a.strides[1] == size and a.strides[0] % size == 0 else None


def _f64_rows(a, n_rows: int, name: str) -> tuple[np.ndarray, int]:
    """``a`` as float64 ``(n_rows, N)`` with contiguous rows (a copy only when it has not) and its
    row stride in elements."""
    a = np.asarray(a, dtype=np.float64)
    stride = _row_stride(a) if a.ndim == 2 else None
    if stride is None:
        a = _f64(a, (n_rows, None), name)
        stride = a.shape[1]
    elif a.shape[0] != n_rows:
        raise ValueError(f"{name} must be shaped ({n_rows}, N), got {a.shape}")
    return a, stride


def new_sums(ref: float) -> np.ndarray:
    """Empty hop sums (:data:`SUMS`) about the angle ``ref`` (rad), for :func:`block_rows` to add to."""
    sums = np.zeros(len(SUMS))
    sums[0] = ref
    sums[SUMS.index("i_d_min"):SUMS.index("i_q_max") + 1] = (np.inf, np.inf, -np.inf, -np.inf)
    return sums


def block_rows(i_abc, v_abc, clarke, limits, theta_last: float, rows: np.ndarray, angle=None, pll=None,
               unwrapped: np.ndarray | None = None, sums: np.ndarray | None = None):
    """One block of the streaming pipeline's signal rows in one pass; writes ``rows`` ``(11, N)``
    (float32 or float64, :data:`ROWS`: the phases, speed, the currents' Park rotation at the angle,
    the voltages' at the mid angle) from ``i_abc``, ``v_abc`` ``(3, N)`` (A, V). Rows of contiguous
    columns are read and written in place (views of a record, a span of the pipeline's ring).

    The angle is either ``angle`` ``(6, N)``: angle (rad), speed (rad/s), cos and sin of the angle
    and of the mid angle angle + Ts speed / 2; or the PLL's over the currents (non-finite samples
    as :func:`numpy.nan_to_num` makes them), ``pll`` = (par, state) as :func:`pll_run`'s.
    ``clarke`` ``(2, 3)``; ``limits`` = (max |i|, max |v|): saturation; ``theta_last``: the unwrapped
    angle before the block, rad. Returns the angle unwrapped from ``theta_last`` ``(N,)`` (written
    into ``unwrapped`` when given, float64), whether a sample is NaN or saturated, and the PLL's new
    state (None with ``angle``). ``sums`` (:func:`new_sums`), when given, is added to in place:
    a hop's sums carried across its blocks, in sample order."""
    i, i_stride = _f64_rows(i_abc, 3, "i_abc")
    v, v_stride = _f64_rows(v_abc, 3, "v_abc")
    n = i.shape[1]
    cl, lim = _f64(clarke, (2, 3), "clarke"), _f64(limits, (2,), "limits")
    rows_stride = _row_stride(rows) if rows.ndim == 2 else None
    if (v.shape[1] != n or rows.dtype not in (np.float32, np.float64) or rows_stride is None
            or rows.shape != (len(ROWS), n) or not rows.flags.writeable):
        raise ValueError(f"block_rows: v_abc (3, {n}) and rows ({len(ROWS)}, {n}), float32 or float64 with "
                         f"contiguous rows, needed; got {v.shape} and {rows.shape}")
    if (angle is None) == (pll is None):
        raise ValueError("block_rows: give either angle or pll")
    if unwrapped is None:
        unwrapped = np.empty(n)
    elif unwrapped.dtype != np.float64 or unwrapped.shape != (n,) or not unwrapped.flags.c_contiguous:
        raise ValueError(f"block_rows: unwrapped must be a contiguous float64 array shaped ({n},)")
    if angle is not None:
        ang, par, zf = _f64(angle, (6, n), "angle"), None, None
    else:
        ang, par = None, _f64(pll[0], (PLL_N_PAR,), "par")
        zf = _f64(np.array(pll[1], dtype=np.float64), (PLL_N_STATE,), "zi")  # a copy, updated in place
    if sums is not None and (sums.dtype != np.float64 or sums.shape != (len(SUMS),) or not sums.flags.c_contiguous
                             or not sums.flags.writeable):
        raise ValueError(f"block_rows: sums must be a writeable contiguous float64 array shaped ({len(SUMS)},)")
    ang_p, par_p, zf_p = (ang.ctypes.data, None, None) if ang is not None else (None, par.ctypes.data, zf.ctypes.data)
    bad = _lib.block_rows(i.ctypes.data, i_stride, v.ctypes.data, v_stride, n, cl.ctypes.data, lim.ctypes.data,
                          float(theta_last), ang_p, par_p, zf_p, unwrapped.ctypes.data, rows.ctypes.data,
                          rows_stride, int(rows.dtype == np.float32), None if sums is None else sums.ctypes.data)
    return unwrapped, bool(bad), zf
