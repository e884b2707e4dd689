"""The whole ``flexjoint run`` (spec -> campaign -> calibration -> identification -> cross-fit -> diagnosis ->
report and recording), and the identification step over a run directory."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from . import spec as specmod
from .diagnosis.diagnose import diagnose_run
from .fmu.build import build_all
from .ident.accept import accept
from .ident.calibration import calibrate_run, load_calibration
from .ident.crossfit import crossfit_run
from .ident.doubled_rate import doubled_rate_check
from .ident.identify import prepare, run_grid, write_grid
from .render.load import load_results
from .render.report import write_report
from .render.viewer import log_run
from .rig.campaign import run_campaign
from .rundir import load_run, recorded_spec

Progress = Callable[[str], None]


def identify_run(run: Path, identify: dict[str, Any] | None = None, progress: Progress | None = None):
    """Grid, cross-validation and selection on a run's identification datasets; writes grid.csv and models/."""

    run = Path(run)
    spec = recorded_spec(run)
    ident = dict(specmod.IDENTIFY_DEFAULTS)
    ident.update(spec.identify if spec else {})
    ident.update(identify or {})
    cal = load_calibration(run)
    prepared = prepare(load_run(run), cal, float(ident["af"]), str(ident["output"]))
    res = run_grid(prepared, ident, progress=progress)
    write_grid(res, run, ident, cal)
    return res, prepared, cal, ident


def run_pipeline(
    spec_name: str | Path,
    out: Path,
    overrides: list[str] | None = None,
    *,
    sim: str | Path = "nominal",
    rrd: Path | None = None,
    spawn: bool = False,
    connect: str | None = None,
    progress: Progress | None = None,
) -> str:
    """``flexjoint run``: every step on one spec into run directory ``out``; returns a short summary."""

    say = progress or (lambda _msg: None)
    t0 = time.perf_counter()
    spec = specmod.load(spec_name, overrides or [])
    out = Path(out)
    fmus = build_all()
    say("FMUs built")
    run_campaign(spec, out, fmus=fmus)
    say(f"campaign: {len(spec.all_experiments())} experiments")
    cal = calibrate_run(out)
    say(f"calibration: Kp {cal.Kp:.4f} deg/V, Ke {cal.Ke:.4f} deg/V, dead zone {cal.dead_zone_v:.4f} V")
    res, _, cal, ident = identify_run(out)
    sel = res.grid.loc[res.selected]
    say(f"identified: ARMAX({sel.na},{sel.nb},{sel.nc},{sel.nk}), mean cross-validation {sel.cv_mean:.2f} %")
    if ident.get("doubled_rate", True):
        doubled_rate_check(out, res.models[res.selected], ident, cal, fmus=fmus)
        say("doubled-rate check")
    cf = crossfit_run(out)
    say(f"cross-fit through FMUs: selected average {cf.loc['selected', 'average']:.2f} %")
    d = diagnose_run(out, sim, out, fmus=fmus)
    found = " + ".join(d.effect_names) or d.verdict
    say(f"diagnosis against {sim}: {found} (verdict {d.verdict}, held-out shrink {d.gap.shrink_pct:.1f} %)")
    res = load_results(out)
    write_report(out, res)
    log_run(out, rrd=rrd, spawn=spawn, connect=connect, results=res)
    verdict = accept(out)
    say("report.md and run.rrd written")
    return (
        f"{out}: selected ARMAX({sel.na},{sel.nb},{sel.nc},{sel.nk}); cross-fit average "
        f"{cf.loc['selected', 'average']:.2f} %; acceptance {'passed' if verdict.passed else 'FAILED'}; "
        f"diagnosis {found}; {time.perf_counter() - t0:.0f} s"
    )
