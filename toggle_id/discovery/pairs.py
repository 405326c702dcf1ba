"""The joint look at pairs (``discover.pair_look``): two effects refitted together, when no single one takes the
record near its noise.

Each step of the loop refits one effect at a time from the current model, whose nominal parameters bend to imitate
what is missing. Where two effects are missing, each one's refit may explain little while the other's error is
still there for the nominal parameters to absorb, and only the two together explain the record. Measured on the
held-out record rec44_d1 (a Stribeck friction and a 0.38-ms dead time on the paper's sweep, 1.448 µm nominal, σ =
1 µm): the Stribeck friction refitted alone from the baseline ends at 1.329 µm (the slider's friction coefficient
μ run down to 0.024), the dead time alone at 1.348 µm (μ up to 6.5); the two together from the baseline with their
single refits' values reach 1.0164 µm (F_s 307.8 N, v_s 0.0294 m/s, τ_d 0.386 ms; truth 307 N, 0.03 m/s, 0.380
ms in the fit's gauge) — from the baseline, from the friction's refit and from the dead time's alike. At the
defaults the loop named neither (docs/discovery.md, *Open problems*).

A pair is refitted by least squares from the current model with both effects at their single refits' values, then,
where the loop's fits are prediction-error ones, polished under the noise model of its own residual (as the
search from the other starts does, :func:`.refit.from_other_starts`: the loop's noise model was fitted to a
residual the missing effects dominate). It is judged against the current model by the judge's rules with both
effects' parameters as the added ones; it replaces the step's best single refit only when it is supported and
lower, and, where that single effect is one of the pair, significant beside it as well; and, above the noise band,
only where it leaves no structure by the noise-aware structure test (:func:`.residual.structure_left_at`): the look
is for two effects that explain the record together. Measured on the set's rec47 (no effect; a random walk on the
sensor, which the AR noise models leave with 160–350 independent samples of 5001) with ``pair_look=4``: no single
effect was supported, while a cogging torque with a sensor offset, refitted together, was (F 11.2, p 4.8e-9, out of
sample z 2.88) at 1.528 µm — above the band — and was added.
"""
from __future__ import annotations

import itertools
import time
from collections.abc import Callable, Collection, Sequence

import numpy as np

from ..effects import ALL_INDEX, EFFECTS_BY_NAME
from .gauge import freed_with
from .model import Fit, Model, _std_errors, _with, fit_free, minimising_under
from .noise import WHITE
from .refit import Refit, under_own_noise
from .residual import structure_left_at
from .settings import DiscoverSettings
from .validation import Judge


def pair_candidates(refits: Sequence[Refit], n: int, m: int) -> list[Refit]:
    """The ``m`` single refits of lowest raw error (one per effect; a refit that could not be simulated left out)."""
    seen: dict[str, Refit] = {}
    for rf in sorted((rf for rf in refits if rf.fit is not None and np.isfinite(rf.sse1)), key=lambda rf: rf.fit.rmse(n)):
        seen.setdefault(rf.name, rf)
    return list(seen.values())[:m]


def pair_fit(model: Model, base: Fit, a: Refit, b: Refit, settings: DiscoverSettings, held: Collection[str]) -> Fit:
    """Effects ``a`` and ``b`` refitted together from ``base`` at their single refits' values (see the module)."""
    free = tuple(dict.fromkeys(freed_with(freed_with(base.free, EFFECTS_BY_NAME[a.name], held),
                                          EFFECTS_BY_NAME[b.name], held)))
    values = {nm: float(rf.fit.theta[ALL_INDEX[nm]]) for rf in (a, b) for nm in EFFECTS_BY_NAME[rf.name].names}
    with minimising_under(model, WHITE):
        fit = fit_free(model, _with(base.theta, values), free, settings.baseline_nfev, settings.fd_rel_step,
                       rounds=settings.rounds)
    return under_own_noise(model, fit, settings)[0] if not model.noise.white else fit


def pair_look(model: Model, judge: Judge, base: Fit, refits: Sequence[Refit], best: Refit | None,
              settings: DiscoverSettings, iteration: int, held: Collection[str],
              say: Callable[[str], None], near_m: float = 0.0) -> tuple[Refit | None, list[dict]]:
    """The pairs of the ``settings.pair_look`` single refits of lowest error, in order, refitted together
    (:func:`pair_fit`) and judged against ``base`` until a supported one ends within ``near_m`` (m RMS); the
    supported pair of lowest raw error that is lower than ``best`` (the step's chosen single refit, None: none) and,
    where ``best`` is one of its effects, significant beside it — as a :class:`~.refit.Refit` named after its member
    of lower single error, the other in ``partner`` — or None; and every pair's report."""
    n = model.n
    found: list[Refit] = []
    report: list[dict] = []
    for a, b in itertools.combinations(pair_candidates(refits, n, settings.pair_look), 2):
        t0 = time.perf_counter()
        fit = pair_fit(model, base, a, b, settings, held)
        names = EFFECTS_BY_NAME[a.name].names + EFFECTS_BY_NAME[b.name].names
        params = {nm: float(fit.theta[ALL_INDEX[nm]]) for nm in names}
        k = len(fit.free) - len(base.free)
        rf = Refit(a.name, iteration, fit, params, base.sse, fit.sse, k, len(fit.free), 0.0, 1.0, float("inf"),
                   False, "", {"pair_of": [a.name, b.name]}, std_errors=_std_errors(fit, names, n), partner=b.name)
        rf.judge(judge.judge_pair(base, fit), base.sse)
        if rf.accepted and best is not None and best.name in (a.name, b.name):
            beside = judge.judge_pair(best.fit, fit)  # the pair against its own member's single refit (nested)
            rf.evidence["beside_" + best.name] = beside.to_dict()
            if not beside.passed:
                rf.accepted, rf.reason = False, f"not significant beside {best.name} alone: {beside.reason}"
        if rf.accepted and fit.rmse(n) > near_m:  # a pair is looked at to explain the record, not to compensate
            left, text = structure_left_at(model, fit.theta, settings)
            rf.evidence["structure_after"] = text
            if left:
                rf.accepted, rf.reason = False, ("supported, but above the noise band with " + text
                                                 + ": together they compensate, they do not explain the record")
        rf.seconds = time.perf_counter() - t0
        say(f"  pair {a.name} + {b.name} refitted together: rms {fit.rmse(n) * 1e6:.4g} µm, F {rf.F:.3g}, "
            f"p {rf.p_value:.3g}, out of sample z {rf.evidence.get('cv_z', np.nan):.3g} → "
            f"{'supported' if rf.accepted else 'rejected: ' + rf.reason} ({rf.seconds:.1f} s)")
        report.append(rf.to_dict(n))
        if rf.accepted:
            found.append(rf)
            if fit.rmse(n) <= near_m and (best is None or fit.rmse(n) < best.fit.rmse(n)):
                break  # near the noise: no other pair can explain much more
    lower = [rf for rf in found if best is None or rf.fit.rmse(n) < best.fit.rmse(n)]
    return min(lower, key=lambda rf: rf.fit.rmse(n), default=None), report
