"""The diagnosis's simulations as tasks of a :class:`harness.executor.Executor`.

The setup (simulation, real experiments, FMU bytes) is sent to every worker once and each worker loads the rig
once. Nine tasks, given as ``(kind, *args)`` calls to :meth:`Pool.map`:

- ``("sse", over, names[, window])``: squared errors per experiment and channel with overrides ``over``;
- ``("fit", effect, base, fit, every)``: :func:`screen_effect`, one effect's parameter alone on top of ``base``;
- ``("refit", base, free, fit, every[, max_nfev])``: :func:`joint_refit`, the linear parameters (and the
  continuous effect parameters ``free``) by output-error least squares;
- ``("recal", fit, every[, start])``: :func:`recalibrate`, the linear parameters from a grid of the sheet's values
  (and from ``start``);
- ``("resid", over, names, k)``: :func:`residual_vector`, a stretch of a residual vector, for a least squares run
  by the client (:meth:`Pool.refit`);
- ``("where", over)``: :func:`where`, where the gap lies;
- ``("loopnoise", over, names)``: :func:`loop_noise`, what the noise a closed loop feeds back leaves, per experiment;
- ``("spread", over, names)``: :func:`spread`, a closed-loop replay's gap beside its own spread, window by window;
- ``("replay", over)``: :func:`replay`, every experiment's simulated angles, for the report's replay figures.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Collection
from typing import Any

import numpy as np
from scipy.optimize import minimize_scalar

from ..executor import Executor, one_blas_thread, worker_rig
from . import recalibrate as recal
from .effects import BY_PARAM, Effect
from .experiments import CHANNELS
from .simulation import (
    SSE,
    Setup,
    lattice_in_loop,
    loop_noise_gap,
    loop_spread,
    mean_squared_gap,
    replay_traces,
    residuals,
)
from .where import where_gap

SENSOR_CHANNELS = {"theta": "sensor.theta_gain", "alpha": "sensor.alpha_gauge_gain"}

__all__ = [
    "Pool",
    "joint_refit",
    "least_squares_refit",
    "loop_noise",
    "moving_channels",
    "replay",
    "residual_vector",
    "screen_effect",
    "spread",
    "squared_errors",
    "stretches",
    "where",
]

Progress = Callable[[str], None]

_CTX: dict[str, Any] = {}


def _bind(setup: Setup) -> None:
    """Make ``setup`` and its rig (loaded once per process, from the FMU bytes) the current ones of this process."""
    _CTX["setup"] = setup
    _CTX["rig"] = worker_rig(setup.fmus)


def squared_errors(over: dict[str, Any], names: list[str], window: str = "all") -> SSE:
    """Squared errors [deg^2] per experiment and channel for overrides ``over`` over a window (see
    :meth:`harness.diagnosis.experiments.RigExperiment.window`)."""
    setup: Setup = _CTX["setup"]
    out = {}
    for n in names:
        x = setup.experiments[n]
        e = residuals(_CTX["rig"], setup, x, over, x.window(window)[0])
        out[n] = {c: float(np.sum(e[c] ** 2)) for c in CHANNELS}
    return out


def moving_channels(setup: Setup, names: list[str]) -> int:
    """K: how many experiment-channels of ``names`` move over their fit windows (sst > 0)."""
    return sum(1 for n in names for c in CHANNELS if setup.experiments[n].sst_fit[c] > 0)


def residual_vector(over: dict[str, Any], names: list[str], k: int | None = None) -> np.ndarray:
    """The fit windows' residuals of ``names``, each channel scaled by 1 / sqrt(K sst) so that the sum of
    squares is the mean squared gap (K = number of experiment-channels that move, :func:`moving_channels` of
    ``names`` unless given: ``names`` are then a stretch of a longer vector): what least squares minimises."""
    setup: Setup = _CTX["setup"]
    parts = []
    k = moving_channels(setup, names) if k is None else k
    for n in names:
        x = setup.experiments[n]
        e = residuals(_CTX["rig"], setup, x, over, x.n_fit)
        parts += [e[c] / math.sqrt(k * x.sst_fit[c]) for c in CHANNELS if x.sst_fit[c] > 0]
    return np.concatenate(parts)


def gain_columns(setup: Setup, names: list[str], fitted: Collection[str] = ()) -> tuple[np.ndarray, np.ndarray] | None:
    """How :func:`residual_vector` of ``names`` moves with the log of each sensor's calibration gain (the measured
    channel, masked and scaled alike; an open-loop replay's theta less its mean, which the replay's offset takes),
    and each gain's relative standard error (:attr:`Setup.gain_rel_se`): (columns, se), None when no gain's error
    is known; the channels ``fitted`` (their sensor's gain is fitted) have none."""
    se = np.array([0.0 if c in fitted else setup.gain_rel_se.get(c, 0.0) for c in CHANNELS])
    if not np.any(se > 0):
        return None
    k = moving_channels(setup, names)
    blocks = []
    for n in names:
        x = setup.experiments[n]
        for i, c in enumerate(CHANNELS):
            if x.sst_fit[c] <= 0:
                continue
            ok = x.valid[c][: x.n_fit]
            y = np.where(ok, (x.theta if c == "theta" else x.alpha)[: x.n_fit], 0.0)
            if c == "theta" and x.replay == "open" and ok.any():
                y = np.where(ok, y - float(np.mean(y[ok])), 0.0)
            col = np.zeros((y.size, len(CHANNELS)))
            col[:, i] = y / math.sqrt(k * x.sst_fit[c])
            blocks.append(col)
    return np.concatenate(blocks), se


def _screen_msg(over: dict[str, Any], names: list[str]) -> float:
    """Mean squared gap of ``names`` over their screening windows."""
    return mean_squared_gap(squared_errors(over, names, "screen"), _CTX["setup"].experiments, names, "screen")


def _fit_continuous(eff: Effect, base: dict[str, Any], names: list[str]) -> tuple[float, float, int]:
    """Coarse grid over [lo, hi] (log or linear) then bounded Brent on the best bracket; returns (value, mean
    squared gap on ``names``' screening windows, evaluations)."""
    log = eff.kind == "log"
    fwd = (lambda x: math.log(x)) if log else (lambda x: x)
    inv = (lambda s: math.exp(s)) if log else (lambda s: s)
    s_lo, s_hi = fwd(eff.lo), fwd(eff.hi)
    pts = np.linspace(s_lo, s_hi, eff.grid)
    vals = [_screen_msg({**base, eff.param: inv(s)}, names) for s in pts]
    i = int(np.argmin(vals))
    best_s, best_v = float(pts[i]), float(vals[i])
    res = minimize_scalar(
        lambda s: _screen_msg({**base, eff.param: inv(s)}, names),
        bounds=(pts[max(i - 1, 0)], pts[min(i + 1, eff.grid - 1)]),
        method="bounded",
        options={"xatol": 0.01 if log else 0.002 * (s_hi - s_lo), "maxiter": 10},
    )
    if res.fun < best_v:
        best_s, best_v = float(res.x), float(res.fun)
    return inv(best_s), best_v, eff.grid + int(res.nfev)


def screen_effect(eff: Effect, base: dict[str, Any], fit: list[str], every: list[str]) -> dict[str, Any]:
    """Screen one effect on top of ``base`` on experiments ``fit`` (their first SCREEN_SECONDS): integers
    enumerated, continuous parameters on a coarse grid and a bounded Brent refinement; squared errors on
    ``every`` experiment. Returns effect, params, fit_msg (mean squared gap on the fit), sse, evaluations."""
    if eff.kind == "int":
        scores = [(_screen_msg({**base, eff.param: v}, fit), v) for v in eff.values]
        msg_fit, value = min(scores, key=lambda s: (s[0], s[1]))
        value, n = int(value), len(scores)
    else:
        value, msg_fit, n = _fit_continuous(eff, base, fit)
    return {
        "effect": eff.name,
        "params": {eff.param: value},
        "fit_msg": msg_fit,
        "sse": squared_errors({**base, eff.param: value}, every),
        "evaluations": n + len(every),
    }


def joint_refit(
    base: dict[str, Any], free: list[str], fit: list[str], every: list[str], max_nfev: int = 30
) -> dict[str, Any]:
    """Output-error least squares of the linear parameters (:data:`harness.diagnosis.recalibrate.LINEAR`) and the
    continuous effect parameters named in ``free`` (with their secondary parameters), from their values in
    ``base`` (linear ones default to the sim's), on the fit windows of ``fit`` (:func:`least_squares_refit`);
    squared errors on ``every``. Returns params, ci95, fit_msg (the mean squared gap at the solution), evaluations,
    sse."""
    res = least_squares_refit(_CTX["setup"], lambda over: residual_vector(over, fit), base, free, fit, max_nfev)
    return {**res, "sse": squared_errors(res["params"], every) if every else {}}


# the global search's grids, factors of the sheet's value, one plane after the other: the drive within a factor 3,
# then the link within a factor 2 and the inertia ratio within 3
GRIDS: tuple[dict[str, tuple[float, ...]], ...] = (
    {"rig.drive_gain": (1 / 3, 3**-0.5, 1.0, 3**0.5, 3.0), "rig.drive_tau": (1 / 3, 3**-0.5, 1.0, 3**0.5, 3.0)},
    {"plant.Ks": (0.5, 2**-0.5, 1.0, 2**0.5, 2.0), "rig.inertia_ratio": (1 / 3, 1.0, 3.0)},
)


CORRELATION_SECONDS = 0.05  # s: the longest a residual's correlation time counts (smoother: model error, not noise)
RECAL_NFEV = 60  # least squares steps from a grid point: a factor sqrt(3) from the truth takes more than a refit


def recalibrate(fit: list[str], every: list[str], start: dict[str, Any] | None = None) -> dict[str, Any]:
    """Recalibration of the linear parameters on ``fit`` that does not hinge on the sheet being close: the residuals
    on each grid of :data:`GRIDS` in turn (the best point of one kept for the next), then :func:`joint_refit` from
    the best point and from ``start`` (another fit's parameters; its effects stay as they are there), the lower cost
    kept (squared errors on ``every``). Returns what :func:`joint_refit` returns, ``evaluations`` in all."""
    setup: Setup = _CTX["setup"]
    kept = {p: v for p, v in (start or {}).items() if p not in recal.LINEAR}  # another fit's effects, kept as fitted
    best: dict[str, Any] = dict(kept)
    evaluations = 0
    for grid in GRIDS:
        axes = [p for p in grid if p in setup.linear()]
        scored = []
        for factors in itertools.product(*(grid[p] for p in axes)):
            over = {**best, **{p: setup.nominal(p) * f for p, f in zip(axes, factors, strict=True)}}
            scored.append((float(np.sum(residual_vector(over, fit) ** 2)), over))
        evaluations += len(scored)
        best = min(scored, key=lambda c: c[0])[1]
    fits = [joint_refit(best, [], fit, every, RECAL_NFEV)]
    if start:
        fits.append(joint_refit(dict(start), [], fit, every, RECAL_NFEV))
    res = min(fits, key=lambda r: r["fit_msg"])
    return {**res, "evaluations": evaluations + sum(r["evaluations"] for r in fits)}


def least_squares_refit(
    setup: Setup,
    resid: Callable[[dict[str, Any]], np.ndarray],
    base: dict[str, Any],
    free: list[str],
    names: list[str],
    max_nfev: int,
    linear: bool = True,
) -> dict[str, Any]:
    """:func:`joint_refit`'s least squares on the residual vector ``resid(overrides)`` (:func:`residual_vector` of
    the experiments ``names``, computed here or over the workers); a linear parameter the data do not determine keeps
    the sim's value, and a closed loop through an ADC lattice is fitted without derivatives
    (:func:`harness.diagnosis.recalibrate.fit`). ``linear`` False: the linear parameters keep the sim's values, only
    the effects' are fitted. Returns params, ci95, fit_msg, evaluations."""
    bounds: dict[str, recal.Bound] = {}
    nominal: dict[str, float] = {}
    encoder = any(setup.experiments[n].encoder for n in names)
    for prm in setup.linear(encoder) if linear else ():
        bounds[prm], nominal[prm] = recal.LINEAR[prm], setup.nominal(prm)
    for prm in free:
        eff = BY_PARAM[prm]
        bounds[prm], nominal[prm] = eff.bound(float(base[prm])), float(base[prm])
        for x, b in eff.extra.items():
            bounds[x], nominal[x] = b, setup.nominal(x)
    fixed = {k: v for k, v in base.items() if k not in bounds}
    gains = gain_columns(setup, names, [c for c, s in SENSOR_CHANNELS.items() if s in bounds])
    prior = {p: sd for p, sd in setup.prior_sd.items() if p in bounds}

    def refit(fixed: dict[str, Any], start: dict[str, Any]) -> recal.Fit:
        if not bounds:  # nothing to fit: the cost as given
            r = resid(fixed)
            return recal.Fit({}, {}, float(np.sum(r**2)), 1, int(np.count_nonzero(r)))
        return recal.fit(
            resid,
            bounds,
            nominal,
            start={k: float(v) for k, v in start.items() if k in bounds},
            fixed=fixed,
            max_nfev=max_nfev,
            hold=() if prior else recal.LINEAR,
            derivative_free=lattice_in_loop(setup, fixed, names),
            calibration=gains,
            prior=prior,
            max_rho=math.exp(-min(setup.experiments[n].Ts for n in names) / CORRELATION_SECONDS),
        )

    f = refit(fixed, base)
    nfev = f.nfev
    for prm in [p for p in fixed if p in BY_PARAM and BY_PARAM[p].kind == "int"]:
        # an integer effect parameter (a delay) was chosen on the rig before this refit, whose linear parameters
        # had compensated it: its neighbours get a look on the refitted rig, and a refit where one is better
        eff, cur = BY_PARAM[prm], int(fixed[prm])
        near = [v for v in eff.values if abs(int(v) - cur) == 1]
        here = {**fixed, **f.values}
        costs = {v: float(np.sum(resid({**here, prm: v}) ** 2)) for v in near}
        nfev += len(near)
        best = min(costs, key=lambda v: costs[v], default=None)
        if best is not None and costs[best] < f.cost:
            g = refit({**fixed, prm: best}, here)
            nfev += g.nfev
            if g.cost < f.cost:
                f, fixed = g, {**fixed, prm: best}
    return {"params": {**fixed, **f.values}, "ci95": f.ci95, "fit_msg": f.cost, "evaluations": nfev}


def where(over: dict[str, Any]) -> dict[str, Any]:
    """Where the gap lies with overrides ``over``: :func:`harness.diagnosis.where.where_gap`."""
    return where_gap(_CTX["setup"], over)


def loop_noise(over: dict[str, Any], names: list[str]) -> dict[str, float]:
    """The mean squared gap the noise fed back through each closed loop of ``names`` leaves, on the rig with
    overrides ``over``: :func:`harness.diagnosis.simulation.loop_noise_gap`."""
    return loop_noise_gap(_CTX["rig"], _CTX["setup"], over, names)


def spread(over: dict[str, Any], names: list[str]) -> dict[str, dict[str, Any]]:
    """Each closed-loop replay of ``names`` with overrides ``over``, its gap beside its own spread per window:
    :func:`harness.diagnosis.simulation.loop_spread`."""
    return loop_spread(_CTX["rig"], _CTX["setup"], over, names)


def replay(over: dict[str, Any]) -> dict[str, dict[str, np.ndarray]]:
    """Every experiment's simulated (theta, alpha) [deg] with overrides ``over``:
    :func:`harness.diagnosis.simulation.replay_traces`."""
    return replay_traces(_CTX["rig"], _CTX["setup"], over)


TASKS: dict[str, Callable[..., Any]] = {
    "sse": squared_errors,
    "fit": screen_effect,
    "refit": joint_refit,
    "recal": recalibrate,
    "resid": residual_vector,
    "where": where,
    "loopnoise": loop_noise,
    "spread": spread,
    "replay": replay,
}


def _run_call(call: tuple[Any, ...], setup: Setup) -> Any:
    _bind(setup)
    kind, *args = call
    return TASKS[kind](*args)


def _label(call: tuple[Any, ...]) -> str:
    """What a task does, for the progress line: "screen backlash", "refit linear + coulomb_torque", "score"."""
    kind = call[0]
    if kind == "fit":
        return f"screen {call[1].name}"
    if kind == "refit":
        return "refit linear" + "".join(f" + {p.split('.', 1)[1]}" for p in call[2])
    if kind == "recal":
        return "recalibrate"
    return {"where": "where", "loopnoise": "loop noise", "spread": "loop spread", "replay": "replay"}.get(kind, "score")


def _weight(call: tuple[Any, ...]) -> int:
    """A rough rank of what a task costs: a recalibration (grids and least squares), then a refit (the more so with
    an effect's parameters free: its rig is no longer linear), then a screening, then a single score."""
    kind = call[0]
    if kind == "recal":
        return 10
    if kind == "refit":
        return 2 + 3 * len(call[2])
    return 1 if kind == "fit" else 0


def stretches(setup: Setup, names: list[str], n: int) -> list[list[str]]:
    """``names`` cut into at most ``n`` consecutive stretches of about equal fit-window samples (what a residual
    vector costs to simulate), none empty."""
    size = np.cumsum([setup.experiments[x].n_fit for x in names])
    cuts = [0, *(int(np.searchsorted(size, size[-1] * i / n)) + 1 for i in range(1, n)), len(names)]
    return [names[a:b] for a, b in itertools.pairwise(cuts) if b > a]


class Pool:
    """The diagnosis's simulations as tasks of a :class:`harness.executor.Executor` (the setup is sent to every
    worker once; each worker loads the rig once): ``map`` takes ``(kind, *args)`` calls (see the module)."""

    def __init__(
        self, setup: Setup, workers: int | None, scheduler: str | None = None, progress: Progress | None = None
    ) -> None:
        self.setup = setup
        self.progress = progress
        self.ex = Executor(workers, scheduler, progress)

    def map(self, calls: list[tuple[Any, ...]]) -> list[Any]:
        """The calls' results in their order; the longest are started first (:func:`_weight`), so that no worker
        is left with a long refit while the others idle."""
        order = sorted(range(len(calls)), key=lambda i: -_weight(calls[i]))
        done = self.ex.map(_run_call, [calls[i] for i in order], self.setup, labels=[_label(calls[i]) for i in order])
        out: list[Any] = [None] * len(calls)
        for i, r in zip(order, done, strict=True):
            out[i] = r
        return out

    def refit(
        self, base: dict[str, Any], free: list[str], names: list[str], max_nfev: int, linear: bool = True
    ) -> dict[str, Any]:
        """:func:`joint_refit` on every experiment of ``names`` (no held-out squared errors), its least squares run
        here and each residual vector computed over the workers, one task per worker of consecutive experiments
        (:func:`stretches`): the same vector as one task computes, so the same path. One task was one worker's work
        while the other idled (the lab's final refit: 31 residual vectors of 10 experiments, 2.3 s)."""
        parts = stretches(self.setup, names, self.ex.n_workers)
        k = moving_channels(self.setup, names)

        def resid(over: dict[str, Any]) -> np.ndarray:
            calls = [("resid", over, part, k) for part in parts]
            return np.concatenate(self.ex.map(_run_call, calls, self.setup, quiet=True))

        with one_blas_thread():  # as in a task: the same BLAS, the same numbers in every backend
            res = least_squares_refit(self.setup, resid, base, free, names, max_nfev, linear)
        if self.progress is not None:
            self.progress(f"{_label(('refit', base, free))} on every experiment")
        return res

    def close(self) -> None:
        self.ex.close()
