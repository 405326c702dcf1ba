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

Where the parts live: the stage plan, the stage problems and the joint polish every method shares in
:mod:`toggle_id.stages`; the result types in :mod:`toggle_id.results`; checkpoints in
:mod:`toggle_id.stage_checkpoint`; Jacobians and the identifiability report in :mod:`toggle_id.sensitivity`;
the GA in :mod:`toggle_id.ga`; the multistart method (``method="fast"``) in :mod:`toggle_id.fast`.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from . import params as P
from .curve import RmseCurve
from .effects import ALL_INDEX
from .errors import CheckpointError
from .fast import identify_fast
from .ga import RGA, GAConfig
from .polish import polish_many
from .problem import FitProblem, JointProblem, free_indices, joint
from .record import Record
from .results import IdentificationResult, StageResult, converged_generation
from .sensitivity import batched_jacobian, identifiability_report
from .simulate import FAST, PRECISE, SolverSettings, extend, simulations_run
from .stage_checkpoint import Checkpointer, stage_from_dict, stage_to_dict
from .stages import (PolishSettings, as_records, joint_plan, joint_polish, stage_bounds, stage_problem,
                     whole_record_result)


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
    tier, step = cfg.jacobian
    jac = lambda x: batched_jacobian(problem, x, step, tier)  # noqa: E731
    res = polish_many(resid, np.array(starts), lower, upper, jac_fn=jac, max_nfev=cfg.max_nfev)
    info = {"improved": bool(res.improved), "sse_before": float(res.sse0), "sse_after": float(res.sse),
            "nfev": int(res.nfev), "start_index": int(getattr(res, "start_index", 0)), "message": str(res.message)}
    return (res.x if res.improved else np.asarray(ga.best_x, float)), info


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
    stored in every checkpoint (the identify job puts its identity there, :mod:`toggle_id.jobdir`).

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
        problem = joint([stage_problem(r, name, free, w, theta, settings, i_q_weight)
                         for r, w in zip(records, windows)])
        if prior is not None:  # finished before the interruption: take its result as it was
            st = stage_from_dict(prior, theta)
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
            done.append(stage_to_dict(st))
        theta = st.theta.copy()
        stages.append(st)
        if on_stage is not None:
            on_stage(st)
    if method == "two_stage" and polish.enabled and polish.final_joint:
        st = joint_polish(records, plan, theta, settings, i_q_weight, bounds, polish, identifiability, noise_var)
        theta = st.theta.copy()
        spent += st.n_simulations
        curve.add(st.name, spent, theta=theta)
        stages.append(st)
        if on_stage is not None:
            on_stage(st)
    return whole_record_result(method, records, k_cs, theta, stages, time.perf_counter() - t_start, curve.points)


def _curve_hook(curve: RmseCurve, problem: FitProblem | JointProblem, spent: int,
                then: Callable[[str, RGA], None] | None) -> Callable[[str, RGA], None]:
    """Per generation: a curve point for the GA's best individual (simulated on the whole record only when it
    changed), then ``then`` (e.g. the fault injection of the tests)."""
    def hook(name: str, g: RGA) -> None:
        curve.add(name, spent + g.n_evaluations, theta=problem.thetas(np.asarray(g.best_x, float)[None, :])[0])
        if then is not None:
            then(name, g)

    return hook
