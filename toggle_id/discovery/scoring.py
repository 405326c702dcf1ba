"""Score tests and magnitude profiles of the candidate effects at a linearisation point.

- The Lagrange-multiplier (score) test: s = y(θ with the effect at a probe setting) − y(θ) (PRECISE finite
  difference), prewhitened with the residual r and the sensitivities J of the free parameters, projected off J's
  range (SVD basis U): s⊥ = (I − UUᵀ)s; score = (s⊥·r)²/(σ² s⊥·s⊥), σ² = ‖(I − UUᵀ)r‖²/(N − rank J), the best
  probe per effect; χ²(1) under "the effect is absent" (a little more for the best of several probes). An effect
  whose s is zero is silent at the probe; one whose s⊥ vanishes is absorbed by the free parameters.
- The profile: each probe's nuisance setting × a geometric grid of magnitudes up to the feasible bound, ranked by
  ‖(I − UUᵀ)(y_meas − y(θ_m))‖² (the residual after the linearised re-adjustment of the free parameters) — the
  nonlinear counterpart of the score test, and the start of the candidate's scout.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from ..effects import ALL_INDEX, EFFECTS_BY_NAME, Effect
from ..identify import stage_bounds
from ..simulate import SolverSettings
from .derivatives import _coords, sensitivities
from .model import Model, Projector, _off_values, _sse, _with
from .noise import WHITE, NoiseModel
from .settings import DiscoverSettings
from .stats import f_test
from .ties import tie_band


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

    @property
    def statistic(self) -> float:
        """The candidate's χ²(1) evidence at this point: the larger of its profile and score-test statistics."""
        return max(self.profile_score, self.score)

    def to_dict(self) -> dict:
        return {"name": self.name, "score": self.score, "p_value": self.p_value, "probe": self.probe,
                "magnitude_linear": self.magnitude_linear, "profile_score": self.profile_score,
                "profile_best": self.profile_best, "scout_rmse_m": self.scout_rmse_m,
                "profile_score_at_nominal_start": self.profile_score_alt, "sensitivity_norm_m": self.sensitivity_norm_m,
                "perp_ratio": self.perp_ratio, "note": self.note}


def score_candidates(model: Model, theta: np.ndarray, r: np.ndarray, proj: Projector, effects: Sequence[Effect],
                     absorbed_ratio: float = 1e-4, y0: np.ndarray | None = None, noise: NoiseModel = WHITE
                     ) -> list[CandidateScore]:
    """Score test of every effect in ``effects`` (see the module docstring), sorted by score (best first).

    ``theta``: current fit (the effects' parameters at their off values); ``r``: its residual (N,);
    ``proj``: range of the free parameters' sensitivities; ``y0``: the model output at ``theta`` when the caller
    has it; ``noise``: the statistics are on the residual and sensitivities prewhitened by it (``proj`` must
    be of the whitened sensitivities). One batched simulation for all probes.
    """
    n = r.size
    r = noise.whiten(r)
    rp = proj.perp(r)
    sigma2 = float(rp @ rp) / max(n - proj.rank, 1)  # = r·r/(N − rank) at a fitted point
    if y0 is None:
        y0 = model.outputs(theta[None, :])[0]
    rows, owners = [], []
    for e in effects:
        base = _with(theta, _off_values(e))
        for pr in model.probes(e):
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
            s = noise.whiten(y - y0)
            s_norm = float(np.linalg.norm(y - y0))
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
    absorbs it in a curved way). ``rows``/``residuals``: the best two grid vectors and a spread of magnitudes
    (:func:`_spread`), and their residuals."""

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
                   cand: CandidateScore, points: int = 14, noise: NoiseModel = WHITE,
                   tier: SolverSettings | None = None) -> Profile:
    """Grid search of ``effect`` at the current fit ``theta`` (residual ``r``) — see :class:`Profile`; its grid
    simulated in ``tier`` (default: the model's Jacobian tier)."""
    base = _with(theta, _off_values(effect))
    mag = effect.magnitude
    rows, labels = [], []
    lin = {json_key(s["probe"]): s.get("magnitude_linear") for s in cand.probes}
    if effect.grid is not None:  # a threshold: magnitudes relative to what this record crosses
        grid = [({}, m) for m in effect.grid(theta, model.record.v_in, points)
                if mag.lower <= m <= mag.upper and m != mag.off]
    else:
        grid = [(pr, m) for pr in model.probes(effect)
                for m in _magnitude_grid(effect, pr, lin.get(json_key(pr)), points)]
    for pr, m in grid:
        setting = dict(pr)
        setting[mag.name] = float(m)
        rows.append(_with(base, setting))
        labels.append(setting)
    n = r.size
    rp = proj.perp(noise.whiten(r))
    ref = float(rp @ rp)
    sigma2 = ref / max(n - proj.rank, 1)
    if not rows:
        return Profile(effect.name, 0.0, {}, [], np.zeros((0, n)), [], 0, "no grid")
    # a screening grid: in the Jacobian's tier (its ~1e-9-m integration error is ~1e-3 of a σ² in the score)
    Rr = noise.whiten(model.residuals(np.array(rows), tier if tier is not None else model.jacobian))
    ok = np.all(np.isfinite(Rr), axis=1)
    perp = np.full(len(rows), np.inf)
    if ok.any():
        Pp = proj.perp(Rr[ok])
        perp[ok] = np.einsum("ij,ij->i", Pp, Pp)
    order = [int(i) for i in np.argsort(perp)[:2] if np.isfinite(perp[i])]
    if not order:
        return Profile(effect.name, 0.0, {}, [], np.zeros((0, n)), [], len(rows), "every grid simulation failed")
    order += [i for i in _spread(labels, perp, mag.name, mag.off, labels[order[0]]) if i not in order]
    score = max(0.0, (ref - perp[order[0]]) / sigma2) if sigma2 > 0 else 0.0
    return Profile(effect.name, float(score), {k: float(v) for k, v in labels[order[0]].items()},
                   [rows[i] for i in order], Rr[order], [float(perp[i]) for i in order], len(rows))


#: grid magnitudes a scout may start from besides the profile's best two, spread over the grid (see _spread)
SPREAD_STARTS = 4


def _spread(labels: Sequence[dict], perp: np.ndarray, name: str, off: float, best: Mapping[str, float]
            ) -> list[int]:
    """Up to :data:`SPREAD_STARTS` grid rows at the best row's nuisance setting, spread evenly (in rank of
    |magnitude − off|) from the smallest magnitude to the largest. The profile ranks the grid by a linearised
    re-adjustment of the free parameters, which says nothing when the effect is large beside a fit that has
    bent to stand in for it (a 0.5-mm backlash against a 127-µm nominal residual: the best-ranked magnitude
    was the smallest); the scout's start is then chosen among these by the actual SSE."""
    nuisance = {k: v for k, v in best.items() if k != name}
    same = [i for i, lab in enumerate(labels) if np.isfinite(perp[i])
            and all(lab.get(k) == v for k, v in nuisance.items())]
    same.sort(key=lambda i: abs(labels[i][name] - off))
    if len(same) <= SPREAD_STARTS:
        return same
    return [same[int(round(j))] for j in np.linspace(0, len(same) - 1, SPREAD_STARTS)]


def refit_start(model: Model, theta: np.ndarray, free: Sequence[str], proj: Projector, prof: Profile
                ) -> tuple[np.ndarray | None, dict]:
    """Start of a refit from the profile's kept grid points (its best two and a spread of magnitudes), each
    with the free parameters as they are and with the linear (minimum-norm) correction; the lowest actual SSE
    wins. Returns (start, info)."""
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
class Point:
    """A linearisation point of one iteration: a parameter vector, its residual, the range of its
    sensitivities, and the candidates' score tests and profiles there."""

    label: str
    theta: np.ndarray
    proj: Projector
    scores: dict
    profiles: dict


def assess(model: Model, label: str, theta: np.ndarray, free: Sequence[str], effects: Sequence[Effect],
           settings: DiscoverSettings, noise: NoiseModel = WHITE) -> Point | None:
    """Score test and profile of every effect in ``effects`` at ``theta`` (free parameters ``free``); None when
    ``theta`` cannot be simulated on the record."""
    y0 = model.outputs(theta[None, :])[0]
    if not np.all(np.isfinite(y0)):
        return None
    r = model.record.x_B - y0
    J = noise.whiten_columns(sensitivities(model, theta, free, settings.jac_rel_step))
    proj = Projector.of(J, settings.rank_rtol)
    scores = score_candidates(model, theta, r, proj, effects, settings.absorbed_ratio, y0, noise)
    # global screening: every candidate gets its grid (a threshold effect is silent at a small probe and a
    # periodic one may be absorbed there, yet either can explain much at a larger magnitude)
    screen = settings.screen
    profiles = {c.name: profile_effect(model, theta, r, proj, EFFECTS_BY_NAME[c.name], c, settings.grid_points,
                                       noise, screen[0] if screen else None)
                for c in scores if c.score > 0.0 or settings.scout_all}
    for c in scores:
        if c.name in profiles:
            c.profile_score = profiles[c.name].score
            c.profile_best = profiles[c.name].best
    return Point(label, theta, proj, {c.name: c for c in scores}, profiles)


def worth_refitting(sse: float, statistic: float, base_sse: float, p_base: int, k: int, n: int,
                    settings: DiscoverSettings, best_sse: float | None = None, realised: float | None = None) -> bool:
    """Beyond the ``top_k`` refits and the score leaders, is a candidate whose scout reached ``sse`` refitted?

    With a refit accepted this round (``best_sse`` its SSE, ``realised`` its F·k): yes while the scout explains
    more than it or comes within the tie band of it (no effect is accepted while a candidate that explains more
    has not been refitted; a rival the record may not tell apart), and while the candidate's score ``statistic``
    exceeds what that refit realised (the same χ² units, each under its own noise model: approximate). A scout's 8
    evaluations can show little of a smooth effect the nominal parameters first absorbed — adversarial record
    rec15: the slider's viscous friction scored 57.9 with a scout at 2.061 µm and refitted to 1.737 µm, where the
    accepted cogging torque had realised F·k = 30 at 2.062 µm. With none accepted yet: while the scout's short
    polish is significant by its own fit (the F-test on the SSEs the loop's fits minimise) against the
    ``p_base``-parameter baseline (``k`` more parameters), so that no effect is dismissed on its scout alone."""
    if best_sse is not None:
        return bool(sse < best_sse + tie_band(best_sse, n, settings.ambiguity_alpha)
                    or (realised is not None and statistic > realised))
    return bool(f_test(base_sse, sse, k, n, p_base + k)[1] < settings.alpha)


def score_leaders(scored: Sequence[CandidateScore], alpha: float, screen: float = 0.0) -> set[str]:
    """The candidates the score test ranks first: the top statistic (the larger of a candidate's profile and
    score-test χ²) and every significant one (statistic above ``screen``) within the test's own resolution of it —
    a difference below the χ²(1) critical value at ``alpha`` (0: the top one alone). To first order the record
    cannot tell such candidates apart, so none of them is dismissed on its 8-evaluation scout; statistics at the
    noise's level all lie within that band of each other and tell nothing (a backlash scores 0 at b_l = 0).
    Measured on adversarial record rec08 (a torque constant that saturates): the saturation and a cubic contact
    stiffness score 276.8 and 277.0; the stiffness's scout reached 0.998 µm, the saturation's 3.023 µm, and with the
    top statistic alone only the stiffness was refitted and accepted, where both refitted tie (the record cannot
    tell them apart)."""
    stat = {c.name: c.statistic for c in scored}
    if not stat:
        return set()
    top = max(stat.values())
    band = float(stats.chi2.isf(alpha, 1)) if alpha > 0 else 0.0
    return {nm for nm, v in stat.items() if v == top or (v >= top - band and v > screen)}
