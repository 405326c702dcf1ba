"""Routes: the discovery loop from more than one nominal basin, and the choice between what they reach.

Without the effect it lacks, the nominal model often has several nearly equal optima on a record, far apart in
the parameters (measured on a cycling record with a 4.3-µm backlash: 2.028 µm polished from the true values,
2.056 from the fast fit, 2.112 from the GA's, 2.12–2.13 from the assigned values). An effect refitted from one
of them may explain the record; from another it stops in a valley where the nominal parameters have already
absorbed part of it, and the loop then either adds a second, compensating effect or says "unexplained". Before
the loop says that structure is left, it therefore runs again from the other nominal fits it was given
(``alternatives``: e.g. the fast multistart fit beside the GA's), each a *route*; a route whose baseline lands in
a basin already tried is skipped, and so is one whose baseline is more than ``max_ratio`` times the lowest
route's (``discover.route_max_ratio``): a worse optimum, not a near-equal one (on the outside records the fast fit
polished to 2–44× the first route's error, which the reference values had rescued, and its loop there ran 19–41
min to end where it began). Where they differ, the routes' best models are compared with Vuong's test
(:func:`.stats.vuong`: non-nested fits of the same record, whitened by the best one's noise
model, Schwarz-corrected for their numbers of parameters): a route another beats significantly is out; of the
rest — fits the record cannot tell apart — the one that explains the record (no structure left) wins, then the
one with fewer parameters, then the earlier route (the job's own nominal fit first).

The nominal fit itself is a multistart problem on such a record: on adversarial record rec17 (a constant load
force, cycling command) 3 of 6 GA seeds end in a basin at 8.02 µm and 3 at 1.98 µm (polished baselines), and from
the 8-µm basin no effect of the library explains the record. While no route has explained the record, the job's
own method is therefore re-run from further seeds (``restarts``): a restart is a route only when its baseline is
lower than every route's so far — a better optimum of the same problem, not just another one.
"""
from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .engine import Outcome
from .model import Fit
from .noise import fit_noise
from .stats import vuong


@dataclass
class Route:
    """One run of the loop: its label (where its nominal fit came from), the plant that ran it (its baseline,
    iterations and refits), the outcome, the nominal fit it started from, or why it was not run."""

    label: str
    plant: Any
    outcome: Outcome | None = None
    nominal: Any = None
    skipped: str | None = None

    @property
    def reached(self) -> Fit:
        """The route's best model: with its compensating effects where it had to demote some."""
        return self.outcome.with_compensating if self.outcome.with_compensating is not None else self.outcome.final

    @property
    def structure_left(self) -> bool:
        return left_in(self.outcome)

    def to_dict(self, n: int, chosen: bool) -> dict:
        out: dict = {"label": self.label, "chosen": chosen, "skipped": self.skipped}
        base = getattr(self.plant, "baseline_fit", None)
        if base is not None:
            out["baseline_rmse_m"] = base.rmse(n)
            out["baseline_from"] = _from_other_start(base)[2:] or None  # None: from the route's own fit
        if self.outcome is not None:
            out.update({"rmse_after_m": self.outcome.final.rmse(n), "rmse_reached_m": self.reached.rmse(n),
                        "added": [a["name"] for a in self.outcome.added],
                        "compensating": [c["name"] for c in self.outcome.compensating],
                        "structure_left": self.structure_left})
        return out


def route_line(d: dict) -> str:
    """One line of text for a route's report entry (:meth:`Route.to_dict`)."""
    return f"route {d['label']}{' (reported)' if d['chosen'] else ''}: " + (
        f"skipped, {d['skipped']}" if d.get("skipped") else
        f"{d['baseline_rmse_m'] * 1e6:.4g}{' (' + d['baseline_from'] + ')' if d.get('baseline_from') else ''} → "
        f"{d['rmse_reached_m'] * 1e6:.4g} µm with "
        f"{', '.join(d['added'] + d['compensating']) or 'no effect'}{'; structure left' if d['structure_left'] else ''}")


def left_in(outcome: Outcome) -> bool:
    """Whether the structure test flags the final model's residual (the toggle plant's details: (diag, r, x))."""
    diag = outcome.structure[0] if isinstance(outcome.structure, tuple) else {}
    return bool((diag or {}).get("verdict", {}).get("structure_left", False))


def same_basin(a: Fit, b: Fit, n: int, rtol: float) -> bool:
    """Two baselines in one basin: their RMS errors agree to ``rtol`` (relative)."""
    ra, rb = a.rmse(n), b.rmse(n)
    return abs(ra - rb) <= rtol * min(ra, rb)


def _from_other_start(base: Fit) -> str:
    """", from another start; its own fit polished to … µm" where another start than the route's own fit won
    (read from :func:`.toggle_plant._baseline`'s report of every start's polish in ``base.info``)."""
    starts = base.info.get("starts") or []
    polished = [s for s in starts if "rmse_m" in s]
    own = next((s for s in starts if s.get("start") == 0), None)
    if not polished or own is None or min(polished, key=lambda s: s["rmse_m"]) is own:
        return ""
    return (", from another start; its own fit polished to "
            + (f"{own['rmse_m'] * 1e6:.4g} µm" if "rmse_m" in own else "nothing: it cannot be simulated"))


def more_routes(routes: list[Route], alternatives: Sequence[tuple[str, Any]], restarts: Sequence[tuple[str, Any]],
                make_plant: Callable[[Any], Any], loop: Callable[[Any], Outcome], n: int, rtol: float,
                say: Callable[[str], None], max_ratio: float = 0.0, deadline: float | None = None,
                budget_text: str = "") -> None:
    """Append to ``routes`` (the first one run) the routes of the other nominal fits.

    ``alternatives`` (other methods' fits): a route each, unless its baseline lies in the basin of one already
    run or exceeds ``max_ratio`` (> 1; 0: no limit) times the lowest route's. ``restarts`` (the first route's
    method from other seeds: multistart of the nominal fit): a route only from a baseline lower than every route's
    so far, and only while every route has left structure — a search for a better nominal optimum, which is worth
    a loop only where the record is not explained yet. Each entry is
    a (label, fit) pair, the fit a nominal fit or a callable that makes it (made only when needed);
    ``make_plant(fit)`` gives the plant whose ``baseline()`` polishes it, ``loop(plant)`` runs the loop.
    ``deadline`` (a :func:`time.perf_counter` value; None: none): no route is started after it — each one left is
    listed as skipped with ``budget_text``, its nominal fit never made."""
    for kind, entries in (("alternative", alternatives), ("restart", restarts)):
        for label, fit in entries:
            ran = [r for r in routes if r.outcome is not None]
            if kind == "restart" and not all(r.structure_left for r in ran):
                break
            if deadline is not None and time.perf_counter() > deadline:
                routes.append(Route(label, None, skipped=budget_text))
                say(f"route {label} skipped: {budget_text}")
                continue
            say(f"route {label}: the loop again from the {label} nominal fit"
                + (" (structure is left after the first route)" if routes[0].structure_left else ""))
            nominal = fit() if callable(fit) else fit
            route = Route(label, make_plant(nominal), nominal=nominal)
            base = route.plant.baseline()
            seen = next((r for r in ran if same_basin(base, r.plant.baseline_fit, n, rtol)), None)
            lowest = min(ran, key=lambda r: r.plant.baseline_fit.rmse(n))  # raw: routes may whiten differently
            if seen is not None:
                route.skipped = (f"its baseline ({base.rmse(n) * 1e6:.4g} µm{_from_other_start(base)}) lies in the "
                                 f"basin of route {seen.label} ({seen.plant.baseline_fit.rmse(n) * 1e6:.4g} µm)")
            elif (kind == "alternative" and max_ratio > 0
                  and base.rmse(n) > max_ratio * lowest.plant.baseline_fit.rmse(n)):
                route.skipped = (f"its baseline ({base.rmse(n) * 1e6:.4g} µm) is more than {max_ratio:g} times route "
                                 f"{lowest.label}'s ({lowest.plant.baseline_fit.rmse(n) * 1e6:.4g} µm): a worse "
                                 f"optimum of the nominal model, not a near-equal one")
            elif kind == "restart" and base.rmse(n) >= lowest.plant.baseline_fit.rmse(n):
                route.skipped = (f"its baseline ({base.rmse(n) * 1e6:.4g} µm) is no lower than route "
                                 f"{lowest.label}'s ({lowest.plant.baseline_fit.rmse(n) * 1e6:.4g} µm)")
            if route.skipped:
                say(f"route {label} skipped: {route.skipped}")
            else:
                route.outcome = loop(route.plant)
            routes.append(route)


def choose(routes: Sequence[Route], residual: Callable[[Fit], np.ndarray], n: int, noise_max_order: int,
           alpha: float) -> tuple[int, list[dict]]:
    """The index of the route to report and the comparisons made (see the module docstring). ``residual(fit)``:
    the raw residual of a fit on the record; ``alpha``: the level of Vuong's test (0: the lowest error wins).

    Every pair of routes that ran is compared (Schwarz-corrected for their numbers of parameters, both residuals
    whitened by the noise model of the lowest-error one); a route another beats significantly is out; of the
    rest (fits the record cannot tell apart, so their errors do not count), the one that explains the record
    wins, then the one with fewer parameters, then the earlier route."""
    run = sorted((i for i, r in enumerate(routes) if r.outcome is not None), key=lambda i: routes[i].reached.rmse(n))
    if len(run) == 1 or not alpha > 0:
        return run[0], []
    k = {i: len(routes[i].reached.free) for i in run}
    r = {i: residual(routes[i].reached) for i in run}
    noise = fit_noise(r[run[0]], noise_max_order)
    beaten: set[int] = set()
    compared = []
    for x, i in enumerate(run):
        for j in run[x + 1:]:
            v = vuong(noise, r[i], r[j], k[i], k[j])
            tied = bool(v["p_value"] >= alpha)
            if not tied:
                beaten.add(j if v["z"] > 0 else i)
            compared.append({"a": routes[i].label, "b": routes[j].label, **v, "tied": tied})
    left = [i for i in run if i not in beaten] or run[:1]
    pick = min(left, key=lambda i: (routes[i].structure_left, k[i], i))
    return pick, compared
