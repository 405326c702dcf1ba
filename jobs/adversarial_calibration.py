"""Calibration of the adversarial set's magnitudes (``python -m jobs.bench_adversarial --calibrate``): the magnitude
of each record's effect at which the nominal model, refitted from the truth to the noiseless record, leaves
sqrt(RMS² + σ²)/σ at the record's target (2 for a library effect, 3 outside the library). The results are pasted
into :data:`jobs.adversarial_set.CALIBRATED`."""
from __future__ import annotations

import math
import time

import numpy as np

from jobs.adversarial_set import base_record, clean_response, draw_truth, effect_values
from jobs.adversarial_specs import DURATION, HELD, Spec

#: First guesses of the calibration (a magnitude of about the right order on the 5-s records).
GUESS = {"tau_c": 1.5, "F_s": 150.0, "c_B": 3000.0, "tau_d": 5e-4, "b_l": 2e-5, "a_cog": 0.1, "F_load": 150.0,
         "k3": 1e12, "x_off": 1.5e-5, "F_b": 20.0, "i_sat": 3000.0, "c_q": 5000.0, "a_s": 2e-6, "pin_mu": 0.005,
         "e_s": 5e-4, "v_db": 2e-3, "d_kt": 5e-3, "c_k": 1e-9, "l_hc": 5e7}



def refit_rms(spec: Spec, theta: np.ndarray, rec, x_clean: np.ndarray, max_nfev: int = 60, rounds: int = 3) -> float:
    """RMS error (m) of the nominal model (effects off) fitted from the truth to the noiseless ``x_clean``."""
    from toggle_id.discovery import Model, fit_free
    from toggle_id.params import PARAM_NAMES
    from toggle_id.simulate import extend

    r = type(rec)(t=rec.t, v_in=rec.v_in, x_B=x_clean, sweep=rec.sweep, x_B0=rec.x_B0, name=rec.name)
    free = [n for n in PARAM_NAMES if n not in HELD]
    fit = fit_free(Model(r), extend(theta)[0], free, max_nfev, rounds=rounds)
    return float(np.sqrt(fit.sse / r.n))


def _first_guess(spec: Spec, param: str, theta: np.ndarray, rec) -> float:
    from toggle_id.params import INDEX

    if param == "s_sat":  # just past the largest drive command K_i·|v_in|
        return min(1.0, 1.05 / (theta[INDEX["K_i"]] * float(np.max(np.abs(rec.v_in)))))
    return GUESS[param]


def _search_coordinate(param: str, floor: float):
    """(to_u, from_u): the coordinate the search works in — log of the magnitude; −log i_sat (a smaller i_sat is
    a stronger effect); log of the excess over the clipping threshold for s_sat."""
    if param == "i_sat":
        return (lambda m: -math.log(m)), (lambda u: math.exp(-u))
    if param == "s_sat":
        return (lambda m: math.log(m - floor)), (lambda u: floor + math.exp(u))
    return math.log, math.exp


def calibrate_param(spec: Spec, param: str, theta: np.ndarray, duration: float = DURATION, tol: float = 0.03,
                    max_evals: int = 9, log=print) -> dict:
    """The magnitude of ``param`` (the other effects of the record off) at which the refitted nominal model leaves
    sqrt(RMS² + σ²)/σ ≈ ``spec.target_of(param)`` (within ``tol``, relative): a search on a log scale — steps by the
    ratio of the RMS errors (about linear in the magnitude for small effects) until the target is bracketed, then
    log-log interpolation kept inside the bracket."""
    from toggle_id.effects import effect_bounds
    from toggle_id.params import INDEX

    rec = base_record(spec.command, duration)
    sigma = spec.sigma_eff
    target = spec.target_of(param)
    target_rms = sigma * math.sqrt(target ** 2 - 1.0)
    upper = np.inf if spec.outside else float(effect_bounds([param])[1][0])
    floor = 1.0 / (theta[INDEX["K_i"]] * float(np.max(np.abs(rec.v_in)))) if param == "s_sat" else 0.0
    to_u, from_u = _search_coordinate(param, floor)

    def rms_of(m: float) -> float:
        effects = {} if spec.outside else {**spec.fixed, param: m}
        x, _ = clean_response(spec, theta, effects, {param: m}, rec)
        return refit_rms(spec, theta, rec, x)

    u = to_u(_first_guess(spec, param, theta, rec))
    lo = hi = None  # (u, rms) on either side of the target
    evals, best = [], None
    for _ in range(max_evals):
        m = min(from_u(u), upper)
        u = to_u(m)
        t0 = time.perf_counter()
        r = rms_of(m)
        ratio = math.sqrt(r * r + sigma ** 2) / sigma
        evals.append({"value": m, "rms_fit_um": r * 1e6, "ratio": ratio})
        log(f"  {spec.key}: {param} = {m:.6g} -> refit RMS {r * 1e6:.4g} um, ratio {ratio:.3f} "
            f"({time.perf_counter() - t0:.0f} s)")
        if best is None or abs(ratio - target) < abs(best[1] - target):
            best = (m, ratio, r)
        if abs(ratio / target - 1.0) <= tol:
            break
        if r < target_rms:
            lo = (u, r) if lo is None or u > lo[0] else lo
            if m >= upper:
                log(f"  {spec.key}: {param} reaches its upper bound {upper:g} below the target")
                break
        else:
            hi = (u, r) if hi is None or u < hi[0] else hi
        if lo is not None and hi is not None:
            f = 0.5
            if lo[1] > 0:
                f = (math.log(target_rms) - math.log(lo[1])) / (math.log(hi[1]) - math.log(lo[1]))
                f = min(max(f, 0.15), 0.85)
            u = lo[0] + f * (hi[0] - lo[0])
        elif r <= 0:
            u += math.log(4.0)
        else:
            u += min(max(math.log(target_rms / r), -math.log(8.0)), math.log(8.0))
    return {"value": best[0], "ratio": best[1], "rms_fit_um": best[2] * 1e6, "evaluations": evals}


def calibrate(specs: list[Spec], duration: float = DURATION, log=print, draw: int = 0) -> dict[str, dict]:
    """Calibrate every magnitude of ``specs`` (on their ``draw``-th machines, :func:`draw_truth`); returns
    {key: {param: {value, ratio, rms_fit_um, evaluations}}}."""
    out: dict[str, dict] = {}
    for spec in specs:
        if not spec.calibrate:
            continue
        theta, _ = draw_truth(spec, draw)
        out[spec.key] = {}
        for param in spec.calibrate:
            out[spec.key][param] = calibrate_param(spec, param, theta, duration, log=log)
        if len(spec.calibrate) > 1:  # the pair's ratio with both effects on, for the record
            rec = base_record(spec.command, duration)
            mags = {p: c["value"] for p, c in out[spec.key].items()}
            x, _ = clean_response(spec, theta, effect_values(spec, mags), mags, rec)
            r = refit_rms(spec, theta, rec, x)
            # as each effect's own calibration
            sigma = spec.sigma_eff
            log(f"  {spec.key}: both effects on -> refit RMS {r * 1e6:.4g} um, ratio "
                f"{math.sqrt(r * r + sigma ** 2) / sigma:.3f} (COMBINED_RATIO)")
    return out


def calibration_table(cal: dict[str, dict]) -> str:
    """``cal`` as the Python source of :data:`CALIBRATED` entries (with the measured ratios)."""
    lines = []
    for key, params in cal.items():
        vals = ", ".join(f'"{p}": ({c["value"]:.6g}, {c["ratio"]:.3f})' for p, c in params.items())
        notes = ", ".join(f'refit RMS {c["rms_fit_um"]:.3g} um' for c in params.values())
        lines.append(f'    "{key}": {{{vals}}},  # {notes}')
    return "\n".join(lines)
