"""The fast identification method: the paper's two-stage structure with multistart least squares instead of the GA.

Stage 1 fits the free-motion parameters on the samples before the clamping instant (D and K_l at the centres of
their domains, as the paper's stage 1); stage 2 fits D and K_l on the samples from the clamping instant on; a
joint polish of all of them on the whole record follows (as :func:`toggle_id.identify.identify` does after its
GA stages). Each stage's search is *successive halving* over random starts drawn uniformly in the feasible
domain (seeded): every start gets a short bounded least-squares polish (trust region in the log coordinates of
:mod:`toggle_id.polish`, forward-difference Jacobian with all columns in one batched simulation), the better half
goes on with a doubled budget, and so on until a few remain; the best is polished to convergence with the PRECISE
tier. Starts that stall above the others are abandoned early, which is where the time goes otherwise: most
starts of the free-motion problem end in a local minimum (see the README's method table).

``route: one_stage`` runs the same search on all parameters and the whole record at once (no stages, no joint
polish).

Deterministic: the starts come from the seed; the polishes are sequential and exact.
"""
from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from .curve import RmseCurve
from .effects import ALL_INDEX
from .errors import ConfigError
from .polish import polish
from .problem import FitProblem, joint
from .record import Record
from .results import IdentificationResult, StageResult
from .sensitivity import batched_jacobian, identifiability_report
from .simulate import FAST, PRECISE, SolverSettings, simulations_run
from .stages import PolishSettings, joint_plan, joint_polish, stage_bounds, stage_problem, whole_record_result


@dataclass
class FastSettings:
    """Successive halving per stage: ``starts`` random starts, polished with ``first_nfev`` residual evaluations,
    the best ``keep`` fraction continued with twice the budget, down to ``finalists`` starts; the best one
    polished with ``final_nfev`` on the PRECISE tier. Stage 2 (two parameters) uses ``starts_stage2``."""

    route: str = "two_stage"
    starts: int = 24
    starts_stage2: int = 4
    first_nfev: int = 4
    keep: float = 0.5
    finalists: int = 2
    final_nfev: int = 60
    joint_prepolish: bool = True
    joint_final_nfev: int = 15
    fd_rel_step: float = 1e-6

    def validate(self) -> FastSettings:
        if self.route not in ("two_stage", "one_stage"):
            raise ConfigError(f"fast.route must be 'two_stage' or 'one_stage', got {self.route!r}")
        if not isinstance(self.joint_prepolish, bool):
            raise ConfigError(f"fast.joint_prepolish must be true or false, got {self.joint_prepolish!r}")
        for name in ("starts", "starts_stage2", "first_nfev", "finalists", "final_nfev", "joint_final_nfev"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ConfigError(f"fast.{name} must be a whole number >= 1, got {v!r}")
        if not 0.0 < float(self.keep) < 1.0:
            raise ConfigError(f"fast.keep must lie in (0, 1), got {self.keep!r}")
        if not 0.0 < float(self.fd_rel_step) < 0.1:
            raise ConfigError(f"fast.fd_rel_step must lie in (0, 0.1), got {self.fd_rel_step!r}")
        return self


def successive_halving(problem: FitProblem, starts: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                       settings: FastSettings, tier: SolverSettings = FAST) -> tuple[np.ndarray, dict]:
    """Multistart bounded least squares on ``problem`` from the rows of ``starts`` (see the module docstring).
    Returns the best point (the PRECISE polish of the best finalist) and a record of the rounds."""
    def resid(t: SolverSettings) -> Callable[[np.ndarray], np.ndarray]:
        return lambda x: problem.residuals(x[None, :], t)[0]

    def jac(t: SolverSettings) -> Callable[[np.ndarray], np.ndarray]:
        return lambda x: batched_jacobian(problem, x, settings.fd_rel_step, t)

    alive = [np.clip(np.asarray(s, float), lower, upper) for s in starts]
    budget = settings.first_nfev
    rounds = []
    while True:
        results = [polish(resid(tier), x, lower, upper, jac_fn=jac(tier), max_nfev=budget) for x in alive]
        order = np.argsort([r.sse for r in results])
        rounds.append({"starts": len(alive), "max_nfev": budget,
                       "sse_m2": [float(results[i].sse) for i in order]})
        if len(alive) <= settings.finalists:
            break
        n_keep = max(settings.finalists, math.ceil(len(alive) * settings.keep))
        alive = [results[i].x for i in order[:n_keep]]
        budget *= 2
    finals = [polish(resid(PRECISE), results[i].x, lower, upper, jac_fn=jac(PRECISE), max_nfev=settings.final_nfev)
              for i in order[:settings.finalists]]
    best = min(finals, key=lambda r: r.sse)
    return best.x, {"rounds": rounds, "final_sse_m2": [float(f.sse) for f in finals], "nfev_final": int(best.nfev),
                    "message": str(best.message)}


def _draw(rng: np.random.Generator, k: int, lower: np.ndarray, upper: np.ndarray, centre: np.ndarray | None = None
          ) -> np.ndarray:
    """``k`` points uniform in the box (the GA's initial population law); the first is ``centre`` if given."""
    X = lower + (upper - lower) * rng.random((k, lower.size))
    if centre is not None:
        X[0] = np.clip(centre, lower, upper)
    return X


def identify_fast(records: Sequence[Record], theta: np.ndarray, *, seed: int = 0,
                  fixed: Mapping[str, float] | None = None, bounds: Mapping[str, Sequence[float]] | None = None,
                  extra_free: Sequence[str] = (), settings: SolverSettings = FAST, i_q_weight: float = 0.0,
                  fast: FastSettings | None = None, polish_settings: PolishSettings | None = None,
                  identifiability: bool = True, noise_var: float | None = None, curve: RmseCurve | None = None,
                  on_stage: Callable[[StageResult], None] | None = None,
                  progress: Callable[[str], None] | None = None) -> IdentificationResult:
    """The fast method on ``records`` from the extended vector ``theta`` (values of the parameters that are not
    free); see the module docstring. Same result type as :func:`toggle_id.identify.identify`, method ``fast``."""
    fast = (fast or FastSettings()).validate()
    polish_settings = polish_settings or PolishSettings()
    say = progress or (lambda msg: None)
    k_cs, plan = joint_plan(records, fast.route, theta, fixed=tuple(fixed or {}), extra_free=extra_free)
    theta = theta.copy()
    for nm in ("D", "K_l"):
        if nm not in (fixed or {}) and fast.route == "two_stage":
            lo, hi = stage_bounds([nm], bounds)
            theta[ALL_INDEX[nm]] = 0.5 * (lo[0] + hi[0])
    t_start = time.perf_counter()
    curve = curve if curve is not None else RmseCurve(records, t0=t_start)
    rng = np.random.default_rng(np.random.SeedSequence(seed))
    stages: list[StageResult] = []
    spent = curve.simulations
    t_report = 0.0  # identifiability reports: not part of the fit
    for name, free, windows in plan:
        problem = joint([stage_problem(r, name, free, w, theta, settings, i_q_weight)
                         for r, w in zip(records, windows)])
        lo, hi = stage_bounds(list(free), bounds)
        k = fast.starts_stage2 if name == "stage2" else fast.starts
        say(f"{name}: {k} starts, {len(free)} parameters")
        t0, n0 = time.perf_counter(), simulations_run()
        starts = _draw(rng, k, lo, hi, centre=problem.x0() if name == "stage2" else None)
        x, info = successive_halving(problem, starts, lo, hi, fast, settings)
        sse = float(problem.sse(x[None, :], PRECISE)[0])
        st = StageResult(name=name, free=free, x=x, theta=problem.thetas(x[None, :])[0], window=windows[0],
                         fitness_ga=float("nan"), fitness=1.0 / sse if sse > 0 else float("inf"), sse=sse,
                         history=[], generations=0, converged_generation=0, n_evaluations=0, seconds_ga=0.0,
                         seconds_polish=time.perf_counter() - t0, polish={"multistart": info},
                         windows=windows if len(records) > 1 else None, n_simulations=simulations_run() - n0)
        if identifiability:
            t_id = time.perf_counter()
            st.identifiability = identifiability_report(problem, x, noise_var)
            t_report += time.perf_counter() - t_id
        spent += st.n_simulations
        curve.add(name, spent, theta=st.theta)
        theta = st.theta.copy()
        stages.append(st)
        if on_stage is not None:
            on_stage(st)
        say(f"{name}: rms {st.rmse_m * 1e6:.4g} µm on its window ({st.seconds_polish:.1f} s)")
    if fast.route == "two_stage":
        t_id = time.perf_counter()
        st = joint_polish(records, plan, theta, settings, i_q_weight, bounds, polish_settings, identifiability,
                          noise_var, pre_tier=settings if fast.joint_prepolish else None,
                          final_nfev=fast.joint_final_nfev if fast.joint_prepolish else None)
        t_report += time.perf_counter() - t_id - st.seconds_polish
        theta = st.theta.copy()
        spent += st.n_simulations
        curve.add(st.name, spent, theta=theta)
        stages.append(st)
        if on_stage is not None:
            on_stage(st)
    extra = {"seconds_fit": time.perf_counter() - t_start - t_report, "seconds_reports": t_report,
             "fast_settings": vars(fast)}
    return whole_record_result("fast", records, k_cs, theta, stages, time.perf_counter() - t_start, curve.points,
                               extra)
