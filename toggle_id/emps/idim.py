"""IDIM-LS: the benchmark's inverse-model least-squares recipe (EMPS_Description.pdf §3, Script_IDIM_LS.m).

1. zero-phase 4th-order Butterworth low-pass (100 Hz) of qm;  2. q̇, q̈ by central differences (``np.gradient``);
3. drop the first 49 samples;  4. Φ = [q̈, q̇, sign q̇, 1], y = gtau·vir;  5. decimate every column and y by 10
(``scipy.signal.decimate``, order-8 Chebyshev, zero phase) and solve by least squares.
On DATA_EMPS this gives M = 95.104, Fv = 203.13, Fc = 20.438, offset = −3.180 (README's independent check).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from ..errors import ConfigError, DataError
from .data import EmpsRecord

#: Regressor columns the recipe knows, by parameter name (symmetric model and the asymmetric model of eq. 12).
TERMS_SYMMETRIC: tuple[str, ...] = ("M", "Fv", "Fc", "offset")
TERMS_ASYMMETRIC: tuple[str, ...] = ("M", "Fv+", "Fc+", "Fv-", "Fc-")


def filtered_derivatives(qm: np.ndarray, dt: float, cutoff_hz: float = 100.0, order: int = 4
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Zero-phase Butterworth-filtered position (m) and its central-difference velocity (m/s) and acceleration (m/s²)."""
    from scipy.signal import butter, filtfilt

    nyq = 0.5 / dt
    if not (0 < cutoff_hz < nyq):
        raise ConfigError(f"cutoff_hz must lie in (0, {nyq}) Hz, got {cutoff_hz}")
    b, a = butter(int(order), cutoff_hz / nyq)
    q = filtfilt(b, a, qm)
    qd = np.gradient(q, dt)
    qdd = np.gradient(qd, dt)
    return q, qd, qdd


def _column(term: str, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
    """One regressor column of Φ for ``term`` (coefficient name)."""
    cols = {
        "M": lambda: qdd,
        "Fv": lambda: qd,
        "Fc": lambda: np.sign(qd),
        "offset": lambda: np.ones_like(qd),
        "Fv+": lambda: np.maximum(qd, 0.0),
        "Fv-": lambda: np.minimum(qd, 0.0),
        "Fc+": lambda: (qd > 0).astype(float),
        "Fc-": lambda: -(qd < 0).astype(float),
    }
    if term not in cols:
        raise ConfigError(f"unknown IDIM-LS term {term!r}; known: {sorted(cols)}")
    return cols[term]()


def idim_ls(record: EmpsRecord, terms: Sequence[str] = TERMS_SYMMETRIC, cutoff_hz: float = 100.0,
            order: int = 4, n_drop: int = 49, decimate_factor: int = 10) -> dict:
    """Run the IDIM-LS recipe on ``record`` with regressor ``terms``; returns a plain dict.

    Keys: ``params`` (term → value, SI units), ``sigma`` (term → standard deviation), ``rel_sigma_pct``,
    ``rel_error_pct`` (100·‖y − Φθ‖/‖y‖ on the decimated data), ``cond`` (condition number of Φ), ``n_rows``.
    """
    from scipy.signal import decimate

    if decimate_factor < 1 or n_drop < 0:
        raise ConfigError(f"need decimate_factor >= 1 and n_drop >= 0, got {decimate_factor}, {n_drop}")
    n_keep = record.n - n_drop
    if n_keep < 30 * decimate_factor + len(terms):
        raise DataError(f"record {record.name!r} too short for IDIM-LS ({record.n} samples)")
    _, qd, qdd = filtered_derivatives(record.qm, record.dt, cutoff_hz, order)
    phi = np.column_stack([_column(t, qd, qdd) for t in terms])[n_drop:]
    y = record.tau[n_drop:]
    if decimate_factor > 1:
        phi = np.column_stack([decimate(c, decimate_factor) for c in phi.T])
        y = decimate(y, decimate_factor)
    theta, _, rank, _ = np.linalg.lstsq(phi, y, rcond=None)
    if rank < phi.shape[1]:
        raise DataError(f"IDIM-LS regressor {list(terms)} is rank deficient on record {record.name!r} "
                        f"(rank {rank}; e.g. the motion never changes direction)")
    resid = y - phi @ theta
    dof = max(phi.shape[0] - phi.shape[1], 1)
    cov = (resid @ resid / dof) * np.linalg.inv(phi.T @ phi)
    sigma = np.sqrt(np.diag(cov))
    return {
        "params": {t: float(v) for t, v in zip(terms, theta)},
        "sigma": {t: float(s) for t, s in zip(terms, sigma)},
        "rel_sigma_pct": {t: float(100 * s / abs(v)) if v != 0 else float("inf") for t, s, v in zip(terms, sigma, theta)},
        "rel_error_pct": float(100 * np.linalg.norm(resid) / np.linalg.norm(y)),
        "cond": float(np.linalg.cond(phi)),
        "n_rows": int(phi.shape[0]),
    }
