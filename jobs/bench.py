"""Throughput benchmark of the batched simulator (:func:`toggle_id.simulate.simulate`).

``python -m jobs.bench [--n 1000] [--repeat 5] [--json PATH]`` prints full 5-s simulations per second (median of
``repeat`` timed runs, after a warm-up whose time, numba compilation or cache load included, is reported apart)
for

- 1000 individuals uniform in the feasible domain (many fail: the status counts are printed),
- 1000 individuals near the assigned values (uniform ±10 %),

at the FAST tier, serial (one core) and parallel (numba threads); the same for PRECISE near the assigned values;
near the assigned values with a 0.5-mm screw backlash (the two-body kernel); stage-1 only (the samples before
the clamp) and stage-2 restarts (from the contact state, D and K_l varied);
and the cost of ``scipy.integrate.solve_ivp`` (Radau and LSODA on :func:`toggle_id.plant.rhs` with a contact
event) per simulation on a few near-assigned individuals, at about the same accuracy.

``--polish`` instead times one bounded least-squares polish (:func:`toggle_id.polish.polish`, 15 parameters 5 %
off, the 5-s record, FAST tier, batched finite-difference Jacobian) with the BLAS pool as it is and with one BLAS
thread, interleaved, and checks that both end at the same point.

``--cold`` instead times the start of a local Ray evaluator on a cold numba cache (a fresh ``NUMBA_CACHE_DIR``
in a fresh interpreter each time, nothing simulated before, as with a record read from a file): kernels compiled
in the driver first (the default, ``RayEvaluator(setup_here=True)``) against every worker compiling them side by
side; seconds until the workers are ready and for their first evaluation, interleaved ``--repeat`` times (each
run takes minutes).

``--shared-cores`` instead times the parallel kernels in processes that share the cores, as the test suite's
workers and jobs run side by side do: batches of 16 near-assigned PRECISE simulations of a 1-s and of a 5-s record
(a discover fit's finite-difference Jacobian) in one process alone and in two at once, with OpenMP's default wait
policy and with ``toggle_id.simulate.SHARED_CORES_ENV`` (threads that sleep while they wait), interleaved
``--repeat`` times.

Timings on a shared machine are noisy: read medians, and compare figures taken in the same run.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable

import numpy as np

from toggle_id.effects import ALL_INDEX
from toggle_id.params import ASSIGNED, LOWER, UPPER
from toggle_id.plant import GEOMETRY, rhs
from toggle_id.record import Record
from toggle_id.simulate import (
    FAST,
    PRECISE,
    SimResult,
    SolverSettings,
    extend,
    simulate,
)


def near_assigned(n: int, rel: float = 0.1, seed: int = 1) -> np.ndarray:
    """(n, 15) parameter vectors uniform within ±rel of the assigned values."""
    rng = np.random.default_rng(seed)
    return ASSIGNED * (1.0 + rel * rng.uniform(-1.0, 1.0, (n, ASSIGNED.size)))


def uniform_domain(n: int, seed: int = 2) -> np.ndarray:
    """(n, 15) parameter vectors uniform in the feasible domain of docs/model.md §6."""
    rng = np.random.default_rng(seed)
    return LOWER + (UPPER - LOWER) * rng.uniform(0.0, 1.0, (n, ASSIGNED.size))


def with_backlash(theta: np.ndarray, b_l: float) -> np.ndarray:
    """Extended parameter vectors with a screw backlash of ``b_l`` (m): the two-body kernel of the lash."""
    out = extend(theta)
    out[:, ALL_INDEX["b_l"]] = b_l
    return out


def cpu_times() -> list[int] | None:
    """The machine's CPU time counters since boot (the ``cpu`` line of ``/proc/stat``: user, nice, system, idle,
    iowait, irq, softirq, steal, ...), or None where there is no such file."""
    try:
        with open("/proc/stat", encoding="ascii") as fh:
            return [int(v) for v in fh.readline().split()[1:]]
    except (OSError, ValueError):
        return None


def steal_share(before: list[int] | None, after: list[int] | None) -> float:
    """The share of the machine's CPU time between two :func:`cpu_times` readings that the hypervisor gave to
    others (steal); NaN where unknown. A virtual machine's 2 cores at 25 % steal run like 1.5 cores."""
    if not before or not after or len(before) < 8 or len(after) < 8:
        return float("nan")
    delta = [a - b for a, b in zip(after[:8], before[:8])]
    total = sum(delta)
    return delta[7] / total if total > 0 else float("nan")


def serial_rate(n: int = 200) -> float:
    """Full 5-s FAST simulations per second on one core (near the assigned values; kernels already loaded): the
    machine's speed as this project sees it, for reading any wall-clock figure beside it."""
    rec = Record.from_sweep("simulation")
    near = near_assigned(n)
    simulate(near[:2], rec, FAST)
    t0 = time.perf_counter()
    simulate(near, rec, FAST)
    return n / (time.perf_counter() - t0)


def steal_text(before: list[int] | None) -> str:
    """The CPU steal since ``before`` (a :func:`cpu_times` reading) in words."""
    steal = steal_share(before, cpu_times())
    return "unknown" if np.isnan(steal) else f"{100 * steal:.0f} %"


def machine_line(before: list[int] | None, n: int = 200) -> str:
    """One line on the machine's speed: :func:`serial_rate` and the CPU steal since ``before``."""
    return (f"machine: {serial_rate(n):.0f} FAST 5-s simulations/s on one core (README figures: 1400-1770/s); "
            f"CPU steal {steal_text(before)} during the run")


def timed(fn: Callable[[], SimResult], repeat: int) -> tuple[float, list[float], SimResult, float]:
    """Median wall time (s) of ``repeat`` calls, all wall times, the last result, and the median CPU time of this
    process (s, summed over its threads: less sensitive than wall time to other jobs on the machine)."""
    times, cpu, res = [], [], None
    for _ in range(repeat):
        c0, t0 = time.process_time(), time.perf_counter()
        res = fn()
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return float(np.median(times)), times, res, float(np.median(cpu))


def scipy_reference(theta: np.ndarray, record: Record, method: str, rtol: float, atol: float) -> np.ndarray:
    """x_B at the record's samples by ``solve_ivp`` on :func:`toggle_id.plant.rhs`, restarting at every contact
    switch (terminal event on x_B − x_B^L)."""
    from scipy.integrate import solve_ivp

    geo = GEOMETRY
    q_L = geo.q_of_xB(geo.x_B_L)
    sweep = record.sweep
    t, y = float(record.t[0]), np.array([geo.q_of_xB(record.x_B0), 0.0, 0.0])
    out = np.full(record.n, np.nan)
    t_end = float(record.t[-1])
    while t < t_end - 1e-12:
        ev = lambda s, yy, *a: q_L - yy[0]
        ev.terminal = True
        sel = record.t[(record.t > t + 1e-12) | ((record.t >= t - 1e-12) & (t == record.t[0]))]
        sol = solve_ivp(rhs, (t, t_end), y, method=method, rtol=rtol, atol=atol, t_eval=sel, events=ev,
                        args=(theta, sweep))
        idx = np.searchsorted(record.t, sol.t - 1e-12)
        out[idx] = 2.0 * geo.r1 * np.cos(sol.y[0])
        if sol.status != 1:
            break
        t, y = float(sol.t_events[0][0]), sol.y_events[0][0].copy()
        # nudge across the switching surface so that the restarted segment starts in the new mode
        y[0] = q_L - 1e-13 if (sol.y[0, -1] > q_L) else q_L + 1e-13
    return out


def row(name: str, n: int, med: float, times: list[float], res: SimResult | None, cpu: float = float("nan"),
        extra: dict | None = None) -> dict:
    d = {"case": name, "n": n, "median_s": med, "sims_per_s": n / med, "times_s": times, "cpu_s": cpu,
         "sims_per_cpu_s": n / cpu if cpu > 0 else float("nan")}
    if res is not None:
        d["status"] = res.status_counts()
        d["mean_steps_ok"] = float(np.mean(res.n_steps[res.ok])) if res.ok.any() else float("nan")
    if extra:
        d.update(extra)
    return d


def polish_rows(repeat: int, max_nfev: int = 30) -> list[dict]:
    """One polish of the 15 parameters (5 % off) on the noisy 5-s record, with the BLAS pool as it is and with one
    thread (:func:`toggle_id.polish.polish` ``blas_threads``), interleaved; median wall and CPU seconds."""
    from toggle_id.polish import polish

    rec = Record.from_sweep("simulation")
    rng = np.random.default_rng(5)
    x_meas = simulate(ASSIGNED[None], rec, FAST).x_B[0] + 1e-6 * rng.standard_normal(rec.n)
    x0 = ASSIGNED * np.exp(0.05 * rng.standard_normal(ASSIGNED.size))

    def resid_many(X: np.ndarray) -> np.ndarray:
        res = simulate(X, rec, FAST, parallel=True)
        return x_meas[None, :] - res.x_B

    def jac(x: np.ndarray) -> np.ndarray:
        h = 1e-6 * np.abs(x)
        R = resid_many(np.vstack([x, x + np.diag(h)]))
        return ((R[1:] - R[0]) / h[:, None]).T

    def run(threads: int | None):
        return polish(lambda x: resid_many(x[None])[0], x0, LOWER, UPPER, log_mask=np.ones(x0.size, bool),
                      jac_fn=jac, max_nfev=max_nfev, blas_threads=threads)

    run(1)  # warm-up: compilation or cache load
    out = {None: ([], [], None), 1: ([], [], None)}
    for _ in range(repeat):
        for threads in (None, 1):
            c0, t0 = time.process_time(), time.perf_counter()
            res = run(threads)
            out[threads][0].append(time.perf_counter() - t0)
            out[threads][1].append(time.process_time() - c0)
            out[threads] = (out[threads][0], out[threads][1], res)
    same = float(np.max(np.abs(np.log(out[None][2].x / out[1][2].x))))
    rows = []
    for threads, label in ((None, "BLAS pool as it is"), (1, "one BLAS thread")):
        times, cpu, res = out[threads]
        rows.append({"case": f"polish, {label}", "n": repeat, "median_s": float(np.median(times)), "times_s": times,
                     "cpu_s": float(np.median(cpu)), "nfev": res.nfev, "sse": res.sse,
                     "max_log_diff_of_results": same})
    return rows


#: One cold start, run in a fresh interpreter: argv[1] "1"/"0" (setup_here), argv[2] workers; prints JSON.
_COLD = r"""
import json, sys, time
import numpy as np
from toggle_id.evaluators import RayEvaluator
from toggle_id.params import ASSIGNED, PARAM_NAMES
from toggle_id.problem import FitProblem
from toggle_id.record import Record
from toggle_id.simulate import FAST
# a record as read from a file (nothing simulated before the evaluator starts; its values do not matter here)
rec = Record.from_sweep("simulation")
rec.x_B = np.full(rec.n, rec.x_B0)
problem = FitProblem(rec, tuple(PARAM_NAMES[:13]), ASSIGNED.copy(), (0, rec.n), FAST)
n = int(sys.argv[2])
t1 = time.perf_counter()
ev = RayEvaluator(problem, n_workers=n, setup_here=sys.argv[1] == "1", ready_timeout_s=3600)
t2 = time.perf_counter()
ev.evaluate(np.tile(problem.x0(), (2 * n, 1)))
t3 = time.perf_counter()
ev.close()
print(json.dumps({"ready_s": t2 - t1, "first_evaluation_s": t3 - t2}))
"""


def cold_rows(repeat: int, workers: int = 2) -> list[dict]:
    """Seconds to a ready local Ray evaluator and its first evaluation on a cold numba cache, with the kernels
    compiled in the driver first and by every worker side by side; ``repeat`` interleaved runs (medians)."""
    out: dict[bool, list[dict]] = {True: [], False: []}
    for _ in range(repeat):
        for here in (True, False):
            with tempfile.TemporaryDirectory(prefix="toggle-id-cold-") as cache:
                env = dict(os.environ, NUMBA_CACHE_DIR=cache)
                proc = subprocess.run([sys.executable, "-c", _COLD, "1" if here else "0", str(workers)], env=env,
                                      capture_output=True, text=True)
            if proc.returncode != 0:
                raise RuntimeError(f"cold start failed: {proc.stderr.strip().splitlines()[-1:]}")
            out[here].append(json.loads(proc.stdout.strip().splitlines()[-1]))
    rows = []
    for here, label in ((True, "driver compiles, workers load"), (False, "every worker compiles")):
        runs = out[here]
        ready = [r["ready_s"] for r in runs]
        first = [r["first_evaluation_s"] for r in runs]
        rows.append({"case": f"cold start, {label}", "n": len(runs), "median_s": float(np.median(ready)),
                     "first_evaluation_s": float(np.median(first)),
                     "ready_plus_first_s": float(np.median(np.add(ready, first))), "runs": runs})
    return rows


_SHARED = """
import json, sys, time
from jobs.bench import near_assigned
from toggle_id.record import Record
from toggle_id.simulate import PRECISE, simulate
rec, th = Record.from_sweep("simulation", float(sys.argv[2])), near_assigned(16)
simulate(th, rec, PRECISE, parallel=True)
n, t0 = int(sys.argv[1]), time.perf_counter()
for _ in range(n):
    simulate(th, rec, PRECISE, parallel=True)
print(json.dumps({"batches_per_s": n / (time.perf_counter() - t0)}))
"""


def shared_cores_rows(repeat: int, seconds: float = 2.0) -> list[dict]:
    """Batches per second of the parallel kernels (16 PRECISE simulations each, of a 1-s and of a 5-s record) in one
    process alone and in two side by side, with OpenMP's default wait policy and with
    :data:`toggle_id.simulate.SHARED_CORES_ENV`; ``repeat`` interleaved runs of about ``seconds`` each (medians; the
    total of the two processes for "two at once")."""
    from toggle_id.simulate import SHARED_CORES_ENV, share_cores

    base = {k: v for k, v in os.environ.items() if k not in SHARED_CORES_ENV}
    policies = (("OpenMP default", base), ("SHARED_CORES_ENV", share_cores(dict(base))))
    rates: dict[tuple[float, str, int], list[float]] = {}
    for _ in range(repeat):
        for duration, batches in ((1.0, int(45 * seconds)), (5.0, int(9 * seconds))):
            for label, env in policies:
                for procs in (1, 2):
                    rates.setdefault((duration, label, procs), []).append(
                        _side_by_side(procs, env, batches, duration))
    return [{"case": f"{duration:g}-s record, {label}, {procs} process{'es' if procs > 1 else ''}", "n": len(r),
             "batches_per_s": float(np.median(r)), "runs": r} for (duration, label, procs), r in rates.items()]


def _side_by_side(procs: int, env: dict, batches: int, duration: float) -> float:
    """Total batches per second of ``procs`` processes running :data:`_SHARED` at once."""
    running = [subprocess.Popen([sys.executable, "-c", _SHARED, str(batches), str(duration)], env=env,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(procs)]
    total = 0.0
    for proc in running:
        out, err = proc.communicate()
        if proc.returncode != 0:
            raise RuntimeError(f"shared-cores run failed: {err.strip().splitlines()[-1:]}")
        total += json.loads(out.strip().splitlines()[-1])["batches_per_s"]
    return total


def _write_json(path: str | None, rows: list[dict]) -> None:
    """The table as JSON at ``path`` (``--json``; nothing when None)."""
    if path:
        with open(path, "w", encoding="utf-8") as fh:
            json.dump(rows, fh, indent=1)


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=1000, help="individuals per population")
    ap.add_argument("--repeat", type=int, default=None, help="timed repeats (median; default 5, with --cold 1)")
    ap.add_argument("--n-scipy", type=int, default=3, help="individuals for the solve_ivp comparison (0: skip)")
    ap.add_argument("--json", type=str, default=None, help="also write the table as JSON")
    ap.add_argument("--quick", action="store_true", help="only the FAST near-assigned cases")
    ap.add_argument("--polish", action="store_true", help="time one least-squares polish with and without one "
                                                          "BLAS thread instead")
    ap.add_argument("--cold", action="store_true", help="time a local Ray evaluator's start on a cold numba "
                                                        "cache instead, on a record read as from a file")
    ap.add_argument("--workers", type=int, default=2, help="Ray workers of --cold")
    ap.add_argument("--shared-cores", action="store_true", help="time the parallel kernels in one process and in two "
                                                                "side by side, with and without SHARED_CORES_ENV")
    args = ap.parse_args(argv)
    if args.repeat is None:
        args.repeat = 1 if args.cold else 5
    if args.shared_cores:
        rows = shared_cores_rows(args.repeat)
        print(f"{'case':52s} {'runs':>4s} {'batches/s':>10s}  (16 PRECISE simulations a batch; the processes' total)")
        for r in rows:
            print(f"{r['case']:52s} {r['n']:4d} {r['batches_per_s']:10.2f}")
        _write_json(args.json, rows)
        return rows
    if args.cold:
        rows = cold_rows(args.repeat, args.workers)
        print(f"{'case':44s} {'runs':>4s} {'ready s':>8s} {'1st eval s':>10s} {'total s':>8s}")
        for r in rows:
            print(f"{r['case']:44s} {r['n']:4d} {r['median_s']:8.1f} {r['first_evaluation_s']:10.1f} "
                  f"{r['ready_plus_first_s']:8.1f}")
        print(f"{args.workers} workers; medians; a fresh NUMBA_CACHE_DIR per run; other jobs on the machine count")
        _write_json(args.json, rows)
        return rows
    if args.polish:
        rows = polish_rows(args.repeat)
        print(f"{'case':32s} {'n':>3s} {'median s':>9s} {'CPU s':>7s} {'nfev':>5s}  SSE (m²)")
        for r in rows:
            print(f"{r['case']:32s} {r['n']:3d} {r['median_s']:9.3f} {r['cpu_s']:7.2f} {r['nfev']:5d}  {r['sse']:.6g}")
        print(f"speed-up with one BLAS thread: {rows[0]['median_s'] / rows[1]['median_s']:.2f}x (medians); largest "
              f"|log ratio| between the two results: {rows[0]['max_log_diff_of_results']:.2g}")
        _write_json(args.json, rows)
        return rows

    before = cpu_times()
    rec = Record.from_sweep("simulation")
    near = near_assigned(args.n)
    dom = uniform_domain(args.n)
    rows: list[dict] = []

    t0 = time.perf_counter()
    for par in (False, True):
        for s in (FAST, PRECISE):
            simulate(near[:4], rec, s, parallel=par)
            simulate(near[:4], rec, s, parallel=par, n_samples=100)
    warm = time.perf_counter() - t0
    rows.append({"case": "warm-up (compile or cache load)", "n": 0, "median_s": warm, "sims_per_s": float("nan"),
                 "times_s": [warm]})

    cases: list[tuple[str, np.ndarray, SolverSettings, bool, dict]] = [
        ("near-assigned FAST serial", near, FAST, False, {}),
        ("near-assigned FAST parallel", near, FAST, True, {}),
    ]
    if not args.quick:
        cases += [("domain FAST serial", dom, FAST, False, {}),
                  ("domain FAST parallel", dom, FAST, True, {}),
                  ("near-assigned PRECISE parallel", near[: max(1, args.n // 4)], PRECISE, True, {}),
                  ("near-assigned + backlash 0.5 mm FAST parallel", with_backlash(near, 5e-4), FAST, True, {})]
    for name, th, s, par, kw in cases:
        med, times, res, cpu = timed(lambda th=th, s=s, par=par, kw=kw: simulate(th, rec, s, parallel=par, **kw),
                                     args.repeat)
        rows.append(row(name, th.shape[0], med, times, res, cpu))

    if not args.quick:
        ref = simulate(ASSIGNED[None], rec, PRECISE)
        n_clamp = int(np.argmax(ref.x_B[0] >= GEOMETRY.x_B_L))
        med, times, res, cpu = timed(lambda: simulate(near, rec, FAST, n_samples=n_clamp, parallel=True), args.repeat)
        rows.append(row(f"stage 1 (n_samples={n_clamp}) FAST parallel", args.n, med, times, res, cpu))
        tc, qc, wc, ic = ref.contact[0]
        st2 = np.repeat(ASSIGNED[None], args.n, axis=0)
        rng = np.random.default_rng(3)
        for j in (1, 4):  # D, K_l
            st2[:, j] *= 1.0 + 0.1 * rng.uniform(-1.0, 1.0, args.n)
        start = (float(tc), (float(qc), float(wc), float(ic)), 1)
        med, times, res, cpu = timed(lambda: simulate(st2, rec, FAST, start=start, parallel=True), args.repeat)
        rows.append(row(f"stage 2 restart at t={tc:.4f} s FAST parallel", args.n, med, times, res, cpu))

        if args.n_scipy > 0:
            few = near[: args.n_scipy]
            ours = simulate(few, rec, PRECISE).x_B
            for method, rtol, atol in (("Radau", 1e-6, 1e-9), ("LSODA", 1e-7, 1e-10)):
                errs, tt = [], []
                for k in range(few.shape[0]):
                    t1 = time.perf_counter()
                    xb = scipy_reference(few[k], rec, method, rtol, atol)
                    tt.append(time.perf_counter() - t1)
                    errs.append(float(np.nanmax(np.abs(xb - ours[k]))))
                med = float(np.median(tt))
                fast_row = next(r for r in rows if r["case"] == "near-assigned FAST serial")
                rows.append({"case": f"scipy solve_ivp {method} rtol={rtol:g} (per sim, serial)", "n": len(tt),
                             "median_s": med, "sims_per_s": 1.0 / med, "times_s": tt,
                             "max_err_um_vs_precise": max(errs) * 1e6,
                             "speedup_ours_serial": fast_row["sims_per_s"] * med})

    print(f"{'case':52s} {'n':>5s} {'median s':>9s} {'sims/s':>9s} {'sims/CPU-s':>10s}  notes")
    for r in rows:
        notes = []
        if "status" in r:
            notes.append(",".join(f"{k}:{v}" for k, v in r["status"].items() if v))
            notes.append(f"steps {r['mean_steps_ok']:.0f}")
        if "max_err_um_vs_precise" in r:
            notes.append(f"err {r['max_err_um_vs_precise']:.3f} um, ours x{r['speedup_ours_serial']:.0f} faster")
        cps = r.get("sims_per_cpu_s", float("nan"))
        print(f"{r['case']:52s} {r['n']:5d} {r['median_s']:9.4f} {r['sims_per_s']:9.1f} {cps:10.1f}  {'; '.join(notes)}")
    print("wall-clock figures depend on other jobs on the machine; sims/CPU-s is per core (this process's CPU time)")
    print(f"CPU steal during the run: {steal_text(before)} (time the hypervisor gave to other machines)")
    _write_json(args.json, rows)
    return rows


if __name__ == "__main__":
    main()
