"""The EMPS job end to end: `python -m jobs.run +experiment=emps` on a shortened part of the measured record,
its report, figures and MLflow runs; bad settings and missing files end in one line and a non-zero exit."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from conftest import run_job
from toggle_id.emps_job import DEFAULT_RECORD, EMPS_DEFAULTS, emps_settings, load_record
from toggle_id.errors import ConfigError, DataError

SAMPLES = 6000  # the record's first 6 s: the loop finds Coulomb friction in ~6 s of fitting
REPORT_KEYS = {"position_rel_error_pct_before", "position_rel_error_pct_after", "effects_added", "candidates",
               "identified", "published", "pct_diff_vs_published", "comparison", "idim_ls", "identifiability",
               "validation", "reference", "wall_seconds", "figures", "mlflow_run_id", "n_samples"}


@pytest.fixture(scope="module")
def emps_dir(shared: Path) -> Path:
    path = shared / "data" / "emps"
    if not (path / "emps_estimation.csv").is_file():
        pytest.skip(f"EMPS data not found in {path}")
    return path


@pytest.fixture(scope="module")
def job(emps_dir: Path, tmp_path_factory) -> dict:
    """One run of the job on the first SAMPLES samples, validated on the next 3000, tracked in a scratch store."""
    from toggle_id.emps import load_emps_csv

    tmp = tmp_path_factory.mktemp("emps_job")
    rec = load_emps_csv(emps_dir / "emps_estimation.csv")
    val = tmp / "held_out.csv"
    np.savetxt(val, np.column_stack([rec.t, rec.vir, rec.qm, rec.qg])[SAMPLES:SAMPLES + 3000], delimiter=",",
               header="t,vir,qm,qg", comments="", fmt="%.17g")
    uri = f"sqlite:///{tmp / 'mlflow.db'}"
    proc = run_job("jobs.run", "+experiment=emps", f"emps.samples={SAMPLES}", f"validation.path={val}",
                   f"hydra.run.dir={tmp / 'run'}", cwd=tmp, env={"MLFLOW_TRACKING_URI": uri})
    return {"proc": proc, "run": tmp / "run", "uri": uri}


def _one_line_error(proc) -> str:
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode != 0
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    return lines[0]


@pytest.mark.integration
def test_job_finds_coulomb_friction_and_writes_the_report(job):
    proc = job["proc"]
    assert proc.returncode == 0, proc.stderr[-3000:]
    last = [ln for ln in proc.stdout.splitlines() if ln.strip()][-1]
    report_path = Path(last.removeprefix("report: "))
    assert last.startswith("report: ") and report_path == (job["run"] / "result.json").resolve()
    rep = json.loads(report_path.read_text())
    assert REPORT_KEYS <= set(rep)
    assert rep["n_samples"] == SAMPLES
    assert rep["effects_added"][0]["name"] == "coulomb_friction"
    assert rep["identified"]["Fc"] > 5.0  # N: the benchmark's Coulomb friction is 20.4 N
    assert rep["position_rel_error_pct_after"] < 0.5 * rep["position_rel_error_pct_before"]
    assert rep["position_rel_error_pct_after"] < rep["published_model_rel_error_pct"]
    # the published values and their comparison
    assert rep["published"] == {"M": 95.1089, "Fv": 203.5034, "Fc": 20.3935, "offset": -3.1648}
    m = rep["comparison"]["M"]
    assert m["published"] == 95.1089 and abs(m["final_model_pct_diff"]) < 2.0 and abs(m["idim_ls_pct_diff"]) < 2.0
    ref = rep["comparison"]["Fc"]
    assert ref["reference_fit"] == pytest.approx(20.39, rel=0.1)
    assert ref["reference_fit_pct_diff"] == pytest.approx(100 * (ref["reference_fit"] / 20.3935 - 1))
    assert set(rep["idim_ls"]["params"]) == {"M", "Fv", "Fc", "offset"}
    # identifiability of the final model, all parameters with finite intervals on 6000 samples
    ident = rep["identifiability"]
    assert ident["param_order"] == rep["free"] and ident["m"] == SAMPLES
    assert ident["rank"] == len(rep["free"]) and ident["identifiable"]["Fc"]
    assert ident["log_mask"]["M"] and not ident["log_mask"].get("offset", False)
    # the held-out continuation: simulated in closed loop, better than the published values
    val = rep["validation"]
    assert val["status"] == 0 and val["n_samples"] == 3000
    assert 0 < val["position_rel_error_pct"] < val["published_model_rel_error_pct"]
    for name in ("response.png", "friction.png", "validation.png"):
        assert (job["run"] / name).stat().st_size > 10_000
    assert "coulomb_friction" in (job["run"] / "table.txt").read_text()


@pytest.mark.integration
def test_job_logs_a_parent_run_with_one_child_per_fit(job):
    from mlflow import MlflowClient

    assert job["proc"].returncode == 0, job["proc"].stderr[-3000:]
    rep = json.loads((job["run"] / "result.json").read_text())
    client = MlflowClient(job["uri"])
    parent = client.get_run(rep["mlflow_run_id"])
    assert parent.info.run_name == "emps" and parent.info.status == "FINISHED"
    assert parent.data.metrics["position_rel_error_pct_after"] == pytest.approx(rep["position_rel_error_pct_after"])
    children = client.search_runs([parent.info.experiment_id],
                                   filter_string=f"tags.`mlflow.parentRunId` = '{parent.info.run_id}'")
    names = sorted(r.info.run_name for r in children)
    expected = sorted(["nominal", "reference"] + [f"round{c['round']}_{c['name']}" for c in rep["candidates"]])
    assert names == expected
    accepted = {r.info.run_name for r in children if r.data.tags.get("accepted") == "True"}
    assert "round1_coulomb_friction" in accepted and len(accepted) == len(rep["effects_added"])
    arts = {a.path for a in client.list_artifacts(parent.info.run_id)}
    assert {"result.json", "table.txt", "figures"} <= arts


@pytest.mark.integration
@pytest.mark.parametrize("args,needle", [
    (["emps.path=/nonexistent/emps.csv"], "not found"),
    (["validation.path=/nonexistent/pulses.mat"], "not found"),
    (["emps.alpha=2"], "emps.alpha"),
])
def test_job_rejects_missing_files_and_bad_settings_in_one_line(tmp_path, args, needle):
    proc = run_job("jobs.run", "+experiment=emps", "tracking.enabled=false", f"hydra.run.dir={tmp_path / 'run'}",
                   *args, cwd=tmp_path, timeout=120)
    line = _one_line_error(proc)
    assert line.startswith("error: ") and needle in line
    assert not (tmp_path / "run" / "result.json").exists()


# ------------------------------------------------------------------------------------------ settings, in process
def test_settings_defaults_and_relative_paths(tmp_path):
    st = emps_settings({"emps": dict(EMPS_DEFAULTS)}, tmp_path)
    assert st.path == DEFAULT_RECORD and st.samples is None and st.validation_path is None
    assert st.candidates == ("coulomb_friction", "offset", "stribeck_friction", "asymmetric_friction")
    st = emps_settings({"emps": {"path": "rec.csv", "samples": 6000, "candidates": ["coulomb_friction"]},
                        "validation": {"path": "val.mat"}, "identifiability": {"noise_std_m": 1e-8}}, tmp_path)
    assert st.path == (tmp_path / "rec.csv").resolve() and st.validation_path == (tmp_path / "val.mat").resolve()
    assert (st.samples, st.candidates, st.noise_std_m) == (6000, ("coulomb_friction",), 1e-8)


@pytest.mark.parametrize("emps,needle", [
    ({"alpha": 0.0}, "emps.alpha"),
    ({"max_corr": 1.5}, "emps.max_corr"),
    ({"samples": 5}, "emps.samples"),
    ({"samples": True}, "emps.samples"),
    ({"max_effects": -1}, "emps.max_effects"),
    ({"candidates": ["coulomb_friction", "gravity"]}, "gravity"),
    ({"candidates": "offset"}, "emps.candidates"),
    ({"solver": "ga"}, "emps.solver"),
    ({"max_nfev": 0}, "emps.max_nfev"),
    ({"sim": {"eps": -1.0}}, "emps.sim"),
    ({"sim": {"rtol": 1e-6}}, "rtol"),
    ({"bogus": 1}, "bogus"),
])
def test_settings_reject_bad_values_in_one_line(emps, needle):
    with pytest.raises(ConfigError, match=needle) as err:
        emps_settings({"emps": emps})
    assert "\n" not in str(err.value)


def test_load_record_needs_a_known_format(tmp_path):
    with pytest.raises(DataError, match="not found"):
        load_record(tmp_path / "absent.csv")
    (tmp_path / "rec.txt").write_text("t,vir,qm,qg\n")
    with pytest.raises(DataError, match="unknown format"):
        load_record(tmp_path / "rec.txt")
