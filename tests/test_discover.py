"""The discovery loop end to end: on records with a known undeclared effect (or none), through the discover job, on
every library effect (slow) and on the classes of measured data (slow).

Fast tests run on a shortened record (the free motion, ~0.36 s, and the start of the clamp) with the nominal
fit started from the true nominal parameters perturbed by a few per cent (no GA); the 5-s records are marked slow.
Its steps in isolation: test_discovery_screening.py (scores, scouts, which candidates are refitted),
test_discovery_starts.py (refits from other starts), test_discovery_judge.py (the judge and the noise models),
test_discovery_model.py (the model, its gauge and domains); shared cases: discovery_cases.py.
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from toggle_id import discovery as D
from toggle_id.effects import ALL_INDEX, EFFECTS, EFFECTS_BY_NAME
from toggle_id.errors import ConfigError
from toggle_id.params import ASSIGNED, PARAM_NAMES
from toggle_id.record import Record
from toggle_id.simulate import PRECISE, simulate

from discovery_cases import FAST, NOISE, SUBSET, discover_on, make_record


# ---------------------------------------------------------------------------------------------- the loop
def test_no_effect_no_false_positive():
    res, _ = discover_on({}, candidates=None, max_effects=2)
    assert res.effects_added == []
    assert res.rmse_after_m == res.rmse_before_m < 1.1 * NOISE
    assert not res.unexplained and "no effect of the library is supported" in res.conclusion
    d = res.to_dict()
    assert d["residual_tests_after"]["whiteness"]["p_value"] > 0.01
    assert d["residual_tests_after"]["lines"]["lines"] == [] and "line at" not in res.conclusion
    assert not d["residual_tests_after"]["periodic"]["periodic"] and "repeats" not in res.conclusion
    assert {c["name"] for c in d["candidates"]} == {e.name for e in EFFECTS}
    # white noise: the prediction-error fits are the least-squares ones, and the report says so
    from toggle_id.discovery.report import summary_text

    assert d["fits_minimise_under"]["kind"] == "white" and "final fit: least squares" in summary_text(res)
    conv = d["residual_tests_after"]["localisation"]["convergence"]
    assert conv["converged"] and conv["dof"] >= 10 and "final fit converged" in summary_text(res)
    # where the loop's time went: the phases add up to its seconds and simulations (exclusive, "other" the rest)
    phases = {r["phase"]: r for r in d["time_by_phase"]}
    assert {"baseline polish", "score tests", "scouts", "refits", "verdict rules"} <= set(phases)
    assert sum(r["simulations"] for r in phases.values()) == res.n_simulations
    assert sum(r["seconds"] for r in phases.values()) == pytest.approx(res.seconds, rel=1e-6)
    assert phases["baseline polish"]["simulations"] > 0 and phases["refits"]["simulations"] > 0
    assert "where the loop's time went: " in summary_text(res)
    json.dumps(d)


def test_glitches_of_the_measurement_are_named_and_left_out(tmp_path, monkeypatch):
    """Three encoder glitches of 40 σ on a record with a sensor offset: found at their samples, left out of every
    fit and test (with them in, the error after could not fall below ≈ 2.4 σ on these 1001 samples), named in the
    report and its conclusion; the offset is found as without them."""
    from toggle_id.discovery.report import summary_text

    rec, truth, start = make_record({"x_off": 5e-5})
    where = [150, 480, 820]
    rec.x_B[where] += np.array([40.0, -40.0, 40.0]) * NOISE
    res = D.discover(rec, nominal=start, settings=D.DiscoverSettings(candidates=("sensor_offset",), **FAST))
    g = res.to_dict()["glitches"]
    assert [x["indices"] for x in g] == [where] and g[0]["count"] == 3
    assert [a["name"] for a in res.effects_added] == ["sensor_offset"]
    assert res.effects_added[0]["params"]["x_off"] == pytest.approx(5e-5, rel=0.05)
    assert res.rmse_after_m < 1.1 * NOISE
    assert "3 sample(s) of test jump away from their neighbours" in res.conclusion
    assert "glitches left out (test): 3 sample(s) at t = 0.150, 0.480, 0.820 s" in summary_text(res)
    from toggle_id import figures
    from toggle_id.discovery.report import write_figures

    drawn = []  # the job's figures, not rendered here (tests/test_residuals.py renders each kind)
    monkeypatch.setattr(figures, "save", lambda fig, path, **kw: (figures.close(fig), drawn.append(Path(path).name)))
    write_figures(tmp_path, rec, res, D.DiscoverSettings(**FAST))
    assert "glitches.png" in drawn
    clean = D.discover(make_record({})[0], nominal=start, settings=D.DiscoverSettings(
        candidates=("sensor_offset",), **{**FAST, "max_effects": 0}))
    assert [x["count"] for x in clean.to_dict()["glitches"]] == [0] and "glitch" not in clean.conclusion


def test_a_tone_in_the_noise_is_named_as_a_line_not_taken_for_an_effect():
    """Mains-like interference on the sensor: a 200-Hz tone of 1.5 σ on a record with no effect. No effect (the
    periodic cogging torque offered) is accepted; the conclusion names the line, its frequency within one Welch
    bin (7.8 Hz on 1001 samples) and its amplitude (without the tone: test_no_effect_no_false_positive)."""
    from toggle_id.discovery.report import summary_text

    rec, truth, start = make_record({})
    rec.x_B = rec.x_B + 1.5 * NOISE * np.sin(2 * np.pi * 200.0 * rec.t + 0.3)
    res = D.discover(rec, nominal=start, settings=D.DiscoverSettings(
        candidates=("cogging_torque", "sensor_offset"), **FAST))
    assert res.effects_added == [] and not res.unexplained
    lines = res.to_dict()["residual_tests_after"]["lines"]["lines"]
    assert len(lines) == 1 and abs(lines[0]["frequency_hz"] - 200.0) < 7.9
    assert lines[0]["amplitude_m"] == pytest.approx(1.5 * NOISE, rel=0.15)
    assert "The noise carries a line at" in res.conclusion and "lines in the final residual" in summary_text(res)


@pytest.mark.slow
def test_a_scale_error_is_named_by_its_pitch():
    """A linear scale's interpolation error (the sensor reads x_B + a·sin(2π·x_B/p + φ), p = 2 mm, a = 2 σ) on a
    record with no effect: the report names the pitch and the amplitude the model leaves, whatever the loop did."""
    from toggle_id.discovery.report import summary_text

    rec, truth, start = make_record({})
    rec.x_B = rec.x_B + 2.0 * NOISE * np.sin(2 * np.pi * rec.x_B / 0.002 + 0.3)
    res = D.discover(rec, nominal=start, settings=D.DiscoverSettings(
        candidates=("cogging_torque", "sensor_offset"), **FAST))
    found = res.to_dict()["residual_tests_after"]["periodic"]
    assert found["periodic"] and found["strongest"] == "x_B"
    assert found["families"]["x_B"]["period"] == pytest.approx(0.002, rel=0.02)
    assert "repeats every 2" in res.conclusion and "periodic in a position" in summary_text(res)


def test_a_validation_record_the_model_cannot_predict_leaves_it_unexplained():
    # the fitted record has no effect; the second record of "the same machine" has a dead time the first cannot
    # show (an effect its command does not excite, say): the nominal model fits the first to its noise and
    # predicts the second with structure left — the report must say the model still lacks something
    rec, truth, start = make_record({})
    other = Record.from_sweep("simulation", 1.0, name="second")
    shifted = truth.copy()
    shifted[ALL_INDEX["tau_d"]] = 2e-3
    other.x_B = simulate(shifted[None, :], other, PRECISE).x_B[0] + NOISE * np.random.default_rng(9).standard_normal(
        other.n)
    settings = D.DiscoverSettings(candidates=("sensor_offset",), **FAST)
    res = D.discover(rec, nominal=start, settings=settings, validation=other)
    pred = res.to_dict()["validation_prediction"]
    assert pred["record"] == "second" and pred["rmse_m"] > 2 * NOISE and pred["structure_left"]
    assert res.unexplained and "validation record second is not predicted to its noise" in res.conclusion
    # the same record as its own validation is predicted to the noise
    res2 = D.discover(rec, nominal=start, settings=settings, validation=rec)
    assert not res2.to_dict()["validation_prediction"]["structure_left"] and not res2.unexplained


def test_a_prediction_error_is_set_against_the_parameters_uncertainty(monkeypatch):
    """parameter_part on linear stand-ins: the fitted record sees the first parameter direction well and the second
    barely; the validation record sees both. A parameter error drawn from the fit's own covariance explains the
    validation residual within its uncertainty (p-values spread over (0, 1), few below the level); the same
    error ten times the fit's standard errors along the well-seen direction is beyond it."""
    import toggle_id.discovery.residual as RS
    from toggle_id.discovery.noise import fit_noise

    rng = np.random.default_rng(0)
    n, sig = 3000, 1e-6
    t = np.linspace(0.0, 3.0, n)
    J_e = np.column_stack([np.sin(2 * np.pi * t), 1e-3 * np.cos(2 * np.pi * 0.3 * t)]) * 1e-5
    J_v = np.column_stack([np.sin(2 * np.pi * t + 0.2), np.cos(2 * np.pi * 0.3 * t)]) * 1e-5

    class Stand:  # a record's model: its sensitivities J (set below) and residual r
        def __init__(self, r):
            self.r = r

    monkeypatch.setattr(RS, "sensitivities", lambda m, th, free, step: m.J)
    cov_e = sig ** 2 * np.linalg.inv(J_e.T @ J_e)
    settings = D.DiscoverSettings()
    p_values, beyond = [], 0
    for k in range(40):
        fit, val = Stand(sig * rng.standard_normal(n)), Stand(None)
        fit.J, val.J = J_e, J_v
        eps = rng.multivariate_normal(np.zeros(2), cov_e)
        r_v = J_v @ eps + sig * rng.standard_normal(n)
        out = RS.parameter_part(fit, ("a", "b"), fit.r, fit_noise(fit.r), val, np.zeros(3), r_v, settings)
        p_values.append(out["p_value"])
        beyond += out["beyond"]
    assert beyond <= 2 and 0.2 < np.median(p_values) < 0.8, (beyond, np.median(p_values))
    eps = np.array([10 * np.sqrt(cov_e[0, 0]), 0.0])
    out = RS.parameter_part(fit, ("a", "b"), fit.r, fit_noise(fit.r), val, np.zeros(3),
                            J_v @ eps + sig * rng.standard_normal(n), settings)
    assert out["beyond"] and out["explained_rms_m"] > 0.5 * np.sqrt(np.mean((J_v @ eps) ** 2))


def test_a_second_route_runs_only_when_structure_is_left_and_the_better_route_is_reported():
    from toggle_id.discovery.report import summary_text

    # the first nominal fit is far off and its baseline polish is cut short (no candidates: the guards of a refit
    # would re-polish it), so structure is left: the loop runs again from the second nominal fit (the truth here)
    # and reports that route; a route whose baseline lands in a basin already tried is skipped, and with nothing
    # left to explain no further nominal fit is even made
    # the far baseline stops at ≈ 10 µm, a residual the families of the structure test (each basis after the
    # sensitivities) would call noise: the convergence check says its own parameters still explain it
    rec, truth, start = make_record({})
    far = start * np.exp(0.4 * np.random.default_rng(3).standard_normal(len(start)))
    settings = D.DiscoverSettings(candidates=(), **{**FAST, "baseline_nfev": 4, "rounds": 1})
    made = []

    def second():
        made.append("truth")
        return truth

    res = D.discover(rec, nominal=far, settings=settings, label="far", alternatives=[("truth", second),
                                                                                      ("again", truth)])
    routes = res.to_dict()["routes"]
    assert made == ["truth"] and [r["label"] for r in routes] == ["far", "truth", "again"]
    assert routes[0]["structure_left"] and not routes[1]["structure_left"] and routes[1]["chosen"]
    assert routes[0]["rmse_after_m"] > 5 * NOISE  # stopped far from its minimum
    assert "basin of route truth" in routes[2]["skipped"]
    assert res.rmse_after_m < 1.1 * NOISE < res.to_dict()["routes"][0]["rmse_after_m"] and not res.unexplained
    assert "from the truth nominal fit it reached a better model" in res.conclusion
    assert "route truth (reported)" in summary_text(res) and "route again: skipped" in summary_text(res)
    json.dumps(res.to_dict())
    alone = D.discover(rec, nominal=far, settings=dataclasses.replace(settings, routes="never"))
    assert alone.unexplained and "The final fit had not converged" in alone.conclusion
    assert "final fit NOT converged" in summary_text(alone)
    made.clear()
    quiet = D.discover(rec, nominal=truth, settings=settings, alternatives=[("truth", second)])
    assert made == [] and len(quiet.to_dict()["routes"]) == 1 and not quiet.unexplained


def test_the_loop_starts_no_route_once_its_time_budget_is_spent_and_says_so():
    # the first route of the case above, on a budget it spends at once: the route from the truth is never made,
    # the report lists it as skipped for the budget and the conclusion says a route was left untried
    rec, truth, start = make_record({})
    far = start * np.exp(0.4 * np.random.default_rng(3).standard_normal(len(start)))
    settings = D.DiscoverSettings(candidates=(), max_seconds=1e-3, **{**FAST, "baseline_nfev": 4, "rounds": 1})
    made = []
    res = D.discover(rec, nominal=far, settings=settings, label="far",
                     alternatives=[("truth", lambda: made.append("truth") or truth)])
    routes = res.to_dict()["routes"]
    assert made == [] and [r["label"] for r in routes] == ["far", "truth"] and routes[0]["chosen"]
    assert "time budget (discover.max_seconds = 0.001 s)" in routes[1]["skipped"]
    assert "time budget (discover.max_seconds = 0.001 s) was spent before the route from the truth" in res.conclusion
    with pytest.raises(ConfigError, match="max_seconds"):
        D.DiscoverSettings(max_seconds=0).validate()


def test_an_alternative_route_far_above_the_first_is_skipped_before_its_loop():
    # the first route's baseline comes from its further start (the truth here, as a job's reference values);
    # an alternative far off polishes alone to many times that error and is skipped before its loop, saying so;
    # with the limit off (route_max_ratio=0) its loop runs, to no avail
    rec, truth, start = make_record({})
    rng = np.random.default_rng(3)
    far, far2 = (start * np.exp(0.4 * rng.standard_normal(len(start))) for _ in range(2))
    settings = D.DiscoverSettings(candidates=(), routes="always", **{**FAST, "baseline_nfev": 4, "rounds": 1})
    limited = D.discover(rec, nominal=far2, starts=[truth], settings=settings, label="far2",
                         alternatives=[("far", far)]).to_dict()["routes"]
    assert [r["label"] for r in limited] == ["far2", "far"] and limited[0]["chosen"]
    assert limited[0]["baseline_rmse_m"] < 1.1 * NOISE
    assert limited[0]["baseline_from"].startswith("from another start; its own fit polished to")
    assert "times route far2's" in limited[1]["skipped"] and "rmse_after_m" not in limited[1]
    off = D.discover(rec, nominal=far2, starts=[truth], settings=dataclasses.replace(settings, route_max_ratio=0.0),
                     label="far2", alternatives=[("far", far)]).to_dict()["routes"]
    assert off[1]["skipped"] is None and off[1]["baseline_rmse_m"] > 5 * NOISE and off[0]["chosen"]
    assert off[1]["baseline_from"] is None and off[0] == limited[0]


#: Each case costs 20-80 s of simulations, so all are slow (issue 15: the default suite's five minutes; the dead-time
#: case was the default suite's until 2026-12-07, 80 s of its 406). The default suite keeps the loop on real
#: simulations in the discover job's end-to-end test below (the same 1-s record, an offset named), and the rules
#: these cases exercise in isolation: which candidates are refitted (a score leader whatever its scout, a scout
#: beyond top_k while it could beat the best refit: test_discovery_screening.py), the judge's verdicts
#: (test_discovery_judge.py).
@pytest.mark.slow
@pytest.mark.parametrize("name,effects,magnitude", [
    ("sensor_offset", {"x_off": 1e-4}, ("x_off", 1e-4)),
    ("constant_load_force", {"F_load": 500.0}, ("F_load", 500.0)),
    ("dead_time", {"tau_d": 2e-3}, ("tau_d", 2e-3)),
    ("coulomb_friction_motor", {"tau_c": 3.0}, ("tau_c", 3.0)),
])
def test_loop_names_the_undeclared_effect(name, effects, magnitude):
    res, _ = discover_on(effects)
    assert res.rmse_before_m > 2.0 * NOISE, "the nominal model absorbed the effect: not a test"
    assert [a["name"] for a in res.effects_added] == [name]
    assert res.iterations[0]["accepted"] == name
    verdicts = {c["name"]: c["verdict"] for c in res.candidates}
    assert verdicts[name] == "accepted" and set(verdicts.values()) <= {"accepted", "compensating", "rejected"}
    # a candidate its scout ranks above it was refitted, never skipped; none its score test ranks above it accepted
    # (until 2026-12 the Coulomb torque's score test ranked above the dead time here, and was refitted and rejected;
    # now the dead time leads it: the rule on a score leader with a weak scout is tested in isolation,
    # test_discovery_screening.py)
    mine = next(c for c in res.candidates if c["name"] == name)
    assert all(c["refitted"] for c in res.candidates if c["scout_rmse_m"] < mine["scout_rmse_m"])
    louder = [c for c in res.candidates if c["score"] > mine["score"]]
    assert all(c["verdict"] != "accepted" for c in louder)
    key, true_value = magnitude
    est = res.effects_added[0]["params"][key]
    assert est == pytest.approx(true_value, rel=0.25)
    assert res.rmse_after_m < 1.05 * NOISE
    assert res.diagnostics_before["verdict"]["structure_left"] and not res.diagnostics_after["verdict"]["structure_left"]


@pytest.mark.slow
def test_loop_names_backlash():
    """The lash opens at every reversal of the flank force: a second degree of freedom the rigid model lacks (slow,
    66 s: the default suite tests the lash's kernel against an independent reference, tests/test_backlash.py)."""
    res, _ = discover_on({"b_l": 5e-4}, candidates=(*SUBSET, "backlash"))
    assert res.rmse_before_m > 20.0 * NOISE
    assert [a["name"] for a in res.effects_added] == ["backlash"]
    assert res.effects_added[0]["params"]["b_l"] == pytest.approx(5e-4, rel=0.05)
    assert res.rmse_after_m < 1.05 * NOISE


@pytest.mark.slow
def test_a_lash_run_out_to_its_bound_comes_back_to_the_truth():
    """The open problem of docs/discovery.md on the default suite's backlash case cut to 0.5 s, the job's defaults:
    before the weaker starts the lash stayed at its stronger start's 1.96 mm (28 µm left), was demoted and the record
    called unexplained at 180 µm; now it is named at its true size."""
    rec, _, start = make_record({"b_l": 5e-4}, 0.5)
    res = D.discover(rec, nominal=start, settings=D.DiscoverSettings(candidates=(*SUBSET, "backlash"), noise_std=NOISE))
    assert [a["name"] for a in res.effects_added] == ["backlash"] and not res.unexplained
    assert res.effects_added[0]["params"]["b_l"] == pytest.approx(5e-4, rel=0.05)
    assert res.rmse_after_m < 1.1 * NOISE


# ---------------------------------------------------------------------------------------------- the job
@pytest.mark.integration
def test_discover_job_end_to_end(tmp_path, job_env):
    from conftest import run_job

    proc = run_job("jobs.run", "+experiment=discover", f"hydra.run.dir={tmp_path / 'run'}", "evaluator=serial",
                   "data.duration=0.5", "data.effects.x_off=5e-5", "discover.nominal=base", "discover.max_effects=1",
                   "discover.candidates=[sensor_offset,constant_load_force]", "progress=false",
                   cwd=tmp_path, env=job_env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    last = [ln for ln in proc.stdout.splitlines() if ln.strip()][-1]
    report = Path(last.removeprefix("report: "))
    assert report == (tmp_path / "run" / "discovery.json").resolve()
    d = json.loads(report.read_text())
    for key in ("effects_added", "candidates", "rmse_before_m", "rmse_after_m", "fitness_before", "fitness_after",
                "final_params", "residual_tests_before", "residual_tests_after", "conclusion"):
        assert key in d, key
    assert [a["name"] for a in d["effects_added"]] == ["sensor_offset"]
    assert d["effects_added"][0]["params"]["x_off"] == pytest.approx(5e-5, rel=0.05)
    assert {c["name"] for c in d["candidates"]} == {"sensor_offset", "constant_load_force"}
    assert all({"name", "score", "accepted"} <= set(c) for c in d["candidates"])
    assert d["rmse_after_m"] < 1.1e-6 and d["rmse_before_m"] > 5e-6
    assert d["fitness_after"] > d["fitness_before"]
    assert d["residual_tests_before"]["whiteness"]["p_value"] < 0.01 < d["residual_tests_after"]["whiteness"]["p_value"]
    for key in ("compensating", "rejected", "noise_model", "localisation", "accepted"):
        assert key in d, key
    assert d["accepted"] == ["sensor_offset"] and d["noise_model"]["after"]["kind"]
    assert d["localisation"]["structure_left"] is False
    for fig in ("residual_before.png", "residual_after.png", "residual_before_after.png",
                "residual_states_before.png", "residual_states_after.png", "localisation_before.png",
                "localisation_after.png"):
        assert (tmp_path / "run" / fig).stat().st_size > 10_000
    from mlflow import MlflowClient

    client = MlflowClient(job_env["MLFLOW_TRACKING_URI"])
    runs = client.search_runs([client.get_experiment_by_name("toggle-id").experiment_id])
    parent = [r for r in runs if "mlflow.parentRunId" not in r.data.tags]
    assert len(parent) == 1 and parent[0].info.run_name.startswith("discover evaluator=serial data.duration=0.5 ")
    assert "data.effects.x_off=5e-5" in parent[0].info.run_name
    # comparing: the result in µm, the shared curve ending at it, the record as a dataset, the model
    assert parent[0].data.metrics["rmse_um"] == pytest.approx(1e6 * d["rmse_after_m"])
    assert parent[0].data.metrics["n_glitches"] == 0 and d["glitches"][0]["count"] == 0
    assert parent[0].data.metrics["n_noise_lines"] == 0
    curve = client.get_metric_history(parent[0].info.run_id, "best_rmse_um")
    assert curve and max(curve, key=lambda m: m.step).value == pytest.approx(1e6 * d["rmse_after_m"])
    assert [i.dataset.name for i in parent[0].inputs.dataset_inputs] == ["simulated_simulation"]
    assert d["model_uri"].removeprefix("models:/") in [o.model_id for o in parent[0].outputs.model_outputs]
    assert "sensor_offset" in parent[0].data.tags["mlflow.note.content"]
    assert parent[0].data.tags["route"] == "base" and [r["label"] for r in d["routes"]] == ["base"]
    children = sorted(r.info.run_name for r in runs if r.data.tags.get("mlflow.parentRunId") == parent[0].info.run_id)
    assert "refit_1_sensor_offset" in children
    assert "figures" in [a.path for a in client.list_artifacts(parent[0].info.run_id)]


@pytest.mark.slow
@pytest.mark.integration
def test_discover_job_runs_the_fast_fit_as_a_second_route_when_asked(tmp_path, job_env):
    from conftest import run_job

    proc = run_job("jobs.run", "+experiment=discover", f"hydra.run.dir={tmp_path / 'run'}", "evaluator=serial",
                   "data.duration=1.0", "data.effects.x_off=5e-5", "discover.nominal=base", "discover.max_effects=1",
                   "discover.candidates=[sensor_offset,constant_load_force]", "progress=false",
                   "discover.routes=always", cwd=tmp_path, env=job_env, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    d = json.loads((tmp_path / "run" / "discovery.json").read_text())
    routes = d["routes"]
    assert [r["label"] for r in routes] == ["base", "fast"]
    # the fast fit's baseline lies in another basin (measured 15.4 against 14.4 µm); both routes name the offset
    # and the record cannot tell their models apart, so the job's own route is reported
    assert not any(r["skipped"] for r in routes)
    assert all(r["added"] == ["sensor_offset"] and not r["structure_left"] for r in routes)
    assert routes[0]["chosen"] and d["accepted"] == ["sensor_offset"]
    assert "route base (reported)" in proc.stdout


@pytest.mark.integration
def test_discover_job_restarts_its_ga_from_the_next_seed_while_the_record_is_unexplained(tmp_path, job_env):
    """No candidate can explain a Coulomb torque, so structure is left: the job fits its GA again from seed 1 (its
    own MLflow child run) and reports it as a route, run or skipped by its baseline; a small GA keeps this cheap."""
    from conftest import run_job
    from mlflow import MlflowClient

    proc = run_job("jobs.run", "+experiment=discover", f"hydra.run.dir={tmp_path / 'run'}", "evaluator=serial",
                   "data.duration=0.5", "data.effects.tau_c=5.0", "discover.candidates=[]", "discover.alternatives=[]",
                   "discover.restarts=1", "discover.catch_all=false", "ga.population=16", "ga.generations=3",
                   "polish.max_nfev=5", "progress=false", cwd=tmp_path, env=job_env, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    d = json.loads((tmp_path / "run" / "discovery.json").read_text())
    routes = d["routes"]
    assert [r["label"] for r in routes] == ["two_stage", "two_stage_seed1"] and routes[0]["structure_left"]
    second = routes[1]
    if second["skipped"]:
        assert second["baseline_rmse_m"] >= routes[0]["baseline_rmse_m"] or "basin of route" in second["skipped"]
    else:
        assert second["baseline_rmse_m"] < routes[0]["baseline_rmse_m"] and "rmse_after_m" in second
    client = MlflowClient(job_env["MLFLOW_TRACKING_URI"])
    runs = client.search_runs([client.get_experiment_by_name("toggle-id").experiment_id])
    seeds = {r.info.run_name: r.data.tags.get("seed") for r in runs if r.data.tags.get("stage") == "nominal"}
    assert seeds == {"nominal": "0", "nominal_seed1": "1"}


@pytest.mark.integration
def test_discover_benchmark_runs_the_job_and_prints_the_median(tmp_path, capsys, monkeypatch, mlflow_template):
    """The benchmark's command line, in this process (the job it times is the one the test above runs as a user
    would): one run, its line and the median printed, the rows written. Its figures are not rendered here (the
    end-to-end test above renders the job's; tests/test_residuals.py each kind) and its store is a copy of the
    session's empty one (the benchmark's own override of ``tracking.uri`` comes first; the last one wins)."""
    from conftest import scratch_store
    from jobs.bench_discover import main

    from toggle_id import figures

    def unrendered(fig, path, **kw):
        figures.close(fig)
        Path(path).write_bytes(b"")
        return str(path)

    monkeypatch.setattr(figures, "save", unrendered)
    main(["--json", str(tmp_path / "bench.json"), "evaluator=serial", "data.duration=0.5", "data.effects.tau_c=0.0",
          "data.effects.x_off=5e-5", "discover.nominal=base", "discover.max_effects=1",
          "discover.candidates=[sensor_offset]", f"tracking.uri={scratch_store(tmp_path / 'store', mlflow_template)}"])
    out = capsys.readouterr().out
    assert "run 0:" in out and "median wall" in out
    rows = json.loads((tmp_path / "bench.json").read_text())
    assert len(rows) == 1 and rows[0]["effects_added"] == ["sensor_offset"] and rows[0]["wall_s"] > 0
    assert rows[0]["rmse_after_um"] < 1.1 and rows[0]["rmse_before_um"] > 5.0
    assert rows[0]["n_simulations"] > 0 and f"{rows[0]['n_simulations']} simulations" in out  # the load-free figure
    # where the time went: the job's split and the loop's phases, whose simulations add up to the loop's
    assert "where the time went (medians): nominal fit 0.0 s, loop" in out and "refits" in out
    assert sum(p["simulations"] for p in rows[0]["phases"]) == rows[0]["n_simulations"]


@pytest.mark.integration
def test_discover_job_rejects_a_bad_setting_in_one_line(tmp_path, job_env):
    """Through the job's own command-line path, in this process (the end-to-end case above runs as a user would)."""
    from conftest import run_in_process

    proc = run_in_process("jobs.run", "+experiment=discover", f"hydra.run.dir={tmp_path / 'run'}",
                          "discover.candidates=[warp_drive]", cwd=tmp_path, env=job_env)
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode != 0 and len(lines) == 1 and "warp_drive" in lines[0]
    assert not (tmp_path / "run" / "discovery.json").exists()


# ---------------------------------------------------------------------------------------------- every effect
#: A magnitude per effect that the nominal model cannot absorb on the 5-s record (refitted, the nominal model
#: stays clearly above the 1-µm noise).
EVERY = {
    "coulomb_friction_motor": {"tau_c": 5.0},
    "stribeck_friction": {"F_s": 200.0, "v_s": 0.03},
    "viscous_friction_slider": {"c_B": 5000.0},
    "dead_time": {"tau_d": 2e-3},
    "backlash": {"b_l": 5e-4},
    "cogging_torque": {"a_cog": 2.0, "n_cog": 6.0, "phi_cog": 0.5},
    "constant_load_force": {"F_load": 1000.0},
    "contact_nonlinear_stiffness": {"k3": 1e13},
    "voltage_saturation": {"s_sat": 0.19},
    "sensor_offset": {"x_off": 1e-4},
    "torque_constant_saturation": {"c_kt": 4e-6},
}


def test_every_library_effect_has_a_slow_test_case():
    assert set(EVERY) == {e.name for e in EFFECTS}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(EVERY))
def test_every_effect_on_the_five_second_record(name):
    effects = EVERY[name]
    eff = EFFECTS_BY_NAME[name]
    rec, truth, start = make_record(effects, duration=5.0)
    silent = make_record({}, duration=5.0)[0]
    if np.max(np.abs(rec.x_B - silent.x_B)) < 1e-9:
        pytest.xfail(f"{name}: the compiled model has no term for it yet (switching it on changes nothing)")
    res = D.discover(rec, nominal=start, settings=D.DiscoverSettings(noise_std=NOISE, max_effects=2))
    mag = eff.magnitude.name
    added = [(a["name"], a["params"].get(mag), a["magnitude"].get("per_K_l", float("nan")) * truth[ALL_INDEX["K_l"]])
             for a in res.effects_added]
    print(f"\n[every-effect] {name}: true {mag}={effects[mag]:g}, added {added}, rms {res.rmse_before_m * 1e6:.3g} -> "
          f"{res.rmse_after_m * 1e6:.3g} um, {res.seconds:.0f} s, unexplained={res.unexplained}")
    assert res.rmse_before_m > 1.1 * NOISE
    assert res.effects_added and res.effects_added[0]["name"] == name
    est = res.effects_added[0]["params"][mag]
    if res.effects_added[0]["magnitude"]["scales_with_mechanism"]:
        # a force is determined only relative to the mechanism (an exact symmetry of x_B scales every force):
        # compare the ratio to the contact stiffness, the quantity the record fixes
        est = res.effects_added[0]["magnitude"]["per_K_l"] * truth[ALL_INDEX["K_l"]]
    if "stall_command_V" in res.effects_added[0]["magnitude"]:
        # the clamped phases fix the saturation as a command, R_s/(K_i·√c_kt) (the stall current is K_i·v/R_s)
        est = (truth[ALL_INDEX["R_s"]] / (res.effects_added[0]["magnitude"]["stall_command_V"] *
                                          truth[ALL_INDEX["K_i"]])) ** 2
        print(f"[every-effect] c_kt·K_i² {res.effects_added[0]['magnitude']['times_K_i2']:.4g} (truth "
              f"{effects[mag] * truth[ALL_INDEX['K_i']] ** 2:.4g}); stall command "
              f"{res.effects_added[0]['magnitude']['stall_command_V']:.4g} V (truth "
              f"{truth[ALL_INDEX['R_s']] / (truth[ALL_INDEX['K_i']] * np.sqrt(effects[mag])):.4g} V)")
    assert est == pytest.approx(effects[mag], rel=0.2)
    assert res.rmse_after_m < 1.02 * NOISE
    assert not res.unexplained


@pytest.mark.slow
def test_no_false_positive_on_the_five_second_record():
    rec, _, start = make_record({}, duration=5.0, seed=3)
    res = D.discover(rec, nominal=start, settings=D.DiscoverSettings(noise_std=NOISE))
    print(f"\n[every-effect] none: added {[a['name'] for a in res.effects_added]}, rms {res.rmse_before_m * 1e6:.3g} -> "
          f"{res.rmse_after_m * 1e6:.3g} um, {res.seconds:.0f} s")
    assert res.effects_added == [] and not res.unexplained


# ---------------------------------------------------------------------------------------------- measured-data classes
def _noise_record(rho: float = 0.0, quantum: float = 0.0, sigma: float = NOISE, seed: int = 11):
    """A 5-s record without effects (parameters perturbed 5 %) with AR(1) noise ``rho`` or an encoder quantum."""
    from toggle_id.app.records import build_record

    rng = np.random.default_rng(seed)
    params = {n: float(v) for n, v in zip(PARAM_NAMES, ASSIGNED * np.exp(0.05 * rng.standard_normal(15)))}
    rec, truth = build_record({"source": "simulated", "sweep": "simulation", "duration": 5.0, "params": params,
                               "effects": {}, "noise_m": sigma, "noise_ar": rho, "quantum_m": quantum,
                               "noise_seed": seed})
    return rec, truth[:15] * np.exp(0.03 * rng.standard_normal(15))


@pytest.mark.slow
@pytest.mark.parametrize("rho,quantum,sigma", [(0.5, 0.0, NOISE), (0.9, 0.0, NOISE), (0.0, 1e-6, 0.0)],
                         ids=["ar1_0.5", "ar1_0.9", "quantised_1um"])
def test_coloured_or_quantised_noise_is_not_an_effect(rho, quantum, sigma):
    rec, start = _noise_record(rho, quantum, sigma)
    res = D.discover(rec, nominal=start, settings=D.DiscoverSettings())
    d = res.to_dict()
    print(f"\n[noise] rho={rho} quantum={quantum}: added {d['accepted']}, compensating "
          f"{[c['name'] for c in d['compensating']]}, noise {d['noise_model']['after']['kind']}, {res.seconds:.0f} s")
    assert res.effects_added == [] and not res.unexplained
    if rho > 0:
        assert d["noise_model"]["after"]["order"] >= 1


@pytest.mark.slow
def test_a_threshold_effect_under_slow_noise_is_named():
    """A screw backlash under AR(1) noise with ρ = 0.9 (rec36's machine of the adversarial set, the cycling command,
    the lash calibrated to ≈ 2σ), on an independent draw of the noise (its first replicate), the nominal fit given
    a few per cent off the truth: slow noise and a lash both leave long runs of one sign; the lash alone is named."""
    from jobs.adversarial_set import draw_truth, make_record, select
    from jobs.adversarial_specs import CALIBRATED

    spec = select("ar09_backlash_cycling")[0]
    rec, _ = make_record(spec, CALIBRATED[spec.key], replicate=1)
    theta, _ = draw_truth(spec)
    start = theta * np.exp(0.03 * np.random.default_rng(7).standard_normal(15))
    res = D.discover(rec, nominal=start, settings=D.DiscoverSettings())
    d = res.to_dict()
    print(f"\n[threshold, AR(1) 0.9] added {d['accepted']}, compensating {[c['name'] for c in d['compensating']]}, "
          f"rms {res.rmse_before_m * 1e6:.4g} -> {res.rmse_after_m * 1e6:.4g} um, {res.seconds:.0f} s")
    assert [a["name"] for a in res.effects_added] == ["backlash"] and not res.unexplained
    assert res.effects_added[0]["params"]["b_l"] == pytest.approx(CALIBRATED[spec.key]["b_l"][0], rel=0.2)
    assert res.rmse_after_m < 1.5 * NOISE and d["noise_model"]["after"]["order"] >= 1


@pytest.mark.slow
def test_noise_loud_at_speed_is_not_an_effect_and_is_named():
    """rec19's machine of the adversarial set (no effect, parameters 30 % off the assigned values) with noise whose σ
    grows with slider B's speed (0.3 + |ẋ_B|/mean|ẋ_B|, rms 1 µm). Before the robust tests the loop ended with a
    cogging torque compensating, the residual "structured", 7 loud samples taken for glitches and a false line
    (measured); now nothing is accepted (the robust F-tests), no sample is taken for a glitch, no line is seen, and
    the report says where the noise is loud. With the robust structure verdict (the default since its statistic
    takes local variances from first differences under a robustly chosen AR order) the residual is not called
    structured either (measured: nothing added or compensating, not unexplained, 168 s)."""
    from jobs.adversarial_set import base_record, clean_response, draw_truth, select

    spec = select("noise_white")[0]
    theta, _ = draw_truth(spec)
    rec = base_record(spec.command, 5.0)
    x, rec.i_q = clean_response(spec, theta, {}, {}, rec)
    v = np.gradient(x, rec.t)
    level = 0.3 + np.abs(v) / np.abs(v).mean()
    rec.x_B = x + NOISE * level / np.sqrt(np.mean(level ** 2)) * np.random.default_rng(1212).standard_normal(rec.n)
    start = theta * np.exp(0.03 * np.random.default_rng(5).standard_normal(15))
    res = D.discover(rec, nominal=start, settings=D.DiscoverSettings())
    d = res.to_dict()
    print(f"\n[noise] loud at speed: added {d['accepted']}, compensating {[c['name'] for c in d['compensating']]}, "
          f"unexplained {res.unexplained}, {res.seconds:.0f} s; {res.conclusion}")
    assert res.effects_added == [] and not res.unexplained
    assert res.diagnostics_after["noise_level"]["strongest"] == "speed" and "noisier in motion" in res.conclusion
    assert not res.diagnostics_after["lines"]["lines"] and not any(g["count"] for g in res.extra.get("glitches") or [])


@pytest.mark.slow
def test_an_effect_outside_the_library_is_unexplained_and_localised():
    """A friction bump on the slider's stroke (independent scipy plant, tests/outside_plant.py): no library effect
    may be accepted; the residual's structure is placed on the slider's position."""
    from outside_plant import Outside, simulate_outside

    rng = np.random.default_rng(21)
    truth = ASSIGNED * np.exp(0.05 * rng.standard_normal(15))
    rec = Record.from_sweep("simulation", 5.0, name="bump")
    x, _, _ = simulate_outside(truth, rec, Outside(bump=(300.0, 0.045, 0.004)))
    rec.x_B = x + NOISE * rng.standard_normal(rec.n)
    start = truth * np.exp(0.03 * rng.standard_normal(15))
    res = D.discover(rec, nominal=start, settings=D.DiscoverSettings())
    d = res.to_dict()
    loc = d["localisation"]
    print(f"\n[outside] added {d['accepted']}, compensating {[c['name'] for c in d['compensating']]}, "
          f"rms {res.rmse_before_m * 1e6:.3g} -> {res.rmse_after_m * 1e6:.3g} um; {loc['text']}")
    assert res.effects_added == [] and res.unexplained
    assert loc["strongest"] in ("x_B", "x_B_dir", "xdot_B")
    assert any(loc["families"][k]["significant"] for k in ("x_B", "x_B_dir"))
    lo, hi = loc["families"]["x_B_dir"]["range"]
    assert lo - 0.004 <= 0.045 <= hi + 0.004


@pytest.mark.slow
def test_two_effects_at_once():
    rec, truth, start = make_record({"c_B": 4000.0, "x_off": 2e-5}, duration=5.0, seed=4)
    res = D.discover(rec, nominal=start, settings=D.DiscoverSettings(noise_std=NOISE))
    names = sorted(a["name"] for a in res.effects_added)
    print(f"\n[two effects] added {names}, rms {res.rmse_before_m * 1e6:.3g} -> {res.rmse_after_m * 1e6:.3g} um")
    assert names == ["sensor_offset", "viscous_friction_slider"]
    assert res.rmse_after_m < 1.05 * NOISE and not res.unexplained
