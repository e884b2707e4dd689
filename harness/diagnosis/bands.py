"""A closed-loop record's behaviour beside its replays': per reference step, what the record did and the band an
ensemble of replays gives.

Behaviour is measured by :mod:`harness.behaviour` (overshoot, settling, the hub's stopping error, the link's peak
deflection, ringing and its frequency after settling, peak command), on the record and on each replay of an
ensemble: the same rig replayed with other noise draws and, where the fit's covariance is known, other draws of its
parameters. A replay that follows the record sample by sample only where the loop does not stick or rattle in a
phase the noise sets; its band is what the model says the record may do.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ..behaviour import METRICS, StepMetrics, step_metrics
from ..spec import physical_range
from .experiments import RigExperiment
from .result import Band, RecordBehaviour, StepBehaviour
from .simulation import MODELS, Setup, gauge_offset, replay

__all__ = [
    "BAND",
    "BEHAVIOUR_SEED",
    "bands",
    "closed_steps",
    "coverage",
    "measured",
    "parameter_draws",
    "replay_metrics",
]

BAND = (2.5, 97.5)  # percentiles of the ensemble that make a metric's band
BEHAVIOUR_SEED = 100  # the first noise seed of a behaviour ensemble (its replay i has seed BEHAVIOUR_SEED + i)


def closed_steps(experiments: Mapping[str, RigExperiment]) -> list[str]:
    """The experiments whose behaviour is measured: closed-loop records with a reference."""
    return [n for n, x in experiments.items() if x.replay == "closed" and x.ref is not None]


def _metrics(x: RigExperiment, theta: np.ndarray, alpha: np.ndarray, u: np.ndarray, offset: float
             ) -> list[StepMetrics]:  # fmt: skip
    m = theta.size
    assert x.ref is not None
    return step_metrics(x.t[:m] - x.t[0], x.ref[:m], theta, alpha - offset, u)


def replay_metrics(rig: Any, setup: Setup, x: RigExperiment, over: Mapping[str, Any], seed: int
                   ) -> list[StepMetrics]:  # fmt: skip
    """The behaviour of ``x`` replayed with ``over`` and the noise seed ``seed``."""
    r = replay(rig, setup, x, {**over, "daq.seed": seed})
    return _metrics(x, r.theta, r.alpha, r.u, gauge_offset(x, over))


def measured(x: RigExperiment, offset: float) -> list[StepMetrics]:
    """The record's own behaviour, its deflection about the gauge's ``offset`` [deg]."""
    return _metrics(x, x.theta, x.alpha, x.u, offset)


def parameter_draws(over: Mapping[str, Any], names: Sequence[str], log: Sequence[bool],
                    cov: Sequence[Sequence[float]], n: int, seed: int,
                    ranges: Sequence[tuple[float, float]] = ()) -> list[dict[str, Any]]:  # fmt: skip
    """``n`` draws of the fitted overrides ``over`` from their covariance ``cov`` (of ``names``, in the fit's
    coordinates: the log of the value where ``log``; each kept within its ``ranges`` (where it was fitted) when given,
    an FMU parameter within its physical range), the first one
    ``over`` itself; without a covariance, ``over`` each time."""
    c = np.asarray(cov, dtype=float)
    if not names or c.size == 0:
        return [dict(over) for _ in range(n)]
    w, v = np.linalg.eigh(0.5 * (c + c.T))
    root = v * np.sqrt(np.clip(w, 0.0, None))
    rng = np.random.default_rng(seed)
    out = [dict(over)]
    for _ in range(n - 1):
        z = root @ rng.standard_normal(len(names))
        d = dict(over)
        for name, is_log, dz in zip(names, log, z, strict=True):
            if name not in over:  # a parameter the overrides no longer hold (an effect removed): not drawn
                continue
            lo, hi = ranges[names.index(name)] if ranges else (-math.inf, math.inf)  # where it was fitted
            if is_log:
                top = math.log(hi / float(over[name])) if hi < math.inf else math.inf
                low = math.log(lo / float(over[name])) if lo > 0 else -math.inf
                value = float(over[name]) * math.exp(min(max(float(dz), low), top, 700.0))
            else:
                value = min(max(float(over[name]) + float(dz), lo), hi)
            table, param = name.split(".", 1)
            if table in MODELS:  # within the FMU's physical range (a friction's breakaway >= 1, a speed >= 0)
                lo, hi = physical_range(MODELS[table], param)
                value = min(max(value, lo), hi)
            d[name] = value
        out.append(d)
    return out


def bands(
    experiments: Mapping[str, RigExperiment], over: Mapping[str, Any], runs: Mapping[str, list[list[StepMetrics]]]
) -> dict[str, RecordBehaviour]:
    """Per experiment of ``runs``: each step's metrics as the record measured them (its deflection about the gauge
    offset of ``over``) beside the ensemble's median and BAND."""
    out = {}
    for name, ens in runs.items():
        x = experiments[name]
        mine = measured(x, gauge_offset(x, over))
        steps = []
        for j, st in enumerate(mine):
            per = {m: [float(getattr(r[j], m)) for r in ens if len(r) > j and r[j].step.start == st.step.start]
                   for m in METRICS}  # fmt: skip
            metrics = {}
            for m, vals in per.items():
                v = np.asarray([a for a in vals if math.isfinite(a)])
                mid, lo, hi = (float(np.percentile(v, q)) for q in (50.0, *BAND)) if v.size else (math.nan,) * 3
                metrics[m] = Band(float(getattr(st, m)), mid, lo, hi)
            steps.append(StepBehaviour(x.t[st.step.start] - x.t[0], st.step.direction, st.step.size_deg, metrics))
        out[name] = RecordBehaviour(steps, coverage(steps))
    return out


def coverage(steps: Sequence[StepBehaviour]) -> float:
    """Share of the measured metrics (defined, with a band) that lie inside their band; NaN when none."""
    inside = [b.lo <= b.measured <= b.hi for s in steps for b in s.metrics.values()
              if math.isfinite(b.measured) and math.isfinite(b.lo)]  # fmt: skip
    return float(np.mean(inside)) if inside else math.nan
