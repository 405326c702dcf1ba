"""Job orchestration: plain-dict configuration in, result files, MLflow runs and figures out.

The jobs in ``jobs/`` compose Hydra configs and call these functions with ``OmegaConf.to_container`` output;
this module never imports Hydra. Each job validates its whole configuration before any work starts, writes
its report atomically into the run directory and returns its path (the job prints ``report: <path>``).
"""
from __future__ import annotations

import json
import logging
import os
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping

import numpy as np

from . import console, jobdir
from . import params as P
from .checkpoint import atomic_write_json, atomic_write_text
from .data import read_csv
from .effects import ALL_INDEX, ALL_NAMES
from .errors import ConfigError
from .ga import GAConfig
from .identify import identify
from .record import COMMANDS, CYCLING, SWEEPS, Record, measure
from .simulate import PRECISE, TIERS, SolverChoice, extend, simulate
from .stages import METHODS, PolishSettings, joint_plan, stage_bounds
from .tracking import Tracker

log = logging.getLogger("toggle_id")
JOBS = ("identify", "table1", "discover", "emps", "identifiability", "excite")


from .job_report import model_response, stage_child_run, write_figures, console_report  # noqa: F401 — the jobs take them from here too

# ------------------------------------------------------------------------------------------ configuration
def _get(cfg: Mapping, path: str, default: Any = None) -> Any:
    node: Any = cfg
    for key in path.split("."):
        if not isinstance(node, Mapping) or key not in node:
            return default
        node = node[key]
    return node


def truth_vector(data: Mapping) -> np.ndarray:
    """Extended parameter vector of a simulated record's truth (assigned values + overrides + effects)."""
    theta = extend(P.ASSIGNED)[0]
    for group in ("params", "effects"):
        for name, value in (data.get(group) or {}).items():
            if value is None:  # null: the assigned value / effect off
                continue
            if name not in ALL_INDEX:
                raise ConfigError(f"data.{group}: unknown parameter {name!r}; known: {', '.join(ALL_NAMES)}")
            theta[ALL_INDEX[name]] = float(value)
    return theta


def _number(data: Mapping, key: str, default: float) -> float:
    """``data[key]`` as a float (``default`` when absent or null); one-line ConfigError otherwise."""
    value = data.get(key, default)
    if value is None:
        value = default
    if isinstance(value, bool):
        raise ConfigError(f"data.{key} must be a number, got {value!r}")
    try:
        return float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"data.{key} must be a number, got {value!r}") from None


def build_record(data: Mapping) -> tuple[Record, np.ndarray | None]:
    """The record a job works on and, for simulated records, the true extended parameter vector.

    A simulated record (``source: simulated``, conf/data/simulated.yaml) is driven by ``command``: ``sweep``
    (the paper's swept sine named by ``sweep``, in continuous time) or ``cycling`` (the open/close cycling
    command :data:`toggle_id.record.CYCLING`, defined by its samples). Its x_B is the PRECISE simulation of the
    truth plus Gaussian noise of standard deviation ``noise_m`` — white, or AR(1) with lag-1 coefficient
    ``noise_ar`` ∈ [0, 1) at the same marginal σ — rounded to multiples of ``quantum_m`` (an encoder; 0: off).
    """
    source = data.get("source")
    if source == "joint":
        raise ConfigError("data=joint (several records) is for the identify job (python -m jobs.run "
                          "+experiment=joint); this job works on one record")
    if source == "csv":
        path = data.get("path")
        if not path or path == "???":
            raise ConfigError("data.path must name a CSV file (data=csv data.path=FILE.csv)")
        return read_csv(path, x_B0=data.get("x_B0")), None
    if source != "simulated":
        raise ConfigError(f"unknown data.source {source!r}; known: simulated, csv")
    command = data.get("command", "sweep") or "sweep"
    if command not in COMMANDS:
        raise ConfigError(f"unknown data.command {command!r}; known: {', '.join(COMMANDS)}")
    sweep = data.get("sweep", "simulation")
    if command == "sweep" and sweep not in SWEEPS:
        raise ConfigError(f"unknown data.sweep {sweep!r}; known: {', '.join(SWEEPS)}")
    noise_model(data)  # checked before any simulation
    duration, rate = _number(data, "duration", 5.0), _number(data, "rate_hz", 1000.0)
    x_B0 = _number(data, "x_B0", 0.020)
    try:
        if command == "cycling":
            rec = Record.from_cycling(CYCLING, duration, rate, x_B0=x_B0, name="simulated_cycling")
        else:
            rec = Record.from_sweep(sweep, duration, rate, x_B0=x_B0, name=f"simulated_{sweep}")
    except ValueError as err:
        raise ConfigError(f"data: {err}") from err
    theta = measure_truth(rec, data)
    rec.meta["command"] = (CYCLING.to_dict() if command == "cycling" else
                           {"kind": "sweep", "sweep": sweep, **SWEEPS[sweep].__dict__})
    return rec, theta


def noise_model(data: Mapping) -> tuple[float, float, float, int]:
    """(noise_m, noise_ar, quantum_m, noise_seed) of a simulated record's ``data`` node, checked (one-line
    ConfigError)."""
    noise = _number(data, "noise_m", 0.0)
    if not (np.isfinite(noise) and noise >= 0):
        raise ConfigError(f"data.noise_m must be a non-negative number, got {noise}")
    rho = _number(data, "noise_ar", 0.0)
    if not (np.isfinite(rho) and 0.0 <= rho < 1.0):
        raise ConfigError(f"data.noise_ar must be an AR(1) coefficient in [0, 1), got {rho}")
    quantum = _number(data, "quantum_m", 0.0)
    if not (np.isfinite(quantum) and quantum >= 0):
        raise ConfigError(f"data.quantum_m must be a non-negative number (m; 0: no quantisation), got {quantum}")
    seed = data.get("noise_seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(f"data.noise_seed must be a non-negative integer, got {seed!r}")
    return noise, rho, quantum, int(seed)


def measure_truth(rec: Record, data: Mapping) -> np.ndarray:
    """Fill the input-only record ``rec`` with the PRECISE response of ``data``'s truth (params, effects): x_B
    with its noise model (:func:`noise_model`), i_q noiseless, the truth and noise in ``meta``. Returns the
    truth's extended vector."""
    noise, rho, quantum, seed = noise_model(data)
    theta = truth_vector(data)
    sim = simulate(theta[None, :], rec, PRECISE)
    if sim.status[0] != 0:
        raise ConfigError(f"the truth of data.params/effects cannot be simulated under {rec.name!r} "
                          f"({sim.status_counts()})")
    rec.x_B = measure(sim.x_B[0], noise_m=noise, noise_ar=rho, quantum_m=quantum, seed=seed)
    rec.i_q = sim.i_q[0].copy()
    rec.meta.update({"truth": {n: float(v) for n, v in zip(ALL_NAMES, theta)}, "noise_m": noise,
                     "noise": {"model": "none" if noise == 0 else "ar1" if rho > 0 else "white", "sigma_m": noise,
                               "ar": rho, "quantum_m": quantum}})
    return theta


#: Keys of a joint data node that are not defaults of its records.
_JOINT_OWN_KEYS = ("source", "records")


def build_records(data: Mapping) -> tuple[list[Record], np.ndarray | None]:
    """The records a job fits and their shared truth (None unless all are simulated from the same vector).

    ``data.source: joint`` (conf/data/joint.yaml) lists the records under ``records:``; each item is a
    simulated-record spec (keys of conf/data/simulated.yaml) or a CSV spec (``source: csv``, ``path``). The
    joint node's other keys (``duration``, ``noise_m``, ``params``, …) are defaults for every item; an item's
    ``params``/``effects`` update the shared ones. Any other source gives a one-record list.
    """
    if data.get("source") != "joint":
        record, truth = build_record(data)
        return [record], truth
    items = data.get("records")
    if not isinstance(items, (list, tuple)) or not items:
        raise ConfigError("data.records must list at least one record (data=joint), e.g. "
                          "[{sweep: simulation}, {sweep: experiment}]")
    shared = {k: v for k, v in data.items() if k not in _JOINT_OWN_KEYS}
    records, truths = [], []
    for i, item in enumerate(items):
        if not isinstance(item, Mapping):
            raise ConfigError(f"data.records[{i}] must be a mapping of record settings, got {item!r}")
        spec = {"source": "simulated", **shared}
        for key, value in item.items():
            if key in ("params", "effects") and isinstance(value, Mapping):
                spec[key] = {**(shared.get(key) or {}), **value}
            else:
                spec[key] = value
        if spec.get("source") not in ("simulated", "csv"):
            raise ConfigError(f"data.records[{i}]: unknown source {spec.get('source')!r}; known: simulated, csv")
        try:
            record, truth = build_record(spec)
        except ConfigError as err:
            raise ConfigError(f"data.records[{i}]: {err}") from err
        if item.get("name"):
            record.name = str(item["name"])
        records.append(record)
        truths.append(truth)
    names = [r.name for r in records]
    for i, r in enumerate(records):  # distinct names for the report and the figures
        if names.count(r.name) > 1:
            r.name = f"{r.name}_{i}"
    shared_truth = truths[0]
    if any(t is None for t in truths) or any(not np.array_equal(t, shared_truth) for t in truths[1:]):
        shared_truth = None
    return records, shared_truth


def ga_config(cfg: Mapping) -> GAConfig:
    try:
        return GAConfig.from_dict(dict(cfg.get("ga") or {}))
    except TypeError as err:
        raise ConfigError(f"ga: {err}") from err


def solver_tier(cfg: Mapping):
    tier = _get(cfg, "solver.ga_tier", SolverChoice.ga_tier)
    if tier not in TIERS:
        raise ConfigError(f"unknown solver.ga_tier {tier!r}; known: {', '.join(TIERS)}")
    return TIERS[tier]


def polish_settings(cfg: Mapping) -> PolishSettings:
    node = dict(cfg.get("polish") or {})
    try:
        ps = PolishSettings(**node)
    except TypeError as err:
        raise ConfigError(f"polish: {err}") from err
    if ps.n_starts < 1 or ps.max_nfev < 1 or not ps.fd_rel_step > 0:
        raise ConfigError("polish: n_starts and max_nfev must be >= 1 and fd_rel_step > 0")
    return ps


def fast_settings(cfg: Mapping):
    """The ``fast`` node (method ``fast``, :class:`toggle_id.fast.FastSettings`), validated."""
    from .fast import FastSettings

    try:
        return FastSettings(**dict(cfg.get("fast") or {})).validate()
    except TypeError as err:
        raise ConfigError(f"fast: {err}") from err


# ------------------------------------------------------------------------------------------ evaluators
@contextmanager
def ray_session(ev: Mapping) -> Iterator[None]:
    """Start (or join) Ray once for the whole job when the evaluator is Ray; shut it down if we started it."""
    if ev.get("kind", "serial") != "ray":
        yield
        return
    from .evaluators import init_ray
    import ray

    started = init_ray(num_cpus=ev.get("n_workers"), address=ev.get("address"),
                       connect_timeout_s=float(ev.get("connect_timeout_s", 10.0)),
                       ship_code=bool(ev.get("ship_code", True)))
    try:
        yield
    finally:
        if started:
            ray.shutdown()


def evaluator_factory(ev: Mapping) -> Callable[[Any], Any]:
    """problem → evaluator, from the ``evaluator`` config node."""
    from .evaluators import make_evaluator

    kind = ev.get("kind", "serial")
    if kind not in ("serial", "ray"):
        raise ConfigError(f"unknown evaluator.kind {kind!r}; known: serial, ray")
    n = ev.get("n_workers")
    if n is not None and (not isinstance(n, int) or n < 1):
        raise ConfigError(f"evaluator.n_workers must be a positive integer or null, got {n!r}")
    timeout = ev.get("ready_timeout_s", 600.0)
    if isinstance(timeout, bool) or not isinstance(timeout, (int, float)) or not timeout > 0:
        raise ConfigError(f"evaluator.ready_timeout_s must be a positive number of seconds, got {timeout!r}")
    connect = ev.get("connect_timeout_s", 10.0)
    if isinstance(connect, bool) or not isinstance(connect, (int, float)) or not connect > 0:
        raise ConfigError(f"evaluator.connect_timeout_s must be a positive number of seconds, got {connect!r}")
    address = ev.get("address")
    if address is not None and (not isinstance(address, str) or not address.strip()):
        raise ConfigError(f"evaluator.address must be null (a local Ray), auto or HOST:PORT, got {address!r}")
    if kind == "serial":
        return lambda problem: make_evaluator("serial", problem)
    return lambda problem: make_evaluator("ray", problem, n_workers=n, address=address,
                                          ready_timeout_s=float(timeout), connect_timeout_s=float(connect))


def make_tracker(cfg: Mapping, project_root: str | Path) -> Tracker:
    tr = cfg.get("tracking") or {}
    uri = tr.get("uri")
    if not uri:
        uri = os.environ.get("MLFLOW_TRACKING_URI") or None
    from .tracking import absolute_uri

    sm = tr.get("system_metrics") or {}
    uri = absolute_uri(uri, project_root)
    with jobdir.store_lock(uri if tr.get("enabled", True) else None):  # jobs started together: one opens it at a time
        return Tracker(uri, tr.get("experiment", "toggle-id"), bool(tr.get("enabled", True)),
                       system_metrics=bool(sm.get("enabled", False)),
                       system_metrics_interval_s=float(sm.get("sampling_interval_s", 10.0)),
                       system_metrics_samples=int(sm.get("samples_before_logging", 1)))


# ------------------------------------------------------------------------------------------ jobs
def _identify_kwargs(cfg: Mapping, run_dir: Path, resume: bool) -> dict:
    fixed = dict(cfg.get("fixed") or {})
    for n in fixed:
        if n not in ALL_INDEX:
            raise ConfigError(f"fixed: unknown parameter {n!r}")
    noise = _get(cfg, "identifiability.noise_std_m")
    return dict(ga=ga_config(cfg), seed=int(cfg.get("seed", 0)), fixed=fixed, bounds=dict(cfg.get("bounds") or {}),
                extra_free=tuple(cfg.get("extra_free") or ()), settings=solver_tier(cfg),
                i_q_weight=float(_get(cfg, "outputs.i_q_weight", 0.0) or 0.0), polish=polish_settings(cfg),
                fast=fast_settings(cfg),
                identifiability=bool(_get(cfg, "identifiability.enabled", True)),
                noise_var=None if noise is None else float(noise) ** 2,
                checkpoint_dir=run_dir, checkpoint_every=int(_get(cfg, "checkpoint.every", 5)), resume=resume)


def validate_config(cfg: Mapping) -> None:
    """Check everything a job needs before it starts (one-line ConfigError naming the problem)."""
    if cfg.get("job", "identify") not in JOBS:
        raise ConfigError(f"unknown job {cfg.get('job')!r}; known: {', '.join(JOBS)}")
    if cfg.get("method", "two_stage") not in METHODS:
        raise ConfigError(f"unknown method {cfg.get('method')!r}; known: {', '.join(METHODS)}")
    ga_config(cfg)
    polish_settings(cfg)
    fast_settings(cfg)
    solver_tier(cfg)
    evaluator_factory(cfg.get("evaluator") or {})
    names = [n for n in (cfg.get("bounds") or {})]
    if names:
        stage_bounds(names, cfg.get("bounds"))


def run_identify(cfg: Mapping, run_dir: str | Path, project_root: str | Path = ".") -> Path:
    """The main job: identify the parameters of one record — or of several jointly (data=joint) — one- or
    two-stage, log and report."""
    validate_config(cfg)
    records, truth = build_records(cfg.get("data") or {})
    identity = jobdir.job_identity(cfg, records)  # stored in every checkpoint; a resume must match it
    run_dir, resume = _run_dir(cfg, run_dir, identity)
    record = records[0]
    method = cfg.get("method", "two_stage")
    kw = _identify_kwargs(cfg, run_dir, resume)
    kw["checkpoint_meta"] = {jobdir.META_KEY: identity}
    joint_plan(records, method, extend(P.ASSIGNED)[0], fixed=tuple(kw["fixed"]))  # records fit the method?
    tracker = make_tracker(cfg, project_root)
    ev = cfg.get("evaluator") or {}
    show = bool(cfg.get("progress", True))
    t0 = time.perf_counter()
    from . import mlflow_run
    from .curve import RmseCurve

    with ray_session(ev), tracker.run(method, tags={"method": method, "job": "identify"},
                                     run_id=_mlflow_run_id(run_dir) if resume else None) as run:
        _remember_mlflow_run(run_dir, run.run_id)
        tracker.log_params(_flat_config(cfg))
        datasets = mlflow_run.log_records(tracker, records, run_dir, enabled=_get(cfg, "tracking.log_datasets", True))
        curve = RmseCurve(records, on_point=mlflow_run.curve_logger(tracker, run.run_id))
        result = identify(records if len(records) > 1 else record, method=method, make_evaluator=evaluator_factory(ev),
                          progress=lambda total, desc: console.progress(total, desc, enabled=show),
                          on_stage=lambda st: stage_child_run(tracker, st, truth),
                          on_generation=_fault_injection(cfg), curve=curve, **kw)
        wall = time.perf_counter() - t0
        report = result.to_dict()
        report.update(_truth_report(result.theta, truth))
        responses = [model_response(r, result.theta) for r in records]
        status = [int(resp["status"]) for resp in responses]
        report.update({"job": "identify", "record": "+".join(r.name for r in records), "wall_seconds": wall,
                       "config": _jsonable_cfg(cfg), "mlflow_run_id": run.run_id,
                       "solver_status": max(status, key=abs)})
        for entry, st in zip(report.get("records") or [], status):
            entry["solver_status"] = st
        final = result.stages[-1] if result.stages else None
        if final is not None and final.identifiability:  # the final fit's (the joint polish's, two-stage)
            report["identifiability"] = {"stage": final.name, **final.identifiability}
        validation = _get(cfg, "validation.path")
        if validation:
            report["validation"] = validation_report(validation, result.theta)
            datasets += mlflow_run.log_records(tracker, [read_csv(validation)], run_dir, "validation",
                                               enabled=_get(cfg, "tracking.log_datasets", True))
        tracker.log_metrics({"fitness": result.fitness, "sse_m2": result.sse, "rmse_m": result.rmse_m,
                             "rmse_um": 1e6 * result.rmse_m, "n_simulations": result.n_simulations,
                             "seconds_total": result.seconds, "wall_seconds": wall,
                             **({"validation.rmse_um": 1e6 * report["validation"]["rmse_m"]} if validation else {}),
                             **{f"rmse_m.{r['name']}": r["rmse_m"] for r in report.get("records") or []},
                             **{f"param.{k}": v for k, v in result.params.items()},
                             **{f"pct_error.{k}": v for k, v in (report.get("pct_error") or {}).items()}})
        write_figures(run_dir, records, result, tracker, method, responses)
        report["datasets"] = datasets
        report["model_uri"], report["seconds_model_logging"] = mlflow_run.log_identified_model(
            tracker, result.theta, records, run_dir, method=method, rmse_m=result.rmse_m,
            enabled=_get(cfg, "tracking.log_model", True))
        tracker.set_tags({"mlflow.note.content": mlflow_run.describe_identification(
            method, records, result.rmse_m, result.n_simulations, wall, truth is not None)})
        path = publish_report(tracker, run_dir, console_report(result, truth), report)
    return path


def publish_report(tracker: Tracker, run_dir: Path, text: str, report: dict, json_name: str = "result.json",
                   text_name: str = "table.txt") -> Path:
    """Print the summary, write it and the JSON report atomically into the run dir, log both to MLflow;
    return the report's absolute path."""
    print(text, flush=True)
    atomic_write_text(run_dir / text_name, text + "\n")
    path = atomic_write_json(run_dir / json_name, report)
    tracker.log_artifact(path)
    tracker.log_artifact(run_dir / text_name)
    return Path(path).resolve()


def _fault_injection(cfg: Mapping):
    """``debug.stop_after_generations=N``: interrupt the run after N generations (as a kill would), to test
    checkpoints and ``resume=``; off by default."""
    n = _get(cfg, "debug.stop_after_generations")
    if not n:
        return None
    count = {"n": 0}

    def stop(stage: str, ga) -> None:
        count["n"] += 1
        if count["n"] >= int(n):
            raise KeyboardInterrupt(f"debug.stop_after_generations={n} reached in {stage}")

    return stop


def validation_report(path: str, theta: np.ndarray) -> dict:
    """Simulation error of the identified model on a second record."""
    rec = read_csv(path)
    sim = simulate(theta[None, :], rec, PRECISE)
    e = rec.x_B - sim.x_B[0]
    return {"path": str(Path(path).resolve()), "status": int(sim.status[0]), "sse_m2": float(np.sum(e * e)),
            "rmse_m": float(np.sqrt(np.mean(e * e))),
            "rel_error_pct": float(100 * np.linalg.norm(e) / np.linalg.norm(rec.x_B))}


def _truth_report(theta: np.ndarray, truth: np.ndarray | None) -> dict:
    if truth is None:
        return {}
    return {"truth": {n: float(truth[i]) for i, n in enumerate(P.PARAM_NAMES)},
            "pct_error": {n: console.pct_error(float(truth[i]), float(theta[i])) for i, n in enumerate(P.PARAM_NAMES)}}


def _run_dir(cfg: Mapping, run_dir: str | Path, identity: Mapping) -> tuple[Path, bool]:
    """The directory the job works in (claimed for this process) and whether it continues a checkpoint there —
    only one that this job (``identity``) wrote (:mod:`toggle_id.jobdir`)."""
    resume = cfg.get("resume")
    if resume:
        path = Path(resume).expanduser().resolve()
        if not (path / "checkpoint.json").exists():
            raise ConfigError(f"resume: no checkpoint in {path}")
        jobdir.claim(path)
        jobdir.check_resume(path, identity)
        return path, True
    path = Path(run_dir).resolve()
    path.mkdir(parents=True, exist_ok=True)
    jobdir.claim(path)
    again = (path / "checkpoint.json").exists() and not (path / "result.json").exists()
    if again:  # an interrupted run in this very directory (an explicit hydra.run.dir): continue it if it is ours
        jobdir.check_resume(path, identity, what=f"run directory {path} holds an unfinished run",
                            fix="give the job another hydra.run.dir")
    return path, again


def _mlflow_run_id(run_dir: Path) -> str | None:
    try:
        return json.loads((run_dir / "mlflow_run.json").read_text())["run_id"]
    except (OSError, ValueError, KeyError):
        return None


def _remember_mlflow_run(run_dir: Path, run_id: str | None) -> None:
    if run_id:
        atomic_write_json(run_dir / "mlflow_run.json", {"run_id": run_id})


def _jsonable_cfg(cfg: Mapping) -> dict:
    return json.loads(json.dumps(cfg, default=str))


#: Configuration keys that say how a job reports, not what it computes: not logged as MLflow parameters.
_NOT_PARAMS = ("run_dir", "tracking.", "progress", "debug.")


def _flat_config(cfg: Mapping) -> dict:
    """The configuration as MLflow parameters: dotted keys, without reporting-only keys (values that say "not
    set" are left out by :meth:`Tracker.log_params`)."""
    from .tracking import flatten

    return {k: v for k, v in flatten(_jsonable_cfg(cfg)).items() if not k.startswith(_NOT_PARAMS)}
