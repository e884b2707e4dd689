"""A controller designed on a rig to a lab's specs, then checked by its prediction (``flexjoint design``).

Three methods, each on the rig's linear model as the controller sees it (:func:`harness.linloop.design_model`: the
twin's own parameters, its effects left out):

- ``lqr``: discrete LQR on the rigid hub and the first link mode sampled at the loop's rate,
  Q = diag(q_theta, q_alpha, q_theta_dot, q_alpha_dot) on the angles and rates as read, R = r; implemented as the
  labs implement it, state feedback with the rates by filtered differences (:mod:`harness.rig.controller`);
- ``lqg``: the same weights on the whole model (every mode the twin has, the DAQ's command delay and the gauge's
  delay as states), and a steady-state Kalman filter in current form from theta and alpha (process noise of ``w`` [V
  rms] at the plant's input, the twin's measurement noise per channel), run in the controller FMU (kind 3);
- ``pd``: the labs' four gains (hub and tip, proportional and derivative by filtered differences), the hub's pair
  placed on the rigid drive (natural frequency w_n, damping zeta: k_theta = w_n^2 tau / K, k_theta_dot = (2 zeta w_n
  tau - 1) / K with K, tau the drive's gain and time constant as read), the tip's as ratios of them.

Weights given (``--weights q=160,60,0.25,1;r=1[;w=1]``) are designed as they are. Otherwise a grid of weights (or the
PD's w_n, zeta and tip ratios) is searched: each candidate's linear loop (its velocity filters or estimator, the DAQ's
delays) runs the reference's largest step for its shortest step's time and is measured (:mod:`harness.behaviour`; its
stopping error gets the band that friction and a command offset hold a hub in without integral action, (breakaway
voltage + |u_offset|) / k_theta); of the candidates that meet every spec there, the one with the largest disk margin
(:class:`harness.linloop.Frequencies`) is checked by :func:`harness.prediction.predict` on the twin with its effects,
parameter spread and noise. Where a spec's band misses its limit, that spec's target is tightened by the factor it
missed by and the most robust candidate under the new targets is checked again, up to :data:`ROUNDS` times. When no
candidate meets the specs on the linear model, or none the prediction passes, no design meets them: one line naming
the spec and by how much. The gains are python-control's ``dlqr`` and the Kalman filter's Riccati solution, by
:func:`harness.linloop.dare` (the same numbers, 30x faster over hundreds of candidates).
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from itertools import product
from typing import Any

import numpy as np

from . import spec as specmod
from .behaviour import reference_steps, step_metrics
from .executor import FmuBytes
from .fmu.plant import dead_zone_voltage
from .linloop import (
    DesignModel,
    Frequencies,
    closed_loop,
    design_model,
    kalman_gain,
    lqr_gain,
    plant_params,
    spectral_radius,
    step_response,
)
from .loopspecs import METHODS, LoopSpecs, Weights
from .prediction import Prediction, Reference, predict
from .rig.controller import NX_MAX, Controller, Estimator
from .spec import fmu_value
from .twin import Twin

__all__ = [
    "DEFAULT_SPECS",
    "ROUNDS",
    "Candidate",
    "Design",
    "DesignError",
    "controller_toml",
    "design",
    "linear_metrics",
    "lqg_controller",
    "lqr_controller",
    "pd_controller",
    "slack",
    "stick_band_deg",
    "design_step",
    "twin_spec",
]

Progress = Callable[[str], None]
DEFAULT_SPECS = "settling=1.5,overshoot=5,band=4"  # Quanser's rotary flexible link courseware: 1.5 s in 4 %, 5 %
ROUNDS = 4  # predictions checked at most, each with its targets tightened where the one before missed
RANK_POINTS = 500  # frequencies of the disk margins that rank the candidates (the chosen one's: 2000)
DEFAULT_CUTOFF = 25.0  # Hz: the velocity filters' cutoff when neither the record's controller nor --cutoff gives one
# the search grids: LQR/LQG weights (R = 1) and the LQG's process noise [V rms]; the PD's w_n [rad/s], zeta, tip ratios
Q_THETA = (3.0, 10.0, 30.0, 100.0, 300.0, 1000.0, 3000.0)
Q_ALPHA = (0.0, 10.0, 30.0, 100.0, 300.0, 1000.0)
Q_THETA_DOT = (0.1, 0.3, 1.0, 3.0)
Q_ALPHA_DOT = (0.1, 1.0)
W_PROCESS = (0.3, 1.0, 3.0)
PD_WN = (3.0, 4.5, 6.0, 8.0, 11.0, 15.0, 20.0)
PD_ZETA = (0.6, 0.75, 0.9, 1.05)
PD_TIP = (-2.0, -1.0, -0.5, 0.0, 0.5, 1.0)
PD_TIP_RATE = (-1.0, -0.5, 0.0, 0.5)


class DesignError(ValueError):
    """No design meets the specs: the message names which and by how much."""


# ----------------------------------------------------------------------------------------------- the gains
def lqr_controller(model: DesignModel, wt: Weights, cutoff: float, rate: float) -> Controller:
    """Discrete LQR on the rigid hub and the first mode (``model`` of one mode, its plant's states), implemented as
    state feedback with filtered differences at ``cutoff`` [Hz]."""
    m = model.plant_only()
    k = lqr_gain(m.Phi, m.Gamma, m.weights(wt.q), np.array([[wt.r]])).ravel()
    return Controller(K=[float(v) for v in k], cutoff=cutoff, sample_rate=rate, source="designed")


def pd_controller(model: DesignModel, wn: float, zeta: float, tip: float, tip_rate: float, cutoff: float,
                  rate: float) -> Controller:  # fmt: skip
    """The four gains: the hub's PD placing the rigid drive's poles at ``wn`` [rad/s], ``zeta``; the tip's as ``tip``
    x k_theta and ``tip_rate`` x k_theta_dot."""
    K, tau = model.drive_gain, model.drive_tau
    kp = wn * wn * tau / K
    kd = max(2.0 * zeta * wn * tau - 1.0, 0.0) / K
    return Controller(K=[kp, tip * kp, kd, tip_rate * kd], cutoff=cutoff, sample_rate=rate, source="designed")


def lqg_controller(model: DesignModel, wt: Weights, noise_rad: tuple[float, float], rate: float) -> Controller:
    """LQR on the whole model and its steady-state Kalman filter in current form: process noise ``wt.w`` [V rms]
    at the plant's input (where the DAQ's delayed command enters it), measurement noise ``noise_rad`` (theta, alpha as
    read) [rad rms], at least NOISE_FLOOR_RAD; the reference asks for the hub's angle state, the first estimate is the
    least-norm state that reads the first samples."""
    n = model.n
    if n > NX_MAX:
        raise DesignError(
            f"the LQG's model has {n} states (modes and delays); the controller FMU holds at most {NX_MAX}"
        )
    K = lqr_gain(model.Phi, model.Gamma, model.weights(wt.q), np.array([[wt.r]]))
    G = np.zeros((n, 1))
    G[: model.n_plant] = model.gamma_plant
    w = float(wt.w if wt.w is not None else W_PROCESS[len(W_PROCESS) // 2])
    Rv = np.diag([max(s, NOISE_FLOOR_RAD) ** 2 for s in noise_rad])
    C = model.C
    L = kalman_gain(model.Phi, C, (w * w) * (G @ G.T), Rv)
    Nr = np.zeros(n)
    Nr[0] = 1.0
    est = Estimator(A=model.Phi.tolist(), B=model.Gamma.ravel().tolist(), C=C.tolist(), L=L.tolist(),
                    K=K.ravel().tolist(), N=Nr.tolist(), X0=np.linalg.pinv(C).tolist())  # fmt: skip
    return Controller(kind="lqg", estimator=est, sample_rate=rate, source="designed")


NOISE_FLOOR_RAD = 1e-6  # rad: an ideal sensor's measurement noise in the Kalman filter (its covariance must be > 0)


# ----------------------------------------------------------------------------------------------- the search
LINEAR_METRICS = ("overshoot_pct", "settling_s", "peak_alpha_deg", "peak_u_v", "ring_alpha_deg", "stop_error_deg")


@dataclass(frozen=True, eq=False)
class Candidate:
    """One design of the search: its ``params`` (the weights, or the PD's w_n, zeta and tip ratios), ``controller``
    and its linear loop's ``metrics`` on the test step (None: the linear loop is unstable)."""

    params: dict[str, float]
    controller: Controller
    metrics: dict[str, float] | None = None


def design_step(reference: Reference) -> tuple[float, int]:
    """The step a candidate's linear loop runs: the reference's largest step [deg] for its shortest step's samples."""
    steps = reference_steps(reference.t, reference.ref_deg, reference.initial_deg)
    if not steps:
        raise ValueError(f"the reference ({reference.label}) has no step to design for")
    return max(s.size_deg for s in steps), min(s.end - s.start for s in steps)


def linear_metrics(
    model: DesignModel, c: Controller, size_deg: float, n: int, band_pct: float, dead_zone_v: float = 0.0
) -> dict[str, float] | None:
    """The linear loop's behaviour on a step of ``size_deg`` from rest over ``n`` samples (a step that does not settle:
    an infinite settling time); None when the loop is unstable. Its stopping error is the step's own plus the band
    the rig's friction leaves a loop without integral action: at rest the command is k_theta times the hub's error,
    and the hub sticks while that is under the breakaway voltage ``dead_zone_v`` [V], up to dead_zone_v / k_theta
    (:func:`stick_band_deg`)."""
    loop = closed_loop(model, c)
    if spectral_radius(loop) >= 1.0:
        return None
    ref = np.full(n, size_deg)
    y = step_response(loop, np.radians(ref))
    t = np.arange(n) * model.Ts
    m = step_metrics(t, ref, np.degrees(y[0]), np.degrees(y[1]), y[2], band_pct=band_pct, initial_deg=0.0)[0]
    out = {k: float(getattr(m, k)) for k in LINEAR_METRICS}
    out["settling_s"] = math.inf if math.isnan(out["settling_s"]) else out["settling_s"]
    out["stop_error_deg"] = abs(out["stop_error_deg"]) + stick_band_deg(c, dead_zone_v)
    return out


def stick_band_deg(c: Controller, dead_zone_v: float) -> float:
    """How far from its reference [deg] a hub can stop under ``c`` where a static ``dead_zone_v`` [V] holds it (the
    friction's breakaway voltage plus the magnitude of a command offset): dead_zone_v / k_theta, the proportional gain
    on the hub's angle at rest (an LQG's on its hub state); 0 with an integral (a PID's ki > 0) or without either,
    infinite without a proportional gain."""
    if dead_zone_v <= 0.0 or (c.kind == "pid" and c.ki > 0):
        return 0.0
    k = c.kp if c.kind == "pid" else c.estimator.K[0] if c.estimator is not None else c.K[0]
    return math.degrees(dead_zone_v / k) if k > 0 else math.inf


def slack(metrics: dict[str, float] | None, targets: dict[str, float]) -> float:
    """The least share left under a target: min over the targets of 1 - value / target (-inf: unstable)."""
    if metrics is None:
        return -math.inf
    return min((1.0 - abs(metrics[m]) / t for m, t in targets.items()), default=0.0)


def _grid(method: str) -> Iterator[dict[str, float]]:
    if method == "pd":
        for wn, z, a, b in product(PD_WN, PD_ZETA, PD_TIP, PD_TIP_RATE):
            yield {"wn": wn, "zeta": z, "tip": a, "tip_rate": b}
        return
    for q in product(Q_THETA, Q_ALPHA, Q_THETA_DOT, Q_ALPHA_DOT):
        for w in W_PROCESS if method == "lqg" else (None,):
            yield {"q_theta": q[0], "q_alpha": q[1], "q_theta_dot": q[2], "q_alpha_dot": q[3], "r": 1.0,
                   **({"w": w} if w is not None else {})}  # fmt: skip


def _weights(params: dict[str, float]) -> Weights:
    q = (params["q_theta"], params["q_alpha"], params["q_theta_dot"], params["q_alpha_dot"])
    return Weights(q, params["r"], params.get("w"))


def _controller(method: str, params: dict[str, float], models: dict[str, DesignModel], cutoff: float, rate: float,
                noise_rad: tuple[float, float]) -> Controller:  # fmt: skip
    if method == "pd":
        return pd_controller(models["gain"], params["wn"], params["zeta"], params["tip"], params["tip_rate"], cutoff,
                             rate)  # fmt: skip
    if method == "lqr":
        return lqr_controller(models["gain"], _weights(params), cutoff, rate)
    return lqg_controller(models["full"], _weights(params), noise_rad, rate)


# ----------------------------------------------------------------------------------------------- the design
@dataclass(frozen=True, eq=False)
class Design:
    """A design: ``method``, the ``chosen`` candidate, its linear loop's ``margins`` (:func:`harness.linloop.
    disk_margin`), its ``prediction`` on the twin (judged against ``specs``), the ``rounds`` of the search (targets,
    chosen parameters, predicted worst values), ``searched`` candidates (0: weights given)."""

    method: str
    twin: str
    specs: LoopSpecs
    chosen: Candidate
    margins: dict[str, float]
    prediction: Prediction
    rounds: list[dict[str, Any]] = field(default_factory=list)
    searched: int = 0

    @property
    def controller(self) -> Controller:
        return self.chosen.controller

    @property
    def passed(self) -> bool:
        judged = self.prediction.judged() or {}
        return all(v["met"] for v in judged.values())

    def to_json(self) -> dict[str, Any]:
        """design.json's content."""
        c = self.controller
        gains: dict[str, Any] = {"K": c.K} if c.kind == "state_feedback" else {}
        if c.estimator is not None:
            gains = {"K": c.estimator.K, "L": c.estimator.L, "states": c.estimator.n}
        return {
            "method": self.method,
            "rig": self.twin,
            "sample_rate": 1.0 / self.prediction.reference.Ts,
            "reference": self.prediction.reference.label,
            "controller": c.to_dict(),
            "gains": gains,
            "parameters": self.chosen.params,
            "searched": self.searched,
            "linear": {"metrics": self.chosen.metrics, **self.margins},
            "specs": self.prediction.judged(),
            "band_pct": self.specs.band_pct,
            "passed": self.passed,
            "rounds": self.rounds,
            "prediction": {"file": "prediction.json", "n": self.prediction.n, "seed": self.prediction.seed},
        }


def _missed(judged: dict[str, dict[str, Any]]) -> str:
    """ "settling time <= 1.5 s, predicted up to 2.1 s (1.4x)" for each spec not met."""
    out = []
    for v in judged.values():
        if not v["met"]:
            p = v["predicted"]
            by = f" ({p / v['limit']:.2g}x)" if math.isfinite(p) else " (the loop diverges)"
            out.append(f"{v['spec']}, predicted up to {p:.3g}{by}")
    return "; ".join(out)


def design(
    twin: Twin,
    method: str,
    reference: Reference,
    specs: LoopSpecs | None = None,
    weights: Weights | None = None,
    rate: float | None = None,
    cutoff: float | None = None,
    n: int = 100,
    seed: int = 0,
    strict: bool = True,
    workers: int | None = None,
    scheduler: str | None = None,
    progress: Progress | None = None,
    fmus: dict[str, FmuBytes] | None = None,
) -> Design:
    """Design a controller on a rig to a lab's specs, then check it by its prediction (see the module docstring).

    Parameters
    ----------
    twin : Twin
        The rig (:func:`harness.load_twin`).
    method : str
        ``lqr``, ``lqg`` (a Kalman filter in the controller FMU) or ``pd`` (the labs' four gains).
    reference : Reference
        What the loop is designed and checked for (:func:`harness.reference_from`), at ``rate``.
    specs : LoopSpecs, optional
        The limits to meet; default :data:`DEFAULT_SPECS` (the Quanser courseware's).
    weights : Weights, optional
        lqr/lqg weights to design with as they are (default: searched to meet the specs).
    rate : float, optional
        The controller's sample rate [Hz]; default the twin's.
    cutoff : float, optional
        lqr/pd: the velocity filters' cutoff [Hz].
    n : int
        Members of the prediction that checks each round's design.
    seed : int
        Seed of the prediction's draws.
    strict : bool
        Raise :class:`DesignError` when no design meets the specs on the linear loop; else return the closest.
    workers : int, optional
        Local worker processes of the predictions (None: the default cluster or the enclosing session's).
    scheduler : str, optional
        A Dask scheduler's address to run on instead.
    progress : callable, optional
        Called with one line of text per round.
    fmus : dict of str to bytes, optional
        The built FMUs as bytes; default :func:`harness.build_all`'s.

    Returns
    -------
    Design
        The chosen gains, the linear loop's disk margins, the prediction judged against the specs and the search's
        rounds.

    Raises
    ------
    DesignError
        One line naming each spec no design meets and by how much (``strict``).
    """
    if method not in METHODS:
        raise ValueError(f"--method {method!r} unknown; valid: {', '.join(METHODS)}")
    say = progress or (lambda _m: None)
    specs = specs or LoopSpecs.parse(DEFAULT_SPECS)
    rate = float(rate or twin.sample_rate)
    if abs(rate * reference.Ts - 1.0) > 1e-9:
        raise ValueError(f"the reference is sampled at {1 / reference.Ts:g} Hz, the design at {rate:g} Hz")
    cutoff = float(cutoff or DEFAULT_CUTOFF)
    tables = twin.tables(noise=False)
    models = {"full": design_model(tables, 1.0 / rate), "gain": design_model(tables, 1.0 / rate, n_modes=1)}
    noise_rad = (math.radians(twin.noise_deg["theta"]), math.radians(twin.noise_deg["alpha"]))
    size, steps = design_step(reference)
    dead_zone = dead_zone_voltage(plant_params(tables.plant)) + abs(fmu_value(tables.plant, "flexjoint", "u_offset"))
    grid = [weights.params()] if weights is not None else list(_grid(method))
    cands = []
    for params in grid:
        try:
            c = _controller(method, params, models, cutoff, rate, noise_rad)
        except (ValueError, np.linalg.LinAlgError) as e:
            if weights is not None:
                raise ValueError(f"--weights: {e}") from None
            continue
        cands.append(Candidate(params, c, linear_metrics(models["full"], c, size, steps, specs.band_pct, dead_zone)))
    say(f"{len(cands)} {method} candidates on the linear loop ({size:g} deg steps, {steps} samples)")
    targets = dict(specs.limits)
    rounds: list[dict[str, Any]] = []
    margins: dict[int, float] = {}  # candidate -> its disk margin, measured when it first meets the targets
    ranking = Frequencies(models["full"], RANK_POINTS)
    tried: set[int] = set()
    last: tuple[Candidate, Prediction] | None = None
    for r in range(ROUNDS if weights is None else 1):
        feasible = [i for i, c in enumerate(cands) if slack(c.metrics, targets) >= 0 or weights is not None]
        if not feasible:
            if r > 0:
                break
            closest = max(range(len(cands)), key=lambda i: slack(cands[i].metrics, targets)) if cands else None
            if strict or closest is None or cands[closest].metrics is None:
                raise DesignError(_linear_miss(method, specs, cands[closest] if closest is not None else None))
            feasible = [closest]  # not strict: the closest design, judged by its prediction
        for i in feasible:
            if i not in margins:
                margins[i] = ranking.disk_margin(cands[i].controller)["disk_margin"]
        best = max(feasible, key=lambda i: (margins[i], slack(cands[i].metrics, targets)))
        if best in tried:
            break
        tried.add(best)
        cand = cands[best]
        say(f"round {r + 1}: {cand.params} (disk margin {margins[best]:.3g})")
        pred = predict(twin, cand.controller, reference, n=n, seed=seed, specs=specs, fmus=fmus, workers=workers,
                       scheduler=scheduler)  # fmt: skip
        judged = pred.judged() or {}
        rounds.append({"targets": dict(targets), "parameters": cand.params, "disk_margin": margins[best],
                       "predicted": {m: v["predicted"] for m, v in judged.items()}})  # fmt: skip
        last = (cand, pred)
        if all(v["met"] for v in judged.values()):
            break
        for m, v in judged.items():
            if not v["met"]:
                p = v["predicted"]
                targets[m] *= v["limit"] / p if math.isfinite(p) and p > 0 else 0.5
    assert last is not None
    cand, pred = last
    out = Design(method, twin.name, specs, cand, Frequencies(models["full"]).disk_margin(cand.controller), pred, rounds,
                 0 if weights is not None else len(cands))  # fmt: skip
    if strict and weights is None and not out.passed:
        raise DesignError(f"no {method} design meets the specs on the rig as predicted: {_missed(pred.judged() or {})}")
    return out


def _linear_miss(method: str, specs: LoopSpecs, cand: Candidate | None) -> str:
    """The one line of a search whose every candidate misses a spec on the linear loop: the closest one's misses."""
    if cand is None or cand.metrics is None:
        return f"no {method} design gives a stable loop on this rig"
    got = {m: abs(cand.metrics[m]) for m in specs.limits}
    misses = [f"{specs.describe(m)}: the closest design reaches {got[m]:.3g} ({got[m] / t:.2g}x)"
              for m, t in specs.limits.items() if got[m] > t]  # fmt: skip
    return f"no {method} design meets the specs on the linear loop: " + "; ".join(misses)


# ----------------------------------------------------------------------------------------------- outputs
def _toml_value(v: Any) -> str:
    if isinstance(v, str):
        return f'"{v}"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    return repr(float(v))


def controller_toml(c: Controller, note: str) -> str:
    """A ``[controller]`` table for a spec (and ``--controller-from``), ``note`` as its comment; an LQG's arrays in
    ``[controller.estimator]``, every number at full precision."""
    keys = [k for k in ("kind", "K", "kp", "ki", "kd", "cutoff", "u_limit", "sample_rate", "ref_delay", "alpha_gain")
            if getattr(c, k) is not None]  # fmt: skip
    if c.kind == "lqg":
        keys = [k for k in keys if k not in ("K", "kp", "ki", "kd", "cutoff")]
    elif c.kind == "state_feedback":
        keys = [k for k in keys if k not in ("kp", "ki", "kd")]
    else:
        keys = [k for k in keys if k != "K"]
    lines = [f"# {line}" for line in note.splitlines()] + ["[controller]"]
    lines += [f"{k} = {_toml_value(getattr(c, k))}" for k in keys]
    if c.estimator is not None:
        lines += ["", "[controller.estimator]"]
        lines += [f"{k} = {_toml_value(getattr(c.estimator, k))}" for k in ("A", "B", "C", "L", "K", "N", "X0")]
    return "\n".join(lines) + "\n"


def twin_spec(twin: Twin, c: Controller, reference: Reference, seed: int) -> specmod.Spec:
    """The twin running the loop as a spec (its tables with its own parameters, the data's noise with ``seed``, the
    controller, the reference as a closed-loop experiment: a signal's, else a constant placeholder whose samples
    :func:`harness.ssp.ssp_bytes` replaces by the record's)."""
    tables = twin.tables(seed=seed)
    plant = dict(tables.plant)
    step = float(plant.pop("internal_step", twin.spec.internal_step))
    plant["theta_start"] = math.radians(reference.theta0_deg) / float(twin.overrides.get("sensor.theta_gain", 1.0))
    table = {k: v for k, v in tomllib.loads(controller_toml(c, "")).get("controller", {}).items()}
    kind, params = reference.signal or (
        "constant",
        {"amplitude": 0.0, "duration": reference.ref_deg.size * reference.Ts},
    )
    exp = {"name": "loop", "loop": "closed", "signal": kind, **params}
    raw = {
        "campaign": {"name": f"{twin.name} under {c.kind}", "sample_rate": 1.0 / reference.Ts, "seed": int(seed),
                     "internal_step": step},
        "plant": plant,
        "daq": {k: v for k, v in tables.daq.items() if k != "sample_rate"},
        "controller": table,
        "experiment": [exp],
    }  # fmt: skip
    return specmod.from_dict(raw, "")
