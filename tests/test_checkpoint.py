"""Checkpoints without pickle: exact round trip, every kind of damage is a one-line CheckpointError."""
from __future__ import annotations

import hashlib
import io
import json
import os
from pathlib import Path

import numpy as np
import pytest

from toggle_id import checkpoint as ck
from toggle_id.checkpoint import (atomic_write_json, atomic_write_text, checkpoint_paths, load_checkpoint,
                                  save_checkpoint, to_jsonable)
from toggle_id.errors import CheckpointError


def sample_arrays() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    return {
        "population": rng.uniform(0, 1, (20, 15)),
        "fitness": np.append(rng.normal(size=19), -np.inf),
        "status": rng.integers(0, 4, 20).astype(np.int8),
        "mask": rng.uniform(size=7) > 0.5,
        "generation": np.int64(42),
        "rng_state": rng.integers(0, 2**63, 4, dtype=np.uint64),
        "spectrum": rng.normal(size=3) + 1j * rng.normal(size=3),
        "empty": np.zeros((0, 15)),
    }


META = {"run": "stage1", "seed": np.int64(7), "best": np.float64(1.5e6), "nan": float("nan"),
        "bounds": np.array([0.0, 1.0]), "names": ("B_m", "D"), "nested": {"ok": np.bool_(True)}}


def assert_one_line_error(prefix: Path, fragment: str) -> str:
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(prefix)
    msg = str(info.value)
    assert "\n" not in msg and fragment in msg, msg
    return msg


@pytest.fixture
def saved(tmp_path: Path) -> Path:
    prefix = tmp_path / "ckpt" / "gen_0042"
    save_checkpoint(prefix, sample_arrays(), META)
    return prefix


def test_round_trip_is_exact(saved: Path) -> None:
    arrays, meta = load_checkpoint(saved)
    ref = sample_arrays()
    assert set(arrays) == set(ref)
    for name, a in ref.items():
        b = arrays[name]
        assert b.dtype == np.asarray(a).dtype and b.shape == np.shape(a), name
        assert np.array_equal(b, a), name
    assert meta == {"run": "stage1", "seed": 7, "best": 1.5e6, "nan": None, "bounds": [0.0, 1.0],
                    "names": ["B_m", "D"], "nested": {"ok": True}}
    assert sorted(os.listdir(saved.parent)) == ["gen_0042.json", "gen_0042.npz"]  # no temporaries left


def test_prefix_forms(tmp_path: Path) -> None:
    npz, js = save_checkpoint(tmp_path, {"x": np.arange(3)}, {})
    assert (npz, js) == (tmp_path / "checkpoint.npz", tmp_path / "checkpoint.json")
    assert checkpoint_paths(tmp_path / "a.b.npz") == (tmp_path / "a.b.npz", tmp_path / "a.b.json")
    for form in (tmp_path, tmp_path / "checkpoint", npz, js):
        assert np.array_equal(load_checkpoint(form)[0]["x"], np.arange(3))


def test_overwrite_replaces(saved: Path) -> None:
    save_checkpoint(saved, {"x": np.ones(2)}, {"gen": 43})
    arrays, meta = load_checkpoint(saved)
    assert list(arrays) == ["x"] and meta == {"gen": 43}


def test_truncated_npz(saved: Path) -> None:
    npz = saved.with_suffix(".npz")
    data = npz.read_bytes()
    npz.write_bytes(data[: len(data) // 2])
    assert_one_line_error(saved, "is truncated or tampered (sha256 mismatch")


def test_tampered_npz_byte(saved: Path) -> None:
    npz = saved.with_suffix(".npz")
    data = bytearray(npz.read_bytes())
    data[len(data) // 3] ^= 0x01
    npz.write_bytes(bytes(data))
    assert_one_line_error(saved, "sha256 mismatch")


def _edit_json(prefix: Path, change) -> None:
    path = prefix.with_suffix(".json")
    header = json.loads(path.read_text())
    change(header)
    path.write_text(json.dumps(header))


@pytest.mark.parametrize("change, fragment", [
    (lambda h: h.update(npz_sha256="0" * 64), "sha256 mismatch"),
    (lambda h: h.update(version=99), "format version 99"),
    (lambda h: h.pop("format"), "not a toggle_id checkpoint"),
    (lambda h: h.pop("arrays"), "malformed"),
    (lambda h: h["arrays"]["population"].update(shape=[15, 20]), "array 'population' is <f8[20, 15]"),
    (lambda h: h["arrays"]["status"].update(dtype="<f8"), "array 'status' is |i1"),
    (lambda h: h["arrays"].pop("mask"), "its json lists"),
], ids=["sha", "version", "format", "no-arrays", "shape", "dtype", "names"])
def test_tampered_json(saved: Path, change, fragment: str) -> None:
    _edit_json(saved, change)
    assert_one_line_error(saved, fragment)


def test_json_not_json(saved: Path) -> None:
    path = saved.with_suffix(".json")
    path.write_text(path.read_text()[:40])
    assert_one_line_error(saved, "not valid JSON")


def test_missing_files(saved: Path, tmp_path: Path) -> None:
    assert_one_line_error(tmp_path / "nothing_here", "not found")
    saved.with_suffix(".npz").unlink()
    assert_one_line_error(saved, "is missing (its json exists)")
    save_checkpoint(saved, {"x": np.zeros(1)}, {})
    saved.with_suffix(".json").unlink()
    assert_one_line_error(saved, "interrupted while saving")


@pytest.mark.parametrize("bad", [
    np.array([1, "a", None], dtype=object),
    np.array(["a", "b"]),
    [[1, 2], [3]],
    np.zeros(2, dtype=[("a", "f8")]),
], ids=["object", "str", "ragged", "structured"])
def test_non_numeric_arrays_refused(tmp_path: Path, bad) -> None:
    with pytest.raises(CheckpointError, match="checkpoint array 'x'"):
        save_checkpoint(tmp_path / "c", {"ok": np.zeros(2), "x": bad}, {})
    assert os.listdir(tmp_path) == []  # nothing written


def test_meta_that_json_cannot_hold_is_refused(tmp_path: Path) -> None:
    with pytest.raises(CheckpointError, match="cannot write a value of type object to JSON"):
        save_checkpoint(tmp_path / "c", {"x": np.zeros(2)}, {"bad": object()})
    assert os.listdir(tmp_path) == []


def test_forged_pickle_is_never_loaded(tmp_path: Path) -> None:
    """An npz with an object array and a json forged to match is refused, not unpickled."""
    prefix = tmp_path / "evil"
    buf = io.BytesIO()
    np.savez(buf, x=np.array([{"a": 1}], dtype=object))
    data = buf.getvalue()
    prefix.with_suffix(".npz").write_bytes(data)
    prefix.with_suffix(".json").write_text(json.dumps({
        "format": ck.FORMAT_NAME, "version": ck.FORMAT_VERSION, "npz": "evil.npz",
        "npz_sha256": hashlib.sha256(data).hexdigest(), "npz_bytes": len(data),
        "arrays": {"x": {"shape": [1], "dtype": "|O"}}, "meta": {}}))
    assert_one_line_error(prefix, "cannot be read as npz")


def test_to_jsonable_and_atomic_json(tmp_path: Path) -> None:
    obj = {1: np.float32(0.5), "a": np.array([[1, 2], [3, 4]], dtype=np.int16), "inf": -np.inf,
           "s": {3}, "p": tmp_path, "nan_arr": np.array([np.nan, 1.0])}
    path = atomic_write_json(tmp_path / "r.json", obj)
    text = path.read_text()
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text) == {"1": 0.5, "a": [[1, 2], [3, 4]], "inf": None, "s": [3], "p": str(tmp_path),
                                "nan_arr": [None, 1.0]}
    with pytest.raises(TypeError, match="complex"):
        to_jsonable({"z": 1j})


def test_atomic_write_keeps_old_file_on_failure(tmp_path: Path, monkeypatch) -> None:
    path = tmp_path / "result.json"
    atomic_write_text(path, "old")
    os.chmod(path, 0o640)

    def broken_replace(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(ck.os, "replace", broken_replace)
    with pytest.raises(OSError, match="disk full"):
        atomic_write_text(path, "new")
    monkeypatch.undo()
    assert path.read_text() == "old"
    assert os.listdir(tmp_path) == ["result.json"]  # the temporary file was removed
    atomic_write_text(path, "new")
    assert path.read_text() == "new" and (os.stat(path).st_mode & 0o777) == 0o640  # mode kept
