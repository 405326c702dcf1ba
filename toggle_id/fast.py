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
polish). ``route: auto`` (the default) takes the paper's two stages when every record clamps once (the paper's
sweeps: the clamp is reached and held) and one stage when a record clamps more than once or never: on the
cycling command stage 1 sees only the samples before the first clamp (146–191 of 5001), whose best fit lies far
in the directions those samples leave open, and no whole-record polish gets back from there (docs/performance.md,
*The fast method on the cycling command*).

The starts of the one-stage route are drawn log-uniformly (``draw: log``) with the electrical time constant
L_q/R_s stratified over ``tau_e_s``: the model has two regimes that mimic each other on a record — a slow current
(τ_e ≈ 0.15 s at the assigned values: the current integrates the voltage) and a fast one (the current follows
K_i·v_in/R_s) — and the domain's uniform law (R_s uniform in 0–1 Ω, L_q in 0–0.01 H) almost never draws the slow
one, where the cycling records' optima lie. The two-stage route keeps the GA's law (uniform in the domain),
under which it reaches the floor on the paper's sweeps.

Deterministic: the starts come from the seed; the polishes are sequential and exact.
"""
from __future__ import annotations

import copy
import dataclasses
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats

from .curve import RmseCurve
from .effects import ALL_INDEX
from .errors import ConfigError
from .plant import GEOMETRY
from .polish import polish
from .problem import FitProblem, joint
from .record import Record
from .results import IdentificationResult, StageResult
from .sensitivity import batched_jacobian, identifiability_report
from .simulate import FAST, FD_TIERS, PRECISE, SolverSettings, precise_jacobian, simulations_run
from .stages import PolishSettings, joint_plan, joint_polish, stage_bounds, stage_problem, whole_record_result


@dataclass
class FastSettings:
    """Successive halving per stage: ``starts`` random starts, polished with ``first_nfev`` residual evaluations,
    the best ``keep`` fraction continued with twice the budget, down to ``finalists`` starts, each polished with
    ``final_nfev`` on the PRECISE tier. Stage 2 (two parameters) uses ``starts_stage2``. ``paths``: how many of
    stage 1's finalists (best first) go on through stage 2 and the joint polish; the lowest whole-record error
    wins. Stage 1 sees only the free motion, and when the record clamps early (the experiment sweep: 79 samples
    for 13 parameters) the best fit of those few samples is often not the start of the best whole-record fit:
    when stage 1 has fewer than ``short_samples_per_param`` samples per free parameter, ``paths_short`` paths
    are taken instead (and at least as many finalists)."""

    route: str = "auto"           # two_stage (the paper's stages, then a joint polish) | one_stage (all, whole record)
    #                               | auto: two_stage when every record clamps once, else one_stage
    draw: str = "auto"            # law of the random starts: uniform (in the domain, as the GA's first population)
    #                               | log (log-uniform over the top `draw_decades` of each domain, the electrical
    #                               time constant L_q/R_s stratified over `tau_e_s`) | auto: log on the one-stage
    #                               route, uniform on the two-stage route
    draw_decades: float = 3.0     # log draws: each positive parameter in [upper / 10**draw_decades, upper]
    tau_e_s: tuple[float, float] = (1e-3, 1.0)  # log draws: the range of L_q/R_s (s), one start per stratum of its log
    starts: int = 24              # random starts of stage 1 (or the one stage), drawn by `draw`, seeded by `seed`
    starts_stage2: int = 4        # starts of stage 2 (D, K_l); the first at the centre of the domain
    first_nfev: int = 4           # residual evaluations of each start's first polish; doubled every round
    keep: float = 0.5             # share of the starts continued after each round (successive halving)
    finalists: int = 2            # starts polished to convergence on the PRECISE tier ...
    final_nfev: int = 60          # ... with this many evaluations each
    joint_prepolish: bool = True  # the joint polish on the GA's (fast) tier first, then on PRECISE ...
    joint_final_nfev: int = 15    # ... with this many evaluations
    fd_rel_step: float = 1e-6     # relative step of the forward-difference Jacobians
    fd_tier: str = "jacobian"     # the finalists' PRECISE polishes' Jacobians: jacobian (simulate.JACOBIAN, 1e-3 step)
    #                               or precise (PRECISE at fd_rel_step); the joint polish always PRECISE
    searches: int = 6             # whole searches of the route, each from new draws, while the best whole-record
    floor_ratio: float = 1.1      # RMS error is above floor_ratio times the record's noise (from its differences,
    #                               difference_noise); the lowest error wins. 1: one search
    paths: int = 1                # stage 1's finalists carried through stage 2 and the joint polish ...
    paths_short: int = 4          # ... or this many (and as many finalists) when stage 1 has fewer than
    short_samples_per_param: float = 10.0  # this many samples per free parameter (an early clamp)

    @property
    def jacobian(self) -> tuple[SolverSettings, float]:
        """The integrator and relative step of the finalists' PRECISE polishes' Jacobians (``fd_tier``)."""
        return precise_jacobian(self.fd_tier, self.fd_rel_step)

    def validate(self) -> FastSettings:
        if self.route not in ("auto", "two_stage", "one_stage"):
            raise ConfigError(f"fast.route must be 'auto', 'two_stage' or 'one_stage', got {self.route!r}")
        if (isinstance(self.floor_ratio, bool) or not isinstance(self.floor_ratio, (int, float))
                or not self.floor_ratio >= 1.0):
            raise ConfigError(f"fast.floor_ratio must be a number >= 1, got {self.floor_ratio!r}")
        if self.draw not in DRAWS:
            raise ConfigError(f"fast.draw must be one of {', '.join(DRAWS)}, got {self.draw!r}")
        if (isinstance(self.draw_decades, bool) or not isinstance(self.draw_decades, (int, float))
                or not 0 < self.draw_decades <= 12):
            raise ConfigError(f"fast.draw_decades must be a number in (0, 12], got {self.draw_decades!r}")
        tau = tuple(self.tau_e_s) if isinstance(self.tau_e_s, (list, tuple)) else ()
        if (len(tau) != 2 or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in tau)
                or not 0 < tau[0] < tau[1] < math.inf):
            raise ConfigError(f"fast.tau_e_s must be two times in seconds, 0 < low < high, got {self.tau_e_s!r}")
        self.tau_e_s = (float(tau[0]), float(tau[1]))
        if not isinstance(self.joint_prepolish, bool):
            raise ConfigError(f"fast.joint_prepolish must be true or false, got {self.joint_prepolish!r}")
        for name in ("starts", "starts_stage2", "first_nfev", "finalists", "final_nfev", "joint_final_nfev", "paths",
                     "paths_short", "searches"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ConfigError(f"fast.{name} must be a whole number >= 1, got {v!r}")
        if not 0.0 < float(self.keep) < 1.0:
            raise ConfigError(f"fast.keep must lie in (0, 1), got {self.keep!r}")
        if not 0.0 < float(self.fd_rel_step) < 0.1:
            raise ConfigError(f"fast.fd_rel_step must lie in (0, 0.1), got {self.fd_rel_step!r}")
        if self.fd_tier not in FD_TIERS:
            raise ConfigError(f"fast.fd_tier must be one of {', '.join(FD_TIERS)}, got {self.fd_tier!r}")
        if self.paths > 1 and self.route == "one_stage":
            raise ConfigError(f"fast.paths > 1 needs route two_stage (the paths are stage 1's finalists), got "
                              f"route {self.route!r}")
        if not (isinstance(self.short_samples_per_param, (int, float)) and self.short_samples_per_param >= 0):
            raise ConfigError(f"fast.short_samples_per_param must be a number >= 0, got "
                              f"{self.short_samples_per_param!r}")
        return self


def successive_halving(problem: FitProblem, starts: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                       settings: FastSettings, tier: SolverSettings = FAST,
                       precise_jac: tuple[SolverSettings, float] | None = None) -> tuple[list[np.ndarray], dict]:
    """Multistart bounded least squares on ``problem`` from the rows of ``starts`` (see the module docstring).
    Returns the PRECISE polishes of the finalists, best first, and a record of the rounds. ``precise_jac``: the
    integrator and relative step of the PRECISE polishes' Jacobians (:attr:`FastSettings.jacobian`; default
    PRECISE at ``settings.fd_rel_step``)."""
    def resid(t: SolverSettings) -> Callable[[np.ndarray], np.ndarray]:
        return lambda x: problem.residuals(x[None, :], t)[0]

    def jac(t: SolverSettings) -> Callable[[np.ndarray], np.ndarray]:
        jt, step = precise_jac if t is PRECISE and precise_jac is not None else (t, settings.fd_rel_step)
        return lambda x: batched_jacobian(problem, x, step, jt)

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
    finals = sorted(finals, key=lambda r: r.sse)
    return [f.x for f in finals], {"rounds": rounds, "final_sse_m2": [float(f.sse) for f in finals],
                                   "nfev_final": int(finals[0].nfev), "message": str(finals[0].message)}


#: Laws of the fast method's random starts (:attr:`FastSettings.draw`).
DRAWS = ("auto", "uniform", "log")


def _draw(rng: np.random.Generator, k: int, lower: np.ndarray, upper: np.ndarray, centre: np.ndarray | None = None,
          *, law: str = "uniform", names: Sequence[str] = (), decades: float = 3.0,
          tau_e_s: tuple[float, float] = (1e-3, 1.0)) -> np.ndarray:
    """``k`` starts in the box; the first is ``centre`` if given. ``law``: ``uniform`` (the GA's initial population
    law) or ``log``: every parameter whose domain is positive log-uniform in [max(lower, upper / 10**decades),
    upper] (the others uniform), and when ``names`` has both L_q and R_s, R_s = L_q / τ_e with log τ_e stratified
    over ``tau_e_s`` (one start in each of k equal strata, in random order; clipped to R_s's domain)."""
    if law == "uniform":
        X = lower + (upper - lower) * rng.random((k, lower.size))
    else:
        u = rng.random((k, lower.size))
        pos = (lower >= 0) & (upper > 0)
        lo = np.where(pos, np.maximum(lower, upper * 10.0 ** -decades), lower)
        X = lower + (upper - lower) * u
        X[:, pos] = np.exp(np.log(lo[pos]) + (np.log(upper[pos]) - np.log(lo[pos])) * u[:, pos])
        names = list(names)
        if "L_q" in names and "R_s" in names:
            iL, iR = names.index("L_q"), names.index("R_s")
            a, b = np.log(tau_e_s[0]), np.log(tau_e_s[1])
            tau = np.exp(a + (b - a) * (rng.permutation(k) + rng.random(k)) / k)
            X[:, iR] = np.clip(X[:, iL] / tau, lower[iR], upper[iR])
    if centre is not None:
        X[0] = np.clip(centre, lower, upper)
    return X


def _lowest(sse: Sequence[float]) -> int:
    """Index of the lowest whole-record SSE; a failed fit (NaN) never wins."""
    return int(np.argmin(np.where(np.isfinite(sse), sse, np.inf)))


def difference_noise(records: Sequence[Record]) -> float:
    """The measurement noise's standard deviation (m) read off the records themselves, pooled over them: for white
    noise on a motion that is smooth at the sampling rate, the third differences of x_B are the noise's, of
    variance 20 σ²; the median absolute deviation ignores the few samples where the motion itself turns sharply
    (the clamp). Correlated noise reads lower (AR(1) ρ = 0.9: about a quarter), which only makes
    :attr:`FastSettings.searches` search more."""
    num = 0.0
    for r in records:
        s = float(stats.median_abs_deviation(np.diff(r.x_B, 3), scale="normal")) / math.sqrt(20.0)
        num += r.n * s * s
    return math.sqrt(num / sum(r.n for r in records))


def fast_route(records: Sequence[Record], route: str) -> tuple[str, list[int]]:
    """The route ``auto`` takes on ``records`` and how many times each clamps (:meth:`Record.clamp_count`): the
    paper's two stages when every record clamps exactly once, else one stage on the whole record(s). Any other
    route as given."""
    clamps = [r.clamp_count(GEOMETRY.x_B_L) for r in records]
    if route != "auto":
        return route, clamps
    return ("two_stage" if all(c == 1 for c in clamps) else "one_stage"), clamps


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
    route, clamps = fast_route(records, fast.route)
    law = fast.draw if fast.draw != "auto" else ("log" if route == "one_stage" else "uniform")
    if fast.route == "auto":
        say(f"route {route}: the record{'s' if len(records) > 1 else ''} clamp{'' if len(records) > 1 else 's'} "
            f"{', '.join(map(str, clamps))} time(s); starts drawn {law}")
    fast = dataclasses.replace(fast, route=route, draw=law)
    k_cs, plan = joint_plan(records, fast.route, theta, fixed=tuple(fixed or {}), extra_free=extra_free)
    theta = theta.copy()
    for nm in ("D", "K_l"):
        if nm not in (fixed or {}) and fast.route == "two_stage":
            lo, hi = stage_bounds([nm], bounds)
            theta[ALL_INDEX[nm]] = 0.5 * (lo[0] + hi[0])
    t_start = time.perf_counter()
    curve = curve if curve is not None else RmseCurve(records, t0=t_start)
    rng = np.random.default_rng(np.random.SeedSequence(seed))
    t_report = 0.0  # seconds of the identifiability reports: not part of the fit

    def fit_stage(name: str, free: tuple[str, ...], windows, theta: np.ndarray, rng: np.random.Generator
                  ) -> tuple[StageResult, list[np.ndarray], FitProblem]:
        """One stage's successive halving from ``theta``: its result (the best finalist), all finalists (extended
        vectors, best first) and the stage's problem."""
        nonlocal t_report
        problem = joint([stage_problem(r, name, free, w, theta, settings, i_q_weight)
                         for r, w in zip(records, windows)])
        lo, hi = stage_bounds(list(free), bounds)
        k = fast.starts_stage2 if name == "stage2" else fast.starts
        say(f"{name}: {k} starts, {len(free)} parameters")
        t0, n0 = time.perf_counter(), simulations_run()
        starts = _draw(rng, k, lo, hi, centre=problem.x0() if name == "stage2" else None,
                       law="uniform" if name == "stage2" else fast.draw, names=free, decades=fast.draw_decades,
                       tau_e_s=fast.tau_e_s)
        halving = fast if name != plan[0][0] else dataclasses.replace(fast, finalists=max(fast.finalists, n_paths))
        finals, info = successive_halving(problem, starts, lo, hi, halving, settings, fast.jacobian)
        x = finals[0]
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
        say(f"{name}: rms {st.rmse_m * 1e6:.4g} µm on its window ({st.seconds_polish:.1f} s)")
        return st, [problem.thetas(f[None, :])[0] for f in finals], problem

    spent = curve.simulations

    def emit(st: StageResult) -> None:
        """A stage of the result: on the fitness curve and to ``on_stage``."""
        nonlocal spent
        spent += st.n_simulations
        curve.add(st.name, spent, theta=st.theta)
        if on_stage is not None:
            on_stage(st)

    def finish(theta: np.ndarray, rng: np.random.Generator, now: bool) -> list[StageResult]:
        """The stages after the first (stage 2, then the joint polish) from stage 1's ``theta``; ``now``: emit each
        as it ends (a single path)."""
        nonlocal t_report
        stages = []
        for name, free, windows in plan[1:]:
            st, _, _ = fit_stage(name, free, windows, theta, rng)
            theta = st.theta.copy()
            stages.append(st)
            if now:
                emit(st)
        if fast.route == "two_stage":
            t_id = time.perf_counter()
            st = joint_polish(records, plan, theta, settings, i_q_weight, bounds, polish_settings, identifiability,
                              noise_var, pre_tier=settings if fast.joint_prepolish else None,
                              final_nfev=fast.joint_final_nfev if fast.joint_prepolish else None)
            t_report += time.perf_counter() - t_id - st.seconds_polish
            stages.append(st)
            if now:
                emit(st)
        return stages

    def search(rng: np.random.Generator, live: bool) -> list[StageResult]:
        """One whole search of the route from draws of ``rng``: its stages; ``live``: emit each as it ends."""
        nonlocal t_report
        first, finals, problem1 = fit_stage(name, free, windows, theta, rng)
        if n_paths == 1:
            if live:
                emit(first)
            stages = [first, *finish(finals[0], rng, now=live)]
        else:  # every path draws stage 2's starts from the same stream; the lowest whole-record error wins
            paths = []
            for j in range(min(n_paths, len(finals))):
                say(f"path {j + 1}: from stage 1's finalist {j + 1}")
                paths.append(finish(finals[j], copy.deepcopy(rng), now=False))
            whole = [p[-1].sse for p in paths]
            chosen = _lowest(whole)
            say(f"path {chosen + 1} chosen: its error on the whole record is the lowest")
            if chosen > 0:  # stage 1's point is that finalist's
                sse = first.polish["multistart"]["final_sse_m2"][chosen]
                first.theta, first.x = finals[chosen].copy(), finals[chosen][[ALL_INDEX[n] for n in first.free]].copy()
                first.sse, first.fitness = sse, 1.0 / sse if sse > 0 else float("inf")
                if identifiability:
                    t_id = time.perf_counter()
                    first.identifiability = identifiability_report(problem1, first.x, noise_var)
                    t_report += time.perf_counter() - t_id
            # the paths not chosen were simulated too: the last stage (where the choice is made) counts them
            others = sum(st.n_simulations for j, p in enumerate(paths) if j != chosen for st in p)
            paths[chosen][-1].n_simulations += others
            paths[chosen][-1].polish["paths"] = {"whole_record_sse_m2": [float(v) for v in whole], "chosen": chosen + 1,
                                                 "n_simulations_other_paths": int(others)}
            stages = [first, *paths[chosen]]
            if live:
                for st in stages:
                    emit(st)
        return stages

    name, free, windows = plan[0]
    n_paths = fast.paths
    if fast.route == "two_stage":  # an early clamp: stage 1 has few samples per parameter to choose its start on
        n_stage1 = sum(hi - lo for lo, hi in windows)
        if n_stage1 < fast.short_samples_per_param * len(free):
            n_paths = max(n_paths, fast.paths_short)
            say(f"stage 1 has {n_stage1} samples for {len(free)} parameters: {n_paths} paths")
    n_all = sum(r.n for r in records)
    sigma = difference_noise(records)
    tried = [search(rng, live=True)]

    def best_rmse() -> float:
        return math.sqrt(min(t[-1].sse for t in tried) / n_all)

    while len(tried) < fast.searches and best_rmse() > fast.floor_ratio * sigma:
        say(f"search {len(tried) + 1}: the best so far, {best_rmse() * 1e6:.4g} µm, is above "
            f"{fast.floor_ratio:g} times the record's noise ({sigma * 1e6:.3g} µm, from its differences)")
        tried.append(search(rng, live=False))
    whole = [t[-1].sse for t in tried]
    chosen = _lowest(whole)
    stages = tried[chosen]
    if len(tried) > 1:
        say(f"search {chosen + 1} of {len(tried)} chosen: its error on the whole record is the lowest")
        # the searches not chosen were simulated too: the last stage counts them (the first is on the curve already,
        # so a later winner's points come after every search)
        others = sum(st.n_simulations for j, t in enumerate(tried) if j != chosen for st in t)
        if chosen > 0:
            first_sims = sum(st.n_simulations for st in tried[0])
            stages[-1].n_simulations += others - first_sims
            for st in stages:
                emit(st)
            stages[-1].n_simulations += first_sims
        else:
            stages[-1].n_simulations += others
        stages[-1].polish["searches"] = {"whole_record_sse_m2": [float(v) for v in whole], "chosen": chosen + 1,
                                         "noise_m": float(sigma), "floor_ratio": float(fast.floor_ratio)}
    theta = stages[-1].theta.copy()
    extra = {"seconds_fit": time.perf_counter() - t_start - t_report, "seconds_reports": t_report,
             "fast_settings": vars(fast)}
    return whole_record_result("fast", records, k_cs, theta, stages, time.perf_counter() - t_start, curve.points,
                               extra)
