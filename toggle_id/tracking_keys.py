"""What the tracker sends to MLflow, made acceptable: store URIs, run names from overrides, keys and values
within MLflow's limits, and the small records of the tracker (run handle, dropped items). See :mod:`.tracking`."""
from __future__ import annotations

import contextlib
import contextvars
import os
import posixpath
import re
from dataclasses import dataclass, field
from typing import Any, Iterator, Mapping, Sequence
from urllib.parse import urlparse
import numpy as np

MAX_PARAM_VAL_LENGTH = 6000
MAX_TAG_VAL_LENGTH = 8000
MAX_KEY_LENGTH = 250
MAX_PARAMS_TAGS_PER_BATCH = 100
MAX_METRICS_PER_BATCH = 1000

#: Tag MLflow's UI uses to nest a child run under its parent.
PARENT_TAG = "mlflow.parentRunId"

_BAD_KEY_CHARS = re.compile(r"[^/\w.\- :]")
_MAX_DROPPED_KEPT = 1000
_HTTP_ENV = ("MLFLOW_HTTP_REQUEST_TIMEOUT", "MLFLOW_HTTP_REQUEST_MAX_RETRIES", "MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR")
#: MLflow error codes that mean "this one request was refused", not "the store is broken".
_REJECTION_CODES = {"INVALID_PARAMETER_VALUE", "RESOURCE_DOES_NOT_EXIST", "RESOURCE_ALREADY_EXISTS"}


class TrackingWarning(UserWarning):
    """Tracking was disabled because the MLflow store failed; the job itself goes on."""


# --------------------------------------------------------------------------------------------- URIs


def default_tracking_uri(root: str | os.PathLike = ".") -> str:
    """Absolute SQLite store URI ``sqlite:////abs/root/mlflow.db`` (the store MLflow 3.x prefers).

    ``root`` is resolved against the current directory NOW, so call it with the project directory
    (under Hydra: ``hydra.utils.get_original_cwd()``), not the per-job output directory.
    """
    path = os.path.abspath(os.path.join(os.path.expanduser(os.fspath(root)), "mlflow.db"))
    return "sqlite:///" + path


def absolute_uri(uri: str | None, root: str | os.PathLike = ".") -> str:
    """Make a tracking URI independent of the working directory.

    * ``None`` or ``""`` → :func:`default_tracking_uri(root) <default_tracking_uri>`;
    * ``sqlite:///rel.db`` → ``sqlite:////<root>/rel.db``; ``file:rel`` → ``file:///<root>/rel``;
    * a bare path ending in ``.db`` → that SQLite file; any other bare path → a store directory (``mlflow.db``
      inside it);
    * ``http(s)://``, ``databricks`` and other schemes are returned unchanged.
    """
    if not uri:
        return default_tracking_uri(root)
    base = os.path.abspath(os.path.expanduser(os.fspath(root)))

    def _abs(path: str) -> str:
        path = os.path.expanduser(path)
        return path if os.path.isabs(path) else os.path.normpath(os.path.join(base, path))

    if uri.startswith("sqlite:///"):
        rest = uri[len("sqlite:///"):]
        if rest.startswith("/") or rest == ":memory:" or rest == "":
            return uri
        return "sqlite:///" + _abs(rest)
    if uri.startswith("file:"):
        return "file://" + _abs(urlparse(uri).path)
    if "://" in uri or uri.startswith("databricks"):
        return uri
    if uri.endswith(".db"):
        return "sqlite:///" + _abs(uri)
    return default_tracking_uri(_abs(uri))


def default_artifact_location(uri: str) -> str | None:
    """Absolute artifact root for a new experiment: ``<dir of the db>/mlruns`` for a SQLite store,
    ``None`` (the server decides) for anything else."""
    if uri.startswith("sqlite:////"):
        db = uri[len("sqlite:///"):]
        return "file://" + os.path.join(os.path.dirname(db), "mlruns")
    return None


# ------------------------------------------------------------------------------------- run context


@dataclass(frozen=True)
class RunContext:
    """What the entry point knows about the job that the library does not: the command-line overrides (Hydra's
    task overrides, e.g. ``("+experiment=two_stage", "ga.population=200", "seed=1")``) and tags for the
    job's outermost run (e.g. ``{"sweep": "/abs/multirun/2026-01-01/10-00-00"}``)."""

    overrides: tuple[str, ...] = ()
    tags: Mapping[str, str] = field(default_factory=dict)


_RUN_CONTEXT: contextvars.ContextVar[RunContext] = contextvars.ContextVar("toggle_id_run_context",
                                                                        default=RunContext())


@contextlib.contextmanager
def run_context(overrides: Sequence[str] = (), tags: Mapping[str, Any] | None = None) -> Iterator[RunContext]:
    """Within this block, a tracker's outermost new run is named ``run_name(name, overrides)`` and gets ``tags``."""
    ctx = RunContext(tuple(str(o) for o in overrides), {str(k): str(v) for k, v in (tags or {}).items()})
    token = _RUN_CONTEXT.set(ctx)
    try:
        yield ctx
    finally:
        _RUN_CONTEXT.reset(token)


#: Overrides that change how a job reports, not what it computes: left out of run names.
_NAME_SKIP = ("hydra.", "hydra/", "tracking.", "tracking=", "progress=", "run_dir=", "resume=")
MAX_RUN_NAME_LENGTH = 250


def run_name(base: str, overrides: Sequence[str] = ()) -> str:
    """A run name that says what differs: ``base`` followed by the overrides, e.g.
    ``run_name("two_stage", ["+experiment=two_stage", "ga.population=200", "seed=1"])`` →
    ``"two_stage ga.population=200 seed=1"``.

    An ``experiment=X`` override is dropped when X is ``base`` and written ``X`` otherwise; Hydra's own, the
    tracking node's and reporting-only overrides (``progress``, ``resume``) are left out; a value that is a path
    is shortened to its file name. At most 250 characters.
    """
    parts = [str(base)]
    for item in overrides:
        text = str(item).strip()
        key, sep, value = text.partition("=")
        key = key.lstrip("+~")
        if not text or any((key + sep).startswith(p) or key.startswith(p) for p in _NAME_SKIP):
            continue
        if key == "experiment":
            if value and value != base and value not in parts:
                parts.append(value)
            continue
        if "/" in value and not value.startswith(("[", "{")):
            value = value.rstrip("/").rsplit("/", 1)[-1]
        parts.append(f"{key}{sep}{value}")
    name = " ".join(parts)
    return name if len(name) <= MAX_RUN_NAME_LENGTH else name[: MAX_RUN_NAME_LENGTH - 1] + "…"


# ------------------------------------------------------------------------------------- value helpers


def flatten(obj: Mapping[str, Any], prefix: str = "", sep: str = ".") -> dict[str, Any]:
    """Flatten nested mappings into dotted keys: ``{"ga": {"pop": 50}}`` → ``{"ga.pop": 50}``.

    Sequences are kept as values (they become one parameter each, e.g. ``"[0.0, 1.0]"``).
    """
    out: dict[str, Any] = {}
    for key, value in obj.items():
        name = f"{prefix}{sep}{key}" if prefix else str(key)
        if isinstance(value, Mapping) or (hasattr(value, "items") and hasattr(value, "keys")
                                          and not isinstance(value, (str, bytes))):
            out.update(flatten(value, name, sep))
        else:
            out[name] = value
    return out


def sanitize_key(key: str) -> str:
    """A key MLflow accepts: characters outside ``[/\\w.\\- :]`` → ``_``, no ``..``/leading ``/``, ≤ 250 chars."""
    key = _BAD_KEY_CHARS.sub("_", str(key)).strip()
    key = posixpath.normpath(key).lstrip("/") if key else "_"
    if key in ("", ".") or key.startswith(".."):
        key = "_" + key.replace("..", "__")
    return key[:MAX_KEY_LENGTH]


def _tag_key(key: Any) -> str:
    """Tag key: MLflow's own ``mlflow.*`` keys unchanged, others sanitised."""
    key = str(key)
    return key if key.startswith("mlflow.") else sanitize_key(key)


def _to_text(value: Any, limit: int) -> str:
    """String form of a parameter/tag value, truncated to ``limit`` characters (marked with ``…``)."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    elif isinstance(value, np.generic):
        value = value.item()
    elif isinstance(value, (tuple, set, frozenset)):
        value = list(value)
    elif hasattr(value, "__iter__") and not isinstance(value, (str, bytes, list, dict)):
        try:  # e.g. a config list node that is not a list
            value = list(value)
        except TypeError:
            pass
    text = value if isinstance(value, str) else str(value)
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _jsonable(obj: Any) -> Any:
    """Recursively turn numpy arrays/scalars and tuples into JSON-serialisable Python objects."""
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    return obj


def _meaningful(value: Any) -> bool:
    """False for values that say "not set": None and empty strings, lists and mappings."""
    if value is None:
        return False
    if isinstance(value, (str, list, tuple, dict, set, frozenset)) and len(value) == 0:
        return False
    return True


def _chunks(items: Sequence[Any], size: int) -> Iterator[Sequence[Any]]:
    for i in range(0, len(items), size):
        yield items[i:i + size]


def _error_code(exc: BaseException) -> str | None:
    return getattr(exc, "error_code", None)


def _is_rejection(exc: BaseException) -> bool:
    """True when one request was refused (bad value) rather than the store being unusable."""
    if _error_code(exc) in _REJECTION_CODES:
        return True
    return isinstance(exc, (TypeError, ValueError)) and _error_code(exc) is None


# ------------------------------------------------------------------------------------------ tracker


@dataclass(frozen=True)
class RunHandle:
    """What ``with tracker.run(...) as run`` yields. ``run_id`` is ``None`` when tracking is off."""

    run_id: str | None
    name: str
    parent_run_id: str | None = None
    resumed: bool = False


@dataclass(frozen=True)
class Dropped:
    """One tracking call that was not logged: the operation, how many items it carried, and why."""

    op: str
    items: int
    reason: str
