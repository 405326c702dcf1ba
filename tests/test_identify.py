"""Identification pipelines: recovery on a simulated record, determinism across evaluators, checkpoints and
resume, fault tolerance of Ray actors during a run."""
from __future__ import annotations

import numpy as np
import pytest

from toggle_id import params as P
from toggle_id.errors import CheckpointError, ConfigError
from toggle_id.evaluators import RayEvaluator, SerialEvaluator, init_ray
from toggle_id.ga import GAConfig
from toggle_id.identify import PolishSettings, identify
from toggle_id.record import Record
from toggle_id.simulate import PRECISE, simulate


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


@pytest.fixture(scope="module")
def ray_session():
    import ray

    started = init_ray(num_cpus=2)
    yield
    if started:
        ray.shutdown()


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
            with pytest.raises(ray.exceptions.RayActorError):  # asynchronous: wait until it is dead
                ray.get(actor.ready.remote(), timeout=60)

    faulty = identify(rec, make_evaluator=make, on_generation=kill, **kw)
    np.testing.assert_array_equal(faulty.theta, clean.theta)
    assert made[-1].stats["restarts"] == 2


class _Interrupt(Exception):
    pass


@pytest.mark.parametrize("stage,gen", [("stage1", 2), ("stage2", 3)])
def test_interrupted_run_resumes_to_the_uninterrupted_result(tmp_path, stage, gen):
    rec = _record(0.6)
    kw = dict(method="two_stage", ga=GAConfig(population=16, generations=5), seed=11, polish=NO_POLISH,
              identifiability=False)
    full = identify(rec, **kw)

    def stop(name, ga):
        if name == stage and ga.generation == gen:
            raise _Interrupt

    with pytest.raises(_Interrupt):
        identify(rec, checkpoint_dir=tmp_path, checkpoint_every=1, on_generation=stop, **kw)
    resumed = identify(rec, checkpoint_dir=tmp_path, checkpoint_every=1, resume=True, **kw)
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
