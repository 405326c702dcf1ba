"""The discovery loop's model: the exact symmetries of x_B (gauge) and the effects' domains in it, Broyden updates,
the stiff fallback's memory and the cache of batches."""
from __future__ import annotations

import numpy as np
import pytest

from toggle_id import discovery as D
from toggle_id.effects import ALL_INDEX
from toggle_id.errors import ConfigError
from toggle_id.params import ASSIGNED, PARAM_NAMES
from toggle_id.record import Record
from toggle_id.simulate import PRECISE, extend, simulate

from discovery_cases import FAST


# ---------------------------------------------------------------------------------------------- the model
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


def test_the_gauge_holds_a_widened_magnitude_to_its_side_not_to_the_librarys_domain():
    """A slider viscous friction inside the library's domain in a gauge at 0.8 times the reference scale reads 1.25
    times more there, beyond the domain: gauge_fix refuses that representative, unless the loop widened the
    magnitude's domain (``widened``), where it is applied with the output unchanged."""
    from toggle_id.discovery.gauge import _scale, gauge_fix

    ref = extend(ASSIGNED)[0]
    theta = ref.copy()
    _scale(theta, 0.8, 1.0)
    theta[ALL_INDEX["c_B"]] = 9000.0
    rec = Record.from_sweep("simulation", 1.0, name="gauge")
    rec.x_B = np.zeros(rec.n)  # outputs only; never fitted
    model = D.Model(rec, PRECISE)
    free = (*PARAM_NAMES, "c_B")
    _, info = gauge_fix(model, theta, free, ref)
    assert not info["applied"] and "feasible domain" in info["note"]
    moved, info = gauge_fix(model, theta, free, ref, widened=("c_B",))
    assert info["applied"], info
    assert info["mechanical_scale"] == pytest.approx(1.25, rel=1e-9)
    assert moved[ALL_INDEX["c_B"]] == pytest.approx(11250.0, rel=1e-9)


def test_broyden_update_meets_the_secant_condition_and_changes_the_jacobian_least_in_scaled_coordinates():
    """discover.jacobian_reuse's update (derivatives.broyden), against its definition: the updated Jacobian maps
    the step onto the residual's change; it differs from the old one by a rank-one term whose row space is the scaled step,
    so a direction orthogonal to the step (scaled) is mapped as before; on a linear residual started from the true
    Jacobian it stays exact; a zero step gives None."""
    from toggle_id.discovery.derivatives import broyden

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


def test_a_screening_fit_runs_in_its_tier_and_reports_the_sse_of_the_residuals_own(monkeypatch):
    """discover.screen_tier=jacobian: a scout's polish simulates every residual and difference in the screening
    integrator (one consistent problem), then its end point once in the model's own tier, whose whitened SSE the
    fit reports (comparable with every other fit's) beside the screening tier's; an unknown tier is one line."""
    from discovery_cases import make_record
    from toggle_id.discovery import DiscoverSettings, Model, fit_free
    from toggle_id.simulate import JACOBIAN, PRECISE

    rec, truth, start = make_record({"x_off": 3e-5}, 0.5)
    model, start = Model(rec), extend(start)[0]
    seen = []
    real = Model._simulated

    def spy(self, plant, settings):
        seen.append((settings.rtol, plant.shape[0]))
        return real(self, plant, settings)

    monkeypatch.setattr(Model, "_simulated", spy)
    screen = DiscoverSettings(screen_tier="jacobian").screen
    assert screen[0] is JACOBIAN and DiscoverSettings().screen is None
    free = ("K_t", "x_off")
    fit = fit_free(model, start, free, 8, screen=screen)
    tiers = [rtol for rtol, _ in seen]
    assert set(tiers[:-1]) <= {JACOBIAN.rtol, JACOBIAN.fallback.rtol} and tiers[-1] == PRECISE.rtol
    assert fit.sse == pytest.approx(float(np.sum(model.fit_residuals(fit.theta[None, :])[0] ** 2)), rel=1e-12)
    assert fit.info["screen_tier_sse"] != fit.sse and fit.sse < fit.info["sse_before"]
    assert fit.sse == pytest.approx(fit.info["screen_tier_sse"], rel=1e-3)  # the tiers differ by integration error
    seen.clear()
    plain = fit_free(model, start, free, 8, coarse=False)
    assert {rtol for rtol, _ in seen} == {PRECISE.rtol} and plain.sse == pytest.approx(fit.sse, rel=0.05)
    with pytest.raises(ConfigError, match="discover.screen_tier must be one of jacobian, precise, got 'fast'"):
        DiscoverSettings(screen_tier="fast").validate()


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


def test_effect_values_carried_to_a_start_at_other_scales_keep_x_B():
    """gauge.carried: effect values fitted at one point, carried to another whose mechanism and current sit at other
    scales, read there as the same effect — a force, torque or damping with the mechanism, the drive limit with the
    current, c_kt with its square, a delay as it is — so the start with them simulates the same x_B as the point
    they were fitted at, where the start is that point's symmetric image."""
    from toggle_id.discovery.gauge import _scale, carried

    rng = np.random.default_rng(12)
    start = extend(ASSIGNED * np.exp(0.3 * rng.standard_normal(len(PARAM_NAMES))))[0]
    truth = {"c_B": 900.0, "tau_c": 0.05, "s_sat": 0.17, "c_kt": 1e-6, "tau_d": 1e-3}
    at = start.copy()
    for nm, v in truth.items():
        at[ALL_INDEX[nm]] = v
    _scale(at, 0.3, 2.5)  # the point the values were fitted at: the mechanism ×0.3, the current ×2.5
    fitted = {nm: float(at[ALL_INDEX[nm]]) for nm in truth}
    assert fitted["c_B"] == pytest.approx(270.0) and fitted["tau_d"] == 1e-3  # (moved, and not)
    back = carried(fitted, start, at)
    assert back == pytest.approx(truth, rel=1e-9)
    rec = Record.from_sweep("simulation", 1.0, name="carried")
    rec.x_B = np.zeros(rec.n)  # outputs only
    with_values = start.copy()
    for nm, v in back.items():
        with_values[ALL_INDEX[nm]] = v
    y = D.Model(rec, PRECISE).outputs(np.array([at, with_values, _with_values(start, fitted)]))
    assert np.all(np.isfinite(y)) and np.max(np.abs(y[0] - y[1])) < 1e-7  # the adaptive steps' tolerance
    assert np.max(np.abs(y[0] - y[2])) > 1e-5  # carried unchanged, they are another effect
    bad = start.copy()
    bad[ALL_INDEX["D"]] = 0.0  # a scale that cannot be read: the values as they are
    assert carried(fitted, bad, at) == fitted


def test_the_domains_make_room_for_a_start_at_a_larger_scale():
    """gauge.domains_at: the effects' domains in one point's gauge widened to hold at another point's scales too (a
    force's domain divided by the factor its value is carried by, the wider of the two; a length as it is);
    domains_of_start does so inside a block only; refit.room_for keeps the room where a find from another start lies
    outside the domains, and leaves them as they are where it does not."""
    from types import SimpleNamespace

    from toggle_id.discovery.gauge import _scale, carried, domains_at, domains_of_start
    from toggle_id.discovery.model import Fit
    from toggle_id.discovery.refit import room_for

    at = extend(ASSIGNED)[0]
    start = at.copy()
    _scale(start, 4.0, 0.5)  # its mechanism at 4 times, its current at half the scale of ``at``
    bounds = {"c_B": (0.0, 581.0), "x_off": (-5e-3, 5e-3), "s_sat": (0.0, 1.0)}
    wide = domains_at(bounds, start, at)
    assert wide["c_B"] == pytest.approx((0.0, 4 * 581.0)) and wide["x_off"] == bounds["x_off"]
    assert wide["s_sat"] == pytest.approx((0.0, 1.0))  # (its domain there, 0.5, is narrower: the wider kept)
    assert carried({"c_B": 581.0}, start, at)["c_B"] == pytest.approx(wide["c_B"][1])  # the edge carried is the edge
    model = SimpleNamespace(gauge_bounds=dict(bounds))
    with domains_of_start(model, start, at):
        assert model.gauge_bounds == wide
    assert model.gauge_bounds == bounds
    model = SimpleNamespace(gauge_bounds=dict(bounds), domains=lambda: model.gauge_bounds)
    inside = Fit(_with_values(start, {"c_B": 500.0}), ("mu", "c_B"), 1.0)
    room_for(model, inside, at)
    assert model.gauge_bounds == bounds
    outside = Fit(_with_values(start, {"c_B": 2000.0}), ("mu", "c_B"), 1.0)
    room_for(model, outside, at)
    assert model.gauge_bounds["c_B"] == pytest.approx((0.0, 4 * 581.0))


def _with_values(theta: np.ndarray, values: dict) -> np.ndarray:
    out = theta.copy()
    for nm, v in values.items():
        out[ALL_INDEX[nm]] = v
    return out


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
