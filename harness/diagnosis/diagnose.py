"""Diagnose the sim-to-real gap: where it lies, which unmodelled effect causes it, how far it shrinks.

The data flow, one module per step:

1. :mod:`harness.diagnosis.experiments`: every non-calibration experiment of the real run in degrees (the run's
   calibration), its invalid samples masked (pot dead band, ADC clipping), split into two folds (a lone record cut
   in time); where each replay starts (the link's ring at a record's start);
2. :mod:`harness.diagnosis.noise`: the data's noise and the ADC lattice they sit on; :mod:`harness.diagnosis.gauge`:
   the gauge's delay behind the hub angle, read from the records;
3. :mod:`harness.diagnosis.simulation`: each experiment replayed on the sim spec's rig as it was run, its gap and
   its gap beside the replays' own spread;
4. :mod:`harness.diagnosis.effects`: the candidate effects worth fitting against this simulation and data;
5. :mod:`harness.diagnosis.search` (its simulations as tasks, :mod:`harness.diagnosis.tasks`): the linear model
   and each record's sensors, the effects on top of it, the verdict, by one rule
   (:class:`harness.diagnosis.search.Policy`); :mod:`harness.diagnosis.bands`: each closed-loop record's
   behaviour beside its replays';
6. :mod:`harness.diagnosis.where`: where the gap of the simulation as given, and recalibrated, lies;
7. :mod:`harness.diagnosis.result`: ``diagnosis.json``, with the caveats of the verdict.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

from .. import spec as specmod
from ..executor import FmuBytes, fmu_bytes
from ..fmu.build import build_all
from ..ident.calibration import load_calibration
from ..rundir import Manifest, RunDir, record_inputs, write_json
from . import recalibrate as recal
from .effects import CandidateContext, candidates
from .experiments import (
    REPLAYS,
    RigExperiment,
    fold_experiments,
    fold_steps,
    load_experiments,
    mark_quiet,
    masked_share,
    moving_records,
    one_rate,
)
from .gauge import gauge_delay
from .noise import noise_floor
from .replays import write_replays
from .result import Diagnosis, FittedParameter, Folds, RecordSensors, RigFit, SensorCalibration, Thresholds
from .rigmodel import prior_sd
from .search import POLICY, Policy, SearchResult, search
from .simulation import Setup, fit_pct, fmu_value, link_keys, offset_key, replay_noise, sim_rig
from .speed import records_speed
from .tasks import SENSOR_CHANNELS, Pool, Replay, Where, rough

__all__ = ["diagnose_run", "priors", "thresholds"]

Progress = Callable[[str], None]
MIN_RECORDS = 2  # an import of this many records or more: each also recalibrated alone, the effects found held


def thresholds(policy: Policy) -> Thresholds:
    """The policy's thresholds as diagnosis.json records them."""
    return Thresholds(policy.none_level, policy.min_gain, policy.explained, policy.resolution, policy.meaning())


def _rig_fit(found: SearchResult) -> RigFit:
    """The fitted rig as its replays use it, with the covariance of what was fitted."""
    fit = found.final_fit
    over = {k: float(v) for k, v in sorted(found.final.items())}
    return RigFit(over, list(fit.names), list(fit.log), [list(r) for r in fit.cov])


def _sensors(found: SearchResult, experiments: dict[str, RigExperiment]) -> dict[str, RecordSensors]:
    """Each record's gauge offset as fitted (a closed loop's, with its interval) or as an open loop's least squares
    took it in the final rig's replay, and where its (first) replay started the link (a closed loop's as fitted)."""
    out: dict[str, RecordSensors] = {}
    for x in experiments.values():
        if x.record in out:
            continue
        key = offset_key(x.record)
        if key in found.final:
            lo, hi = found.final_fit.ci95.get(key, (math.nan, math.nan))
            offset = [float(found.final[key]), float(lo), float(hi)]
        else:
            offset = [float(found.gauge_zeros.get(x.record, x.alpha_rest)), math.nan, math.nan]
        a, r = link_keys(x.name)
        out[x.record] = RecordSensors(
            gauge_offset_deg=offset,
            link_start_deg=float(found.final.get(a, x.link_start[0])),
            link_rate_start_deg_s=float(found.final.get(r, x.link_start[1])),
        )
    return out


def _replays(experiments: dict[str, RigExperiment]) -> dict[str, dict[str, str]]:
    """Per experiment how it was re-simulated (:data:`harness.diagnosis.experiments.REPLAYS`) and why."""
    return {n: {"replay": x.replay, "reason": x.replay_reason} for n, x in experiments.items()}


def _own(p: FittedParameter, record: str) -> str:
    """A record's own fit of a parameter: "name 1.23 [1.2-1.26]"."""
    v, lo, hi = (p.records or {})[record]
    return f"{record} {v:.4g} [{lo:.4g}-{hi:.4g}]"


def _caveats(
    parameters: dict[str, FittedParameter],
    verdict: str,
    folds: Folds | None = None,
    effects: list[str] | None = None,
    still: list[str] | None = None,
    steps: tuple[int, int] = (0, 0),
) -> list[str] | None:
    """What limits the verdict: the records set aside (``still``: nothing in them moves beyond the noise), a fold
    whose closed-loop records hold no step of their reference where the other's do (``steps``: how many each holds,
    :func:`harness.diagnosis.experiments.fold_steps`), which part of the spec does not describe the rig
    (:func:`recal.parts_at_bound`), each recalibrated parameter that ended at its bound (an effect's share of the gap
    may be a wrong linear part's), each one the data do not determine; the linear parameters whose fits on each
    record alone (with the ``effects`` found held) exclude each other, or, without records fitted alone, where nothing
    explains the gap, those of the two folds."""
    out = (
        [f"set aside, nothing in them moves beyond the noise: {', '.join(still)}; diagnosed on the rest"]
        if still
        else []
    )
    if folds is not None and min(steps) == 0 < max(steps):
        empty, full = ("A", "B") if steps[0] == 0 else ("B", "A")
        names = {"A": folds.A, "B": folds.B}
        out.append(
            f"fold {empty} ({', '.join(names[empty])}) holds no step of its reference, fold {full} "
            f"{max(steps)}: the fit on fold {empty} is scored on step responses it never saw; log each record over a "
            "period of its reference (a step each way) so that both folds hold steps"
        )
    out += recal.parts_at_bound({n: (p.nominal, p.fitted) for n, p in parameters.items() if n in recal.LINEAR})
    out += [f"verdict {verdict!r} reached with {p.finding}" for p in parameters.values() if p.at_bound]
    out += [f"{p.finding}" for p in parameters.values() if p.identifiable is False and p.finding and not p.at_bound]
    by_record = [
        f"{recal.LINEAR[n].label} " + " and ".join(f"{_own(p, a)} / {_own(p, b)}" for a, b in p.records_apart)
        for n, p in parameters.items()
        if n in recal.LINEAR and p.records_apart and not p.at_bound
    ]
    if by_record:
        out.append(
            "recalibrated on each record alone, the 95 % intervals exclude each other ("
            + "; ".join(by_record)
            + f"): the linear model{' with ' + ' and '.join(effects) if effects else ''} does not describe these "
            "records as one rig (model error, not noise)"
        )
    fitted_alone = any(p.records for p in parameters.values())
    apart = [n for n, p in parameters.items() if p.folds_disagree and not p.at_bound and not fitted_alone]
    if verdict == "unexplained" and apart:
        fits = "; ".join(
            f"{recal.LINEAR[n].label} {a:.4g} [{lo_a:.4g}-{hi_a:.4g}] and {b:.4g} [{lo_b:.4g}-{hi_b:.4g}]"
            for n in apart
            for (a, lo_a, hi_a), (b, lo_b, hi_b) in [parameters[n].folds or []]
        )
        which = f" ({', '.join(folds.A)} | {', '.join(folds.B)})" if folds else ""
        out.append(
            f"recalibrated on each fold alone{which}, the 95 % intervals exclude each other ({fits}): the linear "
            "model does not describe both as one rig (model error, not noise)"
        )
    return out or None


def priors(
    sim: specmod.Spec, gain_rel_se: dict[str, float], encoder: bool = False
) -> tuple[dict[str, float], dict[str, float]]:
    """The prior sd [log] of each linear parameter recalibration fits (:func:`harness.diagnosis.rigmodel.prior_sd` of
    the sim spec's uncertainty), a sensor whose calibration was measured with the data with that error instead; and
    each channel's calibration error, the spec's where the data's was not measured (a sensor known to 1 % is not
    fitted: its error goes into the intervals; an ``encoder``'s count has none)."""
    sd = prior_sd(sim.plant, sim.factor)
    rel = dict(gain_rel_se)
    if encoder and not gain_rel_se.get("theta"):
        sd["sensor.theta_gain"] = 0.0
    for c, s in SENSOR_CHANNELS.items():
        if gain_rel_se.get(c, 0.0) > 0:
            sd[s] = gain_rel_se[c]
        rel[c] = sd[s]
    return sd, rel


def diagnose_run(
    real: Path,
    sim: str | Path | specmod.Spec = "nominal",
    out: Path | None = None,
    progress: Progress | None = None,
    workers: int | None = None,
    scheduler: str | None = None,
    fmus: dict[str, Path] | None = None,
    replay: str = "auto",
    force: bool = False,
    policy: Policy = POLICY,
) -> Diagnosis:
    """Diagnose the gap between run directory ``real`` and the simulation spec ``sim`` (a path, a name in specs/ or a
    loaded Spec); the candidates are fitted as tasks of a :class:`harness.executor.Executor` (``workers`` processes of
    the default local cluster, 1 = serial, or the Dask cluster at ``scheduler``); ``fmus``: the built plant, DAQ and
    controller FMUs (default: built or taken from the cache); ``replay``: how each experiment is re-simulated
    (:func:`harness.diagnosis.experiments.load_experiments`); a lone record, and a closed-loop record that repeats
    its reference, is cut in time into blocks or two halves, alternating between the folds
    (:func:`harness.diagnosis.experiments.fold_experiments`; a lone record too short for that, or
    records at different sample rates: a one-line DataError, nothing written). Writes ``out/diagnosis.json`` (default
    out = real; another run directory only with ``force``: its report would read the diagnosis as one of its own data)
    and its replays beside the record, per stage (as given, recalibrated, with the effects:
    ``diagnosis.replays.parquet``, :mod:`harness.diagnosis.replays`), and returns it as a
    :class:`harness.diagnosis.result.Diagnosis`; the sha256 of the real run's data and calibration go to out's manifest,
    the wall-clock seconds to ``diagnosis.timing.json``, so that diagnosis.json is byte-stable. ``policy``: the rule
    that decides (:class:`harness.diagnosis.search.Policy`)."""

    t0 = time.perf_counter()
    say = progress or (lambda _m: None)
    real = Path(real)
    if not RunDir(real).manifest.exists():
        raise ValueError(f"{real}: not a run directory (no manifest.json)")
    dest = Path(out) if out is not None else real
    if RunDir(dest).manifest.exists() and dest.resolve() != real.resolve() and not force:
        raise FileExistsError(
            f"--out {dest} is another run (its own data/): a diagnosis of {real} there would be read as one of "
            "that run; give a new --out directory, or --force"
        )
    sim_spec = sim if isinstance(sim, specmod.Spec) else specmod.load(sim)
    cal = load_calibration(real)
    plant, daq = sim_rig(sim_spec)
    adc_range = fmu_value(daq, "daq", "adc_range")
    if replay != "auto" and replay not in REPLAYS:
        raise ValueError(f"replay {replay!r} unknown; valid: auto, {', '.join(REPLAYS)}")
    records = load_experiments(real, cal, sim_spec, adc_range, replay)
    one_rate(records)  # records at different rates: one line, nothing written
    timing = gauge_delay(records)  # the gauge's reading behind the hub's: the data's, in every replay
    if timing.samples:
        for x in records.values():
            x.daq = {**x.daq, "gauge_delay": timing.samples}
    noise, _ = noise_floor(records, adc_range, cal)
    sigma = {"theta": noise.theta_deg, "alpha": noise.alpha_deg}  # [deg], an ADC's quantisation included
    moving, still = moving_records(records, sigma)
    experiments, folds = fold_experiments(moving)
    mark_quiet(experiments, sigma)  # a lone record's blocks
    fmus = fmus or build_all()
    shipped: dict[str, FmuBytes] = {k: fmu_bytes(fmus[k]) for k in ("flexjoint", "daq", "controller") if k in fmus}
    lattice = replay_noise(daq, noise.estimated_deg) if noise.adc_lattice_bits and noise.estimated_deg else {}
    prior, rel_se = priors(sim_spec, cal.gain_rel_se(), all(x.encoder for x in experiments.values()))
    setup = Setup(plant, daq, cal.comb_angles, experiments, shipped, replay_noise(daq, sigma), lattice, rel_se, prior,
                  sigma)  # fmt: skip
    top = max(x.peak_command_v for x in experiments.values())
    cands = candidates(CandidateContext(plant, daq, top, noise.adc_lattice_bits))
    pool = Pool(setup, workers, scheduler, progress)
    try:
        imported = Manifest.load(real).kind == "import"
        unit = list(moving) if imported and len(moving) >= MIN_RECORDS else None
        found = search(pool, experiments, (folds.A, folds.B), cands, say, policy, unit)
        # after recalibration: what recalibration alone fitted (the waterfall's stage), not the final joint refit
        stages = {"given": {}, "recalibrated": found.recalibrated, "effects": found.final}
        before, after, *traces = pool.map([Where({}), Where(found.recalibrated), *(Replay(o) for o in stages.values())])
    finally:
        pool.close()
    after["parameters"] = dict(sorted(found.recalibrated.items()))
    where = {"before": before, "after_recalibration": after, "masked": masked_share(experiments)}
    speed = records_speed(records)  # in amplitude: the hub's speed per volt over open-loop square waves
    if speed is not None:
        where["speed_per_volt"] = speed.to_dict()
    noise = replace(noise, gap=math.sqrt(found.floor.msg), fit_pct=fit_pct(found.floor.msg))
    if any(x.replay == "closed" for x in experiments.values()):
        less = " (less the lattice's LSB^2 / 12 where the replay's ADC quantises: it adds that)" if lattice else ""
        how = {
            "staircase": "; fitted without derivatives where its controller acts on an ADC's or an encoder's steps",
            "jitter": f"; fitted with differences across a play's jitter (steps of {100 * recal.STAIRCASE_STEP:g} %)",
            None: "",
        }[rough(setup, found.final, list(experiments))]
        loop = (f"closed-loop replays: each simulated with the data's noise{less} fed back through its controller, "
                f"its spread the replays with {policy.draws} other noise draws{how}")  # fmt: skip
        noise = replace(noise, method=f"{noise.method}; {loop}")
    diagnosis = Diagnosis(
        real=os.path.relpath(real, dest),  # relative to diagnosis.json, so a moved run dir stays the same bytes
        sim_spec=sim_spec.name if isinstance(sim, specmod.Spec) else str(sim),
        sim_spec_file=Path(sim_spec.path).name,
        calibration=SensorCalibration(
            Kp=cal.Kp,
            Ke=cal.Ke,
            gauge_offset_v=cal.gauge_offset_v,
            gauge_delay_s=timing.seconds,
            gauge_delay_method=timing.describe(),
        ),
        folds=folds,
        verdict=found.verdict,
        parameters=found.parameters,
        recalibration_applied=found.recalibration_applied,
        effects=found.effects,
        candidates=found.candidates,
        rounds=found.rounds,
        gap=found.gap,
        noise_floor=noise,
        thresholds=thresholds(policy),
        where=where,
        replays=_replays(experiments),
        caveats=_caveats(
            found.parameters,
            found.verdict,
            folds,
            [e.effect for e in found.effects],
            still,
            fold_steps(experiments, folds),
        ),
        rig=_rig_fit(found),
        sensors=_sensors(found, experiments),
        behaviour=found.behaviour or None,
    ).rounded()
    diagnosis.write(RunDir(dest).diagnosis)
    write_replays(RunDir(dest).diagnosis_replays, experiments, dict(zip(stages, traces, strict=True)))
    record_inputs(dest, "diagnosis.json", source=real)
    wall = time.perf_counter() - t0
    write_json(RunDir(dest).diagnosis_timing, {"timing_s": wall, "workers": workers, "scheduler": scheduler})
    say(f"verdict {diagnosis.verdict}")
    return diagnosis
