"""The discovery loop's phase clock (toggle_id/discovery/timing.py): each second and simulation is charged to the
innermost phase running, so the rows add up to the total."""
from __future__ import annotations

import time

import pytest

from toggle_id.discovery.timing import PhaseClock, phase_text


class Counter:
    def __init__(self):
        self.n = 0


def test_nested_phases_are_charged_exclusively():
    sims = Counter()
    clock = PhaseClock(lambda: sims.n)
    t0 = time.perf_counter()
    with clock("outer"):
        sims.n += 3
        time.sleep(0.02)
        with clock("inner"):
            sims.n += 5
            time.sleep(0.04)
        sims.n += 1
    with clock("inner"):  # entered again: its totals add up
        sims.n += 2
    sims.n += 7  # outside every phase: "other"
    total = time.perf_counter() - t0
    rows = {r["phase"]: r for r in clock.rows(total, sims.n)}
    assert rows["outer"]["simulations"] == 4 and rows["inner"]["simulations"] == 7
    assert rows["inner"]["entries"] == 2 and rows["outer"]["entries"] == 1
    assert rows["other"]["simulations"] == 7
    assert rows["inner"]["seconds"] >= 0.04 and 0.02 <= rows["outer"]["seconds"] < 0.04 + 0.02
    assert sum(r["seconds"] for r in rows.values()) == pytest.approx(total, rel=1e-9, abs=1e-9)
    assert sum(r["simulations"] for r in rows.values()) == sims.n


def test_a_phase_that_raises_is_still_closed_and_a_scope_prefixes_names():
    clock = PhaseClock()
    with pytest.raises(RuntimeError):
        with clock("fails"):
            raise RuntimeError("boom")
    with clock.scope("route 2: "):
        with clock("refits"):
            pass
    with clock("refits"):
        pass
    assert set(clock.totals) == {"fails", "route 2: refits", "refits"}
    assert clock._stack == [] and clock._prefix == ""


def test_rows_without_totals_have_no_other_row_and_the_text_names_the_largest():
    clock = PhaseClock()
    clock.totals = {"a": [1.0, 10, 1], "b": [3.0, 30, 2], "c": [0.5, 0, 1]}
    rows = clock.rows()
    assert [r["phase"] for r in rows] == ["b", "a", "c"]
    assert phase_text(rows, limit=2) == "b 3.0 s (30 simulations), a 1.0 s (10 simulations), 1 more 0.5 s"
