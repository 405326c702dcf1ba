"""Population evaluators: one interface, ``evaluate(X (P, n)) -> fitness (P,)``, serial or on Ray actors.

The thing evaluated is a *problem*: a picklable object with

* ``setup()`` — compile / warm up; called once per process that evaluates (once per Ray actor);
* ``evaluate(X) -> ndarray`` — fitness of each row of ``X`` (P, n); row i's fitness depends only on row i,
  so the result does not depend on how the population is chunked.

Evaluators own no randomness and never reorder rows, so for a row-deterministic problem every evaluator,
whatever its number of workers, returns the same array bit for bit.

Ray and the network (Ray 2.60, read from its modules ``ray._private.worker``, ``ray._private.services`` and
``ray._private.authentication.authentication_token_setup``): a local Ray started here gets ``include_dashboard=False``
and ``_node_ip_address="127.0.0.1"``, but Ray re-resolves a loopback node address to the machine's routable
IP (``services.resolve_ip_for_localhost``) and its gRPC servers (GCS, raylet, workers) bind the wildcard
address, so ``ray.init`` cannot confine a cluster to loopback. What protects it is token authentication:
a new local cluster turns it on by default when ``RAY_AUTH_MODE`` is unset (``enable_token_auth_by_default``;
the token is generated once into ``~/.ray/auth_token``). This module never turns it off and logs a warning
when the environment has ``RAY_AUTH_MODE=disabled``.

Local or joined (read from the same files and measured): ``address=None`` starts its own local Ray with
``ray.init(address="local")``. Plain ``ray.init()`` would join the cluster named by ``RAY_ADDRESS`` or recorded in
the ``ray_current_cluster`` file of Ray's temporary directory by the last ``ray start``, and it waits minutes when that head has died.
Joining (``"auto"``, ``"host:port"``) is checked first by :func:`join_address`: the cluster must answer within
seconds, and the token is sent when one is found. Ray sends it by itself only when it found the cluster on its own.
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
             log_to_driver: bool = False, connect_timeout_s: float = 10.0, ship_code: bool = True,
             **kwargs: Any) -> bool:
    """Start or join Ray unless it is already initialised; return True when this call initialised it.

    ``address=None`` always starts a new local instance (``ray.init(address="local")``: a ``RAY_ADDRESS`` in the
    environment or a cluster recorded on the machine by ``ray start``, live or dead, is never joined) with
    ``num_cpus`` CPUs (None: all), no dashboard, token authentication left at Ray's default (on).
    ``address="auto"`` or ``"host:port"`` joins a running cluster (:func:`join_address`): it is found and checked
    within ``connect_timeout_s`` seconds, with the cluster's token when this machine has one; any failure is a
    one-line ConfigError naming the fix. ``ship_code``: when joining, this ``toggle_id`` package goes to the
    cluster's workers (:func:`code_runtime_env`), so they run the driver's code whether or not the nodes have it
    installed (they need its dependencies). Extra ``kwargs`` go to ``ray.init``.
    """
    import ray

    if ray.is_initialized():
        return False
    if os.environ.get("RAY_AUTH_MODE", "").lower() == "disabled":
        log.warning("RAY_AUTH_MODE=disabled: this Ray cluster accepts unauthenticated connections")
    options: dict[str, Any] = dict(ignore_reinit_error=True, log_to_driver=log_to_driver)
    if address is None:
        options.update(address="local", num_cpus=num_cpus, include_dashboard=False, _node_ip_address="127.0.0.1")
        options.update(kwargs)
        ray.init(**options)
        return True
    target = join_address(address, connect_timeout_s)
    options.update(address=target)
    if ship_code:
        options.update(runtime_env=code_runtime_env())
    options.update(kwargs)
    try:
        ray.init(**options)
    except Exception as err:  # the checks passed, yet Ray refused (e.g. another Ray version on the cluster)
        text = " ".join(str(err).split())[:300] or type(err).__name__
        raise ConfigError(f"could not join the Ray cluster at {target}: {text}") from None
    return True


# ---- joining a cluster -------------------------------------------------------------------------------------------

#: What to do instead, appended to every "cannot join" message.
_JOIN_FIX = "or leave evaluator.address unset (null) to start a local Ray"

# Run in a fresh interpreter (its stderr, where Ray's C++ client logs, is kept out of the job's): connect a GCS
# client to argv[1] within argv[2] ms. Exit 0: a Ray head answered and accepted us; 3: authentication refused;
# 4: any other failure.
_PROBE = r"""
import sys
try:
    from ray._raylet import InnerGcsClient
    InnerGcsClient.standalone(sys.argv[1], None, int(sys.argv[2]))
except Exception as err:
    text = type(err).__name__ + ": " + " ".join(str(err).split())
    print(text[:400])
    sys.exit(3 if "Authentication" in text or "InvalidAuthToken" in text else 4)
"""


def _split_address(address: str) -> tuple[str, int]:
    """``host:port`` (``[v6]:port`` too) → (host, port); ConfigError naming the expected form otherwise."""
    text = str(address).strip()
    host, sep, port = text.rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536 or "/" in text:
        raise ConfigError(f"evaluator.address {address!r} is not a Ray cluster address: give HOST:PORT of the "
                          f"head (the --port of `ray start --head`, default 6379) or auto, {_JOIN_FIX}")
    return host, int(port)


def _auto_address() -> tuple[str, str]:
    """The cluster ``address="auto"`` means: RAY_ADDRESS, else the one the last ``ray start`` on this machine
    recorded (Ray's ``ray_current_cluster`` file); (address, where it came from). Unlike Ray's own "auto", a
    private ``ray.init()`` instance of another process is never picked."""
    env = os.environ.get("RAY_ADDRESS", "").strip()
    if env:
        return env, "RAY_ADDRESS"
    from ray._private.utils import get_ray_address_file, read_ray_address

    recorded = read_ray_address()
    if recorded:
        return recorded, f"{get_ray_address_file(None)}, written by the last `ray start` on this machine"
    raise ConfigError("evaluator.address=auto: no Ray cluster to join (RAY_ADDRESS is unset and no `ray start` is "
                      "recorded on this machine): start a head with `ray start --head --port=6379`, give "
                      f"evaluator.address=HOST:PORT, {_JOIN_FIX}")


def _token_found() -> bool:
    """Whether this machine has a Ray auth token where Ray looks: RAY_AUTH_TOKEN, the file RAY_AUTH_TOKEN_PATH
    names, or ~/.ray/auth_token."""
    if os.environ.get("RAY_AUTH_TOKEN", "").strip():
        return True
    for path in (os.environ.get("RAY_AUTH_TOKEN_PATH"), os.path.join(os.path.expanduser("~"), ".ray", "auth_token")):
        try:
            if path and open(path, encoding="utf-8").read().strip():
                return True
        except OSError:
            pass
    return False


def _send_token_if_found() -> None:
    """Join with the cluster's token when this machine has one and RAY_AUTH_MODE is unset.

    Ray 2.60 turns token mode on by itself only for a cluster it finds on its own (address None/"auto"); with an
    explicit address the token is not sent unless RAY_AUTH_MODE=token, and a head with token authentication
    (the default of `ray start --head` where ~/.ray/auth_token exists) refuses the join after ~20 s. A token sent
    to a head without authentication is ignored, so sending it whenever there is one is safe.
    """
    if os.environ.get("RAY_AUTH_MODE") is not None or not _token_found():
        return
    os.environ["RAY_AUTH_MODE"] = "token"
    try:  # refresh Ray's cached configuration in this process (what Ray's own auto-enable does)
        from ray._raylet import Config

        Config.initialize("")
    except Exception:  # pragma: no cover - older Ray without token authentication
        pass


def code_runtime_env() -> dict[str, Any]:
    """A Ray ``runtime_env`` that ships this ``toggle_id`` package (without compiled caches) to the workers."""
    package = os.path.dirname(os.path.abspath(__file__))
    return {"py_modules": [package], "excludes": ["__pycache__/", "*.pyc", "*.nbi", "*.nbc"]}


def join_address(address: str, timeout_s: float = 10.0) -> str:
    """Find and check the Ray cluster ``address`` (``"auto"`` or ``"host:port"``) names; return ``host:port``.

    Within at most ``2 * timeout_s + 5`` seconds (TCP, then the GCS probe in a fresh interpreter), usually well
    under one: the address is found (``auto``: :func:`_auto_address`), something must
    accept a TCP connection there, and a Ray head must answer a GCS client and accept this machine's
    credentials (the token is sent when one is found, :func:`_send_token_if_found`). Every failure is a one-line
    ConfigError that names the fix. Ray's own ``ray.init`` would wait 20 s for a refused token and minutes for a
    dead head.
    """
    import socket
    import subprocess
    import sys

    if isinstance(timeout_s, bool) or not isinstance(timeout_s, (int, float)) or not timeout_s > 0:
        raise ConfigError(f"evaluator.connect_timeout_s must be a positive number of seconds, got {timeout_s!r}")
    given = str(address).strip()
    source = None
    if given == "auto":
        given, source = _auto_address()
    if "://" in given:
        raise ConfigError(f"evaluator.address {given!r}{f' (from {source})' if source else ''}: Ray Client "
                          "addresses (ray://) are not supported; give the head's HOST:PORT (`ray start --head "
                          f"--port=PORT`), {_JOIN_FIX}")
    host, port = _split_address(given)
    target = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
    where = f"{target} (from {source})" if source else target
    try:
        socket.create_connection((host, port), timeout=timeout_s).close()
    except OSError as err:
        reason = ("timed out" if isinstance(err, socket.timeout) else
                  "connection refused" if isinstance(err, ConnectionRefusedError) else
                  " ".join(str(err).split()) or type(err).__name__)
        gone = (" — the head recorded there has stopped or crashed" if source and "ray start" in source else "")
        raise ConfigError(f"cannot reach a Ray cluster at {where}: {reason}{gone}; start its head "
                          f"(`ray start --head --port={port}`), point evaluator.address at a running head, "
                          f"{_JOIN_FIX}") from None
    _send_token_if_found()
    try:
        proc = subprocess.run([sys.executable, "-c", _PROBE, target, str(int(timeout_s * 1000))],
                              capture_output=True, text=True, timeout=timeout_s + 5.0)  # + interpreter start
    except subprocess.TimeoutExpired:
        proc = None
    if proc is None or proc.returncode == 4 and "timed out" in proc.stdout.replace("TimedOut", "timed out").lower():
        raise ConfigError(f"no Ray head answers at {where} within {timeout_s:g} s (is it the head's GCS port, "
                          f"`ray start --head --port={port}`?); raise evaluator.connect_timeout_s on a slow network, "
                          f"{_JOIN_FIX}")
    if proc.returncode == 3:
        mode = os.environ.get("RAY_AUTH_MODE", "").lower()
        why = ("RAY_AUTH_MODE=disabled here" if mode == "disabled" else
               "the token found here is not the cluster's" if _token_found() else "no token found on this machine")
        raise ConfigError(f"the Ray cluster at {where} requires its authentication token ({why}): copy the head's "
                          "token (`ray get-auth-token` on the head) into ~/.ray/auth_token here or set "
                          f"RAY_AUTH_TOKEN{', and unset RAY_AUTH_MODE' if mode == 'disabled' else ''}")
    if proc.returncode != 0:
        text = (proc.stdout.strip().splitlines() or [f"exit status {proc.returncode}"])[-1]
        raise ConfigError(f"cannot join a Ray cluster at {where} ({text[:300]}): is it the head's address "
                          f"(`ray start --head --port={port}`)? Point evaluator.address at a running head, {_JOIN_FIX}")
    return target


class RayEvaluator(_EvaluatorBase):
    """Evaluate on ``n_workers`` Ray actors, one contiguous chunk of the population per actor.

    Args:
        problem: picklable problem; put in the object store once, built and set up once per actor.
        n_workers: actors (each reserves 1 CPU); None: the CPUs of the local machine (``address=None``) or of
            the cluster.
        address: None starts a local Ray (never joins one) unless Ray is initialised already; ``"auto"`` /
            ``"host:port"`` joins a cluster (:func:`join_address`).
        max_restarts: actor replacements allowed within one :meth:`evaluate` call before giving up.
        ready_timeout_s: seconds to wait for all actors to finish ``setup`` (s).
        init_kwargs: extra arguments for ``ray.init`` when this evaluator starts Ray.
        connect_timeout_s: seconds to find and check a cluster to join (s).
        setup_here: set the problem up in this process first. On a cold numba cache the local workers then load
            the kernels this process compiled, instead of each compiling them side by side
            (``python -m jobs.bench --cold``); the driver needs them anyway for its own polishes.

    Fault tolerance: when an actor dies (``RayActorError`` and subclasses), it is replaced by a new actor and its
    chunk is evaluated again, so the result equals a fault-free run; ``stats["restarts"]`` counts replacements.
    Errors raised by the problem itself propagate. :meth:`close` kills the actors and shuts Ray down only if this
    evaluator started it.
    """

    def __init__(self, problem: Problem, n_workers: Optional[int] = None, address: Optional[str] = None,
                 max_restarts: int = 10, ready_timeout_s: float = 600.0,
                 init_kwargs: Optional[Mapping[str, Any]] = None, connect_timeout_s: float = 10.0,
                 setup_here: bool = True) -> None:
        super().__init__()
        n_workers = _check_workers(n_workers)
        if isinstance(max_restarts, bool) or not isinstance(max_restarts, int) or max_restarts < 0:
            raise ConfigError(f"max_restarts must be a non-negative integer, got {max_restarts!r}")
        if setup_here:  # see the class docstring
            problem.setup()
        import ray

        self._ray = ray
        num_cpus = n_workers if n_workers is not None else (os.cpu_count() or 1)
        self._owns_ray = init_ray(num_cpus=num_cpus if address is None else None, address=address,
                                  connect_timeout_s=connect_timeout_s, **dict(init_kwargs or {}))
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
