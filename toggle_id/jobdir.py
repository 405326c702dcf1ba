"""A job's run directory: whose it is, and that no other job writes into it.

* **Identity.** :func:`job_identity` digests what determines a job's result: the configuration without the keys
  that do not change it (:data:`NOT_DETERMINING`: evaluator, tracking, checkpointing, progress, …; the ``data``
  node is represented by the records themselves) and the records it fits (their samples, input and initial
  position). The identify job stores it in every checkpoint; :func:`check_resume` refuses, in one line naming
  what differs, to continue a checkpoint that another job wrote.
* **Store.** :func:`store_lock` lets jobs started together open one fresh SQLite MLflow store in turn.
* **Claim.** :func:`claim` takes an exclusive lock on ``<run dir>/job.lock`` for the rest of the process, so two
  jobs never work in one directory at the same time (a second one stops with one line naming the first's pid).

The unique directory itself comes from the job entry points (``jobs/_cli.py``: an exclusive ``mkdir`` of
``<date>/<time>-<random suffix>``); this module never imports Hydra.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

import numpy as np

from .checkpoint import load_checkpoint
from .errors import CheckpointError, ConfigError

#: Top-level configuration keys that never change a job's result (``data`` is digested through its records).
NOT_DETERMINING = ("data", "evaluator", "tracking", "progress", "checkpoint", "resume", "run_dir", "debug",
                   "validation", "hydra")

#: The key of the identity in a checkpoint's metadata.
META_KEY = "job"

_LOCKS: dict[str, Any] = {}  # run dir → open lock file (held until the process ends)


def result_config(cfg: Mapping) -> dict:
    """``cfg`` without the keys of :data:`NOT_DETERMINING`, as plain JSON values."""
    kept = {k: v for k, v in cfg.items() if k not in NOT_DETERMINING}
    return json.loads(json.dumps(kept, default=str))


def _digest(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


def record_digest(records: Sequence[Any]) -> str:
    """SHA-256 of what a fit sees of ``records`` (in order): t, v_in, x_B, i_q, x_B0 and the sweep, if any."""
    h = hashlib.sha256()
    for rec in records:
        for name in ("t", "v_in", "x_B", "i_q"):
            arr = getattr(rec, name, None)
            h.update(name.encode())
            if arr is None:
                h.update(b"none")
            else:
                arr = np.ascontiguousarray(arr, dtype="<f8")
                h.update(str(arr.shape).encode())
                h.update(arr.tobytes())
        h.update(repr(float(getattr(rec, "x_B0", 0.0))).encode())
        sweep = getattr(rec, "sweep", None)
        h.update(_digest(None if sweep is None else getattr(sweep, "__dict__", repr(sweep))).encode())
    return h.hexdigest()


def job_identity(cfg: Mapping, records: Sequence[Any]) -> dict:
    """``{"config_sha256", "record_sha256", "config"}``: the digests a checkpoint carries, and the configuration
    they were computed from (to name what differs)."""
    config = result_config(cfg)
    return {"config_sha256": _digest(config), "record_sha256": record_digest(records), "config": config}


def _flat(obj: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(obj, Mapping):
        out: dict[str, Any] = {}
        for k, v in obj.items():
            out.update(_flat(v, f"{prefix}{k}."))
        return out or {prefix[:-1]: {}}
    return {prefix[:-1]: obj}


def _differences(theirs: Mapping, ours: Mapping, limit: int = 4) -> list[str]:
    a, b = _flat(theirs), _flat(ours)
    keys = sorted(k for k in set(a) | set(b) if a.get(k, "<unset>") != b.get(k, "<unset>"))
    text = [f"{k} {json.dumps(a.get(k, '<unset>'))} there, {json.dumps(b.get(k, '<unset>'))} here"
            for k in keys[:limit]]
    if len(keys) > limit:
        text.append(f"{len(keys) - limit} more")
    return text


def check_resume(run_dir: str | os.PathLike, identity: Mapping, what: str | None = None,
                 fix: str = "start the job afresh without resume=") -> None:
    """Raise a one-line CheckpointError unless the checkpoint in ``run_dir`` was written by the job ``identity``
    describes (same result-determining configuration, same records). ``what`` starts the message (default
    ``resume=<run_dir>``), ``fix`` ends it."""
    run_dir = Path(run_dir)
    what = what or f"resume={run_dir}"
    _, meta = load_checkpoint(run_dir / "checkpoint")
    theirs = meta.get(META_KEY) if isinstance(meta, dict) else None
    if not isinstance(theirs, dict) or "config_sha256" not in theirs or "record_sha256" not in theirs:
        raise CheckpointError(f"{what}: its checkpoint does not say which job wrote it (made before "
                              f"checkpoints carried a job digest), so it cannot be resumed safely; {fix}")
    problems = []
    if theirs["config_sha256"] != identity["config_sha256"]:
        diff = _differences(theirs.get("config") or {}, identity.get("config") or {})
        problems.append("the settings differ (" + "; ".join(diff or ["digest only"]) + ")")
    if theirs["record_sha256"] != identity["record_sha256"]:
        problems.append(f"the record differs (sha256 {theirs['record_sha256'][:12]}… there, "
                        f"{identity['record_sha256'][:12]}… here)")
    if problems:
        raise CheckpointError(f"{what}: its checkpoint belongs to another job: {' and '.join(problems)}; "
                              f"resume with that job's settings and record, or {fix}")


def claim(run_dir: str | os.PathLike) -> Path:
    """Lock ``run_dir`` for this process (``job.lock``, released when the process ends); a one-line ConfigError
    when another running job holds it. Claiming a directory this process already holds is a no-op."""
    run_dir = Path(run_dir).resolve()
    key = str(run_dir)
    if key in _LOCKS:
        return run_dir
    try:
        import fcntl
    except ImportError:  # no flock (Windows): the unique directory names are the only guard
        return run_dir
    run_dir.mkdir(parents=True, exist_ok=True)
    fh = open(run_dir / "job.lock", "a+", encoding="utf-8")
    try:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        fh.seek(0)
        holder = fh.read().strip() or "unknown"
        fh.close()
        raise ConfigError(f"run directory {run_dir} is in use by another running job (pid {holder}); wait for it "
                          "or use another directory") from None
    fh.seek(0)
    fh.truncate()
    fh.write(f"{os.getpid()}\n")
    fh.flush()
    _LOCKS[key] = fh
    return run_dir


@contextlib.contextmanager
def store_lock(uri: str | None) -> Iterator[None]:
    """Hold an inter-process lock on a local SQLite tracking store (``sqlite:///PATH``) while the block runs.

    MLflow creates a new store's tables without guarding against another process doing the same, so jobs started
    together on a fresh ``mlflow.db`` lose all but one race (``table ... already exists``, and that job's tracking
    is off). Opening the store under this lock makes them take turns; other URIs are not locked. The lock file is
    in the system's temporary directory, named after the store's path.
    """
    path = uri[len("sqlite:///"):].split("?")[0] if isinstance(uri, str) and uri.startswith("sqlite:///") else None
    try:
        import fcntl
    except ImportError:  # pragma: no cover - no flock (Windows)
        path = None
    if not path or path.startswith(":memory:"):
        yield
        return
    digest = hashlib.sha256(os.path.abspath(path).encode()).hexdigest()[:16]
    with open(os.path.join(tempfile.gettempdir(), f"toggle_id-store-{digest}.lock"), "a") as fh:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)


def release(run_dir: str | os.PathLike) -> None:
    """Give up the claim on ``run_dir`` (normally held until the process ends)."""
    fh = _LOCKS.pop(str(Path(run_dir).resolve()), None)
    if fh is not None:
        fh.close()
