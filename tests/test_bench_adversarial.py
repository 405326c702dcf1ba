"""The adversarial record set (jobs/bench_adversarial.py): what it writes, that the names hide the truth, the
calibration table covers it, and how the discover runs are judged and resumed."""
from __future__ import annotations

import dataclasses
import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

from jobs import adversarial_set as S
from jobs import adversarial_specs as SP
from jobs import adversarial_verdicts as V
from jobs import bench_adversarial as B
from toggle_id.data import read_csv
from toggle_id.effects import EFFECTS
from toggle_id.params import ASSIGNED, INDEX, PARAM_NAMES
from toggle_id.simulate import PRECISE, extend, simulate


def test_the_set_covers_the_library_the_pairs_the_noise_and_the_outside_effects():
    cats = [s.category for s in SP.SPECS]
    assert len(SP.SPECS) >= 18
    assert cats.count("library") == 21 and cats.count("pair") == 5 and cats.count("outside") == 14
    # a library effect and one outside it at once, on a sweep and on the cycling command
    mixed = [s for s in SP.SPECS if s.category == "mixed"]
    assert {(s.command, s.outside) for s in mixed} == {("simulation", "bump"), ("cycling", "drag")}
    assert all(s.effects == ("cogging_torque",) and s.target_of("a_cog") == 2.0 and
               s.target_of(s.calibrate[1]) == 3.0 for s in mixed)
    # real effects under the noise that must not look like one: AR(1) ρ = 0.9 (five, one faint) and the encoder
    coloured = [(s.noise_m, s.noise_ar, s.quantum_m) for s in SP.SPECS if s.category == "library" and
                (s.noise_ar or s.quantum_m)]
    assert sorted(coloured) == [(0.0, 0.0, 1e-6)] + [(1e-6, 0.9, 0.0)] * 5
    # and a threshold effect under gross errors, whose sharp turns are no glitches
    assert [s.effects for s in SP.SPECS if s.category == "library" and s.outlier_fraction] == [("backlash",)]
    # threshold effects under that slow noise: both leave long runs of one sign in the residual
    assert {s.effects[0] for s in SP.SPECS if s.category == "library" and s.noise_ar == 0.9} >= {
        "voltage_saturation", "backlash"}
    assert any(s.noise_ar == 0.9 for s in SP.SPECS if s.category == "pair")  # and two effects at once under it
    # and an effect outside the library under it: coloured noise and missing physics at once, as in measured data
    assert any(s.noise_ar == 0.9 and s.outside == "bump" for s in SP.SPECS if s.category == "outside")
    # a threshold effect among two at once (the drive's voltage saturation beside a cogging torque)
    assert any("voltage_saturation" in s.effects for s in SP.SPECS if s.category == "pair")
    assert {s.effects[0] for s in SP.SPECS if s.category == "library"} == {e.name for e in EFFECTS}
    noise = {(s.noise_m, s.noise_ar, s.quantum_m, s.outlier_fraction) for s in SP.SPECS
             if s.category == "noise" and not s.disturbance}
    assert noise == {(1e-6, 0.0, 0.0, 0.0), (1e-6, 0.5, 0.0, 0.0), (1e-6, 0.9, 0.0, 0.0), (0.0, 0.0, 1e-6, 0.0),
                     (1e-6, 0.0, 0.0, 0.01)}  # the last: gross errors (an encoder that glitches) on 1 % of samples
    # and disturbances of the reading beyond that model, alone (the model itself off)
    assert sorted(s.disturbance for s in SP.SPECS if s.disturbance) == sorted(S.DISTURBANCES)
    assert all(s.category == "noise" and s.noise_m == 0 for s in SP.SPECS if s.disturbance)
    assert SP.effective_sigma(1e-6, 0.0, 0.01, 10e-6) == pytest.approx(np.sqrt(2) * 1e-6)
    assert {s.outside for s in SP.SPECS if s.category == "outside"} == {
        "bump", "drag", "scale", "pin_friction", "scale_factor", "deadband", "kt_drift", "compliance", "hc_damping"}
    # threshold effects on the paper's sweep too, not only on the cycling command
    assert {s.command for s in SP.SPECS if s.category == "library" and s.effects[0] in ("voltage_saturation",
                                                                                          "backlash")} >= {
        "simulation", "cycling"}
    # the paper's sweep (0.04-0.06 V) never enters the dead band: there it is an offset of the command; the cycling
    # command crosses zero, where the band is a threshold
    assert {s.command for s in SP.SPECS if s.outside == "deadband"} == {"simulation", "cycling"}
    assert len(set(SP.NAMES.values())) == len(SP.SPECS) and SP.NAMES["torque_saturation_simulation"] == "rec08"
    assert {s.command for s in SP.SPECS} == {"simulation", "experiment", "cycling"}
    # every calibrated magnitude is there, with a measured ratio near its target
    for s in SP.SPECS:
        assert set(SP.CALIBRATED.get(s.key, {})) == set(s.calibrate), s.key
        for param, (value, ratio) in SP.CALIBRATED.get(s.key, {}).items():
            assert value > 0 and ratio == pytest.approx(s.target_of(param), rel=0.12), s.key
    # names are unique and say nothing about the content
    names = list(SP.NAMES.values())
    assert len(set(names)) == len(names) and all(n.startswith("rec") and n[3:].isdigit() for n in names)
    assert names != sorted(names)  # nor does the order


def test_generator_writes_the_records_and_the_manifest(tmp_path):
    assert B.main(["--out", str(tmp_path), "--only", "noise_white,noise_quantised", "--duration", "1.0"]) == 0
    man = json.loads((tmp_path / "manifest.json").read_text())
    assert {r["key"] for r in man["records"]} == {"noise_white", "noise_quantised"}
    assert sorted(p.name for p in tmp_path.glob("*.csv")) == sorted(r["file"] for r in man["records"])
    for r in man["records"]:
        rec = read_csv(tmp_path / r["file"])
        assert rec.n == 1001 == r["samples"] and r["effects"] == [] and not r["outside"]
        theta = np.array([r["params"][n] for n in PARAM_NAMES])
        factors = np.abs(np.log(theta / ASSIGNED))
        assert 0.15 <= r["perturbation"]["sigma_log"] <= 0.40 and factors.max() > 0.05
        base = S.base_record(r["command"]["sweep"], 1.0)  # the sweep in continuous time, as simulated
        clean = simulate(extend(theta), base, PRECISE).x_B[0]  # the truth reproduces the record within its noise
        err = rec.x_B - clean
        if r["key"] == "noise_quantised":
            assert r["noise"]["sigma_m"] == 0.0 and r["noise"]["quantum_m"] == 1e-6
            assert np.max(np.abs(rec.x_B / 1e-6 - np.round(rec.x_B / 1e-6))) < 1e-6
            assert np.max(np.abs(err)) <= 0.5e-6 * (1 + 1e-6)
        else:
            assert np.std(err) == pytest.approx(1e-6, rel=0.1) and r["noise"]["model"] == "white"
    # deterministic: the same records again
    before = {p.name: p.read_bytes() for p in tmp_path.glob("*.csv")}
    B.main(["--out", str(tmp_path), "--only", "noise_quantised", "--duration", "1.0"])
    assert {p.name: p.read_bytes() for p in tmp_path.glob("*.csv")} == before
    assert len(json.loads((tmp_path / "manifest.json").read_text())["records"]) == 2  # merged, not replaced


def test_replicates_are_the_same_machine_with_independent_noise(tmp_path):
    """--replicates: recNN_r1 … hold the record's truth, command and noise model, and noise of their own; the record
    itself is unchanged by asking for them."""
    assert B.main(["--out", str(tmp_path / "one"), "--only", "noise_white", "--duration", "0.5"]) == 0
    assert B.main(["--out", str(tmp_path), "--only", "noise_white", "--duration", "0.5", "--replicates", "2"]) == 0
    name = SP.NAMES["noise_white"]
    man = {r["name"]: r for r in json.loads((tmp_path / "manifest.json").read_text())["records"]}
    assert sorted(man) == [name, f"{name}_r1", f"{name}_r2"]
    assert [man[n]["replicate"] for n in sorted(man)] == [0, 1, 2]
    assert (tmp_path / f"{name}.csv").read_bytes() == (tmp_path / "one" / f"{name}.csv").read_bytes()
    recs = [read_csv(tmp_path / man[n]["file"]) for n in sorted(man)]
    for n in sorted(man)[1:]:
        assert man[n]["params"] == man[name]["params"] and man[n]["command"] == man[name]["command"]
        assert man[n]["noise"]["model"] == man[name]["noise"]["model"]
        assert man[n]["noise"]["seed"] != man[name]["noise"]["seed"]
    d1, d2 = recs[1].x_B - recs[0].x_B, recs[2].x_B - recs[0].x_B
    assert np.std(d1) == pytest.approx(np.sqrt(2) * 1e-6, rel=0.15)  # two independent draws of 1-µm noise
    assert abs(np.corrcoef(d1, d2)[0, 1] - 0.5) < 0.15  # both minus the same draw, independent otherwise
    with pytest.raises(SystemExit):
        B.main(["--out", str(tmp_path), "--only", "noise_white", "--replicates", "-1"])
    # a reading quantised without Gaussian noise has nothing random: its replicates would be the record itself
    assert B.main(["--out", str(tmp_path / "q"), "--only", "noise_quantised", "--duration", "0.5",
                   "--replicates", "2"]) == 0
    assert [r["name"] for r in json.loads((tmp_path / "q" / "manifest.json").read_text())["records"]] == \
        [SP.NAMES["noise_quantised"]]


def test_a_held_out_draw_is_another_machine_calibrated_for_itself(tmp_path, monkeypatch):
    """--draw K: each spec on another machine drawn the same way (valid, other parameters, other noise), named
    recNN_dK, with magnitudes calibrated for that machine — measured once and kept in calibration_dK.json."""
    calls = []

    def fake_calibrate(specs, duration, log=print, draw=0):
        calls.append(([s.key for s in specs], draw))
        return {s.key: {p: {"value": 7.5e-4, "ratio": 2.0, "rms_fit_um": 1.7, "evaluations": []}
                        for p in s.calibrate} for s in specs if s.calibrate}

    monkeypatch.setattr(B, "calibrate", fake_calibrate)
    args = ["--out", str(tmp_path), "--only", "noise_white,dead_time", "--duration", "0.5"]
    assert B.main(args) == 0 and calls == []  # the set itself: its own calibration
    assert B.main([*args, "--draw", "1"]) == 0
    assert calls == [(["dead_time"], 1)]  # the effect record's new machine calibrated, the noise record needs none
    assert B.main([*args, "--draw", "1"]) == 0 and len(calls) == 1  # kept: not measured again
    man = {r["name"]: r for r in json.loads((tmp_path / "manifest.json").read_text())["records"]}
    for key in ("noise_white", "dead_time"):
        name = SP.NAMES[key]
        own, held = man[name], man[f"{name}_d1"]
        assert own["draw"] == 0 and held["draw"] == 1
        assert held["params"] != own["params"] and held["noise"]["seed"] != own["noise"]["seed"]
        theta = np.array([held["params"][n] for n in PARAM_NAMES])
        assert S._valid_truth(theta, S.SPECS_BY_KEY[key].command)
    assert man[f"{SP.NAMES['dead_time']}_d1"]["effect_params"]["dead_time"]["tau_d"] == 7.5e-4
    assert man[SP.NAMES["dead_time"]]["effect_params"]["dead_time"]["tau_d"] == SP.CALIBRATED["dead_time"]["tau_d"][0]
    assert json.loads((tmp_path / "calibration_d1.json").read_text())["dead_time"]["tau_d"]["value"] == 7.5e-4
    with pytest.raises(SystemExit):
        B.main([*args, "--draw", "-1"])


def test_an_outside_record_and_an_effect_record_are_written_with_their_truth(tmp_path):
    B.main(["--out", str(tmp_path), "--only", "torque_saturation_simulation,dead_time", "--duration", "0.5"])
    man = {r["key"]: r for r in json.loads((tmp_path / "manifest.json").read_text())["records"]}
    sat, dt = man["torque_saturation_simulation"], man["dead_time"]
    assert sat["outside"]["saturating_torque_constant"]["i_sat"] == SP.CALIBRATED[sat["key"]]["i_sat"][0]
    assert "outside_plant" in sat["simulator"] and sat["calibration"]["target_ratio"] == 3.0
    assert sat["effects"] == ["torque_constant_saturation"] and sat["category"] == "library"
    assert sat["effect_params"]["torque_constant_saturation"]["c_kt"] == pytest.approx(
        SP.CALIBRATED[sat["key"]]["i_sat"][0] ** -2, rel=1e-12)
    assert dt["effect_params"]["dead_time"]["tau_d"] == SP.CALIBRATED["dead_time"]["tau_d"][0]
    assert dt["jobs_simulate"].startswith("python -m jobs.simulate") and "effects.tau_d=" in dt["jobs_simulate"]
    for r in man.values():
        assert read_csv(tmp_path / r["file"]).n == 501


def test_a_disturbed_reading_is_the_measured_one_plus_its_disturbance_of_the_stated_size(tmp_path):
    t = np.arange(5001) * 1e-3
    tone, ar2, walk = (S.disturbance(k, t, 5) for k in ("tone", "ar2", "walk"))
    # the tone: 1 µm of white noise and a 50-Hz line of 1 µm amplitude (power 0.5 µm²)
    line = np.abs(np.fft.rfft(tone))[250] * 2 / t.size
    assert line == pytest.approx(1e-6, rel=0.05) and np.std(tone) == pytest.approx(np.sqrt(1.5) * 1e-6, rel=0.05)
    # resonant AR(2) noise of 1 µm, correlated over many samples; a walk that wanders 3 µm by the end
    assert np.std(ar2) == pytest.approx(1e-6, rel=1e-12) and np.corrcoef(ar2[:-1], ar2[1:])[0, 1] > 0.9
    assert 0.2e-6 < abs(np.mean(walk[-500:])) + np.std(walk) < 20e-6
    np.testing.assert_array_equal(S.disturbance("ar2", t, 5), ar2)  # seeded
    with pytest.raises(ValueError, match="unknown disturbance"):
        S.disturbance("hum", t, 5)
    B.main(["--out", str(tmp_path), "--only", "noise_tone_simulation", "--duration", "0.5", "--validation"])
    man = json.loads((tmp_path / "manifest.json").read_text())["records"][0]
    rec = read_csv(tmp_path / man["file"])
    spec = SP.SPECS_BY_KEY["noise_tone_simulation"]
    clean, _ = S.make_record(dataclasses.replace(spec, disturbance=None), {}, duration=0.5)
    e = S.disturbance("tone", rec.t, man["noise"]["disturbance_seed"])
    np.testing.assert_allclose(rec.x_B, clean.x_B + e, rtol=0, atol=1e-18)
    assert man["noise"]["effective_sigma_m"] == pytest.approx(np.sqrt(np.mean(e ** 2)), rel=1e-12)
    assert S.disturbance_seed(spec, man["validation"]["noise_seed"]) != man["noise"]["disturbance_seed"]  # its own
    # a disturbed reading is random though its measurement model is off: its replicates are drawn again
    assert S.replicate_count(spec, 2) == 3 and S.replicate_count(SP.SPECS_BY_KEY["noise_quantised"], 2) == 1
    _, rep = S.make_record(spec, {}, duration=0.5, replicate=1)
    assert rep["noise"]["disturbance_seed"] != man["noise"]["disturbance_seed"]


def test_a_mixed_record_holds_a_library_effect_and_one_outside_the_library(tmp_path):
    """The independent plant simulates both (the library's cogging term is its own too); the manifest keeps them
    apart — the library effect under ``effects``, the other under ``outside`` — and the row's truth lists both."""
    from outside_plant import Outside, simulate_outside

    B.main(["--out", str(tmp_path), "--only", "mixed_cogging_bump_simulation", "--duration", "0.5"])
    (r,) = json.loads((tmp_path / "manifest.json").read_text())["records"]
    cal = SP.CALIBRATED["mixed_cogging_bump_simulation"]
    assert r["category"] == "mixed" and r["effects"] == ["cogging_torque"] and "outside_plant" in r["simulator"]
    assert r["effect_params"]["cogging_torque"] == {"a_cog": cal["a_cog"][0], "n_cog": 6.0, "phi_cog": 0.5}
    assert list(r["outside"]) == ["friction_bump"] and r["outside"]["friction_bump"]["F_b"] == cal["F_b"][0]
    assert r["calibration"]["target_ratio"] == {"a_cog": 2.0, "F_b": 3.0}
    rec = read_csv(tmp_path / r["file"])
    theta = np.array([r["params"][n] for n in PARAM_NAMES])
    base = S.base_record("simulation", 0.5)
    both = Outside(bump=(cal["F_b"][0], SP.BUMP_AT, SP.BUMP_WIDTH), cogging=(cal["a_cog"][0], 6.0, 0.5))
    clean, _, _ = simulate_outside(theta, base, both)
    assert np.std(rec.x_B - clean) == pytest.approx(1e-6, rel=0.15)
    bump_only, _, _ = simulate_outside(theta, base, Outside(bump=both.bump))
    assert np.max(np.abs(clean - bump_only)) > 2e-6  # the cogging is in it
    report = {"effects_added": [{"name": "cogging_torque"}], "unexplained": True}
    row = V.result_row(r, report, 1.0, "r")
    assert row["truth"] == ["cogging_torque", "friction_bump"] and row["verdict"] == "exact"
    summary = V.summarise([row])
    assert (summary["exact_mixed"], summary["mixed"]) == (1, 1)
    assert "mixed records with their library effects named and the rest called unexplained: 1 of 1" in \
        V.results_markdown([row], summary)


def test_validation_records_are_the_same_machine_under_the_other_command(tmp_path):
    B.main(["--out", str(tmp_path), "--only", "dead_time,outside_bump_cycling", "--duration", "0.5", "--validation"])
    man = {r["key"]: r for r in json.loads((tmp_path / "manifest.json").read_text())["records"]}
    for key, command in (("dead_time", "cycling"), ("outside_bump_cycling", "sweep")):
        entry = man[key]
        val = entry["validation"]
        assert val["command"]["kind"] == command and val["noise_seed"] == entry["noise"]["seed"] + 5000
        main, second = read_csv(tmp_path / entry["file"]), read_csv(tmp_path / val["file"])
        assert second.name.endswith("_validation") and second.n == main.n
        assert not np.allclose(main.v_in, second.v_in)  # another input
    # the truth is the record's: the second record of the dead-time machine is the simulator's output of it
    from toggle_id.app.records import build_record

    dt = man["dead_time"]
    clean, _ = build_record({"source": "simulated", "command": "cycling", "duration": 0.5, "params": dt["params"],
                             "effects": {"tau_d": dt["effect_params"]["dead_time"]["tau_d"]}, "noise_m": 0.0})
    noise = read_csv(tmp_path / dt["validation"]["file"]).x_B - clean.x_B
    assert 0.5e-6 < np.std(noise) < 1.5e-6  # only the noise differs


def test_rows_and_table_show_the_validation_prediction():
    report = {"effects_added": [], "rmse_before_m": 3e-6, "rmse_after_m": 3e-6, "unexplained": True,
              "validation_prediction": {"rmse_m": 3.4e-6, "structure_left": True,
                                        "text": "structure left: grows with model current i_q above 640 A"}}
    row = V.result_row(_entry("outside"), report, 5.0, "r")
    assert row["validation_rmse_um"] == pytest.approx(3.4) and row["validation_structure_left"] is True
    md = V.results_markdown([row], V.summarise([row]))
    assert "validation record predicted (µm)" in md and "3.4 (structure left)" in md
    assert "its validation record: structure left: grows with model current" in md
    plain = V.results_markdown([V.result_row(_entry("noise"), {"effects_added": []}, 1.0, "r")],
                               V.summarise([]))
    assert "validation record predicted" not in plain


def test_a_truth_the_command_cannot_drive_is_redrawn():
    theta = ASSIGNED.copy()
    assert S._valid_truth(theta, "cycling")
    fast = theta.copy()
    fast[INDEX["K_i"]] *= 3.0  # opens beyond x_B = 0
    assert not S._valid_truth(fast, "cycling")
    out = theta.copy()
    out[INDEX["K_l"]] = 1.2e8  # outside the feasible domain of docs/model.md §6
    assert not S._valid_truth(out, "simulation")


def _entry(category, effects=(), name="rec99"):
    return {"name": name, "category": category, "effects": list(effects), "outside": {},
            "noise": {"sigma_m": 1e-6, "ar": 0.0, "quantum_m": 0.0, "effective_sigma_m": 1e-6},
            "command": {"kind": "sweep", "sweep": "simulation"}, "sha256": "abc"}


@pytest.mark.parametrize("category,truth,added,unexplained,expected", [
    ("library", ["dead_time"], ["dead_time"], False, "exact"),
    ("library", ["dead_time"], ["dead_time", "backlash"], False, "spurious"),
    ("pair", ["dead_time", "coulomb_friction_motor"], ["dead_time"], False, "missed"),
    ("library", ["dead_time"], ["backlash"], True, "spurious+missed"),
    ("noise", [], [], False, "exact"),
    ("noise", [], ["sensor_offset"], False, "spurious"),
    ("outside", [], [], True, "unexplained-correct"),
    ("outside", [], [], False, "missed"),
    ("outside", [], ["stribeck_friction"], True, "spurious"),
    # a library effect and one outside the library: the first named, the rest called unexplained
    ("mixed", ["cogging_torque"], ["cogging_torque"], True, "exact"),
    ("mixed", ["cogging_torque"], ["cogging_torque"], False, "exact+outside-missed"),
    ("mixed", ["cogging_torque"], [], True, "missed"),
    ("mixed", ["cogging_torque"], ["cogging_torque", "stribeck_friction"], True, "spurious"),
    ("mixed", ["cogging_torque"], ["stribeck_friction"], False, "spurious+missed+outside-missed"),
])
def test_verdicts(category, truth, added, unexplained, expected):
    report = {"effects_added": [{"name": n} for n in added], "unexplained": unexplained,
              "rmse_before_m": 2e-6, "rmse_after_m": 1e-6}
    assert V.verdict(_entry(category, truth), report) == expected


@pytest.mark.parametrize("category,truth,added,group,expected", [
    ("library", ["torque_constant_saturation"], [], ["contact_nonlinear_stiffness", "torque_constant_saturation"],
     "ambiguous-correct"),
    ("library", ["contact_nonlinear_stiffness"], [], ["torque_constant_saturation", "contact_nonlinear_stiffness"],
     "ambiguous-correct"),
    ("library", ["dead_time"], [], ["backlash", "cogging_torque"], "ambiguous-wrong+missed"),
    ("pair", ["dead_time", "sensor_offset"], ["dead_time"], ["sensor_offset", "constant_load_force"],
     "ambiguous-correct"),
    ("library", ["dead_time"], ["dead_time"], ["backlash", "cogging_torque"], "ambiguous-wrong"),
    ("outside", [], [], ["stribeck_friction", "viscous_friction_slider"], "ambiguous-wrong"),
])
def test_ambiguous_verdicts(category, truth, added, group, expected):
    report = {"effects_added": [{"name": n} for n in added], "unexplained": False,
              "ambiguous": [{"name": group[0], "indistinguishable_from": [{"name": g} for g in group[1:]]}]}
    assert V.verdict(_entry(category, truth), report) == expected


def test_result_rows_read_the_new_keys_when_present_and_do_without_them():
    report = {"effects_added": [{"name": "dead_time"}], "rmse_before_m": 2.5e-6, "rmse_after_m": 1.0e-6,
              "compensating": [{"name": "constant_load_force"}], "rejected": ["backlash"],
              "noise_model": {"after": {"kind": "ar", "order": 1, "ar1_rho": 0.487}}, "unexplained": False,
              "localisation": {"structure_left": False}}
    row = V.result_row(_entry("library", ["dead_time"]), report, 12.0, "/x/discovery.json")
    assert row["accepted"] == ["dead_time"] and row["compensating"] == ["constant_load_force"]
    assert row["rejected"] == ["backlash"] and row["noise_model"] == "AR(1) ρ 0.49"
    assert row["structure_left"] is False
    assert row["before_sigma"] == pytest.approx(2.5) and row["verdict"] == "exact"
    bare = V.result_row(_entry("noise"), {"effects_added": []}, 1.0, "r")
    assert bare["compensating"] == [] and bare["rmse_before_um"] is None and bare["verdict"] == "exact"
    assert bare["noise_model"] is None and bare["structure_left"] is None
    assert V.accepted_effects({"accepted": ["dead_time"]}) == ["dead_time"]  # the list of names alone
    rows = [row, bare, {"record": "rec98", "category": "outside", "verdict": "error", "wall_s": 3.0, "error": "x"}]
    s = V.summarise(rows)
    assert (s["exact_in_library"], s["in_library"], s["nothing_accepted_quiet"], s["quiet"], s["errors"]) == \
        (1, 1, 1, 1, 1)
    md = V.results_markdown(rows, s)
    assert "Exact effect set on 1 of 1 in-library records (1 of them with the RMS after ≤ 1.5 σ); nothing accepted on 1 of 1" in md
    assert "Code: not recorded (every record)." in md  # reports made before they said which code made them


def test_the_where_lines_add_what_repeats_with_a_position():
    report = {"effects_added": [], "unexplained": True,
              "localisation": {"structure_left": True, "text": "structure left: a bump near i_q ≈ 176 A"},
              "residual_tests_after": {"periodic": {"periodic": True, "text": "the residual repeats every 4.81 mm"}}}
    row = V.result_row(_entry("outside", name="rec23"), report, 1.0, "r")
    md = V.results_markdown([row], V.summarise([row]))
    assert ("rec23 (no effect): structure left: a bump near i_q ≈ 176 A; periodic: the residual repeats every "
            "4.81 mm") in md
    quiet = V.result_row(_entry("outside", name="rec24"), {**report, "residual_tests_after": {}}, 1.0, "r")
    assert quiet["periodic"] is None


def test_the_table_says_which_code_made_each_row():
    made = {"effects_added": [], "code": {"version": "0.1.0", "git_commit": "0123456789abcdef", "git_dirty": False}}
    dirty = {"effects_added": [], "code": {"version": "0.1.0", "git_commit": "fedcba9876543210", "git_dirty": True}}
    a = V.result_row(_entry("noise", name="rec01"), made, 1.0, "r")
    b = V.result_row(_entry("noise", name="rec02"), dirty, 1.0, "r")
    assert a["commit"] == "0123456" and b["commit"] == "fedcba9+dirty"
    assert V.code_label({"version": "0.1.0"}) == "version 0.1.0" and V.code_label(None) is None
    assert "Code: 0123456 (every record)." in V.results_markdown([a], V.summarise([a]))
    assert "Code: 0123456 (rec01); fedcba9+dirty (rec02)." in V.results_markdown([a, b], V.summarise([a, b]))


def test_code_version_names_this_checkout_or_only_the_version():
    from toggle_id.provenance import code_version

    code = code_version()
    assert set(code) <= {"version", "git_commit", "git_dirty"} and "version" in code
    if "git_commit" in code:  # a checkout of the project (CI, a user's clone); an installed copy has the version only
        assert code["git_commit"] is None or len(code["git_commit"]) == 40


def test_a_record_judged_before_on_the_same_file_is_not_run_again(tmp_path: Path):
    entry = _entry("noise")
    done = tmp_path / "runs" / entry["name"]
    done.mkdir(parents=True)
    (done / "result_row.json").write_text(json.dumps({"record": entry["name"], "verdict": "exact",
                                                      "csv_sha256": "abc"}))
    assert B.run_one(entry, tmp_path, [], None, 1.0, log=lambda *_: None)["verdict"] == "exact"
    (done / "result_row.json").write_text(json.dumps({"record": entry["name"], "verdict": "exact",
                                                      "csv_sha256": "abc", "overrides": ["discover.nominal=base"]}))
    assert B.run_one(entry, tmp_path, ["discover.nominal=base"], None, 1.0, log=lambda *_: None)["verdict"] == "exact"


def test_jobs_side_by_side_share_the_cores(tmp_path: Path, monkeypatch):
    """With ``--jobs`` > 1 each discover job gets toggle_id.simulate.SHARED_CORES_ENV (a user's setting kept); alone,
    the environment as it is."""
    from toggle_id.simulate import SHARED_CORES_ENV

    seen = []

    def fake_run(cmd, env, **kwargs):
        seen.append({k: env.get(k) for k in SHARED_CORES_ENV})
        return subprocess.CompletedProcess(cmd, 1, "", "not run")

    monkeypatch.setattr(B.subprocess, "run", fake_run)
    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
    manifest = {"records": [{**_entry("noise", name=n), "file": f"{n}.csv"} for n in ("rec01", "rec02", "rec03")]}
    rows, _ = B.run_all(tmp_path, manifest, ["rec01", "rec02"], [], None, 2, 1.0, log=lambda *_: None)
    assert [r["verdict"] for r in rows] == ["error", "error"] and seen == [SHARED_CORES_ENV] * 2
    seen.clear()
    B.run_one(manifest["records"][2], tmp_path, [], None, 1.0, log=lambda *_: None)
    assert seen == [{k: None for k in SHARED_CORES_ENV}]
    monkeypatch.setenv("OMP_WAIT_POLICY", "ACTIVE")
    seen.clear()
    B.run_all(tmp_path, manifest, ["rec01"], [], None, 2, 1.0, log=lambda *_: None)
    assert seen == [{"OMP_WAIT_POLICY": "ACTIVE"}]


@pytest.mark.slow
@pytest.mark.integration
def test_run_judges_one_record_with_the_discover_job(tmp_path):
    """The whole plumbing on one short record: the discover job as a subprocess, its report, the verdict, the
    result files, and a second call that reuses the result."""
    over = ["--override", "discover.nominal=base", "--override", "evaluator=serial", "--override",
            "discover.candidates=[sensor_offset,constant_load_force]", "--override", "discover.max_effects=1"]
    args = ["--out", str(tmp_path), "--only", "noise_white", "--duration", "1.0", "--run", *over]
    assert B.main(args) == 0
    res = json.loads((tmp_path / "results.json").read_text())
    (row,) = res["rows"]
    assert row["record"] == SP.NAMES["noise_white"] and row["verdict"] == "exact" and row["accepted"] == []
    assert row["rmse_after_um"] == pytest.approx(1.0, rel=0.15) and Path(row["report"]).is_file()
    assert "nothing accepted on 1 of 1" in (tmp_path / "results.md").read_text()
    report = json.loads(Path(row["report"]).read_text())
    assert report["code"]["version"] and row["commit"] == V.code_label(report["code"])  # which code made it
    wall = row["wall_s"]
    assert B.main(args) == 0  # resumed: not run again
    assert json.loads((tmp_path / "results.json").read_text())["rows"][0]["wall_s"] == wall


def test_calibration_finds_the_magnitude_whose_refit_leaves_the_target_ratio():
    """jobs.adversarial_calibration on a 1-s record (the voltage saturation under AR(1) noise: steep, searched in
    the excess over the clipping threshold): the ratio of the magnitude found is the target within the tolerance,
    and measuring that magnitude again gives the same ratio."""
    import math

    from jobs import adversarial_calibration as C

    spec = SP.SPECS_BY_KEY["ar09_voltage_saturation_cycling"]
    theta, _ = S.draw_truth(spec)
    out = C.calibrate_param(spec, "s_sat", theta, duration=1.0, log=lambda m: None)
    assert abs(out["ratio"] / spec.target - 1.0) <= 0.03 and out["evaluations"][-1]["value"] == out["value"]
    rec = S.base_record(spec.command, 1.0)
    x, _ = S.clean_response(spec, theta, {"s_sat": out["value"]}, {"s_sat": out["value"]}, rec)
    r = C.refit_rms(spec, theta, rec, x)
    sigma = SP.effective_sigma(spec.noise_m, spec.quantum_m)
    assert math.sqrt(r * r + sigma ** 2) / sigma == pytest.approx(out["ratio"], rel=1e-6)
    assert C.calibration_table({spec.key: {"s_sat": out}}).startswith(f'    "{spec.key}": {{"s_sat": (')


def test_the_gross_error_record_is_what_its_jobs_simulate_command_writes(tmp_path):
    """The noise-only record with gross errors (1 % of samples, 10 µm): the manifest's command line, run through
    ``jobs.simulate``'s own writer, gives the same x_B — the options reach a user's command too."""
    from jobs.simulate import write_record

    B.main(["--out", str(tmp_path), "--only", "noise_outliers", "--duration", "0.5"])
    (r,) = json.loads((tmp_path / "manifest.json").read_text())["records"]
    assert r["noise"]["outlier_fraction"] == 0.01 and r["noise"]["outlier_m"] == 10e-6
    assert r["noise"]["effective_sigma_m"] == pytest.approx(np.sqrt(2) * 1e-6)
    cfg: dict = {"params": {}, "effects": {}}
    for token in r["jobs_simulate"].split()[3:]:
        key, value = token.split("=", 1)
        head, _, tail = key.partition(".")
        value = value if key in ("out", "command", "sweep") else float(value)
        (cfg[head].__setitem__(tail, value) if tail else cfg.__setitem__(key, value))
    cfg["seed"] = int(cfg["seed"])
    assert cfg["outlier_fraction"] == 0.01
    path = write_record({**cfg, "out": "again.csv"}, str(tmp_path))
    mine, again = read_csv(tmp_path / r["file"]), read_csv(path)
    np.testing.assert_array_equal(again.x_B, mine.x_B)
    clean = read_csv(write_record({**cfg, "out": "clean.csv", "outlier_fraction": 0.0}, str(tmp_path)))
    hit = clean.x_B != mine.x_B  # the gross errors, and nothing else, tell the two apart
    assert 0 < hit.sum() < 0.03 * mine.n
