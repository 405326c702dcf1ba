"""The joint look at pairs (toggle_id/discovery/pairs.py): which pairs are refitted, and when a pair replaces the
step's best single effect. The fits and the judge are stand-ins here (the refit of a real pair is measured on the
held-out record rec44_d1: docs/discovery.md); the loop's wiring of a pair (both effects added in one step) is
checked through the plant's forward step."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from toggle_id.discovery import pairs as PR
from toggle_id.discovery.model import Fit
from toggle_id.discovery.refit import Refit
from toggle_id.discovery.settings import DiscoverSettings
from toggle_id.discovery.timing import PhaseClock
from toggle_id.effects import ALL_INDEX, EFFECTS
from toggle_id.params import ASSIGNED
from toggle_id.simulate import extend

from discovery_cases import NOISE, make_record

N = 1000
THETA = extend(ASSIGNED)[0]
BASE_FREE = ("mu", "D")


def _fit(rms_um: float, free=BASE_FREE, **values) -> Fit:
    theta = THETA.copy()
    for nm, v in values.items():
        theta[ALL_INDEX[nm]] = v
    return Fit(theta, tuple(free), (rms_um * 1e-6) ** 2 * N, raw_sse=(rms_um * 1e-6) ** 2 * N)


def _single(name: str, rms_um: float, accepted: bool = False, **values) -> Refit:
    fit = _fit(rms_um, BASE_FREE + tuple(values), **values)
    return Refit(name, 1, fit, dict(values), 0.0, fit.sse, len(values), len(fit.free), 0.0, 1.0, 0.0, accepted, "", {})


class _Judge:
    """Passes a larger model whose RMS is below ``passes_below`` µm (its nested comparisons alike)."""

    def __init__(self, passes_below: float):
        self.passes_below, self.asked = passes_below, []

    def judge_pair(self, small: Fit, large: Fit):
        self.asked.append((small.rmse(N) * 1e6, large.rmse(N) * 1e6))
        ok = large.rmse(N) * 1e6 < self.passes_below and large.sse < small.sse
        return SimpleNamespace(passed=ok, reason="" if ok else "not significant", F=9.0, p_value=1e-9,
                               delta_bic=-5.0, to_dict=lambda: {"cv_z": 3.0})


@pytest.fixture
def model(monkeypatch):
    """A white-noise model whose pairs leave no structure (the structure test is the next test's own case)."""
    monkeypatch.setattr(PR, "structure_left_at", lambda m, theta, settings: (False, "no structure left: …"))
    return SimpleNamespace(n=N, noise=SimpleNamespace(white=True))


def test_a_supported_pair_above_the_band_that_leaves_structure_compensates_and_is_not_taken(monkeypatch, model):
    """The set's rec47 (a random walk on the sensor, no effect), pair_look=4: a cogging torque with a sensor offset
    refitted together was supported at 1.528 µm, where neither alone was, and added. A pair is looked at to explain
    the record: above the noise band it is taken only where it leaves no structure; within the band it is taken
    without asking."""
    monkeypatch.setattr(PR, "pair_fit", lambda m, base, a, b, s, held: _fit(1.3, BASE_FREE + ("a_cog", "x_off")))
    asked = []
    monkeypatch.setattr(PR, "structure_left_at", lambda m, theta, settings: asked.append(1) or (
        True, "structure left: a bump near slider B velocity ≈ 352 mm/s"))
    refits = [_single("cogging_torque", 1.5, a_cog=1e-3), _single("sensor_offset", 1.6, x_off=1e-6)]
    out, report = PR.pair_look(model, _Judge(1.4), _fit(1.6), refits, None, DiscoverSettings(pair_look=2), 1, (),
                               lambda s: None, near_m=1.2e-6)
    assert out is None and asked == [1] and "they compensate" in report[0]["reason"]
    assert report[0]["evidence"]["structure_after"].startswith("structure left")
    asked.clear()  # the same pair within the band: explained, the structure test not asked
    out, _ = PR.pair_look(model, _Judge(1.4), _fit(1.6), refits, None, DiscoverSettings(pair_look=2), 1, (),
                          lambda s: None, near_m=1.35e-6)
    assert out is not None and out.partner == "sensor_offset" and asked == []


def test_the_pairs_of_the_best_single_refits_are_refitted(monkeypatch, model):
    """Every pair of the ``pair_look`` single refits of lowest error, one refit per effect, a failed one left out."""
    seen = []
    monkeypatch.setattr(PR, "pair_fit", lambda m, base, a, b, s, held: seen.append((a.name, b.name)) or
                        _fit(9.0, BASE_FREE + ("tau_d", "x_off")))
    refits = [_single("dead_time", 1.3, tau_d=1e-4), _single("sensor_offset", 1.4, x_off=1e-6),
              _single("dead_time", 1.35, tau_d=2e-4), _single("cogging_torque", 1.2, a_cog=0.1),
              _single("backlash", 1.1, b_l=1e-5)]
    refits[-1].sse1 = float("nan")  # could not be simulated
    out, report = PR.pair_look(model, _Judge(0.5), _fit(1.45), refits, None, DiscoverSettings(pair_look=3), 1, (),
                               lambda s: None)
    assert seen == [("cogging_torque", "dead_time"), ("cogging_torque", "sensor_offset"),
                    ("dead_time", "sensor_offset")]
    assert out is None and len(report) == 3  # none supported (9 µm)


def test_a_supported_pair_below_the_best_single_adds_both(monkeypatch, model):
    """The supported pair of lowest error replaces the step's best single effect, named after its member of lower
    single error with the other as its partner; a pair no lower than that single effect does not."""
    rms = {("stribeck_friction", "dead_time"): 1.02, ("stribeck_friction", "coulomb_friction_motor"): 1.30,
           ("dead_time", "coulomb_friction_motor"): 1.25}
    monkeypatch.setattr(PR, "pair_fit", lambda m, base, a, b, s, held: _fit(
        rms[(a.name, b.name)], BASE_FREE + tuple(a.params) + tuple(b.params), **a.params, **b.params))
    refits = [_single("stribeck_friction", 1.33, F_s=360.0, v_s=0.1), _single("dead_time", 1.35, tau_d=1e-4),
              _single("coulomb_friction_motor", 1.427, accepted=True, tau_c=0.9)]
    best = refits[2]
    out, report = PR.pair_look(model, _Judge(1.4), _fit(1.45), refits, best, DiscoverSettings(pair_look=3), 1, (),
                               lambda s: None)
    assert (out.name, out.partner) == ("stribeck_friction", "dead_time") and out.accepted
    assert out.k == 3 and set(out.params) == {"F_s", "v_s", "tau_d"}
    assert [r["partner"] for r in report] == ["dead_time", "coulomb_friction_motor", "coulomb_friction_motor"]
    # a best single effect lower than every pair: no pair replaces it
    out, _ = PR.pair_look(model, _Judge(1.4), _fit(1.45), refits, _single("dead_time", 1.0, True, tau_d=1e-4),
                          DiscoverSettings(pair_look=3), 1, (), lambda s: None)
    assert out is None


def test_a_pair_with_the_best_single_effect_must_be_significant_beside_it(monkeypatch, model):
    """Where the step's best single effect is one of the pair, the pair is judged against that effect's own refit
    too (nested): not significant there, the single effect stays."""
    monkeypatch.setattr(PR, "pair_fit", lambda m, base, a, b, s, held: _fit(1.20, BASE_FREE + ("tau_d", "x_off")))
    best = _single("dead_time", 1.25, True, tau_d=1e-4)
    refits = [best, _single("sensor_offset", 1.4, x_off=1e-6)]
    judge = _Judge(1.4)
    judge.judge_pair = (lambda f: lambda small, large: f(small, large) if small.rmse(N) > 1.3e-6 else
                        SimpleNamespace(passed=False, reason="F-test not significant", F=1.0, p_value=0.3,
                                        delta_bic=5.0, to_dict=lambda: {}))(judge.judge_pair)
    out, report = PR.pair_look(model, judge, _fit(1.45), refits, best, DiscoverSettings(pair_look=2), 1, (),
                               lambda s: None)
    assert out is None and "not significant beside dead_time" in report[0]["reason"]


def test_pair_settings_are_checked():
    from toggle_id.errors import ConfigError

    assert DiscoverSettings(pair_look=4).validate().pair_look == 4
    for bad in ({"pair_look": -1}, {"pair_look": 2.5}, {"pair_look": True}, {"pair_above": 0.5},
                {"pair_above": "x"}):
        with pytest.raises(ConfigError, match="pair_"):
            DiscoverSettings(**bad).validate()


def test_a_supported_pair_adds_both_effects_in_one_step(monkeypatch):
    """The plant's forward step with a pair chosen: one step, both effects in the model after it and in the loop's
    list (``Step.more``), each with its own parameters at acceptance."""
    from toggle_id.discovery import engine as E
    from toggle_id.discovery import toggle_plant as TP
    from toggle_id.discovery.noise import WHITE

    theta = THETA.copy()
    free = ("mu", "F_s", "v_s", "tau_d")
    pair = _single("stribeck_friction", 1.02, True, F_s=300.0, v_s=0.03, tau_d=4e-4)
    pair.partner = "dead_time"
    monkeypatch.setattr(TP, "_polish_with_effect", lambda m, chosen, *a, **k: Fit(chosen.fit.theta, free, 1.0))
    monkeypatch.setattr(TP, "rescreened", lambda m, name, fit, *a: (fit, []))  # the stand-in has no record
    steps = iter([pair, None])
    monkeypatch.setattr(TP, "_iteration", lambda m, *a, **k: {
        "refits": [], "scores": [], "base": a[1], "better_null": None, "record": {}, "chosen": next(steps),
        "rivals": []})
    plant = TP.TogglePlant(SimpleNamespace(n=N, noise=WHITE, clock=PhaseClock()), SimpleNamespace(glitches=[]),
                           DiscoverSettings(glitch_k=0.0, prediction_error=False, edge_widenings=0,
                                            other_starts_above=0.0), theta, [],
                           ("mu",), (), list(EFFECTS), None, lambda s: None, None)
    plant.baseline_fit, plant.anchor = Fit(theta, ("mu",), 4.0), theta
    final, added = E.forward(plant, None)
    assert [a["name"] for a in added] == ["stribeck_friction", "dead_time"]
    assert added[0]["params_at_acceptance"] == {"F_s": 300.0, "v_s": 0.03}
    assert added[1]["params_at_acceptance"] == {"tau_d": 4e-4} and added[1]["added_with"] == "stribeck_friction"
    assert final.free == free and frozenset(["stribeck_friction", "dead_time"]) in plant.had


def test_the_look_stops_at_a_supported_pair_near_the_noise(monkeypatch, model):
    """Pairs are refitted in order until a supported one ends within the noise band: no other can explain much
    more."""
    seen = []
    monkeypatch.setattr(PR, "pair_fit", lambda m, base, a, b, s, held: seen.append((a.name, b.name)) or _fit(
        1.02 if (a.name, b.name) == ("stribeck_friction", "dead_time") else 1.3, BASE_FREE + ("tau_d",)))
    refits = [_single("stribeck_friction", 1.33, F_s=360.0, v_s=0.1), _single("dead_time", 1.35, tau_d=1e-4),
              _single("sensor_offset", 1.4, x_off=1e-6)]
    out, report = PR.pair_look(model, _Judge(1.4), _fit(1.45), refits, None, DiscoverSettings(pair_look=3), 1, (),
                               lambda s: None, near_m=1.2e-6)
    assert seen == [("stribeck_friction", "dead_time")] and out.partner == "dead_time" and len(report) == 1
    seen.clear()
    PR.pair_look(model, _Judge(1.4), _fit(1.45), refits, None, DiscoverSettings(pair_look=3), 1, (), lambda s: None)
    assert len(seen) == 3  # no band: every pair


def test_the_pair_looks_gate_reads_coloured_noise_as_noise_and_a_missing_effect_as_structure():
    """The gate behind the pair look's RMS band (:func:`toggle_id.discovery.residual.structure_left_at`): AR(1)
    ρ 0.9 noise of σ = 1 µm around the true model is noise (its third differences read about 0.27 µm, so the RMS
    band alone would open), a 20-µm offset the model lacks, under white noise, is structure."""
    from toggle_id.discovery.model import Model
    from toggle_id.discovery.residual import structure_left_at
    from toggle_id.fast import difference_noise

    rec, truth, _ = make_record({}, noise=0.0)
    rng = np.random.default_rng(4)
    e = np.zeros(rec.n)
    w = rng.standard_normal(rec.n) * NOISE * np.sqrt(1.0 - 0.9 ** 2)
    e[0] = NOISE * rng.standard_normal()
    for t in range(1, rec.n):
        e[t] = 0.9 * e[t - 1] + w[t]
    clean = rec.x_B.copy()
    rec.x_B = clean + e
    assert difference_noise([rec]) < 0.4 * NOISE  # the RMS band would read this record as far above its noise
    left, text = structure_left_at(Model(rec), truth, DiscoverSettings())
    assert not left and text.startswith("no structure left")
    rec.x_B = clean + 2e-5 + NOISE * rng.standard_normal(rec.n)
    left, text = structure_left_at(Model(rec), truth, DiscoverSettings())
    assert left and text.startswith("structure left")
