"""Streaming recursive least squares with forgetting (paper eqs. 16-18, Algorithm 1).

The estimator is kept in **information form**: ``R = P^-1`` (n x n) and ``r = R theta`` (n,),
so a whole block ``X`` (N, n), ``y`` (N,) is absorbed with vectorised numpy::

    R <- lam^N R + X^T diag(w) X,     r <- lam^N r + X^T diag(w) y,     w_i = W lam^(N-1-i)

This equals, at every block boundary and for any split into blocks, the per-sample
covariance-form recursion of Algorithm 1 extended with a forgetting factor ``lam``::

    K = P x / (lam/W + x^T P x);  theta += K (y - x^T theta);  P = (P - K x^T P) / lam

started from ``theta0`` and ``P0`` (``R0 = P0^-1``, ``r0 = R0 theta0``); ``lam = 1`` is the
paper's Algorithm 1 (eq. 17's ``W^-1`` is the measurement-noise variance, in units of y^2).

Stabilised forgetting (Kulhavy / Zarrop), ``stabilize=True``::

    R_k = lam R_{k-1} + (1-lam) R0 + W x x^T,   r_k = lam r_{k-1} + (1-lam) r0 + W x y

applied exactly per block with the factor ``(1 - lam^N)``. Because ``R_k >= R0`` (Loewner
order) at all times, ``P <= P0``: without excitation theta relaxes to ``theta0`` and P stays
bounded, instead of blowing up as ``lam^-k`` (the classic windup that makes padasip's RLS go
to inf/NaN on all-zero regressors). With ``lam = 1`` it is a no-op, so offline identification
is exactly Algorithm 1 either way.

Plain forgetting (``stabilize=False``) never produces NaN either: R and r are stored as
``2^e * (R~, r~)`` (integer e, exact power-of-two rescaling) so a block without excitation only
moves the exponent -- theta stays (to rounding), P = R^-1 grows as ``lam^-k`` and saturates at
+-inf once it exceeds the float range (after ~ 709 / -ln(lam) samples, ~70 000 at lam = 0.99).
If excitation returns when the discounted old information is below ~2^-1000 of the new block's,
the old information is lost to rounding: the estimate restarts from the new data and directions
the new data do not excite fall back to theta0.
"""

from __future__ import annotations

import math

import numpy as np

_LOG2_FLOOR = -1000.0  # lam^N below 2^-1000 is computed as exp2(N log2 lam)
_RCOND = 1e-12         # Jacobi-scaled R with a smaller Cholesky pivot^2 is treated as singular


class StreamingRLS:
    """RLS with exponential forgetting and sample weight, information form, fixed memory.

    Parameters
    ----------
    n_params : number of regressors n.
    lam : forgetting factor, 0 < lam <= 1 (1 = no forgetting, paper Alg. 1). Memory ~ 1/(1-lam) samples.
    weight : W of eq. 17, > 0 (inverse measurement-noise variance, 1/units(y)^2).
    theta0 : initial parameters (n,), default zeros.
    p0 : initial covariance P0 -- scalar (P0 = p0 I), (n,) diagonal or (n, n) SPD matrix.
        Default 1e3 (padasip's default eps = 1e-3), a weak prior for O(1) parameters.
    stabilize : stabilised forgetting (see module doc). Default True: the edge agent runs for
        months and must survive long stretches without excitation; with lam = 1 it changes nothing.
    """

    def __init__(self, n_params: int, lam: float = 1.0, weight: float = 1.0, theta0=None,
                 p0=1e3, stabilize: bool = True):
        n = int(n_params)
        if n < 1:
            raise ValueError(f"n_params must be >= 1, got {n_params}")
        if not 0.0 < lam <= 1.0:
            raise ValueError(f"forgetting factor lam must be in (0, 1], got {lam}")
        if not (weight > 0.0 and math.isfinite(weight)):
            raise ValueError(f"weight W must be finite and > 0, got {weight}")
        theta0 = np.zeros(n) if theta0 is None else np.array(theta0, dtype=float).reshape(-1)
        if theta0.shape != (n,) or not np.isfinite(theta0).all():
            raise ValueError(f"theta0 must be {n} finite values")
        p0 = np.asarray(p0, dtype=float)
        if not np.isfinite(p0).all():
            R0 = None
        elif p0.ndim == 0:
            R0 = np.eye(n) / float(p0) if p0 > 0 else None
        elif p0.shape == (n,):
            R0 = np.diag(1.0 / p0) if (p0 > 0).all() else None
        elif p0.shape == (n, n):
            try:
                R0 = _cho_solve(np.linalg.cholesky(p0), np.eye(n))
                R0 = 0.5 * (R0 + R0.T)
            except np.linalg.LinAlgError:
                R0 = None
        else:
            R0 = None
        if R0 is None or not np.isfinite(R0).all():
            raise ValueError("p0 must be finite, > 0: a scalar, (n,) diagonal or (n, n) SPD matrix")
        self.lam, self.weight, self.stabilize = float(lam), float(weight), bool(stabilize)
        self.theta0, self.R0 = theta0, R0
        self.r0 = R0 @ theta0
        self.reset()

    # ----------------------------------------------------------------------------------------
    def reset(self) -> None:
        """Back to the prior (theta0, P0); equal to a fresh instance."""
        self._R = self.R0.copy()      # R = 2^e * _R
        self._r = self.r0.copy()      # r = 2^e * _r
        self._e = 0
        self._n_seen = 0
        self._theta = None
        self._fact = None
        self._w = None  # weights W lam^(N-1-i) of the last block length (a cache, not state)

    @property
    def n_params(self) -> int:
        return self.R0.shape[0]

    @property
    def samples_seen(self) -> int:
        return self._n_seen

    def update(self, X, y) -> None:
        """Absorb a block: X (N, n) regressors, y (N,) outputs, any N >= 0 (eqs. 16-18, exact)."""
        X = np.asarray(X, dtype=float)
        y = np.asarray(y, dtype=float).reshape(-1)
        n = self.n_params
        if X.ndim == 1 and X.shape[0] == n and y.shape == (1,):
            X = X[None, :]
        if X.ndim != 2 or X.shape[1] != n or X.shape[0] != y.shape[0]:
            raise ValueError(f"update needs X (N, {n}) and y (N,), got {X.shape} and {y.shape}")
        N = X.shape[0]
        if N == 0:
            return
        lam = self.lam
        if lam == 1.0:
            a, log2a = 1.0, 0.0
            Xw = X * self.weight
        else:
            a, log2a = lam**N, N * math.log2(lam)            # lam^N may underflow to 0: fine
            if self._w is None or self._w.shape[0] != N:   # cached for the usual fixed block size
                self._w = self.weight * lam ** np.arange(N - 1, -1, -1, dtype=float)
            Xw = X * self._w[:, None]
        G, g = Xw.T @ X, Xw.T @ y
        if not (np.isfinite(G).all() and np.isfinite(g).all()):
            raise ValueError("non-finite regressors or outputs (or overflow) in RLS block; state unchanged")
        if self.stabilize and lam < 1.0:
            G = G + (1.0 - a) * self.R0
            g = g + (1.0 - a) * self.r0
        # R = 2^e R~ with integer e and max|R~| in [0.5, 1): power-of-two rescaling is exact, so
        # this only keeps the mantissas in range (no underflow to 0/NaN without excitation).
        e_old = self._e + math.ceil(log2a) + int(np.frexp(np.abs(self._R).max())[1])
        e_new = int(np.frexp(np.abs(G).max())[1]) if G.any() else e_old
        t = max(e_old, e_new)
        if log2a > _LOG2_FLOOR:                    # exact: lam^N scaled by a power of two
            f = math.ldexp(a, self._e - t)
        else:                                      # huge block: lam^N itself underflows
            f = math.exp2(log2a + (self._e - t))
        R = f * self._R + np.ldexp(G, -t)          # f may underflow to 0 only when the old
        r = f * self._r + np.ldexp(g, -t)          # information is < 2^-1000 of the new
        k = int(np.frexp(np.abs(R).max())[1])
        self._R, self._r, self._e = np.ldexp(0.5 * (R + R.T), -k), np.ldexp(r, -k), t + k
        self._n_seen += N
        self._theta = self._fact = None

    @property
    def theta(self) -> np.ndarray:
        """Current estimate (units of y / units of x): solves R theta = r, cached until the next update.

        Cholesky of the Jacobi-scaled R; if that is numerically singular (scaled condition
        > ~1e12, e.g. plain forgetting lost the old information and the new data do not excite
        every direction) the solution closest to theta0 (in the scaled norm) is returned.
        """
        if self._theta is None:
            fact, d = self._factor()
            if fact is not None:
                self._theta = _cho_solve(fact, self._r / d) / d
            else:
                Rs = self._R / np.outer(d, d)
                u = np.linalg.lstsq(Rs, (self._r - self._R @ self.theta0) / d, rcond=_RCOND)[0]
                self._theta = self.theta0 + u / d
        return self._theta.copy()

    @property
    def information(self) -> np.ndarray:
        """R = P^-1, the information matrix (inverse covariance); finite even when P is not."""
        return np.ldexp(self._R, self._e)

    @property
    def covariance(self) -> np.ndarray:
        """P = R^-1, units 1/(W x^2); with W = 1/sigma_y^2 it is the covariance of theta.

        Plain forgetting without excitation: grows as lam^-k and saturates at +-inf (never NaN);
        all +inf if R is numerically singular. With stabilize: P <= P0.
        """
        fact, d = self._factor()
        n = self.n_params
        if fact is None:
            return np.full((n, n), np.inf)
        Pm = _cho_solve(fact, np.diag(1.0 / d)) / d[:, None]
        Pm = 0.5 * (Pm + Pm.T)
        with np.errstate(over="ignore"):           # ldexp(0, k) = 0: inf but never NaN
            return np.ldexp(Pm, -self._e)

    def predict(self, X) -> np.ndarray:
        """One-step prediction X @ theta for X (N, n) (or (n,) -> scalar)."""
        return np.asarray(X, dtype=float) @ self.theta

    def _factor(self):
        """(Cholesky factor of D^-1 R~ D^-1 or None if numerically singular, D = sqrt(diag R~))."""
        if self._fact is None:
            dg = np.diag(self._R)
            d = np.sqrt(np.where(dg > 0, dg, 1.0))
            fact = None
            if (dg > 0).all():
                try:
                    fact = np.linalg.cholesky(self._R / np.outer(d, d))
                    if np.diag(fact).min() ** 2 < _RCOND:
                        fact = None
                except np.linalg.LinAlgError:
                    fact = None
            self._fact = (fact, d)
        return self._fact

    # ----------------------------------------------------------------------------------------
    def state(self) -> dict:
        """Complete state as plain arrays / numbers (e.g. for ``np.savez``)."""
        return {
            "lam": self.lam, "weight": self.weight, "stabilize": self.stabilize,
            "theta0": self.theta0.copy(), "R0": self.R0.copy(),
            "R": self._R.copy(), "r": self._r.copy(), "log2_scale": self._e,
            "samples_seen": self._n_seen,
        }

    @classmethod
    def from_state(cls, st) -> "StreamingRLS":
        """Rebuild from :meth:`state` (a dict or an ``np.load`` result)."""
        R0 = np.array(st["R0"], dtype=float)
        obj = cls.__new__(cls)
        obj.lam, obj.weight = float(st["lam"]), float(st["weight"])
        obj.stabilize = bool(st["stabilize"])
        obj.theta0, obj.R0 = np.array(st["theta0"], dtype=float), R0
        obj.r0 = R0 @ obj.theta0
        obj._R = np.array(st["R"], dtype=float)
        obj._r = np.array(st["r"], dtype=float)
        obj._e = int(st["log2_scale"])
        obj._n_seen = int(st["samples_seen"])
        obj._theta = obj._fact = obj._w = None
        return obj


def _cho_solve(lower: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve (L L^T) x = b with the lower Cholesky factor L (small n: two plain solves)."""
    return np.linalg.solve(lower.T, np.linalg.solve(lower, b))
