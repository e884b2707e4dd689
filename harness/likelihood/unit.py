"""A unit's records through the likelihood engine: its linear model fitted by maximum likelihood, and what it finds.

The run directory is read as the diagnosis reads it (:func:`harness.diagnosis.experiments.load_experiments`: the
run's calibration, the pot's dead band and the ADC's rails masked); each record carries the lattice its readings sit
on (an ADC's found in its volts, an encoder's counts or a record's last decimal). The sheet's linear parameters are
the start and the priors' centre (:func:`harness.diagnosis.diagnose.priors`: the spec's uncertainty, a sensor
measured with the data known to its calibration's error), the noise's start is the data's (:func:`.fit.noise_start`).

The linear model first: a linear parameter at its bound says that the spec does not describe the rig (which part, in
words: :func:`harness.diagnosis.recalibrate.parts_at_bound`), a white torque at its upper bound that the linear
model cannot draw what the records show; both are findings, not a start for effects (:attr:`UnitFit.findings`).
"""

from __future__ import annotations

import dataclasses
import textwrap
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from .. import spec as specmod
from ..diagnosis import rigmodel
from ..diagnosis.diagnose import priors
from ..diagnosis.experiments import load_experiments
from ..diagnosis.gauge import gauge_delay
from ..diagnosis.noise import adc_lattice
from ..diagnosis.recalibrate import LINEAR, parts_at_bound
from ..diagnosis.result import Diagnosis
from ..diagnosis.simulation import fmu_value, sim_rig
from ..ident.calibration import Calibration, load_calibration
from ..rundir import write_json
from .effects import (
    FRICTION_SHAPE,
    FRICTION_SHAPE_EFFECT,
    INTERIOR,
    NESTED,
    PROFILED,
    SENSOR_NESTED,
    SHAPE,
    nested_start,
    profile_settings,
    search_order,
)
from .fit import BOUNDS, TORQUES, Estimate, MLFit, filter_record, fit, innovations, noise_start, split_values
from .force import EffectCurve, ForcePicture, MissingForce, classify, effect_curve, force_picture
from .model import EFFECTS, rig_model
from .record import Record
from .rule import EffectTest, Rule
from .simulate import whiteness_scale
from .whiteness import LAGS, LEVEL, Where, ljung_box, where

__all__ = [
    "EffectFit",
    "RunRecords",
    "UnitFit",
    "check_records",
    "load_records",
    "fit_run",
    "fit_unit",
    "folds_of",
    "linear_start",
    "with_likelihood",
    "write_likelihood",
]


@dataclass(frozen=True)
class EffectFit:
    """An effect fitted with the linear model from the linear fit: its ``name`` (as ``diagnosis.json`` names
    effects), the ``fit`` (the linear parameters and the noise refitted beside the effect's own), the effect's own
    ``parameters`` (names as the plant FMU's; a nested effect's) or its integer ``settings`` (an integer effect's best,
    by profile), the ``test`` of its likelihood-ratio statistic over the linear model
    (:class:`harness.likelihood.rule.EffectTest`), the drive's torque per volt ``drive`` [N m/V] (a torque's size
    as a command), and a nested effect that passed its test, its size on each of the unit's ``folds``."""

    name: str
    fit: MLFit
    parameters: tuple[str, ...]
    test: EffectTest
    drive: float
    settings: dict[str, int] = field(default_factory=dict)
    folds: tuple[Estimate, ...] = ()

    @property
    def lr(self) -> float:
        """The likelihood-ratio statistic over the model it is nested on (the linear fit, or the linear fit with the
        effects that entered before it), 2 (logL - logL_base) [nats]."""
        return self.test.lr

    def line(self) -> str:
        """The effect in one line (under 100 characters): its parameters with their intervals (a torque also as the
        command it takes), its LR over the critical value and whether it enters."""
        parts = []
        for k in self.parameters:
            e = self.fit.estimates[k]
            volts = f" = {e.value / self.drive:.3g} V" if e.unit == "N m" else ""
            parts.append(f"{e.value:.4g} {e.unit}{volts} (95 % {e.ci95[0]:.3g}..{e.ci95[1]:.3g})")
        parts += [f"{k.split('.')[1]} {v}" for k, v in self.settings.items()]
        t = self.test
        verdict = f"> {t.critical:.3g}: enters" if t.enters else f"<= {t.critical:.3g}: stays out"
        if t.lr > t.critical and not t.enters:
            verdict = f"> {t.critical:.3g} but stays out: held out, {t.held_out:.3g} nats"
        if t.agrees is False:
            verdict += " (folds apart)"
        return f"  {self.name}: {'; '.join(parts)}, LR {t.lr:.3g} {verdict}"

    def to_json(self) -> dict[str, Any]:
        """As an entry of ``effects`` in likelihood.json."""
        f = self.fit
        return {
            "parameters": {k: {"fitted": f.estimates[k].value, "ci95": list(f.estimates[k].ci95),
                               "unit": f.estimates[k].unit, "at_bound": f.estimates[k].at} for k in self.parameters}
                          | {k: {"fitted": v} for k, v in self.settings.items()},
            "likelihood": {"logL": f.loglik, "k": f.k, "n": f.n, **self.test.to_json()},
            "folds": [{"fitted": e.value, "ci95": list(e.ci95)} for e in self.folds],
            "converged": f.converged,
        }  # fmt: skip


@dataclass(frozen=True)
class UnitFit:
    """The likelihood engine's fit of a unit's linear model: the ``fit``, the ``records`` it ran through, the sheet's
    ``nominal`` values, the ``held`` parameters (a sensor known exactly), each record's residuals' lag-one
    autocorrelation per channel (``lag_one``: white residuals give about 0, within +-2/sqrt(n)) and its Ljung-Box
    p-value (``whiteness``: white at :data:`harness.likelihood.whiteness.LEVEL` and above), the
    ``findings`` (a parameter at its bound, in words; none: effects may be tried from here) and what the fitted
    model lacks (``missing_force``, :func:`harness.likelihood.force.classify`: its shape and size, of the smoothed
    ``picture``, :func:`harness.likelihood.force.force_picture`), and the ``effects`` fitted as nested models from the
    linear fit (none where it has a finding), and how many samples late the gauge reads (``gauge_late``, the records'
    own timing: its readings are put back in time). Where an effect enters, the picture is drawn on its fit's linear
    parameters without it (``drawn_without``), and its ``curve`` (:func:`harness.likelihood.force.effect_curve`)
    goes over it. The integer effects that entered (a second mode, a delay: ``structure``) are the linear model's
    own: ``fit`` is the fit with them, and everything after it (the findings, the nested effects, the picture) is
    drawn from it. ``where`` says, per record and channel, in which octave bands and stretches of time the linear
    fit's residuals are not white (:func:`harness.likelihood.whiteness.where`). ``final`` is the linear model with
    every nested effect that entered (None: none did; the last forward step's fit: each effect is nested on the model
    with those that entered before it, the strongest of a step entering), ``final_whiteness`` its
    residuals' Ljung-Box p-values as ``whiteness`` (empty where none entered: ``whiteness`` is the best model's),
    each test's law scaled by ``final_scale`` (what the filter keeps on records the model draws,
    :func:`harness.likelihood.simulate.whiteness_scale`: its friction and its bent gauge are approximations).
    ``lattice_bits``: the bits of an ADC's lattice the records sit on that the sheet's DAQ does not have (0: none)."""

    fit: MLFit
    records: tuple[str, ...]
    nominal: dict[str, float]
    held: dict[str, float]
    lag_one: dict[str, dict[str, float]]
    whiteness: dict[str, dict[str, float]]
    findings: tuple[str, ...]
    missing_force: MissingForce
    picture: ForcePicture
    effects: tuple[EffectFit, ...] = ()
    gauge_late: int = 0
    drawn_without: str | None = None
    curve: EffectCurve | None = None
    structure: tuple[str, ...] = ()
    where: dict[str, dict[str, Where]] = field(default_factory=dict)
    final: MLFit | None = None
    final_whiteness: dict[str, dict[str, float]] = field(default_factory=dict)
    final_scale: dict[str, dict[str, float]] = field(default_factory=dict)
    lattice_bits: int = 0

    def summary(self) -> list[str]:
        """A few lines for the terminal (under 100 characters each): the fit, the parameters that moved most from
        the sheet, the findings, the missing force and the nested effects."""
        f = self.fit
        head = f"likelihood engine: {len(self.records)} records, {f.n} readings, log-likelihood {f.loglik:.1f}"
        lines = [head + ("" if f.converged else f" (search stopped: {f.message[:40]})")]
        if self.structure:
            lines.append(f"  the linear model with: {', '.join(self.structure)} (each entered by the rule)")
        moved = sorted(((abs(np.log(e.value / self.nominal[k])), k, e) for k, e in f.estimates.items()
                        if k in self.nominal and e.value > 0 and self.nominal[k] > 0), reverse=True)  # fmt: skip
        for _, k, e in moved[:5]:
            unit = "" if e.unit == "1" else f" {e.unit}"
            lines.append(f"  {k:24s} {e.value:.4g}{unit} ({e.value / self.nominal[k]:.3g}x the sheet), "
                         f"95 % {e.ci95[0]:.4g}..{e.ci95[1]:.4g}")  # fmt: skip
        if self.gauge_late:
            lines.append(f"  the gauge reads {self.gauge_late} samples late (the records' timing): read so")
        found = ["  " + textwrap.shorten(f"finding: {x}", 98, placeholder=" ...") for x in self.findings[:5]]
        lines += found or ["  nothing at a bound: effects may be tried"]
        grey = [f"{r} {c}" for r, ps in self.whiteness.items() for c, p in ps.items() if p < LEVEL]
        channels = len(self.records) * 2
        white = f"residuals white (Ljung-Box, {LEVEL:g}): {channels - len(grey)} of {channels} record channels"
        lines.append(
            "  " + textwrap.shorten(white + (f"; not: {', '.join(grey)}" if grey else ""), 98, placeholder=" ...")
        )
        at = [f"{r} {c} {w.words()}" for r, ws in self.where.items() for c, w in ws.items() if w.words()]
        if at:
            lines.append("  " + textwrap.shorten(f"not white at: {'; '.join(at)}", 98, placeholder=" ..."))
        without = f" (drawn without {self.drawn_without})" if self.drawn_without else ""
        force = f"missing force{without}: {self.missing_force.words()}"
        lines.append("  " + textwrap.shorten(force, 98, placeholder=" ..."))
        lines += [x.line() for x in self.effects]
        return lines

    def to_json(self) -> dict[str, Any]:
        """The fit as ``likelihood.json`` holds it."""
        f = self.fit
        return {
            "engine": "likelihood",
            "records": list(self.records),
            "loglik": f.loglik,
            "n": f.n,
            "k": f.k,
            "converged": f.converged,
            "evaluations": f.nfev,
            "parameters": {
                name: {
                    "nominal": self.nominal.get(name),
                    "fitted": e.value,
                    "ci95": list(e.ci95),
                    "unit": e.unit,
                    "at_bound": e.at,
                }  # fmt: skip
                for name, e in f.estimates.items()
            },
            "held": self.held,
            "gauge_late_samples": self.gauge_late,
            "lag_one": self.lag_one,
            "whiteness": {"test": "Ljung-Box", "lags": LAGS, "level": LEVEL, "p": self.whiteness},
            "where": {r: {c: dataclasses.asdict(w) for c, w in ws.items()} for r, ws in self.where.items()},
            "findings": list(self.findings),
            "missing_force": self.missing_force.to_json() | {"drawn_without": self.drawn_without},
            "structure": list(self.structure),
            "effects": {x.name: x.to_json() for x in self.effects},
            "final": None if self.final is None else {
                "effects": [x.name for x in self.effects if x.name in NESTED and x.test.enters],
                "loglik": self.final.loglik, "k": self.final.k, "n": self.final.n,
                "whiteness": {"test": "Ljung-Box", "lags": LAGS, "p": self.final_whiteness,
                              "scale": self.final_scale},
                "noise": {k: e.value for k, e in self.final.estimates.items() if k in TORQUES},
            },
            "lattice_bits": self.lattice_bits,
        }  # fmt: skip


def linear_start(plant: dict[str, Any]) -> dict[str, float]:
    """The sheet's values of the linear parameters the engine fits for a plant table: the drive's combos, the link's
    stiffness and damping, the sensors' gains (1: as calibrated)."""
    return rigmodel.combos(plant) | {
        "plant.Ks": rigmodel.plant_value(plant, "Ks"),
        "plant.zeta_link": rigmodel.plant_value(plant, "zeta_link"),
        "sensor.theta_gain": 1.0,
        "sensor.alpha_gauge_gain": 1.0,
    }


@dataclass(frozen=True)
class RunRecords:
    """A run's records as the filter reads them (``records``, each with its lattice [deg], its gauge put back in
    time and its command clamped at the DAQ's output limit: :meth:`Record.clamped`), the command's delay ``delay``
    [samples], whether every record's hub angle is an ``encoder``'s, and how many samples late the gauge reads
    (``gauge_late``: the records' own timing, :func:`harness.diagnosis.gauge.gauge_delay`, as today's diagnosis
    reads it); the run's ``calibration``; the gauge's low-pass time constant ``gauge_tau`` [s] the DAQ's sheet gives
    (0: none known); the bits of an ADC's lattice the records sit on that the sheet's DAQ does not have
    (``lattice_bits``, :func:`harness.diagnosis.noise.adc_lattice`; 0: none)."""

    records: list[Record]
    delay: int
    encoder: bool
    gauge_late: int
    calibration: Calibration
    gauge_tau: float = 0.0
    lattice_bits: int = 0


def load_records(real: Path, sim: specmod.Spec) -> RunRecords:
    """The records of run ``real`` with the DAQ of spec ``sim``: :class:`RunRecords`."""
    cal = load_calibration(real)
    _, daq = sim_rig(sim)
    adc_range = fmu_value(daq, "daq", "adc_range")
    out_limit = fmu_value(daq, "daq", "out_limit")
    exps = load_experiments(real, cal, sim, adc_range)
    bits = adc_lattice(exps, adc_range)
    lsb = 2.0 * adc_range / 2.0**bits if bits else 0.0
    late = gauge_delay(exps).samples
    out = []
    for x in exps.values():
        rec = Record.from_experiment(x)
        step = (max(rec.lattice[0], abs(cal.Kp) * lsb), max(rec.lattice[1], abs(cal.Ke) * lsb))
        out.append(Record(rec.name, rec.Ts, rec.u, rec.y, rec.mask, step).gauge_late(late).clamped(out_limit))
    encoder = all(x.encoder for x in exps.values())
    new = bits if bits and bits != int(fmu_value(daq, "daq", "adc_bits")) else 0
    return RunRecords(out, int(fmu_value(daq, "daq", "delay_samples")), encoder, late, cal,
                      float(fmu_value(daq, "daq", "gauge_tau")), new)  # fmt: skip


def check_records(plant: dict[str, Any], values: dict[str, float], records: list[Record], delay: int = 0) -> None:
    """Refuse, in one line, records the engine cannot fit: a reading whose noise the data cannot determine (its third
    differences are zero on every record: a channel that never changes, or one written without noise or lattice) and
    a record too short for the filter to settle. The filter has settled on the first sample on which the hub's
    predicted reading variance (without a lattice: the Riccati recursion's, which the readings do not move) comes
    within twice its median over the record's second half; a record needs half its readings
    and :data:`harness.likelihood.whiteness.LAGS` times five after that (the whiteness test's).

    Parameters
    ----------
    plant : dict
        The spec's plant table.
    values : dict
        Parameters the filter runs with (the sheet's and the noise's start).
    records : list of Record
        The unit's records.
    delay : int
        The command's delay [samples].

    Raises
    ------
    ValueError
        Naming the record or channel and why.
    """
    for j, (channel, name) in enumerate((("theta", "hub angle"), ("alpha", "gauge"))):
        d3 = [np.diff(r.y[r.mask[:, j], j], 3) for r in records]
        if not any(np.any(d != 0.0) for d in d3):
            raise ValueError(f"the {name} readings ({channel}) have no third differences on any record (no noise, no "
                             "lattice): the data cannot determine their noise")  # fmt: skip
    for rec in records:
        plain = Record(rec.name, rec.Ts, rec.u, np.zeros_like(rec.y), rec.mask)  # its variances the readings' own
        s = filter_record(plant, values, plain, delay).s[:, 0][rec.mask[:, 0]]
        late = s[s.size // 2 :]
        near = np.flatnonzero(s <= 2.0 * np.median(late)) if late.size else np.array([], dtype=int)
        settled = int(near[0]) if near.size else s.size
        if settled > s.size // 2 or s.size - settled < 5 * LAGS:
            raise ValueError(f"record {rec.name}: {s.size} readings, too short for the filter to settle "
                             f"(it settles after {settled}; it needs half the record and {5 * LAGS} more)")  # fmt: skip


def fit_run(
    real: Path, sim: str | Path | specmod.Spec, progress: Callable[[str], None] | None = None, rule: Rule | None = None
) -> UnitFit:
    """Fit the linear model of run ``real``'s records against the sim spec ``sim`` by maximum likelihood.

    Parameters
    ----------
    real : Path
        A run directory (a campaign or an import) with its calibration.
    sim : str, Path or Spec
        The spec whose sheet the fit starts from and whose uncertainty makes the priors.
    progress : callable, optional
        Told what runs now.
    rule : Rule, optional
        How a nested effect is judged (default :class:`harness.likelihood.rule.Rule`'s level).

    Returns
    -------
    UnitFit

    Raises
    ------
    ValueError
        Records the engine cannot fit (:func:`check_records`), before any fit.
    """
    spec = sim if isinstance(sim, specmod.Spec) else specmod.load(sim)
    plant, _ = sim_rig(spec)
    run = load_records(Path(real), spec)
    records, delay, encoder = run.records, run.delay, run.encoder
    sd, _ = priors(spec, run.calibration.gain_rel_se(), encoder)
    nominal = linear_start(plant) | ({"sensor.gauge_tau": run.gauge_tau} if run.gauge_tau > 0 else {})
    held = {k: v for k, v in nominal.items() if sd.get(k, 1.0) == 0.0}  # a sensor known exactly
    check_records(plant, nominal | noise_start(records), records, delay)
    return fit_unit(
        plant,
        records,
        nominal,
        held,
        sd,
        delay,
        rule=rule,
        progress=progress,
        gauge_late=run.gauge_late,
        lattice_bits=run.lattice_bits,
    )


def fit_unit(
    plant: dict[str, Any],
    records: list[Record],
    nominal: dict[str, float],
    held: dict[str, float],
    sd: dict[str, float],
    delay: int = 0,
    *,
    rule: Rule | None = None,
    progress: Callable[[str], None] | None = None,
    gauge_late: int = 0,
    lattice_bits: int = 0,
) -> UnitFit:
    """A unit's records through the engine: the linear model, its findings, the effects nested on it, the missing
    force (what :func:`fit_run` does once it has read a run directory).

    Parameters
    ----------
    plant : dict
        The spec's plant table.
    records : list of Record
        The unit's records, as the filter reads them.
    nominal : dict
        The sheet's linear parameters (:func:`linear_start`): the start and the priors' centre.
    held : dict
        Parameters held at these values (a sensor known exactly).
    sd : dict
        The priors' standard deviations in the search coordinate, by parameter (absent: flat).
    delay : int
        The command's delay [samples].
    rule : Rule, optional
        How a nested effect is judged.
    progress : callable, optional
        Told what runs now.
    gauge_late : int
        How many samples late the gauge read (already put back in ``records``), for the summary.
    lattice_bits : int
        The bits of an ADC's lattice the records sit on that the sheet's DAQ does not have (0: none).

    Returns
    -------
    UnitFit
    """
    say = progress or (lambda _m: None)
    rule = rule or Rule()
    free = {k: v for k, v in nominal.items() if k not in held}
    noise = noise_start(records)
    scales = nominal | noise  # what each search coordinate is a factor of

    def linear_fit(p: dict[str, Any], d: int, start: MLFit | None = None) -> MLFit:
        """The linear model of plant table p at delay d, from the sheet or from a neighbouring fit."""
        begin = free | noise if start is None else {k: v for k, v in start.values().items() if k not in held}
        return fit(p, records, begin, fixed=held, nominal=scales,
                   prior_sd={k: sd[k] for k in free if k in sd}, delay=d)  # fmt: skip

    say(f"maximum likelihood over {len(records)} records")
    res = linear_fit(plant, delay)
    # the linear model's structure first: a second link mode, the command's delay, each by profile against the
    # sheet's (a missing mode drives the one-mode fit to its bounds), the model changed where one enters
    effects: list[EffectFit] = []
    for name in PROFILED:
        if tried := profile_settings(name, plant, delay, min(r.Ts for r in records)):
            say(f"{name}, by profile")
            eff, alt_plant, alt_delay = _profiled(name, tried, plant, delay, records, res, held, linear_fit, rule)
            effects.append(eff)
            if eff.test.enters:
                plant, delay, res = alt_plant, alt_delay, eff.fit
    for name, param in SENSOR_NESTED.items():  # the sensors' dynamics the sheet does not give, nested at none
        if param not in nominal:
            say(f"{name}, nested")
            eff = _nested(name, plant, records, res, held, scales, sd, delay, rule)
            effects.append(eff)
            if eff.test.enters:  # the linear model with it: its search scaled as the nested one's
                res, scales = eff.fit, scales | {param: nested_start(name, records, eff.drive).nominal}
    structure = tuple(x.name for x in effects if x.test.enters)
    values = res.values() | held
    lag_one, white, places = {}, {}, {}
    for rec in records:
        z = filter_record(plant, values, rec, delay).standardised(np.asarray(rec.lattice))
        lag_one[rec.name] = {c: _lag_one(z[:, j]) for j, c in enumerate(("theta", "alpha"))}
        white[rec.name] = _white(z)
        places[rec.name] = {c: where(z[:, j], rec.Ts) for j, c in enumerate(("theta", "alpha"))}
    linear = {k: (nominal[k], e.value) for k, e in res.estimates.items() if k in LINEAR}
    findings = [*parts_at_bound(linear)]
    findings += [f"{BOUNDS[k].label} ends at its upper bound: the linear model cannot draw what the records show"
                 for k, side in res.at_bounds().items() if k in TORQUES and side == "upper"]  # fmt: skip
    # the nested effects, forward: each fitted on the model so far, the strongest that enters added to it, the rest
    # fitted again on that (an effect the model lacks bends the others' fits and their held-out scores)
    nested: dict[str, EffectFit] = {}
    base, on = res, scales
    entered: list[EffectFit] = []
    todo = [] if findings else list(NESTED)
    while todo:
        for name in todo:
            say(f"{name}, nested" + "".join(f" on {x.name}" for x in entered[-1:]))
            nested[name] = _nested(name, plant, records, base, held, on, sd, delay, rule)
        passed = [nested[n] for n in todo if nested[n].test.enters]
        if not passed:
            break
        top = max(passed, key=lambda x: x.lr)
        entered.append(top)
        base, on = top.fit, on | {NESTED[top.name]: nested_start(top.name, records, top.drive).nominal}
        todo = [n for n in todo if n != top.name]
    effects += [nested[n] for n in NESTED if n in nested]
    if any(x.name == "coulomb_friction" for x in entered):  # friction's breakaway and Stribeck drop, on the model
        say("friction's shape, nested")
        shape = _friction_shape(plant, records, base, held, on, sd, delay, rule)
        effects.append(shape)
        if shape.test.enters:
            base = shape.fit
    final, final_white, final_scale = None, {}, {}
    if entered:  # the linear model with every nested effect that entered, and whether its residuals are white
        final = base
        # its filter is an approximation (friction's moments over 1 ms, a bent gauge linearised): its whiteness
        # test's law scaled by what it keeps on records the model draws
        final_scale = whiteness_scale(plant, final.values() | held, records, delay)
        final_white = {rec.name: _white(filter_record(plant, final.values() | held, rec, delay)
                                        .standardised(np.asarray(rec.lattice)), final_scale[rec.name])
                       for rec in records}  # fmt: skip
    say("the missing force")
    kept = max((x for x in effects if x.name in SHAPE and x.test.enters), key=lambda x: x.lr, default=None)
    # drawn on the linear parameters of the nested effect that entered, the effect left out: its force is then the
    # missing one, unbent by the linear fit that had to make up for it (the drive's gain 25 % low on the lab run)
    drawn = values if kept is None else {k: v for k, v in (kept.fit.values() | held).items() if k not in EFFECTS}
    picture = force_picture(plant, drawn, records, delay)
    curve, mf = None, classify(picture)
    if kept is not None:
        param = NESTED[kept.name]
        curve = effect_curve(param, kept.fit.values()[param], picture)
        if SHAPE[kept.name] == mf.shape:  # sized by the nested effect's maximum likelihood
            size = kept.fit.values()[param]
            volts = size / kept.drive if mf.unit == "N m" else mf.dead_band_v
            mf = replace(mf, size=size, dead_band_v=volts, sized_by=kept.name, picture_size=mf.size)
    return UnitFit(res, tuple(r.name for r in records), nominal, held, lag_one, white, tuple(findings), mf,
                   picture, tuple(effects), gauge_late, kept.name if kept else None, curve, structure,
                   places, final, final_white, final_scale, lattice_bits)  # fmt: skip


def _white(z: np.ndarray, scale: dict[str, float] | None = None) -> dict[str, float]:
    """The Ljung-Box p-value of each channel's standardised residuals (n x 2: theta, alpha), its law scaled by the
    channel's ``scale`` where given (:func:`harness.likelihood.simulate.whiteness_scale`)."""
    return {c: ljung_box(z[:, j], scale=(scale or {}).get(c, 1.0)).p for j, c in enumerate(("theta", "alpha"))}


def _nested(
    name: str,
    plant: dict[str, Any],
    records: list[Record],
    linear: MLFit,
    held: dict[str, float],
    nominal: dict[str, float],
    sd: dict[str, float],
    delay: int,
    rule: Rule,
) -> EffectFit:
    """The effect ``name`` (:data:`harness.likelihood.effects.NESTED`) fitted as a nested model from the linear fit
    ``linear``: from inside the effect and from its null (:func:`harness.likelihood.effects.nested_start`), the
    better kept (a search from inside alone can stop in a basin the linear parameters make for it, below the null),
    judged by ``rule``."""
    param = {**NESTED, **SENSOR_NESTED}[name]
    drive = rig_model(plant, *split_values(linear.values() | held)).drive
    at = nested_start(name, records, drive)
    fits = []
    for begin in (at.inside, at.null):
        start = {k: v for k, v in linear.values().items() if k not in held} | {param: begin}
        fits.append(fit(plant, records, start, fixed=held, nominal=nominal | {param: at.nominal},
                        prior_sd={k: sd[k] for k in start if k in sd}, delay=delay))  # fmt: skip
    res = max(fits, key=lambda f: f.loglik)
    drive = rig_model(plant, *split_values(res.values() | held)).drive  # the drive as the nested fit has it
    # the null's maximum: the model it is nested on, or a search that ended with the effect at its null and the rest
    # further on (then the effect's statistic is none of the rest's gain)
    null = max([linear.loglik, *(f.loglik for f in fits if f.values()[param] == at.null)])
    test = rule.test(2.0 * (res.loglik - null), res.estimates[param].inflation, name in INTERIOR)
    scale = nominal | {param: at.nominal}
    test, folds = _held_out(test, plant, records, res, linear, held, scale, sd, delay, param, rule)
    return EffectFit(name, res, (param,), test, drive, folds=folds)


def _held_out(
    test: EffectTest,
    plant: dict[str, Any],
    records: list[Record],
    res: MLFit,
    base: MLFit,
    held: dict[str, float],
    nominal: dict[str, float],
    sd: dict[str, float],
    delay: int,
    param: str,
    rule: Rule,
    base_held: dict[str, float] | None = None,
) -> tuple[EffectTest, tuple[Estimate, ...]]:
    """``test`` of the fit ``res`` nested on ``base``, where its statistic passes, with the rule's held-out
    condition: each of the unit's two folds (:func:`folds_of`) fitted with the effect and without it, the gain of
    each fold's fit on the other fold's records, summed; and its parameter ``param``'s size on each fold (whether
    their intervals agree, said). ``base_held``: what ``base`` held (default ``held``). Returns the test and the
    sizes (none where the statistic does not pass)."""
    if not test.lr > test.critical:
        return test, ()
    parts, fixed = folds_of(records), held if base_held is None else base_held

    def on(part: list[Record], begin: MLFit, keep: dict[str, float]) -> MLFit:
        start = {k: v for k, v in begin.values().items() if k not in keep}
        return fit(plant, part, start, fixed=keep, nominal=nominal, prior_sd={k: sd[k] for k in start if k in sd},
                   delay=delay)  # fmt: skip

    with_it, without = [on(part, res, held) for part in parts], [on(part, base, fixed) for part in parts]
    folds = tuple(f.estimates[param] for f in with_it)
    gain = sum(_scored(plant, a, other, held, delay) - _scored(plant, b, other, fixed, delay)
               for a, b, other in zip(with_it, without, parts[::-1], strict=True))  # fmt: skip
    return replace(rule.agree(test, [e.ci95 for e in folds]), held_out=float(gain)), folds


def _friction_shape(
    plant: dict[str, Any],
    records: list[Record],
    base: MLFit,
    held: dict[str, float],
    nominal: dict[str, float],
    sd: dict[str, float],
    delay: int,
    rule: Rule,
) -> EffectFit:
    """Friction's shape beside its Coulomb level, on the model ``base`` that friction entered: the breakaway ratio
    and the Stribeck speed (:data:`harness.likelihood.effects.FRICTION_SHAPE`) fitted from their start with the rest,
    judged by ``rule`` against ``base`` refitted on the same filter (its breakaway at none: the shape's finer steps;
    the ratio's null at its wall, the speed's undetermined there: one flag each), with the held-out condition."""
    ratio, scale = "plant.stiction_ratio", nominal | FRICTION_SHAPE
    prior = {k: sd[k] for k in base.values() if k in sd and k not in held}
    begin = {k: v for k, v in base.values().items() if k not in held}
    null = fit(plant, records, begin, fixed=held | {ratio: 1.0}, nominal=scale, prior_sd=prior, delay=delay)
    start = {k: v for k, v in null.values().items() if k not in held and k != ratio} | FRICTION_SHAPE
    res = fit(plant, records, start, fixed=held, nominal=scale, prior_sd=prior, delay=delay)
    # a search that ended with no breakaway is the null's, further on (its gain is none of the shape's)
    top = max(null.loglik, res.loglik) if res.values()[ratio] <= 1.0 else null.loglik
    test = rule.test(2.0 * (res.loglik - top), res.estimates[ratio].inflation, (False, True))
    test, folds = _held_out(test, plant, records, res, null, held, scale, sd, delay, ratio, rule, held | {ratio: 1.0})
    drive = rig_model(plant, *split_values(res.values() | held)).drive
    return EffectFit(FRICTION_SHAPE_EFFECT, res, tuple(FRICTION_SHAPE), test, drive, folds=folds)


def folds_of(records: list[Record]) -> tuple[list[Record], list[Record]]:
    """A unit's two folds: a lone record's halves (:meth:`Record.halves`); else its records ordered by their largest
    |command| and dealt alternately, so that each fold holds small commands and large ones (a fold of small ones
    alone does not determine a limit or a bent gauge that the other's large ones show)."""
    if len(records) == 1:
        first, second = records[0].halves()
        return [first], [second]
    ordered = sorted(records, key=lambda r: (float(np.max(np.abs(r.u))) if r.n else 0.0, r.name))
    return ordered[0::2], ordered[1::2]


def _scored(plant: dict[str, Any], fitted: MLFit, records: list[Record], held: dict[str, float], delay: int) -> float:
    """The log-likelihood [nats] of ``records`` under the model ``fitted`` elsewhere."""
    values = fitted.values() | held
    return sum(filter_record(plant, values, r, delay).loglik for r in records)


def _profiled(
    name: str,
    settings: tuple[int, ...],
    plant: dict[str, Any],
    delay: int,
    records: list[Record],
    linear: MLFit,
    held: dict[str, float],
    linear_fit: Callable[..., MLFit],
    rule: Rule,
) -> tuple[EffectFit, dict[str, Any], int]:
    """The integer effect ``name`` (:data:`harness.likelihood.effects.PROFILED`) over ``settings``: the linear model
    fitted there (``linear_fit(plant, delay, start)``), the best judged by ``rule`` against the linear fit
    ``linear`` at the sheet's (:meth:`harness.likelihood.rule.Rule.compare`: the two fits' per-sample log-likelihood
    terms, the level shared among the settings fitted). A second mode is fitted from the sheet; delays on a coarse
    grid and then around its best (:func:`harness.likelihood.effects.search_order`), each from its neighbour's fit
    (from the sheet, a delay far off can fall into a basin with the hub's gain at its bound). Returns the effect, and
    the plant table and delay of its best setting."""
    param = PROFILED[name]
    if param == "plant.n_modes":
        fits = {m: linear_fit({**plant, "n_modes": m}, delay) for m in settings}
    else:
        grid, step = search_order(settings)
        fits, near = {}, linear
        for d in grid:
            fits[d] = near = linear_fit(plant, d, near)
        top = max(fits, key=lambda d: fits[d].loglik)
        for d in (x for x in settings if abs(x - top) < step and x not in fits):
            fits[d] = linear_fit(plant, d, fits[top])
    best = max(fits, key=lambda k: fits[k].loglik)
    p, d = ({**plant, "n_modes": best}, delay) if param == "plant.n_modes" else (plant, best)
    res = fits[best]
    null = innovations(plant, linear.values() | held, records, delay)
    alt = innovations(p, res.values() | held, records, d)
    test = rule.compare(alt.terms - null.terms, null.record, null.sample, len(fits))
    drive = rig_model(p, *split_values(res.values() | held)).drive
    return EffectFit(name, res, (), test, drive, {param: best}), p, d


def _lag_one(z: np.ndarray) -> float:
    ok = np.isfinite(z[:-1]) & np.isfinite(z[1:])
    if ok.sum() < 3:
        return float("nan")
    return float(np.corrcoef(z[:-1][ok], z[1:][ok])[0, 1])


def with_likelihood(diagnosis: Diagnosis, unit: UnitFit) -> Diagnosis:
    """``diagnosis`` with each candidate the engine fitted given its ``likelihood`` (its fit's ``logL``, ``k``,
    ``n`` and its test: :meth:`EffectFit.to_json`'s ``likelihood``)."""
    tried = {x.name: x.to_json()["likelihood"] for x in unit.effects}
    candidates = [replace(c, likelihood=tried.get(c.effect, c.likelihood)) for c in diagnosis.candidates]
    return replace(diagnosis, candidates=candidates)


def write_likelihood(out: Path, unit: UnitFit, verdict: dict[str, Any] | None = None) -> Path:
    """Write ``out/likelihood.json`` (atomically, byte-stable), with the ``verdict`` on the fit where given
    (:meth:`harness.diagnosis.decide.Decision.to_json`), and return its path."""
    path = Path(out) / "likelihood.json"
    write_json(path, unit.to_json() | ({"verdict": verdict} if verdict else {}))
    return path
