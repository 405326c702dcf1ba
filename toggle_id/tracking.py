"""Experiment tracking: a resilient wrapper around MLflow (3.x) that never stops a job.

Design
------
* One embedded store per project, addressed by an ABSOLUTE URI (:func:`default_tracking_uri`): a SQLite
  database ``<root>/mlflow.db`` with artifacts under ``<root>/mlruns``. MLflow 3.17 refuses the plain file
  store (``file:///.../mlruns`` raises "filesystem tracking backend is in maintenance mode" unless
  ``MLFLOW_ALLOW_FILE_STORE=true``) and its own default is ``sqlite:///mlflow.db`` with artifacts in
  ``./mlruns`` — both relative to the working directory, which Hydra changes per job. This module pins
  both to absolute paths.
* Only :class:`mlflow.MlflowClient` is used, never the fluent ``mlflow.start_run`` API: no process-global
  active-run state, and no probing of Databricks/IPython environments (that probe alone costs ~0.6 s on
  the first fluent ``start_run``). Parent/child nesting is the ``mlflow.parentRunId`` tag, as MLflow's UI
  expects.
* Resilience: every MLflow call goes through one guard. A failure of the STORE (unwritable path,
  database error, server that refuses or does not answer) disables the tracker: one
  :class:`TrackingWarning` is emitted naming the call that failed, every later call is a cheap no-op
  recorded in :attr:`Tracker.dropped`, and a one-line summary of what was not logged is written to the
  log when the outermost run ends. A call the store REJECTS (a parameter changed on resume, an
  artifact file that does not exist, a value that cannot be serialised) drops only that call.
  :attr:`Tracker.ok` tells whether tracking is live. Nothing here raises for a tracking problem.
* HTTP stores get short timeouts (``MLFLOW_HTTP_REQUEST_TIMEOUT``, ``MLFLOW_HTTP_REQUEST_MAX_RETRIES``,
  ``MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR``, read by MLflow at request time) for the duration of each call,
  unless the user has set those variables: with MLflow's defaults (7 retries, 120 s timeout) an
  unreachable server stalls a job for ~4 minutes per call.
* ``mlflow`` is imported lazily (≈2 s, plus ≈1.5 s for the SQL store), so importing this module or
  using a disabled tracker costs nothing.
* The outermost run of a job is named after what differs (:func:`run_name`: the job's name and its command-line
  overrides, set by the entry point with :func:`run_context`) and carries the context's tags (e.g. ``sweep``);
  it can sample system metrics (CPU, memory, disk, network: MLflow's ``SystemMetricsMonitor``, which needs
  ``psutil``). Parameters whose value is ``None`` or empty are not logged.
* Datasets (:meth:`Tracker.log_input`) and models (:meth:`Tracker.log_model`) use MLflow's own
  ``mlflow.data`` and ``mlflow.models.Model.log``; the latter reads MLflow's process-wide tracking URI and
  experiment, which are pointed at this tracker's store only for the duration of the call.
"""
from __future__ import annotations

import contextlib
import getpass
import logging
import os
import sys
import threading
import time
import warnings
from collections import Counter
from typing import Any, Callable, Iterator, Mapping, Sequence

import numpy as np

from .errors import ConfigError

logger = logging.getLogger(__name__)

#: MLflow's limits (mlflow.utils.validation), copied so that this module imports without mlflow.
from .tracking_artifacts import ArtifactLogging
from .tracking_keys import (  # noqa: F401 — re-exported: the public names of tracking live there
    Dropped,
    MAX_KEY_LENGTH,
    MAX_METRICS_PER_BATCH,
    MAX_PARAMS_TAGS_PER_BATCH,
    MAX_PARAM_VAL_LENGTH,
    MAX_RUN_NAME_LENGTH,
    MAX_TAG_VAL_LENGTH,
    PARENT_TAG,
    RunContext,
    RunHandle,
    TrackingWarning,
    _HTTP_ENV,
    _MAX_DROPPED_KEPT,
    _RUN_CONTEXT,
    _chunks,
    _is_rejection,
    _meaningful,
    _tag_key,
    _to_text,
    absolute_uri,
    default_artifact_location,
    default_tracking_uri,
    flatten,
    run_context,
    run_name,
    sanitize_key,
)


class Tracker(ArtifactLogging):
    """MLflow runs, parameters, metrics and artifacts for one experiment; never raises for tracking trouble.

    Parameters
    ----------
    uri:
        Tracking URI. ``None`` → ``$MLFLOW_TRACKING_URI`` if set, else :func:`default_tracking_uri` of the
        current directory. Relative SQLite/file paths are made absolute (:func:`absolute_uri`).
    experiment_name:
        Experiment to log into; created (with an absolute artifact location) if missing, restored if deleted.
    enabled:
        ``False`` → every method is a no-op and ``mlflow`` is never imported.
    artifact_location:
        Artifact root for a NEW experiment; default ``<store dir>/mlruns`` for SQLite stores.
    http_timeout_s, http_max_retries:
        Request timeout (s) and retries for ``http(s)://`` stores, unless the ``MLFLOW_HTTP_REQUEST_*``
        environment variables are set.
    system_metrics, system_metrics_interval_s, system_metrics_samples:
        Sample CPU, memory, disk and network use every ``system_metrics_interval_s`` seconds while the
        outermost run is open and log the mean of every ``system_metrics_samples`` samples (``system/*``
        metrics, MLflow's ``SystemMetricsMonitor``; needs ``psutil``). A run shorter than one interval logs none.

    Usage::

        tracker = Tracker(default_tracking_uri(project_dir), "toggle-id")
        with tracker.run("two-stage") as parent:
            tracker.log_params(cfg)
            with tracker.run("stage-1", nested=True):
                tracker.log_metric_history("best_fitness", history)
    """

    def __init__(self, uri: str | None, experiment_name: str = "toggle-id", enabled: bool = True, *,
                 artifact_location: str | None = None, http_timeout_s: int = 5, http_max_retries: int = 1,
                 system_metrics: bool = False, system_metrics_interval_s: float = 10.0,
                 system_metrics_samples: int = 1):
        if not isinstance(experiment_name, str) or not experiment_name.strip():
            raise ConfigError(f"experiment_name must be a non-empty string, got {experiment_name!r}")
        if int(http_timeout_s) < 1 or int(http_max_retries) < 0:
            raise ConfigError(f"http_timeout_s must be ≥ 1 and http_max_retries ≥ 0, "
                              f"got {http_timeout_s}, {http_max_retries}")
        if system_metrics and (not float(system_metrics_interval_s) > 0 or int(system_metrics_samples) < 1):
            raise ConfigError(f"system metrics: the sampling interval must be > 0 s and the samples per logged "
                              f"value >= 1, got {system_metrics_interval_s}, {system_metrics_samples}")
        self.enabled = bool(enabled)
        self.system_metrics = bool(system_metrics)
        self._system_metrics_args = (float(system_metrics_interval_s), int(system_metrics_samples))
        self.experiment_name = experiment_name
        self.uri = absolute_uri(uri or os.environ.get("MLFLOW_TRACKING_URI"))
        self.artifact_location = artifact_location or default_artifact_location(self.uri)
        self.experiment_id: str | None = None
        self.error: str | None = None  # why tracking was disabled, if it was
        self.dropped: list[Dropped] = []
        self._dropped_counts: Counter[str] = Counter()
        self._dropped_items: Counter[str] = Counter()
        self._client: Any = None
        self._stack: list[RunHandle] = []
        self._http = self.uri.startswith(("http://", "https://"))
        self._http_env = {"MLFLOW_HTTP_REQUEST_TIMEOUT": str(int(http_timeout_s)),
                          "MLFLOW_HTTP_REQUEST_MAX_RETRIES": str(int(http_max_retries)),
                          "MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR": "1"}
        self._rejections_logged = 0
        self._summarized = 0
        if self.enabled:
            self._connect()

    # ------------------------------------------------------------------ state

    @property
    def ok(self) -> bool:
        """True while tracking is enabled and the store has not failed."""
        return self.enabled and self._client is not None and self.error is None

    @property
    def run_id(self) -> str | None:
        """Id of the innermost active run (``None`` outside runs or when tracking is off)."""
        return self._stack[-1].run_id if self._stack else None

    @property
    def client(self) -> Any:
        """The underlying :class:`mlflow.MlflowClient` (``None`` when disabled or failed at start)."""
        return self._client

    def dropped_summary(self) -> str:
        """One line naming what was not logged, e.g. ``"log_metrics ×12 (36 items), log_figure ×1"``;
        empty when nothing was dropped."""
        parts = []
        for op, n in self._dropped_counts.items():
            items = self._dropped_items[op]
            parts.append(f"{op} ×{n}" + (f" ({items} items)" if items and items != n else ""))
        return ", ".join(parts)

    def clear_dropped(self) -> None:
        """Forget what was dropped so far (e.g. after reporting it)."""
        self.dropped.clear()
        self._dropped_counts.clear()
        self._dropped_items.clear()
        self._summarized = 0

    # ------------------------------------------------------------------ guard

    @contextlib.contextmanager
    def _call_env(self) -> Iterator[None]:
        """Short HTTP timeouts (unless the user set them) and silenced SQLAlchemy deprecation noise."""
        added = []
        if self._http:
            for name in _HTTP_ENV:
                if name not in os.environ:
                    os.environ[name] = self._http_env[name]
                    added.append(name)
        try:
            with warnings.catch_warnings():
                warnings.filterwarnings("ignore", message=r".*``noload`` loader strategy")
                yield
        finally:
            for name in added:
                os.environ.pop(name, None)

    def _drop(self, op: str, items: int, reason: str) -> None:
        self._dropped_counts[op] += 1
        self._dropped_items[op] += items
        if len(self.dropped) < _MAX_DROPPED_KEPT:
            self.dropped.append(Dropped(op, items, reason))

    def _fail(self, op: str, items: int, exc: BaseException) -> None:
        """Disable tracking after a store failure, with exactly one warning."""
        message = " ".join(f"{type(exc).__name__}: {exc}".split())
        if "filesystem tracking backend" in message:  # MLflow ≥ 3.x refuses file:// stores; say the fix in full
            message = ("MLflow refuses a plain file store: give a database URI such as sqlite:////ABS/PATH/mlflow.db "
                       "(tracking.uri=null is the project's own store) or set MLFLOW_ALLOW_FILE_STORE=true")
        elif len(message) > 300:
            message = message[:299] + "…"
        self.error = f"{op}: {message}"
        if op == "connect":
            what = "nothing will be logged"
        else:
            self._drop(op, items, "store failure")
            what = f"it ({items} item(s)) and every later tracking call are not logged (see Tracker.dropped)"
        warnings.warn(f"MLflow tracking disabled ({self.uri}): {op} failed ({message}); {what}; the job goes on.",
                      TrackingWarning, stacklevel=4)

    def _reject(self, op: str, items: int, exc: BaseException) -> None:
        """Drop one refused call; log the first few refusals."""
        self._drop(op, items, f"rejected: {exc}")
        self._rejections_logged += 1
        if self._rejections_logged <= 5:
            logger.warning("MLflow refused %s (%d item(s)) and it was not logged: %s", op, items,
                           " ".join(str(exc).split())[:300])

    def _call(self, op: str, items: int, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> tuple[bool, Any]:
        """Run one MLflow call; ``(True, result)`` on success, ``(False, None)`` when dropped."""
        if not self.enabled:
            return False, None
        if not self.ok:
            self._drop(op, items, "tracking disabled")
            return False, None
        try:
            with self._call_env():
                return True, fn(*args, **kwargs)
        except Exception as exc:  # noqa: BLE001 — tracking must never stop the job
            if _is_rejection(exc):
                self._reject(op, items, exc)
            else:
                self._fail(op, items, exc)
            return False, None

    def _target(self, op: str, items: int) -> str | None:
        """Run id to log into, or ``None`` (recorded as dropped) when there is none."""
        if not self.enabled:
            return None
        if not self.ok:
            self._drop(op, items, "tracking disabled")
            return None
        run_id = self.run_id
        if run_id is None:
            self._drop(op, items, "no active run")
            if self._rejections_logged < 5:
                self._rejections_logged += 1
                logger.warning("%s called outside a tracked run; not logged", op)
        return run_id

    # ------------------------------------------------------------------ connection

    def _connect(self) -> None:
        def connect() -> Any:
            from mlflow import MlflowClient

            client = MlflowClient(tracking_uri=self.uri)
            exp = client.get_experiment_by_name(self.experiment_name)
            if exp is None:
                try:
                    exp_id = client.create_experiment(self.experiment_name,
                                                      artifact_location=self.artifact_location)
                except Exception as exc:  # another process created it meanwhile
                    exp = client.get_experiment_by_name(self.experiment_name)
                    if exp is None:
                        raise exc
                    exp_id = exp.experiment_id
            else:
                exp_id = exp.experiment_id
                if exp.lifecycle_stage == "deleted":
                    client.restore_experiment(exp_id)
            return client, exp_id

        try:
            with self._call_env():
                self._client, self.experiment_id = connect()
        except Exception as exc:  # noqa: BLE001 — any failure to open the store disables tracking
            self._client = None
            self._fail("connect", 0, exc)

    # ------------------------------------------------------------------ runs

    @contextlib.contextmanager
    def run(self, name: str, tags: Mapping[str, Any] | None = None, nested: bool = False,
            run_id: str | None = None, description: str | None = None) -> Iterator[RunHandle]:
        """Context-managed run. ``nested=True`` makes it a child of the innermost active run.

        ``run_id`` resumes that existing run (status back to RUNNING, same id) instead of creating one; if
        the store does not know it, a new run is created and tagged ``toggle_id.resume_requested``.
        The run ends FINISHED, FAILED (exception) or KILLED (KeyboardInterrupt); exceptions propagate.
        """
        outermost = not self._stack
        handle = self._start(name, tags, nested, run_id, description)
        self._stack.append(handle)
        monitor = self._start_system_metrics(handle) if outermost and self.system_metrics else None
        status = "FINISHED"
        try:
            yield handle
        except KeyboardInterrupt:
            status = "KILLED"
            raise
        except BaseException:
            status = "FAILED"
            raise
        finally:
            self._stack.pop()
            if monitor is not None:  # a store already found broken: its last values cannot be flushed anyway
                self._finish_system_metrics(monitor, 15.0 if self.ok else 1.0)
            if handle.run_id is not None:
                self._call("end_run", 0, self._client.set_terminated, handle.run_id, status)
            total = sum(self._dropped_counts.values())
            if not self._stack and total > self._summarized and self.enabled:
                self._summarized = total
                logger.warning("MLflow tracking: not logged: %s%s", self.dropped_summary(),
                               f" (tracking disabled: {self.error})" if self.error else "")

    def _start_system_metrics(self, handle: RunHandle) -> Any:
        """MLflow's system-metrics monitor on ``handle``'s run (``None`` when it cannot run: no run, no psutil)."""
        if handle.run_id is None:
            return None
        try:
            import psutil  # noqa: F401 — MLflow's CPU monitor needs it
            from mlflow.system_metrics.system_metrics_monitor import SystemMetricsMonitor
        except ImportError as exc:
            self._drop("system_metrics", 0, f"unavailable: {exc}")
            logger.warning("MLflow system metrics are not logged: %s (pip install psutil)", exc)
            return None
        interval, samples = self._system_metrics_args
        logging.getLogger("mlflow.system_metrics").setLevel(logging.WARNING)  # no "skip GPU", "started" lines
        done, monitor = self._call("system_metrics", 0, SystemMetricsMonitor, handle.run_id,
                                   sampling_interval=interval, samples_before_logging=samples,
                                   resume_logging=handle.resumed, tracking_uri=self.uri)
        if not done:
            return None
        monitor.start()
        return monitor

    def _finish_system_metrics(self, monitor: Any, timeout_s: float = 15.0) -> None:
        """Stop the monitor and flush its last values, waiting at most ``timeout_s``: its thread may be stuck in
        a request to a server that went away, and the job must not wait for it."""
        stopper = threading.Thread(target=monitor.finish, name="toggle_id-system-metrics-stop", daemon=True)
        stopper.start()
        stopper.join(timeout_s)
        if stopper.is_alive():
            self._drop("system_metrics", 0, f"the monitor did not stop within {timeout_s:g} s")
            logger.warning("MLflow system metrics: the monitor did not stop within %g s; its last values are "
                           "not logged", timeout_s)

    def _start(self, name: str, tags: Mapping[str, Any] | None, nested: bool, run_id: str | None,
               description: str | None) -> RunHandle:
        parent = next((h.run_id for h in reversed(self._stack) if h.run_id), None) if nested else None
        if not self._stack and not run_id:  # the job's outermost run: named after what differs
            context = _RUN_CONTEXT.get()
            name = run_name(name, context.overrides)
            tags = {**context.tags, **(tags or {})}
            if context.overrides:
                tags.setdefault("overrides", " ".join(context.overrides))
        if not self.ok:
            if self.enabled:
                self._drop("start_run", 1, "tracking disabled")
            return RunHandle(None, name, parent)
        all_tags = {_tag_key(k): _to_text(v, MAX_TAG_VAL_LENGTH) for k, v in (tags or {}).items()}
        if description:
            all_tags["mlflow.note.content"] = _to_text(description, MAX_TAG_VAL_LENGTH)
        if run_id:
            run = None
            try:
                with self._call_env():
                    run = self._client.get_run(run_id)
            except Exception as exc:  # noqa: BLE001
                if not _is_rejection(exc):  # store failure, not "no such run"
                    self._fail("start_run", 1, exc)
            if run is not None:
                if run.info.status != "RUNNING":
                    self._call("resume_run", 1, self._client.update_run, run_id, status="RUNNING")
                all_tags["toggle_id.resumed_at"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
                self._log_tags(run_id, all_tags)
                return RunHandle(run_id, name, run.data.tags.get(PARENT_TAG), resumed=True)
            if not self.ok:
                return RunHandle(None, name, parent)
            logger.warning("MLflow run %s to resume was not found in %s; starting a new run", run_id, self.uri)
            all_tags["toggle_id.resume_requested"] = run_id
        all_tags.setdefault("mlflow.source.name", os.path.basename(sys.argv[0]) if sys.argv and sys.argv[0] else "-")
        all_tags.setdefault("mlflow.source.type", "LOCAL")
        with contextlib.suppress(Exception):
            all_tags.setdefault("mlflow.user", getpass.getuser())
        if parent:
            all_tags[PARENT_TAG] = parent
        done, run = self._call("start_run", 1, self._client.create_run, self.experiment_id,
                               run_name=name, tags=all_tags)
        return RunHandle(run.info.run_id if done else None, name, parent)

    def close(self) -> None:
        """Nothing to release for MLflow clients; kept so a Tracker can be used as a context manager."""

    def __enter__(self) -> "Tracker":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # ------------------------------------------------------------------ logging

    def _log_tags(self, run_id: str, tags: Mapping[str, str]) -> None:
        from mlflow.entities import RunTag

        items = [RunTag(_tag_key(k), v) for k, v in tags.items()]
        for chunk in _chunks(items, MAX_PARAMS_TAGS_PER_BATCH):
            if not self._call("set_tags", len(chunk), self._client.log_batch, run_id, tags=chunk,
                              synchronous=True)[0]:
                return

    def set_tags(self, tags: Mapping[str, Any]) -> None:
        """Set string tags on the active run (values truncated to 8000 characters)."""
        run_id = self._target("set_tags", len(tags))
        if run_id is not None and tags:
            self._log_tags(run_id, {str(k): _to_text(v, MAX_TAG_VAL_LENGTH) for k, v in tags.items()})

    def log_params(self, params: Mapping[str, Any], prefix: str = "") -> None:
        """Log parameters; nested mappings become dotted keys, values are strings truncated to 6000 chars.
        Values that say "not set" (``None``, empty strings, lists and mappings) are left out.

        Re-logging an identical value (e.g. after a resume) is accepted; a changed value is refused by
        MLflow and dropped with a log line.
        """
        flat = {k: v for k, v in flatten(params, prefix).items() if _meaningful(v)} if params else {}
        run_id = self._target("log_params", len(flat))
        if run_id is None or not flat:
            return
        from mlflow.entities import Param

        items = [Param(sanitize_key(k), _to_text(v, MAX_PARAM_VAL_LENGTH)) for k, v in flat.items()]
        for chunk in _chunks(items, MAX_PARAMS_TAGS_PER_BATCH):
            if not self._call("log_params", len(chunk), self._client.log_batch, run_id, params=chunk,
                              synchronous=True)[0] and not self.ok:
                return

    def log_metrics(self, metrics: Mapping[str, Any], step: int | None = None, run_id: str | None = None) -> None:
        """Log scalar metrics (nested mappings → dotted keys) at ``step`` (default 0) into the innermost active
        run, or into ``run_id`` (e.g. a parent while a child is open). Values that are not numbers are dropped;
        NaN/inf are logged as such."""
        flat = flatten(metrics) if metrics else {}
        run_id = run_id if run_id and self.ok else self._target("log_metrics", len(flat))
        if run_id is None or not flat:
            return
        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        items = []
        for key, value in flat.items():
            try:
                items.append(Metric(sanitize_key(key), float(value), now, int(step or 0)))
            except (TypeError, ValueError):
                self._drop("log_metrics", 1, f"{key}: not a number ({value!r})")
        self._log_metric_items("log_metrics", run_id, items)

    def log_metric_history(self, key: str, values: Sequence[float], start_step: int = 0,
                           timestamps_s: Sequence[float] | None = None) -> None:
        """Log a whole series (e.g. best fitness per generation) as steps ``start_step, start_step+1, …``
        in batched calls (≤ 1000 metrics per ``log_batch``). ``timestamps_s`` (Unix seconds, one per
        value) default to now."""
        vals = np.asarray(values, dtype=float).ravel() if values is not None else np.zeros(0)
        run_id = self._target("log_metric_history", vals.size)
        if run_id is None or vals.size == 0:
            return
        if timestamps_s is not None and len(timestamps_s) != vals.size:
            self._drop("log_metric_history", vals.size,
                       f"{key}: {len(timestamps_s)} timestamps for {vals.size} values")
            logger.warning("log_metric_history(%s): %d timestamps for %d values; not logged",
                           key, len(timestamps_s), vals.size)
            return
        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        stamps = [now] * vals.size if timestamps_s is None else [int(s * 1000) for s in timestamps_s]
        name = sanitize_key(key)
        items = [Metric(name, float(v), ts, int(start_step) + i) for i, (v, ts) in enumerate(zip(vals, stamps))]
        self._log_metric_items("log_metric_history", run_id, items)

    def _log_metric_items(self, op: str, run_id: str, items: Sequence[Any]) -> None:
        for chunk in _chunks(list(items), MAX_METRICS_PER_BATCH):
            if not self._call(op, len(chunk), self._client.log_batch, run_id, metrics=chunk,
                              synchronous=True)[0] and not self.ok:
                return
