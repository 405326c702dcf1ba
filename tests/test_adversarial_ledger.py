"""The ledger of the adversarial set's runs (jobs/adversarial_ledger.py): rows kept, read back, the latest per record
under given settings, and an option set beside the defaults record by record."""
from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

import jobs.adversarial_ledger as L
import jobs.bench_adversarial as B


def _row(record: str, verdict: str, overrides=(), **kw) -> dict:
    return {"record": record, "category": kw.pop("category", "library"), "command": "simulation",
            "truth": ["dead_time"], "noise": "σ 1 µm white", "accepted": kw.pop("accepted", ["dead_time"]),
            "compensating": [], "unexplained": False, "rmse_before_um": 2.0, "rmse_after_um": 1.0,
            "before_sigma": 2.0, "after_sigma": 1.0, "verdict": verdict, "wall_s": 300.0, "commit": "abc1234",
            "report": "/somewhere/discovery.json", "overrides": list(overrides), **kw}


def test_a_row_keeps_the_result_without_the_machines_paths_and_says_its_draw_and_settings():
    row = L.ledger_row(_row("rec15_d1", "missed", ["b=2", "a=1"]), jobs=2, date="2026-12-07")
    assert row["draw"] == 1 and row["overrides"] == ["a=1", "b=2"] and row["jobs"] == 2
    assert "report" not in row and row["verdict"] == "missed" and row["commit"] == "abc1234"
    assert L.draw_of("rec07") == 0 and L.draw_of("rec07_r2") == 0 and L.draw_of("rec07_d12") == 12
    assert L.draw_of("rec07_d1_r2") == 1  # a held-out machine's replicate (adversarial_set.replicate_name)
    with pytest.raises(L.LedgerError, match="not a result row"):
        L.ledger_row({"wall_s": 1.0})


def test_rows_are_appended_and_read_back_and_a_bad_line_is_named(tmp_path: Path):
    path = tmp_path / "ledger.jsonl"
    assert L.read(path) == []
    assert L.append(path, [L.ledger_row(_row("rec01", "exact")), L.ledger_row(_row("rec02", "missed"))]) == 2
    assert L.append(path, [L.ledger_row(_row("rec01", "spurious"))]) == 1
    assert [r["verdict"] for r in L.read(path)] == ["exact", "missed", "spurious"]
    with open(path, "a", encoding="utf-8") as fh:
        fh.write("{not json\n")
    with pytest.raises(L.LedgerError, match=r"ledger.jsonl:4: not a JSON line"):
        L.read(path)
    path.write_text('{"record": "rec01"}\n')
    with pytest.raises(L.LedgerError, match=r":1: a ledger line needs a record and a verdict"):
        L.read(path)


def test_the_latest_row_per_record_is_taken_under_exactly_the_settings_asked():
    rows = [L.ledger_row(r) for r in (_row("rec01", "missed"), _row("rec01", "exact"), _row("rec01", "spurious", ["x=1"]),
                                      _row("rec01_d1", "missed"), _row("rec02", "exact", ["x=1", "y=2"]))]
    assert {k: r["verdict"] for k, r in L.latest(rows).items()} == {"rec01": "exact", "rec01_d1": "missed"}
    assert {k: r["verdict"] for k, r in L.latest(rows, draw=0).items()} == {"rec01": "exact"}
    assert {k: r["verdict"] for k, r in L.latest(rows, ["x=1"]).items()} == {"rec01": "spurious"}
    assert list(L.latest(rows, ["y=2", "x=1"])) == ["rec02"]  # the order of the overrides does not matter
    table = L.show(rows, (), 0)
    assert "| rec01 | library |" in table and "Exact effect set on 1 of 1 in-library records" in table
    assert L.show(rows, ["z=3"]) == "no rows with these overrides"


def test_an_option_is_set_beside_the_defaults_record_by_record():
    rows = [L.ledger_row(r) for r in (
        _row("rec15_d1", "missed"), _row("rec15_d1", "exact", ["discover.level_min_count=100"], wall_s=150.0),
        _row("rec03", "exact", category="noise", accepted=[]),
        _row("rec03", "exact", ["discover.level_min_count=100"], category="noise", accepted=[]),
        _row("rec21_d1", "spurious", ["discover.level_min_count=100"], category="outside"))]
    pairs, summary = L.compare(rows, "discover.level_min_count=100")
    assert [p["record"] for p in pairs] == ["rec03", "rec15_d1", "rec21_d1"]
    assert summary == {"records": 3, "kept": 1, "moved": ["rec15_d1"], "better": ["rec15_d1"], "worse": [],
                       "no_default": ["rec21_d1"], "not_run": [], "wall_ratio_median": 0.75}
    text = L.compare_markdown(pairs, summary, "discover.level_min_count=100")
    assert ("| rec15_d1 | library | missed (dead_time, 2 → 1 µm, 300 s; abc1234) | exact (dead_time, 2 → 1 µm, "
            "150 s") in text
    assert text.endswith("1 of 3 records kept their verdict; moved: rec15_d1 (better: rec15_d1; worse: none); "
                         "not run at the defaults: rec21_d1. Wall time with them over the defaults' (median of the "
                         "records; machines and loads differ): 0.75.")
    # a verdict that went wrong, and the records the option has not met yet
    rows += [L.ledger_row(r) for r in (_row("rec04", "exact"), _row("rec07", "exact"),
                                       _row("rec04", "spurious", ["discover.level_min_count=100"]))]
    pairs, summary = L.compare(rows, "discover.level_min_count=100")
    assert summary["worse"] == ["rec04"] and summary["better"] == ["rec15_d1"] and summary["not_run"] == ["rec07"]
    # a tie resolved is better, a named effect turned into a tie worse
    rows += [L.ledger_row(r) for r in (_row("rec20_d1", "ambiguous-correct"), _row("rec08", "exact"),
                                       _row("rec20_d1", "exact", ["discover.level_min_count=100"]),
                                       _row("rec08", "ambiguous-correct", ["discover.level_min_count=100"]))]
    summary = L.compare(rows, "discover.level_min_count=100")[1]
    assert summary["better"] == ["rec15_d1", "rec20_d1"] and summary["worse"] == ["rec04", "rec08"]
    assert L.compare_markdown(pairs, summary, "discover.level_min_count=100").endswith(
        "\nNot yet run with them (1): rec07.")
    with pytest.raises(L.LedgerError, match="needs the overrides"):
        L.compare(rows, "")
    with pytest.raises(L.LedgerError, match="KEY=VALUE"):
        L.parse_overrides("discover.level_min_count")


def test_results_of_the_bench_are_added_and_a_bad_file_is_one_line(tmp_path: Path, capsys):
    res = tmp_path / "results.json"
    res.write_text(json.dumps({"summary": {}, "overrides": ["a=1"], "rows": [_row("rec04", "exact", ["a=1"]),
                                                                              {**_row("rec05", "exact"), "overrides": None}]}))
    ledger = tmp_path / "ledger.jsonl"
    assert L.main(["--ledger", str(ledger), "add", str(res), "--jobs", "2"]) == 0
    got = L.read(ledger)
    assert [(r["record"], r["overrides"], r["jobs"]) for r in got] == [("rec04", ["a=1"], 2), ("rec05", [], 2)]
    assert L.main(["--ledger", str(ledger), "compare", "--overrides", "a=1"]) == 0
    assert "not run at the defaults: rec04" in capsys.readouterr().out
    (tmp_path / "bad.json").write_text("[]")
    assert L.main(["--ledger", str(ledger), "add", str(tmp_path / "bad.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "a results.json has a list of rows" in err and "\n" not in err


def test_the_bench_appends_each_run_it_makes_and_not_one_done_before(tmp_path: Path, monkeypatch):
    def fake_run(cmd, env, **kwargs):
        return subprocess.CompletedProcess(cmd, 1, "", "not run")

    monkeypatch.setattr(B.subprocess, "run", fake_run)
    entry = {"name": "rec01_d1", "category": "noise", "file": "rec01_d1.csv", "sha256": "abc", "effects": {},
             "outside": {}, "command": {"kind": "sweep", "sweep": "simulation"},
             "noise": {"sigma_m": 1e-6, "ar": 0.0, "quantum_m": 0.0}}
    ledger = tmp_path / "ledger.jsonl"
    B.run_one(entry, tmp_path, ["a=1"], None, 1.0, log=lambda *_: None, ledger=ledger, jobs=2)
    got = L.read(ledger)
    assert len(got) == 1 and got[0]["verdict"] == "error" and got[0]["overrides"] == ["a=1"] and got[0]["draw"] == 1
    assert got[0]["jobs"] == 2 and "not run" in got[0]["error"]
    row_path = tmp_path / "runs" / "rec01_d1" / "result_row.json"
    row_path.write_text(json.dumps({**json.loads(row_path.read_text()), "verdict": "exact",
                                    "report": str(tmp_path / "missing.json")}))
    B.run_one(entry, tmp_path, ["a=1"], None, 1.0, log=lambda *_: None, ledger=ledger)  # done before: no new line
    assert len(L.read(ledger)) == 1


def test_the_repositorys_ledger_reads_and_holds_every_record_of_the_set():
    rows = L.read(L.LEDGER)
    names = {r["record"] for r in rows if r["draw"] == 0 and not r["overrides"]}
    assert {f"rec{k:02d}" for k in range(1, 51)} <= names
    assert all(r["verdict"] != "error" for r in rows)
