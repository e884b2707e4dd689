"""The candidate effects, one table: every fact about an effect in one place.

An :class:`Effect` is one FMU parameter (``plant.coulomb_torque``) with its unit, how it is searched (log or
linear range and grid, or integer values), the secondary parameters freed with it in a joint refit (backlash's
``plant.Jm_share``), the magnitudes the blind test hides in its rigs, and its candidate rule: whether it is
worth fitting against a given simulation and data, and with which range. The diagnoser
(:mod:`harness.diagnosis.search`) and the blind test (:mod:`harness.diagnosis.blindtest`) both read
:data:`EFFECTS`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from .recalibrate import Bound

__all__ = [
    "BY_PARAM",
    "EFFECTS",
    "SECONDARY",
    "SELECTED_BY_SPREAD",
    "VERDICTS",
    "CandidateContext",
    "Effect",
    "candidates",
    "effect_params",
]


@dataclass(frozen=True)
class CandidateContext:
    """What decides whether an effect is worth fitting: the simulation's rig tables (``plant``, ``daq``: the sim
    spec's values, FMU defaults not filled in), the largest |command| of the data [V] and the ADC bits whose
    lattice holds the data (0: none)."""

    plant: Mapping[str, Any]
    daq: Mapping[str, Any]
    top_command_v: float
    adc_bits: int


Rule = Callable[["Effect", CandidateContext], "Effect | None"]
SELECTED_BY_SPREAD = "closed-loop spread"  # how an effect kept by its spread entered (FoundEffect.selected_by)


def always(eff: Effect, _ctx: CandidateContext) -> Effect | None:
    """Always a candidate, with the table's range."""
    return eff


def unless_modelled_modes(eff: Effect, ctx: CandidateContext) -> Effect | None:
    """Not a candidate when the simulation already has two link modes."""
    return None if int(ctx.plant.get("n_modes", 1)) >= 2 else eff


def up_to_the_command(eff: Effect, ctx: CandidateContext) -> Effect | None:
    """The amplifier limit searched up to the largest command of the data (at least twice the lower bound)."""
    return replace(eff, hi=max(ctx.top_command_v, 2.0 * eff.lo))


def other_delays(eff: Effect, ctx: CandidateContext) -> Effect | None:
    """Every delay but the simulation's own."""
    cur = int(ctx.daq.get("delay_samples", 0))
    return replace(eff, values=tuple(v for v in eff.values if v != cur))


def lattice_bits(eff: Effect, ctx: CandidateContext) -> Effect | None:
    """The bits of the ADC lattice found in the data, when there is one the simulation does not have already."""
    if not ctx.adc_bits or int(ctx.daq.get("adc_bits", 0)) == ctx.adc_bits:
        return None
    return replace(eff, values=(ctx.adc_bits,))


@dataclass(frozen=True)
class Effect:
    """A candidate effect: one FMU parameter ``param`` ("plant.coulomb_torque") in ``unit``.

    ``kind`` "log" / "linear" (continuous, search bounds ``lo``..``hi``, coarse ``grid`` points) or "int"
    (``values`` enumerated); ``joint``: it moves the rig's resonances or the drive's phase, which recalibrated linear
    parameters mimic, so it is judged only after a joint refit of them; ``extra``: secondary plant parameters freed
    with it in the joint refit, with their absolute bounds; ``blind``: the magnitudes the blind test hides in its
    rigs (log-uniform, or integers); ``rule``: the candidate rule (the effect with the range to search against a
    simulation and data, or None when it is not worth fitting, for the reason ``skipped``); ``signature``: found by
    its signature in the data (the ADC lattice), not by closing the gap: it is added last with its honest shrink,
    never searched; ``spread``: in a closed loop the effect makes the motion depend on the noise the controller feeds
    back (a gear's play rattles in a phase the noise sets), so no replay reproduces the record sample by sample and a
    fit of its gap takes it to zero: it is tested by its spread (:func:`harness.diagnosis.search.by_spread`) when
    closing the gap left it out.
    """

    name: str
    param: str
    unit: str
    kind: str
    lo: float = 0.0
    hi: float = 0.0
    grid: int = 9
    values: tuple[int, ...] = ()
    joint: bool = False
    extra: Mapping[str, Bound] = field(default_factory=dict, hash=False)
    blind: tuple[float, float] = (0.0, 0.0)
    rule: Rule = always
    skipped: str = "already in the simulation"
    signature: bool = False
    spread: bool = False

    @property
    def params(self) -> set[str]:
        """Every FMU parameter the effect sets: its own and the secondary ones."""
        return {self.param, *self.extra}

    @property
    def continuous(self) -> bool:
        """Fitted by least squares (log or linear); an integer effect is enumerated."""
        return self.kind != "int"

    @property
    def selected_by(self) -> str:
        """How the effect enters the model: by its signature in the data, or by the gap it closes."""
        return "adc lattice in the data" if self.signature else "held-out closure"

    def bound(self, value: float) -> Bound:
        """The search range as a :class:`harness.diagnosis.recalibrate.Bound` about the current ``value``."""
        if self.kind == "log":
            return Bound(self.lo / value, self.hi / value, self.unit, self.name)
        return Bound(self.lo, self.hi, self.unit, self.name, log=False)

    def combine(self, values: Sequence[float]) -> float | int:
        """One value from the two folds' fits: geometric mean (log), mean (linear), the common value (int; when
        the folds disagree the search settles it on all experiments)."""
        if self.kind == "log":
            return float(math.exp(np.mean(np.log(values))))
        if self.kind == "linear":
            return float(np.mean(values))
        return int(values[0])

    def draw_blind(self, rng: np.random.Generator) -> float | int:
        """A magnitude the blind test hides in a rig: an integer in ``blind`` (inclusive), else log-uniform."""
        lo, hi = self.blind
        if self.kind == "int":
            return int(rng.integers(int(lo), int(hi) + 1))
        return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


EFFECTS: dict[str, Effect] = {
    "coulomb_friction": Effect(
        "coulomb_friction",
        "plant.coulomb_torque",
        "N m",
        "log",
        1e-3,
        0.5,
        8,
        # breakaway and Stribeck drop: where a loop stops short of a small reference. The fit starts them at the
        # sim's values clipped into range; a drop narrower than 0.005 rad/s is Karnopp's, and at 0 it has no slope
        extra={
            "plant.stiction_ratio": Bound(1.0, 3.0, "1", "breakaway over Coulomb friction", log=False),
            "plant.stribeck_speed": Bound(0.005, 0.5, "rad/s", "Stribeck speed of the friction drop", log=False),
        },
        blind=(0.02, 0.08),
    ),
    "backlash": Effect(
        "backlash",
        "plant.backlash",
        "rad",
        "log",
        2e-4,
        0.05,
        7,
        extra={
            "plant.Jm_share": Bound(
                0.05, 0.95, "1", "share of the hub inertia on the motor side of the play", log=False
            )
        },
        blind=(0.002, 0.01),
        spread=True,
    ),
    # the blind campaign's 2.5 V square and 3 V PRBS reach beyond these limits
    "saturation": Effect(
        "saturation", "plant.amp_limit", "V", "log", 0.1, 10.0, 7, blind=(1.2, 2.2), rule=up_to_the_command
    ),
    "second_mode": Effect(
        "second_mode", "plant.n_modes", "1", "int", values=(2,), joint=True, blind=(2, 2), rule=unless_modelled_modes
    ),
    "delay": Effect(
        "delay",
        "daq.delay_samples",
        "samples",
        "int",
        values=(0, 1, 2, 3, 4, 5),
        joint=True,
        blind=(1, 3),
        rule=other_delays,
    ),
    "quantization": Effect(
        "quantization",
        "daq.adc_bits",
        "bits",
        "int",
        blind=(8, 12),
        rule=lattice_bits,
        skipped="no ADC lattice in the data",
        signature=True,
    ),
    "gauge_nonlinearity": Effect(
        "gauge_nonlinearity", "daq.gauge_cubic", "1", "linear", -0.3, 0.3, 9, blind=(0.02, 0.1)
    ),
}
VERDICTS = (*EFFECTS, "none", "unexplained")
BY_PARAM: dict[str, Effect] = {e.param: e for e in EFFECTS.values()}
SECONDARY: dict[str, Bound] = {p: b for e in EFFECTS.values() for p, b in e.extra.items()}


def candidates(ctx: CandidateContext) -> list[Effect]:
    """The effects worth fitting against this simulation and data, each with its range (table order)."""
    out = []
    for eff in EFFECTS.values():
        c = eff.rule(eff, ctx)
        if c is not None:
            out.append(c)
    return out


def effect_params(effects: Sequence[str]) -> set[str]:
    """Every FMU parameter the named effects set (their own and their secondary ones)."""
    return set().union(*(EFFECTS[e].params for e in effects))
