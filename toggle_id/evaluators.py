"""Population evaluators: one interface, ``evaluate(X (P, n)) -> fitness (P,)``, serial or on Ray actors.

The thing evaluated is a *problem*: a picklable object with

* ``setup()`` — compile / warm up; called once per process that evaluates (once per Ray actor);
* ``evaluate(X) -> ndarray`` — fitness of each row of ``X`` (P, n); row i's fitness depends only on row i,
  so the result does not depend on how the population is chunked.

Evaluators own no randomness and never reorder rows, so for a row-deterministic problem every evaluator,
whatever its number of workers, returns the same array bit for bit.

Ray and the network (Ray 2.60, read from its ``ray/_private/worker.py``, ``services.py`` and
``authentication/authentication_token_setup.py``): a local Ray started here gets ``include_dashboard=False``
and ``_node_ip_address="127.0.0.1"``, but Ray re-resolves a loopback node address to the machine's routable
IP (``services.resolve_ip_for_localhost``) and its gRPC servers (GCS, raylet, workers) bind the wildcard
address, so ``ray.init`` cannot confine a cluster to loopback. What protects it is token authentication:
a new local cluster turns it on by default when ``RAY_AUTH_MODE`` is unset (``enable_token_auth_by_default``;
the token is generated once into ``~/.ray/auth_token``). This module never turns it off and logs a warning
when the environment has ``RAY_AUTH_MODE=disabled``.
"""
from __future__ import annotations

import logging
import os
from typing import Any, Mapping, Optional, Protocol, runtime_checkable

import numpy as np

from toggle_id.errors import ConfigError, DataError

log = logging.getLogger(__name__)

#: Errors that mean "this actor is gone": replace it and evaluate its chunk again.
_ACTOR_LOST_NAMES = ("RayActorError", "ActorDiedError", "ActorUnavailableError")


@runtime_checkable
class Problem(Protocol):
    """What evaluators evaluate (see the module docstring)."""

    def setup(self) -> None:
        """Compile / warm up; called once per evaluating process."""

    def evaluate(self, X: np.ndarray) -> np.ndarray:
        """Fitness (P,) of the rows of ``X`` (P, n)."""


def _check_population(X: np.ndarray) -> np.ndarray:
    """``X`` as a float64 (P, n) array; DataError otherwise."""
    arr = np.asarray(X, dtype=float)
    if arr.ndim != 2:
        raise DataError(f"population must be a 2-D array (P, n), got shape {arr.shape}")
    return arr


def _check_fitness(values: Any, n_rows: int) -> np.ndarray:
    """A problem's output as a float64 (n_rows,) array; DataError otherwise."""
    f = np.asarray(values, dtype=float)
    if f.shape != (n_rows,):
        raise DataError(f"problem.evaluate returned shape {f.shape} for {n_rows} rows; expected ({n_rows},)")
    return f


def _check_workers(n_workers: Optional[int]) -> Optional[int]:
    if n_workers is None:
        return None
    if isinstance(n_workers, bool) or not isinstance(n_workers, (int, np.integer)) or n_workers < 1:
        raise ConfigError(f"n_workers must be a positive integer or None, got {n_workers!r}")
    return int(n_workers)


class _EvaluatorBase:
    """Shared bookkeeping: ``stats`` and the context-manager protocol."""

    def __init__(self) -> None:
        self.stats: dict[str, int] = {"calls": 0, "evaluations": 0, "restarts": 0}

    def evaluate(self, X: np.ndarray) -> np.ndarray:  # pragma: no cover - interface
        raise NotImplementedError

    def __call__(self, X: np.ndarray) -> np.ndarray:
        """Same as :meth:`evaluate`, so an evaluator can be passed where a function is expected."""
        return self.evaluate(X)

    def close(self) -> None:
        """Release workers; idempotent."""

    def __enter__(self) -> "_EvaluatorBase":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class SerialEvaluator(_EvaluatorBase):
    """Evaluate in this process: ``problem.setup()`` once at construction, then ``problem.evaluate(X)``."""

    def __init__(self, problem: Problem) -> None:
        super().__init__()
        self.problem = problem
        problem.setup()

    def evaluate(self, X: np.ndarray) -> np.ndarray:
        """Fitness (P,) of the rows of ``X`` (P, n)."""
        X = _check_population(X)
        f = _check_fitness(self.problem.evaluate(X), X.shape[0]) if X.shape[0] else np.zeros(0)
        self.stats["calls"] += 1
        self.stats["evaluations"] += X.shape[0]
        return f


# ----------------------------------------------------------------------------------------------------------------
# Ray
# ----------------------------------------------------------------------------------------------------------------

_ACTOR_CLASS = None


def _actor_class():
    """The Ray actor class, defined on first use so that importing this module does not import Ray."""
    global _ACTOR_CLASS
    if _ACTOR_CLASS is None:
        import ray

        @ray.remote(num_cpus=1, max_restarts=0)
        class ProblemActor:
            """Holds one problem: built and set up once, then evaluates chunks."""

            def __init__(self, problem: Problem) -> None:
                self._problem = problem
                problem.setup()

            def ready(self) -> dict[str, Any]:
                """``{"pid", "node_id"}`` of this worker (a cheap call that returns once ``setup`` is done)."""
                return {"pid": os.getpid(), "node_id": ray.get_runtime_context().get_node_id()}

            def evaluate(self, chunk_index: int, X: np.ndarray) -> tuple[int, np.ndarray]:
                """(chunk_index, fitness of the rows of X)."""
                return chunk_index, np.asarray(self._problem.evaluate(X), dtype=float)

        _ACTOR_CLASS = ProblemActor
    return _ACTOR_CLASS


def _is_actor_lost(err: BaseException) -> bool:
    import ray.exceptions as rex

    return isinstance(err, tuple(getattr(rex, name) for name in _ACTOR_LOST_NAMES if hasattr(rex, name)))


def init_ray(num_cpus: Optional[int] = None, address: Optional[str] = None,
             log_to_driver: bool = False, **kwargs: Any) -> bool:
    """Start or join Ray unless it is already initialised; return True when this call initialised it.

    ``address=None`` starts a local instance with ``num_cpus`` CPUs (None: all), no dashboard, token
    authentication left at Ray's default (on); ``address="auto"`` or ``"host:port"`` joins a running cluster.
    Extra ``kwargs`` go to ``ray.init``.
    """
    import ray

    if ray.is_initialized():
        return False
    if os.environ.get("RAY_AUTH_MODE", "").lower() == "disabled":
        log.warning("RAY_AUTH_MODE=disabled: this Ray cluster accepts unauthenticated connections")
    options: dict[str, Any] = dict(ignore_reinit_error=True, log_to_driver=log_to_driver)
    if address is None:
        options.update(num_cpus=num_cpus, include_dashboard=False, _node_ip_address="127.0.0.1")
    else:
        options.update(address=address)
    options.update(kwargs)
    ray.init(**options)
    return True


class RayEvaluator(_EvaluatorBase):
    """Evaluate on ``n_workers`` Ray actors, one contiguous chunk of the population per actor.

    Args:
        problem: picklable problem; put in the object store once, built and set up once per actor.
        n_workers: actors (each reserves 1 CPU); None: the CPUs of the local machine (``address=None``) or of
            the cluster.
        address: None starts a local Ray if none is running; ``"auto"`` / ``"host:port"`` joins a cluster.
        max_restarts: actor replacements allowed within one :meth:`evaluate` call before giving up.
        ready_timeout_s: seconds to wait for all actors to finish ``setup`` (s).
        init_kwargs: extra arguments for ``ray.init`` when this evaluator starts Ray.

    Fault tolerance: when an actor dies (``RayActorError`` and subclasses), it is replaced by a new actor and its
    chunk is evaluated again, so the result equals a fault-free run; ``stats["restarts"]`` counts replacements.
    Errors raised by the problem itself propagate. :meth:`close` kills the actors and shuts Ray down only if this
    evaluator started it.
    """

    def __init__(self, problem: Problem, n_workers: Optional[int] = None, address: Optional[str] = None,
                 max_restarts: int = 10, ready_timeout_s: float = 600.0,
                 init_kwargs: Optional[Mapping[str, Any]] = None) -> None:
        super().__init__()
        n_workers = _check_workers(n_workers)
        if isinstance(max_restarts, bool) or not isinstance(max_restarts, int) or max_restarts < 0:
            raise ConfigError(f"max_restarts must be a non-negative integer, got {max_restarts!r}")
        import ray

        self._ray = ray
        num_cpus = n_workers if n_workers is not None else (os.cpu_count() or 1)
        self._owns_ray = init_ray(num_cpus=num_cpus if address is None else None, address=address,
                                  **dict(init_kwargs or {}))
        if n_workers is None:
            n_workers = max(1, int(ray.cluster_resources().get("CPU", 1)))
        self.n_workers = n_workers
        self.max_restarts = max_restarts
        self._problem_ref = ray.put(problem)
        self.actors = [self._new_actor() for _ in range(n_workers)]
        try:
            ray.get([a.ready.remote() for a in self.actors], timeout=ready_timeout_s)
        except ray.exceptions.GetTimeoutError as err:
            cpus = ray.cluster_resources().get("CPU", 0)
            self.close()
            raise ConfigError(f"{n_workers} Ray workers not ready after {ready_timeout_s:g} s (cluster has {cpus:g} "
                              "CPUs; each worker compiles or loads the kernels first, slowly on a busy machine): "
                              "raise evaluator.ready_timeout_s or use evaluator=serial") from err
        except BaseException:
            self.close()
            raise

    def _new_actor(self):
        return _actor_class().remote(self._problem_ref)

    def _replace_actor(self, index: int) -> None:
        """Kill actor ``index`` (if it still lingers) and start a fresh one in its place."""
        try:
            self._ray.kill(self.actors[index], no_restart=True)
        except Exception:  # already dead / unreachable: nothing to kill
            pass
        self.actors[index] = self._new_actor()
        self.stats["restarts"] += 1

    def evaluate(self, X: np.ndarray) -> np.ndarray:
        """Fitness (P,) of the rows of ``X`` (P, n), computed in one chunk per actor; order preserved."""
        ray = self._ray
        if self.actors is None:
            raise RuntimeError("evaluate() called on a closed RayEvaluator")
        X = _check_population(X)
        n_rows = X.shape[0]
        chunks = [c for c in np.array_split(np.arange(n_rows), len(self.actors)) if c.size]
        results: list[Optional[np.ndarray]] = [None] * len(chunks)
        pending: dict[Any, tuple[int, int]] = {}  # ref -> (chunk index, actor index)

        def submit(chunk_index: int, actor_index: int) -> None:
            rows = X[chunks[chunk_index]]
            pending[self.actors[actor_index].evaluate.remote(chunk_index, rows)] = (chunk_index, actor_index)

        for i in range(len(chunks)):
            submit(i, i)
        restarts_here = 0
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            ref = done[0]
            chunk_index, actor_index = pending.pop(ref)
            try:
                got_index, fitness = ray.get(ref)
            except Exception as err:
                if not _is_actor_lost(err):
                    raise
                restarts_here += 1
                if restarts_here > self.max_restarts:
                    raise RuntimeError(f"Ray actors died {restarts_here} times in one evaluation "
                                       f"(max_restarts={self.max_restarts}); giving up") from err
                log.warning("Ray actor %d lost (%s); replacing it and re-evaluating chunk %d",
                            actor_index, type(err).__name__, chunk_index)
                self._replace_actor(actor_index)
                submit(chunk_index, actor_index)
                continue
            results[got_index] = _check_fitness(fitness, chunks[got_index].size)
        self.stats["calls"] += 1
        self.stats["evaluations"] += n_rows
        return np.concatenate(results) if results else np.zeros(0)

    def close(self) -> None:
        """Kill the actors; shut Ray down if this evaluator started it. Idempotent."""
        actors, self.actors = getattr(self, "actors", None), None
        for actor in actors or ():
            try:
                self._ray.kill(actor, no_restart=True)
            except Exception:  # already gone
                pass
        if getattr(self, "_owns_ray", False):
            self._owns_ray = False
            self._ray.shutdown()


def make_evaluator(kind: str, problem: Problem, n_workers: Optional[int] = None,
                   address: Optional[str] = None, **kwargs: Any) -> _EvaluatorBase:
    """``"serial"`` → :class:`SerialEvaluator`; ``"ray"`` → :class:`RayEvaluator` (extra kwargs go to it)."""
    if kind == "serial":
        if kwargs:
            raise ConfigError(f"serial evaluator takes no options, got {', '.join(sorted(kwargs))}")
        return SerialEvaluator(problem)
    if kind == "ray":
        return RayEvaluator(problem, n_workers=n_workers, address=address, **kwargs)
    raise ConfigError(f"unknown evaluator kind {kind!r}; known: serial, ray")
