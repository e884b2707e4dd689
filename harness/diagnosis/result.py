"""``diagnosis.json``, defined once: the dataclasses the diagnoser fills and every reader (blind test, report,
viewer, CLI) loads.

:class:`Diagnosis` has one field per top-level key of the file; the parts a reader uses are typed
(:class:`FoundEffect`, :class:`Candidate`, :class:`FittedParameter`, :class:`Gap` with its
:class:`Decomposition` and :class:`Step`, :class:`NoiseFloor`, :class:`Folds`, :class:`Thresholds`); the bulky
``where`` (the localisation of the gap, :mod:`harness.diagnosis.where`) and ``rounds`` (every candidate of every
round of the forward selection) stay plain JSON.

Units: gaps are sqrt of a mean normalised squared error (0 = identical, 1 = no better than the mean), fit % =
100 (1 - gap), shares and shrinks in %, angles in deg, gains in deg/V, offsets in V. A JSON ``null`` (a NaN the
diagnoser wrote) reads back as NaN in a float field. An optional key that a file does not hold reads as None and
is not written back, so ``Diagnosis.load(p).write(q)`` gives ``q`` the bytes of ``p``.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from ..rundir import DataError, RunDir, from_plain, to_plain, write_json
from .recalibrate import LINEAR, at_bound

__all__ = [
    "APART_MIN",
    "CHANNEL_STAGES",
    "Candidate",
    "Decomposition",
    "Diagnosis",
    "Band",
    "ExperimentGap",
    "FittedParameter",
    "Folds",
    "FoundEffect",
    "Gap",
    "GapSummary",
    "HeldOutGap",
    "NoiseFloor",
    "SensorCalibration",
    "RecordBehaviour",
    "RecordSensors",
    "RigFit",
    "Step",
    "StepBehaviour",
    "Thresholds",
    "apart",
    "round_floats",
]

T = TypeVar("T")
# two fits of one parameter are apart (model error, not noise) when their 95 % intervals exclude each other and they
# differ by more than this share of the larger: closer fits are one rig for any use of them, whatever their
# intervals say (a closed loop's intervals miss the error its start and its fed-back noise make)
APART_MIN = 0.05
FIRST_STAGE = "simulation as given"  # the waterfall's first bar: the held-out gap before anything is fitted


# ----------------------------------------------------------------------------------------------- the parts


@dataclass
class SensorCalibration:
    """The real run's sensor calibration the data were converted with: Kp, Ke [deg/V], gauge offset [V]; the
    gauge's delay behind the hub angle [s] read from the records (:mod:`harness.diagnosis.gauge`; every replay's DAQ
    has it) and how it was read."""

    Kp: float
    Ke: float
    gauge_offset_v: float
    gauge_delay_s: float | None = None
    gauge_delay_method: str | None = None


@dataclass
class Folds:
    """The 2-fold cross-fit: experiment names of folds A and B (one experiment: in both) and the scheme."""

    A: list[str]
    B: list[str]
    scheme: str

    def role(self, experiment: str) -> str:
        """The experiment's fold: "fold A" (scored with parameters fitted on B), "fold B", "A and B" (a lone
        experiment, in both), "—" (not diagnosed)."""
        a, b = experiment in self.A, experiment in self.B
        return "A and B" if a and b else "fold A" if a else "fold B" if b else "—"


def apart(a: list[float], b: list[float]) -> bool:
    """Are two fits [value, lo, hi] of one parameter apart: 95 % intervals that exclude each other, values more
    than APART_MIN apart?"""
    (va, lo_a, hi_a), (vb, lo_b, hi_b) = a, b
    return (hi_a < lo_b or hi_b < lo_a) and abs(va - vb) > APART_MIN * max(abs(va), abs(vb))


@dataclass
class FittedParameter:
    """One row of the parameter table: a linear parameter recalibrated, or the parameter of an effect found, or a
    secondary parameter freed with one (backlash's ``plant.Jm_share``). ``nominal``: the simulation's value,
    ``fitted`` on every experiment's fit window, ``ci95`` its 95 % interval, ``change_pct`` = 100 (fitted /
    nominal - 1) for the linear parameters (NaN otherwise), ``unit``, ``finding``: one sentence (linear and
    secondary parameters; None for an effect's own parameter); for the linear ones ``at_bound`` ("lower", "upper"
    or None: the fit ended at its search bound), ``identifiable`` (False: the 95 % interval spans more than a
    factor 100; left out otherwise) and ``recalibrated``: what recalibration alone fitted, before any effect (the
    geometric mean of the two folds' fits, the model the waterfall's "recalibration" stage scores; ``fitted`` is
    refitted jointly with the effects found, so the two differ where the recalibration compensated an effect),
    ``folds``: recalibration alone on each fold, [fitted, lo, hi] (fold A, fold B: with two records or more, each
    fold is records of its own); ``records``: recalibration alone on each record of a unit of three or more, record ->
    [fitted, lo, hi]. A parameter kept at the spec's value, not fitted, has an interval of NaN
    (:attr:`kept`)."""

    nominal: float
    fitted: float
    ci95: list[float]
    change_pct: float
    unit: str
    finding: str | None = None
    at_bound: str | None = None
    identifiable: bool | None = None
    recalibrated: float | None = None
    folds: list[list[float]] | None = None
    records: dict[str, list[float]] | None = None

    @property
    def records_apart(self) -> list[tuple[str, str]]:
        """The pairs of records whose own fits (:attr:`records`) are apart (:func:`apart`)."""
        r = self.records or {}
        names = list(r)
        return [(a, b) for i, a in enumerate(names) for b in names[i + 1 :] if apart(r[a], r[b])]

    @property
    def folds_disagree(self) -> bool:
        """Are the two folds' own fits apart (:func:`apart`: model error, not noise)?"""
        return self.folds is not None and len(self.folds) == 2 and apart(*self.folds)

    @property
    def kept(self) -> bool:
        """Kept at the spec's value, not fitted (no interval)."""
        return not all(math.isfinite(v) for v in self.ci95)

    @property
    def off_spec(self) -> bool:
        """A linear finding that the rig differs from the spec (not "matches the spec", not unidentifiable)."""
        return self.finding is not None and "matches" not in self.finding and self.identifiable is not False


@dataclass
class FoundEffect:
    """An effect found, in the order it was added. ``params``: its fitted parameter on all experiments
    ({"plant.coulomb_torque": 0.044}); ``params_folds``: fitted on fold A, on fold B; ``gap_before`` /
    ``gap_after``: held-out gap before and after it was added (with ``shrink_pct``, ``fit_pct_*``);
    ``importance_pct``: its share [%] of what removing each effect alone from the final rig reopens of its score
    on every record; ``fitted_on`` / ``held_out``: the experiments of the two fits; ``selected_by``: how it entered;
    ``against_record``: its parameter beside the record's own range ("the logged command reaches 5.5 V");
    ``held_out_fit_pct``: each record's held-out fit [%] before and after it entered (where the evidence for it
    lies: an effect one record does not exercise leaves that record's fit where it was)."""

    effect: str
    params: dict[str, float]
    params_folds: list[dict[str, float]]
    gap_before: float
    gap_after: float
    shrink_pct: float
    fit_pct_before: float
    fit_pct_after: float
    importance_pct: float
    fitted_on: list[list[str]]
    held_out: list[list[str]]
    selected_by: str
    against_record: str | None = None
    held_out_fit_pct: dict[str, list[float]] | None = None


@dataclass
class Candidate:
    """A candidate effect on the first round of the forward selection, alone on top of the recalibrated rig:
    ``params`` fitted (empty when not tried), ``held_out_share_pct``: share [%] of the excess squared gap it closes
    on held-out data (NaN when not tried: it is then ``note``'s reason), ``shrink_pct`` and ``gap_after`` (held
    out), ``refit``: set when a joint refit with the linear parameters did better than the screening;
    ``likelihood``: the likelihood engine's fit of the effect and its test (``logL``, ``k``, ``n``, ``lr``, ``p``,
    ``critical``, ...: :meth:`harness.likelihood.unit.EffectFit.to_json`'s), where ``diagnose --engine likelihood``
    tried it."""

    effect: str
    params: dict[str, float]
    held_out_share_pct: float
    shrink_pct: float | None = None
    gap_after: float | None = None
    refit: str | None = None
    note: str | None = None
    likelihood: dict[str, Any] | None = None

    @property
    def tried(self) -> bool:
        """False for an effect not fitted (already in the simulation, or no ADC lattice in the data)."""
        return math.isfinite(self.held_out_share_pct)


@dataclass
class ExperimentGap:
    """One experiment's fit [%] and residual RMS [deg] per channel (theta, alpha)."""

    fit_pct: dict[str, float]
    rms_deg: dict[str, float]

    @property
    def gap(self) -> float:
        """The experiment's gap: sqrt(mean over channels of (1 - fit / 100)^2) (NaN without a moving channel)."""
        q = [(1.0 - v / 100.0) ** 2 for v in self.fit_pct.values() if math.isfinite(v)]
        return math.sqrt(sum(q) / len(q)) if q else math.nan


@dataclass
class GapSummary:
    """The gap over all experiments with one set of parameters: ``gap``, ``fit_pct``, residual RMS [deg] per
    channel, and per experiment."""

    gap: float
    fit_pct: float
    rms_deg: dict[str, float]
    experiments: dict[str, ExperimentGap]


@dataclass
class HeldOutGap:
    """The gap on held-out data (every experiment scored with parameters fitted on the other fold): before
    anything was fitted and after recalibration and the effects found."""

    gap_before: float
    gap_after: float
    fit_pct_before: float
    fit_pct_after: float


@dataclass
class Step:
    """One stage of the waterfall: "recalibration" or an effect's name, the held-out gap after it, the share [%]
    of the excess squared gap above the floor it closes, and whether it was applied (a recalibration that closes
    nothing is not)."""

    stage: str
    gap_after: float
    closed_pct: float
    applied: bool


CHANNEL_STAGES = ("before", "after_recalibration", "after_effects")  # the stages a fit per channel is given for


@dataclass
class Decomposition:
    """The held-out gap stage by stage: ``before`` (the simulation as given), ``after_recalibration``,
    ``after_effects``, the ``noise_floor`` gap and the ``resolution``, the ``steps`` and their definition;
    ``channels``: the held-out fit [%] per channel (theta, alpha) as given ("before"), recalibrated
    ("after_recalibration") and, when effects were found, with them ("after_effects")."""

    before: float
    after_recalibration: float
    after_effects: float
    noise_floor: float
    resolution: float
    steps: list[Step]
    definition: str
    channels: dict[str, dict[str, float]] | None = None
    within_noise: bool | None = None

    def gap_channel(self, stage: str | None = None) -> str | None:
        """The channel that holds the gap at ``stage`` (default: the last one measured): the one that fits worse,
        None when neither is known."""
        fits = {c: v for c, v in (self.channels or {}).get(stage or self.last_stage(), {}).items() if math.isfinite(v)}
        return min(fits, key=lambda c: fits[c]) if fits else None

    def channel_stages(self) -> list[tuple[str, dict[str, float]]]:
        """(stage, fit [%] per channel) for each stage of CHANNEL_STAGES that has them, in that order."""
        return [(s, self.channels[s]) for s in CHANNEL_STAGES if self.channels and s in self.channels]

    def at_floor(self) -> bool:
        """Is what is left at the last stage within the replays' own spread (:attr:`within_noise`)? Then no channel
        holds a gap worth naming."""
        return bool(self.within_noise)

    def last_stage(self) -> str:
        """The last stage whose fit per channel is known: "after_effects", "after_recalibration" or "before"."""
        return ([s for s, _ in self.channel_stages()] or [CHANNEL_STAGES[0]])[-1]

    def waterfall(self) -> list[tuple[str, float, float]]:
        """(stage, held-out gap after it, closed [%]) from ("simulation as given", before, NaN) on."""
        return [(FIRST_STAGE, self.before, math.nan)] + [(s.stage, s.gap_after, s.closed_pct) for s in self.steps]


@dataclass
class Gap:
    """The sim-to-real gap: ``before`` / ``after`` (simulation as given / final parameters, all experiments),
    ``held_out``, the held-out ``shrink_pct`` and the in-sample one, ``explained_pct`` (share of the excess gap
    left after recalibration that the effects close; NaN when there is no gap beyond noise), the
    ``decomposition`` and the ``definition``."""

    before: GapSummary
    after: GapSummary
    held_out: HeldOutGap
    shrink_pct: float
    shrink_pct_in_sample: float
    explained_pct: float
    decomposition: Decomposition
    definition: str
    records: dict[str, dict[str, float]] | None = None  # a unit's record -> {"own": its fit alone, "joint": ...}

    def per_experiment(self) -> list[tuple[str, float, float]]:
        """(experiment, gap before, gap after) with the final parameters, in the diagnoser's order."""
        after = self.after.experiments
        return [(n, e.gap, after[n].gap if n in after else math.nan) for n, e in self.before.experiments.items()]


@dataclass
class NoiseFloor:
    """The measurement noise estimated from the real data: RMS [deg] per channel (with the ADC's LSB^2 / 12 added
    when the data sit on a lattice; ``estimated_deg`` then holds the estimate without it), the ``method``, the
    experiments it came from, the gap and fit % white noise of that RMS gives, and the ADC bits (0: none)."""

    theta_deg: float
    alpha_deg: float
    method: str
    sources: list[str] = field(metadata={"key": "from"})
    gap: float
    fit_pct: float
    adc_lattice_bits: int
    estimated_deg: dict[str, float] | None = None


@dataclass
class Thresholds:
    """The decision thresholds of the verdict (:class:`harness.diagnosis.search.Policy`) and what they mean."""

    none_level: float
    min_gain: float
    explained: float
    resolution: float
    meaning: str


@dataclass
class RigFit:
    """The rig as the diagnosis fitted it: ``overrides`` exactly as its replays use them (the linear parameters as
    the data determine them, ``rig.drive_gain`` ..., the effects found, the command offset, each record's gauge
    offset ``sensor.alpha_offset@<record>`` [deg]), and the covariance of the fitted ones (``names``, in the fit's
    coordinates: the natural log of the value where ``log``, the value otherwise)."""

    overrides: dict[str, float]
    names: list[str]
    log: list[bool]
    covariance: list[list[float]]


@dataclass
class Band:
    """One behaviour metric of one step: as the record ``measured`` it, and the ``median`` and 95 % band (``lo``,
    ``hi``) of the replays' ensemble (NaN where a metric is not defined: a step that did not settle, a link that
    does not ring)."""

    measured: float
    median: float
    lo: float
    hi: float

    @property
    def inside(self) -> bool:
        """Is the measured value inside the band?"""
        return self.lo <= self.measured <= self.hi

    @property
    def interval_score(self) -> float:
        """The band's interval score (Gneiting and Raftery's proper score of a central 95 % interval, in the metric's
        unit, lower is better): its width, plus 2 / 0.05 times how far the measured value lies outside it; a band
        wider than it needs to be pays its width, one that misses pays its miss."""
        return self.hi - self.lo + 40.0 * (max(self.lo - self.measured, 0.0) + max(self.measured - self.hi, 0.0))


@dataclass
class StepBehaviour:
    """A reference step of a closed-loop record [its start, s from the record's start; direction +1 up, -1 down;
    size, deg] and its metrics (:data:`harness.behaviour.METRICS`), each measured and as replayed."""

    start_s: float
    direction: int
    size_deg: float
    metrics: dict[str, Band]


@dataclass
class RecordBehaviour:
    """A closed-loop record's behaviour step by step beside its replays', and the share of its measured metrics
    inside their bands (``coverage``)."""

    steps: list[StepBehaviour]
    coverage: float


@dataclass
class RecordSensors:
    """One record's sensors as fitted: the gauge's offset [deg] (its reading of the link at rest, in the record's own
    zero: [fitted, lo, hi] where a closed loop fitted it, [value, nan, nan] where an open loop's least squares took
    it), and where the replay started the link (its reading [deg] and rate [deg/s] at the first sample)."""

    gauge_offset_deg: list[float]
    link_start_deg: float | None = None
    link_rate_start_deg_s: float | None = None


# ----------------------------------------------------------------------------------------------- the file


@dataclass
class Diagnosis:
    """``diagnosis.json``: the verdict ("none", "unexplained", "quantization" or an effect's name), the effects
    found, the candidates, the parameter table, the gap and its decomposition, the noise floor, the folds, the
    thresholds, where the gap lies (``where``, plain JSON) and every round of the selection (``rounds``); ``real``:
    the run directory of the data relative to the file's directory; ``sim_spec`` and its file name; ``replays``:
    per experiment how it was re-simulated ("open", "closed", "shooting") and why (None in older files);
    ``caveats``: what limits the verdict (a recalibrated parameter at its bound: the spec may not describe the rig),
    left out when there is none."""

    calibration: SensorCalibration
    candidates: list[Candidate]
    effects: list[FoundEffect]
    folds: Folds
    gap: Gap
    noise_floor: NoiseFloor
    parameters: dict[str, FittedParameter]
    real: str
    recalibration_applied: bool
    rounds: list[list[dict[str, Any]]]
    sim_spec: str
    sim_spec_file: str
    thresholds: Thresholds
    verdict: str
    where: dict[str, Any]
    replays: dict[str, dict[str, str]] | None = None
    caveats: list[str] | None = None
    rig: RigFit | None = None
    sensors: dict[str, RecordSensors] | None = None
    behaviour: dict[str, RecordBehaviour] | None = None

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> Diagnosis:
        """Read ``diagnosis.json`` (``path`` is the file or a run directory holding it); a missing or malformed
        file raises :class:`harness.rundir.DataError` with one line."""
        p = Path(path)
        if p.is_dir():
            p = RunDir(p).diagnosis
        if not p.is_file():
            raise DataError(f"{p}: no such diagnosis (run `flexjoint diagnose` first)")
        try:
            doc = json.loads(p.read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise DataError(f"{p}: not valid JSON ({exc})".replace("\n", " ")) from None
        try:
            return cls.from_dict(doc)
        except DataError as exc:
            raise DataError(f"{p}: {exc}") from None

    @classmethod
    def from_dict(cls, doc: Any) -> Diagnosis:
        """The diagnosis from the JSON's content; a missing key, an unknown one or a value of the wrong type
        raises :class:`harness.rundir.DataError` naming where."""
        return from_plain(cls, doc, "diagnosis")

    def to_dict(self) -> dict[str, Any]:
        """The JSON's content (NaN where the file has null; optional keys that are None left out)."""
        return to_plain(self)

    def rounded(self, digits: int = 10) -> Diagnosis:
        """The same diagnosis with every float to ``digits`` significant digits (:func:`round_floats`): what the
        diagnoser writes."""
        return Diagnosis.from_dict(round_floats(self.to_dict(), digits))

    def write(self, path: str | os.PathLike[str]) -> None:
        """Write atomically with sorted keys (:func:`harness.rundir.write_json`): byte-stable."""
        write_json(Path(path), self.to_dict())

    # ------------------------------------------------------------------------------------------- for readers

    @property
    def effect_names(self) -> list[str]:
        """The effects found, in the order they were added."""
        return [e.effect for e in self.effects]

    def fitted_effect_params(self) -> dict[str, float]:
        """Every effect parameter found, fitted on all experiments ({"plant.backlash": 0.006, ...})."""
        return {k: v for e in self.effects for k, v in e.params.items()}

    def importance_pct(self) -> dict[str, float]:
        """Drop-one importance of each effect found: its share [%] of what removing each effect alone from the final
        rig reopens of its score on every record (they add up to 100)."""
        return {e.effect: e.importance_pct for e in self.effects}

    def waterfall(self) -> list[tuple[str, float, float]]:
        """(stage, held-out gap after it, closed [%]): see :meth:`Decomposition.waterfall`."""
        return self.gap.decomposition.waterfall()

    def off_spec_findings(self) -> list[str]:
        """The parameter findings that say the rig differs from the spec (those that match are left out)."""
        return [p.finding for p in self.parameters.values() if p.off_spec and p.finding is not None]

    def recalibration_moves(self, tolerance_pct: float = 3.0) -> list[str]:
        """Per linear parameter that recalibration alone moved off its final value by more than ``tolerance_pct``
        (the joint refit with the effects moved it), one phrase: "viscous damping 0.0065 (1.6x the spec) by
        recalibration alone, 0.0041 (1x) with the effects"; a value at its search bound says so."""
        out = []
        for name, p in self.parameters.items():
            r = p.recalibrated
            if r is None or not (p.fitted and p.nominal) or abs(100.0 * (r / p.fitted - 1.0)) <= tolerance_pct:
                continue
            if p.kept:  # not fitted: no trade-off
                continue
            label = LINEAR[name].label if name in LINEAR else name
            side, side_final = at_bound(name, p.nominal, r), at_bound(name, p.nominal, p.fitted)
            alone = f"{r / p.nominal:.2g}x the spec" + (f", at its {side} bound" if side else "")
            final = f"{p.fitted / p.nominal:.2g}x" + (f", at its {side_final} bound" if side_final else "")
            out.append(f"{label} {r:.4g} ({alone}) by recalibration alone, {p.fitted:.4g} ({final}) with the effects")
        return out


def round_floats(x: Any, digits: int = 10) -> Any:
    """``x`` (JSON content) with every float to ``digits`` significant digits, so that the file carries no
    last-bit noise of the optimisers (non-finite floats stay)."""
    if isinstance(x, dict):
        return {k: round_floats(v, digits) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [round_floats(v, digits) for v in x]
    if isinstance(x, (float, np.floating)):
        v = float(x)
        return float(f"{v:.{digits}g}") if math.isfinite(v) else v
    return x


# ----------------------------------------------------------------------------------------------- conversion
