"""Output-error identification of the EMPS and the greedy effect-discovery loop.

The output-error residual is r(x) = qm − q_sim(θ(x)) (m) over a chosen subset ``free`` of the parameters, with
the closed loop simulated by :func:`toggle_id.emps.model.simulate_emps`. The fit is bounded least squares with a
batched forward-difference Jacobian (one kernel call for all columns, same RK4 substep count in every row), by
scipy's ``least_squares`` on the raw parameters or by :func:`toggle_id.polish.polish` (``solver='polish'``; log
space for M only: the offset is negative and effect parameters start at zero).

The judge of an effect, :func:`judge_effect`, returns the discovery engine's own verdict object,
:class:`toggle_id.discovery.validation.Evidence` (prewhitened F-test and BIC, time-block cross-validation) plus an
identifiability gate; the greedy loop that uses it is :func:`toggle_id.emps.loop.run_emps_loop`.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Callable, Mapping, Sequence

import numpy as np

from ..discovery.noise import NoiseModel, fit_noise
from ..discovery.stats import compare, out_of_sample, robust_f
from ..discovery.validation import Evidence, in_sample_summary
from ..errors import ConfigError
from .data import EmpsRecord
from .model import (
    INDEX,
    LOWER,
    PARAM_NAMES,
    PUBLISHED,
    PUBLISHED_ASYM_PM,
    UPPER,
    as_theta_batch,
    position_rel_error_pct,
    simulate_emps,
    theta_to_dict,
)

#: Typical magnitude of each parameter (sets finite-difference steps and x_scale), SI units.
_TYPICAL = {"M": 100.0, "Fv": 100.0, "Fc": 10.0, "offset": 1.0, "Fs": 1.0, "vs": 1e-3,
            "Fc_asym": 1.0, "Fv_asym": 10.0}
#: Residual returned (per sample, m) for a parameter vector whose simulation failed.
FAIL_RESIDUAL = 1.0


def _free_index(free: Sequence[str]) -> np.ndarray:
    """Indices of ``free`` in θ; raises ConfigError for unknown or repeated names."""
    unknown = [n for n in free if n not in INDEX]
    if unknown:
        raise ConfigError(f"unknown EMPS parameter(s) {unknown}; known: {list(PARAM_NAMES)}")
    if len(set(free)) != len(free) or not free:
        raise ConfigError(f"free parameters must be a non-empty list without repeats, got {list(free)}")
    return np.array([INDEX[n] for n in free], dtype=np.int64)


def required_substeps(theta: np.ndarray, dt: float, eps: float = 1e-4, h_lambda: float = 0.5,
                      n_sub_min: int = 2) -> np.ndarray:
    """RK4 substeps per sample the kernel picks for each row of θ (mirror of its λ bound), int array (P,)."""
    th = as_theta_batch(theta)
    M, Fv, Fc, _, Fs, vs, dFc, dFv = th.T
    lam = np.abs(Fv) + 2 * np.abs(dFv) + (np.abs(Fc) + np.abs(dFc) + np.abs(Fs)) / eps
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = lam + np.where(Fs != 0, np.abs(Fs) * np.sqrt(2 / np.e) / np.where(vs > 0, vs, 1.0), 0.0)
        n = np.ceil(dt * lam / np.where(M > 0, M, 1.0) / h_lambda)
    return np.maximum(np.nan_to_num(n, nan=n_sub_min, posinf=n_sub_min), n_sub_min).astype(np.int64)


def make_residual(record: EmpsRecord, free: Sequence[str], theta_base: np.ndarray,
                  sim_options: Mapping | None = None) -> Callable[[np.ndarray], np.ndarray]:
    """residual(x) = qm − q_sim (m, length N) with θ[free] = x and the other entries from ``theta_base`` (zero at the
    record's excluded samples, :meth:`EmpsRecord.residual`).

    A failed simulation (status ≠ 0) gives a finite residual of :data:`FAIL_RESIDUAL` m per sample, so optimisers
    reject the point instead of crashing. ``sim_options`` are passed to :func:`simulate_emps`.
    """
    idx = _free_index(free)
    base = np.array(as_theta_batch(theta_base)[0])
    opts = dict(sim_options or {})

    def residual(x: np.ndarray) -> np.ndarray:
        th = base.copy()
        th[idx] = np.asarray(x, dtype=float)
        res = simulate_emps(th, record, **opts)
        if res.status[0] != 0:
            return np.full(record.n, FAIL_RESIDUAL)
        return record.residual(res.q[0])

    return residual


def make_jacobian(record: EmpsRecord, free: Sequence[str], theta_base: np.ndarray, lower: np.ndarray,
                  upper: np.ndarray, rel_step: float = 1e-5,
                  sim_options: Mapping | None = None) -> Callable[[np.ndarray], np.ndarray]:
    """jac(x) = ∂residual/∂x (N, p) by forward differences, all p+1 simulations in one batched kernel call.

    Step j is rel_step·max(|x_j|, typical_j), taken downwards when the upward step would leave the bounds. Every
    row uses the same number of RK4 substeps (the largest any row needs) so the differences are smooth.
    """
    idx = _free_index(free)
    base = np.array(as_theta_batch(theta_base)[0])
    opts = dict(sim_options or {})
    typical = np.array([_TYPICAL[n] for n in free])
    lower = np.asarray(lower, float)
    upper = np.asarray(upper, float)

    def jac(x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        p = x.size
        steps = rel_step * np.maximum(np.abs(x), typical)
        steps = np.where(x + steps > upper, -steps, steps)
        th = np.tile(base, (p + 1, 1))
        th[:, idx] = x
        th[1 + np.arange(p), idx] += steps
        n_sub = required_substeps(th, record.dt, opts.get("eps", 1e-4), opts.get("h_lambda", 0.5),
                                  opts.get("n_sub_min", 2))
        o = dict(opts)
        o["n_sub_min"] = int(n_sub.max())
        o["n_sub_max"] = max(int(n_sub.max()), int(opts.get("n_sub_max", 5000)))
        res = simulate_emps(th, record, **o)
        J = np.zeros((record.n, p))
        if res.status[0] != 0:
            return J
        for j in range(p):
            if res.status[j + 1] == 0:
                J[:, j] = -(res.q[j + 1] - res.q[0]) / steps[j]
        if record.excluded is not None:
            J[record.excluded] = 0.0
        return J

    return jac


@dataclass
class OEFitResult:
    """Result of an output-error fit: full θ (8,), the free names, SSE (m²), samples N, relative position error (%),
    approximate standard deviations of the free parameters (from JᵀJ, white-residual assumption), optimiser info,
    and the residual (N,) and its Jacobian ∂r/∂x (N, p) w.r.t. the free parameters at the optimum."""

    theta: np.ndarray
    free: tuple[str, ...]
    sse: float
    n: int
    rel_error_pct: float
    std: dict = field(default_factory=dict)
    corr: np.ndarray | None = None
    nfev: int = 0
    success: bool = False
    message: str = ""
    seconds: float = 0.0
    residual: np.ndarray | None = field(default=None, repr=False)
    jacobian: np.ndarray | None = field(default=None, repr=False)

    @property
    def params(self) -> dict[str, float]:
        """All parameters as a plain dict."""
        return theta_to_dict(self.theta)


#: Parameters the 'polish' solver may move in log space (strictly positive lower bound); offset, Coulomb and the
#: asymmetries stay affine (they are zero when off, and the offset is negative).
LOG_PARAMS = frozenset({"M"})


SOLVERS = ("scipy", "polish")


def _check_solver(solver: str) -> None:
    """Raise ConfigError for an unknown solver name."""
    if solver not in SOLVERS:
        raise ConfigError(f"solver must be one of {SOLVERS}, got {solver!r}")


def _least_squares(residual: Callable, jac: Callable, x0: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                   x_scale: np.ndarray, max_nfev: int, solver: str,
                   free: Sequence[str]) -> tuple[np.ndarray, int, bool, str]:
    """Bounded nonlinear least squares (the swap point). 'scipy': scipy.optimize.least_squares (trf) on the raw
    parameters, residual in µm; 'polish': :func:`toggle_id.polish.polish` (log space for :data:`LOG_PARAMS`,
    affine otherwise). Both use the batched Jacobian ``jac``. Returns x, nfev, success, message."""
    if solver == "polish":
        from ..polish import polish

        log_mask = np.array([n in LOG_PARAMS for n in free])
        res = polish(residual, x0, lower, upper, log_mask=log_mask, jac_fn=jac, max_nfev=max_nfev,
                     ftol=1e-10, xtol=1e-10, gtol=1e-10)
        return np.asarray(res.x, float), int(res.nfev), bool(res.success), f"polish: {res.message}"
    from scipy.optimize import least_squares

    from ..polish import blas_limit

    scale = 1e6  # residuals in µm for the optimiser's tolerances
    with blas_limit(1):  # the tall, thin SVDs of the trust-region steps (see toggle_id.polish)
        res = least_squares(lambda x: scale * residual(x), x0, jac=lambda x: scale * jac(x), bounds=(lower, upper),
                            x_scale=x_scale, method="trf", max_nfev=max_nfev, ftol=1e-10, xtol=1e-10, gtol=1e-10)
    return res.x, int(res.nfev), bool(res.success), str(res.message)


def _covariance(J: np.ndarray, sse: float, n: int, free: Sequence[str]) -> tuple[dict, np.ndarray]:
    """Approximate σ (dict) and correlation matrix of the free parameters from the Jacobian J (N, p), assuming
    white residuals (they are not: the σ are optimistic; the correlations are what the loop uses)."""
    p = len(free)
    try:
        cov = sse / max(n - p, 1) * np.linalg.inv(J.T @ J)
        d = np.sqrt(np.maximum(np.diag(cov), 0.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            corr = cov / np.outer(d, d)
        return {nm: float(d[i]) for i, nm in enumerate(free)}, corr
    except np.linalg.LinAlgError:
        return {nm: float("nan") for nm in free}, np.full((p, p), np.nan)


def max_abs_corr(corr: np.ndarray | None, new: Sequence[int]) -> float:
    """Largest |correlation| between any parameter index in ``new`` and any other free parameter (NaN → 1)."""
    if corr is None or corr.shape[0] < 2:
        return 0.0
    worst = 0.0
    for i in new:
        row = np.abs(np.delete(corr[i], i))
        worst = max(worst, 1.0 if not np.all(np.isfinite(row)) else float(row.max()))
    return worst


def new_params_corr(small: OEFitResult, large: OEFitResult) -> float:
    """Largest |correlation| of a parameter ``large`` adds (its last ones) with its other free parameters."""
    return max_abs_corr(large.corr, range(len(small.free), len(large.free)))


def effect_last(fit: OEFitResult, params: Sequence[str]) -> OEFitResult:
    """``fit`` with its free parameters reordered so that ``params`` come last (as :func:`judge_effect` expects of
    the larger model: its new parameters last)."""
    order = [i for i, p in enumerate(fit.free) if p not in params] + [i for i, p in enumerate(fit.free) if p in params]
    corr = None if fit.corr is None else fit.corr[np.ix_(order, order)]
    jac = None if fit.jacobian is None else fit.jacobian[:, order]
    return replace(fit, free=tuple(fit.free[i] for i in order), corr=corr, jacobian=jac)


def judge_effect(small: OEFitResult, large: OEFitResult, *, alpha: float = 0.01, max_corr: float = 0.99,
                 noise_max_order: int = 8, cv_block: int = 100, cv_folds: int = 5,
                 cv_alpha: float = 0.5) -> Evidence:
    """The case for ``large`` (the free parameters of ``small`` plus new ones, the new ones last) against ``small``:
    the discovery engine's :class:`~toggle_id.discovery.validation.Evidence`, by the rule of the toggle plant's
    :class:`~toggle_id.discovery.validation.Judge` plus an identifiability gate.

    The noise model is an AR(p ≤ ``noise_max_order``) fitted to the larger model's residual
    (:func:`~toggle_id.discovery.noise.fit_noise`); both residuals are whitened by it for the nested F-test and
    ΔBIC (:func:`~toggle_id.discovery.stats.compare`, the noise coefficients counted as parameters), and each fit
    is cross-validated over time blocks of ``cv_block`` samples dealt to ``cv_folds`` folds with its own Jacobian
    (:func:`~toggle_id.discovery.stats.block_cv`). Unlike ``Judge.judge_pair`` the two output-error fits are not
    refitted under a coloured noise model first (each costs a closed-loop fit); they are compared as fitted.
    ``Evidence.checks``: ``f_test`` (p < ``alpha``), ``robust_f_test`` (the same for the F statistic corrected for a
    noise level that varies, :func:`~toggle_id.discovery.stats.robust_f`), ``bic`` (ΔBIC < 0), ``cross_validation``
    (the cross-validated whitened SSE drops; below 0.5, ``cv_alpha`` asks it to drop by more than the noise would
    make it: :func:`~toggle_id.discovery.stats.out_of_sample`) and ``identifiable`` (each new parameter's |correlation| with the
    others ≤ ``max_corr``, :func:`new_params_corr`); ``Evidence.passed`` when all hold, ``Evidence.reason`` says
    which fail.
    """
    k0, k1 = len(small.free), len(large.free)
    k = max(k1 - k0, 1)
    r0, r1 = small.residual, large.residual
    identifiable = bool(new_params_corr(small, large) <= max_corr)
    if r0 is None or r1 is None or not (np.all(np.isfinite(r0)) and np.all(np.isfinite(r1))):
        inf = float("inf")
        ev = Evidence(NoiseModel(note="a residual is missing or not finite"), 0.0, 1.0, inf, inf, inf, inf, inf)
        ev.checks = {"f_test": False, "robust_f_test": False, "bic": False, "cross_validation": False,
                     "identifiable": identifiable}
        return ev
    noise = fit_noise(r1, noise_max_order)
    c = compare(noise, r0, r1, k, k1)
    oos = out_of_sample(noise, r0, small.jacobian, r1, large.jacobian, cv_block, cv_folds)
    cv0, cv1 = float(oos["cv0"]), float(oos["cv1"])
    rob = robust_f(float(c["F"]), noise, r1, large.jacobian, list(range(k0, k1)), change=r0 - r1)
    ev = Evidence(noise, float(c["F"]), float(c["p_value"]), float(c["delta_bic"]), cv0, cv1, float(c["sse0_w"]),
                  float(c["sse1_w"]), F_robust=rob["F"], p_robust=rob["p_value"], hc_ratio=rob["ratio"],
                  cv_z=oos["z"], cv_p=oos["p_value"], level=float(alpha))
    ev.checks = {"f_test": bool(ev.p_value < alpha), "robust_f_test": bool(ev.p_robust < alpha),
                 "bic": bool(ev.delta_bic < 0), "cross_validation": bool(oos["p_value"] < cv_alpha),
                 "identifiable": identifiable}
    return ev


def significant_in_sample(ev: Evidence) -> bool:
    """The prewhitened F-test, its heteroscedasticity-robust twin and BIC all favour the larger model."""
    return bool(ev.checks.get("f_test") and ev.checks.get("robust_f_test", True) and ev.checks.get("bic"))


def evidence_entry(ev: Evidence, n: int, corr: float, cv_block: int, cv_folds: int) -> dict:
    """The flat keys of a candidate's report entry: ``Evidence.to_dict()`` (noise_model, F, p_value, delta_bic,
    sse_w_before/after, cv_sse_w_before/after, checks, passed, reason) plus ``noise_description``, the whitened
    RMS in and out of sample (m, :func:`~toggle_id.discovery.validation.in_sample_summary`), ``cv_block``,
    ``cv_folds`` and ``max_corr`` (the new parameters' largest |correlation|)."""
    d = ev.to_dict()
    for key in ("validation_sse_before_m2", "validation_sse_after_m2"):  # no validation record judges EMPS effects
        d.pop(key, None)
    return {**d, "noise_description": ev.noise.describe(), **in_sample_summary(ev, n), "cv_block": int(cv_block),
            "cv_folds": int(cv_folds), "max_corr": float(corr)}


def fit_output_error(record: EmpsRecord, free: Sequence[str], theta0: np.ndarray | Mapping[str, float],
                     lower: np.ndarray | None = None, upper: np.ndarray | None = None, *, max_nfev: int = 50,
                     rel_step: float = 1e-5, solver: str = "polish",
                     sim_options: Mapping | None = None) -> OEFitResult:
    """Fit θ[free] by output error (minimise ‖qm − q_sim‖²) from ``theta0``; other entries stay at ``theta0``.

    Bounds default to :data:`~toggle_id.emps.model.LOWER`/``UPPER`` of the free parameters; ``theta0`` is clipped
    into them. ``solver`` picks the optimiser (see :func:`_least_squares`).
    """
    t_start = time.perf_counter()
    _check_solver(solver)
    idx = _free_index(free)
    theta0 = np.array(as_theta_batch(theta0)[0])
    lo = LOWER[idx].copy() if lower is None else np.asarray(lower, float).reshape(-1)
    hi = UPPER[idx].copy() if upper is None else np.asarray(upper, float).reshape(-1)
    if lo.shape != idx.shape or hi.shape != idx.shape or np.any(lo >= hi):
        raise ConfigError(f"bounds for {list(free)} must be {idx.size} values each with lower < upper")
    x0 = np.clip(theta0[idx], lo, hi)
    residual = make_residual(record, free, theta0, sim_options)
    jac = make_jacobian(record, free, theta0, lo, hi, rel_step, sim_options)
    x_scale = np.maximum(np.abs(x0), [_TYPICAL[n] for n in free])
    x, nfev, success, message = _least_squares(residual, jac, x0, lo, hi, x_scale, max_nfev, solver, free)
    r = residual(x)
    theta = theta0.copy()
    theta[idx] = x
    sse = float(r @ r)
    n = record.n
    J = jac(x)
    std, corr = _covariance(J, sse, n, free)
    return OEFitResult(theta=theta, free=tuple(free), sse=sse, n=n,
                       rel_error_pct=float(100 * np.sqrt(sse) / np.linalg.norm(record.qm)), std=std, corr=corr,
                       nfev=nfev, success=success, message=message, seconds=time.perf_counter() - t_start,
                       residual=r, jacobian=J)


def _pct_diff(value: float, reference: float) -> float:
    """100·(value − reference)/|reference|, %."""
    return float(100.0 * (value - reference) / abs(reference))


def _compare_published(theta: np.ndarray, free: Sequence[str]) -> dict:
    """% differences of the model's M, Fv, Fc, offset vs the PDF's symmetric IDIM-LS (None where not in the model)
    and, when the asymmetry is in the model, of Fv±, Fc± vs the PDF's asymmetric IDIM-LS."""
    d = theta_to_dict(theta)
    out = {"symmetric": {k: (_pct_diff(d[k], v) if k in free else None) for k, v in PUBLISHED.items()}}
    if "Fv_asym" in free:
        mine = {"M": d["M"], "Fv+": d["Fv"] + d["Fv_asym"], "Fv-": d["Fv"] - d["Fv_asym"],
                "Fc+": d["Fc"] + d["Fc_asym"], "Fc-": d["Fc"] - d["Fc_asym"]}
        out["asymmetric_values"] = mine
        out["asymmetric"] = {k: _pct_diff(mine[k], v) for k, v in PUBLISHED_ASYM_PM.items()}
    return out


def logged_pulse_gain(record: EmpsRecord) -> float | None:
    """Least-squares gain c in vir ≈ law(qg, qm) + c·pulses: how large the record's pulses appear in its logged
    controller output, relative to ``pulses_N`` (a data check, never used by a fit; None without pulses)."""
    from .model import controller_law

    p = record.pulses
    if not np.any(p != 0):
        return None
    d = record.vir - controller_law(record, pulse_gain=0.0)
    d[:2] = 0.0  # the law's first two samples use an extrapolated velocity
    return float(np.dot(d, p) / np.dot(p, p))


def predict_validation(validation: EmpsRecord, models: Mapping[str, np.ndarray],
                       sim_options: Mapping | None = None) -> dict:
    """Simulate each model (label → θ) in closed loop on a held-out record, its pulses entering at the controller
    output as configured (``pulse_gain`` of ``sim_options``, default 1); nothing is fitted on the record.

    Returns a plain dict: ``record``, ``n_samples``, ``has_pulses``, ``pulse_gain``, ``logged_pulse_gain`` (see
    :func:`logged_pulse_gain`), ``models`` {label: {position_rel_error_pct, max_abs_error_um, status,
    without_pulses_rel_error_pct (the same model with the pulses left out; only for a record with pulses)}} and,
    for the labels ``final`` and ``published``, the flat keys ``position_rel_error_pct``,
    ``published_model_rel_error_pct`` and ``status`` (of the final model).
    """
    opts = dict(sim_options or {})
    labels = list(models)
    thetas = np.stack([as_theta_batch(models[k])[0] for k in labels])
    sim = simulate_emps(thetas, validation, **opts)
    has_pulses = bool(np.any(validation.pulses != 0))
    no_pulse = simulate_emps(thetas, validation, **{**opts, "pulse_gain": 0.0}) if has_pulses else None
    out_models = {}
    for i, k in enumerate(labels):
        entry = {"position_rel_error_pct": float(position_rel_error_pct(validation.qm, sim.q[i])),
                 "max_abs_error_um": float(1e6 * np.max(np.abs(sim.q[i] - validation.qm))),
                 "status": int(sim.status[i])}
        if no_pulse is not None:
            entry["without_pulses_rel_error_pct"] = float(position_rel_error_pct(validation.qm, no_pulse.q[i]))
        out_models[k] = entry
    report = {"record": validation.name, "n_samples": int(validation.n), "has_pulses": has_pulses,
              "pulse_gain": float(opts.get("pulse_gain", 1.0)), "logged_pulse_gain": logged_pulse_gain(validation),
              "models": out_models}
    if "final" in out_models:
        report["position_rel_error_pct"] = out_models["final"]["position_rel_error_pct"]
        report["status"] = out_models["final"]["status"]
    if "published" in out_models:
        report["published_model_rel_error_pct"] = out_models["published"]["position_rel_error_pct"]
    return report
