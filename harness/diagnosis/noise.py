"""The noise floor of the real data, and the ADC lattice the data sit on.

Noise: period-to-period differences of periodic experiments after their transient, with what a slow gain/offset
drift explains removed (theta through its first difference), or without one a MAD estimate from third
differences; plus LSB^2 / 12 when the data sit on an ADC lattice (identical periods quantise alike, so the
difference misses it). Its mean squared gap (the normalisation of
:func:`harness.diagnosis.simulation.mean_squared_gap`) is the floor no simulation can go below.

Lattice: every sample on the lattice of LSB = 2 adc_range / 2^bits, also when the volts were written rounded to a
few decimals; the coarsest lattice gives the bits.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..ident.calibration import Calibration
from .experiments import CHANNELS, RigExperiment
from .result import NoiseFloor
from .simulation import fit_pct

__all__ = [
    "TRANSIENT_S",
    "adc_lattice",
    "decimal_resolution",
    "noise_floor",
    "noise_mean_squared_gap",
    "noise_sigma",
    "value_step",
]

TRANSIENT_S = 8.0  # s dropped at the start of a periodic experiment before its periods are compared


def decimal_resolution(v: np.ndarray, max_decimals: int = 9) -> float:
    """10^-d when every value is written with at most d decimals (a CSV export rounds its volts), else 0."""
    for d in range(max_decimals + 1):
        x = v * 10.0**d
        if np.max(np.abs(x - np.round(x))) < 1e-6:
            return 10.0**-d
    return 0.0


def value_step(v: np.ndarray, max_levels: float = 1e6, on_lattice: float = 0.95) -> float:
    """The common step of the values' differences: the lattice a record sits on (encoder counts, printed decimals, or
    either converted to another unit: 0.001 rad written in degrees), in the values' unit; 0 when they sit on none
    (continuous values, or a lattice of more than ``max_levels`` steps over their range).

    The most common difference between neighbouring distinct values is the step's first guess; the step is then
    fitted by least squares to the values' multiples of it from one of the most frequent values (the lattice may
    have an offset), and kept when a share ``on_lattice`` of the samples lies within the printed rounding of that
    lattice (a capture's first samples can be exact zeros off it).
    """
    v = np.asarray(v, dtype=float)
    v = v[np.isfinite(v)]
    levels, counts = np.unique(v, return_counts=True)
    if levels.size < 3:
        return 0.0
    span = float(levels[-1] - levels[0])
    diffs = np.diff(levels)
    res = decimal_resolution(levels)
    quantum = res or span / max_levels
    values, seen = np.unique(np.round(diffs / quantum), return_counts=True)
    guess = float(values[np.argmax(seen)]) * quantum
    if guess <= span / max_levels:
        return 0.0
    best, share = 0.0, 0.0
    for ref in levels[np.argsort(-counts, kind="stable")[:5]]:  # the lattice through one of the most frequent values
        k = np.round((levels - ref) / guess)
        step = float(np.dot(k, levels - ref) / np.dot(k, k))
        tol = res + 1e-9 * max(abs(levels[0]), abs(levels[-1]), step) + 1e-6 * step  # both ends printed rounded
        on = float(np.sum(counts[np.abs(levels - ref - k * step) <= tol])) / v.size
        if on > share:
            best, share = step, on
    return best if share >= on_lattice else 0.0


def adc_lattice(experiments: dict[str, RigExperiment], adc_range: float, max_bits: int = 24) -> int:
    """ADC bits whose lattice (multiples of LSB = 2 adc_range / 2^bits, ``adc_range`` [V]) holds every real
    sample of theta_v and alpha_v (the coarsest such lattice), 0 when the data are not quantised (or finer than
    ``max_bits``).

    Data written rounded to d decimals sit within half a unit of the d-th decimal of the lattice; lattices
    finer than 50 such units cannot be told from the rounding itself and are not reported."""
    v = np.concatenate([np.r_[x.theta_v, x.alpha_v] for x in experiments.values()])
    res = decimal_resolution(v)
    for bits in range(2, max_bits + 1):
        lsb = 2.0 * adc_range / 2.0**bits
        if res and lsb < 50.0 * res:
            break
        tol = max(0.5 * res * (1.0 + 1e-6), 1e-6 * lsb)
        if np.max(np.abs(v - lsb * np.round(v / lsb))) <= tol:
            return bits
    return 0


def _clipped_var(d: np.ndarray) -> float:
    """Variance about zero with 5-sigma clipping (a few non-periodic events do not count)."""
    d = d[np.isfinite(d)]
    keep = np.ones(d.size, dtype=bool)
    for _ in range(3):
        v = float(np.mean(d[keep] ** 2)) if keep.any() else 0.0
        new = d**2 <= 25.0 * v if v > 0 else keep
        if np.array_equal(new, keep):
            break
        keep = new
    return v


def _period_residual(y: np.ndarray, P: int, s0: int) -> np.ndarray:
    """Differences between consecutive periods of ``y`` (from period ``s0`` on), each with what a slowly
    drifting gain and offset explain removed (least squares on the two periods' mean and a time ramp of it)."""
    M = y.size // P
    blocks = y[s0 * P : M * P].reshape(M - s0, P)
    ramp = np.linspace(-0.5, 0.5, P)
    out = []
    for a, b in zip(blocks[:-1], blocks[1:], strict=True):
        m = 0.5 * (a + b)
        X = np.column_stack([np.ones(P), ramp, m - m.mean(), (m - m.mean()) * ramp])
        d = b - a
        coef, *_ = np.linalg.lstsq(X, d, rcond=None)
        out.append((d - X @ coef) * math.sqrt(P / (P - X.shape[1])))
    return np.concatenate(out)


def _periods_skipped(x: RigExperiment) -> int:
    """Periods dropped at the start: at least one, and at least TRANSIENT_S (the link's mode rings for seconds)."""
    return max(1, math.ceil(TRANSIENT_S / (x.period * x.Ts) - 1e-9))


def _mad3(y: np.ndarray) -> float:
    """Noise RMS of ``y`` from its third difference: 1.4826 MAD / sqrt(20)."""
    d = np.diff(y, 3)
    return 1.4826 * float(np.median(np.abs(d - np.median(d)))) / math.sqrt(20.0)


def noise_sigma(experiments: dict[str, RigExperiment]) -> dict[str, Any]:
    """Measurement-noise RMS [deg] per channel, from the real data: {"theta_deg", "alpha_deg", "method", "from"}.

    With periodic experiments (>= 2 periods after the transient: the first max(one period, TRANSIENT_S) are
    dropped): differences between consecutive periods, alpha directly (var = 2 s^2), theta through its first
    difference (var = 4 s^2), after removing what a slow drift of gain or offset explains (a drifting gauge is a
    gap, not noise). Without: 1.4826 MAD of the third difference / sqrt(20), median over experiments (an upper
    bound when the motion is fast).
    """
    per = [x for x in experiments.values() if x.period > 0 and x.u.size // x.period - _periods_skipped(x) >= 2]
    if per:
        d_th = [_period_residual(np.r_[0.0, np.diff(x.theta)], x.period, _periods_skipped(x)) for x in per]
        d_al = [_period_residual(x.alpha, x.period, _periods_skipped(x)) for x in per]
        s_th = math.sqrt(_clipped_var(np.concatenate(d_th)) / 4.0)
        s_al = math.sqrt(_clipped_var(np.concatenate(d_al)) / 2.0)
        return {"theta_deg": s_th, "alpha_deg": s_al, "method": "period-to-period", "from": [x.name for x in per]}
    s_th = float(np.median([_mad3(x.theta) for x in experiments.values()]))
    s_al = float(np.median([_mad3(x.alpha) for x in experiments.values()]))
    return {"theta_deg": s_th, "alpha_deg": s_al, "method": "MAD of third differences", "from": list(experiments)}


def noise_mean_squared_gap(experiments: dict[str, RigExperiment], sigma: dict[str, float], names: list[str]) -> float:
    """The mean squared gap E that white noise of RMS ``sigma`` [deg] per channel gives on ``names`` (the
    normalisation of :func:`harness.diagnosis.simulation.mean_squared_gap`)."""
    qs = [
        experiments[n].u.size * sigma[c] ** 2 / experiments[n].sst[c]
        for n in names
        for c in CHANNELS
        if experiments[n].sst[c] > 0
    ]
    return float(np.mean(qs)) if qs else 0.0


def noise_floor(
    experiments: dict[str, RigExperiment],
    adc_range: float,
    cal: Calibration,
    scored: dict[str, RigExperiment] | None = None,
) -> tuple[NoiseFloor, float]:
    """The noise floor of the data (:func:`noise_sigma`, plus the ADC's LSB^2 / 12 through Kp and Ke when the
    volts sit on a lattice of an ADC of ``adc_range`` [V], plus step^2 / 12 of a record written on an angle
    lattice, its encoder's counts or its last decimal: ``RigExperiment.lattice_deg``) and its mean squared gap
    over every experiment of ``scored`` (default ``experiments``: the noise is estimated on whole records, the
    gap taken over what the diagnosis scores, e.g. a lone record's two halves)."""
    sigma = noise_sigma(experiments)
    bits = adc_lattice(experiments, adc_range)
    estimated = None
    if bits:  # identical periods quantise alike: the period-to-period estimate misses most of the ADC error
        lsb = 2.0 * adc_range / 2.0**bits
        estimated = {"theta": sigma["theta_deg"], "alpha": sigma["alpha_deg"]}
        sigma["theta_deg"] = math.sqrt(sigma["theta_deg"] ** 2 + (cal.Kp * lsb) ** 2 / 12.0)
        sigma["alpha_deg"] = math.sqrt(sigma["alpha_deg"] ** 2 + (cal.Ke * lsb) ** 2 / 12.0)
        sigma["method"] += " + ADC quantisation variance LSB^2 / 12"
    steps = {c: max((x.lattice_deg or {}).get(c, 0.0) for x in experiments.values()) for c in CHANNELS}
    if any(steps.values()):  # a record written on an angle lattice: third differences of its steps are mostly 0
        estimated = estimated or {"theta": sigma["theta_deg"], "alpha": sigma["alpha_deg"]}
        for c in CHANNELS:
            sigma[f"{c}_deg"] = math.sqrt(sigma[f"{c}_deg"] ** 2 + steps[c] ** 2 / 12.0)
        sigma["method"] += " + the record's angle step^2 / 12"
    rms = {"theta": sigma["theta_deg"], "alpha": sigma["alpha_deg"]}
    scored = experiments if scored is None else scored
    e_noise = noise_mean_squared_gap(scored, rms, list(scored))
    floor = NoiseFloor(
        theta_deg=sigma["theta_deg"],
        alpha_deg=sigma["alpha_deg"],
        method=sigma["method"],
        sources=sigma["from"],
        gap=math.sqrt(e_noise),
        fit_pct=fit_pct(e_noise),
        adc_lattice_bits=bits,
        estimated_deg=estimated,
    )
    return floor, e_noise
