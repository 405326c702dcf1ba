"""The catch-all check (toggle_id.discovery.catchall): an accepted effect that a generic slider force makes
unnecessary is compensating; nothing changes when that force is not supported. The generic force's kernel term
is tested against the library forces it can take the shape of in tests/test_kernels.py."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from toggle_id.discovery import catchall
from toggle_id.discovery.model import Fit
from toggle_id.discovery.settings import DiscoverSettings
from toggle_id.effects import ALL_INDEX, GENERIC_FORCE, EFFECTS_BY_NAME
from toggle_id.kernels import slots as K
from toggle_id.simulate import extend
from toggle_id.params import ASSIGNED


@dataclass
class _Verdict:
    passed: bool
    reason: str = "judged"

    def to_dict(self) -> dict:
        return {"passed": self.passed, "reason": self.reason}


class _Judge:
    """Supports a larger model when the smaller one's SSE exceeds it by more than ``margin``."""

    def __init__(self, margin: float) -> None:
        self.margin = margin
        self.pairs: list[tuple[Fit, Fit]] = []

    def judge_pair(self, small: Fit, large: Fit) -> _Verdict:
        self.pairs.append((small, large))
        return _Verdict(small.sse - large.sse > self.margin)


@dataclass
class _Model:
    n: int = 100


STATES = {"x_B": np.linspace(0.02, 0.07, 50), "xdot_B": np.sin(np.linspace(0, 6, 50))}


def test_the_knots_span_the_records_speed_and_position():
    k = catchall.knots_of(STATES)
    assert k["gx_lo"] == pytest.approx(0.02) and k["gx_hi"] == pytest.approx(0.07)
    assert k["gv_lo"] == pytest.approx(STATES["xdot_B"].min()) and k["gv_hi"] == pytest.approx(1.0, abs=1e-3)
    assert set(catchall.WEIGHTS) == {f"{p}_w{i}" for p in ("gv", "gx") for i in range(K.N_GEN)} - {"gx_w0"}
    assert not set(catchall.WEIGHTS) & {"gv_lo", "gv_hi", "gx_lo", "gx_hi"}
    with pytest.raises(ValueError, match="not finite"):
        catchall.knots_of({"x_B": np.array([0.01, np.nan]), "xdot_B": np.zeros(2)})


def _run(monkeypatch, generic_sse: float, without_sse: dict[str, float], alone_sse: dict[str, float],
         margin: float = 1.0):
    """catch_all on a final model of SSE 10 with a constant load force and a cogging torque accepted; the fit with
    the generic force reaches ``generic_sse``; without effect a, ``without_sse[a]`` with the generic force and
    ``alone_sse[a]`` without it. The judge supports a larger model whose SSE is lower by more than ``margin``."""
    theta = extend(ASSIGNED)[0]
    current = Fit(theta, ("K_t", "F_load", "a_cog"), 10.0)

    def fake_fit(model, start, free, *a, **k):
        assert set(catchall.WEIGHTS) <= set(free)  # the weights are fitted, the knots are set from the record
        assert start[ALL_INDEX["gx_lo"]] == pytest.approx(0.02) and start[ALL_INDEX["gx_hi"]] == pytest.approx(0.07)
        return Fit(start, tuple(free), generic_sse)

    monkeypatch.setattr(catchall, "fit_free", fake_fit)
    added = [{"name": "constant_load_force"}, {"name": "cogging_torque"}]
    said = []

    def without(fit, a):
        if fit is current:
            return Fit(fit.theta, (), alone_sse[a["name"]])
        assert fit.free == current.free + catchall.WEIGHTS  # refitted in full: the model and the generic force
        return Fit(fit.theta, tuple(nm for nm in fit.free if nm not in EFFECTS_BY_NAME[a["name"]].names),
                   without_sse[a["name"]])

    kept, comp, report = catchall.catch_all(_Model(), _Judge(margin), current, added, STATES, without,
                                            DiscoverSettings(), said.append)
    return kept, comp, report, said


def test_an_effect_the_generic_force_makes_unnecessary_is_compensating(monkeypatch):
    # the generic force takes over the load force's work (SSE unchanged without it), not the cogging torque's
    kept, comp, report, said = _run(monkeypatch, 2.0, {"constant_load_force": 2.1, "cogging_torque": 9.0},
                                    {"constant_load_force": 30.0, "cogging_torque": 16.0})
    assert [a["name"] for a in kept] == ["cogging_torque"]
    assert [c["name"] for c in comp] == ["constant_load_force"]
    assert "generic force on slider B" in comp[0]["reason"] and "outside the library" in comp[0]["reason"]
    assert report["supported"] and report["effects"]["constant_load_force"]["needed"] is False
    assert report["effects"]["cogging_torque"]["needed"] is True
    assert report["effects"]["cogging_torque"]["kept_fraction"] == pytest.approx(7.0 / 6.0)
    assert any("not needed" in s for s in said)


def test_a_significant_remainder_of_a_stand_in_does_not_keep_it(monkeypatch):
    # 3 of the 20 the load force explains in the final model are left beside the generic force: significant for
    # the judge, but the generic force does 85 % of its work
    kept, comp, report, _ = _run(monkeypatch, 2.0, {"constant_load_force": 5.0, "cogging_torque": 9.0},
                                 {"constant_load_force": 30.0, "cogging_torque": 16.0})
    assert [c["name"] for c in comp] == ["constant_load_force"]
    assert report["effects"]["constant_load_force"]["kept_fraction"] == pytest.approx(0.15)
    assert report["effects"]["constant_load_force"]["evidence"]["passed"] is True


def test_an_unsupported_generic_force_decides_nothing(monkeypatch):
    kept, comp, report, said = _run(monkeypatch, 9.5, {"constant_load_force": 9.5, "cogging_torque": 9.5},
                                    {"constant_load_force": 30.0, "cogging_torque": 16.0})
    assert [a["name"] for a in kept] == ["constant_load_force", "cogging_torque"] and comp == []
    assert not report["supported"] and report["effects"] == {}
    assert "decides nothing" in said[0]


def test_the_generic_force_is_no_library_effect_and_off_by_default():
    from toggle_id.effects import EFFECTS, EXTRA_DEFAULTS
    assert GENERIC_FORCE.name not in {e.name for e in EFFECTS}
    assert not np.any(EXTRA_DEFAULTS[[ALL_INDEX[nm] - len(ASSIGNED) for nm in GENERIC_FORCE.names]])
