"""What the jobs share: the checks of a configuration, the arguments of ``identify()`` it gives, the evaluator and
the Ray session, the MLflow tracker, the configuration as JSON and as MLflow parameters, and the published report.

A configuration is the plain dict of ``OmegaConf.to_container`` (Hydra stays in ``jobs/``). Each job validates the
whole of it before any work starts (one-line :class:`~toggle_id.errors.ConfigError`), writes its report atomically
into the run directory and returns the report's path (the job prints ``report: <path>``).

Importing this module loads neither the simulator (numba) nor MLflow: a job that checks its settings and finds its
records first (the EMPS job) fails in a second when they are wrong.
"""
from __future__ import annotations

import json
import logging
import os
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterator, Mapping

from .. import jobdir
from ..checkpoint import atomic_write_json, atomic_write_text
from ..effects import ALL_INDEX
from ..errors import ConfigError
from ..ga import GAConfig
from ..provenance import code_version
from ..tracking import Tracker, absolute_uri, flatten

if TYPE_CHECKING:
    from ..stages import PolishSettings

#: The jobs a configuration may name (its ``job`` key); ``jobs/run.py`` maps each to its function in this package.
JOBS = ("identify", "table1", "discover", "emps", "identifiability", "excite")


# ------------------------------------------------------------------------------------------ configuration
def get(cfg: Mapping, path: str, default: Any = None) -> Any:
    """``cfg`` at the dotted ``path`` (``"identifiability.noise_std_m"``), ``default`` where a key is missing."""
    node: Any = cfg
    for key in path.split("."):
        if not isinstance(node, Mapping) or key not in node:
            return default
        node = node[key]
    return node


def jsonable_config(cfg: Mapping) -> dict:
    """The configuration as JSON values (what a report stores under ``config``; anything else as its ``str``)."""
    return json.loads(json.dumps(dict(cfg), default=str))


#: Configuration keys that say how a job reports, not what it computes: not logged as MLflow parameters.
_NOT_PARAMS = ("run_dir", "tracking.", "progress", "debug.")


def flat_config(cfg: Mapping) -> dict:
    """The configuration as MLflow parameters: dotted keys, without reporting-only keys (values that say "not
    set" are left out by :meth:`Tracker.log_params`)."""
    return {k: v for k, v in flatten(jsonable_config(cfg)).items() if not k.startswith(_NOT_PARAMS)}


def ga_config(cfg: Mapping) -> GAConfig:
    """The ``ga`` node as a :class:`~toggle_id.ga.GAConfig`."""
    try:
        return GAConfig.from_dict(dict(cfg.get("ga") or {}))
    except TypeError as err:
        raise ConfigError(f"ga: {err}") from err


def solver_tier(cfg: Mapping):
    """The GA's solver tier (``solver.ga_tier``, :class:`~toggle_id.simulate.SolverChoice`)."""
    from ..simulate import TIERS, SolverChoice

    tier = get(cfg, "solver.ga_tier", SolverChoice.ga_tier)
    if tier not in TIERS:
        raise ConfigError(f"unknown solver.ga_tier {tier!r}; known: {', '.join(TIERS)}")
    return TIERS[tier]


def polish_settings(cfg: Mapping) -> PolishSettings:
    """The ``polish`` node (the least-squares polish after the GA, :class:`~toggle_id.stages.PolishSettings`)."""
    from ..simulate import FD_TIERS
    from ..stages import PolishSettings

    node = dict(cfg.get("polish") or {})
    try:
        ps = PolishSettings(**node)
    except TypeError as err:
        raise ConfigError(f"polish: {err}") from err
    if ps.n_starts < 1 or ps.max_nfev < 1 or not ps.fd_rel_step > 0:
        raise ConfigError("polish: n_starts and max_nfev must be >= 1 and fd_rel_step > 0")
    if ps.fd_tier not in FD_TIERS:
        raise ConfigError(f"polish.fd_tier must be one of {', '.join(FD_TIERS)}, got {ps.fd_tier!r}")
    return ps


def fast_settings(cfg: Mapping):
    """The ``fast`` node (method ``fast``, :class:`toggle_id.fast.FastSettings`), validated."""
    from ..fast import FastSettings

    try:
        return FastSettings(**dict(cfg.get("fast") or {})).validate()
    except TypeError as err:
        raise ConfigError(f"fast: {err}") from err


def validate_config(cfg: Mapping) -> None:
    """Check everything a job needs before it starts (one-line ConfigError naming the problem)."""
    from ..stages import METHODS, stage_bounds

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


def identify_kwargs(cfg: Mapping, run_dir: Path, resume: bool) -> dict:
    """The keyword arguments of :func:`toggle_id.identify.identify` that a configuration gives (GA, seed, fixed
    and free parameters, bounds, solver tier, outputs, polish, fast method, identifiability, checkpoints in
    ``run_dir``, ``resume``)."""
    fixed = dict(cfg.get("fixed") or {})
    for n in fixed:
        if n not in ALL_INDEX:
            raise ConfigError(f"fixed: unknown parameter {n!r}")
    noise = get(cfg, "identifiability.noise_std_m")
    return dict(ga=ga_config(cfg), seed=int(cfg.get("seed", 0)), fixed=fixed, bounds=dict(cfg.get("bounds") or {}),
                extra_free=tuple(cfg.get("extra_free") or ()), settings=solver_tier(cfg),
                i_q_weight=float(get(cfg, "outputs.i_q_weight", 0.0) or 0.0), polish=polish_settings(cfg),
                fast=fast_settings(cfg),
                identifiability=bool(get(cfg, "identifiability.enabled", True)),
                noise_var=None if noise is None else float(noise) ** 2,
                checkpoint_dir=run_dir, checkpoint_every=int(get(cfg, "checkpoint.every", 5)), resume=resume)


# ------------------------------------------------------------------------------------------ evaluators
log = logging.getLogger("toggle_id")
#: Why the job's local Ray could not start (None: it started, or was not asked for); set by :func:`ray_session`,
#: read by the evaluators of :func:`evaluator_factory`.
_LOCAL_RAY_FAILED: list[str] = []


@contextmanager
def ray_session(ev: Mapping) -> Iterator[None]:
    """Start (or join) Ray once for the whole job when the evaluator is Ray; shut it down if we started it.

    A local Ray that does not start (its node timed out on a loaded machine, a full /tmp) is tried once more; if it
    fails again the job goes on with the serial evaluator — the same seed gives the same result whatever the
    number of workers, so only the time changes — and says so in one warning line. Joining a cluster
    (``evaluator.address``) that fails stays an error: that was asked for by name."""
    _LOCAL_RAY_FAILED.clear()
    if ev.get("kind", "serial") != "ray":
        yield
        return
    from .. import evaluators
    import ray

    started = False
    for attempt in (1, 2):
        try:
            started = evaluators.init_ray(num_cpus=ev.get("n_workers"), address=ev.get("address"),
                                          connect_timeout_s=float(ev.get("connect_timeout_s", 10.0)),
                                          ship_code=bool(ev.get("ship_code", True)))
            break
        except ConfigError:
            raise
        except Exception as err:  # Ray's own start-up errors are plain Exceptions
            if ev.get("address") is not None:
                raise
            ray.shutdown()
            if attempt == 2:
                why = " ".join(str(err).split())[:200] or type(err).__name__
                _LOCAL_RAY_FAILED.append(why)
                log.warning(f"local Ray did not start twice ({why}): evaluating serially instead (the same "
                            "result, more time)")
    try:
        yield
    finally:
        _LOCAL_RAY_FAILED.clear()  # the fallback holds for this job's session only
        if started:
            ray.shutdown()


def local_ray_failed() -> str | None:
    """Why this job's local Ray could not start (None: it did, or none was asked for)."""
    return _LOCAL_RAY_FAILED[0] if _LOCAL_RAY_FAILED else None


def evaluator_factory(ev: Mapping) -> Callable[[Any], Any]:
    """problem → evaluator, from the ``evaluator`` config node."""
    from ..evaluators import make_evaluator

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

    def ray_or_serial(problem):
        if address is None and local_ray_failed():  # see ray_session: the job goes on serially
            return make_evaluator("serial", problem)
        return make_evaluator("ray", problem, n_workers=n, address=address, ready_timeout_s=float(timeout),
                              connect_timeout_s=float(connect))
    return ray_or_serial


# ------------------------------------------------------------------------------------------ reporting
def make_tracker(cfg: Mapping, project_root: str | Path) -> Tracker:
    """The job's MLflow :class:`~toggle_id.tracking.Tracker` from the ``tracking`` node (``uri`` null: the
    ``MLFLOW_TRACKING_URI`` environment variable, else the project's local store), opened one job at a time."""
    tr = cfg.get("tracking") or {}
    uri = tr.get("uri")
    if not uri:
        uri = os.environ.get("MLFLOW_TRACKING_URI") or None
    sm = tr.get("system_metrics") or {}
    uri = absolute_uri(uri, project_root)
    with jobdir.store_lock(uri if tr.get("enabled", True) else None):  # jobs started together: one opens it at a time
        return Tracker(uri, tr.get("experiment", "toggle-id"), bool(tr.get("enabled", True)),
                       system_metrics=bool(sm.get("enabled", False)),
                       system_metrics_interval_s=float(sm.get("sampling_interval_s", 10.0)),
                       system_metrics_samples=int(sm.get("samples_before_logging", 1)))


def publish_report(tracker: Tracker, run_dir: Path, text: str, report: dict, json_name: str = "result.json",
                   text_name: str = "table.txt") -> Path:
    """Print the summary, write it and the JSON report atomically into the run dir (with the code that made it,
    ``code``), log both to MLflow; return the report's absolute path."""
    print(text, flush=True)
    atomic_write_text(run_dir / text_name, text + "\n")
    report.setdefault("code", code_version())
    path = atomic_write_json(run_dir / json_name, report)
    tracker.log_artifact(path)
    tracker.log_artifact(run_dir / text_name)
    return Path(path).resolve()
