"""Sensor calibration of the rig: potentiometer gain Kp, strain-gauge gain Ke, motor dead zone.

Conventions (lab 1, section 2): shaft angle theta [deg] = Kp (theta_v - pot_offset_v), Kp in deg/V;
deflection alpha [deg] = Ke (alpha_v - gauge_offset_v), Ke in deg/V; tip angle y = theta + alpha [deg].
The potentiometer wraps from its top voltage to its bottom one at +-180 deg and has a dead band of a few
degrees there, where its voltage holds at the end values.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from scipy.optimize import minimize_scalar

from ..rundir import ExperimentEntry, Manifest, RunDir, read_dataset, record_inputs, write_json
from .preprocess import as_signal, time_axis

__all__ = [
    "Calibration",
    "DeadZone",
    "GaugeCalibration",
    "PotCalibration",
    "alpha_deg",
    "calibrate",
    "comb_table",
    "daq_calibration",
    "dead_zone_estimate",
    "dead_zone_merge",
    "gauge_volts",
    "ke_from_comb",
    "kp_from_ramp",
    "kp_from_table",
    "kp_from_wrap_voltages",
    "theta_deg",
    "tip_deg",
]

# Lab 1 (section 2): Kp = 360 / (5.0635 + 5.0732) deg/V, Ke = -3.3636 deg/V, dead zone 0.3369 V
LAB1_CALIBRATION = {"Kp": 35.5145, "Ke": -3.3636, "dead_zone_v": 0.3369}


# --- potentiometer


def kp_from_wrap_voltages(v_max: float, v_min: float) -> float:
    """Lab 1's formula Kp = 360 / (v_max - v_min) [deg/V] from the pot's end voltages [V]."""
    v_max, v_min = float(v_max), float(v_min)
    if not (math.isfinite(v_max) and math.isfinite(v_min)) or v_max <= v_min:
        raise ValueError(f"need finite v_max > v_min, got v_max={v_max} V, v_min={v_min} V")
    return 360.0 / (v_max - v_min)


@dataclass(frozen=True)
class PotCalibration:
    """Potentiometer calibration from a constant-speed ramp through several wraps.

    Kp [deg/V] from the wrap timing (true gain); Kp_span [deg/V] = 360 / (v_max - v_min), lab 1's formula,
    which over-estimates Kp by 360 / (360 - deadband_deg); v_max, v_min [V] the end voltages; deadband_deg
    = 360 - Kp (v_max - v_min); n_wraps the number of wraps seen. lag_s [s]: when the record starts at rest
    with the command step at t[0], the time after t[0] at which the steady-speed asymptote passes the start
    angle (command delay + mechanical time constant; the ``lag_s`` of :func:`dead_zone_estimate`); NaN when
    the start lies in the dead band or too few tracks are seen. rel_se: Kp's relative standard error from the
    spread of its per-revolution values after the first (NaN from fewer than four revolutions).
    """

    Kp: float
    Kp_span: float
    v_max: float
    v_min: float
    deadband_deg: float
    n_wraps: int
    lag_s: float = float("nan")
    rel_se: float = float("nan")


def _robust_line(t: np.ndarray, v: np.ndarray) -> tuple[float, float, float]:
    """Line v = s (t - tm) + b, refitted up to twice without points beyond 4 MAD; returns (s, b, tm)."""
    tm = float(t.mean())
    keep = np.ones(t.size, dtype=bool)
    s, b = 0.0, 0.0
    for _ in range(3):
        s, b = np.polyfit(t[keep] - tm, v[keep], 1)
        r = v - (s * (t - tm) + b)
        mad = 1.4826 * float(np.median(np.abs(r[keep] - np.median(r[keep]))))
        new = np.abs(r) <= max(4.0 * mad, 1e-12)
        if new.sum() < 3 or np.array_equal(new, keep):
            break
        keep = new
    return float(s), float(b), tm


def kp_from_ramp(t: Any, theta_v: Any) -> PotCalibration:
    """Kp [deg/V] from a constant-speed pot ramp ``theta_v`` [V] at times ``t`` [s] through several wraps.

    Wraps are jumps larger than half the voltage span. Each track between wraps gets a robust line fit on its
    middle 80 % of the voltage range (dead-band holds and jumps excluded) and the time it crosses mid-range.
    One revolution (360 deg) lasts the time between crossings of consecutive tracks, T, so the pot turns
    s T volts per 360 deg (s the track slope [V/s]): Kp = 360 / (s T), median over track pairs. The shaft
    must turn one way only; at least two tracks must cross mid-range (one full revolution observed).
    """
    t = time_axis(t)
    v = as_signal("theta_v", theta_v, t.size)
    lo, hi = float(v.min()), float(v.max())
    span = hi - lo
    if span <= 0:
        raise ValueError("potentiometer voltage is constant: the shaft did not turn")
    dv = np.diff(v)
    jumps = np.flatnonzero(np.abs(dv) > 0.5 * span)
    if jumps.size == 0:
        raise ValueError("no potentiometer wrap found: the shaft must turn through the +-180 deg wrap")
    signs = np.sign(dv[jumps])
    if np.any(signs != signs[0]):
        raise ValueError("the potentiometer wraps in both directions: the ramp must turn the shaft one way")
    direction = -signs[0]  # a downward jump means the shaft turns towards increasing voltage
    bounds = np.concatenate(([0], jumps + 1, [v.size]))
    v_ref = 0.5 * (lo + hi)
    band_lo, band_hi = lo + 0.1 * span, hi - 0.1 * span
    cross: dict[int, tuple[float, float]] = {}  # track index -> (crossing time, slope)
    tops, bottoms = [], []
    for i in range(bounds.size - 1):
        seg = slice(bounds[i], bounds[i + 1])
        ts, vs = t[seg], v[seg]
        if vs.size >= 5:
            tops.append(vs.max())
            bottoms.append(vs.min())
        m = (vs >= band_lo) & (vs <= band_hi)
        if m.sum() < 5:
            continue
        s, b, tm = _robust_line(ts[m], vs[m])
        if s * direction <= 0:
            continue
        tc = tm + (v_ref - b) / s
        if ts[m][0] - 1e-9 <= tc <= ts[m][-1] + 1e-9:
            cross[i] = (tc, s)
    pairs = [(cross[i], cross[i + 1]) for i in cross if i + 1 in cross]
    volts_per_rev = [0.5 * (a[1] + b[1]) * (b[0] - a[0]) for a, b in pairs]
    if not volts_per_rev:
        raise ValueError(
            "need one full revolution (two tracks crossing mid-range between wraps) to time the potentiometer"
        )
    vpr = float(np.median(volts_per_rev))
    kp = 360.0 / abs(vpr)
    steady = np.asarray(volts_per_rev[1:])  # the first revolution is often still speeding up
    rel_se = (
        math.sqrt(math.pi / 2) * float(np.std(steady, ddof=1)) / math.sqrt(steady.size) / abs(vpr)  # a median's
        if steady.size > 2
        else float("nan")
    )
    lag = float("nan")
    later = sorted(i for i in cross if i >= 1)
    if 0.02 < float(v[0] - lo) / span < 0.98 and len(later) >= 2:
        # steady asymptote: crossing times t_c(i) = t_c0 + i T fitted on tracks after the first (start-up)
        _, tc0 = np.polyfit(np.array(later, float), np.array([cross[i][0] for i in later]), 1)
        slope = float(np.median([cross[i][1] for i in later]))
        lag = float(tc0 + (v[0] - v_ref) / slope - t[0])
    v_max = float(np.median(tops))
    v_min = float(np.median(bottoms))
    return PotCalibration(
        Kp=kp,
        Kp_span=kp_from_wrap_voltages(v_max, v_min),
        v_max=v_max,
        v_min=v_min,
        deadband_deg=360.0 - kp * (v_max - v_min),
        n_wraps=int(jumps.size),
        lag_s=lag,
        rel_se=rel_se,
    )


# --- strain gauge


@dataclass(frozen=True)
class GaugeCalibration:
    """Least-squares line angle = Ke (volts - offset_v): Ke [deg/V], offset_v [V] (voltage at zero angle),
    r2 the coefficient of determination, residual_std [deg] = sqrt(SSR / (n - 2))."""

    Ke: float
    offset_v: float
    r2: float
    residual_std: float


def _sensor_line(angle_deg: Any, volts: Any) -> tuple[float, float, float, float]:
    """Least-squares line angle = gain (volts - offset_v) of a sensor's calibration table, lab 1's regression
    of angle [deg] on voltage [V] with intercept: (gain [deg/V], offset_v [V], r2, residual_std [deg])."""
    x = as_signal("volts", volts)
    y = as_signal("angle_deg", angle_deg, x.size)
    if x.size < 3:
        raise ValueError(f"need at least 3 calibration points, got {x.size}")
    if np.ptp(x) == 0:
        raise ValueError("all calibration voltages are equal: the gain is undefined")
    A = np.column_stack([x, np.ones_like(x)])
    (k, c), *_ = np.linalg.lstsq(A, y, rcond=None)
    r = y - (k * x + c)
    ssr = float(r @ r)
    sst = float(((y - y.mean()) ** 2).sum())
    if k == 0:
        raise ValueError("calibration angle does not depend on voltage (zero gain)")
    return float(k), float(-c / k), 1.0 - ssr / sst if sst > 0 else 1.0, math.sqrt(ssr / (x.size - 2))


def ke_from_comb(angle_deg: Any, volts: Any) -> GaugeCalibration:
    """Ke [deg/V] and the gauge offset [V] by least squares of comb angle [deg] on gauge voltage [V]."""
    return GaugeCalibration(*_sensor_line(angle_deg, volts))


def kp_from_table(angle_deg: Any, volts: Any) -> float:
    """Kp [deg/V] as the least-squares slope of angle [deg] on pot voltage [V] (second lab's table 1)."""
    return _sensor_line(angle_deg, volts)[0]


def gauge_volts(alpha_deg: Any, gain: float, offset_v: float, cubic: float = 0.0) -> np.ndarray:
    """The strain gauge's static map, as the DAQ FMU models it: volts [V] = offset_v + alpha / gain (1 + cubic
    (alpha / 10 deg)^2) for a deflection ``alpha_deg`` [deg], ``gain`` [deg/V] (Ke of a linear gauge), ``cubic``
    the relative cubic term at 10 deg (the bridge's zero error outside its nonlinearity)."""
    a = np.asarray(alpha_deg, dtype=float)
    return offset_v + a / gain * (1.0 + cubic * (a / 10.0) ** 2)


def daq_calibration(
    pot_gain: float,
    pot_offset_v: float,
    gauge_gain: float,
    gauge_offset_v: float,
    gauge_cubic: float = 0.0,
    comb_angles: np.ndarray | None = None,
) -> Calibration:
    """The calibration of a simulated DAQ with these parameters, made the way the real rig's is: Kp and the pot
    offset are the DAQ's; Ke and the gauge offset are the least-squares line (:func:`ke_from_comb`) through the
    gauge's static map (:func:`gauge_volts`) over the comb angles [deg] the real gauge was calibrated on, so that
    a gauge nonlinearity is calibrated alike on both sides; without a comb (fewer than 3 angles) or with a linear
    gauge, the DAQ's gauge gain and offset."""
    ke, offset = gauge_gain, gauge_offset_v
    if comb_angles is not None and comb_angles.size >= 3 and gauge_cubic != 0.0:
        g = ke_from_comb(comb_angles, gauge_volts(comb_angles, gauge_gain, gauge_offset_v, gauge_cubic))
        ke, offset = g.Ke, g.offset_v
    return Calibration(Kp=pot_gain, Ke=ke, gauge_offset_v=offset, pot_offset_v=pot_offset_v)


def comb_table(
    t: Any, alpha_v: Any, alpha_true_deg: Any, holds: list[tuple[float, float]]
) -> tuple[np.ndarray, np.ndarray]:
    """Comb table (angle [deg], gauge voltage [V]) from a record of comb deflections held still.

    Each hold (t_start, t_end) [s] is averaged from 0.5 s to 2 s after its start (clipped to t_end), as in
    lab 1. ``alpha_true_deg`` is either one angle per hold (e.g. -atan(l/D)) or a time series like
    ``alpha_v``, averaged over the same windows.
    """
    t = time_axis(t)
    av = as_signal("alpha_v", alpha_v, t.size)
    truth = as_signal("alpha_true_deg", alpha_true_deg)
    per_sample = truth.size == t.size
    if not per_sample and truth.size != len(holds):
        raise ValueError(
            f"alpha_true_deg needs a value per hold ({len(holds)}) or per sample ({t.size}), got {truth.size}"
        )
    if len(holds) == 0:
        raise ValueError("no comb holds given")
    angles, volts = [], []
    for i, m in enumerate(_hold_masks(t, holds)):
        volts.append(float(av[m].mean()))
        angles.append(float(truth[m].mean()) if per_sample else float(truth[i]))
    return np.array(angles), np.array(volts)


def _hold_masks(t: np.ndarray, holds: list[tuple[float, float]]) -> list[np.ndarray]:
    """The samples of each comb hold (t_start, t_end) [s] that are averaged: 0.5 s to 2 s after its start."""
    out = []
    for i, hold in enumerate(holds):
        try:
            t_start, t_end = (float(h) for h in hold)
        except (TypeError, ValueError):
            raise ValueError(f"hold {i} must be a pair (t_start, t_end) in seconds, got {hold!r}") from None
        if not t_end > t_start:
            raise ValueError(f"hold {i} ends before it starts: ({t_start}, {t_end})")
        m = (t >= t_start + 0.5) & (t <= min(t_start + 2.0, t_end))
        if not m.any():
            raise ValueError(f"hold {i} ({t_start}, {t_end}) s has no samples 0.5 s to 2 s after its start")
        out.append(m)
    return out


def hold_sem(t: Any, alpha_v: Any, holds: list[tuple[float, float]]) -> np.ndarray:
    """The standard error [V] of each comb hold's mean voltage (the windows :func:`comb_table` averages)."""
    t = time_axis(t)
    av = as_signal("alpha_v", alpha_v, t.size)
    return np.array([av[m].std(ddof=1) / math.sqrt(m.sum()) if m.sum() > 1 else 0.0 for m in _hold_masks(t, holds)])


def ke_rel_se(angles_deg: Any, volts: Any, sem_v: Any) -> float:
    """Ke's relative standard error from a comb table (angle [deg], mean voltage [V] and its standard error [V] per
    hold): the larger of the line's (its residuals, n - 2 of freedom) and what the holds' noise leaves on the slope
    (many samples of freedom); NaN from fewer than 3 angles."""
    a, v, sem = (np.asarray(x, dtype=float) for x in (angles_deg, volts, sem_v))
    saa = float(np.sum((a - a.mean()) ** 2))
    if a.size < 3 or saa <= 0:
        return float("nan")
    slope, icpt = np.polyfit(a, v, 1)  # volts on angle: the angles are set, the volts measured
    resid = v - (slope * a + icpt)
    sigma = max(math.sqrt(float(resid @ resid) / (a.size - 2)), float(np.sqrt(np.mean(sem**2))))
    return sigma / math.sqrt(saa) / abs(float(slope))


# --- dead zone


@dataclass(frozen=True)
class DeadZone:
    """Dead-zone thresholds [V] from slow command ramps: v_up for the positive ramp, v_down (as |u|) for the
    negative one (None when absent), v_th their mean; t_up, t_down the motion onset times [s]."""

    v_th: float
    v_up: float | None = None
    v_down: float | None = None
    t_up: float | None = None
    t_down: float | None = None


def _runs(sign: np.ndarray) -> list[tuple[int, int]]:
    """Maximal runs [start, stop) of equal nonzero sign."""
    out = []
    edges = np.flatnonzero(np.diff(sign) != 0) + 1
    starts = np.concatenate(([0], edges))
    stops = np.concatenate((edges, [sign.size]))
    for a, b in zip(starts, stops, strict=True):
        if sign[a] != 0:
            out.append((int(a), int(b)))
    return out


def _hinge_ssr(tt: np.ndarray, d: np.ndarray, t0: np.ndarray) -> np.ndarray:
    """SSR of the least-squares fit d ~ b + c max(t - t0, 0)^2 for each candidate t0 (c > 0 required)."""
    x = np.maximum(tt[None, :] - t0[:, None], 0.0) ** 2
    n = tt.size
    sx, sxx = x.sum(1), (x * x).sum(1)
    sd, sxd, sdd = d.sum(), x @ d, float(d @ d)
    det = n * sxx - sx * sx
    with np.errstate(divide="ignore", invalid="ignore"):
        c = (n * sxd - sx * sd) / det
        b = (sd - c * sx) / n
        ssr = sdd - b * sd - c * sxd
    return np.where((det > 0) & (c > 0), ssr, np.inf)


def _onset(t: np.ndarray, th: np.ndarray, sgn: float) -> float | None:
    """Motion onset time [s] in one ramp run (motor at rest at its start), or None if it never moves."""
    d = sgn * (th - th[0])
    head = max(10, d.size // 10)
    base = float(np.median(d[:head]))
    d = d - base
    steps = np.abs(np.diff(th))
    q = float(steps[steps > 0].min()) if np.any(steps > 0) else 0.0
    dd = np.diff(d[:head])
    sigma = 1.4826 * float(np.median(np.abs(dd - np.median(dd)))) / math.sqrt(2.0) if dd.size else 0.0
    band = max(5.0 * sigma, 3.0 * q, 1e-9)
    above = d > band
    hold = 5
    run_ok = np.convolve(above.astype(int), np.ones(hold, dtype=int), "valid") == hold
    hits = np.flatnonzero(run_ok)
    if hits.size == 0:
        return None
    k_exit = int(hits[0])
    far = np.flatnonzero(d[k_exit:] > 20.0 * band)
    k_hi = k_exit + int(far[0]) + 1 if far.size else d.size
    tt, dw = t[:k_hi], d[:k_hi]
    cand = np.linspace(t[0], t[k_exit], min(400, k_exit + 1))
    ssr = _hinge_ssr(tt, dw, cand)
    j = int(np.argmin(ssr))
    if not math.isfinite(float(ssr[j])):
        return None
    step = cand[1] - cand[0] if cand.size > 1 else t[1] - t[0]
    lo, hi = max(t[0], cand[j] - 2 * step), min(t[k_exit], cand[j] + 2 * step)
    if hi <= lo:
        return float(cand[j])
    res = minimize_scalar(
        lambda x: float(_hinge_ssr(tt, dw, np.array([x]))[0]),
        bounds=(lo, hi),
        method="bounded",
        options={"xatol": 1e-6 * (t[-1] - t[0] + 1.0)},
    )
    return float(res.x) if res.fun <= ssr[j] else float(cand[j])


def dead_zone_estimate(t: Any, u: Any, theta_deg: Any, *, lag_s: float = 0.0) -> DeadZone:
    """Dead-zone threshold [V] from slow command ramps (u [V], shaft angle [deg] at times t [s]).

    Each run of positive (negative) command starting with the motor at rest is used up to its largest |u|.
    Motion onset: the angle must leave a noise band (5 noise sigma or 3 quantisation steps, whichever is
    larger) for 5 samples; then theta ~ b + c max(t - t0, 0)^2 is fitted from the run start until the motion
    reaches 20 bands and t0 is the back-extrapolated onset; the threshold is |u(t0 - lag_s)|. With several
    runs of one sign, the first one that moves is used.

    The onset appears late by the command delay plus the motor's mechanical time constant (a first-order
    speed lag tau shifts the quadratic by tau), so the threshold is over-estimated by slope * lag; pass
    ``lag_s`` [s] (delay + tau, e.g. :attr:`PotCalibration.lag_s` from the pot step) to remove it. Without
    it, 0.05 V/s with tau = 30 ms and a 20 ms delay reads about 0.7 % high.
    """
    lag_s = float(lag_s)
    if not (math.isfinite(lag_s) and lag_s >= 0):
        raise ValueError(f"lag_s must be a finite delay >= 0 s, got {lag_s!r}")
    t = time_axis(t)
    u = as_signal("u", u, t.size)
    th = as_signal("theta_deg", theta_deg, t.size)
    scale = float(np.max(np.abs(u)))
    if scale == 0:
        raise ValueError("the command is zero: no ramp to find the dead zone from")
    sign = np.where(np.abs(u) > 1e-9 * scale, np.sign(u), 0.0)
    found: dict[float, tuple[float, float]] = {}
    for a, b in _runs(sign):
        s = float(sign[a])
        if s in found:
            continue
        stop = a + int(np.argmax(np.abs(u[a:b]))) + 1
        if stop - a < 20 or abs(u[stop - 1]) <= abs(u[a]):
            continue
        t0 = _onset(t[a:stop], th[a:stop], s)
        if t0 is not None:
            found[s] = (abs(float(np.interp(t0 - lag_s, t, u))), t0)
    if not found:
        raise ValueError("no motion onset found: the ramp never moved the shaft out of its noise band")
    return _dead_zone(found.get(1.0), found.get(-1.0))


def dead_zone_merge(*estimates: DeadZone) -> DeadZone:
    """Combine estimates from separate records (e.g. "deadzone_up" and "deadzone_down" experiments): the
    first v_up and the first v_down found; v_th their mean [V]."""
    up = next(((e.v_up, e.t_up) for e in estimates if e.v_up is not None), None)
    down = next(((e.v_down, e.t_down) for e in estimates if e.v_down is not None), None)
    if up is None and down is None:
        raise ValueError("no dead-zone estimate to merge")
    return _dead_zone(up, down)


def _dead_zone(up: tuple[float, float | None] | None, down: tuple[float, float | None] | None) -> DeadZone:
    """DeadZone from the (threshold [V], onset [s]) of the up and the down ramp; v_th their mean."""
    vals = [x[0] for x in (up, down) if x is not None]
    return DeadZone(
        v_th=float(np.mean(vals)),
        v_up=up[0] if up else None,
        v_down=down[0] if down else None,
        t_up=up[1] if up else None,
        t_down=down[1] if down else None,
    )


# --- calibration record


@dataclass
class Calibration:
    """Calibration of one rig: Kp [deg/V], Ke [deg/V], gauge_offset_v [V], pot_offset_v [V], dead_zone_v [V]
    (NaN when not measured) and ``source``, a JSON-serialisable dict of provenance (methods, raw numbers)."""

    Kp: float
    Ke: float
    gauge_offset_v: float = 0.0
    pot_offset_v: float = 0.0
    dead_zone_v: float = float("nan")
    source: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("Kp", "Ke", "gauge_offset_v", "pot_offset_v", "dead_zone_v"):
            val = getattr(self, name)
            try:
                val = float(val)
            except (TypeError, ValueError):
                raise ValueError(f"calibration field {name} must be a number, got {val!r}") from None
            if name != "dead_zone_v" and not math.isfinite(val):
                raise ValueError(f"calibration field {name} must be finite, got {val!r}")
            setattr(self, name, val)
        if self.Kp == 0 or self.Ke == 0:
            raise ValueError(f"calibration gains must be nonzero, got Kp={self.Kp}, Ke={self.Ke}")
        if not isinstance(self.source, dict):
            raise ValueError(f"calibration source must be a dict, got {type(self.source).__name__}")

    @property
    def comb_angles(self) -> np.ndarray | None:
        """The comb angles [deg] the gauge was calibrated on (``source["Ke"]["angles_deg"]``), None without a comb."""
        src = self.source.get("Ke", {})
        ang = src.get("angles_deg") if isinstance(src, dict) else None
        return np.asarray(ang, dtype=float) if ang else None

    def gain_rel_se(self) -> dict[str, float]:
        """The relative standard errors of the sensor gains as this run measured them: theta's (Kp, from the pot
        ramp's revolutions) and alpha's (Ke, from the comb: :func:`ke_rel_se`); 0 where the calibration does not say
        (lab 1's values, imported records)."""
        out = {}
        for channel, gain in (("theta", "Kp"), ("alpha", "Ke")):
            src = self.source.get(gain, {})
            se = src.get("rel_se") if isinstance(src, dict) else None
            out[channel] = float(se) if se is not None and math.isfinite(se) else 0.0
        return out

    def to_json(self, path: str | os.PathLike[str]) -> None:
        """Write atomically with sorted keys; floats in shortest round-trip form, NaN (also inside ``source``)
        as null."""
        write_json(Path(path), asdict(self))

    @classmethod
    def from_json(cls, path: str | os.PathLike[str]) -> Calibration:
        """Read a file written by :meth:`to_json`; unknown or missing fields raise ValueError."""
        try:
            d = json.loads(Path(path).read_text(encoding="utf-8"))
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}: not valid JSON ({exc.msg}, line {exc.lineno})") from None
        if not isinstance(d, dict):
            raise ValueError(f"{path}: calibration must be a JSON object")
        names = [f.name for f in fields(cls)]
        unknown = sorted(set(d) - set(names))
        missing = [n for n in ("Kp", "Ke") if n not in d]
        if unknown or missing:
            what = f"unknown field(s) {', '.join(unknown)}" if unknown else f"missing {', '.join(missing)}"
            raise ValueError(f"{path}: {what}; valid fields: {', '.join(names)}")
        if d.get("dead_zone_v", 0.0) is None:
            d["dead_zone_v"] = float("nan")
        return cls(**d)


# --- conversions


def theta_deg(theta_v: Any, cal: Calibration, unwrap: bool = True) -> np.ndarray:
    """Shaft angle [deg] = Kp (theta_v - pot_offset_v); with ``unwrap`` every jump of more than 180 deg
    between samples (a wrap, ~360 deg minus the dead band) is removed by adding +-360 deg."""
    v = as_signal("theta_v", theta_v)
    deg = cal.Kp * (v - cal.pot_offset_v)
    return np.unwrap(deg, period=360.0) if unwrap and deg.size else deg


def alpha_deg(alpha_v: Any, cal: Calibration) -> np.ndarray:
    """Link deflection [deg] = Ke (alpha_v - gauge_offset_v)."""
    return cal.Ke * (as_signal("alpha_v", alpha_v) - cal.gauge_offset_v)


def tip_deg(theta_v: Any, alpha_v: Any, cal: Calibration, unwrap: bool = True) -> np.ndarray:
    """Tip angle y = theta + alpha [deg] from the two sensor voltages [V]."""
    th = theta_deg(theta_v, cal, unwrap)
    al = alpha_deg(alpha_v, cal)
    if th.size != al.size:
        raise ValueError(f"theta_v and alpha_v differ in length: {th.size} vs {al.size}")
    return th + al


# ----------------------------------------------------------------------------------------------- a run directory


def _holds(comb_angle: np.ndarray, t: np.ndarray) -> tuple[list[tuple[float, float]], np.ndarray]:
    """Hold intervals (t_start, t_end) [s] and their comb angles [deg] from a comb_angle column (NaN between)."""
    finite = np.isfinite(comb_angle)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], finite.astype(int), [0]])))
    holds, angles = [], []
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        holds.append((float(t[a]), float(t[b - 1])))
        angles.append(float(comb_angle[a]))
    return holds, np.array(angles)


def _by_signal(experiments: Sequence[ExperimentEntry]) -> tuple[list[str], list[str], list[str]]:
    """Names of the calibration experiments :func:`calibrate` uses: the pot ramp (the first "constant" one), the comb
    (the first "comb" one) and every dead-zone ramp ("ramp"), in the order given (a name given twice counts once,
    with its last entry's signal)."""
    signal = {e.name: e.signal for e in experiments}
    pot = [n for n, s in signal.items() if s == "constant"][:1]
    comb = [n for n, s in signal.items() if s == "comb"][:1]
    ramps = [n for n, s in signal.items() if s == "ramp"]
    return pot, comb, ramps


def calibrate(
    experiments: Sequence[ExperimentEntry], data: Mapping[str, pd.DataFrame | Mapping[str, np.ndarray]]
) -> Calibration:
    """Calibrate the sensors from a run's calibration experiments (their manifest entries) and their data in memory
    (``data[name]``: a dataset as read from a run directory, or a campaign's columns as simulated: t [s], u [V],
    theta_v [V], alpha_v [V], and the comb's comb_angle [deg, NaN between holds]); only the experiments it uses need
    data. Nothing is read or written.

    Kp from the pot ramp through its wraps, Ke by least squares over the comb holds, the dead zone from the slow
    up/down ramps. Missing experiments fall back to lab 1's numbers, and ``source`` says so.
    """

    def col(name: str, column: str) -> np.ndarray:
        return np.asarray(data[name][column], dtype=float)

    pot, comb, ramps = _by_signal(experiments)
    source: dict[str, Any] = {}
    # lab 1's own Kp and Ke stand in when a run has no calibration experiments (imported measurements)
    Kp, Ke, offset, dz, lag = LAB1_CALIBRATION["Kp"], LAB1_CALIBRATION["Ke"], 0.0, math.nan, 0.0
    if pot:
        pc = kp_from_ramp(col(pot[0], "t"), col(pot[0], "theta_v"))
        Kp = pc.Kp
        lag = pc.lag_s if math.isfinite(pc.lag_s) else 0.0
        source["Kp"] = {
            "method": "pot ramp: track slope x wrap period",
            "experiment": pot[0],
            "Kp_span_formula": pc.Kp_span,
            "v_max": pc.v_max,
            "v_min": pc.v_min,
            "n_wraps": pc.n_wraps,
            "lag_s": pc.lag_s,
            "rel_se": pc.rel_se,
        }
    else:
        source["Kp"] = {"method": "lab 1's value (no pot ramp in this run)"}
    if comb:
        t = col(comb[0], "t")
        holds, angles = _holds(col(comb[0], "comb_angle"), t)
        ang, volts = comb_table(t, col(comb[0], "alpha_v"), angles, holds)
        gc = ke_from_comb(ang, volts)
        Ke, offset = gc.Ke, gc.offset_v
        source["Ke"] = {
            "method": "least squares over comb holds (0.5-2 s)",
            "experiment": comb[0],
            "angles_deg": ang.tolist(),
            "volts": volts.tolist(),
            "r2": gc.r2,
            "rel_se": ke_rel_se(ang, volts, hold_sem(t, col(comb[0], "alpha_v"), holds)),
        }
    else:
        source["Ke"] = {"method": "lab 1's value (no comb in this run)"}
    if ramps:
        ests = []
        for n in ramps:
            th = np.unwrap(Kp * col(n, "theta_v"), period=360.0)
            ests.append(dead_zone_estimate(col(n, "t"), col(n, "u"), th, lag_s=lag))
        est = dead_zone_merge(*ests)
        dz = est.v_th
        source["dead_zone_v"] = {
            "method": "onset of motion on slow ramps, corrected by the step lag of the pot ramp",
            "experiments": ramps,
            "v_up": est.v_up,
            "v_down": est.v_down,
            "lag_s": lag,
        }
    return Calibration(Kp=Kp, Ke=Ke, gauge_offset_v=offset, dead_zone_v=dz, source=source)


def calibrate_run(run: Path) -> Calibration:
    """Calibrate the sensors from a run's calibration experiments and write ``calibration.json``.

    Parameters
    ----------
    run : Path
        A run directory with the calibration experiments (pot ramp, comb, dead-zone ramps) in ``data/``.

    Returns
    -------
    Calibration
        Kp [deg/V] from the pot's wraps, Ke [deg/V] by least squares over the comb, the dead zone [V] from the
        slow ramps, the sensor offsets [V], and where each came from.
    """
    run = Path(run)
    exps = Manifest.load(run).entries("calibration")
    pot, comb, ramps = _by_signal(exps)
    data = {n: read_dataset(RunDir(run).dataset(n)) for n in (*pot, *comb, *ramps)}
    cal = calibrate(exps, data)
    cal.to_json(RunDir(run).calibration)
    record_inputs(run, "calibration.json")
    return cal


def load_calibration(run: Path) -> Calibration:
    """``calibration.json`` of a run, calibrating first when it is missing."""
    p = Path(run) / "calibration.json"
    return Calibration.from_json(p) if p.exists() else calibrate_run(run)
