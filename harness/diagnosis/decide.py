"""The verdict by likelihood: the effect a unit's records show, none, or unexplained and why.

The likelihood engine (:func:`harness.likelihood.unit.fit_unit`) has fitted the unit's linear model, its structure
(a second mode, the command's delay) and each nested effect, each judged by :class:`harness.likelihood.rule.Rule`.
The verdict, in this order:

1. ``unexplained`` (``bound``) where the linear fit cannot leave a bound (:attr:`UnitFit.findings`): no effect was
   tried from it;
2. ``unexplained`` (``not_white``) where the best model's residuals (the linear model with every effect that
   entered) are not white: one test, the smallest Ljung-Box p-value over its records and channels times their number
   (Bonferroni), below the rule's ``white`` level;
3. the effect that entered with the largest likelihood-ratio statistic, the others beside it;
4. ``quantization`` where the records sit on an ADC's lattice that the simulation does not have (the data's own
   signature, :func:`harness.diagnosis.noise.adc_lattice`), and no effect entered;
5. ``unexplained`` (``shape``) where the missing force keeps a shape no effect in the library draws (an offset,
   friction unequal each way: :data:`UNDRAWN`);
6. ``none``.
"""

from __future__ import annotations

from dataclasses import dataclass

from ..likelihood.effects import NESTED, PROFILED
from ..likelihood.rule import Rule
from ..likelihood.unit import UnitFit
from .effects import EFFECTS

__all__ = ["LIBRARY", "UNDRAWN", "Decision", "decide"]

# the effects of diagnosis.json's library that the engine fits, nested or by profile (a sensor's low-pass is the
# linear model's, not an effect; quantization is the data's lattice, not a fit)
LIBRARY = tuple(name for name in EFFECTS if name in NESTED or name in PROFILED)
UNDRAWN = ("offset", "asymmetric_friction")  # the missing force's shapes no effect in the library draws


@dataclass(frozen=True)
class Decision:
    """The verdict (one of :data:`harness.diagnosis.effects.VERDICTS`), the ``effects`` found (the strongest first;
    the verdict's where it names one), why it is ``unexplained`` (``bound``, ``not_white``, ``shape``; None
    otherwise) and its ``reason`` in one line."""

    verdict: str
    effects: tuple[str, ...]
    unexplained: str | None
    reason: str

    def to_json(self) -> dict[str, object]:
        """As ``likelihood.json`` holds it."""
        return {"verdict": self.verdict, "effects": list(self.effects), "unexplained": self.unexplained,
                "reason": self.reason}  # fmt: skip


def decide(unit: UnitFit, rule: Rule | None = None) -> Decision:
    """The verdict on a unit's fit (the module docstring's order).

    Parameters
    ----------
    unit : UnitFit
        The likelihood engine's fit of the unit (its ``lattice_bits``: an ADC's lattice the simulation lacks).
    rule : Rule, optional
        The levels (default :class:`harness.likelihood.rule.Rule`'s).

    Returns
    -------
    Decision
    """
    rule = rule or Rule()
    if unit.findings:
        return Decision("unexplained", (), "bound", f"the linear fit cannot leave a bound: {unit.findings[0]}")
    entered = sorted((x for x in unit.effects if x.name in LIBRARY and x.test.enters), key=lambda x: -x.lr)
    bits = unit.lattice_bits
    found = tuple(x.name for x in entered) + (("quantization",) if bits else ())
    white = unit.final_whiteness or unit.whiteness
    ps = [(p, f"{r} {c}") for r, cs in white.items() for c, p in cs.items()]
    if ps:
        p, where = min(ps)
        if p * len(ps) < rule.white:
            model = "the linear model" + (f" with {' and '.join(x.name for x in entered)}" if entered else "")
            return Decision("unexplained", found, "not_white",
                            f"{model} leaves residuals that are not white ({where}: Ljung-Box p {p:.2g}, "
                            f"{len(ps)} record channels)")  # fmt: skip
    if entered:
        top = entered[0]
        return Decision(top.name, found, None, f"{top.name} enters (LR {top.lr:.3g} > {top.test.critical:.3g})")
    if bits:
        why = f"the records sit on a {bits}-bit ADC's lattice the simulation does not have"
        return Decision("quantization", found, None, why)
    if unit.missing_force.shape in UNDRAWN:
        return Decision("unexplained", found, "shape",
                        f"the missing force has a shape no effect draws: {unit.missing_force.words()}")  # fmt: skip
    return Decision("none", found, None, "no effect enters and the residuals are white")
