"""The whole ``flexjoint run`` (spec -> campaign -> calibration -> identification -> cross-fit -> diagnosis ->
report and recording)."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from . import spec as specmod
from .diagnosis.diagnose import diagnose_run
from .fmu.build import build_all
from .ident.accept import accept
from .ident.calibration import calibrate_run
from .ident.crossfit import crossfit_run
from .ident.doubled_rate import doubled_rate_check
from .ident.identify import identify_run
from .render.load import load_results
from .render.report import begin_report
from .render.viewer import log_run
from .rig.campaign import run_campaign
from .rundir import RunDir, new_run, write_json

Progress = Callable[[str], None]


@dataclass
class PipelineResult:
    """What ``flexjoint run`` did: a one-line ``summary`` and the wall time [s] of each ``stage`` in order (also in
    ``run.timing.json`` of the run directory)."""

    summary: str
    stages: dict[str, float] = field(default_factory=dict)

    @property
    def total_s(self) -> float:
        return sum(self.stages.values())


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
    status: Progress | None = None,
    force: bool = False,
) -> PipelineResult:
    """``flexjoint run``: every stage on one spec into a new run directory.

    Build, campaign, calibration, identification, doubled-rate check, export and cross-fit, acceptance,
    diagnosis against ``sim``, report and recording; written aside and moved into place when complete
    (:func:`harness.rundir.new_run`).

    Parameters
    ----------
    spec_name : str or Path
        The spec (a bundled name or a path).
    out : Path
        The run directory to write.
    overrides : list of str, optional
        ``table.name=value`` items, as ``--set``.
    sim : str or Path
        The spec of the simulation the diagnosis judges.
    rrd : Path, optional
        The recording to write; default ``<out>/run.rrd``.
    spawn, connect : optional
        Stream the recording live (:func:`harness.log_run`).
    progress : callable, optional
        Called with a message as each stage ends.
    status : callable, optional
        Called with what runs now, as each stage starts (a live status line's text).
    force : bool
        Replace a run already in ``out``.

    Returns
    -------
    PipelineResult
        The run's summary and the wall time of each stage (also written to ``run.timing.json``).
    """
    with new_run(out, force) as work:
        return _pipeline(spec_name, work, Path(out), overrides, sim, rrd, spawn, connect, progress, status)


def _pipeline(
    spec_name: str | Path,
    out: Path,
    shown: Path,
    overrides: list[str] | None,
    sim: str | Path,
    rrd: Path | None,
    spawn: bool,
    connect: str | None,
    progress: Progress | None,
    status: Progress | None,
) -> PipelineResult:
    """The pipeline into ``out`` (the aside of run directory ``shown``, the one the summary names)."""
    say = progress or (lambda _msg: None)
    now = status or (lambda _msg: None)
    stages: dict[str, float] = {}
    clock = [time.perf_counter()]

    def done(stage: str, message: str) -> None:
        now = time.perf_counter()
        stages[stage] = now - clock[0]
        clock[0] = now
        say(message)

    spec = specmod.load(spec_name, overrides or [])
    out = Path(out)
    now("FMUs: building (only when their sources changed)")
    fmus = build_all()
    done("build", "FMUs built")
    now("campaign: simulating the experiments")
    run_campaign(spec, out, fmus=fmus)
    done("campaign", f"campaign: {len(spec.all_experiments())} experiments")
    now("calibration: Kp, Ke and the dead zone")
    cal = calibrate_run(out)
    done("calibration", f"calibration: Kp {cal.Kp:.4f} deg/V, Ke {cal.Ke:.4f} deg/V, dead zone {cal.dead_zone_v:.4f} V")
    now("identification: ARMAX grid, cross-validation, selection")
    res, _, cal, ident = identify_run(out)
    sel = res.grid.loc[res.selected]
    done("identification", f"identified: ARMAX({sel.na},{sel.nb},{sel.nc},{sel.nk}), mean cross-validation "
         f"{sel.cv_mean:.2f} %")  # fmt: skip
    if ident.get("doubled_rate", True):
        now("doubled-rate check")
        doubled_rate_check(out, res.models[res.selected], ident, cal, fmus=fmus)
        done("doubled_rate", "doubled-rate check")
    now("cross-fit: the models as FMUs on every dataset")
    cf = crossfit_run(out)
    done("crossfit", f"cross-fit through FMUs: selected average {cf.loc['selected', 'average']:.2f} %")
    now(f"diagnosis against {sim}: recalibration, effects, where the gap lies")
    d = diagnose_run(out, sim, out, fmus=fmus)
    found = " + ".join(d.effect_names) or d.verdict
    done("diagnosis", f"diagnosis against {sim}: {found} (verdict {d.verdict}, held-out shrink "
         f"{d.gap.shrink_pct:.1f} %)")  # fmt: skip
    now("report.md, figures and run.rrd")
    results = load_results(out)
    report = begin_report(out, results)  # its figures drawn on the workers while this process writes the recording
    log_run(out, rrd=rrd, spawn=spawn, connect=connect, results=results)
    report.write()
    verdict = accept(out)
    done("report", "report.md and run.rrd written")
    write_json(RunDir(out).run_timing, {"stages_s": stages, "total_s": sum(stages.values())})
    summary = (
        f"{shown}: selected ARMAX({sel.na},{sel.nb},{sel.nc},{sel.nk}); cross-fit average "
        f"{cf.loc['selected', 'average']:.2f} %; acceptance {'passed' if verdict.passed else 'FAILED'}; "
        f"diagnosis {found}; {sum(stages.values()):.0f} s"
    )
    return PipelineResult(summary, stages)
