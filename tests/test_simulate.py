"""Tests of toggle_id.simulate: the three reference trajectories at both tiers, the measured-record path,
degenerate parameters, early stop, restart, and batching (parallel = serial, no cross-talk)."""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from toggle_id.errors import ConfigError
from toggle_id.kernels.slots import PC_IDT, PC_T0, PC_TAUD
from toggle_id.kernels.stepping import _next_stop
from toggle_id.params import ASSIGNED, INDEX, PARAM_NAMES, read_params_file, to_vector
from toggle_id.record import Record
from toggle_id.simulate import (
    FAST,
    JACOBIAN,
    JACOBIAN_REL_STEP,
    PRECISE,
    STATUS_INVALID,
    STATUS_OK,
    SolverSettings,
    extend,
    precise_jacobian,
    simulate,
)


def _reference_dir() -> Path:
    """The reference trajectories made for this project, kept in the repository (tests/reference)."""
    return Path(__file__).resolve().parent / "reference"


REF_DIR = _reference_dir()
#: reference file → excitation (tests/reference/README.md)
REFERENCES = {"assigned_sim_sweep": "simulation", "table1_one_stage_sim_sweep": "simulation",
              "assigned_exp_sweep": "experiment"}
#: tier → (max |x_B error| in m, max |i_q error| as a fraction of the i_q range)
TOLERANCES = {"fast": (1e-6, 1e-3), "precise": (5e-8, 1e-5)}
SETTINGS = {"fast": FAST, "precise": PRECISE}


def _mod(**values: float) -> np.ndarray:
    th = ASSIGNED.copy()
    for name, v in values.items():
        th[INDEX[name]] = v
    return th


@pytest.mark.parametrize("tier", ["fast", "precise"])
@pytest.mark.parametrize("name", sorted(REFERENCES))
def test_reproduces_reference_trajectories(name, tier):
    ref = np.loadtxt(REF_DIR / f"{name}.csv", delimiter=",", skiprows=1)
    theta = to_vector(read_params_file(str(REF_DIR / f"{name}.params")))
    rec = Record.from_sweep(REFERENCES[name])
    np.testing.assert_allclose(rec.t, ref[:, 0], atol=1e-12)
    res = simulate(theta[None, :], rec, SETTINGS[tier])
    assert res.status.tolist() == [STATUS_OK]
    tol_x, tol_i = TOLERANCES[tier]
    err_x = np.max(np.abs(res.x_B[0] - ref[:, 2]))
    err_i = np.max(np.abs(res.i_q[0] - ref[:, 3])) / np.ptp(ref[:, 3])
    assert err_x < tol_x, f"{name} {tier}: max |x_B error| {err_x * 1e6:.4f} µm"
    assert err_i < tol_i, f"{name} {tier}: max |i_q error| {err_i * 100:.5f} % of range"
    # the contact instant is where x_B first reaches x_B^L in the reference
    k = int(np.argmax(ref[:, 2] >= 0.056))
    assert ref[k - 1, 0] < res.contact[0, 0] <= ref[k, 0]


@pytest.mark.parametrize("tier", ["fast", "precise"])
def test_measured_record_agrees_with_sweep_within_interpolation_effect(tier):
    """A record without a sweep gives v_in at the samples only; the simulator interpolates it linearly. The
    interpolation changes x_B by about 0.16 µm (a zero-order hold would shift it by about 8 µm, docs/model.md §5)."""
    rec = Record.from_sweep("simulation")
    measured = Record(t=rec.t, v_in=rec.v_in)
    a = simulate(ASSIGNED[None], rec, SETTINGS[tier])
    b = simulate(ASSIGNED[None], measured, SETTINGS[tier])
    assert b.status.tolist() == [STATUS_OK]
    diff = np.max(np.abs(a.x_B - b.x_B))
    assert diff < (1.0e-6 if tier == "fast" else 0.5e-6)
    assert diff > 1e-9  # the two paths really differ (the measured path interpolates)


def test_degenerate_corners_are_flagged_and_do_not_disturb_the_batch():
    tiny = {"m_2": 1e-6, "m_3": 1e-6, "m_5": 1e-6, "m_B": 1e-6, "m_C": 1e-6}
    rows = {
        "assigned": ASSIGNED,
        "L_q = 0": _mod(L_q=0.0),
        "no inertia": _mod(m_2=0.0, m_3=0.0, m_5=0.0, m_B=0.0, m_C=0.0, J_m=0.0),
        "NaN": _mod(K_t=np.nan),
        "negative": _mod(m_B=-1.0),
        "runaway": _mod(K_i=1e4, J_m=0.0, K_l=0.0, D=0.0, **tiny),
        "stiff clamp": _mod(K_l=1e8, J_m=1e-9, **tiny),
        "tiny L_q": _mod(L_q=1e-7),
        "assigned again": ASSIGNED,
    }
    theta = np.array(list(rows.values()))
    fast = replace(FAST, max_steps=5000)  # the runaway exhausts any budget near the singular end of link 5
    res = simulate(theta, Record.from_sweep("simulation"), fast)
    st = dict(zip(rows, res.status.tolist()))
    for name in ("L_q = 0", "no inertia", "NaN", "negative"):
        assert st[name] == STATUS_INVALID, name
    assert st["runaway"] != STATUS_OK
    for name in ("assigned", "stiff clamp", "tiny L_q", "assigned again"):  # stiff but valid: integrated
        assert st[name] == STATUS_OK, name
    for j, name in enumerate(rows):
        if st[name] == STATUS_OK:
            assert np.all(np.isfinite(res.x_B[j])) and np.all(np.isfinite(res.i_q[j])), name
        else:
            assert np.all(np.isnan(res.x_B[j])) and np.all(np.isnan(res.i_q[j])), name
    alone = simulate(ASSIGNED[None], Record.from_sweep("simulation"), fast)
    np.testing.assert_array_equal(res.x_B[0], alone.x_B[0])
    np.testing.assert_array_equal(res.x_B[-1], alone.x_B[0])
    assert res.status_counts()["invalid parameters"] == 4


def test_step_budget_turns_into_solver_failure():
    res = simulate(ASSIGNED[None], Record.from_sweep("simulation"), replace(FAST, max_steps=50))
    assert res.status.tolist() == [2]
    assert res.n_steps[0] == 50
    assert res.fell_back.tolist() == [False]  # no fallback configured


def test_a_kernel_that_raises_fails_its_rows_instead_of_the_job(monkeypatch):
    """A numerical corner a kernel does not survive (a batch's exception) costs the rows that raise on their own a
    solver-failure status and a warning; the batch's other rows are simulated as they would be alone."""
    import toggle_id.simulate as S

    rec = Record.from_sweep("simulation", duration=0.2)
    theta = np.array([ASSIGNED, _mod(K_t=ASSIGNED[INDEX["K_t"]] * 1.01), ASSIGNED])
    serial = S._KERNELS[False, False]

    def parallel_raises(thetas, rows, *args):
        raise ZeroDivisionError("division by zero")

    def serial_raises_on_row_1(thetas, rows, *args):
        if 1 in rows:
            raise ZeroDivisionError("division by zero")
        serial(thetas, rows, *args)

    monkeypatch.setitem(S._KERNELS, (True, False), parallel_raises)
    monkeypatch.setitem(S._KERNELS, (False, False), serial_raises_on_row_1)
    with pytest.warns(RuntimeWarning, match="raised ZeroDivisionError .* 1 of them fail on their own"):
        res = simulate(theta, rec, FAST, parallel=True)
    assert res.status.tolist() == [STATUS_OK, S.STATUS_SOLVER_FAILURE, STATUS_OK]
    assert np.all(np.isnan(res.x_B[1])) and np.all(np.isnan(res.i_q[1]))
    monkeypatch.undo()
    alone = simulate(ASSIGNED[None], rec, FAST)
    np.testing.assert_array_equal(res.x_B[0], alone.x_B[0])
    np.testing.assert_array_equal(res.x_B[2], alone.x_B[0])


def test_rows_past_the_step_budget_are_redone_by_the_fallback_and_flagged():
    rec = Record.from_sweep("simulation", duration=0.5)
    tight = replace(PRECISE, max_steps=300, fallback=FAST)
    res = simulate(np.repeat(ASSIGNED[None], 2, axis=0), rec, tight)
    alone = simulate(ASSIGNED[None], rec, FAST)
    assert res.fell_back.tolist() == [True, True]
    assert res.status.tolist() == [STATUS_OK, STATUS_OK]
    np.testing.assert_array_equal(res.x_B[0], alone.x_B[0])
    assert not simulate(ASSIGNED[None], rec, PRECISE).fell_back[0]


@pytest.mark.parametrize("tier", ["fast", "precise"])
@pytest.mark.parametrize("n", [100, 362, 2500])
def test_n_samples_is_the_prefix_of_a_full_run(tier, n):
    """Identical up to the last step (which is shortened to end at the last requested sample), and within the
    tier's accuracy there."""
    rec = Record.from_sweep("simulation")
    full = simulate(ASSIGNED[None], rec, SETTINGS[tier])
    part = simulate(ASSIGNED[None], rec, SETTINGS[tier], n_samples=n)
    assert np.all(np.isnan(part.x_B[0, n:])) and np.all(np.isnan(part.i_q[0, n:]))
    d = np.abs(part.x_B[0, :n] - full.x_B[0, :n])
    last_step = int(SETTINGS[tier].hmax / rec.dt) + 1
    assert np.all(d[: max(0, n - last_step)] == 0.0)
    assert d.max() < (0.1e-6 if tier == "fast" else 1e-12)


@pytest.mark.parametrize("tier", ["fast", "precise"])
def test_restart_from_contact_state_reproduces_the_full_run(tier):
    rec = Record.from_sweep("simulation")
    full = simulate(ASSIGNED[None], rec, SETTINGS[tier])
    t_c, q_c, w_c, i_c = full.contact[0]
    assert np.isfinite(t_c)
    res = simulate(ASSIGNED[None], rec, SETTINGS[tier], start=(t_c, (q_c, w_c, i_c), 1))
    k0 = int(np.searchsorted(rec.t, t_c))
    assert res.status.tolist() == [STATUS_OK]
    assert np.all(np.isnan(res.x_B[0, :k0]))
    err = np.max(np.abs(res.x_B[0, k0:] - full.x_B[0, k0:]))
    assert err < (0.3e-6 if tier == "fast" else 1e-10)
    assert res.n_steps[0] < full.n_steps[0]


def test_parallel_equals_serial_and_rows_do_not_interact():
    rng = np.random.default_rng(5)
    theta = ASSIGNED * (1.0 + 0.1 * rng.uniform(-1.0, 1.0, (12, ASSIGNED.size)))
    theta[3, INDEX["L_q"]] = 0.0  # an invalid row in the middle
    rec = Record.from_sweep("simulation")
    ser = simulate(theta, rec, FAST)
    par = simulate(theta, rec, FAST, parallel=True)
    for a, b in ((ser.x_B, par.x_B), (ser.i_q, par.i_q), (ser.status, par.status), (ser.n_steps, par.n_steps),
                 (ser.contact, par.contact)):
        np.testing.assert_array_equal(a, b)
    for j in (0, 7, 11):
        alone = simulate(theta[j:j + 1], rec, FAST)
        np.testing.assert_array_equal(alone.x_B[0], ser.x_B[j])
        np.testing.assert_array_equal(alone.i_q[0], ser.i_q[j])


def test_precise_tier_is_smooth_in_the_parameters():
    """Central differences of x_B in K_t with two step sizes agree: the step-count jitter of the precise tier is
    far below what finite-difference Jacobians resolve."""
    rec = Record.from_sweep("simulation")
    j = INDEX["K_t"]
    slopes = []
    for rel in (1e-4, 1e-5):
        hi, lo = ASSIGNED.copy(), ASSIGNED.copy()
        hi[j] *= 1 + rel
        lo[j] *= 1 - rel
        r = simulate(np.array([hi, lo]), rec, PRECISE, n_samples=1000)
        slopes.append((r.x_B[0, :1000] - r.x_B[1, :1000]) / (2 * rel * ASSIGNED[j]))
    scale = np.max(np.abs(slopes[0]))
    assert np.max(np.abs(slopes[0] - slopes[1])) < 1e-4 * scale


def test_precise_tier_is_smooth_on_a_sampled_input():
    """On a record given by its samples (the cycling command, as read from a CSV: the input is linear between
    samples, kinked at each), the forward difference of x_B in each of the 15 parameters lies within 1 % (of the
    column's norm) of a far tighter integration's: the precise tier's steps stop at the samples. Stepping freely
    across them, the worst column was off by 14 times its norm (m_2; ``python -m jobs.bench_stops``)."""
    from jobs.bench_stops import REFERENCE, fd_noise, fd_points

    rec = Record.from_cycling()
    X = fd_points(ASSIGNED[None, :])
    err = fd_noise(simulate(X, rec, PRECISE, parallel=True).x_B, simulate(X, rec, REFERENCE, parallel=True).x_B)
    assert np.all(err < 1e-2), dict(zip(PARAM_NAMES, np.round(err, 4)))


@pytest.mark.parametrize("use_sweep, tau_d, t, expected", [
    (True, 0.0, 0.0, 1e-3), (True, 0.0, 0.4e-3, 1e-3), (True, 0.0, 1e-3 - 1e-12, 2e-3),
    (True, 0.3e-3, 0.0, 1e-3),                       # a continuous input is not delayed to the samples
    (False, 0.0, 2.5e-3, 3e-3), (False, 0.3e-3, 0.0, 0.3e-3), (False, 0.3e-3, 0.5e-3, 1e-3),
    (False, 0.3e-3, 1.1e-3, 1.3e-3)])
def test_steps_stop_at_the_output_samples_and_the_delayed_input_samples(use_sweep, tau_d, t, expected):
    pc = np.zeros(64)
    pc[PC_T0], pc[PC_IDT], pc[PC_TAUD] = 0.0, 1e3, tau_d
    assert _next_stop(t, pc, use_sweep) == pytest.approx(expected, abs=1e-15)


def test_jacobian_tier_forward_differences_match_precise_central_differences():
    """The JACOBIAN tier at its step gives each column of the x_B Jacobian (the 15 parameters, a 2-s sweep record
    with its clamping) within 3 % of PRECISE central differences: the claim the polishes rely on (its cost is a
    benchmark's figure, README)."""
    rec = Record.from_sweep("simulation", 2.0)
    n = len(ASSIGNED)

    def columns(tier, rel, sign=1.0):
        X = np.repeat(ASSIGNED[None, :], n + 1, axis=0)
        h = sign * rel * np.abs(ASSIGNED)
        X[1:] += np.diag(h)
        x = simulate(X, rec, tier).x_B
        return (x[1:] - x[0]).T / h

    ref = 0.5 * (columns(PRECISE, 1e-4) + columns(PRECISE, 1e-4, -1.0))
    err = np.linalg.norm(columns(JACOBIAN, JACOBIAN_REL_STEP) - ref, axis=0) / np.linalg.norm(ref, axis=0)
    assert np.all(err < 0.03), dict(zip(PARAM_NAMES, np.round(err, 4)))
    assert precise_jacobian("jacobian", 1e-6) == (JACOBIAN, JACOBIAN_REL_STEP)
    assert precise_jacobian("precise", 1e-6) == (PRECISE, 1e-6)
    with pytest.raises(ConfigError, match="fd_tier"):
        precise_jacobian("loose", 1e-6)


def test_settings_reject_bad_values():
    with pytest.raises(ConfigError, match="method"):
        SolverSettings(method="euler")
    with pytest.raises(ConfigError, match="tolerances"):
        SolverSettings(rtol=0.0)


# ---------------------------------------------------------------------------------- synthetic-record options
def _sim_data(**kw) -> dict:
    """A simulated-record spec (conf/data/simulated.yaml) with ``kw`` overrides."""
    return {"source": "simulated", "sweep": "simulation", "duration": 5.0, "noise_m": 1e-6, "noise_seed": 2016,
            **kw}


def test_white_noise_is_bit_identical_to_the_records_before_the_noise_options():
    from toggle_id.app.records import build_record

    rec, truth = build_record(_sim_data(duration=1.0))
    ref = Record.from_sweep("simulation", 1.0)
    old = simulate(truth[None], ref, PRECISE).x_B[0] + 1e-6 * np.random.default_rng(2016).standard_normal(ref.n)
    assert np.array_equal(rec.x_B, old)
    assert rec.meta["noise"] == {"model": "white", "sigma_m": 1e-6, "ar": 0.0, "quantum_m": 0.0}
    assert rec.meta["command"]["kind"] == "sweep" and rec.sweep is not None


@pytest.mark.parametrize("rho", [0.0, 0.5, 0.9])
def test_ar1_noise_has_its_lag_one_correlation_and_keeps_the_marginal_sigma(rho):
    from toggle_id.record import ar1_noise

    sigma, n = 2e-6, 400_000
    e = ar1_noise(n, sigma, rho, np.random.default_rng(1))
    r1 = np.corrcoef(e[:-1], e[1:])[0, 1]
    assert r1 == pytest.approx(rho, abs=0.01)
    assert np.std(e) == pytest.approx(sigma, rel=0.02 if rho < 0.9 else 0.04)
    # stationary from the start: the first sample has the marginal spread over many draws
    starts = np.array([ar1_noise(2, sigma, rho, np.random.default_rng(s))[0] for s in range(2000)])
    assert np.std(starts) == pytest.approx(sigma, rel=0.06)


def test_gross_errors_hit_their_fraction_of_the_samples_with_their_spread_and_nothing_else():
    """Tukey's contaminated normal: a fraction f of the samples carries an extra N(0, s²); the noise before it is
    the noise of a record without gross errors, number for number (they are drawn after it)."""
    from toggle_id.record import gross_errors, measure

    g = gross_errors(200_000, 0.01, 10e-6, np.random.default_rng(3))
    hit = g != 0.0
    assert hit.mean() == pytest.approx(0.01, rel=0.05)
    assert np.std(g[hit]) == pytest.approx(10e-6, rel=0.05)
    x = np.zeros(5000)
    plain = measure(x, noise_m=1e-6, seed=11)
    dirty = measure(x, noise_m=1e-6, outlier_fraction=0.01, outlier_m=10e-6, seed=11)
    changed = dirty != plain
    assert 0 < changed.sum() < 0.02 * x.size and np.array_equal(dirty[~changed], plain[~changed])
    assert np.array_equal(measure(x, noise_m=1e-6, outlier_fraction=0.0, outlier_m=10e-6, seed=11), plain)
    with pytest.raises(ValueError, match="fraction of gross errors"):
        gross_errors(10, 1.0, 1e-6, np.random.default_rng(0))


def test_a_record_with_gross_errors_says_so_in_its_metadata():
    from toggle_id.app.records import build_record

    rec, _ = build_record(_sim_data(duration=1.0, outlier_fraction=0.02, outlier_m=5e-6))
    assert rec.meta["noise"] == {"model": "white", "sigma_m": 1e-6, "ar": 0.0, "quantum_m": 0.0,
                                 "outlier_fraction": 0.02, "outlier_m": 5e-6}


def test_read_only_inputs_run_the_kernel_compiled_for_writeable_ones():
    """Ray hands its workers read-only arrays (the record, the population, a restart state). They must run the
    kernel specialisation compiled for writeable ones, with the same result: another signature would compile every
    kernel again in each worker (minutes on a cold cache)."""
    from toggle_id.kernels.driver import simulate_batch_serial

    rec = Record.from_sweep("simulation", duration=0.2)
    theta = np.repeat(ASSIGNED[None], 2, axis=0)
    start = (0.05, np.array([0.0, 0.0, 0.0]), 0)
    first = simulate(theta, rec, FAST)
    restarted = simulate(theta, rec, FAST, start=(start[0], start[1].copy(), 0))
    n_signatures = len(simulate_batch_serial.signatures)
    frozen = replace(rec, t=rec.t.copy(), v_in=rec.v_in.copy(), sweep=None)
    for arr in (frozen.t, frozen.v_in, theta, start[1]):
        arr.setflags(write=False)
    assert not frozen.t.flags.writeable and not theta.flags.writeable
    np.testing.assert_array_equal(simulate(theta, replace(frozen, sweep=rec.sweep), FAST).x_B, first.x_B)
    np.testing.assert_array_equal(simulate(theta, replace(frozen, sweep=rec.sweep), FAST, start=start).x_B,
                                  restarted.x_B)
    assert len(simulate_batch_serial.signatures) == n_signatures


def test_quantisation_rounds_the_noisy_record_to_multiples_of_the_quantum():
    from toggle_id.app.records import build_record

    q = 1e-6
    rec, truth = build_record(_sim_data(duration=1.0, noise_m=0.0, quantum_m=q))
    clean = simulate(truth[None], Record.from_sweep("simulation", 1.0), PRECISE).x_B[0]
    k = rec.x_B / q
    assert np.max(np.abs(k - np.round(k))) < 1e-6
    assert np.max(np.abs(rec.x_B - clean)) <= 0.5 * q * (1 + 1e-9)
    assert np.std(rec.x_B - clean) == pytest.approx(q / np.sqrt(12), rel=0.1)  # the quantisation error
    noisy, _ = build_record(_sim_data(duration=1.0, noise_m=1e-6, noise_ar=0.5, quantum_m=q))
    assert np.max(np.abs(noisy.x_B / q - np.round(noisy.x_B / q))) < 1e-6  # rounding after the noise
    assert noisy.meta["noise"] == {"model": "ar1", "sigma_m": 1e-6, "ar": 0.5, "quantum_m": q}


def test_cycling_command_opens_and_closes_within_its_voltage_limit():
    from toggle_id.record import CYCLING
    from toggle_id.app.records import build_record

    rec, _ = build_record(_sim_data(command="cycling", noise_m=0.0))
    assert rec.sweep is None and rec.name == "simulated_cycling" and rec.meta["command"]["kind"] == "cycling"
    assert np.max(np.abs(rec.v_in)) <= 0.3 and rec.v_in[0] == 0.0 and CYCLING.v_max <= 0.3
    assert rec.v_in.min() < 0 < rec.v_in.max()  # it opens as well as closes
    x, x_L = rec.x_B, 0.056
    clamped = x >= x_L
    entries = np.flatnonzero(clamped[1:] & ~clamped[:-1])
    exits = np.flatnonzero(~clamped[1:] & clamped[:-1])
    assert len(entries) >= 3 and len(exits) >= 3, "the slider must reach the clamp and come back on several cycles"
    per_cycle = [x[(rec.t >= k * CYCLING.period) & (rec.t < (k + 1) * CYCLING.period)].max() for k in range(4)]
    assert sum(m < x_L for m in per_cycle) >= 1  # and one cycle stays short of it
    assert 0.015 < x.min() and x.max() < 0.07


def test_cycling_record_round_trips_through_csv_to_the_same_simulation(tmp_path):
    """The cycling command is defined by its samples: the simulated record and the same record read back from
    its CSV drive the simulator identically."""
    from toggle_id.data import read_csv, write_csv
    from toggle_id.app.records import build_record

    rec, truth = build_record(_sim_data(command="cycling", duration=2.0, noise_m=0.0, effects={"tau_d": 1e-3}))
    back = read_csv(write_csv(rec, tmp_path / "cyc.csv"))
    assert np.array_equal(back.v_in, rec.v_in) and np.array_equal(back.x_B, rec.x_B) and back.sweep is None
    again = simulate(truth[None], back, PRECISE)
    assert again.status[0] == 0
    np.testing.assert_array_equal(again.x_B[0], rec.x_B)


@pytest.mark.parametrize("override,needle", [
    ({"noise_ar": 1.0}, "data.noise_ar"), ({"noise_ar": -0.1}, "data.noise_ar"),
    ({"noise_ar": "strong"}, "data.noise_ar"), ({"noise_ar": float("nan")}, "data.noise_ar"),
    ({"quantum_m": -1e-6}, "data.quantum_m"), ({"quantum_m": float("inf")}, "data.quantum_m"),
    ({"quantum_m": "fine"}, "data.quantum_m"), ({"command": "zigzag"}, "data.command"),
    ({"noise_m": -1.0}, "data.noise_m"), ({"noise_seed": -3}, "data.noise_seed"),
    ({"noise_seed": 1.5}, "data.noise_seed"), ({"duration": 0.0}, "duration"),
    ({"outlier_fraction": 1.0}, "data.outlier_fraction"), ({"outlier_fraction": -0.01}, "data.outlier_fraction"),
    ({"outlier_m": -1e-6}, "data.outlier_m"), ({"outlier_m": "big"}, "data.outlier_m"),
])
def test_bad_synthetic_record_options_are_one_line_config_errors(override, needle):
    from toggle_id.app.records import build_record

    with pytest.raises(ConfigError, match=needle) as info:
        build_record(_sim_data(**override))
    assert "\n" not in str(info.value)


@pytest.mark.integration
def test_simulate_job_writes_a_cycling_record_and_rejects_bad_noise_in_one_line(tmp_path):
    from conftest import run_in_process, run_job

    from toggle_id.data import read_csv

    # the record in this process (the job's command line writing one: tests/test_jobs.py), the refusal as a user
    # meets it
    proc = run_in_process("jobs.simulate", "out=c.csv", "command=cycling", "duration=1.5", "noise_m=1e-6",
                          "noise_ar=0.5", "quantum_m=1e-6", "seed=4", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip().splitlines()[-1] == f"report: {tmp_path / 'c.csv'}"
    rec = read_csv(tmp_path / "c.csv")
    assert rec.n == 1501 and rec.v_in.min() < 0 < rec.v_in.max() and np.max(np.abs(rec.v_in)) <= 0.3
    assert np.max(np.abs(rec.x_B / 1e-6 - np.round(rec.x_B / 1e-6))) < 1e-6
    bad = run_job("jobs.simulate", "out=d.csv", "noise_ar=1.2", cwd=tmp_path, timeout=300)
    lines = [ln for ln in bad.stderr.splitlines() if ln.strip()]
    assert bad.returncode == 2 and len(lines) == 1 and "noise_ar" in lines[0], bad.stderr
    assert not (tmp_path / "d.csv").exists()


def test_the_machine_line_reads_steal_from_the_cpu_counters():
    """The suite's and the benchmark's machine line: steal is the 8th counter's share of the first eight."""
    from jobs.bench import machine_line, steal_share

    before = [100, 0, 50, 800, 0, 0, 0, 50, 0, 0]
    after = [400, 0, 150, 900, 0, 0, 0, 150, 0, 0]  # +300 user, +100 system, +100 idle, +100 steal
    assert steal_share(before, after) == pytest.approx(100 / 600)
    assert np.isnan(steal_share(None, after)) and np.isnan(steal_share(before[:5], after))
    line = machine_line(None, n=8)
    assert line.startswith("machine: ") and "steal unknown" in line


def test_bench_stops_prints_its_table_and_the_stops_remove_the_jitter(tmp_path, capsys):
    """``python -m jobs.bench_stops`` on 1-s sampled cycling records: one row per record, tier and setting, and on
    each record the precise tier with its stops has every forward-difference column within 1 % of the exact one,
    closer than stepping freely (6.5× a column's norm at worst there, measured); ``sampled`` and ``all`` are one
    thing on a sampled input."""
    from jobs.bench_stops import main

    rows = main(["--n", "1", "--repeat", "1", "--duration", "1", "--only", "cycling, sampled",
                 "--json", str(tmp_path / "stops.json")])
    out = capsys.readouterr().out
    assert "fd noise" in out and len(rows) == 12
    assert json.loads((tmp_path / "stops.json").read_text()) == rows
    for rec in ("cycling, sampled", "cycling, sampled, backlash 0.5 mm"):
        got = {(r["tier"], r["stops"]): r for r in rows if r["record"] == rec}
        assert set(got) == {(t, s) for t in ("PRECISE", "JACOBIAN") for s in ("none", "sampled", "all")}
        assert all(np.isfinite(r["ms_per_sim"]) and r["mean_steps"] > 0 for r in got.values())
        assert got["PRECISE", "sampled"]["fd_noise_worst"] < 1e-2 < got["PRECISE", "none"]["fd_noise_worst"], rec
        assert got["PRECISE", "sampled"]["mean_steps"] == got["PRECISE", "all"]["mean_steps"]  # the same steps
    with pytest.raises(SystemExit, match="no record name contains"):
        main(["--only", "no such record"])


def test_share_cores_sets_the_wait_policy_where_the_user_has_not():
    from toggle_id.simulate import SHARED_CORES_ENV, share_cores

    env = {"PATH": "/bin"}
    assert share_cores(env) is env and env == {"PATH": "/bin", **SHARED_CORES_ENV}
    assert share_cores({"OMP_WAIT_POLICY": "ACTIVE"}) == {"OMP_WAIT_POLICY": "ACTIVE"}


def test_the_shared_cores_benchmark_runs_processes_side_by_side():
    """``python -m jobs.bench --shared-cores`` in small: two processes at once, each a few batches of a short record;
    the total of their rates."""
    import os

    from jobs.bench import _side_by_side
    from toggle_id.simulate import share_cores

    env = share_cores({**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])})
    assert _side_by_side(2, env, 2, 0.2) > 0
    with pytest.raises(RuntimeError, match="shared-cores run failed"):
        _side_by_side(1, env, 2, -1.0)


def test_rows_with_backlash_run_the_kernel_compiled_apart_and_compile_kernels_names_its_kinds():
    """Rows with b_l > 0 go to the two-body integrator's own kernel (a process without backlash never compiles it),
    each row to its kernel in one call; an unknown kind is a one-line error."""
    from toggle_id.effects import ALL_INDEX
    from toggle_id.kernels.driver import lash_batch_serial, simulate_batch_serial
    from toggle_id.simulate import compile_kernels

    compile_kernels(("rigid", "lash"), parallel=False)
    assert simulate_batch_serial.signatures and lash_batch_serial.signatures
    rec = Record.from_sweep("simulation", duration=0.2)
    theta = extend(np.repeat(ASSIGNED[None], 3, axis=0))
    theta[1, ALL_INDEX["b_l"]] = 3e-4
    both = simulate(theta, rec, FAST)
    alone = [simulate(theta[k:k + 1], rec, FAST).x_B[0] for k in range(3)]
    np.testing.assert_array_equal(both.x_B, np.array(alone))
    assert np.max(np.abs(both.x_B[1] - both.x_B[0])) > 1e-7  # the lash acts: the row went to the two-body kernel
    with pytest.raises(ConfigError, match="unknown kinds"):
        compile_kernels(("elastic",))
