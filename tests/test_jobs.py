"""End-to-end tests of the jobs as a user runs them: `python -m jobs.simulate`, `python -m jobs.run`.

Each job runs at least once through its command line (:func:`conftest.run_job`: exit status, the report line,
a one-line error); the matrices of bad input run the same entry points in this process
(:func:`conftest.run_in_process`), which saves an interpreter, the imports and Ray per case.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from conftest import one_line_error, run_in_process, run_job
from toggle_id.data import read_csv, write_csv

pytestmark = pytest.mark.integration

# a 1-s record and a tiny GA on the serial evaluator: the whole job in seconds
QUICK = ["ga=small", "ga.population=16", "ga.generations=3", "evaluator=serial", "data.duration=1.0",
         "polish.max_nfev=5", "progress=false"]


def _last_line(proc) -> str:
    lines = [ln for ln in proc.stdout.splitlines() if ln.strip()]
    return lines[-1] if lines else ""


def test_simulate_job_writes_a_record(tmp_path):
    proc = run_job("jobs.simulate", "out=rec.csv", "params.K_t=0.6", "noise_m=1e-6", "seed=3", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert _last_line(proc) == f"report: {tmp_path / 'rec.csv'}"
    rec = read_csv(tmp_path / "rec.csv")
    assert rec.n == 5001 and rec.i_q is not None
    assert 0.0559 < rec.x_B.max() < 0.06


@pytest.mark.parametrize("args,needle", [
    (["out=a.csv", "params.Bogus=1"], "Bogus"),
    (["out=a.csv", "duration=-1"], "duration"),
    (["out=a.csv", "sweep=sideways"], "sweep"),
    ([], "out"),
])
def test_simulate_job_rejects_bad_arguments_in_one_line(tmp_path, args, needle):
    # in process; through the command line: tests/test_simulate.py (noise_ar=1.2)
    proc = run_in_process("jobs.simulate", *args, cwd=tmp_path)
    assert proc.returncode == 2
    assert needle in one_line_error(proc)
    assert not (tmp_path / "a.csv").exists()


def test_identify_job_two_stage_end_to_end(two_stage_job, request):
    job = two_stage_job  # `python -m jobs.run +experiment=two_stage` on a 1-s record, a tiny GA (conftest)
    if getattr(request.config.option, "loadgroup", False):
        # on a pytest-xdist worker: the tests sharing the job run on this one (built once for the suite)
        assert request.node.nodeid.endswith("@two_stage_job")
    report = Path(_last_line(job.proc).removeprefix("report: "))
    assert report == (job.tmp / "run" / "result.json").resolve()
    res = json.loads(report.read_text())
    assert res["method"] == "two_stage" and set(res["params"]) >= {"K_t", "D", "K_l"}
    assert [s["name"] for s in res["stages"]] == ["stage1", "stage2", "joint_polish"]
    assert res["stages"][0]["generations"] == 3 and len(res["stages"][0]["fitness_history"]) == 3
    assert res["fitness"] > 0 and set(res["seconds_per_stage"]) == {"stage1", "stage2", "joint_polish"}
    assert (job.tmp / "run" / "fitness_history.png").stat().st_size > 1000
    assert (job.tmp / "run" / "response.png").stat().st_size > 1000
    # MLflow: a parent run with one child per stage, fitness history as a stepped metric
    client = job.client
    exp = client.get_experiment_by_name("toggle-id")
    runs = client.search_runs([exp.experiment_id])
    parents = [r for r in runs if "mlflow.parentRunId" not in r.data.tags]
    children = [r for r in runs if r.data.tags.get("mlflow.parentRunId") == parents[0].info.run_id]
    assert len(parents) == 1
    assert sorted(r.info.run_name for r in children) == ["joint_polish", "stage1", "stage2"]
    stage1 = next(r for r in children if r.info.run_name == "stage1")
    hist = client.get_metric_history(stage1.info.run_id, "best_fitness")
    assert [m.step for m in hist] == [1, 2, 3]


def test_identify_job_on_a_csv_record(tmp_path, job_env):
    from toggle_id.app.records import build_record

    # the record jobs.simulate writes (test_simulate_job_writes_a_record); the job in process (the one-stage job's
    # command line: test_multirun_sweep_gives_one_mlflow_run_per_config)
    record, _ = build_record({"source": "simulated", "duration": 1.0, "noise_m": 1e-6})
    write_csv(record, tmp_path / "rec.csv")
    proc = run_in_process("jobs.run", "+experiment=one_stage", "data=csv", f"data.path={tmp_path / 'rec.csv'}",
                          f"hydra.run.dir={tmp_path / 'run'}", *[a for a in QUICK if not a.startswith("data.")],
                          cwd=tmp_path, env=job_env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads((tmp_path / "run" / "result.json").read_text())
    assert res["method"] == "one_stage" and "pct_error" not in res  # no truth for a measured record


def test_multirun_sweep_gives_one_mlflow_run_per_config(tmp_path, job_env):
    proc = run_job("jobs.run", "-m", "+experiment=one_stage", "ga.population=10,12",
                   f"hydra.sweep.dir={tmp_path / 'multi'}", *[a for a in QUICK if "population" not in a],
                   cwd=tmp_path, env=job_env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    from mlflow import MlflowClient

    client = MlflowClient(job_env["MLFLOW_TRACKING_URI"])
    runs = client.search_runs([client.get_experiment_by_name("toggle-id").experiment_id])
    parents = [r for r in runs if "mlflow.parentRunId" not in r.data.tags]
    pops = sorted(r.data.params["ga.population"] for r in parents)
    assert pops == ["10", "12"]
    # named after what differs, grouped under the sweep
    assert sorted(r.info.run_name.split()[1] for r in parents) == ["ga.population=10", "ga.population=12"]
    assert {r.data.tags["sweep"] for r in parents} == {str(tmp_path / "multi")}
    assert sorted(r.data.tags["sweep.job"] for r in parents) == ["0", "1"]
    assert len(list((tmp_path / "multi").glob("*/result.json"))) == 2


@pytest.mark.parametrize("args,needle", [
    (["ga.population=1"], "population"),
    (["ga.crossover_prob=1.5"], "crossover_prob"),
    (["ga.generations=-3"], "generations"),
    (["+bounds.K_l=[2e7,1e7]"], "K_l"),
    (["+bounds.K_l=[1e7,.inf]"], "K_l"),
    (["no_such_key=3"], "no_such_key"),
    (["data=csv", "data.path=/nonexistent/record.csv"], "record.csv"),
    (["method=three_stage"], "three_stage"),
])
def test_bad_configuration_fails_fast_in_one_line(tmp_path, job_env, args, needle):
    quick = [a for a in QUICK if not (a.startswith("data.") and "data=csv" in args)]
    proc = run_in_process("jobs.run", f"hydra.run.dir={tmp_path / 'run'}", *quick, *args, cwd=tmp_path, env=job_env)
    assert proc.returncode == 2 and needle in one_line_error(proc)
    assert not (tmp_path / "run" / "result.json").exists()


def test_a_mistyped_key_fails_on_the_command_line_in_one_line(tmp_path, job_env):
    proc = run_job("jobs.run", f"hydra.run.dir={tmp_path / 'run'}", *QUICK, "ga.populaton=10", cwd=tmp_path,
                   env=job_env)
    line = one_line_error(proc)
    assert proc.returncode == 2 and line.startswith("error: bad configuration") and "populaton" in line, line
    assert not (tmp_path / "run").exists()


def test_bad_csv_fails_fast_in_one_line(tmp_path, job_env):
    (tmp_path / "bad.csv").write_text("t,v_in,xB\n0,0.05,0.02\n0.001,0.05,0.02\n")
    proc = run_job("jobs.run", "data=csv", f"data.path={tmp_path / 'bad.csv'}", f"hydra.run.dir={tmp_path / 'run'}",
                   *[a for a in QUICK if not a.startswith("data.")], cwd=tmp_path, env=job_env)
    assert proc.returncode == 2 and "x_B" in one_line_error(proc)
    assert not (tmp_path / "run" / "result.json").exists()


def _good_rows(n: int = 400) -> list[str]:
    t = np.arange(n) / 1000.0
    x = 0.02 + 0.1 * t
    return [f"{a:.6f},0.05,{b:.9f}" for a, b in zip(t, x)]


BAD_CSVS = {
    "malformed": "t,v_in,x_B\n0,0.05,0.02\n0.001,abc,0.02\n",
    "empty": "",
    "header_only": "t,v_in,x_B\n",
    "missing_column": "t,v_in\n" + "\n".join(r.rsplit(",", 1)[0] for r in _good_rows()),
    "misspelt_column": "t,v_in,xb\n" + "\n".join(_good_rows()),
    "nan": "t,v_in,x_B\n" + "\n".join(_good_rows()[:50] + ["0.050000,nan,0.025"] + _good_rows()[51:]),
    "inf": "t,v_in,x_B\n" + "\n".join(_good_rows()[:50] + ["0.050000,0.05,inf"] + _good_rows()[51:]),
    "duplicated_time": "t,v_in,x_B\n" + "\n".join(_good_rows()[:10] + _good_rows()[9:]),
    "unsorted_time": "t,v_in,x_B\n" + "\n".join(_good_rows()[:10] + _good_rows()[11:12] + _good_rows()[10:11]
                                                + _good_rows()[12:]),
    "non_uniform_time": "t,v_in,x_B\n" + "\n".join(_good_rows()[:10] + ["0.010500,0.05,0.02105"] + _good_rows()[11:]),
    "millimetres": "t,v_in,x_B\n" + "\n".join(f"{r.split(',')[0]},0.05,{1000 * float(r.split(',')[2]):.6f}"
                                              for r in _good_rows()),
    "too_short_for_two_stage": "t,v_in,x_B\n" + "\n".join(_good_rows(100)),
}


@pytest.mark.parametrize("kind", sorted(BAD_CSVS))
def test_every_bad_record_is_rejected_in_one_line(tmp_path, job_env, kind):
    path = tmp_path / f"{kind}.csv"
    path.write_text(BAD_CSVS[kind])
    proc = run_in_process("jobs.run", "+experiment=two_stage", "data=csv", f"data.path={path}",
                          f"hydra.run.dir={tmp_path / 'run'}", *[a for a in QUICK if not a.startswith("data.")],
                          cwd=tmp_path, env=job_env)
    line = one_line_error(proc)
    assert proc.returncode == 2 and line.startswith("error:")
    assert not (tmp_path / "run" / "result.json").exists()


def test_unwritable_tracking_store_does_not_stop_the_job(tmp_path):
    blocker = tmp_path / "not_a_dir"
    blocker.write_text("a file where the store's directory should be")
    env = {"MLFLOW_TRACKING_URI": f"sqlite:///{blocker / 'sub' / 'mlflow.db'}"}
    proc = run_job("jobs.run", "+experiment=one_stage", f"hydra.run.dir={tmp_path / 'run'}", *QUICK,
                   cwd=tmp_path, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (tmp_path / "run" / "result.json").exists() and (tmp_path / "run" / "response.png").exists()
    assert "MLflow tracking disabled" in proc.stderr and "the job goes on" in proc.stderr


def test_table1_job_writes_markdown_and_csv(tmp_path, job_env):
    proc = run_job("jobs.run", "+experiment=table1", "table1.seeds=[0]", f"hydra.run.dir={tmp_path / 'run'}",
                   *QUICK, cwd=tmp_path, env=job_env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    md = (tmp_path / "run" / "table1.md").read_text()
    assert "one_stage" in md and "two_stage" in md and "K_l" in md
    rows = (tmp_path / "run" / "table1_runs.csv").read_text().splitlines()
    assert len(rows) == 3  # header + one run per method
    assert _last_line(proc) == f"report: {(tmp_path / 'run' / 'result.json').resolve()}"
    from mlflow import MlflowClient

    client = MlflowClient(job_env["MLFLOW_TRACKING_URI"])
    runs = client.search_runs([client.get_experiment_by_name("toggle-id").experiment_id])
    methods = [r for r in runs if r.info.run_name in ("one_stage_seed0", "two_stage_seed0")]
    assert len(methods) == 2  # each with the curve both methods share, to overlay them in Compare
    assert all(len(client.get_metric_history(r.info.run_id, "best_rmse_um")) >= 2 for r in methods)


def test_interrupted_job_resumes_to_the_uninterrupted_result(tmp_path, job_env):
    args = ["+experiment=two_stage", "checkpoint.every=1", "ga.generations=4", *QUICK[:1], *QUICK[2:]]
    args = [a for a in args if not a.startswith("ga.generations=3")]
    # the uninterrupted job and the interrupted one (as a kill would: KeyboardInterrupt) in process; the resume as
    # a user types it, in a new process
    full = run_in_process("jobs.run", *args, f"hydra.run.dir={tmp_path / 'full'}", cwd=tmp_path, env=job_env)
    assert full.returncode == 0, full.stderr[-2000:]
    with pytest.raises(KeyboardInterrupt, match="stop_after_generations=6"):
        run_in_process("jobs.run", *args, "debug.stop_after_generations=6", f"hydra.run.dir={tmp_path / 'cut'}",
                       cwd=tmp_path, env=job_env)
    assert (tmp_path / "cut" / "checkpoint.json").exists()
    assert not (tmp_path / "cut" / "result.json").exists()
    resumed = run_job("jobs.run", *args, f"resume={tmp_path / 'cut'}", f"hydra.run.dir={tmp_path / 'other'}",
                      cwd=tmp_path, env=job_env)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    a = json.loads((tmp_path / "full" / "result.json").read_text())
    b = json.loads((tmp_path / "cut" / "result.json").read_text())
    assert a["params"] == b["params"]
    assert [s["fitness_history"] for s in a["stages"]] == [s["fitness_history"] for s in b["stages"]]
    assert b["mlflow_run_id"] == json.loads((tmp_path / "cut" / "mlflow_run.json").read_text())["run_id"]
    from mlflow import MlflowClient

    client = MlflowClient(job_env["MLFLOW_TRACKING_URI"])
    runs = client.search_runs([client.get_experiment_by_name("toggle-id").experiment_id])
    parents = [r for r in runs if "mlflow.parentRunId" not in r.data.tags]
    assert len(parents) == 2  # the full run and the interrupted-then-continued run: not duplicated


def test_joint_job_fits_both_sweeps_and_reports_identifiability(tmp_path, job_env):
    # in this process: the identify job's command line is test_identify_job_two_stage_end_to_end's
    proc = run_in_process("jobs.run", "+experiment=joint", f"hydra.run.dir={tmp_path / 'run'}", *QUICK,
                          cwd=tmp_path, env=job_env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = Path(_last_line(proc).removeprefix("report: "))
    assert _last_line(proc).startswith("report: ") and report == (tmp_path / "run" / "result.json").resolve()
    res = json.loads(report.read_text())
    assert [r["name"] for r in res["records"]] == ["simulated_simulation", "simulated_experiment"]
    assert [r["n_samples"] for r in res["records"]] == [1001, 1001] and res["n_samples"] == 2002
    assert all(r["rmse_m"] > 0 and r["solver_status"] == 0 for r in res["records"])
    ident = res["identifiability"]
    assert ident["stage"] == "joint_polish" and ident["m"] == 2002
    assert set(ident) >= {"param_order", "singular_values", "rank", "null_directions", "std_errors", "ci95"}
    assert len(ident["param_order"]) == 15 and 0 < ident["rank"] <= 15
    assert [s["name"] for s in res["stages"]] == ["stage1", "stage2", "joint_polish"]
    assert len(res["stages"][0]["windows"]) == 2 and all(s["identifiability"] for s in res["stages"])
    assert "pct_error" in res  # both records are simulated from the same truth
    assert (tmp_path / "run" / "response.png").stat().st_size > 1000
    assert (tmp_path / "run" / "response_1_simulated_experiment.png").stat().st_size > 1000
    assert "joint fit of 2 records" in proc.stdout


@pytest.mark.parametrize("records,needle", [
    ("[]", "records"),
    ("[{source:tape}]", "tape"),
    ("[{sweep:simulation},{source:csv}]", "path"),
    ("[{sweep:simulation},{source:csv,path:'BAD'}]", "x_B"),
])
def test_joint_job_rejects_bad_records_in_one_line(tmp_path, job_env, records, needle):
    bad = tmp_path / "bad.csv"
    bad.write_text("t,v_in,xB\n0,0.05,0.02\n0.001,0.05,0.02\n")
    proc = run_in_process("jobs.run", "+experiment=joint", f"data.records={records.replace('BAD', str(bad))}",
                          f"hydra.run.dir={tmp_path / 'run'}", *QUICK, cwd=tmp_path, env=job_env)
    line = one_line_error(proc)
    assert proc.returncode == 2 and line.startswith("error:") and needle in line, line
    assert not (tmp_path / "run" / "result.json").exists()


def test_identifiability_study_with_a_joint_scenario(tmp_path, job_env):
    scenarios = ("[{name:sim,fixed:[]},{name:both,fixed:[],records:[simulation,experiment]},"
                 "{name:both_stage1,window:stage1,fixed:[],records:[simulation,experiment]}]")
    proc = run_job("jobs.run", "+experiment=identifiability", f"study.scenarios={scenarios}", "data.duration=1.0",
                   f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path, env=job_env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads(Path(_last_line(proc).removeprefix("report: ")).read_text())
    sim, both, stage1 = res["scenarios"]
    assert sim["report"]["m"] == 1001 and both["report"]["m"] == 2002
    assert [r["name"] for r in both["records"]] == ["simulated_simulation", "simulated_experiment"]
    assert [r["window"] for r in stage1["records"]] == [[0, 362], [0, 79]] and stage1["report"]["m"] == 441
    assert "x_B (simulation + experiment)" in (tmp_path / "run" / "identifiability.md").read_text()
