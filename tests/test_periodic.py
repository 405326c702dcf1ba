"""The report-only scan of :mod:`toggle_id.discovery.periodic`: an error that repeats with a position is named with
its period and amplitude; white and coloured noise make none."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from toggle_id.discovery.noise import NoiseModel
from toggle_id.discovery.periodic import frequency_grid, periodic, scan

N = 5001


def states(n: int = N) -> dict[str, np.ndarray]:
    """A slider that strokes 20 → 56 mm and back, resting at the ends, with a motor angle that is a strongly
    nonlinear image of its position (as the toggle's crosshead's is)."""
    t = np.arange(n) / 1000.0
    x = 0.038 - 0.018 * np.cos(2 * np.pi * 0.4 * t) ** 3
    return {"x_B": x, "motor_angle": 600.0 * (x - 0.019) ** 2 / 0.037, "t": t}


def noise(seed: int, rho: float = 0.0) -> np.ndarray:
    w = np.random.default_rng(seed).standard_normal(N) * 1e-6 * np.sqrt(1 - rho ** 2)
    return signal.lfilter([1.0], [1.0, -rho], w)


def test_the_scan_is_the_least_squares_fit_of_a_sinusoid_at_each_period():
    st = states()
    x, r = st["x_B"], noise(0)
    freqs = np.array([150.0, 200.0, 333.3])
    got = scan(NoiseModel(), r, x, freqs)
    for f, g in zip(freqs, got):  # the explained sum of squares of lstsq on [sin, cos] over the mean square
        B = np.column_stack([np.sin(2 * np.pi * f * x), np.cos(2 * np.pi * f * x)])
        fit = B @ np.linalg.lstsq(B, r, rcond=None)[0]
        assert g == pytest.approx(float(fit @ fit) / float(r @ r / r.size), rel=1e-9)


def test_a_scale_error_is_named_with_its_pitch_and_amplitude():
    st = states()
    r = noise(1) + 0.5e-6 * np.sin(2 * np.pi * st["x_B"] / 0.005 + 0.3)
    out = periodic(r, st)
    assert out["periodic"] and out["strongest"] == "x_B"
    fam = out["families"]["x_B"]
    assert fam["period"] == pytest.approx(0.005, rel=0.01)
    assert fam["amplitude_m"] == pytest.approx(0.5e-6, rel=0.15)
    assert "mm of slider B position" in out["text"] and "motor revolution" not in out["text"]


def test_a_repetition_per_motor_revolution_is_counted_per_revolution():
    st = states()
    out = periodic(noise(2) + 0.4e-6 * np.sin(6.0 * st["motor_angle"]), st)
    assert out["periodic"] and out["strongest"] == "motor_angle"
    assert out["families"]["motor_angle"]["cycles_per_revolution"] == pytest.approx(6.0, rel=0.01)
    assert "times per motor revolution" in out["text"] and "slider B position" not in out["text"]


def test_a_second_position_is_named_only_where_it_explains_beyond_the_first():
    """An error periodic in one position shows, weaker, in the other (significant here too); it is said only when
    its period explains the residual beyond the best one's — as two errors, one in each position, do."""
    st = states()
    scale = 0.5e-6 * np.sin(2 * np.pi * st["x_B"] / 0.005)
    one = periodic(noise(4) + scale, st)
    fams = one["families"]
    assert fams["x_B"]["significant"] and fams["motor_angle"]["significant"]  # the shadow in the other position
    assert one["strongest"] == "x_B" and not fams["motor_angle"]["beyond_strongest"]
    assert "motor revolution" not in one["text"]
    two = periodic(noise(4) + scale + 0.4e-6 * np.sin(6.0 * st["motor_angle"]), st)
    assert all(f["significant"] for f in two["families"].values())
    other = next(k for k in two["families"] if k != two["strongest"])
    assert two["families"][other]["beyond_strongest"]
    assert "mm of slider B position" in two["text"] and "times per motor revolution" in two["text"]
    assert "may not tell" in two["text"] and "linear scale" in two["text"] and "cogging" in two["text"]


def test_a_fraction_of_a_repetition_per_revolution_is_no_motor_side_cause():
    """A motor's cogging, an encoder's eccentricity and a lead error repeat a whole number of times per revolution:
    3.4 per revolution is said to be none of them, and the slider's period, significant too, is named."""
    st = states()
    out = periodic(noise(5) + 0.4e-6 * np.sin(3.4 * st["motor_angle"]), st)
    fam = out["families"]["motor_angle"]
    assert out["strongest"] == "motor_angle" and fam["cycles_per_revolution"] == pytest.approx(3.4, abs=0.02)
    assert "not a whole number of times per revolution" in out["text"]
    assert ("along slider B position it repeats every" in out["text"]) == out["families"]["x_B"]["significant"]
    whole = periodic(noise(5) + 0.4e-6 * np.sin(3.0 * st["motor_angle"]), st)
    assert "not a whole number" not in whole["text"] and "cogging" in whole["text"]


@pytest.mark.parametrize("rho", [0.0, 0.9])
def test_white_and_coloured_noise_repeat_with_no_position(rho):
    st = states()
    hits = sum(periodic(noise(100 + k, rho), st)["periodic"] for k in range(8))
    assert hits <= 1  # at most 1 % per draw (a conservative Bonferroni over the scan and the positions)


def test_a_position_that_does_not_move_is_not_scanned():
    freqs, m = frequency_grid(np.full(100, 0.03))
    assert freqs.size == 0 and m == 0.0
    st = {"x_B": np.full(N, 0.03)}
    assert periodic(noise(3), st) == {"periodic": False, "alpha": 0.01, "families": {}, "strongest": None,
                                      "text": "the residual repeats with no position"}


def test_a_count_per_revolution_is_whole_within_its_tolerance_and_an_angle_spans_its_range_in_turns():
    from toggle_id.discovery.periodic import turns, whole_count

    assert whole_count(6.04, 0.1) == 6 and whole_count(5.91, 0.1) == 6 and whole_count(3.4, 0.1) is None
    assert whole_count(1.0006, 0.0) is None and whole_count(2.0, 0.0) == 2
    assert turns(np.array([1.0, 1.0 + 3 * np.pi, 2.0])) == pytest.approx(1.5) and turns(np.zeros(3)) == 0.0
