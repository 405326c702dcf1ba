"""Fixtures: a scratch MLflow store, job runners (a new interpreter, or this one), one Ray session for the suite,
and the EMPS benchmark records where the job would find them."""
from __future__ import annotations

import contextlib
import io
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

if int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")) > 1:
    # the workers share the cores, each running the parallel kernels (and the jobs it starts inherit this): see
    # toggle_id.simulate.SHARED_CORES_ENV (the default suite 4 min 45 s -> 4 min 25 s, 2026-11-27)
    from toggle_id.simulate import share_cores

    share_cores(os.environ)


def run_job(module: str, *args: str, cwd: Path, env: dict | None = None, timeout: int = 600
            ) -> subprocess.CompletedProcess:
    """Run ``python -m module args...`` as a user would, in ``cwd``."""
    full_env = {**os.environ, "PYTHONPATH": str(ROOT), **(env or {})}
    return subprocess.run([sys.executable, "-m", module, *args], cwd=cwd, env=full_env, capture_output=True,
                          text=True, timeout=timeout)



def blas_threads() -> list[int]:
    """The thread count of every BLAS library loaded in this process (threadpoolctl)."""
    from threadpoolctl import threadpool_info

    return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]


# ------------------------------------------------------------------------------------------ jobs in this process
@dataclass
class JobOutcome:
    """What a job run by :func:`run_in_process` left: exit status, standard output and error (as a process's)."""
    returncode: int
    stdout: str
    stderr: str


def _run_identify_job(cfg: dict, run_dir: Path, cwd: str, overrides: list[str]) -> str:
    from jobs._cli import guarded
    from jobs.run import run
    from toggle_id.tracking import run_context

    with run_context(overrides, {}):
        return guarded(lambda: run(cfg, str(run_dir), cwd))


def _run_simulate_job(cfg: dict, run_dir: Path, cwd: str, overrides: list[str]) -> str:
    from jobs._cli import guarded
    from jobs.simulate import write_record

    return guarded(lambda: write_record(cfg, cwd))


#: module -> (its Hydra config, what its ``main`` does with the composed configuration)
_ENTRY_POINTS = {"jobs.run": ("config", _run_identify_job), "jobs.simulate": ("simulate", _run_simulate_job)}


def run_in_process(module: str, *args: str, cwd: Path, env: dict | None = None) -> JobOutcome:
    """Run the job of ``python -m module args...`` in this interpreter, through its entry point's own path.

    As ``__main__`` and ``main`` do: ``jobs._cli.precheck`` on the command line (a bad key or override is one line,
    exit status 2), Hydra's composition of the same overrides, the run directory (``hydra.run.dir``, created), then
    the job inside ``jobs._cli.guarded`` (a library input error is one line, exit status 2) and ``report: PATH``.
    In ``cwd`` with ``env`` added (a value None removes the variable), both restored afterwards; the run
    directories the job claimed are released, as at the end of its process. What it saves over :func:`run_job` is
    an interpreter, the imports and the numba cache per case: for matrices of bad input, each job keeping one case
    through :func:`run_job`. An exception the guarded path does not turn into one line (a bug,
    ``KeyboardInterrupt``) propagates. Library modules are those imported by this process, ``conf/`` is read
    at the call: a suite running while someone edits both may see them disagree (a new process would not).
    """
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf, open_dict

    from jobs import _cli
    from toggle_id import jobdir

    config, job = _ENTRY_POINTS[module]
    out, err = io.StringIO(), io.StringIO()
    saved_env, saved_cwd = dict(os.environ), os.getcwd()
    claimed: list = []
    code = 0
    try:
        for key, value in (env or {}).items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value
        os.chdir(cwd)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                _cli.precheck(config, list(args))
                with initialize_config_dir(config_dir=_cli.CONF_DIR, version_base="1.3"):
                    cfg = compose(config_name=config, overrides=list(args), return_hydra_config=True)
                run_dir = Path(cwd) / str(cfg.hydra.run.dir)
                run_dir.mkdir(parents=True, exist_ok=True)
                overrides = list(cfg.hydra.overrides.task)
                with open_dict(cfg):
                    del cfg["hydra"]
                    if "run_dir" in cfg:
                        cfg.run_dir = str(run_dir)
                plain = OmegaConf.to_container(cfg, resolve=True)
                claimed = [run_dir, plain.get("resume")]
                report = job(plain, run_dir, str(cwd), overrides)
                print(f"report: {report}", flush=True)
            except SystemExit as exc:
                code = 0 if exc.code is None else exc.code if isinstance(exc.code, int) else 1
    finally:
        os.chdir(saved_cwd)
        os.environ.clear()
        os.environ.update(saved_env)
        for path in claimed:
            if path:
                jobdir.release(path)
    return JobOutcome(code, out.getvalue(), err.getvalue())


def one_line_error(proc) -> str:
    """The one line a job that refused its input printed to stderr (a non-zero exit, no traceback)."""
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode != 0, proc.stdout[-2000:]
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr[-3000:]
    return lines[0]


# ------------------------------------------------------------------------------------------ one identify job
#: A 1-s record and a tiny GA on the serial evaluator, seed 1: the two-stage identify job in seconds.
TWO_STAGE_QUICK = ["ga=small", "ga.population=16", "ga.generations=3", "evaluator=serial", "data.duration=1.0",
                   "polish.max_nfev=5", "progress=false", "seed=1"]


@pytest.fixture(scope="session")
def two_stage_job(tmp_path_factory, mlflow_template):
    """One tiny two-stage job, run as a user runs it (``python -m jobs.run +experiment=two_stage``, TWO_STAGE_QUICK)
    on a scratch MLflow store, and what it left: ``tmp`` (its run directory is ``tmp/run``), ``uri``, ``proc``,
    ``result`` (result.json), ``client`` and its parent ``run``. Shared by the tests of the job's report, figures
    and MLflow run (tests/test_jobs.py, tests/test_mlflow_compare.py)."""
    import json
    from types import SimpleNamespace

    tmp = tmp_path_factory.mktemp("two_stage")
    uri = scratch_store(tmp, mlflow_template)
    proc = run_job("jobs.run", "+experiment=two_stage", f"hydra.run.dir={tmp / 'run'}", *TWO_STAGE_QUICK, cwd=tmp,
                   env={"MLFLOW_TRACKING_URI": uri})
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads((tmp / "run" / "result.json").read_text())
    from mlflow import MlflowClient

    client = MlflowClient(uri)
    return SimpleNamespace(tmp=tmp, uri=uri, proc=proc, result=result, client=client,
                           run=client.get_run(result["mlflow_run_id"]))


# ------------------------------------------------------------------------------------------ Ray
@pytest.fixture(scope="session")
def ray_session():
    """One small local Ray (2 CPUs) for the whole suite: started by the first test that needs it, shut down at the
    end (each start costs seconds: processes, the object store, the workers' imports)."""
    ray = pytest.importorskip("ray")
    from toggle_id.evaluators import init_ray

    started = init_ray(num_cpus=2)
    yield ray
    if started:
        ray.shutdown()


@pytest.fixture(scope="session")
def mlflow_template(tmp_path_factory) -> Path:
    """An empty MLflow store with its tables made (MLflow creates and migrates a new SQLite store's schema on first
    use: seconds in every job). Tests copy it; a user's first run, and tests that ask for no store, still make it."""
    from mlflow import MlflowClient

    path = tmp_path_factory.mktemp("mlflow_template") / "mlflow.db"
    MlflowClient(f"sqlite:///{path}").search_experiments()
    return path


def scratch_store(directory: Path, template: Path) -> str:
    """A scratch MLflow store in ``directory`` (a copy of the session's empty store) and its absolute URI."""
    directory.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(template, directory / "mlflow.db")
    return f"sqlite:///{directory / 'mlflow.db'}"


@pytest.fixture
def job_env(tmp_path: Path, mlflow_template: Path) -> dict:
    """Environment that points MLflow at a scratch store (absolute URI) for jobs run in a test."""
    return {"MLFLOW_TRACKING_URI": scratch_store(tmp_path, mlflow_template)}


def wait_until_dead(actor, timeout: float = 60.0) -> None:
    """Block until a killed Ray actor is really gone (``ray.kill`` is asynchronous: a call queued just after it
    may still be answered by the old process)."""
    import time

    import ray

    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        try:
            ray.get(actor.ready.remote(), timeout=max(t_end - time.monotonic(), 0.1))
        except ray.exceptions.RayActorError:
            return
        except ray.exceptions.GetTimeoutError:
            break
        time.sleep(0.05)
    pytest.fail(f"the killed actor still answers after {timeout:g} s")


# ------------------------------------------------------------------------------------------ EMPS benchmark records
def _emps_files():
    """The benchmark's EMPS records where the job would find them, or (None, the job's one-line reason)."""
    from toggle_id.emps import EmpsRecordsNotFound, find_benchmark_files

    try:
        return find_benchmark_files(require_validation=True), None
    except EmpsRecordsNotFound as err:
        return None, str(err)


EMPS_FILES, EMPS_MISSING = _emps_files()
#: Tests on the real EMPS records: skipped, with the job's one-line reason, only when the records are absent.
needs_records = pytest.mark.skipif(EMPS_FILES is None, reason=EMPS_MISSING or "")


# ------------------------------------------------------------------------------------------ parallel runs
#: Session fixtures that cost seconds to build: under pytest-xdist (the default: ``-n auto`` in pyproject.toml) the
#: tests that share one run on one worker (``--dist loadgroup``), so each is built once, not once per worker.
SHARED_FIXTURES = ("two_stage_job", "ray_session")


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist's own, which reads the groups into the test ids
def pytest_collection_modifyitems(config, items):
    for item in items:
        shared = [name for name in SHARED_FIXTURES if name in getattr(item, "fixturenames", ())]
        if shared:
            item.add_marker(pytest.mark.xdist_group(shared[0]))


# ------------------------------------------------------------------------------------------ the machine
_CPU_AT_START: list[int] | None = None


def pytest_sessionstart(session):
    global _CPU_AT_START
    from jobs.bench import cpu_times

    _CPU_AT_START = cpu_times()


def _xdist_workers(config) -> int:
    n = config.getoption("numprocesses", default=None)
    if n in ("auto", "logical"):
        return os.cpu_count() or 1
    return int(n or 0)


def pytest_configure(config):
    """Under pytest-xdist, before its workers start: compile the kernels, the rigid integrator (and its sensitivities)
    and the backlash integrator in two processes side by side (:func:`toggle_id.simulate.compile_kernels`), where
    each worker would compile them all on its first simulation (a cold cache: a fresh clone, or after an edit of ``toggle_id/kernels``); on a warm cache they
    only load them. A kind that fails to compile is left to the tests, which then fail with its error."""
    if getattr(config, "workerinput", None) is not None or _xdist_workers(config) < 2:
        return
    from toggle_id.simulate import share_cores

    env = share_cores({**os.environ, "PYTHONPATH": str(ROOT)})
    procs = [subprocess.Popen([sys.executable, "-c", "import sys; from toggle_id.simulate import compile_kernels; "
                               "compile_kernels(sys.argv[1:])", *kinds], cwd=ROOT, env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
             for kinds in (("rigid", "sens"), ("lash",))]
    for proc in procs:
        proc.wait()


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    """The suite's wall time means little without the machine's speed: print it (one core's simulation rate and
    the CPU steal of the run) after a run that got as far as its tests."""
    if not terminalreporter.stats.get("passed"):
        return
    from jobs.bench import machine_line

    terminalreporter.write_line(machine_line(_CPU_AT_START))
