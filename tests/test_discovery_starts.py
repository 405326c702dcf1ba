"""Refits of the discovery loop from other starts: the dismissed candidates and the accepted refits far above the
noise polished again from the baseline's other starts, screened magnitudes, weaker starts at a domain's edge."""
from __future__ import annotations

import numpy as np
import pytest

from toggle_id import discovery as D
from toggle_id.discovery.timing import PhaseClock
from toggle_id.effects import ALL_INDEX, EFFECTS_BY_NAME
from toggle_id.errors import ConfigError
from toggle_id.params import ASSIGNED
from toggle_id.simulate import extend

from discovery_cases import fake_model, refit_case, with_value


# ---------------------------------------------------------------------------------------------- other starts
@pytest.mark.parametrize("base_rms_um, reached, structure", [(30.0, True, True), (30.0, False, True), (3.0, False, True),
                                                              (30.0, True, False)])
def test_far_above_the_noise_the_dismissed_candidates_are_polished_again_from_the_other_starts(
        monkeypatch, base_rms_um, reached, structure):
    """A 3-ms dead time hidden by a bent baseline (its refit there does not move): while nothing supported reaches
    within ``other_starts_above`` times the record's noise, the dismissed candidates whose score is significant are
    polished again from the baseline's other starts, strongest score first, until one ends near the noise; one that
    ends lower replaces its refit and is judged. Within that factor of the noise nothing more is fitted, nor where
    what is left holds no structure by the noise-aware structure test (coloured noise reads low in the record's
    third differences)."""
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
    monkeypatch.setattr(TP, "structure_left_at", lambda model, th, settings: (structure, ""))
    model = SimpleNamespace(n=n, residuals=lambda th: np.random.default_rng(0).standard_normal((1, n)),
                            clock=PhaseClock())
    said = []
    st = DiscoverSettings(top_k=4, second_point=False, ambiguity_alpha=0.0)
    out = TP._iteration(model, None, Fit(theta, ("J_m",), base_sse), theta, ("J_m",),
                        [EFFECTS_BY_NAME[nm] for nm in names], st, 1, (), said.append, None,
                        others=[theta.copy()], noise_m=noise_m)
    assert sorted(rf.name for rf in out["refits"]) == sorted(names)
    if base_rms_um < st.other_starts_above or not structure:
        assert asked == [] and out["chosen"] is None
    elif reached:  # strongest first; the dead time ends near the noise, so the search stops there
        assert asked == ["viscous_friction_slider", "dead_time"]
        assert out["chosen"].name == "dead_time" and out["chosen"].params == {"tau_d": 3e-3}
        assert any("refit dead_time" in s and "from another start of the baseline" in s for s in said)
    else:  # every significant dismissed candidate tried (the backlash's score is not), none lower
        assert asked == ["viscous_friction_slider", "dead_time", "sensor_offset"] and out["chosen"] is None


@pytest.mark.parametrize("first_um, searched", [(0.98, False), (3.0, True)])
def test_once_a_supported_refit_is_near_the_noise_the_rounds_other_refits_are_not_searched_from_other_starts(
        monkeypatch, first_um, searched):
    """The discover job's end-to-end record: a 50-µm offset refitted first to 0.975 µm; the load force after it,
    accepted at 10.6 µm, was polished from four other starts (all 10.59 µm) and never chosen. Once a supported refit
    of the round lies within NEAR_NOISE times the noise, the later refits get no other starts; above, they do."""
    from types import SimpleNamespace

    from toggle_id.discovery import forward as TP
    from toggle_id.discovery.model import Fit
    from toggle_id.discovery.refit import Refit, Scout
    from toggle_id.discovery.scoring import CandidateScore
    from toggle_id.discovery.settings import DiscoverSettings

    n, noise_m = 1000, 1e-6
    base_sse = (15e-6) ** 2 * n
    names = ["sensor_offset", "constant_load_force"]
    theta = extend(ASSIGNED)[0]
    given = {}

    def assess(model, label, th, free, remaining, settings, noise):
        sc = {nm: CandidateScore(nm, 80.0, 0.0, {}, None, 1.0, 1.0) for nm in names}
        return SimpleNamespace(label=label, scores=sc, profiles=set(names), proj=SimpleNamespace(rank=len(free)))

    def refit_candidate(model, base, eff, sc, settings, it, judge, held, anchor=None, others=(), noise_m=0.0):
        given[eff.name] = len(others)
        sse = ((first_um if eff.name == "sensor_offset" else 10.6) * 1e-6) ** 2 * n
        return Refit(eff.name, it, Fit(theta, base.free, sse), {}, base_sse, sse, 1, len(base.free) + 1, 1e3, 0.0,
                     -1e3, True, "ok", {})

    monkeypatch.setattr(TP, "assess", assess)
    monkeypatch.setattr(TP, "scout_candidate", lambda model, base, points, eff, settings, held: Scout(
        eff.name, base_sse * (0.1 if eff.name == "sensor_offset" else 0.5), None, {}))  # the offset's scout first
    monkeypatch.setattr(TP, "refit_candidate", refit_candidate)
    monkeypatch.setattr(TP, "guard_null", lambda *a: None)
    monkeypatch.setattr(TP, "structure_left_at", lambda model, th, settings: (True, ""))
    model = SimpleNamespace(n=n, residuals=lambda th: np.random.default_rng(0).standard_normal((1, n)),
                            clock=PhaseClock())
    out = TP._iteration(model, None, Fit(theta, ("J_m",), base_sse), theta, ("J_m",),
                        [EFFECTS_BY_NAME[nm] for nm in names], DiscoverSettings(top_k=2, second_point=False,
                                                                                ambiguity_alpha=0.0),
                        1, (), lambda s: None, None, others=[theta.copy(), theta.copy()], noise_m=noise_m)
    assert given == {"sensor_offset": 2, "constant_load_force": 2 if searched else 0}
    assert out["chosen"].name == "sensor_offset"


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
    left = with_value(theta, "tau_d", 1e-9)  # the refit from the bent baseline did not move
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
    model = SimpleNamespace(n=1000, noise=WHITE, domain=lambda nm: (0.0, 0.05), domains=dict,  # the library's τ_d
                            gauge_bounds={})
    other = with_value(theta, "mu", 0.3)
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
        out = FW._polish_with_effect(fake_model(n=100), chosen, anchor, free, D.DiscoverSettings(),
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
        out = FW._polish_with_effect(fake_model(n=100), chosen, anchor, free,
                                     D.DiscoverSettings(reanchor_rtol=rtol), lambda m: None)
        return starts, out

    starts, out = run(0.1)
    assert len(starts) == 3 and out.sse == 0.97 and out.theta[ALL_INDEX["b_l"]] == 5.1e-4
    assert starts[2][ALL_INDEX["J_m"]] == anchor[ALL_INDEX["J_m"]] and starts[2][ALL_INDEX["b_l"]] == 5.1e-4
    starts, out = run(0.0)  # off: the stalled fit is kept
    assert len(starts) == 2 and out.sse == 9.3
    with pytest.raises(ConfigError, match="reanchor_rtol"):
        D.DiscoverSettings(reanchor_rtol="x").validate()


def test_an_accepted_refit_far_above_the_noise_is_polished_again_from_the_baselines_other_starts(monkeypatch):
    """A large effect's refit from the baseline's start can stop in a valley (a drive limit at 160 µm: 14 µm); above
    ``other_starts_above`` times the record's noise the accepted refit is polished again from the other starts
    given, with its effect values, and the lowest error is judged and reported; below, or with none given, or off,
    nothing more is fitted."""
    from types import SimpleNamespace

    from toggle_id.discovery import refit as RF
    from toggle_id.discovery.model import Fit
    from toggle_id.discovery.settings import DiscoverSettings

    theta, eff, base, scout = refit_case("voltage_saturation", "s_sat", 0.2, 1000.0)
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
    structure = [True]
    monkeypatch.setattr(RF, "structure_left_at", lambda model, th, settings: (structure[0], ""))
    model = fake_model(n=1000)
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
    structure[0] = False  # far above the noise read off the differences, but what it leaves is noise by the
    judged.clear()  # noise-aware structure test (coloured noise reads low in the differences): nothing more fitted
    kept = RF.refit_candidate(model, base, eff, scout, DiscoverSettings(), 1, SimpleNamespace(judge_pair=pair),
                              others=[other], noise_m=noise)
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

    model = fake_model(fit_residuals=fit_residuals, record=SimpleNamespace(v_in=v_in))
    best = screened_starts(model, EFFECTS_BY_NAME["voltage_saturation"], start)[:2]
    tried = asked[0][:, i]
    assert len(asked) == 1  # one batch
    assert set(np.round(tried[:len(SCREEN_FACTORS)], 12)) == {0.2, 0.28, 0.4, 0.56, 0.8}
    grid = EFFECTS_BY_NAME["voltage_saturation"].grid(start, v_in, len(SCREEN_FACTORS))
    assert np.allclose(np.sort(tried[len(SCREEN_FACTORS):]), np.sort(grid))  # the drive's grid at this start
    assert [b[i] for b in best] == pytest.approx([0.2, sorted(tried, key=lambda v: abs(v - 0.2))[1]])
    assert all(np.array_equal(np.delete(b, i), np.delete(start, i)) for b in best)
    coulomb = screened_starts(model, EFFECTS_BY_NAME["coulomb_friction_motor"],
                              with_value(theta, "tau_c", 0.1))
    assert len(asked[-1]) == len(SCREEN_FACTORS) and len(coulomb) == 5  # no grid: the factors alone


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
        with_value(start, "s_sat", v) for v in (0.27, 0.25, 0.23, 0.2)])
    model = fake_model(n=1000)
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


# ---------------------------------------------------------------------------------------------- the gauge's edge
def _edge_case(monkeypatch, truth: float, *, name: str = "c_B", given: dict | None = None,
               settings: D.DiscoverSettings | None = None, start: float = 1e4):
    """forward.widened_at_edge on a stand-in model whose fits end at ``truth`` clipped into the domain of ``name`` in
    the loop's gauge (its error grows with the distance from ``truth``); the fit starts at ``start``. Returns the
    model, the fit and the domains widened, and the domains each polish kept to."""
    from types import SimpleNamespace

    from toggle_id.discovery import forward as FW
    from toggle_id.discovery.model import Fit
    from toggle_id.stages import stage_bounds

    def domain(k):
        if k in model.gauge_bounds:
            return tuple(model.gauge_bounds[k])
        lo, hi = stage_bounds([k])
        return float(lo[0]), float(hi[0])

    model = SimpleNamespace(n=100, bounds={}, gauge_bounds={}, domain=domain)
    calls = []

    def fake_fit(m, th, fr, *a, **k):
        out = th.copy()
        out[ALL_INDEX[name]] = float(np.clip(truth, *domain(name)))
        calls.append(domain(name))
        return Fit(out, fr, 1.0 + abs(out[ALL_INDEX[name]] - truth) / abs(truth))

    monkeypatch.setattr(FW, "fit_free", fake_fit)
    model.gauge_bounds = {name: (0.0, 1e4)} if name == "c_B" else {}
    th = extend(ASSIGNED)[0]
    th[ALL_INDEX[name]] = start if name == "c_B" else 1.99e-3
    fit = Fit(th, ("J_m", name), 1.0 + abs(th[ALL_INDEX[name]] - truth) / abs(truth))
    out, widened = FW.widened_at_edge(model, {"c_B": "viscous_friction_slider", "b_l": "backlash"}[name], fit,
                                      (settings or D.DiscoverSettings()).validate(), lambda m: None, given or {})
    return model, out, widened, calls


def test_a_scale_type_magnitude_pressing_on_its_domain_in_the_gauge_gets_a_wider_domain(monkeypatch):
    """A slider viscous friction whose fit ends at the edge of its domain in the loop's gauge (the library's, read at
    the baseline's scale, which the fits then move; probe q4): the room from "off" grows edge_widen times and the fit
    is polished again while it presses on the edge and gains, at most edge_widenings times; the widened domain holds
    for the plant's later fits and is recorded."""
    three = D.DiscoverSettings(edge_widen=3.0, edge_widenings=2)
    model, out, widened, calls = _edge_case(monkeypatch, 2.5e4, settings=three)
    assert calls == [(0.0, 3e4)]  # once: inside the widened domain, it no longer presses
    assert out.theta[ALL_INDEX["c_B"]] == pytest.approx(2.5e4)
    assert widened == {"c_B": (0.0, 3e4)} and model.gauge_bounds["c_B"] == (0.0, 3e4)
    model, out, widened, calls = _edge_case(monkeypatch, 1e6, settings=three)
    assert calls == [(0.0, 3e4), (0.0, 9e4)]  # at most twice
    assert out.theta[ALL_INDEX["c_B"]] == pytest.approx(9e4) and widened == {"c_B": (0.0, 9e4)}
    model, out, widened, calls = _edge_case(monkeypatch, 2.5e4)  # the defaults: twice the room, once
    assert calls == [(0.0, 2e4)] and out.theta[ALL_INDEX["c_B"]] == pytest.approx(2e4)


@pytest.mark.parametrize("case", ["inside", "given", "absolute", "off"])
def test_a_domain_is_left_as_it_is_where_the_fit_does_not_press_or_the_domain_is_not_the_gauges(monkeypatch, case):
    """Nothing is widened for a magnitude inside its domain, one whose domain a user gave, one x_B fixes absolutely
    (a backlash, in metres), or with edge_widenings 0."""
    kw = {"inside": dict(truth=5e3, start=5e3), "given": dict(truth=2.5e4, given={"c_B": (0.0, 1e4)}),
          "absolute": dict(truth=5e-3, name="b_l"), "off": dict(truth=2.5e4, settings=D.DiscoverSettings(
              edge_widenings=0))}[case]
    model, out, widened, calls = _edge_case(monkeypatch, **kw)
    assert calls == [] and widened == {}


def test_a_wider_domain_that_does_not_lower_the_error_is_taken_back(monkeypatch):
    """At the edge but not pressing on it (the error least at the edge itself): polished once in the wider domain,
    no gain, the domain as it was."""
    model, out, widened, calls = _edge_case(monkeypatch, 1e4)
    assert calls == [(0.0, 2e4)] and widened == {} and model.gauge_bounds["c_B"] == (0.0, 1e4)
    assert out.theta[ALL_INDEX["c_B"]] == pytest.approx(1e4)


@pytest.mark.parametrize("bad", [{"edge_widen": 1.0}, {"edge_widen": True}, {"edge_widenings": -1},
                                 {"edge_widenings": 1.5}])
def test_edge_widening_settings_are_checked(bad):
    with pytest.raises(ConfigError, match=next(iter(bad))):
        D.DiscoverSettings(**bad).validate()


def test_a_magnitude_outside_the_library_at_the_reference_scale_is_said():
    """loop.beyond_the_library: the value the report states (at the reference scale) against the domain a user gave,
    else the library's."""
    from toggle_id.discovery.loop import beyond_the_library
    from toggle_id.discovery.model import Fit

    th = extend(ASSIGNED)[0]
    th[ALL_INDEX["c_B"]] = 2.5e4
    added = [{"name": "viscous_friction_slider"}]
    fit = Fit(th, ("c_B",), 1.0)
    (line,) = beyond_the_library(added, fit, {}, True)
    assert "c_B reads 2.5e+04 N·s/m at the reference scale" in line and "[0, 1e+04]" in line
    (line,) = beyond_the_library(added, fit, {}, False)
    assert "in the loop's gauge" in line
    assert beyond_the_library(added, fit, {"c_B": (0.0, 3e4)}, True) == []


def test_the_start_the_baseline_came_from_is_searched_too_and_last():
    """The other starts of the searches (TogglePlant._other_starts): each start of the baseline moved into its gauge,
    the one the baseline came from last — with an effect on, its polish may reach another basin than the nominal
    polish from it did (docs/discovery.md, rec15_d1) — and the record's own noise; none when the rule is off."""
    from types import SimpleNamespace

    from toggle_id.data import Record
    from toggle_id.discovery import toggle_plant as TP
    from toggle_id.discovery.gauge import in_gauge_of
    from toggle_id.discovery.settings import DiscoverSettings

    rec = Record.from_sweep("simulation", 0.2, name="starts")
    rec.x_B = np.random.default_rng(0).normal(0.0, 1e-6, rec.n)
    ga = extend(ASSIGNED * np.exp(0.2 * np.random.default_rng(1).standard_normal(len(ASSIGNED))))[0]
    ref = extend(ASSIGNED)[0]

    def plant(settings):
        p = TP.TogglePlant(SimpleNamespace(record=rec, n=rec.n), SimpleNamespace(glitches=[]), settings, ga, [ref],
                           ("mu",), (), [], None, lambda s: None, None)
        p.anchor = ga  # the baseline came from the GA's fit
        return p

    others, noise = plant(DiscoverSettings())._other_starts()
    assert len(others) == 2 and np.allclose(others[0], in_gauge_of(ref, ga)) and np.array_equal(others[1], ga)
    assert noise == pytest.approx(1e-6, rel=0.1)
    assert plant(DiscoverSettings(other_starts_above=0.0))._other_starts() == ([], 0.0)


@pytest.mark.parametrize("base_rms_um, winner_um, structure, looked", [
    (1.45, None, True, True), (1.45, 1.40, True, True), (1.45, 1.0, True, False), (1.1, None, True, False),
    (1.45, 1.40, False, False), (1.45, None, False, False)])
def test_pairs_are_looked_at_only_while_the_model_and_every_single_refit_lie_above_the_noise_band(
        monkeypatch, base_rms_um, winner_um, structure, looked):
    """discover.pair_look: the step's pairs are refitted only while the current model and the best supported single
    refit both lie above ``pair_above`` times the record's noise and what the step leaves (the best single refit,
    or the current model) holds structure by the noise-aware structure test; a pair the look returns becomes the
    step's choice (no rivals are looked for: the pair is judged beside its own member)."""
    from types import SimpleNamespace

    from toggle_id.discovery import forward as TP
    from toggle_id.discovery.model import Fit
    from toggle_id.discovery.refit import Refit, Scout
    from toggle_id.discovery.scoring import CandidateScore
    from toggle_id.discovery.settings import DiscoverSettings

    n, noise_m = 1000, 1e-6
    base_sse = (base_rms_um * 1e-6) ** 2 * n
    names = ["stribeck_friction", "dead_time"]
    theta = extend(ASSIGNED)[0]

    def assess(model, label, th, free, remaining, settings, noise):
        sc = {nm: CandidateScore(nm, 50.0, 0.3, {}, None, 1.0, 1.0) for nm in names}
        return SimpleNamespace(label=label, scores=sc, profiles=set(names), proj=SimpleNamespace(rank=len(free)))

    def refit_candidate(model, base, eff, sc, settings, it, judge, held, anchor=None, **other_starts):
        win = eff.name == "dead_time" and winner_um is not None
        sse = (winner_um * 1e-6) ** 2 * n if win else base_sse * 0.99
        return Refit(eff.name, it, Fit(theta, base.free, sse, raw_sse=sse), {}, base_sse, sse, 1, len(base.free) + 1,
                     50.0 if win else 0.5, 0.0 if win else 0.48, -40.0 if win else 5.0, win, "ok", {})

    asked = []
    pair = Refit("stribeck_friction", 1, Fit(theta, ("J_m",), 1.02e-12 * n, raw_sse=1.02e-12 * n), {}, base_sse,
                 1.02e-12 * n, 3, 4, 1e3, 0.0, -1e3, True, "ok", {}, partner="dead_time")

    def pair_look(model, judge, base, refits, best, settings, it, held, say, near):
        asked.append((best.name if best else None, near))
        return pair, [pair.to_dict(n)]

    monkeypatch.setattr(TP, "assess", assess)
    monkeypatch.setattr(TP, "scout_candidate", lambda model, base, points, eff, settings, held: Scout(
        eff.name, base_sse * 0.99, None, {}))
    monkeypatch.setattr(TP, "refit_candidate", refit_candidate)
    monkeypatch.setattr(TP, "guard_null", lambda *a: None)
    monkeypatch.setattr(TP, "pair_look", pair_look)
    gated = []
    monkeypatch.setattr(TP, "structure_left_at", lambda model, th, settings: (
        gated.append(th) or structure, "structure left: …" if structure else "no structure left: …"))
    model = SimpleNamespace(n=n, residuals=lambda th: np.random.default_rng(0).standard_normal((1, n)),
                            clock=PhaseClock())
    st = DiscoverSettings(top_k=4, second_point=False, ambiguity_alpha=0.0, pair_look=4, other_starts_above=0.0)
    out = TP._iteration(model, None, Fit(theta, ("J_m",), base_sse), theta, ("J_m",),
                        [EFFECTS_BY_NAME[nm] for nm in names], st, 1, (), lambda s: None, None,
                        others=[], noise_m=noise_m)
    if looked:
        assert asked == [("dead_time" if winner_um else None, pytest.approx(1.2e-6))]
        assert out["chosen"] is pair and out["record"]["accepted_with"] == "dead_time" and not out["rivals"]
    else:
        assert asked == [] and "pairs" not in out["record"]
        assert (out["chosen"].name if out["chosen"] else None) == ("dead_time" if winner_um else None)
    off = TP._iteration(model, None, Fit(theta, ("J_m",), base_sse), theta, ("J_m",),
                        [EFFECTS_BY_NAME[nm] for nm in names], DiscoverSettings(top_k=4, second_point=False,
                                                                                ambiguity_alpha=0.0), 1, (),
                        lambda s: None, None, others=[], noise_m=noise_m)
    assert len(asked) == int(looked) and off["chosen"] is not pair  # pair_look 0: off
    assert len(gated) == int(base_rms_um > 1.2 and (winner_um or 2.0) > 1.2)  # the structure test behind the RMS gate
