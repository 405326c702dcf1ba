"""Output-error identification of the EMPS and the greedy effect-discovery loop.

The output-error residual is r(x) = qm − q_sim(θ(x)) (m) over a chosen subset ``free`` of the parameters, with
the closed loop simulated by :func:`toggle_id.emps.model.simulate_emps`. The fit is bounded least squares with a
batched forward-difference Jacobian (one kernel call for all columns, same RK4 substep count in every row), by
scipy's ``least_squares`` on the raw parameters or by :func:`toggle_id.polish.polish` (``solver='polish'``; log
space for M only: the offset is negative and effect parameters start at zero).

:func:`run_emps_loop` fits the nominal model (M, Fv), then adds effects from :data:`~toggle_id.emps.model.EFFECTS`
greedily, each judged by :func:`judge_effect` into the discovery engine's own verdict object,
:class:`toggle_id.discovery.validation.Evidence`, with its statistics (:mod:`toggle_id.discovery.noise`,
:mod:`toggle_id.discovery.stats`) and its acceptance rule plus an identifiability gate. The residuals of a 1 kHz
closed loop are strongly autocorrelated, so counting N ≈ 25 000 independent samples would make any test far too
lenient; instead every comparison describes the noise by an AR(p) model fitted (Yule–Walker, order by BIC) to the
*larger* model's residual and computes its statistics on prewhitened signals. A candidate is accepted only if the
prewhitened F-test gives p < alpha, the prewhitened ΔBIC < 0, the time-block cross-validated whitened SSE drops
(both fits linearised at their optimum with their own Jacobians) and its new parameters stay identifiable
(|correlation| ≤ max_corr, ``Evidence.checks['identifiable']``); among those that pass, the one with the lowest
prewhitened SSE is taken, all of a round's residuals whitened by one noise model (that of the refit that explains
the most, as the toggle plant ranks its refits). The report gives the toggle loop's three lists — ``effects_added``,
``compensating`` (significant in sample, but not out of sample or not identifiable) and ``rejected``, each item
with its ``Evidence.to_dict()`` — and the noise-aware structure test of the final position residual against
position, velocity, drive force and controller output (:func:`toggle_id.discovery.localise.locate`): whether
structure is left, and where.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Mapping, Sequence

import numpy as np

from ..discovery.localise import locate
from ..discovery.noise import NoiseModel, fit_noise, whitened_sse
from ..discovery.stats import block_cv, compare
from ..discovery.validation import Evidence, in_sample_summary
from ..errors import ConfigError, DataError
from .data import EmpsRecord
from .idim import idim_ls
from .model import (
    EFFECTS,
    INDEX,
    LOWER,
    NOMINAL_NAMES,
    OFF,
    PARAM_NAMES,
    PUBLISHED,
    PUBLISHED_ASYM_PM,
    PUBLISHED_THETA,
    UPPER,
    Effect,
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
    """residual(x) = qm − q_sim (m, length N) with θ[free] = x and the other entries from ``theta_base``.

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
        return record.qm - res.q[0]

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

    scale = 1e6  # residuals in µm for the optimiser's tolerances
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


def judge_effect(small: OEFitResult, large: OEFitResult, *, alpha: float = 0.01, max_corr: float = 0.99,
                 noise_max_order: int = 8, cv_block: int = 100, cv_folds: int = 5) -> Evidence:
    """The case for ``large`` (the free parameters of ``small`` plus new ones, the new ones last) against ``small``:
    the discovery engine's :class:`~toggle_id.discovery.validation.Evidence`, by the rule of the toggle plant's
    :class:`~toggle_id.discovery.validation.Judge` plus an identifiability gate.

    The noise model is an AR(p ≤ ``noise_max_order``) fitted to the larger model's residual
    (:func:`~toggle_id.discovery.noise.fit_noise`); both residuals are whitened by it for the nested F-test and
    ΔBIC (:func:`~toggle_id.discovery.stats.compare`, the noise coefficients counted as parameters), and each fit
    is cross-validated over time blocks of ``cv_block`` samples dealt to ``cv_folds`` folds with its own Jacobian
    (:func:`~toggle_id.discovery.stats.block_cv`). Unlike ``Judge.judge_pair`` the two output-error fits are not
    refitted under a coloured noise model first (each costs a closed-loop fit); they are compared as fitted.
    ``Evidence.checks``: ``f_test`` (p < ``alpha``), ``bic`` (ΔBIC < 0), ``cross_validation`` (the cross-validated
    whitened SSE drops) and ``identifiable`` (each new parameter's |correlation| with the others ≤ ``max_corr``,
    :func:`new_params_corr`); ``Evidence.passed`` when all hold, ``Evidence.reason`` says which fail.
    """
    k0, k1 = len(small.free), len(large.free)
    k = max(k1 - k0, 1)
    r0, r1 = small.residual, large.residual
    identifiable = bool(new_params_corr(small, large) <= max_corr)
    if r0 is None or r1 is None or not (np.all(np.isfinite(r0)) and np.all(np.isfinite(r1))):
        inf = float("inf")
        ev = Evidence(NoiseModel(note="a residual is missing or not finite"), 0.0, 1.0, inf, inf, inf, inf, inf)
        ev.checks = {"f_test": False, "bic": False, "cross_validation": False, "identifiable": identifiable}
        return ev
    noise = fit_noise(r1, noise_max_order)
    c = compare(noise, r0, r1, k, k1)
    cv0 = float(block_cv(noise, r0, small.jacobian, cv_block, cv_folds)["cv_sse_w"])
    cv1 = float(block_cv(noise, r1, large.jacobian, cv_block, cv_folds)["cv_sse_w"])
    ev = Evidence(noise, float(c["F"]), float(c["p_value"]), float(c["delta_bic"]), cv0, cv1, float(c["sse0_w"]),
                  float(c["sse1_w"]))
    ev.checks = {"f_test": bool(ev.p_value < alpha), "bic": bool(ev.delta_bic < 0),
                 "cross_validation": bool(cv1 < cv0), "identifiable": identifiable}
    return ev


def significant_in_sample(ev: Evidence) -> bool:
    """The prewhitened F-test and BIC both favour the larger model."""
    return bool(ev.checks.get("f_test") and ev.checks.get("bic"))


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


def _rank_passing(refits: Sequence[tuple[dict, OEFitResult, Effect]],
                  noise_max_order: int) -> tuple[tuple[dict, OEFitResult, Effect] | None, dict]:
    """The refit to accept among those whose checks all passed: the lowest prewhitened SSE, every residual of the
    round whitened by one noise model, as the toggle plant ranks its refits (:mod:`toggle_id.discovery.loop`):
    the AR model of the residual of the refit that explains the most (lowest raw SSE). Each candidate's own noise
    model (the one its tests use) would not do for the ranking: a residual that keeps more structure gets a noise
    model that predicts it and a smaller whitened SSE. Sets ``sse_w_round`` on every entry; returns the chosen
    (entry, fit, effect) or None, and {lead, noise_model} of the round."""
    finite = [rf for rf in refits if rf[1].residual is not None and np.all(np.isfinite(rf[1].residual))]
    if not finite:
        return None, {"lead": None, "noise_model": None}
    lead = min(finite, key=lambda rf: rf[1].sse)
    noise = fit_noise(lead[1].residual, noise_max_order)
    for entry, fit, _ in refits:
        ok = fit.residual is not None and np.all(np.isfinite(fit.residual))
        entry["sse_w_round"] = float(whitened_sse(noise, fit.residual)[0]) if ok else float("inf")
    passing = [rf for rf in refits if rf[0]["passed"]]
    chosen = min(passing, key=lambda rf: rf[0]["sse_w_round"]) if passing else None
    return chosen, {"lead": lead[2].name, "noise_model": noise.to_dict()}


def localisation_signals(record: EmpsRecord, theta: np.ndarray,
                         sim_options: Mapping | None = None) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The position residual qm − q_sim of the model ``theta`` (m) and the signals the structure test bins it by
    (keys of :data:`toggle_id.discovery.localise.SIGNALS`): the simulated load position ``q`` (m), the position
    signed by the direction of motion ``q_dir`` = q·sign(q̇) (m: forward strokes on the positive side, backward ones
    on the negative side, so that a friction force localised on the stroke — which changes sign with the motion
    and averages out in bins of q alone — shows as a level per bin), the velocity ``qdot`` (m/s, central
    differences of q), the simulated drive force ``force`` = gtau·ν (N), the record's controller output ``vir`` (V)
    and the time ``t`` (s). NaN where the simulation fails."""
    sim = simulate_emps(theta, record, **dict(sim_options or {}))
    q, nu = sim.q[0], sim.nu[0]
    qdot = np.gradient(q, record.dt) if np.all(np.isfinite(q)) else np.full(record.n, np.nan)
    return record.qm - q, {"q": q, "q_dir": q * np.sign(qdot), "qdot": qdot, "force": record.gtau * nu,
                           "vir": np.asarray(record.vir, float), "t": np.asarray(record.t, float)}


def localise(record: EmpsRecord, theta: np.ndarray, sim_options: Mapping | None = None, *, bins: int = 12,
             alpha: float = 0.01) -> dict:
    """Is structure left in the position residual of ``theta``, and where? :func:`toggle_id.discovery.localise.locate`
    with no fixed noise model (each family judged under the AR noise model of its own alternative) on the signals of
    :func:`localisation_signals`; position, position signed by the direction of motion and velocity enter the
    verdict (Bonferroni over the three), drive force, controller output and time are shown (in a closed loop the
    controller output carries the position error itself). Returns locate's dict (``structure_left``, ``families``, ``significant``,
    ``strongest``, ``text``); ``{"error": ...}`` when the model cannot be simulated on the record."""
    r, signals = localisation_signals(record, theta, sim_options)
    if not (np.all(np.isfinite(r)) and all(np.all(np.isfinite(v)) for v in signals.values())):
        return {"error": "the final model cannot be simulated on the record", "structure_left": None,
                "text": "no localisation: the final model cannot be simulated on the record"}
    return locate(None, r, signals, bins=int(bins), alpha=float(alpha))


def three_lists(names: Sequence[str], tried: Sequence[dict], evidence: Mapping[int, Evidence],
                max_effects: int | None) -> tuple[list[dict], list[dict], list[dict]]:
    """The verdict per effect, as the toggle plant's ``discovery.json`` gives it: ``effects_added`` (accepted),
    ``compensating`` (its last refit is significant in sample — prewhitened F-test and BIC pass — but no better out
    of sample or not identifiable; never called added) and ``rejected`` (not significant in sample, passed but left
    out by ``max_effects``, or never refitted because an effect it refines is not in the model). Unlike the toggle
    loop, structure left in the final residual does not move the accepted effects to ``compensating``: each passed
    all four checks against the model before it, and the structure test reports separately what is left. Each item:
    ``name``, ``round``, ``params``, ``reason``, ``evidence`` (``Evidence.to_dict()`` of its last judgement, None if
    never judged); an added effect also has ``F``, ``p_value``, ``delta_bic``. ``evidence`` maps ``id(entry)`` of
    the ``tried`` entries to their :class:`Evidence`."""
    added, compensating, rejected = [], [], []
    for name in names:
        mine = [c for c in tried if c["name"] == name]
        if not mine:
            req = [r for r in EFFECTS[name].requires]
            rejected.append({"name": name, "round": None, "params": {}, "evidence": None,
                             "reason": "never refitted: it refines " + ", ".join(req) + ", which is not in the model"
                             if req else "never refitted"})
            continue
        last = next((c for c in mine if c["accepted"]), mine[-1])
        ev = evidence[id(last)]
        item = {"name": name, "round": last["round"], "params": dict(last["params"]), "reason": ev.reason,
                "evidence": ev.to_dict()}
        if last["accepted"]:
            added.append({**item, "F": ev.F, "p_value": ev.p_value, "delta_bic": ev.delta_bic})
        elif ev.passed:
            item["reason"] = (f"passed every check in round {last['round']} but was not added: the limit "
                              f"emps.max_effects = {max_effects} was reached")
            rejected.append(item)
        elif significant_in_sample(ev):
            item["reason"] = "significant in sample (prewhitened F-test and BIC), but " + ev.reason
            compensating.append(item)
        else:
            rejected.append(item)
    added.sort(key=lambda a: a["round"])
    return added, compensating, rejected


def run_emps_loop(record: EmpsRecord, validation: EmpsRecord | None = None, *,
                  candidates: Sequence[str] | None = None, alpha: float = 0.01, max_nfev: int = 50,
                  max_effects: int | None = None, max_corr: float = 0.99, solver: str = "polish",
                  reference_fit: bool = True, noise_max_order: int = 8, cv_block: int = 100, cv_folds: int = 5,
                  structure_bins: int = 12, structure_alpha: float = 0.01,
                  sim_options: Mapping | None = None) -> dict:
    """Nominal output-error fit, then greedy effect discovery; returns a plain (JSON-serialisable) dict report.

    Each round refits all parameters of the current model plus one candidate (from its registry default) for every
    remaining candidate whose ``requires`` are in the model, and judges each refit against the current model with
    :func:`judge_effect` (the discovery engine's :class:`~toggle_id.discovery.validation.Evidence`: AR(p ≤
    ``noise_max_order``) noise model of the refit's residual; prewhitened F-test p < ``alpha``, prewhitened
    ΔBIC < 0, a lower time-block cross-validated whitened SSE with blocks of ``cv_block`` samples dealt to
    ``cv_folds`` folds, and every new parameter identifiable: |correlation| with each other free parameter ≤
    ``max_corr``, e.g. the offset and the Coulomb asymmetry differ only at standstill). Of the candidates that
    pass, the one with the lowest prewhitened SSE is accepted, the round's residuals all whitened by one noise
    model (:func:`_rank_passing`); the loop stops when none passes. Then the noise-aware structure test localises
    what the final model leaves in its position residual (:func:`localise`, ``structure_bins`` bins per signal,
    level ``structure_alpha``). Keys of the report:

    - ``position_rel_error_pct_before`` (nominal M, Fv fit), ``position_rel_error_pct_after`` (final model), %;
    - ``effects_added``, ``compensating``, ``rejected``: the three lists of :func:`three_lists` (each item with
      name, reason, evidence); ``effects_added`` items also keep {params, round, F, p_value, delta_bic};
      ``free`` (final free parameters);
    - ``candidates`` [{round, name, noise_model, F, p_value, delta_bic, in_sample_rms_w_before/after,
      out_of_sample_rms_w_before/after, checks, max_corr, verdict (accepted | passed, not the best | rejected),
      reason, sse_w_round, sse_ratio, rel_error_pct, params, accepted, seconds, …}] (:func:`evidence_entry`);
    - ``rounds`` [{round, lead, noise_model, accepted}]: the noise model each round's ranking whitened by;
    - ``nominal``: the nominal fit {free, identified (M, Fv), rel_error_pct, noise_model};
    - ``noise_model``: the AR noise model of the final model's residual (its effective sample size included);
    - ``structure_left`` (bool, None if the final model cannot be simulated) and ``localisation`` (locate's dict:
      families with p-values and per-bin levels, ``significant``, ``strongest``, ``text``);
    - ``identified`` (all 8 parameters), ``std`` (approximate σ of the free ones, white-residual assumption);
    - ``published``, ``pct_diff_vs_published`` (M, Fv, Fc, offset; None where not in the final model) and, if the
      asymmetry was added, ``pct_diff_vs_published_asym`` and ``asymmetric_values`` (Fv±, Fc±);
    - ``published_model_rel_error_pct``: the PDF's symmetric values simulated by this simulator;
    - ``reference`` (if ``reference_fit``): output-error fit of the PDF's own structure (M, Fv, Fc, offset) with its
      rel. error and % differences vs the PDF;
    - ``validation`` (if given): the held-out record predicted by the final, published and reference models
      (:func:`predict_validation`; nothing is fitted on it);
    - ``seconds``, ``n_samples``, ``alpha``, ``max_corr``, ``noise_max_order``, ``cv_block``, ``cv_folds``,
      ``structure_bins``, ``structure_alpha``, ``solver``.
    """
    t0 = time.perf_counter()
    names = list(EFFECTS) if candidates is None else list(candidates)
    unknown = [c for c in names if c not in EFFECTS]
    if unknown:
        raise ConfigError(f"unknown EMPS effect(s) {unknown}; known: {list(EFFECTS)}")
    if not (0 < alpha < 1):
        raise ConfigError(f"alpha must lie in (0, 1), got {alpha}")
    if not (0 < structure_alpha < 1):
        raise ConfigError(f"structure_alpha must lie in (0, 1), got {structure_alpha}")
    if not (0 < max_corr <= 1):
        raise ConfigError(f"max_corr must lie in (0, 1], got {max_corr}")
    for label, value, least in (("noise_max_order", noise_max_order, 0), ("cv_block", cv_block, 1),
                                ("cv_folds", cv_folds, 2), ("structure_bins", structure_bins, 2)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
            raise ConfigError(f"{label} must be a whole number >= {least}, got {value!r}")
    _check_solver(solver)
    n = record.n
    fit_kw = dict(max_nfev=max_nfev, solver=solver, sim_options=sim_options)
    judge_kw = {"alpha": alpha, "max_corr": max_corr, "noise_max_order": int(noise_max_order),
                "cv_block": int(cv_block), "cv_folds": int(cv_folds)}

    # nominal model: IDIM-LS (M, Fv only) start, then output error
    theta = OFF.copy()
    try:
        start = idim_ls(record, terms=NOMINAL_NAMES)["params"]
        for nm in NOMINAL_NAMES:
            theta[INDEX[nm]] = np.clip(start[nm], LOWER[INDEX[nm]], UPPER[INDEX[nm]])
    except DataError:  # record too short for the recipe: start from the registry's round values
        pass
    free: list[str] = list(NOMINAL_NAMES)
    current = fit_output_error(record, free, theta, **fit_kw)
    nominal = current
    before = current.rel_error_pct

    in_model: list[str] = []
    tried: list[dict] = []
    evidence: dict[int, Evidence] = {}  # id(entry of ``tried``) → its Evidence
    remaining = list(names)
    rnd = 0
    rounds: list[dict] = []
    while remaining and (max_effects is None or len(in_model) < max_effects):
        rnd += 1
        refits: list[tuple[dict, OEFitResult, Effect]] = []
        for name in remaining:
            eff = EFFECTS[name]
            if any(req not in in_model for req in eff.requires):
                continue
            th = current.theta.copy()
            for p, d in zip(eff.params, eff.default):
                th[INDEX[p]] = d
            fit = fit_output_error(record, free + list(eff.params), th, **fit_kw)
            ev = judge_effect(current, fit, **judge_kw)
            entry = {"round": rnd, "name": name,
                     **evidence_entry(ev, n, new_params_corr(current, fit), cv_block, cv_folds),
                     "sse_ratio": float(fit.sse / current.sse), "rel_error_pct": fit.rel_error_pct,
                     "params": {p: float(fit.theta[INDEX[p]]) for p in eff.params}, "accepted": False,
                     "verdict": "passed" if ev.passed else "rejected", "seconds": fit.seconds}
            tried.append(entry)
            evidence[id(entry)] = ev
            refits.append((entry, fit, eff))
        if not refits:
            break
        chosen, ranking = _rank_passing(refits, noise_max_order)
        rounds.append({"round": rnd, **ranking, "accepted": chosen[2].name if chosen else None})
        if chosen is None:
            break
        entry, fit, eff = chosen
        entry["accepted"] = True
        entry["verdict"] = "accepted"
        for other, _, _ in refits:
            if other["passed"] and other is not entry:
                other["verdict"] = "passed, not the best"
                other["reason"] = (f"passed every check, but {eff.name} has the lower prewhitened SSE under the "
                                   f"round's noise model ({entry['sse_w_round']:.4g} against "
                                   f"{other['sse_w_round']:.4g} m²); judged again next round")
        in_model.append(eff.name)
        free += list(eff.params)
        current = fit
        remaining.remove(eff.name)
    added, compensating, rejected = three_lists(names, tried, evidence, max_effects)
    noise_final = fit_noise(current.residual, noise_max_order)
    noise_nominal = fit_noise(nominal.residual, noise_max_order)
    sim_kw = dict(sim_options or {})
    loc = localise(record, current.theta, sim_kw, bins=structure_bins, alpha=structure_alpha)

    pub_sim = simulate_emps(PUBLISHED_THETA, record, **sim_kw)
    cmp = _compare_published(current.theta, free)
    report = {
        "record": record.name,
        "n_samples": int(n),
        "position_rel_error_pct_before": float(before),
        "position_rel_error_pct_after": float(current.rel_error_pct),
        "effects_added": added,
        "compensating": compensating,
        "rejected": rejected,
        "candidates": tried,
        "rounds": rounds,
        "free": list(free),
        "nominal": {"free": list(NOMINAL_NAMES), "identified": {k: nominal.params[k] for k in NOMINAL_NAMES},
                    "rel_error_pct": float(before), "noise_model": noise_nominal.to_dict()},
        "noise_model": {**noise_final.to_dict(), "description": noise_final.describe()},
        "structure_left": loc["structure_left"],
        "localisation": loc,
        "identified": current.params,
        "std": dict(current.std),
        "published": dict(PUBLISHED),
        "pct_diff_vs_published": cmp["symmetric"],
        "published_model_rel_error_pct": float(position_rel_error_pct(record.qm, pub_sim.q[0])),
        "alpha": float(alpha),
        "max_corr": float(max_corr),
        "noise_max_order": int(noise_max_order),
        "cv_block": int(cv_block),
        "cv_folds": int(cv_folds),
        "structure_bins": int(structure_bins),
        "structure_alpha": float(structure_alpha),
        "solver": solver,
    }
    if "asymmetric" in cmp:
        report["asymmetric_values"] = cmp["asymmetric_values"]
        report["pct_diff_vs_published_asym"] = cmp["asymmetric"]
    if reference_fit:
        ref = fit_output_error(record, ["M", "Fv", "Fc", "offset"], PUBLISHED_THETA, **fit_kw)
        report["reference"] = {
            "free": list(ref.free),
            "identified": {k: ref.params[k] for k in ref.free},
            "rel_error_pct": ref.rel_error_pct,
            "pct_diff_vs_published": _compare_published(ref.theta, ref.free)["symmetric"],
        }
    if validation is not None:
        models = {"final": current.theta, "published": PUBLISHED_THETA}
        if "reference" in report:
            models["reference"] = ref.theta
        report["validation"] = predict_validation(validation, models, sim_kw)
    report["seconds"] = float(time.perf_counter() - t0)
    return report
