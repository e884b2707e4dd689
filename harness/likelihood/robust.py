"""The score's variance when the innovations are not independent: a heteroskedasticity and autocorrelation
consistent (HAC) estimate, and what it does to an estimate's variance.

Under the right model a filter's per-sample scores (the slopes of each sample's term of the log-likelihood) are a
martingale difference: their variance summed over a record is the Fisher information, and the likelihood-ratio
statistic of a nested parameter is a chi-square. Where the model is not quite right, a quantised reading at rest
most of all (its cell is one error for hundreds of samples), the scores are autocorrelated, their sum varies more
than the information says, and the statistic grows with it. The long-run covariance of the scores (Newey and West,
1987: the Bartlett kernel; the lags by Andrews, 1991: his AR(1) plug-in, taken per column and pooled) measures by how
much. The information is taken as the scores' own variance at lag 0 (the outer product of the gradient, Berndt, Hall,
Hall and Hausman): the filter's one-step predictive densities make it the information where each is right, a
lattice's cell probabilities included, where a Gaussian's Fisher information would not be. The sandwich
H^-1 Omega H^-1 over H^-1, per parameter, is then the factor (:func:`inflation`) by which its variance, and a nested
parameter's likelihood-ratio statistic, are larger than the information says because the scores are autocorrelated
(the statistic of one parameter tends to that factor times a chi-square: White, 1982; Kent, 1982).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["LongRun", "inflation", "long_run"]


@dataclass(frozen=True)
class LongRun:
    """The long-run covariance ``cov`` (k x k) of per-sample scores summed over ``samples`` samples, with the
    Bartlett kernel over ``lags`` lags, and their covariance at lag 0 alone ``lag0`` (the outer product of the
    gradient)."""

    cov: np.ndarray
    lag0: np.ndarray
    lags: int
    samples: int


def _bandwidth(s: np.ndarray, cap: int) -> int:
    """Andrews' (1991) AR(1) plug-in bandwidth of the Bartlett kernel for the columns of ``s`` (samples x k), each
    weighted by its variance's square: 1.1447 (alpha n)^(1/3), at most ``cap``."""
    a, b = s[1:], s[:-1]
    num = den = 0.0
    for j in range(s.shape[1]):
        bb = float(b[:, j] @ b[:, j])
        if bb <= 0.0:
            continue
        rho = min(max(float(a[:, j] @ b[:, j]) / bb, -0.97), 0.97)
        sig2 = float(np.mean((a[:, j] - rho * b[:, j]) ** 2))
        num += 4.0 * rho**2 * sig2**2 / ((1.0 - rho) ** 6 * (1.0 + rho) ** 2)
        den += sig2**2 / (1.0 - rho) ** 4
    if den <= 0.0:
        return 0
    return int(min(cap, np.ceil(1.1447 * (num / den * s.shape[0]) ** (1.0 / 3.0))))


def long_run(scores: np.ndarray, record: np.ndarray, sample: np.ndarray, lags: int | None = None) -> LongRun:
    """The long-run covariance of the scores of readings, summed by sample.

    Parameters
    ----------
    scores : ndarray
        One row per reading, one column per parameter: the slopes of its term of the log-likelihood [nats per unit
        of the parameter's coordinate].
    record, sample : ndarray of int
        Each reading's record and sample within it: readings of one sample are summed, records are independent
        (no lag crosses from one to the next).
    lags : int, optional
        The Bartlett kernel's lags; default the records' pooled Andrews bandwidth.

    Returns
    -------
    LongRun
        Centred on the scores' mean (at a maximum, the priors' slope).
    """
    scores = np.asarray(scores, dtype=float)
    k = scores.shape[1]
    keys = record.astype(np.int64) * (int(sample.max(initial=0)) + 1) + sample
    uniq, where = np.unique(keys, return_inverse=True)
    per = np.zeros((uniq.size, k))
    np.add.at(per, where, scores)
    rec_of = uniq // (int(sample.max(initial=0)) + 1)
    per -= per.mean(axis=0)
    parts = [per[rec_of == r] for r in np.unique(rec_of)]
    if lags is None:
        cap = max(0, min(p.shape[0] for p in parts) // 4)
        lags = _bandwidth(np.concatenate(parts), cap)
    lag0 = sum((p.T @ p for p in parts), np.zeros((k, k)))
    cov = lag0.copy()
    for p in parts:
        for lag in range(1, min(lags, p.shape[0] - 1) + 1):
            g = p[lag:].T @ p[:-lag]
            cov += (1.0 - lag / (lags + 1.0)) * (g + g.T)
    return LongRun(cov, lag0, lags, int(uniq.size))


def inflation(scores: LongRun) -> np.ndarray:
    """Per parameter, the sandwich variance H^-1 Omega H^-1 (H the ``scores``' lag-0 covariance, Omega their
    long-run covariance) over H^-1: 1 where the scores are not autocorrelated, above 1 where they are. NaN where
    the scores give no variance."""
    h_inv = np.linalg.pinv(scores.lag0)
    sandwich = h_inv @ scores.cov @ h_inv
    model = np.diag(h_inv)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(model > 0.0, np.diag(sandwich) / model, np.nan)
