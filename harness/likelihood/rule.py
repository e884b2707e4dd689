"""Whether a nested effect enters: its likelihood-ratio statistic against its own null distribution.

An effect's parameter is nested in the linear rig at a bound (friction at none, a limit past the records' peak
command), so under the linear rig its likelihood-ratio statistic LR = 2 (logL_effect - logL_linear) is zero half the
time and a chi-square of one degree of freedom the other half (Self and Liang, 1987: the chi-bar-square). Where the
prediction errors are autocorrelated (a quantised reading at rest), the statistic is that law scaled by the
parameter's variance inflation (:func:`harness.likelihood.robust.inflation`, the sandwich's over the information's:
White, 1982). The critical value is that scaled law's quantile at the policy's level, taken no smaller than the
chi-bar-square's own: a sample's autocorrelation only ever widens the law here, and an estimate of it below one is
read as none. Not chi-square on the raw statistic: quantised records make it fire on friction-free twins.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from scipy.stats import chi2

__all__ = ["EffectTest", "Rule"]


@dataclass(frozen=True)
class EffectTest:
    """A nested effect's test: its statistic ``lr`` [2 nats], the ``inflation`` its null law is scaled by, its
    ``p``-value under that law, the ``critical`` value of ``lr`` at the rule's ``level``, and whether it ``enters``
    (``lr`` above ``critical``)."""

    lr: float
    inflation: float
    p: float
    critical: float
    level: float

    @property
    def enters(self) -> bool:
        """The effect enters the model: its statistic beyond the critical value."""
        return self.lr > self.critical

    def to_json(self) -> dict[str, float | bool]:
        """As ``likelihood.json`` and ``diagnosis.json`` hold it, beside the fit's ``logL``, ``k`` and ``n``."""
        return {"lr": self.lr, "p": self.p, "critical": self.critical, "inflation": self.inflation,
                "level": self.level, "enters": self.enters}  # fmt: skip


@dataclass(frozen=True)
class Rule:
    """How an effect is judged: ``level``, the false alarms the rule allows on a rig without the effect (the share
    of friction-free twins on which friction would enter)."""

    level: float = 0.01

    def test(self, lr: float, inflation: float) -> EffectTest:
        """The test of a nested effect whose statistic is ``lr`` [2 nats] and whose parameter's variance inflation is
        ``inflation`` (NaN or below one: read as one).

        Parameters
        ----------
        lr : float
            2 (logL with the effect - logL without) [nats].
        inflation : float
            The effect parameter's sandwich variance over its information's.

        Returns
        -------
        EffectTest
        """
        c = inflation if math.isfinite(inflation) and inflation > 1.0 else 1.0
        p = 0.5 * float(chi2.sf(lr / c, 1)) if lr > 0.0 else 1.0
        critical = c * float(chi2.isf(2.0 * self.level, 1))
        return EffectTest(lr, c, p, critical, self.level)
