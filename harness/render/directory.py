"""``flexjoint report DIR`` on whatever a command wrote: which command wrote a directory (:func:`what_wrote`), and its
report, figures and recording (:func:`report_directory`), each from what the directory holds."""

from __future__ import annotations

from pathlib import Path

from ..rundir import DataError, RunDir
from ..sweep import report_sweep
from .blindtest import report_blindtest
from .load import load_results
from .prediction import report_prediction
from .report import write_report
from .viewer import log_run

__all__ = ["KINDS", "report_directory", "what_wrote"]

KINDS = {
    "run": "manifest.json",  # run, campaign, import, identify, crossfit, diagnose into the run
    "sweep": "sweep.json",
    "blindtest": "blindtest.json",
    "diagnosis": "diagnosis.json",  # diagnose --out elsewhere
    "prediction": "prediction.json",  # predict, design
}


def what_wrote(path: Path) -> str:
    """The kind of output directory ``path`` is (a key of :data:`KINDS`, the first whose file it holds); one
    :class:`harness.rundir.DataError` line when it is none."""
    path = Path(path)
    if not path.is_dir():
        raise DataError(f"{path}: no such run directory")
    for kind, marker in KINDS.items():
        if (path / marker).is_file():
            return kind
    raise DataError(
        f"{path}: nothing to report: no manifest.json (run, campaign, import), diagnosis.json (diagnose --out), "
        "sweep.json (sweep), blindtest.json (blindtest) or prediction.json (predict, design)"
    )


def report_directory(
    path: Path, rrd: Path | None = None, spawn: bool = False, connect: str | None = None
) -> tuple[str, Path, Path]:
    """Write the report of whatever a command wrote: report.md, figures/ and its recording.

    Parameters
    ----------
    path : Path
        A run directory, or the ``--out`` of ``diagnose``, ``sweep`` or ``blindtest``.
    rrd : Path, optional
        The recording to write; default the directory's own (run.rrd, sweep.rrd or blindtest.rrd).
    spawn : bool
        Also stream a run or a diagnosis to a newly spawned viewer.
    connect : str, optional
        Also stream it to a running viewer at this URL.

    Returns
    -------
    kind : str
        What wrote the directory (:func:`what_wrote`).
    report : Path
        Its report.md.
    recording : Path
        Its recording.
    """
    kind = what_wrote(path)
    if kind == "prediction" and not (spawn or connect):
        report = report_prediction(path, rrd or True)
        return kind, report, Path(rrd) if rrd else path / "prediction.rrd"
    if kind in ("sweep", "blindtest", "prediction"):
        if spawn or connect:
            raise ValueError(f"--spawn/--connect stream a run or a diagnosis; open the {kind}'s .rrd with `rerun FILE`")
        if kind == "sweep":
            return (kind, *report_sweep(path, rrd))
        return (kind, *report_blindtest(path, rrd))
    res = load_results(path)
    report = write_report(path, res)
    recording = log_run(path, rrd=rrd, spawn=spawn, connect=connect, results=res)
    return kind, report, recording if recording is not None else RunDir(path).recording
