"""The error profiled along an effect's parameters (toggle_id.discovery.landscape) and the forward step's polish from
a profile's lowest point (forward.rescreened), on stand-in models whose error is a chosen function of one parameter;
then one profile of the real plant."""
from types import SimpleNamespace

import numpy as np
import pytest

from toggle_id.discovery import forward as FW
from toggle_id.discovery import landscape as L
from toggle_id.discovery.model import Fit
from toggle_id.discovery.settings import DiscoverSettings
from toggle_id.effects import ALL_INDEX
from toggle_id.errors import ConfigError
from toggle_id.params import ASSIGNED
from toggle_id.simulate import extend

N = 50
NOISE = 1e-6


def stand_in(error_of, name="b_l", domain=(0.0, 5e-3)):
    """A model of N samples whose raw RMS is ``error_of(value of name)`` (m), the same residual at every sample."""
    def residuals(thetas, tier=None):
        thetas = np.atleast_2d(thetas)
        return np.repeat(np.array([error_of(v) for v in thetas[:, ALL_INDEX[name]]])[:, None], N, axis=1)

    return SimpleNamespace(n=N, residuals=residuals, domain=lambda k: domain, record=None, stiff=set())


def theta_at(name, value):
    th = extend(ASSIGNED)[0]
    th[ALL_INDEX[name]] = value
    return th


def smooth(v):
    return NOISE * (1.0 + 1e7 * (v - 2e-4) ** 2 * 1e3)


def rough(v):
    """A needle at 0.2 mm inside a wavy valley (local minima every 20 µm of lash), like the 0.2-mm lash probe q1."""
    return NOISE * (1.0 + 2e5 * abs(v - 2e-4) + 8.0 * (1.0 - np.cos(2 * np.pi * (v - 2e-4) / 2e-5)))


def test_a_smooth_cost_at_its_optimum_has_one_minimum_and_nothing_below_it():
    p = L.profile(stand_in(smooth), theta_at("b_l", 2e-4), "b_l", 0.25, 61, 0.1 * NOISE)
    assert p.minima == 1 and not p.rough and not p.below_fit()
    assert p.rmse_m == pytest.approx(NOISE) and p.lowest == (pytest.approx(2e-4), pytest.approx(NOISE))
    assert L.rough_text([p], NOISE) == ""


def test_a_rough_cost_counts_its_local_minima_and_finds_the_lower_point():
    p = L.profile(stand_in(rough), theta_at("b_l", 2.2e-4), "b_l", 0.25, 101, 0.1 * NOISE)
    assert p.rough and p.minima >= 4  # the wave's minima within ±25 % of 0.22 mm: 0.18 … 0.26 mm
    assert p.below_fit() and p.lowest[0] == pytest.approx(2e-4, abs=1e-6)
    text = L.rough_text([p], NOISE)
    assert f"{p.minima} local minima" in text and "below the fit's" in text and "b_l around 0.00022 m" in text


def test_a_smooth_cost_away_from_its_optimum_is_said_too():
    p = L.profile(stand_in(smooth), theta_at("b_l", 1.8e-4), "b_l", 0.25, 61, 0.1 * NOISE)
    assert not p.rough and p.below_fit()
    assert "below the fit's" in L.rough_text([p], NOISE) and "local minima" not in L.rough_text([p], NOISE)


def test_the_grid_keeps_to_the_domain_and_holds_the_value():
    g = L.grid(1e-4, (0.0, 1.1e-4), 0.25, 11)
    assert g.min() == pytest.approx(0.75e-4) and g.max() == pytest.approx(1.1e-4) and 1e-4 in g
    g = L.grid(0.0, (0.0, 4.0), 0.25, 5)  # a value at zero: the first quarter of the domain
    assert g.tolist() == [0.0, 0.25, 0.5, 0.75, 1.0]


def test_phases_and_counts_are_not_profiled():
    assert L.profiled_names(["cogging_torque"]) == ["a_cog"]
    assert L.profiled_names(["stribeck_friction", "backlash"]) == ["F_s", "v_s", "b_l"]


def test_failed_simulations_are_gaps_not_minima():
    def failing(v):
        return np.nan if 2.05e-4 < v < 2.1e-4 else smooth(v)

    p = L.profile(stand_in(failing), theta_at("b_l", 2e-4), "b_l", 0.25, 61, 0.1 * NOISE)
    assert p.minima == 1 and np.isnan(p.rmse).any() and p.to_dict()["rmse_grid_m"].count(None) > 0


def _rescreen(monkeypatch, error_of, value, **settings):
    """forward.rescreened on a stand-in whose polish goes to the nearest multiple of 20 µm of lash (the local
    minimum of :func:`rough` its start falls into)."""
    model = stand_in(error_of)
    model.record = "rec"
    monkeypatch.setattr(FW, "difference_noise", lambda recs: NOISE, raising=False)
    starts = []

    def fake_fit(m, th, fr, *a, **k):
        starts.append(float(th[ALL_INDEX["b_l"]]))
        out = th.copy()
        v = round((out[ALL_INDEX["b_l"]] - 2e-4) / 2e-5) * 2e-5 + 2e-4
        out[ALL_INDEX["b_l"]] = v
        return Fit(out, fr, N * error_of(v) ** 2)

    monkeypatch.setattr(FW, "fit_free", fake_fit)
    fit = Fit(theta_at("b_l", value), ("J_m", "b_l"), N * error_of(value) ** 2)
    out, reports = FW.rescreened(model, "backlash", fit, DiscoverSettings(**settings).validate(), lambda m: None,
                                 NOISE)
    return out, reports, starts


def test_a_fit_stopped_in_a_local_minimum_is_polished_from_the_profiles_lowest_point(monkeypatch):
    out, reports, starts = _rescreen(monkeypatch, rough, 2.4e-4)
    assert len(starts) == 1 and starts[0] == pytest.approx(2e-4, abs=3e-6)
    assert out.theta[ALL_INDEX["b_l"]] == pytest.approx(2e-4) and out.rmse(N) == pytest.approx(NOISE)
    (rep,) = reports
    assert rep["name"] == "b_l" and rep["rough"] and rep["polished_rmse_m"] == pytest.approx(NOISE)


@pytest.mark.parametrize("case", ["at the noise", "smooth optimum", "off"])
def test_nothing_is_polished_again_at_the_noise_at_a_smooth_optimum_or_when_off(monkeypatch, case):
    error_of, value, kw = {"at the noise": (rough, 2e-4, {}), "smooth optimum": (
        lambda v: 5 * smooth(v), 2e-4, {}), "off": (rough, 2.4e-4, {"rescreen_points": 0})}[case]
    out, reports, starts = _rescreen(monkeypatch, error_of, value, **kw)
    assert starts == [] and out.theta[ALL_INDEX["b_l"]] == pytest.approx(value)
    assert (reports == []) == (case != "smooth optimum")


@pytest.mark.parametrize("bad", [{"rescreen_points": 2}, {"rescreen_points": 1.5}, {"rescreen_span": 0},
                                 {"rescreen_prominence": -1.0}, {"rescreen_span": True}])
def test_rescreen_settings_are_checked(bad):
    with pytest.raises(ConfigError, match=next(iter(bad))):
        DiscoverSettings(**bad).validate()


def test_the_plants_cost_along_a_viscous_friction_at_the_truth_is_smooth():
    """The real plant: a slider viscous friction on a 1-s sweep with no noise, profiled at the truth — one minimum,
    at the truth, nothing below it — and a figure of it."""
    from toggle_id.discovery.model import Model
    from toggle_id.record import Record
    from toggle_id.simulate import PRECISE, simulate

    th = theta_at("c_B", 2000.0)
    rec = Record.from_sweep("simulation", duration=1.0)
    rec = Record(rec.t, rec.v_in, simulate(th[None], rec, PRECISE).x_B[0], sweep=rec.sweep, x_B0=rec.x_B0,
                 name="viscous")
    p = L.profile(Model(rec), th, "c_B", 0.25, 21, 0.1 * NOISE)
    assert p.minima == 1 and not p.below_fit() and p.lowest[0] == pytest.approx(2000.0)
    assert p.rmse_m < 1e-9 and np.nanmax(p.rmse) > 10 * p.prominence_m  # the valley's walls are in view
    fig = L.figure([p.to_dict()], NOISE)
    assert len(fig.axes) == 1


def test_a_profile_leaves_the_models_state_as_it_was():
    """A profile is a look, not a fit: rows that fall back to the stiff integrator do not send the later fits'
    simulations of that effect set to it (Model.stiff unchanged), so the profile cannot change the loop's path."""
    from dataclasses import replace

    from toggle_id.discovery.model import Model
    from toggle_id.record import Record
    from toggle_id.simulate import FAST, PRECISE, simulate

    rec = Record.from_sweep("simulation", duration=0.5)
    th = theta_at("tau_c", 1.0)
    rec = Record(rec.t, rec.v_in, simulate(th[None], rec, PRECISE).x_B[0], sweep=rec.sweep, x_B0=rec.x_B0,
                 name="coulomb")
    model = Model(rec, replace(PRECISE, max_steps=300, fallback=FAST), parallel=False)
    model.outputs(np.repeat(th[None], 2, axis=0))
    assert model.stiff  # the same batch marks the effect set stiff when fitted ...
    model.stiff = set()
    L.profile(model, th, "tau_c", 0.25, 5, 0.1 * NOISE)
    assert model.stiff == set()  # ... but not when profiled
