"""The search for the effects behind the gap, by one rule for every record.

Every model is fitted on one fold and scored on the other (2-fold cross-fitting), and every decision is taken on
one held-out score (:class:`Score`): window by window, how far the record's gap to the replays is from the spread
they predict there (:func:`harness.diagnosis.simulation.evaluate`: a closed loop's replays with other noise draws,
the noise an open loop's record carries). The thresholds are those of :class:`Policy`, each used once.

1. The linear model (:data:`harness.diagnosis.recalibrate.LINEAR`, the command offset, each closed-loop record's
   gauge offset): recalibrated on each fold from a grid of the sheet's values, and again from the other fold's fit,
   the lower cost kept (:func:`recalibrated`).
2. Rounds of forward selection (:func:`forward_selection`): every candidate effect not chosen yet refitted jointly
   with the linear parameters and the effects chosen (:func:`fit_models`), from the best of its values on the
   current rig and from the other fold's refit; an effect that a loop does not reproduce sample by sample (a gear's
   play, ``Effect.spread``) sized by the score itself on the fitted fold. The candidate that lowers the held-out
   score most enters when it pays (:func:`pays`: it closes ``Policy.min_gain`` of the excess left above its own
   floor); where none does, every pair of those that lower it is refitted together.
3. Backward elimination (:func:`eliminate`): an effect stays while it pays; an effect is kept only where its
   replays' behaviour bands describe the records' as well as without it (:func:`bands_worse`).
4. Verdict (:func:`verdict`).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from . import recalibrate as recal
from .bands import bands, closed_steps, parameter_draws
from .effects import BY_PARAM, EFFECTS, SECONDARY, SELECTED_BY_SPREAD, Effect, effect_params
from .experiments import CHANNELS, RigExperiment
from .result import (
    Band,
    Candidate,
    Decomposition,
    FittedParameter,
    FoundEffect,
    Gap,
    HeldOutGap,
    RecordBehaviour,
    Step,
)
from .rigmodel import COMBOS, plant_value, to_plant
from .simulation import (
    ALPHA_OFFSET,
    LINK_START,
    LOOP_NOISE_SEEDS,
    SSE,
    channel_fits,
    fit_pct,
    gap_summary,
    mean_squared_gap,
)
from .tasks import RECAL_NFEV, Behaviour, Cost, Evaluate, FitResult, Grid, Pool, Recalibrate, Refit, mean_effective

__all__ = [
    "POLICY",
    "Model",
    "Policy",
    "Score",
    "SearchResult",
    "against_record",
    "eliminate",
    "fit_models",
    "forward_selection",
    "importance",
    "search",
    "share_text",
]

Progress = Callable[[str], None]
Overrides = dict[str, Any]


@dataclass(frozen=True)
class Policy:
    """How the diagnosis decides, the same for every record. The score (:class:`Score`) of a model is its held-out
    effective gap: window by window, the record's gap to the replays beside the spread they predict there (an open
    loop's noise; a closed loop's, from replays with other noise draws, each one realisation: the record beside
    their mean, the spread their variance), as
    the profile Gaussian likelihood of the record under that spread plus a model-error variance, given as the mean
    squared gap a replay without spread would need to score the same
    (:func:`harness.diagnosis.simulation.effective_gap`), mean over experiments and channels. Without spread it is
    the mean squared gap; a spread where the record's gap lies lowers it. The floor is what a right model leaves: the
    score of the replay against another noise draw of itself.

    Four thresholds, each applied in one place:

    - ``none_level``: no gap beyond noise when the linear model's held-out score is within this ratio of the floor's,
      as a gap (its square as a mean squared gap, :func:`verdict`); a model within it of its own floor covers what
      a model without its effect left (:meth:`CrossFit.share`);
    - ``min_gain``: an effect (or a pair) enters when it closes this share of the held-out score left above the
      floor of the model with it, and stays while it still does (:func:`pays`);
    - ``explained``: the verdict names an effect when the effects close this share of what the linear model left
      above the floor (else ``unexplained``, :func:`verdict`);
    - ``resolution``: a gap below this share of a record's RMS (a fit of 99.9 %) is no sensor calibration's to
      tell: no window's spread is taken below it.

    Settings, not thresholds: ``draws``, the noise draws beside a closed-loop replay's own that make its spread;
    ``sizing_draws``, those beside each value of an effect sized by that score (a play in a closed loop: with fewer,
    the score's minimum lies at a smaller play);
    ``behaviour_draws``, the replays whose behaviour makes its band."""

    none_level: float = 1.25
    min_gain: float = 0.25
    explained: float = 0.5
    resolution: float = 1e-3
    draws: int = 2
    sizing_draws: int = 4
    behaviour_draws: int = 39

    def meaning(self) -> str:
        """The rule in one paragraph, for diagnosis.json."""
        return (
            "score = held-out effective gap: the record's gap to the replay beside the replays' own spread, window by "
            "window (spread: an open loop's noise; a closed loop's replays with other noise draws, the record beside "
            "their mean), as the profile "
            "Gaussian likelihood of the record under that spread and a model-error variance, given as the mean "
            "squared gap a replay without spread would need to score the same, mean over experiments and channels; "
            "floor: the score of a replay against another noise draw of itself; none: the recalibrated linear "
            f"model's score within none_level ({self.none_level:g}) of the floor's as a gap; an effect (or a pair, "
            f"where no single one does) enters when it closes >= min_gain ({self.min_gain:g}) of the score left "
            "above the floor of the model with it (all of it when that model is within none_level of its own floor "
            "and scores better) and stays while it still does, and only where its replays' behaviour bands (their "
            "interval scores) are no worse than without it; the verdict names the effect whose removal from the rig "
            "fitted on every record reopens most of its score there when "
            "the effects close >= "
            f"explained ({self.explained:g}) of what the linear model left above the floor, else unexplained; no "
            "spread below "
            f"resolution ({self.resolution:g}) x the record's RMS"
        )


POLICY = Policy()


@dataclass(frozen=True)
class Score:
    """A model's held-out score (both folds' fits, each experiment scored by the fit not made on it): ``excess``
    the effective gap (what decides, see :class:`Policy`), ``spread`` its replays' own spread in units of each
    record's variance (mean over experiments and channels), ``msg`` the mean squared gap E
    (fit % = 100 (1 - sqrt(E))), ``sse`` the squared residuals per experiment and channel [deg^2], and the gauge
    offset [deg] each closed-loop record was replayed with (fitted on it where the fit was not)."""

    excess: float
    spread: float
    msg: float
    sse: SSE
    offsets: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class Model:
    """A model of the rig: the ``effects`` on top of the linear model, its fit on each fold (fold A's, scored on B,
    then B's) and its held-out ``score``; ``how`` it was fitted; ``floor``: what it leaves if it is right, its score
    against another noise draw of itself (:func:`floored`)."""

    effects: tuple[str, ...]
    fits: tuple[FitResult, FitResult]
    score: Score
    how: str = "jointly with the linear parameters"
    floor: Score | None = None

    def params(self, k: int) -> Overrides:
        """Fold k's fitted overrides."""
        return dict(self.fits[k].params)


@dataclass
class CrossFit:
    """The 2-fold cross-fit the search scores on: fit k is made on ``fits[k]`` and scored on ``helds[k]``."""

    pool: Pool
    experiments: dict[str, RigExperiment]
    names: list[str]
    fits: list[list[str]]
    helds: list[list[str]]
    policy: Policy
    effects: dict[str, Effect]

    @property
    def all_closed(self) -> bool:
        """Is every experiment a closed-loop replay?"""
        return all(x.replay == "closed" for x in self.experiments.values())

    def _merge(self, parts: list[dict[str, Any]]) -> Score:
        ev = {n: e for part in parts for n, e in part.items()}
        spread, msg = [], []
        for n, e in ev.items():
            x = self.experiments[n]
            for c in CHANNELS:
                if x.moves(c):
                    spread.append(e.spread[c] / x.sst[c])
                    msg.append(e.sse[c] / x.sst[c])
        closed = [n for n in ev if self.experiments[n].replay == "closed"]
        offsets = {self.experiments[n].record: ev[n].offset for n in closed}
        return Score(
            excess=mean_effective(ev, self.experiments),
            spread=float(np.mean(spread)) if spread else math.nan,
            msg=float(np.mean(msg)) if msg else math.nan,
            sse={n: dict(e.sse) for n, e in ev.items()},
            offsets=offsets,
        )

    @property
    def seeds(self) -> tuple[int, ...]:
        """The noise draws a closed loop's replay is averaged over where it plays or sticks where the noise decides
        (``Effect.spread``): as many as beside each of its values where it is sized (``Policy.sizing_draws``)."""
        return LOOP_NOISE_SEEDS[: self.policy.sizing_draws]

    def draws(self, fit: FitResult | Overrides) -> tuple[Overrides, ...]:
        """``Policy.draws`` draws of a fold's fit from its covariance (its overrides each time where it has none)."""
        if isinstance(fit, FitResult):
            return tuple(parameter_draws(fit.params, fit.names, fit.log, fit.cov, self.policy.draws + 1, 2,
                                         fit.ranges)[1:])  # fmt: skip
        return tuple(dict(fit) for _ in range(self.policy.draws))

    def scores(self, folds: Sequence[Sequence[FitResult | Overrides]], pseudo: bool = False) -> list[Score]:
        """The held-out score of each model given as its two folds' fits (or overrides), in one map."""
        p = self.policy
        tasks = [Evaluate(_params(fs[k]), tuple(self.helds[k]), self.draws(fs[k]), p.resolution, pseudo)
                 for fs in folds for k in (0, 1)]  # fmt: skip
        res = self.pool.map(tasks)
        return [self._merge(res[2 * i : 2 * i + 2]) for i in range(len(folds))]

    def on_every_record(self, overs: Sequence[Overrides]) -> list[Score]:
        """The score of each of ``overs`` on every record (not held out: a rig fitted on all of them), in one map."""
        p = self.policy
        res = self.pool.map([Evaluate(o, tuple(self.names), self.draws(o), p.resolution) for o in overs])
        return [self._merge([r]) for r in res]

    def share(self, before: Score, after: Score, floor: Score) -> float:
        """Share of ``before``'s excess above ``floor`` (the floor of the model scored ``after``: what it leaves if
        it is right) that ``after`` closes (may be negative). Where ``before`` is already within that floor (a
        model whose own spread covers the gap before it), all of it when ``after`` scores better and is within
        ``none_level`` of its floor, none otherwise."""
        room = before.excess - floor.excess
        if room > 0:
            return (before.excess - after.excess) / room
        within = after.excess < before.excess and after.excess <= self.policy.none_level**2 * floor.excess
        return 1.0 if within else 0.0


@dataclass
class SearchResult:
    """What the search finds: verdict, effects, candidates, rounds, gap, parameter table, whether recalibration
    was applied, the final overrides (all experiments) and their covariance, the linear parameters recalibration
    alone fitted ({} when not applied), the floor's and the base model's scores, and each closed-loop record's
    behaviour beside its replays' (the final rig, with draws of its parameters and of the noise), and each record's
    gauge zero [deg] in the final rig's replay (fitted, or an open loop's least squares)."""

    verdict: str
    effects: list[FoundEffect]
    candidates: list[Candidate]
    rounds: list[list[dict[str, Any]]]
    gap: Gap
    parameters: dict[str, FittedParameter]
    recalibration_applied: bool
    final: Overrides
    final_fit: FitResult
    recalibrated: Overrides
    floor: Score
    base: Score
    models: dict[str, Model]
    behaviour: dict[str, RecordBehaviour]
    gauge_zeros: dict[str, float]


def floored(cf: CrossFit, model: Model) -> Model:
    """``model`` with its floor: its held-out score against records it would make itself, another noise draw
    (:func:`harness.diagnosis.simulation.evaluate`'s ``pseudo``): what it leaves if it is right, its own spread
    included (a loop that sticks where the noise decides leaves much more than one that does not)."""
    (out,) = floored_all(cf, [model])
    return out


def floored_all(cf: CrossFit, models: Sequence[Model]) -> list[Model]:
    """:func:`floored` of each of ``models``, in one map."""
    missing = [i for i, m in enumerate(models) if m.floor is None]
    floors = cf.scores([list(models[i].fits) for i in missing], pseudo=True) if missing else []
    out = list(models)
    for i, f in zip(missing, floors, strict=True):
        out[i] = replace(out[i], floor=f)
    return out


def _params(fit: FitResult | Overrides) -> Overrides:
    return dict(fit.params) if isinstance(fit, FitResult) else dict(fit)


def shrink_pct(before: float, after: float) -> float:
    """How much a gap fell [%]: 100 (1 - after / before)."""
    return 100.0 * (1.0 - after / before) if before > 0 else 0.0


def share_text(pct: float) -> str:
    """A share of the excess closed [%] as a person reads it: beyond 100 % the excess went below the floor
    ("100 %, below the noise floor", not "100.5 %"); below -100 % the excess grew more than twofold ("widens it
    410x", not "-40951.1 %")."""
    if pct > 100.0:
        return "100 %, below the noise floor"
    if pct < -100.0:
        return f"widens it {1.0 - pct / 100.0:.0f}x"
    return f"{pct:.1f} %"


def combine(prm: str, values: Sequence[float]) -> float:
    """One value of a parameter from the two folds' fits: an effect's own rule (:meth:`Effect.combine`), the
    geometric mean on a log scale, the mean otherwise (an offset)."""
    if prm in BY_PARAM:
        return BY_PARAM[prm].combine(values)
    log = recal.LINEAR[prm].log if prm in recal.LINEAR else min(values) > 0
    return float(math.exp(np.mean(np.log(values)))) if log else float(np.mean(values))


def _free(effects: Sequence[str], cf: CrossFit) -> tuple[str, ...]:
    """The effect parameters a joint refit moves: the continuous ones, but those sized by their spread where every
    replay is a closed loop (``Effect.spread``)."""
    return tuple(cf.effects[e].param for e in effects
                 if cf.effects[e].continuous and not (cf.effects[e].spread and cf.all_closed))  # fmt: skip


def _without(over: Overrides, effects: Sequence[str]) -> Overrides:
    """Overrides with the effects' parameters (their secondary ones too) removed."""
    drop = effect_params(effects)
    return {k: v for k, v in over.items() if k not in drop}


def recalibrated(cf: CrossFit, say: Progress) -> tuple[Model, Score]:
    """The linear model on each fold (:class:`harness.diagnosis.tasks.Recalibrate`), then each fold again from the
    other fold's fit (the lower cost kept: least squares from a fold's own best grid point can stop in another
    basin); and the simulation as given. Returns (the linear model, the score as given)."""
    (*rec,) = cf.pool.map([Recalibrate(tuple(cf.fits[k])) for k in (0, 1)])
    again = cf.pool.map([Refit(_linear_of(rec[1 - k].params), (), tuple(cf.fits[k]), RECAL_NFEV) for k in (0, 1)])
    fits = tuple(min(rec[k], again[k], key=lambda r: r.cost) for k in (0, 1))
    linear, given = cf.scores([list(fits), [{}, {}]])
    say(f"gap as given: fit {fit_pct(given.msg):.2f} %; recalibrated: {fit_pct(linear.msg):.2f} %")
    return Model((), (fits[0], fits[1]), linear, "recalibration"), given


def _linear_of(over: Overrides) -> Overrides:
    return {k: v for k, v in over.items() if k in recal.LINEAR}


def fit_models(
    cf: CrossFit, current: Model, adds: list[tuple[str, ...]], hints: dict[str, Model] | None = None
) -> list[Model]:
    """``current`` with each group of effects of ``adds`` added, refitted on each fold jointly with the linear
    parameters and the effects of ``current``, and scored held out. Each effect starts at the best of its values
    (:class:`harness.diagnosis.tasks.Grid`) on the current fold's rig, and at its best on the sheet's linear rig (the
    fitted linear parameters may have bent to mimic it: a limit as a heavy, damped hub), or at its fit in ``hints``
    (its model alone); each fold is refitted from every start and again from the other fold's refit where that costs
    less; the lowest cost kept. An effect that a closed loop does not reproduce sample by sample (``Effect.spread``)
    is sized instead by the score on the current fold's rig (its values replayed beside their spread), held in the
    refit of the linear parameters and sized again on the refitted rig, from that start only: the derivative-free
    refit from the sheet's linear parameters spends its budget far from them."""
    hints = hints or {}
    table, p = cf.effects, cf.policy
    sized = [{e for e in group if table[e].spread and cf.all_closed} for group in adds]
    starts: list[list[list[Overrides]]] = [[[current.params(k)] for k in (0, 1)] for _ in adds]
    grid_tasks, grid_slots = [], []
    for i, group in enumerate(adds):
        for e in group:
            if e in hints:
                for k in (0, 1):
                    hint = hints[e].params(k)
                    starts[i][k][0].update({q: hint[q] for q in table[e].params if q in hint})
                continue
            by_score = (p.sizing_draws, p.resolution) if e in sized[i] else ()
            for k in (0, 1):
                rigs = (starts[i][k][0], _sheet_linear(starts[i][k][0]))
                one = rigs[1] == rigs[0] or e in sized[i]  # the current rig is the sheet's, or a spread effect
                for j, rig in enumerate(rigs[: 1 if one else 2]):
                    grid_slots.append((i, k, e, j))
                    grid_tasks.append(Grid(table[e], rig, tuple(cf.fits[k]), *by_score))
    best: dict[tuple[int, int, str, int], tuple[float | int, float]] = {}
    for (i, k, e, j), costs in zip(grid_slots, cf.pool.map(grid_tasks), strict=True):
        best[(i, k, e, j)] = min(costs, key=lambda vc: (vc[1], vc[0]))
    for (i, k, e, j), (value, _) in sorted(best.items()):
        if j == 0:
            starts[i][k][0][table[e].param] = value
        else:  # the fitted linear parameters may have bent to mimic it: a start from the sheet's too
            starts[i][k].append({**_sheet_linear(starts[i][k][0]), table[e].param: value})
    free = [_free((*current.effects, *group), cf) for group in adds]
    slots = [(i, k, st) for i in range(len(adds)) for k in (0, 1) for st in starts[i][k]]
    first = cf.pool.map([Refit(st, free[i], tuple(cf.fits[k]), seeds=cf.seeds if sized[i] else ())
                         for i, k, st in slots])  # fmt: skip
    fits: list[list[FitResult]] = [[None, None] for _ in adds]  # type: ignore[list-item]
    resize = [(i, k, e, r) for (i, k, _), r in zip(slots, first, strict=True) for e in sized[i]]
    if resize:  # a spread effect sized again on each refitted rig, the start that then scores best kept
        grids = cf.pool.map([Grid(table[e], r.params, tuple(cf.fits[k]), p.sizing_draws, p.resolution)
                             for i, k, e, r in resize])  # fmt: skip
        chosen: dict[tuple[int, int], tuple[float, FitResult]] = {}
        for (i, k, e, r), costs in zip(resize, grids, strict=True):
            value, score = min(costs, key=lambda vc: (vc[1], vc[0]))
            if (i, k) not in chosen or score < chosen[(i, k)][0]:
                chosen[(i, k)] = (score, replace(r, params={**r.params, table[e].param: value}))
        for (i, k), (_, r) in chosen.items():
            fits[i][k] = r
    for (i, k, _), r in zip(slots, first, strict=True):
        if not sized[i] and (fits[i][k] is None or r.cost < fits[i][k].cost):
            fits[i][k] = r
    _cross_started(cf, fits, free, [not s for s in sized])
    scores = cf.scores([list(fs) for fs in fits])
    models = []
    for group, fs, sc, sz in zip(adds, fits, scores, sized, strict=True):
        how = "by its spread, the linear parameters refitted with it" if sz else "jointly with the linear parameters"
        models.append(Model((*current.effects, *group), (fs[0], fs[1]), sc, how))
    return models


def _sheet_linear(over: Overrides) -> Overrides:
    """Overrides with the linear parameters left at the sheet's (an effect's other start: the fitted linear
    parameters may have made up for it, a delay for a slower drive, a friction for a heavily damped hub)."""
    return {k: v for k, v in over.items() if k not in recal.LINEAR}


def _cross_started(cf: CrossFit, fits: list[list[FitResult]], free: list[tuple[str, ...]], which: list[bool]
                   ) -> None:  # fmt: skip
    """Each fold's refit of the groups ``which`` started again from the other fold's, where the other's parameters
    cost less on this fold's own records than this fold's refit did (its least squares stopped in another basin, or
    where its records hardly move an effect); the lower cost kept, in place."""
    groups = [i for i, w in enumerate(which) if w]
    costs = cf.pool.map([Cost({**fits[i][1 - k].params, **_records_of(fits[i][k].params)}, tuple(cf.fits[k]))
                         for i in groups for k in (0, 1)])  # fmt: skip
    slots = [(i, k) for n, i in enumerate(groups) for k in (0, 1) if costs[2 * n + k] < fits[i][k].cost]
    again = cf.pool.map([Refit({**fits[i][1 - k].params, **_records_of(fits[i][k].params)}, free[i],
                               tuple(cf.fits[k])) for i, k in slots])  # fmt: skip
    for (i, k), r in zip(slots, again, strict=True):
        if r.cost < fits[i][k].cost:
            fits[i][k] = r


def _records_of(over: Overrides) -> Overrides:
    """A fold's own records' parameters, their gauge offsets and their links' starts (kept when the fold is refitted
    from the other fold's parameters)."""
    return {k: v for k, v in over.items() if k.startswith((ALPHA_OFFSET, *LINK_START))}


def _entry(cf: CrossFit, m: Model, current: Model, floor: Score) -> dict[str, Any]:
    """A round's entry for ``m`` against the model it was added to (plain JSON)."""
    added = [e for e in m.effects if e not in current.effects]
    params = {cf.effects[e].param: combine(cf.effects[e].param, [m.fits[k].params[cf.effects[e].param]
                                                                 for k in (0, 1)]) for e in added}  # fmt: skip
    return {
        "effect": " + ".join(added),
        "params": params,
        "held_out_share_pct": 100.0 * cf.share(current.score, m.score, floor),
        "shrink_pct": shrink_pct(math.sqrt(current.score.msg), math.sqrt(m.score.msg)),
        "gap_after": math.sqrt(m.score.msg),
        "excess": m.score.excess,
        "refit": m.how,
    }


@dataclass
class Forward:
    """The forward selection's path: the models chosen in order (the linear model first), every round's entries
    and trials."""

    path: list[Model]
    rounds: list[list[dict[str, Any]]]
    trials: list[list[Model]]


def forward_selection(cf: CrossFit, base: Model, candidates: list[str], say: Progress) -> Forward:
    """Greedy forward selection of ``candidates`` on top of the linear model ``base`` (see the module): each round
    judged against the current model's own floor (:func:`floored`)."""
    p = cf.policy
    fw = Forward([floored(cf, base)], [], [])
    remaining = list(candidates)
    singles: dict[str, Model] = {}
    while remaining:
        current = fw.path[-1]
        floor = current.floor
        assert floor is not None
        if current.score.excess <= p.none_level**2 * floor.excess:
            break
        trials = _better_floored(cf, current, fit_models(cf, current, [(e,) for e in remaining]))
        singles |= {m.effects[-1]: m for m in trials}
        best = min(trials, key=lambda m: (m.score.excess, m.effects))
        entering = best if pays(cf, current, best) else None
        entries = [_entry(cf, m, current, m.floor or floor) for m in trials]
        if entering is None:
            gainers = [m.effects[-1] for m in sorted(trials, key=lambda m: m.score.excess)
                       if m.score.excess < current.score.excess]  # fmt: skip
            pairs: list[tuple[str, ...]] = list(itertools.combinations(gainers, 2))
            if pairs:
                tried = _better_floored(cf, current, fit_models(cf, current, pairs, {e: singles[e] for e in gainers}))
                trials += tried
                entries += [_entry(cf, m, current, m.floor or floor) for m in tried]
                pair = min(tried, key=lambda m: (m.score.excess, m.effects))
                entering = pair if pays(cf, current, pair) else None
        entries.sort(key=lambda r: (-r["held_out_share_pct"], r["effect"]))
        fw.rounds.append(entries)
        fw.trials.append(trials)
        say(f"round {len(fw.rounds)}: " + ", ".join(f"{r['effect']} {share_text(r['held_out_share_pct'])}"
                                                     for r in entries))  # fmt: skip
        if entering is None:
            break
        fw.path.append(entering)
        remaining = [e for e in remaining if e not in entering.effects]
        say(f"  {' and '.join(e for e in entering.effects if e not in current.effects)} enters: held-out fit "
            f"{fit_pct(entering.score.msg):.2f} %")  # fmt: skip
    return fw


def pays(cf: CrossFit, without: Model, with_: Model) -> bool:
    """The rule an effect enters and stays by: the model ``with_`` it closes at least ``min_gain`` of what the model
    ``without`` it leaves above ``with_``'s own floor (:meth:`CrossFit.share`)."""
    if with_.score.excess >= without.score.excess:
        return False
    assert with_.floor is not None
    return cf.share(without.score, with_.score, with_.floor) >= cf.policy.min_gain


def _better_floored(cf: CrossFit, current: Model, models: list[Model]) -> list[Model]:
    """``models`` with the floors of those that score better than ``current`` (the others cannot enter)."""
    better = [i for i, m in enumerate(models) if m.score.excess < current.score.excess]
    out = list(models)
    for i, m in zip(better, floored_all(cf, [models[i] for i in better]), strict=True):
        out[i] = m
    return out


def eliminate(cf: CrossFit, model: Model) -> tuple[Model, dict[str, Score]]:
    """Backward elimination on held-out data: each effect of ``model`` removed (the others and the jointly refitted
    linear parameters kept); the effect whose removal reopens least goes while it does not pay (:func:`pays`, the
    rule it entered by).
    Returns the model kept and {effect: its score without it}."""
    while model.effects:
        less = {e: Model(tuple(x for x in model.effects if x != e),
                         tuple(FitResult(**{**f.__dict__, "params": _without(f.params, [e])})
                               for f in model.fits), model.score, model.how)  # type: ignore[arg-type]
                for e in model.effects}  # fmt: skip
        scores = dict(zip(less, cf.scores([list(m.fits) for m in less.values()]), strict=True))
        weakest = min(model.effects, key=lambda e: (scores[e].excess, e))
        reduced = replace(less[weakest], score=scores[weakest], floor=None)
        model = floored(cf, model)
        if pays(cf, reduced, model):
            return model, scores
        model = reduced
    return model, {}


def importance(cf: CrossFit, effects: Sequence[str], final: Overrides) -> dict[str, float]:
    """Drop-one importance [0, 1] of ``effects`` on the rig fitted on every record (``final``): what removing each
    alone (the others and the linear parameters kept) reopens of the rig's score on every record, as its share of
    what all the removals reopen. Held-out scores chose the effects; which of them the records owe most to is read
    on the rig all of them determine (a fold's fit, on half the records, can sit in another basin)."""
    if len(effects) < 2:
        return {e: 1.0 for e in effects}
    full, *less = cf.on_every_record([final, *(_without(final, [e]) for e in effects)])
    reopen = {e: max(s.excess - full.excess, 0.0) for e, s in zip(effects, less, strict=True)}
    total = sum(reopen.values())
    return {e: r / total if total > 0 else 1.0 / len(reopen) for e, r in reopen.items()}


def verdict(cf: CrossFit, base: Model, final: Model, shares: dict[str, float], signature: list[Effect]
            ) -> tuple[str, float]:  # fmt: skip
    """The verdict and the share of what the linear model left above the final model's floor that the effects close
    (NaN with no gap): ``none`` (or the effect found by its signature in the data) when the linear model's score is
    within ``none_level`` of its own floor; the effect of largest importance (``shares``, :func:`importance`) when the
    effects close ``explained`` of that; else ``unexplained``."""
    p = cf.policy
    assert base.floor is not None and final.floor is not None
    if base.score.excess <= p.none_level**2 * base.floor.excess:
        return (signature[0].name if signature else "none"), math.nan
    explained = cf.share(base.score, final.score, final.floor)
    if final.effects and explained >= p.explained:
        return max(final.effects, key=lambda e: (shares.get(e, 0.0), -final.effects.index(e))), explained
    return "unexplained", explained


def search(
    pool: Pool,
    experiments: dict[str, RigExperiment],
    folds: tuple[list[str], list[str]],
    cands: list[Effect],
    say: Progress,
    policy: Policy = POLICY,
    records: list[str] | None = None,
) -> SearchResult:
    """The linear model, forward selection of the candidate effects ``cands`` on top of it, backward elimination and
    the verdict, every score on held-out data (see the module); ``records``: a unit's records, each also fitted alone
    on its experiments (its blocks, where it was cut in time) with the effects found held (the table's per-record
    column)."""
    names = list(experiments)
    table = {c.name: c for c in cands}
    cf = CrossFit(pool, experiments, names, [folds[0], folds[1]], [folds[1], folds[0]], policy, table)
    base, given = recalibrated(cf, say)
    recal_model = base
    recal_paid = base.score.excess < given.excess
    if not recal_paid:  # the sheet's linear parameters, each record's own gauge offset and link start fitted
        keep = [_records_of(f.params) for f in base.fits]
        base = Model((), (FitResult(keep[0], {}, base.fits[0].cost, 0), FitResult(keep[1], {}, base.fits[1].cost, 0)),
                     given, "the spec's linear parameters")  # fmt: skip
    base = floored(cf, base)
    assert base.floor is not None
    say(f"floor: held-out fit {fit_pct(base.floor.msg):.3f} %")
    signature = [c for c in cands if c.signature]
    searched = [c.name for c in cands if not c.signature]
    fw = forward_selection(cf, base, searched, say)
    model, without = eliminate(cf, fw.path[-1])
    model = _behaviour_kept(cf, model, without, fw.path)
    model = floored(cf, model)
    final_model = model
    if signature:
        fits = tuple(FitResult(**{**model.fits[k].__dict__, "params": {**model.params(k), **{
            c.param: c.values[0] for c in signature}}}) for k in (0, 1))  # fmt: skip
        (sig_score,) = cf.scores([list(fits)])
        final_model = floored(cf, Model((*model.effects, *(c.name for c in signature)), (fits[0], fits[1]),
                                        sig_score, "adc lattice in the data"))  # fmt: skip
    final, final_fit, table_rows = final_params(cf, final_model)
    shares = importance(cf, final_model.effects, final)
    name, explained = verdict(cf, base, final_model, shares, signature)
    floor = final_model.floor
    assert floor is not None
    units = {r: tuple(parts) for r, parts in _by_record(cf).items() if r in (records or [])}
    own = dict(zip(units, pool.map([Recalibrate(parts, final) for parts in units.values()]), strict=True))
    final_fit = between_folds(final_fit, final_model)
    draws = parameter_draws(final, final_fit.names, final_fit.log, final_fit.cov, policy.behaviour_draws, 1,
                            final_fit.ranges)  # fmt: skip
    looped = closed_steps(experiments)
    behaviour: dict[str, RecordBehaviour] = {}
    for part in pool.map([Behaviour(tuple(draws), (n,)) for n in looped]):
        behaviour |= bands(experiments, final, part)
    rec_alone = _recalibrated_alone(recal_model)  # shown beside the table's values, applied or not
    for prm, value in rec_alone.items():
        if prm in table_rows:
            table_rows[prm].recalibrated = value
            table_rows[prm].folds = [_fit_row(f, prm) for f in recal_model.fits]
            if own:
                table_rows[prm].records = {n: _fit_row(r, prm) for n, r in own.items()}
    (ev_final,) = pool.map([Evaluate(final, tuple(names), (), policy.resolution)])
    sse_final = {n: dict(e.sse) for n, e in ev_final.items()}
    gauge_zeros: dict[str, float] = {}
    for n, e in ev_final.items():
        gauge_zeros.setdefault(experiments[n].record, e.offset)
    path = _path(fw, model) + ([final_model] if signature else [])
    steps = [Step("recalibration", math.sqrt(base.score.msg), 100.0 * cf.share(given, base.score, floor),
                  recal_paid)]  # fmt: skip
    for prev, m in itertools.pairwise([base, *path]):
        added = " + ".join(e for e in m.effects if e not in prev.effects)
        steps.append(Step(added, math.sqrt(m.score.msg), 100.0 * cf.share(prev.score, m.score, floor), True))
    last = path[-1] if path else base
    before, after = gap_summary(given.sse, experiments, names), gap_summary(sse_final, experiments, names)
    gap = Gap(
        before=before,
        after=after,
        held_out=HeldOutGap(
            math.sqrt(given.msg), math.sqrt(last.score.msg), fit_pct(given.msg), fit_pct(last.score.msg)
        ),  # fmt: skip
        shrink_pct=shrink_pct(math.sqrt(given.msg), math.sqrt(last.score.msg)),
        shrink_pct_in_sample=shrink_pct(before.gap, after.gap),
        explained_pct=100.0 * explained,
        decomposition=Decomposition(
            before=math.sqrt(given.msg),
            after_recalibration=math.sqrt(base.score.msg),
            after_effects=math.sqrt(last.score.msg),
            noise_floor=math.sqrt(floor.msg),
            resolution=policy.resolution,
            steps=steps,
            definition=DECOMPOSITION_DEFINITION,
            within_noise=last.score.excess <= policy.none_level**2 * floor.excess,
            channels={
                "before": channel_fits(given.sse, experiments, names),
                "after_recalibration": channel_fits(base.score.sse, experiments, names),
                **({"after_effects": channel_fits(last.score.sse, experiments, names)} if path else {}),
            },
        ),
        definition=GAP_DEFINITION,
        records={
            n: {"own": fit_pct(r.cost), "joint": fit_pct(mean_squared_gap(sse_final, experiments, list(units[n])))}
            for n, r in own.items()
        }
        or None,  # fmt: skip
    )
    return SearchResult(
        verdict=name,
        effects=_found_effects(cf, base, path, final, shares),
        candidates=_candidate_table(cf, fw, base, base.floor, signature),
        rounds=fw.rounds,
        gap=gap,
        parameters=table_rows,
        recalibration_applied=recal_paid,
        final=final,
        final_fit=final_fit,
        recalibrated=rec_alone if recal_paid else {},
        floor=floor,
        base=base.score,
        models={"base": base, "final": final_model},
        behaviour=behaviour,
        gauge_zeros=gauge_zeros,
    )


def held_out_bands(cf: CrossFit, fits: Sequence[FitResult]) -> dict[tuple[str, int, str], Band]:
    """Each of the held-out closed-loop records' behaviour metrics (every reference step's) beside the band of
    ``Policy.behaviour_draws`` replays of the fold's fitted rig with other draws of the noise, each fold's model
    replaying the records it was not fitted on: {(experiment, step, metric): band}, where defined. The bands compare
    models (what each does, and how far the noise spreads it), not the precision of a fold's fit: a parameter that
    half a record does not determine would spread its draws over its whole range."""
    n = cf.policy.behaviour_draws
    tasks, slots = [], []
    for k in (0, 1):
        draws = tuple(dict(fits[k].params) for _ in range(n))
        for name in closed_steps({x: cf.experiments[x] for x in cf.helds[k]}):
            slots.append((k, name))
            tasks.append(Behaviour(draws, (name,)))
    out = {}
    for (k, name), res in zip(slots, cf.pool.map(tasks), strict=True):
        for j, st in enumerate(bands(cf.experiments, fits[k].params, res)[name].steps):
            for m, b in st.metrics.items():
                if math.isfinite(b.measured) and math.isfinite(b.lo):
                    out[(name, j, m)] = b
    return out


def bands_worse(with_it: dict[tuple[str, int, str], Band], without: dict[tuple[str, int, str], Band]) -> bool:
    """Do a model's bands describe the records' behaviour worse than those of the model without its effect, beyond
    chance: a sign test at 95 % of the metrics' interval scores (:attr:`Band.interval_score`: a band pays its width
    and its miss, so a vague band is not rewarded for covering), on the metrics both define?"""
    common = with_it.keys() & without.keys()
    worse = sum(with_it[k].interval_score > without[k].interval_score for k in common)
    better = sum(with_it[k].interval_score < without[k].interval_score for k in common)
    return worse - better > 1.96 * math.sqrt(worse + better)


def _behaviour_kept(cf: CrossFit, model: Model, without: dict[str, Score], path: list[Model]) -> Model:
    """An effect is kept only where the behaviour bands of its replays describe the held-out records' behaviour as
    well as those of the model without it (:func:`held_out_bands`, :func:`bands_worse`; the model the forward
    selection had without it, ``path``, else the model with it removed): removed, the least important first, while
    its model's bands are worse (``without``: each effect's score without it, :func:`eliminate`'s)."""
    if not model.effects or not closed_steps(cf.experiments):
        return model
    for e in sorted(model.effects, key=lambda e: (without[e].excess, e)):
        if e not in model.effects:
            continue
        rest = tuple(x for x in model.effects if x != e)
        prev = next((m for m in reversed(path) if set(m.effects) == set(rest)), None)
        less = prev.fits if prev is not None else tuple(
            FitResult(**{**f.__dict__, "params": _without(f.params, [e])}) for f in model.fits)  # fmt: skip
        if not bands_worse(held_out_bands(cf, model.fits), held_out_bands(cf, less)):
            continue
        model = prev if prev is not None else Model(rest, (less[0], less[1]), without[e], model.how)
        model, without = eliminate(cf, model) if model.effects else (model, {})
    return model


def _path(fw: Forward, kept: Model) -> list[Model]:
    """The models of the forward path after the linear one, ending with the model kept (an elimination's result
    replaces the forward path's last model)."""
    path = fw.path[1:]
    if not kept.effects:
        return []
    if path and path[-1].effects == kept.effects:
        return path
    return [m for m in path if set(m.effects) < set(kept.effects)] + [kept]


def _recalibrated_alone(base: Model) -> Overrides:
    """What recalibration alone fitted: each linear parameter combined over the two folds' fits."""
    return {prm: combine(prm, [float(f.params[prm]) for f in base.fits]) for prm in recal.LINEAR
            if all(prm in f.params for f in base.fits)}  # fmt: skip


def _fit_row(res: FitResult, prm: str) -> list[float]:
    """A fit of ``prm`` as the table's folds and records give it: [fitted, lo, hi]."""
    return [float(res.params[prm]), *map(float, res.ci95.get(prm, (math.nan,) * 2))]


def between_folds(fit: FitResult, model: Model) -> FitResult:
    """The final fit with what its two folds' fits disagree on added to its covariance (d d^T, d the folds'
    difference over sqrt 2 in the fit's coordinates, for the parameters both folds fitted): the records' own
    variability, which a closed loop's residuals do not show."""
    a, b = (f.params for f in model.fits)
    d = np.array([(math.log(a[n] / b[n]) if lg else a[n] - b[n]) / math.sqrt(2.0)
                  if n in a and n in b and (not lg or a[n] * b[n] > 0) else 0.0
                  for n, lg in zip(fit.names, fit.log, strict=True)])  # fmt: skip
    if not d.size:
        return fit
    cov = np.asarray(fit.cov, dtype=float).reshape(d.size, d.size) + np.outer(d, d)
    return FitResult(**{**fit.__dict__, "cov": tuple(tuple(float(v) for v in row) for row in cov)})


def final_params(cf: CrossFit, model: Model) -> tuple[Overrides, FitResult, dict[str, FittedParameter]]:
    """The reported parameters: integers from the folds (when they disagree, settled by the lower gap on all
    experiments), then the linear parameters, the continuous effect parameters and each record's gauge offset fitted
    jointly on every experiment's fit window from the folds' combined values, with 95 % intervals (an effect sized
    by its spread held at its folds' combined value). Returns (overrides, the fit, parameter table)."""
    start: Overrides = {}
    for prm in set(model.fits[0].params) | set(model.fits[1].params):
        vals = [f.params[prm] for f in model.fits if prm in f.params]
        start[prm] = vals[0] if len(vals) == 1 else combine(prm, vals)
    for name in model.effects:
        eff = cf.effects[name]
        a, b = (f.params[eff.param] for f in model.fits)
        if not eff.continuous and a != b:
            opts = sorted({a, b})
            res = cf.pool.map([Evaluate({**start, eff.param: v}, tuple(cf.names), (), cf.policy.resolution)
                               for v in opts])  # fmt: skip
            start[eff.param] = min(zip(opts, res, strict=True), key=lambda o: cf._merge([o[1]]).msg)[0]
    free = _free(model.effects, cf)
    linear = any(prm in f.params for f in model.fits for prm in recal.LINEAR)
    spread = cf.all_closed and any(cf.effects[e].spread for e in model.effects if e in cf.effects)
    fit = cf.pool.refit(start, free, cf.names, 20, linear, cf.seeds if spread else ())
    final = fit.params
    table: dict[str, FittedParameter] = {}
    extras = [x for p in free for x in BY_PARAM[p].extra]
    fitted_linear = cf.pool.setup.linear(any(x.encoder for x in cf.experiments.values()))
    for prm in [*fitted_linear, *free, *extras]:
        nom = cf.pool.setup.nominal(prm)
        val, ci = float(final.get(prm, nom)), fit.ci95.get(prm, (math.nan, math.nan))
        row = FittedParameter(nominal=nom, fitted=val, ci95=[float(ci[0]), float(ci[1])], change_pct=math.nan, unit="")
        if prm in recal.LINEAR:
            row.unit = recal.LINEAR[prm].unit
        if prm in recal.LINEAR and not linear:
            row.change_pct = 0.0
            row.finding = recal.kept_finding(prm, nom)
        elif prm in recal.LINEAR and not recal.LINEAR[prm].log:
            row.finding = recal.offset_finding(prm, val, ci)
        elif prm in recal.LINEAR:
            row.change_pct = 100.0 * (val / nom - 1.0)
            row.finding = recal.finding(prm, nom, val, ci, cf.pool.setup.prior_sd.get(prm))
            row.at_bound = recal.at_bound(prm, nom, val)
            row.identifiable = None if recal.identifiable(ci) else False
        elif prm in SECONDARY:
            row.unit = SECONDARY[prm].unit
            row.finding = f"{SECONDARY[prm].label}: {val:.3g} (spec {nom:.3g})"
        else:
            row.unit = BY_PARAM[prm].unit
        table[prm] = row
    if linear:
        table |= implied(cf.pool.setup.plant, final, fit.ci95)
    return final, fit, table


def implied(
    sheet: dict[str, Any], final: Overrides, ci95: dict[str, tuple[float, float]]
) -> dict[str, FittedParameter]:
    """The physical values (:data:`harness.diagnosis.recalibrate.IMPLIED`) the fitted combos ``final`` imply on the
    sheet's plant (:func:`harness.diagnosis.rigmodel.to_plant`), their intervals from the combos' (each end taken
    alone, the log deviations added in quadrature)."""
    combos = {p: float(final[p]) for p in COMBOS if p in final}
    mid = to_plant(combos, sheet)
    dev: dict[str, list[float]] = {k: [0.0, 0.0] for k in mid}
    for p in combos:
        for end in ci95.get(p, (math.nan, math.nan)):
            if not (math.isfinite(end) and end > 0):
                continue
            moved = to_plant({**combos, p: end}, sheet)
            for k in mid:
                d = math.log(moved[k] / mid[k])
                dev[k][0 if d < 0 else 1] += d * d
    out = {}
    for k, v in mid.items():
        name = f"plant.{k}"
        nom = plant_value(sheet, k)
        lo, hi = v * math.exp(-math.sqrt(dev[k][0])), v * math.exp(math.sqrt(dev[k][1]))
        out[name] = FittedParameter(
            nominal=nom,
            fitted=v,
            ci95=[lo, hi],
            change_pct=100.0 * (v / nom - 1.0),
            unit=recal.IMPLIED[name][1],
            finding=f"implied by the drive's fit: {recal.finding(name, nom, v, (lo, hi))}",
        )
    return out


def against_record(param: str, value: float, experiments: dict[str, RigExperiment]) -> str | None:
    """An effect's fitted parameter beside what the records themselves span, so that a value no record supports reads
    as such ("amplifier limit 1.05 V; the logged command reaches 5.53 V, 4 % of its samples beyond the limit")."""
    u = np.concatenate([x.u for x in experiments.values()])
    if param == "plant.amp_limit":
        beyond = 100.0 * float(np.mean(np.abs(u) > value))
        return (f"amplifier limit {value:.3g} V; the logged command reaches {float(np.max(np.abs(u))):.3g} V, "
                f"{beyond:.0f} % of its samples beyond the limit")  # fmt: skip
    if param == "daq.delay_samples":
        rates = sorted({round(1.0 / x.Ts, 6) for x in experiments.values()})
        ms = ", ".join(f"{1e3 * value / r:.3g} ms at {r:g} Hz" for r in rates)
        return f"{value:g} sample(s) of command delay: {ms}"
    if param == "plant.backlash":
        span = max(float(np.percentile(np.abs(x.theta - np.median(x.theta)), 95)) for x in experiments.values())
        return f"gear play {math.degrees(value):.3g} deg; the hub moves up to {span:.3g} deg (95th percentile)"
    return None


def _found_effects(cf: CrossFit, base: Model, path: list[Model], final: Overrides, shares: dict[str, float]
                   ) -> list[FoundEffect]:  # fmt: skip
    """The effects found, in the order they entered, each with the held-out gap before and after it entered (and
    each record's)."""
    out = []
    prev = base
    for m in path:
        for name in (e for e in m.effects if e not in prev.effects):
            eff = cf.effects[name]
            p = eff.param
            gb, ga = math.sqrt(prev.score.msg), math.sqrt(m.score.msg)
            out.append(
                FoundEffect(
                    effect=name,
                    params={p: final.get(p, combine(p, [f.params[p] for f in m.fits]))},
                    params_folds=[{p: f.params[p]} for f in m.fits],
                    gap_before=gb,
                    gap_after=ga,
                    shrink_pct=shrink_pct(gb, ga),
                    fit_pct_before=100.0 * (1.0 - gb),
                    fit_pct_after=100.0 * (1.0 - ga),
                    importance_pct=100.0 * shares[name] if name in shares else math.nan,
                    fitted_on=[cf.fits[0], cf.fits[1]],
                    held_out=[cf.helds[0], cf.helds[1]],
                    selected_by=(SELECTED_BY_SPREAD if eff.spread and cf.all_closed else eff.selected_by),
                    against_record=against_record(
                        p, float(final[p] if p in final else m.fits[0].params[p]), cf.experiments
                    ),
                    held_out_fit_pct={
                        r: [fit_pct(mean_squared_gap(s.sse, cf.experiments, parts)) for s in (prev.score, m.score)]
                        for r, parts in _by_record(cf).items()
                    },
                )
            )
        prev = m
    return out


def _by_record(cf: CrossFit) -> dict[str, list[str]]:
    """Each record's experiments (a record cut in time: its blocks), in order."""
    out: dict[str, list[str]] = {}
    for n in cf.names:
        out.setdefault(cf.experiments[n].record, []).append(n)
    return out


def _candidate_table(cf: CrossFit, fw: Forward, base: Model, floor: Score, signature: list[Effect]
                     ) -> list[Candidate]:  # fmt: skip
    """The first round's candidates, each alone on top of the linear model, best held-out share first; the effects
    found by their signature; then the effects not tried, with the reason."""
    out = []
    for m in fw.trials[0] if fw.trials else []:
        if len(m.effects) != 1:
            continue
        r = _entry(cf, m, base, floor)
        out.append(Candidate(r["effect"], r["params"], r["held_out_share_pct"], r["shrink_pct"], r["gap_after"],
                             r["refit"]))  # fmt: skip
    out += [Candidate(c.name, {c.param: c.values[0]}, math.nan, note="bits from the ADC lattice of the data")
            for c in signature]  # fmt: skip
    out.sort(key=lambda c: (-c.held_out_share_pct if math.isfinite(c.held_out_share_pct) else math.inf, c.effect))
    tried = {c.effect for c in out}
    for name, eff in EFFECTS.items():
        if name not in tried and name not in cf.effects:
            out.append(Candidate(effect=name, params={}, held_out_share_pct=math.nan, note=eff.skipped))
        elif name not in tried:
            out.append(Candidate(effect=name, params={}, held_out_share_pct=math.nan,
                                 note="not tried: no gap beyond the replays' own spread"))  # fmt: skip
    return out


GAP_DEFINITION = (
    "gap = sqrt(mean over experiments and channels (theta, alpha) of ||y_real - y_sim||^2 / ||y_real - mean||^2) "
    "over valid samples (pot dead band and ADC clipping masked); fit % = 100 (1 - gap); shrink % = 100 (1 - "
    "gap_after / gap_before); held_out: every experiment scored with parameters fitted on the other fold; after: "
    "final parameters, all data"
)
DECOMPOSITION_DEFINITION = (
    "held-out gaps: before = the simulation as given; after_recalibration = its linear parameters fitted on the "
    "other fold; after_effects = with the effects found, fitted jointly with the linear parameters on the other "
    "fold; noise_floor = what a right model leaves (the replay with another noise draw as the record); closed_pct = "
    "share of the excess score (the record's gap beyond the replays' own spread, window by window) above the "
    "floor's that the stage closes"
)
