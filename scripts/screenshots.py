"""Screenshots of the MLflow UI for the README: the runs table, one- vs two-stage `best_rmse_um` curves, a sweep's
parallel-coordinates view.

    pip install -e ".[screenshots]"            # Playwright's Python API; the browser is Debian's chromium
    python scripts/screenshots.py --demo       # make a few small runs in a scratch store first, then shoot
    python scripts/screenshots.py --store mlflow.db --out docs/screenshots

It starts `mlflow server` on loopback (a free port) over the store, drives a headless Chromium
(``--chromium /usr/bin/chromium``) through Playwright and writes PNGs into ``--out``. Nothing here is needed by
the jobs or the tests.
"""
from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
import urllib.parse
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM_FLAGS = ["--headless=new", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                  "--disable-dev-shm-usage", "--disable-extensions", "--disable-sync", "--no-first-run",
                  "--metrics-recording-only", "--mute-audio"]
# small runs that still show the methods apart (a 2-s record, ~30 s each on two cores)
DEMO = ["ga=small", "ga.generations=15", "evaluator=serial", "data.duration=2.0", "polish.max_nfev=15",
        "progress=false"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def make_demo_runs(store: Path, workdir: Path) -> None:
    """A one-stage and a two-stage run, and a two-stage sweep over population and seed, into ``store``."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MLFLOW_TRACKING_URI": f"sqlite:///{store}"}
    jobs = [["+experiment=one_stage", "ga.population=100", *DEMO, f"hydra.run.dir={workdir / 'one'}"],
            ["+experiment=two_stage", "ga.population=100", *DEMO, f"hydra.run.dir={workdir / 'two'}"],
            ["-m", "+experiment=two_stage", "ga.population=40,100", "seed=0,1", *DEMO,
             f"hydra.sweep.dir={workdir / 'sweep'}"]]
    for args in jobs:
        print("run: python -m jobs.run", " ".join(args), flush=True)
        subprocess.run([sys.executable, "-m", "jobs.run", *args], cwd=workdir, env=env, check=True,
                       stdout=subprocess.DEVNULL)


def stop_server(server: subprocess.Popen) -> None:
    """Stop the `mlflow server` started here and the workers it spawned (its process group)."""
    import signal

    for sig, wait in ((signal.SIGTERM, 30), (signal.SIGKILL, 10)):
        try:
            os.killpg(server.pid, sig)
        except ProcessLookupError:
            return
        try:
            server.wait(timeout=wait)
            time.sleep(1.0)  # the workers leave after the server
        except subprocess.TimeoutExpired:
            continue
        try:
            os.killpg(server.pid, 0)
        except ProcessLookupError:
            return


def start_server(store: Path, artifacts: Path) -> tuple[subprocess.Popen, str]:
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    proc = subprocess.Popen([sys.executable, "-m", "mlflow", "server", "--host", "127.0.0.1", "--port", str(port),
                             "--backend-store-uri", f"sqlite:///{store}", "--artifacts-destination", str(artifacts),
                             "--workers", "1"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)  # its own process group: the server and its workers
    deadline = time.monotonic() + 120
    while True:
        try:
            with urllib.request.urlopen(f"{base}/health", timeout=2):
                return proc, base
        except OSError:
            if proc.poll() is not None or time.monotonic() > deadline:
                stop_server(proc)
                raise SystemExit("error: mlflow server did not start")
            time.sleep(0.5)


def api(base: str, path: str, body: dict | None = None) -> dict:
    req = urllib.request.Request(f"{base}/api/2.0/mlflow/{path}", method="POST" if body is not None else "GET",
                                 data=None if body is None else json.dumps(body).encode(),
                                 headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(req, timeout=30) as resp:
        return json.loads(resp.read().decode())


def find_runs(base: str, experiment: str) -> tuple[str, list[dict]]:
    exp = api(base, "experiments/get-by-name?" + urllib.parse.urlencode({"experiment_name": experiment}))
    exp_id = exp["experiment"]["experiment_id"]
    runs = api(base, "runs/search", {"experiment_ids": [exp_id], "max_results": 500,
                                     "filter": "tags.`mlflow.parentRunId` IS NULL"}).get("runs", [])
    return exp_id, runs


def shoot(base: str, exp_id: str, runs: list[dict], out: Path, chromium: str, settle_s: float = 6.0) -> list[Path]:
    """runs_table.png, best_rmse_one_vs_two_stage.png (the shared curve of a one-stage and a two-stage run on one
    axis) and sweep_parallel_coordinates.png (the runs of one sweep), those whose runs exist."""
    from playwright.sync_api import sync_playwright

    def tags(run: dict) -> dict:
        return {t["key"]: t["value"] for t in run["data"].get("tags", [])}

    identify = [r for r in runs if tags(r).get("job") == "identify" and "sweep" not in tags(r)]
    pair = [next((r for r in identify if tags(r).get("method") == m), None) for m in ("one_stage", "two_stage")]
    sweeps: dict[str, list[dict]] = {}
    for r in runs:
        if "sweep" in tags(r):
            sweeps.setdefault(tags(r)["sweep"], []).append(r)
    sweep = max(sweeps.values(), key=len) if sweeps else []
    exps = json.dumps([exp_id])
    shots = []
    out.mkdir(parents=True, exist_ok=True)
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=chromium, args=CHROMIUM_FLAGS, headless=True)
        page = browser.new_page(viewport={"width": 1600, "height": 1000}, device_scale_factor=1)

        def show_columns(names: tuple[str, ...]) -> None:
            """Tick metric columns in the runs table's "Columns" menu (the table shows none by default)."""
            page.get_by_role("button", name="Columns").first.click()
            time.sleep(1.0)
            box = page.get_by_placeholder("Search columns")
            for col in names:
                box.fill(col)
                time.sleep(0.8)
                item = page.get_by_text(col, exact=True)
                if item.count():
                    item.last.click()
                    time.sleep(0.5)
            box.fill("")
            page.keyboard.press("Escape")
            time.sleep(1.5)

        def save(name: str, url: str, columns: tuple[str, ...] = ()) -> None:
            page.goto(url, wait_until="load")
            time.sleep(settle_s)
            close = page.get_by_role("button", name="Close")  # the UI's assistant panel
            if close.count():
                close.first.click()
                time.sleep(1.0)
            if columns:
                show_columns(columns)
            path = out / name
            page.screenshot(path=str(path))
            shots.append(path)
            print("wrote", path, flush=True)

        save("runs_table.png", f"{base}/#/experiments/{exp_id}/runs", columns=("rmse_um", "n_simulations"))
        if all(pair):
            ids = json.dumps([r["info"]["run_id"] for r in pair])
            save("best_rmse_one_vs_two_stage.png",
                 f"{base}/#/metric?runs={ids}&metric={json.dumps('best_rmse_um')}&experiments={exps}"
                 f"&plot_metric_keys={json.dumps(['best_rmse_um'])}&plot_layout={{}}&x_axis=step&y_axis_scale=log"
                 f"&line_smoothness=1&show_point=true&deselected_curves=[]&last_linear_y_axis_range=[]")
        if sweep:
            ids = json.dumps([r["info"]["run_id"] for r in sweep])
            save("sweep_parallel_coordinates.png", f"{base}/#/compare-runs?runs={ids}&experiments={exps}")
        browser.close()
    return shots


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", default=str(ROOT / "mlflow.db"), help="SQLite store (default: the project's)")
    ap.add_argument("--experiment", default="toggle-id")
    ap.add_argument("--out", default=str(ROOT / "docs" / "screenshots"))
    ap.add_argument("--chromium", default="/usr/bin/chromium")
    ap.add_argument("--demo", action="store_true", help="make small runs in a scratch store and shoot those")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="toggle_id_shots_") as tmp:
        store = Path(args.store).resolve()
        if args.demo:
            store = Path(tmp) / "mlflow.db"
            make_demo_runs(store, Path(tmp))
        server, base = start_server(store, Path(tmp) / "artifacts")
        try:
            exp_id, runs = find_runs(base, args.experiment)
            shoot(base, exp_id, runs, Path(args.out), args.chromium)
        finally:
            stop_server(server)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
