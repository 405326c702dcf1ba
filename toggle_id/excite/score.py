"""Scores of an input: the separation of two rival explanations that survives refitting, and the singular values
of the sensitivities of x_B to the 15 parameters.

*Separation.* Rival A (an effect on) and rival B (the nominal model, which may absorb it) both explain the
record. On a candidate input, A's response y_A is the data; B's free parameters are refitted to it and the RMS
of what is left, y_A − y_B(refitted), is the separation (m) — divided by the noise σ it says how many σ the two
explanations stay apart on that input. :func:`linear_separation` is its first-order estimate (the part of
y_A − y_B outside the range of B's sensitivities: one batched simulation, the search's score);
:func:`refit_separation` the real refit (bounded least squares, :func:`toggle_id.discovery.fit_free`, from B's
parameters, from A's nominal part and from the first-order Gauss–Newton point; the best one counts).

*Spectrum.* :func:`spectrum` gives the singular values of the x_B sensitivities w.r.t. the log-parameters
(fourth-order differences), the numerical rank the Jacobian's own error resolves
(:func:`toggle_id.sensitivity.numerical_rank_rtol`) and which parameters are identifiable under noise σ
(:func:`toggle_id.identifiability.analyze`).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from .. import params as P
from ..discovery.derivatives import _coords, sensitivities
from ..discovery.model import Model, fit_free
from ..effects import ALL_INDEX
from ..identifiability import analyze
from ..problem import FitProblem
from ..record import Record
from ..sensitivity import log_jacobian_model, numerical_rank_rtol
from ..simulate import PRECISE, STATUS_NAMES, STATUS_OK, simulate


@dataclass
class Rival:
    """Two explanations of one record: ``theta_a`` (extended vector, effect ``effect`` on) and ``theta_b`` (the
    nominal model, effect off; or the effect ``against`` on instead). ``free_b``: B's parameters a refit may move.
    ``rms_a_m`` / ``rms_b_m``: their RMS errors on the record (both should be near the noise: the record cannot
    tell them apart). ``key``: the rival's name in metrics (default ``effect``)."""

    name: str
    effect: str
    params: dict[str, float]
    theta_a: np.ndarray
    theta_b: np.ndarray
    free_b: tuple[str, ...]
    rms_a_m: float = float("nan")
    rms_b_m: float = float("nan")
    source: str = "config"
    record_separation_m: float = float("nan")
    extra: dict = field(default_factory=dict)
    key: str = ""
    against: str | None = None

    def __post_init__(self) -> None:
        self.key = self.key or self.effect

    def to_dict(self) -> dict:
        b_names = (*P.PARAM_NAMES, *(nm for nm in self.free_b if nm not in P.PARAM_NAMES))
        return {"name": self.name, "key": self.key, "effect": self.effect, "against": self.against,
                "params": dict(self.params), "source": self.source,
                "free_b": list(self.free_b), "rms_a_um": 1e6 * self.rms_a_m, "rms_b_um": 1e6 * self.rms_b_m,
                "theta_a": {nm: float(self.theta_a[ALL_INDEX[nm]]) for nm in (*P.PARAM_NAMES, *self.params)},
                "theta_b": {nm: float(self.theta_b[ALL_INDEX[nm]]) for nm in b_names}, **self.extra}


def responses(record: Record, thetas: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """(P, N) PRECISE x_B of extended vectors on ``record`` (NaN rows for failures) and each row's status."""
    res = simulate(np.atleast_2d(thetas), record, PRECISE, parallel=np.atleast_2d(thetas).shape[0] > 1)
    x = res.x_B.copy()
    x[res.status != STATUS_OK] = np.nan
    return x, [STATUS_NAMES.get(int(s), str(int(s))) for s in res.status]


def _with_output(record: Record, x_B: np.ndarray) -> Record:
    return Record(t=record.t, v_in=record.v_in, x_B=x_B, sweep=record.sweep, x_B0=record.x_B0, name=record.name)


def linear_separation(record: Record, rival: Rival, y_a: np.ndarray, y_b: np.ndarray, rel_step: float = 1e-5,
                      return_step: bool = False):
    """First-order separation (m RMS): the part of y_A − y_B outside the range of B's sensitivities on ``record``
    (the least-squares step of B's free parameters taken exactly, in the linear model). NaN on failure. With
    ``return_step`` also B's vector moved by that step (the Gauss–Newton point; None on failure or when the step
    overflows)."""
    d = y_a - y_b
    if not np.all(np.isfinite(d)):
        return (float("nan"), None) if return_step else float("nan")
    J = sensitivities(Model(_with_output(record, y_b), parallel=True), rival.theta_b, rival.free_b, rel_step)
    if not np.all(np.isfinite(J)):
        return (float("nan"), None) if return_step else float("nan")
    # columns scaled to unit norm (the least-squares solution is invariant; the conditioning is not)
    norms = np.linalg.norm(J, axis=0)
    keep = norms > 0
    Jn = J[:, keep] / norms[keep]
    coef, *_ = np.linalg.lstsq(Jn, d, rcond=1e-10)
    r = d - Jn @ coef
    sep = float(np.sqrt(np.mean(r * r)))
    if not return_step:
        return sep
    du = np.zeros(len(rival.free_b))
    du[keep] = coef / norms[keep]
    mask, scale = _coords(rival.free_b, rival.theta_b)
    theta = rival.theta_b.copy()
    with np.errstate(over="ignore", invalid="ignore"):  # a step too long to take is no Gauss–Newton point
        for j, nm in enumerate(rival.free_b):
            i = ALL_INDEX[nm]
            theta[i] = theta[i] * np.exp(du[j]) if mask[j] else theta[i] + du[j] * scale[j]
    return sep, (theta if np.all(np.isfinite(theta)) else None)


def refit_separation(record: Record, rival: Rival, y_a: np.ndarray, *, max_nfev: int, rounds: int,
                     fd_rel_step: float = 1e-4) -> dict:
    """Refit B's free parameters to A's response ``y_a`` on ``record`` (from B's parameters and from A's nominal
    part and from B's Gauss–Newton point of the first-order separation; the best counts). Returns separation_m
    (RMS of what is left), the refitted vector and response."""
    model = Model(_with_output(record, y_a), parallel=True)
    start_a = rival.theta_b.copy()
    start_a[:P.N_PARAMS] = rival.theta_a[:P.N_PARAMS]
    y_b0, _ = responses(record, rival.theta_b)
    _, start_gn = linear_separation(record, rival, y_a, y_b0[0], return_step=True)
    starts = [rival.theta_b, start_a] + ([start_gn] if start_gn is not None else [])
    best = None
    for start in starts:
        fit = fit_free(model, start, rival.free_b, max_nfev, fd_rel_step, rounds=rounds)
        if best is None or fit.sse < best.sse:
            best = fit
    y_b, _ = responses(record, best.theta)
    r = y_a - y_b[0]
    sep = float(np.sqrt(np.mean(r * r))) if np.all(np.isfinite(r)) else float("nan")
    return {"separation_m": sep, "theta_b_refit": best.theta, "y_b_refit": y_b[0], "nfev": int(best.info["nfev"]),
            "n_simulations": int(model.n_sims)}


def spectrum(record: Record, theta: np.ndarray, noise_std: float, names: Sequence[str] = P.PARAM_NAMES,
             others: Sequence[Record] = ()) -> dict:
    """Singular values (m per unit log-parameter, descending), numerical rank and identifiable parameters of x_B's
    sensitivities at ``theta`` on ``record`` (stacked with ``others``: several experiments fitted jointly).

    Every input is taken at its samples, as a candidate input is: a record simulated in memory from its swept sine
    is integrated freely, and there the Jacobian's own error (what the numerical rank is resolved against) is far
    larger than with steps that stop at the samples — measured on the default record, rank 5 resolved (s6 = 1.3e-6
    m) where its sampled input resolves 8 — so the record and a proposal would be compared on different footing."""
    Js, Es = [], []
    for rec in (record, *others):
        rec = rec if rec.sweep is None else replace(rec, sweep=None)
        y, status = responses(rec, theta)
        if not np.all(np.isfinite(y[0])):
            return {"error": f"simulation failed ({status[0]})"}
        prob = FitProblem(_with_output(rec, y[0]), tuple(names), theta, (0, rec.n), PRECISE)
        J, E = log_jacobian_model(prob, prob.x0(), return_error=True)
        if not np.all(np.isfinite(J)):
            return {"error": "sensitivities not finite"}
        Js.append(J)
        Es.append(E)
    J, E = np.vstack(Js), np.vstack(Es)
    rtol = numerical_rank_rtol(J, E)
    x = np.array([theta[ALL_INDEX[n]] for n in names])
    rep = analyze(J, np.zeros(J.shape[0]), list(names), x, log_mask=x > 0, noise_var=noise_std ** 2,
                  rank_rtol=rtol, n_params_fitted=len(names))
    s = [float(v) for v in rep.singular_values]
    return {"singular_values": s, "rank": int(rep.rank), "practical_rank": int(rep.practical_rank),
            "identifiable": [n for n, ok in zip(names, rep.identifiable) if ok],
            "null_combinations": list(rep.null_combinations)}


def sv_at(spec: dict, k: int) -> float:
    """The k-th (1-based) singular value of a :func:`spectrum`, NaN if unknown."""
    s = spec.get("singular_values") or []
    return float(s[k - 1]) if len(s) >= k else float("nan")
