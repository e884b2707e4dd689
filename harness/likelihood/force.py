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

from .fit import run_filter
from .kalman import smooth
from .model import DEG, Noise, rig_model
from .record import Record

__all__ = ["ForcePicture", "ForceTrace", "force_picture"]

INTENSITY_RANGE = (1e-5, 10.0)  # N m / sqrt(s): where the force's intensity is searched (log), beside none


@dataclass(frozen=True)
class ForceTrace:
    """One record's smoothed missing force ``force`` [N m] and its standard deviation ``force_sd``, beside the
    hub's smoothed speed ``speed`` [deg/s], the command ``u`` [V] and the smoothed deflection ``alpha`` [deg], at
    times ``t`` [s]."""

    name: str
    t: np.ndarray
    force: np.ndarray
    force_sd: np.ndarray
    speed: np.ndarray
    u: np.ndarray
    alpha: np.ndarray


@dataclass(frozen=True)
class ForcePicture:
    """The missing force of a fitted model: its random walk's ``intensity`` [N m/sqrt(s)] (0: the records want none),
    the log-likelihood it gains over the model without it ``gain`` [nats], and each record's ``traces``."""

    intensity: float
    gain: float
    traces: tuple[ForceTrace, ...]


def _loglik(plant: Mapping[str, Any], values: Mapping[str, float], records: Sequence[Record], delay: int,
            intensity: float) -> float:  # fmt: skip
    model = rig_model(plant, *_split(values, intensity), force=True)
    d = {rec.Ts: model.discretise(rec.Ts) for rec in records}
    return sum(run_filter(model, d[rec.Ts], rec, delay).loglik for rec in records)


def _split(values: Mapping[str, float], intensity: float) -> tuple[dict[str, float], Noise]:
    linear = {k: v for k, v in values.items() if not k.startswith("noise.")}
    noise = Noise.from_values({**values, "noise.hub_force": intensity})
    return linear, noise


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
    values = {k: v for k, v in values.items() if k != "noise.hub_force"}
    none = _loglik(plant, values, records, delay, 0.0)
    lo, hi = (math.log(x) for x in INTENSITY_RANGE)
    best = minimize_scalar(lambda s: -_loglik(plant, values, records, delay, math.exp(s)), bounds=(lo, hi),
                           method="bounded", options={"xatol": 1e-3})  # fmt: skip
    intensity, ll = (math.exp(best.x), -best.fun) if -best.fun > none else (0.0, none)
    model = rig_model(plant, *_split(values, intensity), force=True)
    traces = []
    for rec in records:
        disc = model.discretise(rec.Ts)
        f = run_filter(model, disc, rec, delay, keep=True)
        x, P = smooth(disc, f)
        i_d, i_w = model.states.index("d"), model.states.index("theta_dot")
        gauge = model.C[1, : i_d - 1]  # the gauge's row without its offset
        traces.append(ForceTrace(
            rec.name, np.arange(rec.n) * rec.Ts, x[:, i_d], np.sqrt(np.maximum(P[:, i_d, i_d], 0.0)),
            x[:, i_w] * DEG, rec.u, x[:, : i_d - 1] @ gauge,
        ))  # fmt: skip
    return ForcePicture(intensity, ll - none, tuple(traces))
