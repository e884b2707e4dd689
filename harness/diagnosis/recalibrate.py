"""Recalibrate a simulation's linear physical parameters against measured data (output-error least squares).

A real rig never matches its datasheet: viscous damping, link stiffness, link damping, inertia and motor gain
are 10 to 50 % off. Before any unmodelled effect is blamed for a sim-to-real gap, those parameters are fitted
to the data by simulating the rig (the caller supplies the residual function: it runs the plant FMU) with
:func:`scipy.optimize.least_squares` (trust-region reflective, bounded), each parameter as the log of its ratio
to the spec's value (so bounds are factors and steps are relative). Standard errors come from the Jacobian at
the solution, cov = s^2 (J^T J)^-1 with s^2 = SSE / (N - p): the usual output-error intervals, which assume
white residuals and are therefore optimistic when model error, not noise, dominates (said in the report).

:data:`LINEAR` is the table of what is recalibrated and within which physical bounds. The motor gain is one
factor on kt * eta_g * eta_m: kt carries it (drive torque and back-EMF damping both scale with it, as they do
with the efficiencies, and kt has no upper bound of 1).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares


@dataclass(frozen=True)
class Bound:
    """A parameter's search range as factors ``lo``..``hi`` of its nominal value (``log``) or as absolute
    values (``log`` False: a parameter that may be zero or negative), with its unit and a plain name."""

    lo: float
    hi: float
    unit: str
    label: str
    log: bool = True


# linear physical parameters of the plant, recalibrated before any effect is tried
LINEAR: dict[str, Bound] = {
    "plant.Beq": Bound(0.2, 5.0, "N m s/rad", "viscous damping"),
    "plant.Ks": Bound(0.5, 2.0, "N m/rad", "link stiffness"),
    "plant.zeta_link": Bound(0.2, 10.0, "1", "link damping ratio"),
    "plant.Jeq": Bound(0.6, 1.6, "kg m^2", "hub inertia"),
    "plant.kt": Bound(0.6, 1.5, "N m/A", "motor gain (kt eta_g eta_m)"),
}

Residuals = Callable[[dict[str, float]], np.ndarray]


@dataclass
class Fit:
    """Least-squares result: ``values`` (parameter -> fitted value), ``ci95`` (parameter -> (lo, hi)), ``cost``
    = sum of squared residuals at the solution, ``nfev`` simulations used, ``n`` residuals that count."""

    values: dict[str, float]
    ci95: dict[str, tuple[float, float]]
    cost: float
    nfev: int
    n: int


def _to_x(value: float, nominal: float, b: Bound) -> float:
    return math.log(value / nominal) if b.log else value


def _from_x(x: float, nominal: float, b: Bound) -> float:
    return nominal * math.exp(x) if b.log else x


def _x_bounds(b: Bound) -> tuple[float, float]:
    return (math.log(b.lo), math.log(b.hi)) if b.log else (b.lo, b.hi)


def fit(
    residuals: Residuals,
    bounds: Mapping[str, Bound],
    nominal: Mapping[str, float],
    start: Mapping[str, float] | None = None,
    fixed: Mapping[str, float] | None = None,
    max_nfev: int = 30,
) -> Fit:
    """Fit the parameters of ``bounds`` (FMU names, "plant.Ks") by bounded least squares on ``residuals``
    (parameter dict -> residual vector; ``fixed`` overrides are added to every call), from ``start`` (default
    ``nominal``), bounds relative to ``nominal``. Returns the fit with 95 % intervals from the Jacobian."""
    names = list(bounds)
    fixed = dict(fixed or {})
    start = {**nominal, **(start or {})}
    lo_hi = [_x_bounds(bounds[n]) for n in names]
    x0 = np.array(
        [
            min(max(_to_x(start[n], nominal[n], bounds[n]), lo + 1e-9), hi - 1e-9)
            for n, (lo, hi) in zip(names, lo_hi, strict=True)
        ]
    )

    def params(x: np.ndarray) -> dict[str, float]:
        return {**fixed, **{n: _from_x(float(v), nominal[n], bounds[n]) for n, v in zip(names, x, strict=True)}}

    res = least_squares(
        lambda x: residuals(params(x)),
        x0,
        bounds=([b[0] for b in lo_hi], [b[1] for b in lo_hi]),
        method="trf",
        diff_step=1e-3,
        x_scale=1.0,
        max_nfev=max_nfev,
        xtol=1e-3,
        ftol=1e-4,
    )
    r = res.fun
    n_eff = int(np.count_nonzero(r))
    dof = max(n_eff - len(names), 1)
    s2 = 2.0 * float(res.cost) / dof
    cov = s2 * np.linalg.pinv(res.jac.T @ res.jac)
    se = np.minimum(np.sqrt(np.clip(np.diag(cov), 0.0, None)), 50.0)  # an unidentifiable direction: no bound
    values = params(res.x)
    ci = {}
    for i, n in enumerate(names):
        lo = _from_x(float(res.x[i] - 1.96 * se[i]), nominal[n], bounds[n])
        hi = _from_x(float(res.x[i] + 1.96 * se[i]), nominal[n], bounds[n])
        ci[n] = (min(lo, hi), max(lo, hi))
    return Fit({n: values[n] for n in names}, ci, float(2.0 * res.cost), int(res.nfev), n_eff)


AT_BOUND = 0.02  # a fitted factor within 2 % (in log) of a bound sits at it
UNIDENTIFIABLE = 100.0  # a 95 % interval wider than this factor (hi / lo) says the data do not determine it


def at_bound(name: str, nominal: float, fitted: float) -> str | None:
    """ "lower" or "upper" when ``fitted`` ends at (within AT_BOUND of) the bound of :data:`LINEAR`, else None."""
    b = LINEAR.get(name)
    if b is None or not nominal:
        return None
    lo, hi = _x_bounds(b)
    x = _to_x(fitted, nominal, b)
    if x <= lo + AT_BOUND * (1.0 if b.log else abs(lo) or 1.0):
        return "lower"
    if x >= hi - AT_BOUND * (1.0 if b.log else abs(hi) or 1.0):
        return "upper"
    return None


def identifiable(ci95: tuple[float, float]) -> bool:
    """False when the 95 % interval of a positive parameter spans more than UNIDENTIFIABLE (or reaches 0)."""
    lo, hi = ci95
    return lo > 0 and hi / lo <= UNIDENTIFIABLE


def finding(name: str, nominal: float, fitted: float, ci95: tuple[float, float]) -> str:
    """One sentence a lab report would print: "the link stiffness is 15 % higher than the spec (1.3 -> 1.5 N
    m/rad)", or "matches the spec" when the spec's value lies inside the 95 % interval or within 3 %; "at its upper
    bound (1.6x the spec): the spec may not describe this rig" when the fit ended at a bound of :data:`LINEAR`;
    "not identifiable from these data" when its interval spans more than UNIDENTIFIABLE."""
    b = LINEAR.get(name)
    label = b.label if b else name
    unit = f" {b.unit}" if b and b.unit != "1" else ""
    side = at_bound(name, nominal, fitted)
    if side is not None:
        return (f"{label} at its {side} bound ({fitted / nominal:.2g}x the spec: {nominal:.4g} -> {fitted:.4g}{unit}): "
                "the spec may not describe this rig")  # fmt: skip
    if not identifiable(ci95):
        return (f"{label} is not identifiable from these data (fitted {fitted:.4g}{unit}, 95 % interval "
                f"{ci95[0]:.3g}..{ci95[1]:.3g}; spec {nominal:.4g})")  # fmt: skip
    change = 100.0 * (fitted / nominal - 1.0) if nominal else math.nan
    if (ci95[0] <= nominal <= ci95[1]) or abs(change) < 3.0:
        return f"{label} matches the spec ({nominal:.4g}{unit}, fitted {fitted:.4g})"
    word = "higher" if change > 0 else "lower"
    return f"{label} is {abs(change):.0f} % {word} than the spec ({nominal:.4g} -> {fitted:.4g}{unit})"
