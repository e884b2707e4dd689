"""The rig a controller is designed on and predicted for: a spec's rig, or the twin a diagnosis identified.

``load_twin(RIG)`` reads RIG as a spec (a path or a bundled name: its rig as written, its ``[uncertainty]`` the spread
of its sheet values) or as a diagnosis directory (``diagnosis.json``: the sim spec it judged against, with the
diagnosis's fitted linear parameters and the effects it found applied on top, the data's noise floor (without an ADC
or encoder lattice's share where the twin's DAQ quantises: the sheet's, or an ADC the diagnosis found), the spread of
the fitted values). A :class:`Twin` holds the sheet's tables and the overrides on top of them, in the diagnosis's names:

- ``rig.drive_gain``, ``rig.drive_tau``, ``rig.inertia_ratio``: the drive, mapped onto the plant's kt, km, Beq and Jeq
  by :func:`harness.diagnosis.rigmodel.to_plant`;
- ``plant.<name>``, ``daq.<name>``: an FMU parameter (``plant.Ks``, an effect's ``plant.coulomb_torque``);
- ``sensor.theta_gain``, ``sensor.alpha_gauge_gain``: a sensor's reading per true angle (the DAQ's gain divided by
  it: the data, and the controller, read through the sheet's calibration);
- ``sensor.alpha_offset@<record>``: a record's gauge reading at rest [deg], which its controller acted on (applied
  when that record is predicted; a record the diagnosis did not fit gets its own, :func:`with_record_offset`).

:meth:`Twin.tables` gives the plant and DAQ FMU parameters of one set of overrides (noise on: the data's RMS per
channel) and the calibration the controller reads the DAQ with; :func:`draw` samples sets of overrides from the
twin's :class:`Spread`; :func:`load_record` reads a closed-loop record (reference, angles as read, command and its
controller).

The spread, in one function (:func:`spread_of_diagnosis`): a diagnosis's top-level ``rig`` (overrides and their
covariance in the fit's coordinates, the log of a positive parameter) when it has one; otherwise its ``parameters``
rows, each drawn independently, lognormal for a positive parameter (normal otherwise) with the standard deviation of
its 95 % interval (width / 3.92 in log). Either way each parameter's variance gets the spread between its fits on the
two folds or on each record added (their variance about their mean: fits on parts of the data that exclude each other
are model error, which the covariance of the fit on all of them leaves out).
A spec's spread is its sheet's (:func:`harness.diagnosis.rigmodel.prior_sd`: the
95 % factor of each sheet value in ``[uncertainty]``) about its own values.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from . import spec as specmod
from .diagnosis.experiments import load_experiments
from .diagnosis.recalibrate import IMPLIED, LINEAR
from .diagnosis.result import Diagnosis, NoiseFloor
from .diagnosis.rigmodel import COMBOS, SENSORS, combos, prior_sd, to_plant
from .diagnosis.simulation import offset_key
from .fmu.cosim import CALIBRATION
from .fmu.modeldesc import source_model
from .ident.calibration import alpha_deg, load_calibration, theta_deg
from .rig.controller import Controller
from .rundir import DataError, Manifest, RunDir, check_rig, read_dataset, sample_time

__all__ = ["Record", "RigTables", "Spread", "Twin", "draw", "load_record", "load_twin", "measurement_noise",
           "process_noise", "spread_of_diagnosis", "with_record_offset"]  # fmt: skip

MODELS = {"plant": "flexjoint", "daq": "daq"}  # the FMU behind each table
NOISE = {"theta": ("noise_theta", "pot_gain"), "alpha": ("noise_alpha", "gauge_gain")}  # channel -> DAQ noise, gain


@dataclass(frozen=True)
class Spread:
    """How a twin's parameters vary: ``names`` (the overrides' names), ``center`` (their values), ``log`` (drawn as
    the log of the value: a positive parameter) and ``cov``, their covariance in those coordinates (row-major)."""

    names: tuple[str, ...] = ()
    center: tuple[float, ...] = ()
    log: tuple[bool, ...] = ()
    cov: tuple[tuple[float, ...], ...] = ()

    def sd(self) -> dict[str, float]:
        """Each parameter's standard deviation in its coordinates (log: a relative one)."""
        return {n: math.sqrt(max(self.cov[i][i], 0.0)) for i, n in enumerate(self.names)}


@dataclass(frozen=True)
class RigTables:
    """One rig to simulate: the plant and DAQ FMU parameters (the true sensors, the data's noise on) and the
    ``calibration`` the controller reads the DAQ's volts with (theta_gain, theta_offset, alpha_gain, alpha_offset: the
    sheet's, as the lab's)."""

    plant: dict[str, Any]
    daq: dict[str, Any]
    calibration: dict[str, float]


@dataclass(frozen=True)
class Twin:
    """The rig a controller is designed on and predicted for (see the module docstring).

    ``name``: what it is ("spec lab", "diagnosis of quanser"); ``source``: "spec" or "diagnosis"; ``spec``: the sheet
    (the sim spec of a diagnosis); ``sample_rate`` [Hz] of its records (a spec's own); ``plant``/``daq``: the sheet's
    tables (noise off, a record's sensor settings: an encoder, the gauge's delay); ``overrides``: the fitted values and
    effects on top; ``noise_deg``: measurement noise RMS [deg] per channel as read; ``spread``: how the overrides vary;
    ``run``: the diagnosed run (its records), None for a spec; ``process``: the plant's process noise, the white
    torques' intensities on the hub and at the link's tip (the plant FMU's ``hub_torque_noise``, ``tip_torque_noise``
    [N m sqrt(s)]: the likelihood engine's maximum-likelihood ones, :func:`process_noise`; none for a spec)."""

    name: str
    source: str
    spec: specmod.Spec
    sample_rate: float
    plant: dict[str, Any]
    daq: dict[str, Any]
    overrides: dict[str, float]
    noise_deg: dict[str, float]
    spread: Spread = field(default_factory=Spread)
    run: Path | None = None
    process: dict[str, float] = field(default_factory=dict)

    def tables(
        self, over: dict[str, float] | None = None, seed: int = 0, noise: bool = True, record: str | None = None
    ) -> RigTables:
        """The rig with the overrides ``over`` (default: the twin's own), the noise seed ``seed`` (the DAQ's and the
        plant's) and the measurement and process noise (``noise`` False: off); ``record``: the record whose gauge
        offset the gauge reads (its ``sensor.alpha_offset@<record>`` [deg as read] where the diagnosis fitted it, else
        none)."""
        over = dict(self.overrides if over is None else over)
        drive = {k: float(v) for k, v in over.items() if k in COMBOS}
        plant = {**self.plant, **(to_plant(drive, self.plant) if drive else {})}
        believed = dict(self.daq)
        for key, v in over.items():
            table, name = key.split(".", 1)
            if table in MODELS:
                (plant if table == "plant" else believed)[name] = _typed(MODELS[table], name, v)
        daq = dict(believed)
        for s, name in SENSORS.items():  # reading = gain x true angle: the DAQ's volts per degree scale with it
            if s in over:
                daq[name] = specmod.fmu_value(believed, "daq", name) / float(over[s])
        for c, (vn, gain) in NOISE.items():
            daq[vn] = self.noise_deg[c] / abs(specmod.fmu_value(believed, "daq", gain)) if noise else 0.0
        daq["seed"] = int(seed) % (2**31 - 1)
        if noise and self.process:
            plant |= self.process | {"noise_seed": daq["seed"]}
        offset = float(over.get(offset_key(record), 0.0)) if record is not None else 0.0
        daq["gauge_offset"] = specmod.fmu_value(believed, "daq", "gauge_offset") + offset / specmod.fmu_value(
            believed, "daq", "gauge_gain"
        )  # the reading at rest, which the controller acts on
        cal = {k: specmod.fmu_value(believed, "daq", v) for k, v in CALIBRATION.items()}
        return RigTables(plant, daq, cal)

    def value(self, name: str) -> float:
        """An override's value in the twin (the sheet's when not overridden: :meth:`sheet_value`)."""
        return float(self.overrides[name]) if name in self.overrides else self.sheet_value(name)

    def sheet_value(self, name: str) -> float:
        """A parameter's value on the sheet: a combo's of its plant table, an FMU parameter's, 1 for a sensor gain."""
        table, key = name.split(".", 1)
        if table == "rig":
            return combos(self.plant)[name]
        if table == "sensor":
            return 1.0
        return specmod.fmu_value(self.plant if table == "plant" else self.daq, MODELS[table], key)


def _typed(model: str, name: str, v: Any) -> Any:
    """An FMU parameter's value with its declared type (an Integer's rounded)."""
    kind = specmod.fmu_parameters(model).get(name, ("Real", 0.0))[0]
    return int(round(float(v))) if kind == "Integer" else float(v)


def _spec_noise(spec: specmod.Spec) -> dict[str, float]:
    """A spec's measurement noise [deg as read] per channel: its DAQ's noise [V] through its gains."""
    return {c: specmod.fmu_value(spec.daq, "daq", vn) * abs(specmod.fmu_value(spec.daq, "daq", g))
            for c, (vn, g) in NOISE.items()}  # fmt: skip


def _spec_tables(spec: specmod.Spec) -> tuple[dict[str, Any], dict[str, Any]]:
    plant = {"internal_step": spec.internal_step, **spec.plant}
    daq = {k: v for k, v in spec.daq.items() if k not in ("noise_theta", "noise_alpha", "seed")}
    return plant, daq


def twin_of_spec(spec: specmod.Spec) -> Twin:
    """A spec's rig as written; its spread the sheet's (``[uncertainty]``) about its values."""
    plant, daq = _spec_tables(spec)
    sd = prior_sd(plant, spec.factor)
    names = [*COMBOS, "plant.Ks", "plant.zeta_link", *SENSORS]
    base = Twin(spec.name, "spec", spec, spec.sample_rate, plant, daq, {}, _spec_noise(spec))
    center = [base.sheet_value(n) for n in names]
    var = [sd[n] ** 2 for n in names]
    cov = tuple(tuple(var[i] if i == j else 0.0 for j in range(len(names))) for i in range(len(names)))
    spread = Spread(tuple(names), tuple(center), (True,) * len(names), cov)
    return Twin(f"spec {spec.name}", "spec", spec, spec.sample_rate, plant, daq, {}, _spec_noise(spec), spread)


def _positive(p: dict[str, Any]) -> bool:
    lo, hi = p.get("ci95", [math.nan, math.nan])
    return all(isinstance(v, (int, float)) and v > 0 for v in (p.get("fitted"), lo, hi))


def spread_of_diagnosis(doc: dict[str, Any]) -> tuple[dict[str, float], Spread]:
    """The overrides a diagnosis applies (name -> value) and their spread, from its JSON content ``doc``.

    With a top-level ``rig`` (:class:`harness.diagnosis.result.RigFit`: ``overrides`` as its replays use them,
    ``names``, ``log`` and ``covariance`` of the fitted ones in the fit's coordinates): those, each variance widened by
    the spread of its row's fits on the parts of the data (:func:`_parts_var`).
    Otherwise from ``parameters`` and ``effects``: the linear parameters fitted
    (:data:`harness.diagnosis.recalibrate.LINEAR`, not the physical values they imply) and every effect's parameters,
    each row with a finite 95 % interval drawn independently (see the module docstring); a row kept at the spec's
    value, or an Integer parameter (a delay in samples), is not drawn."""
    params: dict[str, Any] = doc.get("parameters", {})
    if doc.get("rig"):
        return _rig_spread(doc["rig"], params)
    effect_params = {k: float(v) for e in doc.get("effects", []) for k, v in e.get("params", {}).items()}
    over: dict[str, float] = {}
    for name, p in params.items():
        if name in IMPLIED or not (name in LINEAR or name in effect_params or name.startswith("plant.")):
            continue
        over[name] = float(p["fitted"])
    over |= {k: v for k, v in effect_params.items() if k not in over}
    names: list[str] = []
    logs: list[bool] = []
    var: list[float] = []
    for name in over:
        p = params.get(name)
        table, key = name.split(".", 1)
        if p is None or (table in MODELS and specmod.fmu_parameters(MODELS[table]).get(key, ("Real",))[0] != "Real"):
            continue
        lo, hi = (float("nan") if v is None else float(v) for v in p.get("ci95", [None, None]))
        if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
            continue
        log = _positive(p)
        width = math.log(hi / lo) if log else hi - lo
        names.append(name)
        logs.append(log)
        var.append((width / (2 * 1.96)) ** 2 + _parts_var(p, log))
    cov = tuple(tuple(v if i == j else 0.0 for j in range(len(var))) for i, v in enumerate(var))
    return over, Spread(tuple(names), tuple(over[n] for n in names), tuple(logs), cov)


def _rig_spread(rig: dict[str, Any], params: dict[str, Any]) -> tuple[dict[str, float], Spread]:
    """A diagnosis's ``rig`` (RigFit) as overrides and spread, each variance widened by its row's parts
    (:func:`_parts_var`)."""
    over = {str(k): float(v) for k, v in rig["overrides"].items()}
    names = tuple(str(n) for n in rig.get("names", ()))
    logs = tuple(bool(v) for v in rig.get("log", ()))
    cov = np.array(rig.get("covariance", ()), dtype=float).reshape(len(names), len(names))
    cov += np.diag([_parts_var(params.get(n, {}), lg) for n, lg in zip(names, logs, strict=True)])
    matrix = tuple(tuple(float(x) for x in row) for row in cov)
    return over, Spread(names, tuple(over[n] for n in names), logs, matrix)


def _parts_var(p: dict[str, Any], log: bool) -> float:
    """The variance [in log where ``log``] of a parameter row's fits on the parts of the data (its two folds, or each
    record of a unit): 0 with fewer than two."""
    parts = [v[0] for v in (p.get("folds") or [])] or [v[0] for v in (p.get("records") or {}).values()]
    parts = [v for v in parts if v is not None and math.isfinite(v) and (not log or v > 0)]
    return float(np.var(np.log(parts) if log else parts)) if len(parts) >= 2 else 0.0


def _sim_spec(diag: Diagnosis, where: Path) -> specmod.Spec:
    """The spec a diagnosis judged against: its ``sim_spec`` (a bundled name or a path as given, or beside the
    diagnosis), else its file name among the bundled specs."""
    for cand in (diag.sim_spec, where / diag.sim_spec, diag.sim_spec_file):
        try:
            return specmod.load(cand)
        except specmod.SpecError:
            continue
    raise DataError(f"{where}: the spec it was diagnosed against ({diag.sim_spec}) is not found; give it as RIG")


def _quantises(daq: dict[str, Any], channel: str) -> bool:
    """Does the DAQ ``daq`` put ``channel`` on a lattice (its ADC, or theta's encoder)?"""
    encoder = channel == "theta" and int(specmod.fmu_value(daq, "daq", "theta_sensor")) == 1
    return encoder or int(specmod.fmu_value(daq, "daq", "adc_bits")) > 0


def measurement_noise(floor: NoiseFloor, daq: dict[str, Any], over: dict[str, float]) -> dict[str, float]:
    """The twin's measurement noise RMS [deg as read] per channel from a diagnosis's noise ``floor``: without the
    lattice's LSB^2 / 12 on a channel the twin's DAQ quantises (it adds that share itself), else the floor with it.
    The DAQ as the twin simulates it: the sheet's table ``daq`` with the DAQ overrides among ``over`` (an ADC's bits
    the diagnosis found), as the diagnosis's replays decide it."""
    total = {"theta": floor.theta_deg, "alpha": floor.alpha_deg}
    simulated = {**daq, **{k.split(".", 1)[1]: v for k, v in over.items() if k.split(".", 1)[0] == "daq"}}
    return {c: (floor.estimated_deg or total)[c] if _quantises(simulated, c) else total[c] for c in total}


def twin_of_diagnosis(where: Path, spec: specmod.Spec | None = None) -> Twin:
    """The twin a diagnosis directory ``where`` identified (``spec``: the spec it judged against, default
    :func:`_sim_spec`): the sheet's tables, the diagnosed run's sensor settings (an encoder) and the gauge's delay,
    the overrides and spread of :func:`spread_of_diagnosis`, the noise floor as measurement noise."""
    where = Path(where)
    diag = Diagnosis.load(where)
    doc = json.loads(RunDir(where).diagnosis.read_text(encoding="utf-8"))
    spec = spec or _sim_spec(diag, where)
    run = (where / diag.real).resolve()
    man = Manifest.load(run)
    rate = man.sample_rate or spec.sample_rate
    plant, daq = _spec_tables(spec)
    first = next((e for e in man.experiments if e.role != "calibration"), None)
    if first is not None and first.theta_sensor == "encoder":
        daq |= {"theta_sensor": 1, "encoder_counts": float(first.counts_per_rev or 4096)}
    if diag.calibration.gauge_delay_s:
        daq["gauge_delay"] = int(round(diag.calibration.gauge_delay_s * rate))
    over, spread = spread_of_diagnosis(doc)
    noise = measurement_noise(diag.noise_floor, daq, over)
    name = f"diagnosis of {run.name}"
    return Twin(name, "diagnosis", spec, float(rate), plant, daq, over, noise, spread, run, process_noise(where))


def process_noise(where: Path) -> dict[str, float]:
    """The process noise a diagnosis directory ``where`` found: the likelihood engine's maximum-likelihood white
    torques (``likelihood.json``: the best model's, the linear model with the effects that entered, else the linear
    fit's) as the plant FMU's ``hub_torque_noise`` and ``tip_torque_noise`` [N m sqrt(s)]; none without the engine's
    fit."""
    path = RunDir(where).likelihood
    if not path.is_file():
        return {}
    doc = json.loads(path.read_text(encoding="utf-8"))
    fitted = {k: float(v["fitted"]) for k, v in doc.get("parameters", {}).items()}
    fitted |= {k: float(v) for k, v in ((doc.get("final") or {}).get("noise") or {}).items()}
    names = {"noise.hub_torque": "hub_torque_noise", "noise.link_torque": "tip_torque_noise"}
    return {fmu: fitted[k] for k, fmu in names.items() if fitted.get(k, 0.0) > 0.0}


def load_twin(rig: str | Path) -> Twin:
    """The rig to design on and predict for, as ``RIG`` is given on the command line.

    Parameters
    ----------
    rig : str or Path
        A diagnosis directory (holding diagnosis.json: the identified twin, with the effects found, the intervals and
        the data's noise) or a spec (a path or a bundled name: its rig, its ``[uncertainty]`` as its spread).

    Returns
    -------
    Twin
        The rig's tables, the fitted values on top and their spread.

    Raises
    ------
    DataError
        One line when a directory holds no diagnosis (no model of the rig to close a loop on).
    """
    spec = check_rig(rig)
    return twin_of_diagnosis(Path(rig)) if spec is None else twin_of_spec(spec)


def draw(twin: Twin, n: int, seed: int) -> list[dict[str, float]]:
    """``n`` sets of overrides drawn from the twin's spread (multivariate normal in its coordinates, a positive
    parameter's log), each on top of the twin's own overrides; a value drawn beyond its bounds (:func:`_bounds`: the
    fit's walls, an FMU's range) is put on the bound (a static friction at least the Coulomb level; a parameter the
    data did not determine, whose standard error is capped far out, within the walls its fit had)."""
    sp = twin.spread
    rng = np.random.Generator(np.random.PCG64([int(seed), 35]))
    if not sp.names:
        return [dict(twin.overrides) for _ in range(n)]
    mu = np.array([math.log(c) if lg else c for c, lg in zip(sp.center, sp.log, strict=True)])
    cov = np.array(sp.cov, dtype=float)
    w, v = np.linalg.eigh(0.5 * (cov + cov.T))
    cov = (v * np.clip(w, 0.0, None)) @ v.T  # the nearest positive semidefinite covariance
    z = rng.multivariate_normal(mu, cov, size=n, method="eigh")
    bounds = [_bounds(twin, nm) for nm in sp.names]
    out = []
    for row in z:
        vals = {nm: float(np.clip(math.exp(v) if lg else v, *b))
                for nm, v, lg, b in zip(sp.names, row, sp.log, bounds, strict=True)}  # fmt: skip
        out.append({**twin.overrides, **vals})
    return out


def with_record_offset(twin: Twin, record: Record) -> Twin:
    """The twin whose gauge reads ``record``'s offset (``sensor.alpha_offset@<record>`` [deg as read], which the
    record's controller acted on): the diagnosis's fit for a record of the diagnosed run, else the record's reading at
    rest as a diagnosis starts its replay (:attr:`harness.diagnosis.experiments.RigExperiment.alpha_rest`): a record
    the twin was not identified from has a gauge zero of its own (an importer leaves it where the link never rests)."""
    key = offset_key(record.name)
    own = twin.run is not None and record.run.resolve() == twin.run.resolve()
    if own and key in twin.overrides:
        return twin
    adc_range = specmod.fmu_value(twin.daq, "daq", "adc_range")
    x = load_experiments(record.run, load_calibration(record.run), twin.spec, adc_range)[record.name]
    return replace(twin, overrides={**twin.overrides, key: float(x.alpha_rest)})


def _bounds(twin: Twin, name: str) -> tuple[float, float]:
    """Where a drawn parameter is clipped: a linear parameter's search walls (:data:`harness.diagnosis.recalibrate.
    LINEAR`, factors of the sheet's value), else the range an FMU parameter's modelDescription.xml declares, else none
    (a record's gauge offset)."""
    if name in LINEAR:
        b = LINEAR[name]
        nominal = twin.sheet_value(name)
        return (b.lo * nominal, b.hi * nominal) if b.log else (b.lo, b.hi)
    table, key = name.split(".", 1)
    v = source_model(MODELS[table]).parameters().get(key) if table in MODELS else None
    if v is None:
        return -math.inf, math.inf
    return (-math.inf if v.min is None else v.min), (math.inf if v.max is None else v.max)


@dataclass(frozen=True, eq=False)
class Record:
    """A closed-loop record as read: ``t`` [s], reference ``ref``, ``theta``, ``alpha`` [deg] (the run's calibration,
    theta unwrapped), command ``u`` [V], at ``Ts`` [s], with its ``controller`` (None when the run has none)."""

    run: Path
    name: str
    Ts: float
    t: np.ndarray
    ref: np.ndarray
    theta: np.ndarray
    alpha: np.ndarray
    u: np.ndarray
    controller: Controller | None


def load_record(run: str | Path, name: str | None = None) -> Record:
    """A closed-loop record of run directory ``run``: experiment ``name``, else its first closed-loop one (one with a
    reference); one line when it has none."""
    run = Path(run)
    man = Manifest.load(run)
    closed = [e for e in man.experiments if e.loop == "closed" and e.role != "calibration"]
    if name is not None:
        closed = [e for e in closed if e.name == name]
    if not closed:
        which = f"no closed-loop record named {name!r}" if name else "no closed-loop record (none has a reference)"
        raise DataError(f"{run}: {which}")
    e = closed[0]
    df = read_dataset(RunDir(run).dataset(e.name))
    if "ref" not in df.columns:
        raise DataError(f"{run}: record {e.name!r} has no reference column")
    cal = load_calibration(run)
    ctrl = Controller(**e.controller) if e.controller else None
    return Record(
        run=run,
        name=e.name,
        Ts=sample_time(df),
        t=df["t"].to_numpy(float),
        ref=df["ref"].to_numpy(float),
        theta=theta_deg(df["theta_v"].to_numpy(float), cal),
        alpha=alpha_deg(df["alpha_v"].to_numpy(float), cal),
        u=df["u"].to_numpy(float),
        controller=ctrl,
    )
