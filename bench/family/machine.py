"""The machine's magnetics: a flux map from one magnetic energy function, and the magnet's space harmonics.

Frames: amplitude-invariant Clarke (beta = (b - c)/sqrt 3) and d = alpha cos(theta) + beta sin(theta),
q = -alpha sin(theta) + beta cos(theta); phase a's magnet flux is psi_m cos(theta_e) at theta_e = 0.

Flux map (``FluxMap``, the states are the flux linkages, the currents follow explicitly): with the
armature flux x = psi_d - psi_m (Wb) and y = psi_q (Wb), the magnetic energy per 1.5 is

    W(x, y) = x^2/(2 L_d) + beta x^3/3 + c x y^2 + y^2/(2 L_q) + alpha |y|^(n+2) / ((n+2) L_q psi_qr^n)

and the currents are its gradient (so d psi_d/d i_q = d psi_q/d i_d: one energy, reciprocal):

    i_d = x/L_d + beta x^2 + c y^2
    i_q = y/L_q (1 + alpha |y/psi_qr|^n) + 2 c x y

beta > 0: L_d grows under demagnetising i_d and drops under magnetising i_d (the magnet's bias);
alpha > 0: self-saturation of L_q; c > 0: cross-saturation (i_q lowers psi_d at i_d = 0, and a negative
i_d raises psi_q). All zero: the linear machine psi_d = psi_m + L_d i_d, psi_q = L_q i_q.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: indices into a flux-map array
FM_LD, FM_LQ, FM_PSI_M, FM_BETA, FM_ALPHA, FM_N, FM_PSI_QR, FM_C = range(8)


def flux_map(ld_h: float, lq_h: float, psi_m_wb: float, beta: float = 0.0, alpha: float = 0.0,
             n: float = 2.0, psi_qr_wb: float = 1.0, c: float = 0.0) -> np.ndarray:
    """Flux-map parameter array for the kernels (H, H, Wb, A/Wb^2, -, -, Wb, A/Wb^2)."""
    return np.array([ld_h, lq_h, psi_m_wb, beta, alpha, n, psi_qr_wb, c], dtype=np.float64)


@njit(cache=True)
def currents_from_flux(psi_d, psi_q, fm):
    """(i_d, i_q) in A of the flux linkages (Wb), the gradient of the energy function."""
    x = psi_d - fm[FM_PSI_M]
    y = psi_q
    i_d = x / fm[FM_LD] + fm[FM_BETA] * x * x + fm[FM_C] * y * y
    sat = fm[FM_ALPHA] * np.abs(y / fm[FM_PSI_QR]) ** fm[FM_N] if fm[FM_ALPHA] != 0.0 else 0.0
    i_q = y / fm[FM_LQ] * (1.0 + sat) + 2.0 * fm[FM_C] * x * y
    return i_d, i_q


@njit(cache=True)
def inverse_inductance(psi_d, psi_q, fm):
    """Hessian of the energy, d(i_d, i_q)/d(psi_d, psi_q) in 1/H: (a_dd, a_dq, a_qq)."""
    x = psi_d - fm[FM_PSI_M]
    y = psi_q
    a_dd = 1.0 / fm[FM_LD] + 2.0 * fm[FM_BETA] * x
    a_dq = 2.0 * fm[FM_C] * y
    sat = fm[FM_ALPHA] * (fm[FM_N] + 1.0) * np.abs(y / fm[FM_PSI_QR]) ** fm[FM_N] if fm[FM_ALPHA] != 0.0 else 0.0
    a_qq = (1.0 + sat) / fm[FM_LQ] + 2.0 * fm[FM_C] * x
    return a_dd, a_dq, a_qq


@njit(cache=True)
def flux_from_currents(i_d, i_q, fm):
    """(psi_d, psi_q) in Wb at the currents (A): Newton on the explicit i(psi), from the linear guess."""
    psi_d = fm[FM_PSI_M] + fm[FM_LD] * i_d
    psi_q = fm[FM_LQ] * i_q
    for _ in range(60):
        e_d, e_q = currents_from_flux(psi_d, psi_q, fm)
        e_d -= i_d
        e_q -= i_q
        a_dd, a_dq, a_qq = inverse_inductance(psi_d, psi_q, fm)
        det = a_dd * a_qq - a_dq * a_dq
        step_d = (a_qq * e_d - a_dq * e_q) / det
        step_q = (a_dd * e_q - a_dq * e_d) / det
        psi_d -= step_d
        psi_q -= step_q
        if abs(step_d) + abs(step_q) < 1e-13 * (1.0 + abs(psi_d) + abs(psi_q)):
            break
    return psi_d, psi_q


@njit(cache=True)
def flux_from_currents_array(i_d, i_q, fm):
    """Vector form of :func:`flux_from_currents` over equal-length arrays."""
    psi_d = np.empty(i_d.size)
    psi_q = np.empty(i_d.size)
    for k in range(i_d.size):
        psi_d[k], psi_q[k] = flux_from_currents(i_d[k], i_q[k], fm)
    return psi_d, psi_q


def torque_nm(i_d, i_q, fm, pole_pairs: int):
    """Electromagnetic torque 1.5 p (psi_d i_q - psi_q i_d) of the flux map (N m), no harmonics."""
    i_d, i_q = np.broadcast_arrays(np.asarray(i_d, float), np.asarray(i_q, float))
    psi_d, psi_q = flux_from_currents_array(i_d.ravel().copy(), i_q.ravel().copy(), fm)
    return (1.5 * pole_pairs * (psi_d * i_q.ravel() - psi_q * i_d.ravel())).reshape(i_d.shape)


def is_convex(fm: np.ndarray, i_max: float) -> bool:
    """Whether the energy is strictly convex (positive definite incremental inductance) over
    currents up to ``i_max`` (A peak) in every direction: the map is then one-to-one and physical."""
    mag = np.linspace(0.0, i_max, 25)
    ang = np.linspace(0.0, 2 * np.pi, 48, endpoint=False)
    i_d = (mag[:, None] * np.cos(ang)).ravel()
    i_q = (mag[:, None] * np.sin(ang)).ravel()
    psi_d, psi_q = flux_from_currents_array(i_d, i_q, fm)
    for pd, pq, want_d, want_q in zip(psi_d, psi_q, i_d, i_q):
        a_dd, a_dq, a_qq = inverse_inductance(pd, pq, fm)
        got = currents_from_flux(pd, pq, fm)
        if a_dd <= 0 or a_dd * a_qq - a_dq * a_dq <= 0 or abs(got[0] - want_d) + abs(got[1] - want_q) > 1e-6 * (1 + i_max):
            return False
    return True


# ---------------------------------------------------------------- magnet flux space harmonics


def harmonic_terms(orders, amplitudes_wb, phases_rad) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Phase-a magnet flux harmonics psi_h cos(h theta + phi_h) (phases b, c at theta -+ 2 pi/3) as
    rotor-frame terms psi_h exp(j s (m theta + phi_h)): (s, m, psi_h, phi_h) arrays.

    Orders 6k+1 (7, 13) are positive sequence: s = +1, m = h - 1; orders 6k-1 (5, 11) negative:
    s = -1, m = h + 1. Triplen orders are zero sequence and do not link a star winding's currents."""
    sign, mult = [], []
    for h in orders:
        if h % 3 == 0:
            raise ValueError(f"order {h}: a triplen harmonic is zero sequence")
        positive = h % 3 == 1
        sign.append(1.0 if positive else -1.0)
        mult.append(h - 1 if positive else h + 1)
    return (np.array(sign, float), np.array(mult, float), np.asarray(amplitudes_wb, float),
            np.asarray(phases_rad, float))


@njit(cache=True)
def harmonic_flux(theta, h_sign, h_mult, h_amp, h_phase):
    """Rotor-frame magnet harmonic flux (psi_hd, psi_hq) (Wb) and its derivative d/dtheta_e (Wb/rad)."""
    pd = 0.0
    pq = 0.0
    dd = 0.0
    dq = 0.0
    for j in range(h_amp.size):
        arg = h_sign[j] * (h_mult[j] * theta + h_phase[j])
        c = np.cos(arg)
        s = np.sin(arg)
        pd += h_amp[j] * c
        pq += h_amp[j] * s
        k = h_sign[j] * h_mult[j] * h_amp[j]
        dd -= k * s
        dq += k * c
    return pd, pq, dd, dq
