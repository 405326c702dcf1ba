"""What the two integrators (:mod:`.rigid`, :mod:`.backlash`) share: the continuous extension's polynomial,
DOPRI5's PI step-size controller, one bracket update of the Illinois root finder (event location), where a step
must stop (the samples) and the first output sample of a simulation.
"""
from __future__ import annotations

import math

import numba as nb

from .geometry import _geometry, _x_of_q
from .slots import PC_IDT, PC_T0, PC_TAUD, STOPS_ALL, STOPS_SAMPLED


@nb.njit(cache=True, inline="always")
def _dense(th_, r1, r2, r3, r4, r5):
    """Continuous extension at fraction θ of the step: r1 + θ(r2 + (1−θ)(r3 + θ(r4 + (1−θ) r5))) (DOPRI5's;
    Rodas4's is the same form with r5 = 0)."""
    s = 1.0 - th_
    return r1 + th_ * (r2 + s * (r3 + th_ * (r4 + s * r5)))


@nb.njit(cache=True, inline="always")
def _pi_control(err, h, facold):
    """DOPRI5's PI step-size controller (beta 0.04, safety 0.9, factors in [0.2, 10]) for the scaled error
    ``err`` of a step of size h: (accepted, the next step size — the retry's after a rejection —, facold)."""
    fac11 = err ** 0.17
    if err > 1.0:
        return False, h / min(fac11 / 0.9, 5.0), facold
    fac = max(0.1, min(5.0, fac11 / facold ** 0.04 / 0.9))
    return True, h / fac, max(err, 1e-4)


@nb.njit(cache=True, inline="always")
def _illinois(a, b, ga, gb, side, th_, gm):
    """One bracket update of the Illinois (modified regula falsi) method: the new point th_ with value gm
    replaces the end of [a, b] with the same sign; an end kept twice in a row has its value halved."""
    if (gm < 0.0) == (ga < 0.0):
        if side == -1:
            gb *= 0.5
        return th_, b, gm, gb, -1
    if side == 1:
        ga *= 0.5
    return a, th_, ga, gm, 1


@nb.njit(cache=True, inline="always")
def _stops_on(mode, use_sweep):
    """Whether steps stop at the samples under the settings' S_STOPS ``mode`` for this kind of input."""
    return mode == STOPS_ALL or (mode == STOPS_SAMPLED and not use_sweep)


@nb.njit(cache=True, inline="always")
def _next_stop(t, pc, use_sweep):
    """Where a step that starts at t must end at the latest when steps stop at the samples: the next output
    sample and, for a sampled input (linear between its samples, so kinked at each; shifted by the dead time),
    the next input sample. A point within 1e-7 of a sample interval before one counts as on it."""
    idt = pc[PC_IDT]
    t_next = pc[PC_T0] + (math.floor((t - pc[PC_T0]) * idt + 1e-7) + 1.0) / idt
    if not use_sweep and pc[PC_TAUD] != 0.0:
        t0 = pc[PC_T0] + pc[PC_TAUD]
        t_next = min(t_next, t0 + (math.floor((t - t0) * idt + 1e-7) + 1.0) / idt)
    return t_next


@nb.njit(cache=True)
def _first_sample(q, iq, t_start, t_out, n_out, geo, xoff, out_x, out_i):
    """(ok, k): k the first output sample after ``t_start``; the sample at ``t_start`` itself, if there is one,
    is written from the start state (ok False: that state lies outside the assembly range)."""
    k = 0
    while k < n_out and t_out[k] < t_start - 1e-12:
        k += 1
    if k < n_out and abs(t_out[k] - t_start) <= 1e-12:
        if not _geometry(q, geo)[0]:
            return False, k
        out_x[k] = _x_of_q(q, geo) + xoff
        out_i[k] = iq
        k += 1
    return True, k
