"""Finite-difference sensitivities of a fit problem's residual, batched in one simulation each, and the
identifiability report built on them (:mod:`toggle_id.identifiability` does the linear algebra).

:func:`batched_jacobian` is the Jacobian every least-squares polish uses (GA stages, joint polish, the fast
method); :func:`log_jacobian_model` the higher-order one of the identifiability reports.
"""
from __future__ import annotations

import numpy as np

from .identifiability import analyze
from .problem import FitProblem, JointProblem
from .simulate import PRECISE, SolverSettings


def batched_jacobian(problem: FitProblem | JointProblem, x: np.ndarray, rel_step: float, settings: SolverSettings
                     ) -> np.ndarray:
    """Forward-difference Jacobian of the residual in physical units, all columns in one batched simulation."""
    n = x.size
    h = rel_step * np.maximum(np.abs(x), 1e-12)
    X = np.repeat(x[None, :], n + 1, axis=0)
    X[1:] += np.diag(h)
    R = problem.residuals(X, settings, parallel=True)
    return (R[1:] - R[0]).T / h


def log_jacobian_model(problem: FitProblem | JointProblem, x: np.ndarray, rel_step: float = 1e-4,
                       settings: SolverSettings = PRECISE, return_error: bool = False):
    """Jacobian of the model output w.r.t. log-parameters (affine steps for x ≤ 0), batched in one simulation.

    Fourth-order central differences (steps ±h, ±2h). With ``return_error`` the same stencil at 2h (one more
    pair of points per parameter, ±4h) gives a second estimate; the spectral norm of their difference
    measures the Jacobian's numerical error (integrator jitter and truncation), below which singular values
    carry no information — exact symmetries of the model (e.g. K_i·c, λ_d·c, K_t/c) fall there. It returns
    the difference matrix E; ‖E v‖ bounds the error of the output's sensitivity along a direction v.
    """
    n = x.size
    pos = x > 0
    steps = np.where(pos, rel_step, rel_step * np.maximum(np.abs(x), 1e-12))
    mults = (2.0, 1.0, -1.0, -2.0, 4.0, -4.0) if return_error else (2.0, 1.0, -1.0, -2.0)
    k = len(mults)
    X = np.repeat(x[None, :], k * n, axis=0)
    for j in range(n):
        for i, m in enumerate(mults):
            X[k * j + i, j] = x[j] * np.exp(m * rel_step) if pos[j] else x[j] + m * steps[j]
    R = problem.residuals(X, settings, parallel=True)  # residual = measured − model: model's derivative is −dR
    d4 = (-R[0::k] + 8.0 * R[1::k] - 8.0 * R[2::k] + R[3::k]).T / (12.0 * steps)
    if not return_error:
        return -d4
    d4_2h = (-R[4::k] + 8.0 * R[0::k] - 8.0 * R[3::k] + R[5::k]).T / (24.0 * steps)
    bad = ~np.isfinite(d4_2h)
    return -d4, np.where(bad, 0.0, d4 - d4_2h)


def identifiability_report(problem: FitProblem | JointProblem, x: np.ndarray, noise_var: float | None = None,
                           robust: bool = True) -> dict:
    """Sensitivity/uncertainty report of ``problem`` at ``x`` (see :mod:`toggle_id.identifiability`).

    The residual's correlation is estimated (an AR(p) noise model, :func:`toggle_id.discovery.noise.fit_noise`)
    and the sensitivities and residual are prewhitened by it before the analysis, so that the standard errors
    and intervals count the independent samples the record really has; the report names the noise model. A
    known ``noise_var`` (the marginal variance σ²) is turned into the innovation variance of that model. With
    ``robust`` (at a fitted ``x``) each variance is the larger of the classical one and the HC3 sandwich's (a
    noise level that varies); a design-time report at the truth, whose residual is not a fit's, passes False."""
    from .discovery.noise import fit_noise

    J, E = log_jacobian_model(problem, x, return_error=True)
    r = problem.residuals(x[None, :], PRECISE)[0]
    if not np.all(np.isfinite(J)) or not np.all(np.isfinite(r)):
        return {"error": "simulation failed near the optimum; no sensitivity report"}
    noise = fit_noise(r)
    J, r, noise_var = noise.prewhiten(J, r, noise_var)
    E = noise.whiten_columns(E)
    rtol = numerical_rank_rtol(J, E)
    rep = analyze(J, r, list(problem.free), x, log_mask=x > 0, noise_var=noise_var, rank_rtol=rtol,
                  robust=robust)
    out = rep.to_dict()
    out["noise_model"] = noise.to_dict()
    out["jacobian_error_norm"] = float(np.linalg.norm(E, 2))
    return out


def numerical_rank_rtol(J: np.ndarray, E: np.ndarray, safety: float = 3.0) -> float:
    """Relative singular-value tolerance that keeps the directions the Jacobian resolves.

    Singular direction v_j is resolved while s_j > safety·‖E v_j‖ (E: the Jacobian's error estimate along
    that direction); the tolerance is put halfway (geometrically) between the last resolved singular value
    and the next one.
    """
    _, s, vt = np.linalg.svd(J, full_matrices=False)
    if s.size == 0 or s[0] <= 0:
        return 1e-9
    ok = s > safety * np.linalg.norm(E @ vt.T, axis=0)
    rank = int(np.argmin(ok)) if not ok.all() else s.size
    if rank == s.size:
        return max(1e-12, 0.5 * s[-1] / s[0])
    if rank == 0:
        return 0.5
    return float(np.sqrt(s[rank - 1] * max(s[rank], 1e-300)) / s[0])
