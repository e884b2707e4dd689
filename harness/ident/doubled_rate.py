"""The doubled-rate check of lab 1 (its section 3.4): the selected model scored on the same experiment
simulated at twice the sample rate, as it is and re-identified at that rate (``doubled_rate.json``)."""

from __future__ import annotations

from pathlib import Path
from typing import TypedDict

import numpy as np
import pandas as pd

from .. import spec as specmod
from ..fmu.build import build_all
from ..rig.campaign import simulate_spec
from ..rundir import RunDir, record_inputs, recorded_spec, write_json
from . import armax
from .calibration import Calibration
from .identify import prepare


class DoubledRate(TypedDict, total=False):
    """``doubled_rate.json``: the ``experiment`` re-run at ``sample_rate_hz`` [Hz], the selected model's ``orders``
    (na, nb, nc, nk), its fit [%] applied as is (``fit_model_50hz_as_is``) and the same orders re-identified at
    the doubled rate (``fit_reidentified_100hz``), the ratio of their static gains per sample
    (``gain_ratio_as_is``); or only ``skipped``, why there was no check."""

    experiment: str
    sample_rate_hz: float
    orders: list[int]
    fit_model_50hz_as_is: float
    fit_reidentified_100hz: float
    gain_ratio_as_is: float
    skipped: str


def doubled_rate_check(
    run: Path,
    selected: armax.ArmaxModel,
    ident: specmod.IdentifySettings,
    cal: Calibration,
    experiment: str | None = None,
    fmus: dict[str, Path] | None = None,
) -> DoubledRate:
    """Lab 1's section 3.4: run an experiment at twice the sampling rate and score the 50 Hz model on it.

    Reports the 50 Hz model applied sample by sample to 100 Hz data, as lab 1 did (its per-sample gain is
    twice too large: it "thinks the effect of the input is much bigger"), and the same orders re-identified at
    100 Hz. ``fmus``: the built plant and DAQ FMUs (default: built, or taken from the cache).
    """

    spec = recorded_spec(run)
    if spec is None:
        return {"skipped": "imported data: no rig to re-run at a doubled rate"}
    exp = spec.experiment(experiment or spec.experiments[len(spec.experiments) // 2].name)
    fast = specmod.from_dict(specmod.apply_overrides(spec.raw, [f"campaign.sample_rate={2 * spec.sample_rate}"]))

    cols = simulate_spec(fast, fmus or build_all(), experiments=[fast.experiment(exp.name)], workers=1)[exp.name]
    p = prepare({exp.name: pd.DataFrame(cols)}, cal, float(ident["af"]), str(ident["output"]))[exp.name]
    ic = str(ident["ic"])
    out: DoubledRate = {
        "experiment": exp.name,
        "sample_rate_hz": fast.sample_rate,
        "orders": [selected.na, selected.nb, selected.nc, selected.nk],
    }
    out["fit_model_50hz_as_is"] = armax.compare(selected, p.u_d, p.y_f, ic=ic)
    refit = armax.estimate(p.u_d, p.y_f, selected.na, selected.nb, selected.nc, selected.nk, Ts=fast.Ts)
    out["fit_reidentified_100hz"] = armax.compare(refit, p.u_d, p.y_f, ic=ic)
    out["gain_ratio_as_is"] = float(np.sum(selected.B) / np.sum(selected.A)) / float(np.sum(refit.B) / np.sum(refit.A))
    write_json(RunDir(run).doubled_rate, out)
    record_inputs(run, "doubled_rate.json")
    return out
