"""The discovery loop's judge: comparisons under coloured noise, prediction-error fits under the noise model of a
residual, raw comparisons across noise models, out-of-sample gains and the forward step's level."""
from __future__ import annotations

import numpy as np
import pytest

from toggle_id import discovery as D
from toggle_id.discovery.timing import PhaseClock
from toggle_id.effects import ALL_INDEX, EFFECTS_BY_NAME
from toggle_id.errors import ConfigError
from toggle_id.params import ASSIGNED
from toggle_id.simulate import extend

from discovery_cases import fake_model


# ---------------------------------------------------------------------------------------------- the judge
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
    model = SimpleNamespace(n=100, noise=WHITE, residuals=lambda th: np.zeros((1, 100)), clock=PhaseClock())
    polished = []

    def fake_fit_free(m, start, free, *a, **k):
        polished.append(m.noise)
        return Fit(start, tuple(free), 4.0, noise=m.noise)

    monkeypatch.setattr(TP, "fit_free", fake_fit_free)
    monkeypatch.setattr("toggle_id.discovery.refit.fit_free", fake_fit_free)  # the refits without an effect
    monkeypatch.setattr(TP, "_polish_with_effect", lambda m, chosen, *a, **k: Fit(theta, ("mu", "x_off"), 3.0,
                                                                              noise=m.noise))
    # the stand-in model has no record to read its noise off: the profile of the added effect (forward.rescreened,
    # tests/test_landscape.py) is not this test's
    monkeypatch.setattr(TP, "rescreened", lambda m, name, fit, *a: (fit, []))
    noises, chosen = [], [None, SimpleNamespace(name="sensor_offset", F=50.0, p_value=1e-9, delta_bic=-40.0,
                                                params={}, evidence={}, fit=Fit(theta, ("mu", "x_off"), 3.0),
                                                partner=None)]

    def iteration(m, *a, **k):
        noises.append(m.noise)
        return {"refits": [], "scores": [], "base": a[1], "better_null": None, "record": {}, "chosen": chosen.pop(0),
                "rivals": []}

    monkeypatch.setattr(TP, "_iteration", iteration)
    plant = TP.TogglePlant(model, SimpleNamespace(glitches=[]),
                           DiscoverSettings(prediction_error=pem, glitch_k=0.0, other_starts_above=0.0),
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

    def polish_with_effect(m, chosen, *a, **k):
        under.append(m.noise)
        return Fit(theta, ("mu", "tau_d"), 3.0, noise=m.noise)

    monkeypatch.setattr(TP, "_polish_with_effect", polish_with_effect)
    monkeypatch.setattr(TP, "rescreened", lambda m, name, fit, *a: (fit, []))  # the stand-in has no record
    found = SimpleNamespace(name="dead_time", F=50.0, p_value=1e-9, delta_bic=-40.0, params={}, evidence={},
                            fit=Fit(theta, ("mu", "tau_d"), 3.0, noise=own), partner=None)
    monkeypatch.setattr(TP, "_iteration", lambda m, *a, **k: {
        "refits": [], "scores": [], "base": a[1], "better_null": None, "record": {}, "chosen": found, "rivals": []})
    model = SimpleNamespace(n=100, noise=loops, clock=PhaseClock())
    plant = TP.TogglePlant(model, SimpleNamespace(glitches=[]), DiscoverSettings(glitch_k=0.0, other_starts_above=0.0),
                           theta, [], ("mu",), (), [], None, lambda s: None, None)
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
    plant.model, plant.fit_noise, plant.referee, plant.gauge_bounds = fake_model(n=n, noise=None), None, judge, {}
    plant.pool = [EFFECTS_BY_NAME[nm] for nm in ("backlash", "dead_time", "sensor_offset")]
    plant.anchor, plant.free, plant.held, plant.say, plant.on_refit = None, (), (), print, None
    for bonferroni, family in ((True, 2), (False, 1)):
        plant.s = D.DiscoverSettings(bonferroni=bonferroni, other_starts_above=0).validate()  # (no starts here)
        judge.family = 1
        with pytest.MonkeyPatch.context() as mp, pytest.raises(RuntimeError, match="stop"):
            mp.setattr(TP, "_iteration", fake_iteration)
            plant.forward_step(large, [{"name": "backlash"}], 2)
        assert seen[-1] == family and judge.family == 1  # two left; reset after the step, whatever happened


def test_a_model_without_an_effect_also_starts_from_the_loops_own_fit_of_it(monkeypatch):
    """Backward elimination's model without an effect is refitted from the current model with the effect off and,
    when the loop had fitted that model itself (:attr:`TogglePlant.had`), from that fit too; the lower is kept.
    From the current model alone a prediction-error refit drifted to 3.567 µm where the baseline had 2.544 µm
    (rec15_d1). The polish is replaced by a stand-in whose SSE is one coordinate of its start."""
    from types import SimpleNamespace

    from toggle_id.discovery import refit as RF
    from toggle_id.discovery.model import Fit
    from toggle_id.discovery.toggle_plant import TogglePlant
    from toggle_id.effects import ALL_INDEX
    from toggle_id.params import ASSIGNED
    from toggle_id.simulate import extend

    starts = []

    def polish(model, theta, free, *args, **kw):
        starts.append((theta.copy(), tuple(free)))
        return Fit(theta.copy(), tuple(free), float(theta[ALL_INDEX["J_m"]]))

    monkeypatch.setattr(RF, "fit_free", polish)
    base = extend(ASSIGNED)[0]
    free = ("J_m", "R_s", "x_off")
    current = Fit(base.copy(), free, 1.0)
    current.theta[ALL_INDEX["x_off"]], current.theta[ALL_INDEX["J_m"]] = 2e-5, 5.0
    plant = TogglePlant(SimpleNamespace(), None, D.DiscoverSettings(), base, [], free, (), [], None, print, None)
    added = [{"name": "sensor_offset"}]
    assert plant.without(current, added[0], added).theta[ALL_INDEX["J_m"]] == 5.0 and len(starts) == 1
    assert starts[0][1] == ("J_m", "R_s") and starts[0][0][ALL_INDEX["x_off"]] == 0.0
    for had_j, kept in ((1.0, 1.0), (9.0, 5.0)):  # the loop's own fit is lower, then higher
        starts.clear()
        had = base.copy()
        had[ALL_INDEX["J_m"]] = had_j
        plant.had[frozenset()] = Fit(had, ("J_m", "R_s"), had_j)
        out = plant.without(current, added[0], added)
        assert len(starts) == 2 and out.theta[ALL_INDEX["J_m"]] == kept and out.free == ("J_m", "R_s")


def test_a_noise_model_that_is_an_error_the_model_lacks_is_not_whitened_by(monkeypatch):
    """With ``pe_guard_alpha``, a nested comparison whose larger model's prediction-error refit drifts from its
    least-squares fit beyond the noise (:func:`.noise.prediction_error_drift`) is judged on the loop's own
    least-squares fits, unwhitened, with the F-test and BIC deflated by the residual's serial correlation
    (:func:`.stats.serial_ratio`); within the bound, or with the guard off, the whitened refits are judged as before."""
    from toggle_id.discovery import validation as V
    from toggle_id.discovery.model import Fit
    from toggle_id.discovery.noise import NoiseModel
    from toggle_id.discovery.settings import DiscoverSettings
    from toggle_id.discovery.stats import serial_ratio

    n, rho = 2000, 0.8
    ar = NoiseModel((rho,), 1.0, 1.0 / (1 - rho ** 2), n)
    rng = np.random.default_rng(3)
    r1 = np.zeros(n)
    for i in range(1, n):  # a slow residual: what whitening would call noise
        r1[i] = rho * r1[i - 1] + rng.standard_normal()
    t = np.linspace(0.0, 1.0, n)
    J1 = np.column_stack([np.ones(n), np.sin(2 * np.pi * t)])
    theta = extend(ASSIGNED)[0]
    small, large = Fit(theta, ("mu",), sse=1.2 * float(r1 @ r1)), Fit(theta, ("mu", "x_off"), sse=float(r1 @ r1))
    drift_to = {}

    def fake_fit_free(model, start, names, *a, **k):  # the whitened refits; the larger one's raw SSE as set
        return Fit(start.copy(), tuple(names), sse=1.0, raw_sse=drift_to.get(len(names), 1.0), noise=ar)

    asked = []

    def evidence(s, lg, noise):
        asked.append((s, lg, noise))
        return V.Evidence(noise, 60.0, 1e-12, -50.0, 1.0, 0.9, s.sse, lg.sse,
                          checks={"f_test": True, "robust_f_test": True, "bic": True, "cross_validation": True})

    for guard, excess, serial in ((1e-3, 1e3, True), (1e-3, 1e-6, False), (0.0, 1e3, False)):
        monkeypatch.setattr(V, "fit_free", fake_fit_free)
        monkeypatch.setattr(V, "fit_noise", lambda r, order: ar)
        judge = V.Judge(type("M", (), {"noise": V.WHITE, "settings": None, "parallel": False, "n": n})(),
                        DiscoverSettings(pe_guard_alpha=guard))
        monkeypatch.setattr(judge, "residual_and_jacobian", lambda fit: (r1, J1))
        monkeypatch.setattr(judge, "evidence", evidence)
        monkeypatch.setattr(judge, "_reported_gain", lambda s, lg: True)
        drift_to[2] = large.sse + excess * ar.peak_spectrum
        asked.clear()
        ev = judge.judge_pair(small, large)
        if serial:
            assert asked == [(small, large, V.WHITE)]  # the loop's own fits, unwhitened
            c = serial_ratio(r1, J1, [1])["ratio"]
            assert c > 3.0  # AR(1) 0.8 and a slow column: about (1 + ρ)/(1 − ρ) = 9
            assert ev.inference == "least squares (HAC)" and "not noise" in ev.drift and ev.noise is ar
            assert ev.F == pytest.approx(60.0 / c) and ev.hc_ratio == pytest.approx(c)
            assert ev.delta_bic == pytest.approx((n / c) * np.log(1 / 1.2) + np.log(n / c))
            assert ev.checks["f_test"] == (ev.p_value < judge.level) and ev.checks["robust_f_test"] == ev.checks["f_test"]
            assert ev.to_dict()["inference"] == "least squares (HAC)"
        else:
            assert len(asked) == 1 and asked[0][0] is not small and asked[0][2] is ar  # the whitened refits
            assert ev.inference == "prewhitened" and ev.drift is None
