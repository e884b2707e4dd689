"""The rig's parameters by maximum likelihood over the records of one unit, with intervals from the information.

The records share one parameter set (the linear parameters of :data:`harness.diagnosis.recalibrate.LINEAR` and the
noise's of :data:`harness.likelihood.model.NOISE`); each record has its own start (the filter's first state, wide
enough that the first samples decide it) and gauge offset (a state). The objective is the records' summed Gaussian
log-likelihood (:func:`log_likelihood`) plus the priors the caller gives (a normal in the search coordinate: the log
of a parameter's ratio to its nominal value, or the value itself; :class:`harness.diagnosis.recalibrate.Bound`),
maximised within the bounds by scoring (Levenberg-Marquardt on the filter's prediction errors, :func:`_ascend`), in
units of a prior's sd where that is tighter than the coordinate's own. The linear model first: the noise is held at
its start (:func:`noise_start`) until the linear parameters have been fitted, then all are freed, the torques'
intensities searched as variances.
The intervals come from the Fisher information at the maximum, the Jacobian of the prediction errors (Ljung's
covariance of the prediction-error estimate; a lattice's readings taken as Gaussian with its q^2 / 12, which errs
wide): 95 %, symmetric in the search coordinate.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ..diagnosis.recalibrate import LINEAR, Bound
from ..workercall import one_blas_thread
from .kalman import Discrete, Filtered, kalman_filter
from .model import EFFECTS, NOISE, SENSORS, Noise, StochasticModel, rig_model
from .record import Record
from .robust import inflation, long_run

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

BOUNDS: dict[str, Bound] = {**LINEAR, **SENSORS, **EFFECTS, **NOISE}
TORQUES = ("noise.hub_torque", "noise.link_torque")  # the process noise: freed once the rest is fitted
GRAD_STEP = 1e-5  # search-coordinate step of the gradient's forward differences
TOL_NATS = 1e-4  # the search stops when a step gains less log-likelihood than this [nats]
LM_START, LM_FACTOR, LM_GIVE_UP = 1e-3, 10.0, 1e8  # Levenberg-Marquardt's damping: its least, its factor, its most
AT_BOUND = 1e-3  # a parameter this close to a wall (in the search coordinate) ends at its bound


@dataclass(frozen=True)
class Estimate:
    """A fitted parameter: its ``value``, its 95 % interval ``ci95``, its ``unit``, ``at`` "lower" or "upper"
    when it ends at a bound (else None), and the ``inflation`` of its variance where the prediction errors are not
    independent: the sandwich's over the information's (:func:`harness.likelihood.robust.inflation`; 1 where the
    scores are white, NaN where the information gives none)."""

    value: float
    ci95: tuple[float, float]
    unit: str
    at: str | None = None
    inflation: float = 1.0


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
    """Parameters by name as :func:`harness.likelihood.model.rig_model` takes them: the linear ones, the sensors'
    dynamics and the effects, and the noise."""
    keep = {k: v for k, v in values.items() if k in LINEAR or k in SENSORS or k in EFFECTS}
    return keep, Noise.from_values(values)


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
    the force up to the drive's at 1 V); with a play, the teeth anywhere in it (uniformly) and the motor at the
    hub's speed."""
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
    if "gauge" in idx:  # the gauge's low-pass output: as the link's deflection
        var[idx["gauge"]] = (amp + 1.0) ** 2
    if "d" in idx:
        var[idx["d"]] = model.drive**2
    P0 = np.diag(var)
    if "gap" in idx:  # the teeth anywhere in the play, the motor turning with the hub
        P0[idx["gap"], idx["gap"]] = model.play**2 / 12.0
        w, v = idx["motor_speed"], idx["theta_dot"]
        P0[w, v] = P0[v, w] = P0[w, w] = var[v]
    return x0, P0


def run_filter(
    model: StochasticModel, discrete: Discrete, record: Record, delay: int = 0, keep: bool = False
) -> Filtered:
    """The filter of ``model`` (sampled: ``discrete``) through ``record`` from :func:`start_state`, the command
    delayed by ``delay`` samples (through the amplifier's limit: :meth:`StochasticModel.inputs`), the readings on the
    record's lattice; ``keep`` keeps the states for the smoother."""
    x0, P0 = start_state(model, record)
    u = model.inputs(record.delayed(delay))
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
    return innovations(plant, values, records, delay).loglik


@dataclass(frozen=True)
class Innovations:
    """The records' summed log-likelihood ``loglik`` [nats] and, one after another, their measured readings'
    innovations ``e`` [deg], predicted variances ``s`` [deg^2], terms of the log-likelihood ``terms`` [nats],
    whether each sits on a lattice (``cell``), and the ``record`` and ``sample`` it was read at: what a scoring step
    and the scores' long-run covariance need of a filter's pass."""

    loglik: float
    e: np.ndarray
    s: np.ndarray
    terms: np.ndarray
    cell: np.ndarray
    record: np.ndarray
    sample: np.ndarray


def innovations(
    plant: Mapping[str, Any], values: Mapping[str, float], records: Sequence[Record], delay: int = 0
) -> Innovations:
    """The filter of the rig ``plant`` with ``values`` through ``records``: :class:`Innovations` (BLAS on one thread:
    its matrices are small, and a second thread only contends for the cores)."""
    # a search's trial far off can overflow the sampling's exponentials: its log-likelihood is then NaN (the search
    # steps back), not a warning on the user's screen
    with one_blas_thread(), np.errstate(over="ignore", invalid="ignore"):
        model = rig_model(plant, *split_values(values), force="noise.hub_force" in values)
        discrete: dict[float, Discrete] = {}
        total, parts = 0.0, []
        for i, rec in enumerate(records):
            if rec.Ts not in discrete:
                discrete[rec.Ts] = model.discretise(rec.Ts)
            f = run_filter(model, discrete[rec.Ts], rec, delay)
            total += f.loglik
            cell = np.broadcast_to(np.asarray(rec.lattice) > 0, f.e.shape)
            at = np.broadcast_to(np.arange(rec.n)[:, None], f.e.shape)
            parts.append([a[rec.mask] for a in (f.e, f.s, f.terms, cell, np.full(f.e.shape, i), at)])
    return Innovations(total, *(np.concatenate(p) for p in zip(*parts, strict=True)))


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

    def point(xi: np.ndarray) -> tuple[float, Innovations | None]:  # the log posterior [nats], the innovations
        nonlocal evaluations
        evaluations += 1
        x = xi * c
        try:
            inn = innovations(plant, values(x), records, delay)
        except ValueError:  # values the plant refuses (a damping past its range)
            return -math.inf, None
        if not math.isfinite(inn.loglik):
            return -math.inf, None
        return inn.loglik - 0.5 * float(np.sum((x / sd) ** 2)), inn

    # searched in units of a tight prior's sd (a sensor's gain known to 3e-5 would otherwise be a wall of curvature
    # a million times the others')
    c = np.minimum(sd, 1.0)
    # the linear model first: the noise held at its start until the rest has been fitted, so that a white torque
    # cannot carry the hub from a start far off (its basin lies there: the drive twice too strong) nor a link's
    # torque take its gauge's noise; then all of it, the torques searched as variances (their slope at none says
    # whether any helps)
    first = np.array([n not in NOISE for n in names])
    xi, converged, message = x0 / c, True, ""
    walls_xi = [(lo / ci, hi / ci) for (lo, hi), ci in zip(walls, c, strict=True)]
    for free in (first, np.ones(len(names), bool)) if not first.all() else (first,):
        xi, converged, message = _ascend(point, xi, free, walls_xi, (c / sd) ** 2, maxiter)
    x = xi * c
    se = np.full(x.size, math.inf)  # no interval where the information is not positive
    grown = np.full(x.size, math.nan)
    f, inn = point(xi)
    if inn is not None:
        sl = _slopes(point, xi, f, inn, np.arange(xi.size), walls_xi)
        var = np.diag(np.linalg.pinv(sl.fisher(inn, (c / sd) ** 2)))
        se[sl.idx] = np.where(var > 0.0, np.sqrt(np.abs(var)), math.inf) * c[sl.idx]
        grown[sl.idx] = inflation(long_run(sl.Jl, inn.record, inn.sample))
    estimates = {}
    for i, (n, b, (lo, hi)) in enumerate(zip(names, bounds, walls, strict=True)):
        at = "lower" if x[i] <= lo + AT_BOUND else "upper" if x[i] >= hi - AT_BOUND else None
        ends = np.clip([x[i] - 1.96 * se[i], x[i] + 1.96 * se[i]], lo, hi)  # an interval ends at the bounds
        lo_hi = sorted(b.from_x(float(v), nominal[n]) for v in ends)  # sorted: a falling map (a limit's share)
        estimates[n] = Estimate(b.from_x(float(x[i]), nominal[n]), (lo_hi[0], lo_hi[1]), b.unit, at, float(grown[i]))
    ll = inn.loglik if inn is not None else log_likelihood(plant, values(x), records, delay)  # the pass at x
    return MLFit(estimates, ll, n_obs, len(names), evaluations, converged, message)


@dataclass(frozen=True)
class _Slopes:
    """Forward differences at a point of the search: the coordinates ``idx`` they were taken on, the log posterior's
    slopes ``g`` and the innovations', their variances' and the likelihood terms' (``Je``, ``Js``, ``Jl``: one column
    per coordinate)."""

    idx: np.ndarray
    g: np.ndarray
    Je: np.ndarray
    Js: np.ndarray
    Jl: np.ndarray

    def fisher(self, inn: Innovations, prior_curvature: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """The Fisher information of the readings' Gaussian law (a lattice's q^2 / 12 in their variance; only the
        readings ``rows`` where given) plus the priors' curvature: sum_k (de/dx)^2 / s + (ds/dx)^2 / (2 s^2)."""
        on = slice(None) if rows is None else rows
        Je, Js, s = self.Je[on], self.Js[on], inn.s[on][:, None]
        return Je.T @ (Je / s) + 0.5 * Js.T @ (Js / s**2) + np.diag(prior_curvature[self.idx])


def _slopes(
    point: Callable[[np.ndarray], tuple[float, Innovations | None]],
    x: np.ndarray,
    f: float,
    inn: Innovations,
    coords: np.ndarray,
    walls: Sequence[tuple[float, float]],
    leaning: bool = True,
) -> _Slopes:
    """:class:`_Slopes` at ``x`` (log posterior ``f``, innovations ``inn``) along ``coords``, each step inward from
    a wall; a coordinate past which the model fails is left out, and unless ``leaning``, one at a wall that its
    slope leans against."""
    g, de, ds, dl, idx = [], [], [], [], []
    for i in coords:
        lo, hi = walls[i]
        h = GRAD_STEP if x[i] + GRAD_STEP <= hi else -GRAD_STEP
        xp = x.copy()
        xp[i] += h
        fp, ip = point(xp)
        if ip is None:  # past where the model holds
            continue
        gi = (fp - f) / h
        if not leaning and ((x[i] <= lo and gi <= 0.0) or (x[i] >= hi and gi >= 0.0)):
            continue
        g.append(gi)
        de.append((ip.e - inn.e) / h)
        ds.append((ip.s - inn.s) / h)
        dl.append((ip.terms - inn.terms) / h)
        idx.append(i)
    n = inn.e.size
    cols = [np.array(a).T if a else np.zeros((n, 0)) for a in (de, ds, dl)]
    return _Slopes(np.array(idx, dtype=int), np.array(g), *cols)


def _ascend(
    point: Callable[[np.ndarray], tuple[float, Innovations | None]],
    x0: np.ndarray,
    free: np.ndarray,
    walls: Sequence[tuple[float, float]],
    prior_curvature: np.ndarray,
    maxiter: int,
) -> tuple[np.ndarray, bool, str]:
    """Maximise the log posterior ``point`` gives over the coordinates ``free`` of ``x0`` within ``walls`` by scoring
    (Levenberg-Marquardt on the prediction errors, as Ljung's prediction-error method does it): the gradient by
    forward differences of the log posterior; the curvature from the same passes, the Fisher information of the
    readings' Gaussian law, (de/dx)^2 / s + (ds/dx)^2 / (2 s^2) summed (s with a lattice's q^2 / 12), plus the
    priors' ``prior_curvature``. A reading on a lattice is not Gaussian (its cell's probability): where there are
    some, a second step takes their curvature as the square of their terms' slopes (Berndt-Hall-Hall-Hausman), and
    the step that gains more is taken (the Gaussian's leads from far off, the cells' near a noise below the step).
    A step is taken where it gains, and where it gains more than its quadratic promised, the search goes on along it,
    twice as far each time, while that gains; a coordinate at a wall that its gradient leans against is held.
    Returns the maximum, whether the search converged (a step gains under :data:`TOL_NATS`, or none gains) and why
    it stopped."""
    lo, hi = np.array(walls).T
    x = x0.copy()
    f, inn = point(x)
    if inn is None:
        return x, False, "the search's start is outside the model"
    lam = LM_START
    for _ in range(maxiter):
        sl = _slopes(point, x, f, inn, np.flatnonzero(free), walls, leaning=False)
        if not sl.idx.size:
            return x, True, "every coordinate at a wall it leans against"
        idx, gv = sl.idx, sl.g
        curvatures = [sl.fisher(inn, prior_curvature)]
        if inn.cell.any():  # a lattice: its cells' own curvature beside the Gaussian's, the step that gains more
            Jl = sl.Jl[inn.cell]
            curvatures.append(sl.fisher(inn, prior_curvature, rows=~inn.cell) + Jl.T @ Jl)
        while True:
            steps = []
            for F in curvatures:
                step = np.linalg.lstsq(F + lam * np.diag(np.diag(F)), gv, rcond=None)[0]
                xn = x.copy()
                xn[idx] = np.clip(x[idx] + step, lo[idx], hi[idx])
                fn, i_n = point(xn)
                steps.append((fn, xn, i_n, float(gv @ step - 0.5 * step @ F @ step)))
            fn, xn, i_n, promised = max(steps, key=lambda t: t[0])
            if i_n is not None and fn > f:
                while fn - f > promised:  # the quadratic undersells the way: on along it, twice as far each time
                    xe = x.copy()
                    xe[idx] = np.clip(x[idx] + 2.0 * (xn[idx] - x[idx]), lo[idx], hi[idx])
                    fe, i_e = point(xe)
                    if i_e is None or fe <= fn:
                        break
                    promised = 2.0 * (fn - f)
                    xn, fn, i_n = xe, fe, i_e
                gain, x, f, inn = fn - f, xn, fn, i_n
                lam = max(lam / LM_FACTOR, LM_START)
                break
            lam *= LM_FACTOR
            if lam > LM_GIVE_UP:
                return x, True, "no step gains"
        if gain < TOL_NATS:
            return x, True, "a step gains under the tolerance"
    return x, False, f"{maxiter} iterations"
