"""The PMSM dq model (paper eqs. 5-6, 13-14) and the transmission torque model (eqs. 10-12, 15).

A model is linear in its parameters. Each axis ``x`` in (d, q) predicts the next current

    i_x(k+1) = sum_j theta_x[j] * column_j(k)

where a column is either a *state* term (a dq current, optionally multiplied by omega_e(k)) or an
*exogenous* term computed from measured signals (voltage, speed, effect regressors). The two forms:

* ``lumped`` -- the paper's eqs. 13-14, omega_e folded into the parameters (one speed only):
  d: [i_q, i_d, v_d] -> [w Lq Ts/Ld, 1 - Rs Ts/Ld, Ts/Ld]
  q: [i_q, i_d, v_q, w] -> [1 - Rs Ts/Lq, -w Ld Ts/Lq, Ts/Lq, -psi_m Ts/Lq]
* ``speed`` -- the same eq. 6 with omega_e(k) as a regressor (one set across speeds and transients):
  d: [i_d, w i_q, v_d] -> [1 - Rs Ts/Ld, Lq Ts/Ld, Ts/Ld]
  q: [i_q, w i_d, v_q, w] -> [1 - Rs Ts/Lq, -Ld Ts/Lq, Ts/Lq, -psi_m Ts/Lq]

Because state terms are explicit, the same parameters give the one-step predictor and the
free-run simulation x(k+1) = (A0 + omega_e(k) A1) x(k) + u(k) (a C kernel, agent/kernels.py).

An *output* term (``Term(output=True)``, e.g. a current-sensor offset) acts on the measurement,
not on the dynamics: the measured current is y(k) = x(k) + o(k) with o(k) = sum_j theta_j c_j(k)
(A); the simulation starts from x(0) = y(0) - o(0) and returns y. In the one-step regression an
output column enters as an ordinary column c_j(k) (an approximation used only by ``fit_record``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from agent.frames import abc_to_dq
from agent.kernels import simulate_ltv

FORMS = ("lumped", "speed")


@dataclass(frozen=True)
class Signals:
    """dq-frame signals of one record or window: currents (A), voltages (V), angle (rad), speed (rad/s)."""

    i_dq: np.ndarray  #: (2, N) A
    v_dq: np.ndarray  #: (2, N) V
    theta_e: np.ndarray  #: (N,) rad, unwrapped
    omega_e: np.ndarray  #: (N,) rad/s
    ts: float  #: sampling period, s
    i_abc: np.ndarray | None = None  #: (3, N) A, for effects that act per phase
    v_abc: np.ndarray | None = None  #: (3, N) V
    pole_pairs: int | None = None  #: for effects tied to the shaft angle theta_e / p
    p_in: np.ndarray | None = None  #: (N,) W, instantaneous input power v_a i_a + v_b i_b + v_c i_c
    cos_sin: np.ndarray | None = None  #: (2, N) cos(theta_e), sin(theta_e) when already computed

    @property
    def n(self) -> int:
        return self.omega_e.size

    @property
    def power(self) -> np.ndarray:
        """Instantaneous electrical input power, W (eq. 10's P_in)."""
        return self.p_in if self.p_in is not None else input_power(self.v_abc, self.i_abc)

    @classmethod
    def from_abc(cls, v_abc, i_abc, theta_e, omega_e, ts, pole_pairs: int | None = None) -> "Signals":
        """Currents are samples at t_k; voltage sample k is the voltage held over [t_k, t_k + T_s)
        (the zero-order hold behind eq. 6), so it is rotated at the interval's mid angle
        theta_e + omega_e T_s / 2."""
        theta_e = np.unwrap(np.asarray(theta_e, dtype=float))
        omega_e = np.asarray(omega_e, dtype=float)
        i_dq, _ = abc_to_dq(i_abc, theta_e)
        v_dq, _ = abc_to_dq(v_abc, theta_e + 0.5 * omega_e * ts)
        return cls(i_dq, v_dq, theta_e, omega_e, ts, np.asarray(i_abc), np.asarray(v_abc), pole_pairs,
                   input_power(v_abc, i_abc))

    def slice(self, start: int, stop: int) -> "Signals":
        cut = slice(start, stop)
        opt = lambda a: None if a is None else a[:, cut]  # noqa: E731
        return Signals(self.i_dq[:, cut], self.v_dq[:, cut], self.theta_e[cut], self.omega_e[cut], self.ts,
                       opt(self.i_abc), opt(self.v_abc), self.pole_pairs,
                       None if self.p_in is None else self.p_in[cut], opt(self.cos_sin))


@dataclass(frozen=True)
class Term:
    """One regressor column. ``state`` = index of the dq current it multiplies (0 d, 1 q) or None for
    an exogenous column given by ``exo(signals) -> (N,)``; ``speed`` multiplies by omega_e(k);
    ``output``: an exogenous column added to the measured current instead of the state equation."""

    name: str
    state: int | None = None
    speed: bool = False
    exo: Callable[[Signals], np.ndarray] | None = None
    output: bool = False

    def column(self, sig: Signals) -> np.ndarray:
        base = sig.i_dq[self.state] if self.state is not None else self.exo(sig)
        return base * sig.omega_e if self.speed else base


_V_D = Term("v_d", exo=lambda s: s.v_dq[0])
_V_Q = Term("v_q", exo=lambda s: s.v_dq[1])
_W = Term("w", exo=lambda s: s.omega_e)

#: Base regressors of each form: (d-axis terms, q-axis terms), in the paper's column order.
BASE_TERMS: dict[str, tuple[tuple[Term, ...], tuple[Term, ...]]] = {
    "lumped": ((Term("i_q", 1), Term("i_d", 0), _V_D),
               (Term("i_q", 1), Term("i_d", 0), _V_Q, _W)),
    "speed": ((Term("i_d", 0), Term("w*i_q", 1, speed=True), _V_D),
              (Term("i_q", 1), Term("w*i_d", 0, speed=True), _V_Q, _W)),
}


def regressors(terms: tuple[Term, ...], sig: Signals) -> np.ndarray:
    """(N, n) regressor matrix of one axis; row k predicts the current at k+1."""
    return np.column_stack([t.column(sig) for t in terms])


@dataclass
class DQModel:
    """Identified discrete dq model (eq. 6) with its regression form and extra terms."""

    form: str
    ts: float
    theta_d: np.ndarray
    theta_q: np.ndarray
    extra_d: tuple[Term, ...] = ()
    extra_q: tuple[Term, ...] = ()
    fe_hz: float = float("nan")  #: operating point the model was identified at
    meta: dict = field(default_factory=dict)
    discretisation: str = "euler"  #: "euler" (eq. 6 as it stands) or "zoh2" (:meth:`propagation`)

    @property
    def terms(self) -> tuple[tuple[Term, ...], tuple[Term, ...]]:
        base_d, base_q = BASE_TERMS[self.form]
        return base_d + self.extra_d, base_q + self.extra_q

    def one_step(self, sig: Signals) -> np.ndarray:
        """One-step-ahead prediction (2, N); sample 0 is the measurement.
        With output terms: y(k+1) = A(k) (y(k) - o(k)) + u(k) + o(k+1)."""
        o = self.output(sig)
        if o is None and self.discretisation == "euler":
            out = np.empty_like(sig.i_dq)
            out[:, 0] = sig.i_dq[:, 0]
            for axis, (terms, theta) in enumerate(zip(self.terms, (self.theta_d, self.theta_q))):
                out[axis, 1:] = (regressors(terms, sig) @ theta)[:-1]
            return out
        o = np.zeros_like(sig.i_dq) if o is None else o
        a0, a1, u = self.propagation(sig)
        x = sig.i_dq - o
        w = sig.omega_e[:-1]
        ax = np.einsum("ij,jk->ik", a0, x[:, :-1]) + w * np.einsum("ij,jk->ik", a1, x[:, :-1])
        return np.hstack((sig.i_dq[:, :1], ax + u[:, :-1] + o[:, 1:]))

    def propagation(self, sig: Signals) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(A0', A1', u'): the free run x(k+1) = (A0' + omega_e(k) A1') x(k) + u'(k) on ``sig``.

        ``euler``: the model's own matrices and inputs (eq. 6: A = I + A_c T_s, u = B_c T_s v).
        ``zoh2``: the zero-order-hold solution to second order in T_s, written with those Euler
        matrices: x(k+1) = x + (I + A)/2 (A x + u - x) = (I + A^2)/2 x + (I + A)/2 u. Euler leaves
        out the -(omega_e T_s)^2/2 of the rotating frame's exact transition matrix, a damping that
        a fit then books as resistance (R + omega_e^2 T_s L/2: +17 % at omega_e T_s = 0.05), which
        under MTPA shows on d as R i_d. omega_e^2 is linearised about the record's mean speed."""
        u = self.exogenous(sig)
        if self.discretisation == "euler":
            return (*self.state_matrices(), u)
        a0, a1 = self.state_matrices()
        return (*self.transition(float(np.mean(sig.omega_e))), zoh2_input(a0, a1, sig.omega_e, u))

    def transition(self, omega_e: float) -> tuple[np.ndarray, np.ndarray]:
        """(A0', A1') of :meth:`propagation` about the speed ``omega_e`` (rad/s; zoh2 linearises
        omega_e^2 there, Euler does not need it)."""
        a0, a1 = self.state_matrices()
        return (a0, a1) if self.discretisation == "euler" else zoh2_matrices(a0, a1, omega_e)

    def psi_input(self, sig: Signals, on_q: bool = False) -> np.ndarray:
        """u'(k) (2, N) of +1 Wb of magnet flux (the back-EMF column w on q, coefficient -T_s/L_q per
        Wb); ``on_q``: of +1 Wb along the frame's q axis instead (back-EMF -omega_e psi_q on d, a frame
        that is not the rotor's: :attr:`agent.workbench.fitting.Prepared.turned`)."""
        u = np.zeros((2, sig.n))
        if on_q:
            u[0] = self.theta_d[2] * sig.omega_e  # theta_d[2] = T_s/L_d in both forms
        else:
            u[1] = -self.theta_q[2] * sig.omega_e  # theta_q[2] = T_s/L_q in both forms
        if self.discretisation == "euler":
            return u
        a0, a1 = self.state_matrices()
        return zoh2_input(a0, a1, sig.omega_e, u)

    def state_matrices(self) -> tuple[np.ndarray, np.ndarray]:
        """(A0, A1): x(k+1) = (A0 + omega_e(k) A1) x(k) + u(k)."""
        a0, a1 = np.zeros((2, 2)), np.zeros((2, 2))
        for axis, (terms, theta) in enumerate(zip(self.terms, (self.theta_d, self.theta_q))):
            for term, value in zip(terms, theta):
                if term.state is not None:
                    (a1 if term.speed else a0)[axis, term.state] += value
        return a0, a1

    def exogenous(self, sig: Signals) -> np.ndarray:
        """u(k), (2, N): the sum of the exogenous columns times their parameters."""
        u = np.zeros((2, sig.n))
        for axis, (terms, theta) in enumerate(zip(self.terms, (self.theta_d, self.theta_q))):
            for term, value in zip(terms, theta):
                if term.state is None and not term.output:
                    u[axis] += value * term.column(sig)
        return u

    def output(self, sig: Signals) -> np.ndarray | None:
        """o(k), (2, N): the output terms' contribution to the measured current (A), None without any."""
        if not any(t.output for terms in self.terms for t in terms):
            return None
        o = np.zeros((2, sig.n))
        for axis, (terms, theta) in enumerate(zip(self.terms, (self.theta_d, self.theta_q))):
            for term, value in zip(terms, theta):
                if term.output:
                    o[axis] += value * term.column(sig)
        return o

    def simulate(self, sig: Signals, x0: np.ndarray | None = None) -> np.ndarray:
        """Free-run simulation (2, N) driven by measured voltages and speed, from ``x0`` (default:
        the first measured current). Diverging output is returned as is (inf/NaN)."""
        a0, a1, u = self.propagation(sig)
        x0 = sig.i_dq[:, 0] if x0 is None else np.asarray(x0, dtype=float)
        o = self.output(sig)
        if o is None:
            return simulate_ltv(a0, a1, sig.omega_e, u, x0)
        return simulate_ltv(a0, a1, sig.omega_e, u, x0 - o[:, 0]) + o

    def spectral_radius(self, omega_e: float) -> float:
        """Largest |eigenvalue| of the state matrix at speed ``omega_e`` (rad/s); < 1 means stable."""
        a0, a1 = self.transition(omega_e)
        return float(np.max(np.abs(np.linalg.eigvals(a0 + omega_e * a1))))

    def physical(self, omega_e: float | None = None) -> dict[str, float]:
        """Physical parameters recovered from the lumped ones (Rs ohm, Ld/Lq H, psi_m Wb).

        d axis gives Ld, Rs and (lumped form: through omega_e) Lq; q axis gives Lq, Rs, Ld, psi_m.
        ``omega_e`` (rad/s) defaults to the model's operating point; it is needed for the lumped form.
        """
        w = 2 * np.pi * self.fe_hz if omega_e is None else omega_e
        ts = self.ts
        if self.form == "lumped":
            a_dq, a_dd, b_d = self.theta_d[:3]
            a_qq, a_qd, b_q, c_q = self.theta_q[:4]
            lq_d, ld_q = a_dq / (w * b_d), -a_qd / (w * b_q)
        else:
            a_dd, l_d, b_d = self.theta_d[:3]
            a_qq, l_q, b_q, c_q = self.theta_q[:4]
            lq_d, ld_q = l_d / b_d, -l_q / b_q
        return {
            "Rs_d": (1 - a_dd) / b_d, "Rs_q": (1 - a_qq) / b_q,
            "Ld": ts / b_d, "Lq": ts / b_q, "Lq_from_d": lq_d, "Ld_from_q": ld_q,
            "psi_m": -c_q / b_q, "Ts_over_Lq": b_q,
        }

    def is_plausible(self, omega_e: float | None = None) -> tuple[bool, str]:
        """Positive R and L and a stable free-run at ``omega_e`` (rad/s); returns (ok, reason).

        psi_m is not checked: at one steady operating point only Rs i_q + omega_e psi_m is
        identifiable, so a fit may trade the two (see :meth:`physical`) while predicting well."""
        w = 2 * np.pi * self.fe_hz if omega_e is None else omega_e
        p = self.physical(w)
        bad = [k for k in ("Rs_d", "Rs_q", "Ld", "Lq") if not (np.isfinite(p[k]) and p[k] > 0)]
        if bad:
            return False, "non-positive " + ", ".join(bad)
        rho = self.spectral_radius(w)
        if not rho < 1.0:
            return False, f"unstable free-run (spectral radius {rho:.6f})"
        return True, "ok"

    def from_physical(self, rs: float, ld: float, lq: float, psi_m: float, omega_e: float | None = None) -> None:
        """Set the base parameters from physical values (extra terms keep their parameters)."""
        w = 2 * np.pi * self.fe_hz if omega_e is None else omega_e
        self.theta_d = np.concatenate((lumped_params(self.form, self.ts, rs, ld, lq, psi_m, w)[0],
                                       self.theta_d[3:]))
        self.theta_q = np.concatenate((lumped_params(self.form, self.ts, rs, ld, lq, psi_m, w)[1],
                                       self.theta_q[4:]))


def zoh2_matrices(a0: np.ndarray, a1: np.ndarray, w0: float) -> tuple[np.ndarray, np.ndarray]:
    """(I + A^2)/2 with A = A0 + omega A1, as B0 + omega B1 (omega^2 ~ 2 w0 omega - w0^2)."""
    eye = np.eye(2)
    return 0.5 * (eye + a0 @ a0 - w0 ** 2 * a1 @ a1), 0.5 * (a0 @ a1 + a1 @ a0 + 2.0 * w0 * a1 @ a1)


def zoh2_input(a0: np.ndarray, a1: np.ndarray, omega: np.ndarray, u: np.ndarray) -> np.ndarray:
    """(I + A(k))/2 u(k), A(k) = A0 + omega(k) A1, for (2, N) inputs."""
    return 0.5 * (u + a0 @ u + omega * (a1 @ u))


def lumped_params(form: str, ts: float, rs: float, ld: float, lq: float, psi_m: float,
                  omega_e: float) -> tuple[np.ndarray, np.ndarray]:
    """Base parameter vectors (d, q) of ``form`` from physical values (eq. 6, Euler)."""
    if form == "lumped":
        d = [omega_e * lq * ts / ld, 1 - rs * ts / ld, ts / ld]
        q = [1 - rs * ts / lq, -omega_e * ld * ts / lq, ts / lq, -psi_m * ts / lq]
    else:
        d = [1 - rs * ts / ld, lq * ts / ld, ts / ld]
        q = [1 - rs * ts / lq, -ld * ts / lq, ts / lq, -psi_m * ts / lq]
    return np.array(d), np.array(q)


# --- transmission (eqs. 10-12, 15) -------------------------------------------------------------

def input_power(v_abc: np.ndarray, i_abc: np.ndarray) -> np.ndarray:
    """Instantaneous electrical input power P_in = v_a i_a + v_b i_b + v_c i_c, W."""
    return np.einsum("ij,ij->j", v_abc, i_abc)


def torque_regression(sig: Signals, pole_pairs: int, torque_per_watt: float) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 15: regressor columns [theta_m, omega_m] (2, N), y = T_shaft (N,) with T_shaft = (T_rated/P_rated) P_in
    (eq. 10) and theta_m = theta_e/p, omega_m = omega_e/p (eq. 12).

    theta_m is the unwrapped angle measured from the middle of the record: at steady speed it is
    then orthogonal to the constant omega_m, so K_GT takes the torque's drift over the record and
    B_GT the mean torque over speed, instead of the two trading off through an arbitrary origin.
    """
    t_shaft = torque_per_watt * sig.power
    theta_m = (sig.theta_e - np.mean(sig.theta_e)) / pole_pairs
    return np.vstack((theta_m, sig.omega_e / pole_pairs)), t_shaft


def nrmse(i_meas: np.ndarray, i_model: np.ndarray) -> dict[str, float]:
    """Normalised RMS error of dq currents (2, N), as fractions.

    Each axis and the total are normalised by the RMS current-vector magnitude
    sqrt(mean(i_d^2 + i_q^2)), so the d axis (near zero under id = 0 control) gets a meaningful
    figure; ``total`` equals the per-phase RMS error over the per-phase RMS current.
    """
    err = np.asarray(i_meas) - np.asarray(i_model)
    ref = np.sqrt(np.mean(np.sum(np.asarray(i_meas) ** 2, axis=0)))
    d, q = np.sqrt(np.mean(err**2, axis=1)) / ref
    return {"d": float(d), "q": float(q), "total": float(np.sqrt(np.mean(np.sum(err**2, axis=0))) / ref)}
