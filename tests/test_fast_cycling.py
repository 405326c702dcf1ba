"""The fast method on records that clamp more than once (toggle_id/fast.py: ``route: auto``, the log draws with the
electrical time constant stratified, the searches repeated while above the record's own noise)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from toggle_id import params as P
from toggle_id.app.records import build_record
from toggle_id.errors import ConfigError
from toggle_id.fast import FastSettings, _draw, difference_noise, fast_route, identify_fast
from toggle_id.plant import GEOMETRY
from toggle_id.record import Record
from toggle_id.simulate import extend, simulations_run
from toggle_id.stages import stage_bounds

X_BL = GEOMETRY.x_B_L


def _simulated(**kw) -> Record:
    data = {"source": "simulated", "duration": 5.0, "params": {}, "effects": {}, "noise_m": 1e-6, "noise_seed": 2}
    return build_record({**data, **kw})[0]


@pytest.fixture(scope="module")
def cycling():
    return _simulated(command="cycling")


@pytest.fixture(scope="module")
def sweep():
    return _simulated(duration=1.0)


def test_clamp_count_counts_closings_not_the_jitter_of_a_held_clamp(cycling, sweep):
    assert sweep.clamp_count(X_BL) == 1
    assert cycling.clamp_count(X_BL) == 3  # four cycles in 5 s, one of which stops short of the clamp
    t = np.arange(9) * 1e-3
    jitter = Record(t=t, v_in=np.zeros(9), x_B=X_BL + np.array([-5, -1, 0.1, -0.2, 0.1, -0.3, 0.2, -0.4, 0.1]) * 1e-3)
    assert jitter.clamp_count(X_BL) == 1          # dips of less than 1 mm do not reopen it
    assert jitter.clamp_count(X_BL, release=1e-4) == 4
    never = Record(t=t, v_in=np.zeros(9), x_B=np.full(9, 0.02))
    assert never.clamp_count(X_BL) == 0


def test_the_automatic_route_follows_the_clamps(cycling, sweep):
    assert fast_route([sweep], "auto") == ("two_stage", [1])
    assert fast_route([cycling], "auto") == ("one_stage", [3])
    assert fast_route([sweep, cycling], "auto")[0] == "one_stage"  # one stage for all when any record clamps again
    never = Record(t=sweep.t[:50], v_in=sweep.v_in[:50], x_B=sweep.x_B[:50])  # 50 ms: no clamp yet
    assert fast_route([never], "auto")[0] == "one_stage"
    assert fast_route([cycling], "two_stage")[0] == "two_stage" and fast_route([sweep], "one_stage")[0] == "one_stage"


def test_uniform_draws_are_the_gas_law_bit_for_bit():
    lo, hi = stage_bounds(list(P.PARAM_NAMES), None)
    got = _draw(np.random.default_rng(7), 5, lo, hi)
    want = lo + (hi - lo) * np.random.default_rng(7).random((5, lo.size))
    np.testing.assert_array_equal(got, want)


def test_log_draws_cover_the_top_decades_and_stratify_the_electrical_time_constant():
    names = list(P.PARAM_NAMES)
    lo, hi = stage_bounds(names, None)
    k, decades, tau = 40, 3.0, (1e-3, 1.0)
    X = _draw(np.random.default_rng(1), k, lo, hi, law="log", names=names, decades=decades, tau_e_s=tau)
    assert np.all(X >= lo) and np.all(X <= hi)
    others = [i for i, n in enumerate(names) if n != "R_s"]
    assert np.all(X[:, others] >= hi[others] * 10 ** -decades)
    # log-uniform: the decades of each parameter are about equally filled (k = 40 over 3 decades)
    top = np.mean(X[:, others] >= hi[others] / 10, axis=0)
    assert np.all((top > 0.1) & (top < 0.6))
    iL, iR = names.index("L_q"), names.index("R_s")
    t_e = X[:, iL] / X[:, iR]
    unclipped = X[:, iR] < hi[iR]
    strata = np.floor((np.log(t_e) - np.log(tau[0])) / (np.log(tau[1]) - np.log(tau[0])) * k).astype(int)
    assert len(set(strata[unclipped])) == unclipped.sum()  # one start per stratum of log τ_e
    assert unclipped.sum() >= k // 2
    # the same stream gives the same draws
    np.testing.assert_array_equal(X, _draw(np.random.default_rng(1), k, lo, hi, law="log", names=names,
                                           decades=decades, tau_e_s=tau))


def test_the_noise_is_read_off_the_records_differences(cycling, sweep):
    assert difference_noise([cycling]) == pytest.approx(1e-6, rel=0.12)
    assert difference_noise([sweep]) == pytest.approx(1e-6, rel=0.12)
    slow = _simulated(duration=1.0, noise_ar=0.9)
    assert difference_noise([slow]) < 0.5e-6  # correlated noise reads low: the method then only searches more


@pytest.mark.parametrize("bad", [{"route": "three"}, {"draw": "normal"}, {"draw_decades": 0}, {"tau_e_s": [1.0, 0.1]},
                                 {"tau_e_s": [0.001]}, {"searches": 0}, {"floor_ratio": 0.5},
                                 {"paths": 2, "route": "one_stage"}])
def test_the_new_settings_are_checked(bad):
    with pytest.raises(ConfigError, match="fast\\."):
        FastSettings(**bad).validate()


TINY = dict(starts=3, first_nfev=2, finalists=1, final_nfev=4)


def test_searches_repeat_while_above_the_noise_and_the_lowest_wins(sweep):
    said = []
    n0 = simulations_run()
    res = identify_fast([sweep], extend(P.ASSIGNED)[0], seed=2, identifiability=False, progress=said.append,
                        fast=FastSettings(route="one_stage", searches=3, floor_ratio=1.0, **TINY))
    spent = simulations_run() - n0
    info = res.stages[-1].polish["searches"]
    whole = info["whole_record_sse_m2"]
    assert len(whole) == 3 and info["chosen"] - 1 == int(np.argmin(whole))  # tiny budgets: never at the floor
    assert res.stages[-1].sse == pytest.approx(min(whole), rel=1e-12)
    assert info["noise_m"] == pytest.approx(difference_noise([sweep]))
    assert sum(m.startswith("search ") for m in said) == 3  # two more searches, and the choice
    # every search's simulations are counted, and the curve never loses the best
    # (not a search's: the result's whole-record check and one simulation per point of the curve)
    assert res.n_simulations == spent - 1 - len(res.curve)
    assert res.curve[-1].rmse_m == pytest.approx(math.sqrt(min(whole) / sweep.n), rel=1e-6)
    once = identify_fast([sweep], extend(P.ASSIGNED)[0], seed=2, identifiability=False,
                         fast=FastSettings(route="one_stage", searches=3, floor_ratio=1e6, **TINY))
    assert "searches" not in once.stages[-1].polish  # at "the floor" at once: one search
    assert once.stages[-1].sse == pytest.approx(whole[0], rel=1e-12)  # the first search is the one-search method


@pytest.mark.slow
def test_a_cycling_record_of_a_machine_far_from_the_assigned_values_is_fitted_to_its_noise():
    """On the cycling command the fast method's stage 1 sees 146–191 samples and its whole-record polish ended at
    18–35 µm (σ = 1 µm); one stage from log draws, searched again while above the noise, reaches the floor.
    The machine is adversarial record rec45's (its 15 parameters 15–40 % off the assigned values), no effect."""
    truth = {"B_m": 0.0117, "D": 20200.0, "J_m": 3.02e-05, "K_i": 117.0, "K_l": 7.04e7, "K_t": 0.36, "L_q": 0.00122,
             "R_s": 0.00747, "m_2": 1.85, "m_3": 1.19, "m_5": 0.524, "m_B": 7.82, "m_C": 3.47, "mu": 0.143,
             "lambda_d": 0.0307}  # rec45's, to three digits
    rec = _simulated(command="cycling", params=truth, noise_seed=5)
    res = identify_fast([rec], extend(P.ASSIGNED)[0], seed=0, identifiability=False)
    assert [s.name for s in res.stages] == ["one_stage"]
    assert res.rmse_m < 1.1e-6, res.stages[-1].polish.get("searches")
