"""Joining a Ray cluster as a user does (``ray start --head``, then ``evaluator.address=auto|HOST:PORT``), failing in
one line within seconds when it cannot, and the embedded default that always starts its own local Ray."""
from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest
from conftest import ROOT, run_job

from toggle_id.errors import ConfigError
from toggle_id.evaluators import join_address

pytest.importorskip("ray")

# a 1-s record and a tiny GA: the whole job in seconds
QUICK = ["+experiment=two_stage", "ga=small", "ga.population=16", "ga.generations=2", "data.duration=1.0",
         "polish.max_nfev=3", "progress=false", "tracking.enabled=false"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def ray_tmp():
    """A private Ray temp dir (RAY_TMPDIR; short, for Ray's socket paths): what this test records there (a dead
    head, a cluster of its own) never reaches other Ray users of the machine."""
    path = tempfile.mkdtemp(prefix="tgray", dir="/tmp" if os.path.isdir("/tmp") else None)
    yield Path(path)
    shutil.rmtree(path, ignore_errors=True)


def _record_dead_head(ray_tmp: Path) -> str:
    """Write what a `ray start` head that was killed leaves behind: its address in ray_current_cluster."""
    dead = f"127.0.0.1:{_free_port()}"
    (ray_tmp / "ray").mkdir(parents=True, exist_ok=True)
    (ray_tmp / "ray" / "ray_current_cluster").write_text(dead)
    return dead


# ------------------------------------------------------------------------------------------ failures, in one line
@pytest.mark.parametrize("address,needle", [
    ("foo", "is not a Ray cluster address"),
    ("host:", "is not a Ray cluster address"),
    ("host:99999", "is not a Ray cluster address"),
    ("ray://127.0.0.1:10001", "Ray Client addresses (ray://) are not supported"),
])
def test_a_malformed_address_is_refused(address, needle):
    with pytest.raises(ConfigError) as info:
        join_address(address, 5)
    assert needle in str(info.value) and "\n" not in str(info.value)


def test_nothing_listening_is_reported_at_once_with_the_fix():
    port = _free_port()
    t0 = time.monotonic()
    with pytest.raises(ConfigError) as info:
        join_address(f"127.0.0.1:{port}", 5)
    msg = str(info.value)
    assert time.monotonic() - t0 < 5
    assert "connection refused" in msg and f"ray start --head --port={port}" in msg and "\n" not in msg


def test_auto_without_a_cluster_says_how_to_start_one(ray_tmp, monkeypatch):
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    monkeypatch.setenv("RAY_TMPDIR", str(ray_tmp))
    with pytest.raises(ConfigError, match=r"no Ray cluster to join .*ray start --head"):
        join_address("auto", 5)


def test_auto_names_a_dead_head_recorded_by_ray_start(ray_tmp, monkeypatch):
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    monkeypatch.setenv("RAY_TMPDIR", str(ray_tmp))
    dead = _record_dead_head(ray_tmp)
    with pytest.raises(ConfigError) as info:
        join_address("auto", 5)
    msg = str(info.value)
    assert dead in msg and "ray_current_cluster" in msg and "has stopped or crashed" in msg


def test_something_that_is_not_a_ray_head_is_given_up_on_within_the_timeout():
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(8)
    held = []

    def accept_and_stay_silent() -> None:
        while True:
            try:
                held.append(srv.accept()[0])
            except OSError:
                return

    threading.Thread(target=accept_and_stay_silent, daemon=True).start()
    t0 = time.monotonic()
    try:
        with pytest.raises(ConfigError, match="no Ray head answers at"):
            join_address(f"127.0.0.1:{srv.getsockname()[1]}", 2)
    finally:
        srv.close()
        for c in held:
            c.close()
    assert time.monotonic() - t0 < 2 + 2 + 5 + 5  # TCP, then the probe (timeout + interpreter start), and slack


@pytest.mark.integration
def test_the_job_reports_an_unreachable_cluster_in_one_line(tmp_path):
    port = _free_port()
    t0 = time.monotonic()
    proc = run_job("jobs.run", *QUICK, f"evaluator.address=127.0.0.1:{port}", cwd=tmp_path, timeout=120)
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == 2 and len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert "connection refused" in lines[0] and f"ray start --head --port={port}" in lines[0]
    assert time.monotonic() - t0 < 60


# ------------------------------------------------------------------------------------------ the embedded default
_LOCAL = """
import ray
from toggle_id.evaluators import init_ray
init_ray(num_cpus=1)
print("LOCAL", ray.cluster_resources().get("CPU"), flush=True)
ray.shutdown()
"""


def test_the_default_starts_its_own_ray_despite_a_stale_address_and_a_dead_head(ray_tmp):
    env = {**os.environ, "PYTHONPATH": str(ROOT), "RAY_TMPDIR": str(ray_tmp),
           "RAY_ADDRESS": f"127.0.0.1:{_free_port()}"}
    _record_dead_head(ray_tmp)
    t0 = time.monotonic()
    proc = subprocess.run([sys.executable, "-c", _LOCAL], env=env, capture_output=True, text=True, timeout=180)
    assert "LOCAL 1.0" in proc.stdout, proc.stderr[-3000:]
    assert time.monotonic() - t0 < 120


# ------------------------------------------------------------------------------------------ a real head
def _head_processes(ray_tmp: Path) -> list:
    """The processes of the head started under ``ray_tmp`` (named by its session directory) and their children."""
    import psutil

    found = {}
    for p in psutil.process_iter(["cmdline"]):
        try:
            if any(str(ray_tmp) in arg for arg in p.info["cmdline"] or ()):
                found[p.pid] = p
                for c in p.children(recursive=True):
                    found[c.pid] = c
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            pass
    return list(found.values())


def _kill_head(ray_tmp: Path) -> int:
    procs = _head_processes(ray_tmp)
    for p in procs:
        try:
            p.send_signal(signal.SIGKILL)  # as a crash would: nothing cleaned up, the address stays recorded
        except Exception:
            pass
    return len(procs)


@pytest.mark.slow
@pytest.mark.integration
def test_a_job_joins_a_head_with_token_auth_and_the_default_runs_after_the_head_dies(tmp_path, ray_tmp):
    token = tmp_path / "auth_token"
    token.write_text("toggle-id-test-" + os.urandom(16).hex())
    base = {**os.environ, "PYTHONPATH": str(ROOT), "RAY_TMPDIR": str(ray_tmp), "RAY_AUTH_TOKEN_PATH": str(token)}
    for key in ("RAY_ADDRESS", "RAY_AUTH_MODE", "RAY_AUTH_TOKEN"):
        base.pop(key, None)
    port = _free_port()
    ray_bin = shutil.which("ray") or str(Path(sys.executable).with_name("ray"))
    head = subprocess.run([ray_bin, "start", "--head", f"--port={port}", "--node-ip-address=127.0.0.1",
                           "--num-cpus=1", "--include-dashboard=false", "--disable-usage-stats"],
                          env={**base, "RAY_AUTH_MODE": "token"}, capture_output=True, text=True, timeout=120)
    try:
        assert head.returncode == 0, head.stdout[-2000:] + head.stderr[-2000:]
        recorded = (ray_tmp / "ray" / "ray_current_cluster").read_text().strip()
        assert recorded.endswith(f":{port}")

        # the job joins with nothing set but where the token is (RAY_AUTH_MODE unset): auto, then HOST:PORT
        for address in ("auto", f"127.0.0.1:{port}"):
            proc = run_job("jobs.run", *QUICK, f"evaluator.address={address}", cwd=tmp_path, env=base, timeout=600)
            assert proc.returncode == 0, proc.stderr[-3000:]
            assert f"Connecting to existing Ray cluster at address: {recorded}" in proc.stderr
            assert Path(proc.stdout.strip().splitlines()[-1].removeprefix("report: ")).is_file()

        # a wrong token: one line, at once
        t0 = time.monotonic()
        proc = run_job("jobs.run", *QUICK, f"evaluator.address=127.0.0.1:{port}", cwd=tmp_path,
                       env={**base, "RAY_AUTH_TOKEN": "not-the-token"}, timeout=120)
        lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
        assert proc.returncode == 2 and len(lines) == 1, proc.stderr[-2000:]
        assert "requires its authentication token" in lines[0] and "~/.ray/auth_token" in lines[0]
        assert time.monotonic() - t0 < 60

        assert _kill_head(ray_tmp) > 0
        time.sleep(1.0)
        assert not _head_processes(ray_tmp)

        # the head is dead but recorded, and RAY_ADDRESS points at it: the default job starts its own Ray
        t0 = time.monotonic()
        proc = run_job("jobs.run", *QUICK, "evaluator.n_workers=1", cwd=tmp_path,
                       env={**base, "RAY_ADDRESS": recorded}, timeout=300)
        assert proc.returncode == 0, proc.stderr[-3000:]
        assert "Started a local Ray instance" in proc.stderr
        assert time.monotonic() - t0 < 240
    finally:
        _kill_head(ray_tmp)


@pytest.mark.integration
def test_a_local_ray_that_will_not_start_leaves_the_job_to_the_serial_evaluator(tmp_path, monkeypatch, caplog):
    """On a loaded machine Ray's local node may time out while starting: tried twice, then the job goes on serially
    with one warning line, and the same seed gives the same result; a cluster asked for by address stays an error."""
    from conftest import run_in_process

    from toggle_id import evaluators
    from toggle_id.app.common import local_ray_failed, ray_session

    calls = []

    def will_not_start(**kw):
        calls.append(kw)
        raise Exception("The current node timed out during startup. This could happen because some of the raylet "
                        "failed to startup or the GCS has become overloaded.")

    monkeypatch.setattr(evaluators, "init_ray", will_not_start)
    fell_back = run_in_process("jobs.run", *QUICK, f"hydra.run.dir={tmp_path / 'ray'}", cwd=tmp_path)
    assert fell_back.returncode == 0, fell_back.stderr[-2000:]
    assert len(calls) == 2
    assert local_ray_failed() is None  # the fallback ended with its job's session
    assert any("local Ray did not start twice" in r.getMessage() and "evaluating serially" in r.getMessage()
               for r in caplog.records)
    serial = run_in_process("jobs.run", *QUICK, "evaluator=serial", f"hydra.run.dir={tmp_path / 'serial'}",
                            cwd=tmp_path)
    assert serial.returncode == 0, serial.stderr[-2000:]
    a, b = (json.loads((tmp_path / d / "result.json").read_text()) for d in ("ray", "serial"))
    assert a["fitness"] == b["fitness"] and a["params"] == b["params"]
    with pytest.raises(Exception, match="timed out during startup"):
        with ray_session({"kind": "ray", "address": "127.0.0.1:6379"}):
            pass
