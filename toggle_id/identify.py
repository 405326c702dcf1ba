"""Identification pipelines: one-stage and two-stage RGA (docs/model.md §7), local polish, identifiability.

The pipeline knows the plant only through :class:`toggle_id.problem.FitProblem`; the GA knows nothing of the
plant; evaluators know nothing of either. Everything here takes plain arguments (the jobs translate Hydra
configs into them).

Two-stage, as the paper: stage 1 fits the 13 free-motion parameters on the samples before the measured
clamping instant, with D and K_l at the centres of their domains; stage 2 fits D and K_l on the samples from
that instant on, the 13 held at their stage-1 values. Stage 2 does not re-simulate the shared free motion: one
simulation finds the model's first contact, and every individual restarts from that state.

Several records (multi-experiment): one parameter vector for all of them. Each stage's problem is then a
:class:`toggle_id.problem.JointProblem` of the records' stage problems — every record with its own clamping
instant, windows and stage-2 restart — whose fitness is 1/(sum of the records' ΣE²); the polish, the final
joint polish and the identifiability report work on the stacked residuals.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from . import params as P
from .checkpoint import load_checkpoint, save_checkpoint
from .curve import CurvePoint, RmseCurve
from .effects import ALL_INDEX, ALL_NAMES, effect_bounds
from .errors import CheckpointError, ConfigError
from .ga import RGA, GAConfig, join_state, split_state
from .identifiability import analyze
from .plant import GEOMETRY
from .polish import polish_many
from .problem import FitProblem, JointProblem, free_indices, joint
from .record import Record
from .simulate import FAST, PRECISE, STATUS_OK, SolverSettings, extend, simulate, simulations_run

METHODS = ("one_stage", "two_stage", "fast")  # fast: multistart least squares in the two stages (toggle_id/fast.py)


@dataclass
class PolishSettings:
    """Local least-squares refinement after the GA (kept only if it improves the fit)."""

    enabled: bool = True
    n_starts: int = 3          # the GA's best distinct individuals to start from
    max_nfev: int = 60         # residual evaluations per start (finite-difference Jacobians counted apart)
    fd_rel_step: float = 1e-6  # relative finite-difference step of the Jacobian (PRECISE simulations)
    final_joint: bool = True   # two-stage: finish with a polish of all free parameters on the whole record


@dataclass
class StageResult:
    """What one GA stage found: free names and values, fitness 1/ΣE², history, timing, diagnostics."""

    name: str
    free: tuple[str, ...]
    x: np.ndarray
    theta: np.ndarray
    window: tuple[int, int]
    fitness_ga: float
    fitness: float
    sse: float
    history: list[float]
    generations: int
    converged_generation: int
    n_evaluations: int
    seconds_ga: float
    seconds_polish: float = 0.0
    polish: dict | None = None
    identifiability: dict | None = None
    windows: tuple[tuple[int, int], ...] | None = None  # joint fits: every record's window (``window``: the first's)
    n_simulations: int = 0  # simulations the stage spent: GA individuals, polish residuals and Jacobian columns

    @property
    def n_samples(self) -> int:
        return sum(k1 - k0 for k0, k1 in (self.windows or (self.window,)))

    @property
    def rmse_m(self) -> float:
        return float(np.sqrt(self.sse / max(1, self.n_samples)))

    def to_dict(self) -> dict:
        windows = {} if self.windows is None else {"windows": [list(w) for w in self.windows]}
        return {"name": self.name, "free": list(self.free), "params": dict(zip(self.free, map(float, self.x))),
                "window": list(self.window), **windows, "fitness_ga": self.fitness_ga, "fitness": self.fitness,
                "sse_m2": self.sse, "rmse_m": self.rmse_m, "generations": self.generations,
                "converged_generation": self.converged_generation, "n_evaluations": self.n_evaluations,
                "seconds_ga": self.seconds_ga, "seconds_polish": self.seconds_polish,
                "seconds": self.seconds_ga + self.seconds_polish, "fitness_history": list(self.history),
                "n_simulations": self.n_simulations, "polish": self.polish, "identifiability": self.identifiability}


@dataclass
class IdentificationResult:
    """The identified extended parameter vector, per-stage results and the whole-record fit."""

    method: str
    theta: np.ndarray
    stages: list[StageResult]
    fitness: float
    sse: float
    n_samples: int
    seconds: float
    clamp_index: int
    extra: dict = field(default_factory=dict)
    curve: list[CurvePoint] = field(default_factory=list)  # best whole-record RMS vs simulations (toggle_id.curve)

    @property
    def params(self) -> dict[str, float]:
        return {n: float(self.theta[i]) for i, n in enumerate(P.PARAM_NAMES)}

    @property
    def rmse_m(self) -> float:
        return float(np.sqrt(self.sse / self.n_samples))

    @property
    def n_simulations(self) -> int:
        """Simulations the whole identification spent (its stages' sum)."""
        return sum(s.n_simulations for s in self.stages)

    def to_dict(self) -> dict:
        extra = {n: float(self.theta[ALL_INDEX[n]]) for n in ALL_NAMES[P.N_PARAMS:]}
        return {"method": self.method, "params": self.params, "effect_params": extra,
                "fitness": self.fitness, "sse_m2": self.sse, "rmse_m": self.rmse_m, "rmse_um": 1e6 * self.rmse_m,
                "n_samples": self.n_samples, "n_simulations": self.n_simulations,
                "curve": [p.to_dict() for p in self.curve],
                "clamp_index": self.clamp_index, "seconds_total": self.seconds,
                "seconds_per_stage": {s.name: s.seconds_ga + s.seconds_polish for s in self.stages},
                "stages": [s.to_dict() for s in self.stages], **self.extra}


def converged_generation(history: Sequence[float], rel: float = 0.01) -> int:
    """First generation (1-based) whose best fitness is within ``rel`` of the final best."""
    h = np.asarray(history, dtype=float)
    if h.size == 0:
        return 0
    return int(np.argmax(h >= (1.0 - rel) * h[-1])) + 1


def stage_bounds(names: Sequence[str], overrides: Mapping[str, Sequence[float]] | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Feasible domains of physical and effect parameters, with per-name ``[low, high]`` overrides."""
    overrides = dict(overrides or {})
    unknown = [n for n in overrides if n not in ALL_INDEX]
    if unknown:
        raise ConfigError(f"bounds given for unknown parameter(s) {', '.join(unknown)}")
    phys = [n for n in names if n in P.INDEX]
    extra = [n for n in names if n not in P.INDEX]
    lo, hi = np.empty(len(names)), np.empty(len(names))
    if phys:
        l1, h1 = P.bounds(phys, {k: v for k, v in overrides.items() if k in P.INDEX})
        for k, n in enumerate(phys):
            lo[names.index(n)], hi[names.index(n)] = l1[k], h1[k]
    if extra:
        l2, h2 = effect_bounds(extra)
        for k, n in enumerate(extra):
            low, high = overrides.get(n, (l2[k], h2[k]))
            lo[names.index(n)], hi[names.index(n)] = float(low), float(high)
    for n, a, b in zip(names, lo, hi):
        if not (np.isfinite(a) and np.isfinite(b)) or not a < b:
            raise ConfigError(f"bounds of {n} are inverted, empty or not finite: [{a}, {b}]")
    return lo, hi


class Checkpointer:
    """GA state (population, fitness, RNG, generation, best, stage) saved every ``every`` generations, with the
    results of the stages already finished; written atomically (JSON + npz, no pickle)."""

    def __init__(self, directory: str | Path, every: int = 5, meta: Mapping[str, Any] | None = None) -> None:
        if int(every) < 1:
            raise ConfigError(f"checkpoint.every must be >= 1, got {every}")
        self.prefix = Path(directory) / "checkpoint"
        self.every = int(every)
        self.meta = dict(meta or {})  # saved along (e.g. the job's identity, toggle_id.jobdir)

    def exists(self) -> bool:
        return self.prefix.with_suffix(".json").exists()

    def save(self, stage: str, ga: RGA, done: list[dict]) -> None:
        arrays, meta = split_state(ga.state_dict())
        save_checkpoint(self.prefix, arrays, {**self.meta, "stage": stage, "ga": meta, "done": done})

    def load(self) -> tuple[str, dict, list[dict]]:
        arrays, meta = load_checkpoint(self.prefix)
        try:
            return str(meta["stage"]), join_state(arrays, meta["ga"]), list(meta["done"])
        except (KeyError, TypeError) as err:
            raise CheckpointError(f"checkpoint {self.prefix} lacks {err}") from err


def _noop_progress(total: int, desc: str):
    class _P:
        def update(self, best: float, extra: str | None = None) -> None: ...
        def close(self) -> None: ...
    return _P()


def run_ga_stage(name: str, problem: FitProblem | JointProblem, ga_config: GAConfig, seed: int,
                 make_evaluator: Callable[[Any], Any], *, bounds: Mapping[str, Sequence[float]] | None = None,
                 progress: Callable[[int, str], Any] = _noop_progress, checkpointer: Checkpointer | None = None,
                 resume_state: dict | None = None, done: list[dict] | None = None,
                 on_generation: Callable[[str, RGA], None] | None = None
                 ) -> tuple[RGA, float, np.ndarray | None]:
    """Run the GA on ``problem`` (resuming from ``resume_state`` if given); return the GA, its wall time and
    the last evaluated population (starts for the polish)."""
    lo, hi = stage_bounds(list(problem.free), bounds)
    ga = RGA.from_state(resume_state) if resume_state is not None else RGA(lo, hi, ga_config, seed=seed)
    if resume_state is not None and (not np.array_equal(ga.lower, lo) or not np.array_equal(ga.upper, hi)):
        raise CheckpointError(f"checkpoint of stage {name} was made with other bounds")
    bar = progress(ga_config.generations, name)
    for best in ga.history:
        bar.update(best)
    t0 = time.perf_counter()
    X = None
    with make_evaluator(problem) as evaluator:
        while not ga.done:
            X = ga.ask()
            ga.tell(evaluator.evaluate(X))
            bar.update(ga.best_fitness)
            if on_generation is not None:
                on_generation(name, ga)
            if checkpointer is not None and (ga.generation % checkpointer.every == 0 or ga.done):
                checkpointer.save(name, ga, done or [])
    bar.close()
    return ga, time.perf_counter() - t0, X


def _batched_jacobian(problem: FitProblem | JointProblem, x: np.ndarray, rel_step: float, settings: SolverSettings
                      ) -> np.ndarray:
    """Forward-difference Jacobian of the residual in physical units, all columns in one batched simulation."""
    n = x.size
    h = rel_step * np.maximum(np.abs(x), 1e-12)
    X = np.repeat(x[None, :], n + 1, axis=0)
    X[1:] += np.diag(h)
    R = problem.residuals(X, settings, parallel=True)
    return (R[1:] - R[0]).T / h


def log_jacobian_model(problem: FitProblem | JointProblem, x: np.ndarray, rel_step: float = 1e-4,
                       settings: SolverSettings = PRECISE, return_error: bool = False):
    """Jacobian of the model output w.r.t. log-parameters (affine steps for x ≤ 0), batched in one simulation.

    Fourth-order central differences (steps ±h, ±2h). With ``return_error`` the same stencil at 2h (one more
    pair of points per parameter, ±4h) gives a second estimate; the spectral norm of their difference
    measures the Jacobian's numerical error (integrator jitter and truncation), below which singular values
    carry no information — exact symmetries of the model (e.g. K_i·c, λ_d·c, K_t/c) fall there. It returns
    the difference matrix E; ‖E v‖ bounds the error of the output's sensitivity along a direction v.
    """
    n = x.size
    pos = x > 0
    steps = np.where(pos, rel_step, rel_step * np.maximum(np.abs(x), 1e-12))
    mults = (2.0, 1.0, -1.0, -2.0, 4.0, -4.0) if return_error else (2.0, 1.0, -1.0, -2.0)
    k = len(mults)
    X = np.repeat(x[None, :], k * n, axis=0)
    for j in range(n):
        for i, m in enumerate(mults):
            X[k * j + i, j] = x[j] * np.exp(m * rel_step) if pos[j] else x[j] + m * steps[j]
    R = problem.residuals(X, settings, parallel=True)  # residual = measured − model: model's derivative is −dR
    d4 = (-R[0::k] + 8.0 * R[1::k] - 8.0 * R[2::k] + R[3::k]).T / (12.0 * steps)
    if not return_error:
        return -d4
    d4_2h = (-R[4::k] + 8.0 * R[0::k] - 8.0 * R[3::k] + R[5::k]).T / (24.0 * steps)
    bad = ~np.isfinite(d4_2h)
    return -d4, np.where(bad, 0.0, d4 - d4_2h)


def polish_stage(problem: FitProblem | JointProblem, ga: RGA, lower: np.ndarray, upper: np.ndarray,
                 cfg: PolishSettings, last: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """Bounded least squares (PRECISE tier) from the GA's best and the best distinct individuals of its last
    population ``last``; keeps the GA best unless a start improves the SSE."""
    starts = [np.asarray(ga.best_x, float)]
    if last is not None and ga.last_fitness is not None and len(last) == len(ga.last_fitness):
        order = np.argsort(-ga.last_fitness)
        for i in order:
            if len(starts) >= cfg.n_starts:
                break
            if not any(np.allclose(last[i], s) for s in starts):
                starts.append(last[i])
    resid = lambda x: problem.residuals(x[None, :], PRECISE)[0]  # noqa: E731
    jac = lambda x: _batched_jacobian(problem, x, cfg.fd_rel_step, PRECISE)  # noqa: E731
    res = polish_many(resid, np.array(starts), lower, upper, jac_fn=jac, max_nfev=cfg.max_nfev)
    info = {"improved": bool(res.improved), "sse_before": float(res.sse0), "sse_after": float(res.sse),
            "nfev": int(res.nfev), "start_index": int(getattr(res, "start_index", 0)), "message": str(res.message)}
    return (res.x if res.improved else np.asarray(ga.best_x, float)), info


def identifiability_report(problem: FitProblem | JointProblem, x: np.ndarray, noise_var: float | None = None
                           ) -> dict:
    """Sensitivity/uncertainty report of ``problem`` at ``x`` (see :mod:`toggle_id.identifiability`).

    The residual's correlation is estimated (an AR(p) noise model, :func:`toggle_id.discovery.noise.fit_noise`)
    and the sensitivities and residual are prewhitened by it before the analysis, so that the standard errors
    and intervals count the independent samples the record really has; the report names the noise model. A
    known ``noise_var`` (the marginal variance σ²) is turned into the innovation variance of that model."""
    from .discovery.noise import fit_noise

    J, E = log_jacobian_model(problem, x, return_error=True)
    r = problem.residuals(x[None, :], PRECISE)[0]
    if not np.all(np.isfinite(J)) or not np.all(np.isfinite(r)):
        return {"error": "simulation failed near the optimum; no sensitivity report"}
    noise = fit_noise(r)
    if not noise.white:
        J, E, r = noise.whiten_columns(J), noise.whiten_columns(E), noise.whiten(r)
        if noise_var is not None:
            noise_var = noise_var / noise.variance_ratio
    rtol = numerical_rank_rtol(J, E)
    rep = analyze(J, r, list(problem.free), x, log_mask=x > 0, noise_var=noise_var, rank_rtol=rtol)
    out = rep.to_dict()
    out["noise_model"] = noise.to_dict()
    out["jacobian_error_norm"] = float(np.linalg.norm(E, 2))
    return out


def numerical_rank_rtol(J: np.ndarray, E: np.ndarray, safety: float = 3.0) -> float:
    """Relative singular-value tolerance that keeps the directions the Jacobian resolves.

    Singular direction v_j is resolved while s_j > safety·‖E v_j‖ (E: the Jacobian's error estimate along
    that direction); the tolerance is put halfway (geometrically) between the last resolved singular value
    and the next one.
    """
    _, s, vt = np.linalg.svd(J, full_matrices=False)
    if s.size == 0 or s[0] <= 0:
        return 1e-9
    ok = s > safety * np.linalg.norm(E @ vt.T, axis=0)
    rank = int(np.argmin(ok)) if not ok.all() else s.size
    if rank == s.size:
        return max(1e-12, 0.5 * s[-1] / s[0])
    if rank == 0:
        return 0.5
    return float(np.sqrt(s[rank - 1] * max(s[rank], 1e-300)) / s[0])


def make_problems(record: Record, method: str, base: np.ndarray, *, fixed: Sequence[str] = (),
                  extra_free: Sequence[str] = (), settings: SolverSettings = FAST, i_q_weight: float = 0.0
                  ) -> tuple[int, list[tuple[str, tuple[str, ...], tuple[int, int]]]]:
    """Stage plan of ``method``: (clamp index, [(stage name, free names, sample window)])."""
    if method not in METHODS:
        raise ConfigError(f"unknown identification method {method!r}; known: {', '.join(METHODS)}")
    x_BL = GEOMETRY.x_B_L
    k_c = record.clamp_index(x_BL)
    n = record.n
    fixed = set(fixed)
    unknown = fixed - set(ALL_NAMES)
    if unknown:
        raise ConfigError(f"cannot fix unknown parameter(s) {', '.join(sorted(unknown))}")
    if method == "one_stage":
        free = tuple(nm for nm in P.PARAM_NAMES if nm not in fixed) + tuple(extra_free)
        return k_c, [("one_stage", free, (0, n))]
    if k_c >= n:
        raise ConfigError(f"two-stage identification needs the clamping instant: measured x_B never reaches "
                          f"x_B^L = {x_BL} m (max {np.nanmax(record.x_B):.6g} m)")
    if k_c < 2:
        raise ConfigError("two-stage identification needs free motion before the clamping instant; "
                          f"x_B ≥ x_B^L from sample {k_c}")
    s1 = tuple(nm for nm in P.FREE_NAMES if nm not in fixed) + tuple(extra_free)
    s2 = tuple(nm for nm in P.CLAMP_NAMES if nm not in fixed)
    return k_c, [("stage1", s1, (0, k_c)), ("stage2", s2, (k_c, n))]


def as_records(record: Record | Sequence[Record]) -> list[Record]:
    """One record or several as a non-empty list (ConfigError for an empty one)."""
    records = [record] if isinstance(record, Record) else list(record)
    if not records:
        raise ConfigError("no record to identify from")
    if not all(isinstance(r, Record) for r in records):
        raise ConfigError("identify() takes a Record or a sequence of Records")
    return records


def joint_plan(records: Sequence[Record], method: str, base: np.ndarray, *, fixed: Sequence[str] = (),
               extra_free: Sequence[str] = ()
               ) -> tuple[list[int], list[tuple[str, tuple[str, ...], tuple[tuple[int, int], ...]]]]:
    """:func:`make_problems` for every record: (clamp indices, [(stage name, free names, windows per record)])."""
    k_cs, plans = [], []
    for r in records:
        try:
            k_c, plan = make_problems(r, method, base, fixed=fixed, extra_free=extra_free)
        except ConfigError as err:
            if len(records) == 1:
                raise
            raise ConfigError(f"record {r.name}: {err}") from err
        k_cs.append(k_c)
        plans.append(plan)
    stages = [(name, free, tuple(p[i][2] for p in plans)) for i, (name, free, _) in enumerate(plans[0])]
    return k_cs, stages


def identify(record: Record | Sequence[Record], *, method: str = "two_stage", ga: GAConfig | None = None,
             seed: int = 0, make_evaluator: Callable[[Any], Any] | None = None,
             base: Mapping[str, float] | np.ndarray | None = None,
             fixed: Mapping[str, float] | None = None, bounds: Mapping[str, Sequence[float]] | None = None,
             extra_free: Sequence[str] = (), settings: SolverSettings = FAST, i_q_weight: float = 0.0,
             polish: PolishSettings | None = None, identifiability: bool = True,
             progress: Callable[[int, str], Any] = _noop_progress, checkpoint_dir: str | Path | None = None,
             checkpoint_every: int = 5, checkpoint_meta: Mapping[str, Any] | None = None, resume: bool = False,
             noise_var: float | None = None,
             on_generation: Callable[[str, RGA], None] | None = None,
             on_stage: Callable[[StageResult], None] | None = None,
             curve: RmseCurve | None = None, fast: Any = None) -> IdentificationResult:
    """Identify the plant's parameters from ``record`` by the paper's RGA, one- or two-stage.

    ``record``: one record, or several fitted jointly with one parameter vector (multi-experiment; fitness
    1/ΣE² over all of them). ``base``: starting extended vector (names → values; default the assigned values,
    effects off) — it sets the values of parameters that are not free. ``fixed``: parameters held at given
    values (e.g. from a datasheet). ``extra_free``: effect parameters to fit along (discovery). The same
    ``seed`` gives the same result whatever the evaluator and its number of workers. ``checkpoint_meta`` is
    stored in every checkpoint (the workflow puts the job's identity there, :mod:`toggle_id.jobdir`).

    ``method="fast"``: the two stages by multistart least squares instead of the GA
    (:func:`toggle_id.fast.identify_fast`, settings ``fast``: a :class:`toggle_id.fast.FastSettings`); ``ga``,
    ``make_evaluator`` and the checkpoints are not used.

    ``curve``: where the best whole-record RMS error against cumulative simulations goes (one more PRECISE
    simulation per generation whose best individual changed; :mod:`toggle_id.curve`), e.g. one whose
    ``on_point`` logs it live; default a new one. Its points are the result's ``curve``.
    """
    from .evaluators import SerialEvaluator

    records = as_records(record)
    many = len(records) > 1
    ga = (ga or GAConfig()).validate()
    polish = polish or PolishSettings()
    make_evaluator = make_evaluator or SerialEvaluator
    theta = extend(P.ASSIGNED)[0]
    if isinstance(base, Mapping):
        for k, v in base.items():
            theta[free_indices([k])[0]] = float(v)
    elif base is not None:
        theta = extend(np.asarray(base, float))[0]
    for k, v in (fixed or {}).items():
        theta[free_indices([k])[0]] = float(v)
    if method == "fast":
        from .fast import identify_fast

        return identify_fast(records, theta, seed=seed, fixed=fixed, bounds=bounds, extra_free=extra_free,
                             settings=settings, i_q_weight=i_q_weight, fast=fast, polish_settings=polish,
                             identifiability=identifiability, noise_var=noise_var, curve=curve, on_stage=on_stage)
    k_cs, plan = joint_plan(records, method, theta, fixed=tuple(fixed or {}), extra_free=extra_free)
    if method == "two_stage":  # D and K_l at the centres of their domains during stage 1 (docs/model.md §7)
        for nm in P.CLAMP_NAMES:
            if nm not in (fixed or {}):
                lo, hi = stage_bounds([nm], bounds)
                theta[ALL_INDEX[nm]] = 0.5 * (lo[0] + hi[0])
    seeds = np.random.SeedSequence(seed).generate_state(len(plan), dtype=np.uint32)

    ckpt = Checkpointer(checkpoint_dir, checkpoint_every, checkpoint_meta) if checkpoint_dir is not None else None
    resume_stage, resume_state, done = None, None, []
    if resume:
        if ckpt is None or not ckpt.exists():
            raise CheckpointError(f"nothing to resume in {checkpoint_dir}")
        resume_stage, resume_state, done = ckpt.load()
    stages: list[StageResult] = []
    t_start = time.perf_counter()
    curve = curve if curve is not None else RmseCurve(records, t0=t_start)
    spent = curve.simulations  # simulations before this stage (a curve passed in may already have some)
    for (name, free, windows), stage_seed in zip(plan, seeds):
        prior = next((d for d in done if d["name"] == name), None)
        problem = joint([_stage_problem(r, name, free, w, theta, settings, i_q_weight)
                         for r, w in zip(records, windows)])
        if prior is not None:  # finished before the interruption: take its result as it was
            st = _stage_from_dict(prior, theta)
            spent += st.n_simulations
            curve.add(name, spent, theta=st.theta, notify=False)  # logged before the interruption
        else:
            state = resume_state if resume_stage == name else None
            g, secs, last = run_ga_stage(name, problem, ga, int(stage_seed), make_evaluator, bounds=bounds,
                                   progress=progress, checkpointer=ckpt, resume_state=state, done=done,
                                   on_generation=_curve_hook(curve, problem, spent, on_generation))
            lo, hi = stage_bounds(list(free), bounds)
            x, pinfo, secs_p = np.asarray(g.best_x, float), None, 0.0
            n0 = simulations_run()
            if polish.enabled:
                t0 = time.perf_counter()
                x, pinfo = polish_stage(problem, g, lo, hi, polish, last)
                secs_p = time.perf_counter() - t0
            sse = float(problem.sse(x[None, :], PRECISE)[0])
            st = StageResult(name=name, free=free, x=x, theta=problem.thetas(x[None, :])[0], window=windows[0],
                             fitness_ga=float(g.best_fitness), fitness=1.0 / sse if sse > 0 else float("inf"),
                             sse=sse, history=list(g.history), generations=g.generation,
                             converged_generation=converged_generation(g.history), n_evaluations=g.n_evaluations,
                             seconds_ga=secs, seconds_polish=secs_p, windows=windows if many else None,
                             n_simulations=g.n_evaluations + simulations_run() - n0)
            spent += st.n_simulations
            curve.add(f"{name}_polish" if polish.enabled else name, spent, theta=st.theta)
            if identifiability:
                st.identifiability = identifiability_report(problem, x, noise_var)
            st.polish = pinfo
            done.append(_stage_to_dict(st))
        theta = st.theta.copy()
        stages.append(st)
        if on_stage is not None:
            on_stage(st)
    if method == "two_stage" and polish.enabled and polish.final_joint:
        st = _joint_polish(records, plan, theta, settings, i_q_weight, bounds, polish, identifiability, noise_var)
        theta = st.theta.copy()
        spent += st.n_simulations
        curve.add(st.name, spent, theta=theta)
        stages.append(st)
        if on_stage is not None:
            on_stage(st)
    per_record = []
    for r in records:
        full = FitProblem(r, ("D",), theta, (0, r.n), PRECISE)
        per_record.append(float(full.sse(theta[None, ALL_INDEX["D"]][:, None])[0]))
    sse = sum(per_record)
    extra = {}
    if many:
        extra["records"] = [{"name": r.name, "n_samples": r.n, "clamp_index": k, "sse_m2": e,
                             "rmse_m": float(np.sqrt(e / r.n))} for r, k, e in zip(records, k_cs, per_record)]
    return IdentificationResult(method=method, theta=theta, stages=stages,
                                fitness=1.0 / sse if sse > 0 else float("inf"), sse=sse,
                                n_samples=sum(r.n for r in records), seconds=time.perf_counter() - t_start,
                                clamp_index=k_cs[0], extra=extra, curve=list(curve.points))


def _curve_hook(curve: RmseCurve, problem: FitProblem | JointProblem, spent: int,
                then: Callable[[str, RGA], None] | None) -> Callable[[str, RGA], None]:
    """Per generation: a curve point for the GA's best individual (simulated on the whole record only when it
    changed), then ``then`` (e.g. the fault injection of the tests)."""
    def hook(name: str, g: RGA) -> None:
        curve.add(name, spent + g.n_evaluations, theta=problem.thetas(np.asarray(g.best_x, float)[None, :])[0])
        if then is not None:
            then(name, g)

    return hook


def _joint_polish(records: Sequence[Record], plan: list, theta: np.ndarray, settings: SolverSettings,
                  i_q_weight: float, bounds: Mapping[str, Sequence[float]] | None, polish: PolishSettings,
                  identifiability: bool, noise_var: float | None) -> StageResult:
    """After the two GA stages: all their free parameters polished together on the whole record(s).

    Stage 1 sees only the free motion, where several parameter combinations are not determined; the clamped
    phase then exposes them (e.g. the stall current K_i·v/R_s). The paper's stage values stay in the report.
    """
    free = tuple(dict.fromkeys(n for _, names, _ in plan for n in names))
    problem = joint([FitProblem(r, free, theta, (0, r.n), settings, i_q_weight=i_q_weight) for r in records])
    windows = tuple((0, r.n) for r in records)
    lo, hi = stage_bounds(list(free), bounds)
    x0 = problem.x0()
    t0 = time.perf_counter()
    n0 = simulations_run()
    resid = lambda x: problem.residuals(x[None, :], PRECISE)[0]  # noqa: E731
    jac = lambda x: _batched_jacobian(problem, x, polish.fd_rel_step, PRECISE)  # noqa: E731
    res = polish_many(resid, x0[None, :], lo, hi, jac_fn=jac, max_nfev=polish.max_nfev)
    x = res.x if res.improved else x0
    sse = float(problem.sse(x[None, :], PRECISE)[0])
    n_sims = simulations_run() - n0
    st = StageResult(name="joint_polish", free=free, x=x, theta=problem.thetas(x[None, :])[0], window=windows[0],
                     fitness_ga=float("nan"), fitness=1.0 / sse if sse > 0 else float("inf"), sse=sse, history=[],
                     generations=0, converged_generation=0, n_evaluations=0, seconds_ga=0.0,
                     seconds_polish=time.perf_counter() - t0,
                     polish={"improved": bool(res.improved), "sse_before": float(res.sse0),
                             "sse_after": float(res.sse), "nfev": int(res.nfev), "message": str(res.message)},
                     windows=windows if len(records) > 1 else None, n_simulations=n_sims)
    if identifiability:
        st.identifiability = identifiability_report(problem, x, noise_var)
    return st


def _stage_problem(record: Record, name: str, free: tuple[str, ...], window: tuple[int, int], theta: np.ndarray,
                   settings: SolverSettings, i_q_weight: float) -> FitProblem:
    """The stage's problem; stage 2 restarts every individual from the model's first contact."""
    if name != "stage2":
        return FitProblem(record, free, theta, window, settings, i_q_weight=i_q_weight)
    shared = simulate(theta[None, :], record, PRECISE)
    t_c = shared.contact[0, 0]
    if shared.status[0] != STATUS_OK or not np.isfinite(t_c):
        return FitProblem(record, free, theta, window, settings, i_q_weight=i_q_weight)
    start = (float(t_c), tuple(shared.contact[0, 1:]), 1)
    return FitProblem(record, free, theta, window, settings, start=start, prefix_x=shared.x_B[0],
                      prefix_i=shared.i_q[0], i_q_weight=i_q_weight)


def _stage_to_dict(st: StageResult) -> dict:
    d = st.to_dict()
    d["theta"] = [float(v) for v in st.theta]
    d["x"] = [float(v) for v in st.x]
    return d


def _stage_from_dict(d: dict, theta: np.ndarray) -> StageResult:
    return StageResult(name=d["name"], free=tuple(d["free"]), x=np.array(d["x"]), theta=np.array(d["theta"]),
                       window=tuple(d["window"]), fitness_ga=d["fitness_ga"], fitness=d["fitness"], sse=d["sse_m2"],
                       history=list(d["fitness_history"]), generations=d["generations"],
                       converged_generation=d["converged_generation"], n_evaluations=d["n_evaluations"],
                       seconds_ga=d["seconds_ga"], seconds_polish=d["seconds_polish"], polish=d.get("polish"),
                       identifiability=d.get("identifiability"),
                       windows=None if d.get("windows") is None else tuple(tuple(w) for w in d["windows"]),
                       n_simulations=int(d.get("n_simulations", d["n_evaluations"])))
