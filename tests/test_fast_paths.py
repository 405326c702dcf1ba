"""The fast method's paths (toggle_id/fast.py ``paths``): several of stage 1's finalists carried through stage 2 and
the joint polish, the lowest whole-record error winning."""
from __future__ import annotations

import numpy as np
import pytest

from toggle_id import params as P
from toggle_id.errors import ConfigError
from toggle_id.fast import FastSettings, identify_fast
from toggle_id.simulate import extend
from toggle_id.app.records import build_record


@pytest.fixture(scope="module")
def record():
    return build_record({"source": "simulated", "sweep": "experiment", "duration": 1.0, "params": {},
                         "effects": {}, "noise_m": 1e-6, "noise_seed": 4})[0]


SMALL = dict(starts=4, starts_stage2=2, first_nfev=3, finalists=2, final_nfev=10, joint_final_nfev=5,
             short_samples_per_param=0.0, searches=1)  # no automatic paths: the tests set them


def test_the_chosen_path_has_the_lowest_whole_record_error_and_one_path_is_the_default_method(record):
    two = identify_fast([record], extend(P.ASSIGNED)[0], seed=1, fast=FastSettings(**SMALL, paths=2),
                        identifiability=False)
    info = two.stages[-1].polish["paths"]
    assert len(info["whole_record_sse_m2"]) == 2
    assert info["whole_record_sse_m2"][info["chosen"] - 1] == min(info["whole_record_sse_m2"])
    assert two.stages[-1].sse == pytest.approx(min(info["whole_record_sse_m2"]), rel=1e-12)
    # stage 1 reports the finalist the chosen path started from
    finals = two.stages[0].polish["multistart"]["final_sse_m2"]
    assert two.stages[0].sse == pytest.approx(finals[info["chosen"] - 1], rel=1e-12)
    one = identify_fast([record], extend(P.ASSIGNED)[0], seed=1, fast=FastSettings(**SMALL, paths=1),
                        identifiability=False)
    assert "paths" not in one.stages[-1].polish
    # every path's simulations are counted: the last stage holds those of the path not chosen
    assert info["n_simulations_other_paths"] > 0
    assert two.n_simulations == sum(st.n_simulations for st in two.stages) > one.n_simulations
    # the first path is the single-path method: with two paths the result is never worse
    assert two.stages[-1].sse <= one.stages[-1].sse * (1 + 1e-12)
    if info["chosen"] == 1:
        np.testing.assert_array_equal(two.theta, one.theta)


def test_an_early_clamp_takes_more_paths(record):
    """The experiment sweep clamps after 79 samples: 13 parameters have fewer than 10 samples each in stage 1, so
    ``paths_short`` of its finalists go on (the finalists raised to as many)."""
    said = []
    res = identify_fast([record], extend(P.ASSIGNED)[0], seed=1, identifiability=False, progress=said.append,
                        fast=FastSettings(**{**SMALL, "short_samples_per_param": 10.0, "paths_short": 3}))
    assert any("3 paths" in m for m in said)
    assert len(res.stages[0].polish["multistart"]["final_sse_m2"]) == 3
    assert len(res.stages[-1].polish["paths"]["whole_record_sse_m2"]) == 3
    long_enough = identify_fast([record], extend(P.ASSIGNED)[0], seed=1, identifiability=False,
                                fast=FastSettings(**{**SMALL, "short_samples_per_param": 1.0, "paths_short": 3}))
    assert "paths" not in long_enough.stages[-1].polish


@pytest.mark.parametrize("bad,msg", [({"short_samples_per_param": -1.0}, "fast.short_samples_per_param"),
                                     ({"paths": 2, "route": "one_stage"}, "needs route two_stage"),
                                     ({"paths": 0}, "fast.paths"), ({"paths_short": 0}, "fast.paths_short")])
def test_paths_are_checked(bad, msg):
    with pytest.raises(ConfigError, match=msg):
        FastSettings(**bad).validate()
