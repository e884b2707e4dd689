"""Sensor faults of a record, found at import: a pot's wrap, a jump no hub makes, a channel pinned at a rail or stuck.

Each fault is a :class:`Fault`, said in one line (record, time, size, what was done) and written to the run's
``manifest.json`` (the experiment's ``faults``); nothing is fitted across one silently.

- A jump of theta between two samples that no hub makes: more than :func:`fastest_step_deg` (``WRAP_MARGIN`` times
  the drive's steady speed at the largest command, from the plant FMU's sheet values, over one sample), or half a
  turn. On a pot it is a wrap when it is one turn less the dead band (:func:`is_turn`: the DAQ FMU's
  ``pot_deadband``), seen through the calibration; a wrap is unwrapped by the turn, as the diagnosis and the
  identification read theta (:func:`harness.ident.calibration.theta_deg`). Any other such jump (an encoder's, a pot
  whose span the calibration does not give) cuts the record there into parts, each kept if long enough.
- A run of identical samples of theta or alpha that the channel's noise makes improbable (:func:`same_chance`: fewer
  than ``RUN_CHANCE`` such runs expected by chance in the record) while another channel moves beyond its noise: at
  the channel's extreme a rail (an ADC's clamp, a pot's track end), elsewhere a stuck channel. Its samples are
  masked, not deleted (the experiment's ``masked`` sample ranges): the diagnosis compares none of them
  (:func:`harness.diagnosis.experiments.load_experiments`) and the identification fits around them
  (:func:`harness.ident.identify.prepare`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from ..diagnosis.rigmodel import combos
from ..fmu.modeldesc import source_model

__all__ = [
    "MIN_RUN",
    "MOVE_SIGMAS",
    "RUN_CHANCE",
    "WRAP_MARGIN",
    "Fault",
    "fastest_step_deg",
    "impossible_jumps",
    "is_turn",
    "mask",
    "noise_sigma",
    "pinned_runs",
    "resolution",
    "same_chance",
]

WRAP_MARGIN = 2.0  # the fastest a hub moves: this many times its drive's steady speed at the largest command
RUN_CHANCE = 1e-3  # a run of identical samples is a fault when fewer than this many are expected by chance
MIN_RUN = 3  # ... and it holds at least this many samples
MOVE_SIGMAS = 5.0  # another channel moves over a run when it changes by more than this many times its noise
TURN_DEG = 360.0


@dataclass(frozen=True)
class Fault:
    """One sensor fault of a record: ``kind`` "wrap", "jump", "rail" or "stuck" of ``channel`` (theta or alpha) at
    sample ``row`` (``time_s`` [s]), over ``samples`` samples, its ``size`` in words and what was ``done``."""

    record: str
    channel: str
    kind: str
    row: int
    time_s: float
    samples: int
    size: str
    done: str

    def line(self) -> str:
        """The fault in one line: record, channel, kind, time and row, size, what was done."""
        return (f"fault: {self.record}: {self.channel} {self.kind} at {self.time_s:.4g} s (row {self.row}): "
                f"{self.size}; {self.done}")  # fmt: skip

    def to_dict(self) -> dict[str, object]:
        """JSON-safe, with its line."""
        return {**asdict(self), "line": self.line()}


def fastest_step_deg(Ts: float, u_peak: float) -> float:
    """The most a hub turns in one sample of ``Ts`` [s] [deg]: WRAP_MARGIN times the drive's steady speed (the plant
    FMU's sheet: :func:`harness.diagnosis.rigmodel.combos`) at the larger of the record's peak command ``u_peak`` [V]
    and the DAQ's clamp (``out_limit``), capped at half a turn (a jump beyond it is no motion, whatever the rate)."""
    top = source_model("daq").variables["out_limit"].start
    volts = max(abs(float(u_peak)), float(top) if top is not None else 0.0)
    speed = math.degrees(combos({})["rig.drive_gain"] * volts)
    return min(WRAP_MARGIN * speed * Ts, 0.5 * TURN_DEG)


def impossible_jumps(theta_deg: np.ndarray, limit: float) -> np.ndarray:
    """Samples i where theta [deg] jumps from i to i + 1 by more than ``limit`` [deg]."""
    return np.flatnonzero(np.abs(np.diff(np.asarray(theta_deg, dtype=float))) > limit)


def is_turn(jump: float, limit: float) -> bool:
    """Is a jump [deg] a pot's wrap: one turn less what the hub moved (up to ``limit``) and its dead band (the DAQ
    FMU's ``pot_deadband``, twice over: a rig's may be wider than the twin's), and more than half a turn (what
    :func:`harness.ident.calibration.theta_deg` unwraps)?"""
    band = float(source_model("daq").variables["pot_deadband"].start or 0.0)
    return max(0.5 * TURN_DEG, TURN_DEG - limit - 2.0 * band) < abs(jump) <= TURN_DEG + limit


def noise_sigma(x: np.ndarray) -> float:
    """A channel's white noise [its unit, RMS]: the MAD of its third differences / sqrt(20) (a smooth motion's third
    differences are small, a white noise's have 20 times its variance)."""
    x = np.asarray(x, dtype=float)
    if x.size < 8:
        return 0.0
    d3 = np.diff(x, 3)
    return 1.4826 * float(np.median(np.abs(d3 - np.median(d3)))) / math.sqrt(20.0)


def same_chance(x: np.ndarray, sigma: float) -> float:
    """The chance that a sample of a channel at rest reads the same as the one before: the larger of what its noise
    ``sigma`` allows (its step, a lattice or printed decimal, else the float's spacing, over the spread of the
    difference of two noise samples: q / (2 sqrt(pi) sigma)) and what the record shows (the share of its runs of
    identical samples that last two samples or more: a lattice's or a printed rounding's, which a few runs of a fault
    hardly move); 1 without noise (identical samples then say nothing)."""
    x = np.asarray(x, dtype=float)
    if sigma <= 0 or x.size < 2:
        return 1.0
    model = resolution(x) / (2.0 * math.sqrt(math.pi) * sigma)
    lengths = np.diff(_run_edges(x))
    shown = float(np.mean(lengths >= 2))
    return min(1.0, max(model, shown))


def resolution(x: np.ndarray) -> float:
    """The smallest step between a channel's distinct values (beyond a billionth of their range: a lattice converted
    between units in floats), the float's spacing when it has no two: its ADC's or printed lattice, or for continuous
    values a step far below their noise."""
    levels = np.unique(np.asarray(x, dtype=float))
    span = float(levels[-1] - levels[0]) if levels.size else 0.0
    gaps = np.diff(levels)
    gaps = gaps[gaps > 1e-9 * span]
    return float(gaps.min()) if gaps.size else float(np.spacing(max(abs(span), 1.0)))


def _run_edges(x: np.ndarray) -> np.ndarray:
    """The first sample of every run of identical samples of ``x``, and its length at the end."""
    return np.r_[0, np.flatnonzero(np.diff(x) != 0) + 1, x.size]


def _moves(x: np.ndarray, a: int, b: int) -> bool:
    """Does ``x`` change over samples a..b by more than MOVE_SIGMAS times its noise (and at all)?"""
    span = float(np.ptp(x[a:b]))
    return span > 0 and span > MOVE_SIGMAS * noise_sigma(x)


def pinned_runs(x: np.ndarray, others: list[np.ndarray]) -> list[tuple[str, list[tuple[int, int]]]]:
    """The runs of identical samples of channel ``x`` that its noise makes improbable (n p^(L - 1) < RUN_CHANCE for a
    run of L >= MIN_RUN samples, p :func:`same_chance`) while one of ``others`` moves beyond its noise, as (kind,
    [(first, end), ...]): at the channel's extreme a "rail", with every sample of the record at that value (a rail
    is one value: its short touches too), elsewhere "stuck", a run each."""
    x = np.asarray(x, dtype=float)
    p = same_chance(x, noise_sigma(x))
    if p >= 1.0 or x.size < MIN_RUN:
        return []
    edges = _run_edges(x)
    runs = [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:], strict=True)]
    lo, hi = float(np.min(x)), float(np.max(x))
    out: list[tuple[str, list[tuple[int, int]]]] = []
    rails: list[float] = []
    for a, b in runs:
        if b - a < MIN_RUN or x.size * p ** (b - a - 1) >= RUN_CHANCE or not any(_moves(o, a, b) for o in others):
            continue
        if x[a] not in (lo, hi):
            out.append(("stuck", [(a, b)]))
        elif float(x[a]) not in rails:
            rails.append(float(x[a]))
            out.append(("rail", [(c, d) for c, d in runs if x[c] == x[a]]))
    return sorted(out, key=lambda k: k[1][0])


def mask(n: int, spans: list[tuple[int, int]]) -> np.ndarray:
    """Boolean mask of ``n`` samples, True inside each [first, end) of ``spans``."""
    out = np.zeros(n, dtype=bool)
    for a, b in spans:
        out[a:b] = True
    return out
