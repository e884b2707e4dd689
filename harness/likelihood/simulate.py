"""Records drawn from a fitted stochastic model: the parametric bootstrap of what the filter leaves on data its model
makes.

:func:`draw_records` simulates the model a fit describes
(:meth:`harness.likelihood.model.StochasticModel.discretise`) under a record's command, mask and lattice: the
process noise over each step, friction as the time-stepping methods of non-smooth mechanics take it on the state
itself (the torque that brings the hub to rest where that is within +-Fc, else +-Fc against the motion), a gear's
play as the filter steps it (``fmus/master/kalman.c``: its sides apart, or in contact after a plastic impact), on
steps of :data:`FINE_STEP` (the filter holds its friction over 1 ms: a hub that stops within a step is stopped at
the step's end, its impulse on the link a step late; on these steps the draws replay the plant FMU's event-located
stick-slip, and its play within 1.5e-3 deg), the gauge bent, the readings' white noise, rounded to the record's
lattice. The filter run through such draws meets its own approximations (friction's moments over its coarser steps,
the bent gauge's linearisation, the start's wide prior) and nothing else: what its innovations keep there is what
the model leaves on data it describes (:func:`whiteness_scale`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from .fit import filter_record, split_values, start_state
from .model import rig_model
from .record import Record
from .whiteness import LAGS, ljung_box

__all__ = ["DRAWS", "FINE_STEP", "draw_records", "friction_torque", "whiteness_scale"]

DRAWS = 10  # records drawn per record to measure what the filter leaves on the model's own data
FINE_STEP = 5e-5  # s: the draws' friction step (they replay the plant FMU's stick-slip within 3.2e-5 deg, 1 ms 1.2e-4)


def draw_records(
    plant: Mapping[str, Any],
    values: Mapping[str, float],
    record: Record,
    delay: int,
    rng: np.random.Generator,
    draws: int = DRAWS,
) -> np.ndarray:
    """Readings drawn from the model of ``plant`` with ``values`` (linear, effects and noise, as
    :func:`harness.likelihood.fit.fit` names them) under ``record``'s command delayed ``delay`` samples, from the
    state the filter starts at (the hub at its first reading, at rest), on ``record``'s lattice.

    Parameters
    ----------
    plant : mapping
        The spec's plant table.
    values : mapping
        The model's parameters.
    record : Record
        Its command, sample time and lattice are the draws'.
    delay : int
        The command's delay [samples].
    rng : numpy.random.Generator
        The draws' noise.
    draws : int
        How many.

    Returns
    -------
    ndarray, shape (draws, n, 2)
        The readings [deg].
    """
    model = rig_model(plant, *split_values(values))
    d = model.discretise(record.Ts, FINE_STEP)
    inputs = model.inputs(record.delayed(delay))
    u = inputs @ d.B.T  # each sample's input term (in contact)
    x0, _ = start_state(model, record)
    L = _root(d.Q)
    n = u.shape[0]
    X = np.repeat(x0[:, None], draws, axis=1)
    friction = d.friction > 0.0 and d.hub is not None
    hub = d.hub if d.hub is not None else np.zeros(x0.size)
    play = None
    if d.play > 0.0 and d.loose is not None and d.impact is not None:
        play = (d.loose[0], d.loose[1], _root(d.loose[2]), d.A @ d.impact, d.impact)
    y = np.empty((draws, n, 2))
    for k in range(n):
        z = d.C @ X
        if d.cubic is not None and d.bend is not None:
            z += d.cubic[:, None] * (d.bend @ X) ** 3
        y[:, k] = z.T
        for _ in range(d.substeps):
            if play is None:
                X = d.A @ X + u[k][:, None] + L @ rng.standard_normal(X.shape)
            else:  # the sides apart, or in contact where the gap would pass +-play / 2
                Af, Bf, Lf, M, impact = play
                Xf = Af @ X + (Bf @ inputs[k])[:, None] + Lf @ rng.standard_normal(X.shape)
                edge = 0.5 * d.play * np.sign(Xf[d.gap]) * (np.abs(Xf[d.gap]) > 0.5 * d.play)
                with np.errstate(invalid="ignore", divide="ignore"):  # where the teeth meet within the step
                    tau = np.nan_to_num(np.clip((edge - X[d.gap]) / (Xf[d.gap] - X[d.gap]), 0.0, 1.0))
                Xc = M @ X + np.outer(d.A[:, d.gap], edge) + u[k][:, None] + L @ rng.standard_normal(X.shape)
                Xi = impact @ Xf
                Xi[d.gap] = edge
                X = np.where(edge != 0, (1.0 - tau) * Xc + tau * Xi, Xf)
            if friction:  # the friction torque over the step: to rest within +-Fs, else sliding against the motion
                X += np.outer(hub, friction_torque(X[d.speed], hub[d.speed], d.friction, d.breakaway, d.stribeck))
    y += np.sqrt(d.r) * rng.standard_normal(y.shape)
    q = np.asarray(record.lattice, dtype=float)
    return np.where(q > 0, np.round(y / np.where(q > 0, q, 1.0)) * q, y)


def friction_torque(v: np.ndarray, b: float, fc: float, fs: float = 0.0, vs: float = 0.0) -> np.ndarray:
    """The friction torque [N m] held over a step that would end at the hub speed ``v`` without it (``b``: a unit
    torque's effect on the speed over the step): -v / b where that is within +-Fs (Fs = max(``fs``, ``fc``): the hub
    sticks), else against the motion, ``fc`` + (Fs - ``fc``) exp(-(v / ``vs``)^2) (``fc`` alone where ``vs`` is 0;
    the filter's law, ``fmus/master/kalman.c``)."""
    top = max(fs, fc)
    drop = (top - fc) * np.exp(-((v / vs) ** 2)) if vs > 0.0 else 0.0
    return np.where(np.abs(v) <= b * top, -v / b, -np.sign(v) * (fc + drop))


def _root(Q: np.ndarray) -> np.ndarray:
    """L with Q = L L' for a covariance Q (its eigenvectors scaled: Q may be singular)."""
    w, V = np.linalg.eigh(Q)
    return V * np.sqrt(np.clip(w, 0.0, None))


def whiteness_scale(
    plant: Mapping[str, Any],
    values: Mapping[str, float],
    records: Sequence[Record],
    delay: int,
    draws: int = DRAWS,
    seed: int = 0,
) -> dict[str, dict[str, float]]:
    """What the filter's innovations keep on records its model draws: per record and channel, the Ljung-Box
    statistic's mean over ``draws`` draws (:func:`draw_records`) over its value on white residuals (its
    :data:`harness.likelihood.whiteness.LAGS` degrees of freedom), at least 1. The whiteness test of that record's
    channel takes its law scaled by this (an exact filter keeps nothing: about 1).

    Parameters
    ----------
    plant, values, records, delay
        The fitted model and the records it was fitted to.
    draws : int
        Records drawn per record.
    seed : int
        The draws' seed (the same scale every time).

    Returns
    -------
    dict
        ``{record: {"theta": scale, "alpha": scale}}``.
    """
    rng = np.random.default_rng(seed)
    out: dict[str, dict[str, float]] = {}
    for rec in records:
        q = np.zeros((draws, 2))
        for i, y in enumerate(draw_records(plant, values, rec, delay, rng, draws)):
            drawn = Record(rec.name, rec.Ts, rec.u, y, rec.mask, rec.lattice)
            z = filter_record(plant, values, drawn, delay).standardised(np.asarray(rec.lattice), seed=i)
            q[i] = [ljung_box(z[:, j]).statistic for j in range(2)]
        out[rec.name] = {c: max(1.0, float(np.mean(q[:, j])) / LAGS) for j, c in enumerate(("theta", "alpha"))}
    return out
