"""Where the sim-to-real gap lies: in time, in frequency (with the FRF against the measured BLA, from
:mod:`harness.diagnosis.frf`), in amplitude, and near events (motion reversals, pot wraps).

The analysis functions are pure: numpy arrays in, JSON-safe dicts (Python floats, ints, str, bool, lists) out.
NaN marks "undefined" (the diagnosis writer turns it into null). The residual is ``e = y_real - y_sim`` in the
unit of y (deg for the shaft or tip angle); its energy over a set of samples is the sum of e^2 there (the
``energy_*`` keys; not the diagnoser's mean squared gap). Times are in s, frequencies in Hz, commands in V.
:func:`where_gap` runs them on every experiment of a diagnosis, re-simulated.

Classifier thresholds are module constants, so the report can quote them:

- amplitude (:func:`by_amplitude`): ``ratio = rel_rms(lowest |u| bin) / rel_rms(highest |u| bin)`` with
  ``rel_rms = rms(e) / rms(u)`` per bin; ``ratio > AMP_SMALL_RATIO`` (2) is "grows at small commands" (dead
  zone / Coulomb friction signature), ``ratio < AMP_LARGE_RATIO`` (0.5) "grows at large commands"
  (saturation signature), otherwise "flat"; fewer than 3 bins with ``AMP_MIN_COUNT`` samples is
  "undetermined".
- amplitude through the plant (:func:`amplitude_curve`, used by :func:`where`): the same ratio on the
  fitted static error curve, but "flat" when its nonlinear part explains less than ``AMP_MIN_EXPLAINED``
  (2 %) of the residual rate's energy beyond a linear model with ``AMP_LAGS`` (2) extra lags.
- events (:func:`summarise_where`): residual energy "concentrates" at an event mask when its enrichment
  (energy share / time share) is at least ``EVENT_ENRICHMENT`` (2) and the mask holds at least
  ``EVENT_MIN_SHARE`` (10 %) of the residual energy.
- nonlinearity (:func:`summarise_where`): odd / even detection lines of a multisine reveal a nonlinearity
  when their level is at least ``NL_DETECT_DB`` (10 dB) above the noise level, or above ``NL_FLOOR_DB``
  (-80 dB re the excited output) when the noise is lower (noise-free simulations).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from scipy.signal import lfilter, savgol_coeffs, savgol_filter, welch

from ..executor import worker_rig
from ..ident.preprocess import as_signal, time_axis
from ..rig.signals import MultisineLines
from .frf import NAN, band_edges, bla, frf_gap, json_float, json_floats, positive, safe_ratio
from .simulation import Setup, simulate

__all__ = [
    "AMP_LAGS",
    "AMP_LARGE_RATIO",
    "AMP_MIN_COUNT",
    "AMP_MIN_EXPLAINED",
    "AMP_SMALL_RATIO",
    "EVENT_ENRICHMENT",
    "EVENT_MIN_SHARE",
    "FLAT",
    "GROWS_LARGE",
    "GROWS_SMALL",
    "NL_DETECT_DB",
    "NL_FLOOR_DB",
    "UNDETERMINED",
    "amplitude_curve",
    "by_amplitude",
    "near_events",
    "residual_by_band",
    "residual_by_window",
    "reversal_mask",
    "summarise_where",
    "where",
    "where_gap",
    "wrap_mask",
]

AMP_SMALL_RATIO = 2.0
AMP_LARGE_RATIO = 0.5
AMP_MIN_COUNT = 20
AMP_LAGS = 2
AMP_MIN_EXPLAINED = 0.02
EVENT_ENRICHMENT = 2.0
EVENT_MIN_SHARE = 0.1
NL_DETECT_DB = 10.0
NL_FLOOR_DB = -80.0
GROWS_SMALL = "grows at small commands"
GROWS_LARGE = "grows at large commands"
FLAT = "flat"
UNDETERMINED = "undetermined"


def _num(x: Any) -> float:
    """Float from a JSON value that may be None."""
    return NAN if x is None else float(x)


# --- time


def residual_by_window(t: np.ndarray, e: np.ndarray, window_s: float, *, top: int = 5) -> dict[str, Any]:
    """Residual RMS and energy share per time window of ``window_s`` s, from ``t[0]``.

    Returns ``start_s`` and ``rms`` (unit of e) and ``share`` (of total sum e^2) per window (the last one may
    be shorter), ``top`` windows by share as {start_s, end_s, share, rms}, and the concentration index
    ``top10_share``: the energy share of the top 10 % of windows (at least one), next to ``top10_uniform``,
    the share that fraction of windows would hold if the residual were spread evenly.
    """
    t = time_axis(t)
    e = as_signal("e", e, t.size)
    w = positive("window_s", window_s)
    idx = np.floor((t - t[0]) / w + 1e-9).astype(np.int64)
    nw = int(idx[-1]) + 1
    energy = np.bincount(idx, weights=e**2, minlength=nw)
    count = np.bincount(idx, minlength=nw)
    filled = count > 0
    rms = np.full(nw, NAN)
    rms[filled] = np.sqrt(energy[filled] / count[filled])
    total = float(energy.sum())
    share = energy / total if total > 0 else np.full(nw, NAN)
    starts = t[0] + w * np.arange(nw)
    k10 = max(1, math.ceil(0.1 * nw))
    order = np.argsort(-energy, kind="stable")
    top_list = [
        {
            "start_s": json_float(starts[i]),
            "end_s": json_float(min(starts[i] + w, t[-1])),
            "share": json_float(share[i]),
            "rms": json_float(rms[i]),
        }
        for i in order[: max(0, int(top))]
    ]
    return {
        "window_s": w,
        "n_windows": nw,
        "start_s": json_floats(starts),
        "rms": json_floats(rms),
        "share": json_floats(share),
        "top": top_list,
        "top10_share": json_float(energy[order[:k10]].sum() / total) if total > 0 else NAN,
        "top10_uniform": json_float(count[order[:k10]].sum() / t.size),
        "rms_total": json_float(math.sqrt(total / t.size)),
    }


def _spans_to_mask(t: np.ndarray, t0: np.ndarray, t1: np.ndarray, width_s: float) -> np.ndarray:
    """Boolean mask of the samples inside any [t0 - width, t1 + width]."""
    mask = np.zeros(t.size, dtype=bool)
    if t0.size == 0:
        return mask
    lo = np.searchsorted(t, t0 - width_s - 1e-12, side="left")
    hi = np.searchsorted(t, t1 + width_s + 1e-12, side="right")
    delta = np.zeros(t.size + 1, dtype=np.int64)
    np.add.at(delta, lo, 1)
    np.add.at(delta, hi, -1)
    return np.cumsum(delta[:-1]) > 0


def _sign_change_spans(x: np.ndarray, thr: float) -> tuple[np.ndarray, np.ndarray]:
    """Sign changes of x with hysteresis: (last index beyond -+thr, first index beyond +-thr) per change."""
    big = np.flatnonzero(np.abs(x) > thr)
    if big.size < 2:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    s = np.sign(x[big])
    flip = np.flatnonzero(s[1:] != s[:-1])
    return big[flip], big[flip + 1]


def _sg_window(Ts: float, n: int) -> int:
    """Savitzky-Golay window: ~0.1 s, odd, at least 5 samples, at most n (odd)."""
    w = max(5, int(round(0.1 / Ts)) | 1)
    if w > n:
        w = n if n % 2 else n - 1
    return w


def _velocity(theta: np.ndarray, Ts: float) -> tuple[np.ndarray, float]:
    """Smoothed derivative [unit/s] (Savitzky-Golay, order 2, ~0.1 s) and its noise std estimate."""
    w = _sg_window(Ts, theta.size)
    if w < 3:
        return np.gradient(theta, Ts), 0.0
    v = savgol_filter(theta, w, 2, deriv=1, delta=Ts, mode="interp")
    # white-noise level of theta from its second difference (var 6 sigma^2 for white noise, ~0 for smooth
    # motion), robustly (MAD), propagated through the derivative filter's coefficients
    d2 = np.diff(theta, 2)
    sigma = 1.4826 * float(np.median(np.abs(d2 - np.median(d2)))) / math.sqrt(6.0) if d2.size else 0.0
    h = savgol_coeffs(w, 2, deriv=1, delta=Ts)
    return v, sigma * float(np.linalg.norm(h))


def reversal_mask(
    t: np.ndarray,
    theta_deg: np.ndarray | None,
    u: np.ndarray | None,
    width_s: float = 0.2,
) -> np.ndarray:
    """Samples within ``width_s`` s of a motion reversal or a command sign change (boolean array).

    Shaft reversals: ``theta_deg`` [deg] is unwrapped (period 360, so pot wraps do not count),
    differentiated by a Savitzky-Golay filter (order 2, ~0.1 s window) and its sign is read with
    hysteresis: only samples with |v| above ``max(4 sigma_v, 0.02 * p95(|v|))`` count, sigma_v being the
    noise std of v estimated from the second difference of theta. A reversal spans from the last sample
    moving one way to the first moving the other way (the stop in between included), widened by ``width_s``
    on each side. Command sign changes: the same hysteresis on ``u`` [V] with threshold ``0.01 max|u|``.
    Either input may be None (not both).
    """
    t = time_axis(t)
    width = positive("width_s", width_s)
    if theta_deg is None and u is None:
        raise ValueError("reversal_mask needs theta_deg or u (or both)")
    Ts = float(np.median(np.diff(t)))
    mask = np.zeros(t.size, dtype=bool)
    if theta_deg is not None:
        theta = np.unwrap(as_signal("theta_deg", theta_deg, t.size), period=360.0)
        v, sigma_v = _velocity(theta, Ts)
        thr = max(4.0 * sigma_v, 0.02 * float(np.percentile(np.abs(v), 95)))
        if thr > 0:
            i0, i1 = _sign_change_spans(v, thr)
            mask |= _spans_to_mask(t, t[i0], t[i1], width)
    if u is not None:
        u = as_signal("u", u, t.size)
        thr = 0.01 * float(np.max(np.abs(u)))
        if thr > 0:
            i0, i1 = _sign_change_spans(u, thr)
            mask |= _spans_to_mask(t, t[i0], t[i1], width)
    return mask


def wrap_mask(t: np.ndarray, theta_v: np.ndarray, width_s: float = 0.2, *, jump_v: float = 0.0) -> np.ndarray:
    """Samples within ``width_s`` s of a potentiometer wrap (boolean array).

    A wrap is a jump of the raw pot voltage ``theta_v`` [V] between consecutive samples larger than ``jump_v``
    [V]; by default (0) half the observed voltage span, and at least 2 V (a wrap jumps across the whole track,
    ~10 V; smooth motion moves far less than 2 V per sample).
    """
    t = time_axis(t)
    v = as_signal("theta_v", theta_v, t.size)
    width = positive("width_s", width_s)
    if not jump_v:
        jump = max(0.5 * float(v.max() - v.min()), 2.0)
    else:
        jump = positive("jump_v", jump_v)
    k = np.flatnonzero(np.abs(np.diff(v)) > jump)
    return _spans_to_mask(t, t[k], t[k + 1], width)


def near_events(t: np.ndarray, e: np.ndarray, mask: np.ndarray) -> dict[str, Any]:
    """Residual energy inside an event mask vs the time the mask covers.

    ``energy_share`` = sum of e^2 inside / total, ``time_share`` = samples inside / all, ``enrichment`` their
    ratio (1: no preference; > 1: the residual concentrates at the events; NaN without events or residual).
    ``n_events`` counts the separate runs of the mask.
    """
    t = time_axis(t)
    e = as_signal("e", e, t.size)
    m = np.asarray(mask)
    if m.shape != t.shape:
        raise ValueError(f"mask has shape {m.shape}, expected {t.shape} (one flag per sample)")
    m = m.astype(bool)
    e2 = e**2
    energy_in, energy_total = float(e2[m].sum()), float(e2.sum())
    n_in = int(m.sum())
    energy_share = safe_ratio(energy_in, energy_total)
    time_share = n_in / t.size
    runs = int(np.count_nonzero(np.diff(m.astype(np.int8)) == 1) + int(m[0]))
    return {
        "n_events": runs,
        "energy_share": energy_share,
        "time_share": float(time_share),
        "enrichment": safe_ratio(energy_share, time_share) if n_in else NAN,
        "energy_in": energy_in,
        "energy_total": energy_total,
        "samples_in": n_in,
        "samples_total": int(t.size),
    }


# --- frequency


def _welch(x: np.ndarray, Ts: float) -> tuple[np.ndarray, np.ndarray]:
    """One-sided PSD [unit^2/Hz]; Hann segments of ~10 s (power of 2, at most the record), no detrend."""
    nper = min(x.size, 1 << max(3, math.ceil(math.log2(10.0 / Ts))))
    return welch(x, fs=1.0 / Ts, window="hann", nperseg=nper, detrend=False, scaling="density")


def residual_by_band(
    e: np.ndarray, Ts: float, bands_hz: Sequence[float] | None = None, *, y: np.ndarray | None = None
) -> dict[str, Any]:
    """Residual power per frequency band (Welch PSD integrated over the band, DC counted in the lowest band).

    ``bands``: {lo_hz, hi_hz, power [unit^2], share, ratio}, ``ratio`` = residual / signal power in the band
    when ``y`` (e.g. the measured output) is given. ``dominant``: the band with the largest share.
    """
    e = as_signal("e", e)
    Ts = positive("Ts", Ts)
    edges = band_edges(Ts, bands_hz)
    f, pe = _welch(e, Ts)
    py = _welch(as_signal("y", y, e.size), Ts)[1] if y is not None else None
    df = float(f[1] - f[0]) if f.size > 1 else 1.0 / Ts
    which = np.searchsorted(edges, f, side="right") - 1
    which[f >= edges[-1]] = edges.size - 2  # Nyquist belongs to the last band
    inside = (f >= edges[0]) & (f <= edges[-1])
    nb = edges.size - 1
    pow_e = np.bincount(which[inside], weights=pe[inside], minlength=nb)[:nb] * df
    pow_y = np.bincount(which[inside], weights=py[inside], minlength=nb)[:nb] * df if py is not None else None
    total = float(pow_e.sum())
    bands = []
    for b in range(nb):
        bands.append(
            {
                "lo_hz": json_float(edges[b]),
                "hi_hz": json_float(edges[b + 1]),
                "power": json_float(pow_e[b]),
                "share": safe_ratio(pow_e[b], total),
                "ratio": safe_ratio(pow_e[b], pow_y[b]) if pow_y is not None else NAN,
            }
        )
    best = int(np.argmax(pow_e)) if total > 0 else 0
    return {
        "bands": bands,
        "dominant": {
            "lo_hz": bands[best]["lo_hz"],
            "hi_hz": bands[best]["hi_hz"],
            "share": bands[best]["share"],
        },
        "total_power": total,
        "df_hz": df,
        "n": int(e.size),
        "Ts": Ts,
    }


# --- amplitude


def _classify(rel_low: float, rel_high: float) -> tuple[float, str]:
    """(ratio, trend) from the relative error at the smallest and the largest commands.

    ratio = rel_low / rel_high (NaN when undefined or infinite; the trend is still decided)."""
    if not (math.isfinite(rel_low) and math.isfinite(rel_high)):
        return NAN, UNDETERMINED
    if rel_high > 0:
        ratio = rel_low / rel_high
    elif rel_low > 0:
        return NAN, GROWS_SMALL  # zero error at large commands
    else:
        return NAN, FLAT  # no error at all
    if ratio > AMP_SMALL_RATIO:
        return ratio, GROWS_SMALL
    if ratio < AMP_LARGE_RATIO:
        return ratio, GROWS_LARGE
    return ratio, FLAT


def by_amplitude(
    u: np.ndarray, e: np.ndarray, bins: Sequence[float] | None = None, *, n_bins: int = 5
) -> dict[str, Any]:
    """Residual RMS against the command level |u| [V], and the amplitude signature.

    ``bins``: edges of |u| in V (default: ``n_bins`` quantile bins of |u|; coincident quantiles merge, so a
    +-A PRBS or square wave gives one bin). Per bin: {lo_v, hi_v, n, u_rms [V], e_rms [unit of e],
    rel_rms = e_rms / u_rms}. ``ratio`` = rel_rms of the lowest over the highest populated bin (bins with
    at least ``AMP_MIN_COUNT`` samples); ``trend`` is GROWS_SMALL if ratio > AMP_SMALL_RATIO, GROWS_LARGE if
    ratio < AMP_LARGE_RATIO, FLAT otherwise, UNDETERMINED with fewer than 3 populated bins. ``loglog_slope``:
    slope of log e_rms on log u_rms over populated bins (1: proportional error, < 1: saturating like a dead
    zone, > 1: growing like clipping). Relative, not absolute, RMS is classified: a dead zone's residual
    u - dz(u) is capped at the threshold: its absolute RMS still rises with |u| while its relative one falls.
    Noise in e inflates rel_rms at small |u|, so a noisy, otherwise exact model can read GROWS_SMALL.
    """
    u = as_signal("u", u)
    e = as_signal("e", e, u.size)
    a = np.abs(u)
    if bins is None:
        if isinstance(n_bins, bool) or not isinstance(n_bins, (int, np.integer)) or n_bins < 1:
            raise ValueError(f"n_bins must be a positive integer, got {n_bins!r}")
        edges = np.unique(np.quantile(a, np.linspace(0.0, 1.0, int(n_bins) + 1)))
        if edges.size < 2:
            edges = np.array([edges[0], edges[0]])
    else:
        edges = as_signal("bins", bins)
        if edges.size < 2 or np.any(np.diff(edges) <= 0) or edges[0] < 0:
            raise ValueError(f"bins must be >= 2 increasing |u| edges >= 0 V, got {list(edges)}")
    nb = edges.size - 1
    which = np.clip(np.searchsorted(edges, a, side="right") - 1, 0, nb - 1)
    inside = (a >= edges[0]) & (a <= edges[-1])
    rows = []
    for b in range(nb):
        sel = inside & (which == b)
        n = int(sel.sum())
        u_rms = math.sqrt(float(np.mean(u[sel] ** 2))) if n else NAN
        e_rms = math.sqrt(float(np.mean(e[sel] ** 2))) if n else NAN
        rows.append(
            {
                "lo_v": json_float(edges[b]),
                "hi_v": json_float(edges[b + 1]),
                "n": n,
                "u_rms": json_float(u_rms),
                "e_rms": json_float(e_rms),
                "rel_rms": safe_ratio(e_rms, u_rms) if n else NAN,
            }
        )
    pop = [r for r in rows if r["n"] >= AMP_MIN_COUNT and math.isfinite(r["rel_rms"])]
    ratio, slope, trend = NAN, NAN, UNDETERMINED
    if len(pop) >= 3:
        ratio, trend = _classify(pop[0]["rel_rms"], pop[-1]["rel_rms"])
        ok = [r for r in pop if r["e_rms"] > 0 and r["u_rms"] > 0]
        if len(ok) >= 2:
            lu, le = np.log([r["u_rms"] for r in ok]), np.log([r["e_rms"] for r in ok])
            slope = float(np.polyfit(lu, le, 1)[0])
    return {
        "bins": rows,
        "ratio": ratio,
        "loglog_slope": json_float(slope),
        "trend": trend,
        "thresholds": {"small": AMP_SMALL_RATIO, "large": AMP_LARGE_RATIO, "min_count": AMP_MIN_COUNT},
    }


def _arx_fit(u: np.ndarray, dy: np.ndarray, order: int) -> tuple[np.ndarray, np.ndarray, float]:
    """LS ARX(order, order + 1, nk = 0) from u to dy: (a, b, fit), fit = 1 - ||resid|| / ||dy||."""
    na, nb = order, order + 1
    rows = np.arange(max(na, nb - 1), u.size)
    phi = np.column_stack([-dy[rows - i] for i in range(1, na + 1)] + [u[rows - j] for j in range(nb)])
    theta, *_ = np.linalg.lstsq(phi, dy[rows], rcond=None)
    ref = float(np.linalg.norm(dy[rows]))
    fit = 1.0 - float(np.linalg.norm(dy[rows] - phi @ theta)) / ref if ref > 0 else NAN
    return np.r_[1.0, theta[:na]], theta[na:], fit


def amplitude_curve(
    u: np.ndarray, e: np.ndarray, y_sim: np.ndarray, *, n_knots: int = 6, order: int = 8
) -> dict[str, Any]:
    """Static error curve g(|u|) [V] behind a residual seen through the plant's dynamics, and its trend.

    Model (Hammerstein, with the simulation's own dynamics): e = F g(u) + sum_i c_i F u(t - i), i <= AMP_LAGS,
    g odd and piecewise linear in |u| with g(0) = 0 and ``n_knots`` knots evenly spaced up to the 99th
    percentile of |u| (linear beyond); the lag terms absorb linear dynamic mismatch (a delay). F is an
    ARX(order, order + 1, nk = 0) least-squares fit from u to the first difference of ``y_sim`` (exact for a
    noise-free linear simulation of that order). The first difference of e is regressed on F applied to the
    bases: one linear least-squares problem. ``g_v`` is g at the knots (the command error that explains the
    residual: a dead zone d gives |g| = |u| below d and d above, clipping at L gives 0 below L and |u| - L
    above), ``rel`` = |g| / knot, ``ratio`` = rel at the lowest knot / rel at the highest, classified with
    the thresholds of :func:`by_amplitude`. ``nl_explained``: share of the residual rate's energy the
    nonlinear part of g explains beyond the linear model (F u and its lags; ``linear_explained``); below
    AMP_MIN_EXPLAINED the trend is FLAT (the error is proportional to the command, or not static). Binning e
    by |u| directly would let the plant's lag smear large-command errors into small-command samples.
    ``trend`` is UNDETERMINED when a knot interval holds fewer than AMP_MIN_COUNT samples (a +-A PRBS or
    square wave), the simulated output does not move, or the ARX fit is unstable or poor (fit < 0.9).
    """
    u = as_signal("u", u)
    e = as_signal("e", e, u.size)
    ys = as_signal("y_sim", y_sim, u.size)
    out: dict[str, Any] = {
        "method": "hammerstein",
        "knots_v": [],
        "g_v": [],
        "rel": [],
        "ratio": NAN,
        "trend": UNDETERMINED,
        "arx_fit": NAN,
        "thresholds": {"small": AMP_SMALL_RATIO, "large": AMP_LARGE_RATIO},
    }
    if isinstance(n_knots, bool) or not isinstance(n_knots, (int, np.integer)) or n_knots < 1:
        raise ValueError(f"n_knots must be a positive integer, got {n_knots!r}")
    order = int(order)
    if order < 1 or u.size < 10 * (2 * order + 1 + n_knots):
        return out
    a_abs = np.abs(u)
    grid = np.linspace(0.0, float(np.quantile(a_abs, 0.99)), int(n_knots) + 1)
    knots = grid[1:]
    counts = np.histogram(a_abs, bins=grid)[0] if grid[-1] > 0 else np.zeros(0)
    dy = np.diff(ys, prepend=ys[0])
    if knots.size < 3 or counts.size == 0 or counts.min() < AMP_MIN_COUNT or not np.any(dy):
        return out
    a, b, fit = _arx_fit(u, dy, order)
    out["arx_fit"] = json_float(fit)
    if not (math.isfinite(fit) and fit >= 0.9) or np.max(np.abs(np.roots(a))) >= 1.0:
        return out
    # tent functions of |u| on the grid 0, knots; the tent at 0 is left out (g(0) = 0); beyond the last knot
    # its tent is extended linearly
    beyond = np.clip((a_abs - grid[-1]) / (grid[-1] - grid[-2]), 0.0, None)
    basis = []
    for j in range(1, grid.size):
        unit = np.zeros(grid.size)
        unit[j] = 1.0
        tent = np.interp(a_abs, grid, unit) + (unit[-1] - unit[-2]) * beyond
        basis.append(lfilter(b, a, np.sign(u) * tent))
    de = np.diff(e, prepend=e[0])
    fu = lfilter(b, a, u)
    lags = [np.r_[np.zeros(i), fu[:-i]] for i in range(1, AMP_LAGS + 1)]
    full = np.column_stack(basis + lags)
    coef, *_ = np.linalg.lstsq(full, de, rcond=None)
    lin = np.column_stack([fu, *lags])
    cl, *_ = np.linalg.lstsq(lin, de, rcond=None)
    energy = float(de @ de)
    ssr_full = float(np.sum((de - full @ coef) ** 2))
    ssr_lin = float(np.sum((de - lin @ cl) ** 2))
    explained = (ssr_lin - ssr_full) / energy if energy > 0 else NAN
    g = coef[: knots.size]
    rel = np.abs(g) / knots
    out.update(knots_v=json_floats(knots), g_v=json_floats(g), rel=json_floats(rel), nl_explained=json_float(explained))
    out["linear_explained"] = json_float(1.0 - ssr_lin / energy) if energy > 0 else NAN
    ratio, trend = _classify(float(rel[0]), float(rel[-1]))
    if not (math.isfinite(explained) and explained >= AMP_MIN_EXPLAINED):
        trend = FLAT
    out.update(ratio=ratio, trend=trend)
    return out


# --- one experiment, and pooled


def _rate(x: np.ndarray, Ts: float) -> np.ndarray:
    """First difference / Ts [unit/s], 0 at the first sample (the integrator removed, no smoothing)."""
    return np.diff(x, prepend=x[0]) / Ts


def where(
    t: np.ndarray,
    u: np.ndarray,
    y_real: np.ndarray,
    y_sim: np.ndarray,
    Ts: float,
    *,
    theta_v: np.ndarray | None = None,
    theta_deg: np.ndarray | None = None,
    window_s: float | None = None,
    width_s: float = 0.2,
    period_samples: int | None = None,
    lines: MultisineLines | None = None,
    domain: str = "rate",
) -> dict[str, Any]:
    """Localise the residual ``e = y_real - y_sim`` of one experiment in time, frequency and amplitude.

    ``domain="rate"`` (default) analyses the residual's rate r = (e[k] - e[k-1]) / Ts [unit/s] and the rate
    of y: the plant integrates, so an angle residual is dominated by its accumulated drift, which hides
    where it was made; ``"angle"`` analyses e itself. With x = r or e:
    ``time``: :func:`residual_by_window` of x (``window_s`` default: duration / 40, at least 10 samples).
    ``frequency``: :func:`residual_by_band` of x, with the measured y (or its rate) as the signal; with
    ``period_samples`` and ``lines`` (a multisine experiment) also ``bla`` (the measured BLA of u -> y or
    its rate, as dict) and ``frf`` (:func:`frf_gap` of the simulation's BLA on the same lines).
    ``amplitude``: :func:`amplitude_curve` (the static command error behind e, through the simulation's
    dynamics), with ``binned``: :func:`by_amplitude` of the rate residual against |u|, for display.
    ``events``: :func:`near_events` of x at reversals (:func:`reversal_mask` of theta_deg, default
    y_real, and u) and at pot wraps (:func:`wrap_mask`, only with theta_v), both ``width_s`` wide.
    ``rms``: RMS of e [unit]; ``rms_rate``: RMS of r [unit/s].
    """
    t = time_axis(t)
    n = t.size
    u = as_signal("u", u, n)
    yr = as_signal("y_real", y_real, n)
    ys = as_signal("y_sim", y_sim, n)
    Ts = positive("Ts", Ts)
    if domain not in ("rate", "angle"):
        raise ValueError(f"unknown residual domain {domain!r}; valid: rate, angle")
    if (period_samples is None) != (lines is None):
        raise ValueError("give both period_samples and lines for the BLA, or neither")
    e = yr - ys
    r = _rate(e, Ts)
    x, xr, xs = (r, _rate(yr, Ts), _rate(ys, Ts)) if domain == "rate" else (e, yr, ys)
    if window_s is None:
        window_s = max((t[-1] - t[0] + Ts) / 40.0, 10.0 * Ts)
    freq = residual_by_band(x, Ts, y=xr)
    if lines is not None and period_samples:
        b_real = bla(u, xr, period_samples, lines)
        b_sim = bla(u, xs, period_samples, lines)
        freq["bla"] = b_real.to_dict()
        freq["frf"] = frf_gap(b_real, b_sim.G)
    amp = amplitude_curve(u, e, ys)
    amp["binned"] = by_amplitude(u, r)
    rev = reversal_mask(t, yr if theta_deg is None else theta_deg, u, width_s)
    events: dict[str, Any] = {"reversals": near_events(t, x, rev)}
    if theta_v is not None:
        events["wraps"] = near_events(t, x, wrap_mask(t, theta_v, width_s))
    return {
        "domain": domain,
        "rms": json_float(math.sqrt(float(np.mean(e**2)))),
        "rms_rate": json_float(math.sqrt(float(np.mean(r**2)))),
        "time": residual_by_window(t, x, window_s),
        "frequency": freq,
        "amplitude": amp,
        "events": events,
    }


def _pool_events(per: Mapping[str, Mapping[str, Any]], key: str) -> dict[str, Any]:
    e_in = e_tot = 0.0
    s_in = s_tot = n_ev = 0
    for d in per.values():
        ev = (d.get("events") or {}).get(key)
        if not ev:
            continue
        e_in += _num(ev.get("energy_in"))
        e_tot += _num(ev.get("energy_total"))
        s_in += int(ev.get("samples_in") or 0)
        s_tot += int(ev.get("samples_total") or 0)
        n_ev += int(ev.get("n_events") or 0)
    if s_tot == 0:
        return {
            "n_events": 0,
            "energy_share": NAN,
            "time_share": NAN,
            "enrichment": NAN,
            "concentrates": False,
        }
    es, ts = safe_ratio(e_in, e_tot), s_in / s_tot
    enr = safe_ratio(es, ts) if s_in else NAN
    conc = bool(math.isfinite(enr) and enr >= EVENT_ENRICHMENT and es >= EVENT_MIN_SHARE)
    return {
        "n_events": n_ev,
        "energy_share": es,
        "time_share": float(ts),
        "enrichment": enr,
        "concentrates": conc,
    }


def summarise_where(per_experiment: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """Pool :func:`where` results over experiments: band, amplitude regime, events, and a one-line headline.

    Band shares pool residual energy (band power x samples); the amplitude regime is the majority trend among
    experiments whose trend is determined (ties and none: UNDETERMINED); events pool energy and samples
    inside the masks (concentrates: enrichment >= EVENT_ENRICHMENT and energy share >= EVENT_MIN_SHARE);
    ``nonlinearity`` holds the highest odd / even detection-line levels over multisine experiments, flagged
    when NL_DETECT_DB above that experiment's noise level (or above NL_FLOOR_DB, whichever is higher).
    """
    if not isinstance(per_experiment, Mapping) or not per_experiment:
        raise ValueError("summarise_where needs a non-empty dict of experiment name -> where() result")
    # frequency
    pooled: dict[tuple[float, float], float] = {}
    for d in per_experiment.values():
        fr = d.get("frequency") or {}
        n = int(fr.get("n") or 0)
        for b in fr.get("bands") or []:
            k = (round(_num(b["lo_hz"]), 6), round(_num(b["hi_hz"]), 6))
            p = _num(b.get("power"))
            if math.isfinite(p):
                pooled[k] = pooled.get(k, 0.0) + p * n
    total = sum(pooled.values())
    bands = [{"lo_hz": k[0], "hi_hz": k[1], "share": safe_ratio(v, total)} for k, v in sorted(pooled.items())]
    dom = max(bands, key=lambda b: b["share"] if math.isfinite(b["share"]) else -1.0) if bands else None
    # amplitude
    votes: dict[str, int] = {}
    ratios = []
    for d in per_experiment.values():
        am = d.get("amplitude") or {}
        tr = am.get("trend", UNDETERMINED)
        votes[tr] = votes.get(tr, 0) + 1
        r = _num(am.get("ratio"))
        if tr != UNDETERMINED and math.isfinite(r):
            ratios.append(r)
    decided = {k: v for k, v in votes.items() if k != UNDETERMINED}
    regime = UNDETERMINED
    if decided:
        best = max(decided.values())
        winners = [k for k, v in decided.items() if v == best]
        regime = winners[0] if len(winners) == 1 else UNDETERMINED
    # time
    conc = [_num((d.get("time") or {}).get("top10_share")) for d in per_experiment.values()]
    conc = [c for c in conc if math.isfinite(c)]
    worst: dict[str, Any] | None = None
    for name, d in per_experiment.items():
        tops = (d.get("time") or {}).get("top") or []
        if tops and math.isfinite(_num(tops[0].get("share"))):
            if worst is None or _num(tops[0]["share"]) > worst["share"]:
                worst = {"experiment": str(name), **{k: _num(v) for k, v in tops[0].items()}}
    # FRF, when multisine experiments were analysed
    frf_n = frf_x = 0
    for d in per_experiment.values():
        fg = (d.get("frequency") or {}).get("frf")
        if fg:
            frf_n += int(fg.get("n_lines") or 0)
            frf_x += int(fg.get("n_exceed") or 0)
    # nonlinear distortion at the multisine detection lines: the strongest experiment
    nl = {"odd_level_db": NAN, "even_level_db": NAN, "noise_level_db": NAN, "odd": False, "even": False}
    for d in per_experiment.values():
        bd = (d.get("frequency") or {}).get("bla")
        if not bd:
            continue
        noise = _num(bd.get("noise_level_db"))
        for kind in ("odd", "even"):
            lev = _num(bd.get(f"{kind}_level_db"))
            if math.isfinite(lev) and not lev <= nl[f"{kind}_level_db"]:
                nl[f"{kind}_level_db"] = lev
            floor = max(noise, NL_FLOOR_DB) if math.isfinite(noise) else NL_FLOOR_DB
            if math.isfinite(lev) and lev - floor >= NL_DETECT_DB:
                nl[kind] = True
        if math.isfinite(noise) and not noise >= nl["noise_level_db"]:
            nl["noise_level_db"] = noise
    events = {
        "reversals": _pool_events(per_experiment, "reversals"),
        "wraps": _pool_events(per_experiment, "wraps"),
    }
    # headline
    parts = []
    if dom is not None and math.isfinite(dom["share"]):
        band = f"{dom['lo_hz']:g}-{dom['hi_hz']:g} Hz"
        parts.append(f"residual power mostly at {band} ({100 * dom['share']:.0f} %)")
    else:
        parts.append("no residual power")
    sig = {GROWS_SMALL: " (dead zone / friction signature)", GROWS_LARGE: " (saturation signature)"}
    if regime == UNDETERMINED:
        parts.append("amplitude trend undetermined")
    elif regime == FLAT:
        parts.append("no amplitude law (error proportional to the command)")
    else:
        parts.append(f"error {regime}{sig.get(regime, '')}")
    nl_names = {"odd": "odd nonlinearity (friction, cubic terms)", "even": "even nonlinearity (asymmetry)"}
    for kind, what in nl_names.items():
        if nl[kind]:
            parts.append(f"{what} at the multisine's {kind} lines ({nl[f'{kind}_level_db']:.0f} dB)")
    for key, label in (("reversals", "motion reversals"), ("wraps", "pot wraps")):
        ev = events[key]
        if ev["concentrates"]:
            parts.append(
                f"concentrated at {label} ({100 * ev['energy_share']:.0f} % of energy in "
                f"{100 * ev['time_share']:.0f} % of time, {ev['enrichment']:.1f}x)"
            )
    if frf_n:
        parts.append(f"FRF outside the BLA's 2-sigma band at {frf_x}/{frf_n} lines")
    return {
        "n_experiments": len(per_experiment),
        "frequency": {
            "bands": bands,
            "dominant_band": None if dom is None else f"{dom['lo_hz']:g}-{dom['hi_hz']:g} Hz",
            "dominant_share": NAN if dom is None else dom["share"],
        },
        "amplitude": {
            "regime": regime,
            "votes": votes,
            "median_ratio": json_float(np.median(ratios)) if ratios else NAN,
        },
        "time": {
            "mean_top10_share": json_float(np.mean(conc)) if conc else NAN,
            "worst_window": worst,
        },
        "events": events,
        "nonlinearity": nl,
        "frf": {"n_lines": frf_n, "n_exceed": frf_x, "share_exceed": safe_ratio(frf_x, frf_n)},
        "headline": "; ".join(parts),
    }


# --- every experiment of a diagnosis


def _bridge(y_real: np.ndarray, y_sim: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """``y_sim`` with the residual across invalid samples interpolated linearly from the valid ones around
    them, so that a masked stretch adds neither residual nor a step (which the rate domain would read as an
    event)."""
    if ok.all() or not ok.any():
        return y_sim
    e = y_real - y_sim
    i = np.arange(e.size)
    e[~ok] = np.interp(i[~ok], i[ok], e[ok])
    return y_real - e


def where_gap(setup: Setup, over: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Where the gap of the simulation (with overrides ``over``) lies: per experiment and channel
    (theta in the rate domain, alpha in the angle domain) :func:`where` (for a multisine also the simulated FRF
    against the measured BLA), pooled per channel by :func:`summarise_where`. Samples masked as invalid are
    bridged (:func:`_bridge`)."""
    per: dict[str, dict[str, Any]] = {"theta": {}, "alpha": {}}
    rig = worker_rig(setup.fmus)
    for name, x in setup.experiments.items():
        th, al, on_track = simulate(rig, setup, x, over or {})
        th = _bridge(x.theta, th, x.valid["theta"] & on_track)
        al = _bridge(x.alpha, al, x.valid["alpha"])
        period, lines = (x.period, x.lines) if x.lines is not None else (None, None)
        for ch, yr, ys, dom in (("theta", x.theta, th, "rate"), ("alpha", x.alpha, al, "angle")):
            try:
                per[ch][name] = where(x.t, x.u, yr, ys, x.Ts, theta_v=x.theta_v, theta_deg=x.theta, domain=dom,
                                      period_samples=period, lines=lines)  # fmt: skip
            except ValueError as err:
                per[ch][name] = {"error": str(err)}
    what = "as given" if not over else "with its linear parameters recalibrated"
    out: dict[str, Any] = {
        "definition": f"residual e = y_real - y_sim of the simulation {what}, before effects; "
        "samples in the pot dead band or clipped by the ADC carry no residual"
    }
    for ch in ("theta", "alpha"):
        ok = {k: v for k, v in per[ch].items() if "error" not in v}
        out[ch] = summarise_where(ok) if ok else {}
    out["experiments"] = per
    return out
