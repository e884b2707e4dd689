"""The rig's parameters by maximum likelihood over the records of one unit, with intervals from the Hessian.

The records share one parameter set (the linear parameters of :data:`harness.diagnosis.recalibrate.LINEAR` and the
noise's of :data:`harness.likelihood.model.NOISE`); each record has its own start (the filter's first state, wide
enough that the first samples decide it) and gauge offset (a state). The objective is the records' summed Gaussian
log-likelihood (:func:`log_likelihood`) plus the priors the caller gives (a normal in the search coordinate: the log
of a parameter's ratio to its nominal value, or the value itself; :class:`harness.diagnosis.recalibrate.Bound`),
maximised by L-BFGS-B within the bounds, its gradient by central differences, in units of a prior's sd where that is
tighter than the coordinate's own. The linear model first: the noise is held at its start (:func:`noise_start`)
until the linear parameters have been fitted, then all are freed, the torques' intensities searched as variances.
The intervals come from the numerical Hessian of that objective at its maximum: 95 %, symmetric in the search
coordinate.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy.optimize import minimize

from ..diagnosis.recalibrate import LINEAR, Bound
from .kalman import Discrete, Filtered, kalman_filter
from .model import EFFECTS, NOISE, Noise, StochasticModel, rig_model
from .record import Record

__all__ = [
    "Estimate",
    "MLFit",
    "filter_record",
    "fit",
    "log_likelihood",
    "noise_start",
    "run_filter",
    "split_values",
    "start_state",
]

BOUNDS: dict[str, Bound] = {**LINEAR, **EFFECTS, **NOISE}
TORQUES = ("noise.hub_torque", "noise.link_torque")  # the process noise: freed once the rest is fitted
GRAD_STEP = 1e-5  # search-coordinate step of the gradient's central differences
HESS_STEP = 1e-3  # ... and of the Hessian's second differences
OUTSIDE = 1e6  # the search's objective [nats per reading] where the model fails: a wall it backs off from
TOL_NATS = 1e-4  # the search stops when an iteration gains less log-likelihood than this [nats] ...
RESTART_GAIN, RESTARTS = 0.01, 5  # ... and starts again from there, up to 5 times, while a search gains more [nats]
AT_BOUND = 1e-3  # a parameter this close to a wall (in the search coordinate) ends at its bound


@dataclass(frozen=True)
class Estimate:
    """A fitted parameter: its ``value``, its 95 % interval ``ci95``, its ``unit``, and ``at`` "lower" or "upper"
    when it ends at a bound (else None)."""

    value: float
    ci95: tuple[float, float]
    unit: str
    at: str | None = None


@dataclass(frozen=True)
class MLFit:
    """A maximum-likelihood fit: the ``estimates`` by parameter, the records' log-likelihood ``loglik`` at them
    (without the priors), the readings ``n`` it sums over, the free parameters ``k``, the objective's evaluations
    ``nfev`` and whether the search ``converged`` (else ``message`` says why it stopped)."""

    estimates: dict[str, Estimate]
    loglik: float
    n: int
    k: int
    nfev: int
    converged: bool
    message: str = ""

    def values(self) -> dict[str, float]:
        """The fitted values by parameter."""
        return {name: e.value for name, e in self.estimates.items()}

    def at_bounds(self) -> dict[str, str]:
        """The parameters that end at a bound, and which."""
        return {name: e.at for name, e in self.estimates.items() if e.at is not None}


def split_values(values: Mapping[str, float]) -> tuple[dict[str, float], Noise]:
    """Parameters by name as :func:`harness.likelihood.model.rig_model` takes them: the linear ones and the effects,
    and the noise."""
    return {k: v for k, v in values.items() if k in LINEAR or k in EFFECTS}, Noise.from_values(values)


def noise_start(records: Sequence[Record]) -> dict[str, float]:
    """Where the noise's search starts: each reading's white noise [deg] from its third differences (their median
    absolute value, as a white noise's: 0.6745 sqrt(20) sigma; a record's smooth motion cancels in them), at least a
    tenth of a lattice's step; the torques' intensities at 1e-3 N m sqrt(s) on the hub and 1e-4 at the tip (a small
    share of the drive's torque)."""
    out = {}
    for j, name in enumerate(("noise.theta", "noise.alpha")):
        sds = []
        for rec in records:
            y, m = rec.y[:, j], rec.mask[:, j]
            ok = m[3:] & m[2:-1] & m[1:-2] & m[:-3]
            d3 = (y[3:] - 3.0 * y[2:-1] + 3.0 * y[1:-2] - y[:-3])[ok]
            sd = float(np.median(np.abs(d3))) / (0.6745 * math.sqrt(20.0)) if d3.size else 0.0
            sds.append(max(sd, 0.1 * rec.lattice[j], 1e-4))
        out[name] = float(np.median(sds))
    return out | {"noise.hub_torque": 1e-3, "noise.link_torque": 1e-4}


def start_state(model: StochasticModel, record: Record) -> tuple[np.ndarray, np.ndarray]:
    """The filter's first state and its covariance for ``record``: the hub where its first reading puts it, the
    link at rest, the gauge offset its first reading and no missing force, each with a variance wide enough for the
    first samples to decide it (the hub's speed up to the record's fastest, the link's deflection up to its largest,
    the force up to the drive's at 1 V)."""
    nx = model.A.shape[0]
    idx = {name: i for i, name in enumerate(model.states)}
    links = [i for name, i in idx.items() if name.startswith("a_") and not name.startswith("a_dot")]
    rates = [i for name, i in idx.items() if name.startswith("a_dot")]
    c_theta = model.C[0, idx["theta"]]
    y, m = record.y, record.mask
    first = [int(np.argmax(m[:, j])) if m[:, j].any() else 0 for j in range(2)]
    sd_theta, sd_alpha = model.noise.theta + record.lattice[0], model.noise.alpha + record.lattice[1]
    th = y[m[:, 0], 0]
    speed = float(np.max(np.abs(np.diff(th)))) / record.Ts if th.size > 1 else 0.0
    al = y[m[:, 1], 1]
    amp = float(np.max(np.abs(al - np.median(al)))) if al.size else 0.0
    c_alpha = abs(model.C[1, links[0]]) or 1.0
    x0 = np.zeros(nx)
    x0[idx["theta"]] = y[first[0], 0] / c_theta
    x0[idx["b_alpha"]] = y[first[1], 1]
    var = np.zeros(nx)
    var[idx["theta"]] = ((3.0 * sd_theta + 1.0) / c_theta) ** 2
    var[links] = ((amp + 1.0) / c_alpha) ** 2
    var[idx["theta_dot"]] = ((speed + 10.0) / abs(c_theta)) ** 2
    var[rates] = model.w1**2 * var[links]
    var[idx["b_alpha"]] = (amp + 3.0 * sd_alpha + 1.0) ** 2
    if "d" in idx:
        var[idx["d"]] = model.drive**2
    return x0, np.diag(var)


def run_filter(
    model: StochasticModel, discrete: Discrete, record: Record, delay: int = 0, keep: bool = False
) -> Filtered:
    """The filter of ``model`` (sampled: ``discrete``) through ``record`` from :func:`start_state`, the command
    delayed by ``delay`` samples, the readings on the record's lattice; ``keep`` keeps the states for the smoother."""
    x0, P0 = start_state(model, record)
    u = np.column_stack([record.delayed(delay), np.ones(record.n)])
    discrete = replace(discrete, q=np.asarray(record.lattice, dtype=float))
    return kalman_filter(discrete, u, record.y, record.mask, x0, P0, keep=keep)


def filter_record(
    plant: Mapping[str, Any], values: Mapping[str, float], record: Record, delay: int = 0, keep: bool = False
) -> Filtered:
    """The filter of the rig ``plant`` with ``values`` (linear and noise parameters) through ``record``, its command
    delayed by ``delay`` samples (the DAQ's ``delay_samples``); ``keep`` keeps its states for the smoother."""
    model = rig_model(plant, *split_values(values), force="noise.hub_force" in values)
    return run_filter(model, model.discretise(record.Ts), record, delay, keep)


def log_likelihood(
    plant: Mapping[str, Any], values: Mapping[str, float], records: Sequence[Record], delay: int = 0
) -> float:
    """The records' summed Gaussian log-likelihood [nats] under the rig ``plant`` with ``values`` (NaN if the
    filter fails)."""
    model = rig_model(plant, *split_values(values), force="noise.hub_force" in values)
    discrete: dict[float, Discrete] = {}
    total = 0.0
    for rec in records:
        if rec.Ts not in discrete:
            discrete[rec.Ts] = model.discretise(rec.Ts)
        total += run_filter(model, discrete[rec.Ts], rec, delay).loglik
    return total


def fit(
    plant: Mapping[str, Any],
    records: Sequence[Record],
    start: Mapping[str, float],
    *,
    fixed: Mapping[str, float] | None = None,
    nominal: Mapping[str, float] | None = None,
    prior_sd: Mapping[str, float] | None = None,
    delay: int = 0,
    maxiter: int = 300,
) -> MLFit:
    """Fit the parameters ``start`` names by maximum likelihood over ``records``.

    Parameters
    ----------
    plant : mapping
        The spec's plant table (the sheet).
    records : sequence of Record
        The unit's records; they share one parameter set.
    start : mapping
        The free parameters (:data:`BOUNDS`' names) and where the search starts.
    fixed : mapping, optional
        Parameters held at these values.
    nominal : mapping, optional
        The values the bounds are factors of and the priors centred on; default ``start``.
    prior_sd : mapping, optional
        A normal prior's standard deviation in the search coordinate, by parameter (none: a flat prior).
    delay : int
        The command's delay [samples].
    maxiter : int
        The search's iterations at most.

    Returns
    -------
    MLFit
    """
    names = list(start)
    unknown = sorted(set(names) - set(BOUNDS))
    if unknown:
        raise ValueError(f"not a parameter of the likelihood engine: {', '.join(unknown)}")
    fixed, nominal, prior_sd = dict(fixed or {}), dict(nominal or start), dict(prior_sd or {})
    bounds = [BOUNDS[n] for n in names]
    walls = [b.x_range() for b in bounds]
    x0 = np.array([min(max(b.to_x(start[n], nominal[n]), lo + 1e-6), hi - 1e-6)
                   for n, b, (lo, hi) in zip(names, bounds, walls, strict=True)])  # fmt: skip
    sd = np.array([prior_sd.get(n, math.inf) for n in names])
    n_obs = int(sum(int(r.mask.sum()) for r in records))
    evaluations = 0

    def values(x: np.ndarray) -> dict[str, float]:
        return fixed | {n: b.from_x(float(v), nominal[n]) for n, b, v in zip(names, bounds, x, strict=True)}

    def objective(x: np.ndarray) -> float:  # minus the log posterior [nats]
        nonlocal evaluations
        evaluations += 1
        try:
            ll = log_likelihood(plant, values(x), records, delay)
        except ValueError:  # values the plant refuses (a damping past its range)
            return math.inf
        return math.inf if not math.isfinite(ll) else -ll + 0.5 * float(np.sum((x / sd) ** 2))

    # searched in units of a tight prior's sd (a sensor's gain known to 3e-5 would otherwise be a wall of curvature
    # a million times the others', and the search would stop where it starts)
    c = np.minimum(sd, 1.0)

    def scaled(xi: np.ndarray) -> float:
        return objective(xi * c)

    # the linear model first: the noise held at its start until the rest has been fitted, so that a white torque
    # cannot carry the hub from a start far off (its basin lies there: the drive twice too strong) nor a link's
    # torque take its gauge's noise; then all of it, the torques searched as variances (their slope at none says
    # whether any helps)
    first = np.array([n not in NOISE for n in names])
    xi, converged, message = x0 / c, True, ""
    walls_xi = [(lo / ci, hi / ci) for (lo, hi), ci in zip(walls, c, strict=True)]
    for free in (first, np.ones(len(names), bool)) if not first.all() else (first,):
        before = math.inf
        for _ in range(RESTARTS):  # L-BFGS-B can stop in a slow valley on a poor step: restarted while that pays
            xi, converged, message = _search(scaled, xi, free, walls_xi, 1.0 / max(n_obs, 1), maxiter)
            after = scaled(xi)
            if not before - after > RESTART_GAIN:
                break
            before = after
    x = xi * c
    H = _hessian(scaled, xi, walls_xi)
    try:
        se = np.sqrt(np.maximum(np.diag(np.linalg.inv(H)), 0.0)) * c
    except np.linalg.LinAlgError:
        se = np.full(x.size, math.inf)
    estimates = {}
    for i, (n, b, (lo, hi)) in enumerate(zip(names, bounds, walls, strict=True)):
        at = "lower" if x[i] <= lo + AT_BOUND else "upper" if x[i] >= hi - AT_BOUND else None
        ci = (b.from_x(float(x[i] - 1.96 * se[i]), nominal[n]), b.from_x(float(x[i] + 1.96 * se[i]), nominal[n]))
        estimates[n] = Estimate(b.from_x(float(x[i]), nominal[n]), ci, b.unit, at)
    ll = log_likelihood(plant, values(x), records, delay)
    return MLFit(estimates, ll, n_obs, len(names), evaluations, converged, message)


def _search(
    f: Callable[[np.ndarray], float],
    x0: np.ndarray,
    free: np.ndarray,
    walls: Sequence[tuple[float, float]],
    scale: float,
    maxiter: int,
) -> tuple[np.ndarray, bool, str]:
    """Minimise ``f`` (scaled by ``scale`` for L-BFGS-B's tolerances) over the coordinates ``free`` of ``x0`` within
    ``walls``, its gradient by central differences; returns the minimum, whether the search converged and why it
    stopped."""
    idx = np.flatnonzero(free)
    lo, hi = np.array(walls).T

    def full(z: np.ndarray) -> np.ndarray:
        x = x0.copy()
        x[idx] = z
        return x

    def value(z: np.ndarray) -> float:
        return min(f(full(z)) * scale, OUTSIDE)

    def gradient(z: np.ndarray) -> np.ndarray:
        g = np.empty(z.size)
        for j, i in enumerate(idx):
            up, down = full(z), full(z)
            up[i], down[i] = min(up[i] + GRAD_STEP, hi[i]), max(down[i] - GRAD_STEP, lo[i])
            g[j] = (f(up) - f(down)) / (up[i] - down[i])
        return g * scale

    res = minimize(value, x0[idx], jac=gradient, method="L-BFGS-B", bounds=[walls[int(i)] for i in idx],
                   options={"maxiter": maxiter, "ftol": TOL_NATS * scale, "gtol": 1e-7})  # fmt: skip
    return full(res.x), bool(res.success), str(res.message)


def _hessian(f: Any, x: np.ndarray, walls: Sequence[tuple[float, float]]) -> np.ndarray:
    """The Hessian of ``f`` at ``x`` by second differences of step :data:`HESS_STEP` (one-sided at a wall)."""
    p = x.size
    h = np.full(p, HESS_STEP)
    for i, (lo, hi) in enumerate(walls):  # a step that would cross a wall moves the point inside instead
        h[i] = min(HESS_STEP, max((hi - lo) / 4.0, 1e-12))
    xc = np.array([min(max(x[i], lo + h[i]), hi - h[i]) for i, (lo, hi) in enumerate(walls)])
    f0 = f(xc)
    H = np.empty((p, p))
    e = np.eye(p) * h
    fp = [f(xc + e[i]) for i in range(p)]
    fm = [f(xc - e[i]) for i in range(p)]
    for i in range(p):
        H[i, i] = (fp[i] - 2.0 * f0 + fm[i]) / h[i] ** 2
        for j in range(i):
            H[i, j] = H[j, i] = (
                f(xc + e[i] + e[j]) - f(xc + e[i] - e[j]) - f(xc - e[i] + e[j]) + f(xc - e[i] - e[j])
            ) / (4.0 * h[i] * h[j])
    return H
