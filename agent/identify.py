"""Parameter identification of one record (paper Alg. 1 applied to eqs. 13-15).

Steps: angle and speed (the record's ``theta_e``/``omega_e`` or the PLL), dq signals, regressors,
a low-pass *prefilter* applied identically to every regressor column and to the output, then
streaming RLS (exact batch least squares for ``lam = 1``).

Why the prefilter: the current regressors carry white measurement noise, which biases least squares
(errors in variables) badly on steady-state data where the true current ripple is small. Filtering
both sides of a linear-in-parameters equation with the same linear filter keeps the equation exact
while removing the noise above the band where the drive's dynamics live. ``prefilter_hz=None``
gives the paper's unfiltered estimate.

If the estimate is not physically plausible (non-positive R, L, psi_m or an unstable free-run),
it is replaced by the closest plausible one in the metric of the RLS information matrix
(a bounded fit over Rs, Ld, Lq, psi_m), and ``FitResult.constrained`` says so.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from agent.model import BASE_TERMS, DQModel, Signals, Term, lumped_params, regressors, torque_regression
from agent.pll import track
from agent.profile import DriveProfile
from agent.records import Record
from agent.rls import StreamingRLS

PREFILTER_HZ: float | None = None  #: default prefilter cut-off, Hz (4th-order Butterworth); None = off
PREFILTER_ORDER = 4


def record_signals(record: Record, profile: DriveProfile) -> Signals:
    """dq signals of a record: angle/speed from its columns when present, else from the PLL on the
    currents, started where the record starts (:meth:`agent.pll.PLL.reset`)."""
    rate = profile.sampling.rate_hz
    if record.theta_e is not None:
        theta = np.unwrap(record.theta_e)
        omega = record.omega_e if record.omega_e is not None else np.gradient(theta) * rate
    else:
        theta, omega = track(record.i_abc, rate, profile.rated_fe_hz)  # no acquisition transient
    return Signals.from_abc(record.v_abc, record.i_abc, theta, omega, 1.0 / rate, profile.motor.pole_pairs)


def operating_point(sig: Signals, profile: DriveProfile) -> dict[str, float]:
    """A record's operating point as a drive shows it: ``fe_hz`` (electrical frequency, Hz) and
    ``load_pct``, the torque over the rated torque (%), 1.5 p (psi_m i_q + (L_d - L_q) i_d i_q)
    with psi_m from the nameplate (``psi_m_wb`` or the back-EMF constant), else from the rating
    (rated torque at rated current, i_d = 0: then the q current over the rated current), and the
    reluctance term where the nameplate gives L_d and L_q (a salient machine under MTPA); where the
    profile has neither, the input power over the rated power. ``input_power_pct`` is that input
    power (eq. 10's P_in) in any case. One definition from the profile alone, so that a baseline and
    the running agent read the same figure."""
    i = sig.i_dq
    return operating_point_of_means(float(np.mean(sig.power)), float(np.mean(i[1])), float(np.mean(sig.omega_e)),
                                    profile, float(np.mean(i[0] * i[1])))


def operating_point_of_means(power_w: float, i_q_a: float, omega_e: float, profile: DriveProfile,
                             i_dq_a2: float = 0.0) -> dict[str, float]:
    """:func:`operating_point` from the record's mean input power (W), q current (A), speed (rad/s)
    and mean i_d i_q (A^2)."""
    p_in = 100.0 * power_w / profile.motor.rated_power_w
    m, plate = profile.motor, profile.nameplate
    psi = (plate.psi_m(m.pole_pairs) if plate else None) or m.psi_m_from_rating
    reluctance = (plate.ld_h - plate.lq_h) * i_dq_a2 if plate and plate.ld_h and plate.lq_h else 0.0
    load = p_in if psi is None else 100.0 * 1.5 * m.pole_pairs * (psi * i_q_a + reluctance) / m.rated_torque_nm
    return {"fe_hz": omega_e / (2 * np.pi), "load_pct": load, "input_power_pct": p_in}


@dataclass
class FitResult:
    """Identified parameters of one record."""

    model: DQModel
    theta_torque: np.ndarray  #: [K_GT (N m/rad), B_GT (N m s/rad)], eq. 15
    info_d: np.ndarray  #: RLS information matrices (inverse covariance), for constrained fits
    info_q: np.ndarray
    constrained: bool = False
    reason: str = "ok"
    operating_point: dict = field(default_factory=dict)

    @property
    def cluster_point(self) -> np.ndarray:
        """(Ts/Lq, B_GT): the paper's parameter-cluster coordinates (Alg. 4)."""
        return np.array([self.model.theta_q[2], self.theta_torque[1]])


def prefilter(columns: np.ndarray, rate_hz: float, cutoff_hz: float | None) -> np.ndarray:
    """Low-pass every column (N, m) with the same Butterworth filter, started at the first row's value."""
    if cutoff_hz is None:
        return columns
    import scipy.signal  # noqa: PLC0415 (heavy; the default path has no prefilter)

    sos = scipy.signal.butter(PREFILTER_ORDER, cutoff_hz, fs=rate_hz, output="sos")
    zi = scipy.signal.sosfilt_zi(sos)[:, :, None] * columns[0][None, None, :]
    return scipy.signal.sosfilt(sos, columns, axis=0, zi=zi)[0]


def fit_axes(sig: Signals, terms: tuple[tuple[Term, ...], ...], prefilter_hz: float | None = PREFILTER_HZ,
             axes: tuple[int, ...] = (0, 1)) -> list[StreamingRLS]:
    """One RLS per axis (0 d, 1 q) on the (prefiltered) regression i_x(k+1) = X(k) theta_x."""
    rate = 1.0 / sig.ts
    out = []
    for axis, axis_terms in zip(axes, terms):
        x = regressors(axis_terms, sig)[:-1]
        both = prefilter(np.column_stack((x, sig.i_dq[axis, 1:])), rate, prefilter_hz)
        rls = StreamingRLS(x.shape[1], lam=1.0, p0=1e6)
        rls.update(both[:, :-1], both[:, -1])
        out.append(rls)
    return out


def fit_record(sig: Signals, profile: DriveProfile, form: str = "lumped",
               extra: tuple[tuple[Term, ...], tuple[Term, ...]] = ((), ()),
               prefilter_hz: float | None = PREFILTER_HZ, plausible: bool = True) -> FitResult:
    """Identify the dq model (eqs. 13-14) and the torque model (eq. 15) of one record.

    With ``plausible`` an implausible estimate is replaced by the closest plausible one
    (:func:`constrain`); without, the raw RLS estimate is kept (the paper's Algs. 2 and 4 average
    and cluster raw estimates) and ``FitResult.reason`` says what is implausible about it."""
    base_d, base_q = BASE_TERMS[form]
    rls_d, rls_q = fit_axes(sig, (base_d + extra[0], base_q + extra[1]), prefilter_hz)
    op = operating_point(sig, profile)
    model = DQModel(form, sig.ts, rls_d.theta, rls_q.theta, extra[0], extra[1], fe_hz=op["fe_hz"])
    fit = FitResult(model, fit_torque(sig, profile), rls_d.information, rls_q.information, operating_point=op)
    ok, fit.reason = model.is_plausible()
    if not ok and plausible:
        constrain(fit, psi_m_prior(profile))
        fit.constrained = True
    return fit


def fit_torque(sig: Signals, profile: DriveProfile) -> np.ndarray:
    """[K_GT (N m/rad), B_GT (N m s/rad)] of the torque regression (eq. 15) over the record."""
    (theta_m, omega_m), t_shaft = torque_regression(sig, profile.motor.pole_pairs, profile.torque_per_watt)
    return solve_torque(theta_m @ theta_m, theta_m @ omega_m, omega_m @ omega_m, theta_m @ t_shaft, omega_m @ t_shaft)


def solve_torque(tt: float, tw: float, ww: float, ty: float, wy: float) -> np.ndarray:
    """[K_GT, B_GT] from the torque regression's dot products (t: theta_m, w: omega_m, y: T_shaft):
    RLS without forgetting in information form (R = P0^-1 + X^T X, r = X^T y), P0 = 1e6, from the
    two columns' dot products directly since there are only two."""
    info = np.array([[tt, tw], [tw, ww]]) + 1e-6 * np.eye(2)
    return np.linalg.solve(info, np.array([ty, wy]))


def cluster_point(sig: Signals, profile: DriveProfile, form: str = "lumped", extra_q: tuple[Term, ...] = (),
                  prefilter_hz: float | None = PREFILTER_HZ) -> np.ndarray:
    """(Ts/Lq, B_GT) of Alg. 4 lines 7-9: the q-axis regression's input gain and the torque model's
    friction term, without the d axis that the cluster does not use."""
    (rls_q,) = fit_axes(sig, (BASE_TERMS[form][1] + tuple(extra_q),), prefilter_hz, axes=(1,))
    return np.array([rls_q.theta[2], fit_torque(sig, profile)[1]])


def psi_m_prior(profile: DriveProfile) -> float | None:
    """Nameplate magnet flux linkage, Wb: the profile's ``[nameplate]`` value, else from the rated
    torque and current, T_rated = 1.5 p psi_m sqrt(2) I_rated (id = 0)."""
    m = profile.motor
    if profile.nameplate is not None and profile.nameplate.psi_m(m.pole_pairs) is not None:
        return profile.nameplate.psi_m(m.pole_pairs)
    return m.psi_m_from_rating


def constrain(fit: FitResult, psi_m: float | None = None) -> None:
    """Replace the base parameters by the plausible (Rs, Ld, Lq, psi_m > 0) set closest to the
    estimate in the information metric: min sum_axes (g(p) - theta)^T R (g(p) - theta).

    At one steady operating point only Rs i_q + omega_e psi_m is identifiable, not the two apart;
    ``psi_m`` (Wb, e.g. :func:`psi_m_prior`) fixes the magnet flux so that Rs takes the rest.
    """
    model = fit.model
    w = 2 * np.pi * model.fe_hz
    nd, nq = len(BASE_TERMS[model.form][0]), len(BASE_TERMS[model.form][1])
    # the base parameters' block: the extra terms (effects) keep their estimates
    chol_d, chol_q = _sqrt_info(fit.info_d[:nd, :nd]), _sqrt_info(fit.info_q[:nq, :nq])
    scale = np.array([1.0, 1e-2, 1e-2, 0.1])  # Rs ohm, Ld H, Lq H, psi_m Wb: typical magnitudes
    phys = model.physical(w)
    guess = np.array([phys["Rs_q"], phys["Ld"], phys["Lq"], phys["psi_m"] if psi_m is None else psi_m])
    guess = np.where(np.isfinite(guess) & (guess > 0), guess, scale)
    free = slice(0, 4 if psi_m is None else 3)

    def params(z):  # log parametrisation, within 2e-9 .. 5e8 of the typical magnitudes
        p = guess.copy()
        p[free] = np.exp(np.clip(z, -20.0, 20.0)) * scale[free]
        return p

    def residual(z):
        g_d, g_q = lumped_params(model.form, model.ts, *params(z), w)
        return np.concatenate((chol_d @ (g_d - model.theta_d[:nd]), chol_q @ (g_q - model.theta_q[:nq])))

    model.from_physical(*params(levenberg_marquardt(residual, np.log(guess[free] / scale[free]))), omega_e=w)


def levenberg_marquardt(residual, x0: np.ndarray, max_iter: int = 200, tol: float = 1e-12) -> np.ndarray:
    """Minimise ||residual(x)||^2 from ``x0`` (a few parameters; forward-difference Jacobian).

    Numpy only: the running agent constrains a learned model without scipy (the gateway install).
    The damping falls after a step that lowers the cost and rises after one that does not."""
    x = np.asarray(x0, dtype=float).copy()
    r = residual(x)
    cost, lam = float(r @ r), 1e-3
    for _ in range(max_iter):
        h = 1e-7 * (1.0 + np.abs(x))
        jac = np.column_stack([(residual(x + np.eye(x.size)[j] * h[j]) - r) / h[j] for j in range(x.size)])
        g, hess = jac.T @ r, jac.T @ jac
        while True:
            step = np.linalg.solve(hess + lam * np.diag(np.diag(hess) + 1e-12), -g)
            r_new = residual(x + step)
            c_new = float(r_new @ r_new)
            if np.isfinite(c_new) and c_new < cost:
                x, r, lam = x + step, r_new, max(lam / 3.0, 1e-12)
                done = cost - c_new <= tol * cost or np.linalg.norm(step) <= tol * (1.0 + np.linalg.norm(x))
                cost = c_new
                break
            lam *= 4.0
            if lam > 1e12:
                return x
        if done:
            return x
    return x


def _sqrt_info(info: np.ndarray) -> np.ndarray:
    """W with W^T W = info (symmetric PSD), robust to near-singular matrices."""
    e, v = np.linalg.eigh(0.5 * (info + info.T))
    return np.sqrt(np.clip(e, 0.0, None))[:, None] * v.T


def refine_output_error(model: DQModel, sigs: list[Signals], max_records: int = 8,
                        max_samples: int = 25_000) -> DQModel:
    """Simulation-error refinement of ``model`` on healthy records (returns a new model).

    Minimises sum ||i_dq - free-run(i_dq)||^2 over the physical parameters (Rs, Ld, Lq, psi_m,
    kept positive by a log parametrisation) and the extra terms' parameters. The simulation is
    driven by voltages and speed only, so current-sensor noise does not bias it (unlike the
    one-step regression), and the result is plausible by construction. Uses up to ``max_records``
    records (evenly chosen) and the first ``max_samples`` samples of each.
    """
    w = 2 * np.pi * model.fe_hz
    base_d, base_q = (len(t) for t in BASE_TERMS[model.form])
    pick = np.unique(np.linspace(0, len(sigs) - 1, min(max_records, len(sigs))).round().astype(int))
    parts = [sigs[j].slice(0, max_samples) for j in pick]
    scale = np.array([1.0, 1e-2, 1e-2, 0.1])  # Rs ohm, Ld H, Lq H, psi_m Wb: typical magnitudes
    trial = DQModel(model.form, model.ts, model.theta_d.copy(), model.theta_q.copy(), model.extra_d,
                    model.extra_q, model.fe_hz, dict(model.meta))

    def unpack(z):
        trial.from_physical(*(np.exp(z[:4]) * scale), omega_e=w)
        trial.theta_d[base_d:] = z[4:4 + len(model.extra_d)]
        trial.theta_q[base_q:] = z[4 + len(model.extra_d):]

    def residual(z):
        unpack(z)
        res = np.concatenate([(s.i_dq - trial.simulate(s)).ravel() for s in parts])
        return np.nan_to_num(res, nan=1e6, posinf=1e6, neginf=-1e6)

    phys = model.physical(w)
    guess = np.array([phys["Rs_q"], phys["Ld"], phys["Lq"], phys["psi_m"]])
    guess = np.where(np.isfinite(guess) & (guess > 0), guess, scale)
    z0 = np.concatenate((np.log(guess / scale), model.theta_d[base_d:], model.theta_q[base_q:]))
    import scipy.optimize  # noqa: PLC0415

    sol = scipy.optimize.least_squares(residual, z0, method="trf", x_scale="jac", max_nfev=200)
    unpack(sol.x)
    trial.meta["refined"] = "output-error"
    return trial
