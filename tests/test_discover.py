"""The discovery loop: score test, refit, F-test/BIC, on records with a known undeclared effect (or none).

Fast tests run on a shortened record (the free motion, ~0.36 s, and the start of the clamp) with the nominal
fit started from the true nominal parameters perturbed by a few per cent (no GA); the every-effect test on the
5-s record is marked slow.
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
from toggle_id.simulate import PRECISE, extend, simulate

NOISE = 1e-6



def _fake_model(**attrs):
    """A stand-in for :class:`toggle_id.discovery.model.Model` with ``attrs``, whose effects keep to the library's
    feasible domains (no gauge of its own)."""
    from types import SimpleNamespace

    from toggle_id.stages import stage_bounds

    def domain(name):
        lo, hi = stage_bounds([name])
        return float(lo[0]), float(hi[0])

    return SimpleNamespace(domain=domain, gauge_bounds={}, **attrs)

def make_record(effects: dict, duration: float = 1.0, seed: int = 0, pert: float = 0.05, start_pert: float = 0.03,
                noise: float = NOISE) -> tuple[Record, np.ndarray, np.ndarray]:
    """A simulated record with ``effects`` switched on, the other parameters perturbed away from the assigned
    values (log-normal, ``pert``), noise σ = ``noise``; and a nominal start a few per cent off the truth."""
    rng = np.random.default_rng(seed)
    truth = extend(ASSIGNED * np.exp(pert * rng.standard_normal(len(PARAM_NAMES))))[0]
    for k, v in effects.items():
        truth[ALL_INDEX[k]] = v
    rec = Record.from_sweep("simulation", duration, name="test")
    sim = simulate(truth[None, :], rec, PRECISE)
    assert sim.status[0] == 0
    rec.x_B = sim.x_B[0] + noise * rng.standard_normal(rec.n)
    start = truth[:len(PARAM_NAMES)] * np.exp(start_pert * rng.standard_normal(len(PARAM_NAMES)))
    return rec, truth, start


#: Fast-test settings: a few candidates, one effect at most, small budgets.
FAST = dict(top_k=2, max_effects=1, grid_points=8, baseline_nfev=40, refit_nfev=30, null_nfev=20, noise_std=NOISE)
SUBSET = ("constant_load_force", "sensor_offset", "coulomb_friction_motor", "dead_time")


def run(effects: dict, candidates=SUBSET, duration: float = 1.0, **kw) -> tuple[D.DiscoveryResult, np.ndarray]:
    rec, truth, start = make_record(effects, duration)
    settings = D.DiscoverSettings(candidates=candidates, **{**FAST, **kw})
    return D.discover(rec, nominal=start, settings=settings), truth


# ---------------------------------------------------------------------------------------------- pieces
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
                        ({"catch_all": "yes"}, "catch_all"), ({"fd_tier": "loose"}, "fd_tier"),
                        ({"jacobian_reuse": -1}, "jacobian_reuse"), ({"jacobian_reuse": True}, "jacobian_reuse"),
                        ({"stronger_starts": [0.5]}, "stronger_starts"), ({"stronger_starts": 3}, "stronger_starts"),
                        ({"routes": "sometimes"}, "routes"), ({"route_rtol": 1.0}, "route_rtol"),
                        ({"route_max_ratio": 1.0}, "route_max_ratio"), ({"route_max_ratio": "x"}, "route_max_ratio"),
                        ({"glitch_k": -1.0}, "glitch_k"), ({"glitch_k": True}, "glitch_k"),
                        ({"unconverged_share": 1.0}, "unconverged_share"),
                        ({"unconverged_share": "x"}, "unconverged_share"),
                        ({"other_starts_above": 0.5}, "other_starts_above"),
                        ({"other_starts_above": True}, "other_starts_above")]:
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
    model = SimpleNamespace(n=n, residuals=lambda th: np.random.default_rng(0).standard_normal((1, n)))
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


@pytest.mark.parametrize("base_rms_um, reached", [(30.0, True), (30.0, False), (3.0, False)])
def test_far_above_the_noise_the_dismissed_candidates_are_polished_again_from_the_other_starts(
        monkeypatch, base_rms_um, reached):
    """A 3-ms dead time hidden by a bent baseline (its refit there does not move): while nothing supported reaches
    within ``other_starts_above`` times the record's noise, the dismissed candidates whose score is significant are
    polished again from the baseline's other starts, strongest score first, until one ends near the noise; one that
    ends lower replaces its refit and is judged. Within that factor of the noise nothing more is fitted."""
    from types import SimpleNamespace

    from toggle_id.discovery import forward as TP
    from toggle_id.discovery.model import Fit
    from toggle_id.discovery.refit import Refit, Scout
    from toggle_id.discovery.scoring import CandidateScore
    from toggle_id.discovery.settings import DiscoverSettings

    n, noise_m = 1000, 1e-6
    base_sse = (base_rms_um * 1e-6) ** 2 * n
    stat = {"viscous_friction_slider": 211.0, "dead_time": 54.1, "sensor_offset": 27.4, "backlash": 0.5}
    names = list(stat)
    theta = extend(ASSIGNED)[0]

    def assess(model, label, th, free, remaining, settings, noise):
        sc = {nm: CandidateScore(nm, stat[nm], 0.3, {}, None, 1.0, 1.0) for nm in names}
        return SimpleNamespace(label=label, scores=sc, profiles=set(names), proj=SimpleNamespace(rank=len(free)))

    def refit_candidate(model, base, eff, sc, settings, it, judge, held, anchor=None, **other_starts):
        return Refit(eff.name, it, Fit(theta, base.free, base_sse * 0.99), {}, base_sse, base_sse * 0.99, 1,
                     len(base.free) + 1, 0.5, 0.48, 5.0, False, "F-test not significant", {})

    asked = []

    def from_other_starts(model, base, rf, settings, judge, others, noise):
        asked.append(rf.name)
        if rf.name != "dead_time" or not reached:
            return None
        return Refit(rf.name, rf.iteration, Fit(theta, base.free, (0.99e-6) ** 2 * n), {"tau_d": 3e-3}, base_sse,
                     (0.99e-6) ** 2 * n, 1, len(base.free) + 1, 1e4, 0.0, -1e3, True, "ok",
                     {"before_other_starts": {"rmse_m": 30e-6}})

    monkeypatch.setattr(TP, "assess", assess)
    monkeypatch.setattr(TP, "scout_candidate", lambda model, base, points, eff, settings, held: Scout(
        eff.name, base_sse * 0.99, None, {}))
    monkeypatch.setattr(TP, "refit_candidate", refit_candidate)
    monkeypatch.setattr(TP, "from_other_starts", from_other_starts)
    monkeypatch.setattr(TP, "guard_null", lambda *a: None)
    model = SimpleNamespace(n=n, residuals=lambda th: np.random.default_rng(0).standard_normal((1, n)))
    said = []
    st = DiscoverSettings(top_k=4, second_point=False, ambiguity_alpha=0.0)
    out = TP._iteration(model, None, Fit(theta, ("J_m",), base_sse), theta, ("J_m",),
                        [EFFECTS_BY_NAME[nm] for nm in names], st, 1, (), said.append, None,
                        others=[theta.copy()], noise_m=noise_m)
    assert sorted(rf.name for rf in out["refits"]) == sorted(names)
    if base_rms_um < st.other_starts_above:
        assert asked == [] and out["chosen"] is None
    elif reached:  # strongest first; the dead time ends near the noise, so the search stops there
        assert asked == ["viscous_friction_slider", "dead_time"]
        assert out["chosen"].name == "dead_time" and out["chosen"].params == {"tau_d": 3e-3}
        assert any("refit dead_time" in s and "from another start of the baseline" in s for s in said)
    else:  # every significant dismissed candidate tried (the backlash's score is not), none lower
        assert asked == ["viscous_friction_slider", "dead_time", "sensor_offset"] and out["chosen"] is None


def test_a_dismissed_refit_is_polished_from_the_other_starts_at_its_profiles_magnitude_where_it_left_it_off(
        monkeypatch):
    """refit.from_other_starts: a refit left at "off" (τ_d ≈ 0) starts from its profile's best grid magnitude at
    each other start, in order until one ends within NEAR_NOISE times the noise; the lowest is judged when it is
    lower than the refit (its first error kept in the report), None otherwise."""
    from types import SimpleNamespace

    from toggle_id.discovery import refit as RF
    from toggle_id.discovery.model import Fit
    from toggle_id.discovery.noise import WHITE, NoiseModel
    from toggle_id.discovery.refit import Refit
    from toggle_id.discovery.settings import DiscoverSettings

    theta = extend(ASSIGNED)[0]
    base = Fit(theta.copy(), ("mu",), sse=900.0 * 1e-12 * 1000)
    left = _with_value(theta, "tau_d", 1e-9)  # the refit from the bent baseline did not move
    rf = Refit("dead_time", 1, Fit(left, ("mu", "tau_d"), 890e-12 * 1000), {"tau_d": 1e-9}, base.sse,
               890e-12 * 1000, 1, 2, 1.0, 0.3, 5.0, False, "F-test not significant", {"best_grid": {"tau_d": 2e-3}})
    ends = iter([0.9e-6, 1.0e-6])  # RMS of the polishes, in order
    starts = []

    def fake_fit_free(model, start, names, *a, **k):
        starts.append(start.copy())
        return Fit(start.copy(), tuple(names), sse=next(ends) ** 2 * 1000)

    def pair(small, large):
        return SimpleNamespace(F=1e4, p_value=0.0, delta_bic=-1e3, passed=True, reason="ok", to_dict=lambda: {})

    monkeypatch.setattr(RF, "fit_free", fake_fit_free)
    monkeypatch.setattr(RF, "_std_errors", lambda fit, names, n: {})
    model = SimpleNamespace(n=1000, noise=WHITE, domain=lambda nm: (0.0, 0.05))  # the library's τ_d domain
    other = _with_value(theta, "mu", 0.3)
    got = RF.from_other_starts(model, base, rf, DiscoverSettings(), SimpleNamespace(judge_pair=pair),
                               [other, other], 1e-6)
    assert len(starts) == 1  # 0.9 µm is within 1.5 times the noise: the second start is not polished
    assert starts[0][ALL_INDEX["tau_d"]] == 2e-3 and starts[0][ALL_INDEX["mu"]] == 0.3
    assert got.accepted and got.sse1 == pytest.approx(0.81e-12 * 1000) and got.params["tau_d"] == 2e-3
    assert got.search["before_other_starts"]["rmse_m"] == pytest.approx(np.sqrt(890e-12))
    ends = iter([40e-6, 35e-6])  # neither lower than the refit: nothing replaces it
    starts.clear()
    assert RF.from_other_starts(model, base, rf, DiscoverSettings(), SimpleNamespace(judge_pair=pair),
                                [other, other], 1e-6) is None
    assert len(starts) == 2 and [round(p["rmse_m"] * 1e6) for p in rf.search["other_starts"]] == [40, 35]
    # under a coloured noise model (fitted to a residual the missing effect dominates) the search is by least
    # squares, and the lowest is polished once more the prediction-error way under the noise model of its own
    # residual — not the loop's, which whitened the effect away — and the loop's is left in place
    coloured = NoiseModel(a=(0.9,), sigma2_e=1e-12, sigma2=5e-12, n=1000)
    own = NoiseModel(a=(0.2,), sigma2_e=1e-12, sigma2=1.04e-12, n=1000)
    model.noise, seen, starts[:], residuals_of = coloured, [], [], []
    ends = iter([0.9e-6, 0.92e-6])

    def noted(model_, start, names, *a, **k):
        seen.append(model_.noise)
        return fake_fit_free(model_, start, names, *a, **k)

    def own_noise(model_, theta_, settings_):
        residuals_of.append(theta_.copy())
        return own

    monkeypatch.setattr(RF, "fit_free", noted)
    monkeypatch.setattr(RF, "fitting_noise", own_noise)
    got = RF.from_other_starts(model, base, rf, DiscoverSettings(), SimpleNamespace(judge_pair=pair),
                               [other, other], 1e-6)
    assert seen == [WHITE, own] and model.noise is coloured
    assert len(residuals_of) == 1 and np.array_equal(residuals_of[0], starts[0])  # the least-squares fit's residual
    assert got.sse1 == pytest.approx(0.92e-6 ** 2 * 1000)
    assert got.search["other_starts"][-1]["under"] == own.describe()
    # fitted under different noise models, the find and the refit compare by their raw errors: a whitened SSE under
    # its own model above the refit's (under the loop's) is no reason to drop a raw error of a third of it
    rf.fit = Fit(left, ("mu", "tau_d"), (2.5e-6) ** 2 * 1000, raw_sse=(6e-6) ** 2 * 1000, noise=coloured)

    def own_fit(model_, start, names, *a, **k):
        seen.append(model_.noise)
        return Fit(start.copy(), tuple(names), sse=(3e-6) ** 2 * 1000, raw_sse=(2e-6) ** 2 * 1000,
                   noise=model_.noise)

    monkeypatch.setattr(RF, "fit_free", own_fit)
    got = RF.from_other_starts(model, base, rf, DiscoverSettings(), SimpleNamespace(judge_pair=pair),
                               [other], 1e-6)
    assert got is not None and got.fit.noise is own and got.fit.rmse(1000) == pytest.approx(2e-6)


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


# ---------------------------------------------------------------------------------------------- the loop
def test_no_effect_no_false_positive():
    res, _ = run({}, candidates=None, max_effects=2)
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


#: Each case costs 20-45 s of simulations. By default: dead time, where a candidate its score test ranks above it is
#: refitted and rejected (the whole loop: ranking, refits, verdicts, magnitude, white residual after). The others
#: are slow: the loop naming an offset is the discover job's end-to-end test below (the same 1-s record), and every
#: effect, these included, is named on the 5-s record by the slow every-effect test.
@pytest.mark.parametrize("name,effects,magnitude", [
    pytest.param("sensor_offset", {"x_off": 1e-4}, ("x_off", 1e-4), marks=pytest.mark.slow),
    pytest.param("constant_load_force", {"F_load": 500.0}, ("F_load", 500.0), marks=pytest.mark.slow),
    ("dead_time", {"tau_d": 2e-3}, ("tau_d", 2e-3)),
    pytest.param("coulomb_friction_motor", {"tau_c": 3.0}, ("tau_c", 3.0), marks=pytest.mark.slow),
])
def test_loop_names_the_undeclared_effect(name, effects, magnitude):
    res, _ = run(effects)
    assert res.rmse_before_m > 2.0 * NOISE, "the nominal model absorbed the effect: not a test"
    assert [a["name"] for a in res.effects_added] == [name]
    assert res.iterations[0]["accepted"] == name
    verdicts = {c["name"]: c["verdict"] for c in res.candidates}
    assert verdicts[name] == "accepted" and set(verdicts.values()) <= {"accepted", "compensating", "rejected"}
    # a candidate its scout ranks above it was refitted, never skipped; in the default case the Coulomb torque's
    # score test ranks above the dead time (its scout below): refitted too, while nothing was accepted, and rejected
    mine = next(c for c in res.candidates if c["name"] == name)
    assert all(c["refitted"] for c in res.candidates if c["scout_rmse_m"] < mine["scout_rmse_m"])
    louder = [c for c in res.candidates if c["score"] > mine["score"]]
    assert all(c["verdict"] != "accepted" for c in louder)
    if name == "dead_time":
        assert [c["name"] for c in louder] == ["coulomb_friction_motor"] and louder[0]["refitted"]
    key, true_value = magnitude
    est = res.effects_added[0]["params"][key]
    assert est == pytest.approx(true_value, rel=0.25)
    assert res.rmse_after_m < 1.05 * NOISE
    assert res.diagnostics_before["verdict"]["structure_left"] and not res.diagnostics_after["verdict"]["structure_left"]



def test_loop_names_backlash():
    """The lash opens at every reversal of the flank force: a second degree of freedom the rigid model lacks."""
    res, _ = run({"b_l": 5e-4}, candidates=(*SUBSET, "backlash"))
    assert res.rmse_before_m > 20.0 * NOISE
    assert [a["name"] for a in res.effects_added] == ["backlash"]
    assert res.effects_added[0]["params"]["b_l"] == pytest.approx(5e-4, rel=0.05)
    assert res.rmse_after_m < 1.05 * NOISE


def test_an_effect_polished_to_the_edge_of_its_domain_is_polished_again_from_weaker_starts(monkeypatch):
    """forward._polish_with_effect: a magnitude at the edge of its feasible domain (a lash run out to its bound by a
    stronger start) is polished again from the nominal fit as given with the magnitude at each weaker_starts share;
    the lowest error is kept. Inside its domain, nothing more is tried."""
    from types import SimpleNamespace

    from toggle_id.discovery import forward as FW
    from toggle_id.discovery.model import Fit

    theta = extend(ASSIGNED)[0]
    anchor = theta * 1.01
    free = ("J_m",)
    assert FW.at_bound(EFFECTS_BY_NAME["backlash"], 1.96e-3) and not FW.at_bound(EFFECTS_BY_NAME["backlash"], 5e-4)
    offset = EFFECTS_BY_NAME["sensor_offset"]  # two-sided: the bound on the value's own side
    assert FW.at_bound(offset, 0.99 * offset.magnitude.lower) and not FW.at_bound(offset, 0.5 * offset.magnitude.lower)

    def run(b_l: float) -> tuple[list, Fit]:
        starts = []

        def fake_fit(model, th, fr, *a, **k):
            starts.append(th.copy())
            b = th[ALL_INDEX["b_l"]]
            return Fit(th.copy(), fr, 1.0 + abs(b - 5e-4) * 1e3)  # the error is least at the true lash

        monkeypatch.setattr(FW, "fit_free", fake_fit)
        th = theta.copy()
        th[ALL_INDEX["b_l"]] = b_l
        chosen = SimpleNamespace(name="backlash", fit=Fit(th, (*free, "b_l"), 2.0))
        out = FW._polish_with_effect(_fake_model(n=100), chosen, anchor, free, D.DiscoverSettings(),
                                     lambda m: None)
        return starts, out

    starts, out = run(1.96e-3)
    assert len(starts) == 4  # the refit, the nominal fit as given, and the two weaker starts from it
    assert [s[ALL_INDEX["b_l"]] for s in starts[2:]] == pytest.approx([1.96e-3 / 3, 1.96e-4])
    assert all(np.allclose(s[ALL_INDEX["J_m"]], anchor[ALL_INDEX["J_m"]]) for s in starts[1:])
    assert out.theta[ALL_INDEX["b_l"]] == pytest.approx(1.96e-3 / 3)  # the lowest error
    starts, out = run(6e-4)
    assert len(starts) == 2 and out.theta[ALL_INDEX["b_l"]] == pytest.approx(6e-4)
    with pytest.raises(ConfigError, match="weaker_starts"):
        D.DiscoverSettings(weaker_starts=(2.0,)).validate()


def test_a_second_start_that_moves_the_effect_is_started_again_at_the_values_reached(monkeypatch):
    """forward._polish_with_effect: when the polish from the nominal fit as given wins but moves the effect's
    magnitude by more than reanchor_rtol, the nominal fit as given is polished once more at the magnitude reached
    (the nominal parameters bent on the way and stalled: the default suite's backlash case on an AMD machine)."""
    from types import SimpleNamespace

    from toggle_id.discovery import forward as FW
    from toggle_id.discovery.model import Fit

    a, b = np.zeros(len(ALL_INDEX)), np.zeros(len(ALL_INDEX))
    a[ALL_INDEX["b_l"]], b[ALL_INDEX["b_l"]] = 3.26e-4, 5.1e-4
    assert FW.moved_effects(a, b, ["b_l"], 0.1) == ["b_l"] and FW.moved_effects(a, b, ["b_l"], 0.5) == []
    assert FW.moved_effects(a, b, ["b_l"], 0.0) == [] and FW.moved_effects(a, a, ["b_l"], 0.1) == []
    theta = extend(ASSIGNED)[0]
    anchor = theta * 1.01
    free = ("J_m",)

    def run(rtol: float) -> tuple[list, Fit]:
        starts = []

        def fake_fit(model, th, fr, *a, **k):
            starts.append(th.copy())
            out = th.copy()
            if not np.isclose(th[ALL_INDEX["J_m"]], anchor[ALL_INDEX["J_m"]]):
                return Fit(out, fr, 50.0)  # the refit's valley
            if abs(th[ALL_INDEX["b_l"]] - 5.1e-4) < 1e-6:
                return Fit(out, fr, 0.97)  # the nominal fit as given at the right lash: the floor
            out[ALL_INDEX["b_l"]] = 5.1e-4
            out[ALL_INDEX["J_m"]] *= 1.5  # the nominal parameters bend on the way, and stall there
            return Fit(out, fr, 9.3)

        monkeypatch.setattr(FW, "fit_free", fake_fit)
        th = theta.copy()
        th[ALL_INDEX["b_l"]] = 3.26e-4
        chosen = SimpleNamespace(name="backlash", fit=Fit(th, (*free, "b_l"), 60.0))
        out = FW._polish_with_effect(_fake_model(n=100), chosen, anchor, free,
                                     D.DiscoverSettings(reanchor_rtol=rtol), lambda m: None)
        return starts, out

    starts, out = run(0.1)
    assert len(starts) == 3 and out.sse == 0.97 and out.theta[ALL_INDEX["b_l"]] == 5.1e-4
    assert starts[2][ALL_INDEX["J_m"]] == anchor[ALL_INDEX["J_m"]] and starts[2][ALL_INDEX["b_l"]] == 5.1e-4
    starts, out = run(0.0)  # off: the stalled fit is kept
    assert len(starts) == 2 and out.sse == 9.3
    with pytest.raises(ConfigError, match="reanchor_rtol"):
        D.DiscoverSettings(reanchor_rtol="x").validate()


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


def test_the_gauge_moves_effects_along_the_symmetries_without_changing_x_B():
    """gauge_fix scales force-type effects with the mechanism and the drive limit (1/V) and the torque saturation
    (c_kt, 1/A²: as c²) with the current scale; with all three on, the representative nearest the reference has
    the same x_B (else gauge_fix would refuse it), and c_kt·K_i² is unchanged."""
    from toggle_id.discovery.gauge import gauge_fix

    theta = extend(ASSIGNED * np.exp(0.2 * np.random.default_rng(4).standard_normal(len(PARAM_NAMES))))[0]
    theta[ALL_INDEX["c_kt"]], theta[ALL_INDEX["tau_c"]], theta[ALL_INDEX["s_sat"]] = 4e-6, 0.5, 0.01
    rec = Record.from_sweep("simulation", 5.0, name="gauge")
    rec.x_B = np.zeros(rec.n)  # outputs only; never fitted
    model = D.Model(rec, PRECISE)
    off = theta.copy()
    off[ALL_INDEX["c_kt"]] = 0.0
    y = model.outputs(np.array([theta, off]))
    assert np.max(np.abs(y[0] - y[1])) > 1e-6  # the saturation acts on this record
    ref = extend(ASSIGNED)[0]
    moved, info = gauge_fix(model, theta, PARAM_NAMES, ref)
    assert info["applied"], info
    assert abs(np.log(info["current_scale"])) > 0.01
    t = ALL_INDEX["tau_c"]
    assert moved[t] == pytest.approx(theta[t] * info["mechanical_scale"], rel=1e-12)
    ki, c = ALL_INDEX["K_i"], ALL_INDEX["c_kt"]
    assert moved[c] * moved[ki] ** 2 == pytest.approx(theta[c] * theta[ki] ** 2, rel=1e-12)
    assert moved[c] != pytest.approx(theta[c], rel=1e-3)


def test_broyden_update_meets_the_secant_condition_and_changes_the_jacobian_least_in_scaled_coordinates():
    """discover.jacobian_reuse's update (model.broyden), against its definition: the updated Jacobian maps the step
    onto the residual's change; it differs from the old one by a rank-one term whose row space is the scaled step,
    so a direction orthogonal to the step (scaled) is mapped as before; on a linear residual started from the true
    Jacobian it stays exact; a zero step gives None."""
    from toggle_id.discovery.model import broyden

    rng = np.random.default_rng(3)
    m, k = 40, 5
    scale = np.array([1e-3, 1.0, 50.0, 2e4, 0.2])
    A = rng.standard_normal((m, k)) / scale[None, :]
    J0 = A + 0.3 * rng.standard_normal((m, k)) / scale[None, :]
    x0 = scale * rng.uniform(0.5, 2.0, k)
    x1 = x0 + scale * 0.1 * rng.standard_normal(k)
    r0, r1 = A @ x0, A @ x1
    J1 = broyden(J0, x0, r0, x1, r1, scale)
    assert np.allclose(J1 @ (x1 - x0), r1 - r0, rtol=1e-10, atol=1e-12 * np.abs(r1 - r0).max())
    dz = (x1 - x0) / scale
    assert np.linalg.matrix_rank((J1 - J0) * scale[None, :], tol=1e-9 * np.abs(J1 * scale).max()) == 1
    w = rng.standard_normal(k)
    w -= (w @ dz) / (dz @ dz) * dz  # orthogonal to the scaled step
    assert np.allclose((J1 * scale) @ w, (J0 * scale) @ w)
    assert np.allclose(broyden(A, x0, r0, x1, r1, scale), A)
    assert broyden(J0, x0, r0, x0.copy(), r0, scale) is None


# ---------------------------------------------------------------------------------------------- the job
@pytest.mark.integration
def test_discover_job_end_to_end(tmp_path, job_env):
    from conftest import run_job

    proc = run_job("jobs.run", "+experiment=discover", f"hydra.run.dir={tmp_path / 'run'}", "evaluator=serial",
                   "data.duration=1.0", "data.effects.x_off=5e-5", "discover.nominal=base", "discover.max_effects=1",
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
    assert len(parent) == 1 and parent[0].info.run_name.startswith("discover evaluator=serial data.duration=1.0 ")
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
def test_discover_benchmark_runs_the_job_and_prints_the_median(tmp_path, capsys):
    """The benchmark's command line, in this process (the job it times is the one the test above runs as a user
    would): one run, its line and the median printed, the rows written."""
    from jobs.bench_discover import main

    main(["--json", str(tmp_path / "bench.json"), "evaluator=serial", "data.duration=0.5", "data.effects.tau_c=0.0",
          "data.effects.x_off=5e-5", "discover.nominal=base", "discover.max_effects=1",
          "discover.candidates=[sensor_offset]"])
    out = capsys.readouterr().out
    assert "run 0:" in out and "median wall" in out
    rows = json.loads((tmp_path / "bench.json").read_text())
    assert len(rows) == 1 and rows[0]["effects_added"] == ["sensor_offset"] and rows[0]["wall_s"] > 0
    assert rows[0]["rmse_after_um"] < 1.1 and rows[0]["rmse_before_um"] > 5.0


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


def test_model_sends_an_effect_set_whose_rows_fell_back_straight_to_the_fallback():
    """Once most rows of a batch with some effects on exhausted the primary's budget, the Model integrates that
    effect set with the fallback directly (same values), and other effect sets still with the primary."""
    from dataclasses import replace

    from toggle_id.discovery.model import Model, effects_on
    from toggle_id.simulate import FAST

    rec = Record.from_sweep("simulation", duration=0.5)
    theta = extend(ASSIGNED)[0]
    x = simulate(theta[None], rec, PRECISE).x_B[0]
    rec = Record(rec.t, rec.v_in, x, sweep=rec.sweep, x_B0=rec.x_B0, name="fallback")
    tight = replace(PRECISE, max_steps=300, fallback=FAST)
    model = Model(rec, tight, parallel=False)
    on = theta.copy()
    on[ALL_INDEX["tau_c"]] = 1.0
    first = model.outputs(np.repeat(on[None], 2, axis=0))
    assert model.stiff == {effects_on(on)}
    again = model.outputs(on[None])
    np.testing.assert_array_equal(again[0], first[0])
    np.testing.assert_array_equal(again[0], simulate(on[None], rec, FAST).x_B[0])
    assert effects_on(theta) != effects_on(on)


def test_model_serves_a_batch_asked_for_again_from_its_cache_bit_for_bit(monkeypatch):
    """The same rows on the same settings are simulated once (values identical to a fresh simulation, n_sims counting
    the simulations run); other settings or other rows are simulated; the cache keeps to its byte budget."""
    import toggle_id.discovery.model as M
    from toggle_id.simulate import FAST

    rec = Record.from_sweep("simulation", duration=0.2)
    theta = extend(ASSIGNED)[0]
    rec = Record(rec.t, rec.v_in, simulate(theta[None], rec, PRECISE).x_B[0], sweep=rec.sweep, x_B0=rec.x_B0,
                 name="cache")
    T = np.repeat(theta[None], 3, axis=0)
    T[1, ALL_INDEX["K_t"]] *= 1.01
    T[2, ALL_INDEX["B_m"]] *= 1.02
    model = M.Model(rec, parallel=False)
    first = model.residuals(T)
    again = model.residuals(T)
    assert (model.n_sims, model.n_cached) == (3, 3)
    np.testing.assert_array_equal(again, first)
    np.testing.assert_array_equal(first, rec.x_B[None, :] - simulate(T, rec, PRECISE).x_B)
    model.residuals(T, FAST)  # other settings: simulated
    model.residuals(T[:2])  # another batch: simulated
    assert (model.n_sims, model.n_cached) == (8, 3)
    np.testing.assert_array_equal(model.residuals(T[:2]), first[:2])
    assert model.n_cached == 5
    # a budget of one batch of three rows: the older batches are dropped, the newest kept
    monkeypatch.setattr(M, "CACHE_BYTES", 3 * rec.n * 8)
    small = M.Model(rec, parallel=False)
    small.residuals(T)
    small.residuals(T[:1])
    assert small._cache_bytes <= M.CACHE_BYTES and len(small._cache) == 1
    small.residuals(T)
    assert (small.n_sims, small.n_cached) == (7, 0)


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

    theta, eff, base, scout = _refit_case("coulomb_friction_motor", "tau_c", 0.01, 100.0)
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
    model = _fake_model(n=1000)
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


def _coloured_judge(monkeypatch, fake_fit_free):
    """A Judge whose fits are ``fake_fit_free`` under a coloured noise model; the fits it would compare are
    collected in the list returned beside it."""
    from types import SimpleNamespace

    from toggle_id.discovery import validation as V
    from toggle_id.discovery.settings import DiscoverSettings

    monkeypatch.setattr(V, "fit_free", fake_fit_free)
    monkeypatch.setattr(V, "fit_noise", lambda r, order: SimpleNamespace(white=False))
    judge = V.Judge(SimpleNamespace(noise="white", settings=None, parallel=False, n=5000), DiscoverSettings())
    monkeypatch.setattr(judge, "residual_and_jacobian", lambda fit: (np.zeros(5), None))
    seen = []
    monkeypatch.setattr(judge, "evidence", lambda s, lg, noise: seen.append((s, lg)) or SimpleNamespace(checks={}))
    return judge, seen


def test_a_coloured_comparison_refits_the_larger_model_also_from_the_smaller_models_whitened_fit(monkeypatch):
    """Under a coloured noise model both fits are refitted whitened; the larger one also from the smaller one's
    whitened fit with everything else as in the larger (nested), and the lower of its two refits is judged: from its
    own least-squares point alone it ends above the smaller model here (F < 0)."""
    from types import SimpleNamespace

    from toggle_id.discovery import validation as V
    from toggle_id.discovery.model import Fit

    theta = extend(ASSIGNED)[0]
    small = Fit(theta.copy(), ("mu",), sse=10.0)
    large = Fit(theta.copy(), ("mu", "tau_c"), sse=8.0)
    large.theta[ALL_INDEX["tau_c"]], large.theta[ALL_INDEX["mu"]] = 0.2, 0.5
    large.theta[ALL_INDEX["gs_lo"]] = 0.02  # fixed, not free: shapes the larger model (a generic term's knot)

    def fake_fit_free(model, start, names, *a, **k):
        names = tuple(names)
        out = Fit(start.copy(), names, sse=9.0)
        if names == ("mu",):
            out.theta[ALL_INDEX["mu"]] = 0.3  # the smaller model's whitened optimum
        else:  # the larger one: from its least-squares point 9.5, from the nested start 7.0
            out.sse = 7.0 if start[ALL_INDEX["mu"]] == 0.3 else 9.5
        return out

    judge, seen = _coloured_judge(monkeypatch, fake_fit_free)
    judge.judge_pair(small, large)
    small_w, large_w = seen[0]
    assert small_w.sse == 9.0 and large_w.sse == 7.0
    assert large_w.theta[ALL_INDEX["mu"]] == 0.3 and large_w.theta[ALL_INDEX["tau_c"]] == 0.2
    assert large_w.theta[ALL_INDEX["gs_lo"]] == 0.02  # the nested start keeps what shapes the larger model
    assert judge.model.noise == "white"  # the model's own noise model is restored
    seen.clear()
    monkeypatch.setattr(V, "fit_noise", lambda r, order: SimpleNamespace(white=True))
    # white: the least-squares fits are compared as they are, and their gain is the judge's own F-test
    assert judge.judge_pair(small, large).checks == {}
    assert seen[0] == (small, large)
    # prediction-error fits (under the loop's coloured noise model) compared as they are: their own gain must show
    ar = SimpleNamespace(a=(0.9,), white=False)
    pem_small = Fit(small.theta, small.free, 10.0, raw_sse=10.0, noise=ar)
    assert judge.judge_pair(pem_small, Fit(large.theta, large.free, 9.99, raw_sse=8.0, noise=ar)).checks == {
        "reported_fits": False}
    assert judge.judge_pair(pem_small, Fit(large.theta, large.free, 8.0, raw_sse=9.99, noise=ar)).checks == {
        "reported_fits": True}


def test_a_coloured_comparison_refits_the_smaller_model_also_from_the_larger_models_valley(monkeypatch):
    """rec33: a refit whose effect went to nothing (c_B ≈ 1 N·s/m) while its nominal parameters moved to another
    valley passed at F 126. The smaller model is refitted whitened also from the larger one's whitened fit with the
    new parameters as the smaller has them: the valley is then the smaller model's too."""

    from toggle_id.discovery.model import Fit

    theta = extend(ASSIGNED)[0]
    small = Fit(theta.copy(), ("mu",), sse=10.0)
    large = Fit(theta.copy(), ("mu", "c_B"), sse=10.5)
    large.theta[ALL_INDEX["c_B"]], large.theta[ALL_INDEX["mu"]] = 1.0, 0.9  # another valley of mu

    def fake_fit_free(model, start, names, *a, **k):
        # the whitened SSE is lower in the valley mu ≈ 0.9, whatever c_B
        return Fit(start.copy(), tuple(names), sse=6.0 if start[ALL_INDEX["mu"]] == 0.9 else 9.0)

    judge, seen = _coloured_judge(monkeypatch, fake_fit_free)
    judge.judge_pair(small, large)
    small_w, large_w = seen[0]
    assert small_w.sse == 6.0 and large_w.sse == 6.0  # no gain left to the effect
    assert small_w.free == ("mu",) and small_w.theta[ALL_INDEX["c_B"]] == theta[ALL_INDEX["c_B"]]  # its own c_B
    assert small_w.theta[ALL_INDEX["mu"]] == 0.9
    # its least-squares fit above the smaller model's: whatever the whitened refits say, not the model reported
    assert judge.judge_pair(small, large).checks == {"reported_fits": False}
    assert judge.judge_pair(small, Fit(large.theta, large.free, 9.0)).checks == {"reported_fits": True}
    # and such a refit is not listed as lowering the error (compensating) either
    from toggle_id.discovery.refit import Refit
    rf = Refit("viscous_friction_slider", 1, large, {}, 10.0, 10.5, 1, 2, 84.8, 1e-20, -75.0, False, "", {},
               evidence={"checks": {"f_test": True, "robust_f_test": True, "bic": True, "reported_fits": False}})
    assert not rf.lowers_error
    rf.evidence["checks"]["reported_fits"] = True
    assert rf.lowers_error


def test_the_reported_fits_check_compares_the_loops_fits_as_they_were_minimised():
    """Both fits under one noise model (prediction-error fitting): their whitened SSEs; else the raw ones."""
    from types import SimpleNamespace

    from toggle_id.discovery.model import Fit
    from toggle_id.discovery.validation import loop_sse

    ar = SimpleNamespace(a=(0.9,))
    theta = extend(ASSIGNED)[0]
    small = Fit(theta, ("mu",), 2.0, raw_sse=10.0, noise=ar)
    large = Fit(theta, ("mu", "c_B"), 1.0, raw_sse=10.5, noise=ar)
    assert loop_sse(small, large) == (2.0, 1.0)
    large.noise = SimpleNamespace(a=(0.8,))
    assert loop_sse(small, large) == (10.0, 10.5)


@pytest.mark.parametrize("pem, white", [(True, False), (False, False), (True, True)])
def test_prediction_error_fitting_refits_under_the_noise_model_of_the_current_residual(monkeypatch, pem, white):
    """discover.prediction_error: the baseline is polished again under the noise model of its residual less its
    structure (residual.fitting_noise), and so is each model with an accepted effect; every fit of the plant then
    minimises under it. Off: least squares throughout; a white noise model: the least-squares fit is kept."""
    from types import SimpleNamespace

    from toggle_id.discovery import toggle_plant as TP
    from toggle_id.discovery.model import Fit
    from toggle_id.discovery.noise import WHITE, NoiseModel
    from toggle_id.discovery.settings import DiscoverSettings

    theta = extend(ASSIGNED)[0]
    ar = [NoiseModel(a=(0.9,), sigma2_e=0.19e-12, sigma2=1e-12, n=100),
          NoiseModel(a=(0.85,), sigma2_e=0.3e-12, sigma2=1e-12, n=100)]
    estimates = iter([WHITE] * 2 if white else ar)
    monkeypatch.setattr(TP, "fitting_noise", lambda model, th, s: next(estimates))
    monkeypatch.setattr(TP, "fit_noise", lambda r, order: WHITE)
    monkeypatch.setattr(TP, "_baseline", lambda model, th, others, free, s, say: (
        Fit(th, tuple(free), 5.0, noise=WHITE), th))
    model = SimpleNamespace(n=100, noise=WHITE, residuals=lambda th: np.zeros((1, 100)))
    polished = []

    def fake_fit_free(m, start, free, *a, **k):
        polished.append(m.noise)
        return Fit(start, tuple(free), 4.0, noise=m.noise)

    monkeypatch.setattr(TP, "fit_free", fake_fit_free)
    monkeypatch.setattr(TP, "_polish_with_effect", lambda m, chosen, *a: Fit(theta, ("mu", "x_off"), 3.0,
                                                                              noise=m.noise))
    noises, chosen = [], [None, SimpleNamespace(name="sensor_offset", F=50.0, p_value=1e-9, delta_bic=-40.0,
                                                params={}, evidence={}, fit=Fit(theta, ("mu", "x_off"), 3.0))]

    def iteration(m, *a, **k):
        noises.append(m.noise)
        return {"refits": [], "scores": [], "base": a[1], "better_null": None, "record": {}, "chosen": chosen.pop(0),
                "rivals": []}

    monkeypatch.setattr(TP, "_iteration", iteration)
    plant = TP.TogglePlant(model, SimpleNamespace(glitches=[]), DiscoverSettings(prediction_error=pem, glitch_k=0.0),
                           theta, [], ("mu",), (), [], None, lambda s: None, None)
    base = plant.baseline()
    refit = pem and not white
    assert (base.sse, polished) == ((4.0, [ar[0]]) if refit else (5.0, []))
    assert plant.forward_step(base, [], 1).chosen is None  # nothing added: the model and its noise model kept
    step = plant.forward_step(base, [], 2)  # an effect added: its model refitted under its residual's noise model
    assert step.after.noise == (ar[1] if refit else WHITE) and step.after.sse == (4.0 if refit else 3.0)
    assert noises == ([ar[0], ar[0]] if refit else [WHITE, WHITE])
    assert polished == ([ar[0], ar[1]] if refit else [])
    model.noise = "changed by a judge"
    plant.without(base, None, [])  # every fit of the plant under its noise model
    assert polished[-1] == (ar[1] if refit else WHITE)


def test_the_step_chooses_by_raw_errors_among_refits_fitted_under_different_noise_models():
    """forward.lowest_of: the lowest SSE as minimised when every supported refit shares a noise model; by the raw
    error when they do not (whitened SSEs under different models do not compare)."""
    from types import SimpleNamespace

    from toggle_id.discovery.forward import lowest_of
    from toggle_id.discovery.model import Fit
    from toggle_id.discovery.noise import NoiseModel

    theta = extend(ASSIGNED)[0]
    loops, own = NoiseModel(a=(0.9,), sigma2_e=1e-12, sigma2=5e-12, n=100), NoiseModel(a=(0.2,), n=100)

    def refit(name, sse_w, rms, noise):
        return SimpleNamespace(name=name, sse1=sse_w, fit=Fit(theta, ("mu",), sse_w, raw_sse=rms ** 2 * 100,
                                                                noise=noise))

    offset, found = refit("sensor_offset", 1.0e-9, 6.7e-6, loops), refit("dead_time", 1.2e-9, 2.6e-6, loops)
    assert lowest_of([offset, found], 100) is offset and lowest_of([], 100) is None
    found.fit.noise = own
    assert lowest_of([offset, found], 100) is found


def test_an_effect_found_under_its_own_noise_model_is_polished_under_it(monkeypatch):
    """An accepted refit fitted under another noise model than the loop's (refit.from_other_starts: the noise model
    of its own residual) is polished with its effect under that one, which the loop's fits use from then on; under
    the loop's, fitted to a residual the effect dominated, the polish could whiten the effect away again."""
    from types import SimpleNamespace

    from toggle_id.discovery import toggle_plant as TP
    from toggle_id.discovery.model import Fit
    from toggle_id.discovery.noise import NoiseModel
    from toggle_id.discovery.settings import DiscoverSettings

    theta = extend(ASSIGNED)[0]
    loops, own, after = (NoiseModel(a=(a,), sigma2_e=1e-12, sigma2=2e-12, n=100) for a in (0.95, 0.3, 0.2))
    estimates = iter([after])
    monkeypatch.setattr(TP, "fitting_noise", lambda model, th, s: next(estimates))
    monkeypatch.setattr(TP, "fit_free", lambda m, start, free, *a, **k: Fit(start, tuple(free), 2.0, noise=m.noise))
    under = []

    def polish_with_effect(m, chosen, *a):
        under.append(m.noise)
        return Fit(theta, ("mu", "tau_d"), 3.0, noise=m.noise)

    monkeypatch.setattr(TP, "_polish_with_effect", polish_with_effect)
    found = SimpleNamespace(name="dead_time", F=50.0, p_value=1e-9, delta_bic=-40.0, params={}, evidence={},
                            fit=Fit(theta, ("mu", "tau_d"), 3.0, noise=own))
    monkeypatch.setattr(TP, "_iteration", lambda m, *a, **k: {
        "refits": [], "scores": [], "base": a[1], "better_null": None, "record": {}, "chosen": found, "rivals": []})
    model = SimpleNamespace(n=100, noise=loops)
    plant = TP.TogglePlant(model, SimpleNamespace(glitches=[]), DiscoverSettings(glitch_k=0.0), theta, [], ("mu",),
                           (), [], None, lambda s: None, None)
    plant.fit_noise = loops
    step = plant.forward_step(Fit(theta, ("mu",), 4.0, noise=loops), [], 1)
    assert under == [own]  # not the loop's
    assert step.after.noise is after and plant.fit_noise is after  # then its residual's, as after every effect
    found.fit.noise = loops  # fitted under the loop's own: polished under it, as before
    estimates = iter([after])
    plant.fit_noise = model.noise = loops
    plant.forward_step(Fit(theta, ("mu",), 4.0, noise=loops), [], 2)
    assert under == [own, loops]


def test_the_fitting_noise_model_leaves_out_what_the_states_express():
    """A smooth error of the states (a missing friction's) on white noise: the AR model of the whole residual takes it
    for slow noise; with what functions of the states express taken out first, the noise is white again."""
    from toggle_id.discovery.localise import structure_removed
    from toggle_id.discovery.noise import fit_noise

    rng = np.random.default_rng(4)
    t = np.linspace(0.0, 1.0, 2000)
    x = np.sin(2 * np.pi * 1.5 * t)
    v = np.gradient(x, t)
    r = 5.0 * np.tanh(v / 2.0) + rng.standard_normal(t.size)  # a Coulomb-like error of 5 σ, white noise of 1
    signals = {"x_B": x, "xdot_B": v, "v_in": np.cos(2 * np.pi * 1.5 * t), "t": t}
    assert fit_noise(r, 8).effective_fraction < 0.2
    left = structure_removed(r, signals, bins=12, lags=50, lag_step=5)
    assert fit_noise(left, 8).white and np.std(left) == pytest.approx(1.0, rel=0.1)


def test_the_judge_wants_a_significant_out_of_sample_gain():
    """``discover.cv_alpha``: the cross-validation check of the judge is the test of the held-out error's
    drop against the noise's spread of it (:func:`toggle_id.discovery.stats.out_of_sample`) at that level; at 0.5 it is the old sign rule. Residuals
    and sensitivities are given to the judge's cache, so nothing is simulated."""
    from types import SimpleNamespace

    from toggle_id.discovery.model import Fit
    from toggle_id.discovery.noise import NoiseModel
    from toggle_id.discovery.validation import Judge

    n = 5001
    e = np.random.default_rng(3).standard_normal(n) * 1e-6
    small = Fit(np.zeros(3), ("J_m",), 0.0)
    large = Fit(np.ones(3), ("J_m", "tau_c"), 0.0)
    J0, J1 = np.zeros((n, 1)), np.zeros((n, 2))  # no parameter moves: the held-out errors are the residuals
    wave = np.sin(np.linspace(0, 40, n))
    wave -= (wave @ e) / (e @ e) * e  # orthogonal to the noise: the gain is exactly |a·wave|²
    for amp, strict, sign in ((3e-8, False, True), (3e-7, True, True)):  # 0.05 % and 4.5 % of the error
        r0 = e + amp * wave
        verdicts = []
        for level in (0.05, 0.5):
            judge = Judge(SimpleNamespace(noise=NoiseModel(), n=n), D.DiscoverSettings(cv_alpha=level).validate())
            judge._cache[judge._key(small)] = (r0, J0)
            judge._cache[judge._key(large)] = (e, J1)
            ev = judge.evidence(small, large, NoiseModel())
            assert ev.cv1 < ev.cv0 and ev.to_dict()["cv_p_value"] == ev.cv_p
            verdicts.append(ev.checks["cross_validation"])
        assert verdicts == [strict, sign]
    for bad in (0.0, 0.6, True, "x"):
        with pytest.raises(ConfigError, match="discover.cv_alpha"):
            D.DiscoverSettings(cv_alpha=bad).validate()


def test_a_forward_step_judges_its_best_candidate_at_alpha_over_their_number():
    """``discover.bonferroni``: the forward step picks the best of the m candidates it has left, so the judge's
    F-tests are at alpha / m (:attr:`~toggle_id.discovery.validation.Judge.level`). rec12 (backlash, cycling, the
    fast nominal fit): a Coulomb friction on top at p 5.2e-4, the best of nine, passed alpha = 1e-3."""
    from types import SimpleNamespace

    from toggle_id.discovery.model import Fit
    from toggle_id.discovery.noise import NoiseModel
    from toggle_id.discovery.validation import Judge

    n = 5001
    rng = np.random.default_rng(8)
    e = rng.standard_normal(n) * 1e-6
    small = Fit(np.zeros(3), ("J_m",), 0.0)
    large = Fit(np.ones(3), ("J_m", "tau_c"), 0.0)
    wave = np.sin(np.linspace(0, 40, n))
    wave -= (wave @ e) / (e @ e) * e
    r0 = e + np.sqrt(13.0 / (wave @ wave)) * 1e-6 * wave  # in-sample gain 13 σ²: F ≈ 13, p ≈ 3e-4
    judge = Judge(SimpleNamespace(noise=NoiseModel(), n=n), D.DiscoverSettings().validate())
    judge._cache[judge._key(small)] = (r0, np.zeros((n, 1)))
    judge._cache[judge._key(large)] = (e, np.zeros((n, 2)))
    alone = judge.evidence(small, large, NoiseModel())
    assert 1e-4 < alone.p_value < 1e-3 and alone.checks["f_test"] and judge.level == 1e-3
    judge.family = 10
    assert judge.level == pytest.approx(1e-4)
    among_ten = judge.evidence(small, large, NoiseModel())
    assert among_ten.p_value == alone.p_value and not among_ten.checks["f_test"]
    assert not among_ten.passed and "F-test not significant at 0.0001" in among_ten.reason
    assert among_ten.to_dict()["level"] == pytest.approx(1e-4)
    with pytest.raises(ConfigError, match="discover.bonferroni"):
        D.DiscoverSettings(bonferroni="yes").validate()
    from toggle_id.discovery import toggle_plant as TP

    seen = []

    def fake_iteration(model, referee, *a, **k):
        seen.append(referee.family)
        raise RuntimeError("stop")

    plant = object.__new__(TP.TogglePlant)
    plant.model, plant.fit_noise, plant.referee, plant.gauge_bounds = _fake_model(n=n, noise=None), None, judge, {}
    plant.pool = [EFFECTS_BY_NAME[nm] for nm in ("backlash", "dead_time", "sensor_offset")]
    plant.anchor, plant.free, plant.held, plant.say, plant.on_refit = None, (), (), print, None
    for bonferroni, family in ((True, 2), (False, 1)):
        plant.s = D.DiscoverSettings(bonferroni=bonferroni, other_starts_above=0).validate()  # (no starts here)
        judge.family = 1
        with pytest.MonkeyPatch.context() as mp, pytest.raises(RuntimeError, match="stop"):
            mp.setattr(TP, "_iteration", fake_iteration)
            plant.forward_step(large, [{"name": "backlash"}], 2)
        assert seen[-1] == family and judge.family == 1  # two left; reset after the step, whatever happened


def test_a_nominal_vector_moved_into_anothers_gauge_holds_its_values_and_the_same_x_B():
    """gauge.in_gauge_of: the held parameters (K_l, K_i, m_C) take the other vector's values, the effects follow
    their scales (a force with the mechanism, the drive limit with the current, c_kt as its square), and x_B does
    not move; a move out of the feasible domain gives None."""
    from toggle_id.discovery.gauge import GAUGE_HELD, in_gauge_of

    rng = np.random.default_rng(11)
    theta = extend(ASSIGNED * np.exp(0.3 * rng.standard_normal(len(PARAM_NAMES))))[0]
    like = extend(ASSIGNED * np.exp(0.3 * rng.standard_normal(len(PARAM_NAMES))))[0]
    theta[ALL_INDEX["tau_c"]], theta[ALL_INDEX["s_sat"]], theta[ALL_INDEX["c_kt"]] = 0.05, 0.17, 1e-6
    moved = in_gauge_of(theta, like)
    assert moved is not None
    for nm in GAUGE_HELD.values():
        assert moved[ALL_INDEX[nm]] == pytest.approx(like[ALL_INDEX[nm]], rel=1e-12)
    ki, kl = ALL_INDEX["K_i"], ALL_INDEX["K_l"]
    assert moved[ALL_INDEX["s_sat"]] * moved[ki] == pytest.approx(theta[ALL_INDEX["s_sat"]] * theta[ki], rel=1e-12)
    assert moved[ALL_INDEX["c_kt"]] * moved[ki] ** 2 == pytest.approx(theta[ALL_INDEX["c_kt"]] * theta[ki] ** 2,
                                                                       rel=1e-12)
    assert moved[ALL_INDEX["tau_c"]] / moved[kl] == pytest.approx(theta[ALL_INDEX["tau_c"]] / theta[kl], rel=1e-12)
    rec = Record.from_sweep("simulation", 1.0, name="gauge")
    rec.x_B = np.zeros(rec.n)  # outputs only
    y = D.Model(rec, PRECISE).outputs(np.array([theta, moved]))
    assert np.all(np.isfinite(y)) and np.max(np.abs(y[0] - y[1])) < 1e-10
    far = like.copy()
    far[ki] = theta[ki] * 1e-4  # K_t would have to grow 1e4-fold, past its bound
    assert in_gauge_of(theta, far) is None


def test_the_effects_domains_hold_at_the_reference_scale_in_any_gauge():
    """gauge.domains_in_gauge: a loop whose mechanism sits at 1.6 times the reference scale and its current at half
    of it reads a force-type magnitude's domain 1.6 times wider, a drive limit's (1/V) twice and a torque
    saturation's (1/A²) four times; an effect the gauge does not scale (a dead time, a lash) keeps the library's.
    So a magnitude inside the domain at the reference scale (a viscous friction of 9000 N·s/m, domain 0–10⁴) is
    inside it in the loop's gauge, and the model's fits keep to that (Model.domains, the record's own over it)."""
    from toggle_id.discovery.gauge import _scale, domains_in_gauge, gauge_scales
    from toggle_id.stages import stage_bounds

    ref = extend(ASSIGNED)[0]
    ref[ALL_INDEX["c_B"]] = 9000.0
    loop = ref.copy()
    _scale(loop, 1.6, 0.5)  # mechanism ×1.6; current ×0.5 (K_i ×2, K_t ×0.5)
    c_m, c_e = gauge_scales(loop, PARAM_NAMES, ref)
    assert (c_m, c_e) == (pytest.approx(1 / 1.6, rel=1e-12), pytest.approx(2.0, rel=1e-12))
    dom = domains_in_gauge(c_m, c_e)
    lib = {nm: tuple(float(b[0]) for b in stage_bounds([nm])) for nm in ("c_B", "s_sat", "c_kt", "tau_c")}
    assert dom["c_B"] == pytest.approx((0.0, 1.6 * lib["c_B"][1]), rel=1e-12)
    assert dom["tau_c"] == pytest.approx((0.0, 1.6 * lib["tau_c"][1]), rel=1e-12)
    assert dom["s_sat"] == pytest.approx((0.0, lib["s_sat"][1] / 2.0), rel=1e-12)  # s_sat·K_i is what x_B sees
    assert dom["c_kt"] == pytest.approx((0.0, lib["c_kt"][1] / 4.0), rel=1e-12)
    assert "tau_d" not in dom and "b_l" not in dom and "n_cog" not in dom
    assert loop[ALL_INDEX["c_B"]] == pytest.approx(14400.0) and dom["c_B"][0] <= 14400.0 <= dom["c_B"][1]
    assert domains_in_gauge(1.0, 1.0) == {}
    rec = Record.from_sweep("simulation", 0.2, name="domains")
    rec.x_B = np.zeros(rec.n)
    model = D.Model(rec, PRECISE)
    model.gauge_bounds, model.bounds = dom, {"c_B": (0.0, 5000.0)}
    assert model.domain("c_B") == (0.0, 5000.0) and model.domain("s_sat") == dom["s_sat"]
    assert model.domain("tau_d") == tuple(float(b[0]) for b in stage_bounds(["tau_d"]))
    # a user's domain takes the library's place, read at the reference scale too; one the gauge does not scale as given
    given = domains_in_gauge(c_m, c_e, {"c_B": (0.0, 3e4), "tau_d": (0.0, 0.01)})
    assert given["c_B"] == pytest.approx((0.0, 4.8e4)) and given["tau_d"] == (0.0, 0.01)
    assert given["s_sat"] == dom["s_sat"]


def test_an_added_effect_left_at_the_edge_of_its_domain_is_said_and_a_bad_domain_is_one_line():
    """loop.at_the_edge: an added effect whose magnitude the final fit left within 5 % of its domain's bound (in the
    loop's gauge) gets a sentence; one inside does not. discover(bounds=...) with an unknown or empty domain fails
    with one line before any work."""
    from toggle_id.discovery.loop import at_the_edge
    from toggle_id.discovery.model import Fit

    rec = Record.from_sweep("simulation", 0.2, name="edge")
    rec.x_B = np.zeros(rec.n)
    model = D.Model(rec, PRECISE)
    model.gauge_bounds = {"c_B": (0.0, 1.6e4)}
    theta = extend(ASSIGNED)[0]
    theta[ALL_INDEX["c_B"]] = 1.59e4
    added = [{"name": "viscous_friction_slider"}]
    edge = at_the_edge(model, added, Fit(theta, ("c_B",), 1.0))
    assert len(edge) == 1 and "+bounds.c_B=" in edge[0] and "1.6e+04" in edge[0]
    theta[ALL_INDEX["c_B"]] = 1.2e4  # beyond the library's 10⁴, inside the gauge's domain
    assert at_the_edge(model, added, Fit(theta, ("c_B",), 1.0)) == []
    for bad, word in (({"c_X": (0.0, 1.0)}, "unknown"), ({"c_B": (5.0, 1.0)}, "inverted")):
        with pytest.raises(ConfigError, match=word):
            D.discover(rec, bounds=bad)


def test_an_accepted_refit_far_above_the_noise_is_polished_again_from_the_baselines_other_starts(monkeypatch):
    """A large effect's refit from the baseline's start can stop in a valley (a drive limit at 160 µm: 14 µm); above
    ``other_starts_above`` times the record's noise the accepted refit is polished again from the other starts
    given, with its effect values, and the lowest error is judged and reported; below, or with none given, or off,
    nothing more is fitted."""
    from types import SimpleNamespace

    from toggle_id.discovery import refit as RF
    from toggle_id.discovery.model import Fit
    from toggle_id.discovery.settings import DiscoverSettings

    theta, eff, base, scout = _refit_case("voltage_saturation", "s_sat", 0.2, 1000.0)
    other = theta.copy()
    other[ALL_INDEX["mu"]] = 0.3  # the other start: another place of the nominal parameters
    starts = []

    def fake_fit_free(model, start, names, *a, **k):
        starts.append(start.copy())
        from_other = start[ALL_INDEX["mu"]] == 0.3
        return Fit(start.copy(), tuple(names), sse=1.0 if from_other else 50.0)

    judged = []

    def pair(small, large):
        judged.append(large.sse)
        return SimpleNamespace(F=1.0, p_value=0.0, delta_bic=-1.0, passed=True, reason="ok", to_dict=lambda: {})

    monkeypatch.setattr(RF, "fit_free", fake_fit_free)
    monkeypatch.setattr(RF, "_std_errors", lambda fit, names, n: {})
    monkeypatch.setattr(RF, "revived", lambda th, free: None)
    monkeypatch.setattr(RF, "screened_starts", lambda model, effect, start: [start])  # (tested on its own below)
    model = _fake_model(n=1000)
    noise = 0.02  # RMS 0.224 from the scout's start: above 5 times it
    rf = RF.refit_candidate(model, base, eff, scout, DiscoverSettings(), 1, SimpleNamespace(judge_pair=pair),
                            others=[other], noise_m=noise)
    assert rf.accepted and rf.sse1 == 1.0 and judged == [50.0, 1.0]
    assert rf.search["before_other_starts"]["rmse_m"] == pytest.approx(np.sqrt(50.0 / 1000))
    assert rf.search["other_starts"] == [{"rmse_m": pytest.approx(np.sqrt(1.0 / 1000)), "nfev": None}]
    assert starts[-1][ALL_INDEX["s_sat"]] == 0.2 and starts[-1][ALL_INDEX["mu"]] == 0.3  # with the refit's values
    for others, noise_m, above in (([other], 0.05, 5.0), ([], noise, 5.0), ([other], noise, 0.0)):
        judged.clear()  # within 5 times the noise, no other start, off
        kept = RF.refit_candidate(model, base, eff, scout, DiscoverSettings(other_starts_above=above), 1,
                                  SimpleNamespace(judge_pair=pair), others=others, noise_m=noise_m)
        assert kept.sse1 == 50.0 and judged == [50.0] and "other_starts" not in kept.search


def test_another_start_is_screened_over_the_effects_magnitudes_and_its_threshold_grid_in_one_batch():
    """refit.screened_starts: the start with the magnitude at SCREEN_FACTORS of its value and, for a drive limit,
    at its grid there, ranked by the fits' objective in one batch; the best two, failed rows never."""
    from types import SimpleNamespace

    from toggle_id.discovery.refit import SCREEN_FACTORS, screened_starts

    theta = extend(ASSIGNED)[0]
    start = theta.copy()
    i = ALL_INDEX["s_sat"]
    start[i] = 0.4
    v_in = np.full(50, 0.06)
    asked = []

    def fit_residuals(rows):  # the objective is least at s_sat 0.2; one row fails
        asked.append(rows.copy())
        out = np.tile((rows[:, i] - 0.2)[:, None], (1, 3))
        out[np.isclose(rows[:, i], 0.28), :] = np.nan
        return out

    model = _fake_model(fit_residuals=fit_residuals, record=SimpleNamespace(v_in=v_in))
    best = screened_starts(model, EFFECTS_BY_NAME["voltage_saturation"], start)[:2]
    tried = asked[0][:, i]
    assert len(asked) == 1  # one batch
    assert set(np.round(tried[:len(SCREEN_FACTORS)], 12)) == {0.2, 0.28, 0.4, 0.56, 0.8}
    grid = EFFECTS_BY_NAME["voltage_saturation"].grid(start, v_in, len(SCREEN_FACTORS))
    assert np.allclose(np.sort(tried[len(SCREEN_FACTORS):]), np.sort(grid))  # the drive's grid at this start
    assert [b[i] for b in best] == pytest.approx([0.2, sorted(tried, key=lambda v: abs(v - 0.2))[1]])
    assert all(np.array_equal(np.delete(b, i), np.delete(start, i)) for b in best)
    coulomb = screened_starts(model, EFFECTS_BY_NAME["coulomb_friction_motor"],
                              _with_value(theta, "tau_c", 0.1))
    assert len(asked[-1]) == len(SCREEN_FACTORS) and len(coulomb) == 5  # no grid: the factors alone


def _with_value(theta, name, value):
    out = theta.copy()
    out[ALL_INDEX[name]] = value
    return out


def test_the_other_starts_are_polished_in_their_screened_order_until_one_reaches_the_floor(monkeypatch):
    """refit._from_other_starts: a drive limit's basin is narrow and the objective at a start does not rank it, so
    every screened start is polished in order, and the search stops at the first that reaches the floor; a start
    whose polish comes back to the refit's own RMS is left there."""
    from types import SimpleNamespace

    from toggle_id.discovery import refit as RF
    from toggle_id.discovery.model import Fit
    from toggle_id.discovery.settings import DiscoverSettings

    theta = extend(ASSIGNED)[0]
    ends = {0.27: 11.7e-6, 0.25: 11.6e-6, 0.23: 1.0e-6, 0.2: 1.0e-6}  # RMS where a polish from s_sat ends
    polished = []

    def fake_fit_free(model, start, names, *a, **k):
        v = round(float(start[ALL_INDEX["s_sat"]]), 6)
        polished.append(v)
        return Fit(start.copy(), tuple(names), sse=ends[v] ** 2 * 1000)

    monkeypatch.setattr(RF, "fit_free", fake_fit_free)
    monkeypatch.setattr(RF, "screened_starts", lambda model, effect, start: [
        _with_value(start, "s_sat", v) for v in (0.27, 0.25, 0.23, 0.2)])
    model = _fake_model(n=1000)
    eff = EFFECTS_BY_NAME["voltage_saturation"]
    fits = RF._from_other_starts(model, eff, [theta, theta], ("s_sat",), DiscoverSettings(), 1.5e-6)
    assert polished == [0.27, 0.25, 0.23] and fits[-1].rmse(1000) == pytest.approx(1.0e-6)
    polished.clear()
    fits = RF._from_other_starts(model, eff, [theta, theta], ("s_sat",), DiscoverSettings(), 0.5e-6)
    assert polished == [0.27, 0.25, 0.23, 0.2] * 2 and len(fits) == 8  # none reaches it: every start tried
    polished.clear()  # a polish back at the refit's own optimum (11.6 µm, within SAME_OPTIMUM) ends its start
    fits = RF._from_other_starts(model, eff, [theta, theta], ("s_sat",), DiscoverSettings(), 0.5e-6, 11.6e-6 * 1.0005)
    assert polished == [0.27, 0.25] * 2 and len(fits) == 4
    polished.clear()  # one farther from it (11.7 vs 11.6 µm, 0.9 %) does not
    fits = RF._from_other_starts(model, eff, [theta, theta], ("s_sat",), DiscoverSettings(), 0.5e-6, 11.8e-6)
    assert polished == [0.27, 0.25, 0.23, 0.2] * 2


def _refit_case(effect: str, param: str, value: float, base_sse: float):
    """(theta, effect, base fit, scout) of a refit test: the assigned values, a baseline with μ free, and a scout
    at ``param`` = ``value``."""
    from toggle_id.discovery import refit as RF
    from toggle_id.discovery.model import Fit

    theta = extend(ASSIGNED)[0]
    eff = EFFECTS_BY_NAME[effect]
    scout = RF.Scout(eff.name, 90.0, _with_value(theta, param, value), {"best_grid": {param: value}})
    return theta, eff, Fit(theta.copy(), ("mu",), sse=base_sse), scout
