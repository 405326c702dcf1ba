"""Close the loop: find the residual structure, trace it to the effect the model lacks, add it, repeat.

The loop (:func:`discover`) works on one record and the extended parameter vector of
:mod:`toggle_id.effects`; it never names an effect — it only reads the library (``EFFECTS``), so adding an
effect is adding a term to the kernel and an :class:`~toggle_id.effects.Effect` entry there.

1. *Baseline*: the nominal fit (e.g. the two-stage RGA + polish of :func:`toggle_id.identify.identify`, and
   any further start such as the assigned values) is polished on the whole record with all its free
   parameters together (PRECISE tier, log space, restarted while it improves); the best is the baseline.
   Every later comparison is against a model fitted to the same samples with the same machinery.
2. *Diagnostics* of the residual (:mod:`toggle_id.residuals`): whiteness (Ljung–Box), input cross-correlation,
   correlation with the states, spectrum.
3. *Score* each candidate not yet in the model, at "effect off":
   - the Lagrange-multiplier (score) test: s = y(θ with the effect at a probe setting) − y(θ) (PRECISE finite
     difference), projected off the sensitivities J of the free parameters (log-space Jacobian, SVD basis U of
     its range), s⊥ = (I − UUᵀ)s; score = (s⊥·r)²/(σ² s⊥·s⊥), σ² = ‖(I − UUᵀ)r‖²/(N − rank J), the best probe
     per effect. Under "the effect is absent" it is χ²(1) (a little more for the best of several probes). An
     effect whose s is zero is silent on this record; one whose s⊥ vanishes is absorbed by the free parameters.
   - the *profile*: each probe's nuisance setting × a geometric grid of magnitudes up to the feasible bound,
     ranked by ‖(I − UUᵀ)(y_meas − y(θ_m))‖² (the residual after the linearised re-adjustment of the free
     parameters) — the nonlinear counterpart of the score test, which also gives a start for the refit.
   Both are computed at the polished fit and, as a second linearisation point, at the nominal start with the
   effects added so far: a large effect can bend the polished nominal parameters far from physical values
   (masses → 0, friction × 50), where the local picture of the right candidate is distorted.
4. *Scout and refit*: every candidate whose score or profile at the polished fit passes ``screen_alpha`` is
   polished briefly (``scout_nfev``) from the best grid start of each point with its parameters freed: how much
   of the residual it can explain. The ``top_k`` best scouts are refitted in full.
5. *Accept* a refit only if the F-test on the SSE (k added parameters) has p < ``alpha`` AND BIC improves.
   Before accepting, the nominal model is re-polished from the refit's nominal parameters (effect off): a refit
   that only found a better nominal optimum is not evidence for the effect. The accepted candidate with the
   lowest SSE joins the model (re-polished, also from the nominal start); repeat from 2 until nothing is
   accepted or ``max_effects`` is reached.
6. *Report* the final parameters at the representative nearest the reference values along the exact
   symmetries of x_B(t) (:func:`gauge_fix`): every force of the mechanism scales with its masses, the current
   scale trades K_i, λ_d against K_t, and m_C trades against J_m·Z². The magnitude of a force-type effect is
   therefore determined only relative to the mechanism's scale, i.e. at the reference's scale.

When nothing in the library is accepted while the residual still fails the whiteness or input-correlation
test, the result says so (``unexplained``) instead of forcing an effect in.

:func:`run_discover` is the job (``python -m jobs.run +experiment=discover``).
"""
from __future__ import annotations

import logging
import time
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats

from . import params as P
from . import residuals as R
from .effects import ALL_INDEX, ALL_NAMES, EFFECTS, EFFECTS_BY_NAME, Effect
from .errors import ConfigError, DataError
from .identify import IdentificationResult, stage_bounds
from .plant import GEOMETRY
from .polish import polish
from .record import Record
from .simulate import PRECISE, STATUS_OK, SolverSettings, extend, simulate

log = logging.getLogger("toggle_id")


# ------------------------------------------------------------------------------------------ settings
@dataclass
class DiscoverSettings:
    """Numbers of the discovery loop a user may change (conf/experiment/discover.yaml, node ``discover``).

    - top_k: candidates refitted per iteration (best scouts); alpha: level of the F-test an effect must pass
      (BIC must improve too); max_effects: most effects added; candidates: effect names to consider (None: all).
    - screen_alpha: a candidate is scouted only if its score or profile statistic at the polished fit exceeds
      the χ²(1) quantile of this level (1: always).
    - alpha_diag: level of the residual tests; acf_lags, ccf_lags, ccf_step: their lags (samples).
    - baseline_nfev, refit_nfev, null_nfev, scout_nfev: polish budgets (residual evaluations) of the
      baseline, a refit, the nominal re-polish guarding an acceptance, and a scout; rounds / refit_rounds:
      restarts of the baseline and guard / refit polishes while they still improve.
    - second_point: also linearise at the nominal start (see the module docstring); gauge: report the
      representatives nearest the reference along the exact symmetries; grid_points: magnitudes per probe.
    - hold_gauge: during the loop's polishes, hold one parameter per exact symmetry of x_B (K_l, K_i, m_C; see
      :data:`GAUGE_HELD`) at its value — the same fits without the flat directions that stall the trust region
      in long valleys; an effect that breaks a symmetry (``Effect.breaks``) frees its parameter again.
    - fd_rel_step: relative forward-difference step of the polish Jacobian (1e-4: smaller steps drown in the
      adaptive integrator's step-selection noise); jac_rel_step: (log-)step of the sensitivities J;
      rank_rtol: relative singular-value cut-off of J; absorbed_ratio: ‖s⊥‖/‖s‖ below which an effect counts
      as absorbed by the free parameters.
    - noise_std: known measurement noise (m), only reported as rms/noise; parallel: threaded simulation batches.
    """

    top_k: int = 3
    alpha: float = 1e-3
    max_effects: int = 3
    candidates: tuple[str, ...] | None = None
    screen_alpha: float = 0.01
    alpha_diag: float = 0.01
    acf_lags: int = 20
    ccf_lags: int = 50
    ccf_step: int = 5
    baseline_nfev: int = 60
    refit_nfev: int = 40
    null_nfev: int = 30
    scout_nfev: int = 8
    refit_rounds: int = 2
    rounds: int = 3
    second_point: bool = True
    gauge: bool = True
    hold_gauge: bool = True
    grid_points: int = 10
    fd_rel_step: float = 1e-4
    jac_rel_step: float = 1e-4
    rank_rtol: float = 1e-7
    absorbed_ratio: float = 1e-4
    noise_std: float | None = None
    parallel: bool = True

    def validate(self) -> DiscoverSettings:
        """Raise ConfigError naming the first bad value; normalise ``candidates``."""
        for name in ("alpha", "screen_alpha", "alpha_diag", "fd_rel_step", "jac_rel_step", "rank_rtol",
                     "absorbed_ratio", "noise_std"):
            v = getattr(self, name)
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float))):
                raise ConfigError(f"discover.{name} must be a number, got {v!r}")
        if not isinstance(self.top_k, int) or self.top_k < 1:
            raise ConfigError(f"discover.top_k must be a positive integer, got {self.top_k!r}")
        if not 0.0 < float(self.alpha) < 1.0:
            raise ConfigError(f"discover.alpha must lie in (0, 1), got {self.alpha!r}")
        if not 0.0 < float(self.screen_alpha) <= 1.0:
            raise ConfigError(f"discover.screen_alpha must lie in (0, 1], got {self.screen_alpha!r}")
        if not 0.0 < float(self.alpha_diag) < 1.0:
            raise ConfigError(f"discover.alpha_diag must lie in (0, 1), got {self.alpha_diag!r}")
        if not isinstance(self.max_effects, int) or self.max_effects < 0:
            raise ConfigError(f"discover.max_effects must be a non-negative integer, got {self.max_effects!r}")
        for name in ("acf_lags", "ccf_lags", "ccf_step", "baseline_nfev", "refit_nfev", "null_nfev", "scout_nfev",
                     "grid_points", "rounds", "refit_rounds"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise ConfigError(f"discover.{name} must be a positive integer, got {v!r}")
        for name in ("fd_rel_step", "jac_rel_step", "rank_rtol", "absorbed_ratio"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0.0 < float(v) < 1.0):
                raise ConfigError(f"discover.{name} must lie in (0, 1), got {v!r}")
        if self.noise_std is not None and not (np.isfinite(self.noise_std) and self.noise_std > 0):
            raise ConfigError(f"discover.noise_std must be a positive number of metres or null, got {self.noise_std!r}")
        if self.candidates is not None:
            if isinstance(self.candidates, str):
                self.candidates = None if self.candidates == "all" else (self.candidates,)
            if self.candidates is not None:
                names = tuple(str(c) for c in self.candidates)
                unknown = [c for c in names if c not in EFFECTS_BY_NAME]
                if unknown:
                    raise ConfigError(f"discover.candidates: unknown effect(s) {', '.join(unknown)}; "
                                      f"known: {', '.join(EFFECTS_BY_NAME)}")
                self.candidates = names
        return self

    @classmethod
    def from_dict(cls, node: Mapping[str, Any] | None) -> DiscoverSettings:
        """Settings from a config node; unknown keys are a ConfigError."""
        node = dict(node or {})
        known = {f for f in cls.__dataclass_fields__}
        extra = sorted(set(node) - known - {"nominal", "base"})
        if extra:
            raise ConfigError(f"discover: unknown setting(s) {', '.join(extra)}; known: {', '.join(sorted(known))}")
        kw = {k: v for k, v in node.items() if k in known}
        if isinstance(kw.get("candidates"), (list, tuple)):
            kw["candidates"] = tuple(kw["candidates"])
        return cls(**kw).validate()


# ------------------------------------------------------------------------------------------ the model
class Model:
    """Simulations of one record in the PRECISE tier: residuals, batched, with failures as NaN rows."""

    def __init__(self, record: Record, settings: SolverSettings = PRECISE, parallel: bool = True) -> None:
        if record.x_B is None:
            raise DataError(f"record {record.name!r} has no measured x_B to fit")
        self.record = record
        self.settings = settings
        self.parallel = parallel
        self.n_sims = 0

    @property
    def n(self) -> int:
        return self.record.n

    def outputs(self, thetas: np.ndarray) -> np.ndarray:
        """(P, N) model x_B [m] of extended vectors ``thetas`` (P, N_THETA); NaN rows for failures."""
        thetas = np.atleast_2d(thetas)
        self.n_sims += thetas.shape[0]
        res = simulate(thetas, self.record, self.settings, parallel=self.parallel and thetas.shape[0] > 1)
        x = res.x_B
        x[res.status != STATUS_OK] = np.nan
        return x

    def residuals(self, thetas: np.ndarray) -> np.ndarray:
        """(P, N) measured − model [m]."""
        return self.record.x_B[None, :] - self.outputs(thetas)

    def response(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """x_B [m], i_q [A] and the status of one vector."""
        res = simulate(np.atleast_2d(theta), self.record, self.settings)
        return res.x_B[0], res.i_q[0], int(res.status[0])


def _sse(r: np.ndarray) -> np.ndarray:
    r = np.atleast_2d(r)
    s = np.einsum("ij,ij->i", r, r)
    s[~np.isfinite(s)] = np.inf
    return s


def _typical(names: Sequence[str], theta: np.ndarray) -> np.ndarray:
    """A typical magnitude per parameter: |value|, or for an effect parameter at 0 its probe size."""
    out = np.abs(np.array([theta[ALL_INDEX[n]] for n in names], float))
    probe_size: dict[str, float] = {}
    for e in EFFECTS:
        for pr in e.probe:
            for k, v in pr.items():
                off = next(p.off for p in e.params if p.name == k)
                probe_size[k] = max(probe_size.get(k, 0.0), abs(float(v) - off))
    for j, n in enumerate(names):
        floor = probe_size.get(n, 0.0) or 1e-12
        out[j] = max(out[j], floor)
    return out


def _coords(names: Sequence[str], theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Analysis coordinates of ``names`` at ``theta``: log for positive parameters with lower bound ≥ 0,
    else u = x / scale. Returns (log_mask, scale)."""
    lo, _ = stage_bounds(list(names))
    x = np.array([theta[ALL_INDEX[n]] for n in names], float)
    mask = (lo >= 0.0) & (x > 0.0)
    return mask, _typical(names, theta)


def sensitivities(model: Model, theta: np.ndarray, names: Sequence[str], rel_step: float = 1e-5) -> np.ndarray:
    """Central-difference Jacobian (N, p) of the model output w.r.t. the analysis coordinates of ``names``
    (see :func:`_coords`), one batched simulation. Columns whose simulation failed are zero."""
    mask, scale = _coords(names, theta)
    p = len(names)
    T = np.repeat(theta[None, :], 2 * p, axis=0)
    steps = np.empty(p)
    for j, n in enumerate(names):
        i = ALL_INDEX[n]
        if mask[j]:
            T[2 * j, i] = theta[i] * np.exp(rel_step)
            T[2 * j + 1, i] = theta[i] * np.exp(-rel_step)
            steps[j] = rel_step
        else:
            T[2 * j, i] = theta[i] + rel_step * scale[j]
            T[2 * j + 1, i] = theta[i] - rel_step * scale[j]
            steps[j] = rel_step
    Y = model.outputs(T)
    J = ((Y[0::2] - Y[1::2]) / (2.0 * steps[:, None])).T
    J[:, ~np.all(np.isfinite(J), axis=0)] = 0.0
    return J


@dataclass
class Projector:
    """Orthonormal basis U of the range of J (rank by ``rank_rtol``) and its pseudo-inverse pieces."""

    U: np.ndarray
    s: np.ndarray
    Vt: np.ndarray

    @classmethod
    def of(cls, J: np.ndarray, rank_rtol: float = 1e-7) -> Projector:
        if J.size == 0:
            return cls(np.zeros((J.shape[0], 0)), np.zeros(0), np.zeros((0, J.shape[1])))
        U, s, Vt = np.linalg.svd(J, full_matrices=False)
        k = int(np.sum(s > rank_rtol * s[0])) if s.size and s[0] > 0 else 0
        return cls(U[:, :k], s[:k], Vt[:k])

    @property
    def rank(self) -> int:
        return int(self.s.size)

    def perp(self, v: np.ndarray) -> np.ndarray:
        """(I − U Uᵀ) v for v (N,) or (P, N) rows."""
        v = np.asarray(v, float)
        if self.rank == 0:
            return v.copy()
        return v - (v @ self.U) @ self.U.T

    def solve(self, r: np.ndarray) -> np.ndarray:
        """Minimum-norm least-squares step δu with J δu ≈ r."""
        if self.rank == 0:
            return np.zeros(self.Vt.shape[1])
        return self.Vt.T @ ((self.U.T @ r) / self.s)


# ------------------------------------------------------------------------------------------ scoring
@dataclass
class CandidateScore:
    """Score test of one effect at the current fit: the best probe, its χ²(1) statistic and p-value,
    the first-order magnitude estimate (LM step) and why no test was possible (``note``)."""

    name: str
    score: float
    p_value: float
    probe: dict
    magnitude_linear: float | None
    sensitivity_norm_m: float
    perp_ratio: float
    note: str = ""
    probes: list = field(default_factory=list)
    profile_score: float = 0.0
    profile_best: dict = field(default_factory=dict)
    scout_rmse_m: float | None = None
    profile_score_alt: float | None = None

    def to_dict(self) -> dict:
        return {"name": self.name, "score": self.score, "p_value": self.p_value, "probe": self.probe,
                "magnitude_linear": self.magnitude_linear, "profile_score": self.profile_score,
                "profile_best": self.profile_best, "scout_rmse_m": self.scout_rmse_m,
                "profile_score_at_nominal_start": self.profile_score_alt, "sensitivity_norm_m": self.sensitivity_norm_m,
                "perp_ratio": self.perp_ratio, "note": self.note}


def _with(theta: np.ndarray, values: Mapping[str, float]) -> np.ndarray:
    out = theta.copy()
    for k, v in values.items():
        out[ALL_INDEX[k]] = float(v)
    return out


def _off_values(effect: Effect) -> dict[str, float]:
    return {p.name: p.off for p in effect.params}


def score_candidates(model: Model, theta: np.ndarray, r: np.ndarray, proj: Projector, effects: Sequence[Effect],
                     absorbed_ratio: float = 1e-4, y0: np.ndarray | None = None) -> list[CandidateScore]:
    """Score test of every effect in ``effects`` (see the module docstring), sorted by score (best first).

    ``theta``: current fit (the effects' parameters at their off values); ``r``: its residual (N,);
    ``proj``: range of the free parameters' sensitivities; ``y0``: the model output at ``theta`` when the caller
    has it. One batched simulation for all probes.
    """
    n = r.size
    rp = proj.perp(r)
    sigma2 = float(rp @ rp) / max(n - proj.rank, 1)  # = r·r/(N − rank) at a fitted point
    if y0 is None:
        y0 = model.outputs(theta[None, :])[0]
    rows, owners = [], []
    for e in effects:
        base = _with(theta, _off_values(e))
        for pr in e.probe:
            rows.append(_with(base, pr))
            owners.append((e, pr))
    Y = model.outputs(np.array(rows)) if rows else np.zeros((0, n))
    noise_floor = 1e-12 * np.sqrt(n)  # integrator round-off, m
    per_effect: dict[str, list[CandidateScore]] = {}
    for (e, pr), y in zip(owners, Y):
        mag = e.magnitude
        if not np.all(np.isfinite(y)):
            cand = CandidateScore(e.name, 0.0, 1.0, dict(pr), None, float("nan"), 0.0, "probe simulation failed")
        else:
            s = y - y0
            s_norm = float(np.linalg.norm(s))
            sp = proj.perp(s)
            sp_norm = float(np.linalg.norm(sp))
            ratio = sp_norm / s_norm if s_norm > 0 else 0.0
            if s_norm <= noise_floor:
                cand = CandidateScore(e.name, 0.0, 1.0, dict(pr), None, s_norm, ratio,
                                      "no output sensitivity on this record (term silent or not implemented)")
            elif ratio < absorbed_ratio:
                cand = CandidateScore(e.name, 0.0, 1.0, dict(pr), None, s_norm, ratio,
                                      "absorbed by the free parameters (no direction of its own)")
            else:
                c = float(sp @ r) / (sp_norm ** 2)
                score = float(sp @ r) ** 2 / (sigma2 * sp_norm ** 2) if sigma2 > 0 else 0.0
                step = float(pr.get(mag.name, mag.off)) - mag.off
                est = mag.off + c * step
                note = "" if mag.lower <= est <= mag.upper else \
                    "the score points outside the feasible domain (e.g. a negative friction)"
                cand = CandidateScore(e.name, score, float(stats.chi2.sf(score, 1)), dict(pr), est, s_norm, ratio,
                                      note)
        per_effect.setdefault(e.name, []).append(cand)
    best: dict[str, CandidateScore] = {}
    for name, cands in per_effect.items():
        top = max(cands, key=lambda c: c.score)
        top.probes = [{"probe": c.probe, "score": c.score, "magnitude_linear": c.magnitude_linear, "note": c.note}
                      for c in cands]
        best[name] = top
    return sorted(best.values(), key=lambda c: -c.score)


# ------------------------------------------------------------------------------------------ fitting
@dataclass
class Fit:
    """A fitted model: extended vector, free names, SSE on the whole record and the polish's record."""

    theta: np.ndarray
    free: tuple[str, ...]
    sse: float
    info: dict = field(default_factory=dict)
    jac_u: np.ndarray | None = None
    scaling: Any = None

    def rmse(self, n: int) -> float:
        return float(np.sqrt(self.sse / n))


def fit_free(model: Model, theta: np.ndarray, free: Sequence[str], max_nfev: int, fd_rel_step: float = 1e-4,
             bounds: Mapping[str, Sequence[float]] | None = None, rounds: int = 1, round_rtol: float = 1e-4) -> Fit:
    """Polish ``free`` parameters of ``theta`` on the whole record (PRECISE, bounded least squares in log
    space for positive parameters). Keeps ``theta`` when nothing improves; never raises for a failed trial.

    ``rounds`` > 1 restarts the polish from its result (a fresh trust region) while a round still lowers the
    SSE by more than ``round_rtol`` (relative): the nominal parameters lie in long curved valleys (scaling
    symmetries), where one trust-region run often stops early.
    """
    fit = _fit_once(model, theta, free, max_nfev, fd_rel_step, bounds)
    info = dict(fit.info)
    for _ in range(max(int(rounds), 1) - 1):
        more = _fit_once(model, fit.theta, free, max_nfev, fd_rel_step, bounds)
        gain = (fit.sse - more.sse) / fit.sse if fit.sse > 0 else 0.0
        if more.sse < fit.sse:
            info["nfev"] += more.info["nfev"]
            info["seconds"] += more.info["seconds"]
            info["sse_after"] = more.sse
            info["message"] = more.info["message"]
            info["rounds"] = info.get("rounds", 1) + 1
            fit = more
        if gain <= round_rtol:
            break
    fit.info = info
    return fit


def _fit_once(model: Model, theta: np.ndarray, free: Sequence[str], max_nfev: int, fd_rel_step: float,
              bounds: Mapping[str, Sequence[float]] | None) -> Fit:
    free = tuple(free)
    idx = np.array([ALL_INDEX[n] for n in free], dtype=np.int64)
    lo, hi = stage_bounds(list(free), bounds)
    x0 = np.clip(theta[idx].astype(float), lo, hi)
    typ = _typical(free, theta)
    mask = (lo >= 0.0) & (x0 > 0.0)
    # a log parameter must start strictly inside its bounds
    x0 = np.where(mask, np.clip(x0, lo + 1e-12 * typ, hi * (1 - 1e-12)), x0)

    def thetas_of(X: np.ndarray) -> np.ndarray:
        T = np.repeat(theta[None, :], X.shape[0], axis=0)
        T[:, idx] = X
        return T

    def resid(x: np.ndarray) -> np.ndarray:
        return model.residuals(thetas_of(x[None, :]))[0]

    def jac(x: np.ndarray) -> np.ndarray:
        h = fd_rel_step * np.maximum(np.abs(x), typ)
        h = np.where(x + h > hi, -h, h)
        X = np.repeat(x[None, :], len(free) + 1, axis=0)
        X[1:] += np.diag(h)
        Rr = model.residuals(thetas_of(X))
        return (Rr[1:] - Rr[0]).T / h

    t0 = time.perf_counter()
    res = polish(resid, x0, lo, hi, log_mask=mask, jac_fn=jac, max_nfev=max_nfev)
    out = thetas_of(res.x[None, :])[0]
    info = {"sse_before": float(res.sse0), "sse_after": float(res.sse), "improved": bool(res.improved),
            "nfev": int(res.nfev), "message": str(res.message), "seconds": time.perf_counter() - t0}
    return Fit(out, free, float(res.sse), info, res.jac, res.scaling)


def parameter_uncertainty(model: Model, fit: Fit, settings: DiscoverSettings, held: Sequence[str] = ()) -> dict:
    """Identifiability report (:func:`toggle_id.identifiability.analyze`) of the free parameters at ``fit``:
    standard errors, 95 % intervals and whether each parameter is determined by the record (a parameter
    with a component along a null direction of the sensitivities is not, whatever its local curvature).

    ``held``: parameters treated as known — one per exact symmetry fixed by :func:`gauge_fix` (the
    symmetry's scale is then the reference's, and e.g. a friction torque is determined relative to it)."""
    from .identifiability import analyze

    names = [nm for nm in fit.free if nm not in set(held)]
    try:
        J = sensitivities(model, fit.theta, names, settings.jac_rel_step)
        r = model.residuals(fit.theta[None, :])[0]
        mask, scale = _coords(names, fit.theta)
        x = np.array([fit.theta[ALL_INDEX[nm]] for nm in names])
        noise = settings.noise_std ** 2 if settings.noise_std else None
        out = analyze(J, r, names, x, log_mask=mask, scale=scale, noise_var=noise).to_dict()
        out["held_for_symmetries"] = list(held)
        return out
    except (ConfigError, DataError, np.linalg.LinAlgError, ValueError) as err:
        return {"error": str(err)}


def _std_errors(fit: Fit, names: Sequence[str], n: int) -> dict[str, float | None]:
    """Gauss–Newton standard errors (physical units) of ``names`` from the polish's Jacobian (pseudo-inverse:
    directions the data do not see are left out, so read them as lower bounds there)."""
    if fit.jac_u is None or fit.scaling is None:
        return {k: None for k in names}
    J = np.asarray(fit.jac_u, float)
    sigma2 = fit.sse / max(n - J.shape[1], 1)
    try:
        cov = sigma2 * np.linalg.pinv(J.T @ J, rcond=1e-12)
    except np.linalg.LinAlgError:
        return {k: None for k in names}
    x = np.array([fit.theta[ALL_INDEX[k]] for k in fit.free])
    dxdu = fit.scaling.dx_du(x)
    out = {}
    for k in names:
        j = fit.free.index(k)
        v = cov[j, j]
        out[k] = float(np.sqrt(v) * abs(dxdu[j])) if np.isfinite(v) and v >= 0 else None
    return out


def _magnitude_grid(effect: Effect, probe: Mapping[str, float], linear: float | None, points: int) -> np.ndarray:
    """Magnitudes to try for ``effect`` at ``probe``'s nuisance setting: geometric on |m − off| from a tenth
    of the probe step to the feasible bound, on each side the domain allows, plus the LM estimate."""
    mag = effect.magnitude
    step = abs(float(probe.get(mag.name, mag.off)) - mag.off) or 1e-12
    vals = []
    for sign, bound in ((1.0, mag.upper), (-1.0, mag.lower)):
        room = (bound - mag.off) * sign
        if room <= 0:
            continue
        lo_ = min(0.1 * step, 0.5 * room)
        hi_ = 0.98 * room
        vals.extend(mag.off + sign * np.geomspace(lo_, hi_, points))
    if linear is not None and np.isfinite(linear):
        vals.append(float(np.clip(linear, mag.lower, mag.upper)))
    v = np.unique(np.array(vals, float))
    return v[(v != mag.off) & (v >= mag.lower) & (v <= mag.upper)]


@dataclass
class Profile:
    """The 1-D search of one effect: every probe's nuisance setting × a magnitude grid, each ranked by the
    residual left after the linearised re-adjustment of the free parameters, ‖(I − UUᵀ)(y_meas − y(θ_m))‖².

    ``score`` = (‖(I − UUᵀ) r‖² − min over the grid)/σ²: the nonlinear counterpart of the score test (equal to
    it for a small effect that is linear in its magnitude, larger when the effect acts nonlinearly or the fit
    absorbs it in a curved way). ``rows``/``residuals``: the best two grid vectors and their residuals."""

    name: str
    score: float
    best: dict
    rows: list
    residuals: np.ndarray
    perp_sse: list
    n_grid: int
    note: str = ""

    def to_dict(self) -> dict:
        return {"score": self.score, "best": self.best, "n_grid": self.n_grid, "perp_sse_m2": self.perp_sse,
                "note": self.note}


def profile_effect(model: Model, theta: np.ndarray, r: np.ndarray, proj: Projector, effect: Effect,
                   cand: CandidateScore, points: int = 14) -> Profile:
    """Grid search of ``effect`` at the current fit ``theta`` (residual ``r``) — see :class:`Profile`."""
    base = _with(theta, _off_values(effect))
    mag = effect.magnitude
    rows, labels = [], []
    lin = {json_key(s["probe"]): s.get("magnitude_linear") for s in cand.probes}
    for pr in effect.probe:
        for m in _magnitude_grid(effect, pr, lin.get(json_key(pr)), points):
            setting = dict(pr)
            setting[mag.name] = float(m)
            rows.append(_with(base, setting))
            labels.append(setting)
    n = r.size
    rp = proj.perp(r)
    ref = float(rp @ rp)
    sigma2 = ref / max(n - proj.rank, 1)
    if not rows:
        return Profile(effect.name, 0.0, {}, [], np.zeros((0, n)), [], 0, "no grid")
    Rr = model.residuals(np.array(rows))
    ok = np.all(np.isfinite(Rr), axis=1)
    perp = np.full(len(rows), np.inf)
    if ok.any():
        Pp = proj.perp(Rr[ok])
        perp[ok] = np.einsum("ij,ij->i", Pp, Pp)
    order = [int(i) for i in np.argsort(perp)[:2] if np.isfinite(perp[i])]
    if not order:
        return Profile(effect.name, 0.0, {}, [], np.zeros((0, n)), [], len(rows), "every grid simulation failed")
    score = max(0.0, (ref - perp[order[0]]) / sigma2) if sigma2 > 0 else 0.0
    return Profile(effect.name, float(score), {k: float(v) for k, v in labels[order[0]].items()},
                   [rows[i] for i in order], Rr[order], [float(perp[i]) for i in order], len(rows))


def refit_start(model: Model, theta: np.ndarray, free: Sequence[str], proj: Projector, prof: Profile
                ) -> tuple[np.ndarray | None, dict]:
    """Start of a refit from the profile's best two grid points, each with the free parameters as they are
    and with the linear (minimum-norm) correction; the lowest actual SSE wins. Returns (start, info)."""
    if not prof.rows:
        return None, {"grid": prof.n_grid, "note": prof.note}
    mask, scale = _coords(free, theta)
    idx = np.array([ALL_INDEX[n] for n in free], dtype=np.int64)
    lo, hi = stage_bounds(list(free))
    starts = []
    for row, res in zip(prof.rows, prof.residuals):
        starts.append(row)
        du = np.clip(proj.solve(res), -0.5, 0.5)
        corrected = row.copy()
        x = corrected[idx]
        x = np.where(mask, x * np.exp(du), x + du * scale)
        corrected[idx] = np.clip(x, lo, hi)
        starts.append(corrected)
    S = np.array(starts)
    sse = _sse(model.residuals(S))
    j = int(np.argmin(sse))
    info = {"grid": prof.n_grid, "best_grid": prof.best, "grid_perp_sse_m2": prof.perp_sse[j // 2],
            "start_sse_m2": float(sse[j]), "start_corrected": bool(j % 2)}
    return (S[j] if np.isfinite(sse[j]) else None), info


def json_key(d: Mapping[str, float]) -> tuple:
    return tuple(sorted((k, round(float(v), 12)) for k, v in d.items()))


@dataclass
class Refit:
    """One candidate refitted: its fit, the F-test and BIC against the nominal baseline, and the verdict."""

    name: str
    iteration: int
    fit: Fit | None
    params: dict
    sse0: float
    sse1: float
    k: int
    p1: int
    F: float
    p_value: float
    delta_bic: float
    accepted: bool
    reason: str
    search: dict
    null_sse: float | None = None
    std_errors: dict = field(default_factory=dict)
    seconds: float = 0.0

    def to_dict(self, n: int) -> dict:
        return {"name": self.name, "iteration": self.iteration, "params": self.params, "std_errors": self.std_errors,
                "sse_before_m2": self.sse0, "sse_after_m2": self.sse1, "rmse_before_m": float(np.sqrt(self.sse0 / n)),
                "rmse_after_m": float(np.sqrt(self.sse1 / n)) if np.isfinite(self.sse1) else None,
                "added_params": self.k, "total_params": self.p1, "F": self.F, "p_value": self.p_value,
                "delta_bic": self.delta_bic, "significant": self.accepted, "reason": self.reason,
                "null_refit_sse_m2": self.null_sse, "search": self.search,
                "polish": self.fit.info if self.fit else None, "seconds": self.seconds}


def f_test(sse0: float, sse1: float, k: int, n: int, p1: int) -> tuple[float, float, float]:
    """F statistic and p-value of adding ``k`` parameters (model with ``p1`` in all, ``n`` residuals) and
    ΔBIC = n·ln(SSE1/SSE0) + k·ln n (negative: the larger model is preferred)."""
    dof2 = max(n - p1, 1)
    if not (np.isfinite(sse1) and sse1 > 0) or not np.isfinite(sse0):
        return 0.0, 1.0, float("inf")
    F = ((sse0 - sse1) / k) / (sse1 / dof2)
    p = float(stats.f.sf(F, k, dof2)) if F > 0 else 1.0
    dbic = float(n * np.log(sse1 / sse0) + k * np.log(n))
    return float(F), p, dbic


@dataclass
class Point:
    """A linearisation point of one iteration: a parameter vector, its residual, the range of its
    sensitivities, and the candidates' score tests and profiles there."""

    label: str
    theta: np.ndarray
    proj: Projector
    scores: dict
    profiles: dict


def assess(model: Model, label: str, theta: np.ndarray, free: Sequence[str], effects: Sequence[Effect],
           settings: DiscoverSettings) -> Point | None:
    """Score test and profile of every effect in ``effects`` at ``theta`` (free parameters ``free``); None when
    ``theta`` cannot be simulated on the record."""
    y0 = model.outputs(theta[None, :])[0]
    if not np.all(np.isfinite(y0)):
        return None
    r = model.record.x_B - y0
    J = sensitivities(model, theta, free, settings.jac_rel_step)
    proj = Projector.of(J, settings.rank_rtol)
    scores = score_candidates(model, theta, r, proj, effects, settings.absorbed_ratio, y0)
    profiles = {c.name: profile_effect(model, theta, r, proj, EFFECTS_BY_NAME[c.name], c, settings.grid_points)
                for c in scores if c.score > 0.0}
    for c in scores:
        if c.name in profiles:
            c.profile_score = profiles[c.name].score
            c.profile_best = profiles[c.name].best
    return Point(label, theta, proj, {c.name: c for c in scores}, profiles)


@dataclass
class Scout:
    """A short polish of one candidate from each linearisation point's best grid start: how much of the
    residual the effect can explain with the free parameters re-adjusted (the ranking of the refits)."""

    name: str
    sse: float
    theta: np.ndarray | None
    search: dict
    seconds: float = 0.0


def scout_candidate(model: Model, base: Fit, points: Sequence[Point], effect: Effect, settings: DiscoverSettings,
                    held: Collection[str] = ()) -> Scout:
    """From each point's profile: the best grid start (:func:`refit_start`), polished for ``scout_nfev``
    evaluations with the effect's parameters freed (and the gauge parameters of ``held`` it makes determined);
    the lowest SSE is the candidate's scout result."""
    t0 = time.perf_counter()
    results, infos = [], []
    for pt in points:
        prof = pt.profiles.get(effect.name)
        if prof is None or not prof.rows:
            continue
        st, info = refit_start(model, pt.theta, base.free, pt.proj, prof)
        info["point"] = pt.label
        infos.append(info)
        if st is None:
            continue
        fit = fit_free(model, st, freed_with(base.free, effect, held), settings.scout_nfev, settings.fd_rel_step)
        info["scout_sse_m2"] = fit.sse
        results.append((fit.sse, fit.theta, info))
    if not results:
        return Scout(effect.name, float("inf"), None, {"starts": infos, "note": "no simulable start"},
                     time.perf_counter() - t0)
    sse, theta, info = min(results, key=lambda r_: r_[0])
    search = dict(info)
    search["scouts"] = {i["point"]: i.get("scout_sse_m2") for i in infos}
    return Scout(effect.name, float(sse), theta, search, time.perf_counter() - t0)


def refit_candidate(model: Model, base: Fit, effect: Effect, scout: Scout, settings: DiscoverSettings,
                    iteration: int, held: Collection[str] = ()) -> Refit:
    """Polish with the effect's parameters freed, continuing from the scout, then the F-test/BIC against
    ``base``."""
    t0 = time.perf_counter()
    n = model.n
    names = effect.names
    free = freed_with(base.free, effect, held)
    k = len(free) - len(base.free)  # the effect's parameters and any gauge parameter it frees
    p1 = len(free)
    if scout.theta is None:
        return Refit(effect.name, iteration, None, {}, base.sse, float("inf"), k, p1, 0.0, 1.0, float("inf"),
                     False, "no simulable start for the effect", scout.search, seconds=time.perf_counter() - t0)
    fit = fit_free(model, scout.theta, free, settings.refit_nfev, settings.fd_rel_step,
                   rounds=settings.refit_rounds)
    params = {nm: float(fit.theta[ALL_INDEX[nm]]) for nm in names}
    F, p, dbic = f_test(base.sse, fit.sse, k, n, p1)
    passed = p < settings.alpha and dbic < 0
    reason = "significant (F-test and BIC)" if passed else \
        ("F-test not significant" if p >= settings.alpha else "BIC does not improve")
    out = Refit(effect.name, iteration, fit, params, base.sse, fit.sse, k, p1, F, p, dbic, passed, reason,
                scout.search, std_errors=_std_errors(fit, names, n))
    out.seconds = time.perf_counter() - t0 + scout.seconds
    return out


def guard_null(model: Model, base: Fit, refit: Refit, effect: Effect, settings: DiscoverSettings) -> Fit | None:
    """Re-polish the model without the effect from the refit's parameters; if it beats the baseline the
    refit is re-tested against it. Returns the better null fit (or None when it did not improve)."""
    start = _with(refit.fit.theta, _off_values(effect))
    null = fit_free(model, start, base.free, settings.null_nfev, settings.fd_rel_step, rounds=settings.rounds)
    refit.null_sse = null.sse
    if null.sse < base.sse:
        F, p, dbic = f_test(null.sse, refit.sse1, refit.k, model.n, refit.p1)
        refit.sse0, refit.F, refit.p_value, refit.delta_bic = null.sse, F, p, dbic
        refit.accepted = p < settings.alpha and dbic < 0
        if not refit.accepted:
            refit.reason = ("a better nominal optimum explains the gain: " +
                            ("F-test not significant" if p >= settings.alpha else "BIC does not improve"))
        return null
    return None


# ------------------------------------------------------------------------------------------ symmetries
#: Parameters that scale together with every force of the mechanism: multiplying all of them (and every effect
#: parameter whose unit is a force, torque, damping or stiffness) by c leaves x_B(t) and i_q(t) unchanged.
MECHANICAL = ("m_2", "m_3", "m_5", "m_B", "m_C", "J_m", "B_m", "K_t", "K_l", "D")
#: The current scale: i_q → i_q/c with K_i → K_i/c, λ_d → λ_d/c, K_t → c·K_t leaves x_B(t) unchanged.
ELECTRICAL = {"K_t": 1.0, "K_i": -1.0, "lambda_d": -1.0}


#: The parameter held at its value to fix each symmetry in the uncertainty analysis (one per symmetry).
GAUGE_HELD = {"mechanical": "K_l", "current": "K_i", "inertia_split": "m_C"}


def gauge_symmetries(free: Collection[str], broken: Collection[str] = ()) -> list[str]:
    """The exact symmetries of x_B whose parameters are all in ``free`` and that no effect in the model breaks."""
    f = set(free)
    members = {"mechanical": MECHANICAL, "current": tuple(ELECTRICAL), "inertia_split": ("m_C", "J_m")}
    return [s for s, names in members.items() if s not in broken and set(names) <= f]


def freed_with(base_free: Sequence[str], effect: Effect, held: Collection[str]) -> tuple[str, ...]:
    """The parameters of a refit with ``effect`` on: the base fit's, the gauge parameters ``effect`` makes
    determined again (held so far), and the effect's own."""
    back = tuple(GAUGE_HELD[s] for s in effect.breaks if GAUGE_HELD[s] in held and GAUGE_HELD[s] not in base_free)
    return tuple(base_free) + back + effect.names


def _force_like(name: str) -> bool:
    """An effect parameter in newtons (force, torque, damping, stiffness) scales with the mechanism."""
    for e in EFFECTS:
        for p in e.params:
            if p.name == name:
                return p.unit.startswith("N")
    return False


def gauge_fix(model: Model, theta: np.ndarray, free: Sequence[str], reference: np.ndarray,
              tol_m: float = 2e-8, broken: Collection[str] = ()) -> tuple[np.ndarray, dict]:
    """Move ``theta`` along the exact symmetries of x_B(t) to the point closest (in log space) to ``reference``.

    The symmetries (see :data:`MECHANICAL`, :data:`ELECTRICAL`, and m_C + J_m·Z² of MODEL.md §3) leave the output
    unchanged, so the fit is the same; the representative nearest the reference values makes the parameters —
    and the magnitudes of force-type effects, which scale with the mechanism — comparable with the reference. A
    symmetry is used only if all its parameters are free, the move stays within the feasible domains, and the
    output is verified unchanged (``tol_m``); symmetries in ``broken`` (broken by an effect of the model) are
    not used. Returns (theta, {"mechanical_scale", "current_scale", ...}).
    """
    from .plant import GEOMETRY as G

    out = theta.copy()
    info: dict = {"mechanical_scale": 1.0, "current_scale": 1.0, "applied": False}
    free = set(free)
    mech = [n for n in MECHANICAL]
    sym = gauge_symmetries(free, broken)
    use_m = "mechanical" in sym
    use_e = "current" in sym
    use_split = "inertia_split" in sym
    if not (use_m or use_e or use_split):
        return out, info
    names = sorted(set(mech if use_m else []) | set(ELECTRICAL if use_e else []))
    x = np.array([out[ALL_INDEX[n]] for n in names])
    ref = np.array([reference[ALL_INDEX[n]] for n in names])
    if np.any(x <= 0) or np.any(ref <= 0):
        return out, info
    cols = []
    if use_m:
        cols.append([1.0 if n in mech else 0.0 for n in names])
    if use_e:
        cols.append([ELECTRICAL.get(n, 0.0) for n in names])
    A = np.array(cols).T
    logc = np.linalg.lstsq(A, np.log(ref) - np.log(x), rcond=None)[0]
    c_m = float(np.exp(logc[0])) if use_m else 1.0
    c_e = float(np.exp(logc[-1])) if use_e else 1.0
    if use_m:
        for n in mech:
            out[ALL_INDEX[n]] *= c_m
        for n in ALL_NAMES[P.N_PARAMS:]:
            if _force_like(n):
                out[ALL_INDEX[n]] *= c_m
    if use_e:
        for n, k in ELECTRICAL.items():
            out[ALL_INDEX[n]] *= c_e ** k
        for e in EFFECTS:  # a limit on the drive voltage K_i·v (unit 1/V) follows the current scale
            for p in e.params:
                if p.unit == "1/V":
                    out[ALL_INDEX[p.name]] *= c_e
    if use_split and reference[ALL_INDEX["m_C"]] > 0 and reference[ALL_INDEX["J_m"]] > 0:
        Z2 = G.Z ** 2
        total = out[ALL_INDEX["m_C"]] + out[ALL_INDEX["J_m"]] * Z2
        rc, rj = reference[ALL_INDEX["m_C"]], reference[ALL_INDEX["J_m"]]
        fr = np.linspace(1e-3, 1 - 1e-3, 2001)
        cost = (np.log(fr * total / rc)) ** 2 + (np.log((1 - fr) * total / Z2 / rj)) ** 2
        f = fr[int(np.argmin(cost))]
        out[ALL_INDEX["m_C"]], out[ALL_INDEX["J_m"]] = f * total, (1 - f) * total / Z2
    lo, hi = stage_bounds(list(ALL_NAMES))
    if np.any(out < lo) or np.any(out > hi):
        info["note"] = "the symmetric representative nearest the reference leaves the feasible domain; not applied"
        return theta.copy(), info
    y = model.outputs(np.array([theta, out]))
    diff = float(np.nanmax(np.abs(y[0] - y[1]))) if np.all(np.isfinite(y)) else np.inf
    if not diff <= tol_m:
        info["note"] = f"output changed by {diff:.3g} m along the symmetry; not applied"
        return theta.copy(), info
    held = ([GAUGE_HELD["mechanical"]] if use_m else []) + ([GAUGE_HELD["current"]] if use_e else [])
    if use_split:
        held.append(GAUGE_HELD["inertia_split"])
    info.update({"mechanical_scale": c_m, "current_scale": c_e, "applied": True, "output_change_m": diff,
                 "held": held})
    return out, info


# ------------------------------------------------------------------------------------------ result
@dataclass
class DiscoveryResult:
    """What the loop found: the model before and after, every candidate's score and refit, the diagnostics."""

    record: str
    n: int
    baseline: Fit
    final: Fit
    effects_added: list[dict]
    candidates: list[dict]
    iterations: list[dict]
    diagnostics_before: dict
    diagnostics_after: dict
    residual_before: np.ndarray
    residual_after: np.ndarray
    nominal: dict | None
    conclusion: str
    unexplained: bool
    seconds: float
    n_simulations: int
    refits: list[Refit] = field(default_factory=list)
    extra: dict = field(default_factory=dict)

    @property
    def rmse_before_m(self) -> float:
        return self.baseline.rmse(self.n)

    @property
    def rmse_after_m(self) -> float:
        return self.final.rmse(self.n)

    def to_dict(self) -> dict:
        def params_of(fit: Fit) -> dict:
            return {"physical": {nm: float(fit.theta[i]) for i, nm in enumerate(P.PARAM_NAMES)},
                    "effects": {nm: float(fit.theta[ALL_INDEX[nm]]) for nm in ALL_NAMES[P.N_PARAMS:]},
                    "free": list(fit.free)}

        return {"record": self.record, "n_samples": self.n,
                "effects_added": self.effects_added, "candidates": self.candidates,
                "rmse_before_m": self.rmse_before_m, "rmse_after_m": self.rmse_after_m,
                "fitness_before": 1.0 / self.baseline.sse if self.baseline.sse > 0 else float("inf"),
                "fitness_after": 1.0 / self.final.sse if self.final.sse > 0 else float("inf"),
                "sse_before_m2": self.baseline.sse, "sse_after_m2": self.final.sse,
                "params_before": params_of(self.baseline), "params_after": params_of(self.final),
                "final_params": {**params_of(self.final)["physical"],
                                 **{nm: float(self.final.theta[ALL_INDEX[nm]]) for nm in ALL_NAMES[P.N_PARAMS:]}},
                "residual_tests_before": self.diagnostics_before, "residual_tests_after": self.diagnostics_after,
                "conclusion": self.conclusion, "unexplained": self.unexplained, "iterations": self.iterations,
                "baseline_polish": self.baseline.info, "nominal": self.nominal, "seconds": self.seconds,
                "n_simulations": self.n_simulations, **self.extra}


# ------------------------------------------------------------------------------------------ the loop
def residual_report(model: Model, theta: np.ndarray, settings: DiscoverSettings, split_index: int | None
                    ) -> tuple[dict, np.ndarray, dict]:
    """Diagnostics of the residual of ``theta`` (dict), the residual (N,) and the state signals."""
    x, i_q, status = model.response(theta)
    rec = model.record
    r = rec.x_B - x
    if status != STATUS_OK or not np.all(np.isfinite(r)):
        return {"error": f"the model cannot be simulated on this record (status {status})"}, r, {}
    states = R.plant_states(rec.t, x, i_q, x_off=float(theta[ALL_INDEX["x_off"]]))
    d = R.diagnose(rec.t, r, rec.v_in, states, alpha=settings.alpha_diag, acf_lags=settings.acf_lags,
                   ccf_lags=settings.ccf_lags, ccf_step=settings.ccf_step, split_index=split_index,
                   noise_std=settings.noise_std)
    return d, r, states


def _nominal_theta(nominal: IdentificationResult | np.ndarray | Mapping[str, float] | None) -> np.ndarray:
    theta = extend(P.ASSIGNED)[0]
    if nominal is None:
        return theta
    if isinstance(nominal, IdentificationResult):
        return extend(np.asarray(nominal.theta, float))[0]
    if isinstance(nominal, Mapping):
        return _with(theta, nominal)
    return extend(np.asarray(nominal, float))[0]


def discover(record: Record, *, nominal: IdentificationResult | np.ndarray | Mapping[str, float] | None = None,
             effects: Sequence[Effect] = EFFECTS, settings: DiscoverSettings | None = None,
             free: Sequence[str] | None = None, fixed: Mapping[str, float] | None = None,
             starts: Sequence[np.ndarray | Mapping[str, float]] = (),
             reference: np.ndarray | Mapping[str, float] | None = None, on_refit: Callable[[Refit], None] | None = None, progress: Callable[[str], None] | None = None
             ) -> DiscoveryResult:
    """Run the discovery loop on ``record`` (see the module docstring).

    nominal: the nominal fit (an :class:`IdentificationResult`, an extended/physical vector or a name → value
        mapping; None: the assigned values) — the loop starts by polishing it on the whole record.
    effects: the candidate library (default all of :data:`toggle_id.effects.EFFECTS`), filtered by
        ``settings.candidates``. free: nominal parameters fitted (default the 15 physical ones minus
        ``fixed``); fixed: parameters held at given values. starts: further starting points of the baseline
        polish (e.g. the assigned values beside a GA result); the best polished one is the baseline.
    reference: the values the reported parameters are brought closest to along the exact symmetries of the
        output (:func:`gauge_fix`; default the assigned values) — it fixes the otherwise arbitrary scale of the
        mechanism, and with it the magnitude of force-type effects.
    on_refit: called with every :class:`Refit` (e.g. to log an MLflow child run); progress: one-line messages.
    """
    settings = (settings or DiscoverSettings()).validate()
    say = progress or (lambda msg: log.info(msg))
    t_start = time.perf_counter()
    model = Model(record, PRECISE, settings.parallel)
    fixed = dict(fixed or {})
    for k in fixed:
        if k not in ALL_INDEX:
            raise ConfigError(f"fixed: unknown parameter {k!r}")
    theta = _with(_nominal_theta(nominal), fixed)
    free = tuple(free) if free is not None else tuple(n for n in P.PARAM_NAMES if n not in fixed)
    for k in free:
        if k not in ALL_INDEX:
            raise ConfigError(f"unknown free parameter {k!r}")
    pool = [e for e in effects if settings.candidates is None or e.name in settings.candidates]
    pool = [e for e in pool if not any(p in free or p in fixed for p in e.names)]
    # one parameter per exact symmetry of x_B held during the polishes (the gauge): same fits, no flat directions
    held = tuple(GAUGE_HELD[s] for s in gauge_symmetries(free)) if settings.hold_gauge else ()
    free = tuple(nm for nm in free if nm not in held)
    split = record.clamp_index(GEOMETRY.x_B_L)
    split = split if 0 < split < record.n else None
    n = record.n

    # 1. baseline: the nominal model polished on the whole record (from every start; the best is kept)
    anchors = [theta] + [_with(_nominal_theta(st), fixed) for st in starts]
    current, anchor, start_report = None, theta, []
    for k, th0 in enumerate(anchors):
        if not np.all(np.isfinite(model.residuals(th0[None, :])[0])):
            start_report.append({"start": k, "error": "cannot be simulated on this record"})
            continue
        say(f"baseline polish of {len(free)} parameters on {n} samples (start {k + 1} of {len(anchors)})")
        fit = fit_free(model, th0, free, settings.baseline_nfev, settings.fd_rel_step, rounds=settings.rounds)
        start_report.append({"start": k, "rmse_m": fit.rmse(n), "nfev": fit.info["nfev"]})
        say(f"  rms {fit.rmse(n) * 1e6:.4g} µm ({fit.info['nfev']} evaluations, {fit.info['seconds']:.1f} s)")
        if current is None or fit.sse < current.sse:
            current, anchor = fit, th0
    if current is None:
        raise DataError("the nominal model cannot be simulated on this record from any start; fit it first")
    current.info["starts"] = start_report
    baseline = current

    iterations: list[dict] = []
    added: list[dict] = []
    first_scores: list[CandidateScore] | None = None
    accepted_names: set[str] = set()
    all_refits: list[Refit] = []
    for it in range(1, settings.max_effects + 1):
        remaining = [e for e in pool if e.name not in accepted_names]
        if not remaining:
            break
        points = [assess(model, "current fit", current.theta, current.free, remaining, settings)]
        # second linearisation point: the nominal fit as given, with the effects added so far — the polished
        # fit may have bent the nominal parameters far towards the missing effect (masses → 0, friction × 50),
        # where the local picture of the remaining candidates is distorted
        alt = _with(anchor, {nm: current.theta[ALL_INDEX[nm]] for nm in current.free if nm not in free})
        if settings.second_point and not np.allclose(alt, current.theta, rtol=1e-3, atol=0.0):
            second = assess(model, "nominal start", alt, current.free, remaining, settings)
            if second is not None:  # (None: the nominal start cannot be simulated with these effects)
                points.append(second)
        scores = list(points[0].scores.values())  # the score tests proper: at the fitted point
        for c in scores:
            for pt in points[1:]:
                c.profile_score_alt = pt.scores[c.name].profile_score
        say("scores (profile | LM): " + ", ".join(f"{c.name} {c.profile_score:.3g} | {c.score:.3g}"
                                                  for c in sorted(scores, key=lambda c: -c.profile_score)))
        # screened at the fitted point (where the statistics mean what they say); every screened candidate is
        # scouted (short polish with the effect freed, from each point) and the refits follow the scouts
        screen = float(stats.chi2.isf(settings.screen_alpha, 1))
        here = points[0].scores
        # (a candidate the fitted point cannot see at all — silent there, e.g. a voltage limit above the fit's
        # drive voltage — is judged by the scout from the other point instead)
        screened = [c for c in scores if any(c.name in pt.profiles for pt in points)
                    and (max(here[c.name].profile_score, here[c.name].score) > screen
                         or (c.name not in points[0].profiles
                             and any(pt.scores[c.name].profile_score > screen for pt in points[1:])))]
        scouts = {c.name: scout_candidate(model, current, points, EFFECTS_BY_NAME[c.name], settings, held)
                  for c in screened}
        for c in scores:
            c.scout_rmse_m = float(np.sqrt(scouts[c.name].sse / n)) if c.name in scouts else None
        order = sorted(scouts.values(), key=lambda sc: sc.sse)
        scores.sort(key=lambda c: (scouts[c.name].sse if c.name in scouts else np.inf, -c.profile_score))
        if first_scores is None:
            first_scores = scores
        say("scouts: " + (", ".join(f"{sc.name} {np.sqrt(sc.sse / n) * 1e6:.4g} µm" for sc in order) or "none"))
        refits: list[Refit] = []
        for sc in order[:settings.top_k]:
            eff = EFFECTS_BY_NAME[sc.name]
            rf = refit_candidate(model, current, eff, sc, settings, it, held)
            if rf.accepted:
                better_null = guard_null(model, current, rf, eff, settings)
                if better_null is not None and better_null.sse < current.sse:
                    say(f"  nominal re-polish from the {eff.name} refit lowered the baseline to "
                        f"{better_null.rmse(n) * 1e6:.4g} µm")
                    current = better_null
                    if not added:  # still the nominal model: the error "before" is this better fit's
                        baseline = current
                    for other in refits:  # earlier refits are compared with the better baseline too
                        if other.accepted:
                            F, p, dbic = f_test(current.sse, other.sse1, other.k, n, other.p1)
                            other.sse0, other.F, other.p_value, other.delta_bic = current.sse, F, p, dbic
                            other.accepted = p < settings.alpha and dbic < 0
                            if not other.accepted:
                                other.reason = "not significant against the re-polished nominal model"
            say(f"  refit {eff.name}: rms {np.sqrt(rf.sse1 / n) * 1e6:.4g} µm, F {rf.F:.3g}, p {rf.p_value:.3g}, "
                f"ΔBIC {rf.delta_bic:.4g} → {'accepted' if rf.accepted else 'rejected'} ({rf.seconds:.1f} s)")
            refits.append(rf)
            all_refits.append(rf)
            if on_refit is not None:
                on_refit(rf)
        winners = [rf for rf in refits if rf.accepted]
        chosen = min(winners, key=lambda rf: rf.sse1) if winners else None
        iterations.append({"iteration": it, "rmse_m": current.rmse(n), "rank_J": points[0].proj.rank,
                           "points": [pt.label for pt in points],
                           "scores": [c.to_dict() for c in scores],
                           "refits": [rf.to_dict(n) for rf in refits],
                           "accepted": chosen.name if chosen else None})
        if chosen is None:
            break
        accepted_names.add(chosen.name)
        current = fit_free(model, chosen.fit.theta, chosen.fit.free, settings.baseline_nfev, settings.fd_rel_step,
                           rounds=settings.rounds)
        # second start: the nominal fit as given (before the baseline polish bent it towards the missing
        # effect) with the effects' current values — the polished baseline may sit in another valley
        effect_names = [nm for nm in chosen.fit.free if nm not in free]
        alt = fit_free(model, _with(anchor, {nm: current.theta[ALL_INDEX[nm]] for nm in effect_names}),
                       chosen.fit.free, settings.baseline_nfev, settings.fd_rel_step, rounds=settings.rounds)
        if alt.sse < current.sse:
            say(f"  second start (nominal fit + effects) reached {alt.rmse(n) * 1e6:.4g} µm "
                f"instead of {current.rmse(n) * 1e6:.4g} µm")
            current = alt
        added.append({"name": chosen.name, "iteration": it, "F": chosen.F, "p_value": chosen.p_value,
                      "delta_bic": chosen.delta_bic, "rmse_after_m": current.rmse(n),
                      "params_at_acceptance": chosen.params})
        say(f"added {chosen.name} {chosen.params}; rms {current.rmse(n) * 1e6:.4g} µm")

    # the representatives of the fits nearest the reference along the exact symmetries (same output)
    ref = _with(_nominal_theta(reference), fixed) if reference is not None else _with(extend(P.ASSIGNED)[0], fixed)
    gauge_before = gauge_after = {"applied": False}
    if settings.gauge:
        broken = {sym for a in added for sym in EFFECTS_BY_NAME[a["name"]].breaks}
        baseline.theta, gauge_before = gauge_fix(model, baseline.theta, baseline.free + held, ref)
        current.theta, gauge_after = gauge_fix(model, current.theta, tuple(set(current.free) | set(held)), ref,
                                               broken=broken)
    uncertainty = parameter_uncertainty(model, current, settings, gauge_after.get("held", ())) if added else {}
    for a in added:  # the values of the final model (later refits move earlier effects' parameters too)
        eff = EFFECTS_BY_NAME[a["name"]]
        a["params"] = {nm: float(current.theta[ALL_INDEX[nm]]) for nm in eff.names}
        a["std_errors"] = {nm: (uncertainty.get("std_errors") or {}).get(nm) for nm in eff.names}
        a["ci95"] = {nm: (uncertainty.get("ci95") or {}).get(nm) for nm in eff.names}
        a["identifiable"] = {nm: (uncertainty.get("identifiable") or {}).get(nm) for nm in eff.names}
        a["magnitude"] = {"name": eff.magnitude.name, "value": a["params"][eff.magnitude.name],
                          "unit": eff.magnitude.unit, "std_error": a["std_errors"][eff.magnitude.name],
                          "identifiable": a["identifiable"][eff.magnitude.name],
                          "scales_with_mechanism": _force_like(eff.magnitude.name),
                          "at_reference_scale": bool(gauge_after.get("applied")) and _force_like(eff.magnitude.name)}
        k_l = float(current.theta[ALL_INDEX["K_l"]])
        if _force_like(eff.magnitude.name) and k_l > 0:
            # x_B fixes a force only relative to the mechanism (every force scales with it, exactly): the ratio
            # to the contact stiffness is what the record determines, whatever representative is reported
            a["magnitude"]["per_K_l"] = a["params"][eff.magnitude.name] / k_l
    diag_before, r_before, _ = residual_report(model, baseline.theta, settings, split)
    diag_after, r_after, _ = residual_report(model, current.theta, settings, split)
    cands = []
    for c in first_scores or []:
        tried = [rf for rf in all_refits if rf.name == c.name]
        cands.append({**c.to_dict(), "accepted": c.name in accepted_names, "refitted": bool(tried),
                      "refit_p_value": min((rf.p_value for rf in tried), default=None)})
    structure = diag_after.get("verdict", {}).get("structure_left", False)
    unexplained = bool(structure)
    conclusion = _conclusion(added, diag_before, diag_after, unexplained, settings)
    return DiscoveryResult(record=record.name, n=n, baseline=baseline, final=current, effects_added=added,
                           candidates=cands, iterations=iterations, diagnostics_before=diag_before,
                           diagnostics_after=diag_after, residual_before=r_before, residual_after=r_after,
                           nominal=nominal.to_dict() if isinstance(nominal, IdentificationResult) else None,
                           conclusion=conclusion, unexplained=unexplained, seconds=time.perf_counter() - t_start,
                           n_simulations=model.n_sims, refits=all_refits,
                           extra={"symmetry_gauge": {"before": gauge_before, "after": gauge_after},
                                  "identifiability_after": uncertainty})


def _conclusion(added: list[dict], before: dict, after: dict, unexplained: bool, s: DiscoverSettings) -> str:
    """One plain sentence (or two) on what was found and what is left."""
    def tests(d: dict) -> str:
        w = d.get("whiteness", {})
        u = d.get("input_correlation", {})
        return (f"Ljung–Box p = {w.get('p_value', float('nan')):.3g}, "
                f"input-correlation p = {u.get('p_value', float('nan')):.3g} (level {s.alpha_diag:g})")

    if added:
        text = "added " + ", ".join(f"{a['name']} ({a['magnitude']['name']} = {a['magnitude']['value']:.4g} "
                                    f"{a['magnitude']['unit']})" for a in added)
        text += f"; RMS error {before.get('rms_m', float('nan')) * 1e6:.4g} → {after.get('rms_m', float('nan')) * 1e6:.4g} µm."
    else:
        text = "no effect of the library is significant (F-test and BIC); the nominal model is kept."
    if unexplained:
        text += (" Residual structure remains that no effect of the library explains: " + tests(after) + ".")
    else:
        text += " The residual is consistent with white noise independent of the input: " + tests(after) + "."
    return text


# ------------------------------------------------------------------------------------------ the job
def discover_settings(cfg: Mapping) -> DiscoverSettings:
    """Settings from the ``discover`` node of a job config (ConfigError on a bad value)."""
    node = dict(cfg.get("discover") or {})
    nominal = node.get("nominal", "ga")
    if nominal not in ("ga", "base"):
        raise ConfigError(f"discover.nominal must be 'ga' (two-stage RGA + polish) or 'base' (polish from the "
                          f"assigned/base values), got {nominal!r}")
    if node.get("noise_std") is None:
        noise = (cfg.get("identifiability") or {}).get("noise_std_m")
        if noise is not None:
            node["noise_std"] = float(noise)
    try:
        return DiscoverSettings.from_dict(node)
    except TypeError as err:
        raise ConfigError(f"discover: {err}") from err


def run_discover(cfg: Mapping, run_dir: str | Path, project_root: str | Path = ".") -> Path:
    """The discover job: nominal two-stage fit, the discovery loop, figures, MLflow, ``discovery.json``."""
    from . import console, workflow
    from .identify import identify

    workflow.validate_config(cfg)
    settings = discover_settings(cfg)
    nominal_mode = (cfg.get("discover") or {}).get("nominal", "ga")
    method = cfg.get("method", "two_stage")
    fixed = dict(cfg.get("fixed") or {})
    for nm in fixed:
        if nm not in ALL_INDEX:
            raise ConfigError(f"fixed: unknown parameter {nm!r}")
    if cfg.get("extra_free"):
        raise ConfigError("extra_free is not used by the discover job: the loop frees effect parameters itself")
    base_start = _base_vector(cfg)
    ga = workflow.ga_config(cfg)
    polish_cfg = workflow.polish_settings(cfg)
    tier = workflow.solver_tier(cfg)
    ev = cfg.get("evaluator") or {}
    make_eval = workflow.evaluator_factory(ev)
    run_dir = Path(run_dir).resolve()
    run_dir.mkdir(parents=True, exist_ok=True)
    record, truth = workflow.build_record(cfg.get("data") or {})
    if record.x_B is None:
        raise DataError(f"record {record.name!r} has no measured x_B")
    if settings.noise_std is None and truth is not None:
        noise = float((cfg.get("data") or {}).get("noise_m", 0.0) or 0.0)
        settings.noise_std = noise if noise > 0 else None
    tracker = workflow.make_tracker(cfg, project_root)
    show = bool(cfg.get("progress", True))
    t0 = time.perf_counter()
    with workflow.ray_session(ev), tracker.run("discover", tags={"job": "discover", "method": method}) as run:
        tracker.log_params(workflow._flat_config(cfg))
        nominal_result: IdentificationResult | None = None
        if nominal_mode == "ga":
            with tracker.run("nominal", tags={"stage": "nominal"}, nested=True):
                nominal_result = identify(record, method=method, ga=ga, seed=int(cfg.get("seed", 0)),
                                          make_evaluator=make_eval, fixed=fixed, bounds=dict(cfg.get("bounds") or {}),
                                          settings=tier, polish=polish_cfg, identifiability=False,
                                          progress=lambda total, desc: console.progress(total, desc, enabled=show),
                                          on_stage=lambda st: workflow.stage_child_run(tracker, st, truth))
                tracker.log_metrics({"fitness": nominal_result.fitness, "rmse_m": nominal_result.rmse_m,
                                     "seconds": nominal_result.seconds})
        nominal = nominal_result if nominal_result is not None else base_start
        starts = [base_start] if nominal_result is not None else []

        def on_refit(rf: Refit) -> None:
            with tracker.run(f"refit_{rf.iteration}_{rf.name}", tags={"effect": rf.name,
                                                                       "iteration": str(rf.iteration)}, nested=True):
                tracker.log_params({"effect": rf.name, "iteration": rf.iteration,
                                    **{f"start.{k}": v for k, v in (rf.search.get("best_grid") or {}).items()}})
                tracker.log_metrics({"sse_before_m2": rf.sse0, "sse_after_m2": rf.sse1, "F": rf.F,
                                     "p_value": rf.p_value, "delta_bic": rf.delta_bic, "accepted": float(rf.accepted),
                                     "rmse_after_m": float(np.sqrt(rf.sse1 / record.n)) if np.isfinite(rf.sse1) else
                                     float("nan"), "seconds": rf.seconds,
                                     **{f"param.{k}": v for k, v in rf.params.items()}})

        res = discover(record, nominal=nominal, settings=settings, fixed=fixed, starts=starts, reference=base_start,
                       on_refit=on_refit,
                       progress=(lambda msg: print(msg, flush=True)) if show else None)
        wall = time.perf_counter() - t0
        report = res.to_dict()
        report.update({"job": "discover", "wall_seconds": wall, "mlflow_run_id": run.run_id,
                       "config": workflow._jsonable_cfg(cfg), "nominal_mode": nominal_mode,
                       "settings": asdict(settings)})
        if truth is not None:
            report["truth"] = {nm: float(truth[i]) for i, nm in enumerate(ALL_NAMES)}
        tracker.log_metrics({"rmse_before_m": res.rmse_before_m, "rmse_after_m": res.rmse_after_m,
                             "fitness_before": report["fitness_before"], "fitness_after": report["fitness_after"],
                             "n_effects_added": len(res.effects_added), "wall_seconds": wall,
                             "ljung_box_p_before": res.diagnostics_before.get("whiteness", {}).get("p_value", np.nan),
                             "ljung_box_p_after": res.diagnostics_after.get("whiteness", {}).get("p_value", np.nan),
                             **{f"score.{c['name']}": c["score"] for c in res.candidates}})
        tracker.set_tags({"effects_added": ",".join(a["name"] for a in res.effects_added) or "none"})
        for path in write_figures(run_dir, record, res, settings):
            tracker.log_artifact(path, "figures")
        path = workflow.publish_report(tracker, run_dir, summary_text(res), report, "discovery.json", "discovery.txt")
    return path


def _base_vector(cfg: Mapping) -> np.ndarray:
    """Start of the baseline polish when no GA runs: the assigned values with ``discover.base`` overrides."""
    theta = extend(P.ASSIGNED)[0]
    for k, v in ((cfg.get("discover") or {}).get("base") or {}).items():
        if k not in ALL_INDEX:
            raise ConfigError(f"discover.base: unknown parameter {k!r}")
        theta[ALL_INDEX[k]] = float(v)
    return theta


def write_figures(run_dir: Path, record: Record, res: DiscoveryResult, settings: DiscoverSettings) -> list[str]:
    """Residual diagnostics before/after, residual against states and input, and the before/after comparison."""
    from . import figures

    out = []
    split = record.clamp_index(GEOMETRY.x_B_L)
    t_split = float(record.t[split]) if 0 < split < record.n else None
    model = Model(record, PRECISE, settings.parallel)
    for label, fit, r in (("before", res.baseline, res.residual_before), ("after", res.final, res.residual_after)):
        if not np.all(np.isfinite(r)):
            continue
        fig = R.diagnostics_figure(record.t, r, alpha=settings.alpha_diag, title=f"Residual diagnostics ({label})")
        out.append(figures.save(fig, run_dir / f"residual_{label}.png"))
        x, i_q, _ = model.response(fit.theta)
        states = R.plant_states(record.t, x, i_q, x_off=float(fit.theta[ALL_INDEX["x_off"]]))
        fig = R.states_figure(r, states, record.v_in, dt=record.dt, alpha=settings.alpha_diag,
                              title=f"Residual against the states and the input ({label})")
        out.append(figures.save(fig, run_dir / f"residual_states_{label}.png"))
    if np.all(np.isfinite(res.residual_before)) and np.all(np.isfinite(res.residual_after)):
        names = ", ".join(a["name"] for a in res.effects_added) or "no effect added"
        fig = R.comparison_figure(record.t, {"before (nominal)": res.residual_before, f"after ({names})":
                                             res.residual_after}, noise_std=settings.noise_std, split_time=t_split)
        out.append(figures.save(fig, run_dir / "residual_before_after.png"))
    return out


def summary_text(res: DiscoveryResult) -> str:
    """Console summary: candidate table (first iteration), effects added, RMS before/after, conclusion."""
    from . import console

    rows = [[c["name"], c["score"], c["p_value"], "yes" if c["refitted"] else "", "yes" if c["accepted"] else "",
             c["note"]] for c in res.candidates]
    lines = [console.text_table(["effect", "score χ²(1)", "p", "refitted", "accepted", "note"], rows)]
    for a in res.effects_added:
        se = a["std_errors"].get(a["magnitude"]["name"])
        lines.append(f"added {a['name']}: {a['magnitude']['name']} = {a['magnitude']['value']:.5g} "
                     f"{a['magnitude']['unit']}" + (f" ± {se:.2g}" if se else "") +
                     f"  (F-test p {a['p_value']:.3g}, ΔBIC {a['delta_bic']:.4g})")
        if "per_K_l" in a["magnitude"]:
            lines.append(f"  a force-type magnitude: x_B fixes it only relative to the mechanism's common scale "
                         f"({a['magnitude']['name']}/K_l = {a['magnitude']['per_K_l']:.5g} per N/m; at the "
                         "reference scale above — fix one mechanical parameter, e.g. fixed.K_t, to pin it)")
    lines.append(f"RMS error before {res.rmse_before_m * 1e6:.4g} µm, after {res.rmse_after_m * 1e6:.4g} µm; "
                 f"{res.seconds:.1f} s, {res.n_simulations} simulations")
    lines.append(res.conclusion)
    return "\n".join(lines)
