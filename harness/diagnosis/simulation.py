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
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

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
    "fit_offset",
    "mean_squared_gap",
    "offset_key",
    "replay_noise",
    "replay_traces",
    "residuals",
    "sim_calibration",
    "sim_rig",
    "simulate",
]

ALPHA_OFFSET = "sensor.alpha_offset"  # a record's gauge offset [deg], per record: :func:`offset_key`
SENSOR_DAQ = ("pot_gain", "pot_offset", "gauge_gain", "gauge_offset", "gauge_cubic")  # the calibration's DAQ parameters
SSE = dict[str, dict[str, float]]  # experiment -> channel -> sum of squared residuals [deg^2]
MODELS = {"plant": "flexjoint", "daq": "daq"}  # the FMU behind each rig table
SENSOR_KNOWN = 0.01  # a sensor gain known to 1 % (sd, log) is not fitted: its error goes into the intervals
REPLAY_NOISE_SEED = 7  # noise seed of every closed-loop replay (:attr:`Setup.loop_noise`)
LOOP_NOISE_SEEDS = (1, 2, 3, 4)  # other seeds, whose replays against it show what noise fed back spreads
PSEUDO_SEED = 11  # the noise draw of the record a right model would leave (:func:`evaluate`'s floor)
OFFSET_STEP = 0.1  # deg: the step of a held-out record's gauge offset fit (:func:`fit_offset`)
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
    plant, daq = {}, {}
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
    return daq_calibration(
        *(fmu_value(daq, "daq", k) for k in SENSOR_DAQ),
        comb_angles=comb_angles,
    )


def offset_key(record: str) -> str:
    """The override of a record's gauge offset: "sensor.alpha_offset@<record>" [deg, as the record reads it]."""
    return f"{ALPHA_OFFSET}@{record}"


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
    ({"plant.x": v, ...}), and the mask of the theta samples where the simulated pot is on its track.

    The gauge reads its record's offset (:func:`gauge_offset`), which a closed loop's controller acts on; an
    open-loop replay's offsets are then fitted by least squares (theta's: the integrator's unknown initial state, as
    MATLAB's ``compare`` estimates it; alpha's: the gauge's zero, which nothing feeds back there)."""
    d_over = _split_overrides(over)[1]
    delta = gauge_offset(exp, over)
    plant, daq, believed = rig_tables(setup, exp, over)
    daq["gauge_offset"] = fmu_value(daq, "daq", "gauge_offset") + delta / fmu_value(believed, "daq", "gauge_gain")
    noise = setup.lattice_noise if setup.lattice_noise and _quantises(setup, exp, d_over) else setup.loop_noise
    if exp.replay == "closed" and noise:
        daq = {**daq, **{k: v for k, v in noise.items() if k not in d_over}}
        daq["seed"] = d_over.get("seed", REPLAY_NOISE_SEED)
    # at the angle read first, the link as the record shows it there, as the sensors read them
    start = {"theta_start": math.radians(float(exp.theta[0])), **(exp.start_state if exp.replay != "shooting" else {})}
    plant = {**plant, **true_state(start, over, delta)}
    if exp.replay == "closed":
        c = Controller(**exp.controller)  # type: ignore[arg-type]
        ctrl = c.fmu_parameters(1.0 / exp.Ts)
        ctrl = {k: fmu_value(believed, "daq", v) for k, v in CALIBRATION.items()} | ctrl  # the lab's calibration
        ctrl |= {k: v for k, v in exp.start_state.items() if k.endswith("_dot_start")}  # its velocity filter too
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
    th = np.unwrap(reading, period=360.0)
    al = alpha_deg(res["alpha_v"], cal)
    if exp.replay == "open":
        ok = on_track & exp.valid["theta"][: th.size]
        d = exp.theta[: th.size] - th
        th += float(np.mean(d[ok])) if ok.any() else float(np.mean(d))  # initial shaft angle: least squares
        ok_a = exp.valid["alpha"][: al.size]
        if ok_a.any():
            al += float(np.mean((exp.alpha[: al.size] - al)[ok_a]))  # the gauge's zero: least squares
    else:  # started at the measured angle: only whole turns of the pot's wrap to restore
        th += 360.0 * np.round((exp.theta[0] - th[0]) / 360.0)
    return th, al, on_track


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
    rig: Any, setup: Setup, exp: RigExperiment, over: Mapping[str, Any], n: int | None = None
) -> dict[str, np.ndarray]:
    """Residual y_real - y_sim [deg] per channel of one experiment (first ``n`` samples), 0 where a sample is not
    valid on either side (pot dead band, ADC clipping)."""
    th, al, on_track = simulate(rig, setup, exp, over, n)
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
    qs = [sse[n][c] / ssts[n][c] for n in names for c in CHANNELS if ssts[n][c] > 0]
    return float(np.mean(qs)) if qs else math.nan


def channel_fits(sse: SSE, experiments: dict[str, RigExperiment], names: list[str]) -> dict[str, float]:
    """Fit % per channel: 100 (1 - sqrt(E_c)), E_c the mean over ``names`` of the channel's sse / sst (experiments
    where it does not move skipped; NaN where it moves in none)."""
    out = {}
    for c in CHANNELS:
        qs = [sse[n][c] / experiments[n].sst[c] for n in names if experiments[n].sst[c] > 0]
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
            fit_pct={c: fit_pct(sse[n][c] / x.sst[c]) if x.sst[c] > 0 else math.nan for c in CHANNELS},
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
    """One experiment replayed beside its own spread, per channel [deg^2 summed over its valid samples]: ``sse`` the
    squared residual of the record to the replay; ``spread`` what the replay itself predicts there, window by window
    (SPREAD_SECONDS): a closed loop's mean squared difference between the replay and its replays with other noise
    draws (LOOP_NOISE_SEEDS: the noise its controller fed back, and both replays' measurement noise), an open loop's
    the data's measurement noise, at least the resolution's; ``excess`` how far the record's gap is from that
    spread, window by window (the sum of n |gap - spread| over windows of n samples: a replay that is right leaves
    the noise's fluctuation, one that misses leaves its misfit, one that spreads more than the record its excess
    spread). ``offset``: the record's gauge offset the replay read [deg] (fitted on it where the fit left none)."""

    sse: dict[str, float]
    excess: dict[str, float]
    spread: dict[str, float]
    offset: float


def _weighted(exp: RigExperiment, th: np.ndarray, al: np.ndarray, on: np.ndarray) -> np.ndarray:
    """An experiment's residuals to a replay, both channels, each over its valid samples and scaled by
    1 / sqrt(sst) (what least squares weighs them by)."""
    m = th.size
    parts = []
    for c, y in (("theta", th), ("alpha", al)):
        if exp.sst[c] > 0:
            ok = exp.valid[c][:m] & (on if c == "theta" else True)
            parts.append(np.where(ok, (exp.theta if c == "theta" else exp.alpha)[:m] - y, 0.0) / math.sqrt(exp.sst[c]))
    return np.concatenate(parts) if parts else np.zeros(0)


def fit_offset(rig: Any, setup: Setup, exp: RigExperiment, over: Mapping[str, Any]) -> float:
    """The gauge offset [deg] of ``exp``'s record that fits its replay with ``over`` best, by one Gauss-Newton step
    from its reading at rest (:attr:`RigExperiment.alpha_rest`; exact where the loop is linear in it, as a loop
    without friction or play is): a held-out record's own zero, fitted on it as its initial state would be."""
    key, d0, h = offset_key(exp.record), exp.alpha_rest, OFFSET_STEP
    r0 = _weighted(exp, *simulate(rig, setup, exp, {**over, key: d0}))
    j = (_weighted(exp, *simulate(rig, setup, exp, {**over, key: d0 + h})) - r0) / h
    jj = float(np.dot(j, j))
    return d0 - float(np.dot(j, r0)) / jj if jj > 0 else d0


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
    draws: int,
    pseudo: bool = False,
    resolution: float = 0.0,
) -> Evaluation:
    """``exp`` replayed with ``over`` beside its own spread (:class:`Evaluation`): a closed loop with ``draws`` other
    noise draws, its record's gauge offset fitted on it where ``over`` has none (:func:`fit_offset`). ``pseudo``:
    the record replaced by what the replay itself would record with another noise draw (a closed loop's replay with
    PSEUDO_SEED, an open loop's replay with the data's white noise): what a right model leaves, the floor.
    ``resolution``: the smallest gap that counts, as a share of the record's RMS about its mean (a spread below it
    is taken at it)."""
    over = dict(over)
    key = offset_key(exp.record)
    closed = exp.replay == "closed" and bool(setup.loop_noise)
    if exp.replay == "closed" and key not in over:
        over[key] = fit_offset(rig, setup, exp, over)
    th0, al0, on0 = simulate(rig, setup, exp, over)
    m = th0.size
    sims = {"theta": th0, "alpha": al0}
    others = [simulate(rig, setup, exp, {**over, "daq.seed": s}) for s in LOOP_NOISE_SEEDS[:draws]] if closed else []
    if pseudo and closed:
        th, al, on = simulate(rig, setup, exp, {**over, "daq.seed": PSEUDO_SEED})
        data, on0 = {"theta": th, "alpha": al}, on0 & on
    elif pseudo:
        rng = np.random.default_rng(PSEUDO_SEED)
        data = {c: sims[c] + rng.normal(0.0, setup.sigma_deg.get(c, 0.0), m) for c in CHANNELS}
    else:
        data = {"theta": exp.theta[:m], "alpha": exp.alpha[:m]}
    w = max(1, int(round(SPREAD_SECONDS / exp.Ts)))
    out: dict[str, dict[str, float]] = {"sse": {}, "excess": {}, "spread": {}}
    for c in CHANNELS:
        ok = exp.valid[c][:m] & (on0 if c == "theta" else True)
        r2 = (data[c] - sims[c]) ** 2
        gap, count = _windows(r2, ok, w)
        floor = max(setup.sigma_deg.get(c, 0.0) ** 2, resolution**2 * exp.sst[c] / max(exp.u.size, 1))
        if others:
            spread = np.zeros_like(gap)
            for th, al, on in others:
                y = th if c == "theta" else al
                sub = ok & (on if c == "theta" else True)
                s_sum, s_cnt = _windows((y - sims[c]) ** 2, sub, w)
                spread += np.divide(s_sum, s_cnt, out=np.zeros_like(s_sum), where=s_cnt > 0) / len(others)
            spread = np.maximum(spread, floor)
        else:
            spread = np.full(gap.shape, floor)
        mean_gap = np.divide(gap, count, out=np.zeros_like(gap), where=count > 0)
        out["sse"][c] = float(np.sum(gap))
        out["excess"][c] = float(np.sum(count * np.abs(mean_gap - spread)))
        out["spread"][c] = float(np.sum(count * spread))
    return Evaluation(out["sse"], out["excess"], out["spread"], float(over.get(key, exp.alpha_rest)))
