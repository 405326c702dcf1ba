"""The fast identification method (toggle_id/fast.py): multistart least squares in the paper's two stages."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from toggle_id import params as P
from toggle_id.errors import ConfigError
from toggle_id.fast import FastSettings, identify_fast
from toggle_id.simulate import extend
from toggle_id.app.records import build_record

NOISE = 1e-6


def _record(duration: float = 1.0, seed: int = 3):
    return build_record({"source": "simulated", "sweep": "simulation", "duration": duration, "params": {},
                         "effects": {}, "noise_m": NOISE, "noise_seed": seed})[0]


@pytest.fixture(scope="module")
def record():
    return _record()


SMALL = FastSettings(starts=4, starts_stage2=2, first_nfev=3, finalists=1, final_nfev=20, searches=1)


def test_fast_halves_its_starts_and_never_loses_the_best(record):
    res = identify_fast([record], extend(P.ASSIGNED)[0], seed=0, fast=SMALL, identifiability=False)
    assert res.method == "fast" and [s.name for s in res.stages] == ["stage1", "stage2", "joint_polish"]
    rounds = res.stages[0].polish["multistart"]["rounds"]
    assert [r["starts"] for r in rounds] == [4, 2, 1]
    assert [r["max_nfev"] for r in rounds] == [3, 6, 12]
    # each round continues the best of the one before: its best SSE never rises
    best = [min(r["sse_m2"]) for r in rounds]
    assert all(b1 <= b0 * (1 + 1e-12) for b0, b1 in zip(best, best[1:]))
    # the joint polish starts from the two stages' result and keeps it unless it improves; whether a few starts
    # find the noise floor is a matter for the benchmark (python -m jobs.bench_methods), not for this test
    after = {p.stage: p.rmse_m for p in res.curve}  # whole-record RMS after each stage
    assert set(after) == {"stage1", "stage2", "joint_polish"}
    assert res.rmse_m == pytest.approx(after["joint_polish"], rel=1e-9) and res.rmse_m <= after["stage2"] * (1 + 1e-9)
    assert 0 < res.extra["seconds_fit"] <= res.seconds
    assert res.n_simulations > 0 and res.curve and res.curve[-1].rmse_m == pytest.approx(res.rmse_m, rel=1e-6)


def test_fast_is_deterministic(record):
    kw = dict(seed=5, fast=FastSettings(starts=3, starts_stage2=2, first_nfev=2, finalists=1, final_nfev=5,
                                         searches=2, floor_ratio=1.0),
              identifiability=False)
    a = identify_fast([record], extend(P.ASSIGNED)[0], **kw)
    b = identify_fast([record], extend(P.ASSIGNED)[0], **kw)
    np.testing.assert_array_equal(a.theta, b.theta)


@pytest.mark.parametrize("bad", [{"starts": 0}, {"keep": 1.0}, {"final_nfev": 2.5}, {"fd_rel_step": 0.0},
                                 {"fd_tier": "loose"}])
def test_fast_settings_are_checked(bad):
    with pytest.raises(ConfigError, match="fast\\."):
        FastSettings(**bad).validate()


@pytest.mark.integration
def test_fast_job_end_to_end(tmp_path, job_env):
    from conftest import run_job

    proc = run_job("jobs.run", "+experiment=fast", f"hydra.run.dir={tmp_path / 'run'}", "data.duration=1.0",
                   "fast.starts=4", "fast.starts_stage2=2", "fast.final_nfev=20", "fast.searches=1", "progress=false",
                   cwd=tmp_path, env=job_env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = Path([ln for ln in proc.stdout.splitlines() if ln.strip()][-1].removeprefix("report: "))
    d = json.loads(report.read_text())
    assert d["method"] == "fast" and d["seconds_fit"] > 0 and d["rmse_m"] > 0
    assert [s["name"] for s in d["stages"]] == ["stage1", "stage2", "joint_polish"]
    assert d["stages"][0]["polish"]["multistart"]["rounds"][0]["starts"] == 4


def test_fast_job_rejects_a_bad_setting(tmp_path, job_env):
    """Through the job's own command-line path, in this process (its end-to-end case above runs as a user would)."""
    from conftest import run_in_process

    proc = run_in_process("jobs.run", "+experiment=fast", f"hydra.run.dir={tmp_path / 'run'}", "fast.keep=2",
                          cwd=tmp_path, env=job_env)
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode != 0 and len(lines) == 1 and "fast.keep" in lines[0]


@pytest.mark.slow
def test_bench_methods_prints_its_table(tmp_path, job_env):
    from conftest import run_job

    out = tmp_path / "methods.md"
    proc = run_job("jobs.bench_methods", "--fast", "1", "--two-stage", "0", "--one-stage", "0", "--out", str(out),
                   "data.duration=1.0", "fast.starts=3", "fast.starts_stage2=2", "fast.final_nfev=10",
                   "fast.searches=1",
                   cwd=tmp_path, env=job_env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = [ln for ln in out.read_text().splitlines() if ln.startswith("| fast |")]
    assert len(rows) == 1 and " of 1 |" in rows[0]
    runs = json.loads(out.with_suffix(".json").read_text())
    assert runs[0]["method"] == "fast" and runs[0]["simulations"] > 0 and runs[0]["curve"]


def test_fast_one_stage_route_fits_everything_at_once(record):
    res = identify_fast([record], extend(P.ASSIGNED)[0], seed=1, identifiability=False,
                        fast=FastSettings(route="one_stage", starts=3, first_nfev=2, finalists=1, final_nfev=5,
                                          searches=1))
    assert [s.name for s in res.stages] == ["one_stage"]
    assert len(res.stages[0].free) == 15 and res.stages[0].window == (0, record.n)
    assert res.rmse_m == pytest.approx(res.stages[0].rmse_m, rel=1e-9)


def test_fast_route_is_checked():
    with pytest.raises(ConfigError, match="fast.route"):
        FastSettings(route="three_stage").validate()
