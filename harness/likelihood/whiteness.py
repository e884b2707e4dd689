"""Are a filter's residuals white? The Ljung-Box portmanteau test on standard normal residuals.

Under the right model a record's residuals (:meth:`harness.likelihood.kalman.Filtered.standardised`: innovations
over their standard deviations, or randomised quantile residuals on a lattice) are independent standard normals;
their autocorrelations at lags 1..m then make Q = n (n + 2) sum_k r_k^2 / (n - k) a chi-square of m degrees of
freedom (Ljung and Box, 1978). Masked samples are left out of each lag's products: each lag's autocorrelation is
taken over the m_k pairs it has and weighs (m_k + 2), which is Ljung and Box's weight where nothing is masked.

Where a record's residuals are not white, :func:`by_window` says when (the same test on each of its stretches) and
:func:`by_band` at which frequencies: a white series' periodogram ordinates over its variance are independent
exponentials, so 2 sum over a band's m ordinates is a chi-square of 2 m degrees of freedom; a band with more power
than that (a mode the model misses rings there) stands out. Octave bands from the Nyquist frequency down; each family
of tests at the level shared among its members (Bonferroni), so that a white record flags none at the level.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

__all__ = [
    "LEVEL",
    "LAGS",
    "MIN_WINDOW",
    "WINDOW_LAGS",
    "Band",
    "Whiteness",
    "Window",
    "by_band",
    "by_window",
    "ljung_box",
]

LEVEL = 0.01  # a record's residuals are not white when the test's p-value is below this
LAGS = 20  # autocorrelations the test sums
WINDOW_LAGS = 5  # ... on a stretch of a record (20 over 250 residuals: white records flagged 3.7 % at 1 %; 5: 0.9 %)
MIN_WINDOW = 100  # residuals a stretch holds at least


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


def ljung_box(z: np.ndarray, lags: int = LAGS, level: float = LEVEL, scale: float = 1.0) -> Whiteness:
    """The Ljung-Box test of the residuals ``z`` (NaN where masked), its chi-square law scaled by ``scale`` (what an
    approximate filter keeps on its model's own data: :func:`harness.likelihood.simulate.whiteness_scale`).

    Parameters
    ----------
    z : ndarray
        Standard normal residuals, in time order.
    lags : int
        The autocorrelations summed.
    level : float
        The test's level.
    scale : float
        The statistic's law is ``scale`` times the chi-square's.

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
    return Whiteness(q, lags, n, float(chi2.sf(q / scale, lags)), level)


@dataclass(frozen=True)
class Band:
    """A frequency band's test: ``lo_hz``..``hi_hz``, its residuals' power over a white series' (``ratio``), the
    p-value of that much power or more, and whether it stands out (``flagged``: p below the level shared among the
    bands)."""

    lo_hz: float
    hi_hz: float
    ratio: float
    p: float
    flagged: bool


@dataclass(frozen=True)
class Window:
    """A stretch of a record, ``t0``..``t1`` [s], and its Ljung-Box p-value; ``flagged`` where it is below the level
    shared among the stretches."""

    t0: float
    t1: float
    p: float
    flagged: bool


def by_band(z: np.ndarray, Ts: float, level: float = LEVEL, min_ordinates: int = 8) -> tuple[Band, ...]:
    """The residuals ``z`` (NaN where masked, sampled every ``Ts`` [s]) tested for excess power in octave bands.

    Parameters
    ----------
    z : ndarray
        Standard normal residuals, in time order.
    Ts : float
        Their sample time [s].
    level : float
        The level shared among the bands.
    min_ordinates : int
        The lowest band holds at least this many periodogram ordinates.

    Returns
    -------
    tuple of Band
        From the lowest band up to the Nyquist frequency.
    """
    ok = np.isfinite(z)
    x = np.where(ok, z - np.mean(z[ok]), 0.0)
    n = x.size
    var = float(np.sum(x**2)) / max(int(ok.sum()), 1)
    power = np.abs(np.fft.rfft(x)) ** 2 / max(int(ok.sum()), 1) / var if var > 0 else np.zeros(n // 2 + 1)
    freqs = np.fft.rfftfreq(n, Ts)
    k = np.arange(1, (n - 1) // 2 + 1)  # the ordinates between 0 and Nyquist
    edges = [k[-1] + 1]
    while edges[-1] // 2 >= min_ordinates:
        edges.append(edges[-1] // 2)
    edges = sorted({*edges, 1})
    bands = [(lo, hi) for lo, hi in zip(edges[:-1], edges[1:], strict=True) if hi - lo >= min_ordinates]
    out = []
    for lo, hi in bands:
        m = hi - lo
        total = float(np.sum(power[lo:hi]))
        p = float(chi2.sf(2.0 * total, 2 * m))
        out.append(Band(float(freqs[lo]), float(freqs[hi - 1]), total / m, p, p < level / len(bands)))
    return tuple(out)


def by_window(
    z: np.ndarray, Ts: float, windows: int = 10, lags: int = WINDOW_LAGS, level: float = LEVEL
) -> tuple[Window, ...]:
    """The residuals ``z`` (NaN where masked, every ``Ts`` [s]) cut into ``windows`` stretches (fewer where a stretch
    would hold under :data:`MIN_WINDOW` residuals), each Ljung-Box tested over ``lags`` autocorrelations at the
    level shared among them.

    Returns
    -------
    tuple of Window
        In time order.
    """
    w = max(1, min(windows, z.size // MIN_WINDOW))
    cuts = np.linspace(0, z.size, w + 1).astype(int)
    tests = []
    for a, b in zip(cuts[:-1], cuts[1:], strict=True):
        try:
            tests.append((a, b, ljung_box(z[a:b], lags, level).p))
        except ValueError:  # too few measured residuals in the stretch
            continue
    return tuple(Window(a * Ts, b * Ts, p, p < level / len(tests)) for a, b, p in tests)


@dataclass(frozen=True)
class Where:
    """Where a record channel's residuals are not white: its octave ``bands`` (:func:`by_band`) and its stretches
    ``windows`` (:func:`by_window`)."""

    bands: tuple[Band, ...]
    windows: tuple[Window, ...]

    @classmethod
    def from_json(cls, doc: dict) -> Where:
        """As ``likelihood.json``'s ``where`` holds one record channel (:func:`dataclasses.asdict`'s)."""
        return cls(tuple(Band(**b) for b in doc.get("bands", ())), tuple(Window(**w) for w in doc.get("windows", ())))

    def words(self) -> str:
        """The flagged bands and stretches in a few words ("31-62 Hz, 1.5-2 s"), empty where none is flagged."""
        parts = [f"{b.lo_hz:.3g}-{b.hi_hz:.3g} Hz" for b in self.bands if b.flagged]
        parts += [f"{w.t0:.3g}-{w.t1:.3g} s" for w in self.windows if w.flagged]
        return ", ".join(parts)


def where(z: np.ndarray, Ts: float, level: float = LEVEL) -> Where:
    """:class:`Where` of the residuals ``z`` (NaN where masked) sampled every ``Ts`` [s]."""
    return Where(by_band(z, Ts, level), by_window(z, Ts, level=level))
