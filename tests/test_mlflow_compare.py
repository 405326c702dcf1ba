"""MLflow for comparing and reusing results (issue 20): errors in µm, one curve for every method, runs named after
what differs, only meaningful parameters, the record as a dataset, the identified model as a pyfunc model, system
metrics — checked on a tiny two-stage job as a user runs it, and (slow) through a real `mlflow server`'s REST API."""
from __future__ import annotations

import json
import math
import os
import socket
import subprocess
import sys
import time
import urllib.parse
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from conftest import ROOT, TWO_STAGE_QUICK, run_job

pytestmark = pytest.mark.filterwarnings("ignore:.*noload.*")

# a 1-s record and a tiny GA on the serial evaluator, seed 1 (conftest.TWO_STAGE_QUICK)
QUICK = TWO_STAGE_QUICK
NAME = "two_stage ga=small ga.population=16 ga.generations=3 evaluator=serial data.duration=1.0 polish.max_nfev=5 seed=1"

# Loads the logged model in a fresh interpreter (the tracking URI from the environment, as a user would) and prints
# the RMS difference (µm) between its prediction and the x_B of a record.
PREDICT = """
import json, sys
import numpy as np, pandas as pd, mlflow.pyfunc
uri, csv = sys.argv[1], sys.argv[2]
model = mlflow.pyfunc.load_model(uri)
df = pd.read_csv(csv)
out = model.predict(df[["t", "v_in"]])
print(json.dumps({"columns": list(out.columns), "rms_um": 1e6 * float(np.sqrt(np.mean((out["x_B"] - df["x_B"]) ** 2)))}))
"""


def _predict_in_fresh_process(model_uri: str, csv: Path, tracking_uri: str, cwd: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MLFLOW_TRACKING_URI": tracking_uri}
    proc = subprocess.run([sys.executable, "-c", PREDICT, model_uri, str(csv)], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _clean_record(tmp: Path) -> Path:
    """A noiseless 1-s record with the default (assigned) parameters, as `jobs.simulate out=clean.csv duration=1.0
    noise_m=0` writes it (that job's command line: tests/test_jobs.py)."""
    from toggle_id.data import write_csv
    from toggle_id.app.records import build_record

    record, _ = build_record({"source": "simulated", "duration": 1.0, "noise_m": 0.0})
    return write_csv(record, tmp / "clean.csv")


@pytest.fixture(scope="module")
def two_stage(two_stage_job):
    """The tiny two-stage job of conftest (run once for the suite), seed 1."""
    return two_stage_job


@pytest.mark.integration
def test_parent_run_reports_the_error_in_micrometres(two_stage):
    res, metrics = two_stage.result, two_stage.run.data.metrics
    assert res["rmse_m"] > 0 and res["rmse_um"] == pytest.approx(1e6 * res["rmse_m"])
    assert metrics["rmse_um"] == pytest.approx(1e6 * res["rmse_m"])
    assert metrics["rmse_m"] == pytest.approx(res["rmse_m"])  # kept beside it


@pytest.mark.integration
def test_best_rmse_curve_runs_over_all_stages_against_simulations(two_stage):
    res, client, run_id = two_stage.result, two_stage.client, two_stage.run.info.run_id
    curve = sorted(client.get_metric_history(run_id, "best_rmse_um"), key=lambda m: m.step)
    assert len(curve) >= 2
    steps, values = [m.step for m in curve], [m.value for m in curve]
    assert steps == sorted(set(steps))  # one point per step, in increasing simulation count
    assert all(b <= a for a, b in zip(values, values[1:]))  # the best so far never gets worse
    assert steps[-1] == res["n_simulations"] == sum(s["n_simulations"] for s in res["stages"])
    assert values[-1] == pytest.approx(res["rmse_um"])  # ends at the result (the joint polish's whole-record fit)
    # it spans stage 1 (whose GA spent 3 x 16 individuals), stage 2 and the polishes
    assert steps[0] == 16 and {p["stage"] for p in res["curve"]} >= {"stage1", "stage2", "joint_polish"}
    assert [p["simulations"] for p in res["curve"]] == steps
    # the paper's per-stage fitness stays on the children
    children = client.search_runs([two_stage.run.info.experiment_id],
                                  filter_string=f"tags.`mlflow.parentRunId` = '{run_id}'")
    stage1 = next(r for r in children if r.info.run_name == "stage1")
    assert [m.step for m in client.get_metric_history(stage1.info.run_id, "best_fitness")] == [1, 2, 3]


@pytest.mark.integration
def test_the_record_is_a_dataset_input(two_stage):
    from toggle_id.data import read_csv

    inputs = two_stage.run.inputs.dataset_inputs
    assert len(inputs) == 1
    ds, tags = inputs[0].dataset, {t.key: t.value for t in inputs[0].tags}
    assert tags["mlflow.data.context"] == "training" and ds.name == "simulated_simulation"
    assert ds.digest == two_stage.result["datasets"][0]["digest"]
    source = json.loads(ds.source)["uri"]
    assert Path(source) == (two_stage.tmp / "run" / "record.csv").resolve()
    rec = read_csv(source)  # the simulated record as fitted, readable by data=csv data.path=…
    assert rec.n == 1001 and json.loads(ds.schema)["mlflow_colspec"][2]["name"] == "x_B"


@pytest.mark.integration
def test_the_logged_model_predicts_a_noiseless_record_in_a_fresh_process(two_stage):
    res = two_stage.result
    assert res["model_uri"].startswith("models:/")
    model_id = res["model_uri"].removeprefix("models:/")
    assert model_id in [o.model_id for o in two_stage.run.outputs.model_outputs]
    clean = _clean_record(two_stage.tmp)
    out = _predict_in_fresh_process(res["model_uri"], clean, two_stage.uri, two_stage.tmp)
    assert out["columns"] == ["t", "x_B", "i_q"]
    # the identified model: within the run's own RMS error (against the 1-µm-noise record) + 1 µm of the truth —
    # and no better than that by more than the noise, i.e. it is this run's model and not the truth
    assert res["rmse_um"] - 1.0 <= out["rms_um"] <= res["rmse_um"] + 1.0
    assert res["seconds_model_logging"] < 10.0


@pytest.mark.integration
def test_only_meaningful_parameters_are_logged(two_stage):
    params = two_stage.run.data.params
    assert "None" not in params.values() and "[]" not in params.values()
    assert not [k for k in params if k.startswith(("data.params.", "data.effects.", "tracking.", "debug."))]
    assert params["ga.population"] == "16" and params["seed"] == "1" and params["data.duration"] == "1.0"


@pytest.mark.integration
def test_run_is_named_after_its_overrides_and_described_in_one_line(two_stage):
    run, res = two_stage.run, two_stage.result
    assert run.info.run_name == NAME
    assert "seed=1" in run.data.tags["overrides"] and "sweep" not in run.data.tags
    note = run.data.tags["mlflow.note.content"]
    assert "\n" not in note and note.startswith("two-stage identification of simulated_simulation")
    assert f"{res['rmse_um']:.4g} µm" in note


def test_fitness_figure_shows_the_ga_stages_only(tmp_path, monkeypatch):
    """The joint polish has no generations: no line "joint_polish (final n/a)" in the parent's figure."""
    from toggle_id import figures
    from toggle_id.app.job_report import write_figures
    from toggle_id.identify import IdentificationResult, StageResult
    from toggle_id.record import Record
    from toggle_id.tracking import Tracker

    saved = []
    monkeypatch.setattr(figures, "save", lambda fig, path: saved.append(fig) or str(path))
    monkeypatch.setattr(figures, "response_comparison", lambda *a, **k: None)

    def stage(name, history):
        return StageResult(name=name, free=("D",), x=np.zeros(1), theta=np.zeros(1), window=(0, 1), fitness_ga=1.0,
                           fitness=1.0, sse=1.0, history=history, generations=len(history), converged_generation=0,
                           n_evaluations=0, seconds_ga=0.0)

    result = IdentificationResult("two_stage", np.zeros(1), [stage("stage1", [1.0, 2.0]), stage("stage2", [3.0, 4.0]),
                                                            stage("joint_polish", [])], 1.0, 1.0, 1, 0.0, 0)
    write_figures(tmp_path, [Record.from_sweep("simulation", 0.1)], result, Tracker(None, "e", enabled=False),
                  "two_stage", [{"x_B": None, "F_i": None}])
    labels = [t.get_text() for t in saved[0].axes[0].get_legend().get_texts()]
    assert labels == ["stage1 (final 2)", "stage2 (final 4)"]


def test_run_names_say_what_differs():
    from toggle_id.tracking import run_name

    assert run_name("two_stage", ["+experiment=two_stage", "ga.population=200", "seed=1"]) == \
        "two_stage ga.population=200 seed=1"
    assert run_name("two_stage", ["+experiment=joint", "hydra.run.dir=/x/y", "progress=false",
                                  "data=csv", "data.path=/home/u/records/a.csv", "tracking.uri=x.db"]) == \
        "two_stage joint data=csv data.path=a.csv"
    assert run_name("discover", []) == "discover"
    assert len(run_name("x", [f"k{i}=v" for i in range(200)])) == 250


def test_curve_keeps_the_best_so_far_and_simulates_only_new_models():
    from toggle_id import params as P
    from toggle_id.curve import RmseCurve
    from toggle_id.record import Record
    from toggle_id.simulate import PRECISE, extend, simulate, simulations_run

    rec = Record.from_sweep("simulation", 0.5)
    truth = extend(P.ASSIGNED)[0]
    rec.x_B = simulate(truth[None, :], rec, PRECISE).x_B[0]
    other = truth.copy()
    other[P.INDEX["K_t"]] *= 1.05
    seen = []
    curve = RmseCurve(rec, on_point=seen.append)
    n0 = simulations_run()
    a = curve.add("s", 10, theta=other)
    b = curve.add("s", 20, theta=other)  # the same model again: no new simulation
    assert simulations_run() - n0 == 1
    c = curve.add("s", 30, theta=truth)
    d = curve.add("s", 40, theta=other)
    assert a.rmse_m > 1e-6 and b.rmse_m == a.rmse_m and c.rmse_m == pytest.approx(0.0, abs=1e-12)
    assert [p.best_rmse_m for p in (a, b, c, d)] == [a.rmse_m, a.rmse_m, c.rmse_m, c.rmse_m]
    assert [p.simulations for p in seen] == [10, 20, 30, 40] and curve.simulations == 40


def test_tracker_samples_system_metrics_on_the_outermost_run(tmp_path):
    from toggle_id.tracking import Tracker

    tr = Tracker(f"sqlite:///{tmp_path / 'mlflow.db'}", "e", system_metrics=True, system_metrics_interval_s=0.2)
    assert tr.ok, tr.error
    with tr.run("outer") as run:
        tr.log_params({"a": 1, "b": None, "c": [], "d": {"e": None, "f": 2}})
        with tr.run("inner", nested=True) as inner:
            time.sleep(1.5)
    metrics = tr.client.get_run(run.run_id).data.metrics
    assert "system/cpu_utilization_percentage" in metrics and "system/system_memory_usage_megabytes" in metrics
    assert not [k for k in tr.client.get_run(inner.run_id).data.metrics if k.startswith("system/")]
    assert tr.client.get_run(run.run_id).data.params == {"a": "1", "d.f": "2"}
    assert not tr.dropped


# ------------------------------------------------------------------------------------------ a real MLflow server
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def stop_server(server: subprocess.Popen) -> None:
    """Stop the `mlflow server` started here and the workers it spawned (its process group)."""
    import signal

    for sig, wait in ((signal.SIGTERM, 30), (signal.SIGKILL, 10)):
        try:
            os.killpg(server.pid, sig)
        except ProcessLookupError:
            return
        try:
            server.wait(timeout=wait)
            time.sleep(1.0)  # the workers leave after the server
        except subprocess.TimeoutExpired:
            continue
        try:
            os.killpg(server.pid, 0)
        except ProcessLookupError:
            return


def _get(base: str, path: str, **query) -> dict:
    url = f"{base}{path}" + (f"?{urllib.parse.urlencode(query)}" if query else "")
    with urllib.request.urlopen(url, timeout=10) as resp:
        return json.loads(resp.read().decode())


@pytest.mark.slow
def test_a_job_logged_to_an_mlflow_server_has_metrics_curve_dataset_and_model(tmp_path):
    port = _free_port()
    base = f"http://127.0.0.1:{port}"
    server = subprocess.Popen([sys.executable, "-m", "mlflow", "server", "--host", "127.0.0.1", "--port", str(port),
                               "--backend-store-uri", f"sqlite:///{tmp_path / 'server.db'}",
                               "--artifacts-destination", str(tmp_path / "artifacts"), "--workers", "1"],
                              cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                              start_new_session=True)  # its own process group: the server and its workers
    try:
        deadline = time.monotonic() + 120
        while True:
            try:
                with urllib.request.urlopen(f"{base}/health", timeout=2):
                    break
            except OSError:
                if server.poll() is not None or time.monotonic() > deadline:
                    pytest.fail(f"mlflow server did not start: {server.stderr.read()[-2000:] if server.stderr else ''}")
                time.sleep(0.5)
        proc = run_job("jobs.run", "+experiment=two_stage", f"hydra.run.dir={tmp_path / 'run'}", *QUICK, cwd=tmp_path,
                       env={"MLFLOW_TRACKING_URI": base})
        assert proc.returncode == 0, proc.stderr[-3000:]
        assert "tracking disabled" not in proc.stderr
        res = json.loads((tmp_path / "run" / "result.json").read_text())
        run = _get(base, "/api/2.0/mlflow/runs/get", run_id=res["mlflow_run_id"])["run"]
        assert run["info"]["run_name"] == NAME and run["info"]["status"] == "FINISHED"
        metrics = {m["key"]: m["value"] for m in run["data"]["metrics"]}
        assert metrics["rmse_um"] == pytest.approx(res["rmse_um"])
        history = _get(base, "/api/2.0/mlflow/metrics/get-history", run_id=res["mlflow_run_id"],
                       metric_key="best_rmse_um")["metrics"]
        assert len(history) >= 2 and max(history, key=lambda m: m["step"])["value"] == pytest.approx(res["rmse_um"])
        datasets = run["inputs"]["dataset_inputs"]
        assert [d["dataset"]["digest"] for d in datasets] == [res["datasets"][0]["digest"]]
        model_id = res["model_uri"].removeprefix("models:/")
        assert model_id in [m["model_id"] for m in run["outputs"]["model_outputs"]]
        model = _get(base, f"/api/2.0/mlflow/logged-models/{model_id}")["model"]
        assert model["info"]["source_run_id"] == res["mlflow_run_id"]
        out = _predict_in_fresh_process(res["model_uri"], _clean_record(tmp_path), base, tmp_path)
        assert out["rms_um"] <= res["rmse_um"] + 1.0 and not math.isnan(out["rms_um"])
    finally:
        stop_server(server)
