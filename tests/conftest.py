"""Fixtures: a scratch MLflow store, job runners, and the EMPS benchmark records where the job would find them."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def run_job(module: str, *args: str, cwd: Path, env: dict | None = None, timeout: int = 600
            ) -> subprocess.CompletedProcess:
    """Run ``python -m module args...`` as a user would, in ``cwd``."""
    full_env = {**os.environ, "PYTHONPATH": str(ROOT), **(env or {})}
    return subprocess.run([sys.executable, "-m", module, *args], cwd=cwd, env=full_env, capture_output=True,
                          text=True, timeout=timeout)


@pytest.fixture
def job_env(tmp_path: Path) -> dict:
    """Environment that points MLflow at a scratch store (absolute URI) for jobs run in a test."""
    return {"MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}"}


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
