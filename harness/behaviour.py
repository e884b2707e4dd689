"""A closed loop's behaviour per reference step, measured on any series of it (a record, a replay, an ensemble member).

A loop that tracks a square (step) reference of the hub angle is judged step by step, as a lab's Part II judges its
controller: how far the hub overshoots, when it settles, how far from the reference it stops, how far the link
deflects and rings, how much voltage it takes. :func:`reference_steps` cuts the series at the reference's changes,
:func:`step_metrics` measures each step and :func:`summarize` pools them.

Definitions (step from level ``r0`` to level ``r1``, size ``S = |r1 - r0|`` [deg], direction ``d = sign(r1 - r0)``;
the step runs from the first sample of its transition (a ramped reference's transition is one step) to the next
step's first sample; its *tail* is its last ``tail_s`` seconds, at most its second half):

- ``overshoot_pct``: the hub's peak beyond the new reference, ``100 max(0, max d (theta - r1)) / S``;
- ``final_deg``: the step's own final value, the mean of theta over the tail;
- ``settling_s``: the last entry into the band of ``band_pct`` % of S around the final value, from the step's start:
  ``t[k + 1] - t[start]`` with k the last sample at ``|theta - final| >= band``; 0 when the step never leaves the band,
  NaN when its last sample is outside it (not settled);
- ``stop_error_deg``: ``d (r1 - final)``: positive when the hub stops short of the reference;
- ``peak_alpha_deg``, ``peak_u_v``: the largest ``|alpha|``, ``|u|`` over the step;
- ``ring_alpha_deg``: RMS of alpha over the tail, its mean removed;
- ``ring_hz``: the dominant frequency of alpha over the tail (its Hann-windowed spectrum's peak, refined to a
  fraction of a bin), NaN when alpha does not ring there: when the peak (+-2 bins of the unpadded spectrum) holds less
  than half the tail's variance, or the tail holds less than two periods of it.

The settling time is python-control's ``step_info`` rule (``T[last outside + 1]``, band ``SettlingTimeThreshold`` x
the final value) with two differences that make it a step's own, independent of where the step starts: the band is a
share of the step's size, not of the final value (the two agree for a step from 0), and it is centred on the final
value the response reaches, as MATLAB's ``stepinfo`` does; ``stepinfo`` (R2021b on) sizes its band by the peak error
instead. Overshoot is measured against the reference, not the final value as both do: with friction the hub stops
short and an overshoot of the final value is not one of the reference.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar

__all__ = [
    "METRICS",
    "POOLED_BY",
    "Pooled",
    "Step",
    "StepMetrics",
    "StepSummary",
    "reference_steps",
    "ring_frequency",
    "step_metrics",
    "summarize",
]

METRICS = ("overshoot_pct", "settling_s", "stop_error_deg", "peak_alpha_deg", "peak_u_v", "ring_alpha_deg", "ring_hz")
# how each metric is pooled over a series' steps into one number (Pooled's field): the worst step for what a spec
# bounds, the mean for the signed stopping error, the median for the ringing's frequency
POOLED_BY = {
    "overshoot_pct": "worst",
    "settling_s": "worst",
    "stop_error_deg": "mean",
    "peak_alpha_deg": "worst",
    "peak_u_v": "worst",
    "ring_alpha_deg": "worst",
    "ring_hz": "median",
}
RING_SHARE = 0.5  # the spectral peak's least share of the tail's variance for alpha to ring
RING_PERIODS = 2.0  # the least number of periods the tail must hold for a ringing's frequency


@dataclass(frozen=True)
class Step:
    """One step of a reference: samples ``start`` (the transition's first) to ``end`` (exclusive: the next step's
    first), from level ``from_deg`` to ``to_deg`` [deg], ``direction`` +1 (up) or -1 (down), ``size_deg`` > 0."""

    start: int
    end: int
    from_deg: float
    to_deg: float
    direction: int
    size_deg: float


@dataclass(frozen=True)
class StepMetrics:
    """The loop's behaviour over one step (definitions in the module docstring); ``step`` is the step measured."""

    step: Step
    overshoot_pct: float
    settling_s: float
    final_deg: float
    stop_error_deg: float
    peak_alpha_deg: float
    peak_u_v: float
    ring_alpha_deg: float
    ring_hz: float


@dataclass(frozen=True)
class Pooled:
    """One metric over a series' steps: ``mean``, ``median``, ``worst`` (the largest, or for a signed metric the
    largest in magnitude, its sign kept), over the ``n`` steps where it is defined (NaN when none is; ``worst`` NaN
    too when a step's is NaN: a step that did not settle)."""

    mean: float
    median: float
    worst: float
    n: int


@dataclass(frozen=True)
class StepSummary:
    """A series' steps pooled: one :class:`Pooled` per metric of :data:`METRICS`, and the stopping error's mean over
    the steps up and the steps down [deg] (NaN without such steps)."""

    n_steps: int
    overshoot_pct: Pooled
    settling_s: Pooled
    stop_error_deg: Pooled
    peak_alpha_deg: Pooled
    peak_u_v: Pooled
    ring_alpha_deg: Pooled
    ring_hz: Pooled
    stop_error_up_deg: float
    stop_error_down_deg: float

    def value(self, name: str) -> float:
        """Metric ``name`` pooled into one number as :data:`POOLED_BY` says."""
        return float(getattr(getattr(self, name), POOLED_BY[name]))


def _series(*arrays: np.ndarray) -> list[np.ndarray]:
    out = [np.asarray(a, dtype=float) for a in arrays]
    n = out[0].size
    if any(a.ndim != 1 or a.size != n for a in out):
        raise ValueError("the series must be 1-D arrays of the same length")
    return out


def reference_steps(t: np.ndarray, ref: np.ndarray, initial_deg: float | None = None) -> list[Step]:
    """The steps of a (square, step) reference: the segments between its changes.

    Parameters
    ----------
    t : array
        Time [s] of every sample.
    ref : array
        The reference [deg]. A run of consecutive changing samples (a ramped switch) is one transition.
    initial_deg : float, optional
        The level the loop rests at before the series starts (a simulation from rest: 0). When given and the first
        reference differs from it, the first segment is a step from it; else the first segment is not a step.

    Returns
    -------
    list of Step
        In time order; a transition back to the level it left (a spike) is no step and its samples stay in the
        step before. The last step, which the series may cut short, is left out when it holds fewer samples than
        the shortest of the others.
    """
    t, ref = _series(t, ref)
    if ref.size == 0:
        return []
    tol = 1e-9 * max(1.0, float(np.max(np.abs(ref))))
    changed = np.flatnonzero(np.abs(np.diff(ref)) > tol) + 1  # sample i differs from i - 1
    starts = changed[np.diff(changed, prepend=-2) != 1].tolist()  # the first sample of each run of changes
    cuts: list[tuple[int, float, float]] = []  # (start, from, to)
    if initial_deg is not None and abs(ref[0] - initial_deg) > tol:
        cuts.append((0, float(initial_deg), 0.0))
    for s in starts:
        cuts.append((s, float(ref[s - 1]), 0.0))
    bounds = [c[0] for c in cuts] + [ref.size]
    steps: list[Step] = []
    for (s, r0, _), nxt in zip(cuts, bounds[1:], strict=True):
        r1 = float(ref[nxt - 1])
        if abs(r1 - r0) <= tol:  # back where it was: the samples belong to the step before
            if steps:
                last = steps[-1]
                steps[-1] = Step(last.start, nxt, last.from_deg, last.to_deg, last.direction, last.size_deg)
            continue
        steps.append(Step(s, nxt, r0, r1, 1 if r1 > r0 else -1, abs(r1 - r0)))
    if len(steps) >= 2:  # the series, not the reference, ends the last step: kept when it lasts as long as the rest
        last = steps[-1]
        if last.end - last.start < min(st.end - st.start for st in steps[:-1]):
            steps.pop()
    return steps


def ring_frequency(t: np.ndarray, x: np.ndarray) -> float:
    """The dominant frequency [Hz] of ``x`` sampled at times ``t`` (uniform), NaN when it does not ring.

    The peak of the Hann-windowed periodogram of x with its mean removed, zero-padded 8 times and refined by the
    largest |DTFT| within one padded bin; NaN when the peak (+-2 bins of the unpadded spectrum) holds less than
    RING_SHARE of the variance or the series holds less than RING_PERIODS periods of it.
    """
    t, x = _series(t, x)
    n = x.size
    if n < 8:
        return math.nan
    dt = float(t[-1] - t[0]) / (n - 1)
    y = (x - x.mean()) * np.hanning(n)
    power = np.abs(np.fft.rfft(y)) ** 2
    total = float(power[1:].sum())
    if total <= 0.0:
        return math.nan
    k = int(np.argmax(power[1:])) + 1
    if float(power[max(k - 2, 1) : k + 3].sum()) < RING_SHARE * total:
        return math.nan
    pad = 8 * n
    fine = np.abs(np.fft.rfft(y, pad)) ** 2
    j = int(np.argmax(fine[1:])) + 1
    tn = np.arange(n) * dt

    def neg(f: float) -> float:
        return -float(np.abs(np.sum(y * np.exp(-2j * math.pi * f * tn))))

    df = 1.0 / (pad * dt)
    f = float(minimize_scalar(neg, bounds=((j - 1) * df, (j + 1) * df), method="bounded").x)
    return f if f * (n * dt) >= RING_PERIODS else math.nan


def step_metrics(
    t: np.ndarray,
    ref: np.ndarray,
    theta: np.ndarray,
    alpha: np.ndarray,
    u: np.ndarray,
    band_pct: float = 5.0,
    tail_s: float = 1.0,
    initial_deg: float | None = None,
) -> list[StepMetrics]:
    """The loop's behaviour over every step of its reference (definitions in the module docstring).

    Parameters
    ----------
    t : array
        Time [s].
    ref, theta, alpha : array
        Reference, hub angle and link deflection [deg].
    u : array
        Command [V].
    band_pct : float
        The settling band, % of the step's size around its final value.
    tail_s : float
        The tail [s] whose mean is the final value and whose alpha is the ringing (at most half the step).
    initial_deg : float, optional
        The level before the series (:func:`reference_steps`).

    Returns
    -------
    list of StepMetrics
        One per step, in time order.
    """
    t, ref, theta, alpha, u = _series(t, ref, theta, alpha, u)
    if not band_pct > 0 or not tail_s > 0:
        raise ValueError(f"band_pct and tail_s must be > 0, got {band_pct} and {tail_s}")
    out = []
    for st in reference_steps(t, ref, initial_deg):
        s, e = st.start, st.end
        th, al = theta[s:e], alpha[s:e]
        n_tail = max(1, min(int(np.count_nonzero(t[s:e] > t[e - 1] - tail_s)), (e - s) // 2))
        final = float(np.mean(th[-n_tail:]))
        d = st.direction
        overshoot = 100.0 * max(0.0, float(np.max(d * (th - st.to_deg)))) / st.size_deg
        outside = np.flatnonzero(np.abs(th - final) >= band_pct / 100.0 * st.size_deg)
        if outside.size == 0:
            settling = 0.0
        elif outside[-1] + 1 < e - s:
            settling = float(t[s + outside[-1] + 1] - t[s])
        else:
            settling = math.nan
        tail = al[-n_tail:]
        out.append(
            StepMetrics(
                step=st,
                overshoot_pct=overshoot,
                settling_s=settling,
                final_deg=final,
                stop_error_deg=d * (st.to_deg - final),
                peak_alpha_deg=float(np.max(np.abs(al))),
                peak_u_v=float(np.max(np.abs(u[s:e]))),
                ring_alpha_deg=float(np.sqrt(np.mean((tail - tail.mean()) ** 2))),
                ring_hz=ring_frequency(t[e - n_tail : e], tail),
            )
        )
    return out


def _pool(values: np.ndarray) -> Pooled:
    ok = values[np.isfinite(values)]
    if ok.size == 0:
        return Pooled(math.nan, math.nan, math.nan, 0)
    worst = float(ok[np.argmax(np.abs(ok))]) if ok.size == values.size else math.nan
    return Pooled(float(np.mean(ok)), float(np.median(ok)), worst, int(ok.size))


def summarize(metrics: list[StepMetrics]) -> StepSummary:
    """The steps of a series pooled per metric (:class:`Pooled`), the stopping error also by direction.

    Parameters
    ----------
    metrics : list of StepMetrics
        The steps (:func:`step_metrics`).

    Returns
    -------
    StepSummary
    """
    pooled = {name: _pool(np.array([getattr(m, name) for m in metrics], dtype=float)) for name in METRICS}

    def by_direction(d: int) -> float:
        vals = [m.stop_error_deg for m in metrics if m.step.direction == d]
        return float(np.mean(vals)) if vals else math.nan

    return StepSummary(
        n_steps=len(metrics), **pooled, stop_error_up_deg=by_direction(1), stop_error_down_deg=by_direction(-1)
    )
