"""Recalibrate a simulation's linear physical parameters against measured data (output-error least squares).

A real rig never matches its sheet. Before any unmodelled effect is blamed for a sim-to-real gap, the linear
parameters the data determine (:data:`LINEAR`: the drive's gain and time constant, the inertia ratio, the link, the
sensors' gains; :mod:`harness.diagnosis.rigmodel`) are fitted to the data by simulating the rig (the caller supplies
the residual function: it runs the plant FMU) with :func:`scipy.optimize.least_squares` (trust-region reflective),
each parameter as the log of its ratio to the spec's value. The bounds are far walls; inside them the spec's
uncertainty is a prior (``prior``: sd in log about the spec's value), a residual row w x / sd per parameter, w^2 the
residual variance per independent sample at the solution (taken again from it while it falls: the start's
variance would overweight the prior). Residuals that model error makes smooth are worth fewer samples than they
have: n (1 - rho) / (1 + rho) (:func:`effective_samples`, rho their lag-one autocorrelation up to ``max_rho``).

Intervals: cov = (J^T J / s^2 + P)^-1, s^2 = SSE / (N - p) x n / n_eff (residuals as correlated as they are, not
white), P the priors' precisions: a parameter the data do not determine keeps its prior's interval. The data were
converted to angles with calibrated sensor gains whose own errors move the fit too: given how the residuals move
with each gain (``calibration``: columns G and standard errors s_g), the intervals hold A diag(s_g^2) A^T, A = J^+ G.

A replay rough in the parameters takes another search. Through an ADC lattice or an encoder's counts in a closed loop
(``rough`` "staircase") the controller acts on quantised angles, so the whole trajectory is a staircase in the
parameters: flat to a 0.1 % step, jumping at the next; least squares stops at its start. It is fitted by Powell's
search on the same sum of squares, steps down to :data:`POWELL_XTOL`, its intervals from a Jacobian taken with steps
of :data:`STAIRCASE_STEP`. A play in a closed loop (``rough`` "jitter") makes its contacts jitter the replay about a
trend: least squares then takes its differences across the jitter, with steps of STAIRCASE_STEP, and weighs its
prior as any least squares does. Powell's search makes one pass, its prior weighed by the start's variance: it ends
on its budget, not at a minimum where the variance could be taken again, so another pass would only search on.

Without priors, a parameter the data do not determine (its 95 % interval wider than a factor
:data:`UNIDENTIFIABLE`) drifts along a flat valley of the cost; such a parameter (of those the caller names
``hold``) keeps the spec's value when that costs less than :data:`HOLD_TOLERANCE` more (:attr:`Fit.held`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Literal

import numpy as np
from scipy.optimize import OptimizeResult, least_squares, minimize


@dataclass(frozen=True)
class Bound:
    """A parameter's search range as factors ``lo``..``hi`` of its nominal value (``log``) or as absolute
    values (``log`` False: a parameter that may be zero or negative), with its unit, a plain name and the part of the
    rig (and of its spec) it belongs to."""

    lo: float
    hi: float
    unit: str
    label: str
    log: bool = True
    part: str = ""
    square: bool = False

    def to_x(self, value: float, nominal: float) -> float:
        """The search coordinate of ``value``: the log of its ratio to ``nominal``, the value itself (``log``
        False), or the square of its ratio (``square``: a noise's intensity searched as its variance, so that the
        slope at none says whether some would help)."""
        if self.square:
            return (value / nominal) ** 2
        return math.log(value / nominal) if self.log else value

    def from_x(self, x: float, nominal: float) -> float:
        """The value at the search coordinate ``x`` (the inverse of :meth:`to_x`)."""
        if self.square:
            return nominal * math.sqrt(max(x, 0.0))
        return nominal * math.exp(x) if self.log else x

    def x_range(self) -> tuple[float, float]:
        """The search coordinate's walls."""
        if self.square:
            return (self.lo**2, self.hi**2)
        return (math.log(self.lo), math.log(self.hi)) if self.log else (self.lo, self.hi)


# the rig's linear parameters as the data determine them (harness.diagnosis.rigmodel), recalibrated before any effect
# is tried; the bounds are far walls (a factor 20 on the drive), the spec's uncertainty is a prior inside them
DRIVE = "hub and drive (motor, gear and amplifier: Kg, kt, km, Rm, efficiencies, Jeq, Beq)"
LINK = "link (Ks, zeta_link, its length, mass and tip mass)"
SENSOR = "sensors (the pot's or encoder's and the strain gauge's calibration)"
LINEAR: dict[str, Bound] = {
    "rig.drive_gain": Bound(0.05, 20.0, "rad/(V s)", "drive gain (hub speed per volt)", part=DRIVE),
    "rig.drive_tau": Bound(0.05, 20.0, "s", "drive time constant", part=DRIVE),
    "rig.inertia_ratio": Bound(0.05, 20.0, "1", "hub-to-link inertia ratio", part=DRIVE),
    "plant.Ks": Bound(0.1, 10.0, "N m/rad", "link stiffness", part=LINK),
    "plant.zeta_link": Bound(0.05, 30.0, "1", "link damping ratio", part=LINK),
    "sensor.theta_gain": Bound(0.25, 4.0, "1", "hub angle sensor's gain (reading per true angle)", part=SENSOR),
    "sensor.alpha_gauge_gain": Bound(0.1, 10.0, "1", "strain gauge's gain (reading per true angle)", part=SENSOR),
    "plant.u_offset": Bound(-2.0, 2.0, "V", "command offset (the amplifier's input zero)", log=False, part=DRIVE),
}
# a closed-loop replay's own parameters (harness.diagnosis.simulation.nuisance_keys), fitted with the linear ones: its
# record's gauge offset [deg] as the record reads it, and its link's deflection from rest [deg] and rate [deg/s] at its
# start
OWN: dict[str, Bound] = {
    "sensor.alpha_offset": Bound(-30.0, 30.0, "deg", "gauge offset (its reading of the link at rest)", log=False),
    "link.alpha_start": Bound(-30.0, 30.0, "deg", "the link's deflection at the record's start", log=False),
    "link.alpha_rate": Bound(-1000.0, 1000.0, "deg/s", "the link's rate at the record's start", log=False),
}
# the physical values the fitted combos imply (rigmodel.to_plant), reported beside them: (plain name, unit)
IMPLIED: dict[str, tuple[str, str]] = {
    "plant.Jeq": ("hub inertia", "kg m^2"),
    "plant.Beq": ("viscous damping", "N m s/rad"),
    "plant.kt": ("motor gain (kt eta_g eta_m)", "N m/A"),
    "plant.km": ("back-EMF constant", "V s/rad"),
}

Residuals = Callable[[dict[str, float]], np.ndarray]
Rough = Literal["staircase", "jitter"]  # how residuals are rough in the parameters (see the module)
AT_BOUND = 0.02  # a fitted factor within 2 % (in log) of a bound sits at it
UNIDENTIFIABLE = 100.0  # a 95 % interval wider than this factor (hi / lo) says the data do not determine it
PRIOR_HELD = 0.8  # an interval at least 0.8x its prior's wide: the data did not determine the parameter
HOLD_TOLERANCE = 0.02  # an undetermined parameter keeps the spec's value when that costs < 2 % more squared error
SE_CAP = 50.0  # standard error [log of the factor] of a parameter the residuals do not determine: no interval
STAIRCASE_STEP = 0.05  # differences' step (log) where 0.1 % tells nothing: a lattice's column, a play's jitter
# a prior's weight settles: a least-squares fit is made again from its solution, the prior weighed by its residual
# variance, while the variance is under PRIOR_SETTLED x the one that weighed it, PRIOR_PASSES fits at most
PRIOR_PASSES = 8
PRIOR_SETTLED = 0.8
POWELL_XTOL = 0.01  # a derivative-free fit's smallest step: 1 % of a parameter (log)
BROYDEN_EVERY = 3  # least squares' Jacobian by differences at every third point it accepts, by Broyden's between


@dataclass
class Fit:
    """Least-squares result: ``values`` (parameter -> fitted value), ``ci95`` (parameter -> (lo, hi)), ``cost``
    = sum of squared residuals at the solution, ``nfev`` simulations used, ``n`` residuals that count, ``held``
    the parameters the data did not determine, kept at their nominal value; ``cov`` the covariance of the fitted
    parameters ``names`` in the fit's coordinates (the log of the value on a log scale, the value otherwise)."""

    values: dict[str, float]
    ci95: dict[str, tuple[float, float]]
    cost: float
    nfev: int
    n: int
    held: tuple[str, ...] = ()
    names: tuple[str, ...] = ()
    cov: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))


def fit(
    residuals: Residuals,
    bounds: Mapping[str, Bound],
    nominal: Mapping[str, float],
    start: Mapping[str, float] | None = None,
    fixed: Mapping[str, float] | None = None,
    max_nfev: int = 30,
    hold: Collection[str] = (),
    rough: Rough | None = None,
    calibration: tuple[np.ndarray, np.ndarray] | None = None,
    prior: Mapping[str, float] | None = None,
    max_rho: float = 0.999,
    local: Mapping[str, np.ndarray] | None = None,
) -> Fit:
    """Fit the parameters of ``bounds`` (FMU names, "plant.Ks") by bounded least squares on ``residuals``
    (parameter dict -> residual vector; ``fixed`` overrides are added to every call), from ``start`` (default
    ``nominal``), bounds relative to ``nominal``; ``rough``: how the residuals are rough in the parameters (see the
    module): ``"staircase"``, by Powell's search (a closed loop through a lattice; up to (parameters + 1) ``max_nfev``
    evaluations); ``"jitter"``, least squares with differences of STAIRCASE_STEP (a closed loop with a play);
    ``calibration``: how the residuals move with the log of each sensor gain (residuals x gains) and the gains'
    standard errors, which the intervals hold; ``prior``: a parameter's prior standard deviation [log] about
    ``nominal``, weighed against the residuals' variance per independent sample (:func:`effective_samples` up to
    ``max_rho``; see the module); ``local``: a parameter that moves only some residuals (a record's own gauge
    offset), with the mask of those residuals: such parameters with disjoint masks share one simulation of the
    Jacobian (:func:`grouped_jacobian`). Returns the fit with 95 % intervals from the Jacobian (and the priors);
    those of ``hold`` that the data do not determine are kept at ``nominal`` (see the module)."""
    f = _fit(residuals, bounds, nominal, start, fixed, max_nfev, rough, calibration, prior, max_rho, local)
    loose = [n for n in bounds if n in hold and not identifiable(f.ci95[n])]
    if not loose:
        return f
    at_spec = {n: float(nominal[n]) for n in loose}
    rest = {n: b for n, b in bounds.items() if n not in at_spec}
    if rest:
        start_rest = {n: v for n, v in f.values.items() if n in rest}
        g = _fit(
            residuals,
            rest,
            nominal,
            start_rest,
            {**(fixed or {}), **at_spec},
            max_nfev,
            rough,
            calibration,
            prior,
            max_rho,
            local,
        )
    else:  # nothing left to fit: the cost at the spec's values
        r = residuals({**(fixed or {}), **at_spec})
        g = Fit({}, {}, float(np.sum(r**2)), 1, int(np.count_nonzero(r)))
    if g.cost > (1.0 + HOLD_TOLERANCE) * f.cost:
        return replace(f, nfev=f.nfev + g.nfev)  # the spec's value fits clearly worse: the free fit stands
    values = {n: g.values[n] if n in g.values else at_spec[n] for n in bounds}
    ci = {n: g.ci95.get(n, f.ci95[n]) for n in bounds}
    return Fit(values, ci, g.cost, f.nfev + g.nfev, g.n, tuple(loose), g.names, g.cov)


def _fit(
    residuals: Residuals,
    bounds: Mapping[str, Bound],
    nominal: Mapping[str, float],
    start: Mapping[str, float] | None,
    fixed: Mapping[str, float] | None,
    max_nfev: int,
    rough: Rough | None = None,
    calibration: tuple[np.ndarray, np.ndarray] | None = None,
    prior: Mapping[str, float] | None = None,
    max_rho: float = 0.999,
    local: Mapping[str, np.ndarray] | None = None,
) -> Fit:
    """:func:`fit`'s one bounded least squares (or Powell search)."""
    names = list(bounds)
    derivative_free = rough == "staircase"
    fixed = dict(fixed or {})
    start = {**nominal, **(start or {})}
    lo_hi = [bounds[n].x_range() for n in names]
    x0 = np.array(
        [
            min(max(bounds[n].to_x(start[n], nominal[n]), lo + 1e-9), hi - 1e-9)
            for n, (lo, hi) in zip(names, lo_hi, strict=True)
        ]
    )

    def params(x: np.ndarray) -> dict[str, float]:
        return {**fixed, **{n: bounds[n].from_x(float(v), nominal[n]) for n, v in zip(names, x, strict=True)}}

    last: list[tuple[bytes, np.ndarray]] = []

    def data(x: np.ndarray) -> np.ndarray:  # the residuals, the last ones kept (least squares starts at x0 again)
        if not last or last[0][0] != x.tobytes():
            last[:] = [(x.tobytes(), residuals(params(x)))]
        return last[0][1]

    priors = dict(prior or {})
    sel = np.array([n in priors and bounds[n].log for n in names])
    sd = np.array([priors[n] if s else 1.0 for n, s in zip(names, sel, strict=True)])

    def variance(x: np.ndarray) -> float:  # a prior's weight: the residual variance per independent sample
        r = data(x)
        return float(np.sum(r**2)) / max(effective_samples(r, max_rho) - len(names), 1.0)

    w2 = variance(x0) if sel.any() else 0.0

    def full(x: np.ndarray) -> np.ndarray:
        return np.concatenate([data(x), math.sqrt(w2) * x[sel] / sd[sel]]) if sel.any() else data(x)

    masks = [None if local is None else local.get(n) for n in names]
    broyden = Broyden(full, lo_hi, masks, sel, STAIRCASE_STEP if rough == "jitter" else None)

    nfev, before = 0, None
    for _ in range(PRIOR_PASSES):  # the start's variance overweights the prior: again with the solution's
        if derivative_free:
            res = _powell(full, x0, lo_hi, max_nfev * (len(names) + 1))
        else:
            res = least_squares(
                full,
                x0,
                bounds=([b[0] for b in lo_hi], [b[1] for b in lo_hi]),
                method="trf",
                jac=partial(broyden, weight=w2),
                diff_step=1e-3,
                x_scale=1.0,
                max_nfev=max_nfev,
                xtol=1e-3,
                ftol=1e-4,
            )
        nfev += int(res.nfev)
        cost = float(np.sum(data(res.x) ** 2))
        if before is not None and cost > before[1]:  # a lighter prior cannot cost the data more: the search failed
            res = before[0]  # there, and the pass before stands
            break
        if derivative_free or not sel.any() or (v := variance(res.x)) > PRIOR_SETTLED * w2:
            break
        before, x0, w2 = (res, cost), res.x, v
    r = data(res.x)
    n_eff = int(np.count_nonzero(r))
    dof = max(n_eff - len(names), 1)
    s2 = float(np.sum(r**2)) / dof * n_eff / max(effective_samples(r, max_rho), 1.0)  # smooth residuals: fewer samples
    exact = broyden.exact(res.x, w2) if not derivative_free else np.array(res.jac, dtype=float)
    jac = _felt(data, res.x, r, exact[: r.size], lo_hi)
    info = jac.T @ jac / max(s2, 1e-300) + np.diag(np.where(sel, 1.0 / sd**2, 0.0))
    cov = np.linalg.pinv(info)
    if calibration is not None:  # what the sensor gains' errors move the fit by (see the module)
        g, g_se = calibration
        shift = np.linalg.pinv(jac) @ g
        cov = cov + shift @ np.diag(np.asarray(g_se, dtype=float) ** 2) @ shift.T
    se = np.minimum(np.sqrt(np.clip(np.diag(cov), 0.0, None)), SE_CAP)  # an unidentifiable direction: no bound
    se[_in_null_space(jac) & ~sel] = SE_CAP  # pinv gives a direction the residuals do not feel zero variance
    values = params(res.x)
    ci = {}
    for i, n in enumerate(names):
        lo = bounds[n].from_x(float(res.x[i] - 1.96 * se[i]), nominal[n])
        hi = bounds[n].from_x(float(res.x[i] + 1.96 * se[i]), nominal[n])
        ci[n] = (min(lo, hi), max(lo, hi))
    sd_cov = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    cov = cov / np.outer(sd_cov, sd_cov) * np.outer(se, se)  # the correlations, with the variances as capped
    return Fit({n: values[n] for n in names}, ci, float(np.sum(r**2)), nfev, n_eff, (), tuple(names), cov)


class Broyden:
    """The Jacobian least squares asks for at each point it accepts: by forward differences
    (:func:`grouped_jacobian`) every BROYDEN_EVERY points, and between them by Broyden's rank-one update from the
    last two points' residuals (J += (df - J dx) dx^T / dx^T dx), which costs no simulation. The intervals are taken
    from a Jacobian by differences at the solution (:meth:`exact`: the one least squares took there, if it did).
    ``weight``: the prior rows' weight of the residuals ``fun`` gives now; ``step``: the differences' step in the fit's
    coordinates (None: least squares' own, 0.1 % of each value)."""

    def __init__(
        self,
        fun: Callable[[np.ndarray], np.ndarray],
        lo_hi: list[tuple[float, float]],
        masks: list[np.ndarray | None],
        prior_rows: np.ndarray,
        step: float | None = None,
    ) -> None:
        self.fun, self.lo_hi, self.masks, self.prior_rows, self.step = fun, lo_hi, masks, prior_rows, step
        self.last: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self.since = 0
        self.by_differences: tuple[bytes, np.ndarray] | None = None  # the last Jacobian by differences, at x

    def exact(self, x: np.ndarray, weight: float) -> np.ndarray:
        """The Jacobian by differences at ``x`` (:func:`grouped_jacobian`), the one taken there already when the prior
        rows' ``weight`` is the same."""
        key = x.tobytes() + np.float64(weight).tobytes()
        if self.by_differences is None or self.by_differences[0] != key:
            jac = grouped_jacobian(self.fun, x, self.lo_hi, self.masks, self.prior_rows, self.step)
            self.by_differences = (key, jac)
        return self.by_differences[1]

    def __call__(self, x: np.ndarray, weight: float) -> np.ndarray:
        f = self.fun(x)
        if self.last is None or self.since + 1 >= BROYDEN_EVERY or f.size != self.last[1].size:
            jac = self.exact(x, weight)
            self.since = 0
        else:
            x0, f0, jac = self.last
            dx = x - x0
            dd = float(dx @ dx)
            jac = jac + np.outer((f - f0) - jac @ dx, dx) / dd if dd > 0 else jac
            self.since += 1
        self.last = (x.copy(), f.copy(), jac)
        return jac


def grouped_jacobian(
    fun: Callable[[np.ndarray], np.ndarray],
    x: np.ndarray,
    lo_hi: list[tuple[float, float]],
    masks: list[np.ndarray | None],
    prior_rows: np.ndarray,
    step: float | None = None,
) -> np.ndarray:
    """The forward-difference Jacobian of ``fun`` at ``x`` (steps of 0.001 x |x|, sqrt(eps) x max(1, |x|) where
    that is no step, backward at an upper bound: least squares' own rule; steps of ``step`` when given) where a column
    with a mask (``masks[j]``: the data rows it moves; None: every row) moves only those rows: columns whose masks are
    disjoint are stepped together, one evaluation for the group.
    ``prior_rows``: which parameters have a prior row after the data rows (in order), each moved by its own column
    only."""
    f0 = fun(x)
    n_data = f0.size - int(np.sum(prior_rows))
    prior_row = np.cumsum(prior_rows) - 1 + n_data
    groups: list[list[int]] = [[j] for j, m in enumerate(masks) if m is None]
    local: list[tuple[list[int], np.ndarray]] = []
    for j, m in enumerate(masks):
        if m is None:
            continue
        for cols, used in local:
            if not np.any(used & m):
                cols.append(j)
                used |= m
                break
        else:
            local.append(([j], m.copy()))
    groups += [cols for cols, _ in local]
    jac = np.zeros((f0.size, x.size))
    for cols in groups:
        h = np.zeros(x.size)
        for j in cols:
            sign = 1.0 if x[j] >= 0 else -1.0
            h[j] = sign * (1e-3 * abs(float(x[j])) if step is None else step)
            if (x[j] + h[j]) - x[j] == 0.0:  # at 0: the smallest step that tells (least squares' own rule)
                h[j] = math.sqrt(np.finfo(float).eps) * sign * max(1.0, abs(float(x[j])))
            if not lo_hi[j][0] <= x[j] + h[j] <= lo_hi[j][1]:
                h[j] = -h[j]
        df = fun(x + h) - f0
        for j in cols:
            m = masks[j]
            if m is None:  # every row
                jac[:, j] = df / h[j]
                continue
            jac[:n_data, j][m] = df[:n_data][m] / h[j]
            if prior_rows[j]:
                jac[prior_row[j], j] = df[prior_row[j]] / h[j]
    return jac


def effective_samples(r: np.ndarray, max_rho: float = 0.999) -> float:
    """How many independent samples the residuals ``r`` are worth: n (1 - rho) / (1 + rho), rho their lag-one
    autocorrelation (an AR(1) residual's; model error makes residuals smooth, rho near 1) up to ``max_rho``, zeros
    left out."""
    v = r[r != 0.0]
    if v.size < 3:
        return float(v.size)
    rho = float(np.clip(np.dot(v[1:], v[:-1]) / max(float(np.dot(v, v)), 1e-300), 0.0, max_rho))
    return v.size * (1.0 - rho) / (1.0 + rho)


def _powell(
    resid: Callable[[np.ndarray], np.ndarray], x0: np.ndarray, lo_hi: list[tuple[float, float]], max_nfev: int
) -> OptimizeResult:
    """Powell's bounded search for the least sum of squares of ``resid`` from ``x0``, returned as least squares
    returns it (x, fun, cost = half the sum of squares, nfev) with a zero Jacobian for :func:`_felt` to take."""
    p = minimize(
        lambda x: float(np.sum(resid(x) ** 2)),
        x0,
        method="Powell",
        bounds=lo_hi,
        options={"xtol": POWELL_XTOL, "ftol": 1e-4, "maxfev": max_nfev},
    )
    r = resid(p.x)
    return OptimizeResult(
        x=p.x, fun=r, cost=0.5 * float(np.sum(r**2)), nfev=int(p.nfev) + 1, jac=np.zeros((r.size, x0.size))
    )


def _felt(
    resid: Callable[[np.ndarray], np.ndarray],
    x: np.ndarray,
    r: np.ndarray,
    jac: np.ndarray,
    lo_hi: list[tuple[float, float]],
) -> np.ndarray:
    """The Jacobian ``jac`` at ``x`` (residuals ``r``) with each column that is zero taken again by a step of
    STAIRCASE_STEP: a simulation on a lattice (the ADC's, an encoder's) feels no 0.1 % step of a parameter it does
    depend on, and a zero column would read as a parameter determined to the last digit (or, once seen, as one the
    data do not determine). A column still zero after the step is a parameter the residuals do not feel."""
    norms = np.linalg.norm(jac, axis=0)
    for i in np.flatnonzero(norms <= 1e-12 * max(float(norms.max(initial=0.0)), 1e-300)):
        h = STAIRCASE_STEP if x[i] + STAIRCASE_STEP <= lo_hi[i][1] else -STAIRCASE_STEP
        step = x.copy()
        step[i] += h
        jac[:, i] = (resid(step) - r) / h
    return jac


def _in_null_space(jac: np.ndarray) -> np.ndarray:
    """Per parameter (column of the Jacobian ``jac``, residuals x parameters): does it take part in a direction the
    residuals do not feel (a singular value below 1e-9 of the largest, or every one zero)? From the eigenvectors of
    the small J^T J (parameters x parameters), never an SVD of the tall J."""
    w, v = np.linalg.eigh(jac.T @ jac)
    top = float(w.max(initial=0.0))
    null = w <= 1e-18 * top if top > 0 else np.ones(w.size, dtype=bool)
    return np.sum(v[:, null] ** 2, axis=1) > 1e-6


def at_bound(name: str, nominal: float, fitted: float) -> str | None:
    """ "lower" or "upper" when ``fitted`` ends at (within AT_BOUND of) the bound of :data:`LINEAR`, else None."""
    b = LINEAR.get(name)
    if b is None or not nominal:
        return None
    lo, hi = b.x_range()
    x = b.to_x(fitted, nominal)
    if x <= lo + AT_BOUND * (1.0 if b.log else abs(lo) or 1.0):
        return "lower"
    if x >= hi - AT_BOUND * (1.0 if b.log else abs(hi) or 1.0):
        return "upper"
    return None


def parts_at_bound(fitted: Mapping[str, tuple[float, float]]) -> list[str]:
    """Which part of the spec does not describe the rig, in words, from the linear parameters that end at their
    search bounds (``fitted``: parameter -> (nominal, fitted)): one sentence per part of :data:`LINEAR` ("the spec's
    link ... does not describe this rig: link stiffness (2x the spec) ends at its search bound"), [] when none does."""
    by_part: dict[str, list[str]] = {}
    for name, (nominal, value) in fitted.items():
        side = at_bound(name, nominal, value)
        if side is not None:
            b = LINEAR[name]
            by_part.setdefault(b.part, []).append(f"{b.label} ({value / nominal:.2g}x the spec, {side})")
    out = []
    for part, items in by_part.items():
        listed = items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]
        ends = "ends at its search bound" if len(items) == 1 else "end at their search bounds"
        out.append(f"the spec's {part} does not describe this rig: {listed} {ends}; measure "
                   f"{'it' if len(items) == 1 else 'them'} before trusting an effect's share of the gap")  # fmt: skip
    return out


def identifiable(ci95: tuple[float, float]) -> bool:
    """False when the 95 % interval of a positive parameter spans more than UNIDENTIFIABLE (or reaches 0)."""
    lo, hi = ci95
    return lo > 0 and hi / lo <= UNIDENTIFIABLE


def _label_unit(name: str) -> tuple[str, str]:
    """A parameter's plain name and its unit as a sentence ends a value with (" N m/rad"; "" for a ratio)."""
    b = LINEAR.get(name)
    label, unit = (b.label, b.unit) if b else IMPLIED.get(name, (name, "1"))
    return label, (f" {unit}" if unit != "1" else "")


def kept_finding(name: str, nominal: float) -> str:
    """The sentence of a linear parameter kept at the spec's value ``nominal`` because recalibrating did not improve
    the held-out fit (not fitted)."""
    label, unit = _label_unit(name)
    return f"{label} kept at the spec's {nominal:.4g}{unit}: recalibrating did not improve the held-out fit"


def offset_finding(name: str, fitted: float, ci95: tuple[float, float]) -> str:
    """The sentence of an offset fitted about 0 (the command offset): "command offset (the amplifier's input zero)
    -0.121 V (95 % interval -0.123..-0.119)", "... 0.002 V: none (95 % interval ...)" when the interval holds 0."""
    b = LINEAR.get(name)
    label, unit = (b.label, b.unit) if b else (name, "")
    none = ": none" if ci95[0] <= 0.0 <= ci95[1] else ""
    return f"{label} {fitted:+.3g} {unit}{none} (95 % interval {ci95[0]:+.3g}..{ci95[1]:+.3g})"


def finding(name: str, nominal: float, fitted: float, ci95: tuple[float, float], prior: float | None = None) -> str:
    """One sentence a lab report would print: "the link stiffness is 15 % higher than the spec (1.3 -> 1.5 N
    m/rad)", or "matches the spec" when the spec's value lies inside the 95 % interval or within 3 %; "at its upper
    bound (1.6x the spec): the spec may not describe this rig" when the fit ended at a bound of :data:`LINEAR`;
    "not identifiable from these data" when its interval spans more than UNIDENTIFIABLE (", kept at the spec's value"
    when the fit held it there); "not determined by these data" when its interval is nearly its ``prior``'s (sd [log]:
    the data narrowed it by less than PRIOR_HELD)."""
    label, unit = _label_unit(name)
    side = at_bound(name, nominal, fitted)
    if side is not None:
        return (f"{label} at its {side} bound ({fitted / nominal:.2g}x the spec: {nominal:.4g} -> {fitted:.4g}{unit}): "
                "the spec may not describe this rig")  # fmt: skip
    if not identifiable(ci95):
        interval = f"95 % interval {ci95[0]:.3g}..{ci95[1]:.3g}"
        if fitted == nominal:  # held at the spec's value: the data fit as well there (see the module)
            return f"{label} is not identifiable from these data: kept at the spec's {nominal:.4g}{unit} ({interval})"
        return (
            f"{label} is not identifiable from these data (fitted {fitted:.4g}{unit}, {interval}; spec {nominal:.4g})"
        )
    if prior and ci95[0] > 0 and math.log(ci95[1] / ci95[0]) > PRIOR_HELD * 2 * 1.96 * prior:
        return (f"{label} is not determined by these data: it stays near the spec's {nominal:.4g}{unit} within its "
                f"prior (fitted {fitted:.4g}, 95 % interval {ci95[0]:.3g}..{ci95[1]:.3g})")  # fmt: skip
    change = 100.0 * (fitted / nominal - 1.0) if nominal else math.nan
    if (ci95[0] <= nominal <= ci95[1]) or abs(change) < 3.0:
        return f"{label} matches the spec ({nominal:.4g}{unit}, fitted {fitted:.4g})"
    word = "higher" if change > 0 else "lower"
    return f"{label} is {abs(change):.0f} % {word} than the spec ({nominal:.4g} -> {fitted:.4g}{unit})"
