"""A closed loop's behaviour on a rig, predicted with bands (``flexjoint predict``).

An ensemble of N closed-loop co-simulations (plant, DAQ and controller FMUs in the one master,
:meth:`harness.fmu.cosim.Rig.run_closed`) of a controller on a :class:`harness.twin.Twin`: member i runs the twin with
the i-th draw of its parameters (:func:`harness.twin.draw`) and its own measurement-noise seed, from the hub's start
angle, tracking the reference. Each member's behaviour is measured per reference step (:mod:`harness.behaviour`,
angles as the controller's calibration reads them) and pooled over the steps (:data:`harness.behaviour.POOLED_BY`: the
worst step for what a spec bounds, the mean of the signed stopping error); per metric the ensemble gives the median
and the 95 % band (the 2.5 % and 97.5 % order statistics). A member whose loop diverged has infinite worst metrics (a
step that never settled an infinite settling time): the band says so. The traces' pointwise median and band go to
``prediction.parquet``.

With a record (a closed-loop run: its reference, its controller unless another is given, its first angle), the
record's own metrics are ``measured`` beside the bands and the median trace's fit to it is ``fit_pct`` (MATLAB
``compare``'s fit, 100 (1 - ||y - y_median|| / ||y - mean y||), per channel).

Members run as tasks of the one executor (:class:`harness.executor.Executor`), in batches, the FMUs sent as bytes; the
result does not depend on where they ran.
"""

from __future__ import annotations

import json
import math
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from .behaviour import METRICS, POOLED_BY, step_metrics, summarize
from .executor import Executor, FmuBytes, fmu_bytes, worker_rig
from .fmu.build import build_all
from .ident.armax import fit_percent
from .loopspecs import LoopSpecs, controller_source
from .rig.controller import Controller, delayed, parse_controller
from .rig.signals import SIGNAL_KINDS, generate
from .rundir import DataError
from .spec import SpecError, controller_table
from .twin import Record, RigTables, Twin, draw, load_record, with_record_offset

__all__ = [
    "BAND",
    "DEFAULT_REFERENCE",
    "MetricBand",
    "Prediction",
    "Reference",
    "controller_from",
    "judge_specs",
    "predict",
    "reference_from",
    "simulate_loop",
]

Progress = Callable[[str], None]
BAND = (0.025, 0.975)  # the band's quantiles: 95 %
DEFAULT_REFERENCE = "square:f=0.25;amplitude=30;duration=8"  # a lab's square reference when neither a record nor one
BATCH = 10  # members per task


# ----------------------------------------------------------------------------------------------- bands
@dataclass(frozen=True)
class MetricBand:
    """One metric over the ensemble: ``median`` and the 95 % band ``lo``..``hi``; ``measured`` on the record (None
    without one)."""

    median: float
    lo: float
    hi: float
    measured: float | None = None

    def worst(self, metric: str) -> float:
        """The band's end a spec bounds: ``hi``, for the stopping error its larger magnitude."""
        return max(abs(self.lo), abs(self.hi)) if metric == "stop_error_deg" else self.hi

    def holds(self, value: float, tolerance: float = 0.0) -> bool:
        """Is ``value`` inside the band, or within ``tolerance`` (a share) of the median?"""
        if value is None or not math.isfinite(value):
            return False
        return self.lo <= value <= self.hi or abs(value - self.median) <= tolerance * abs(self.median)


def judge_specs(bands: dict[str, MetricBand], specs: LoopSpecs) -> dict[str, dict[str, Any]]:
    """Each spec against its band: ``{metric: {"limit", "predicted" (the band's end it bounds), "met", "spec"}}``."""
    out = {}
    for m, limit in specs.limits.items():
        worst = bands[m].worst(m)
        out[m] = {"limit": limit, "predicted": worst, "met": bool(worst <= limit), "spec": specs.describe(m)}
    return out


# ----------------------------------------------------------------------------------------------- reference
@dataclass(frozen=True, eq=False)
class Reference:
    """A reference of the hub angle ``ref_deg`` [deg] at ``Ts`` [s]; the hub starts at rest at ``theta0_deg``;
    ``initial_deg``: the level before it (its first segment a step from there; None: a record's, whose history is not
    known); ``label`` what it is; ``signal``: (kind, parameters) of a spec signal, None for a record's."""

    ref_deg: np.ndarray
    Ts: float
    theta0_deg: float
    initial_deg: float | None
    label: str
    signal: tuple[str, dict[str, Any]] | None = None

    @property
    def t(self) -> np.ndarray:
        return np.arange(self.ref_deg.size) * self.Ts


def parse_signal(text: str) -> tuple[str, dict[str, Any]]:
    """``KIND:NAME=VALUE;...`` (a spec experiment's signal and its ``duration`` [s]) as (kind, parameters)."""
    kind, sep, rest = str(text).partition(":")
    kind = kind.strip()
    if not sep or kind not in SIGNAL_KINDS:
        raise ValueError(f"--reference {text!r}: expected a run directory or KIND:NAME=VALUE;... with KIND one of "
                         f"{', '.join(SIGNAL_KINDS)}, e.g. {DEFAULT_REFERENCE}")  # fmt: skip
    params: dict[str, Any] = {}
    for item in [s for s in rest.split(";") if s.strip()]:
        name, eq, value = (p.strip() for p in item.partition("="))
        try:
            params[name] = float(value) if eq else math.nan
        except ValueError:
            raise ValueError(f"--reference {text!r}: {name}={value!r} is not a number") from None
    if not (params.get("duration", 0) > 0):
        raise ValueError(f"--reference {text!r}: give its duration=SECONDS (> 0)")
    return kind, params


def reference_from(text: str | None, rate: float, record: Record | None = None) -> Reference:
    """The reference a loop tracks, from its command-line form.

    Parameters
    ----------
    text : str or None
        A run directory (its first closed-loop record's reference), or a signal ``KIND:NAME=VALUE;...;duration=S``
        (``square:f=0.25;amplitude=30;duration=8``, amplitude in deg) from rest at 0; None: the record's, else
        :data:`DEFAULT_REFERENCE`.
    rate : float
        The loop's sample rate [Hz] a signal is generated at.
    record : Record, optional
        A closed-loop record (:func:`harness.twin.load_record`) whose reference is taken when ``text`` is None.

    Returns
    -------
    Reference
        The hub angle's reference [deg] per sample, its start and its label.
    """
    if text is not None and Path(text).is_dir():
        record = load_record(text)
        text = None
    if text is None and record is not None:
        return Reference(record.ref.copy(), record.Ts, float(record.theta[0]), None, f"record {record.name}")
    kind, params = parse_signal(text or DEFAULT_REFERENCE)
    Ts = 1.0 / rate
    n = int(round(params["duration"] / Ts))
    gen = {k: v for k, v in params.items() if k != "duration"}
    try:
        ref = generate(kind, n, Ts, gen)
    except (TypeError, ValueError) as e:
        raise ValueError(f"--reference {text or DEFAULT_REFERENCE!r}: {e}") from None
    return Reference(ref, Ts, 0.0, 0.0, f"{kind} " + ", ".join(f"{k} {v:g}" for k, v in params.items()), (kind, params))


def controller_from(text: str | None, source: str | None, record: Record | None) -> Controller:
    """The controller to predict: ``--controller KIND:...``, else ``--controller-from`` (a design's or any directory's
    controller.toml, a TOML file with a ``[controller]`` table, or a run's first closed-loop record's controller), else
    the record's (:func:`harness.loopspecs.controller_source`); one line when none is given."""
    which = controller_source(text, source, record is not None)
    if which == "controller" and text is not None:
        return parse_controller(text)
    if which == "controller_from" and source is not None:
        return _controller_file(Path(source))
    if record is not None and record.controller is not None:
        return record.controller
    name = record.name if record is not None else ""
    raise DataError(f"--record: its record {name!r} has no controller; give --controller KIND:... or --controller-from")


def _controller_file(p: Path) -> Controller:
    toml = p / "controller.toml" if p.is_dir() else p
    if p.is_dir() and not toml.is_file():
        rec = load_record(p)
        if rec.controller is None:
            raise DataError(f"--controller-from {p}: its record {rec.name!r} has no controller")
        return rec.controller
    if not toml.is_file():
        raise FileNotFoundError(f"--controller-from {p}: no such file or directory")
    try:
        raw = tomllib.loads(toml.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as e:
        raise SpecError(f"{toml}: malformed TOML: {e}") from None
    if "controller" not in raw:
        raise SpecError(f"{toml}: no [controller] table")
    return controller_table(raw["controller"])


# ----------------------------------------------------------------------------------------------- one loop
def loop_rate(controller: Controller, twin: Twin) -> float:
    """The loop's sample rate [Hz]: the controller's own, else the twin's records'."""
    return float(controller.sample_rate or twin.sample_rate)


def simulate_loop(
    rig: Any, tables: RigTables, controller: Controller, ref_deg: np.ndarray, Ts: float, theta0_deg: float,
    theta_gain: float = 1.0,
) -> dict[str, Any]:  # fmt: skip
    """One closed loop on a loaded :class:`harness.fmu.cosim.Rig`: the rig ``tables``, the controller reading the DAQ
    through ``tables.calibration`` (its own gauge calibration when it has one), tracking ``ref_deg`` [deg] at ``Ts``
    [s] from rest where the hub reads ``theta0_deg`` (``theta_gain``: the hub sensor's reading per true angle).
    Returns ``theta``, ``alpha`` [deg] as read (theta unwrapped, whole turns of a pot's wrap restored), ``u`` [V] and
    ``diverged`` (the sample it diverged at, -1 when it held; then held to the end)."""
    params = {**tables.calibration, **controller.fmu_parameters(1.0 / Ts)}
    plant = {**tables.plant, "theta_start": math.radians(theta0_deg) / theta_gain}
    ref = np.radians(delayed(ref_deg, controller.ref_delay))
    res = rig.run_closed(ref, Ts, params, plant=plant, daq=tables.daq, diverged="hold")
    cal = tables.calibration
    th = np.unwrap(cal["theta_gain"] * (res["theta_v"] - cal["theta_offset"]), period=360.0)
    th += 360.0 * np.round((theta0_deg - th[0]) / 360.0)
    al = cal["alpha_gain"] * (res["alpha_v"] - cal["alpha_offset"])
    return {"theta": th, "alpha": al, "u": res["u"], "diverged": int(res["diverged_at"])}


def pooled(
    t: np.ndarray, ref: np.ndarray, theta: np.ndarray, alpha: np.ndarray, u: np.ndarray, band_pct: float,
    initial_deg: float | None, diverged: bool = False,
) -> dict[str, float]:  # fmt: skip
    """A series' metrics pooled over its steps (:data:`harness.behaviour.POOLED_BY`), plus the stopping error up and
    down; a worst metric that is NaN (a step that never settled) or a diverged loop's is +inf."""
    s = summarize(step_metrics(t, ref, theta, alpha, u, band_pct=band_pct, initial_deg=initial_deg))
    out = {m: s.value(m) for m in METRICS}
    out |= {"stop_error_up_deg": s.stop_error_up_deg, "stop_error_down_deg": s.stop_error_down_deg}
    for m in METRICS:
        if POOLED_BY[m] == "worst" and (diverged or math.isnan(out[m])) and s.n_steps:
            out[m] = math.inf
    if diverged:
        out |= {"stop_error_deg": math.nan, "stop_error_up_deg": math.nan, "stop_error_down_deg": math.nan}
    return out


@dataclass(frozen=True, eq=False)
class LoopJob:
    """What every member shares: the twin, the controller, the reference, the settling band, the FMUs as bytes, and
    the record whose gauge offset the gauge reads (:func:`harness.twin.with_record_offset`; None: none)."""

    twin: Twin
    controller: Controller
    reference: Reference
    band_pct: float
    fmus: dict[str, FmuBytes]
    record: str | None = None


def _members(batch: list[tuple[int, dict[str, float], int]], job: LoopJob) -> list[dict[str, Any]]:
    """A batch of members, a task: each the twin with its draw and noise seed."""
    rig = worker_rig(job.fmus)
    ref = job.reference
    out = []
    for i, over, seed in batch:
        tables = job.twin.tables(over, seed, record=job.record)
        gain = float(over.get("sensor.theta_gain", 1.0))
        res = simulate_loop(rig, tables, job.controller, ref.ref_deg, ref.Ts, ref.theta0_deg, gain)
        vals = pooled(ref.t, ref.ref_deg, res["theta"], res["alpha"], res["u"], job.band_pct, ref.initial_deg,
                      res["diverged"] >= 0)  # fmt: skip
        out.append({"i": i, **{k: res[k] for k in ("theta", "alpha", "u", "diverged")}, "values": vals})
    return out


# ----------------------------------------------------------------------------------------------- the ensemble
@dataclass(frozen=True, eq=False)
class Prediction:
    """An ensemble's prediction: its ``rig`` (the twin's name), ``controller``, ``reference``, ``n`` members and
    ``seed``, the settling ``band_pct``, ``specs`` (None: none stated); per metric the members' pooled values
    (``values``, metric -> array of n), the traces' pointwise ``bands`` (channel -> (lo, median, hi) arrays),
    ``diverged`` members; with a ``record``: its ``measured`` metrics and the median trace's ``fit_pct``."""

    rig: str
    controller: Controller
    reference: Reference
    n: int
    seed: int
    band_pct: float
    values: dict[str, np.ndarray]
    bands: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]
    diverged: int
    record: Record | None = None
    measured: dict[str, float] | None = None
    fit_pct: dict[str, float] | None = None
    specs: LoopSpecs | None = None
    draws: list[dict[str, float]] = field(default_factory=list)

    def metric_bands(self) -> dict[str, MetricBand]:
        """Median and 95 % band of every metric (``measured`` beside it with a record)."""
        out = {}
        for m, v in self.values.items():
            finite_or_inf = v[~np.isnan(v)]
            if finite_or_inf.size == 0:
                lo = med = hi = math.nan
            else:
                med = float(np.median(finite_or_inf))
                lo, hi = (float(np.quantile(finite_or_inf, q, method="inverted_cdf")) for q in BAND)
            meas = None if self.measured is None else self.measured.get(m)
            out[m] = MetricBand(med, lo, hi, meas)
        return out

    def judged(self) -> dict[str, dict[str, Any]] | None:
        """:func:`judge_specs` of the specs stated (None without)."""
        return judge_specs(self.metric_bands(), self.specs) if self.specs else None

    def to_json(self) -> dict[str, Any]:
        """prediction.json's content."""
        bands = self.metric_bands()
        doc: dict[str, Any] = {
            "metrics": {
                m: {"median": b.median, "lo": b.lo, "hi": b.hi, "measured": b.measured} for m, b in bands.items()
            },  # fmt: skip
            "fit_pct": self.fit_pct,
            "n": self.n,
            "seed": self.seed,
            "rig": self.rig,
            "controller": self.controller.to_dict(),
            "reference": self.reference.label,
            "record": None if self.record is None else str(self.record.run),
            "sample_rate": 1.0 / self.reference.Ts,
            "band_pct": self.band_pct,
            "band": "95 %: the 2.5 % and 97.5 % order statistics of the members",
            "diverged": self.diverged,
            "definitions": DEFINITIONS,
        }
        if self.specs is not None:
            doc["specs"] = self.judged()
            doc["passed"] = all(v["met"] for v in doc["specs"].values())
        return doc


DEFINITIONS = {
    "overshoot_pct": "the hub's peak beyond the new reference, % of the step; the worst step",
    "settling_s": "last entry into the band of band_pct % of the step around the step's final value (the mean over "
    "its last second, at most half the step), from the step's start; the worst step (infinite: one never settled)",
    "stop_error_deg": "reference minus the hub's final value, times the step's direction (positive: short of the "
    "reference); the mean over the steps (also up and down)",
    "peak_alpha_deg": "the largest |alpha| over a step; the worst step",
    "peak_u_v": "the largest |u| over a step; the worst step",
    "ring_alpha_deg": "RMS of alpha over a step's last second (at most half the step), its mean removed; the worst "
    "step",
    "ring_hz": "the dominant frequency of alpha over that second (none: it does not ring); the median step",
}


def _fit(y: np.ndarray, yhat: np.ndarray) -> float:
    """MATLAB ``compare``'s fit [%] (:func:`harness.ident.armax.fit_percent`), NaN for a channel that does not move."""
    try:
        return fit_percent(y, yhat)
    except ValueError:
        return math.nan


def predict(
    twin: Twin,
    controller: Controller,
    reference: Reference,
    n: int = 200,
    seed: int = 0,
    band_pct: float = 5.0,
    record: Record | None = None,
    specs: LoopSpecs | None = None,
    fmus: dict[str, FmuBytes] | None = None,
    workers: int | None = None,
    scheduler: str | None = None,
    progress: Progress | None = None,
) -> Prediction:
    """Predict a controller's loop on a rig: an ensemble of closed-loop co-simulations, with median and 95 % bands.

    Member i runs the twin with the i-th draw of its parameters and its own measurement noise (see the module
    docstring); the same inputs give the same numbers, serially or on a cluster.

    Parameters
    ----------
    twin : Twin
        The rig (:func:`harness.load_twin`): a spec's, or the twin a diagnosis identified.
    controller : Controller
        The control law (:func:`harness.parse_controller`, a design's, a record's).
    reference : Reference
        What the hub tracks (:func:`harness.reference_from`), sampled at the loop's rate.
    n : int
        Members of the ensemble.
    seed : int
        Seed of the parameter and noise draws.
    band_pct : float
        The settling band [% of the step].
    record : Record, optional
        A closed-loop record to set the prediction beside: its measured metrics and the median's fit.
    specs : LoopSpecs, optional
        Limits to judge each metric's band against.
    fmus : dict of str to bytes, optional
        The built FMUs as bytes; default :func:`harness.build_all`'s.
    workers : int, optional
        Local worker processes (None: the default cluster or the enclosing session's; 1: serial, in-process).
    scheduler : str, optional
        A Dask scheduler's address to run on instead.
    progress : callable, optional
        Called with one line of text as members are done.

    Returns
    -------
    Prediction
        Per metric the members' values (median and band by :meth:`Prediction.metric_bands`), the traces' pointwise
        median and band, and with a record its measured values and fit.
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"--n must be a positive number of members, got {n!r}")
    rate = loop_rate(controller, twin)
    if abs(rate * reference.Ts - 1.0) > 1e-9:
        raise ValueError(f"the reference is sampled at {1 / reference.Ts:g} Hz, the loop at {rate:g} Hz")
    if specs is not None:
        band_pct = specs.band_pct
    shipped = fmus or {k: fmu_bytes(v) for k, v in build_all().items() if k in ("flexjoint", "daq", "controller")}
    if record is not None:
        twin = with_record_offset(twin, record)  # its gauge reads the record's offset
    draws = draw(twin, n, seed)
    rng = np.random.Generator(np.random.PCG64([int(seed), 36]))
    seeds = [int(s) for s in rng.integers(1, 2**31 - 1, size=n)]
    items = [(i, draws[i], seeds[i]) for i in range(n)]
    batches = [items[i : i + BATCH] for i in range(0, n, BATCH)]
    job = LoopJob(twin, controller, reference, band_pct, shipped, record.name if record is not None else None)
    if len(batches) == 1 and scheduler is None:
        workers = 1
    with Executor(workers, scheduler, progress) as ex:
        done = ex.map(_members, batches, job, desc="members", labels=[f"{b[0][0]}-{b[-1][0]}" for b in batches])
    members = sorted((m for b in done for m in b), key=lambda m: m["i"])
    values = {k: np.array([m["values"][k] for m in members]) for k in members[0]["values"]}
    bands = {}
    for c in ("theta", "alpha", "u"):
        stack = np.vstack([m[c] for m in members])
        lo, med, hi = np.quantile(stack, [BAND[0], 0.5, BAND[1]], axis=0)
        bands[c] = (lo, med, hi)
    measured = fit = None
    if record is not None:
        m = min(record.ref.size, reference.ref_deg.size)
        measured = pooled(record.t[:m], record.ref[:m], record.theta[:m], record.alpha[:m], record.u[:m], band_pct,
                          reference.initial_deg)  # fmt: skip
        fit = {
            "theta": _fit(record.theta[:m], bands["theta"][1][:m]),
            "alpha": _fit(record.alpha[:m], bands["alpha"][1][:m]),
        }
    return Prediction(
        rig=twin.name,
        controller=controller,
        reference=reference,
        n=n,
        seed=seed,
        band_pct=band_pct,
        values=values,
        bands=bands,
        diverged=sum(m["diverged"] >= 0 for m in members),
        record=record,
        measured=measured,
        fit_pct=fit,
        specs=specs,
        draws=draws,
    )


def with_specs(pred: Prediction, specs: LoopSpecs | None) -> Prediction:
    """The prediction judged against ``specs``."""
    return replace(pred, specs=specs)


def accept_prediction(where: Path, specs: str | None = None) -> tuple[bool, list[str]]:
    """``flexjoint accept`` on what predict or design wrote: each spec against the band of prediction.json.

    Parameters
    ----------
    where : Path
        The directory predict or design wrote (holding prediction.json).
    specs : str, optional
        Specs to judge now (``settling=1.5,overshoot=5``) instead of those the prediction states.

    Returns
    -------
    tuple of (bool, list of str)
        Whether every spec's band is met, and one phrase per spec.

    Raises
    ------
    ValueError
        One line when the prediction states no spec and none is given.
    """
    doc = json.loads((Path(where) / "prediction.json").read_text(encoding="utf-8"))
    if specs is not None:
        judged_specs = LoopSpecs.parse(specs)
        bands = {m: MetricBand(*(math.inf if b[k] is None else b[k] for k in ("median", "lo", "hi")))
                 for m, b in doc["metrics"].items()}  # fmt: skip
        judged = judge_specs(bands, judged_specs)
    else:
        judged = doc.get("specs")
    if not judged:
        raise ValueError(f"{where}: its prediction states no specs; give --specs settling=1.5,overshoot=5,...")
    lines = []
    for v in judged.values():
        p = v["predicted"]
        shown = "infinite (diverged or never settled)" if p is None or not math.isfinite(p) else f"{p:.4g}"
        lines.append(f"{v['spec']}: predicted up to {shown}" + ("" if v["met"] else " (NOT met)"))
    return all(v["met"] for v in judged.values()), lines
