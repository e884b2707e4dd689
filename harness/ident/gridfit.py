"""The order grid's tasks, what a worker of ``flexjoint identify`` runs: ARMAX fits of a slice of the orders on one
prepared dataset, and the cross-validation of fitted models on every dataset.

The module needs numpy and :mod:`harness.ident.armax` only, so that a worker that runs the grid imports no more
(:func:`harness.ident.identify.run_grid` builds the tasks and assembles their rows).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from . import armax

Orders = list[tuple[int, int, int]]


@dataclass
class PreparedExperiment:
    """One experiment's dataset ready for identification: detrended command u_d [V], filtered difference y_f
    [deg/sample]."""

    name: str
    u_d: np.ndarray
    y_f: np.ndarray
    y: np.ndarray  # the angle itself [deg]
    u: np.ndarray  # the raw command [V]
    Ts: float
    y_f_offset: float = 0.0  # mean removed from y_f [deg/sample]: the operating point's mean rate


def causal(na: int, nb: int, nk: int) -> bool:
    """Lab 1's causality rule in the forward-shift operator: deg B(z) + nk <= deg A(z), i.e. nb + nk <= na."""
    return nb + nk <= na


def fit_order(p: PreparedExperiment, na: int, nb: int, nc: int, nk: int, ic: str) -> dict[str, Any]:
    """One order on one dataset: the grid's row (orders, causal, stable, fit [%]) with the model as a dict (None
    for a non-causal order, which is not fitted)."""
    row: dict[str, Any] = {"dataset": p.name, "na": na, "nb": nb, "nc": nc, "nk": nk, "n_params": na + nb + nc}
    row["causal"] = causal(na, nb, nk)
    if not row["causal"]:
        return {**row, "stable": False, "fit": math.nan, "model": None}
    m = armax.estimate(p.u_d, p.y_f, na, nb, nc, nk, Ts=p.Ts)
    return {**row, "stable": m.stable, "fit": armax.compare(m, p.u_d, p.y_f, ic=ic), "model": m.to_dict()}


def fit_slice(task: tuple[PreparedExperiment, Orders], nk: int, ic: str) -> list[dict[str, Any]]:
    """One task of the grid: a dataset and a slice of the orders, a row per order (:func:`fit_order`)."""
    p, orders = task
    return [fit_order(p, na, nb, nc, nk, ic) for na, nb, nc in orders]


def cross_validate(
    models: list[armax.ArmaxModel], prepared: dict[str, PreparedExperiment], ic: str
) -> list[list[float]]:
    """One task of the cross-validation: each model's fit [%] on every dataset (MATLAB compare's)."""
    return [[armax.compare(m, p.u_d, p.y_f, ic=ic) for p in prepared.values()] for m in models]
