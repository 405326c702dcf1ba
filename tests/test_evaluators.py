"""Serial and Ray evaluators: same fitness bit for bit, whatever the workers, and after actors die."""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from conftest import wait_until_dead

from toggle_id.errors import ConfigError, DataError
from toggle_id.evaluators import RayEvaluator, SerialEvaluator, make_evaluator
from toggle_id.ga import GAConfig, run_ga

ray = pytest.importorskip("ray")
# Ray workers cannot import this test module by name: ship its classes by value.
ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])


class ToyProblem:
    """fitness = 1 / (1 + Σ (x - 0.3)²), with a count of setup calls (per process)."""

    def __init__(self, delay_s: float = 0.0) -> None:
        self.delay_s = delay_s
        self.setup_calls = 0

    def setup(self) -> None:
        self.setup_calls += 1

    def evaluate(self, X: np.ndarray) -> np.ndarray:
        if self.delay_s:
            time.sleep(self.delay_s)
        return 1.0 / (1.0 + np.sum((X - 0.3) ** 2, axis=1))


class CrashOnceProblem(ToyProblem):
    """The first process to evaluate anything dies abruptly (as a segfaulting worker would); later ones work."""

    def __init__(self, marker: str) -> None:
        super().__init__()
        self.marker = marker

    def evaluate(self, X: np.ndarray) -> np.ndarray:
        try:
            fd = os.open(self.marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            return super().evaluate(X)
        os.close(fd)
        os._exit(1)


class AlwaysCrashProblem(ToyProblem):
    def evaluate(self, X: np.ndarray) -> np.ndarray:
        os._exit(1)


class RaisingProblem(ToyProblem):
    def evaluate(self, X: np.ndarray) -> np.ndarray:
        raise ValueError("problem bug")


class WrongShapeProblem(ToyProblem):
    def evaluate(self, X: np.ndarray) -> np.ndarray:
        return np.zeros(X.shape[0] + 1)


@pytest.fixture
def population() -> np.ndarray:
    return np.random.default_rng(7).uniform(-1.0, 2.0, size=(37, 4))


# ---- serial ----------------------------------------------------------------------------------------------------


def test_serial_calls_setup_once_and_counts(population):
    problem = ToyProblem()
    with SerialEvaluator(problem) as ev:
        f1 = ev.evaluate(population)
        f2 = ev(population[:5])
    assert problem.setup_calls == 1
    np.testing.assert_array_equal(f1, ToyProblem().evaluate(population))
    np.testing.assert_array_equal(f2, f1[:5])
    assert ev.stats == {"calls": 2, "evaluations": 42, "restarts": 0}


def test_serial_rejects_bad_shapes(population):
    with pytest.raises(DataError, match="2-D"):
        SerialEvaluator(ToyProblem()).evaluate(population[0])
    with pytest.raises(DataError, match="shape"):
        SerialEvaluator(WrongShapeProblem()).evaluate(population)


def test_factory_and_option_errors():
    assert isinstance(make_evaluator("serial", ToyProblem()), SerialEvaluator)
    with pytest.raises(ConfigError, match="unknown evaluator kind"):
        make_evaluator("dask", ToyProblem())
    with pytest.raises(ConfigError, match="n_workers"):
        RayEvaluator(ToyProblem(), n_workers=0)
    with pytest.raises(ConfigError, match="n_workers"):
        make_evaluator("ray", ToyProblem(), n_workers=1.5)


# ---- ray -------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("n_workers", [1, 2])
def test_ray_matches_serial_bit_for_bit(ray_session, population, n_workers):
    expected = SerialEvaluator(ToyProblem()).evaluate(population)
    with make_evaluator("ray", ToyProblem(), n_workers=n_workers) as ev:
        assert len(ev.actors) == n_workers
        got = ev.evaluate(population)
        tiny = ev.evaluate(population[:1])  # fewer rows than workers
        empty = ev.evaluate(population[:0])
    np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(tiny, expected[:1])
    assert empty.shape == (0,)
    assert ev.stats == {"calls": 3, "evaluations": 38, "restarts": 0}
    assert ev.actors is None  # closed
    assert ray.is_initialized()  # the evaluator did not start Ray, so it must not stop it


@pytest.mark.parametrize("here", [True, False])
def test_ray_sets_the_problem_up_in_the_driver_first_unless_told_not_to(ray_session, population, here):
    """On a cold numba cache the workers then load what the driver compiled (``python -m jobs.bench --cold``)."""
    problem = ToyProblem()
    with RayEvaluator(problem, n_workers=1, setup_here=here) as ev:
        assert problem.setup_calls == (1 if here else 0)
        np.testing.assert_array_equal(ev.evaluate(population), ToyProblem().evaluate(population))


def test_ray_replaces_actor_killed_between_evaluations(ray_session, population):
    expected = SerialEvaluator(ToyProblem()).evaluate(population)
    with RayEvaluator(ToyProblem(), n_workers=2) as ev:
        np.testing.assert_array_equal(ev.evaluate(population), expected)
        killed = ev.actors[1]
        ray.kill(killed)
        wait_until_dead(killed)
        np.testing.assert_array_equal(ev.evaluate(population), expected)
        assert ev.stats["restarts"] == 1
        assert ev.actors[1] is not killed
        np.testing.assert_array_equal(ev.evaluate(population), expected)
        assert ev.stats["restarts"] == 1


def test_ray_replaces_actor_killed_during_evaluation(ray_session, population, tmp_path):
    expected = SerialEvaluator(ToyProblem()).evaluate(population)
    marker = str(tmp_path / "crashed")
    with RayEvaluator(CrashOnceProblem(marker), n_workers=2) as ev:
        got = ev.evaluate(population)
        assert os.path.exists(marker)  # one actor really did die mid-evaluation
        assert ev.stats["restarts"] == 1
    np.testing.assert_array_equal(got, expected)


def test_ray_gives_up_after_max_restarts(ray_session, population):
    with RayEvaluator(AlwaysCrashProblem(), n_workers=1, max_restarts=2) as ev:
        with pytest.raises(RuntimeError, match="giving up"):
            ev.evaluate(population)
        assert ev.stats["restarts"] == 2


def test_ray_problem_errors_propagate(ray_session, population):
    with RayEvaluator(RaisingProblem(), n_workers=1) as ev:
        with pytest.raises(ValueError, match="problem bug"):
            ev.evaluate(population)
        assert ev.stats["restarts"] == 0
    with RayEvaluator(WrongShapeProblem(), n_workers=2) as ev:
        with pytest.raises(DataError, match="shape"):
            ev.evaluate(population)


def test_ga_run_identical_serial_and_ray(ray_session):
    config = GAConfig(population=40, generations=15)
    lower, upper = np.full(3, -1.0), np.full(3, 2.0)
    serial = run_ga(SerialEvaluator(ToyProblem()), lower, upper, config, seed=11)
    with RayEvaluator(ToyProblem(), n_workers=2) as ev:
        parallel = run_ga(ev, lower, upper, config, seed=11)
    np.testing.assert_array_equal(parallel.best_x, serial.best_x)
    assert parallel.history == serial.history
    assert serial.n_evaluations == 40 * 15
    assert serial.best_fitness > 0.99  # it did optimise: the optimum is 1 at x = 0.3


_MULTI_NODE_SCRIPT = textwrap.dedent("""
    import sys, numpy as np, ray
    from ray.cluster_utils import Cluster
    sys.path.insert(0, {tests!r})
    import test_evaluators as t
    ray.cloudpickle.register_pickle_by_value(t)
    from toggle_id.evaluators import RayEvaluator, SerialEvaluator
    # head without CPUs, three 1-CPU worker nodes: two actors on two nodes, one node spare
    cluster = Cluster(initialize_head=True, head_node_args={{"num_cpus": 0, "include_dashboard": False}})
    workers = [cluster.add_node(num_cpus=1) for _ in range(3)]
    try:
        cluster.wait_for_nodes()
        ray.init(address=cluster.address, log_to_driver=False)
        X = np.random.default_rng(3).random((25, 4))
        expected = SerialEvaluator(t.ToyProblem()).evaluate(X)
        with RayEvaluator(t.ToyProblem(), n_workers=2, address=cluster.address, ready_timeout_s=60) as ev:
            assert np.array_equal(ev.evaluate(X), expected)
            nodes = [ray.get(a.ready.remote())["node_id"] for a in ev.actors]
            assert len(set(nodes)) == 2, nodes
            victim = next(w for w in workers if w.node_id == nodes[0])
            cluster.remove_node(victim)  # the node of actor 0 fails
            assert np.array_equal(ev.evaluate(X), expected)
            assert ev.stats["restarts"] >= 1, ev.stats
            moved = ray.get(ev.actors[0].ready.remote())["node_id"]
            assert moved not in (nodes[0], nodes[1]), (moved, nodes)
    finally:
        ray.shutdown()
        cluster.shutdown()
    print("MULTI-NODE-OK")
""")


@pytest.mark.slow
def test_ray_multi_node_cluster_survives_node_loss():
    """A multi-node cluster: actors spread over nodes; losing a node's actor still gives the serial fitness."""
    script = _MULTI_NODE_SCRIPT.format(tests=os.path.dirname(__file__))
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([root, os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=180,
                          cwd=root, env=env)
    assert "MULTI-NODE-OK" in proc.stdout, proc.stdout[-2000:] + proc.stderr[-4000:]


def test_the_ray_readiness_timeout_is_a_checked_setting():
    from toggle_id.app.common import evaluator_factory

    for bad in (0, -5, "soon", True):
        with pytest.raises(ConfigError, match="ready_timeout_s"):
            evaluator_factory({"kind": "ray", "ready_timeout_s": bad})
    assert callable(evaluator_factory({"kind": "ray", "ready_timeout_s": 30}))
