"""Local identifiability of fitted parameters: SVD of the sensitivity matrix, null directions, confidence intervals.

Model-agnostic: the input is a Jacobian of the model output (or of the residual — same thing up to sign) with
respect to *analysis coordinates* ``u`` at the fitted point, the residual there, and the parameter names.

Coordinates. A positive parameter is analysed in log space, ``u = log(theta)``: a unit step is a factor e,
so columns of parameters with wildly different units are comparable and every confidence interval stays
positive. A parameter flagged False in ``log_mask`` (one that may be ≤ 0, an offset say) uses ``u = theta/s``
with ``s = |theta|`` (or 1 when theta = 0, or a caller-given scale): near theta a unit step in u is a change by
the parameter's own magnitude, as for log coordinates. :func:`log_jacobian` and :func:`fd_jacobian` produce
Jacobians in these coordinates.

Criteria (let J = U S Vᵀ, singular values s_1 ≥ … ≥ s_n, right singular vectors v_j):

- *numerical rank*: directions with ``s_j > rank_rtol · s_1`` (default ``rank_rtol`` = 1e-6, see
  :data:`RANK_RTOL`). Smaller singular values are indistinguishable from the error of a finite-difference
  Jacobian of an ODE solution (solver tolerance / step ≈ 1e-6 relative at best), i.e. exact or numerically
  exact symmetries of the model.
- *practical rank*: of those, the directions along which the data pin the parameters to better than a
  factor e: the (1 − alpha) confidence half-width along v_j, ``q · sigma / s_j``, at most
  ``ci_halfwidth_limit`` (default 1 log unit). Here sigma is the noise standard deviation and q the
  (1 − alpha/2) quantile (Student t with m − p_eff degrees of freedom when sigma is estimated from the
  residual, normal when ``noise_var`` is given). The other directions are *null directions* (kind
  "numerical" or "practical").
- *noise*: ``sigma² = SSE / (m − p_eff)``, ``p_eff = n_params_fitted`` or else the numerical rank.
- *covariance* (Gauss–Newton, log/scaled space): ``C = sigma² · V_r S_r⁻² V_rᵀ`` over the numerically
  identifiable directions. Practically-null directions stay in: their large variance is the honest
  uncertainty of the parameters they involve. Numerically-null directions (infinite variance) are left out
  and handled by the leakage rule below.
- *per parameter*: leakage ``ℓ_i = ‖P_null e_i‖`` = norm of parameter i's components along the numerical
  null directions. Parameter i is identifiable iff ``ℓ_i ≤ null_threshold`` (default 0.1: smaller components
  are taken for round-off in the estimated null vector) and its CI half-width in u, ``q · sqrt(C_ii)``, is at
  most ``ci_halfwidth_limit`` (a parameter with a component c along a practical null direction j gets at least
  ``|c| · q · sigma / s_j``, so it is flagged exactly when that component matters). Non-identifiable
  parameters get ``std_errors``/``ci95`` None.
- *noise whose level varies* (``robust=True``): the covariance above takes the noise's variance as one number.
  When it varies along the record (an encoder noisier at speed) and a parameter's sensitivity concentrates where
  it is loud, that variance is far too small. With ``robust`` the HC3 sandwich (MacKinnon & White 1985),
  ``C_HC = V_r S_r⁻¹ (U_rᵀ diag(e_i²/(1−h_i)²) U_r) S_r⁻¹ V_rᵀ`` (h_i the leverages), is computed beside it, and
  every variance (per parameter and along each singular direction) is the larger of the two — never narrower
  than the classical interval, so under one variance it changes nothing but the sandwich's own scatter (a few
  per cent). ``hc_ratio`` reports C_HC,ii / C_ii per parameter.
- *intervals*: computed in u and mapped back: ``theta · exp(±q · std_u)`` for log parameters (positive,
  asymmetric), ``theta ± q · s · std_u`` otherwise. Standard errors in physical units by the delta method,
  ``std_theta ≈ theta · std_u`` (log) or ``s · std_u``.

Null combinations. A null direction v (unit vector in u) means the output does not change when
``log theta_i`` moves by ``t · v_i`` for all i together. The string reported for it, e.g.
``"a^1 · b^-1"``, is the *unidentifiable* combination ``prod theta_i^(v_i / max|v|)`` — the one that moves
freely; products orthogonal to it (here ``a · b``) are what the data determine. Components below
``null_threshold`` (of the unit vector) are omitted. With several null directions the SVD basis of the null
space is arbitrary (any rotation of it is as valid), so read them together.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
from scipy import stats

from .errors import ConfigError, DataError

#: Default relative singular-value tolerance of the numerical rank (see the module docstring).
RANK_RTOL = 1e-6
#: Default half-width (log units; 1 = a factor e) above which a direction/parameter is practically unidentifiable.
CI_HALFWIDTH_LIMIT = 1.0
#: Default component size (of a unit vector) that counts as "substantial" along a null direction.
NULL_THRESHOLD = 0.1


# ---------------------------------------------------------------------------------------------- Jacobians
def _coordinates(x: np.ndarray, log_mask: Sequence[bool] | bool | None,
                 scale: Sequence[float] | None) -> tuple[np.ndarray, np.ndarray]:
    """(log_mask, scale) as arrays; validates that log parameters are positive."""
    n = x.shape[0]
    if log_mask is None or isinstance(log_mask, (bool, np.bool_)):
        mask = np.full(n, True if log_mask is None else bool(log_mask))
    else:
        mask = np.asarray(log_mask, dtype=bool)
        if mask.shape != (n,):
            raise ConfigError(f"log_mask must have shape ({n},), got {mask.shape}")
    if np.any(mask & ~(x > 0.0)):
        bad = np.flatnonzero(mask & ~(x > 0)).tolist()
        raise ConfigError(f"log coordinates need theta > 0, violated at indices {bad}")
    if scale is None:
        s = np.where(np.abs(x) > 0.0, np.abs(x), 1.0)
    else:
        s = np.asarray(scale, dtype=float)
        if s.shape != (n,) or not np.all(np.isfinite(s) & (s > 0.0)):
            raise ConfigError(f"scale must be ({n},) positive finite values")
    return mask, s


def log_jacobian(jac_phys: np.ndarray, x: Sequence[float], log_mask: Sequence[bool] | bool | None = None,
                 scale: Sequence[float] | None = None) -> np.ndarray:
    """Jacobian in analysis coordinates from a physical one: ``dy/dlog(theta) = dy/dtheta · theta`` per column
    (``dy/d(theta/s) = dy/dtheta · s`` where ``log_mask`` is False). ``jac_phys`` (m, n), ``x`` (n,)."""
    x = np.asarray(x, dtype=float)
    jac_phys = np.asarray(jac_phys, dtype=float)
    if jac_phys.ndim != 2 or jac_phys.shape[1] != x.shape[0]:
        raise ConfigError(f"jac_phys must have shape (m, {x.shape[0]}), got {jac_phys.shape}")
    mask, s = _coordinates(x, log_mask, scale)
    return jac_phys * np.where(mask, x, s)[None, :]


def fd_jacobian(fun: Callable[[np.ndarray], np.ndarray], x: Sequence[float], rel_step: float = 1e-6,
                log: Sequence[bool] | bool = True, *, scale: Sequence[float] | None = None,
                vectorized: bool = False) -> np.ndarray:
    """Central-difference Jacobian of ``fun`` in analysis coordinates, (m, n).

    fun: theta (n,) → output (m,); with ``vectorized`` it takes (k, n) and returns (k, m) (one batched call
    for all 2n points — e.g. a simulator that integrates a population at once).
    rel_step: step h in u (log units for log parameters: theta · e^{±h}; else theta ± h·s).
    For outputs computed by an ODE solver with relative tolerance tol, the differencing error is ≈ tol/h:
    choose h ≈ 1e-4 … 1e-3 there rather than the default.
    Columns where a perturbed output is not finite come back NaN (``analyze`` rejects them, naming the
    parameter).
    """
    x = np.asarray(x, dtype=float)
    if x.ndim != 1:
        raise ConfigError(f"x must be 1-D, got shape {x.shape}")
    if not rel_step > 0.0:
        raise ConfigError(f"rel_step must be > 0, got {rel_step}")
    mask, s = _coordinates(x, log, scale)
    n = x.shape[0]
    points = np.repeat(x[None, :], 2 * n, axis=0)
    for k in range(n):
        for row, sign in ((2 * k, 1.0), (2 * k + 1, -1.0)):
            points[row, k] = x[k] * math.exp(sign * rel_step) if mask[k] else x[k] + sign * rel_step * s[k]
    if vectorized:
        out = np.asarray(fun(points), dtype=float)
        if out.ndim != 2 or out.shape[0] != 2 * n:
            raise ConfigError(f"vectorized fun must return (k, m) for k = {2 * n} points, got {out.shape}")
    else:
        out = np.stack([np.asarray(fun(p), dtype=float).ravel() for p in points])
    return ((out[0::2] - out[1::2]) / (2.0 * rel_step)).T


# ---------------------------------------------------------------------------------------------- report
@dataclass
class IdentifiabilityReport:
    """Result of :func:`analyze` (all arrays in ``param_order``; u = analysis coordinates).

    x: fitted values (physical). singular_values (n,), descending, zero-padded when m < n. vt: right singular
    vectors as rows (n, n). rank / practical_rank: see the module docstring. null_directions (k, n): unit
    vectors in u, most null first, sign fixed so the first component ≥ null_threshold is positive;
    null_kinds: "numerical" or "practical"; null_halfwidths: (1 − alpha) CI half-width along each (inf for
    numerical nulls or unknown noise); null_combinations: readable unidentifiable products.
    noise_std: sigma (None if m ≤ p_eff and no noise_var); dof; quantile q. cov_u (n, n): covariance in u
    (None without sigma). std_u (n,): sqrt(C_ii) (NaN where unknown). leakage (n,): norm along the numerical
    null space. std_errors / ci95: physical, None when not identifiable. identifiable: per parameter.
    robust: whether the HC3 sandwich was taken (``analyze(robust=True)`` with a noise level); then std_u holds
    the larger of the two variances and hc_ratio (n,) C_HC,ii / C_ii.
    """

    param_order: list[str]
    x: np.ndarray
    log_mask: np.ndarray
    scale: np.ndarray
    m: int
    sse: float
    singular_values: np.ndarray
    vt: np.ndarray
    rank: int
    practical_rank: int
    rank_rtol: float
    null_directions: np.ndarray
    null_kinds: list[str]
    null_halfwidths: np.ndarray
    null_combinations: list[str]
    noise_std: float | None
    dof: int
    alpha: float
    quantile: float
    cov_u: np.ndarray | None
    std_u: np.ndarray
    leakage: np.ndarray
    identifiable: np.ndarray
    std_errors: list[float | None]
    ci95: list[tuple[float, float] | None]
    robust: bool = False
    hc_ratio: np.ndarray | None = None

    def to_dict(self) -> dict:
        """JSON-serialisable summary: plain floats/lists/dicts, NaN and ±inf → None."""
        names = self.param_order
        return {
            "param_order": list(names),
            "values": {n: _num(v) for n, v in zip(names, self.x)},
            "log_mask": {n: bool(b) for n, b in zip(names, self.log_mask)},
            "m": int(self.m),
            "sse": _num(self.sse),
            "singular_values": [_num(v) for v in self.singular_values],
            "rank": int(self.rank),
            "practical_rank": int(self.practical_rank),
            "rank_rtol": _num(self.rank_rtol),
            "null_directions": [[_num(v) for v in d] for d in self.null_directions],
            "null_kinds": list(self.null_kinds),
            "null_halfwidths": [_num(v) for v in self.null_halfwidths],
            "null_combinations": list(self.null_combinations),
            "noise_std": _num(self.noise_std),
            "dof": int(self.dof),
            "ci_level": 1.0 - self.alpha,
            "quantile": _num(self.quantile),
            "std_log": {n: _num(v) for n, v in zip(names, self.std_u)},
            "leakage": {n: _num(v) for n, v in zip(names, self.leakage)},
            "std_errors": {n: _num(v) for n, v in zip(names, self.std_errors)},
            "ci95": {n: (None if c is None else [_num(c[0]), _num(c[1])]) for n, c in zip(names, self.ci95)},
            "identifiable": {n: bool(b) for n, b in zip(names, self.identifiable)},
            "cov_log": None if self.cov_u is None else [[_num(v) for v in row] for row in self.cov_u],
            "covariance": "classical and HC3 sandwich, the larger variance" if self.robust else "classical",
            "hc_ratio": None if not self.robust or self.hc_ratio is None
            else {n: _num(v) for n, v in zip(names, self.hc_ratio)},
        }


def _num(v: float | None) -> float | None:
    """Plain float, or None for None/NaN/inf."""
    if v is None:
        return None
    v = float(v)
    return v if math.isfinite(v) else None


def _fmt_exponent(c: float) -> str:
    return f"{c:.2g}"


def _combination(direction: np.ndarray, names: Sequence[str], log_mask: np.ndarray, scale: np.ndarray,
                 threshold: float) -> str:
    """Readable product for a unit null direction: components ≥ threshold, normalised so the largest is 1."""
    big = np.flatnonzero(np.abs(direction) >= threshold)
    if big.size == 0:
        big = np.array([int(np.argmax(np.abs(direction)))])
    cmax = float(np.max(np.abs(direction)))
    parts = []
    for i in big:
        c = direction[i] / cmax
        if log_mask[i]:
            parts.append(f"{names[i]}^{_fmt_exponent(c)}")
        else:
            parts.append(f"exp({_fmt_exponent(c)}·{names[i]}/{scale[i]:.3g})")
    return " · ".join(parts)


def analyze(jac_log: np.ndarray, residual: np.ndarray, names: Sequence[str], x: Sequence[float], *,
            n_params_fitted: int | None = None, rank_rtol: float | None = None, noise_var: float | None = None,
            alpha: float = 0.05, log_mask: Sequence[bool] | bool | None = None, scale: Sequence[float] | None = None,
            ci_halfwidth_limit: float = CI_HALFWIDTH_LIMIT, null_threshold: float = NULL_THRESHOLD,
            robust: bool = False) -> IdentifiabilityReport:
    """Local identifiability analysis at a fitted point (see the module docstring for every criterion).

    jac_log: (m, n) Jacobian of the output/residual w.r.t. the analysis coordinates (log theta by default).
    residual: (m,) residual at the fit (same weighting as the Jacobian). names: n parameter names.
    x: (n,) fitted values, physical units. n_params_fitted: p_eff for the noise estimate (default: rank).
    rank_rtol: relative singular-value tolerance (default :data:`RANK_RTOL`). noise_var: known noise variance
    of the residual entries (else estimated). alpha: 1 − confidence level (the ``ci95`` key holds the
    (1 − alpha) interval). log_mask/scale: coordinates (default: all log). robust: variances no smaller than
    the HC3 sandwich's (noise whose level varies along the record; see the module docstring).
    Raises :class:`ConfigError` for inconsistent shapes/options and :class:`DataError` for a non-finite
    Jacobian or residual (naming the first bad parameter).
    """
    x = np.asarray(x, dtype=float)
    names = [str(s) for s in names]
    n = x.shape[0]
    if x.ndim != 1 or len(names) != n:
        raise ConfigError(f"x must be 1-D with one value per name ({len(names)}), got shape {x.shape}")
    jac = np.asarray(jac_log, dtype=float)
    r = np.asarray(residual, dtype=float).ravel()
    if jac.ndim != 2 or jac.shape[1] != n:
        raise ConfigError(f"jac_log must have shape (m, {n}), got {jac.shape}")
    m = jac.shape[0]
    if r.shape[0] != m:
        raise ConfigError(f"residual has {r.shape[0]} entries but jac_log has {m} rows")
    bad_cols = np.flatnonzero(~np.all(np.isfinite(jac), axis=0))
    if bad_cols.size:
        raise DataError(f"jacobian column of {names[bad_cols[0]]} is not finite")
    if not np.all(np.isfinite(r)):
        raise DataError("residual contains non-finite entries")
    if not 0.0 < alpha < 1.0:
        raise ConfigError(f"alpha must lie in (0, 1), got {alpha}")
    rtol = RANK_RTOL if rank_rtol is None else float(rank_rtol)
    if not 0.0 <= rtol < 1.0:
        raise ConfigError(f"rank_rtol must lie in [0, 1), got {rtol}")
    if noise_var is not None and not (math.isfinite(noise_var) and noise_var >= 0.0):
        raise ConfigError(f"noise_var must be finite and >= 0, got {noise_var}")
    if not ci_halfwidth_limit > 0.0 or not 0.0 < null_threshold < 1.0:
        raise ConfigError("ci_halfwidth_limit must be > 0 and null_threshold in (0, 1)")
    mask, s_scale = _coordinates(x, log_mask, scale)

    # SVD with a full set of n right singular vectors (also when m < n).
    u_left, sv, vt = np.linalg.svd(jac, full_matrices=m < n)
    s = np.zeros(n)
    s[: sv.shape[0]] = sv[:n]
    smax = float(s[0]) if n else 0.0
    numerical = s > rtol * smax if smax > 0.0 else np.zeros(n, dtype=bool)
    rank = int(np.count_nonzero(numerical))

    # Noise level and quantile.
    sse = float(r @ r)
    p_eff = rank if n_params_fitted is None else int(n_params_fitted)
    dof = m - p_eff
    if noise_var is not None:
        sigma: float | None = math.sqrt(noise_var)
        q = float(stats.norm.ppf(1.0 - alpha / 2.0))
    elif dof > 0:
        sigma = math.sqrt(sse / dof)
        q = float(stats.t.ppf(1.0 - alpha / 2.0, dof))
    else:
        sigma, q = None, float("nan")

    # Heteroscedasticity-robust (HC3) variances, in units of the classical ones, along the singular directions.
    v = vt.T
    inflate = np.ones(n)
    cov_hc = None
    if robust and sigma is not None and sigma > 0.0 and rank > 0 and m > rank:
        ur = u_left[:, : sv.shape[0]][:, numerical[: sv.shape[0]]]
        h = np.minimum(np.einsum("ij,ij->i", ur, ur), 0.99)
        g = ur * (r / (1.0 - h))[:, None]
        core = g.T @ g  # Cov of the coordinates along v_j, times s_j² (the sandwich's meat)
        a = v[:, numerical] / s[numerical]
        cov_hc = a @ core @ a.T
        inflate[numerical] = np.maximum(np.diag(core) / sigma ** 2, 1.0)

    # Half-widths along singular directions and the practical rank.
    with np.errstate(divide="ignore", invalid="ignore"):
        halfwidth = np.where(numerical, q * (sigma if sigma is not None else np.nan) * np.sqrt(inflate)
                             / np.where(numerical, s, 1.0), np.inf)
    practical = numerical & ~(halfwidth > ci_halfwidth_limit) if sigma is not None else numerical.copy()
    practical_rank = int(np.count_nonzero(practical))

    # Covariance over the numerical subspace; leakage along the numerical null space.
    vr = v[:, numerical]
    hc_ratio = np.ones(n)
    if sigma is not None:
        cov = (sigma ** 2) * (vr / s[numerical] ** 2) @ vr.T
        var = np.maximum(np.diag(cov), 0.0)
        if cov_hc is not None:
            var_hc = np.maximum(np.diag(cov_hc), 0.0)
            with np.errstate(divide="ignore", invalid="ignore"):
                hc_ratio = np.where(var > 0.0, var_hc / np.where(var > 0.0, var, 1.0), 1.0)
            var = np.maximum(var, var_hc)
        std_u = np.sqrt(var)
    else:
        cov, std_u = None, np.full(n, np.nan)
    leakage = np.linalg.norm(v[:, ~numerical], axis=1) if rank < n else np.zeros(n)
    identifiable = leakage <= null_threshold
    if sigma is not None:
        identifiable &= q * std_u <= ci_halfwidth_limit

    std_errors: list[float | None] = []
    ci: list[tuple[float, float] | None] = []
    for i in range(n):
        if not identifiable[i] or sigma is None:
            std_errors.append(None)
            ci.append(None)
        elif mask[i]:
            std_errors.append(float(x[i] * std_u[i]))
            ci.append((float(x[i] * math.exp(-q * std_u[i])), float(x[i] * math.exp(q * std_u[i]))))
        else:
            half = q * std_u[i] * s_scale[i]
            std_errors.append(float(std_u[i] * s_scale[i]))
            ci.append((float(x[i] - half), float(x[i] + half)))

    # Null directions, most null first (smallest singular value first).
    null_idx = [j for j in range(n - 1, -1, -1) if not practical[j]]
    dirs = []
    for j in null_idx:
        d = v[:, j].copy()
        big = np.flatnonzero(np.abs(d) >= null_threshold)
        if d[big[0] if big.size else int(np.argmax(np.abs(d)))] < 0:
            d = -d
        dirs.append(d)
    null_dirs = np.array(dirs).reshape(len(dirs), n)
    return IdentifiabilityReport(
        param_order=names, x=x.copy(), log_mask=mask, scale=s_scale, m=m, sse=sse,
        singular_values=s, vt=vt, rank=rank, practical_rank=practical_rank, rank_rtol=rtol,
        null_directions=null_dirs,
        null_kinds=["numerical" if not numerical[j] else "practical" for j in null_idx],
        null_halfwidths=np.array([halfwidth[j] for j in null_idx]),
        null_combinations=[_combination(d, names, mask, s_scale, null_threshold) for d in null_dirs],
        noise_std=sigma, dof=dof, alpha=alpha, quantile=q, cov_u=cov, std_u=std_u, leakage=leakage,
        identifiable=identifiable, std_errors=std_errors, ci95=ci, robust=bool(robust and cov_hc is not None),
        hc_ratio=hc_ratio)


def format_table(report: IdentifiabilityReport) -> str:
    """Short console table: name, value, std err, (1 − alpha) CI, identifiable; then the null combinations."""
    level = f"{100 * (1 - report.alpha):.0f}% CI"
    head = f"{'name':<12} {'value':>11} {'std err':>10}  {level:<25} identifiable"
    lines = [head, "-" * len(head)]
    for i, name in enumerate(report.param_order):
        se = report.std_errors[i]
        ci = report.ci95[i]
        se_s = "-" if se is None else f"{se:.3g}"
        ci_s = "-" if ci is None else f"[{ci[0]:.4g}, {ci[1]:.4g}]"
        lines.append(f"{name:<12} {report.x[i]:>11.5g} {se_s:>10}  {ci_s:<25} "
                     f"{'yes' if report.identifiable[i] else 'NO'}")
    sigma = "unknown" if report.noise_std is None else f"{report.noise_std:.3g}"
    lines.append(f"rank {report.rank}/{len(report.param_order)} (numerical, rtol {report.rank_rtol:g}), "
                 f"practical rank {report.practical_rank}, noise std {sigma}")
    for combo, kind, hw in zip(report.null_combinations, report.null_kinds, report.null_halfwidths):
        extra = f", CI half-width {hw:.3g} log units" if math.isfinite(hw) else ""
        lines.append(f"not identifiable ({kind}{extra}): {combo}")
    return "\n".join(lines)
