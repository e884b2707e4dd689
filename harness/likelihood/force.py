"""The missing force: what the fitted model lacks, estimated as a random-walk torque on the hub and smoothed.

Kristensen, Madsen and Jorgensen (2004), CTSM's systematic model improvement: with the model's parameters fitted,
a state ``d`` [N m] is added on the hub, a random walk whose intensity is fitted by maximum likelihood (the model's
other parameters held), and the Rauch-Tung-Striebel smoother gives its path through each record. Drawn against the
hub's speed, a jump at zero speed is friction; a flat top, a limit; a gap around zero command, a dead band.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import minimize_scalar

from .fit import log_likelihood, run_filter, split_values
from .kalman import smooth
from .model import DEG, rig_model
from .record import Record

__all__ = ["ForcePicture", "ForceTrace", "MissingForce", "classify", "force_picture"]

INTENSITY_RANGE = (1e-5, 10.0)  # N m / sqrt(s): where the force's intensity is searched (log), beside none


@dataclass(frozen=True)
class ForceTrace:
    """One record's smoothed missing force ``force`` [N m] and its standard deviation ``force_sd``, beside the
    hub's smoothed speed ``speed`` [deg/s] and its standard deviation ``speed_sd``, the command ``u`` [V] and the
    smoothed deflection ``alpha`` [deg], at times ``t`` [s]."""

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
class MissingForce:
    """What the missing force's shape says: ``shape`` "friction" (a jump at zero speed, against the motion) or "none";
    its ``size`` [N m] (half the jump: the Coulomb level) with its ``unit``, the command it takes to make it
    ``dead_band_v`` [V], and the samples the records hold at rest (``samples_near_zero``: within three of the speed's
    standard deviations of zero), where a stick phase would show."""

    shape: str
    size: float
    unit: str
    dead_band_v: float
    samples_near_zero: int

    def to_json(self) -> dict[str, Any]:
        """As ``missing_force`` in likelihood.json."""
        return {"shape": self.shape, "size": self.size, "unit": self.unit, "dead_band_v": self.dead_band_v,
                "samples_near_zero": self.samples_near_zero}  # fmt: skip


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
    for rec in records:
        disc = model.discretise(rec.Ts)
        f = run_filter(model, disc, rec, delay, keep=True)
        x, P = smooth(disc, f)
        gauge = model.C[1, : i_d - 1]  # the gauge's row without its offset
        traces.append(ForceTrace(
            rec.name, np.arange(rec.n) * rec.Ts, x[:, i_d], np.sqrt(np.maximum(P[:, i_d, i_d], 0.0)),
            x[:, i_w] * DEG, np.sqrt(np.maximum(P[:, i_w, i_w], 0.0)) * DEG, rec.u, x[:, : i_d - 1] @ gauge,
        ))  # fmt: skip
    return ForcePicture(intensity, ll - none, tuple(traces), model.drive)


def classify(picture: ForcePicture) -> MissingForce:
    """Name the missing force's shape: friction where the force, while the hub turns (its speed more than three of
    its standard deviations from zero), opposes the motion on both sides and the step between the two sides' medians
    stands out of their spread (each side's median absolute deviation over the square root of its samples, three
    times over); none where the records want no force or it does not stand out.

    Parameters
    ----------
    picture : ForcePicture
        :func:`force_picture`'s.

    Returns
    -------
    MissingForce
    """
    force = np.concatenate([tr.force for tr in picture.traces])
    speed = np.concatenate([tr.speed for tr in picture.traces])
    moving = np.abs(speed) > 3.0 * np.concatenate([tr.speed_sd for tr in picture.traces])
    near = int(np.sum(~moving))
    fwd, back = force[moving & (speed > 0)], force[moving & (speed < 0)]
    if picture.intensity == 0.0 or fwd.size < 3 or back.size < 3:
        return MissingForce("none", 0.0, "N m", 0.0, near)
    f, b = float(np.median(fwd)), float(np.median(back))
    spread = sum(float(np.median(np.abs(x - np.median(x)))) / math.sqrt(x.size) for x in (fwd, back))
    if f < 0.0 < b and b - f > 3.0 * spread:
        size = 0.5 * (b - f)
        return MissingForce("friction", size, "N m", size / picture.drive, near)
    return MissingForce("none", 0.0, "N m", 0.0, near)
