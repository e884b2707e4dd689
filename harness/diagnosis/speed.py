"""Where the gap lies in amplitude, read from open-loop square waves: the hub's steady speed per volt.

A voltage square wave drives the hub at a constant speed on each plateau once its transient has passed; on a linear
rig that speed is proportional to the command, so the speed per volt is the same at every amplitude. A dead band (a
dead zone or Coulomb friction at the shaft) takes ``u_db`` off every command, so the speed per volt falls at small
amplitudes; a saturating amplifier caps large commands, so it falls at large ones.

Per record (:func:`plateau_speeds`): the command's plateaus (flat runs between jumps; all but the first, which
starts from rest, and a last one cut short), each one's hub speed [deg/s] as the least-squares slope of the hub
angle over its last third (the transient passed), signed along the command. A record whose speed over the last
third agrees with that over the middle third (within :data:`STEADY_TOL` and three standard errors, median over its
plateaus) is *steady*; others keep their transient, which on a linear rig scales with the command at a given
plateau length, so they are compared only with plateaus of their own length.

Over records (:func:`speed_per_volt`): ``s = k_g (|u| + u_0 sgn(u) - u_db)`` by least squares, one gain ``k_g``
[deg/s/V] per group (all steady plateaus, and each plateau length of the others), a command offset ``u_0`` [V] and
one dead band ``u_db`` [V] with its standard error. Plateaus where the hub stays at rest are left out of the fit
(counted). The trend: :data:`FALLS_SMALL` when ``u_db`` exceeds :data:`Z_SE` standard errors and
:data:`DB_MIN_SHARE` of the smallest amplitude, :data:`FALLS_LARGE` when ``-u_db`` does, :data:`HOLDS` otherwise,
:data:`UNDETERMINED` when no group holds two amplitudes or the fit has no degree of freedom left.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from ..rundir import to_plain
from .experiments import RigExperiment

__all__ = [
    "AMP_TOL",
    "DB_MIN_SHARE",
    "FALLS_LARGE",
    "FALLS_SMALL",
    "FLAT_TOL",
    "HOLDS",
    "JUMP_SHARE",
    "LENGTH_TOL",
    "MIN_WINDOW",
    "STEADY_TOL",
    "UNDETERMINED",
    "Z_SE",
    "AmplitudeSpeed",
    "PlateauSpeed",
    "SpeedPerVolt",
    "plateau_speeds",
    "records_speed",
    "speed_per_volt",
]

JUMP_SHARE = 0.25  # a jump of the command: at least this share of its span in one sample
FLAT_TOL = 0.02  # a plateau: the command within this share of its span
LENGTH_TOL = 0.02  # a square wave: its plateaus equal in length within this share (and 2 samples)
AMP_TOL = 0.05  # amplitudes within this share of each other are one amplitude
MIN_WINDOW = 10  # samples: the fewest valid ones in a plateau's last third
STEADY_TOL = 0.05  # a steady plateau: speed over the last and the middle third agree within this share
Z_SE = 2.0  # a dead band (or its opposite) is read when beyond this many standard errors ...
DB_MIN_SHARE = 0.05  # ... and beyond this share of the smallest amplitude
FALLS_SMALL = "falls at small commands"
FALLS_LARGE = "falls at large commands"
HOLDS = "holds"
UNDETERMINED = "undetermined"
STEADY = "steady"


@dataclass(frozen=True)
class PlateauSpeed:
    """One plateau of a square wave: its command ``u_v`` [V], the hub's speed along it ``speed_deg_s`` [deg/s]
    with its standard error ``se_deg_s``, over its last third, and its length ``length_s`` [s]."""

    u_v: float
    speed_deg_s: float
    se_deg_s: float
    length_s: float


@dataclass(frozen=True)
class AmplitudeSpeed:
    """One amplitude's plateaus: ``amplitude_v`` [V] (median |u|), how many (``n_plateaus``; ``n_still`` of them
    with the hub at rest), the records holding them, the median speed per volt ``speed_per_volt`` [deg/s/V] and the
    median ``relative`` one: speed over ``k_g |u|``, the gain the fit gives the plateau's group (1 on a linear rig),
    or, when the speed per volt falls at large commands, over the group's highest speed per volt (its small
    commands')."""

    amplitude_v: float
    n_plateaus: int
    n_still: int
    records: tuple[str, ...]
    speed_per_volt: float
    relative: float


@dataclass(frozen=True)
class SpeedPerVolt:
    """The hub's steady speed per volt over a run's open-loop square waves, by amplitude (:func:`speed_per_volt`).

    ``trend``: :data:`FALLS_SMALL`, :data:`FALLS_LARGE`, :data:`HOLDS` or :data:`UNDETERMINED`; ``dead_band_v``
    and ``dead_band_se_v`` [V]: the fitted ``u_db`` and its standard error (NaN undetermined; negative: the speed
    per volt falls at large commands); ``offset_v`` [V]: the command offset ``u_0``; ``gains_deg_s_v``: each
    group's ``k_g`` [deg/s/V] ("steady", or a plateau length like "0.25 s"); ``records``: the square waves read;
    ``skipped``: why each other record was not; ``line``: the finding in one sentence."""

    trend: str
    dead_band_v: float
    dead_band_se_v: float
    offset_v: float
    amplitudes: tuple[AmplitudeSpeed, ...]
    gains_deg_s_v: dict[str, float]
    records: tuple[str, ...]
    skipped: dict[str, str] = field(default_factory=dict)
    line: str = ""

    def to_dict(self) -> dict[str, object]:
        """JSON content (NaN for undefined; the diagnosis writer makes it null)."""
        return to_plain(self)


def _ols(t: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Slope of y on t and its standard error (NaN with fewer than 3 points)."""
    if t.size < 3:
        return math.nan, math.nan
    tc = t - t.mean()
    sxx = float(tc @ tc)
    b = float(tc @ (y - y.mean())) / sxx
    r = y - y.mean() - b * tc
    return b, math.sqrt(float(r @ r) / (t.size - 2) / sxx)


def _plateaus(u: np.ndarray) -> list[tuple[int, int]] | str:
    """(start, end) of every plateau of a square-wave command but the first; or why the command is not one."""
    span = float(np.max(u) - np.min(u))
    if not span > 0:
        return "constant command"
    cuts = np.flatnonzero(np.abs(np.diff(u)) > JUMP_SHARE * span) + 1
    edges = [0, *cuts.tolist(), u.size]
    segs = [(a, b) for a, b in zip(edges[:-1], edges[1:], strict=True) if b > a]
    if any(np.ptp(u[a:b]) > FLAT_TOL * span for a, b in segs):
        return "not a square wave (the command is not flat between its jumps)"
    inner = segs[1:]
    if len(inner) < 2:
        return "not a square wave (fewer than three plateaus)"
    lengths = np.array([b - a for a, b in inner])
    full = int(np.median(lengths[:-1])) if lengths.size > 2 else int(lengths.max())
    tol = max(2.0, LENGTH_TOL * full)
    if np.any(np.abs(lengths[:-1] - full) > tol):
        return "not a square wave (plateaus of unequal length)"
    if full - lengths[-1] > tol:
        inner = inner[:-1]  # the last one cut short by the record's end
    return inner


def plateau_speeds(
    t: np.ndarray, u: np.ndarray, theta_deg: np.ndarray, valid: np.ndarray | None = None
) -> tuple[list[PlateauSpeed], bool] | str:
    """The hub's speed on each plateau of an open-loop square wave, and whether the record is steady.

    ``t`` [s], ``u`` [V], ``theta_deg`` [deg, unwrapped], ``valid`` (samples that say something about the hub;
    default all). Returns ([:class:`PlateauSpeed`, ...], steady) or, for a record that is no square wave or too
    short to read, why (one phrase). Plateaus at zero command (within :data:`FLAT_TOL` of the span) are left out.
    """
    t, u, th = (np.asarray(x, float) for x in (t, u, theta_deg))
    ok = np.ones(t.size, bool) if valid is None else np.asarray(valid, bool)
    spans = _plateaus(u)
    if isinstance(spans, str):
        return spans
    span = float(np.ptp(u))
    Ts = float(np.median(np.diff(t)))
    out: list[PlateauSpeed] = []
    drift: list[float] = []
    for a, b in spans:
        level = float(np.median(u[a:b]))
        if abs(level) <= FLAT_TOL * span:
            continue
        third = (b - a) // 3
        last = slice(b - third, b)
        mid = slice(b - 2 * third, b - third)
        m_last, m_mid = ok[last], ok[mid]
        if int(m_last.sum()) < MIN_WINDOW:
            continue
        s, se = _ols(t[last][m_last], th[last][m_last])
        sign = math.copysign(1.0, level)
        out.append(PlateauSpeed(level, sign * s, se, (b - a) * Ts))
        if int(m_mid.sum()) >= MIN_WINDOW:
            s_mid, se_mid = _ols(t[mid][m_mid], th[mid][m_mid])
            drift.append(abs(s - s_mid) - 3.0 * math.hypot(se, se_mid) - STEADY_TOL * abs(s))
    if not out:
        return f"plateaus too short to read (fewer than {MIN_WINDOW} valid samples in their last third)"
    steady = bool(drift) and float(np.median(drift)) <= 0.0
    return out, steady


def _clusters(values: np.ndarray, tol: float) -> np.ndarray:
    """Group index of each value: sorted values within ``tol`` (relative) of their group's first share a group."""
    order = np.argsort(values, kind="stable")
    group = np.zeros(values.size, int)
    g, first = -1, -math.inf
    for i in order:
        if values[i] > first * (1.0 + tol) + 1e-12:
            g, first = g + 1, float(values[i])
        group[i] = g
    return group


def _still(p: PlateauSpeed) -> bool:
    """The hub at rest on a plateau: its speed within three standard errors of zero, or backwards."""
    return not p.speed_deg_s > 3.0 * p.se_deg_s


def _fit(a: np.ndarray, sgn: np.ndarray, s: np.ndarray, g: np.ndarray, ng: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Least squares of s = k_g (a + u0 sgn - u_db): parameters [k_0..k_ng-1, u0, u_db], their covariance (None
    without a degree of freedom left)."""

    def res(p: np.ndarray) -> np.ndarray:
        return p[g] * (a + p[ng] * sgn - p[ng + 1]) - s

    def jac(p: np.ndarray) -> np.ndarray:
        J = np.zeros((s.size, ng + 2))
        J[np.arange(s.size), g] = a + p[ng] * sgn - p[ng + 1]
        J[:, ng] = p[g] * sgn
        J[:, ng + 1] = -p[g]
        return J

    k0 = np.array([float(np.median(s[g == i] / a[g == i])) for i in range(ng)])
    sol = least_squares(res, np.r_[k0, 0.0, 0.0], jac=jac, method="lm", x_scale="jac")
    dof = s.size - (ng + 2)
    if dof <= 0:
        return sol.x, None
    J = jac(sol.x)
    sigma2 = float(sol.fun @ sol.fun) / dof
    try:
        cov = sigma2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return sol.x, None
    return sol.x, cov


def speed_per_volt(
    per_record: Mapping[str, tuple[Sequence[PlateauSpeed], bool]], skipped: Mapping[str, str] | None = None
) -> SpeedPerVolt:
    """The hub's speed per volt by amplitude over records' plateaus (:func:`plateau_speeds`), and its trend.

    ``per_record``: record name -> (plateaus, steady); ``skipped``: record name -> why it was not read (kept in
    the result). See the module's docstring for the model and the rule."""
    skipped = dict(skipped or {})
    names, plats, keys = [], [], []
    for name, (ps, steady) in per_record.items():
        for p in ps:
            names.append(name)
            plats.append(p)
            keys.append(STEADY if steady else f"{p.length_s:.3g} s")
    if not plats:
        return SpeedPerVolt(UNDETERMINED, math.nan, math.nan, math.nan, (), {}, (), skipped,
                            "speed per volt: no open-loop square wave to read")  # fmt: skip
    a_all = np.array([abs(p.u_v) for p in plats])
    still = np.array([_still(p) for p in plats])
    moving = np.flatnonzero(~still)
    gkeys = sorted({keys[i] for i in moving})
    g = np.array([gkeys.index(keys[i]) for i in moving], int)
    a, s = a_all[moving], np.array([plats[i].speed_deg_s for i in moving])
    sgn = np.sign([plats[i].u_v for i in moving])
    amp_group = _clusters(a_all, AMP_TOL)
    two_amps = any(len(set(amp_group[moving][g == i])) >= 2 for i in range(len(gkeys)))
    params = cov = None
    if moving.size and two_amps:
        params, cov = _fit(a, sgn, s, g, len(gkeys))
    db = se = off = math.nan
    gains: dict[str, float] = {}
    if params is not None:
        gains = {k: float(params[i]) for i, k in enumerate(gkeys)}
        off, db = float(params[-2]), float(params[-1])
        if cov is not None:
            se = math.sqrt(max(float(cov[-1, -1]), 0.0))
    trend = _trend(db, se, float(a_all.min()))
    rel_all = np.full(a_all.size, math.nan)
    if trend == FALLS_LARGE:  # the small commands' speed per volt is the linear gain; the fit's is not
        spv_m = s / a
        ref = [max(float(np.median(spv_m[(g == i) & (amp_group[moving] == j)])) for j in set(amp_group[moving][g == i]))
               for i in range(len(gkeys))]  # fmt: skip
        rel_all[moving] = spv_m / np.array(ref)[g]
    elif params is not None:
        rel_all[moving] = s / (params[g] * a)
    amps = []
    for j in range(int(amp_group.max()) + 1):
        idx = np.flatnonzero(amp_group == j)
        spv = [plats[i].speed_deg_s / a_all[i] for i in idx]
        rel = rel_all[idx][np.isfinite(rel_all[idx])]
        amps.append(AmplitudeSpeed(
            amplitude_v=float(np.median(a_all[idx])),
            n_plateaus=int(idx.size),
            n_still=int(still[idx].sum()),
            records=tuple(sorted({names[i] for i in idx})),
            speed_per_volt=float(np.median(spv)),
            relative=float(np.median(rel)) if rel.size else math.nan,
        ))  # fmt: skip
    result = SpeedPerVolt(trend, db, se, off, tuple(amps), gains, tuple(per_record), skipped)
    return SpeedPerVolt(**{**result.__dict__, "line": _line(result)})


def _trend(db: float, se: float, smallest: float) -> str:
    if not (math.isfinite(db) and math.isfinite(se)):
        return UNDETERMINED
    floor = max(Z_SE * se, DB_MIN_SHARE * smallest)
    if db > floor:
        return FALLS_SMALL
    if -db > floor:
        return FALLS_LARGE
    return HOLDS


def _line(r: SpeedPerVolt) -> str:
    """The finding in one sentence: the trend first, then each amplitude's speed per volt (and its share of the
    linear gain), then how many records."""
    amps = ", ".join(f"{x.amplitude_v:.3g} V {x.speed_per_volt:.3g}" for x in r.amplitudes)
    rel = ", ".join(f"{100 * x.relative:.0f}" for x in r.amplitudes if math.isfinite(x.relative))
    rest = sum(x.n_still for x in r.amplitudes)
    tail = f": {amps} deg/s/V" + (f" ({rel} % of the linear gain)" if rel else "")
    tail += (f", the hub at rest on {rest} plateaus" if rest else "") + f", over {len(r.records)} square waves"
    fit = f"dead band {r.dead_band_v:.3g} +- {r.dead_band_se_v:.2g} V"
    if r.trend == UNDETERMINED:
        why = "one amplitude per plateau length" if len(r.amplitudes) > 1 else "one amplitude"
        if math.isfinite(r.dead_band_v):
            why = "too few plateaus for a standard error"
        return f"hub speed per volt: its law in amplitude undetermined ({why}){tail}"
    if r.trend == FALLS_SMALL:
        return f"hub speed per volt {r.trend}, {fit} (friction or a dead zone){tail}"
    if r.trend == FALLS_LARGE:
        return f"hub speed per volt {r.trend} (saturation){tail.replace('the linear gain', 'the small ones')}"
    return f"hub speed per volt holds ({fit}: none){tail}"


def records_speed(records: Mapping[str, RigExperiment]) -> SpeedPerVolt | None:
    """:func:`speed_per_volt` over a run's open-loop square waves (whole records, theta's invalid samples left
    out); None when the run holds none (closed-loop records, and commands that are no square wave, say why in
    ``skipped`` when some other record is one)."""
    per: dict[str, tuple[Sequence[PlateauSpeed], bool]] = {}
    skipped: dict[str, str] = {}
    for name, x in records.items():
        got = "closed loop" if x.ref is not None else plateau_speeds(x.t, x.u, x.theta, x.valid.get("theta"))
        if isinstance(got, str):
            skipped[name] = got
        else:
            per[name] = got
    return speed_per_volt(per, skipped) if per else None
