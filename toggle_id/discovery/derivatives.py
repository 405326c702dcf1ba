"""Derivatives of a :class:`~.model.Model`'s outputs: the sensitivities in analysis coordinates the score tests
and the range tests use (:func:`sensitivities`), by central differences or — ``discover.derivatives: analytic`` —
forward sensitivities of the PRECISE tier's DOPRI5 steps (:func:`toggle_id.simulate.simulate_sensitivities`)
through the generic sensor error's output map (:func:`output_derivatives`), which the polishes' Jacobians use too.

One simulation with its variational equations gives every column at once, where forward differences take one
simulation per column and central differences two. What the kernel cannot differentiate — the dead time, the
backlash's two-body integrator, the generic force's knot positions — is left to the caller's finite
differences: :func:`output_derivatives` returns NaN columns, or None for the whole
vector.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from ..effects import ALL_INDEX, TERMS, sensor_error
from ..identify import stage_bounds
from ..kernels import slots as K
from ..simulate import ANALYTIC_SLOTS, STATUS_OK, simulate_sensitivities

if TYPE_CHECKING:  # annotations only: model imports this module
    from .model import Model

#: values of ``discover.derivatives``
DERIVATIVES = ("fd", "analytic")


def output_derivatives(model: Model, theta: np.ndarray, idx: np.ndarray) -> np.ndarray | None:
    """(N, len(idx)) ∂x/∂θ of ``model.outputs`` at the extended vector ``theta`` for the slots ``idx``; NaN
    columns for slots it does not differentiate; None when it cannot (backlash on, a failed simulation). The
    integrator is the model's for ``theta`` (the stiff fallback for a stiff effect set); a vector that exhausts
    DOPRI5's budget goes to the fallback and marks its effect set stiff, as a batch would."""
    settings = model._settings_for(theta)
    if theta[K.B_L] > 0.0:
        return None
    idx = np.asarray(idx, dtype=np.int64)
    plant = np.array([s for s in dict.fromkeys(idx.tolist()) if s in ANALYTIC_SLOTS], dtype=np.int64)
    gs_w = (idx >= K.GS_W0) & (idx < K.GS_W0 + K.N_GS)
    model.n_sims += 1
    model.n_derivative_runs += 1
    # the columns in two groups on the two threads: 5–15 % faster than one (python -m jobs.bench_jacobian)
    res = simulate_sensitivities(theta, model.record, settings, plant, threads=2 if model.parallel else 1)
    if res.fell_back:  # as a batch whose rows fell back (Model.outputs): this effect set is stiff
        model.mark_stiff(theta)
    if res.status != STATUS_OK or res.sens_status != STATUS_OK:
        return None
    x = res.x_B
    W = theta[K.GS_W0:K.GS_W0 + K.N_GS]
    D = np.full((x.size, idx.size), np.nan)
    col = {s: j for j, s in enumerate(plant.tolist())}
    if np.any(W != 0.0):  # the output map x ↦ x + h(x): plant columns scale by 1 + h'(x)
        knots = np.linspace(theta[K.GS_LO], theta[K.GS_HI], K.N_GS)
        slope = np.diff(W) / np.diff(knots)
        seg = np.clip(np.searchsorted(knots, x, side="right") - 1, 0, K.N_GS - 2)
        inside = (x > knots[0]) & (x < knots[-1])
        gain = 1.0 + np.where(inside, slope[seg], 0.0)
    else:
        gain = np.ones_like(x)
    for j, s in enumerate(idx.tolist()):
        if s in col:
            D[:, j] = res.dx[col[s]] * gain
        elif gs_w[j] and theta[K.GS_HI] > theta[K.GS_LO]:  # linear in its weights: the weight's hat function at x
            e = np.zeros(K.N_THETA)
            e[K.GS_LO], e[K.GS_HI], e[s] = theta[K.GS_LO], theta[K.GS_HI], 1.0
            D[:, j] = sensor_error(e[None, :], x)[0]
    if model.excluded is not None:  # samples taken as measured: no derivative
        D[model.excluded, :] = 0.0
    return D


def _typical(names: Sequence[str], theta: np.ndarray) -> np.ndarray:
    """A typical magnitude per parameter: |value|, or for an effect parameter at 0 its probe size."""
    out = np.abs(np.array([theta[ALL_INDEX[n]] for n in names], float))
    probe_size: dict[str, float] = {}
    for e in TERMS:
        for pr in e.probe:
            for k, v in pr.items():
                off = next(p.off for p in e.params if p.name == k)
                probe_size[k] = max(probe_size.get(k, 0.0), abs(float(v) - off))
    for j, n in enumerate(names):
        floor = probe_size.get(n, 0.0) or 1e-12
        out[j] = max(out[j], floor)
    return out


def _coords(names: Sequence[str], theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Analysis coordinates of ``names`` at ``theta``: log for positive parameters with lower bound ≥ 0,
    else u = x / scale. Returns (log_mask, scale)."""
    lo, _ = stage_bounds(list(names))
    x = np.array([theta[ALL_INDEX[n]] for n in names], float)
    mask = (lo >= 0.0) & (x > 0.0)
    return mask, _typical(names, theta)


def sensitivities(model: Model, theta: np.ndarray, names: Sequence[str], rel_step: float = 1e-5) -> np.ndarray:
    """Jacobian (N, p) of the model output w.r.t. the analysis coordinates of ``names`` (see :func:`_coords`):
    central differences in one batched simulation, or with ``model.derivatives`` analytic the forward
    sensitivities (:mod:`.derivatives`; differences for the columns they do not give). Columns whose simulation
    failed are zero."""
    if model.derivatives == "analytic":
        idx = np.array([ALL_INDEX[n] for n in names], dtype=np.int64)
        D = output_derivatives(model, theta, idx)
        if D is not None:
            mask, scale = _coords(names, theta)
            D = D * np.where(mask, theta[idx], scale)[None, :]  # ∂/∂log θ = θ ∂/∂θ; ∂/∂u = scale ∂/∂θ
            todo = ~np.all(np.isfinite(D), axis=0)
            if todo.any():
                D[:, todo] = _differenced(model, theta, [n for n, t in zip(names, todo) if t], rel_step)
            return D
    return _differenced(model, theta, names, rel_step)


def _differenced(model: Model, theta: np.ndarray, names: Sequence[str], rel_step: float) -> np.ndarray:
    """:func:`sensitivities` by central differences, all columns in one batched simulation."""
    mask, scale = _coords(names, theta)
    p = len(names)
    T = np.repeat(theta[None, :], 2 * p, axis=0)
    steps = np.empty(p)
    for j, n in enumerate(names):
        i = ALL_INDEX[n]
        if mask[j]:
            T[2 * j, i] = theta[i] * np.exp(rel_step)
            T[2 * j + 1, i] = theta[i] * np.exp(-rel_step)
            steps[j] = rel_step
        else:
            T[2 * j, i] = theta[i] + rel_step * scale[j]
            T[2 * j + 1, i] = theta[i] - rel_step * scale[j]
            steps[j] = rel_step
    Y = model.outputs(T)
    J = ((Y[0::2] - Y[1::2]) / (2.0 * steps[:, None])).T
    J[:, ~np.all(np.isfinite(J), axis=0)] = 0.0
    return J


def broyden(J: np.ndarray, x0: np.ndarray, r0: np.ndarray, x1: np.ndarray, r1: np.ndarray, scale: np.ndarray
            ) -> np.ndarray | None:
    """Broyden's rank-one update of the Jacobian ``J`` = dr/dx at ``x0`` to ``x1`` (residuals ``r0``, ``r1``), in
    the coordinates x/``scale``: the least change of J (Frobenius norm, scaled) that maps the step onto the change of
    the residual, so the columns of parameters of very different sizes are corrected in proportion. None for a zero
    step."""
    dz = (x1 - x0) / scale
    nz = float(dz @ dz)
    if not nz > 0.0:
        return None
    Jz = J * scale[None, :]
    Jz = Jz + np.outer(r1 - r0 - Jz @ dz, dz) / nz
    return Jz / scale[None, :]
