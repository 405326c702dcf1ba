"""An adversarial set of records on which the discovery loop is judged.

``python -m jobs.bench_adversarial --out DIR [--only NAME,...] [--duration S] [--calibrate] [--validation]
[--replicates K] [--draw K] [--run] [--jobs N] [--timeout S] [--mlflow-uri URI] [--override KEY=VALUE ...]
[--ledger PATH]``

Writes CSV records (docs/model.md §8, via :func:`toggle_id.data.write_csv`) and ``manifest.json`` (the truth of each:
parameters, effects, noise model, command) into DIR. A record's name (``rec01`` …) says nothing about what is in
it; only the manifest does. The set — what each record holds, how its truth is drawn, the calibration — is
:mod:`jobs.adversarial_set`; the verdicts and the tables are :mod:`jobs.adversarial_verdicts`.

``--validation`` also writes each machine's second record, ``recNN_validation.csv``: the same truth, effects and
noise model under the other kind of command (:data:`jobs.adversarial_set.SECOND_COMMAND`: a swept machine is also cycled, a cycled one
swept at A = 0.25 V) with independent noise; the discover runs get it as ``validation.path`` (predicted, never
fitted: an effect must predict it better, and structure left in its prediction makes the result unexplained).

``--replicates K`` also writes (and runs) K replicates of each record, ``recNN_r1`` …: the same machine, command
and noise model with independent noise (none of a record without random noise, the quantised reading alone). A
verdict is one draw of the noise; the replicates say how often it comes out so — on the noise-only records, how
often the loop names an effect that is not there.

``--draw K`` (K ≥ 1) writes (and runs) the K-th *held-out* set instead, ``recNN_dK``: each spec on another machine,
its 15 parameters drawn as the set's are but from another seed, with its own noise, and its magnitudes calibrated
for that machine to the spec's target (measured once, kept in ``calibration_dK.json``). The set's rules were
made while looking at the set's records; a held-out draw is data they were not made on.

``--run`` then runs the discover job on every record (``python -m jobs.run +experiment=discover data=csv
data.path=… seed=0 progress=false``; MLflow off unless ``--mlflow-uri``; ``--override`` adds Hydra overrides),
``--jobs`` at a time, and writes ``results.json`` and ``results.md``: truth, accepted effects, compensating ones,
RMS before → after (µm and multiples of σ), the verdict (exact / spurious / missed / unexplained-correct) and the
wall time, with a summary. A record whose run already succeeded (on the same CSV) is not run again.
``--ledger PATH`` also appends each run made to the ledger of the set's runs (:mod:`jobs.adversarial_ledger`).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from jobs.adversarial_calibration import calibrate, calibration_table
from jobs.adversarial_set import ROOT, generate, replicate_count, replicate_name, select
from jobs.adversarial_specs import CALIBRATED, DURATION, NAMES
from jobs.adversarial_verdicts import result_row, results_markdown, summarise
from toggle_id.checkpoint import atomic_write_text
from toggle_id.simulate import share_cores


def run_one(entry: dict, out: Path, extra: list[str], mlflow_uri: str | None, timeout: float, log=print, *,
            shared_cores: bool = False, ledger: Path | None = None, jobs: int = 1) -> dict:
    """Run the discover job on one record (skipped if it already succeeded on the same CSV with the same
    overrides); its result row. ``shared_cores``: other jobs run beside it (``--jobs`` > 1). ``ledger``: a run
    made here is also appended there (:mod:`jobs.adversarial_ledger`), with ``jobs`` side by side."""
    if entry.get("validation"):  # the machine's second record: predicted, never fitted
        extra = [*extra, f"validation.path={(out / entry['validation']['file']).resolve()}"]
    run_dir = out / "runs" / entry["name"]
    row_path = run_dir / "result_row.json"
    if row_path.exists():
        row = json.loads(row_path.read_text())
        if (row.get("verdict") != "error" and row.get("csv_sha256") == entry.get("sha256")
                and row.get("validation_sha256") == (entry.get("validation") or {}).get("sha256")
                and row.get("overrides", []) == list(extra)):
            report = Path(row.get("report") or "")
            if report.is_file():  # judged again from its report (the judging may have changed, not the run)
                row = {**result_row(entry, json.loads(report.read_text()), row["wall_s"], str(report)),
                       "overrides": list(extra), "validation_sha256": row.get("validation_sha256")}
                from toggle_id.checkpoint import atomic_write_json

                atomic_write_json(row_path, row)
            log(f"{entry['name']}: done before ({row['verdict']})")
            return row
    run_dir.mkdir(parents=True, exist_ok=True)
    tracking = [f"tracking.uri={mlflow_uri}"] if mlflow_uri else ["tracking.enabled=false"]
    cmd = [sys.executable, "-m", "jobs.run", "+experiment=discover", "data=csv",
           f"data.path={(out / entry['file']).resolve()}", "seed=0", "progress=false", *tracking,
           f"hydra.run.dir={run_dir.resolve()}", *extra]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)}
    if shared_cores:  # jobs side by side: see toggle_id.simulate.SHARED_CORES_ENV
        share_cores(env)
    log(f"{entry['name']}: running the discover job …")
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout,
                              check=False)
        code, stdout, stderr = proc.returncode, proc.stdout, proc.stderr
    except subprocess.TimeoutExpired as exc:
        code, stdout, stderr = -1, exc.stdout or "", f"timeout after {timeout:g} s"
        stdout = stdout if isinstance(stdout, str) else stdout.decode(errors="replace")
    wall = time.perf_counter() - t0
    (run_dir / "stdout.txt").write_text(stdout)
    (run_dir / "stderr.txt").write_text(stderr if isinstance(stderr, str) else str(stderr))
    lines = [ln for ln in stdout.splitlines() if ln.strip()]
    report_path = lines[-1].removeprefix("report: ").strip() if lines and lines[-1].startswith("report: ") else None
    if code != 0 or not report_path or not Path(report_path).exists():
        tail = " ".join((stderr or "").strip().splitlines()[-3:])[-500:]
        row = {"record": entry["name"], "category": entry["category"], "verdict": "error", "wall_s": wall,
               "error": f"exit {code}: {tail}", "csv_sha256": entry.get("sha256")}
    else:
        row = result_row(entry, json.loads(Path(report_path).read_text()), wall, report_path)
    row["overrides"] = list(extra)
    row["validation_sha256"] = (entry.get("validation") or {}).get("sha256")
    from toggle_id.checkpoint import atomic_write_json

    atomic_write_json(row_path, row)
    if ledger is not None:
        from jobs.adversarial_ledger import append, ledger_row

        append(ledger, [ledger_row(row, jobs=jobs)])
    log(f"{entry['name']}: {row['verdict']} ({wall:.0f} s)")
    return row


def run_all(out: Path, manifest: dict, names: list[str], extra: list[str], mlflow_uri: str | None, jobs: int,
            timeout: float, log=print, ledger: Path | None = None) -> tuple[list[dict], dict]:
    from toggle_id.checkpoint import atomic_write_json

    entries = [r for r in manifest["records"] if r["name"] in names]
    if jobs <= 1:
        rows = [run_one(e, out, extra, mlflow_uri, timeout, log, ledger=ledger) for e in entries]
    else:
        with ThreadPoolExecutor(max_workers=jobs) as pool:
            rows = list(pool.map(lambda e: run_one(e, out, extra, mlflow_uri, timeout, log, shared_cores=True,
                                                   ledger=ledger, jobs=jobs), entries))
    done = {}
    for r in manifest["records"]:  # every record with a result so far, this run's or an earlier one's
        p = out / "runs" / r["name"] / "result_row.json"
        if p.exists():
            done[r["name"]] = json.loads(p.read_text())
    rows_all = [done[k] for k in sorted(done)]
    summary = summarise(rows_all)
    md = results_markdown(rows_all, summary)
    atomic_write_json(out / "results.json", {"summary": summary, "rows": rows_all, "overrides": extra})
    atomic_write_text(out / "results.md", md + "\n")
    print(md, flush=True)
    return rows, summary


# ------------------------------------------------------------------------------------------ command line
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m jobs.bench_adversarial", description=__doc__.split("\n")[0])
    ap.add_argument("--out", required=True, help="directory of the records, the manifest and the results")
    ap.add_argument("--only", default=None, help="comma-separated record names (rec07) or keys (noise_white)")
    ap.add_argument("--duration", type=float, default=DURATION, help="record length in s (the calibration is for 5)")
    ap.add_argument("--calibrate", action="store_true", help="measure the magnitudes again (slow) and use them")
    ap.add_argument("--run", action="store_true", help="run the discover job on each record and judge it")
    ap.add_argument("--jobs", type=int, default=1, help="discover jobs at a time (default 1: sequential)")
    ap.add_argument("--timeout", type=float, default=7200.0, help="seconds per discover job")
    ap.add_argument("--mlflow-uri", default=None, help="track the runs in this MLflow store (default: no tracking)")
    ap.add_argument("--override", action="append", default=[], help="extra Hydra override of every run (repeatable)")
    ap.add_argument("--ledger", default=None,
                    help="also append each run made here to this ledger (docs/adversarial_ledger.jsonl: "
                         "python -m jobs.adversarial_ledger)")
    ap.add_argument("--validation", action="store_true",
                    help="also write each machine's second record (the other command, independent noise) and give it "
                         "to the discover job as validation.path: predicted, never fitted")
    ap.add_argument("--replicates", type=int, default=0,
                    help="also write (and run) K replicates of each record: the same machine, independent noise")
    ap.add_argument("--draw", type=int, default=0,
                    help="K > 0: the K-th held-out set instead — each spec on another machine drawn the same way, "
                         "its magnitudes calibrated for it (kept in OUT/calibration_dK.json), records recNN_dK")
    args = ap.parse_args(argv)
    if not (args.duration > 0):
        ap.error(f"--duration must be positive, got {args.duration}")
    if args.jobs < 1:
        ap.error(f"--jobs must be at least 1, got {args.jobs}")
    if args.replicates < 0:
        ap.error(f"--replicates must be at least 0, got {args.replicates}")
    if args.draw < 0:
        ap.error(f"--draw must be at least 0, got {args.draw}")
    out = Path(args.out).expanduser().resolve()
    specs = select(args.only)
    calibrated = {k: dict(v) for k, v in CALIBRATED.items()} if args.draw == 0 else {}
    if args.calibrate or args.draw:
        out.mkdir(parents=True, exist_ok=True)
        path = out / ("calibration.json" if args.draw == 0 else f"calibration_d{args.draw}.json")
        # a held-out machine's magnitudes are its own: measured once, kept beside its records
        known = json.loads(path.read_text()) if args.draw and path.exists() else {}
        todo = [s for s in specs if s.calibrate and (args.calibrate or s.key not in known)]
        cal = calibrate(todo, args.duration, draw=args.draw) if todo else {}
        known.update(cal)
        for key, params in known.items():
            calibrated[key] = {p: (c["value"], c["ratio"]) for p, c in params.items()}
        atomic_write_text(path, json.dumps(known, indent=1))
        if cal and args.draw == 0:
            print("CALIBRATED entries (paste into jobs/adversarial_specs.py):\n" + calibration_table(cal), flush=True)
    manifest = generate(out, specs, calibrated, args.duration, validation=args.validation, replicates=args.replicates,
                        draw=args.draw)
    if args.run:
        names = [replicate_name(NAMES[s.key], k, args.draw) for s in specs
                 for k in range(replicate_count(s, args.replicates))]
        _, summary = run_all(out, manifest, names, args.override, args.mlflow_uri, args.jobs, args.timeout,
                             ledger=Path(args.ledger).expanduser().resolve() if args.ledger else None)
        if summary["errors"]:
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
