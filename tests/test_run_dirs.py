"""No job writes into another's directory: unique run directories, checkpoints that name their job, claimed dirs."""
from __future__ import annotations

import json
import re
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT, one_line_error, run_in_process, run_job

from jobs import _cli
from toggle_id import jobdir
from toggle_id.checkpoint import save_checkpoint
from toggle_id.errors import CheckpointError, ConfigError
from toggle_id.record import Record

# a 1-s record and a tiny GA on the serial evaluator (as in test_jobs)
QUICK = ["+experiment=two_stage", "ga=small", "ga.population=16", "ga.generations=3", "evaluator=serial",
         "data.duration=1.0", "polish.max_nfev=5", "progress=false", "tracking.enabled=false"]


# ------------------------------------------------------------------------------------------ unique directories
def test_unique_dir_never_reuses_an_existing_directory(tmp_path, monkeypatch):
    base = str(tmp_path / "outputs" / "2030-01-01" / "12-00-00")
    draws = iter(["aaaaaa", "aaaaaa", "bbbbbb"])
    monkeypatch.setattr(_cli.secrets, "token_hex", lambda n: next(draws))
    first = _cli.unique_dir(base)
    second = _cli.unique_dir(base)  # draws the taken name again, then a free one
    assert (first, second) == (f"{base}-aaaaaa", f"{base}-bbbbbb")
    assert Path(first).is_dir() and Path(second).is_dir()


def test_unique_dirs_from_many_threads_in_the_same_second_are_distinct(tmp_path):
    base = str(tmp_path / "outputs" / "2030-01-01" / "12-00-00")
    got: list[str] = []
    threads = [threading.Thread(target=lambda: got.append(_cli.unique_dir(base))) for _ in range(32)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(set(got)) == 32
    assert sorted(p.name for p in Path(base).parent.iterdir()) == sorted(Path(p).name for p in got)


def _hydra_dirs(tmp_path, monkeypatch, overrides=()) -> tuple[str, str]:
    from hydra import compose, initialize_config_dir

    monkeypatch.chdir(tmp_path)
    with initialize_config_dir(config_dir=_cli.CONF_DIR, version_base="1.3"):
        cfg = compose(config_name="config", overrides=list(overrides), return_hydra_config=True)
    return str(cfg.hydra.run.dir), str(cfg.hydra.sweep.dir)


def test_each_job_gets_its_own_run_and_sweep_directory(tmp_path, monkeypatch):
    a_run, a_sweep = _hydra_dirs(tmp_path, monkeypatch)
    b_run, b_sweep = _hydra_dirs(tmp_path, monkeypatch)
    pattern = r"(outputs|multirun)/\d{4}-\d\d-\d\d/\d\d-\d\d-\d\d-[0-9a-f]{6}"
    for d in (a_run, b_run, a_sweep, b_sweep):
        assert re.fullmatch(pattern, d), d
        assert (tmp_path / d).is_dir()  # created by the resolver, before Hydra writes anything
    assert a_run != b_run and a_sweep != b_sweep


def test_composing_the_command_line_creates_no_directory(tmp_path, monkeypatch):
    from hydra import compose, initialize_config_dir

    monkeypatch.chdir(tmp_path)
    with initialize_config_dir(config_dir=_cli.CONF_DIR, version_base="1.3"):
        compose(config_name="config", overrides=["seed=3"], return_hydra_config=True)  # what _cli.precheck does
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------------------ job identity
def _record(noise: float = 0.0) -> Record:
    rec = Record.from_sweep("simulation", 0.2, 1000.0)
    rec.x_B = np.linspace(0.02, 0.03, rec.n) + noise
    return rec


CFG = {"job": "identify", "method": "two_stage", "seed": 0, "ga": {"population": 16, "generations": 3},
       "fixed": {}, "bounds": {}, "evaluator": {"kind": "serial"}, "tracking": {"enabled": False},
       "progress": True, "checkpoint": {"every": 5}, "resume": None, "run_dir": "/x", "debug": {},
       "data": {"source": "simulated", "duration": 0.2}}


def _checkpoint(run_dir: Path, identity: dict | None) -> None:
    meta = {"stage": "stage1", "ga": {}, "done": []}
    if identity is not None:
        meta[jobdir.META_KEY] = identity
    save_checkpoint(run_dir / "checkpoint", {"x": np.arange(3)}, meta)


def test_identity_ignores_what_does_not_change_the_result():
    ident = jobdir.job_identity(CFG, [_record()])
    same = {**CFG, "evaluator": {"kind": "ray", "n_workers": 2}, "progress": False, "run_dir": "/y",
            "checkpoint": {"every": 1}, "debug": {"stop_after_generations": 2}, "tracking": {"enabled": True}}
    assert jobdir.job_identity(same, [_record()]) == ident
    assert jobdir.job_identity({**CFG, "seed": 1}, [_record()])["config_sha256"] != ident["config_sha256"]
    assert jobdir.job_identity(CFG, [_record(1e-9)])["record_sha256"] != ident["record_sha256"]
    assert jobdir.job_identity(CFG, [_record(), _record()])["record_sha256"] != ident["record_sha256"]


def test_resume_of_the_same_job_is_accepted(tmp_path):
    ident = jobdir.job_identity(CFG, [_record()])
    _checkpoint(tmp_path, json.loads(json.dumps(ident)))
    jobdir.check_resume(tmp_path, jobdir.job_identity({**CFG, "evaluator": {"kind": "ray"}}, [_record()]))


@pytest.mark.parametrize("other,record,fragments", [
    ({"seed": 1}, _record(), ["the settings differ", "seed 0 there, 1 here"]),
    ({"ga": {"population": 20, "generations": 3}}, _record(), ["ga.population 16 there, 20 here"]),
    ({}, _record(1e-6), ["the record differs", "sha256"]),
    ({"seed": 2}, _record(1e-6), ["seed 0 there, 2 here", "the record differs"]),
])
def test_resume_of_another_jobs_checkpoint_is_refused_in_one_line(tmp_path, other, record, fragments):
    _checkpoint(tmp_path, jobdir.job_identity(CFG, [_record()]))
    with pytest.raises(CheckpointError) as info:
        jobdir.check_resume(tmp_path, jobdir.job_identity({**CFG, **other}, [record]))
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith(f"resume={tmp_path}: its checkpoint belongs to another job")
    for fragment in fragments:
        assert fragment in msg, msg


def test_a_checkpoint_that_does_not_name_its_job_is_refused(tmp_path):
    _checkpoint(tmp_path, None)
    with pytest.raises(CheckpointError, match="does not say which job wrote it"):
        jobdir.check_resume(tmp_path, jobdir.job_identity(CFG, [_record()]))


# ------------------------------------------------------------------------------------------ claims
_HOLD = """
import sys, time
sys.path.insert(0, {root!r})
from toggle_id import jobdir
jobdir.claim(sys.argv[1])
print("held", flush=True)
time.sleep(60)
"""


def test_a_directory_in_use_by_another_running_job_is_refused(tmp_path):
    holder = subprocess.Popen([sys.executable, "-c", _HOLD.format(root=str(ROOT)), str(tmp_path)],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(ConfigError, match=rf"in use by another running job \(pid {holder.pid}\)"):
            jobdir.claim(tmp_path)
    finally:
        holder.kill()
        holder.wait()
    assert jobdir.claim(tmp_path) == tmp_path.resolve()  # free again once that job has ended
    assert jobdir.claim(tmp_path) == tmp_path.resolve()  # and claiming it again in this process is a no-op
    jobdir.release(tmp_path)


# ------------------------------------------------------------------------------------------ the job, end to end
@pytest.mark.integration
def test_the_job_refuses_to_resume_another_jobs_checkpoint(tmp_path, job_env):
    # the interrupted job in this process (as a kill would: KeyboardInterrupt); one refusal through the command
    # line, the other in this process
    with pytest.raises(KeyboardInterrupt, match="stop_after_generations=2"):
        run_in_process("jobs.run", *QUICK, "checkpoint.every=1", "debug.stop_after_generations=2",
                       f"hydra.run.dir={tmp_path / 'cut'}", cwd=tmp_path, env=job_env)
    assert (tmp_path / "cut" / "checkpoint.json").exists()
    before = (tmp_path / "cut" / "checkpoint.npz").read_bytes()
    for runner, change, needle in ((run_job, "seed=1", "seed 0 there, 1 here"),
                                   (run_in_process, "data.noise_seed=5", "the record differs")):
        proc = runner("jobs.run", *QUICK, "checkpoint.every=1", change, f"resume={tmp_path / 'cut'}",
                      cwd=tmp_path, env=job_env)
        line = one_line_error(proc)
        assert proc.returncode == 2 and "its checkpoint belongs to another job" in line and needle in line, line
    assert (tmp_path / "cut" / "checkpoint.npz").read_bytes() == before  # left as it was
    assert not (tmp_path / "cut" / "result.json").exists()
    runs = [p for p in (tmp_path / "outputs").glob("*/*") if p.is_dir()]
    assert len(runs) == 2  # each refused job had its own directory, none wrote into the other's


@pytest.mark.slow
@pytest.mark.integration
def test_five_jobs_started_together_keep_their_directories_results_and_mlflow_runs(tmp_path, job_env):
    """Five jobs from one checkout in the same second, on one fresh SQLite MLflow store (as the embedded default)."""
    import os

    from mlflow import MlflowClient

    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]), **job_env}
    args = [a for a in QUICK if not a.startswith("tracking.")]
    procs = [subprocess.Popen([sys.executable, "-m", "jobs.run", *args, f"seed={seed}"], cwd=tmp_path, env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for seed in range(5)]
    outs = [p.communicate(timeout=900) for p in procs]
    for p, (out, err) in zip(procs, outs):
        assert p.returncode == 0, err[-3000:]
        assert "tracking disabled" not in err, err[-3000:]
    reports = [Path(out.strip().splitlines()[-1].removeprefix("report: ")) for out, _ in outs]
    dirs = {r.parent for r in reports}
    assert len(dirs) == 5 and dirs == {p for p in (tmp_path / "outputs").glob("*/*") if p.is_dir()}
    results = [json.loads(r.read_text()) for r in reports]
    assert [res["config"]["seed"] for res in results] == list(range(5))
    client = MlflowClient(job_env["MLFLOW_TRACKING_URI"])
    runs = client.search_runs([client.get_experiment_by_name("toggle-id").experiment_id])
    parents = {r.info.run_id: r for r in runs if "mlflow.parentRunId" not in r.data.tags}
    assert len(parents) == 5
    for res in results:
        run = parents[res["mlflow_run_id"]]
        assert run.info.status == "FINISHED" and run.data.params["seed"] == str(res["config"]["seed"])
