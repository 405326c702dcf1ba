"""The catch-all check (toggle_id.discovery.catchall): an accepted effect that a generic slider force makes
unnecessary is compensating; nothing changes when that force is not supported. The generic force's kernel term
is tested against the library forces it can take the shape of in tests/test_kernels.py."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from toggle_id.discovery import catchall
from toggle_id.discovery.model import Fit
from toggle_id.discovery.settings import DiscoverSettings
from toggle_id.discovery.timing import PhaseClock
from toggle_id.effects import ALL_INDEX, GENERIC_FORCE, EFFECTS_BY_NAME
from toggle_id.kernels import slots as K
from toggle_id.simulate import extend
from toggle_id.params import ASSIGNED


@dataclass
class _Verdict:
    """In sample (F-test, BIC) as given; the cross-validation fails, as it does for the generic force's many
    weights (catchall.SUPPORT leaves it out)."""

    passed: bool
    reason: str = "judged"

    @property
    def checks(self) -> dict:
        return {"f_test": self.passed, "bic": self.passed, "cross_validation": False}

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
class _Record:
    x_B: np.ndarray = field(default_factory=lambda: np.linspace(0.021, 0.069, 100))


@dataclass
class _Noise:
    a: tuple = ()


@dataclass
class _Model:
    """What the check and the plant read of a model: its size, record and the state its fits depend on
    (:func:`catchall.model_state`)."""

    n: int = 100
    record: _Record = field(default_factory=_Record)
    noise: _Noise = field(default_factory=_Noise)
    settings: str = "precise"
    jacobian: str = "precise"
    jacobian_step: float | None = None
    jacobian_reuse: int = 0
    derivatives: str = "fd"
    stiff: set = field(default_factory=set)
    excluded: np.ndarray | None = None
    clock: PhaseClock = field(default_factory=PhaseClock)

    def domains(self) -> dict:
        return {}


STATES = {"x_B": np.linspace(0.02, 0.07, 50), "xdot_B": np.sin(np.linspace(0, 6, 50))}


def test_the_knots_span_the_records_speed_and_position():
    k = catchall.knots_of(STATES, _Record().x_B)
    assert k["gx_lo"] == pytest.approx(0.02) and k["gx_hi"] == pytest.approx(0.07)
    assert k["gv_lo"] == pytest.approx(STATES["xdot_B"].min()) and k["gv_hi"] == pytest.approx(1.0, abs=1e-3)
    assert k["gs_lo"] == pytest.approx(0.021) and k["gs_hi"] == pytest.approx(0.069)  # the measured position's
    assert set(catchall.WEIGHTS) == ({f"{p}_w{i}" for p in ("gv", "gx") for i in range(K.N_GEN)} - {"gx_w0"}
                                     | {f"gs_w{i}" for i in range(K.N_GS)})
    assert not set(catchall.WEIGHTS) & {"gv_lo", "gv_hi", "gx_lo", "gx_hi", "gs_lo", "gs_hi"}
    with pytest.raises(ValueError, match="not finite"):
        catchall.knots_of({"x_B": np.array([0.01, np.nan]), "xdot_B": np.zeros(2)}, np.zeros(2))
    with pytest.raises(ValueError, match="not finite"):
        catchall.knots_of(STATES, np.array([0.01, np.inf]))
    at_rest = catchall.knots_of(STATES, np.full(5, 0.03))
    assert at_rest["gs_hi"] - at_rest["gs_lo"] == pytest.approx(1e-6)


def _run(monkeypatch, generic_sse: float, without_sse: dict[str, float], alone_sse: dict[str, float],
         margin: float = 1.0, reading_sse: float | None = None, added: tuple[str, ...] = ("constant_load_force",
                                                                                          "cogging_torque"),
         rivals: dict[str, list[dict]] | None = None, with_rival=None, looked: bool = False,
         share: dict[str, float | None] | None = None):
    """catch_all on a final model of SSE 10 with a constant load force and a cogging torque accepted; the fit with
    the generic force reaches ``generic_sse``, with the generic reading error beside it ``reading_sse`` (default:
    the same); without effect a, ``without_sse[a]`` with the generic terms and ``alone_sse[a]`` without them. The
    judge supports a larger model whose SSE is lower by more than ``margin``. ``rivals``: an effect's tied rivals;
    ``with_rival``: passed on; ``looked``: the check made again with the force and reading-error fits of the first
    (as the final check takes them from the second look), which must then be all it skips. ``share``: given, the
    calibrated share (``discover.catch_all_calibrated``) of each effect were it true (:func:`catchall.share_if_true`,
    asked only of an effect significant beside the generic terms that keeps less than ``catch_all_keep``); not given,
    the check runs without it."""
    theta = extend(ASSIGNED)[0]
    theta[ALL_INDEX["a_cog"]] = 0.01  # the accepted cogging torque's size
    current = Fit(theta, ("K_t", "F_load", "a_cog"), 10.0)
    fitted = []

    def fake_fit(model, start, free, *a, **k):
        # the weights are fitted, the knots are set from the record
        assert set(free) & set(catchall.WEIGHTS) and set(free) - set(catchall.WEIGHTS) <= set(current.free)
        assert start[ALL_INDEX["gx_lo"]] == pytest.approx(0.02) and start[ALL_INDEX["gx_hi"]] == pytest.approx(0.07)
        fitted.append(tuple(free))
        with_reading = set(catchall.SENSOR_WEIGHTS) <= set(free) or np.any(start[K.GS_W0:K.GS_W0 + K.N_GS])
        sse = reading_sse if with_reading and reading_sse is not None else generic_sse
        out = start.copy()
        if with_reading and reading_sse is not None:
            out[K.GS_W0:K.GS_W0 + K.N_GS] = 1e-6 * np.cos(np.arange(K.N_GS))  # a fitted reading error
        return Fit(out, tuple(free), sse)

    monkeypatch.setattr(catchall, "fit_free", fake_fit)
    added = [{"name": nm, **({"indistinguishable_from": rivals[nm]} if nm in (rivals or {}) else {})}
             for nm in added]
    said = []

    def without(fit, a):
        if fit is current:
            return Fit(fit.theta, (), alone_sse[a["name"]])
        # refitted in full: the model and the generic terms (the reading error only where it was needed)
        assert fit.free == current.free + (catchall.WEIGHTS if reading_sse is not None and generic_sse - reading_sse
                                           > margin else catchall.FORCE_WEIGHTS)
        return Fit(fit.theta, tuple(nm for nm in fit.free if nm not in EFFECTS_BY_NAME[a["name"]].names),
                   without_sse[a["name"]])

    store: dict = {}
    asked: list[str] = []

    def share_if_true(model, fit, a, knots, weights, settings):
        assert knots == catchall.knots_of(STATES, model.record.x_B)
        if fit is not current:  # a tied rival: the final model with it in its effect's place
            tied = next(b for b in added if a in b.get("indistinguishable_from", ()))
            names = EFFECTS_BY_NAME[tied["name"]].names
            assert fit.free == tuple(nm for nm in current.free if nm not in names)
            assert all(fit.theta[ALL_INDEX[k]] == v for k, v in a["params"].items())
            assert fit.theta[ALL_INDEX["a_cog"]] == 0.0  # switched off
        asked.append(a["name"])
        return share[a["name"]]

    monkeypatch.setattr(catchall, "share_if_true", share_if_true)
    settings = DiscoverSettings(catch_all_calibrated=share is not None)
    kept, comp, report = catchall.catch_all(_Model(), _Judge(margin), current, added, STATES, without,
                                            settings, said.append, store, with_rival=with_rival)
    assert set(asked) <= set(share or {})
    # the force's weights, then the model with them; the reading error's weights from there, then everything
    assert fitted[:4] == [catchall.FORCE_WEIGHTS, current.free + catchall.FORCE_WEIGHTS, catchall.SENSOR_WEIGHTS,
                          current.free + catchall.WEIGHTS]
    assert store["force"].free == current.free + catchall.FORCE_WEIGHTS
    assert store["both"].free == current.free + catchall.WEIGHTS
    if looked:
        first, n_first = (kept, comp, report, said[1:]), len(fitted)
        said.clear()
        again = catchall.catch_all(_Model(), _Judge(margin), current, added, STATES, without, settings,
                                   said.append, with_rival=with_rival, looked=(store["force"], store["both"]))
        assert len(fitted) == 2 * n_first - 4 and fitted[n_first:] == fitted[4:n_first]
        assert "fitted on this model before" in said[0]
        assert (*again, said[2:]) == first  # the same verdicts, report and lines
    return kept, comp, report, said


def test_an_effect_the_generic_force_makes_unnecessary_is_compensating(monkeypatch):
    # the generic force takes over the load force's work (SSE unchanged without it), not the cogging torque's
    kept, comp, report, said = _run(monkeypatch, 2.0, {"constant_load_force": 2.1, "cogging_torque": 9.0},
                                    {"constant_load_force": 30.0, "cogging_torque": 16.0})
    assert [a["name"] for a in kept] == ["cogging_torque"]
    assert [c["name"] for c in comp] == ["constant_load_force"]
    assert "generic force on slider B" in comp[0]["reason"] and "position reading" not in comp[0]["reason"]
    assert "outside the library" in comp[0]["reason"]
    assert report["supported"] and report["effects"]["constant_load_force"]["needed"] is False
    assert report["reading_error"]["needed"] is False and report["sensor_rms_m"] == 0.0
    assert report["effects"]["cogging_torque"]["needed"] is True
    assert report["effects"]["cogging_torque"]["kept_fraction"] == pytest.approx(7.0 / 6.0)
    assert any(s.startswith("  without constant_load_force:") and s.endswith("→ not needed") for s in said)


@pytest.mark.parametrize("generic_sse, reading_sse", [(2.0, None), (2.0, 0.5)])
def test_the_final_check_takes_over_the_generic_fits_of_the_second_look(monkeypatch, generic_sse, reading_sse):
    """Given the force and reading-error fits already made on the model (``looked``), the check skips those four fits
    and nothing else, and reaches the same verdicts, report and lines."""
    _run(monkeypatch, generic_sse, {"constant_load_force": 2.1, "cogging_torque": 9.0},
         {"constant_load_force": 30.0, "cogging_torque": 16.0}, reading_sse=reading_sse, looked=True)


@pytest.mark.parametrize("rival_sse, resolved", [
    (8.0, False),    # supported (9.0 → 8.0), and keeps all of the cogging's gain 11 − 10 = 1.0: still tied
    (8.875, False),  # supported, keeps 12.5 % of it (catch_all_keep is 10 %)
    (8.93, True),    # supported (0.07 > margin 0.05), but keeps 7 %
    (8.97, True),    # not supported: the generic force does its work
])
def test_a_tie_of_a_kept_effect_is_judged_beside_the_generic_terms(monkeypatch, rival_sse, resolved):
    """A cogging torque tied with a Stribeck friction, kept beside the generic force (9.0 → 2.0 with it): the
    rival, switched on in its place there, stays tied when it is needed as the cogging is (the judge's support,
    and catch_all_keep of the gain the two share without the generic terms), and the tie is resolved for the
    cogging otherwise."""
    rival = {"name": "stribeck_friction", "params": {"F_s": 4.5, "v_s": 0.018}}
    seen = []

    def with_rival(fit, rv):
        seen.append((fit.sse, rv["name"], dict(rv["params"])))
        return Fit(fit.theta, fit.free + ("F_s", "v_s"), rival_sse)

    kept, comp, report, said = _run(monkeypatch, 2.0, {"constant_load_force": 2.1, "cogging_torque": 9.0},
                                    {"constant_load_force": 30.0, "cogging_torque": 11.0},
                                    margin=0.05, rivals={"cogging_torque": [rival]}, with_rival=with_rival)
    assert [a["name"] for a in kept] == ["cogging_torque"]
    assert seen == [(9.0, "stribeck_friction", {"F_s": 4.5, "v_s": 0.018})]  # beside the generic terms, in its place
    cog = kept[0]
    case = report["effects"]["cogging_torque"]["rivals"]["stribeck_friction"]
    assert case["needed"] is (not resolved)
    assert case["kept_fraction"] == pytest.approx(9.0 - rival_sse)
    if resolved:
        assert cog["indistinguishable_from"] == []
        assert [r["name"] for r in cog["ties_resolved"]] == ["stribeck_friction"]
        assert "stood in for part of what the library lacks" in cog["ties_resolved"][0]["reason"]
        assert said[-1].endswith("not needed: the tie is resolved for cogging_torque")
    else:
        assert [r["name"] for r in cog["indistinguishable_from"]] == ["stribeck_friction"]
        assert "ties_resolved" not in cog and said[-1].endswith("still needed: the tie stays")


@pytest.mark.parametrize("share, resolved", [(0.5, False), (0.9, True), (None, True)])
def test_a_rival_under_the_floor_is_read_against_what_a_true_rival_would_keep(monkeypatch, share, resolved):
    """The rival of the case above keeps 7 % beside the generic terms, significant: under catch_all_keep, so it is
    held to the calibrated rule the kept effect would be. A true rival of its size keeping 50 % there would keep
    less than it does beyond a tenth of that (5 %): the tie stays; 90 % (floor 9 %) or a twin that failed (None): the
    plain floor, and the tie is resolved."""
    rival = {"name": "stribeck_friction", "params": {"F_s": 4.5, "v_s": 0.018}}
    kept, _, report, said = _run(monkeypatch, 2.0, {"constant_load_force": 2.1, "cogging_torque": 9.0},
                                 {"constant_load_force": 30.0, "cogging_torque": 11.0}, margin=0.05,
                                 rivals={"cogging_torque": [rival]},
                                 with_rival=lambda fit, rv: Fit(fit.theta, fit.free + ("F_s", "v_s"), 8.93),
                                 share={"stribeck_friction": share, "constant_load_force": None})
    case = report["effects"]["cogging_torque"]["rivals"]["stribeck_friction"]
    assert case["share_if_true"] == share and case["needed"] is (not resolved)
    assert report["effects"]["cogging_torque"]["share_if_true"] is None  # kept by the plain floor, never asked
    assert (kept[0]["indistinguishable_from"] == []) is resolved
    assert ("a true one of its size" in said[-1]) is (share is not None)


def test_without_with_rival_the_ties_stay_as_they_are(monkeypatch):
    rival = {"name": "stribeck_friction", "params": {"F_s": 4.5, "v_s": 0.018}}
    kept, _, report, _ = _run(monkeypatch, 2.0, {"constant_load_force": 2.1, "cogging_torque": 9.0},
                              {"constant_load_force": 30.0, "cogging_torque": 16.0},
                              rivals={"cogging_torque": [rival]})
    assert kept[0]["indistinguishable_from"] == [rival] and "rivals" not in report["effects"]["cogging_torque"]


def test_the_named_effects_values_beside_the_generic_terms_are_reported(monkeypatch):
    """The catch-all's report gives each effect's values in the fit with the generic terms, and the conclusion
    names them beside the final model's own for the effects it adds."""
    from toggle_id.discovery.report import _conclusion

    _, comp, report, _ = _run(monkeypatch, 2.0, {"constant_load_force": 2.1, "cogging_torque": 9.0},
                              {"constant_load_force": 30.0, "cogging_torque": 16.0})
    theta = extend(ASSIGNED)[0]
    got = report["effects"]["cogging_torque"]["values_with_generic"]
    assert set(got) == {"a_cog", "n_cog", "phi_cog"} and got["n_cog"] == pytest.approx(theta[ALL_INDEX["n_cog"]])
    cog = {"name": "cogging_torque", "magnitude": {"name": "a_cog", "value": 0.0106, "unit": "N·m"}}
    after = {"rms_m": 2.95e-6, "verdict": {"structure_left": True}, "localisation": {"text": "grows with speed"}}
    text = _conclusion([cog], {"rms_m": 3.25e-6}, after, True, DiscoverSettings(), comp,
                       catch={**report, "rmse_m": 1.0e-6})
    assert f"named effects' values are cogging_torque a_cog {got['a_cog']:.4g}, n_cog {got['n_cog']:.4g}" in text
    assert "constant_load_force F_load" not in text  # compensating: not named, its values not given
    assert "neither is the effect's size" in text and "range" not in text  # not a range for the truth (rec38_d1)
    assert "named effects' values" not in _conclusion([], {"rms_m": 3.25e-6}, after, True, DiscoverSettings(), comp,
                                                      catch={**report, "rmse_m": 1.0e-6})


@pytest.mark.parametrize("reading_sse, needed", [(1.5, False), (0.5, True)])
def test_the_reading_error_joins_the_generic_force_only_where_it_is_needed_beyond_it(monkeypatch, reading_sse,
                                                                                      needed):
    # beside the force (SSE 2.0) the reading error takes the SSE to 1.5 (not significant: the judge's margin is 1)
    # or 0.5: only then is it part of the generic terms an effect is judged against
    kept, comp, report, said = _run(monkeypatch, 2.0, {"constant_load_force": 2.1, "cogging_torque": 9.0},
                                    {"constant_load_force": 30.0, "cogging_torque": 16.0}, reading_sse=reading_sse)
    assert report["reading_error"]["needed"] is needed
    assert report["reading_error"]["rmse_force_only_m"] == pytest.approx(np.sqrt(2.0 / 100))
    assert report["reading_error"]["rmse_with_it_m"] == pytest.approx(np.sqrt(reading_sse / 100))
    assert report["rmse_m"] == pytest.approx(np.sqrt((reading_sse if needed else 2.0) / 100))
    assert (report["sensor_rms_m"] > 0) is needed
    assert ("position reading" in comp[0]["reason"]) is needed
    assert ("sensor error h(x_B) beside it: " in said[0]) and (("not needed" in said[0]) is not needed)


@pytest.mark.parametrize("without_load, demoted", [(3.0, True), (5.0, False)])
def test_a_significant_remainder_keeps_an_effect_only_above_the_floor(monkeypatch, without_load, demoted):
    # the load force explains 20 in the final model; beside the generic force 1 (5 %: below catch_all_keep, a
    # polish's leftover) or 3 (15 %) — significant for the judge either way
    kept, comp, report, _ = _run(monkeypatch, 2.0, {"constant_load_force": without_load, "cogging_torque": 9.0},
                                 {"constant_load_force": 30.0, "cogging_torque": 16.0}, margin=0.5)
    assert ("constant_load_force" in [c["name"] for c in comp]) is demoted
    assert report["effects"]["constant_load_force"]["kept_fraction"] == pytest.approx((without_load - 2.0) / 20.0)
    assert report["effects"]["constant_load_force"]["evidence"]["passed"] is True


@pytest.mark.parametrize("share, demoted", [(0.04, False), (0.6, True), (None, True), (0.01, True)])
def test_a_small_share_is_read_against_what_a_true_effect_would_keep(monkeypatch, share, demoted):
    # the load force keeps 5 % of its gain (1 of 20), significant: below catch_all_keep, so the share a true load
    # force would keep beside the generic terms is asked. 4 %: they span its signature and 5 % is what a true one
    # keeps — needed; 60 %: a true one would keep twelve times more, and 5 % is below a tenth of it (catch_all_keep
    # of the share) — compensating; the twin failed (None) — the plain rule; 1 %: under catch_all_share_min (2 %),
    # the generic terms span a true one too and 5 % would pass on significance alone — the plain rule. The cogging
    # torque keeps 70 %, never asked.
    kept, comp, report, said = _run(monkeypatch, 2.0, {"constant_load_force": 3.0, "cogging_torque": 9.0},
                                    {"constant_load_force": 30.0, "cogging_torque": 20.0}, margin=0.5,
                                    share={"constant_load_force": share})
    assert ("constant_load_force" in [c["name"] for c in comp]) is demoted
    assert ("constant_load_force" in [a["name"] for a in kept]) is not demoted
    assert report["effects"]["constant_load_force"]["share_if_true"] == share
    assert report["effects"]["cogging_torque"]["share_if_true"] is None
    line = next(ln for ln in said if "without constant_load_force" in ln)
    assert ("a true one of its size" in line) is (share is not None)
    assert ("they span it, too little to tell" in line) is (share == 0.01)
    assert line.endswith("not needed" if demoted else "still needed")


def test_an_effect_not_significant_beside_the_generic_terms_is_never_calibrated(monkeypatch):
    # the load force keeps 0.5 % (0.1 of 20): not significant for the judge, so no calibration can keep it
    kept, comp, report, _ = _run(monkeypatch, 2.0, {"constant_load_force": 2.1, "cogging_torque": 9.0},
                                 {"constant_load_force": 30.0, "cogging_torque": 20.0}, margin=0.5, share={})
    assert [c["name"] for c in comp] == ["constant_load_force"]
    assert report["effects"]["constant_load_force"]["share_if_true"] is None


def test_an_unsupported_generic_force_decides_nothing(monkeypatch):
    kept, comp, report, said = _run(monkeypatch, 9.5, {"constant_load_force": 9.5, "cogging_torque": 9.5},
                                    {"constant_load_force": 30.0, "cogging_torque": 16.0})
    assert [a["name"] for a in kept] == ["constant_load_force", "cogging_torque"] and comp == []
    assert not report["supported"] and report["effects"] == {}
    assert "they decide nothing" in said[0]


def test_the_report_gives_the_forces_shape_its_figure_and_a_sentence_of_the_conclusion(monkeypatch, tmp_path):
    from toggle_id import figures
    from toggle_id.discovery.report import _conclusion

    _, comp, report, _ = _run(monkeypatch, 2.0, {"constant_load_force": 2.1, "cogging_torque": 9.0},
                              {"constant_load_force": 30.0, "cogging_torque": 16.0})
    sh = report["shape"]
    assert sh["x_m"][0] == pytest.approx(0.02) and sh["x_m"][-1] == pytest.approx(0.07) and len(sh["g_N"]) == K.N_GEN
    assert sh["xs_m"][0] == pytest.approx(0.021) and sh["xs_m"][-1] == pytest.approx(0.069)
    assert len(sh["h_m"]) == K.N_GS and report["n_knots_sensor"] == K.N_GS and report["sensor_rms_m"] == 0.0
    th = extend(ASSIGNED)[0]
    th[ALL_INDEX["gv_lo"]], th[ALL_INDEX["gv_hi"]] = -0.1, 0.8
    th[K.GV_W0:K.GV_W0 + K.N_GEN] = np.arange(K.N_GEN)
    got = catchall.shape_of(th)
    assert got["f_N"] == list(range(K.N_GEN)) and got["v_m_s"][-1] == pytest.approx(0.8)
    png = figures.save(catchall.figure(report), tmp_path / "catch_all.png")
    assert Path(png).stat().st_size > 5000
    before = {"rms_m": 3e-6}
    after = {"rms_m": 1.3e-6, "verdict": {"structure_left": True}, "localisation": {"text": "a bump"}}
    text = _conclusion([], before, after, True, DiscoverSettings(), comp, catch={**report, "rmse_m": 1.0e-6})
    assert "error of the position reading, both of unknown shape" not in text and "reading error's part" not in text
    assert "adds nothing significant beside it" in text and "1 µm" in text and "catch_all.png" in text
    needed = {**report, "rmse_m": 1.0e-6, "reading_error": {**report["reading_error"], "needed": True}}
    text = _conclusion([], before, after, True, DiscoverSettings(), comp, catch=needed)
    assert "error of the position reading, both of unknown shape" in text and "reading error's part" in text
    assert "scale error" not in text  # h is flat here: no trend to describe
    assert "a hint, not a finding" not in text
    held_out = {**needed, "reading_error": {**needed["reading_error"],
                                            "evidence": {"checks": {"cross_validation": False}}}}
    assert "a hint, not a finding" in _conclusion([], before, after, True, DiscoverSettings(), comp, catch=held_out)
    xs = np.asarray(report["shape"]["xs_m"])
    ramp = {**report["shape"], "h_m": list(5e-4 * (xs - xs[0]) + 2e-6 * np.sin(xs / 1e-3))}
    text = _conclusion([], before, after, True, DiscoverSettings(), comp,
                       catch={**needed, "shape": ramp, "sensor_trend": catchall.trend_of(ramp)})
    assert "as a scale error of 0.0005 would" in text and "rises 23.8 µm over the 48 mm measured" in text
    # not supported: the missing thing is no function of the slider's state (and nothing is said when no
    # structure is left)
    text = _conclusion([], before, after, True, DiscoverSettings(), comp, catch={**report, "supported": False})
    assert "Neither a force on slider B nor an error of the position reading" in text and "takes the error" not in text
    assert "no function of the slider's position and speed" in text and "catch_all.png" not in text
    quiet = {**after, "verdict": {"structure_left": False}}
    assert "unknown shape" not in _conclusion([], before, quiet, False, DiscoverSettings(), comp,
                                              catch={**report, "supported": False})


def test_with_nothing_accepted_the_catch_all_reports_what_kind_of_thing_is_missing(monkeypatch):
    """An unexplained record (structure left, no effect accepted, rec28 of the adversarial set): the generic terms
    are fitted for the report alone — no effect to judge, none refitted without."""
    kept, comp, report, said = _run(monkeypatch, 2.0, {}, {}, added=())
    assert kept == [] and comp == [] and report["effects"] == {}
    assert report["supported"] and report["rmse_m"] == pytest.approx(np.sqrt(2.0 / 100))
    assert "catch-all: a generic slider force" in said[0]


@pytest.mark.parametrize("left, supported, reading, kinds", [
    (False, True, False, set()), (True, False, False, set()), (True, True, False, {"slider"}),
    (True, True, True, {"slider", "reading"})])
def test_the_second_look_asks_the_catch_all_once_per_model_what_kind_of_term_is_missing(monkeypatch, left, supported,
                                                                                       reading, kinds):
    """The forward step's second look (toggle_plant.TogglePlant.missing_kinds): only with structure left; the kinds
    of library effect the supported generic terms stand in for; the report-only fits reused by the final report when
    the model is the same, never taken as the report of another model."""
    from toggle_id.discovery import toggle_plant as TP
    from toggle_id.discovery.refit import Scout

    calls = []

    def fake_catch_all(model, judge, current, added, states, without, settings, say, store=None, **k):
        calls.append(current)
        generic = Fit(current.theta, current.free + catchall.FORCE_WEIGHTS, 0.5)
        store.update(generic=generic, force=generic, both=Fit(current.theta, current.free + catchall.WEIGHTS, 0.4))
        return [], [], {"supported": supported, "reading_error": {"needed": reading}}

    monkeypatch.setattr(TP, "catch_all", fake_catch_all)
    plant = TP.TogglePlant(_Model(), None, DiscoverSettings(), extend(ASSIGNED)[0], [], (), (), [], None,
                           lambda s: None, None)
    fit, other = Fit(extend(ASSIGNED)[0], (), 1.0), Fit(extend(ASSIGNED)[0], (), 2.0)
    plant._structure = fit, (left, ({}, None, STATES))
    assert plant.missing_kinds(fit) == kinds
    assert calls == ([fit] if left else []) and plant.catch_report is None  # no report of the final model yet
    plant.describe_missing(fit, ({}, None, STATES))  # the same model: its fits reused
    assert calls == [fit] and plant.catch_report["supported"] is supported
    plant.catch_report = None
    plant.describe_missing(other, ({}, None, STATES))  # another model: fitted anew
    assert calls == [fit, other]
    # the third look (discover.beside_generic) refits beside the generic terms of the catch-all's fit of that model
    seen = []
    monkeypatch.setattr(TP, "beside_generic", lambda model, judge, base, generic, scouts, *a: seen.append(
        (base, generic.free, scouts)) or ["refit"])
    assert plant._beside(other, []) == [] and not seen  # nothing to refit
    plant._structure = other, (left, ({}, None, STATES))
    scout = Scout("cogging_torque", 1.0, None, {})
    assert plant._beside(other, [scout]) == (["refit"] if kinds else [])
    assert seen == ([(other, other.free + catchall.FORCE_WEIGHTS, [scout])] if kinds else [])


def test_the_second_looks_generic_fits_are_reused_only_on_the_same_model_in_the_same_state(monkeypatch):
    """TogglePlant: the final check (:meth:`explains`) is given the second look's force and reading-error fits only
    when they were made on the same fit (values, free names, noise model) with the model in the state it is in now —
    not after an effect set was marked stiff or the noise model changed, nor when the state changed during them."""
    from toggle_id.discovery import toggle_plant as TP

    model = _Model()
    force, both = Fit(extend(ASSIGNED)[0], ("a",), 1.0), Fit(extend(ASSIGNED)[0], ("b",), 0.5)
    grow = []

    def fake_catch_all(model_, judge, current, added, states, without, settings, say, store=None, looked=None, **k):
        if store is not None:
            store.update(generic=both, force=force, both=both)
            model.stiff.update(grow)
        fake_catch_all.looked = looked
        return list(added), [], {"supported": True, "reading_error": {"needed": True}}

    monkeypatch.setattr(TP, "catch_all", fake_catch_all)
    plant = TP.TogglePlant(model, None, DiscoverSettings(), extend(ASSIGNED)[0], [], (), (), [], None,
                           lambda s: None, None)
    fit = Fit(extend(ASSIGNED)[0], ("K_t",), 1.0)
    details = ({}, None, STATES)
    plant._structure = fit, (True, details)
    added = [{"name": "constant_load_force"}]

    def final(current):
        plant.explains(current, list(added), details, added)
        return fake_catch_all.looked

    assert plant.missing_kinds(fit) == {"slider", "reading"}
    assert final(fit) == (force, both)
    same_values = Fit(fit.theta.copy(), ("K_t",), 2.0)  # the same start and free names: the same fits
    assert final(same_values) == (force, both)
    assert final(Fit(fit.theta, ("K_t", "B_m"), 1.0)) is None  # other free names
    moved = fit.theta.copy()
    moved[0] *= 1 + 1e-12
    assert final(Fit(moved, ("K_t",), 1.0)) is None
    model.stiff.add(b"set")  # an effect set marked stiff since: the fits would run on another integrator
    assert final(fit) is None
    model.stiff.clear()
    model.noise = _Noise((0.5,))  # another noise model to minimise under
    plant.fit_noise = model.noise
    assert final(fit) is None
    # a set marked stiff during the second look's own fits: the later ones of the same fits would differ
    plant._looked, grow[:] = None, [b"other"]
    assert plant.missing_kinds(fit) == {"slider", "reading"} and plant._looked[3] is None
    assert final(fit) is None


@pytest.mark.parametrize("n_cog, without, with_it, turns, expected", [
    (6.04, (True, 6.03), (False, 6.0), 2.34, "ripple"),  # rec37: its range of 14.7 rad holds 14 periods at n = 6
    (6.04, (True, 6.03), (True, 6.02), 2.34, None),      # still there with it: it did not take it
    # not significant without it, where the missing physics' misfit may hide it (rec38): judged beside the generic
    # terms, by the catch-all check
    (6.04, (False, 6.03), (False, 6.0), 2.34, "beside"),
    (1.0, (True, 1.05), (False, 1.0), 2.34, None),   # rec01-like: a low count over 2 periods, a localised error
    (6.04, (True, 3.4), (False, 3.4), 2.34, "beside"),  # another count: not its ripple; beside the generic terms
    (6.3, (True, 6.3), (False, 6.3), 2.34, None),    # no whole count: no motor's cogging
    (6.04, (True, 6.03), (False, 6.0), 1.5, None),   # a range of 9 periods only
])
def test_a_cogging_torque_explains_where_its_ripple_shows_without_it_over_many_periods(n_cog, without, with_it, turns,
                                                                                     expected):
    """TogglePlant.own_signature: a cogging torque that removed little of the structure energy explains when the
    residual of the model without it repeats at its whole count per revolution, significantly, over at least
    signature_min_periods (10) periods of the motor angle's range, and the residual with it does not; where the
    residual without it repeats at no such count, it goes on to the catch-all check, marked hidden_ripple."""
    from toggle_id.discovery import toggle_plant as TP

    th = extend(ASSIGNED)[0].copy()
    th[ALL_INDEX["n_cog"]] = n_cog
    current, reduced = Fit(th, (), 1.0), Fit(extend(ASSIGNED)[0], (), 2.0)
    states = {"motor_angle": np.linspace(0.0, 2 * np.pi * turns, 50)}

    def fam(sig, count):
        return {"periodic": {"families": {"motor_angle": {"significant": sig, "cycles_per_revolution": count,
                                                          "repeats": f"{count} times per motor revolution"}}}}

    plant = TP.TogglePlant(_Model(), None, DiscoverSettings(), th, [], (), (), [], None, lambda m: None, None)
    plant.structure = lambda fit: (True, (fam(*(without if fit is reduced else with_it)), None, states))
    a = {"name": "cogging_torque", "_reduced": reduced}
    why = plant.own_signature(current, a)
    assert (why is not None) is (expected is not None)
    assert ("hidden_ripple" in a) is (expected == "beside")
    if expected == "ripple":
        assert "over 14 periods" in why and "explains the ripple" in why
    if expected == "beside":
        assert a["hidden_ripple"] == n_cog and "by the catch-all check" in why
    assert plant.own_signature(current, {"name": "dead_time", "_reduced": reduced}) is None


@pytest.mark.parametrize("catch_all_on, needed", [(True, True), (True, False), (False, True)])
def test_a_cogging_whose_ripple_is_hidden_is_judged_beside_the_generic_terms(monkeypatch, catch_all_on, needed):
    """TogglePlant.explains: a cogging marked hidden_ripple (own_signature) is kept or not by the catch-all check,
    like any effect it judges; without the catch-all check nothing can judge it beside the generic terms, and it is
    compensating, while another effect is kept as before."""
    from toggle_id.discovery import toggle_plant as TP

    th = extend(ASSIGNED)[0].copy()
    states = {"motor_angle": np.linspace(0.0, 2 * np.pi * 2.34, 50)}
    cog = {"name": "cogging_torque", "hidden_ripple": 6.0, "own_signature": "its ripple hidden"}
    other = {"name": "dead_time"}
    judged = []

    def fake_catch_all(model, judge, cur, added, st, without, s, say, store=None, **k):
        assert callable(k["with_rival"])  # the ties of what it keeps are judged beside the generic terms too
        judged.extend(a["name"] for a in added)
        kept = [a for a in added if needed or a["name"] != "cogging_torque"]
        return kept, [dict(a, reason="a generic force does its work") for a in added if a not in kept], {}

    monkeypatch.setattr(TP, "catch_all", fake_catch_all)
    plant = TP.TogglePlant(_Model(), None, DiscoverSettings(catch_all=catch_all_on), th, [], (), (), [], None,
                           lambda m: None, None)
    plant._fitting = lambda: None
    added, compensating = plant.explains(Fit(th, (), 1.0), [cog, other], ({}, None, states), [cog, other])
    kept = catch_all_on and needed
    assert judged == (["cogging_torque", "dead_time"] if catch_all_on else [])
    assert [a["name"] for a in added] == (["cogging_torque", "dead_time"] if kept else ["dead_time"])
    assert [c["name"] for c in compensating] == ([] if kept else ["cogging_torque"])
    if not catch_all_on:
        assert "discover.catch_all" in compensating[0]["reason"]


def test_an_effect_accepted_beside_the_generic_terms_is_judged_there_not_by_the_structure_energy():
    """TogglePlant.own_signature: an effect accepted beside the catch-all's generic terms (its evidence holds
    beside_generic) is exempt from the structure-energy split — whatever its count — and goes on to the catch-all
    check; the same effect accepted the ordinary way is not."""
    from toggle_id.discovery import toggle_plant as TP

    th = extend(ASSIGNED)[0].copy()
    th[ALL_INDEX["n_cog"]] = 4.6  # no whole count: the ripple rule alone would not keep it
    current, reduced = Fit(th, (), 1.0), Fit(extend(ASSIGNED)[0], (), 2.0)
    plant = TP.TogglePlant(_Model(), None, DiscoverSettings(), th, [], (), (), [], None, lambda m: None, None)
    beside = {"name": "cogging_torque", "_reduced": reduced,
              "evidence": {"beside_generic": {"reason": "F 80.1, BIC −60, out of sample 1.2e-8 → 9.7e-9 m²"}}}
    why = plant.own_signature(current, beside)
    assert why is not None and "beside a generic slider force" in why and "out of sample 1.2e-8" in why
    assert plant.own_signature(current, {"name": "dead_time", "evidence": beside["evidence"]}) is not None
    assert plant.own_signature(current, {"name": "cogging_torque", "_reduced": reduced, "evidence": {}}) is None


def test_the_trend_of_the_reading_error_is_its_straight_line_part():
    xs = np.linspace(0.02, 0.066, K.N_GS)
    line = catchall.trend_of({"xs_m": list(xs), "h_m": list(-3e-6 + 4e-4 * xs)})
    assert line["scale_error"] == pytest.approx(4e-4) and line["r2"] == pytest.approx(1.0)
    assert line["rise_m"] == pytest.approx(4e-4 * 0.046)
    wave = catchall.trend_of({"xs_m": list(xs), "h_m": list(4e-6 * np.sin(2 * np.pi * xs / 5e-3))})
    assert wave["r2"] < catchall.TREND_R2  # a periodic error is no scale error
    assert catchall.trend_of({"xs_m": list(xs), "h_m": [0.0] * K.N_GS}) == {"scale_error": 0.0, "rise_m": 0.0,
                                                                             "r2": 0.0}


def test_the_generic_force_is_no_library_effect_and_off_by_default():
    from toggle_id.effects import EFFECTS, EXTRA_DEFAULTS
    assert GENERIC_FORCE.name not in {e.name for e in EFFECTS}
    assert not np.any(EXTRA_DEFAULTS[[ALL_INDEX[nm] - len(ASSIGNED) for nm in GENERIC_FORCE.names]])


@pytest.mark.slow
@pytest.mark.parametrize("offset", [0.0, 2e-5])
def test_on_the_plant_a_load_force_standing_in_for_a_drag_is_compensating_and_a_true_offset_is_kept(offset):
    """A drag quadratic in the slider's speed (independent scipy plant, tests/outside_plant.py) on the experiment
    sweep, where a constant load force takes most of it; with a true sensor offset of 20 µm beside it in the
    second case. The catch-all check on the fitted model demotes the load force and keeps the offset."""
    from outside_plant import Outside, simulate_outside

    from toggle_id.discovery.model import Model, _with, fit_free
    from toggle_id.discovery.refit import without_effect
    from toggle_id.discovery.residual import residual_report
    from toggle_id.discovery.validation import Judge
    from toggle_id.params import PARAM_NAMES
    from toggle_id.record import Record
    from toggle_id.simulate import PRECISE

    rng = np.random.default_rng(22)
    truth = ASSIGNED * np.exp(0.05 * rng.standard_normal(15))
    rec = Record.from_sweep("experiment", 5.0, name="drag")
    x, _, _ = simulate_outside(truth, rec, Outside(drag=1958.6))  # the adversarial set's rec22 magnitude
    rec.x_B = x + offset + 1e-6 * rng.standard_normal(rec.n)
    s = DiscoverSettings().validate()
    model = Model(rec, PRECISE, s.parallel, jacobian=s.jacobian)
    added = [{"name": "constant_load_force"}] + ([{"name": "sensor_offset"}] if offset else [])
    free = tuple(nm for nm in PARAM_NAMES if nm not in ("K_l", "K_i", "m_C")) + tuple(
        nm for a in added for nm in EFFECTS_BY_NAME[a["name"]].names)
    starts = [_with(extend(truth)[0], {"F_load": f}) for f in (-300.0, -100.0, 100.0, 300.0)]
    sse = [float(np.sum(model.residuals(th[None, :])[0] ** 2)) for th in starts]
    current = fit_free(model, starts[int(np.argmin(sse))], free, s.baseline_nfev, s.fd_rel_step, rounds=s.rounds)
    diag, _, states = residual_report(model, current.theta, s, None)
    kept, comp, report = catchall.catch_all(
        model, Judge(model, s), current, added, states,
        lambda fit, a: without_effect(model, fit, a["name"], added, (), s), s, print)
    print(f"\n[catch-all] final {current.rmse(model.n) * 1e6:.4g} um, with the generic force "
          f"{report['rmse_m'] * 1e6:.4g} um; kept {[a['name'] for a in kept]}, compensating "
          f"{[c['name'] for c in comp]}")
    assert diag["verdict"]["structure_left"]  # the load force leaves the drag's structure
    assert report["supported"] and report["rmse_m"] < 1.05e-6
    # the drag is a force: a reading error beside the generic force is not needed (were it kept, its constant would
    # do the true offset's work, and the offset would be demoted with the load force)
    assert not report["reading_error"]["needed"]
    assert [c["name"] for c in comp] == ["constant_load_force"]
    assert [a["name"] for a in kept] == (["sensor_offset"] if offset else [])


@pytest.mark.parametrize("n_cog, odd", [(6.0, False), (6.04, False), (5.93, False), (3.29, True), (2.5, True)])
def test_a_cogging_torque_that_repeats_a_fraction_of_times_per_revolution_is_no_motors(n_cog, odd):
    """An accepted cogging torque with n_cog off a whole number stands in for something else (rec23 of the
    adversarial set: a scale error of 5-mm pitch took a cogging torque at n_cog 3.29; rec28: a dead band of the drive
    took one at n_cog 1.54, and the noise model the rest)."""
    from toggle_id.discovery.periodic import implausible
    from toggle_id.simulate import extend
    from toggle_id.params import ASSIGNED

    theta = extend(ASSIGNED)[0]
    theta[ALL_INDEX["n_cog"]] = n_cog
    why = implausible("cogging_torque", theta, DiscoverSettings().cogging_whole_tol)
    assert (why is not None) == odd
    if odd:
        assert f"{n_cog:.3g} times per motor revolution" in why
    assert implausible("dead_time", theta, 0.1) is None
    with pytest.raises(Exception, match="cogging_whole_tol"):
        DiscoverSettings(cogging_whole_tol=0.7).validate()


def test_the_generic_sensor_error_is_added_at_the_models_position_and_costs_no_simulation():
    from toggle_id.discovery.model import Model
    from toggle_id.effects import sensor_error
    from toggle_id.record import Record
    from toggle_id.simulate import PRECISE, simulate

    rec = Record.from_sweep("simulation", duration=1.0)
    theta = extend(ASSIGNED)[0]
    rec.x_B = simulate(theta[None, :], rec, PRECISE).x_B[0] + 1e-6 * np.sin(np.arange(rec.n))  # a "measured" x_B
    model = Model(rec, parallel=False)
    lo, hi = float(rec.x_B.min()), float(rec.x_B.max())
    w = 1e-5 * np.cos(np.arange(K.N_GS))
    T = np.repeat(theta[None, :], 4, axis=0)
    T[:, K.GS_LO], T[:, K.GS_HI] = lo, hi
    T[1, K.GS_W0:] = w
    T[2, K.GS_W0 + 3] = 2e-6
    T[3, K.K_T] *= 1.01  # a plant change: a second simulation
    X = model.outputs(T)
    assert model.n_sims == 2
    plain = simulate(T[[0, 3]], rec, PRECISE).x_B
    knots = np.linspace(lo, hi, K.N_GS)
    np.testing.assert_allclose(X[0], plain[0], rtol=0, atol=1e-15)
    # h at the model's (noise-free) position: piecewise-linear interpolation of the weights between the knots
    np.testing.assert_allclose(X[1] - plain[0], np.interp(plain[0], knots, w), rtol=0, atol=1e-15)
    hat = np.clip(1.0 - np.abs((plain[0] - knots[3]) / (knots[1] - knots[0])), 0.0, None)  # the 4th knot's hat
    np.testing.assert_allclose(X[2] - plain[0], 2e-6 * hat, rtol=0, atol=1e-15)
    np.testing.assert_allclose(X[3], plain[1], rtol=0, atol=1e-15)
    x_resp = model.response(T[1])[0]
    np.testing.assert_allclose(x_resp, X[1], rtol=0, atol=1e-15)
    np.testing.assert_allclose(sensor_error(T[[0, 1]], np.vstack([plain[0], plain[1]]))[1],
                               np.interp(plain[1], knots, w))
    bad = T[1].copy()
    bad[K.GS_HI] = lo
    with pytest.raises(ValueError, match="gs_hi > gs_lo"):
        sensor_error(bad, plain[0])


def _an_offset_beside_a_reading_error(error):
    """A 1-s simulation-sweep record with no effect of the library and the reading error ``error(x)`` (m) added to
    the true position, 1 µm of noise; the nominal model with a sensor offset fitted to it (the offset alone must be
    significant), then the catch-all. Returns (kept, compensating, report)."""
    from toggle_id.discovery.model import Model, fit_free
    from toggle_id.discovery.residual import _residual
    from toggle_id.discovery.validation import Judge
    from toggle_id.record import Record
    from toggle_id.simulate import PRECISE, simulate

    rec = Record.from_sweep("simulation", duration=1.0)
    truth = extend(ASSIGNED)[0]
    x = simulate(truth[None, :], rec, PRECISE).x_B[0]
    rec.x_B = x + error(x) + 1e-6 * np.random.default_rng(4).standard_normal(rec.n)
    model = Model(rec)
    s = DiscoverSettings(baseline_nfev=40, null_nfev=20)
    free = ("mu", "K_i")
    current = fit_free(model, truth, free + ("x_off",), s.baseline_nfev, s.fd_rel_step)
    alone = fit_free(model, truth, free, s.baseline_nfev, s.fd_rel_step)
    judge = Judge(model, s)
    assert judge.judge_pair(alone, current).checks["f_test"]  # the offset alone is significant
    states = _residual(model, current.theta)[1]

    def without(fit, a):  # the sensor offset switched off, the rest refitted
        start = fit.theta.copy()
        start[ALL_INDEX["x_off"]] = 0.0
        return fit_free(model, start, tuple(n for n in fit.free if n != "x_off"), s.baseline_nfev, s.fd_rel_step)

    return catchall.catch_all(model, judge, current, [{"name": "sensor_offset"}], states, without, s, print)


@pytest.mark.slow
def test_a_sensor_offset_that_stands_in_for_a_scale_error_is_compensating():
    """rec23's case, small: a linear scale's interpolation error (pitch 4 mm, 4 µm, largest where the slider rests
    clamped) on a record with no effect of the library. A sensor offset takes up its value at the clamped end and
    is significant; the generic error of the reading does that work and more, so the offset is compensating."""
    phase = [0.0]

    def scale(x):
        phase[0] = np.pi / 2 - 2 * np.pi * x[-1] / 4e-3
        return 4e-6 * np.sin(2 * np.pi * x / 4e-3 + phase[0])

    kept, comp, report = _an_offset_beside_a_reading_error(scale)
    assert report["supported"] and report["reading_error"]["needed"]
    assert kept == [] and [c["name"] for c in comp] == ["sensor_offset"]
    assert report["sensor_rms_m"] > 2e-6
    # the fitted reading error holds the scale's error: its 4-mm component has the scale's amplitude and phase. (Its
    # smooth part trades with the generic force and the parameters on a stroke run once: the record fixes only
    # the sum, which reaches the noise.)
    xf = np.linspace(report["shape"]["xs_m"][0], report["shape"]["xs_m"][-1], 4000)
    u, arg = (xf - xf[0]) / np.ptp(xf), 2 * np.pi * xf / 4e-3 + phase[0]
    B = np.column_stack([np.sin(arg), np.cos(arg), np.ones_like(u), u, u ** 2, u ** 3])
    c = np.linalg.lstsq(B, np.interp(xf, report["shape"]["xs_m"], report["shape"]["h_m"]), rcond=None)[0]
    assert c[0] == pytest.approx(4e-6, rel=0.25) and abs(c[1]) < 1e-6
    # to the noise, not below it
    assert 0.9e-6 < report["rmse_m"] < 1.1e-6
    assert report["sensor_trend"]["r2"] < catchall.TREND_R2  # no scale error is called


@pytest.mark.slow
def test_a_sensor_offset_that_stands_in_for_a_wrong_scale_factor_is_compensating_and_the_trend_named():
    """A scale that reads 0.05 % long (x·(1 + 5e-4)), small: the offset takes up its mean; the reading error is
    needed beside the force, the offset is compensating, and the reading error is called a scale error."""
    kept, comp, report = _an_offset_beside_a_reading_error(lambda x: 5e-4 * x)
    print(f"\n[catch-all] scale factor: trend {report['sensor_trend']}, rms {report['rmse_m'] * 1e6:.4g} um")
    assert report["supported"] and report["reading_error"]["needed"]
    assert kept == [] and [c["name"] for c in comp] == ["sensor_offset"]
    assert report["sensor_trend"]["r2"] >= catchall.TREND_R2
    # its size only roughly, as the report says: the force and the parameters trade with h (measured: 9.8e-4 here,
    # 6.2e-4 on a 5-s experiment-sweep record of the same error; the text's claim is the order, checked here)
    assert 5e-4 / 3 < report["sensor_trend"]["scale_error"] < 3 * 5e-4
    assert 0.9e-6 < report["rmse_m"] < 1.1e-6


def test_a_cogging_torque_is_probed_and_fitted_only_at_counts_the_record_holds_enough_periods_of():
    """discover.cogging_min_periods: the floor on n_cog is 2π·periods over the motor angle's range (the angle from
    the mechanism's kinematics, θ_r = Z·x_C); the model's fits keep to it from a start below it, and the
    score tests and grids probe within it, each setting once."""
    from toggle_id.discovery.model import Model, fit_free
    from toggle_id.discovery.periodic import cogging_domain, cogging_floor
    from toggle_id.plant import GEOMETRY, kinematics
    from toggle_id.record import Record
    from toggle_id.simulate import PRECISE, simulate

    rec = Record.from_sweep("simulation", duration=1.0)
    theta = extend(ASSIGNED)[0].copy()
    theta[ALL_INDEX["a_cog"]], theta[ALL_INDEX["n_cog"]] = 0.3, 6.0
    rec.x_B = simulate(theta[None, :], rec, PRECISE).x_B[0]
    q = np.arccos(np.clip(rec.x_B / (GEOMETRY.r1 + GEOMETRY.r3), -1.0, 1.0))
    span = float(np.ptp(GEOMETRY.Z * np.asarray(kinematics(q, GEOMETRY)["x_C"])))
    floor = cogging_floor(rec, 10.0)
    assert floor == pytest.approx(20.0 * np.pi / span) and 1.0 < floor < 6.0
    at_rest = Record.from_sweep("simulation", duration=1.0)
    at_rest.x_B = np.full(at_rest.n, float(rec.x_B[0]))
    assert cogging_floor(at_rest, 10.0) == np.inf

    model = Model(rec, parallel=False)
    cog = EFFECTS_BY_NAME["cogging_torque"]
    assert model.probes(cog) == list(cog.probe)  # no narrowed domain: the library's probes
    model.bounds["n_cog"] = (floor, 48.0)
    probes = model.probes(cog)
    assert min(p["n_cog"] for p in probes) == pytest.approx(floor)
    assert len(probes) == len(cog.probe) - 2 * sum(n < floor for n in (1, 2, 3, 4)) + 2  # the low counts: one each
    start = theta.copy()
    start[ALL_INDEX["n_cog"]] = 1.0
    fit = fit_free(model, start, ("a_cog", "n_cog", "phi_cog"), 6)
    assert fit.theta[ALL_INDEX["n_cog"]] >= floor
    said: list[str] = []
    fresh = Model(rec, parallel=False)
    pool = list(EFFECTS_BY_NAME.values())
    assert cogging_domain(fresh, pool, 0.0, said.append) == pool and fresh.bounds == {} and not said
    assert cogging_domain(fresh, pool, 10.0, said.append) == pool
    assert fresh.bounds["n_cog"] == pytest.approx((floor, 48.0)) and "counts from" in said[-1]
    rest = Model(at_rest, parallel=False)
    assert cogging_domain(rest, pool, 10.0, said.append) == [e for e in pool if e is not cog]
    assert rest.bounds == {} and "left out" in said[-1]
    with pytest.raises(Exception, match="cogging_min_periods"):
        DiscoverSettings(cogging_min_periods=2.0).validate()
    DiscoverSettings(cogging_min_periods=0.0).validate()


@dataclass
class _Evidence:
    """In sample as given (``in_sample``); every check, out of sample too, ``passed``."""

    passed: bool
    in_sample: bool
    F: float = 9.0
    p_value: float = 1e-3
    delta_bic: float = -5.0
    reason: str = "judged"

    def to_dict(self) -> dict:
        return {"checks": {"f_test": self.in_sample, "bic": self.in_sample, "cross_validation": self.passed}}


def test_an_effect_supported_beside_the_generic_terms_is_refitted_without_them_and_accepted(monkeypatch):
    """catchall.beside_generic: each effect fitted on the model with the generic terms from its scout, judged there;
    one supported there is refitted on the model without them from the values reached, and accepted where it lowers
    the error there in sample, though its out-of-sample check fails (the missing physics still in the residual); a
    cogging torque's count is held at its whole value from there."""
    from toggle_id.discovery.refit import Scout

    theta = extend(ASSIGNED)[0]
    base = Fit(theta, ("K_t",), 10.0)
    generic = Fit(theta, ("K_t",) + catchall.WEIGHTS, 2.0)
    fitted = []

    def fake_fit(model, start, free, *a, **k):
        fitted.append((start.copy(), tuple(free)))
        beside = set(catchall.WEIGHTS) <= set(free)
        sse = (1.0 if "a_cog" in free else 1.99) if beside else (8.0 if "a_cog" in free else 9.99)
        return Fit(start.copy(), tuple(free), sse)

    def fake_from_current(model, fit, sc, settings):
        assert fit is generic
        th = fit.theta.copy()
        th[ALL_INDEX["a_cog" if sc.name == "cogging_torque" else "tau_d"]] = 0.01
        th[ALL_INDEX["n_cog"]] = 5.97 if sc.name == "cogging_torque" else th[ALL_INDEX["n_cog"]]
        return Scout(sc.name, 0.0, th, {})

    class Judge:
        def judge_pair(self, small, large):
            gain = small.sse - large.sse
            return _Evidence(passed=gain > 0.5 and small is not base, in_sample=gain > 0.5)

    monkeypatch.setattr(catchall, "fit_free", fake_fit)
    monkeypatch.setattr(catchall, "from_current", fake_from_current)
    errors_of = []
    monkeypatch.setattr(catchall, "_std_errors", lambda fit, names, n: errors_of.append(tuple(names)) or {})
    said: list[str] = []
    scouts = [Scout("cogging_torque", 5.0, None, {}), Scout("dead_time", 5.0, None, {})]
    out = catchall.beside_generic(_Model(), Judge(), base, generic, scouts, DiscoverSettings(), (), 2, said.append)
    assert [rf.name for rf in out] == ["cogging_torque"]  # the dead time does nothing beside the generic terms
    rf = out[0]
    assert rf.accepted and "beside a generic slider force" in rf.reason and rf.iteration == 2
    assert rf.params["a_cog"] == 0.01 and rf.params["n_cog"] == 6.0 and rf.sse0 == 10.0 and rf.sse1 == 8.0
    start, free = fitted[1]  # without the generic terms: the base model with the values reached beside them
    # the count, determined beside the generic terms, held at its whole value
    assert free == ("K_t", "a_cog", "phi_cog") and start[ALL_INDEX["n_cog"]] == 6.0
    assert not np.any(start[K.GV_W0:K.GV_W0 + K.N_GEN])
    assert fitted[0][1] == generic.free + ("a_cog", "n_cog", "phi_cog")
    assert "beside_generic" in rf.evidence and len(said) == 3
    assert errors_of == [("a_cog", "phi_cog")]  # of the free parameters only
    # out of sample no better, and no gain in sample either: not accepted
    monkeypatch.setattr(catchall, "fit_free", lambda model, start, free, *a, **k: Fit(
        start.copy(), tuple(free), 1.0 if set(catchall.WEIGHTS) <= set(free) else 9.9))
    again = catchall.beside_generic(_Model(), Judge(), base, generic, scouts[:1], DiscoverSettings(), (), 2,
                                    said.append)
    assert len(again) == 1 and not again[0].accepted


def test_the_share_a_true_effect_keeps_is_measured_on_its_noise_free_twin():
    """:func:`catchall.share_if_true` on a real model (0.5-s sweep, a 20-µm sensor offset accepted): the generic
    reading error holds a constant, so a true offset keeps nothing beside it; beside the generic force alone it keeps
    a part (measured 6.7 %: on this open-loop drive a force of the position moves the slider along much of the
    stroke alike, not all of it). The twin is simulated, not the record: the record's noise does not enter."""
    import dataclasses

    from toggle_id.discovery.model import Model, _with
    from toggle_id.record import Record
    from toggle_id.simulate import simulate

    rec = Record.from_sweep("simulation", 0.5)
    theta = _with(extend(ASSIGNED)[0], {"x_off": 2e-5})
    x = simulate(theta[None, :], rec).x_B[0] + 2e-5 + 1e-6 * np.random.default_rng(0).standard_normal(rec.n)
    model = Model(dataclasses.replace(rec, x_B=x), parallel=False)
    current = Fit(theta, ("K_t", "B_m", "x_off"), float(np.sum((x - model.outputs(theta[None, :])[0]) ** 2)))
    states = {"x_B": model.outputs(_with(theta, {"x_off": 0.0})[None, :])[0], "xdot_B": np.linspace(-0.01, 0.2, rec.n)}
    knots = catchall.knots_of(states, x)
    settings = DiscoverSettings(baseline_nfev=30)
    before = model.n_sims
    both = catchall.share_if_true(model, current, {"name": "sensor_offset"}, knots, catchall.WEIGHTS, settings)
    force = catchall.share_if_true(model, current, {"name": "sensor_offset"}, knots, catchall.FORCE_WEIGHTS, settings)
    assert 0.0 <= both < 1e-4 and 0.01 < force < 1.0
    assert model.n_sims > before + 100  # the twin's simulations are counted as the job's
    assert model.record.x_B is x  # the record itself is left as it was
