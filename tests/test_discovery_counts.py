"""A count a machine has whole (a motor's cogging repeats a whole number of times per revolution): once its effect
is accepted, the count is held at the whole number it lies near (forward.whole_counted), and the starts the loop
builds from the nominal fit with the effects so far carry it (forward.effects_on)."""
from __future__ import annotations

import numpy as np
import pytest

from toggle_id.discovery.forward import COUNTS, effects_on, whole_counted
from toggle_id.discovery.model import Model, fit_free
from toggle_id.discovery.settings import DiscoverSettings
from toggle_id.effects import ALL_INDEX, EFFECTS_BY_NAME
from toggle_id.params import ASSIGNED
from toggle_id.record import Record
from toggle_id.simulate import PRECISE, extend, simulate

COGGING = EFFECTS_BY_NAME["cogging_torque"].names  # a_cog, n_cog, phi_cog


def test_the_effects_so_far_carry_a_held_count():
    nominal = ("K_t", "R_s")
    # the count held (not free): still the cogging's, so a start from the nominal fit with the effects carries it
    assert set(effects_on(nominal + ("a_cog", "phi_cog"), nominal)) == set(COGGING)
    assert effects_on(nominal + COGGING, nominal) == list(COGGING)
    assert effects_on(nominal + ("c_B",), nominal) == ["c_B"]  # an effect of one parameter: itself
    assert effects_on(nominal, nominal) == []
    assert set(COUNTS) <= set(COGGING)


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


def test_a_count_near_a_whole_number_is_held_there(cogging_record):
    truth, rec = cogging_record
    model = Model(rec, parallel=False)
    start = truth.copy()
    start[ALL_INDEX["n_cog"]] = 6.04
    s = DiscoverSettings()
    loose = fit_free(model, start, COGGING, 5, s.fd_rel_step)  # a short polish: the count still off the whole
    said: list[str] = []
    held, report = whole_counted(model, "cogging_torque", loose, s, said.append)
    assert "n_cog" not in held.free and set(held.free) == {"a_cog", "phi_cog"}
    assert held.theta[ALL_INDEX["n_cog"]] == 6.0
    assert report["n_cog"]["held_at"] == 6 and report["n_cog"]["fitted"] == pytest.approx(loose.theta[ALL_INDEX["n_cog"]])
    assert report["n_cog"]["rmse_held_m"] == pytest.approx(held.rmse(model.n))
    assert held.rmse(model.n) < 1e-8  # held at the truth's count, the rest polished back to it
    assert len(said) == 1 and "held at 6" in said[0]


def whole_count_of(fit):
    from toggle_id.discovery.periodic import whole_count
    return whole_count(fit.theta[ALL_INDEX["n_cog"]], DiscoverSettings().cogging_whole_tol)


def test_a_count_far_from_a_whole_number_stays_free(cogging_record):
    truth, rec = cogging_record
    model = Model(rec, parallel=False)
    start = truth.copy()
    start[ALL_INDEX["n_cog"]] = 6.4
    s = DiscoverSettings()
    fit = fit_free(model, start, COGGING, 1, s.fd_rel_step)
    assert whole_count_of(fit) is None
    same, report = whole_counted(model, "cogging_torque", fit, s, lambda _: None)
    assert same is fit and report == {}  # judged at the end (toggle_plant.implausible), not held
    # an effect without a count: nothing to hold
    same, report = whole_counted(model, "viscous_friction_slider", fit, s, lambda _: None)
    assert same is fit and report == {}
