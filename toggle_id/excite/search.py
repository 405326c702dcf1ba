"""The seeded search for the input that tells the rivals apart: random candidates of every family, then a local
refinement of the best few (bounded Nelder–Mead in the family's unit cube), every candidate scored by the
first-order separations and the resolved singular values; the best few verified by full refits.

A candidate's *score* is the smallest share of its goals it meets: for each effect rival its separation / σ over
``separation_target``; for the parameters the gain of the k-th resolved singular value over the record's, over
``sv_gain_target`` (a candidate whose numerical rank is higher than the record's meets that goal); the mean share
(× 0.01) breaks ties. A rejected
candidate (failed simulation, not into the clamp and back) scores −inf and keeps its status.
"""
from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize

from ..data import X_B_L
from ..record import Record
from .inputs import Candidate, candidate_record, clamp_check, dimension
from .score import Rival, linear_separation, refit_separation, responses, spectrum, sv_at
from .settings import ExciteSettings


@dataclass
class Evaluation:
    """What one candidate input scored. Separations in m (RMS); ``refit`` only for verified candidates."""

    index: int
    candidate: Candidate
    status: str
    score: float = -np.inf
    linear_m: dict[str, float] = field(default_factory=dict)
    refit_m: dict[str, float] | None = None
    spectrum: dict | None = None
    sv_gain: float = float("nan")
    final_score: float = -np.inf
    seconds: float = 0.0
    curves: dict = field(default_factory=dict, repr=False)  # rival → (y_A, y_B refitted), verified ones only

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    def to_dict(self, sigma: float) -> dict:
        out = {"index": self.index, **self.candidate.to_dict(), "status": self.status,
               "score": _num(self.score), "final_score": _num(self.final_score), "seconds": self.seconds,
               "linear_separation_um": {k: _num(1e6 * v) for k, v in self.linear_m.items()},
               "linear_separation_sigma": {k: _num(v / sigma) for k, v in self.linear_m.items()},
               "sv_gain": _num(self.sv_gain)}
        if self.refit_m is not None:
            out["predicted_separation_um"] = {k: _num(1e6 * v) for k, v in self.refit_m.items()}
            out["predicted_separation_sigma"] = {k: _num(v / sigma) for k, v in self.refit_m.items()}
        if self.spectrum is not None:
            out["rank"] = self.spectrum.get("rank")
            out["singular_values"] = self.spectrum.get("singular_values")
        return out


def _num(v: float) -> float | None:
    v = float(v)
    return v if np.isfinite(v) else None


def resolved_sv(spec: dict | None, k: int) -> float:
    """The k-th singular value if the Jacobian resolves it (k ≤ numerical rank), else 0."""
    if not spec or "error" in spec:
        return 0.0
    return sv_at(spec, k) if spec.get("rank", 0) >= k else 0.0


class Scorer:
    """Scores candidate inputs against the rivals of one record (see the module docstring)."""

    def __init__(self, settings: ExciteSettings, rivals: Sequence[Rival], theta: np.ndarray, sigma: float,
                 x_B0: float, baseline: dict | None) -> None:
        self.s = settings
        self.rivals = list(rivals)
        self.theta = theta
        self.sigma = sigma
        self.x_B0 = x_B0
        self.baseline = baseline  # the record's spectrum (parameters rival), None when not scored
        self.base_sv = sv_at(baseline, settings.sv_index) if baseline else float("nan")
        self.count = 0

    def record_of(self, c: Candidate) -> Record:
        return candidate_record(c, self.s.v_max, self.s.duration, self.s.rate_hz, self.x_B0)

    def goals(self, ev: Evaluation, separations: dict[str, float]) -> float:
        shares = [separations[r.name] / self.sigma / self.s.separation_target for r in self.rivals]
        if self.baseline is not None:
            gain = ev.sv_gain / self.s.sv_gain_target if np.isfinite(ev.sv_gain) else 0.0
            if ev.spectrum and ev.spectrum.get("rank", 0) > self.baseline.get("rank", 0):
                gain = max(gain, 1.0)
            shares.append(gain)
        shares = [v if np.isfinite(v) else -np.inf for v in shares]
        if not shares:
            return 0.0
        # the smallest share decides; the mean breaks ties (e.g. a goal no candidate meets at all)
        return float(min(shares) + 0.01 * np.mean(shares))

    def evaluate(self, c: Candidate) -> Evaluation:
        t0 = time.perf_counter()
        ev = Evaluation(self.count, c, "ok")
        self.count += 1
        rec = self.record_of(c)
        thetas = np.vstack([self.theta] + [v for r in self.rivals for v in (r.theta_a, r.theta_b)])
        y, status = responses(rec, thetas)
        for row, st in zip(y, status):
            reason = clamp_check(row, X_B_L, x_B_min=self.s.x_B_min, clamp_margin=self.s.clamp_margin,
                                 min_clamp_samples=self.s.min_clamp_samples, min_exits=self.s.min_exits)
            if reason != "ok":
                ev.status = reason if st == "ok" else f"simulation failed ({st})"
                break
        if ev.ok:
            for j, r in enumerate(self.rivals):
                ev.linear_m[r.name] = linear_separation(rec, r, y[1 + 2 * j], y[2 + 2 * j], self.s.jac_rel_step)
            if self.baseline is not None:
                ev.spectrum = spectrum(rec, self.theta, self.sigma)
                ev.sv_gain = resolved_sv(ev.spectrum, self.s.sv_index) / self.base_sv
            ev.score = self.goals(ev, ev.linear_m)
        ev.seconds = time.perf_counter() - t0
        return ev

    def verify(self, ev: Evaluation) -> Evaluation:
        """Full refits of every effect rival on ``ev``'s input; its final score from the refit separations."""
        rec = self.record_of(ev.candidate)
        ev.refit_m = {}
        for r in self.rivals:
            y, _ = responses(rec, r.theta_a)
            out = refit_separation(rec, r, y[0], max_nfev=self.s.refit_nfev, rounds=self.s.refit_rounds,
                                   fd_rel_step=self.s.fd_rel_step)
            ev.refit_m[r.name] = out["separation_m"]
            ev.curves[r.name] = (y[0], out["y_b_refit"])
        ev.final_score = self.goals(ev, ev.refit_m)
        return ev


def search(scorer: Scorer, say: Callable[[str], None] = lambda m: None) -> list[Evaluation]:
    """Random candidates of every family (until ``n_random`` are accepted, at most ``random_tries`` times as many
    tries: a family most of whose inputs leave the stroke still gets its starting points), then a local refinement
    of the best candidate of each of the ``refine_starts`` best families: bounded Nelder–Mead in the family's unit
    cube (:func:`_refine`), ``n_refine`` evaluations in all. Seeded by ``settings.seed``: the same seed gives the
    same candidates and scores."""
    s = scorer.s
    rng = np.random.default_rng(np.random.SeedSequence([s.seed, 16]))
    evals: list[Evaluation] = []

    def run(c: Candidate, phase: str) -> Evaluation:
        ev = scorer.evaluate(c)
        evals.append(ev)
        seps = ", ".join(f"{k.split(' ')[0]} {1e6 * v:.3g} µm" for k, v in ev.linear_m.items())
        extra = (f"; s{s.sv_index} ×{ev.sv_gain:.3g}, rank {ev.spectrum.get('rank')}" if ev.spectrum else "")
        say(f"candidate {ev.index + 1} ({phase} {c.family}): " +
            (f"score {ev.score:.3g} (first-order {seps}{extra})" if ev.ok else f"rejected: {ev.status}") +
            f" [{ev.seconds:.1f} s]")
        return ev

    for fam in s.families:
        valid = 0
        for _ in range(s.random_tries * s.n_random):
            ev = run(Candidate(fam, tuple(float(x) for x in rng.random(dimension(fam))), int(rng.integers(2 ** 31))),
                     "random")
            valid += ev.ok
            if valid >= s.n_random:
                break
    best_of: dict[str, Evaluation] = {}
    for e in evals:
        if e.ok and (e.candidate.family not in best_of or e.score > best_of[e.candidate.family].score):
            best_of[e.candidate.family] = e
    starts = sorted(best_of.values(), key=lambda e: -e.score)[:s.refine_starts]
    for k, start in enumerate(starts):
        budget = s.n_refine // len(starts) + (1 if k < s.n_refine % len(starts) else 0)
        _refine(start, budget, s.refine_radius, lambda c: run(c, "refine"))
    return evals


class _Spent(Exception):
    """The refinement's budget of evaluations is spent."""


def _refine(start: Evaluation, budget: int, radius: float, run: Callable[[Candidate], Evaluation]) -> None:
    """Bounded Nelder–Mead (scipy) on ``start``'s family's unit cube, maximising the score, at most ``budget``
    evaluations; the first simplex is ``start`` and a step of ``radius`` along each axis (inwards at a bound).
    A rejected candidate counts as worse than any accepted one; no candidate is scored twice. Deterministic."""
    if budget < 1:
        return
    u0 = np.array(start.candidate.u)
    simplex = [u0]
    for i in range(len(u0)):
        u = u0.copy()
        u[i] = u[i] + radius if u[i] + radius <= 1.0 else u[i] - radius
        simplex.append(u)
    seen = {tuple(u0): -start.score}  # candidates already scored (the start; a point the simplex comes back to)
    left = budget

    def loss(u: np.ndarray) -> float:
        nonlocal left
        key = tuple(float(x) for x in np.clip(u, 0.0, 1.0))
        if key not in seen:
            if left <= 0:
                raise _Spent
            left -= 1
            ev = run(Candidate(start.candidate.family, key, start.candidate.seed))
            seen[key] = -ev.score if ev.ok and np.isfinite(ev.score) else 1.0
        return seen[key]

    try:
        minimize(loss, u0, method="Nelder-Mead", bounds=[(0.0, 1.0)] * len(u0),
                 # the budget of new candidates (_Spent) ends it, not scipy's count, which includes repeated points
                 options={"initial_simplex": np.array(simplex), "maxfev": 100 * (budget + len(u0)), "xatol": 1e-3,
                          "fatol": 1e-4})
    except _Spent:
        pass


def verify_best(scorer: Scorer, evals: Sequence[Evaluation], say: Callable[[str], None] = lambda m: None
                ) -> list[Evaluation]:
    """Verify by full refits the ``refit_top`` best candidates and, per rival, its best first-order candidate;
    returns the verified ones, best final score first."""
    valid = sorted((e for e in evals if e.ok), key=lambda e: -e.score)
    chosen = valid[:scorer.s.refit_top]
    for r in scorer.rivals:
        top = max(valid, key=lambda e: e.linear_m.get(r.name, -np.inf), default=None)
        if top is not None and top not in chosen:
            chosen.append(top)
    if not scorer.rivals:
        for ev in chosen:
            ev.final_score = ev.score
        return chosen
    for ev in chosen:
        t0 = time.perf_counter()
        scorer.verify(ev)
        say(f"refit candidate {ev.index + 1} ({ev.candidate.family}): " + ", ".join(
            f"{k} {1e6 * v:.3g} µm = {v / scorer.sigma:.3g} σ" for k, v in ev.refit_m.items()) +
            f" [{time.perf_counter() - t0:.1f} s]")
    return sorted(chosen, key=lambda e: -e.final_score)
