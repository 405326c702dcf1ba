"""The ledger of the adversarial set's runs: one JSON line per discover run, kept in the repository
(``docs/adversarial_ledger.jsonl``), so that what the loop did on each record — under which code and which settings
— outlives the session that ran it, and an option can be judged against the defaults record by record.

``python -m jobs.adversarial_ledger add OUT/results.json [...]`` adds the rows of :mod:`jobs.bench_adversarial`
results (``bench_adversarial --ledger PATH`` adds each run as it ends); ``show [--overrides "K=V ..."]`` prints the
latest row of every record under exactly those overrides (none: the defaults of each row's commit) as the README's
table; ``compare --overrides "K=V ..."`` sets each record's latest run with the overrides beside its latest run at
the defaults and says which verdicts moved and which way, which records the option has not met yet and the median
ratio of wall times — what an option must show before it becomes a default (README, *the loop judged on records
made outside its tests*).

A row is a result row of :func:`jobs.adversarial_verdicts.result_row` without the paths of the machine that made
it, plus ``overrides`` (sorted), ``draw`` (0: the set, K: the K-th held-out draw), ``jobs`` (discover jobs that ran
side by side, where known) and ``date``. Rows are only ever appended; a record's "latest" is its last line.
"""
from __future__ import annotations

import argparse
import datetime as _dt
import json
import re
import statistics
import sys
import threading
from collections.abc import Iterable, Sequence
from pathlib import Path

from jobs.adversarial_set import ROOT
from jobs.adversarial_verdicts import results_markdown, summarise

#: The ledger the repository keeps.
LEDGER = ROOT / "docs" / "adversarial_ledger.jsonl"

#: Fields of a result row the ledger keeps (paths and long texts of the machine that ran it are left out).
FIELDS = ("record", "category", "command", "truth", "noise", "accepted", "ambiguous", "compensating", "unexplained",
          "noise_model", "structure_left", "rmse_before_um", "rmse_after_um", "before_sigma", "after_sigma",
          "verdict", "wall_s", "commit", "csv_sha256", "localisation", "error")

_LOCK = threading.Lock()  # discover jobs side by side in one bench process append from their threads


class LedgerError(ValueError):
    """A ledger line or an argument that cannot be read (one line, naming it)."""


def draw_of(record: str) -> int:
    """The held-out draw a record's name says (:func:`jobs.adversarial_set.replicate_name`: ``rec15_d1`` and its
    replicates ``rec15_d1_r2`` → 1; ``rec15`` and its replicates → 0)."""
    m = re.search(r"_d(\d+)(?:_r\d+)?$", record)
    return int(m.group(1)) if m else 0


def ledger_row(row: dict, *, jobs: int | None = None, date: str | None = None) -> dict:
    """The ledger's line for a result row of :mod:`jobs.bench_adversarial` (its ``overrides`` sorted)."""
    if "record" not in row or "verdict" not in row:
        raise LedgerError(f"not a result row (no record or verdict): {sorted(row)[:8]}")
    out = {k: row[k] for k in FIELDS if k in row}
    out["overrides"] = sorted(row.get("overrides") or [])
    out["draw"] = draw_of(row["record"])
    out["jobs"] = jobs
    out["date"] = date or _dt.date.today().isoformat()
    return out


def append(path: Path, rows: Iterable[dict]) -> int:
    """Append ledger lines (made by :func:`ledger_row`) to ``path``, one ``write`` per line; how many."""
    lines = [json.dumps(r, ensure_ascii=False, sort_keys=True) + "\n" for r in rows]
    with _LOCK, open(path, "a", encoding="utf-8") as fh:
        for line in lines:
            fh.write(line)
            fh.flush()
    return len(lines)


def read(path: Path) -> list[dict]:
    """Every line of the ledger at ``path``, in order ([] for a file that does not exist)."""
    path = Path(path)
    if not path.exists():
        return []
    rows = []
    for k, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except json.JSONDecodeError as exc:
            raise LedgerError(f"{path}:{k}: not a JSON line ({exc.msg})") from None
        if not isinstance(row, dict) or "record" not in row or "verdict" not in row:
            raise LedgerError(f"{path}:{k}: a ledger line needs a record and a verdict")
        rows.append(row)
    return rows


def parse_overrides(text: str | Sequence[str] | None) -> list[str]:
    """``"a=1 b=2"`` (or a list of ``K=V``) as the sorted list a row keeps; each item must be a Hydra ``K=V``."""
    items = (text.split() if isinstance(text, str) else list(text)) if text else []
    for it in items:
        if "=" not in it or it.startswith("="):
            raise LedgerError(f"an override is KEY=VALUE, got {it!r}")
    return sorted(items)


def latest(rows: Sequence[dict], overrides: Sequence[str] = (), draw: int | None = None) -> dict[str, dict]:
    """Each record's last row run with exactly ``overrides`` (of held-out draw ``draw``; None: every draw)."""
    want = sorted(overrides)
    out: dict[str, dict] = {}
    for r in rows:
        if r.get("overrides", []) == want and (draw is None or r.get("draw", draw_of(r["record"])) == draw):
            out[r["record"]] = r
    return out


def show(rows: Sequence[dict], overrides: Sequence[str] = (), draw: int | None = None) -> str:
    """The README's table of the latest rows under ``overrides``, with its summary."""
    last = latest(rows, overrides, draw)
    table = [last[k] for k in sorted(last)]  # record names are zero-padded: rec02 < rec02_d1 < rec10
    return results_markdown(table, summarise(table)) if table else "no rows with these overrides"


#: How much a verdict is worth to a user, to say which way a moved one went: right (3); right, but tied with a rival
#: the record cannot tell from it (2); nothing named where something was due, or a true effect left unflagged beside
#: the rest (1); something wrong named or offered (0).
_RANKS = {"exact": 3, "unexplained-correct": 3, "ambiguous-correct": 2, "exact+outside-missed": 1, "missed": 1,
          "spurious": 0, "ambiguous-wrong": 0}


def _rank(row: dict) -> int:
    return _RANKS.get(row["verdict"], 0)


def compare(rows: Sequence[dict], overrides: Sequence[str], draw: int | None = None) -> tuple[list[dict], dict]:
    """Every record run with ``overrides``, beside its latest run at the defaults: (pairs, summary). A pair's
    ``moved`` is True where the verdict differs (a record never run at the defaults: None)."""
    want = parse_overrides(overrides)
    if not want:
        raise LedgerError("compare needs the overrides to set beside the defaults")
    mine, default = latest(rows, want, draw), latest(rows, (), draw)
    pairs = []
    for rec in sorted(mine):
        d = default.get(rec)
        pairs.append({"record": rec, "category": mine[rec].get("category"), "default": d, "with": mine[rec],
                      "moved": None if d is None else d["verdict"] != mine[rec]["verdict"]})
    moved = [p for p in pairs if p["moved"]]
    summary = {"records": len(pairs), "kept": sum(p["moved"] is False for p in pairs),
               "moved": [p["record"] for p in moved],
               "better": [p["record"] for p in moved if _rank(p["with"]) > _rank(p["default"])],
               "worse": [p["record"] for p in moved if _rank(p["with"]) < _rank(p["default"])],
               "no_default": [p["record"] for p in pairs if p["moved"] is None],
               "not_run": sorted(set(default) - set(mine))}
    ratios = [p["with"]["wall_s"] / p["default"]["wall_s"] for p in pairs
              if p["default"] and (p["default"].get("wall_s") or 0) > 0 and p["with"].get("wall_s") is not None]
    summary["wall_ratio_median"] = statistics.median(ratios) if ratios else None
    return pairs, summary


def _cell(r: dict | None) -> str:
    if r is None:
        return "–"
    acc = ", ".join(r.get("accepted") or []) or "none"
    rms = ("" if r.get("rmse_after_um") is None else
           f", {r.get('rmse_before_um', float('nan')):.4g} → {r['rmse_after_um']:.4g} µm")
    wall = "" if r.get("wall_s") is None else f", {r['wall_s']:.0f} s"
    return f"{r['verdict']} ({acc}{rms}{wall}; {r.get('commit') or 'commit not recorded'})"


def compare_markdown(pairs: list[dict], summary: dict, overrides: Sequence[str]) -> str:
    head = (f"| record | kind | defaults | with {' '.join(parse_overrides(overrides))} | verdict moved |\n"
            "|---|---|---|---|---|")
    body = [f"| {p['record']} | {p['category']} | {_cell(p['default'])} | {_cell(p['with'])} | "
            f"{'–' if p['moved'] is None else ('**yes**' if p['moved'] else 'no')} |" for p in pairs]
    s = summary
    tail = (f"{s['kept']} of {s['records']} records kept their verdict"
            + (f"; moved: {', '.join(s['moved'])} (better: {', '.join(s['better']) or 'none'}; worse: "
               f"{', '.join(s['worse']) or 'none'})" if s["moved"] else "")
            + (f"; not run at the defaults: {', '.join(s['no_default'])}" if s["no_default"] else "") + "."
            + ("" if s.get("wall_ratio_median") is None else
               f" Wall time with them over the defaults' (median of the records; machines and loads differ): "
               f"{s['wall_ratio_median']:.2f}.")
            + (f"\nNot yet run with them ({len(s['not_run'])}): {', '.join(s['not_run'])}." if s["not_run"] else ""))
    return "\n".join([head, *body, "", tail])


def add_results(path: Path, results: Sequence[Path], jobs: int | None = None) -> int:
    """Append the rows of :mod:`jobs.bench_adversarial`'s ``results.json`` files (their ``overrides`` as run)."""
    rows = []
    for res in results:
        try:
            data = json.loads(Path(res).read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as exc:
            raise LedgerError(f"{res}: cannot read a results.json ({exc})") from None
        if not isinstance(data, dict) or not isinstance(data.get("rows"), list):
            raise LedgerError(f"{res}: a results.json has a list of rows")
        for r in data["rows"]:
            rows.append(ledger_row({**r, "overrides": r.get("overrides", data.get("overrides", []))}, jobs=jobs))
    return append(path, rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m jobs.adversarial_ledger", description=__doc__.split("\n")[0])
    ap.add_argument("--ledger", default=str(LEDGER), help=f"the ledger (default {LEDGER.relative_to(ROOT)})")
    sub = ap.add_subparsers(dest="cmd", required=True)
    a = sub.add_parser("add", help="append the rows of bench_adversarial results.json files")
    a.add_argument("results", nargs="+")
    a.add_argument("--jobs", type=int, default=None, help="discover jobs that ran side by side")
    for name in ("show", "compare"):
        p = sub.add_parser(name)
        p.add_argument("--overrides", default="", help='the runs\' Hydra overrides, e.g. "discover.pair_look=4"')
        p.add_argument("--draw", type=int, default=None, help="only this draw (0: the set, K: held-out draw K)")
    args = ap.parse_args(argv)
    try:
        path = Path(args.ledger)
        if args.cmd == "add":
            print(f"{add_results(path, [Path(r) for r in args.results], args.jobs)} row(s) added to {path}")
        elif args.cmd == "show":
            print(show(read(path), parse_overrides(args.overrides), args.draw))
        else:
            pairs, summary = compare(read(path), parse_overrides(args.overrides), args.draw)
            print(compare_markdown(pairs, summary, args.overrides))
    except LedgerError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
