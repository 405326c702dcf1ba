"""Output-error identification of the EMPS and the greedy effect-discovery loop.

The output-error residual is r(x) = qm − q_sim(θ(x)) (m) over a chosen subset ``free`` of the parameters, with
the closed loop simulated by :func:`toggle_id.emps.model.simulate_emps`. The fit is bounded least squares with a
batched forward-difference Jacobian (one kernel call for all columns, same RK4 substep count in every row), by
scipy's ``least_squares`` on the raw parameters or by :func:`toggle_id.polish.polish` (``solver='polish'``; log
space for M only: the offset is negative and effect parameters start at zero).

:func:`run_emps_loop` fits the nominal model (M, Fv), then adds effects from :data:`~toggle_id.emps.model.EFFECTS`
greedily: every round it refits the current model plus each eligible remaining candidate, and accepts the best
(lowest BIC) among those that pass an F-test on the SSE (p < alpha), lower the BIC and stay identifiable
(|correlation| ≤ max_corr). The residuals are strongly autocorrelated (closed loop, 1 kHz), so with N ≈ 25 000
the F-test and BIC are lenient: they rank candidates well but accept small improvements.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Mapping, Sequence

import numpy as np

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
    approximate standard deviations of the free parameters (from JᵀJ, white-residual assumption), optimiser info."""

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

    @property
    def params(self) -> dict[str, float]:
        """All parameters as a plain dict."""
        return theta_to_dict(self.theta)

    def bic(self) -> float:
        """Gaussian BIC N·ln(SSE/N) + k·ln N with k = number of free parameters."""
        return bic(self.sse, self.n, len(self.free))


def bic(sse: float, n: int, k: int) -> float:
    """N·ln(SSE/N) + k·ln N."""
    return float(n * np.log(max(sse, 1e-300) / n) + k * np.log(n))


def f_test_pvalue(sse0: float, k0: int, sse1: float, k1: int, n: int) -> float:
    """p-value of the nested-model F-test: F = ((SSE0 − SSE1)/(k1 − k0)) / (SSE1/(N − k1)); 1.0 if SSE did not drop."""
    from scipy.stats import f as f_dist

    if k1 <= k0 or sse1 >= sse0 or n <= k1:
        return 1.0
    stat = ((sse0 - sse1) / (k1 - k0)) / (sse1 / (n - k1))
    return float(f_dist.sf(stat, k1 - k0, n - k1))


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
    std, corr = _covariance(jac(x), sse, n, free)
    return OEFitResult(theta=theta, free=tuple(free), sse=sse, n=n,
                       rel_error_pct=float(100 * np.sqrt(sse) / np.linalg.norm(record.qm)), std=std, corr=corr,
                       nfev=nfev,
                       success=success, message=message, seconds=time.perf_counter() - t_start)


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


def run_emps_loop(record: EmpsRecord, validation: EmpsRecord | None = None, *,
                  candidates: Sequence[str] | None = None, alpha: float = 0.01, max_nfev: int = 50,
                  max_effects: int | None = None, max_corr: float = 0.99, solver: str = "polish",
                  reference_fit: bool = True,
                  sim_options: Mapping | None = None) -> dict:
    """Nominal output-error fit, then greedy effect discovery; returns a plain (JSON-serialisable) dict report.

    Each round refits all parameters of the current model plus one candidate (from its registry default) for every
    remaining candidate whose ``requires`` are in the model, and accepts the lowest-BIC candidate among those with
    F-test p < ``alpha``, ΔBIC < 0 and every new parameter identifiable (|correlation| with each other free
    parameter ≤ ``max_corr``; e.g. the offset and the Coulomb asymmetry differ only at standstill); it stops when
    none passes. Keys of the report:

    - ``position_rel_error_pct_before`` (nominal M, Fv fit), ``position_rel_error_pct_after`` (final model), %;
    - ``effects_added`` [{name, params}], ``candidates`` [{round, name, score = ΔBIC (negative = better),
      p_value, max_corr, sse_ratio, rel_error_pct, params, accepted, seconds}], ``free`` (final free parameters);
    - ``nominal``: the nominal fit {free, identified (M, Fv), rel_error_pct};
    - ``identified`` (all 8 parameters), ``std`` (approximate σ of the free ones, white-residual assumption);
    - ``published``, ``pct_diff_vs_published`` (M, Fv, Fc, offset; None where not in the final model) and, if the
      asymmetry was added, ``pct_diff_vs_published_asym`` and ``asymmetric_values`` (Fv±, Fc±);
    - ``published_model_rel_error_pct``: the PDF's symmetric values simulated by this simulator;
    - ``reference`` (if ``reference_fit``): output-error fit of the PDF's own structure (M, Fv, Fc, offset) with its
      rel. error and % differences vs the PDF;
    - ``validation`` (if given): the held-out record predicted by the final, published and reference models
      (:func:`predict_validation`; nothing is fitted on it);
    - ``seconds``, ``n_samples``, ``alpha``, ``solver``.
    """
    t0 = time.perf_counter()
    names = list(EFFECTS) if candidates is None else list(candidates)
    unknown = [c for c in names if c not in EFFECTS]
    if unknown:
        raise ConfigError(f"unknown EMPS effect(s) {unknown}; known: {list(EFFECTS)}")
    if not (0 < alpha < 1):
        raise ConfigError(f"alpha must lie in (0, 1), got {alpha}")
    if not (0 < max_corr <= 1):
        raise ConfigError(f"max_corr must lie in (0, 1], got {max_corr}")
    _check_solver(solver)
    n = record.n
    fit_kw = dict(max_nfev=max_nfev, solver=solver, sim_options=sim_options)

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

    added: list[dict] = []
    tried: list[dict] = []
    remaining = list(names)
    rnd = 0
    while remaining and (max_effects is None or len(added) < max_effects):
        rnd += 1
        best = None
        in_model = {a["name"] for a in added}
        for name in remaining:
            eff = EFFECTS[name]
            if any(req not in in_model for req in eff.requires):
                continue
            th = current.theta.copy()
            for p, d in zip(eff.params, eff.default):
                th[INDEX[p]] = d
            fit = fit_output_error(record, free + list(eff.params), th, **fit_kw)
            k0, k1 = len(free), len(free) + len(eff.params)
            p_value = f_test_pvalue(current.sse, k0, fit.sse, k1, n)
            d_bic = fit.bic() - current.bic()
            corr_new = max_abs_corr(fit.corr, range(k0, k1))
            entry = {"round": rnd, "name": name, "score": float(d_bic), "p_value": p_value, "max_corr": corr_new,
                     "sse_ratio": float(fit.sse / current.sse), "rel_error_pct": fit.rel_error_pct,
                     "params": {p: float(fit.theta[INDEX[p]]) for p in eff.params}, "accepted": False,
                     "seconds": fit.seconds}
            tried.append(entry)
            if p_value < alpha and d_bic < 0 and corr_new <= max_corr and (best is None or d_bic < best[0]["score"]):
                best = (entry, fit, eff)
        if best is None:
            break
        entry, fit, eff = best
        entry["accepted"] = True
        added.append({"name": eff.name, "params": dict(entry["params"])})
        free += list(eff.params)
        current = fit
        remaining.remove(eff.name)

    sim_kw = dict(sim_options or {})
    pub_sim = simulate_emps(PUBLISHED_THETA, record, **sim_kw)
    cmp = _compare_published(current.theta, free)
    report = {
        "record": record.name,
        "n_samples": int(n),
        "position_rel_error_pct_before": float(before),
        "position_rel_error_pct_after": float(current.rel_error_pct),
        "effects_added": added,
        "candidates": tried,
        "free": list(free),
        "nominal": {"free": list(NOMINAL_NAMES), "identified": {k: nominal.params[k] for k in NOMINAL_NAMES},
                    "rel_error_pct": float(before)},
        "identified": current.params,
        "std": dict(current.std),
        "published": dict(PUBLISHED),
        "pct_diff_vs_published": cmp["symmetric"],
        "published_model_rel_error_pct": float(position_rel_error_pct(record.qm, pub_sim.q[0])),
        "alpha": float(alpha),
        "max_corr": float(max_corr),
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
