"""Batched simulation over the rows of a parameter array: each row goes to the rigid integrator
(:func:`toggle_id.kernels.rigid._simulate_one`) or, with backlash b_l > 0, to the two-body one
(:func:`toggle_id.kernels.backlash.simulate_lash`). :func:`simulate_batch_serial` (one Ray actor = one core) and
:func:`simulate_batch_parallel` (numba threads) are what :mod:`toggle_id.simulate` calls.
"""
from __future__ import annotations

import numba as nb
import numpy as np

from .backlash import simulate_lash as _simulate_lash
from .rigid import _simulate_one
from .slots import B_L, OK


@nb.njit(cache=True)
def _simulate_row(thetas, r, geo, tab, head, t_out, n_out, v, sweep, use_sweep, t_start, y0, contact0, settings,
                  out_x, out_i, status, n_steps, events):
    """Simulate row r of ``thetas`` into row r of the outputs; samples not simulated (before ``t_start``, from
    ``n_out`` on, or all of them when the simulation failed) are NaN."""
    xr = out_x[r]
    ir = out_i[r]
    if thetas[r, B_L] > 0.0:  # backlash: a second mechanical degree of freedom while the lash is open
        st, ns, tc, qc, wc, ic = _simulate_lash(thetas[r], geo, tab, head, t_out, n_out, v, sweep, use_sweep,
                                                t_start, y0, contact0, settings, xr, ir)
    else:
        st, ns, tc, qc, wc, ic = _simulate_one(thetas[r], geo, tab, head, t_out, n_out, v, sweep, use_sweep,
                                               t_start, y0, contact0, settings, xr, ir)
    n = t_out.shape[0]
    if st != OK:
        for k in range(n):
            xr[k] = np.nan
            ir[k] = np.nan
    else:
        for k in range(n):
            if k >= n_out or t_out[k] < t_start - 1e-12:
                xr[k] = np.nan
                ir[k] = np.nan
    status[r] = st
    n_steps[r] = ns
    events[r, 0], events[r, 1], events[r, 2], events[r, 3] = tc, qc, wc, ic


@nb.njit(cache=True)
def simulate_batch_serial(thetas, rows, geo, tab, head, t_out, n_out, v, sweep, use_sweep, t_start, y0, contact0,
                          settings, out_x, out_i, status, n_steps, events):
    """Serial loop over the rows ``rows`` of ``thetas`` (one Ray actor = one core)."""
    for p in range(rows.shape[0]):
        _simulate_row(thetas, rows[p], geo, tab, head, t_out, n_out, v, sweep, use_sweep, t_start, y0, contact0,
                      settings, out_x, out_i, status, n_steps, events)


@nb.njit(cache=True, parallel=True)
def simulate_batch_parallel(thetas, rows, geo, tab, head, t_out, n_out, v, sweep, use_sweep, t_start, y0,
                            contact0, settings, out_x, out_i, status, n_steps, events):
    """Threaded loop over the rows ``rows`` of ``thetas`` (standalone use: jobs.simulate, benchmarks)."""
    for p in nb.prange(rows.shape[0]):
        _simulate_row(thetas, rows[p], geo, tab, head, t_out, n_out, v, sweep, use_sweep, t_start, y0, contact0,
                      settings, out_x, out_i, status, n_steps, events)
