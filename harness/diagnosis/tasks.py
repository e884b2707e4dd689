"""The diagnosis's simulations as tasks of a :class:`harness.executor.Executor`.

The setup (simulation, real experiments, FMU bytes) is sent to every worker once and each worker loads the rig
once. A task is a frozen dataclass whose :meth:`run` does its work on the worker's rig:

- :class:`Recalibrate`: the linear parameters fitted from a grid of the sheet's values (:func:`recalibrate`);
- :class:`Refit`: the linear parameters and some effect parameters refitted jointly by output-error least squares
  (:func:`joint_refit`);
- :class:`Grid`: one effect's values (its log grid, or its integers) on top of a rig, each with the least-squares
  cost of the fit experiments (where a joint refit starts);
- :class:`Evaluate`: experiments replayed beside their own spread (:func:`harness.diagnosis.simulation.evaluate`),
  what the held-out score is made of;
- :class:`Residual`: a stretch of a residual vector, for a least squares run by the client (:meth:`Pool.refit`);
- :class:`Where`: where the gap lies; :class:`Replay`: every experiment's simulated angles, for the report.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Collection
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.optimize import minimize_scalar

from ..behaviour import StepMetrics
from ..executor import Executor, one_blas_thread, worker_rig
from . import recalibrate as recal
from .bands import BEHAVIOUR_SEED, replay_metrics
from .effects import BY_PARAM, Effect
from .experiments import CHANNELS
from .simulation import Evaluation, Setup, evaluate, lattice_in_loop, nuisance_keys, replay_traces, residuals
from .where import where_gap

SENSOR_CHANNELS = {"theta": "sensor.theta_gain", "alpha": "sensor.alpha_gauge_gain"}
Overrides = dict[str, Any]  # {"plant.Ks": 1.5, "daq.delay_samples": 1, "sensor.alpha_offset@rec": 0.3, ...}

__all__ = [
    "Behaviour",
    "Cost",
    "Evaluate",
    "FitResult",
    "Grid",
    "Pool",
    "Recalibrate",
    "Refit",
    "Replay",
    "Residual",
    "Where",
    "joint_refit",
    "least_squares_refit",
    "mean_effective",
    "moving_channels",
    "own_rows",
    "recalibrate",
    "residual_vector",
    "stretches",
]

Progress = Callable[[str], None]

_CTX: dict[str, Any] = {}

CORRELATION_SECONDS = 0.05  # s: the longest a residual's correlation time counts (smoother: model error, not noise)
RECAL_STARTS = 2  # the best points of each grid plane carried on, least squares from the last plane's: two basins
RECAL_NFEV = 60  # least squares steps from a grid point: a factor sqrt(3) from the truth takes more than a refit
REFIT_NFEV = 15  # least squares steps of a joint refit from a rig already near


def _bind(setup: Setup) -> None:
    """Make ``setup`` and its rig (loaded once per process, from the FMU bytes) the current ones of this process."""
    _CTX["setup"] = setup
    _CTX["rig"] = worker_rig(setup.fmus)


@dataclass(frozen=True)
class FitResult:
    """A least-squares fit: the overrides fitted (``params``, with the fixed ones), each fitted parameter's 95 %
    interval, ``cost`` the mean squared gap on the fit windows, the simulations it took, and the covariance of the
    fitted parameters in the fit's coordinates (``names``; log of the value for a parameter on a log scale) with the
    range each was searched in (``ranges``, its values)."""

    params: Overrides
    ci95: dict[str, tuple[float, float]]
    cost: float
    evaluations: int
    names: tuple[str, ...] = ()
    cov: tuple[tuple[float, ...], ...] = ()
    log: tuple[bool, ...] = ()
    ranges: tuple[tuple[float, float], ...] = ()


def moving_channels(setup: Setup, names: list[str]) -> int:
    """K: how many experiment-channels of ``names`` move over their fit windows (sst > 0)."""
    return sum(1 for n in names for c in CHANNELS if setup.experiments[n].moves(c, "fit"))


def mean_effective(ev: dict[str, Evaluation], experiments: dict[str, Any]) -> float:
    """The score of replays ``ev`` ({experiment: Evaluation}): the mean effective gap over the experiment-channels
    that move (:meth:`harness.diagnosis.experiments.RigExperiment.moves`); NaN when none does."""
    vals = [e.effective[c] for n, e in ev.items() for c in CHANNELS if experiments[n].moves(c)]
    return float(np.mean(vals)) if vals else math.nan


def residual_vector(over: Overrides, names: list[str], k: int | None = None, seeds: tuple[int, ...] = ()
                    ) -> np.ndarray:  # fmt: skip
    """The fit windows' residuals of ``names``, each channel scaled by 1 / sqrt(K sst) so that the sum of
    squares is the mean squared gap (K = number of experiment-channels that move, :func:`moving_channels` of
    ``names`` unless given: ``names`` are then a stretch of a longer vector): what least squares minimises.
    ``seeds``: closed loops replayed as the mean of their replays with these noise draws too
    (:func:`harness.diagnosis.simulation.residuals`)."""
    setup: Setup = _CTX["setup"]
    parts = []
    k = moving_channels(setup, names) if k is None else k
    for n in names:
        x = setup.experiments[n]
        e = residuals(_CTX["rig"], setup, x, over, x.n_fit, seeds)
        parts += [e[c] / math.sqrt(k * x.sst_fit[c]) for c in CHANNELS if x.moves(c, "fit")]
    return np.concatenate(parts)


def own_rows(setup: Setup, names: list[str]) -> dict[str, tuple[float, np.ndarray]]:
    """Each closed-loop replay's own parameters among ``names`` (:func:`harness.diagnosis.simulation.nuisance_keys`:
    a record's gauge offset, an experiment's link at its start), each with its start and the mask of the rows of
    :func:`residual_vector` of ``names`` it moves."""
    sizes = [(n, setup.experiments[n].n_fit * sum(1 for c in CHANNELS if setup.experiments[n].moves(c, "fit")))
             for n in names]  # fmt: skip
    total = sum(m for _, m in sizes)
    out: dict[str, tuple[float, np.ndarray]] = {}
    at = 0
    for n, m in sizes:
        for key, start in nuisance_keys(setup.experiments[n]).items():
            mask = out.setdefault(key, (start, np.zeros(total, dtype=bool)))[1]
            mask[at : at + m] = True
        at += m
    return out


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
            if not x.moves(c, "fit"):
                continue
            ok = x.valid[c][: x.n_fit]
            y = np.where(ok, (x.theta if c == "theta" else x.alpha)[: x.n_fit], 0.0)
            if x.replay == "open" and ok.any():
                y = np.where(ok, y - float(np.mean(y[ok])), 0.0)
            col = np.zeros((y.size, len(CHANNELS)))
            col[:, i] = y / math.sqrt(k * x.sst_fit[c])
            blocks.append(col)
    return np.concatenate(blocks), se


def rough(setup: Setup, over: Overrides, names: list[str]) -> recal.Rough | None:
    """How the replay of the experiments ``names`` with ``over`` is rough in the parameters, so that least squares'
    0.1 % differences tell nothing: ``"staircase"``, a closed loop through a quantising sensor (an ADC lattice, an
    encoder's counts: its controller acts on a staircase, flat between its steps); ``"jitter"``, a closed loop with an
    effect switched on that no replay follows sample by sample (``Effect.spread``: a play, whose contacts jitter the
    replay about a trend that steps of a few per cent follow); None: smooth."""
    loops = [setup.experiments[n] for n in names if setup.experiments[n].replay == "closed"]
    if lattice_in_loop(setup, over, names) or any(x.encoder for x in loops):
        return "staircase"
    spread = any(BY_PARAM[p].spread and float(v) > 0 for p, v in over.items() if p in BY_PARAM)
    return "jitter" if loops and spread else None


def least_squares_refit(
    setup: Setup,
    resid: Callable[[Overrides], np.ndarray],
    base: Overrides,
    free: Collection[str],
    names: list[str],
    max_nfev: int,
    linear: bool = True,
) -> FitResult:
    """Output-error least squares on the residual vector ``resid(overrides)`` (:func:`residual_vector` of the
    experiments ``names``, computed here or over the workers) of the linear parameters
    (:data:`harness.diagnosis.recalibrate.LINEAR`; ``linear`` False: they keep their values in ``base``), the
    continuous effect parameters ``free`` (with their secondary parameters) and each closed-loop replay's own
    parameters (:func:`own_rows`: its record's gauge offset, its link at its start), from their
    values in ``base`` (linear ones default to the sim's); a replay rough in the parameters (:func:`rough`) is fitted
    without derivatives on a staircase, and with differences across the jitter on a play
    (:func:`harness.diagnosis.recalibrate.fit`). An integer effect parameter in ``base`` (a delay, chosen
    on a rig whose linear parameters had compensated it) has its neighbours tried on the refitted rig, and is moved
    where a refit there is better."""
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
    local = {}
    for key, (start, mask) in own_rows(setup, names).items():
        bounds[key], nominal[key], local[key] = recal.OWN[key.split("@", 1)[0]], start, mask
    fixed = {k: v for k, v in base.items() if k not in bounds}
    gains = gain_columns(setup, names, [c for c, s in SENSOR_CHANNELS.items() if s in bounds])
    prior = {p: sd for p, sd in setup.prior_sd.items() if p in bounds}

    def refit(fixed: Overrides, start: Overrides) -> recal.Fit:
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
            rough=rough(setup, fixed, names),
            calibration=gains,
            prior=prior,
            max_rho=math.exp(-min(setup.experiments[n].Ts for n in names) / CORRELATION_SECONDS),
            local=local,
        )

    f = refit(fixed, base)
    nfev = f.nfev
    for prm in [p for p in fixed if p in BY_PARAM and BY_PARAM[p].kind == "int"]:
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
    return FitResult(
        params={**fixed, **f.values},
        ci95=f.ci95,
        cost=f.cost,
        evaluations=nfev,
        names=tuple(f.names),
        cov=tuple(tuple(float(v) for v in row) for row in f.cov),
        log=tuple(bounds[n].log for n in f.names),
        ranges=tuple(_value_range(bounds[n], nominal[n]) for n in f.names),
    )


def _value_range(b: recal.Bound, nominal: float) -> tuple[float, float]:
    """A search range as values: factors of the nominal value on a log scale, the bounds themselves otherwise."""
    return (nominal * b.lo, nominal * b.hi) if b.log else (b.lo, b.hi)


def joint_refit(base: Overrides, free: Collection[str], fit: list[str], max_nfev: int = REFIT_NFEV) -> FitResult:
    """:func:`least_squares_refit` of the experiments ``fit`` on this worker's rig."""
    return least_squares_refit(_CTX["setup"], lambda over: residual_vector(over, fit), base, free, fit, max_nfev)


# the global search's grids, factors of the sheet's value, one plane after the other: the drive within a factor 3,
# then the link within a factor 2 and the inertia ratio within 3
GRIDS: tuple[dict[str, tuple[float, ...]], ...] = (
    {"rig.drive_gain": (1 / 3, 3**-0.5, 1.0, 3**0.5, 3.0), "rig.drive_tau": (1 / 3, 3**-0.5, 1.0, 3**0.5, 3.0)},
    {"plant.Ks": (0.5, 2**-0.5, 1.0, 2**0.5, 2.0), "rig.inertia_ratio": (1 / 3, 1.0, 3.0)},
)


def recalibrate(fit: list[str], start: Overrides | None = None) -> FitResult:
    """Recalibration of the linear parameters on ``fit`` that does not hinge on the sheet being close: the residuals
    on each grid of :data:`GRIDS` in turn (the best point of one kept for the next), then :func:`joint_refit` from
    the best point and from ``start`` (another fit's parameters; its effects stay as they are there), the lower cost
    kept."""
    setup: Setup = _CTX["setup"]
    kept = {p: v for p, v in (start or {}).items() if p not in recal.LINEAR}  # another fit's effects, kept as fitted
    bests: list[Overrides] = [dict(kept)]
    evaluations = 0
    for grid in GRIDS:
        axes = [p for p in grid if p in setup.linear()]
        scored: list[tuple[float, int, Overrides]] = []
        for best in bests:
            for factors in itertools.product(*(grid[p] for p in axes)):
                over = {**best, **{p: setup.nominal(p) * f for p, f in zip(axes, factors, strict=True)}}
                scored.append((float(np.sum(residual_vector(over, fit) ** 2)), len(scored), over))
        evaluations += len(scored)
        bests = [over for _, _, over in sorted(scored, key=lambda c: c[:2])[:RECAL_STARTS]]
    fits = [joint_refit(best, [], fit, RECAL_NFEV) for best in bests]
    if start:
        fits.append(joint_refit(dict(start), [], fit, RECAL_NFEV))
    res = min(fits, key=lambda r: r.cost)
    return FitResult(**{**res.__dict__, "evaluations": evaluations + sum(r.evaluations for r in fits)})


def effect_values(eff: Effect) -> list[float | int]:
    """An effect's values tried for a start: its integers, or its grid over [lo, hi] (log or linear)."""
    if eff.kind == "int":
        return list(eff.values)
    pts = np.linspace(math.log(eff.lo), math.log(eff.hi), eff.grid) if eff.kind == "log" else np.linspace(
        eff.lo, eff.hi, eff.grid)  # fmt: skip
    return [float(math.exp(p)) if eff.kind == "log" else float(p) for p in pts]


# ------------------------------------------------------------------------------------------------- the tasks


@dataclass(frozen=True)
class Recalibrate:
    """:func:`recalibrate` on the experiments ``fit`` (from ``start`` too, when given)."""

    fit: tuple[str, ...]
    start: Overrides | None = None
    label = "recalibrate"
    weight = 10

    def run(self) -> FitResult:
        return recalibrate(list(self.fit), self.start)


@dataclass(frozen=True)
class Refit:
    """:func:`least_squares_refit` of the experiments ``fit`` from ``base``, the effect parameters ``free`` with the
    linear ones (``linear`` False: the linear ones held); ``seeds``: closed loops replayed as the mean of their
    replays with these noise draws too (:func:`residual_vector`)."""

    base: Overrides
    free: tuple[str, ...]
    fit: tuple[str, ...]
    max_nfev: int = REFIT_NFEV
    linear: bool = True
    seeds: tuple[int, ...] = ()

    @property
    def label(self) -> str:
        return "refit linear" + "".join(f" + {p.split('.', 1)[1]}" for p in self.free)

    @property
    def weight(self) -> int:
        return 2 + 3 * len(self.free)

    def run(self) -> FitResult:
        setup: Setup = _CTX["setup"]
        fit = list(self.fit)
        return least_squares_refit(setup, lambda over: residual_vector(over, fit, seeds=self.seeds), self.base,
                                   self.free, fit, self.max_nfev, self.linear)  # fmt: skip


@dataclass(frozen=True)
class Grid:
    """Each of an effect's values (:func:`effect_values`) on top of ``base``, with its cost on the experiments
    ``fit``, and a continuous effect's best value refined between its neighbours by bounded Brent (in log for a log
    scale): [(value, cost)]. The cost is least squares' (the mean squared gap), or with ``draws`` > 0 the score
    (:func:`mean_effective`: the gap beside the spread of that many replays with other noise draws; an effect no
    replay follows sample by sample, ``Effect.spread``)."""

    effect: Effect
    base: Overrides
    fit: tuple[str, ...]
    draws: int = 0
    resolution: float = 0.0
    weight = 1

    @property
    def label(self) -> str:
        return f"grid {self.effect.name}"

    def run(self) -> list[tuple[float | int, float]]:
        fit, eff = list(self.fit), self.effect
        setup: Setup = _CTX["setup"]

        def cost(v: float | int) -> float:
            over = {**self.base, eff.param: v}
            if not self.draws:
                return float(np.sum(residual_vector(over, fit) ** 2))
            ev = {n: evaluate(_CTX["rig"], setup, setup.experiments[n], over, [over] * self.draws, False,
                              self.resolution) for n in fit}  # fmt: skip
            return mean_effective(ev, setup.experiments)

        values = effect_values(eff)
        out = [(v, cost(v)) for v in values]
        if eff.continuous:
            log = eff.kind == "log"
            i = min(range(len(out)), key=lambda j: (out[j][1], j))
            lo, hi = values[max(i - 1, 0)], values[min(i + 1, len(values) - 1)]
            ends = (math.log(lo), math.log(hi)) if log else (lo, hi)
            res = minimize_scalar(
                lambda x: cost(math.exp(x) if log else x),
                bounds=ends,
                method="bounded",
                options={"xatol": 0.01 if log else 0.002 * (eff.hi - eff.lo), "maxiter": 10},
            )
            out.append((float(math.exp(res.x) if log else res.x), float(res.fun)))
        return out


@dataclass(frozen=True)
class Cost:
    """The least-squares cost (mean squared gap on the fit windows) of the experiments ``fit`` with ``over``."""

    over: Overrides
    fit: tuple[str, ...]
    label = "cost"
    weight = 0

    def run(self) -> float:
        return float(np.sum(residual_vector(self.over, list(self.fit)) ** 2))


@dataclass(frozen=True)
class Evaluate:
    """The experiments ``names`` replayed with ``over`` beside their own spread
    (:func:`harness.diagnosis.simulation.evaluate`: its replays with ``draws``, other draws of the fitted parameters
    each with another noise draw; ``pseudo`` the floor's record): {experiment: Evaluation}."""

    over: Overrides
    names: tuple[str, ...]
    draws: tuple[Overrides, ...]
    resolution: float
    pseudo: bool = False
    label = "score"
    weight = 0

    def run(self) -> dict[str, Evaluation]:
        setup: Setup = _CTX["setup"]
        return {
            n: evaluate(_CTX["rig"], setup, setup.experiments[n], self.over, self.draws, self.pseudo, self.resolution)
            for n in self.names
        }


@dataclass(frozen=True)
class Behaviour:
    """Each experiment of ``names`` replayed with each of ``overs`` (a draw of the rig) and its own noise draw
    (seed BEHAVIOUR_SEED + i), its behaviour per step: {experiment: [[StepMetrics per step] per replay]}
    (:func:`harness.diagnosis.bands.replay_metrics`)."""

    overs: tuple[Overrides, ...]
    names: tuple[str, ...]
    label = "behaviour"
    weight = 1

    def run(self) -> dict[str, list[list[StepMetrics]]]:
        setup: Setup = _CTX["setup"]
        return {n: [replay_metrics(_CTX["rig"], setup, setup.experiments[n], over, BEHAVIOUR_SEED + i)
                    for i, over in enumerate(self.overs)] for n in self.names}  # fmt: skip


@dataclass(frozen=True)
class Residual:
    """:func:`residual_vector` of a stretch ``names`` of a longer vector (``k`` its moving channels; ``seeds`` its
    noise draws)."""

    over: Overrides
    names: tuple[str, ...]
    k: int
    seeds: tuple[int, ...] = ()
    label = "residuals"
    weight = 0

    def run(self) -> np.ndarray:
        return residual_vector(self.over, list(self.names), self.k, self.seeds)


@dataclass(frozen=True)
class Where:
    """Where the gap lies with ``over``: :func:`harness.diagnosis.where.where_gap`."""

    over: Overrides = field(default_factory=dict)
    label = "where"
    weight = 0

    def run(self) -> dict[str, Any]:
        return where_gap(_CTX["setup"], self.over)


@dataclass(frozen=True)
class Replay:
    """Every experiment's simulated (theta, alpha) [deg] with ``over``:
    :func:`harness.diagnosis.simulation.replay_traces`."""

    over: Overrides = field(default_factory=dict)
    label = "replay"
    weight = 0

    def run(self) -> dict[str, dict[str, np.ndarray]]:
        return replay_traces(_CTX["rig"], _CTX["setup"], self.over)


def _run_task(task: Any, setup: Setup) -> Any:
    _bind(setup)
    return task.run()


def stretches(setup: Setup, names: list[str], n: int) -> list[list[str]]:
    """``names`` cut into at most ``n`` consecutive stretches of about equal fit-window samples (what a residual
    vector costs to simulate), none empty."""
    size = np.cumsum([setup.experiments[x].n_fit for x in names])
    cuts = [0, *(int(np.searchsorted(size, size[-1] * i / n)) + 1 for i in range(1, n)), len(names)]
    return [names[a:b] for a, b in itertools.pairwise(cuts) if b > a]


class Pool:
    """The diagnosis's simulations as tasks of a :class:`harness.executor.Executor` (the setup is sent to every
    worker once; each worker loads the rig once): :meth:`map` takes tasks (see the module)."""

    def __init__(
        self, setup: Setup, workers: int | None, scheduler: str | None = None, progress: Progress | None = None
    ) -> None:
        self.setup = setup
        self.progress = progress
        self.ex = Executor(workers, scheduler, progress)

    def map(self, tasks: list[Any]) -> list[Any]:
        """The tasks' results in their order; the longest are started first (their ``weight``), so that no worker
        is left with a long refit while the others idle."""
        order = sorted(range(len(tasks)), key=lambda i: -tasks[i].weight)
        done = self.ex.map(_run_task, [tasks[i] for i in order], self.setup, labels=[tasks[i].label for i in order])
        out: list[Any] = [None] * len(tasks)
        for i, r in zip(order, done, strict=True):
            out[i] = r
        return out

    def refit(self, base: Overrides, free: Collection[str], names: list[str], max_nfev: int, linear: bool = True,
              seeds: tuple[int, ...] = ()) -> FitResult:  # fmt: skip
        """:func:`least_squares_refit` on every experiment of ``names``, its least squares run here and each residual
        vector computed over the workers, one task per worker of consecutive experiments (:func:`stretches`): the
        same vector as one task computes, so the same path (``seeds``: :func:`residual_vector`'s)."""
        parts = stretches(self.setup, names, self.ex.n_workers)
        k = moving_channels(self.setup, names)

        def resid(over: Overrides) -> np.ndarray:
            tasks = [Residual(over, tuple(part), k, seeds) for part in parts]
            return np.concatenate(self.ex.map(_run_task, tasks, self.setup, quiet=True))

        with one_blas_thread():  # as in a task: the same BLAS, the same numbers in every backend
            res = least_squares_refit(self.setup, resid, base, free, names, max_nfev, linear)
        if self.progress is not None:
            self.progress(f"{Refit(base, tuple(free), ()).label} on every experiment")
        return res

    def close(self) -> None:
        self.ex.close()
