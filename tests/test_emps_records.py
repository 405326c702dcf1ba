"""Where the EMPS job finds the benchmark's records, and what it says when it does not.

The records are the benchmark's and never ship with the project: the job looks in ``emps.data_dir`` (else
``$TOGGLE_ID_EMPS_DIR``), then in the official loader's cache ``~/.nonlinear_benchmarks/EMPS/`` (and its
subfolders), and checks each file's sha256. Missing records and wrong files end the job in one line.
Tests that need the real files skip, with the job's own one-line reason, only when they are absent.
"""
from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from toggle_id.emps import data as emps_data
from toggle_id.emps.data import (
    CITATION,
    ENV_DIR,
    ESTIMATION_FILE,
    SHA256,
    VALIDATION_FILE,
    EmpsRecordsNotFound,
    find_benchmark_files,
    loader_cache_dir,
    search_places,
    sha256_of,
)
from toggle_id.app.emps import emps_settings, locate_records, run_emps
from toggle_id.errors import ConfigError, DataError

ROOT = Path(__file__).resolve().parents[1]


from conftest import EMPS_FILES as FILES, needs_records, run_in_process  # noqa: E402


def _clean_env(home: Path, **extra: str) -> dict:
    """The caller's environment with HOME replaced and no $TOGGLE_ID_EMPS_DIR (unless given in ``extra``)."""
    env = {k: v for k, v in os.environ.items() if k != ENV_DIR}
    env.update({"HOME": str(home), "PYTHONPATH": str(ROOT), "MPLCONFIGDIR": str(home / ".mpl")}, **extra)
    return env


def _job(*args: str, cwd: Path, env: dict, timeout: int = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "jobs.run", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=timeout)


def _one_line_error(proc: subprocess.CompletedProcess) -> str:
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode != 0, proc.stdout[-2000:]
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    return lines[0]


def _fake_pair(folder: Path, tag: str = "") -> dict[str, str]:
    """Two small stand-in files named like the benchmark's; returns their sha256 (to patch SHA256 with)."""
    folder.mkdir(parents=True, exist_ok=True)
    out = {}
    for name in (ESTIMATION_FILE, VALIDATION_FILE):
        (folder / name).write_bytes(f"stand-in {name} {tag}".encode())
        out[name] = sha256_of(folder / name)
    return out


# ------------------------------------------------------------------------------------------ constants
def test_hashes_and_citation_are_the_benchmark_readme_values():
    assert SHA256 == {"DATA_EMPS.mat": "6cf6814ae14618795da0101aae2bb97ff0c6351b0501b5492751b02b07facf7e",
                      "DATA_EMPS_PULSES.mat": "0eab75bb1f6b16228ee78791343a88bf9bfd9a51036ac9807d7b5fc11c0e1704"}
    assert "Janot" in CITATION and "Data Set and Reference Models of EMPS" in CITATION


def test_loader_cache_dir_follows_the_official_loader(tmp_path):
    assert loader_cache_dir({"HOME": str(tmp_path)}, "linux") == tmp_path / ".nonlinear_benchmarks" / "EMPS"
    assert loader_cache_dir({"HOME": str(tmp_path)}, "darwin") == (
        tmp_path / "Library" / "Application Support" / "nonlinear_benchmarks" / "EMPS")


# ------------------------------------------------------------------------------------------ not found
def test_job_without_records_stops_in_one_line(tmp_path):
    """`python -m jobs.run +experiment=emps` with an empty HOME and no $TOGGLE_ID_EMPS_DIR: one line naming the
    files, their source, the citation and both places to put them; non-zero exit; nothing written."""
    home = tmp_path / "home"
    home.mkdir()
    t0 = time.perf_counter()
    proc = _job("+experiment=emps", cwd=tmp_path, env=_clean_env(home))
    seconds = time.perf_counter() - t0
    line = _one_line_error(proc)
    assert line.startswith("error: ")
    for needle in (ESTIMATION_FILE, VALIDATION_FILE, "nonlinearbenchmark.org", "pip install nonlinear-benchmarks",
                   "nonlinear_benchmarks.EMPS()", "Janot, M. Gautier, M. Brunot", "Data Set and Reference Models",
                   "emps.data_dir=", ENV_DIR, str(home / ".nonlinear_benchmarks" / "EMPS")):
        assert needle in line, needle
    assert not list(tmp_path.rglob("result.json")) and not (tmp_path / "mlflow.db").exists()
    assert seconds < 60, seconds  # the process only imports and looks: no fit, no tracking


def test_lookup_fails_before_any_work_in_process(tmp_path):
    (tmp_path / "home").mkdir()
    with pytest.raises(EmpsRecordsNotFound) as err:  # before any work: no run directory, no simulation
        run_emps({"emps": {}, "tracking": {"enabled": False}}, tmp_path / "run", tmp_path,
                 env={"HOME": str(tmp_path / "home")})
    assert "\n" not in str(err.value) and not (tmp_path / "run").exists()


def test_configured_dir_is_named_in_the_message_and_must_exist(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    env = {"HOME": str(tmp_path)}
    with pytest.raises(EmpsRecordsNotFound, match=f"emps.data_dir={empty}"):
        find_benchmark_files(empty, env)
    with pytest.raises(EmpsRecordsNotFound, match=f"\\${ENV_DIR}={empty}"):
        find_benchmark_files(None, {**env, ENV_DIR: str(empty)})
    with pytest.raises(ConfigError, match="not a directory"):
        find_benchmark_files(tmp_path / "nowhere", env)
    with pytest.raises(ConfigError, match="emps.data_dir"):
        emps_settings({"emps": {"data_dir": "nowhere"}}, tmp_path)


# ------------------------------------------------------------------------------------------ wrong file
def test_wrong_file_stops_the_job_in_one_line(tmp_path):
    data = tmp_path / "data"
    _fake_pair(data)
    (tmp_path / "home").mkdir()
    # in this process (the job's command line: test_job_without_records_stops_in_one_line)
    proc = run_in_process("jobs.run", "+experiment=emps", f"emps.data_dir={data}", cwd=tmp_path,
                          env={**_clean_env(tmp_path / "home"), ENV_DIR: None})
    line = _one_line_error(proc)
    assert proc.returncode == 2 and "sha256" in line
    assert str(data / ESTIMATION_FILE) in line and SHA256[ESTIMATION_FILE] in line
    assert "nonlinearbenchmark.org" in line


def test_wrong_file_is_an_error_not_a_reason_to_look_further(tmp_path, monkeypatch):
    good = _fake_pair(tmp_path / "home" / ".nonlinear_benchmarks" / "EMPS")
    for name, digest in good.items():
        monkeypatch.setitem(emps_data.SHA256, name, digest)
    env = {"HOME": str(tmp_path / "home")}
    assert find_benchmark_files(None, env).estimation.origin == "loader cache"
    _fake_pair(tmp_path / "mine", tag="edited")
    with pytest.raises(DataError, match="sha256") as err:
        find_benchmark_files(tmp_path / "mine", env)
    assert "\n" not in str(err.value) and not isinstance(err.value, EmpsRecordsNotFound)


# ------------------------------------------------------------------------------------------ search order
def test_search_order_configured_dir_then_env_then_cache(tmp_path, monkeypatch):
    home = tmp_path / "home"
    cache = home / ".nonlinear_benchmarks" / "EMPS"
    digests = _fake_pair(cache)
    for d in ("cfg", "env"):
        _fake_pair(tmp_path / d)  # same bytes: same digests
    for name, digest in digests.items():
        monkeypatch.setitem(emps_data.SHA256, name, digest)
    env = {"HOME": str(home), ENV_DIR: str(tmp_path / "env")}
    f = find_benchmark_files(tmp_path / "cfg", env)
    assert (f.estimation.origin, f.estimation.path.parent) == ("emps.data_dir", (tmp_path / "cfg").resolve())
    f = find_benchmark_files(None, env)
    assert (f.estimation.origin, f.validation.origin) == (f"${ENV_DIR}", f"${ENV_DIR}")
    f = find_benchmark_files(None, {"HOME": str(home)})
    assert f.estimation.origin == "loader cache" and f.estimation.path.parent == cache.resolve()
    assert [p.origin for p in search_places(tmp_path / "cfg", env)][0] == "emps.data_dir"  # env ignored then
    # only the validation file in the configured dir: the estimation file comes from the cache
    (tmp_path / "cfg" / ESTIMATION_FILE).unlink()
    f = find_benchmark_files(tmp_path / "cfg", env)
    assert (f.estimation.origin, f.validation.origin) == ("loader cache", "emps.data_dir")


def test_cache_subfolder_is_searched(tmp_path, monkeypatch):
    home = tmp_path / "home"
    digests = _fake_pair(home / ".nonlinear_benchmarks" / "EMPS" / "EMPS")
    for name, digest in digests.items():
        monkeypatch.setitem(emps_data.SHA256, name, digest)
    f = find_benchmark_files(None, {"HOME": str(home)})
    assert f.estimation.path.parent.name == "EMPS" and f.estimation.path.parent.parent.name == "EMPS"


def test_validation_record_absent_or_switched_off(tmp_path, monkeypatch):
    home = tmp_path / "home"
    cache = home / ".nonlinear_benchmarks" / "EMPS"
    digests = _fake_pair(cache)
    for name, digest in digests.items():
        monkeypatch.setitem(emps_data.SHA256, name, digest)
    env = {"HOME": str(home)}
    src = locate_records(emps_settings({"emps": {}}, tmp_path), env)
    assert src["estimation"]["found_in"] == "loader cache" and src["validation"]["file"] == VALIDATION_FILE
    assert src["estimation"]["sha256_verified"] and src["validation"]["sha256_verified"]
    assert "skipped" in locate_records(emps_settings({"emps": {"validate": False}}, tmp_path), env)["validation"]
    (cache / VALIDATION_FILE).unlink()
    src = locate_records(emps_settings({"emps": {}}, tmp_path), env)
    assert VALIDATION_FILE in src["validation"]["skipped"] and "\n" not in src["validation"]["skipped"]
    with pytest.raises(EmpsRecordsNotFound, match=VALIDATION_FILE):
        find_benchmark_files(None, env, require_validation=True)


def test_own_record_needs_no_hash(tmp_path):
    own = tmp_path / "mine.csv"
    own.write_text("t,vir,qm,qg\n")
    src = locate_records(emps_settings({"emps": {"path": str(own)}}, tmp_path), {"HOME": str(tmp_path)})
    assert src["estimation"]["found_in"] == "emps.path" and not src["estimation"]["sha256_verified"]
    assert "skipped" in src["validation"]
    with pytest.raises(DataError, match="not found"):
        locate_records(emps_settings({"emps": {"path": "absent.mat"}}, tmp_path), {"HOME": str(tmp_path)})


# ------------------------------------------------------------------------------------------ the real files
@needs_records
def test_real_records_found_in_the_loader_cache(tmp_path):
    """A temporary HOME with the two files linked into ~/.nonlinear_benchmarks/EMPS/ (and, separately, into a
    subfolder of it), no $TOGGLE_ID_EMPS_DIR: found, verified, and the benchmark's validation record beside an
    ``emps.path`` that is the benchmark's estimation file."""
    for home, sub in ((tmp_path / "h1", ()), (tmp_path / "h2", ("EMPS.unzipped",))):
        cache = home.joinpath(".nonlinear_benchmarks", "EMPS", *sub)
        cache.mkdir(parents=True)
        for f in (FILES.estimation, FILES.validation):
            (cache / f.name).symlink_to(f.path)
        found = find_benchmark_files(None, {"HOME": str(home)}, require_validation=True)
        assert found.estimation.origin == found.validation.origin == "loader cache"
        assert found.estimation.sha256 == SHA256[ESTIMATION_FILE]
        assert found.validation.sha256 == SHA256[VALIDATION_FILE]
    src = locate_records(emps_settings({"emps": {"path": str(FILES.estimation.path)}}, tmp_path), {})
    assert src["estimation"]["sha256_verified"] and src["validation"]["file"] == VALIDATION_FILE


@needs_records
def test_job_finds_the_records_in_the_loader_cache(tmp_path):
    """The job as a user runs it after `nonlinear_benchmarks.EMPS()`: HOME with the cache, no configuration (in
    this process; the EMPS job's command line: test_job_without_records_stops_in_one_line and
    tests/test_emps_job.py)."""
    home = tmp_path / "home"
    cache = home / ".nonlinear_benchmarks" / "EMPS"
    cache.mkdir(parents=True)
    for f in (FILES.estimation, FILES.validation):
        (cache / f.name).symlink_to(f.path)
    proc = run_in_process("jobs.run", "+experiment=emps", "emps.samples=3000", "emps.candidates=[coulomb_friction]",
                          "emps.reference_fit=false", "identifiability.enabled=false", "tracking.enabled=false",
                          f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path, env={**_clean_env(home), ENV_DIR: None})
    assert proc.returncode == 0, proc.stderr[-3000:]
    import json

    rep = json.loads((tmp_path / "run" / "result.json").read_text())
    assert rep["data"]["estimation"]["found_in"] == "loader cache"
    assert rep["data"]["validation"]["sha256"] == SHA256[VALIDATION_FILE]
    assert rep["validation"]["n_samples"] == 24841 and rep["validation"]["has_pulses"]
    assert "validation DATA_EMPS_PULSES" in proc.stdout
