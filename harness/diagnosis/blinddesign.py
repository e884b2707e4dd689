"""The blind test's ``design`` family: does a controller designed on the identified twin meet its specs on the rig?

Each case is a wrong-sheet rig (:func:`harness.diagnosis.blindtest.draw_wrong_sheet`: drive gain and time constant
x1/3..3, Ks x0.5..2, gauge gain x0.5..2 off the sheet, every other rig with one in-library effect) logged as a lab
would log it: under a controller designed on its sheet (:data:`METHOD` to :data:`SPECS`, :func:`harness.design.design`
on the sheet spec: the same for every rig at a sample rate, :func:`sheet_design`), its data converted with the sheet's
calibration. The run is diagnosed against the sheet; a controller is designed to the same specs on the twin the
diagnosis identified (:func:`harness.twin.twin_of_diagnosis`), with its predicted bands; both controllers then run on
the TRUE rig (its parameters, its effect, noise of a seed of its own), tracking :data:`REFERENCE`, read through the
sheet's calibration as the lab reads it. Scored: the identified design's true behaviour meets every spec
(``identified_met``), the sheet design's (``sheet_met``), and each of the true rig's metrics under the identified
design inside its predicted 95 % band (``band_hits``, pooled over rigs and metrics: ``band_coverage``).
"""

from __future__ import annotations

import shutil
import tempfile
import time
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from .. import spec as specmod
from ..design import Design, controller_toml, design
from ..executor import FmuBytes, fmu_file, worker_rig
from ..loopspecs import SPEC_KEYS, LoopSpecs
from ..prediction import MetricBand, Reference, judge_specs, pooled, reference_from, simulate_loop
from ..rig.campaign import run_campaign
from ..rig.controller import Controller
from ..twin import RigTables, twin_of_diagnosis, twin_of_spec
from .blindcase import Answer, campaign_spec, case_sets, hide_truth, score_case
from .diagnose import diagnose_run

__all__ = ["BAND_METRICS", "METHOD", "REFERENCE", "SPECS", "design_group", "design_scores", "run_design_case",
           "sheet_design", "true_seed", "with_controller"]  # fmt: skip

METHOD = "lqr"  # the labs' Part II
SPECS = "settling=1.5,overshoot=5,stop=3,alpha=15,voltage=10,band=5"  # s, %, deg, deg, V, % of the step
REFERENCE = "square:f=0.25;amplitude=30;duration=8"  # the check's reference (quick: 4 s)
N_CHECK = 100  # members of each design's prediction
BAND_METRICS = ("overshoot_pct", "settling_s", "stop_error_deg", "peak_alpha_deg", "peak_u_v", "ring_alpha_deg")
TRUE_SEED = 4242  # mixed with a case's campaign seed: its true rig's noise seed (:func:`true_seed`)


def true_seed(case: dict[str, Any]) -> int:
    """The noise seed of a case's true rig: its campaign seed and :data:`TRUE_SEED` mixed
    (:class:`numpy.random.SeedSequence`), so that the true rig's noise is apart from its campaign's and its
    predictions', and the cases of another blind-test seed run their true rigs with noise of their own."""
    state = np.random.SeedSequence([int(case["campaign_seed"]), TRUE_SEED]).generate_state(1)[0]
    return int(state) % (2**31 - 1)


def _reference(rate: float, quick: bool) -> Reference:
    text = REFERENCE.replace("duration=8", "duration=4") if quick else REFERENCE
    return reference_from(text, rate)


def sheet_design(sheet: specmod.Spec, quick: bool, fmus: dict[str, FmuBytes] | None = None) -> Controller:
    """The controller a lab designs on its sheet (``sheet``: the family's spec at a sample rate): :data:`METHOD` to
    :data:`SPECS`, checked on the sheet with its own uncertainty (the best the search found when that check misses)."""
    d = design(twin_of_spec(sheet), METHOD, _reference(sheet.sample_rate, quick), LoopSpecs.parse(SPECS), n=N_CHECK,
               strict=False, fmus=fmus)  # fmt: skip
    return d.controller


def _true_tables(true_spec: specmod.Spec, sheet: specmod.Spec, seed: int) -> RigTables:
    """The true rig's tables (its noise with ``seed``), read through the sheet's calibration as the lab reads it."""
    t = twin_of_spec(true_spec).tables(seed=seed)
    believed = twin_of_spec(sheet).tables(noise=False)
    return RigTables(t.plant, t.daq, believed.calibration)


def _true_metrics(rig: Any, tables: RigTables, c: Controller, ref: Reference) -> dict[str, float]:
    res = simulate_loop(rig, tables, c, ref.ref_deg, ref.Ts, ref.theta0_deg)
    return pooled(ref.t, ref.ref_deg, res["theta"], res["alpha"], res["u"], LoopSpecs.parse(SPECS).band_pct,
                  ref.initial_deg, res["diverged"] >= 0)  # fmt: skip


def _meets(values: dict[str, float], specs: LoopSpecs) -> bool:
    """Does one loop's behaviour meet every spec (the rule :func:`harness.prediction.judge_specs` applies to a band)?"""
    return all(v["met"] for v in judge_specs({m: MetricBand(x, x, x) for m, x in values.items()}, specs).values())


def design_scores(identified: Design, true_id: dict[str, float], true_sheet: dict[str, float]) -> dict[str, Any]:
    """A case's design scores: the specs met on the true rig by each design, and each metric of the identified
    design's true loop inside its predicted band."""
    specs = identified.specs
    bands = identified.prediction.metric_bands()
    hits = {m: bool(bands[m].lo <= true_id[m] <= bands[m].hi) for m in BAND_METRICS}
    return {
        "identified_met": _meets(true_id, specs),
        "sheet_met": _meets(true_sheet, specs),
        "band_hits": hits,
        "true_identified": {m: true_id[m] for m in BAND_METRICS},
        "true_sheet": {m: true_sheet[m] for m in BAND_METRICS},
        "predicted": {m: [bands[m].lo, bands[m].median, bands[m].hi] for m in BAND_METRICS},
        "identified_passed_own_check": identified.passed,
        "identified_controller": identified.controller.to_dict(),
    }


def with_controller(spec: specmod.Spec, c: Controller) -> specmod.Spec:
    """``spec`` logged under ``c``, which reads alpha through the sheet's gauge gain (the spec's controller's)."""
    raw = specmod.apply_overrides(spec.raw, [])  # a deep copy
    own = raw.get("controller", {}).get("alpha_gain")
    table = tomllib.loads(controller_toml(c, ""))["controller"]
    raw["controller"] = {**table, **({"alpha_gain": own} if own is not None else {})}
    return specmod.from_dict(raw, spec.path)


def run_design_case(case: dict[str, Any], root: Path | None, quick: bool, fmus: dict[str, FmuBytes]) -> dict[str, Any]:
    """One case of the family (see the module docstring), a task: the rig's campaign under the sheet's controller
    (``case["sheet_controller"]``), its diagnosis against the sheet, the identified design, both designs on the true
    rig; returns the case with its ``score``: the diagnosis's (as the wrong_sheet family scores it) and ``design``."""
    tc = time.perf_counter()
    files = {k: fmu_file(v) for k, v in fmus.items()}
    sheet_c = Controller(**case["sheet_controller"])
    seed = case_sets(case)
    sheet = with_controller(campaign_spec(quick, seed[1:], case["family"]), sheet_c)
    truth = [f"{k}={v}" for k, v in {**case.get("nuisance", {}), **case["truth_params"]}.items()]
    true_spec = with_controller(campaign_spec(quick, truth + seed, case["family"]), sheet_c)
    ref = _reference(sheet.sample_rate, quick)
    specs = LoopSpecs.parse(SPECS)
    with tempfile.TemporaryDirectory(prefix="flexjoint-blind-") as tmp:
        d = Path(root if root is not None else tmp) / f"case_{case['case']:03d}"
        if d.exists():
            shutil.rmtree(d)
        run_campaign(true_spec, d, fmus=files, workers=1)
        hide_truth(d, sheet, seed, sheet=True)
        diag = diagnose_run(d, sheet, d, workers=1, fmus=files)
        twin = twin_of_diagnosis(d, spec=sheet)
        identified = design(twin, METHOD, ref, specs, n=N_CHECK, seed=int(case["campaign_seed"]) % 1000, strict=False,
                            workers=1, fmus=fmus)  # fmt: skip
    rig = worker_rig(fmus)
    tables = _true_tables(true_spec, sheet, true_seed(case))
    true_id = _true_metrics(rig, tables, identified.controller, ref)
    true_sheet = _true_metrics(rig, tables, sheet_c, ref)
    score = {**score_case(case, Answer.of_diagnosis(diag)), "design": design_scores(identified, true_id, true_sheet)}
    return {**case, "score": score, "timing_s": time.perf_counter() - tc}


def design_group(cases: list[dict[str, Any]], share: Any) -> dict[str, Any]:
    """The family's shares (``share``: the blind test's share of a list of flags): specs met on the true rig by the
    identified and by the sheet designs, and the band coverage over every (rig, metric); per metric too."""
    ds = [c["score"]["design"] for c in cases if "design" in c["score"]]
    per = {m: share([d["band_hits"][m] for d in ds]) for m in BAND_METRICS}
    return {
        "n": len(ds),
        "specs": SPECS,
        "method": METHOD,
        "specs_met_identified": share([d["identified_met"] for d in ds]),
        "specs_met_sheet": share([d["sheet_met"] for d in ds]),
        "band_coverage": share([h for d in ds for h in d["band_hits"].values()]),
        "band_coverage_per_metric": per,
        "spec_names": [SPEC_KEYS[k][2] for k in SPEC_KEYS if SPEC_KEYS[k][0] in LoopSpecs.parse(SPECS).limits],
    }
