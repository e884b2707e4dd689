"""The missing force: what the fitted model lacks, estimated as a random-walk torque on the hub and smoothed.

Kristensen, Madsen and Jorgensen (2004), CTSM's systematic model improvement: with the model's parameters fitted,
a state ``d`` [N m] is added on the hub, a random walk whose intensity is fitted by maximum likelihood (the model's
other parameters held), and the Rauch-Tung-Striebel smoother gives its path through each record. Drawn against the
hub's speed, a jump at zero speed is friction; a flat top, a limit; a gap around zero command, a dead band or an
offset. :func:`classify` names the shape and its size by one regression on those shapes' columns (its levels in
:class:`ShapePolicy`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import minimize_scalar

from ..workercall import one_blas_thread
from .fit import log_likelihood, run_filter, split_values
from .kalman import smooth
from .model import DEG, rig_model
from .record import Record

__all__ = [
    "SHAPES",
    "EffectCurve",
    "ForcePicture",
    "ForceTrace",
    "MissingForce",
    "ShapePolicy",
    "classify",
    "effect_curve",
    "force_picture",
]

INTENSITY_RANGE = (1e-5, 10.0)  # N m / sqrt(s): where the force's intensity is searched (log), beside none


@dataclass(frozen=True)
class ForceTrace:
    """One record's smoothed missing force ``force`` [N m] and its standard deviation ``force_sd``, beside the
    hub's smoothed speed ``speed`` [deg/s] and its standard deviation ``speed_sd``, the command ``u`` [V] as the
    plant receives it (the DAQ's delay applied) and the smoothed deflection ``alpha`` [deg], at times ``t`` [s]."""

    name: str
    t: np.ndarray
    force: np.ndarray
    force_sd: np.ndarray
    speed: np.ndarray
    speed_sd: np.ndarray
    u: np.ndarray
    alpha: np.ndarray


@dataclass(frozen=True)
class ForcePicture:
    """The missing force of a fitted model: its random walk's ``intensity`` [N m/sqrt(s)] (0: the records want none),
    the log-likelihood it gains over the model without it ``gain`` [nats], each record's ``traces``, and the drive's
    torque per volt ``drive`` [N m/V] (a force's size as the command that would make it)."""

    intensity: float
    gain: float
    traces: tuple[ForceTrace, ...]
    drive: float


@dataclass(frozen=True)
class EffectCurve:
    """A fitted effect's torque on the hub as the missing force of the model without it would show it: its
    ``label``, drawn against the traces' field ``x`` ("speed" [deg/s] or "u" [V]) at ``xs``, the torque ``ys``
    [N m]."""

    label: str
    x: str
    xs: np.ndarray
    ys: np.ndarray


def effect_curve(parameter: str, value: float, picture: ForcePicture) -> EffectCurve:
    """The curve of the effect ``parameter`` at ``value`` over ``picture``'s range: Coulomb friction
    (``plant.coulomb_torque`` [N m]) -Fc sign(speed) against the hub's speed, the stick phase the vertical at zero;
    the amplifier's limit (``plant.amp_limit`` [V]) the drive's torque of what it clips, drive (clip(u, +-L) - u),
    against the command.

    Raises
    ------
    ValueError
        For a parameter with no curve.
    """
    if parameter == "plant.coulomb_torque":
        top = max((float(np.max(np.abs(tr.speed))) for tr in picture.traces), default=1.0)
        return EffectCurve(f"Coulomb friction {value:.3g} N m", "speed", np.array([-top, 0.0, 0.0, top]),
                           np.array([value, value, -value, -value]))  # fmt: skip
    if parameter == "plant.amp_limit":
        top = max((float(np.max(np.abs(tr.u))) for tr in picture.traces), default=1.0)
        u = np.linspace(-top, top, 201)
        return EffectCurve(f"amplifier limit {value:.3g} V", "u", u, picture.drive * (np.clip(u, -value, value) - u))
    raise ValueError(f"no curve for the effect parameter {parameter!r}")


@dataclass(frozen=True)
class MissingForce:
    """What the missing force's shape says (:func:`classify`): ``shape``, one of :data:`SHAPES`; its ``size`` in
    ``unit``: friction's Coulomb level [N m] (asymmetric friction: the mean of its two levels), a limit's level [V],
    an offset's [V] (signed), 0 for "none" and "too_few_at_rest"; the command friction takes to overcome
    ``dead_band_v`` [V]; the samples the records hold at rest (``samples_near_zero``: the smoothed speed within
    :attr:`ShapePolicy.moving_sd` of its standard deviations of zero, or changing sign before the next), where
    friction's jump shows; and friction's two ``levels`` [N m] (forward, backward: the force's magnitude against the
    motion each way; (0, 0) for the other shapes). ``sized_by`` says where the size comes from: "picture" (the
    classifier's regression on the smoothed force) or the nested effect of that shape that entered (its
    maximum-likelihood size; the smoother's random walk rounds a small force's jumps off, so the regression reads
    it small), the picture's own then in ``picture_size``."""

    shape: str
    size: float
    unit: str
    dead_band_v: float
    samples_near_zero: int
    levels: tuple[float, float] = (0.0, 0.0)
    sized_by: str = "picture"
    picture_size: float | None = None

    def words(self) -> str:
        """The verdict in words, as the summary, the report, the figure and the recording say it: "friction of
        0.03 N m (0.125 V of command)" (asymmetric friction with its levels each way), "limit at 1.2 V", "offset of
        0.1 V", "too few samples at rest ...", "none"."""
        if self.shape in ("friction", "asymmetric_friction"):
            ways = (f", {self.levels[0]:.3g} forward and {self.levels[1]:.3g} backward"
                    if self.shape == "asymmetric_friction" else "")  # fmt: skip
            return f"{self.shape}{ways} of {self.size:.3g} {self.unit} ({self.dead_band_v:.3g} V of command)"
        if self.shape == "limit":
            return f"limit at {self.size:.3g} {self.unit}"
        if self.shape == "offset":
            return f"offset of {self.size:.3g} {self.unit}"
        if self.shape == "too_few_at_rest":
            return "too few samples at rest (the hub never rests: friction and an offset look alike)"
        return self.shape

    def to_json(self) -> dict[str, Any]:
        """As ``missing_force`` in likelihood.json."""
        return {"shape": self.shape, "size": self.size, "unit": self.unit, "dead_band_v": self.dead_band_v,
                "samples_near_zero": self.samples_near_zero, "levels": list(self.levels), "sized_by": self.sized_by,
                "picture_size": self.picture_size}  # fmt: skip

    @classmethod
    def from_json(cls, doc: Mapping[str, Any]) -> MissingForce:
        """The verdict as likelihood.json's ``missing_force`` holds it (:meth:`to_json`; ``levels`` (0, 0) when
        absent: a file written before they were)."""
        lv = doc.get("levels") or (0.0, 0.0)
        pic = doc.get("picture_size")
        return cls(str(doc["shape"]), float(doc["size"]), str(doc["unit"]), float(doc["dead_band_v"]),
                   int(doc["samples_near_zero"]), (float(lv[0]), float(lv[1])), str(doc.get("sized_by", "picture")),
                   None if pic is None else float(pic))  # fmt: skip


def force_picture(
    plant: Mapping[str, Any], values: Mapping[str, float], records: Sequence[Record], delay: int = 0
) -> ForcePicture:
    """The missing force of the rig ``plant`` with the fitted ``values`` (linear and noise parameters) through
    ``records``.

    Parameters
    ----------
    plant : mapping
        The spec's plant table.
    values : mapping
        The fitted parameters (:func:`harness.likelihood.fit.fit`'s), held.
    records : sequence of Record
        The unit's records.
    delay : int
        The command's delay [samples].

    Returns
    -------
    ForcePicture
    """
    with one_blas_thread():  # small matrices: a second BLAS thread only contends for the cores
        return _picture(plant, values, records, delay)


def _picture(
    plant: Mapping[str, Any], values: Mapping[str, float], records: Sequence[Record], delay: int
) -> ForcePicture:
    """:func:`force_picture`'s work."""

    def loglik(intensity: float) -> float:  # the model with the force state (also at none)
        return log_likelihood(plant, {**values, "noise.hub_force": intensity}, records, delay)

    none = loglik(0.0)
    lo, hi = (math.log(x) for x in INTENSITY_RANGE)
    best = minimize_scalar(lambda s: -loglik(math.exp(s)), bounds=(lo, hi), method="bounded",
                           options={"xatol": 1e-3})  # fmt: skip
    intensity, ll = (math.exp(best.x), -best.fun) if -best.fun > none else (0.0, none)
    model = rig_model(plant, *split_values({**values, "noise.hub_force": intensity}), force=True)
    i_d, i_w = model.states.index("d"), model.states.index("theta_dot")
    traces = []
    for rec in records:  # the command as the plant receives it (delayed), so that a limit's excess lines up
        disc = model.discretise(rec.Ts)
        f = run_filter(model, disc, rec, delay, keep=True)
        x, P = smooth(disc, f)
        gauge = model.C[1, : i_d - 1]  # the gauge's row without its offset
        traces.append(ForceTrace(
            rec.name, np.arange(rec.n) * rec.Ts, x[:, i_d], np.sqrt(np.maximum(P[:, i_d, i_d], 0.0)),
            x[:, i_w] * DEG, np.sqrt(np.maximum(P[:, i_w, i_w], 0.0)) * DEG, rec.delayed(delay),
            x[:, : i_d - 1] @ gauge,
        ))  # fmt: skip
    return ForcePicture(intensity, ll - none, tuple(traces), model.drive)


@dataclass(frozen=True)
class ShapePolicy:
    """The classifier's few levels (:func:`classify`).

    Attributes
    ----------
    moving_sd : float
        The hub moves where its smoothed speed lies beyond this many of its standard deviations from zero; elsewhere,
        and between two samples whose speeds differ in sign, it is at rest.
    passages : int
        The passages through rest (runs of samples at rest) the records must hold for friction's jump to be seen:
        two, so that the hub has turned both ways across rest.
    level : float
        A shape stands out when its coefficient lies this many standard errors from zero, on its physical side.
    block_times : float
        The standard errors' blocks span this many correlation times of the residual (or of the smoother's error,
        the longer).
    limit_quantiles : tuple of float
        The limit's 1-D search looks at these quantiles of the command's magnitude (lowest, highest) ...
    limit_steps : int
        ... in this many steps.
    min_beyond : float
        A limit is tried only where the command exceeds it on at least this share of the samples.
    """

    moving_sd: float = 3.0
    passages: int = 2
    level: float = 5.0
    block_times: float = 4.0
    limit_quantiles: tuple[float, float] = (0.5, 0.98)
    limit_steps: int = 25
    min_beyond: float = 0.02


SHAPES = ("friction", "asymmetric_friction", "limit", "offset", "too_few_at_rest", "none")


@dataclass(frozen=True)
class _Columns:
    """The regression's rows (the samples where the hub moves), its shape columns by name, and each row's trace."""

    force: np.ndarray
    force_sd: np.ndarray
    trace: np.ndarray
    X: np.ndarray
    names: tuple[str, ...]


@dataclass(frozen=True)
class _Judged:
    """A least-squares fit of the force on the shape columns: coefficients and their standard errors by column."""

    coef: dict[str, float]
    t: dict[str, float]
    ssr: float


def classify(picture: ForcePicture, policy: ShapePolicy | None = None) -> MissingForce:
    """Name the missing force's shape and its size: one regression of the smoothed force, where the hub moves, on a
    library of shape columns, each judged by its coefficient over its standard error.

    The columns (forces in N m): ``offset``, the constant ``drive`` (its coefficient the amplifier's input offset
    [V]); ``friction``, ``-sign(speed)`` (its coefficient the Coulomb level [N m]); ``limit``,
    ``-drive (u - clip(u, +-L))`` (coefficient 1 at the amplifier's limit ``L`` [V], found by a 1-D search over the
    command's magnitudes that minimises the residual; tried where the command exceeds ``L`` on enough samples). The
    samples are strongly correlated: the standard errors are a block sandwich (the coefficients' covariance from
    each block's sum of column times residual, blocks of a few correlation times of the residual) plus the same
    with the smoother's ``force_sd`` in place of the residual (at an intensity of zero the force is one constant a
    residual cannot show). The rule, in order:

    1. the force varies only where the records want its random walk at the same level (a log-likelihood gain of
       ``level**2 / 2`` nats: the likelihood-ratio statistic past ``level**2``); else only the offset is tried;
       friction only where the hub passes through rest :attr:`ShapePolicy.passages` times, both ways;
    2. a column stands out when its coefficient lies :attr:`ShapePolicy.level` standard errors on its physical side
       (friction and a limit: opposing the drive; an offset: either);
    3. none stands out: "none";
    4. the one furthest out names the shape; friction with an offset beside it that leaves the force opposing the
       motion both ways: "asymmetric_friction" (size the mean of the two levels, ``levels`` each);
    5. an offset where friction could not be tried: "too_few_at_rest" (a constant force that friction on a hub
       turning one way would make as well).

    Parameters
    ----------
    picture : ForcePicture
        :func:`force_picture`'s.
    policy : ShapePolicy, optional
        The levels; default :class:`ShapePolicy`'s.

    Returns
    -------
    MissingForce
    """
    pol = policy or ShapePolicy()
    drive = picture.drive
    moving, rest = [], 0
    passages = 0
    for tr in picture.traces:
        still = np.abs(tr.speed) <= pol.moving_sd * tr.speed_sd
        still[:-1] |= np.sign(tr.speed[:-1]) * np.sign(tr.speed[1:]) < 0  # passing through rest between samples
        rest += int(still.sum())
        passages += int(np.sum(still[1:] & ~still[:-1]) + still[0])
        moving.append(~still)
    speed = np.concatenate([tr.speed[m] for tr, m in zip(picture.traces, moving, strict=True)])
    u = np.concatenate([tr.u[m] for tr, m in zip(picture.traces, moving, strict=True)])
    force = np.concatenate([tr.force[m] for tr, m in zip(picture.traces, moving, strict=True)])
    force_sd = np.concatenate([tr.force_sd[m] for tr, m in zip(picture.traces, moving, strict=True)])
    trace = np.concatenate([np.full(int(m.sum()), i) for i, m in enumerate(moving)])
    if force.size < 3:
        return MissingForce("none", 0.0, "N m", 0.0, rest)
    base = {"offset": np.full(force.size, drive)}
    varying = picture.gain >= 0.5 * pol.level**2  # the random walk wanted at the columns' level
    both_ways = bool(np.any(speed > 0) and np.any(speed < 0))
    seen = passages >= pol.passages and both_ways
    if varying and seen:
        base["friction"] = -np.sign(speed)
    taus = _smoother_times(picture)
    judged = _judge(_columns(base, force, force_sd, trace), taus, pol)
    limit = 0.0
    mag = np.abs(u)
    for L in np.unique(np.quantile(mag, np.linspace(*pol.limit_quantiles, pol.limit_steps))):
        if not varying or L <= 0.0 or np.mean(mag > L) < pol.min_beyond:
            continue
        cols = base | {"limit": -drive * (u - np.clip(u, -L, L))}
        j = _judge(_columns(cols, force, force_sd, trace), taus, pol)
        if "limit" in j.t and j.ssr < judged.ssr:
            judged, limit = j, float(L)
    physical = {"offset": 0.0, "friction": 1.0, "limit": 1.0}  # the side a shape's coefficient must lie on
    out = {k: t for k, t in judged.t.items() if (abs(t) if physical[k] == 0.0 else t) > pol.level}
    if not out:
        return MissingForce("none", 0.0, "N m", 0.0, rest)
    name = max(out, key=lambda k: abs(out[k]))
    c = judged.coef
    if name == "limit":
        return MissingForce("limit", limit, "V", 0.0, rest)
    if name == "friction":
        forward, backward = c["friction"] - drive * c.get("offset", 0.0), c["friction"] + drive * c.get("offset", 0.0)
        if "offset" in out and min(forward, backward) > 0.0:
            size = 0.5 * (forward + backward)
            return MissingForce("asymmetric_friction", size, "N m", size / drive, rest, (forward, backward))
        size = c["friction"]
        return MissingForce("friction", size, "N m", size / drive, rest, (size, size))
    if not seen:
        return MissingForce("too_few_at_rest", 0.0, "N m", 0.0, rest)
    return MissingForce("offset", c["offset"], "V", 0.0, rest)


def _smoother_times(picture: ForcePicture) -> list[float]:
    """Each trace's smoother error's correlation time [samples]: a random walk of intensity q known to sd s is
    remembered over s^2 / q^2 seconds; at an intensity of zero, the whole record."""
    out = []
    for tr in picture.traces:
        n = tr.t.size
        dt = float(tr.t[1] - tr.t[0]) if n > 1 else 1.0
        s = float(np.median(tr.force_sd))
        out.append(float(n) if picture.intensity == 0.0 else min(float(n), (s / picture.intensity) ** 2 / dt))
    return out


def _columns(cols: Mapping[str, np.ndarray], force: np.ndarray, force_sd: np.ndarray, trace: np.ndarray) -> _Columns:
    return _Columns(force, force_sd, trace, np.column_stack(list(cols.values())), tuple(cols))


def _judge(cols: _Columns, taus: Sequence[float], pol: ShapePolicy) -> _Judged:
    """Least squares of the force on the columns, with block-sandwich standard errors (:func:`classify`)."""
    X, f = cols.X, cols.force
    XtX = X.T @ X
    if np.linalg.matrix_rank(XtX) < X.shape[1]:
        return _Judged({}, {}, math.inf)
    coef = np.linalg.solve(XtX, X.T @ f)
    r = f - X @ coef
    meat = np.zeros_like(XtX)
    for i, tau_s in enumerate(taus):
        on = cols.trace == i
        n = int(on.sum())
        if n == 0:
            continue
        size = max(1, min(n, math.ceil(pol.block_times * max(_correlation_time(r[on]), tau_s))))
        Xi, ri, si = X[on], r[on], cols.force_sd[on]
        for a in range(0, n, size):
            g, h = Xi[a : a + size].T @ ri[a : a + size], Xi[a : a + size].T @ si[a : a + size]
            meat += np.outer(g, g) + np.outer(h, h)
    inv = np.linalg.inv(XtX)
    se = np.sqrt(np.maximum(np.diag(inv @ meat @ inv), 1e-300))
    names = cols.names
    return _Judged(dict(zip(names, map(float, coef), strict=True)),
                   dict(zip(names, map(float, coef / se), strict=True)),
                   float(r @ r))  # fmt: skip


def _correlation_time(r: np.ndarray) -> float:
    """The lag [samples] where the residual's autocorrelation first falls below 1/e (its length if never; 1 for a
    residual of none)."""
    r = r - r.mean()
    v = float(r @ r)
    if v <= 0.0:
        return 1.0
    n = r.size
    spec = np.fft.rfft(r, 2 * n)
    acf = np.fft.irfft(spec * np.conj(spec))[:n] / v
    below = np.flatnonzero(acf < math.exp(-1.0))
    return float(below[0]) if below.size else float(n)
