"""Batched simulation over the rows of a parameter array: rows without backlash go to the rigid integrator
(:func:`toggle_id.kernels.rigid._simulate_one`), rows with backlash b_l > 0 to the two-body one
(:func:`toggle_id.kernels.backlash.simulate_lash`). What :mod:`toggle_id.simulate` calls: :func:`simulate_batch_serial`
(one Ray actor = one core) and :func:`simulate_batch_parallel` (numba threads), for rows with backlash
:func:`lash_batch_serial` and :func:`lash_batch_parallel`, and for one vector with its forward sensitivities
:func:`sensitivities_row`. Each is compiled on its first use only: a process that never
simulates backlash (most jobs) compiles the rigid integrator alone, about half of a cold start (measured: 18-21 s
against 42-46 s for both).
"""
from __future__ import annotations

import numba as nb
import numpy as np

from .backlash import simulate_lash as _simulate_lash
from .rigid import _simulate_one
from .sens import sens_replay
from .slots import OK, S_MAXSTEPS


@nb.njit(cache=True)
def _store_row(r, st, ns, tc, qc, wc, ic, t_out, n_out, t_start, xr, ir, status, n_steps, events):
    """Row r's status, step count and contact event; NaN where no sample was simulated (before ``t_start``, from
    ``n_out`` on, or all of them when the simulation failed)."""
    n = t_out.shape[0]
    for k in range(n):
        if st != OK or k >= n_out or t_out[k] < t_start - 1e-12:
            xr[k] = np.nan
            ir[k] = np.nan
    status[r] = st
    n_steps[r] = ns
    events[r, 0], events[r, 1], events[r, 2], events[r, 3] = tc, qc, wc, ic


@nb.njit(cache=True)
def _rigid_row(thetas, rows, geo, tab, head, t_out, n_out, v, sweep, use_sweep, t_start, y0, contact0, settings,
                out_x, out_i, status, n_steps, events, p):
    """Row ``rows[p]`` of ``thetas`` by the rigid integrator, into its row of the outputs."""
    r = rows[p]
    st, ns, tc, qc, wc, ic = _simulate_one(thetas[r], geo, tab, head, t_out, n_out, v, sweep, use_sweep, t_start,
                                           y0, contact0, settings, out_x[r], out_i[r], np.empty((0, 2)))
    _store_row(r, st, ns, tc, qc, wc, ic, t_out, n_out, t_start, out_x[r], out_i[r], status, n_steps, events)


@nb.njit(cache=True)
def _lash_row(thetas, rows, geo, tab, head, t_out, n_out, v, sweep, use_sweep, t_start, y0, contact0, settings,
               out_x, out_i, status, n_steps, events, p):
    """Row ``rows[p]`` of ``thetas`` by the two-body integrator (backlash: a second mechanical degree of freedom
    while the lash is open), into its row of the outputs."""
    r = rows[p]
    st, ns, tc, qc, wc, ic = _simulate_lash(thetas[r], geo, tab, head, t_out, n_out, v, sweep, use_sweep, t_start,
                                            y0, contact0, settings, out_x[r], out_i[r])
    _store_row(r, st, ns, tc, qc, wc, ic, t_out, n_out, t_start, out_x[r], out_i[r], status, n_steps, events)


@nb.njit(cache=True)
def simulate_batch_serial(thetas, rows, geo, tab, head, t_out, n_out, v, sweep, use_sweep, t_start, y0, contact0,
                          settings, out_x, out_i, status, n_steps, events):
    """Serial loop over the rows ``rows`` of ``thetas`` (one Ray actor = one core), rigid integrator."""
    for p in range(rows.shape[0]):
        _rigid_row(thetas, rows, geo, tab, head, t_out, n_out, v, sweep, use_sweep, t_start, y0, contact0, settings,
                    out_x, out_i, status, n_steps, events, p)


@nb.njit(cache=True, parallel=True)
def simulate_batch_parallel(thetas, rows, geo, tab, head, t_out, n_out, v, sweep, use_sweep, t_start, y0,
                            contact0, settings, out_x, out_i, status, n_steps, events):
    """Threaded loop over the rows ``rows`` of ``thetas`` (standalone use: jobs.simulate, benchmarks), rigid."""
    for p in nb.prange(rows.shape[0]):
        _rigid_row(thetas, rows, geo, tab, head, t_out, n_out, v, sweep, use_sweep, t_start, y0, contact0, settings,
                    out_x, out_i, status, n_steps, events, p)


@nb.njit(cache=True)
def lash_batch_serial(thetas, rows, geo, tab, head, t_out, n_out, v, sweep, use_sweep, t_start, y0, contact0,
                      settings, out_x, out_i, status, n_steps, events):
    """:func:`simulate_batch_serial` by the two-body integrator (rows with backlash)."""
    for p in range(rows.shape[0]):
        _lash_row(thetas, rows, geo, tab, head, t_out, n_out, v, sweep, use_sweep, t_start, y0, contact0, settings,
                   out_x, out_i, status, n_steps, events, p)


@nb.njit(cache=True, parallel=True)
def lash_batch_parallel(thetas, rows, geo, tab, head, t_out, n_out, v, sweep, use_sweep, t_start, y0, contact0,
                        settings, out_x, out_i, status, n_steps, events):
    """:func:`simulate_batch_parallel` by the two-body integrator (rows with backlash)."""
    for p in nb.prange(rows.shape[0]):
        _lash_row(thetas, rows, geo, tab, head, t_out, n_out, v, sweep, use_sweep, t_start, y0, contact0, settings,
                   out_x, out_i, status, n_steps, events, p)


@nb.njit(cache=True, parallel=True)
def sensitivities_row(th, geo, tab, head, t_out, n_out, v, sweep, use_sweep, t_start, y0, contact0, settings,
                      out_x, out_i, cols, out_dx, n_chunks):
    """One parameter vector by the rigid integrator (DOPRI5 settings) into ``out_x``, ``out_i``, and ∂x_B/∂θ of
    the slots ``cols`` into ``out_dx`` (len(cols), N) by retracing its steps (:func:`~.sens.sens_replay`), the
    columns in ``n_chunks`` groups over numba's threads. Returns the simulation's status and step count and the
    replay's worst status (OK when every group succeeded)."""
    steplog = np.empty((int(settings[S_MAXSTEPS]) + 1, 2))
    st, ns, _, _, _, _ = _simulate_one(th, geo, tab, head, t_out, n_out, v, sweep, use_sweep, t_start, y0,
                                       contact0, settings, out_x, out_i, steplog)
    if st != OK:
        return st, ns, st
    P = cols.shape[0]
    chunk_status = np.zeros(n_chunks, dtype=np.int64)
    for c in nb.prange(n_chunks):
        lo = c * P // n_chunks
        hi = (c + 1) * P // n_chunks
        if hi > lo:
            chunk_status[c] = sens_replay(th, geo, tab, head, t_out, n_out, v, sweep, use_sweep, t_start, y0,
                                          contact0, steplog, cols[lo:hi], out_dx[lo:hi])
    return st, ns, int(chunk_status.max())
