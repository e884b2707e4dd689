"""The rule's false alarms and power, measured on blind twins run through the FMUs.

A case is a 5 s record at 500 Hz of the textbook rig (two link modes) through the plant, DAQ and (closed loop)
controller FMUs: open loop a random +-0.8 V square, closed loop the state feedback of ``specs/closed_loop.toml`` on
a +-20 deg square reference; 2 mV of noise on both readings through an ADC of 8, 10 or 12 bits, read as a user's
calibrated degrees. Its seed draws the command and the noise, and picks the loop (even: closed) and the ADC (8, 10,
12 bits in turn). Each case is fitted as a unit's records are (:func:`harness.likelihood.fit.fit`: the linear
parameters from 10 % off with the noise from the data, then Coulomb friction nested from inside and from its null,
the better kept) and judged by the :class:`harness.likelihood.rule.Rule`. On friction-free cases the share on which
friction enters is the rule's false alarms; with Coulomb friction, the share on which it enters is its power, and
the share sized within 25 % its accuracy. A case whose hub leaves the pot's track is skipped: its readings wrap.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np

from ..diagnosis import rigmodel
from ..executor import Executor, worker_rig
from ..fmu.build import build_all
from ..fmu.modeldesc import bundled_model
from ..rig.controller import Controller
from . import fit as mlfit
from .record import Record
from .rule import EffectTest, Rule

__all__ = ["Case", "CaseResult", "RuleCalibration", "calibrate_rule", "judge_case", "twin_record"]

PLANT = {"n_modes": 2}  # the textbook rig with its second mode
TS, SAMPLES, NOISE_V = 2e-3, 2500, 0.002
GAINS = (9.231, -18.769, 1.203, -0.041)  # specs/closed_loop.toml's state feedback
TRACK_DEG = 170.0  # a hub beyond this wraps the pot: the case is skipped
SIZED = 0.25  # a friction sized within this share of the twin's counts as sized


@dataclass(frozen=True)
class Case:
    """A blind twin: its ``seed``, whether its loop is ``closed``, its ADC's ``bits`` and its Coulomb friction
    ``coulomb`` [N m]."""

    seed: int
    closed: bool
    bits: int
    coulomb: float

    @classmethod
    def of_seed(cls, seed: int, coulomb: float) -> Case:
        """The case of ``seed``: closed loop on even seeds, the ADC's bits 8, 10, 12 in turn."""
        return cls(seed, seed % 2 == 0, (8, 10, 12)[seed % 3], coulomb)


@dataclass(frozen=True)
class CaseResult:
    """A case judged: the friction's ``test`` and its fitted value ``fitted`` [N m] (None where ``skipped`` says
    why the case was not fitted)."""

    case: Case
    test: EffectTest | None
    fitted: float | None
    skipped: str = ""


@cache
def _daq(name: str) -> float:
    """The DAQ FMU's default of parameter ``name``."""
    return float(bundled_model("daq").parameters()[name].start or 0.0)


def _readings(out: dict[str, np.ndarray]) -> np.ndarray:
    """The DAQ's volts as a user's calibrated degrees (the pot's and the gauge's own gains and offsets)."""
    th = (out["theta_v"] - _daq("pot_offset")) * _daq("pot_gain")
    al = (out["alpha_v"] - _daq("gauge_offset")) * _daq("gauge_gain")
    return np.column_stack([th, al])


def twin_record(case: Case, fmus: dict[str, Any] | None = None) -> Record:
    """The case's record (:mod:`module docstring <harness.likelihood.calibrate>`), its readings on the ADC's lattice
    in degrees; ``fmus`` the built FMUs (default :func:`harness.fmu.build.build_all`'s)."""
    fmus = fmus or build_all()
    rig = worker_rig({k: fmus[k] for k in ("flexjoint", "daq", "controller")})
    rng = np.random.default_rng(case.seed)
    daq = {"noise_theta": NOISE_V, "noise_alpha": NOISE_V, "seed": case.seed, "adc_bits": case.bits}
    plant = {**PLANT, "coulomb_torque": case.coulomb}
    if case.closed:
        ref = np.radians(np.where(np.arange(SAMPLES) * TS % 2.0 < 1.0, 20.0, -20.0))
        ctrl = Controller(K=list(GAINS), cutoff=15.0).fmu_parameters(1 / TS)
        out = rig.run_closed(ref, TS, ctrl, plant=plant, daq=daq)
    else:
        u = 0.8 * np.where(np.cumsum(rng.random(SAMPLES) < 5.0 * TS) % 2 == 0, 1.0, -1.0)
        out = rig.run(u, TS, plant=plant, daq=daq)
    lsb = 2.0 * _daq("adc_range") / 2**case.bits
    step = (lsb * _daq("pot_gain"), lsb * abs(_daq("gauge_gain")))
    return Record(f"seed{case.seed}", TS, out["u"], _readings(out), np.ones((SAMPLES, 2), bool), step)


def judge_case(case: Case, rule: Rule, fmus: dict[str, Any] | None = None) -> CaseResult:
    """Fit the case's twin as a unit's records are, friction nested, and judge the friction by ``rule``."""
    rec = twin_record(case, fmus)
    if np.abs(rec.y[:, 0]).max() > TRACK_DEG:
        return CaseResult(case, None, None, "the hub leaves the pot's track")
    truth = rigmodel.combos(PLANT) | {"plant.Ks": rigmodel.plant_value(PLANT, "Ks"),
                                      "plant.zeta_link": rigmodel.plant_value(PLANT, "zeta_link")}  # fmt: skip
    noise = mlfit.noise_start([rec])
    fixed = {"sensor.theta_gain": 1.0, "sensor.alpha_gauge_gain": 1.0}
    nominal = truth | noise | {"plant.coulomb_torque": 0.013}  # the torque of 0.1 V
    lin = mlfit.fit(PLANT, [rec], {k: 1.1 * v for k, v in truth.items()} | noise, fixed=fixed, nominal=nominal)
    fits = [mlfit.fit(PLANT, [rec], lin.values() | {"plant.coulomb_torque": begin}, fixed=fixed, nominal=nominal)
            for begin in (0.005, 0.0)]  # fmt: skip
    best = max(fits, key=lambda f: f.loglik)
    e = best.estimates["plant.coulomb_torque"]
    return CaseResult(case, rule.test(2.0 * (best.loglik - lin.loglik), e.inflation), e.value)


@dataclass(frozen=True)
class RuleCalibration:
    """The rule on friction-free cases (``null``) and on cases with friction (``effect``)."""

    rule: Rule
    null: tuple[CaseResult, ...]
    effect: tuple[CaseResult, ...]

    @staticmethod
    def _judged(results: tuple[CaseResult, ...]) -> list[CaseResult]:
        return [r for r in results if r.test is not None]

    @property
    def false_alarms(self) -> float:
        """The share of judged friction-free cases on which friction entered."""
        judged = self._judged(self.null)
        return sum(r.test.enters for r in judged if r.test) / max(len(judged), 1)

    @property
    def power(self) -> float:
        """The share of judged cases with friction on which it entered."""
        judged = self._judged(self.effect)
        return sum(r.test.enters for r in judged if r.test) / max(len(judged), 1)

    @property
    def sized(self) -> float:
        """The share of judged cases with friction on which it entered sized within :data:`SIZED` of the twin's."""
        judged = self._judged(self.effect)
        ok = [r for r in judged if r.test and r.test.enters and r.fitted is not None
              and abs(r.fitted / r.case.coulomb - 1.0) <= SIZED]  # fmt: skip
        return len(ok) / max(len(judged), 1)

    def to_json(self) -> dict[str, Any]:
        """The shares, the cases' counts and the largest statistic on a friction-free case."""
        null_lr = [r.test.lr for r in self._judged(self.null) if r.test]
        return {
            "level": self.rule.level,
            "null": {"cases": len(self.null), "judged": len(null_lr), "false_alarms": self.false_alarms,
                     "largest_lr": max(null_lr, default=float("nan"))},
            "effect": {"cases": len(self.effect), "judged": len(self._judged(self.effect)), "power": self.power,
                       "sized_within": SIZED, "sized": self.sized,
                       "coulomb": self.effect[0].case.coulomb if self.effect else None},
        }  # fmt: skip


def calibrate_rule(
    n: int = 100,
    seed: int = 0,
    coulomb: float = 0.01,
    rule: Rule | None = None,
    workers: int | None = None,
    progress: Callable[[str], None] | None = None,
) -> RuleCalibration:
    """The rule's false alarms on ``n`` friction-free cases and its power on ``n`` with Coulomb friction
    ``coulomb`` [N m], seeds ``seed`` to ``seed + n - 1`` each, on an :class:`harness.executor.Executor` of
    ``workers``.

    Parameters
    ----------
    n : int
        Cases of each kind.
    seed : int
        The first case's seed.
    coulomb : float
        The friction of the cases with an effect [N m].
    rule : Rule, optional
        The rule judged (default :class:`harness.likelihood.rule.Rule`).
    workers : int, optional
        The executor's workers (default the machine's).
    progress : callable, optional
        Told of each case done.

    Returns
    -------
    RuleCalibration
    """
    rule = rule or Rule()
    cases = [Case.of_seed(s, c) for c in (0.0, coulomb) for s in range(seed, seed + n)]
    fmus = build_all()
    with Executor(workers, progress=progress) as ex:
        results = ex.map(judge_case, cases, rule, fmus, desc="rule case")
    return RuleCalibration(rule, tuple(results[:n]), tuple(results[n:]))
