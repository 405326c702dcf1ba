"""The excite job (issue 16): input families within limits, the separation of rival explanations that survives
refitting, the resolved singular values, the seeded search, `jobs.simulate input.path=` and the job end to end.

References: an exact symmetry of x_B (every mechanical parameter scaled by c leaves x_B unchanged, docs/model.md)
gives two different rivals that no input can separate; a 5 N·m motor Coulomb torque on a nominal model that is not
refitted to any record is separated by tens of µm on any stroke. Default tests use 1-s inputs; the acceptance
checks of the issue on the 5-s record are marked slow.
"""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from toggle_id.data import X_B_L, read_csv, read_input, write_csv
from toggle_id.discovery.gauge import MECHANICAL
from toggle_id.effects import ALL_INDEX
from toggle_id.errors import ConfigError, DataError
from toggle_id.excite import (FAMILY_PARAMS, Candidate, ExciteSettings, Rival, Scorer, candidate_record,
                              clamp_check, input_signal, linear_separation, refit_separation, search, spectrum)
from toggle_id.excite.rivals import FREE_B, effect_rival, specs_from_discovery
from toggle_id.excite.score import responses
from toggle_id.excite.search import resolved_sv
from toggle_id.excite.settings import RivalSpec
from toggle_id.params import ASSIGNED
from toggle_id.record import Record
from toggle_id.simulate import PRECISE, extend, simulate

THETA = extend(ASSIGNED)[0]
#: A 1-s input of the steps family that closes into the clamp and opens again on the assigned plant.
STEPS_1S = Candidate("steps", (0.8, 0.8, 0.3, 0.3, 0.0, 0.5), 0)
CHECK = dict(x_B_min=0.008, clamp_margin=3e-4, min_clamp_samples=30, min_exits=1)


def short_record() -> Record:
    return candidate_record(STEPS_1S, 0.3, 1.0, 1000.0, 0.020)


# ---------------------------------------------------------------------------------------------- settings
def test_settings_validate_and_reject_bad_values_in_one_line():
    s = ExciteSettings.from_dict({"n_random": 2, "families": "sweep",
                                  "rivals": [{"effect": "coulomb_friction_motor", "params": {"tau_c": 0.3}}]})
    assert s.families == ("sweep",) and s.rivals[0].params == {"tau_c": 0.3}
    for bad, needle in [({"v_max": -1}, "v_max"), ({"n_random": 0}, "n_random"), ({"families": ["chirp"]}, "families"),
                        ({"bogus": 1}, "bogus"), ({"sv_index": 16}, "sv_index"),
                        ({"rivals": [{"effect": "warp"}]}, "warp"),
                        ({"rivals": [{"effect": "coulomb_friction_motor", "params": {"tau_c": 0.0}}]}, "magnitude"),
                        ({"rivals": [{"effect": "coulomb_friction_motor", "params": {"tau_c": 99.0}}]}, "domain"),
                        ({"rivals": ["coulomb_friction_motor"]}, "magnitude"), ({"duration": 0.01}, "samples"),
                        ({"rival_rms_sigma": 0}, "rival_rms_sigma"),
                        ({"rivals": [{"effect": "coulomb_friction_motor", "params": {"tau_c": 0.3},
                                      "against": {"effect": "coulomb_friction_motor", "params": {"tau_c": 0.1}}}]},
                         "its own rival"),
                        ({"rivals": [{"effect": "coulomb_friction_motor", "params": {"tau_c": 0.3},
                                      "against": {"effect": "sensor_offset", "params": {}}}]}, "against.*magnitude")]:
        with pytest.raises(ConfigError, match=needle) as err:
            ExciteSettings.from_dict(bad)
        assert "\n" not in str(err.value)


def test_a_pair_of_effects_is_one_rival_and_a_discovery_gives_its_ambiguous_pairs(tmp_path):
    s = ExciteSettings.from_dict({"rivals": [{"effect": "torque_constant_saturation", "params": {"c_kt": 3e-7},
                                              "against": {"effect": "contact_nonlinear_stiffness",
                                                          "params": {"k3": 1e12}, "against": None}}]})
    r = s.rivals[0]
    assert r.against.effect == "contact_nonlinear_stiffness" and r.against.params == {"k3": 1e12}
    assert r.key == "torque_constant_saturation_vs_contact_nonlinear_stiffness"
    disc = {"effects_added": [{"name": "sensor_offset", "params": {"x_off": 1e-4}}], "compensating": [],
            "ambiguous": [{"name": "torque_constant_saturation", "params": {"c_kt": 3e-7},
                           "indistinguishable_from": [{"name": "contact_nonlinear_stiffness", "params": {"k3": 2e12}},
                                                      {"name": "warp_drive", "params": {"w": 1.0}}]}]}
    (tmp_path / "discovery.json").write_text(json.dumps(disc))
    specs = specs_from_discovery(tmp_path / "discovery.json")
    assert [(sp.key, sp.params) for sp in specs] == [
        ("sensor_offset", {"x_off": 1e-4}),
        ("torque_constant_saturation_vs_contact_nonlinear_stiffness", {"c_kt": 3e-7})]
    assert specs[1].against.params == {"k3": 2e12}


def test_a_rival_that_does_not_explain_the_record_is_flagged():
    from toggle_id.app.excite import rival_warnings

    good = Rival("good", "coulomb_friction_motor", {"tau_c": 0.3}, THETA, THETA, FREE_B, rms_a_m=1.0e-6, rms_b_m=1.2e-6)
    stuck = Rival("stuck", "coulomb_friction_motor", {"tau_c": 0.3}, THETA, THETA, FREE_B, rms_a_m=1e-6, rms_b_m=9e-6)
    failed = Rival("failed", "coulomb_friction_motor", {"tau_c": 0.3}, THETA, THETA, FREE_B)   # RMS NaN
    out = rival_warnings([good, stuck, failed], 1e-6, 1.5)
    assert len(out) == 2 and out[0].startswith("stuck: ") and "B 9 µm" in out[0] and out[1].startswith("failed: ")
    assert rival_warnings([good], 1e-6, 1.25) == [] and len(rival_warnings([good], 1e-6, 1.15)) == 1


# ---------------------------------------------------------------------------------------------- inputs
@pytest.mark.parametrize("family", sorted(FAMILY_PARAMS))
def test_every_input_respects_the_limits(family):
    rng = np.random.default_rng(3)
    for k in range(20):
        c = Candidate(family, tuple(rng.random(len(FAMILY_PARAMS[family]))), k)
        for v_max, duration in ((0.3, 5.0), (0.1, 2.0)):
            t, v = input_signal(c, v_max, duration, 1000.0)
            assert t.size == int(round(duration * 1000)) + 1 and t[0] == 0.0
            assert np.allclose(np.diff(t), 1e-3, rtol=0, atol=1e-12)
            assert np.all(np.isfinite(v)) and np.max(np.abs(v)) <= v_max + 1e-15
        assert np.array_equal(input_signal(c, 0.3, 5.0, 1000.0)[1], input_signal(c, 0.3, 5.0, 1000.0)[1])


def test_clamp_check_on_constructed_trajectories():
    t = np.linspace(0, 1, 1001)
    up_down = 0.020 + 0.0365 * np.sin(np.pi * t)       # into the clamp (56.5 mm) and back once
    assert clamp_check(up_down, X_B_L, **CHECK) == "ok"
    assert "leaves the clamp 0" in clamp_check(np.minimum(0.020 + 0.1 * t, 0.057), X_B_L, **CHECK)
    assert "never clamps" in clamp_check(0.020 + 0.03 * t, X_B_L, **CHECK)
    assert "leaves the stroke" in clamp_check(up_down - 0.015, X_B_L, **CHECK)
    assert "after 0 samples" in clamp_check(np.full(1001, 0.057), X_B_L, **CHECK)
    assert clamp_check(np.full(1001, np.nan), X_B_L, **CHECK) == "simulation failed"


# ---------------------------------------------------------------------------------------------- separation
def test_rivals_related_by_an_exact_symmetry_are_not_separated():
    """x_B is unchanged when every mechanical parameter is scaled by c: different parameters, no separation."""
    rec = short_record()
    theta_a = THETA.copy()
    for nm in MECHANICAL:
        theta_a[ALL_INDEX[nm]] *= 1.3
    y, status = responses(rec, np.vstack([theta_a, THETA]))
    assert status == ["ok", "ok"] and np.max(np.abs(y[0] - y[1])) < 1e-8   # integrator tolerance
    assert clamp_check(y[1], X_B_L, **CHECK) == "ok"
    rival = Rival("sym", "coulomb_friction_motor", {"tau_c": 0.0}, theta_a, THETA, FREE_B)
    assert linear_separation(rec, rival, y[0], y[1]) < 1e-8
    assert refit_separation(rec, rival, y[0], max_nfev=5, rounds=1)["separation_m"] < 1e-8


def test_a_large_torque_the_nominal_model_cannot_absorb_is_separated():
    rec = short_record()
    theta_a = THETA.copy()
    theta_a[ALL_INDEX["tau_c"]] = 5.0
    y, _ = responses(rec, np.vstack([theta_a, THETA]))
    rival = Rival("tau", "coulomb_friction_motor", {"tau_c": 5.0}, theta_a, THETA, FREE_B)
    lin = linear_separation(rec, rival, y[0], y[1])
    out = refit_separation(rec, rival, y[0], max_nfev=10, rounds=1)
    raw = float(np.sqrt(np.mean((y[0] - y[1]) ** 2)))
    assert 10e-6 < out["separation_m"] <= raw and 10e-6 < lin <= raw
    # what is left is what the refitted B really leaves
    assert out["separation_m"] == pytest.approx(float(np.sqrt(np.mean((y[0] - out["y_b_refit"]) ** 2))))


def test_a_pair_rival_lets_the_refit_move_the_other_effect():
    """Rival A: a cubic contact stiffness; rival B: the nominal model with a motor Coulomb torque instead. B is
    built by refitting its nominal parameters with the torque on, and B's refits may move the torque: what they
    leave is at most what a B with the torque held leaves (the same starts, one more free parameter)."""
    rec = short_record()
    theta_a = THETA.copy()
    theta_a[ALL_INDEX["k3"]] = 3e13
    y, _ = responses(rec, theta_a)
    data = Record(t=rec.t, v_in=rec.v_in, x_B=y[0], sweep=rec.sweep, x_B0=rec.x_B0, name="k3")
    spec = RivalSpec("contact_nonlinear_stiffness", {"k3": 3e13},
                     against=RivalSpec("coulomb_friction_motor", {"tau_c": 0.5}))
    rival = effect_rival(data, THETA, spec, max_nfev=4, rounds=1)
    assert rival.name == "contact_nonlinear_stiffness vs coulomb_friction_motor" and rival.against == "coulomb_friction_motor"
    assert "tau_c" in rival.free_b and rival.theta_b[ALL_INDEX["tau_c"]] > 0 and rival.theta_b[ALL_INDEX["k3"]] == 0
    assert rival.theta_a[ALL_INDEX["k3"]] == 3e13 and rival.theta_a[ALL_INDEX["tau_c"]] == 0
    assert rival.to_dict()["theta_b"]["tau_c"] == rival.theta_b[ALL_INDEX["tau_c"]]
    y_a, _ = responses(rec, rival.theta_a)
    free = refit_separation(rec, rival, y_a[0], max_nfev=6, rounds=1)
    held = refit_separation(rec, Rival("held", rival.effect, rival.params, rival.theta_a, rival.theta_b,
                                       tuple(nm for nm in rival.free_b if nm != "tau_c")), y_a[0], max_nfev=6, rounds=1)
    assert free["theta_b_refit"][ALL_INDEX["tau_c"]] != rival.theta_b[ALL_INDEX["tau_c"]]
    assert 0 < free["separation_m"] <= held["separation_m"] * (1 + 1e-9)


def test_spectrum_and_resolved_singular_values():
    rec = short_record()
    sp = spectrum(rec, THETA, 1e-6)
    s = np.array(sp["singular_values"])
    assert s.size == 15 and np.all(np.diff(s) <= 0) and 1 <= sp["rank"] <= 12   # 3 exact symmetries of x_B
    assert resolved_sv(sp, sp["rank"]) == s[sp["rank"] - 1] and resolved_sv(sp, sp["rank"] + 1) == 0.0
    assert resolved_sv({"error": "x"}, 1) == 0.0


def test_a_swept_record_is_compared_at_its_samples_as_a_candidate_is():
    """A record simulated in memory from its swept sine integrates freely; its spectrum is taken from the same
    input at its samples (linearly interpolated, steps stopping at them), where the candidates' are."""
    from dataclasses import replace

    rec = Record.from_sweep("simulation", duration=1.0)
    assert rec.sweep is not None
    sampled = spectrum(replace(rec, sweep=None), THETA, 1e-6)
    assert spectrum(rec, THETA, 1e-6) == sampled
    assert len(sampled["singular_values"]) == 15 and sampled["rank"] >= 1


def test_search_is_seeded_and_rejects_with_a_status():
    settings = ExciteSettings.from_dict({"duration": 1.0, "n_random": 2, "n_refine": 2, "parameters": False,
                                         "families": ["steps", "cycling"], "seed": 5})
    theta_a = THETA.copy()
    theta_a[ALL_INDEX["tau_c"]] = 0.3
    rival = Rival("tau", "coulomb_friction_motor", {"tau_c": 0.3}, theta_a, THETA, FREE_B)

    def run():
        return search(Scorer(settings, [rival], THETA, 1e-6, 0.020, None))

    a, b = run(), run()
    n_refine = 2 if any(e.ok for e in a) else 0
    for fam in ("steps", "cycling"):  # random candidates until 2 are accepted, at most 3 × 2 tries
        tried = [e for e in a[:len(a) - n_refine] if e.candidate.family == fam]
        assert 2 <= len(tried) <= 6
        assert sum(e.ok for e in tried) == 2 and tried[-1].ok or len(tried) == 6
    assert [(e.candidate, e.status, e.score) for e in a] == [(e.candidate, e.status, e.score) for e in b]
    assert all(e.ok or e.score == -np.inf for e in a) and all(e.status for e in a)


class _BowlScorer:
    """A stand-in for :class:`Scorer` with a known score surface: −‖u − target‖² in the unit cube of each family
    (the steps family's candidates with u[0] < 0.1 are rejected); no simulation."""

    def __init__(self, settings: ExciteSettings):
        self.s, self.count = settings, 0
        self.target = {"steps": np.full(6, 0.62), "cycling": np.full(7, 0.3)}

    def evaluate(self, c: Candidate):
        from toggle_id.excite.search import Evaluation

        ev = Evaluation(self.count, c, "ok")
        self.count += 1
        if c.family == "steps" and c.u[0] < 0.1:
            ev.status = "never clamps (stand-in)"
            return ev
        ev.score = -float(np.sum((np.array(c.u) - self.target[c.family]) ** 2))
        return ev


def test_the_refinement_climbs_from_the_best_of_each_family_within_its_budget():
    settings = ExciteSettings.from_dict({"n_random": 4, "n_refine": 120, "refine_starts": 2,
                                         "families": ["steps", "cycling"], "seed": 3})
    a = search(_BowlScorer(settings))
    b = search(_BowlScorer(settings))
    assert [(e.candidate, e.status, e.score) for e in a] == [(e.candidate, e.status, e.score) for e in b]
    random, refine = a[:-120], a[-120:]
    assert all(sum(e.ok for e in random if e.candidate.family == fam) == 4 for fam in ("steps", "cycling"))
    assert sum(e.candidate.family == "cycling" for e in random) == 4 and 8 <= len(random) <= 8 + 8  # no cycling one refused
    assert len({e.candidate for e in a}) == len(a)  # nothing scored twice
    for fam in ("steps", "cycling"):
        first = max(e.score for e in random if e.ok and e.candidate.family == fam)
        after = max(e.score for e in refine if e.ok and e.candidate.family == fam)
        # 60 Nelder–Mead evaluations from the family's best random candidate go most of the way to the top (0)
        assert after > 0.25 * first, (fam, first, after)
    assert all(0.0 <= x <= 1.0 for e in refine for x in e.candidate.u)
    one = search(_BowlScorer(ExciteSettings.from_dict({"n_random": 4, "n_refine": 7, "refine_starts": 1,
                                                       "families": ["steps", "cycling"], "seed": 3})))
    assert len({e.candidate.family for e in one[-7:]}) == 1 and sum(e.ok for e in one[:-7]) == 8


# ---------------------------------------------------------------------------------------------- jobs.simulate
def _write_input(path: Path, t: np.ndarray, v: np.ndarray) -> Path:
    np.savetxt(path, np.c_[t, v], delimiter=",", header="t,v_in", comments="", fmt="%.17g")
    return path


def test_an_input_csv_round_trips_through_jobs_simulate(tmp_path):
    from conftest import run_job

    rec = short_record()
    src = write_csv(Record(t=rec.t, v_in=rec.v_in), tmp_path / "excitation.csv")
    proc = run_job("jobs.simulate", "out=rec.csv", f"input.path={src}", "effects.tau_c=0.3", "noise_m=0",
                   cwd=tmp_path, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = read_csv(tmp_path / "rec.csv")
    assert np.array_equal(out.t, rec.t) and np.array_equal(out.v_in, rec.v_in)
    theta = THETA.copy()
    theta[ALL_INDEX["tau_c"]] = 0.3
    ref = simulate(theta[None, :], Record(t=rec.t, v_in=rec.v_in), PRECISE)
    assert np.max(np.abs(out.x_B - ref.x_B[0])) < 1e-12


def _bad_input(path: Path, kind: str) -> None:
    t = np.arange(501) / 1000.0
    v = 0.1 * np.sin(2 * np.pi * t)
    if kind == "over":
        _write_input(path, t, 4.0 * v)
    elif kind == "nonuniform":
        t2 = t.copy()
        t2[200] += 3e-4
        _write_input(path, t2, v)
    elif kind == "column":
        np.savetxt(path, np.c_[t, v], delimiter=",", header="t,u", comments="")


@pytest.mark.parametrize("kind, needle", [("over", "over the machine's limit"), ("nonuniform", "non-uniform"),
                                          ("column", "missing required column 'v_in'"), ("missing", "not found")])
def test_a_bad_input_file_is_a_one_line_data_error(tmp_path, kind, needle):
    path = tmp_path / "in.csv"
    _bad_input(path, kind)
    with pytest.raises(DataError, match=re.escape(needle)) as err:
        read_input(path, rate_hz=1000.0, v_max=0.3, max_duration=60.0)
    assert "\n" not in str(err.value)


def test_the_simulate_job_refuses_a_bad_input_file_in_one_line_with_a_non_zero_exit(tmp_path):
    """The command-line path of the cases above (one of them: the job wraps the same DataError)."""
    from conftest import run_job

    path = tmp_path / "in.csv"
    _bad_input(path, "over")
    proc = run_job("jobs.simulate", "out=rec.csv", f"input.path={path}", cwd=tmp_path, timeout=120)
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == 2 and len(lines) == 1 and "over the machine's limit" in lines[0], proc.stderr[-2000:]
    assert not (tmp_path / "rec.csv").exists()


# ---------------------------------------------------------------------------------------------- the job
@pytest.mark.integration
def test_excite_job_end_to_end(tmp_path, job_env):
    from conftest import run_job

    # a discovery that left a tied pair: it becomes a second rival, started from its final model; the proposed input
    # lasts 2 s (in 1 s the few random inputs of this budget rarely close and open the clamp: nothing is proposed)
    final = {nm: float(THETA[ALL_INDEX[nm]]) for nm in ALL_INDEX}
    (tmp_path / "discovery.json").write_text(json.dumps({
        "effects_added": [], "compensating": [], "final_params": final,
        "ambiguous": [{"name": "torque_constant_saturation", "params": {"c_kt": 1e-6},
                       "indistinguishable_from": [{"name": "contact_nonlinear_stiffness", "params": {"k3": 1e13}}]}]}))
    proc = run_job("jobs.run", "+experiment=excite", f"hydra.run.dir={tmp_path / 'run'}", "data.duration=1.0",
                   "data.effects.tau_c=0.3", f"excite.discovery={tmp_path / 'discovery.json'}", "excite.duration=2.0", "excite.n_random=2", "excite.n_refine=1",
                   "excite.refit_top=1", "excite.refit_nfev=5", "excite.refit_rounds=1", "excite.rival_nfev=5",
                   "excite.families=[steps,cycling]", "fast.starts=2", "fast.final_nfev=10", "tracking.log_model=false",
                   "tracking.system_metrics.enabled=false", cwd=tmp_path, env=job_env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    last = [ln for ln in proc.stdout.splitlines() if ln.strip()][-1]
    report = Path(last.removeprefix("report: "))
    assert report == (tmp_path / "run" / "excite.json").resolve()
    assert "candidate 1 (random steps)" in proc.stdout
    d = json.loads(report.read_text())
    for key in ("proposed", "rivals", "parameters", "candidates", "families", "separates", "sigma_um", "limits"):
        assert key in d, key
    assert d["n_candidates"] == len(d["candidates"]) >= 4 and d["sigma_um"] == pytest.approx(1.0)
    rv, pair = d["rivals"]
    assert rv["effect"] == "coulomb_friction_motor" and rv["params"] == {"tau_c": 0.3}
    assert pair["name"] == "torque_constant_saturation vs contact_nonlinear_stiffness" and pair["source"] == "discovery"
    assert pair["theta_a"]["c_kt"] == 1e-6 and pair["theta_b"]["k3"] > 0 and "k3" in pair["free_b"]
    assert d["proposed"] is not None
    assert rv["predicted_separation_um"] >= 0 and "predicted_separation_sigma" in rv
    # the power of Vuong's test on a record under the proposed input, from the separation and its length
    z = np.sqrt(2001) * rv["predicted_separation_sigma"] / 2.0
    assert rv["expected_vuong_z"] == pytest.approx(z) and 0.05 <= rv["vuong_power"] <= 1.0
    assert f"probability {rv['vuong_power']:.3g}" in (tmp_path / "run" / "excite.txt").read_text()
    ex = read_csv(tmp_path / "run" / "excitation.csv", require_x_B=False, expect_rate_hz=1000.0)
    assert ex.n == 2001 and np.max(np.abs(ex.v_in)) <= 0.3
    assert (tmp_path / "run" / "excite.png").stat().st_size > 10_000
    assert len(d["parameters"]["singular_values_before"]) == 15
    from mlflow import MlflowClient

    client = MlflowClient(job_env["MLFLOW_TRACKING_URI"])
    runs = client.search_runs([client.get_experiment_by_name("toggle-id").experiment_id])
    assert len(runs) == 1 and runs[0].info.run_name.startswith("excite ")
    assert "sigma_um" in runs[0].data.metrics
    assert "separation_sigma.torque_constant_saturation_vs_contact_nonlinear_stiffness" in runs[0].data.metrics


# ---------------------------------------------------------------------------------------------- acceptance
@pytest.mark.slow
@pytest.mark.integration
def test_issue_16_acceptance_torque(tmp_path, job_env):
    """Issue 16's first point, on the paper's sweep with a 0.3 N·m motor Coulomb torque (1 µm noise), the job asked
    to tell the torque from slider friction (``excite.parameters=false``; the parameters are the second point): the
    proposed input separates them by ≥ 3 σ after refitting, and the discover job names the torque on a record
    simulated under that input with RMS ≤ 1.5 σ. The discover job fits its nominal model with the fast method, as
    the excite job does: on this input (its first clamp after 4 s) the two-stage GA's nominal fit stops at ≈ 24 µm
    (README). Measured: 7.56 σ; the torque named alone, τ_c 0.297 N·m, 0.9996 µm."""
    from conftest import run_job

    proc = run_job("jobs.run", "+experiment=excite", f"hydra.run.dir={tmp_path / 'run'}", "data.effects.tau_c=0.3",
                   "excite.parameters=false", "progress=false", cwd=tmp_path, env=job_env, timeout=1800)
    assert proc.returncode == 0, proc.stderr[-3000:]
    d = json.loads((tmp_path / "run" / "excite.json").read_text())
    assert d["rivals"][0]["predicted_separation_sigma"] >= 3.0
    proc = run_job("jobs.simulate", "out=under.csv", f"input.path={tmp_path / 'run' / 'excitation.csv'}",
                   "effects.tau_c=0.3", "noise_m=1e-6", "seed=1", cwd=tmp_path, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    proc = run_job("jobs.run", "+experiment=discover", "method=fast", "data=csv", f"data.path={tmp_path / 'under.csv'}",
                   f"hydra.run.dir={tmp_path / 'disc'}", "progress=false", cwd=tmp_path, env=job_env, timeout=3600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    disc = json.loads((tmp_path / "disc" / "discovery.json").read_text())
    assert disc["accepted"] == ["coulomb_friction_motor"] and disc["rmse_after_m"] <= 1.5e-6


@pytest.mark.slow
@pytest.mark.integration
def test_issue_16_acceptance_parameters(tmp_path, job_env):
    """Issue 16's second point, on the default record (no effect, paper's sweep): the proposed input raises the
    numerical rank of x_B, or its 8th resolved singular value by ≥ 10×, and the report says which parameters
    become identifiable (a list, possibly empty: README)."""
    from conftest import run_job

    proc = run_job("jobs.run", "+experiment=excite", "excite.rivals=[]", f"hydra.run.dir={tmp_path / 'run'}",
                   "progress=false", cwd=tmp_path, env=job_env, timeout=1800)
    assert proc.returncode == 0, proc.stderr[-3000:]
    par = json.loads((tmp_path / "run" / "excite.json").read_text())["parameters"]
    assert par["met"] and (par["rank_after"] > par["rank_before"] or par["sv_gain"] >= 10.0)
    assert isinstance(par["become_identifiable"], list)
