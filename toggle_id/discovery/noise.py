"""The measurement noise model: an autoregressive model of the residual, and prewhitening.

A physical model's residual on 1 kHz data is rarely white: a closed loop, an encoder, a filter in the drive
colour the noise, and every statistic that counts N independent samples is then far too confident (an AR(1)
noise with ρ = 0.9 carries about (1 − ρ)/(1 + ρ)·N ≈ N/19 independent samples). The engine therefore works the
prediction-error way (Ljung, *System Identification*, ch. 7): it describes the noise by an AR(p) model

    e(t) = A(q) r(t),  A(q) = 1 − a₁q⁻¹ − … − a_p q⁻ᵖ,  e white with variance σ_e²,

estimated from a residual by Yule–Walker (Levinson–Durbin, :func:`scipy.linalg.solve_toeplitz`), the order
chosen by BIC up to ``max_order`` (or, ``method='burg'``, by Burg's lattice recursion, :func:`burg`: Yule–Walker's
biased autocovariance flattens a sharp spectral peak — on resonant AR(2) noise of pole radius 0.97 it gives
a = (1.71, −0.54, −0.19) for (1.925, −0.941), and the prewhitened residual stays coloured; measured by
``python -m jobs.bench_noise``). Every test statistic is computed on prewhitened signals: the filter A(q) is
applied to the residual *and* to every sensitivity or regressor, so a linear test on the whitened quantities
has its textbook distribution when the noise model is adequate.

The order-0 model is white noise (A = 1), so a record with white noise is judged exactly as before.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from scipy import linalg, signal, stats


@dataclass(frozen=True)
class NoiseModel:
    """AR(p) noise: coefficients ``a`` (a₁…a_p), innovation variance ``sigma2_e`` (m²), the residual's variance
    ``sigma2`` (m²) and the number of samples it was estimated from."""

    a: tuple[float, ...] = ()
    sigma2_e: float = float("nan")
    sigma2: float = float("nan")
    n: int = 0
    note: str = ""
    #: the order chosen by the heteroscedasticity-robust criterion (:func:`fit_noise`'s ``robust``)
    robust_order: bool = False
    #: how the coefficients were estimated (:data:`METHODS`)
    method: str = "yule_walker"

    @property
    def order(self) -> int:
        return len(self.a)

    @property
    def white(self) -> bool:
        return self.order == 0

    @property
    def filter(self) -> np.ndarray:
        """FIR taps of A(q): [1, −a₁, …, −a_p]."""
        return np.r_[1.0, -np.asarray(self.a, float)]

    def whiten(self, x: np.ndarray) -> np.ndarray:
        """A(q) applied along the last axis, the first p samples whitened by their stationary covariance: the exact
        Gaussian likelihood (Prais–Winsten's first sample, √(1 − ρ²)·r(0), for AR(1); the exact likelihood of an AR(p)
        model in Box, Jenkins & Reinsel, *Time Series Analysis*), so every sample has innovation variance and none is
        ignored.

        History: with zero initial conditions the first samples were r(0), r(1) − a₁r(0), … — barely filtered, so under
        noise with a strong low-frequency gain one of them outweighed hundreds of innovations (the prewhitened F-test
        of a constant fired on 92 % of resonant AR(2) draws at the 1 % level); from 2026-12-03 to 2026-12-07 they
        were set to 0 (the conditional likelihood), which made a parameter seen only by them free: the catch-all's
        reading error at a record's starting position took any value there (rec25_d1: 33 µm of raw error at the
        first sample, its fit ending far above the model it started from). Measured by ``python -m jobs.bench_noise``
        (the tests' false alarms). Statistics that work on the lags' regression still drop the first p samples."""
        x = np.asarray(x, float)
        if self.white:
            return x
        y = signal.lfilter(self.filter, [1.0], x, axis=-1)
        p = self.order
        L = self._start_factor
        if L is None:  # no stationary start (not expected of Yule–Walker or Burg): the conditional likelihood
            y[..., :p] = 0.0
        elif x.shape[-1]:
            k = min(p, x.shape[-1])  # a record shorter than p: the leading block of L is the factor of its samples
            head = x[..., :k].reshape(-1, k)
            # a failed simulation's residual is not finite: it stays so (a status, never an error)
            y[..., :k] = linalg.solve_triangular(L[:k, :k], head.T, lower=True, check_finite=False).T.reshape(
                x[..., :k].shape)
        return y

    @cached_property
    def _start_factor(self) -> np.ndarray | None:
        """Lower Cholesky factor of the first p samples' covariance in units of σ_e² (None: not stationary)."""
        return start_factor(self.a)

    def whiten_columns(self, J: np.ndarray) -> np.ndarray:
        """A(q) applied to every column of an (N, p) matrix."""
        return self.whiten(np.asarray(J, float).T).T

    def prewhiten(self, J: np.ndarray, r: np.ndarray, noise_var: float | None = None
                  ) -> tuple[np.ndarray, np.ndarray, float | None]:
        """A least-squares problem under this noise: sensitivities ``J`` (N, p) and residual ``r`` whitened, and a
        known marginal noise variance σ² turned into the innovation variance σ_e² (None stays None)."""
        if self.white:
            return np.asarray(J, float), np.asarray(r, float), noise_var
        return (self.whiten_columns(J), self.whiten(r),
                None if noise_var is None else noise_var / self.variance_ratio)

    @property
    def variance_ratio(self) -> float:
        """σ²/σ_e²: how much the colour inflates the variance of a sum (the long-run variance ratio is larger)."""
        return self.sigma2 / self.sigma2_e if self.sigma2_e > 0 else 1.0

    @property
    def peak_spectrum(self) -> float:
        """The largest value of the noise's power spectrum, σ_e²/min|A(e^{iω})|² (m² per unit of normalised
        frequency, white: σ_e²): no quadratic form of the noise exceeds it times its squared weights."""
        if self.white:
            return float(self.sigma2_e)
        _, h = signal.freqz(self.filter, worN=2048)
        return float(self.sigma2_e / max(float(np.min(np.abs(h) ** 2)), 1e-300))

    @property
    def effective_fraction(self) -> float:
        """n_eff/N: the variance of a white-noise mean over that of this noise's mean, σ²·A(1)²/σ_e² (the
        long-run variance is σ_e²/A(1)²); 1 for white noise, (1 − ρ)/(1 + ρ) for AR(1)."""
        if self.white or not self.sigma2 > 0:
            return 1.0
        a1 = float(np.sum(self.filter))  # A(1)
        long_run = self.sigma2_e / a1 ** 2 if a1 != 0 else np.inf  # spectral density at 0 × 2π
        return float(min(1.0, self.sigma2 / long_run)) if np.isfinite(long_run) else 0.0

    def to_dict(self) -> dict:
        rho1 = float(self.a[0]) if self.order == 1 else None
        return {"kind": "white" if self.white else f"AR({self.order})", "order": self.order,
                "coefficients": [float(c) for c in self.a], "ar1_rho": rho1,
                "innovation_std_m": float(np.sqrt(self.sigma2_e)) if self.sigma2_e >= 0 else None,
                "residual_std_m": float(np.sqrt(self.sigma2)) if self.sigma2 >= 0 else None,
                "effective_sample_fraction": self.effective_fraction,
                "effective_samples": int(round(self.effective_fraction * self.n)), "n": self.n,
                "method": METHOD_NAMES[self.method] + " AR(p), order by "
                          + ("a heteroscedasticity-robust BIC (HC0 Wald of the lags)" if self.robust_order else "BIC")
                          + "; statistics on prewhitened residuals and sensitivities",
                "note": self.note}

    def describe(self) -> str:
        if self.white:
            return f"white noise, σ = {np.sqrt(self.sigma2) * 1e6:.3g} µm"
        coeffs = ", ".join(f"{c:.3g}" for c in self.a)
        return (f"AR({self.order}) noise (a = {coeffs}), σ = {np.sqrt(self.sigma2) * 1e6:.3g} µm, innovation "
                f"σ_e = {np.sqrt(self.sigma2_e) * 1e6:.3g} µm, ≈{self.effective_fraction * self.n:.0f} "
                f"independent samples of {self.n}")


def stationary_autocovariance(a: tuple[float, ...] | np.ndarray) -> np.ndarray | None:
    """γ(0), …, γ(p) of the AR(p) process r(t) = Σ aₖ r(t − k) + e(t) with unit innovation variance, from the
    Yule–Walker equations read the other way (γ(k) − Σ aⱼ γ(|k − j|) = δₖ, k = 0 … p); None when the process is
    not stationary (a pole of 1/A(q) on or outside the unit circle)."""
    a = np.asarray(a, float)
    p = a.size
    if p == 0:
        return np.ones(1)
    if np.any(np.abs(np.roots(np.r_[1.0, -a])) >= 1.0):
        return None
    M = np.eye(p + 1)
    for k in range(p + 1):
        for j in range(1, p + 1):
            M[k, abs(k - j)] -= a[j - 1]
    return np.linalg.solve(M, np.eye(p + 1)[0])


def start_factor(a: tuple[float, ...] | np.ndarray) -> np.ndarray | None:
    """Lower Cholesky factor L of the p × p covariance (unit innovations) of an AR(p) process's first p samples:
    L⁻¹·r(0 … p−1) has the innovations' variance (:meth:`NoiseModel.whiten`). None when not stationary."""
    g = stationary_autocovariance(a) if np.size(a) else None
    if g is None:
        return None
    try:  # positive definite for a stationary model; near a unit root rounding may say otherwise
        return linalg.cholesky(linalg.toeplitz(g[:-1]), lower=True)
    except linalg.LinAlgError:
        return None


WHITE = NoiseModel(note="assumed white (no residual to estimate from)")
#: the estimators of :func:`fit_noise` and how reports name them
METHOD_NAMES = {"yule_walker": "Yule-Walker", "burg": "Burg"}
METHODS = tuple(METHOD_NAMES)


def burg(r: np.ndarray, max_order: int) -> list[tuple[tuple[float, ...], float]]:
    """Burg's estimates of the AR(1) … AR(``max_order``) models of the mean-removed ``r``: for each order the
    coefficients a₁…a_p (r(t) = Σ a_j r(t−j) + e(t)) and the innovation variance. Each reflection coefficient
    minimises the sum of the forward and backward prediction errors' squares over the record (no window), so
    |k| < 1 and every model is stable, and a sharp spectral peak keeps its height (Yule–Walker's biased
    autocovariance flattens it)."""
    e = np.asarray(r, float) - float(np.mean(r))
    f, b = e[1:].copy(), e[:-1].copy()
    a = np.zeros(0)
    s2 = float(e @ e) / e.size
    out = []
    for _ in range(int(max_order)):
        den = float(f @ f + b @ b)
        if not den > 0 or f.size < 2:
            break
        k = 2.0 * float(f @ b) / den
        a = np.r_[a - k * a[::-1], k]
        s2 *= 1.0 - k * k
        out.append((tuple(float(x) for x in a), s2))
        f, b = (f - k * b)[1:], (b - k * f)[:-1]
    return out


def autocovariance(r: np.ndarray, max_lag: int) -> np.ndarray:
    """Biased sample autocovariance c₀…c_K of the mean-removed ``r`` (FFT)."""
    e = np.asarray(r, float) - float(np.mean(r))
    n = e.size
    nfft = 1 << int(np.ceil(np.log2(2 * n)))
    f = np.fft.rfft(e, nfft)
    return np.fft.irfft(f * np.conj(f), nfft)[:max_lag + 1] / n


def fit_noise(r: np.ndarray, max_order: int = 8, penalty: str = "bic", robust: bool = False,
              method: str = "yule_walker") -> NoiseModel:
    """AR(p) model of a residual ``r``, p ≤ ``max_order`` chosen by BIC (``penalty='aic'``: AIC); the
    coefficients by Yule–Walker or (``method='burg'``) by :func:`burg`.

    Yule–Walker estimates are always stable (the Toeplitz matrix of a biased autocovariance is positive
    definite). A non-finite residual gives the white model with a note.

    ``robust``: the order chosen by the same penalty on the heteroscedasticity-robust Wald statistic of the lags
    in the least-squares autoregression (:func:`_robust_order`) instead of the likelihood ratio. White noise whose
    level varies along the record (loud where the slider moves fast) has sample autocorrelations far more
    scattered than 1/√N, and BIC then picks a spurious AR(6–8) (measured: every one of three draws of rec19's
    machine); a statistic that prewhitens by it is no longer calibrated.
    """
    if method not in METHODS:
        raise ValueError(f"noise model method must be one of {', '.join(METHODS)}, got {method!r}")
    r = np.asarray(r, float)
    if r.size < 10 or not np.all(np.isfinite(r)):
        return NoiseModel(note="residual not finite or too short: white noise assumed")
    n = r.size
    K = int(min(max(max_order, 0), n // 10))
    c = autocovariance(r, K)
    if not c[0] > 0:
        return NoiseModel((), 0.0, 0.0, n, "zero residual")
    pen = np.log(n) if penalty == "bic" else 2.0
    best = (n * np.log(c[0]), (), float(c[0]))
    fits = []
    lattice = burg(r, K) if method == "burg" else None
    for p in range(1, K + 1):
        if lattice is not None:
            if p > len(lattice):
                break
            a, s2 = lattice[p - 1]
        else:
            a = linalg.solve_toeplitz(c[:p], c[1:p + 1])
            s2 = float(c[0] - a @ c[1:p + 1])
        if not s2 > 0:
            break
        fits.append((tuple(float(x) for x in a), s2))
        crit = n * np.log(s2) + p * pen
        if crit < best[0]:
            best = (crit, *fits[-1])
    if robust:
        p = min(_robust_order(r, len(fits), pen), len(fits))
        a, s2 = fits[p - 1] if p else ((), float(c[0]))
        return NoiseModel(a, s2, float(c[0]), n, robust_order=True, method=method)
    _, a, s2 = best
    return NoiseModel(a, s2, float(c[0]), n, method=method)


def _robust_order(r: np.ndarray, max_order: int, pen: float) -> int:
    """The order p ≤ ``max_order`` that minimises −(t₁² + … + t_p²) + p·``pen``, t_j the heteroscedasticity-robust
    (HC0) t-statistic of the last lag's coefficient in the least-squares regression of r(t) on r(t−1) … r(t−j)
    (the partial autocorrelation at lag j). When the noise's level is the same everywhere t_j² is the increment
    of the likelihood ratio n·log(σ²_{j−1}/σ²_j) of BIC, to first order."""
    if max_order < 1:
        return 0
    e = np.asarray(r, float) - float(np.mean(r))
    n, K = e.size, max_order
    y = e[K:]
    X = np.column_stack([e[K - k:n - k] for k in range(1, K + 1)])
    best_p, best, total = 0, 0.0, 0.0
    for p in range(1, K + 1):
        Xp = X[:, :p]
        try:
            bread = np.linalg.inv(Xp.T @ Xp)
        except np.linalg.LinAlgError:
            break
        beta = bread @ (Xp.T @ y)
        S = Xp * (y - Xp @ beta)[:, None]
        var = float((bread @ (S.T @ S) @ bread)[-1, -1])
        if not var > 0:
            break
        total += beta[-1] ** 2 / var
        if -total + p * pen < best:
            best, best_p = -total + p * pen, p
    return best_p


def whitened_sse(noise: NoiseModel, r: np.ndarray) -> np.ndarray:
    """Σ e² of the prewhitened residual(s) ``r`` (N,) or (P, N); non-finite rows give inf."""
    e = noise.whiten(np.atleast_2d(np.asarray(r, float)))
    s = np.einsum("ij,ij->i", e, e)
    s[~np.isfinite(s)] = np.inf
    return s


def prediction_error_drift(ls: Any, pe: Any, noise: NoiseModel, alpha: float) -> str | None:
    """Why the prediction-error fit ``pe`` under ``noise`` is not to be trusted beside the least-squares fit ``ls``
    it started from (None: it is, or ``alpha`` is 0, or ``ls`` is not a least-squares fit).

    When the model holds the truth both fits are consistent, and least squares minimises the raw SSE, so the
    prediction-error fit's raw SSE exceeds it only by Δθᵀ JᵀJ Δθ with Var Δθ ≤ the least-squares covariance: at
    most the noise spectrum's peak (:attr:`NoiseModel.peak_spectrum`) times a χ² with as many degrees of freedom
    as free parameters (a Hausman-type comparison of two estimators). Far more means the noise model's slow part
    is an error the model lacks, which the whitened criterion lets the fit drift along: on rec15_d1 of the
    adversarial held-out draw (a viscous friction and an offset missing) the fast nominal fit went from 2.252 to
    2.544 µm, its other seeds from 4.60 to 7.19 µm, and the friction's refit under that noise model gained nothing
    (F 0.017). ``ls`` and ``pe``: fits with ``sse``/``raw_sse`` and ``free``."""
    if not alpha > 0 or noise.white or ls.minimised_under != ():
        return None
    raw = lambda f: f.raw_sse if f.raw_sse is not None else f.sse  # noqa: E731
    excess = raw(pe) - raw(ls)
    k = max(len(pe.free), 1)
    bound = noise.peak_spectrum * float(stats.chi2.isf(alpha, k))
    if not excess > bound:
        return None
    return (f"its raw SSE exceeds the least-squares fit's by {excess:.3g} m², more than the {bound:.3g} m² the "
            f"noise allows at {alpha:g} (χ²({k}) times the noise spectrum's peak): an error the model lacks, not noise")
