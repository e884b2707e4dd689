"""Are a filter's residuals white? The Ljung-Box portmanteau test on standard normal residuals.

Under the right model a record's residuals (:meth:`harness.likelihood.kalman.Filtered.standardised`: innovations
over their standard deviations, or randomised quantile residuals on a lattice) are independent standard normals;
their autocorrelations at lags 1..m then make Q = n (n + 2) sum_k r_k^2 / (n - k) a chi-square of m degrees of
freedom (Ljung and Box, 1978). Masked samples are left out of each lag's products: each lag's autocorrelation is
taken over the m_k pairs it has and weighs (m_k + 2), which is Ljung and Box's weight where nothing is masked.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

__all__ = ["LEVEL", "LAGS", "Whiteness", "ljung_box"]

LEVEL = 0.01  # a record's residuals are not white when the test's p-value is below this
LAGS = 20  # autocorrelations the test sums


@dataclass(frozen=True)
class Whiteness:
    """The Ljung-Box test of one series: its ``statistic`` Q over ``lags`` autocorrelations of ``n`` residuals, its
    ``p`` value, and whether the series is ``white`` at ``level``."""

    statistic: float
    lags: int
    n: int
    p: float
    level: float

    @property
    def white(self) -> bool:
        """The residuals pass the test: p at or above the level."""
        return self.p >= self.level


def ljung_box(z: np.ndarray, lags: int = LAGS, level: float = LEVEL) -> Whiteness:
    """The Ljung-Box test of the residuals ``z`` (NaN where masked).

    Parameters
    ----------
    z : ndarray
        Standard normal residuals, in time order.
    lags : int
        The autocorrelations summed.
    level : float
        The test's level.

    Returns
    -------
    Whiteness
    """
    ok = np.isfinite(z)
    x = np.where(ok, z - np.mean(z[ok]), 0.0)
    n = int(ok.sum())
    if n <= lags + 1:
        raise ValueError(f"{n} residuals: too few for a whiteness test of {lags} lags")
    var = float(np.sum(x**2)) / n
    q = 0.0
    for k in range(1, lags + 1):
        pairs = int(np.sum(ok[k:] & ok[:-k]))
        rho = float(np.sum(x[k:] * x[:-k])) / (pairs * var) if pairs else 0.0
        q += (pairs + 2) * rho**2  # Ljung and Box's n (n + 2) r_k^2 / (n - k), r_k over the pairs a mask leaves
    return Whiteness(q, lags, n, float(chi2.sf(q, lags)), level)
