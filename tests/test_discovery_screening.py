"""The discovery loop's screening: settings, the statistics, score tests and magnitude profiles, which candidates are
scouted and refitted, stronger magnitudes and the guard's null refits."""
from __future__ import annotations

import json

import numpy as np
import pytest

from toggle_id import discovery as D
from toggle_id.discovery.timing import PhaseClock
from toggle_id.effects import ALL_INDEX, EFFECTS, EFFECTS_BY_NAME
from toggle_id.errors import ConfigError
from toggle_id.params import ASSIGNED, PARAM_NAMES
from toggle_id.simulate import extend

from discovery_cases import fake_model, make_record, refit_case


# ---------------------------------------------------------------------------------------------- screening
def test_settings_validate_and_reject_bad_values():
    from toggle_id.app.discover import discover_settings

    s = D.DiscoverSettings.from_dict({"top_k": 2, "candidates": ["dead_time"], "nominal": "ga", "base": {}})
    assert s.top_k == 2 and s.candidates == ("dead_time",)
    assert D.DiscoverSettings.from_dict({"candidates": "all"}).candidates is None
    assert D.DiscoverSettings.from_dict({"stronger_starts": [2, 5]}).stronger_starts == (2.0, 5.0)
    assert D.DiscoverSettings.from_dict({"stronger_starts": []}).stronger_starts == ()
    assert D.DiscoverSettings.from_dict({"other_starts_above": 0}).other_starts_above == 0
    for bad, needle in [({"top_k": 0}, "top_k"), ({"alpha": 1.5}, "alpha"), ({"candidates": ["nope"]}, "nope"),
                        ({"bogus": 1}, "bogus"), ({"max_effects": -1}, "max_effects"),
                        ({"noise_std": -1.0}, "noise_std"), ({"catch_all_keep": 1.0}, "catch_all_keep"),
                        ({"catch_all": "yes"}, "catch_all"), ({"catch_all_calibrated": 1}, "catch_all_calibrated"),
                        ({"catch_all_share_min": 1.5}, "catch_all_share_min"),
                        ({"fd_tier": "loose"}, "fd_tier"),
                        ({"jacobian_reuse": -1}, "jacobian_reuse"), ({"jacobian_reuse": True}, "jacobian_reuse"),
                        ({"stronger_starts": [0.5]}, "stronger_starts"), ({"stronger_starts": 3}, "stronger_starts"),
                        ({"routes": "sometimes"}, "routes"), ({"route_rtol": 1.0}, "route_rtol"),
                        ({"route_max_ratio": 1.0}, "route_max_ratio"), ({"route_max_ratio": "x"}, "route_max_ratio"),
                        ({"glitch_k": -1.0}, "glitch_k"), ({"glitch_k": True}, "glitch_k"),
                        ({"unconverged_share": 1.0}, "unconverged_share"),
                        ({"unconverged_share": "x"}, "unconverged_share"),
                        ({"other_starts_above": 0.5}, "other_starts_above"),
                        ({"other_starts_above": True}, "other_starts_above"),
                        ({"level_min_count": -1}, "level_min_count"), ({"level_min_count": True}, "level_min_count"),
                        ({"pe_guard_alpha": 1.0}, "pe_guard_alpha"), ({"pe_guard_alpha": "x"}, "pe_guard_alpha"),
                        ({"cv_rcond": 0.0}, "cv_rcond"), ({"cv_rcond": True}, "cv_rcond")]:
        with pytest.raises(ConfigError, match=needle):
            D.DiscoverSettings.from_dict(bad)
    with pytest.raises(ConfigError, match="nominal"):
        discover_settings({"discover": {"nominal": "magic"}})
    with pytest.raises(ConfigError, match="alternatives"):
        discover_settings({"discover": {"alternatives": ["gradient_descent"]}})
    for bad in (-1, 1.5, True, "two"):
        with pytest.raises(ConfigError, match="restarts"):
            discover_settings({"discover": {"restarts": bad}})
    assert discover_settings({"discover": {"restarts": 0}}) is not None
    assert D.DiscoverSettings.from_dict({"alternatives": ["fast"], "routes": "always"}).routes == "always"


def test_f_test_and_bic():
    n, p1 = 1000, 16
    F, p, dbic = D.f_test(2.0, 1.0, 1, n, p1)
    assert F == pytest.approx((1.0 / 1) / (1.0 / (n - p1)))
    assert p < 1e-100 and dbic == pytest.approx(n * np.log(0.5) + np.log(n))
    F, p, dbic = D.f_test(1.0, 0.9999, 1, n, p1)  # a noise-sized gain: neither test is passed
    assert p > 0.5 and dbic > 0
    assert D.f_test(1.0, np.inf, 1, n, p1) == (0.0, 1.0, float("inf"))


def test_projector_removes_the_range_and_solves():
    rng = np.random.default_rng(0)
    J = rng.standard_normal((200, 4))
    J[:, 3] = J[:, 0] + J[:, 1]  # rank 3
    P = D.Projector.of(J)
    assert P.rank == 3
    v = rng.standard_normal(200)
    assert np.allclose(J.T @ P.perp(v), 0.0, atol=1e-10)
    du = np.array([0.1, -0.2, 0.3, 0.0])
    assert np.allclose(J @ P.solve(J @ du), J @ du)


def test_magnitude_grid_spans_the_domain_on_the_allowed_sides():
    g = D._magnitude_grid(EFFECTS_BY_NAME["constant_load_force"], {"F_load": 1.0}, 37.0, 10)
    assert (g < 0).sum() == 10 and (g > 0).sum() == 11 and 37.0 in g
    assert g.min() >= -2000 and g.max() <= 2000
    g = D._magnitude_grid(EFFECTS_BY_NAME["dead_time"], {"tau_d": 1e-4}, -1.0, 10)
    assert np.all(g > 0) and g.max() <= 0.05  # tau_d ≥ 0: the negative LM estimate is clipped away


def test_candidates_within_the_score_tests_resolution_of_the_top_one_all_lead():
    from toggle_id.discovery.scoring import CandidateScore
    from toggle_id.discovery.scoring import score_leaders

    def cand(name, score, profile):
        return CandidateScore(name, score, 0.0, {}, None, 1.0, 1.0, profile_score=profile)

    # rec08's first iteration: the saturation and the stiffness differ by 0.13 (far below χ²(1)'s 3.84 at 0.05)
    scored = [cand("torque_constant_saturation", 276.835, 276.0), cand("contact_nonlinear_stiffness", 276.972, 274.0),
              cand("voltage_saturation", 34.6, 2.33), cand("cogging_torque", 2.64, 2.62)]
    assert score_leaders(scored, 0.05) == {"torque_constant_saturation", "contact_nonlinear_stiffness"}
    assert score_leaders(scored, 0.0) == {"contact_nonlinear_stiffness"}  # the top statistic alone
    # the larger of the two statistics counts: a profile far above the score test leads too
    assert score_leaders([cand("a", 10.0, 50.0), cand("b", 48.0, 1.0), cand("c", 45.0, 1.0)], 0.05) == {"a", "b"}
    assert score_leaders([], 0.05) == set()
    # statistics at the noise's level all lie within the band: only the top one leads (a backlash's test record)
    noise = [cand("dead_time", 2.85, 3.1), cand("backlash", 2.51, 2.72), cand("coulomb_friction_motor", 1.82, 2.32)]
    assert score_leaders(noise, 0.05, screen=3.84) == {"dead_time"}
    assert score_leaders(scored, 0.05, screen=3.84) == {"torque_constant_saturation", "contact_nonlinear_stiffness"}


def test_a_leader_whose_refit_explains_nothing_hands_its_look_to_the_next_significant_leaders():
    """Held-out rec46_d1's first route: the dead time led the score test and its refit found nothing; the backlash,
    second by its score, had scouted fifth and was never refitted alone. Now it is, before the catch-all."""
    from types import SimpleNamespace as NS

    from toggle_id.discovery.forward import next_leaders
    from toggle_id.discovery.scoring import CandidateScore

    def cand(name, stat):
        return CandidateScore(name, stat, 0.0, {}, None, 1.0, 1.0, profile_score=0.0)

    scores = [cand("dead_time", 165.0), cand("backlash", 132.0), cand("constant_load_force", 130.0),
              cand("stribeck_friction", 120.0), cand("cogging_torque", 39.0), cand("viscous_friction_slider", 5.0)]
    order = [NS(name=nm) for nm in ("cogging_torque", "constant_load_force", "stribeck_friction", "backlash",
                                    "viscous_friction_slider", "dead_time")]  # the scouts' order
    screen = 6.63

    def refit(name, F, k=1, accepted=False):
        return NS(name=name, F=F, k=k, accepted=accepted)

    def run(refits, answers):
        """The names the rule sends to a refit, each refit's result taken from ``answers`` as it comes."""
        sent = []
        for sc in next_leaders(refits, scores, order, {"dead_time"}, screen, 0.05):
            sent.append(sc.name)
            refits.append(answers[sc.name])
        return sent

    first = [refit("cogging_torque", 30.7, 3), refit("constant_load_force", 213.0), refit("dead_time", -0.002)]
    # the backlash and the load force (130, within χ²(1)'s 3.84 of 132) lead next; the load force was refitted
    assert run(list(first), {"backlash": refit("backlash", 779.0, accepted=True)}) == ["backlash"]
    # the backlash explains nothing either: set aside too; the load force (130) leads alone and was refitted
    assert run(list(first), {"backlash": refit("backlash", 0.5)}) == ["backlash"]
    # a leader that explained something, though not accepted: its score told something, nobody else is owed a look
    assert run([*first[:2], refit("dead_time", 40.0)], {}) == []
    # something of the round supported: the rule does not run
    assert run([*first[:2], refit("dead_time", -0.002), refit("sensor_offset", 50.0, accepted=True)], {}) == []
    # below the screen no statistic is evidence: with only noise-level scores left nothing is sent
    quiet = [cand("dead_time", 165.0), cand("viscous_friction_slider", 5.0)]
    assert list(next_leaders([refit("dead_time", 0.0)], quiet, order, {"dead_time"}, screen, 0.05)) == []
    # the setting is validated
    with pytest.raises(ConfigError, match="next_leaders"):
        D.DiscoverSettings.from_dict({"next_leaders": "yes"})


def test_beyond_top_k_a_scout_is_refitted_while_it_could_beat_or_tie_the_best_refit_or_its_score_exceeds_it():
    from toggle_id.discovery.settings import DiscoverSettings
    from toggle_id.discovery.scoring import worth_refitting

    n, st = 5001, DiscoverSettings(alpha=0.01, ambiguity_alpha=0.05)

    def sse(rms_um):
        return (rms_um * 1e-6) ** 2 * n

    best, realised = sse(2.0), 30.0  # an accepted refit at 2 µm that realised F·k = 30

    def worth(rms_um, statistic, **kw):
        return worth_refitting(sse(rms_um), statistic, sse(2.178), 13, 1, n, st, **kw)

    assert worth(1.9, 0.0, best_sse=best, realised=realised)  # its scout already explains more
    assert worth(2.004, 0.0, best_sse=best, realised=realised)  # within the tie band: a possible rival
    assert not worth(2.3, 20.0, best_sse=best, realised=realised)  # far above, and its score is below F·k
    assert worth(2.3, 57.9, best_sse=best, realised=realised)  # rec15: the score says more than the scout shows
    assert not worth(2.3, float("nan"), best_sse=best, realised=realised)
    # none accepted yet: refitted while the scout's short polish is significant as least squares (F-test, k = 1)
    assert worth(2.17, 0.0) and not worth(2.1779, 1e6)
    assert not worth_refitting(sse(2.17), 0.0, sse(2.178), 13, 1, n, DiscoverSettings(alpha=1e-12))


@pytest.mark.parametrize("kinds, refitted", [
    (set(), []), ({"slider"}, ["viscous_friction_slider"]),
    ({"slider", "reading"}, ["viscous_friction_slider", "sensor_offset"])])
def test_with_nothing_supported_the_catch_alls_kind_of_term_sends_its_untried_effects_to_a_refit(
        monkeypatch, kinds, refitted):
    """rec33 of the adversarial set: a faint slider viscous friction scouts 8th and is never refitted; the refits
    made fail. When the catch-all's generic force (or reading error) explains what is left, every library effect of
    that kind the scouts left untried is refitted — not the others (a dead time), and nothing when none is asked."""
    from types import SimpleNamespace

    from toggle_id.discovery import forward as TP
    from toggle_id.discovery.model import Fit
    from toggle_id.discovery.refit import Refit, Scout
    from toggle_id.discovery.scoring import CandidateScore
    from toggle_id.discovery.settings import DiscoverSettings

    n, base_sse = 1000, 1.0
    rms = {"coulomb_friction_motor": 0.99, "stribeck_friction": 0.992, "constant_load_force": 0.994,
           "dead_time": 0.996, "viscous_friction_slider": 0.998, "sensor_offset": 0.9985}  # scout SSE, in order
    names = list(rms)
    theta = extend(ASSIGNED)[0]

    def assess(model, label, th, free, remaining, settings, noise):
        sc = {nm: CandidateScore(nm, 300.0 if nm == names[0] else 1.0, 0.3, {}, None, 1.0, 1.0) for nm in names}
        return SimpleNamespace(label=label, scores=sc, profiles=set(names), proj=SimpleNamespace(rank=len(free)))

    def refit_candidate(model, base, eff, sc, settings, it, judge, held, anchor=None, **other_starts):
        return Refit(eff.name, it, Fit(theta, base.free, 0.999), {}, base_sse, 0.999, 1, len(base.free) + 1, 0.5,
                     0.48, 5.0, False, "F-test not significant", {})

    monkeypatch.setattr(TP, "assess", assess)
    monkeypatch.setattr(TP, "scout_candidate", lambda model, base, points, eff, settings, held: Scout(
        eff.name, rms[eff.name], None, {}))
    monkeypatch.setattr(TP, "refit_candidate", refit_candidate)
    model = SimpleNamespace(n=n, residuals=lambda th: np.random.default_rng(0).standard_normal((1, n)),
                            clock=PhaseClock())
    asked = []

    def second_look(fit):
        asked.append(fit)
        return kinds

    said = []
    st = DiscoverSettings(top_k=3, second_point=False, alpha=1e-12)  # no scout beyond the top 3 is worth a refit
    out = TP._iteration(model, None, Fit(theta, ("J_m",), base_sse), theta, ("J_m",),
                        [EFFECTS_BY_NAME[nm] for nm in names], st, 1, (), said.append, None, second_look)
    assert [rf.name for rf in out["refits"]] == names[:3] + refitted
    assert len(asked) == 1 and out["chosen"] is None  # asked once, of the model the refits were judged against
    assert any("of any shape explains what is left (catch-all): refitting" in s for s in said) is bool(refitted)
    # the dead time is no force nor a reading error: never sent by the catch-all
    assert "dead_time" not in [rf.name for rf in out["refits"]]


def test_a_second_look_refit_starts_from_the_current_model_with_the_effect_fitted_alone(monkeypatch):
    """refit.from_current: the effect's parameters alone polished at the current model, from the scout's
    values and from its grid's best; the lower kept, the scout's search kept with it."""
    from toggle_id.discovery import refit as TP
    from toggle_id.discovery.model import Fit
    from toggle_id.discovery.refit import Scout
    from toggle_id.discovery.settings import DiscoverSettings

    base = Fit(extend(ASSIGNED)[0], ("J_m", "R_s"), 4.0)
    calls = []

    def fake_fit(model, start, free, nfev, step, coarse=True, rounds=1):
        calls.append((start.copy(), tuple(free)))
        return Fit(start, tuple(free), abs(start[ALL_INDEX["c_B"]] - 1193.0))  # lower nearer the truth

    monkeypatch.setattr(TP, "fit_free", fake_fit)
    away = base.theta.copy()
    away[ALL_INDEX["c_B"]], away[ALL_INDEX["J_m"]] = 1.0, 7.0  # the scout's point: another J_m
    sc = Scout("viscous_friction_slider", 9.0, away, {"best_grid": {"c_B": 1000.0}}, 2.0)
    got = TP.from_current(None, base, sc, DiscoverSettings())
    assert [free for _, free in calls] == [("c_B",), ("c_B",)]
    assert [st[ALL_INDEX["c_B"]] for st, _ in calls] == [1.0, 1000.0]
    assert all(st[ALL_INDEX["J_m"]] == base.theta[ALL_INDEX["J_m"]] for st, _ in calls)  # the current model's
    assert got.theta[ALL_INDEX["c_B"]] == 1000.0 and got.sse == 193.0 and got.search["from_current_model"]
    assert got.search["best_grid"] == {"c_B": 1000.0} and got.seconds == 2.0
    none = Scout("viscous_friction_slider", np.inf, None, {}, 0.0)
    assert TP.from_current(None, base, none, DiscoverSettings()) is none  # nothing to start from


def test_score_test_at_the_truth_names_an_offset_and_estimates_it():
    """At the true nominal parameters the residual of an offset is the offset: the score test puts
    sensor_offset far ahead with its first-order magnitude; an effect that is not there (backlash) is not
    significant."""
    rec, truth, _ = make_record({"x_off": 3e-5}, duration=1.0)
    theta = truth.copy()
    theta[ALL_INDEX["x_off"]] = 0.0
    model = D.Model(rec)
    r = model.residuals(theta[None, :])[0]
    proj = D.Projector.of(D.sensitivities(model, theta, PARAM_NAMES))
    scores = D.score_candidates(model, theta, r, proj, EFFECTS)
    assert scores[0].name == "sensor_offset"
    assert scores[0].magnitude_linear == pytest.approx(3e-5, rel=0.05)
    assert scores[0].p_value < 1e-100 and scores[0].score > scores[1].score
    backlash = next(c for c in scores if c.name == "backlash")
    assert backlash.p_value > 0.01
    json.dumps([c.to_dict() for c in scores])


def test_guard_null_refits_the_effect_from_a_better_nominal_optimum_before_dismissing_it(monkeypatch):
    """The guard's re-polish without the effect finds a better nominal optimum that explains the first refit's
    gain; the effect is then refitted once from that optimum (its nominal values, the refit's effect values) and
    judged on the new fit, which wins here."""
    from types import SimpleNamespace

    from toggle_id.discovery import refit as RF
    from toggle_id.discovery.model import Fit
    from toggle_id.discovery.settings import DiscoverSettings

    theta = extend(ASSIGNED)[0]
    base_free = ("mu", "B_m")
    eff = EFFECTS_BY_NAME["coulomb_friction_motor"]
    free = base_free + eff.names
    base = Fit(theta.copy(), base_free, sse=10.0)
    first = Fit(theta.copy(), free, sse=8.0)
    first.theta[ALL_INDEX["tau_c"]] = 0.2
    calls = []

    def fake_fit_free(model, start, names, *a, **k):
        calls.append((tuple(names), start.copy()))
        if tuple(names) == base_free:
            return Fit(start.copy(), base_free, sse=7.0)  # a better nominal optimum than the refit
        out = Fit(start.copy(), tuple(names), sse=5.0)
        out.theta[ALL_INDEX["tau_c"]] = 0.3
        return out

    def pair(small, large):
        ok = large.sse < small.sse - 1.0
        return SimpleNamespace(F=1.0, p_value=0.0 if ok else 1.0, delta_bic=-1.0 if ok else 1.0, passed=ok,
                               reason="ok" if ok else "F-test not significant", to_dict=lambda: {})

    monkeypatch.setattr(RF, "fit_free", fake_fit_free)
    monkeypatch.setattr(RF, "_std_errors", lambda fit, names, n: {})
    rf = RF.Refit(eff.name, 1, first, {"tau_c": 0.2}, 10.0, 8.0, 1, 3, 0.0, 1.0, 0.0, True, "", {})
    model = SimpleNamespace(n=100)
    null = RF.guard_null(model, base, rf, eff, DiscoverSettings(), SimpleNamespace(judge_pair=pair))
    assert null.sse == 7.0
    again = [c for c in calls if c[0] == free]
    assert len(again) == 1
    assert again[0][1][ALL_INDEX["tau_c"]] == 0.2  # the refit's effect value on the better optimum's nominal values
    assert rf.accepted and rf.fit.sse == 5.0 and rf.params == {"tau_c": 0.3} and rf.sse0 == 7.0
    assert rf.search["refitted_from_better_null"]


def test_stronger_magnitudes_step_out_from_the_larger_of_refit_and_grid_within_the_domain():
    from toggle_id.discovery.refit import stronger_magnitudes

    coulomb = EFFECTS_BY_NAME["coulomb_friction_motor"]  # tau_c in [0, 20], off 0
    assert stronger_magnitudes(coulomb, 0.0086, 0.0091, (3, 10)) == pytest.approx([0.0273, 0.091])
    assert stronger_magnitudes(coulomb, 0.0086, 0.0091, (1, 3)) == pytest.approx([0.0091, 0.0273])  # grid's best
    assert stronger_magnitudes(coulomb, 0.0091, 0.0086, (1, 3)) == pytest.approx([0.0273])  # x1: where it stopped
    assert stronger_magnitudes(coulomb, 0.0, 0.01, (3,)) == pytest.approx([0.03])  # refit at off: the grid's side
    assert stronger_magnitudes(coulomb, 0.0, None, (3,)) == []  # nothing to step out from
    assert stronger_magnitudes(coulomb, 1.0, None, (3, 100, 1000)) == pytest.approx([3.0, 19.6])  # capped, once
    load = EFFECTS_BY_NAME["constant_load_force"]  # both signs allowed: the refit's side is kept
    assert stronger_magnitudes(load, -0.92, -8.08, (3,)) == pytest.approx([-24.24])


def test_a_significant_refit_is_repeated_from_stronger_magnitudes_and_the_lowest_sse_is_judged(monkeypatch):
    """A refit dismissed where it stopped (a small magnitude, in a valley) is repeated from 3× and 10× further
    out; the start whose polish ends lowest is converged and judged again, and the report says which it was."""
    from types import SimpleNamespace

    from toggle_id.discovery import refit as RF
    from toggle_id.discovery.model import Fit
    from toggle_id.discovery.settings import DiscoverSettings

    theta, eff, base, scout = refit_case("coulomb_friction_motor", "tau_c", 0.01, 100.0)
    valley = {0.01: 50.0, 0.03: 45.0, 0.1: 20.0, 0.165: 20.0}  # SSE after a polish started at tau_c

    def fake_fit_free(model, start, names, *a, **k):
        tc = round(float(start[ALL_INDEX["tau_c"]]), 6)
        out = Fit(start.copy(), tuple(names), sse=valley.get(tc, 60.0))
        if tc in (0.1, 0.165):
            out.theta[ALL_INDEX["tau_c"]] = 0.165  # the polish from far out reaches the optimum
        return out

    judged = []

    def pair(small, large):  # the valley's refit is dismissed, the optimum's accepted
        judged.append(large.sse)
        ok = large.sse < 30.0
        return SimpleNamespace(F=1.0, p_value=0.0 if ok else 1.0, delta_bic=-1.0, passed=ok,
                               reason="ok" if ok else "no better out of sample", to_dict=lambda: {})

    monkeypatch.setattr(RF, "fit_free", fake_fit_free)
    monkeypatch.setattr(RF, "_std_errors", lambda fit, names, n: {})
    monkeypatch.setattr(RF, "revived", lambda th, free: None)
    model = fake_model(n=1000)
    rf = RF.refit_candidate(model, base, eff, scout, DiscoverSettings(), 1, SimpleNamespace(judge_pair=pair))
    assert [s["start"] for s in rf.search["stronger_starts"]] == pytest.approx([0.03, 0.1])
    assert [s["chosen"] for s in rf.search["stronger_starts"]] == [False, True]
    assert rf.params == {"tau_c": pytest.approx(0.165)} and judged == [50.0, 20.0]  # converged there, judged
    assert rf.accepted and rf.search["before_stronger_start"]["reason"] == "no better out of sample"
    off = RF.refit_candidate(model, base, eff, scout, DiscoverSettings(stronger_starts=()), 1,
                             SimpleNamespace(judge_pair=pair))
    assert "stronger_starts" not in off.search and off.params == {"tau_c": pytest.approx(0.01)}
    assert not off.accepted
    judged.clear()
    valley[0.01] = 25.0  # accepted where it stopped: no stronger start is tried
    kept = RF.refit_candidate(model, base, eff, scout, DiscoverSettings(), 1, SimpleNamespace(judge_pair=pair))
    assert kept.accepted and "stronger_starts" not in kept.search and judged == [25.0]
