"""Identification pipelines: recovery on a simulated record, determinism across evaluators, checkpoints and
resume, fault tolerance of Ray actors during a run."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import wait_until_dead

from toggle_id import params as P
from toggle_id.errors import CheckpointError, ConfigError
from toggle_id.evaluators import RayEvaluator, SerialEvaluator
from toggle_id.ga import GAConfig
from toggle_id.identify import identify
from toggle_id.record import Record
from toggle_id.simulate import PRECISE, simulate
from toggle_id.stages import PolishSettings


def _record(duration: float, noise: float = 1e-6, seed: int = 0) -> Record:
    rec = Record.from_sweep("simulation", duration=duration)
    sim = simulate(P.ASSIGNED[None], rec, PRECISE)
    rec.x_B = sim.x_B[0] + noise * np.random.default_rng(seed).standard_normal(rec.n)
    rec.i_q = sim.i_q[0]
    return rec


def _near_truth_bounds(rel: float) -> dict:
    return {n: [a * (1 - rel), a * (1 + rel)] for n, a in zip(P.PARAM_NAMES, P.ASSIGNED)}


NO_POLISH = PolishSettings(enabled=False)


def test_two_stage_fit_reaches_the_noise_level():
    """A short two-stage run (GA in ±30 % domains, then the polish) fits a 1-µm-noise record to ~1 µm RMS."""
    rec = _record(1.5)
    res = identify(rec, method="two_stage", ga=GAConfig(population=40, generations=8), seed=1,
                   bounds=_near_truth_bounds(0.3), polish=PolishSettings(max_nfev=40), identifiability=False)
    assert [s.name for s in res.stages] == ["stage1", "stage2", "joint_polish"]
    assert res.rmse_m < 1.5e-6, res.rmse_m
    assert all(s.fitness >= s.fitness_ga * 0.999 for s in res.stages if s.generations)  # polish never worsens


def test_two_stage_needs_the_clamping_instant():
    rec = _record(0.2)  # ends before the slider reaches x_B^L
    with pytest.raises(ConfigError, match="clamping"):
        identify(rec, method="two_stage", ga=GAConfig(population=4, generations=1), polish=NO_POLISH,
                 identifiability=False)


def test_same_seed_same_result_serial_and_ray_1_or_2_workers(ray_session):
    rec = _record(0.6)
    kw = dict(method="two_stage", ga=GAConfig(population=24, generations=4), seed=7, polish=NO_POLISH,
              identifiability=False)
    serial = identify(rec, make_evaluator=SerialEvaluator, **kw)
    for n in (1, 2):
        par = identify(rec, make_evaluator=lambda p, n=n: RayEvaluator(p, n_workers=n), **kw)
        np.testing.assert_array_equal(par.theta, serial.theta)
        assert [s.history for s in par.stages] == [s.history for s in serial.stages]


def test_killed_actor_mid_run_gives_the_fault_free_result(ray_session):
    import ray

    rec = _record(0.6)
    kw = dict(method="one_stage", ga=GAConfig(population=24, generations=5), seed=3, polish=NO_POLISH,
              identifiability=False)
    clean = identify(rec, make_evaluator=SerialEvaluator, **kw)
    made = []

    def make(problem):
        made.append(RayEvaluator(problem, n_workers=2))
        return made[-1]

    def kill(stage, ga):
        if ga.generation in (2, 4):
            actor = made[-1].actors[0]
            ray.kill(actor, no_restart=True)
            wait_until_dead(actor)

    faulty = identify(rec, make_evaluator=make, on_generation=kill, **kw)
    np.testing.assert_array_equal(faulty.theta, clean.theta)
    assert made[-1].stats["restarts"] == 2


class _Interrupt(Exception):
    pass


def _interrupt_and_resume(tmp_path, rec, stage: str, gen: int, **kw):
    """The uninterrupted result, and the result of a run stopped in ``stage`` at generation ``gen`` and resumed
    from its checkpoint."""
    full = identify(rec, **kw)

    def stop(name, ga):
        if name == stage and ga.generation == gen:
            raise _Interrupt

    with pytest.raises(_Interrupt):
        identify(rec, checkpoint_dir=tmp_path, checkpoint_every=1, on_generation=stop, **kw)
    return full, identify(rec, checkpoint_dir=tmp_path, checkpoint_every=1, resume=True, **kw)


@pytest.mark.parametrize("stage,gen", [("stage1", 2), ("stage2", 3)])
def test_interrupted_run_resumes_to_the_uninterrupted_result(tmp_path, stage, gen):
    full, resumed = _interrupt_and_resume(tmp_path, _record(0.6), stage, gen, method="two_stage",
                                          ga=GAConfig(population=16, generations=5), seed=11, polish=NO_POLISH,
                                          identifiability=False)
    np.testing.assert_array_equal(resumed.theta, full.theta)
    assert [s.history for s in resumed.stages] == [s.history for s in full.stages]


@pytest.mark.parametrize("damage", ["truncate", "tamper", "json"])
def test_truncated_or_tampered_checkpoint_is_rejected(tmp_path, damage):
    rec = _record(0.6)
    kw = dict(method="one_stage", ga=GAConfig(population=8, generations=2), seed=0, polish=NO_POLISH,
              identifiability=False, checkpoint_dir=tmp_path, checkpoint_every=1)
    identify(rec, **kw)
    npz, js = tmp_path / "checkpoint.npz", tmp_path / "checkpoint.json"
    if damage == "truncate":
        npz.write_bytes(npz.read_bytes()[: npz.stat().st_size // 2])
    elif damage == "tamper":
        data = bytearray(npz.read_bytes())
        data[len(data) // 2] ^= 0xFF
        npz.write_bytes(bytes(data))
    else:
        js.write_text(js.read_text()[:-20])
    with pytest.raises(CheckpointError):
        identify(rec, resume=True, **kw)


def test_fixed_parameters_stay_fixed():
    rec = _record(0.6)
    res = identify(rec, method="one_stage", ga=GAConfig(population=8, generations=2), fixed={"K_i": 100.0},
                   polish=NO_POLISH, identifiability=False)
    assert res.params["K_i"] == 100.0
    assert "K_i" not in res.stages[0].free


# ------------------------------------------------------------------------------------------ joint (multi-record)
def _clean_record(sweep: str, duration: float = 1.0) -> Record:
    rec = Record.from_sweep(sweep, duration=duration, name=f"clean_{sweep}")
    sim = simulate(P.ASSIGNED[None], rec, PRECISE)
    rec.x_B, rec.i_q = sim.x_B[0], sim.i_q[0]
    return rec


def test_joint_problem_stacks_residuals_and_sums_sse():
    from toggle_id.problem import FitProblem, JointProblem, joint

    recs = [_clean_record("simulation"), _clean_record("experiment")]
    free = ("K_t", "B_m", "mu")
    probs = [FitProblem(r, free, P.ASSIGNED, (0, r.n)) for r in recs]
    jp = JointProblem(probs)
    X = jp.x0()[None, :] * np.array([[1.0, 1.0, 1.0], [1.01, 0.98, 1.02], [0.97, 1.03, 1.0]])
    np.testing.assert_allclose(jp.sse(X), probs[0].sse(X) + probs[1].sse(X), rtol=1e-12)
    assert jp.residuals(X).shape == (3, recs[0].n + recs[1].n) == (3, jp.n_residuals)
    f = jp.evaluate(X[1:])
    np.testing.assert_allclose(f, 1.0 / (probs[0].sse(X[1:]) + probs[1].sse(X[1:])), rtol=1e-12)
    assert joint(probs[:1]) is probs[0]
    with pytest.raises(ConfigError, match="same parameters"):
        JointProblem([probs[0], FitProblem(recs[1], ("K_t",), P.ASSIGNED, (0, recs[1].n))])


def test_joint_two_stage_fit_reports_identifiability_of_both_records():
    """Two noise-free records (both sweeps), six parameters fixed: every stage is fitted on both records, the
    final joint polish's identifiability report stacks their residuals and is self-consistent."""
    recs = [_clean_record("simulation"), _clean_record("experiment")]
    fixed = {n: float(P.ASSIGNED[P.INDEX[n]]) for n in ("K_i", "J_m", "L_q", "m_2", "m_3", "m_5")}
    res = identify(recs, method="two_stage", ga=GAConfig(population=16, generations=3), seed=2, fixed=fixed,
                   bounds=_near_truth_bounds(0.1), polish=PolishSettings(n_starts=1, max_nfev=4),
                   noise_var=1e-12)
    assert [s.name for s in res.stages] == ["stage1", "stage2", "joint_polish"]
    from toggle_id.plant import GEOMETRY

    k_c = [r.clamp_index(GEOMETRY.x_B_L) for r in recs]
    assert res.stages[0].windows == ((0, k_c[0]), (0, k_c[1]))
    assert res.stages[1].windows == ((k_c[0], recs[0].n), (k_c[1], recs[1].n))
    final = res.stages[-1]
    assert final.windows == ((0, recs[0].n), (0, recs[1].n))
    rep = final.identifiability
    names = rep["param_order"]
    assert names == list(final.free) and not set(fixed) & set(names) and len(names) == 9
    assert rep["m"] == recs[0].n + recs[1].n  # the residual vector of both records
    assert len(rep["singular_values"]) == len(names) and 0 < rep["rank"] <= len(names)
    assert len(rep["null_directions"]) == len(names) - rep["rank"]
    assert set(rep["ci95"]) == set(rep["std_errors"]) == set(names)
    for n in names:
        if rep["identifiable"][n]:
            lo, hi = rep["ci95"][n]
            assert lo <= rep["values"][n] <= hi
    recs_out = res.extra["records"]
    assert [r["name"] for r in recs_out] == ["clean_simulation", "clean_experiment"]
    assert [r["clamp_index"] for r in recs_out] == k_c
    assert res.n_samples == recs[0].n + recs[1].n
    assert res.sse == pytest.approx(sum(r["sse_m2"] for r in recs_out), rel=1e-12)
    assert res.params["K_i"] == fixed["K_i"]


def test_joint_fit_same_seed_same_result_serial_and_ray(ray_session):
    recs = [_record(0.6), _clean_record("experiment", 0.6)]
    kw = dict(method="two_stage", ga=GAConfig(population=24, generations=3), seed=5, polish=NO_POLISH,
              identifiability=False)
    serial = identify(recs, make_evaluator=SerialEvaluator, **kw)
    par = identify(recs, make_evaluator=lambda p: RayEvaluator(p, n_workers=2), **kw)
    np.testing.assert_array_equal(par.theta, serial.theta)
    assert [s.history for s in par.stages] == [s.history for s in serial.stages]


def test_interrupted_joint_run_resumes_to_the_uninterrupted_result(tmp_path):
    recs = [_record(0.6), _clean_record("experiment", 0.6)]
    full, resumed = _interrupt_and_resume(tmp_path, recs, "stage2", 2, method="two_stage",
                                          ga=GAConfig(population=16, generations=4), seed=4, polish=NO_POLISH,
                                          identifiability=False)
    np.testing.assert_array_equal(resumed.theta, full.theta)
    assert [s.windows for s in resumed.stages] == [s.windows for s in full.stages]
    assert [s.history for s in resumed.stages] == [s.history for s in full.stages]
