"""Where the discovery loop's time goes: seconds and simulations per phase of the loop (the baseline polish, the
score tests, the scouts, the refits, the verdict rules, the report), for the job's report and for measuring what an
optimisation saves (issue 14). Phases nest; each second and each simulation is charged to the innermost phase
running (so the rows add up to the loop's total, with what no phase marks as ``other``)."""
from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager


class PhaseClock:
    """Exclusive time and simulation counts per named phase; ``count()`` gives the simulations run so far."""

    def __init__(self, count: Callable[[], int] = lambda: 0):
        self._count = count
        self._stack: list[str] = []
        self._prefix = ""
        self._mark = (time.perf_counter(), count())
        self.totals: dict[str, list] = {}  # name -> [seconds, simulations, entries]

    def _charge(self) -> None:
        now, n = time.perf_counter(), self._count()
        if self._stack:
            row = self.totals.setdefault(self._stack[-1], [0.0, 0, 0])
            row[0] += now - self._mark[0]
            row[1] += n - self._mark[1]
        self._mark = (now, n)

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        """Charge what runs inside to ``name`` (within the current :meth:`scope`), less the phases nested in it."""
        self._charge()
        self._stack.append(self._prefix + name)
        self.totals.setdefault(self._stack[-1], [0.0, 0, 0])[2] += 1
        try:
            yield
        finally:
            self._charge()
            self._stack.pop()

    @contextmanager
    def scope(self, prefix: str) -> Iterator[None]:
        """Phases opened inside are named ``prefix`` + their name (e.g. the loop run again from another route)."""
        before, self._prefix = self._prefix, prefix
        try:
            yield
        finally:
            self._prefix = before

    def rows(self, seconds_total: float | None = None, simulations_total: int | None = None) -> list[dict]:
        """One row per phase, the most expensive first: ``phase``, ``seconds``, ``simulations``, ``entries``; with
        the totals, a row ``other`` for what no phase marked (when there is any)."""
        out = [{"phase": k, "seconds": v[0], "simulations": v[1], "entries": v[2]} for k, v in self.totals.items()]
        if seconds_total is not None:
            rest_s = seconds_total - sum(r["seconds"] for r in out)
            rest_n = (simulations_total - sum(r["simulations"] for r in out)) if simulations_total is not None else 0
            if rest_s > 0.05 or rest_n > 0:
                out.append({"phase": "other", "seconds": max(rest_s, 0.0), "simulations": rest_n, "entries": 0})
        return sorted(out, key=lambda r: -r["seconds"])


def phase_text(rows: list[dict], limit: int = 8) -> str:
    """The rows in one line: "scouts 21.3 s (4 180 simulations), refits 18.0 s (…), …" (the ``limit`` largest)."""
    parts = [f"{r['phase']} {r['seconds']:.1f} s ({r['simulations']} simulations)" for r in rows[:limit]]
    more = rows[limit:]
    if more:
        parts.append(f"{len(more)} more {sum(r['seconds'] for r in more):.1f} s")
    return ", ".join(parts)
