"""Whether an effect enters: its likelihood-ratio statistic against its own null distribution.

An effect's parameter is nested in the linear rig at a bound (friction at none, a limit past the records' peak
command), so under the linear rig its likelihood-ratio statistic LR = 2 (logL_effect - logL_linear) is zero half the
time and a chi-square of one degree of freedom the other half (Self and Liang, 1987: the chi-bar-square). Where the
prediction errors are autocorrelated (a quantised reading at rest), the statistic is that law scaled by the
parameter's variance inflation (:func:`harness.likelihood.robust.inflation`, the sandwich's over the information's:
White, 1982). The critical value is that scaled law's quantile at the policy's level, taken no smaller than the
chi-bar-square's own: a sample's autocorrelation only ever widens the law here, and an estimate of it below one is
read as none. Not chi-square on the raw statistic: quantised records make it fire on friction-free twins. An effect of
either sign (the gauge's nonlinearity) has its null inside its range: its law is the chi-square of one degree of
freedom, scaled alike.

An integer effect (the command's delay, a second link mode) is not nested: the alternative is another model with as
many free parameters, and the statistic has no chi-square law. Its test (:meth:`Rule.compare`) is Vuong's (1989):
the per-sample differences of the two models' log-likelihood terms, summed, over their long-run standard deviation
(the same HAC estimate, :func:`harness.likelihood.robust.long_run`), a standard normal where neither model is closer
to the records; the alternative enters when it is closer at the level, divided among the settings tried
(Bonferroni).

An effect that passes its test is also fitted on each of the unit's two folds (its records dealt alternately by
their largest command, or a lone record's halves: :func:`harness.likelihood.unit.folds_of`), the linear model beside
it; it enters only where each fold's records gain in likelihood under the effect fitted on the other, summed
(:attr:`EffectTest.held_out`: a fit the records do not share does not carry over). Whether its 95 % intervals on the
folds share a value is said (:meth:`Rule.agree`), not yet required: the friction's intervals are narrower than the
filter's own error (one friction torque held over each 1 ms substep), so that a record's halves can disagree on a
true friction (the validation page).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import brentq
from scipy.stats import chi2, norm

from .robust import long_run

__all__ = ["EffectTest", "Rule"]


@dataclass(frozen=True)
class EffectTest:
    """An effect's test: its statistic ``lr`` [2 nats], the ``inflation`` of its null law by the samples'
    autocorrelation, its ``p``-value under that law, the ``critical`` value of ``lr`` at the rule's ``level``,
    whether it ``enters`` (``lr`` above ``critical`` and, where measured, a positive ``held_out`` gain), the ``law``:
    "chi-bar-square" (a nested effect, its null at a wall), "chi-square" (one whose null lies inside its range) or
    "vuong" (an integer one), whether its intervals on the unit's folds share a value (``agrees``; None: not
    fitted on folds), and its ``held_out`` gain [nats]: the log-likelihood of each fold's records under the effect
    fitted on the other over the linear model fitted there, summed (None: not measured)."""

    lr: float
    inflation: float
    p: float
    critical: float
    level: float
    law: str = "chi-bar-square"
    agrees: bool | None = None
    held_out: float | None = None

    @property
    def enters(self) -> bool:
        """The effect enters the model: its statistic beyond the critical value, and the records it was not fitted to
        gain in likelihood where that was measured (``agrees`` is said beside it, not required: the module docstring
        says why)."""
        return self.lr > self.critical and (self.held_out is None or self.held_out > 0.0)

    def to_json(self) -> dict[str, float | bool | str | None]:
        """As ``likelihood.json`` and ``diagnosis.json`` hold it, beside the fit's ``logL``, ``k`` and ``n``."""
        return {"lr": self.lr, "p": self.p, "critical": self.critical, "inflation": self.inflation,
                "level": self.level, "enters": self.enters, "law": self.law, "agrees": self.agrees,
                "held_out": self.held_out}  # fmt: skip


@dataclass(frozen=True)
class Rule:
    """How an effect is judged: ``level``, the false alarms the rule allows on a rig without the effect (the share
    of friction-free twins on which friction would enter); ``white``, the level of the one test of whether the best
    model's residuals are white (:func:`harness.diagnosis.decide.decide`: the smallest of its records' and channels'
    Ljung-Box p-values, Bonferroni over them)."""

    level: float = 0.01
    white: float = 0.01

    def test(self, lr: float, inflation: float, interior: bool | Sequence[bool] = False) -> EffectTest:
        """The test of a nested effect whose statistic is ``lr`` [2 nats] and whose parameter's variance inflation is
        ``inflation`` (NaN or below one: read as one); an ``interior`` null (an effect of either sign, none inside its
        range) takes the chi-square of one degree of freedom, not the chi-bar-square. An effect of several parameters
        gives one flag each: with k of them at a wall and m inside, the law is the mixture of chi-squares of m + j
        degrees of freedom, j of the k walls left (binomial weights C(k, j) / 2^k; Self and Liang's case of
        independent parameters).

        Parameters
        ----------
        lr : float
            2 (logL with the effect - logL without) [nats].
        inflation : float
            The effect parameter's sandwich variance over its information's.
        interior : bool or sequence of bool
            The effect's null lies inside its range, not at a wall (one flag per parameter).

        Returns
        -------
        EffectTest
        """
        c = inflation if math.isfinite(inflation) and inflation > 1.0 else 1.0
        flags = (interior,) if isinstance(interior, bool) else tuple(interior)
        k, m = flags.count(False), flags.count(True)
        weights = [(math.comb(k, j) / 2**k, m + j) for j in range(k + 1)]  # (weight, degrees of freedom)

        def sf(x: float) -> float:
            return sum(w * float(chi2.sf(x, dof)) for w, dof in weights if dof > 0) if x > 0.0 else 1.0

        p = sf(lr / c)
        top = float(chi2.isf(self.level / 2**k, k + m))  # the law's tail lies below the largest chi-square's
        critical = c * float(brentq(lambda x: sf(x) - self.level, 1e-9, top + 1.0))
        law = "chi-square" if k == 0 else "chi-bar-square"
        return EffectTest(lr, c, p, critical, self.level, law)

    @staticmethod
    def agree(test: EffectTest, intervals: Sequence[tuple[float, float]]) -> EffectTest:
        """``test`` with whether the effect's 95 % ``intervals`` on the unit's folds (its records, or a record's
        halves) share a value: one size on every fold, not one that only the unit's whole fits."""
        lo = max(a for a, _ in intervals)
        hi = min(b for _, b in intervals)
        return replace(test, agrees=bool(lo <= hi))

    def compare(self, gain: np.ndarray, record: np.ndarray, sample: np.ndarray, settings: int = 1) -> EffectTest:
        """Vuong's test of an integer effect's best setting against the null model.

        Parameters
        ----------
        gain : ndarray
            Per reading, the alternative's log-likelihood term minus the null's [nats].
        record, sample : ndarray of int
            Each reading's record and sample (:class:`harness.likelihood.fit.Innovations`).
        settings : int
            The settings the best was chosen from (the level is divided among them).

        Returns
        -------
        EffectTest
            ``lr`` 2 sum(gain); ``critical`` the statistic at which the sum reaches the normal's quantile times its
            long-run standard deviation; ``inflation`` the long-run variance over the variance at lag 0.
        """
        total = float(np.sum(gain))
        run = long_run(np.asarray(gain, dtype=float)[:, None], record, sample)
        sd = float(np.sqrt(max(run.cov[0, 0], 0.0)))
        grown = run.cov[0, 0] / run.lag0[0, 0] if run.lag0[0, 0] > 0.0 else 1.0
        if sd == 0.0:  # the two models give the same terms: nothing to tell
            return EffectTest(2.0 * total, float(grown), 1.0, math.inf, self.level, "vuong")
        p = min(1.0, settings * float(norm.sf(total / sd)))
        critical = 2.0 * float(norm.isf(self.level / settings)) * sd
        return EffectTest(2.0 * total, float(grown), p, critical, self.level, "vuong")
