"""Safe checkpoints (no pickle) and atomic file writes.

A checkpoint with prefix ``P`` is two files:

- ``P.npz`` — numeric arrays only (``np.savez``, loaded with ``allow_pickle=False``);
- ``P.json`` — the user's metadata plus the format version, the SHA-256 of the npz bytes and the name,
  shape and dtype of every array.

Both are written atomically (temporary file in the same directory, then ``os.replace``). The json is
written last and an older json is removed before the new npz is written, so a checkpoint is complete
exactly when its json exists and matches its npz; anything else is reported as a :class:`CheckpointError`.

:func:`atomic_write_text` and :func:`atomic_write_json` are reused by the writers of result files.
"""
from __future__ import annotations

import hashlib
import io
import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from .errors import CheckpointError

#: Identifies the json of a checkpoint; bumped when the layout changes.
FORMAT_NAME = "toggle_id.checkpoint"
FORMAT_VERSION = 1

#: dtype kinds a checkpoint may hold: bool, signed/unsigned integer, float, complex.
NUMERIC_KINDS = frozenset("biufc")

# The process umask, read once at import (reading it means setting it), for the mode of new files.
_UMASK = os.umask(0o022)
os.umask(_UMASK)


# --------------------------------------------------------------------------------------------------
# atomic writes
# --------------------------------------------------------------------------------------------------

def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` so that readers see either the old file or the complete new one.

    The bytes go to a temporary file in the same directory, are flushed to disk, and the file is renamed
    over ``path`` (``os.replace``, atomic on POSIX and Windows). The new file gets the mode of the file it
    replaces, else the default mode for new files (0666 minus the umask). Returns ``path`` as a Path.
    """
    path = Path(path)
    directory = path.parent if str(path.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(dir=directory, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        try:
            mode = os.stat(path).st_mode & 0o7777
        except FileNotFoundError:
            mode = 0o666 & ~_UMASK
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    _fsync_dir(directory)
    return path


def _fsync_dir(directory: Path) -> None:
    """Best effort: make a rename in ``directory`` durable (a no-op where directories cannot be opened)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def atomic_write_text(path: str | os.PathLike, text: str, encoding: str = "utf-8") -> Path:
    """Write ``text`` to ``path`` atomically (see :func:`atomic_write_bytes`)."""
    return atomic_write_bytes(path, text.encode(encoding))


def to_jsonable(obj: Any) -> Any:
    """``obj`` with numpy scalars/arrays, tuples, sets and paths turned into plain JSON types.

    Non-finite floats (NaN, ±Inf) become ``None`` (JSON ``null``), so the output is strict JSON. Mapping
    keys become strings. Raises ``TypeError`` naming the type of anything else that JSON cannot hold.
    """
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        value = float(obj)
        return value if math.isfinite(value) else None
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return to_jsonable(obj.item())
    if isinstance(obj, Mapping):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, (set, frozenset)):
        return [to_jsonable(v) for v in sorted(obj, key=repr)]
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    raise TypeError(f"cannot write a value of type {type(obj).__name__} to JSON")


def atomic_write_json(path: str | os.PathLike, obj: Any, indent: int | None = 2) -> Path:
    """Write ``obj`` as strict JSON to ``path`` atomically (numpy converted, NaN/Inf → null)."""
    text = json.dumps(to_jsonable(obj), indent=indent, allow_nan=False, ensure_ascii=False)
    return atomic_write_text(path, text + "\n")


# --------------------------------------------------------------------------------------------------
# checkpoints
# --------------------------------------------------------------------------------------------------

def checkpoint_paths(prefix: str | os.PathLike) -> tuple[Path, Path]:
    """The ``(npz, json)`` paths of a checkpoint.

    ``prefix`` is a path without suffix (``runs/gen``), or either file of the pair (a ``.npz``/``.json``
    suffix is dropped), or an existing directory (the checkpoint is then ``<dir>/checkpoint``).
    """
    p = Path(prefix)
    if p.is_dir():
        p = p / "checkpoint"
    elif p.suffix in (".npz", ".json"):
        p = p.with_suffix("")
    return p.with_name(p.name + ".npz"), p.with_name(p.name + ".json")


def _check_arrays(arrays: Mapping[str, Any]) -> dict[str, np.ndarray]:
    """Arrays as numpy arrays; raises CheckpointError for a bad name or a non-numeric dtype."""
    if not isinstance(arrays, Mapping):
        raise CheckpointError(f"checkpoint arrays must be a dict of name → array, got {type(arrays).__name__}")
    out: dict[str, np.ndarray] = {}
    for name, value in arrays.items():
        if not isinstance(name, str) or not name or any(c in name for c in "/\\\0") or name.startswith("."):
            raise CheckpointError(f"checkpoint array name {name!r} is not usable (non-empty text, no '/', "
                                  "no backslash, not starting with '.')")
        try:
            arr = np.asarray(value)
        except ValueError as exc:  # ragged nested sequences
            raise CheckpointError(f"checkpoint array {name!r} is not a regular array ({_one_line(exc)})") from None
        if arr.dtype.kind not in NUMERIC_KINDS:
            kind = "object" if arr.dtype.kind == "O" else "non-numeric"
            raise CheckpointError(f"checkpoint array {name!r} has dtype {arr.dtype} ({kind}); "
                                  "only bool/int/float/complex arrays are stored (no pickle)")
        out[name] = arr
    return out


def save_checkpoint(prefix: str | os.PathLike, arrays: Mapping[str, Any], meta: Mapping[str, Any] | None = None
                    ) -> tuple[Path, Path]:
    """Write a checkpoint: numeric ``arrays`` to ``<prefix>.npz``, ``meta`` and checksums to ``<prefix>.json``.

    ``meta`` must be JSON-representable after :func:`to_jsonable` (NaN/Inf come back as ``None``).
    Raises CheckpointError for object/string arrays or metadata JSON cannot hold. Returns ``(npz, json)``.
    """
    npz_path, json_path = checkpoint_paths(prefix)
    arrs = _check_arrays(arrays)
    try:
        meta_json = to_jsonable(dict(meta or {}))
    except TypeError as exc:
        raise CheckpointError(f"checkpoint metadata for {json_path}: {exc}") from None
    buf = io.BytesIO()
    np.savez(buf, **arrs)
    data = buf.getvalue()
    header = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "npz": npz_path.name,
        "npz_sha256": hashlib.sha256(data).hexdigest(),
        "npz_bytes": len(data),
        "arrays": {name: {"shape": list(a.shape), "dtype": a.dtype.str} for name, a in arrs.items()},
        "meta": meta_json,
    }
    npz_path.parent.mkdir(parents=True, exist_ok=True)
    # An old json must not vouch for a half-replaced pair: drop it first, write it last.
    try:
        json_path.unlink()
    except FileNotFoundError:
        pass
    atomic_write_bytes(npz_path, data)
    atomic_write_json(json_path, header)
    return npz_path, json_path


def load_checkpoint(prefix: str | os.PathLike) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Read a checkpoint written by :func:`save_checkpoint`; returns ``(arrays, meta)``.

    Verifies the json, its format version, the SHA-256 of the npz and every array's name, shape and
    dtype; any problem raises CheckpointError with a one-line message. No pickle is ever loaded.
    """
    npz_path, json_path = checkpoint_paths(prefix)
    if not json_path.exists():
        if npz_path.exists():
            raise CheckpointError(f"checkpoint {json_path} is missing: {npz_path.name} exists without it "
                                  "(interrupted while saving?)")
        raise CheckpointError(f"checkpoint {npz_path.with_suffix('')} not found (no {json_path.name})")
    try:
        header = json.loads(json_path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CheckpointError(f"checkpoint {json_path} is unreadable or not valid JSON "
                              f"({_one_line(exc)})") from None
    _check_header(header, json_path)
    try:
        data = npz_path.read_bytes()
    except FileNotFoundError:
        raise CheckpointError(f"checkpoint {npz_path} is missing (its json exists)") from None
    except OSError as exc:
        raise CheckpointError(f"checkpoint {npz_path} is unreadable ({_one_line(exc)})") from None
    if len(data) != header["npz_bytes"] or hashlib.sha256(data).hexdigest() != header["npz_sha256"]:
        raise CheckpointError(f"checkpoint {npz_path} is truncated or tampered (sha256 mismatch; "
                              f"{len(data)} bytes, {header['npz_bytes']} expected)")
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as npz:
            arrays = {name: npz[name] for name in npz.files}
    except Exception as exc:  # numpy raises several types for a broken archive
        raise CheckpointError(f"checkpoint {npz_path} cannot be read as npz ({_one_line(exc)})") from None
    expected = header["arrays"]
    if set(arrays) != set(expected):
        raise CheckpointError(f"checkpoint {npz_path} holds arrays {sorted(arrays)}, its json lists {sorted(expected)}")
    for name, spec in expected.items():
        a = arrays[name]
        if list(a.shape) != list(spec["shape"]) or a.dtype.str != spec["dtype"]:
            raise CheckpointError(f"checkpoint {npz_path}: array {name!r} is {a.dtype.str}{list(a.shape)}, "
                                  f"its json says {spec['dtype']}{list(spec['shape'])}")
    return arrays, header["meta"]


def _check_header(header: Any, json_path: Path) -> None:
    """Raise CheckpointError unless ``header`` has the layout :func:`save_checkpoint` writes."""
    if not isinstance(header, dict) or header.get("format") != FORMAT_NAME:
        raise CheckpointError(f"checkpoint {json_path} is not a toggle_id checkpoint (format field missing)")
    if header.get("version") != FORMAT_VERSION:
        raise CheckpointError(f"checkpoint {json_path} has format version {header.get('version')!r}; "
                              f"this toggle_id reads version {FORMAT_VERSION}")
    ok = (isinstance(header.get("npz_sha256"), str) and isinstance(header.get("npz_bytes"), int)
          and isinstance(header.get("meta"), dict) and isinstance(header.get("arrays"), dict)
          and all(isinstance(s, dict) and isinstance(s.get("shape"), list) and isinstance(s.get("dtype"), str)
                  for s in header["arrays"].values()))
    if not ok:
        raise CheckpointError(f"checkpoint {json_path} is malformed (missing or mistyped fields)")


def _one_line(exc: BaseException) -> str:
    """An exception as one short line of text."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text[:200]
