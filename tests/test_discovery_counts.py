"""A count a machine has whole (a motor's cogging repeats a whole number of times per revolution): once its effect
is accepted near a whole count, the count is held there (periodic.whole_counts, the polish's ``hold``), and the
starts the loop builds from the nominal fit with the effects so far carry it (forward.effects_on)."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from toggle_id.discovery import forward as FW
from toggle_id.discovery import periodic as P
from toggle_id.discovery.model import Model, fit_free
from toggle_id.discovery.settings import DiscoverSettings
from toggle_id.effects import ALL_INDEX, EFFECTS_BY_NAME
from toggle_id.params import ASSIGNED
from toggle_id.record import Record
from toggle_id.simulate import PRECISE, extend, simulate

COGGING = EFFECTS_BY_NAME["cogging_torque"].names  # a_cog, n_cog, phi_cog
TOL = DiscoverSettings().cogging_whole_tol


def test_the_effects_so_far_carry_a_held_count():
    nominal = ("K_t", "R_s")
    # the count held (not free): still the cogging's, so a start from the nominal fit with the effects carries it
    assert set(FW.effects_on(nominal + ("a_cog", "phi_cog"), nominal)) == set(COGGING)
    assert FW.effects_on(nominal + COGGING, nominal) == list(COGGING)
    assert FW.effects_on(nominal + ("c_B",), nominal) == ["c_B"]  # an effect of one parameter: itself
    assert FW.effects_on(nominal, nominal) == []
    assert set(P.COUNTS) <= set(COGGING)


@pytest.mark.parametrize("n_cog, free, expected", [
    (6.035, COGGING, {"n_cog": 6}),
    (5.95, COGGING, {"n_cog": 6}),
    (4.56, COGGING, {}),  # no whole count: left free, judged at the end (toggle_plant.implausible)
    (6.035, ("a_cog", "phi_cog"), {}),  # held already
])
def test_a_count_near_a_whole_number_is_held_there(n_cog, free, expected):
    theta = extend(ASSIGNED)[0]
    theta[ALL_INDEX["n_cog"]] = n_cog
    assert P.whole_counts("cogging_torque", theta, free, TOL) == expected
    assert P.whole_counts("viscous_friction_slider", theta, ("c_B",), TOL) == {}  # no count at all


@pytest.fixture(scope="module")
def cogging_record():
    """One second of the paper's sweep from the assigned machine with a cogging of 6 per revolution, no noise."""
    th = extend(ASSIGNED)[0]
    for nm, v in {"a_cog": 0.3, "n_cog": 6.0, "phi_cog": 0.5}.items():
        th[ALL_INDEX[nm]] = v
    rec = Record.from_sweep("simulation", duration=1.0)
    rec = Record(rec.t, rec.v_in, simulate(th[None], rec, PRECISE).x_B[0], sweep=rec.sweep, x_B0=rec.x_B0,
                 name="cogging")
    return th, rec


def test_the_polish_holds_the_count_where_the_step_put_it(cogging_record):
    """The real plant: a refit of the cogging at n_cog 6.04, polished with the count held — the count stays at 6, is
    no longer free, and the rest is polished back to the truth; the log says so."""
    truth, rec = cogging_record
    model = Model(rec, parallel=False)
    s = DiscoverSettings()
    start = truth.copy()
    start[ALL_INDEX["n_cog"]] = 6.04
    refit = fit_free(model, start, ("a_cog", "phi_cog"), 1, s.fd_rel_step)
    refit.free = COGGING
    hold = P.whole_counts("cogging_torque", refit.theta, refit.free, TOL)
    said: list[str] = []
    out = FW._polish_with_effect(model, SimpleNamespace(name="cogging_torque", fit=refit), truth, (), s, said.append,
                                 hold=hold)
    assert hold == {"n_cog": 6} and "n_cog" not in out.free and set(out.free) == {"a_cog", "phi_cog"}
    assert out.theta[ALL_INDEX["n_cog"]] == 6.0
    assert out.rmse(model.n) < 1e-8 < refit.rmse(model.n)
    assert any("n_cog 6.04 held at 6" in line for line in said)


def test_the_report_says_where_a_count_was_held():
    from toggle_id.discovery.model import Fit
    from toggle_id.discovery.report import DiscoveryResult, summary_text

    th = extend(ASSIGNED)[0]
    added = {"name": "cogging_torque", "std_errors": {"a_cog": 1e-4}, "p_value": 1e-9, "delta_bic": -40.0,
             "magnitude": {"name": "a_cog", "value": 0.0057, "unit": "N·m"},
             "held_whole": {"n_cog": {"fitted": 6.035, "held_at": 6, "rmse_free_m": 2.972e-6,
                                      "rmse_held_m": 2.952e-6}}}
    res = DiscoveryResult("rec", 100, Fit(th, (), 1e-10), Fit(th, (), 5e-11), [added], [], [], {}, {},
                          np.zeros(100), np.zeros(100), None, "", False, 1.0, 10)
    text = summary_text(res)
    assert "added cogging_torque: a_cog = 0.0057 N·m" in text
    assert ("n_cog held at 6, a whole count per revolution, from the step that added it (its refit had 6.035 at "
            "2.972 µm; polished with it held, 2.952 µm)") in text
