"""Diagnose the sim-to-real gap: which unmodelled effect causes it, how far it shrinks, where it lies.

Comparison. Every non-calibration experiment of the REAL run is re-simulated on the SIM spec's rig (plant and
DAQ FMUs, the spec's ``[plant]``/``[daq]`` and its per-experiment overrides, measurement noise off, DAQ
sample rate 1/Ts of the data) with the REAL command ``u`` from the data. Both sides are converted to degrees
the way each is calibrated: real volts with the real run's calibration (Kp, Ke, offsets), simulated volts with
the simulation's own pot gain/offset and, when the real gauge was calibrated on a comb, the least-squares Ke of
the simulated gauge over the same comb angles (so a gauge nonlinearity is calibrated alike on both sides).
theta [deg] is unwrapped; the simulation starts at the first real shaft angle (so pot wraps coincide) and its
constant offset is then fitted by least squares (the integrator's unknown initial state, as MATLAB's
``compare`` estimates it: one noisy first sample must not offset a whole record). Two channels: theta
(friction, backlash, saturation, delay show here) and alpha (modes, delay, backlash impacts, gauge
nonlinearity show here).

Gap. Per experiment and channel q = ||y_real - y_sim||^2 / ||y_real - mean||^2; over experiments E = mean q
(channels and experiments weighted alike), gap g = sqrt(E), fit % = 100 (1 - g) (MATLAB ``compare``'s fit,
pooled) and the residual RMS [deg] per channel. Angles, not their filtered differences: on the lab campaign the
noise-only gap of theta is 0.002 in angle and 0.009 in the velocity domain, for the same effect gaps.

Noise floor. From the real data: period-to-period differences of periodic experiments after their transient,
with what a slow gain/offset drift explains removed (theta through its first difference), or without one a
MAD estimate from third differences; plus LSB^2 / 12 when the data sit on an ADC lattice (identical periods
quantise alike, so the difference misses it). E_noise is the E that this white noise gives.

Which effect. 2-fold cross-fitting: the experiments are split into folds A and B (stratified by signal kind and
command level); each candidate's FMU parameter is fitted on one fold (its first FIT_SECONDS per experiment) and
scored on the other, so every experiment is held out once. Integers are enumerated; continuous parameters get a
coarse grid (log or linear) and a bounded Brent refinement of the best bracket. Score: the share of the excess
squared gap closed on held-out data, closure = (E_before - E_after) / (E_before - E_noise). Greedy: the best
candidate is added while closure >= MIN_CLOSURE (0.3; two balanced effects split the gap, so the first closes
only about half of it; measured on the blind test, mimics left after the truth is modelled and candidates
facing a drifting gauge close <= 25 %); after each addition the earlier continuous parameters are refitted and
the rest are refitted on top, until the gap left is within NONE_RATIO x the noise gap. Quantisation barely
moves the gap: it is detected by its signature (every sample on the lattice of LSB = 2 adc_range / 2^bits; the
coarsest lattice gives the bits) and added last with its honest (even negative) shrink.

Verdict: ``none`` when the gap before is within NONE_RATIO (2) x the noise gap and no lattice (``quantization``
with one); otherwise the effect found that accounts for most of the excess gap (drop-one: removing it from the
final model reopens the most), if the effects found close >= EXPLAINED (90 %) of the excess squared gap on
held-out data; else ``unexplained`` (the partial candidates stay listed with their honest shrink). In-library
rigs close >= 99 %; a 3-mode rig with the 2-mode candidate ~80 %, doubled viscous damping with friction ~60 %.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import minimize_scalar

from . import spec as specmod
from .calibration import Calibration, alpha_deg, ke_from_comb, theta_deg
from .data import DataError, load_manifest, read_dataset, sample_time, write_json
from .pipeline import load_calibration

Progress = Callable[[str], None]

# Decision thresholds (see the module docstring for why these values)
NONE_RATIO = 2.0  # gap within 2x the noise gap (E within 4x E_noise): no gap beyond noise
MIN_CLOSURE = 0.3  # a candidate must close >= 30 % of the excess squared gap left on held-out experiments
EXPLAINED = 0.9  # the effects found must close >= 90 % of the excess squared gap for a verdict naming one
CHANNELS = ("theta", "alpha")
TRANSIENT_S = 8.0  # s dropped at the start of a periodic experiment before its periods are compared
FIT_SECONDS = 30.0  # parameters are fitted on the first 30 s of each experiment (scored on all of it)


@dataclass(frozen=True)
class Effect:
    """A candidate effect: one FMU parameter ``param`` ("plant.coulomb_torque") in ``unit``.

    ``kind`` "log" / "linear" (continuous, bounds ``lo``..``hi``, coarse ``grid`` points) or "int" (``values``
    enumerated; for quantisation the values come from the ADC lattice found in the data).
    """

    name: str
    param: str
    unit: str
    kind: str
    lo: float = 0.0
    hi: float = 0.0
    grid: int = 9
    values: tuple[int, ...] = ()


EFFECTS: dict[str, Effect] = {
    "coulomb_friction": Effect("coulomb_friction", "plant.coulomb_torque", "N m", "log", 1e-3, 0.5, 8),
    "backlash": Effect("backlash", "plant.backlash", "rad", "log", 2e-4, 0.05, 7),
    "saturation": Effect("saturation", "plant.amp_limit", "V", "log", 0.1, 10.0, 7),
    "second_mode": Effect("second_mode", "plant.n_modes", "1", "int", values=(2,)),
    "delay": Effect("delay", "daq.delay_samples", "samples", "int", values=(0, 1, 2, 3, 4, 5)),
    "quantization": Effect("quantization", "daq.adc_bits", "bits", "int"),
    "gauge_nonlinearity": Effect("gauge_nonlinearity", "daq.gauge_cubic", "1", "linear", -0.3, 0.3, 9),
}
VERDICTS = (*EFFECTS, "none", "unexplained")


# ----------------------------------------------------------------------------------------------- data


@dataclass
class Trial:
    """One real experiment prepared for comparison: command ``u`` [V] at ``Ts`` [s], real ``theta``/``alpha``
    [deg] (calibrated, theta unwrapped), raw volts, ``sst`` per channel [deg^2] (sum of squares about the
    mean), the sim spec's per-experiment ``plant``/``daq`` overrides, ``kind`` (signal) and ``period`` (samples
    of a periodic command, 0 if none)."""

    name: str
    kind: str
    Ts: float
    t: np.ndarray
    u: np.ndarray
    theta: np.ndarray
    alpha: np.ndarray
    theta_v: np.ndarray
    alpha_v: np.ndarray
    sst: dict[str, float]
    plant: dict[str, Any] = field(default_factory=dict)
    daq: dict[str, Any] = field(default_factory=dict)
    period: int = 0
    role: str = "identification"
    n_fit: int = 0
    sst_fit: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.n_fit = min(self.u.size, max(16, int(round(FIT_SECONDS / self.Ts))))
        ys = (self.theta[: self.n_fit], self.alpha[: self.n_fit])
        self.sst_fit = {c: float(np.sum((y - y.mean()) ** 2)) for c, y in zip(CHANNELS, ys, strict=True)}


@dataclass
class Setup:
    """The simulation being judged: its rig parameters (noise off), the real run's comb angles [deg] for the
    sim-side gauge calibration (None: use the sim's gauge gain), and the real trials."""

    plant: dict[str, Any]
    daq: dict[str, Any]
    comb_angles: np.ndarray | None
    trials: dict[str, Trial]
    plant_fmu: str = ""
    daq_fmu: str = ""


def _periodic(u: np.ndarray, hint: int = 0) -> int:
    """Period [samples] of a command repeated at least 3 times (``hint`` tried first), 0 when none."""
    n = u.size
    tol = 1e-9 * max(float(np.max(np.abs(u))), 1e-12)
    cands = [hint] if hint > 0 else []
    cands += [p for p in range(16, n // 3 + 1) if n % p == 0]
    for p in cands:
        if 0 < p <= n // 3 and np.all(np.abs(u[p:] - u[:-p]) <= tol) and np.ptp(u[:p]) > 0:
            return p
    return 0


def load_trials(real: Path, cal: Calibration, sim: specmod.Spec) -> dict[str, Trial]:
    """Every non-calibration experiment of run ``real`` as a :class:`Trial` (manifest order)."""
    manifest = load_manifest(real)
    exps = [e for e in manifest["experiments"] if e.get("role", "identification") != "calibration"]
    if not exps:
        raise DataError(f"{real}: no identification or analysis experiments to diagnose")
    raw_spec = manifest.get("spec") if manifest.get("kind") == "campaign" else None
    sim_exps = {e.name: e for e in sim.all_experiments()}
    out: dict[str, Trial] = {}
    for e in exps:
        df = read_dataset(Path(real) / "data" / f"{e['name']}.parquet")
        Ts = sample_time(df)
        u = df["u"].to_numpy(float)
        th_v, al_v = df["theta_v"].to_numpy(float), df["alpha_v"].to_numpy(float)
        th, al = theta_deg(th_v, cal), alpha_deg(al_v, cal)
        hint = 0
        if raw_spec is not None:
            for d in raw_spec.get("experiment", []):
                if d.get("name") == e["name"] and d.get("signal") == "multisine" and "period" in d:
                    hint = int(round(float(d["period"]) / Ts))
        se = sim_exps.get(e["name"])
        out[e["name"]] = Trial(
            name=e["name"],
            kind=str(e.get("signal", "imported")),
            Ts=Ts,
            t=df["t"].to_numpy(float),
            u=u,
            theta=th,
            alpha=al,
            theta_v=th_v,
            alpha_v=al_v,
            sst={c: float(np.sum((y - y.mean()) ** 2)) for c, y in zip(CHANNELS, (th, al), strict=True)},
            plant=dict(se.plant) if se else {},
            daq=dict(se.daq) if se else {},
            period=_periodic(u, hint),
            role=str(e.get("role", "identification")),
        )
    return out


def sim_rig(sim: specmod.Spec) -> tuple[dict[str, Any], dict[str, Any]]:
    """The sim spec's rig parameters with measurement noise off: (plant, daq)."""
    plant = {"internal_step": sim.internal_step, **sim.plant}
    daq = {**sim.daq, "noise_theta": 0.0, "noise_alpha": 0.0}
    return plant, daq


def _split_overrides(over: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    plant, daq = {}, {}
    for k, v in over.items():
        table, name = k.split(".", 1)
        (plant if table == "plant" else daq)[name] = v
    return plant, daq


def _daq_value(daq: dict[str, Any], name: str) -> float:
    return float(daq.get(name, specmod.fmu_parameters("daq")[name][1]))


def sim_gauge_calibration(daq: dict[str, Any], comb_angles: np.ndarray | None) -> tuple[float, float]:
    """(Ke [deg/V], offset [V]) for converting simulated gauge volts: the least-squares line over the real
    comb angles through the simulated static gauge map, or the DAQ's gauge gain and offset without a comb."""
    gg, go, gc = (_daq_value(daq, k) for k in ("gauge_gain", "gauge_offset", "gauge_cubic"))
    if comb_angles is None or comb_angles.size < 3 or gc == 0.0:
        return gg, go
    a = comb_angles
    v = (a / gg + go) * (1.0 + gc * (a / 10.0) ** 2)
    g = ke_from_comb(a, v)
    return g.Ke, g.offset_v


def simulate(
    rig: Any, setup: Setup, trial: Trial, over: dict[str, Any], n: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Simulated (theta, alpha) [deg] of one trial (its first ``n`` samples) on the sim rig with ``over``
    ({"plant.x": v, ...})."""
    p_over, d_over = _split_overrides(over)
    plant = {**setup.plant, **trial.plant, **p_over}
    daq = {**setup.daq, **trial.daq, **d_over}
    plant.setdefault("theta_start", math.radians(float(trial.theta[0])))
    res = rig.run(trial.u[:n], trial.Ts, plant=plant, daq=daq)
    kp, po = _daq_value(daq, "pot_gain"), _daq_value(daq, "pot_offset")
    th = np.unwrap(kp * (res["theta_v"] - po), period=360.0)
    th += float(np.mean(trial.theta[: th.size] - th))  # initial shaft angle: least squares (see module doc)
    ke, go = sim_gauge_calibration(daq, setup.comb_angles)
    return th, ke * (res["alpha_v"] - go)


# ----------------------------------------------------------------------------------------------- workers

_CTX: dict[str, Any] = {}


def _init(setup: Setup) -> None:
    from .cosim import Rig

    _CTX["setup"] = setup
    _CTX["rig"] = Rig(Path(setup.plant_fmu), Path(setup.daq_fmu))


def _sse(over: dict[str, Any], names: list[str], fit: bool = False) -> dict[str, dict[str, float]]:
    """Squared errors [deg^2] per trial and channel for overrides ``over`` (``fit``: first n_fit samples)."""
    setup: Setup = _CTX["setup"]
    out = {}
    for n in names:
        tr = setup.trials[n]
        m = tr.n_fit if fit else tr.u.size
        th, al = simulate(_CTX["rig"], setup, tr, over, m)
        out[n] = {"theta": float(np.sum((tr.theta[:m] - th) ** 2)), "alpha": float(np.sum((tr.alpha[:m] - al) ** 2))}
    return out


def energy(sse: dict[str, dict[str, float]], trials: dict[str, Trial], names: list[str], fit: bool = False) -> float:
    """Mean normalised squared error E over ``names`` and both channels (channels with no motion skipped)."""
    ssts = {n: trials[n].sst_fit if fit else trials[n].sst for n in names}
    qs = [sse[n][c] / ssts[n][c] for n in names for c in CHANNELS if ssts[n][c] > 0]
    return float(np.mean(qs)) if qs else math.nan


def _objective(over: dict[str, Any], names: list[str]) -> float:
    return energy(_sse(over, names, fit=True), _CTX["setup"].trials, names, fit=True)


def _fit_continuous(
    eff: Effect, base: dict[str, Any], names: list[str], lo: float, hi: float, grid: int, start: float | None
):
    """Coarse grid then bounded Brent on the best bracket, or (``start`` given: a refit) Brent on [lo, hi]
    only; returns (value, E on ``names``, evaluations)."""
    log = eff.kind == "log"
    fwd = (lambda x: math.log(x)) if log else (lambda x: x)
    inv = (lambda s: math.exp(s)) if log else (lambda s: s)
    s_lo, s_hi = fwd(lo), fwd(hi)
    if start is None:
        pts = np.linspace(s_lo, s_hi, grid)
        vals = [_objective({**base, eff.param: inv(s)}, names) for s in pts]
        i = int(np.argmin(vals))
        a, b = pts[max(i - 1, 0)], pts[min(i + 1, grid - 1)]
        best_s, best_v = float(pts[i]), float(vals[i])
    else:
        a, b = s_lo, s_hi
        best_s = fwd(start)
        best_v = _objective({**base, eff.param: start}, names)
        grid = 1
    res = minimize_scalar(
        lambda s: _objective({**base, eff.param: inv(s)}, names),
        bounds=(a, b),
        method="bounded",
        options={"xatol": 0.01 if log else 0.002 * (s_hi - s_lo), "maxiter": 10},
    )
    if res.fun < best_v:
        best_s, best_v = float(res.x), float(res.fun)
    return inv(best_s), best_v, grid + int(res.nfev)


def fit_effect(
    eff: Effect,
    base: dict[str, Any],
    fit: list[str],
    every: list[str],
    refit: tuple[float, float, float] | None = None,
) -> dict[str, Any]:
    """Fit one effect on top of ``base`` on experiments ``fit`` (their first FIT_SECONDS); squared errors on
    ``every`` experiment. ``refit`` = (lo, hi, current): a local refit of a continuous parameter."""
    if eff.kind == "int":
        scores = [(_objective({**base, eff.param: v}, fit), v) for v in eff.values]
        e_fit, value = min(scores, key=lambda s: (s[0], s[1]))
        value, n = int(value), len(scores)
    elif refit is None:
        value, e_fit, n = _fit_continuous(eff, base, fit, eff.lo, eff.hi, eff.grid, None)
    else:
        value, e_fit, n = _fit_continuous(eff, base, fit, refit[0], refit[1], 0, refit[2])
    return {
        "effect": eff.name,
        "params": {eff.param: value},
        "fit_energy": e_fit,
        "sse": _sse({**base, eff.param: value}, every),
        "evaluations": n + len(every),
    }


def _task(kind: str, *args: Any) -> Any:
    if kind == "sse":
        return _sse(*args)
    return fit_effect(*args)


class _Pool:
    """Candidate fits on ``workers`` processes (each with its own Rig), or in-process for workers <= 1."""

    def __init__(self, setup: Setup, workers: int) -> None:
        self.workers = workers
        self.ex = None
        if workers > 1:
            self.ex = ProcessPoolExecutor(max_workers=workers, initializer=_init, initargs=(setup,))
        else:
            _init(setup)

    def map(self, calls: list[tuple[Any, ...]]) -> list[Any]:
        if self.ex is None:
            return [_task(*c) for c in calls]
        futs = [self.ex.submit(_task, *c) for c in calls]
        return [f.result() for f in futs]

    def close(self) -> None:
        if self.ex is not None:
            self.ex.shutdown()
        elif "rig" in _CTX:
            _CTX.pop("rig").close()


# ----------------------------------------------------------------------------------------------- signatures


def adc_lattice(trials: dict[str, Trial], adc_range: float, max_bits: int = 24) -> int:
    """ADC bits whose lattice (multiples of LSB = 2 adc_range / 2^bits) holds every real sample of theta_v and
    alpha_v (the coarsest such lattice), 0 when the data are not quantised (or finer than ``max_bits``)."""
    v = np.concatenate([np.r_[t.theta_v, t.alpha_v] for t in trials.values()])
    for bits in range(2, max_bits + 1):
        lsb = 2.0 * adc_range / 2.0**bits
        r = v / lsb
        if np.max(np.abs(r - np.round(r))) < 1e-6:
            return bits
    return 0


def _clipped_var(d: np.ndarray) -> float:
    """Variance about zero with 5-sigma clipping (a few non-periodic events do not count)."""
    d = d[np.isfinite(d)]
    keep = np.ones(d.size, dtype=bool)
    for _ in range(3):
        v = float(np.mean(d[keep] ** 2)) if keep.any() else 0.0
        new = d**2 <= 25.0 * v if v > 0 else keep
        if np.array_equal(new, keep):
            break
        keep = new
    return v


def _period_residual(y: np.ndarray, P: int, s0: int) -> np.ndarray:
    """Differences between consecutive periods of ``y`` (from period ``s0`` on), each with what a slowly
    drifting gain and offset explain removed (least squares on the two periods' mean and a time ramp of it)."""
    M = y.size // P
    blocks = y[s0 * P : M * P].reshape(M - s0, P)
    ramp = np.linspace(-0.5, 0.5, P)
    out = []
    for a, b in zip(blocks[:-1], blocks[1:], strict=True):
        m = 0.5 * (a + b)
        X = np.column_stack([np.ones(P), ramp, m - m.mean(), (m - m.mean()) * ramp])
        d = b - a
        coef, *_ = np.linalg.lstsq(X, d, rcond=None)
        out.append((d - X @ coef) * math.sqrt(P / (P - X.shape[1])))
    return np.concatenate(out)


def noise_sigma(trials: dict[str, Trial]) -> dict[str, Any]:
    """Measurement-noise RMS [deg] per channel, from the real data.

    With periodic experiments (>= 2 periods after the transient: the first max(one period, TRANSIENT_S) are
    dropped, the link's mode rings for seconds): differences between consecutive periods, alpha directly
    (var = 2 s^2), theta through its first difference (var = 4 s^2), after removing what a slow drift of gain
    or offset explains (a drifting gauge is a gap, not noise). Without: 1.4826 MAD of the third difference
    / sqrt(20), median over experiments (an upper bound when the motion is fast).
    """

    def skip(t: Trial) -> int:
        return max(1, math.ceil(TRANSIENT_S / (t.period * t.Ts) - 1e-9))

    per = [t for t in trials.values() if t.period > 0 and t.u.size // t.period - skip(t) >= 2]
    if per:
        d_th = [_period_residual(np.r_[0.0, np.diff(t.theta)], t.period, skip(t)) for t in per]
        d_al = [_period_residual(t.alpha, t.period, skip(t)) for t in per]
        s_th = math.sqrt(_clipped_var(np.concatenate(d_th)) / 4.0)
        s_al = math.sqrt(_clipped_var(np.concatenate(d_al)) / 2.0)
        return {"theta_deg": s_th, "alpha_deg": s_al, "method": "period-to-period", "from": [t.name for t in per]}

    def mad3(x: np.ndarray) -> float:
        d = np.diff(x, 3)
        return 1.4826 * float(np.median(np.abs(d - np.median(d)))) / math.sqrt(20.0)

    s_th = float(np.median([mad3(t.theta) for t in trials.values()]))
    s_al = float(np.median([mad3(t.alpha) for t in trials.values()]))
    return {"theta_deg": s_th, "alpha_deg": s_al, "method": "MAD of third differences", "from": list(trials)}


def noise_energy(trials: dict[str, Trial], sigma: dict[str, Any], names: list[str]) -> float:
    """E that white noise of RMS ``sigma`` gives on ``names`` (same normalisation as :func:`energy`)."""
    s = {"theta": sigma["theta_deg"], "alpha": sigma["alpha_deg"]}
    qs = [trials[n].u.size * s[c] ** 2 / trials[n].sst[c] for n in names for c in CHANNELS if trials[n].sst[c] > 0]
    return float(np.mean(qs)) if qs else 0.0


# ----------------------------------------------------------------------------------------------- split


def split(trials: dict[str, Trial]) -> tuple[list[str], list[str]]:
    """Two folds A, B of experiment names for 2-fold cross-fitting (fit on A, score on B, and back): within each
    signal kind (sorted by peak |u|, then name) the experiments alternate between the folds, the first of
    every other kind going to B, so both folds span the kinds and the command levels. One experiment: it is
    both folds (nothing can be held out)."""
    names = list(trials)
    if len(names) == 1:
        return names, names
    kinds: dict[str, list[str]] = {}
    for n in names:
        kinds.setdefault(trials[n].kind, []).append(n)
    a, b = [], []
    for g, kind in enumerate(sorted(kinds)):
        grp = sorted(kinds[kind], key=lambda n: (round(float(np.max(np.abs(trials[n].u))), 6), n))
        for i, n in enumerate(grp):
            (a if (i + g) % 2 == 0 else b).append(n)
    if not b:  # every kind a singleton of the same parity
        b.append(a.pop())
    order = {n: i for i, n in enumerate(names)}
    return sorted(a, key=order.get), sorted(b, key=order.get)


# ----------------------------------------------------------------------------------------------- reporting


def gap_summary(sse: dict[str, dict[str, float]], trials: dict[str, Trial], names: list[str]) -> dict[str, Any]:
    """Gap over ``names``: fit % = 100 (1 - sqrt(E)), ``gap`` = sqrt(E), residual RMS [deg] per channel, and
    per experiment the fit % per channel."""
    E = energy(sse, trials, names)
    n_tot = sum(trials[n].u.size for n in names)
    per = {}
    for n in names:
        t = trials[n]
        per[n] = {
            "fit_pct": {c: 100.0 * (1.0 - math.sqrt(sse[n][c] / t.sst[c])) if t.sst[c] > 0 else math.nan
                        for c in CHANNELS},
            "rms_deg": {c: math.sqrt(sse[n][c] / t.u.size) for c in CHANNELS},
        }  # fmt: skip
    return {
        "gap": math.sqrt(E),
        "fit_pct": 100.0 * (1.0 - math.sqrt(E)),
        "rms_deg": {c: math.sqrt(sum(sse[n][c] for n in names) / n_tot) for c in CHANNELS},
        "experiments": per,
    }


def _shrink(before: float, after: float) -> float:
    return 100.0 * (1.0 - after / before) if before > 0 else 0.0


def _closure(e_before: float, e_after: float, e_noise: float) -> float:
    excess = e_before - e_noise
    return (e_before - e_after) / excess if excess > 0 else 0.0


def _round(x: Any, digits: int = 10) -> Any:
    """Round floats to ``digits`` significant digits so the JSON does not carry last-bit noise."""
    if isinstance(x, dict):
        return {k: _round(v, digits) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_round(v, digits) for v in x]
    if isinstance(x, (float, np.floating)):
        v = float(x)
        return float(f"{v:.{digits}g}") if math.isfinite(v) else v
    return x


# ----------------------------------------------------------------------------------------------- main


def _comb_angles(cal: Calibration) -> np.ndarray | None:
    src = cal.source.get("Ke", {}) if isinstance(cal.source, dict) else {}
    ang = src.get("angles_deg") if isinstance(src, dict) else None
    return np.asarray(ang, dtype=float) if ang else None


def _combine(eff: Effect, values: list[float]) -> float | int:
    """One parameter value from the two folds' fits: geometric mean (log), mean (linear), the common value
    (int; when the folds disagree, resolved by :func:`_select` on all experiments)."""
    if eff.kind == "log":
        return float(math.exp(np.mean(np.log(values))))
    if eff.kind == "linear":
        return float(np.mean(values))
    return int(values[0])


def diagnose_run(
    real: Path,
    sim: str | Path | specmod.Spec = "nominal",
    out: Path | None = None,
    progress: Progress | None = None,
    workers: int | None = None,
) -> dict[str, Any]:
    """Diagnose the gap between run directory ``real`` and the simulation spec ``sim`` (a path, a name in
    specs/ or a loaded Spec); ``workers`` processes fit the candidates (default 2). Writes
    ``out/diagnosis.json`` (default out = real) and returns its content plus ``timing_s`` (wall-clock seconds,
    written to ``diagnosis.timing.json`` so that diagnosis.json is byte-stable)."""
    from .build import build_all

    t0 = time.perf_counter()
    say = progress or (lambda _m: None)
    real = Path(real)
    if not (real / "manifest.json").exists():
        raise ValueError(f"{real}: not a run directory (no manifest.json)")
    sim_spec = sim if isinstance(sim, specmod.Spec) else specmod.load(sim)
    cal = load_calibration(real)
    trials = load_trials(real, cal, sim_spec)
    plant, daq = sim_rig(sim_spec)
    fmus = build_all()
    setup = Setup(plant, daq, _comb_angles(cal), trials, str(fmus["flexjoint"]), str(fmus["daq"]))
    names = list(trials)
    folds = split(trials)
    sigma = noise_sigma(trials)
    bits = adc_lattice(trials, _daq_value(daq, "adc_range"))
    if bits:  # identical periods quantise alike: the period-to-period estimate misses most of the ADC error
        lsb = 2.0 * _daq_value(daq, "adc_range") / 2.0**bits
        sigma["estimated_deg"] = {"theta": sigma["theta_deg"], "alpha": sigma["alpha_deg"]}
        sigma["theta_deg"] = math.sqrt(sigma["theta_deg"] ** 2 + (cal.Kp * lsb) ** 2 / 12.0)
        sigma["alpha_deg"] = math.sqrt(sigma["alpha_deg"] ** 2 + (cal.Ke * lsb) ** 2 / 12.0)
        sigma["method"] += " + ADC quantisation variance LSB^2 / 12"
    e_noise = noise_energy(trials, sigma, names)
    cands = _candidates(trials, plant, daq, bits)
    if workers is None:
        workers = min(2, os.cpu_count() or 1)
    pool = _Pool(setup, workers)
    try:
        result = _select(pool, trials, names, folds, cands, e_noise, say)
    finally:
        pool.close()
    where = where_gap(setup, real)
    dest = Path(out) if out is not None else real
    doc = {
        "real": os.path.relpath(real, dest),  # relative to diagnosis.json, so a moved run dir stays the same bytes
        "sim_spec": sim_spec.name if isinstance(sim, specmod.Spec) else str(sim),
        "sim_spec_file": Path(sim_spec.path).name,
        "calibration": {"Kp": cal.Kp, "Ke": cal.Ke, "gauge_offset_v": cal.gauge_offset_v},
        "folds": {"A": folds[0], "B": folds[1], "scheme": "2-fold cross-fit: fit on A score on B, and back"},
        "verdict": result["verdict"],
        "effects": result["effects"],
        "candidates": result["candidates"],
        "rounds": result["rounds"],
        "gap": result["gap"],
        "noise_floor": {
            **sigma,
            "gap": math.sqrt(e_noise),
            "fit_pct": 100.0 * (1.0 - math.sqrt(e_noise)),
            "adc_lattice_bits": bits,
        },
        "thresholds": {
            "none_ratio": NONE_RATIO,
            "min_closure": MIN_CLOSURE,
            "explained": EXPLAINED,
            "meaning": "none: gap before <= none_ratio x noise gap (and no ADC lattice); an effect is added "
            "when it closes >= min_closure of the excess (above-noise) squared gap left, on held-out data; the "
            "verdict names the first effect when together they close >= explained of the excess, else unexplained",
        },
        "where": where,
    }
    doc = _round(doc)
    write_json(dest / "diagnosis.json", doc)
    timing = time.perf_counter() - t0
    write_json(dest / "diagnosis.timing.json", {"timing_s": timing, "workers": workers})
    say(f"verdict {doc['verdict']}")
    return {**doc, "timing_s": timing}


def _candidates(trials: dict[str, Trial], plant: dict, daq: dict, bits: int) -> list[Effect]:
    """The candidate effects worth fitting against this sim (those it does not model already)."""
    out = []
    for eff in EFFECTS.values():
        if eff.name == "second_mode" and int(plant.get("n_modes", 1)) >= 2:
            continue
        if eff.name == "quantization":
            if not bits or int(daq.get("adc_bits", 0)) == bits:
                continue
            eff = Effect(eff.name, eff.param, eff.unit, "int", values=(bits,))
        if eff.name == "saturation":
            top = max(float(np.max(np.abs(t.u))) for t in trials.values())
            eff = Effect(eff.name, eff.param, eff.unit, "log", eff.lo, max(top, 2.0 * eff.lo), eff.grid)
        if eff.name == "delay":
            cur = int(daq.get("delay_samples", 0))
            eff = Effect(eff.name, eff.param, eff.unit, "int", values=tuple(v for v in eff.values if v != cur))
        out.append(eff)
    return out


def _cv(results: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """Held-out squared errors of the two folds, merged (every experiment scored by the fold not fitted on it)."""
    return {**results[0]["sse"], **results[1]["sse"]}


def _select(
    pool: _Pool,
    trials: dict[str, Trial],
    names: list[str],
    folds: tuple[list[str], list[str]],
    cands: list[Effect],
    e_noise: float,
    say: Progress,
) -> dict[str, Any]:
    """Greedy selection over the candidates with 2-fold cross-fitting; verdict, effects, candidates, gaps."""
    fits, helds = [folds[0], folds[1]], [folds[1], folds[0]]
    (sse0,) = pool.map([("sse", {}, names)])
    e0 = energy(sse0, trials, names)
    say(f"gap before: fit {100 * (1 - math.sqrt(e0)):.2f} %, noise floor {100 * math.sqrt(e_noise):.3f} %")
    no_gap = e0 <= NONE_RATIO**2 * e_noise
    bases: list[dict[str, Any]] = [{}, {}]
    chosen: list[str] = []
    rounds: list[list[dict[str, Any]]] = []
    remaining = [c for c in cands if c.name != "quantization"]
    e_base = e0
    while remaining:
        beyond = not no_gap and e_base > NONE_RATIO**2 * e_noise
        if rounds and not beyond:
            break  # the candidates are fitted once (for the record) even when there is no gap beyond noise
        res = pool.map([("fit", c, bases[k], fits[k], helds[k]) for c in remaining for k in (0, 1)])
        ranked = []
        for i, c in enumerate(remaining):
            pair = res[2 * i : 2 * i + 2]
            e_cv = energy(_cv(pair), trials, names)
            ranked.append(
                {
                    "effect": c.name,
                    "fold_params": [r["params"] for r in pair],
                    "params": {c.param: _combine(c, [r["params"][c.param] for r in pair])},
                    "held_out_share_pct": 100.0 * _closure(e_base, e_cv, e_noise),
                    "shrink_pct": _shrink(math.sqrt(e_base), math.sqrt(e_cv)),
                    "gap_after": math.sqrt(e_cv),
                }
            )
        ranked.sort(key=lambda r: (-r["held_out_share_pct"], r["effect"]))
        rounds.append(ranked)
        best = ranked[0]
        say(f"round {len(rounds)}: {best['effect']} closes {best['held_out_share_pct']:.1f} % of the excess gap")
        if not beyond or best["held_out_share_pct"] < 100.0 * MIN_CLOSURE:
            break
        for k in (0, 1):
            bases[k].update(best["fold_params"][k])
        chosen.append(best["effect"])
        e_base = best["gap_after"] ** 2
        remaining = [c for c in remaining if c.name != best["effect"]]
        earlier = [c for c in chosen[:-1] if EFFECTS[c].kind != "int"]
        if earlier:  # refit the earlier continuous parameters now that this effect is modelled
            bases = _polish(pool, bases, earlier, fits)
            (s1, s2) = pool.map([("sse", bases[k], helds[k]) for k in (0, 1)])
            e_base = energy({**s1, **s2}, trials, names)
        say(f"  gap left {math.sqrt(e_base):.4f} (noise {math.sqrt(e_noise):.4f})")
    signature = [c.name for c in cands if c.name == "quantization"]
    for c in cands:
        if c.name == "quantization":
            for k in (0, 1):
                bases[k][c.param] = c.values[0]
    order = chosen + signature
    # cumulative held-out gaps in greedy order, with each fold's final parameters
    calls = []
    for j in range(len(order)):
        keys = [_param(e) for e in order[: j + 1]]
        calls += [("sse", {p: bases[k][p] for p in keys}, helds[k]) for k in (0, 1)]
    # drop-one: the excess gap each closure-chosen effect accounts for with all the others modelled
    if len(chosen) >= 2:
        keys_all = [_param(e) for e in chosen]
        for e in chosen:
            calls += [("sse", {p: bases[k][p] for p in keys_all if p != _param(e)}, helds[k]) for k in (0, 1)]
    sses = pool.map(calls)
    final = _final_params(pool, bases, order, trials, names)
    (sse_final,) = pool.map([("sse", final, names)]) if order else (sse0,)
    effects = []
    prev = sse0
    for j, name in enumerate(order):
        cur = {**sses[2 * j], **sses[2 * j + 1]}
        gb, ga = math.sqrt(energy(prev, trials, names)), math.sqrt(energy(cur, trials, names))
        p = _param(name)
        effects.append(
            {
                "effect": name,
                "params": {p: final[p]},
                "params_folds": [{p: bases[0][p]}, {p: bases[1][p]}],
                "gap_before": gb,
                "gap_after": ga,
                "shrink_pct": _shrink(gb, ga),
                "fit_pct_before": 100.0 * (1.0 - gb),
                "fit_pct_after": 100.0 * (1.0 - ga),
                "fitted_on": [fits[0], fits[1]],
                "held_out": [helds[0], helds[1]],
                "selected_by": "adc lattice in the data" if name in signature else "held-out closure",
            }
        )
        prev = cur
    # share of the excess gap the effects found by closure explain (held-out), quantisation aside
    e_expl = energy({**sses[2 * len(chosen) - 2], **sses[2 * len(chosen) - 1]}, trials, names) if chosen else e0
    explained = min(_closure(e0, e_expl, e_noise), 1.0) if not no_gap else math.nan
    importance = {chosen[0]: explained} if len(chosen) == 1 else {}
    for j, e in enumerate(chosen if len(chosen) >= 2 else []):
        i = 2 * (len(order) + j)
        e_without = energy({**sses[i], **sses[i + 1]}, trials, names)
        importance[e] = (e_without - e_expl) / (e0 - e_noise) if e0 > e_noise else 0.0
    for eff in effects:
        eff["importance_pct"] = 100.0 * importance[eff["effect"]] if eff["effect"] in importance else math.nan
    if chosen and explained >= EXPLAINED:
        verdict = max(chosen, key=lambda e: (importance[e], -chosen.index(e)))
    elif no_gap:
        verdict = "quantization" if signature else "none"
    else:
        verdict = "unexplained"
    g_cv = effects[-1]["gap_after"] if effects else math.sqrt(e0)
    before, after = gap_summary(sse0, trials, names), gap_summary(sse_final, trials, names)
    gap = {
        "before": before,
        "after": after,
        "held_out": {"gap_before": math.sqrt(e0), "gap_after": g_cv, "fit_pct_before": 100 * (1 - math.sqrt(e0)),
                     "fit_pct_after": 100 * (1 - g_cv)},
        "shrink_pct": _shrink(math.sqrt(e0), g_cv),
        "shrink_pct_in_sample": _shrink(before["gap"], after["gap"]),
        "explained_pct": 100.0 * explained,
        "definition": "gap = sqrt(mean over experiments and channels (theta, alpha) of ||y_real - y_sim||^2 / "
        "||y_real - mean||^2); fit % = 100 (1 - gap); shrink % = 100 (1 - gap_after / gap_before); held_out: "
        "every experiment scored with parameters fitted on the other fold; after: final parameters, all data",
    }  # fmt: skip
    candidates = list(rounds[0]) if rounds else []
    for c in cands:
        if c.name == "quantization":
            (sq,) = pool.map([("sse", {c.param: c.values[0]}, names)])
            e_q = energy(sq, trials, names)
            candidates.append(
                {
                    "effect": c.name,
                    "params": {c.param: c.values[0]},
                    "held_out_share_pct": 100.0 * _closure(e0, e_q, e_noise),
                    "shrink_pct": _shrink(math.sqrt(e0), math.sqrt(e_q)),
                    "gap_after": math.sqrt(e_q),
                    "note": "bits from the ADC lattice of the data (nothing fitted, so all experiments are held out)",
                }
            )
    candidates.sort(key=lambda r: (-r["held_out_share_pct"], r["effect"]))
    for name in EFFECTS:
        if name not in {c.name for c in cands}:
            why = "no ADC lattice in the data" if name == "quantization" else "already in the simulation"
            candidates.append({"effect": name, "params": {}, "held_out_share_pct": None, "note": why})
    return {
        "verdict": verdict,
        "effects": effects,
        "candidates": candidates,
        "rounds": rounds,
        "gap": gap,
        "final": final,
        "sse0": sse0,
        "sse_final": sse_final,
    }


def _param(effect: str) -> str:
    return EFFECTS[effect].param


def _polish(pool: _Pool, bases: list[dict], chosen: list[str], fits: list[list[str]]) -> list[dict]:
    """One coordinate pass per fold: refit every chosen continuous parameter with the others in place (Brent
    on value / 1.6 .. value x 1.6 for log parameters, +-0.03 for linear ones)."""
    bases = [dict(b) for b in bases]
    for name in chosen:
        eff = EFFECTS[name]
        if eff.kind == "int":
            continue
        calls = []
        for k in (0, 1):
            v = bases[k][eff.param]
            lo, hi = (v / 1.6, v * 1.6) if eff.kind == "log" else (v - 0.03, v + 0.03)
            others = {p: x for p, x in bases[k].items() if p != eff.param}
            calls.append(("fit", eff, others, fits[k], [], (lo, hi, v)))
        for k, r in enumerate(pool.map(calls)):
            bases[k][eff.param] = r["params"][eff.param]
    return bases


def _final_params(
    pool: _Pool, bases: list[dict], order: list[str], trials: dict[str, Trial], names: list[str]
) -> dict[str, Any]:
    """The reported parameters: the two folds' values combined; integers the folds disagree on are settled by
    the lower gap on all experiments."""
    final = {}
    for name in order:
        eff = EFFECTS[name]
        final[eff.param] = _combine(eff, [bases[0][eff.param], bases[1][eff.param]])
    for name in order:
        eff = EFFECTS[name]
        if eff.kind == "int" and bases[0][eff.param] != bases[1][eff.param]:
            opts = sorted({bases[0][eff.param], bases[1][eff.param]})
            sse = pool.map([("sse", {**final, eff.param: v}, names) for v in opts])
            final[eff.param] = min(zip(opts, sse, strict=True), key=lambda o: energy(o[1], trials, names))[0]
    return final


def _lines(real: Path, trial: Trial) -> Any:
    """The multisine line design of a periodic campaign experiment (None when it cannot be rebuilt)."""
    from .signals import multisine_lines

    m = load_manifest(real)
    if m.get("kind") != "campaign" or trial.period == 0:
        return None
    table = next((d for d in m["spec"].get("experiment", []) if d.get("name") == trial.name), None)
    entry = next((e for e in m["experiments"] if e["name"] == trial.name), None)
    if table is None or entry is None or table.get("signal") != "multisine":
        return None
    return multisine_lines(
        trial.period,
        trial.Ts,
        float(table["f_min"]),
        float(table["f_max"]),
        odd=bool(table.get("odd", True)),
        seed=int(entry["seed"]),
        skip_one_per_group=bool(table.get("skip_one_per_group", True)),
    )


def where_gap(setup: Setup, real: Path, over: dict[str, Any] | None = None) -> dict[str, Any]:
    """Where the gap lies, from :mod:`harness.gap`: per experiment and channel (theta in the rate domain, alpha
    in the angle domain) the residual by time window, frequency band (and, for a multisine, the simulated FRF
    against the measured BLA with its noise and nonlinear-distortion levels), command amplitude, and near
    motion reversals and pot wraps; pooled per channel by :func:`harness.gap.summarise_where`."""
    try:
        from . import gap as gapmod
    except ImportError:  # the where module is optional
        return {"skipped": "harness.gap is not available"}
    from .cosim import Rig

    per: dict[str, dict[str, Any]] = {"theta": {}, "alpha": {}}
    with Rig(Path(setup.plant_fmu), Path(setup.daq_fmu)) as rig:
        for name, tr in setup.trials.items():
            th, al = simulate(rig, setup, tr, over or {})
            lines = _lines(real, tr)
            ms = {"period_samples": tr.period, "lines": lines} if lines is not None else {}
            for ch, yr, ys, dom in (("theta", tr.theta, th, "rate"), ("alpha", tr.alpha, al, "angle")):
                try:
                    per[ch][name] = gapmod.where(
                        tr.t, tr.u, yr, ys, tr.Ts, theta_v=tr.theta_v, theta_deg=tr.theta, domain=dom, **ms
                    )
                except ValueError as err:
                    per[ch][name] = {"error": str(err)}
    out: dict[str, Any] = {"definition": "residual e = y_real - y_sim of the simulation as given (before effects)"}
    for ch in ("theta", "alpha"):
        ok = {k: v for k, v in per[ch].items() if "error" not in v}
        out[ch] = gapmod.summarise_where(ok) if ok else {}
    out["experiments"] = per
    return out
