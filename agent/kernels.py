"""The per-sample recursions of the agent's runtime path, in C (``agent/_kernels.c``) through ctypes.

The PLL loop and the dq model's free-run simulation are the only sample-by-sample loops the
running agent needs. They are plain C so that the agent never imports numba: numba and its LLVM
cost about 120 MB of resident memory, most of the agent's 150 MB budget. The shared object is
built in place by ``make setup`` (``pip install -e .``, a setuptools extension declared in
pyproject.toml) and sits next to this file. The development tools (``agent.simulator``,
``agent.workbench``) keep numba.
"""

from __future__ import annotations

import ctypes
import importlib.machinery
from pathlib import Path

import numpy as np
from numpy.ctypeslib import ndpointer

_NAME = "_kernels"


_ABI = 2  #: the interface of agent/_kernels.c this module calls (its kernels_abi())


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
_lib.simulate_ltv.restype = None
_lib.simulate_ltv.argtypes = [_IN, _IN, _IN, _IN, _IN, ctypes.c_ssize_t, _OUT]

#: Length of the PLL's parameter vector and of its state vector.
PLL_N_PAR, PLL_N_STATE = 10, 9


def _f64(a, shape: tuple[int | None, ...], name: str) -> np.ndarray:
    """``a`` as a C-contiguous float64 array (no copy when it already is one) of ``shape``
    (None: any length)."""
    a = np.ascontiguousarray(a, dtype=np.float64)
    if a.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, a.shape)):
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
