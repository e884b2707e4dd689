"""An experiment of the real rig re-simulated on the sim spec's rig, and the gap between them.

Every experiment is re-simulated on the sim spec's rig (plant and DAQ FMUs, the spec's ``[plant]``/``[daq]`` and
its per-experiment overrides, measurement noise off, DAQ sample rate 1/Ts of the data) as it was run
(:attr:`RigExperiment.replay`): an open-loop experiment with the real command ``u`` from the data; a closed-loop
record from its reference through the controller FMU (reference -> controller -> DAQ -> plant -> DAQ ->
controller), with the data's own noise in its DAQ (:attr:`Setup.loop_noise`: the controller acted on noisy samples),
started at the measured shaft angle (trial parameters whose loop diverges hold its last sample: a
large gap, not an error); a closed-loop record whose controller is not known by multiple
shooting: the real command replayed open loop in windows of SHOOTING_SECONDS, each started again from the measured
state (theta, alpha and their rates, smoothed), so that the drift an open-loop replay of a feedback-controlled
command integrates cannot dominate the gap.

Both sides are converted to degrees the way each is calibrated: real volts with the real run's calibration,
simulated volts with :func:`harness.ident.calibration.daq_calibration` of the simulated DAQ (its pot
gain and offset; when the real gauge was calibrated on a comb, the least-squares Ke of the simulated gauge over the
same comb angles, so a gauge nonlinearity is calibrated alike on both sides). theta [deg] is unwrapped; the
simulation starts at the first real shaft angle (so pot wraps coincide) and its constant offset is then fitted by
least squares (the integrator's unknown initial state, as MATLAB's ``compare`` estimates it: one noisy first sample
must not offset a whole record). A closed-loop or multiple-shooting replay starts from the measured angle and
keeps it: the feedback (or the restart) fixes the offset.

Gap. Per experiment and channel q = ||y_real - y_sim||^2 / ||y_real - mean||^2 over valid samples; the mean
squared gap E = mean q over experiments and channels (channels with no motion skipped), the gap g = sqrt(E), fit %
= 100 (1 - g) (MATLAB ``compare``'s fit, pooled). A replay's gap is also set beside its own spread, window by
window (:func:`evaluate`): what the search scores.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
from scipy.optimize import minimize_scalar

from .. import spec as specmod
from ..executor import FmuBytes
from ..fmu.cosim import CALIBRATION
from ..ident.calibration import Calibration, alpha_deg, daq_calibration, theta_deg
from ..rig.controller import Controller, delayed
from ..spec import fmu_value
from .experiments import CHANNELS, DEADBAND_GUARD, SHOOTING_SECONDS, RigExperiment, measured_state
from .recalibrate import LINEAR
from .result import ExperimentGap, GapSummary
from .rigmodel import COMBOS, SENSORS, SHEET, combos, to_plant

__all__ = [
    "SSE",
    "Setup",
    "channel_fits",
    "fit_pct",
    "fmu_value",
    "gap_summary",
    "gauge_offset",
    "evaluate",
    "fit_nuisance",
    "link_keys",
    "nuisance_keys",
    "mean_squared_gap",
    "offset_key",
    "replay",
    "replay_noise",
    "replay_traces",
    "residuals",
    "sim_calibration",
    "sim_rig",
    "simulate",
    "effective_gap",
]

ALPHA_OFFSET = "sensor.alpha_offset"  # a record's gauge offset [deg], per record: :func:`offset_key`
LINK_START = (
    "link.alpha_start",
    "link.alpha_rate",
)  # a closed loop's link at its start [deg, deg/s]: :func:`link_keys`
SENSOR_DAQ = ("pot_gain", "pot_offset", "gauge_gain", "gauge_offset", "gauge_cubic")  # the calibration's DAQ parameters
SSE = dict[str, dict[str, float]]  # experiment -> channel -> sum of squared residuals [deg^2]
MODELS = {"plant": "flexjoint", "daq": "daq"}  # the FMU behind each rig table
SENSOR_KNOWN = 0.01  # a sensor gain known to 1 % (sd, log) is not fitted: its error goes into the intervals
REPLAY_NOISE_SEED = 7  # noise seed of every closed-loop replay (:attr:`Setup.loop_noise`)
LOOP_NOISE_SEEDS = (1, 2, 3, 4)  # other seeds, whose replays against it show what noise fed back spreads
PSEUDO_SEED = 11  # the noise draw of the record a right model would leave (:func:`evaluate`'s floor)
OFFSET_STEP = 0.1  # deg (deg/s x 10): the step of a held-out record's own parameters' fit (:func:`fit_nuisance`)
SPREAD_SECONDS = 0.25  # s: the windows in which a replay's gap is set beside its spread (:func:`evaluate`)


@dataclass
class Setup:
    """The simulation being judged: its rig parameters (noise off), the real run's comb angles [deg] for the
    sim-side gauge calibration (None: use the sim's gauge gain), the real experiments, the plant and DAQ
    FMUs as bytes ({"flexjoint": ..., "daq": ...}) and the DAQ noise of the closed-loop replays (``loop_noise``:
    {"noise_theta": V rms, "noise_alpha": V rms}, the data's own, :func:`replay_noise`; {} none). ``lattice_noise``:
    that noise without the LSB^2 / 12 of the ADC lattice the data sit on, for a replay whose own ADC quantises (its
    quantiser adds that share; {}: the data sit on no lattice, ``loop_noise`` throughout). ``gain_rel_se``: the
    relative standard error of the data's calibration gain per channel ({"theta": Kp's, "alpha": Ke's}; {}: not
    known), which the fitted parameters' intervals hold (:func:`harness.diagnosis.recalibrate.fit`); ``prior_sd``:
    the prior sd [log] of each linear parameter; ``sigma_deg``: the data's noise RMS [deg] per channel (an ADC's
    quantisation included)."""

    plant: dict[str, Any]
    daq: dict[str, Any]
    comb_angles: np.ndarray | None
    experiments: dict[str, RigExperiment]
    fmus: dict[str, FmuBytes] = field(default_factory=dict)
    loop_noise: dict[str, float] = field(default_factory=dict)
    lattice_noise: dict[str, float] = field(default_factory=dict)
    gain_rel_se: dict[str, float] = field(default_factory=dict)
    prior_sd: dict[str, float] = field(default_factory=dict)
    sigma_deg: dict[str, float] = field(default_factory=dict)

    @cached_property
    def sheet(self) -> tuple[dict[str, Any], dict[str, Any]]:
        """The plant and DAQ tables with the FMU defaults filled in where a replay reads them itself (the sheet's
        parameters :func:`harness.diagnosis.rigmodel.to_plant` maps the combos with; the DAQ's calibration and dead
        band): looked up once, not in every simulation. The same values the FMUs default to."""
        plant = {p: fmu_value(self.plant, "flexjoint", p) for p in SHEET if p in specmod.fmu_parameters("flexjoint")}
        names = {*SENSOR_DAQ, *CALIBRATION.values(), "pot_deadband"}
        return {**plant, **self.plant}, {**{d: fmu_value(self.daq, "daq", d) for d in sorted(names)}, **self.daq}

    def nominal(self, param: str) -> float:
        """The simulation's own value of a parameter: an FMU parameter's ("plant.Ks": the sim spec's, else the FMU
        default), a combo's of the sim's plant (:data:`harness.diagnosis.rigmodel.COMBOS`), 1 for a sensor's gain."""
        table, name = param.split(".", 1)
        if table == "rig":
            return combos(self.plant)[param]
        if table == "sensor":
            return 1.0
        return fmu_value(self.plant if table == "plant" else self.daq, MODELS[table], name)

    def linear(self, encoder: bool = False) -> list[str]:
        """The linear parameters recalibration fits (:data:`harness.diagnosis.recalibrate.LINEAR`): the drive's and
        the link's, and a sensor's gain where its prior is wider than SENSOR_KNOWN (not an encoder's count)."""
        out = []
        for p in LINEAR:
            if p in SENSORS and (self.prior_sd.get(p, 0.0) < SENSOR_KNOWN or (p == "sensor.theta_gain" and encoder)):
                continue
            out.append(p)
        return out


def sim_rig(sim: specmod.Spec) -> tuple[dict[str, Any], dict[str, Any]]:
    """The sim spec's rig parameters with measurement noise off: (plant, daq)."""
    plant = {"internal_step": sim.internal_step, **sim.plant}
    daq = {**sim.daq, "noise_theta": 0.0, "noise_alpha": 0.0}
    return plant, daq


def _split_overrides(over: Mapping[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """{"plant.x": v, "daq.y": w} -> ({"x": v}, {"y": w}); the combos and sensor gains left out."""
    plant: dict[str, Any] = {}
    daq: dict[str, Any] = {}
    for k, v in over.items():
        table, name = k.split(".", 1)
        if table in ("plant", "daq"):
            (plant if table == "plant" else daq)[name] = v
    return plant, daq


def rig_tables(
    setup: Setup, exp: RigExperiment, over: Mapping[str, Any]
) -> tuple[dict[str, Any], dict[str, Any], dict[str, Any]]:
    """The plant and DAQ parameters of ``exp``'s replay with overrides ``over`` (combos mapped onto the plant by
    :func:`harness.diagnosis.rigmodel.to_plant`, a sensor's gain onto the DAQ's: reading = gain x true angle), and
    the DAQ as the data's calibration believes it (the sensor gains as given): (plant, daq, calibrated daq)."""
    p_over, d_over = _split_overrides(over)
    plant_sheet, daq_sheet = setup.sheet
    sheet = {**plant_sheet, **exp.plant}
    drive = {k: float(v) for k, v in over.items() if k in COMBOS}
    plant = {**sheet, **(to_plant(drive, sheet) if drive else {}), **p_over}
    believed = {**daq_sheet, **exp.daq, **d_over}
    daq = dict(believed)
    for s, name in SENSORS.items():
        if s in over:
            daq[name] = fmu_value(believed, "daq", name) / float(over[s])
    return plant, daq, believed


def sim_calibration(daq: Mapping[str, Any], comb_angles: np.ndarray | None) -> Calibration:
    """The calibration that converts the simulated DAQ's volts (``daq``: its parameters, FMU defaults for the
    rest), made as the real rig's: :func:`harness.ident.calibration.daq_calibration`."""
    pot_gain, pot_offset, gauge_gain, gauge_offset, gauge_cubic = (fmu_value(daq, "daq", k) for k in SENSOR_DAQ)
    return daq_calibration(pot_gain, pot_offset, gauge_gain, gauge_offset, gauge_cubic, comb_angles=comb_angles)


def offset_key(record: str) -> str:
    """The override of a record's gauge offset: "sensor.alpha_offset@<record>" [deg, as the record reads it]."""
    return f"{ALPHA_OFFSET}@{record}"


def link_keys(experiment: str) -> tuple[str, str]:
    """The overrides of an experiment's link at its start, its deflection from rest [deg] and rate [deg/s] as the
    gauge reads them: ("link.alpha_start@<experiment>", "link.alpha_rate@<experiment>")."""
    return f"{LINK_START[0]}@{experiment}", f"{LINK_START[1]}@{experiment}"


def nuisance_keys(exp: RigExperiment) -> dict[str, float]:
    """A closed-loop replay's own parameters, each with where a fit starts it: its record's gauge offset (its reading
    at rest) and its link's state at its start (from the record: :attr:`RigExperiment.link_start`); {} for another
    replay (an open loop's offsets are fitted by its least squares, its start read from the record)."""
    if exp.replay != "closed":
        return {}
    a, r = link_keys(exp.name)
    return {offset_key(exp.record): exp.alpha_rest, a: exp.link_start[0], r: exp.link_start[1]}


def gauge_offset(exp: RigExperiment, over: Mapping[str, Any]) -> float:
    """The gauge offset [deg] of ``exp``'s record in a replay with ``over``: the record's own override
    (:func:`offset_key`), else its reading at rest (:attr:`RigExperiment.alpha_rest`)."""
    return float(over.get(offset_key(exp.record), exp.alpha_rest))


def true_state(state: Mapping[str, float], over: Mapping[str, Any], alpha_offset_deg: float = 0.0) -> dict[str, float]:
    """A measured start state (plant parameters theta_start, alpha_start [rad], theta_dot_start, alpha_dot_start
    [rad/s], as read) as the true angles and rates that sensors with ``over``'s gains (reading = gain x true angle +
    offset, the gauge's ``alpha_offset_deg``) read so."""
    gain = {
        c: float(over.get(s, 1.0)) for c, s in (("theta", "sensor.theta_gain"), ("alpha", "sensor.alpha_gauge_gain"))
    }
    offset = {"alpha_start": math.radians(alpha_offset_deg)}
    return {k: (v - offset.get(k, 0.0)) / gain[k.split("_", 1)[0]] for k, v in state.items()}


def simulate(
    rig: Any, setup: Setup, exp: RigExperiment, over: Mapping[str, Any], n: int | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Simulated (theta, alpha) [deg] of one experiment (its first ``n`` samples) on the sim rig with ``over``
    ({"plant.x": v, ...}), and the mask of the theta samples where the simulated pot is on its track
    (:func:`replay`)."""
    r = replay(rig, setup, exp, over, n)
    return r.theta, r.alpha, r.on_track


@dataclass(frozen=True)
class Replayed:
    """One experiment's replay: theta, alpha [deg] as its sensors read them, the samples where the simulated pot is
    on its track, the command [V] (a closed loop's controller's; the logged one otherwise) and the gauge's zero
    [deg] it read the link with (an open loop's as its least squares took it)."""

    theta: np.ndarray
    alpha: np.ndarray
    on_track: np.ndarray
    u: np.ndarray
    alpha_zero: float


def replay(rig: Any, setup: Setup, exp: RigExperiment, over: Mapping[str, Any], n: int | None = None) -> Replayed:
    """One experiment (its first ``n`` samples) replayed on the sim rig with ``over`` ({"plant.x": v, ...}).

    The gauge reads its record's offset (:func:`gauge_offset`), which a closed loop's controller acts on; an
    open-loop replay's offsets are then fitted by least squares (theta's: the integrator's unknown initial state, as
    MATLAB's ``compare`` estimates it; alpha's: the gauge's zero, which nothing feeds back there)."""
    d_over = _split_overrides(over)[1]
    delta = gauge_offset(exp, over)
    plant, daq, believed = rig_tables(setup, exp, over)
    # the gauge reads as the lab's did, before the import zeroed the record (the zero it took is the controller's
    # alpha_bias): its raw zero error through the ADC's lattice and into the controller, the zero taken off after
    zero = float((exp.controller or {}).get("alpha_bias", 0.0)) if exp.replay == "closed" else 0.0
    daq["gauge_offset"] = fmu_value(daq, "daq", "gauge_offset") + (delta + zero) / fmu_value(
        believed, "daq", "gauge_gain"
    )
    noise = setup.lattice_noise if setup.lattice_noise and _quantises(setup, exp, d_over) else setup.loop_noise
    if exp.replay == "closed" and noise:
        daq = {**daq, **{k: v for k, v in noise.items() if k not in d_over}}
        daq["seed"] = d_over.get("seed", REPLAY_NOISE_SEED)
    # at the angle read first, the link as the record shows it there (a closed loop's as fitted), as the sensors read
    start = {"theta_start": math.radians(float(exp.theta[0])), **(exp.start_state if exp.replay != "shooting" else {})}
    if exp.replay == "closed":
        a, r = link_keys(exp.name)
        start["alpha_start"] = math.radians(delta + float(over.get(a, exp.link_start[0])))
        start["alpha_dot_start"] = math.radians(float(over.get(r, exp.link_start[1])))
    plant = {**plant, **true_state(start, over, delta)}
    if exp.replay == "closed":
        c = Controller(**{**(exp.controller or {}), "alpha_bias": 0.0})  # reads it raw
        ctrl = c.fmu_parameters(1.0 / exp.Ts)
        ctrl = {k: fmu_value(believed, "daq", v) for k, v in CALIBRATION.items()} | ctrl  # the lab's calibration
        ctrl |= {k: v for k, v in start.items() if k.endswith("_dot_start")}  # its velocity filter too
        ref = np.radians(delayed(exp.ref, c.ref_delay)[:n])  # type: ignore[arg-type]  # what the controller acted on
        res = rig.run_closed(ref, exp.Ts, ctrl, plant=plant, daq=daq, diverged="hold")
    elif exp.replay == "shooting":
        res = _shooting(rig, exp, plant, daq, n, over, delta)
    else:
        res = rig.run(exp.u[:n], exp.Ts, plant=plant, daq=daq)
    cal = sim_calibration(believed, setup.comb_angles)
    reading = theta_deg(res["theta_v"], cal, unwrap=False)
    if exp.encoder:
        on_track = np.ones(reading.size, dtype=bool)
    else:
        edge = 180.0 - 0.5 * fmu_value(daq, "daq", "pot_deadband") - DEADBAND_GUARD
        on_track = np.abs(reading) < edge
    th = unwrapped(reading)
    al = alpha_deg(res["alpha_v"], cal) - zero
    if exp.replay == "open":
        ok = on_track & exp.valid["theta"][: th.size]
        d = exp.theta[: th.size] - th
        th += float(np.mean(d[ok])) if ok.any() else float(np.mean(d))  # initial shaft angle: least squares
        ok_a = exp.valid["alpha"][: al.size]
        if ok_a.any():
            shift = float(np.mean((exp.alpha[: al.size] - al)[ok_a]))  # the gauge's zero: least squares
            al += shift
            delta += shift
    else:  # started at the measured angle: only whole turns of the pot's wrap to restore
        th += 360.0 * np.round((exp.theta[0] - th[0]) / 360.0)
    return Replayed(th, al, on_track, np.asarray(res.get("u", exp.u[:n]), dtype=float), delta)


def unwrapped(deg: np.ndarray) -> np.ndarray:
    """``np.unwrap(deg, period=360.0)`` [deg]: where no sample jumps by half a turn or more (the pot did not wrap), the
    same numbers without its corrections' arithmetic. Samples within less than half a turn of each other (their range)
    cannot jump so; a wider range is checked sample by sample."""
    if deg.size > 1 and (float(deg.max() - deg.min()) < 180.0 or bool(np.all(np.abs(np.diff(deg)) < 180.0))):
        out = deg.copy()
        out[1:] += 0.0  # as np.unwrap adds its (zero) corrections: -0.0 becomes 0.0 after the first sample
        return out
    return np.unwrap(deg, period=360.0)


def _shooting(
    rig: Any,
    exp: RigExperiment,
    plant: dict[str, Any],
    daq: dict[str, Any],
    n: int | None,
    over: Mapping[str, Any],
    alpha_offset_deg: float,
) -> dict:
    """Multiple-shooting replay: the logged command open loop in windows of SHOOTING_SECONDS, each started from
    the measured state (:func:`measured_state`, as the sensors of ``over`` read it, the gauge with
    ``alpha_offset_deg``); the windows' outputs end to end."""
    m = exp.u[:n].size
    w = max(2, int(round(SHOOTING_SECONDS / exp.Ts)))
    x0 = measured_state(exp)
    parts = []
    for s in range(0, m, w):
        start = {"theta_start": x0[s, 0], "alpha_start": x0[s, 1], "theta_dot_start": x0[s, 2]}
        start["alpha_dot_start"] = x0[s, 3]
        plant_s = {**plant, **true_state(start, over, alpha_offset_deg)}
        parts.append(rig.run(exp.u[s : min(s + w, m)], exp.Ts, plant=plant_s, daq=daq))
    return {k: np.concatenate([p[k] for p in parts]) for k in ("theta_v", "alpha_v")}


def residuals(
    rig: Any, setup: Setup, exp: RigExperiment, over: Mapping[str, Any], n: int | None = None, seeds: Sequence[int] = ()
) -> dict[str, np.ndarray]:
    """Residual y_real - y_sim [deg] per channel of one experiment (first ``n`` samples), 0 where a sample is not
    valid on either side (pot dead band, ADC clipping). ``seeds``: a closed loop's replay is the mean of its replay
    and its replays with these noise draws (each one realisation of a loop that plays or sticks where the noise
    decides: least squares on one realisation would favour the rig whose realisations spread least)."""
    th, al, on_track = simulate(rig, setup, exp, over, n)
    if seeds and exp.replay == "closed" and setup.loop_noise:
        more = [simulate(rig, setup, exp, {**over, "daq.seed": s}, n) for s in seeds]
        th = np.mean([th, *(r[0] for r in more)], axis=0)
        al = np.mean([al, *(r[1] for r in more)], axis=0)
        on_track = np.logical_and.reduce([on_track, *(r[2] for r in more)])
    m = th.size
    e_th = np.where(exp.valid["theta"][:m] & on_track, exp.theta[:m] - th, 0.0)
    e_al = np.where(exp.valid["alpha"][:m], exp.alpha[:m] - al, 0.0)
    return {"theta": e_th, "alpha": e_al}


def replay_traces(rig: Any, setup: Setup, over: Mapping[str, Any]) -> dict[str, dict[str, np.ndarray]]:
    """Every experiment's replay on the sim rig with overrides ``over``: {experiment: {"theta": [deg], "alpha":
    [deg]}}, NaN where the simulated pot is off its track (what a person compares with the record)."""
    out = {}
    for name, x in setup.experiments.items():
        th, al, on_track = simulate(rig, setup, x, over)
        out[name] = {"theta": np.where(on_track, th, np.nan), "alpha": al}
    return out


def _quantises(setup: Setup, exp: RigExperiment, d_over: Mapping[str, Any]) -> bool:
    """Does the sim DAQ quantise (adc_bits > 0) in ``exp``'s replay with the DAQ overrides ``d_over``?"""
    return int({**setup.daq, **exp.daq, **d_over}.get("adc_bits", 0)) > 0


def lattice_in_loop(setup: Setup, over: Mapping[str, Any], names: list[str]) -> bool:
    """Does one of the experiments ``names`` run in closed loop through an ADC lattice on the sim rig with ``over``
    (the controller acting on quantised angles, so its replay is a staircase in the rig's parameters)?"""
    d_over = _split_overrides(over)[1]
    return any(x.replay == "closed" and _quantises(setup, x, d_over) for x in (setup.experiments[n] for n in names))


def mean_squared_gap(sse: SSE, experiments: dict[str, RigExperiment], names: list[str], window: str = "all") -> float:
    """The mean squared gap E: mean over ``names`` and both channels of sse / sst over a window (see
    :meth:`RigExperiment.window`; channels with no motion skipped); the gap is sqrt(E)."""
    ssts = {n: experiments[n].window(window)[1] for n in names}
    qs = [sse[n][c] / ssts[n][c] for n in names for c in CHANNELS if experiments[n].moves(c, window)]
    return float(np.mean(qs)) if qs else math.nan


def channel_fits(sse: SSE, experiments: dict[str, RigExperiment], names: list[str]) -> dict[str, float]:
    """Fit % per channel: 100 (1 - sqrt(E_c)), E_c the mean over ``names`` of the channel's sse / sst (experiments
    where it does not move skipped; NaN where it moves in none)."""
    out = {}
    for c in CHANNELS:
        qs = [sse[n][c] / experiments[n].sst[c] for n in names if experiments[n].moves(c)]
        out[c] = fit_pct(float(np.mean(qs))) if qs else math.nan
    return out


def fit_pct(e: float) -> float:
    """Fit % = 100 (1 - sqrt(E)) of a mean squared gap E."""
    return 100.0 * (1.0 - math.sqrt(e))


def gap_summary(sse: SSE, experiments: dict[str, RigExperiment], names: list[str]) -> GapSummary:
    """Gap over ``names``: fit % = 100 (1 - sqrt(E)), ``gap`` = sqrt(E), residual RMS [deg] per channel, and
    per experiment the fit % and residual RMS [deg] per channel."""
    E = mean_squared_gap(sse, experiments, names)
    n_tot = sum(experiments[n].u.size for n in names)
    per = {}
    for n in names:
        x = experiments[n]
        per[n] = ExperimentGap(
            fit_pct={c: fit_pct(sse[n][c] / x.sst[c]) if x.moves(c) else math.nan for c in CHANNELS},
            rms_deg={c: math.sqrt(sse[n][c] / x.u.size) for c in CHANNELS},
        )  # fmt: skip
    return GapSummary(
        gap=math.sqrt(E),
        fit_pct=fit_pct(E),
        rms_deg={c: math.sqrt(sum(sse[n][c] for n in names) / n_tot) for c in CHANNELS},
        experiments=per,
    )


def replay_noise(daq: Mapping[str, Any], sigma_deg: Mapping[str, float]) -> dict[str, float]:
    """The DAQ noise [V rms] of a closed-loop replay: the data's noise RMS ``sigma_deg`` [deg] per channel through
    the sim DAQ's gains (``daq``: its parameters, FMU defaults for the rest)."""
    return {
        "noise_theta": sigma_deg["theta"] / abs(fmu_value(daq, "daq", "pot_gain")),
        "noise_alpha": sigma_deg["alpha"] / abs(fmu_value(daq, "daq", "gauge_gain")),
    }


@dataclass(frozen=True)
class Evaluation:
    """One experiment replayed beside its own spread, per channel: ``sse`` the squared residual of the record to the
    replay [deg^2 summed over its valid samples]; ``spread`` the variance the replays predict about their centre
    [deg^2, summed likewise], window by window (SPREAD_SECONDS): a closed loop's replays (with other noise draws,
    LOOP_NOISE_SEEDS, and other draws of the fitted parameters) are each one realisation of the loop, their centre
    their mean and the spread their variance as a new realisation's about that mean; an open loop's centre is the
    replay, its spread the data's measurement noise and the parameter draws' spread; at least the resolution's.
    ``effective``: the record's gap to the centre beside that spread as one mean squared gap in units of the
    record's variance (:func:`effective_gap`: the gap itself where the replay has no spread). ``own``: the replay's
    own parameters it was replayed with (its record's gauge offset, its link at its start: fitted on it where the
    fit left them out)."""

    sse: dict[str, float]
    effective: dict[str, float]
    spread: dict[str, float]
    own: dict[str, float]

    @property
    def offset(self) -> float:
        """The record's gauge offset [deg] the replay read."""
        return next((v for k, v in self.own.items() if k.startswith(ALPHA_OFFSET)), math.nan)


def _weighted(exp: RigExperiment, th: np.ndarray, al: np.ndarray, on: np.ndarray) -> np.ndarray:
    """An experiment's residuals to a replay, both channels, each over its valid samples and scaled by
    1 / sqrt(sst) (what least squares weighs them by)."""
    m = th.size
    parts = []
    for c, y in (("theta", th), ("alpha", al)):
        if exp.moves(c):
            ok = exp.valid[c][:m] & (on if c == "theta" else True)
            parts.append(np.where(ok, (exp.theta if c == "theta" else exp.alpha)[:m] - y, 0.0) / math.sqrt(exp.sst[c]))
    return np.concatenate(parts) if parts else np.zeros(0)


def fit_nuisance(rig: Any, setup: Setup, exp: RigExperiment, over: Mapping[str, Any]) -> dict[str, float]:
    """The closed-loop replay's own parameters ``over`` lacks (:func:`nuisance_keys`: its record's gauge offset, its
    link at its start) that fit it best, by one Gauss-Newton step from where the record puts them (exact where the
    loop is linear in them, as a loop without friction or play is): a held-out record's own, fitted on it as its
    initial state would be."""
    start = {k: v for k, v in nuisance_keys(exp).items() if k not in over}
    if not start:
        return {}
    keys = list(start)
    x0 = np.array([start[k] for k in keys])
    steps = np.array([OFFSET_STEP if k.startswith(ALPHA_OFFSET) or k.startswith(LINK_START[0]) else 10 * OFFSET_STEP
                      for k in keys])  # fmt: skip
    r0 = _weighted(exp, *simulate(rig, setup, exp, {**over, **start}))
    cols = []
    for j, k in enumerate(keys):
        cols.append(
            (_weighted(exp, *simulate(rig, setup, exp, {**over, **start, k: x0[j] + steps[j]})) - r0) / steps[j]
        )
    jac = np.column_stack(cols)
    dx = np.linalg.lstsq(jac, -r0, rcond=None)[0]
    return {k: float(v) for k, v in zip(keys, x0 + dx, strict=True)}


def effective_gap(gap: np.ndarray, count: np.ndarray, spread: np.ndarray, scale: float) -> float:
    """The record's gap to a replay beside the spread the replay predicts, window by window, as one mean squared gap
    [in units of ``scale``, the record's variance per sample]: the profile Gaussian likelihood of the record under the
    replay's predictive variance (its ``spread`` per window, deg^2) plus a model-error variance fitted to it, given as
    the mean squared gap a replay without spread would need to score the same, exp(S - 1) with S the least
    mean over windows of log(v + t) + m / (v + t) (m a window's mean squared gap, ``gap`` [deg^2] summed over its
    ``count`` valid samples, v its spread, t the model-error variance, all in units of ``scale``; windows weighted by
    their samples). Without spread it is the mean squared gap itself; a spread where the record's gap lies lowers
    it, a spread the record does not show raises it, and one as wide as the gap everywhere leaves it where it was."""
    ok = count > 0
    if not ok.any() or scale <= 0:
        return 0.0
    n, m, v = count[ok], gap[ok] / count[ok] / scale, spread[ok] / scale
    w = n / float(np.sum(n))

    def score(t: float) -> float:
        return float(np.sum(w * (np.log(v + t) + m / (v + t))))

    top = float(np.max(m)) + 1e-300
    best = minimize_scalar(lambda u: score(math.exp(u)), bounds=(math.log(top) - 40.0, math.log(top) + 1.0),
                           method="bounded", options={"xatol": 1e-6})  # fmt: skip
    s = min(score(math.exp(float(best.x))), score(0.0) if float(np.min(v)) > 0 else math.inf)
    return math.exp(s - 1.0)


def _windows(v: np.ndarray, ok: np.ndarray, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Sums of ``v`` over its valid samples (``ok``) and their counts, per window of ``w`` samples (the last one
    partial)."""
    edges = np.arange(0, v.size, w)
    return np.add.reduceat(np.where(ok, v, 0.0), edges), np.add.reduceat(ok.astype(float), edges)


def evaluate(
    rig: Any,
    setup: Setup,
    exp: RigExperiment,
    over: Mapping[str, Any],
    draws: Sequence[Mapping[str, Any]],
    pseudo: bool = False,
    resolution: float = 0.0,
) -> Evaluation:
    """``exp`` replayed with ``over`` beside its own spread (:class:`Evaluation`): its replays with each of ``draws``
    (other draws of the fitted parameters, each with another noise draw: LOOP_NOISE_SEEDS), its own parameters
    fitted on it where ``over`` has none (:func:`fit_nuisance`). ``pseudo``: the record replaced by what the replay
    itself would record with another noise draw (a closed loop's replay with PSEUDO_SEED, an open loop's replay with
    the data's white noise): what a right model leaves, the floor. ``resolution``: the smallest gap that counts, as a
    share of the record's RMS about its mean (a spread below it is taken at it)."""
    own = fit_nuisance(rig, setup, exp, over)
    over = {**over, **own}
    key = offset_key(exp.record)
    over.setdefault(key, exp.alpha_rest)
    closed = exp.replay == "closed" and bool(setup.loop_noise)
    first = replay(rig, setup, exp, over)
    th0, al0, on0 = first.theta, first.alpha, first.on_track
    m = th0.size
    sims = {"theta": th0, "alpha": al0}
    others = [simulate(rig, setup, exp, {**d, **own, "daq.seed": s})
              for d, s in zip(draws, LOOP_NOISE_SEEDS, strict=False)]  # fmt: skip
    if pseudo and closed:
        th, al, on = simulate(rig, setup, exp, {**over, "daq.seed": PSEUDO_SEED})
        data, on0 = {"theta": th, "alpha": al}, on0 & on
    elif pseudo:
        rng = np.random.default_rng(PSEUDO_SEED)
        data = {c: sims[c] + rng.normal(0.0, setup.sigma_deg.get(c, 0.0), m) for c in CHANNELS}
    else:
        data = {"theta": exp.theta[:m], "alpha": exp.alpha[:m]}
    w = max(1, int(round(SPREAD_SECONDS / exp.Ts)))
    out: dict[str, dict[str, float]] = {"sse": {}, "effective": {}, "spread": {}}
    for c in CHANNELS:
        ok = exp.valid[c][:m] & (on0 if c == "theta" else True)
        gap, count = _windows((data[c] - sims[c]) ** 2, ok, w)
        floor = max(setup.sigma_deg.get(c, 0.0) ** 2, resolution**2 * exp.sst[c] / max(exp.u.size, 1))
        centre, spread, valid = sims[c], np.full(gap.shape, floor), ok
        if others:
            ys = [th if c == "theta" else al for th, al, _ in others]
            valid = ok & (np.logical_and.reduce([on for _, _, on in others]) if c == "theta" else True)
            if closed:  # each replay one realisation of the loop: their mean, and a new one's spread about it
                ys.append(sims[c])
                centre = np.mean(ys, axis=0)
                dev = sum((y - centre) ** 2 for y in ys) / (len(ys) - 1) * (1.0 + 1.0 / len(ys))
            else:  # the replay without noise: the fitted parameters' spread about it, and the data's noise
                dev = sum((y - sims[c]) ** 2 for y in ys) / len(ys) + setup.sigma_deg.get(c, 0.0) ** 2
            s_sum, s_cnt = _windows(dev, valid, w)
            spread = np.maximum(np.divide(s_sum, s_cnt, out=np.zeros_like(s_sum), where=s_cnt > 0), floor)
        off, n_off = _windows((data[c] - centre) ** 2, valid, w)
        out["sse"][c] = float(np.sum(gap))
        out["spread"][c] = float(np.sum(count * spread))
        out["effective"][c] = effective_gap(off, n_off, spread, exp.sst[c] / max(exp.u.size, 1))
    own = {k: float(v) for k, v in over.items() if k in nuisance_keys(exp) or k == key}
    own[key] = first.alpha_zero  # an open loop's as its least squares took it
    return Evaluation(out["sse"], out["effective"], out["spread"], own)
