"""The stage plan every identification method shares (docs/model.md §7): which parameters are free on which
samples (:func:`make_problems`, :func:`joint_plan` for several records), their feasible domains
(:func:`stage_bounds`), each stage's problem (:func:`stage_problem`: stage 2 restarts from the model's first
contact) and the joint polish of all free parameters on the whole record(s) that ends a two-stage fit
(:func:`joint_polish`, with its :class:`PolishSettings`).

The GA method (:mod:`toggle_id.identify`) and the multistart one (:mod:`toggle_id.fast`) both build on it.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from . import params as P
from .effects import ALL_INDEX, ALL_NAMES, effect_bounds
from .errors import ConfigError
from .plant import GEOMETRY
from .polish import polish_many
from .problem import FitProblem, joint
from .record import Record
from .results import IdentificationResult, StageResult
from .sensitivity import batched_jacobian, identifiability_report
from .simulate import FAST, PRECISE, STATUS_OK, SolverSettings, precise_jacobian, simulate, simulations_run


METHODS = ("one_stage", "two_stage", "fast")  # fast: multistart least squares in the two stages (toggle_id/fast.py)


@dataclass
class PolishSettings:
    """Local least-squares refinement after the GA (kept only if it improves the fit)."""

    enabled: bool = True
    n_starts: int = 3          # the GA's best distinct individuals to start from
    max_nfev: int = 60         # residual evaluations per start (finite-difference Jacobians counted apart)
    fd_rel_step: float = 1e-6  # relative finite-difference step of the Jacobian in the residuals' own tier
    fd_tier: str = "precise"   # a GA stage's PRECISE polish's Jacobian: precise (PRECISE, fd_rel_step) or jacobian
    #                            (simulate.JACOBIAN, 1e-3 step, half the cost); the joint polish always PRECISE
    final_joint: bool = True   # two-stage: finish with a polish of all free parameters on the whole record

    @property
    def jacobian(self) -> tuple[SolverSettings, float]:
        """The integrator and relative step of a PRECISE polish's finite-difference Jacobian (``fd_tier``)."""
        return precise_jacobian(self.fd_tier, self.fd_rel_step)


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


def stage_problem(record: Record, name: str, free: tuple[str, ...], window: tuple[int, int], theta: np.ndarray,
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


def joint_polish(records: Sequence[Record], plan: list, theta: np.ndarray, settings: SolverSettings,
                 i_q_weight: float, bounds: Mapping[str, Sequence[float]] | None, polish: PolishSettings,
                 identifiability: bool, noise_var: float | None, pre_tier: SolverSettings | None = None,
                 final_nfev: int | None = None) -> StageResult:
    """After the two GA stages: all their free parameters polished together on the whole record(s).

    Stage 1 sees only the free motion, where several parameter combinations are not determined; the clamped
    phase then exposes them (e.g. the stall current K_i·v/R_s). The paper's stage values stay in the report.
    ``pre_tier`` (e.g. FAST): polish on that tier first (``polish.max_nfev``), then on PRECISE with
    ``final_nfev`` evaluations — most of the way at the cheaper tier's cost.
    """
    free = tuple(dict.fromkeys(n for _, names, _ in plan for n in names))
    problem = joint([FitProblem(r, free, theta, (0, r.n), settings, i_q_weight=i_q_weight) for r in records])
    windows = tuple((0, r.n) for r in records)
    lo, hi = stage_bounds(list(free), bounds)
    x0 = problem.x0()
    t0 = time.perf_counter()
    n0 = simulations_run()
    def resid(tier: SolverSettings):
        return lambda x: problem.residuals(x[None, :], tier)[0]

    def jac(tier: SolverSettings):  # the identification's last word: PRECISE Jacobians whatever polish.fd_tier
        return lambda x: batched_jacobian(problem, x, polish.fd_rel_step, tier)

    start = x0
    if pre_tier is not None:
        pre = polish_many(resid(pre_tier), x0[None, :], lo, hi, jac_fn=jac(pre_tier), max_nfev=polish.max_nfev)
        start = pre.x if pre.improved else x0
    res = polish_many(resid(PRECISE), start[None, :], lo, hi, jac_fn=jac(PRECISE),
                      max_nfev=polish.max_nfev if final_nfev is None else final_nfev)
    if pre_tier is not None:  # the PRECISE polish judged against the nominal start, not the pre-polished one
        sse0 = float(problem.sse(x0[None, :], PRECISE)[0])
        res.improved = bool(res.sse < sse0)
        res.sse0 = sse0
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


def whole_record_result(method: str, records: Sequence[Record], k_cs: Sequence[int], theta: np.ndarray,
                        stages: list[StageResult], seconds: float, curve_points: list, extra: dict | None = None
                        ) -> IdentificationResult:
    """The identification result of ``theta`` on the whole record(s) (PRECISE), with every record's own error
    when there are several."""
    per_record = []
    for r in records:
        full = FitProblem(r, ("D",), theta, (0, r.n), PRECISE)
        per_record.append(float(full.sse(theta[None, ALL_INDEX["D"]][:, None])[0]))
    sse = sum(per_record)
    extra = dict(extra or {})
    if len(records) > 1:
        extra["records"] = [{"name": r.name, "n_samples": r.n, "clamp_index": k, "sse_m2": e,
                             "rmse_m": float(np.sqrt(e / r.n))} for r, k, e in zip(records, k_cs, per_record)]
    return IdentificationResult(method=method, theta=theta, stages=stages,
                                fitness=1.0 / sse if sse > 0 else float("inf"), sse=sse,
                                n_samples=sum(r.n for r in records), seconds=seconds, clamp_index=k_cs[0],
                                extra=extra, curve=list(curve_points))
