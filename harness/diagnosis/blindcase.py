"""One blind case's rig as the lab knows it, and its score: the family's campaign (:func:`campaign_spec`, with the
case's seed and rate, :func:`case_sets`), the truth hidden from the run it wrote (:func:`hide_truth`, a sheet family's
data converted with the sheet's calibration), and the diagnosis scored against the truth (:func:`score_case`). What
:mod:`harness.diagnosis.blindtest` and the design family (:mod:`harness.diagnosis.blinddesign`) both build on."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from .. import spec as specmod
from ..ident.calibration import Calibration
from ..likelihood.effects import FRICTION_SHAPE_EFFECT
from ..likelihood.unit import UnitFit
from ..rundir import Manifest, RunDir, record_inputs
from .decide import Decision
from .effects import EFFECTS
from .result import Diagnosis, FittedParameter
from .rigmodel import combos, plant_value, to_plant
from .simulation import fmu_value

BLIND_SPEC = specmod.SPEC_DIR / "blind.toml"
CLOSED_SPEC = specmod.SPEC_DIR / "blind_closed.toml"
LOOP_FAMILIES = ("closed", "wrong_sheet", "design")  # run under state feedback on specs/blind_closed.toml
SHEET_FAMILIES = ("wrong_sheet", "design")  # rigs off their sheet, the lab never recalibrating
CLOSED_RATES = (500.0, 1000.0)  # Hz: the closed-loop families' cases alternate between these sample rates

MAG_TOL = 0.25  # fitted magnitude within 25 %
KS_TOL, BEQ_TOL = 0.10, 0.25  # recalibrated Ks and Beq within 10 % and 25 % of the rig's
# what the diagnosis is scored on: its parameter row -> the truth's key in a case's ``sheet_truth``
SHEET_ROWS = ("rig.drive_gain", "rig.drive_tau", "plant.Ks", "sensor.alpha_gauge_gain")
SHEET_TOL = 0.10  # each within 10 % of the rig's


def sheet_plant() -> dict[str, Any]:
    """The plant table of the wrong_sheet family's sheet (specs/blind_closed.toml; FMU defaults for the rest)."""
    return dict(campaign_spec(family="wrong_sheet").plant)


def campaign_spec(quick: bool = False, overrides: list[str] | None = None, family: str = "twin") -> specmod.Spec:
    """The blind campaign of a family (specs/blind.toml; the closed-loop families' specs/blind_closed.toml: for
    wrong_sheet without its comb, the lab never recalibrating its gauge, and with the controller reading alpha through
    the sheet's gauge gain) with ``--set``-style overrides; ``quick`` shortens every open-loop experiment to 12 s and
    the multisine to 5 periods of 4 s, every closed-loop one to 4 s (same commands and levels: for tests)."""
    path = CLOSED_SPEC if family in LOOP_FAMILIES else BLIND_SPEC
    raw = specmod.load(path).raw
    if family in SHEET_FAMILIES:
        raw = specmod.apply_overrides(raw, [])  # a deep copy
        raw.pop("calibration", None)
        raw["controller"]["alpha_gain"] = fmu_value(raw.get("daq", {}), "daq", "gauge_gain")
    if quick:
        raw = specmod.apply_overrides(raw, [])  # a deep copy
        for e in raw["experiment"]:
            if e.get("loop") == "closed":
                e["duration"] = 4.0
            elif e["signal"] == "multisine":
                e.update(period=4.0, duration=20.0)
            else:
                e["duration"] = 12.0
    return specmod.from_dict(specmod.apply_overrides(raw, overrides or []), str(path))


def case_sets(case: dict[str, Any]) -> list[str]:
    """The overrides that make a case's campaign: its seed, and the closed family's sample rate."""
    sets = [f"campaign.seed={case['campaign_seed']}"]
    if case.get("family") in LOOP_FAMILIES:
        sets.append(f"campaign.sample_rate={CLOSED_RATES[case['case'] % len(CLOSED_RATES)]}")
    return sets


def hide_truth(dest: Path, base: specmod.Spec, seed: list[str], sheet: bool) -> Path:
    """A hidden rig's run ``dest`` as the lab knows it: its manifest shows ``base`` (the campaign, with the case's
    ``seed`` overrides) instead of the truth; ``sheet``: its data get the sheet's calibration (the lab never
    recalibrated)."""
    m = Manifest.load(dest)
    replace(m, spec=specmod.apply_overrides(base.raw, seed), spec_sha256="hidden", generator=None).write(dest)
    if sheet:
        sheet_calibration(base).to_json(RunDir(dest).calibration)
        record_inputs(dest, "calibration.json")
    return dest


def sheet_calibration(sheet: specmod.Spec) -> Calibration:
    """The calibration a lab that never recalibrated its sensors converts its data with: the sheet's DAQ gains and
    offsets (Kp, Ke [deg/V], offsets [V])."""
    v = {k: fmu_value(sheet.daq, "daq", k) for k in ("pot_gain", "pot_offset", "gauge_gain", "gauge_offset")}
    why = "the sheet's (spec daq.{}), not measured on this rig"
    return Calibration(
        Kp=v["pot_gain"],
        Ke=v["gauge_gain"],
        gauge_offset_v=v["gauge_offset"],
        pot_offset_v=v["pot_offset"],
        source={"Kp": {"method": why.format("pot_gain")}, "Ke": {"method": why.format("gauge_gain")}},
    )


def _rel_err(true: float, fitted: float | None) -> float:
    if fitted is None:
        return math.inf
    return abs(float(fitted) - float(true)) / abs(float(true))


@dataclass(frozen=True)
class Answer:
    """What a diagnosis answered, as a blind case scores it: the ``verdict``, the effects ``found`` (their order),
    each effect parameter ``fitted`` ({"plant.coulomb_torque": 0.03, ...}), the held-out ``shrink_pct`` (NaN where
    the engine does not replay) and the parameter table ``parameters`` (its linear rows)."""

    verdict: str
    found: list[str]
    fitted: dict[str, float]
    shrink_pct: float
    parameters: dict[str, FittedParameter]

    @classmethod
    def of_diagnosis(cls, diag: Diagnosis) -> Answer:
        """The replay diagnosis's answer (``diagnosis.json``)."""
        return cls(diag.verdict, diag.effect_names, diag.fitted_effect_params(), float(diag.gap.shrink_pct),
                   diag.parameters)  # fmt: skip

    @classmethod
    def of_likelihood(cls, unit: UnitFit, decision: Decision, plant: dict[str, Any]) -> Answer:
        """The likelihood engine's answer: the ``decision``'s verdict and effects, each effect's parameter as its
        nested fit has it (an integer effect's setting; friction's with its shape where that entered), the linear
        parameters of the best model (:attr:`UnitFit.final`, else the linear fit) and the plant parameters they imply
        on the sheet's ``plant`` (:func:`rigmodel.to_plant`: kt, km, Beq, Jeq; no interval)."""
        fitted: dict[str, float] = {}
        for x in unit.effects:
            if x.name in decision.effects:
                fitted |= {k: x.fit.values()[k] for k in x.parameters} | {k: float(v) for k, v in x.settings.items()}
        shape = next((x for x in unit.effects if x.name == FRICTION_SHAPE_EFFECT and x.test.enters), None)
        if shape is not None and "coulomb_friction" in decision.effects:  # friction sized with its shape
            fitted |= {k: shape.fit.values()[k] for k in ("plant.coulomb_torque", *shape.parameters)}
        if "quantization" in decision.effects:
            fitted["daq.adc_bits"] = float(unit.lattice_bits)
        best = unit.final or unit.fit
        rows = {k: FittedParameter(unit.nominal[k], e.value, list(e.ci95), 100.0 * (e.value / unit.nominal[k] - 1.0),
                                   e.unit, at_bound=e.at)
                for k, e in best.estimates.items() if k in unit.nominal and unit.nominal[k]}  # fmt: skip
        for k, v in to_plant({k: e.value for k, e in best.estimates.items()}, plant).items():
            sheet = plant_value(plant, k)
            rows.setdefault(f"plant.{k}", FittedParameter(sheet, v, [math.nan, math.nan], 100.0 * (v / sheet - 1.0),
                                                          ""))  # fmt: skip
        return cls(decision.verdict, list(decision.effects), fitted, math.nan, rows)


def score_case(case: dict[str, Any], answer: Answer) -> dict[str, Any]:
    """Score one diagnosis's answer against the hidden truth."""
    verdict = answer.verdict
    found = answer.found
    fitted = answer.fitted
    shrink = answer.shrink_pct
    out: dict[str, Any] = {"verdict": verdict, "found": found, "fitted": fitted, "shrink_pct": shrink}
    kind = case["kind"]
    if kind == "single":
        eff = case["truth_effects"][0]
        param = EFFECTS[eff].param
        err = _rel_err(case["truth_params"][param], fitted.get(param) if eff in found else None)
        out.update(top1=verdict == eff, param_error=err, param_ok=bool(err <= MAG_TOL + 1e-12),
                   param_ok_20=bool(err <= 0.20 + 1e-12))  # fmt: skip
    elif kind == "none":
        out.update(correct=verdict == "none", turned_into_effect=verdict in EFFECTS)
    elif kind == "two":
        effs = case["truth_effects"]
        errs = {
            EFFECTS[e].param: _rel_err(case["truth_params"][EFFECTS[e].param], fitted.get(EFFECTS[e].param))
            if e in found else math.inf
            for e in effs
        }  # fmt: skip
        out.update(both=all(e in found for e in effs), top1_in_truth=verdict in effs, param_errors=errs)
    else:
        out.update(correct=verdict == "unexplained")
    params = answer.parameters
    if case.get("sheet_truth"):
        out.update(sheet_scores(case["sheet_truth"], params))
    elif case.get("nuisance") and "plant.Ks" in params:  # a row the diagnosis has not (the drive held): a miss
        ks = _rel_err(case["nuisance"]["plant.Ks"], params["plant.Ks"].fitted)
        beq_row = params.get("plant.Beq")
        beq = _rel_err(case["nuisance"]["plant.Beq"], None if beq_row is None else beq_row.fitted)
        out.update(ks_error=ks, beq_error=beq, recal_ok=bool(ks <= KS_TOL and beq <= BEQ_TOL))
    return out


def sheet_scores(truth: dict[str, float], params: dict[str, FittedParameter]) -> dict[str, Any]:
    """A wrong_sheet rig's sheet quantities (:data:`SHEET_ROWS`) against the diagnosis's parameter rows: each row's
    ``sheet_status`` ("fitted", "kept" at the spec's value, or "not fitted": no such row), its relative error
    ``sheet_errors`` (None when not fitted), ``sheet_ok`` within :data:`SHEET_TOL`, and ``sheet_all_ok``. Beside
    them, not scored: the drive's gain and time constant the plant rows imply (``sheet_implied_errors``, from the
    fitted kt, km, Beq, Jeq, Ks through :func:`rigmodel.combos`)."""
    status, errors, ok = {}, {}, {}
    for row in SHEET_ROWS:
        p = params.get(row)
        status[row] = "not fitted" if p is None else "kept" if p.kept else "fitted"
        err = None if p is None else _rel_err(truth[row], p.fitted)
        errors[row] = err
        ok[row] = bool(err is not None and err <= SHEET_TOL + 1e-12)
    plant = {k.split(".", 1)[1]: p.fitted for k, p in params.items() if k.startswith("plant.")}
    implied = combos({**sheet_plant(), **plant})
    implied_err = {k: _rel_err(truth[k], implied[k]) for k in ("rig.drive_gain", "rig.drive_tau")}
    return {"sheet_status": status, "sheet_errors": errors, "sheet_ok": ok, "sheet_all_ok": all(ok.values()),
            "sheet_implied_errors": implied_err}  # fmt: skip
