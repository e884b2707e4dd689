"""The strain gauge's delay behind the hub angle, read from the records themselves.

Whatever drives the hub, the link answers its motion: alpha / theta = g s^2 / (s^2 + 2 zeta w s + w^2) for one
mode (w the link's clamped frequency), a real ratio away from the resonance, with no drive, friction or command
delay in it. So alpha predicted from the measured theta through that filter shows how far the gauge's reading lags
the hub's: the delay that fits best. A command delay moves both channels alike and leaves it at none.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from scipy import optimize, signal

from .experiments import RigExperiment

__all__ = ["MAX_DELAY_S", "MIN_GAIN_PCT", "MIN_LINK_FIT_PCT", "GaugeDelay", "gauge_delay"]

MAX_DELAY_S = 0.25  # s: the longest delay searched
MIN_RECORD_S = 4 * MAX_DELAY_S  # s: a record shorter than this is not read
SCANS = 4  # scans of the delay, the link filter refitted at each one's best
MIN_GAIN_PCT = 2.0  # points of alpha's fit a delay must gain over none to count
MIN_LINK_FIT_PCT = 50.0  # a link fit below this (alpha barely moves, or not as one mode) decides nothing
START_HZ = (0.5, 1.0, 2.0, 4.0, 8.0)  # clamped frequencies the link fit starts from


@dataclass(frozen=True)
class GaugeDelay:
    """The gauge's delay behind the hub: ``samples`` at ``Ts`` [s] (0: none found), alpha's fit [%] from theta
    through the link without delay and with it, the link's clamped frequency [Hz] and damping ratio that fit, and
    the records it was read from."""

    samples: int
    Ts: float
    fit_none_pct: float
    fit_pct: float
    link_hz: float
    link_zeta: float
    records: tuple[str, ...]

    @property
    def seconds(self) -> float:
        """The delay [s]."""
        return round(self.samples * self.Ts, 9)

    def describe(self) -> str:
        """One line: what was found and how well it fits."""
        if not self.records:
            return f"no record of {MIN_RECORD_S:g} s with theta read throughout: the gauge's timing was not read"
        link = f"alpha from theta through a {self.link_hz:.3g} Hz link fits {self.fit_none_pct:.1f} %"
        records = ", ".join(self.records)
        if not self.samples:
            return f"the gauge reads on time: {link}, no delay gains {MIN_GAIN_PCT:g} points ({records})"
        return (
            f"the gauge reads {1e3 * self.seconds:.4g} ms ({self.samples} samples) behind the hub angle: {link} on "
            f"time, {self.fit_pct:.1f} % so delayed ({records})"
        )


class _LinkFit:
    """alpha [rad] from theta [rad] through the one-mode link filter, each record's gain and offset by linear
    least squares; residuals on the samples after the longest delay searched."""

    def __init__(self, records: list[tuple[np.ndarray, np.ndarray, np.ndarray]], Ts: float, skip: int) -> None:
        self.records, self.Ts, self.skip = records, Ts, skip
        self.sst = sum(float(np.sum((a[skip:][m[skip:]] - a[skip:][m[skip:]].mean()) ** 2)) for _, a, m in records)

    def _filtered(self, p: np.ndarray) -> list[np.ndarray]:
        w, zeta = math.exp(p[0]), p[1]
        k = 2.0 / self.Ts  # the filter by Tustin's rule: s = k (z - 1) / (z + 1)
        a = np.array([k * k + 2 * zeta * w * k + w * w, 2 * (w * w - k * k), k * k - 2 * zeta * w * k + w * w])
        b = k * k * np.array([1.0, -2.0, 1.0])
        return [signal.lfilter(b, a, th - th[0]) for th, _, _ in self.records]

    def residuals(self, p: np.ndarray, d: int) -> np.ndarray:
        out = []
        for y, (_, al, ok) in zip(self._filtered(p), self.records, strict=True):
            keep = ok[self.skip :]
            yd, z = y[self.skip - d : y.size - d][keep], al[self.skip :][keep]
            yc, zc = yd - yd.mean(), z - z.mean()  # the gain and offset by least squares
            g = float(yc @ zc) / float(yc @ yc) if yc.any() else 0.0
            out.append(zc - g * yc)
        return np.concatenate(out)

    def scan(self, p: np.ndarray, top: int) -> int:
        """The delay 0..top [samples] that fits best with the link filter ``p`` held."""
        sse = np.zeros(top + 1)
        for y, (_, al, ok) in zip(self._filtered(p), self.records, strict=True):
            keep = ok[self.skip :]
            z = al[self.skip :][keep]
            zc = z - z.mean()
            for d in range(top + 1):
                yd = y[self.skip - d : y.size - d][keep]
                yc = yd - yd.mean()
                yy = float(yc @ yc)
                sse[d] += float(zc @ zc) - (float(yc @ zc) ** 2 / yy if yy > 0 else 0.0)
        return int(np.argmin(sse))

    def fit(self, d: int, starts: list[np.ndarray]) -> tuple[float, np.ndarray]:
        """(fit %, [ln w, zeta]) of the best start for delay ``d`` samples."""
        lo, hi = [math.log(2 * math.pi * 0.05), 1e-4], [math.log(0.45 * math.pi / self.Ts), 1.0]
        best = None
        for p0 in starts:
            r = optimize.least_squares(self.residuals, np.clip(p0, lo, hi), bounds=(lo, hi), args=(d,))
            if best is None or r.cost < best.cost:
                best = r
        assert best is not None
        return 100.0 * (1.0 - math.sqrt(2.0 * best.cost / self.sst)), best.x


def gauge_delay(experiments: Mapping[str, RigExperiment]) -> GaugeDelay:
    """The delay [samples] of the gauge's reading behind the hub angle that fits alpha from theta best over the
    experiments together (those whose theta is read throughout: no pot dead band to filter across), 0 where it
    gains less than MIN_GAIN_PCT over none or the link fit stays below MIN_LINK_FIT_PCT. The delay is scanned with
    the link filter held, the filter refitted at the best, until the best holds; then the neighbours are refitted
    until none fits better."""
    xs = [x for x in experiments.values() if x.valid["theta"].all() and x.u.size * x.Ts > MIN_RECORD_S]
    Ts = next(iter(experiments.values())).Ts
    none = GaugeDelay(0, Ts, 0.0, 0.0, 0.0, 0.0, ())
    if not xs:
        return none
    top = int(round(MAX_DELAY_S / Ts))
    fit = _LinkFit([(np.radians(x.theta), np.radians(x.alpha), x.valid["alpha"]) for x in xs], Ts, top)
    if fit.sst <= 0.0:
        return none
    scores = {0: fit.fit(0, [np.array([math.log(2 * math.pi * f), 0.05]) for f in START_HZ])}
    d = 0
    for _ in range(SCANS):
        best = fit.scan(scores[d][1], top)
        if best in scores:
            break
        scores[best] = fit.fit(best, [scores[d][1]])
        d = best
    d = max(scores, key=lambda k: scores[k][0])
    for side in (-1, 1):  # the neighbours, while they fit better
        while 0 <= d + side <= top and (d + side) not in scores:
            scores[d + side] = fit.fit(d + side, [scores[d][1]])
            if scores[d + side][0] <= scores[d][0]:
                break
            d += side
    (f0, p0), (f1, p1) = scores[0], scores[d]
    names = tuple(x.name for x in xs)
    if max(f0, f1) < MIN_LINK_FIT_PCT or f1 - f0 < MIN_GAIN_PCT:
        d, f1, p1 = 0, f0, p0
    return GaugeDelay(d, Ts, round(f0, 2), round(f1, 2), math.exp(p1[0]) / (2 * math.pi), float(p1[1]), names)
