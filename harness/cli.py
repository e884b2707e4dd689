"""The ``flexjoint`` command line: a thin layer over the library. Errors are one line and a non-zero exit."""

from __future__ import annotations

import atexit
import contextlib
import logging
import math
import os
import signal
import sys
import time
from collections.abc import Callable
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Annotated, Any, cast

import typer
import typer.core

from ._version import __version__

if TYPE_CHECKING:
    from rich.console import Console
    from rich.table import Table

    from .diagnosis.result import Diagnosis
    from .ident.identify import GridResult
    from .pipeline import PipelineResult
    from .render.summary import Summary

# A command imports what it runs when it runs (here, and only here, imports sit inside functions): ``--help`` and
# ``--version`` then answer without loading numpy, fmpy, Dask or the pipeline (tests/test_cli_startup.py).


class _Commands(typer.core.TyperGroup):
    """The command group: ``--help`` lists each command with its first sentence whole, wrapped under the others,
    where click cuts it to the line's width with "..."."""

    def format_commands(self, ctx: Any, formatter: Any) -> None:  # typer's click Context and HelpFormatter
        cmds = [(n, c) for n in self.list_commands(ctx) if (c := self.get_command(ctx, n)) and not c.hidden]
        if cmds:
            with formatter.section("Commands"):
                formatter.write_dl([(n, c.get_short_help_str(limit=10_000)) for n, c in cmds])


app = typer.Typer(
    cls=_Commands,
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,  # click's help: wrapped to the terminal, never an option's text cut with "…"
    help="Flexible-joint rig twin, ARMAX identification, cross-fit and sim-to-real diagnosis.",
)


class _LazyConsole:
    """A rich ``Console`` made on first use: importing rich costs ``--version`` a quarter of its time."""

    def __init__(self, **kwargs: Any) -> None:
        object.__setattr__(self, "_kwargs", kwargs)
        object.__setattr__(self, "_console", None)

    def _get(self) -> Console:
        if self._console is None:
            from rich.console import Console

            object.__setattr__(self, "_console", Console(**self._kwargs))
        return self._console

    def __getattr__(self, name: str) -> Any:
        return getattr(self._get(), name)

    def __setattr__(self, name: str, value: Any) -> None:
        setattr(self._get(), name, value)


err = cast("Console", _LazyConsole(stderr=True, highlight=False))
out = cast("Console", _LazyConsole(highlight=False))  # the terminal's width; piped: $COLUMNS, else 80

SpecArg = Annotated[str, typer.Argument(help="campaign spec: a path or a name in specs/ (lab, nominal)")]
SetOpt = Annotated[list[str] | None, typer.Option("--set", help="override one parameter: table.name=value")]
SchedulerOpt = Annotated[
    str | None,
    typer.Option(
        "--scheduler",
        envvar="FLEXJOINT_SCHEDULER",
        help="Dask scheduler address (tcp://HOST:8786) to run on; default: an embedded local cluster",
    ),
]
WorkersOpt = Annotated[
    int | None, typer.Option("--workers", min=1, help="local worker processes (default 2; 1: serial, in-process)")
]
ForceOpt = Annotated[bool, typer.Option("--force", help="replace a run already in --out (every file of it removed)")]


def _user_errors() -> tuple[type[BaseException], ...]:
    """The library's errors that are a user's mistake (one line, exit 2): its own kinds where they are loaded (a
    command that failed before importing them cannot have raised them), and the built-in ones it raises."""
    own = [getattr(sys.modules.get(m), n, None) for m, n in _OWN_ERRORS]
    return (
        *(e for e in own if isinstance(e, type)),
        ValueError,
        FileNotFoundError,
        RuntimeError,
        NotADirectoryError,
        IsADirectoryError,
        FileExistsError,
        PermissionError,
    )


_OWN_ERRORS = (("harness.spec", "SpecError"), ("harness.rundir", "DataError"), ("harness.fmu.binding", "FMUError"))


def _out_dir(path: Path, option: str = "--out") -> Path:
    """Refuse an output directory that cannot be one (an existing file, or a file on its path) before any work."""
    for p in (path, *path.parents):
        if p.exists() and not p.is_dir():
            where = "" if p == path else f" ({p} is a file)"
            raise NotADirectoryError(f"{option} {path}: not a directory{where}; give a new or existing directory")
    return path


def _fit(table: Any, width: int | None = None) -> Any:
    """A rich table made to fit ``width`` (default ``out``'s) without cutting a cell: every column folds, never "…"
    (a column marked no_wrap keeps its widest cell whole); a table too wide for its borders loses them (one space
    between columns); one still too wide is wrapped: its columns in parts, one under the other, each part with the
    first column again (the title above the first, the caption under all, as wide as the terminal)."""
    from rich import box
    from rich.console import Group
    from rich.measure import Measurement
    from rich.table import Table
    from rich.text import Text

    for c in table.columns:
        c.overflow = "fold"
        if c.no_wrap:
            c.min_width = max((len(str(x)) for x in (c.header, *c.cells)), default=0)
    wide = out.options.update_width(10_000)
    width = width or out.width
    if Measurement.get(out, wide, table).maximum <= width:
        return table
    table.box, table.padding, table.show_edge = box.SIMPLE_HEAD, (0, 1), False
    if Measurement.get(out, wide, table).minimum <= width:
        return table
    first, parts = table.columns[0], [list[Any]()]
    for c in table.columns[1:]:
        if parts[-1] and sum((x.min_width or 12) + 3 for x in (first, *parts[-1], c)) > width:  # pad, rule
            parts.append([])
        parts[-1].append(c)
    tables = []
    for i, cols in enumerate(parts):
        t = Table(box=table.box, padding=table.padding, show_edge=False, title_justify=table.title_justify)
        t.title = table.title if i == 0 else None
        for c in (first, *cols):
            t.add_column(c.header, justify=c.justify, no_wrap=c.no_wrap, min_width=c.min_width, overflow="fold")
        for r in range(table.row_count):
            t.add_row(*(c._cells[r] for c in (first, *cols)))
        tables.append(t)
    return Group(*tables, *([Text(str(table.caption), style="dim")] if table.caption else []))


def _table(table: Any) -> Any:
    """A table of a command's summary: :func:`_fit` to the summary's width (:data:`harness.render.summary.WIDTH`
    at most)."""
    from .render.summary import WIDTH

    return _fit(table, min(out.width, WIDTH))


class _Elapsed:
    """A rich renderable: the last progress message and the seconds since the stage started, redrawn live."""

    def __init__(self, label: str, start: float) -> None:
        self.label, self.start, self.item = label, start, "starting"

    def __rich__(self) -> str:
        return f"[dim]{self.label}[/] {self.item} [dim]({time.perf_counter() - self.start:.0f} s)[/]"


_status = None  # the live status line of the running command (stopped in main)


class _StdoutEndsStatus:
    """``out``'s file while a live status runs: a command's result on stdout first ends the status line (which
    would otherwise share the terminal line with it), then goes to the real stdout."""

    encoding = "utf-8"

    def write(self, text: str) -> int:
        _stop_status()
        return sys.stdout.write(text)

    def flush(self) -> None:
        sys.stdout.flush()

    def isatty(self) -> bool:
        return sys.stdout.isatty()

    def fileno(self) -> int:
        return sys.stdout.fileno()


def _progress(label: str) -> Callable[[str], None]:
    """A progress printer for long work, the ``progress: Callable[[str], None]`` the library calls: one line per
    message on stderr with the elapsed time; in an interactive terminal also a live status line (spinner, last
    message, a running clock) so that a long silent stage still shows that it works."""
    global _status
    start = time.perf_counter()
    live = _Elapsed(label, start)
    if err.is_terminal and out.is_terminal:  # interactive only: never redirect a piped stdout into stderr
        if _status is not None:
            _status.stop()
        _status = err.status(live, spinner="dots")
        _status.start()
        out.file = _StdoutEndsStatus()  # type: ignore[assignment]

    def report(item: str) -> None:
        live.item = item
        err.print(f"[dim]{label}[/] {item} [dim]({time.perf_counter() - start:.1f} s)[/]", soft_wrap=True)

    def status(item: str) -> None:  # what runs now: the live line only, no line of its own
        live.item = item

    report.status = status  # type: ignore[attr-defined]
    return report


def _stop_status() -> None:
    global _status
    if _status is not None:
        status, _status = _status, None
        status.stop()
        out.file = None  # type: ignore[assignment]  # back to the current sys.stdout


def _version(value: bool) -> None:
    if value:
        print(f"flexjoint-harness {__version__}")  # plain: the version does not wait for rich
        raise typer.Exit()


@app.callback()
def _main(
    version: Annotated[
        bool, typer.Option("--version", callback=_version, is_eager=True, help="print the version and exit")
    ] = False,
) -> None:
    pass


@app.command()
def build(force: Annotated[bool, typer.Option(help="rebuild even if cached")] = False) -> None:
    """Compile the FMUs in fmus/ (plant, DAQ, controller, generic ARMAX model) and the co-simulation master's step
    loops (fmus/master) into the cache, only when sources changed."""
    from .fmu.build import MODELS, build_fmu, build_master

    for name in (*MODELS, "armax"):
        path = build_fmu(name, force=force)
        out.print(f"{name}: {path}", soft_wrap=True)
    out.print(f"master: {build_master(force=force)}", soft_wrap=True)


@app.command()
def specs() -> None:
    """List the bundled campaign specs (name and description); use a name wherever a SPEC is expected."""
    from .spec import SPEC_DIR, bundled_specs

    found = bundled_specs()
    if not found:
        raise FileNotFoundError(f"no bundled specs in {SPEC_DIR}")
    width = max(map(len, found))
    for name, desc in found.items():
        out.print(f"{name:<{width}}  {desc}", markup=False)
    out.print(f"[dim]({SPEC_DIR}; `flexjoint init DIR --spec NAME` copies one to edit)[/]")


@app.command()
def info(
    spec: Annotated[str | None, typer.Argument(help="a spec (path or bundled name) whose values to show")] = None,
    set_: SetOpt = None,
    as_json: Annotated[bool, typer.Option("--json", help="print the list as JSON")] = False,
) -> None:
    """List every plant, DAQ and controller parameter with its unit, value, default and range.

    Each is named table.name, as --set and the spec's tables name it; the value is the SPEC's, the default and the
    declared range the FMU's, and a sheet value the diagnosis recalibrates has the SPEC's 95 % uncertainty on it
    ([uncertainty])."""
    import json

    from rich.table import Table
    from rich.text import Text

    from . import spec as specmod
    from .parameters import parameters, value_text

    s = specmod.load(spec, set_ or []) if spec is not None else None
    rows = parameters(s)
    if as_json:
        out.print(json.dumps([r.to_dict() for r in rows], indent=1), markup=False, soft_wrap=True)
        return
    title = f"parameters of {s.name} (value: the spec's, else the default)" if s else "parameters"
    narrow = out.width < 110  # the description under the name instead of a column squeezed to a word a line
    if s is not None and narrow:
        title += "; in brackets the spec's 95 % uncertainty on a sheet value"
    t = Table(title=f"{title}; set one with --set table.name=value", title_justify="left")
    t.add_column("parameter", no_wrap=not narrow)
    t.add_column("unit", no_wrap=True)
    if s is not None:
        t.add_column("value", justify="right", no_wrap=True)
    t.add_column("default", justify="right", no_wrap=True)
    t.add_column("range", no_wrap=True)
    if s is not None and not narrow:
        t.add_column("95 %", no_wrap=True)  # the spec's uncertainty on a sheet value: the diagnosis's prior
    if not narrow:
        t.add_column("description", ratio=1)
    for r in rows:
        value = [value_text(r.default if r.spec is None else r.spec)] if s is not None else []
        name = Text(r.key, style="bold" if r.spec is not None else "")
        if narrow:  # the description (and the uncertainty) under the name
            name.append("\n  " + r.description + (f" ({r.within})" if r.within else ""), style="dim")
        within = [r.within] if s is not None and not narrow else []
        cells: list[Text | str] = [name, r.unit, *value, value_text(r.default), r.range, *within]
        cells += [] if narrow else [r.description]
        t.add_row(*cells)
    out.print(_fit(t))


@app.command()
def init(
    directory: Annotated[Path, typer.Argument(help="directory to copy the spec into (created if missing)")],
    spec: Annotated[str, typer.Option("--spec", help="bundled spec to copy (see `flexjoint specs`)")] = "lab",
    force: Annotated[bool, typer.Option(help="overwrite an existing file")] = False,
) -> None:
    """Copy a bundled spec into DIRECTORY to edit, then run it with `flexjoint campaign DIRECTORY/NAME.toml`."""
    from .spec import SPEC_DIR, SpecError, bundled_specs

    found = bundled_specs()
    name = spec.removesuffix(".toml")
    if name not in found:
        raise SpecError(f"no bundled spec {spec!r}; bundled: {', '.join(found) or 'none'}")
    dest = _out_dir(directory, "DIRECTORY") / f"{name}.toml"
    if dest.exists() and not force:
        raise FileExistsError(f"{dest} exists; pass --force to overwrite it")
    directory.mkdir(parents=True, exist_ok=True)
    dest.write_text((SPEC_DIR / f"{name}.toml").read_text(encoding="utf-8"), encoding="utf-8")
    out.print(f"{dest} (edit it, then: flexjoint campaign {dest} --out RUN)")


@app.command()
def campaign(
    spec: SpecArg,
    out_dir: Annotated[Path, typer.Option("--out", help="run directory to write")],
    set_: SetOpt = None,
    scheduler: SchedulerOpt = None,
    workers: WorkersOpt = None,
    force: ForceOpt = False,
) -> None:
    """Run a spec's experiments on the rig twin: writes manifest.json and data/<experiment>.parquet."""
    from . import spec as specmod
    from .clusterprocess import prestart

    s = specmod.load(spec, set_ or [])
    prestart(workers, scheduler, ["harness.rig.campaign"])  # the workers start while the campaign loads
    from .rundir import check_new_run

    check_new_run(out_dir, force)
    from .rig.campaign import run_campaign

    t0 = time.perf_counter()
    manifest = run_campaign(
        s, out_dir, progress=_progress("simulated"), workers=workers, scheduler=scheduler, force=force
    )
    out.print(f"{len(manifest.experiments)} experiments -> {out_dir} ({time.perf_counter() - t0:.2f} s)")


@app.command()
def ssp(
    spec: SpecArg,
    out_file: Annotated[Path, typer.Option("--out", help="SSP archive to write (FILE.ssp)")],
    experiment: Annotated[
        str | None,
        typer.Option(help="experiment to carry (default: the first closed-loop one of a spec with a controller)"),
    ] = None,
    loop: Annotated[str | None, typer.Option(help="open or closed: refuse an experiment of the other loop")] = None,
    set_: SetOpt = None,
) -> None:
    """Write a spec's rig running one experiment as SSP 1.0, for other co-simulation masters.

    The archive holds SystemStructure.ssd (plant, daq, controller, signal, their connections and parameters) and
    the FMUs under resources/."""
    from . import spec as specmod
    from .ssp import SUBSTEPS, ssp_experiment, write_ssp

    if out_file.is_dir():
        raise IsADirectoryError(f"--out {out_file}: a directory; give the SSP file to write, e.g. rig.ssp")
    s = specmod.load(spec, set_ or [])
    exp = ssp_experiment(s, experiment, loop)
    write_ssp(s, out_file, exp.name)
    out.print(
        f"{s.name} {exp.name} ({exp.loop} loop) -> {out_file}: master step {s.Ts / SUBSTEPS:g} s, plant {s.Ts:g} s",
        soft_wrap=True,
    )
    if int({**s.daq, **exp.daq}.get("delay_samples", 0)) == 0 and exp.loop == "closed":
        err.print(
            "note: daq.delay_samples = 0: the controller acts within the sample, which only a master that orders the "
            "FMUs by their feedthrough reproduces; one that steps them all at once adds a sample of delay",
            soft_wrap=True,
        )


@app.command("import")
def import_(
    files: Annotated[
        list[str],
        typer.Argument(
            help="records: .csv/.txt/.tsv, .mat (v5, v7.3), .parquet, each [NAME=]FILE (named NAME, else by its "
            "stem); one record in several files sharing its time base (a QUARC or Simulink To File per scope): "
            "[NAME=]FILE+FILE+..., a headerless file's columns as STEM:POSITION in --columns"
        ),
    ],
    out_dir: Annotated[Path, typer.Option("--out", help="run directory to write")],
    columns: Annotated[
        str | None, typer.Option(help="column map, e.g. time=t,Vm=u,hub=theta,tip=alpha (tip=-alpha: opposite sign)")
    ] = None,
    units: Annotated[str | None, typer.Option(help="units, e.g. theta=deg,alpha=rad,u=V,t=s")] = None,
    link_length: Annotated[float | None, typer.Option(help="link length in m (for tip deflections in m or mm)")] = None,
    counts_per_rev: Annotated[
        float | None,
        typer.Option(help="encoder counts per revolution (> 0): theta is an encoder's, step 360/counts deg"),
    ] = None,
    kp: Annotated[float | None, typer.Option("--kp", help="pot gain Kp in deg/V of the lab's DAQ")] = None,
    ke: Annotated[float | None, typer.Option("--ke", help="gauge gain Ke in deg/V of the lab's DAQ")] = None,
    calibration: Annotated[Path | None, typer.Option(help="calibration.json to carry (Kp, Ke, offsets)")] = None,
    controller: Annotated[
        str | None,
        typer.Option(
            help="controller of closed-loop records (a column mapped to ref), KIND:NAME=VALUE;... in quotes: "
            "'state_feedback:K=k_theta,k_alpha,k_theta_dot,k_alpha_dot;cutoff=HZ;u_limit=V' (V/rad, V s/rad; "
            "u = K (x_ref - x)) or 'pid:kp=V/rad;ki=V/(rad s);kd=V s/rad;cutoff=HZ;u_limit=V'; also ref_delay="
            "SAMPLES, alpha_bias=DEG; cutoff: velocity filter (default 50 Hz), u_limit 0: none. Default: identified "
            "from the record by least squares, with its R^2 (below 0.9: a warning, no closed-loop replay)"
        ),
    ] = None,
    theta_sensor: Annotated[
        str | None,
        typer.Option(
            help="theta's sensor: pot (wrap and dead band) or encoder (needs --counts-per-rev); default: encoder when "
            "theta is in counts or --counts-per-rev is given, else pot"
        ),
    ] = None,
    zero_alpha: Annotated[
        bool,
        typer.Option(help="zero the deflection on each record's quietest 0.25 s at rest (the gauge's zero), if any"),
    ] = False,
    force: ForceOpt = False,
) -> None:
    """Bring real records into a run directory: data/<name>.parquet, calibration.json, manifest.json. A column
    mapped to ref (--columns theta_ref_deg=ref) makes a record closed loop, its controller given or identified.
    Records of any rate >= 10 Hz, at least 2 s and 100 samples long (two folds)."""
    from .rig.controller import parse_controller
    from .rig.records import ImportOptions, calibration_option, import_records, parse_map

    opts = ImportOptions(
        columns=parse_map(columns, "--columns"),
        units=parse_map(units, "--units"),
        link_length=link_length,
        counts_per_rev=counts_per_rev,
        calibration=calibration_option(kp, ke, calibration),
        controller=parse_controller(controller) if controller else None,
        theta_sensor=theta_sensor,
        zero_alpha=zero_alpha,
    )

    def note(m: str) -> None:
        err.print(m if m.startswith(("warning: ", "fault: ")) else f"note: {m}", markup=False, soft_wrap=True)

    written = import_records(files, out_dir, opts, note=note, force=force)
    out.print(f"imported {len(written)} dataset(s) -> {out_dir}")


@app.command()
def identify(
    run_dir: Annotated[Path, typer.Argument(help="run directory (from campaign or import)")],
    set_: SetOpt = None,
    scheduler: SchedulerOpt = None,
    workers: WorkersOpt = None,
) -> None:
    """Calibrate, then the ARMAX grid per dataset, cross-validation and selection: grid.csv, models/."""
    from . import spec as specmod
    from .clusterprocess import prestart

    over = specmod.apply_overrides({}, set_ or []).get("identify", {})
    prestart(workers, scheduler, ["harness.ident.gridfit"])  # the workers start while the identification loads
    from .rundir import Manifest

    Manifest.load(run_dir)  # not a run directory: one line before the identification loads
    from .executor import session
    from .ident.doubled_rate import doubled_rate_check
    from .ident.identify import identify_run

    with session(workers, scheduler):  # the grid's tasks run on this session's cluster
        res, _, cal, ident = identify_run(run_dir, over, progress=_progress("grid"))
    from .render.summary import Summary

    g = res.grid
    s = Summary("grid.csv")
    zone = f"dead zone {cal.dead_zone_v:.4f} V" if math.isfinite(cal.dead_zone_v) else "dead zone not measured"
    assumed = " (lab 1's, assumed: no calibration given)" if cal.source.get("assumed") else ""
    s.line(
        f"Kp {cal.Kp:.4f} deg/V, Ke {cal.Ke:.4f} deg/V{assumed}, {zone}; "
        f"{len(g)} orders x datasets, {int(g['causal'].sum())} causal, {int(g['survivor'].sum())} survivors"
    )
    s.table(_table(crossval_table(res)))
    sel = g.loc[res.selected]
    s.line(f"selected ARMAX({sel.na},{sel.nb},{sel.nc},{sel.nk}) from {sel.dataset}: {res.rule}")
    if ident.get("doubled_rate", True):
        d = doubled_rate_check(run_dir, res.models[res.selected], ident, cal)
        if "skipped" not in d:
            s.line(
                f"doubled rate ({d['sample_rate_hz']:g} Hz, {d['experiment']}): 50 Hz model as is "
                f"{d['fit_model_50hz_as_is']:.1f} %, re-identified {d['fit_reidentified_100hz']:.1f} %"
            )
    s.close(f"full detail: {run_dir / 'grid.csv'}, {run_dir / 'models'}")
    s.print(out)


def _numbered_table(title: str, names: list[str], file: str) -> tuple[Table, list[str]]:
    """A rich table of datasets numbered as its columns (``names``; of more than
    :data:`harness.render.summary.MAX_ROWS` the first ones, the rest named as in ``file``), with a model column and
    an average column, and the datasets it shows."""
    from rich.table import Table

    from .render.summary import MAX_ROWS, more

    shown = names[: MAX_ROWS - 1] if len(names) > MAX_ROWS else names
    t = Table(title=title)
    t.add_column("model", no_wrap=True)
    for j in range(1, len(shown) + 1):
        t.add_column(str(j), justify="right", no_wrap=True)
    t.add_column("average", justify="right", no_wrap=True)
    t.caption = "datasets: " + ", ".join(f"{j} {n}" for j, n in enumerate(shown, 1))
    if len(shown) < len(names):
        t.caption += f", {more(len(names) - len(shown), file)}"
    return t, shown


def crossval_table(res: GridResult) -> Table:
    """Lab 1's table 2: each dataset's best model (rows) cross-validated on every dataset (columns); of more than
    :data:`harness.render.summary.MAX_ROWS` datasets the first ones (the average over all of them)."""
    t, shown = _numbered_table(
        "cross-validation fit % (rows: model of dataset i; columns: dataset j)", list(res.datasets), "grid.csv"
    )
    rows = [(n, res.best[n]) for n in shown if n in res.best]
    for i, (name, row_i) in enumerate([*rows, ("selected", res.selected)], 1):
        r = res.grid.loc[row_i]
        cells = [f"{r[f'cv_{n}']:.2f}" for n in shown]
        label = f"{i} ({r.na},{r.nb},{r.nc})" if name != "selected" else f"sel ({r.na},{r.nb},{r.nc})"
        t.add_row(label, *cells, f"{r['cv_mean']:.2f}")
    return t


def crossfit_table(df: Any) -> Table:
    """The cross-fit matrix (a pandas frame: each dataset's model and the selected one (rows) through its FMU on
    every dataset (columns) and their average), its datasets numbered; of more than
    :data:`harness.render.summary.MAX_ROWS` datasets the first ones (the average over all of them)."""
    names = [c for c in df.columns if c != "average"]
    t, shown = _numbered_table(
        "cross-fit through the exported FMUs, fit % (rows: model of dataset i; columns: dataset j)", names,
        "crossfit.csv",
    )  # fmt: skip
    number = {n: str(j) for j, n in enumerate(names, 1)}
    for model in [*(m for m in df.index if m in shown), *(m for m in df.index if m not in names)]:
        cells = [f"{df.loc[model, n]:.2f}" for n in (*shown, "average")]
        t.add_row(number.get(model, str(model)), *cells)
    return t


@app.command()
def accept(
    run_dir: Annotated[
        Path, typer.Argument(help="run directory with an identified model, or what predict or design wrote")
    ],
    min_fit: Annotated[float | None, typer.Option(help="override accept.min_fit (%)")] = None,
    min_average_fit: Annotated[float | None, typer.Option(help="override accept.min_average_fit (%)")] = None,
    specs: Annotated[
        str | None,
        typer.Option(
            help="a prediction or design: judge these specs instead of its own (settling=1.5,overshoot=5,...)"
        ),
    ] = None,
) -> None:
    """Exit 0 when the selected model meets the spec's fit thresholds, 1 (naming the failing cells) when not. On what
    predict or design wrote (prediction.json): 0 when every spec's predicted band meets its limit, 1 naming those that
    do not."""
    if (run_dir / "prediction.json").is_file():
        from .prediction import accept_prediction

        ok, lines = accept_prediction(run_dir, specs)
        if ok:
            out.print("accepted: " + "; ".join(lines), soft_wrap=True)
            return
        print("rejected: " + "; ".join(lines), file=sys.stderr)
        raise typer.Exit(1)
    if specs is not None:
        raise ValueError(f"--specs judges a prediction; {run_dir} holds no prediction.json")
    from .ident.accept import accept as gate

    over = {k: v for k, v in (("min_fit", min_fit), ("min_average_fit", min_average_fit)) if v is not None}
    v = gate(run_dir, over)
    if v.passed:
        out.print(
            f"accepted: every dataset >= {v.thresholds['min_fit']:g} %, average {v.average:.2f} % "
            f">= {v.thresholds['min_average_fit']:g} % ({v.source})"
        )
        return
    print(f"rejected ({v.source}): " + "; ".join(v.failures), file=sys.stderr)
    raise typer.Exit(1)


RigArg = Annotated[
    str,
    typer.Argument(help="the rig: a diagnosis directory (its identified twin) or a spec (a path or a bundled name)"),
]


def prediction_screen(doc: dict, directory: Path, n: int) -> Summary:
    """What ``flexjoint predict`` prints (:mod:`harness.render.summary`'s rule: one screen): each metric's median
    [95 % band] (and measured), the median's fit to the record, the specs judged, where the prediction is."""
    from .render.summary import Summary, joined
    from .render.tables import fmt_any

    s = Summary("prediction.json")
    metrics, measured = [], False
    for m, b in doc["metrics"].items():
        if m.startswith("stop_error_") or m == "ring_hz":
            continue
        measured = measured or b.get("measured") is not None
        meas = f", measured {fmt_any(b['measured'])}" if b.get("measured") is not None else ""
        metrics.append(f"{m} {fmt_any(b['median'])} [{fmt_any(b['lo'])}..{fmt_any(b['hi'])}]{meas}")
    s.line("each metric's median [95 % band]" + (", measured on the record:" if measured else ":"))
    s.items(metrics, 2)
    if fit := doc.get("fit_pct"):
        s.line(f"median's fit theta {fit['theta']:.1f} %, alpha {fit['alpha']:.1f} %")
    if doc.get("specs"):
        s.line(f"specs: {'met' if doc['passed'] else 'NOT met'} ("
               + joined((v["spec"] for v in doc["specs"].values()), "prediction.json") + ")")  # fmt: skip
    s.close(f"{n} members -> {directory} (prediction.json, report.md)")
    return s


@app.command()
def predict(
    rig: RigArg,
    out_dir: Annotated[Path, typer.Option("--out", help="directory for prediction.json, report.md, figures/")],
    controller: Annotated[
        str | None,
        typer.Option(help="the controller, KIND:NAME=VALUE;... in quotes, as flexjoint import takes it"),
    ] = None,
    controller_from: Annotated[
        Path | None,
        typer.Option(
            help="a design's directory (controller.toml), a TOML file with a [controller] table, or a run "
            "(its closed-loop record's controller)"
        ),
    ] = None,
    reference: Annotated[
        str | None,
        typer.Option(
            help="a run (its closed-loop record's reference) or a signal KIND:NAME=VALUE;...;duration=S "
            "(default: the record's, else square:f=0.25;amplitude=30;duration=8)"
        ),
    ] = None,
    record: Annotated[
        Path | None,
        typer.Option(
            help="a closed-loop run: its reference and controller unless given, its behaviour measured "
            "beside the bands and the median's fit to it"
        ),
    ] = None,
    n: Annotated[int, typer.Option("--n", min=1, help="members of the ensemble")] = 200,
    seed: Annotated[int, typer.Option("--seed", min=0, help="seed of the parameter and noise draws")] = 0,
    specs: Annotated[
        str | None,
        typer.Option(help="specs to judge: settling=S,overshoot=PCT,alpha=DEG,voltage=V,stop=DEG,ring=DEG,band=PCT"),
    ] = None,
    scheduler: SchedulerOpt = None,
    workers: WorkersOpt = None,
) -> None:
    """Predict a controller's loop on the rig as an ensemble (parameter draws from the rig's intervals, noise draws):
    each behaviour metric's median and 95 % band, with a record the measured ones beside them: prediction.json."""
    import json

    from .clusterprocess import prestart
    from .loopspecs import LoopSpecs, controller_source
    from .rig.controller import parse_controller

    _out_dir(out_dir)
    judged = LoopSpecs.parse(specs) if specs else None
    controller_source(controller, str(controller_from) if controller_from else None, record is not None)
    if controller is not None:
        parse_controller(controller)  # a mistake in which controller, or in it, is told before the twin loads
    from .rundir import check_rig

    check_rig(rig)  # a RIG that names no rig: one line before a cluster starts
    prestart(workers, scheduler, ["harness.prediction"])  # the workers start while the twin loads
    from .prediction import controller_from as pick_controller
    from .prediction import loop_rate, reference_from
    from .prediction import predict as run_predict
    from .render.prediction import write_prediction
    from .twin import load_record, load_twin

    rec = load_record(record) if record is not None else None
    ctrl = pick_controller(controller, str(controller_from) if controller_from else None, rec)
    twin = load_twin(rig)
    ref = reference_from(reference, loop_rate(ctrl, twin), rec)
    pred = run_predict(
        twin, ctrl, ref, n=n, seed=seed, record=rec, specs=judged, progress=_progress("predict"),
        **_parallel(workers, scheduler),
    )  # fmt: skip
    path = write_prediction(pred, out_dir)
    doc = json.loads((out_dir / "prediction.json").read_text())
    prediction_screen(doc if judged is not None else {**doc, "specs": None}, path.parent, n).print(out)


@app.command()
def design(
    rig: RigArg,
    method: Annotated[str, typer.Option(help="lqr, lqg (Kalman filter in the controller FMU) or pd")],
    out_dir: Annotated[Path, typer.Option("--out", help="directory for design.json, controller.toml, loop.ssp")],
    specs: Annotated[
        str | None,
        typer.Option(
            help="settling=S,overshoot=PCT,alpha=DEG,voltage=V,stop=DEG,ring=DEG,band=PCT (default the "
            "Quanser courseware's settling=1.5,overshoot=5,band=4)"
        ),
    ] = None,
    weights: Annotated[
        str | None, typer.Option(help="lqr/lqg weights q=Q1,Q2,Q3,Q4;r=R[;w=W] (default: searched to the specs)")
    ] = None,
    rate: Annotated[float | None, typer.Option(help="the controller's sample rate [Hz] (default the rig's)")] = None,
    cutoff: Annotated[
        float | None,
        typer.Option(
            help="lqr/pd: the velocity filters' cutoff [Hz] (default the diagnosed record's controller's, else 25)"
        ),
    ] = None,
    reference: Annotated[
        str | None,
        typer.Option(
            help="a run or a signal KIND:NAME=VALUE;...;duration=S to design and check for (default: the "
            "diagnosed record's at its rate, else square:f=0.25;amplitude=30;duration=8)"
        ),
    ] = None,
    n: Annotated[int, typer.Option("--n", min=1, help="members of the prediction that checks each design")] = 100,
    seed: Annotated[int, typer.Option("--seed", min=0, help="seed of the prediction's draws")] = 0,
    scheduler: SchedulerOpt = None,
    workers: WorkersOpt = None,
) -> None:
    """Design a controller on the rig (its identified twin or a spec) to a lab's specs, checked by predicting its loop
    with the rig's effects, intervals and noise: design.json, controller.toml, loop.ssp and the prediction."""
    from .clusterprocess import prestart
    from .loopspecs import METHODS, LoopSpecs, parse_weights

    _out_dir(out_dir)
    if method not in METHODS:
        raise ValueError(f"--method {method!r} unknown; valid: {', '.join(METHODS)}")
    wt = parse_weights(weights, method) if weights is not None else None
    judged = LoopSpecs.parse(specs) if specs is not None else None
    from .rundir import check_rig

    check_rig(rig)  # a RIG that names no rig: one line before a cluster starts
    prestart(workers, scheduler, ["harness.prediction"])  # the workers start while the search runs
    from .design import design as run_design
    from .executor import session
    from .prediction import reference_from
    from .render.prediction import write_design
    from .rundir import DataError
    from .twin import load_record, load_twin

    twin = load_twin(rig)
    hz = float(rate or twin.sample_rate)
    rec = None
    if reference is None and twin.run is not None:
        with contextlib.suppress(DataError):  # a diagnosed run without a closed-loop record: the default square
            rec = load_record(twin.run)
        rec = rec if rec is not None and abs(rec.Ts * hz - 1.0) < 1e-9 else None
    ref = reference_from(reference, hz, rec)
    if cutoff is None and rec is not None and rec.controller is not None and rec.controller.kind != "lqg":
        cutoff = rec.controller.cutoff  # the lab's own velocity filter
    with session(workers, scheduler):  # one cluster for every round's prediction
        d = run_design(
            twin, method, ref, specs=judged, weights=wt, rate=hz, cutoff=cutoff, n=n, seed=seed,
            progress=_progress("design"),
        )  # fmt: skip
    path = write_design(d, twin, out_dir)
    design_screen(d.to_json(), method, path.parent).print(out)


def design_screen(doc: dict, method: str, directory: Path) -> Summary:
    """What ``flexjoint design`` prints (:mod:`harness.render.summary`'s rule: one screen): the controller's
    parameters and disk margin, each spec predicted (met or not), where the design is."""
    from .render.summary import Summary

    s = Summary("design.json")
    s.line(f"{method}: {doc['parameters']}; disk margin {doc['linear']['disk_margin']:.3g}")
    s.items([f"{v['spec']}: predicted {v['predicted']:.3g} ({'met' if v['met'] else 'NOT met'})"
             for v in (doc["specs"] or {}).values()])  # fmt: skip
    s.close(f"-> {directory} (controller.toml, loop.ssp, design.json, prediction.json)")
    return s


@app.command()
def crossfit(run_dir: Annotated[Path, typer.Argument(help="run directory with identified models")]) -> None:
    """Export every model as an FMU and score each on every dataset through fmpy: crossfit.csv."""
    from .ident.crossfit import crossfit_run
    from .render.summary import Summary

    df = crossfit_run(run_dir, progress=_progress("crossfit"))
    s = Summary("crossfit.csv")
    s.table(_table(crossfit_table(df)))
    s.close(f"full detail: {run_dir / 'crossfit.csv'}")
    s.print(out)


@app.command()
def diagnose(
    real: Annotated[Path, typer.Option("--real", help="run directory of the rig (campaign or import)")],
    sim: Annotated[str, typer.Option("--sim", help="spec of the simulation being judged")] = "nominal",
    out_dir: Annotated[Path | None, typer.Option("--out", help="where to write diagnosis.json (default REAL)")] = None,
    replay: Annotated[
        str,
        typer.Option(
            help="how experiments are re-simulated: auto (closed-loop records through their controller, or by "
            "multiple shooting without one; open-loop ones as logged), closed, shooting or open for all"
        ),
    ] = "auto",
    scheduler: SchedulerOpt = None,
    workers: WorkersOpt = None,
    force: Annotated[bool, typer.Option("--force", help="write into --out even when it is another run")] = False,
    engine: Annotated[
        str,
        typer.Option(
            help="replay (today's diagnosis) or likelihood: today's, and beside it the likelihood engine's maximum-"
            "likelihood fit of the linear model (likelihood.json) and its missing force (force_picture.png, .parquet)"
        ),
    ] = "replay",
) -> None:
    """Where the sim-to-real gap lies, which unmodelled effect causes it, how far it shrinks: diagnosis.json."""
    from . import spec as specmod
    from .clusterprocess import prestart

    if out_dir is not None:
        _out_dir(out_dir)
    specmod.load(sim)  # a bad --sim: one line before anything starts
    if engine not in ("replay", "likelihood"):
        raise typer.BadParameter(f"--engine {engine!r}: replay or likelihood")
    prestart(workers, scheduler, ["harness.diagnosis.tasks"])  # the workers start while the diagnosis loads
    from .rundir import Manifest

    Manifest.load(real)  # not a run directory: one line before the diagnosis loads
    if engine == "likelihood":  # fitted first: records it cannot fit are one line before anything is written
        from .likelihood.unit import fit_run

        unit = fit_run(real, sim, progress=_progress("likelihood"))
    from .diagnosis.diagnose import diagnose_run

    d = diagnose_run(
        real, sim, out_dir, progress=_progress("diagnose"), replay=replay, force=force, **_parallel(workers, scheduler)
    )
    diagnosis_screen(d, out_dir or real).print(out)
    if engine == "likelihood":
        from .diagnosis.decide import decide
        from .likelihood.unit import with_likelihood, write_likelihood
        from .render.force import write_force_views
        from .render.summary import Summary
        from .rundir import RunDir

        with_likelihood(d, unit).write(RunDir(out_dir or real).diagnosis)  # each model tried: its likelihood too

        _, png = write_force_views(out_dir or real, unit.picture, unit.missing_force.words(), unit.curve)
        verdict = decide(unit)
        s = Summary("likelihood.json")
        s.lines(unit.summary())
        s.lines([f"  verdict by likelihood: {verdict.verdict}: {verdict.reason}"])
        s.close(f"the whole fit: {write_likelihood(out_dir or real, unit, verdict.to_json())}")
        s.close(f"the missing force drawn: {png} (its traces: force_picture.parquet)")
        s.print(out)


def _parallel(workers: int | None, scheduler: str | None) -> dict:
    """``workers=`` / ``scheduler=`` keyword arguments for a parallel library call, only those given."""
    return {k: v for k, v in (("workers", workers), ("scheduler", scheduler)) if v is not None}


@app.command()
def sweep(
    spec: SpecArg,
    vary: Annotated[
        list[str],
        typer.Option(
            "--vary",
            help="table.name=DIST: normal(mu,sigma), uniform(lo,hi), lognormal(median,s), triangular(lo,mode,hi)",
        ),
    ],
    out_dir: Annotated[Path, typer.Option("--out", help="directory for sweep.parquet, sweep.json, report.md")],
    n: Annotated[int, typer.Option("--n", min=1, help="number of rigs")] = 50,
    seed: Annotated[int, typer.Option("--seed", min=0, help="seed of the draws and of each rig's noise")] = 0,
    model: Annotated[Path | None, typer.Option("--model", help="score this models/<m>.json on every rig")] = None,
    orders: Annotated[str | None, typer.Option("--orders", help="identify one order na,nb,nc per rig")] = None,
    sampler: Annotated[str, typer.Option("--sampler", help="lhs (Latin hypercube) or sobol")] = "lhs",
    set_: SetOpt = None,
    scheduler: SchedulerOpt = None,
    workers: WorkersOpt = None,
) -> None:
    """Monte Carlo over rig tolerances: N rigs, each one's campaign, identification and acceptance, as tasks."""
    from . import spec as specmod
    from .sweep import run_sweep

    _out_dir(out_dir)
    s = specmod.load(spec, set_ or [])
    doc = run_sweep(
        s,
        vary,
        n,
        seed,
        out_dir,
        model=model,
        orders=orders,
        sampler=sampler,
        workers=workers,
        scheduler=scheduler,
        progress=_progress("done"),
    )
    p, sens = doc["summary"]["pass"], doc["summary"]["sensitivity"]
    top = sens["ranking"][0]
    most = (
        f"most sensitive: {top['param']} (S1 {top['s1']:.2f})"
        if math.isfinite(top["s1"])
        else f"sensitivity indices: n = {p['n']} rigs too few"
    )
    from .render.summary import Summary

    screen = Summary("sweep.json")
    screen.line(
        f"{p['n']} rigs: {p['passed']} pass = {100 * p['rate']:.1f} % (95 % CI {100 * p['ci95'][0]:.1f}-"
        f"{100 * p['ci95'][1]:.1f} %); {most}; {doc['wall_s']:.1f} s -> {out_dir}"
    )
    screen.print(out)


@app.command()
def report(
    run_dir: Annotated[
        Path, typer.Argument(help="what run, campaign, import, identify, diagnose (--out), sweep or blindtest wrote")
    ],
    rrd: Annotated[Path | None, typer.Option("--rrd", help="recording file (default DIR/run.rrd)")] = None,
    spawn: Annotated[bool, typer.Option("--spawn", help="open a Rerun viewer")] = False,
    connect: Annotated[str | None, typer.Option("--connect", help="stream to a running viewer at URL")] = None,
) -> None:
    """Write report.md, figures/ and the Rerun recording for whatever a command wrote, each section from what the
    directory holds."""
    from .render.directory import report_directory

    _, path, recording = report_directory(run_dir, rrd=rrd, spawn=spawn, connect=connect)
    out.print(f"{path} ({path.stat().st_size / 1024:.1f} kB), {path.parent / 'figures'}, {recording}")


def interval_text(lo: float, hi: float) -> str:
    """An interval with enough significant digits (4 to 10) for its ends to differ: 0.49988..0.49992, not
    0.4999..0.4999."""
    for digits in range(4, 11):
        a, b = f"{lo:.{digits}g}", f"{hi:.{digits}g}"
        if a != b:
            break
    return f"{a}..{b}"


def diagnosis_summary(d: Diagnosis) -> str:
    """The terminal's summary of a diagnosis (:func:`diagnosis_screen`) as text, one line per line, unwrapped."""
    return str(diagnosis_screen(d))


def _moved(p: Any) -> tuple[int, float]:
    """A parameter's place in "the parameters that moved most": first those found off the spec beyond their 95 %
    interval, then the others the data determine, then those they do not; in each, the largest move first (the log
    of fitted over the spec's value; off a spec of 0, an offset, the largest when beyond its interval)."""
    lo, hi = p.ci95
    undetermined = p.identifiable is False or "not determined" in (p.finding or "")
    beyond = p.off_spec and math.isfinite(lo) and math.isfinite(hi) and not lo <= p.nominal <= hi
    kind = 2 if undetermined else 0 if beyond else 1
    if p.nominal == 0 or p.fitted == 0 or p.fitted / p.nominal <= 0:
        moved = math.inf if beyond else 0.0
    else:
        moved = abs(math.log(p.fitted / p.nominal))
    return kind, -moved


def diagnosis_screen(d: Diagnosis, directory: Path | None = None) -> Summary:
    """What ``flexjoint diagnose`` prints (:mod:`harness.render.summary`'s rule: one screen): the verdict, the gap
    (as given, recalibrated, with the effects, the noise floor; per channel and on every experiment), the effects,
    the parameters that moved most, each record's fit, sensors and behaviour, the caveats' first sentences, how
    experiments were replayed, and where the full detail is (``directory``'s diagnosis.json and report.md)."""
    from .render.gap_text import behaviour_outside
    from .render.summary import Summary, brief, joined, more

    where = "diagnosis.json"
    s = Summary(where)
    s.line(f"verdict: {d.verdict}")
    if d.calibration.gauge_delay_s:
        s.line(f"data: {brief(d.calibration.gauge_delay_method or '', where)}", 2)
    for e in cut_effects(d, where):
        s.line(e, 2)
    dec = d.gap.decomposition
    fits = {"before": dec.before, "after recalibration": dec.after_recalibration,
            "after effects": dec.after_effects, "noise floor": dec.noise_floor}  # fmt: skip
    s.line("held-out fit: " + ", ".join(f"{k} {100 * (1 - g):.2f} %" for k, g in fits.items()))
    if dec.channels:
        s.line("held-out fit per channel: " + ", ".join(
            f"{k.replace('_', ' ')} " + " ".join(f"{c} {v:.1f} %" for c, v in by.items())
            for k, by in dec.channel_stages()
        ) + ("; what is left is within the replays' own spread" if dec.at_floor()
             else f"; the gap is in {dec.gap_channel()}"))  # fmt: skip
    gap = d.gap
    s.line(f"gap: fit {gap.before.fit_pct:.2f} % -> {gap.after.fit_pct:.2f} %, total shrink {gap.shrink_pct:.1f} %")
    found = [(n, p) for n, p in d.parameters.items() if p.finding is not None]
    kept = [n for n, p in found if p.kept]
    found = sorted(((n, p) for n, p in found if not p.kept), key=lambda x: _moved(x[1]))
    if found:
        s.line("parameters that moved most:")
        lines = []
        for name, p in found:
            lo, hi = p.ci95
            shown = p.kept or "95 % interval" in (p.finding or "")  # an undetermined one's finding gives it already
            lines.append(f"{name}: {p.finding}" + ("" if shown else f" (95 % interval {interval_text(lo, hi)})"))
        s.items(lines, 2)
    if kept:
        s.line("kept at the spec's values (recalibrating them did not improve the held-out fit): "
               + joined(kept, where))  # fmt: skip
    s.items([f"caveat: {brief(c, where)}" for c in d.caveats or []])
    kinds: dict[str, list[str]] = {}
    for r in (d.replays or {}).values():
        kinds.setdefault(r["replay"], []).append(r["reason"])
    for kind, why in sorted(kinds.items()):  # each kind's first reason; the others (their R^2) in the file
        n, other = len(why), len(set(why)) - 1
        s.line(f"replay: {kind}" + (f", {n} experiments" if n > 1 else "") + f" ({why[0]})"
               + (f", {more(other, where).replace('more', 'more reasons')}" if other else ""))  # fmt: skip
    if d.gap.records:
        s.line("each record's fit, recalibrated alone -> with the joint parameters: " + joined(
            (f"{n} {r['own']:.1f} -> {r['joint']:.1f} %" for n, r in d.gap.records.items()), where))  # fmt: skip
    if d.sensors:
        s.line("sensors, each record's gauge offset: " + joined(
            (f"{n} {r.gauge_offset_deg[0]:.4g} deg" + (f" ({r.gauge_offset_deg[1]:.4g}..{r.gauge_offset_deg[2]:.4g})"
             if math.isfinite(r.gauge_offset_deg[1]) else " (least squares, open loop)")
             for n, r in d.sensors.items()), where))  # fmt: skip
    speed = d.where.get("speed_per_volt") if isinstance(d.where, dict) else None
    if isinstance(speed, dict) and speed.get("line") and speed.get("trend") != "undetermined":  # else in the report
        s.line(f"where, in amplitude: {brief(str(speed['line']), where)}")
    outside = behaviour_outside(d)
    if outside and d.behaviour:
        s.line("behaviour, each record's step metrics inside the replays' 95 % band: " + joined(
            (f"{n} {100.0 * d.behaviour[n].coverage:.0f} %" + (f" ({len(ms)} outside)" if ms else "")
             for n, ms in outside.items()), where))  # fmt: skip
    if directory is not None:
        report = directory / "report.md"
        s.close(f"full detail: {directory / 'diagnosis.json'}, " + (
            f"{report}" if report.is_file() else f"report.md (flexjoint report {directory})"))  # fmt: skip
    return s


def cut_effects(d: Diagnosis, where: str) -> list[str]:
    """The effects found, in the order they were added, each with its fitted parameters and shrink (and a line of
    its parameter against the record's own range), cut after :data:`harness.render.summary.MAX_ITEMS`."""
    from .render.summary import MAX_ITEMS, more

    lines = []
    for e in d.effects[:MAX_ITEMS]:
        params = ", ".join(f"{k}={v:.4g}" for k, v in e.params.items())
        lines.append(f"+ {e.effect} ({params}): shrink {e.shrink_pct:.1f} % on held-out experiments")
        if e.against_record:
            lines.append(f"  {e.against_record}")
    if len(d.effects) > MAX_ITEMS:
        lines.append(more(len(d.effects) - MAX_ITEMS, where))
    return lines


@app.command()
def blindtest(
    n: Annotated[int, typer.Option("--n", help="number of hidden-effect rigs")] = 40,
    seed: Annotated[int, typer.Option("--seed", help="seed of the draws")] = 0,
    out_dir: Annotated[Path, typer.Option("--out", help="directory for blindtest.json")] = Path("."),
    family: Annotated[
        list[str] | None,
        typer.Option(
            "--family",
            help="twin, nuisance, independent, closed (the nuisance rigs under state feedback, 500 Hz and 1 kHz "
            "records replayed in closed loop), wrong_sheet (closed-loop rigs whose drive, Ks and gauge gain are off "
            "their sheet, the data converted with the sheet's gauge gain), real_like (units of the CU arm logged as "
            "real records are: gauge offsets, a ringing start, a command offset, two controllers, imported with "
            "--zero-alpha); the last two only when named; repeat; default the first four",
        ),
    ] = None,
    quick: Annotated[bool, typer.Option("--quick", help="the shortened blind campaign (12 s experiments)")] = False,
    keep: Annotated[bool, typer.Option("--keep", help="keep the case run directories in OUT/blind_cases")] = False,
    scheduler: SchedulerOpt = None,
    workers: WorkersOpt = None,
    engine: Annotated[
        str,
        typer.Option(help="replay (today's diagnosis) or likelihood (the likelihood engine's fit and verdict)"),
    ] = "replay",
) -> None:
    """Score the diagnoser on rigs with hidden effects: blindtest.json.

    Each rig hides none, one or two effects, or one outside the library. Families: our twin, the twin with its linear
    parameters off the datasheet, an independent simulator, the off-datasheet twin in closed loop and, when named,
    closed-loop rigs off their sheet."""
    from .diagnosis.blindtest import FAMILIES, not_fitted_line
    from .diagnosis.blindtest import blindtest as run_blind

    fams = tuple(family) if family else FAMILIES
    if engine not in ("replay", "likelihood"):
        raise typer.BadParameter(f"--engine {engine!r}: replay or likelihood")
    res = run_blind(
        n, seed, out_dir, progress=_progress("blindtest"), families=fams, quick=quick, keep=keep, engine=engine,
        **_parallel(workers, scheduler),
    )  # fmt: skip
    from .render.summary import Summary

    s = Summary("blindtest.json")
    s.table(_table(blindtest_table(res["totals"])))
    if line := not_fitted_line(res["totals"]):
        s.line(line)
    s.items([f"skipped family {why}" for why in res.get("skipped", [])])
    s.close(f"{res['n']} cases in {res['timing_s']:.0f} s -> {Path(out_dir) / 'blindtest.json'}")
    s.print(out)


def blindtest_table(tot: dict[str, Any]) -> Table:
    """The blind test's scores per family and pooled, each share with its 95 % interval and count."""
    from rich.table import Table

    def cell(share: dict) -> str:
        if not share["n"]:
            return "-"
        lo, hi = share["ci95"]
        return f"{share['pct']:.0f} % [{lo:.0f}-{hi:.0f}] ({share['k']}/{share['n']})"

    from .diagnosis.blindtest import score_share, shown_rows
    from .render.summary import joined

    cols = [*tot.get("families", {}), "pooled"]
    t = Table(title="blind test (share, 95 % Wilson interval, count)")
    t.add_column("score")
    for c in cols:
        t.add_column(c, justify="right")
    for label in shown_rows(tot):
        t.add_row(label, *[cell(score_share(tot["families"][c] if c != "pooled" else tot, label)) for c in cols])

    def verdict(v: dict) -> str:
        if not v.get("n"):
            return "no cases"
        if not v.get("enough", True):
            return f"too few cases to tell: {v['n']}"
        return "met" if v["met"] else "NOT met"

    targets = (f"{k} >= {v['target']:g} ({verdict(v)})" for k, v in tot["targets"].items())
    t.caption = "targets: " + joined(targets, "blindtest.json", "; ")
    return t


# the modules of flexjoint run's tasks: campaign, ARMAX grid, diagnosis, report figures
PIPELINE_TASKS = ("harness.rig.campaign", "harness.ident.gridfit", "harness.diagnosis.tasks", "harness.render.figures")


@app.command()
def run(
    spec: Annotated[str, typer.Option("--spec", help="campaign spec")] = "lab",
    out_dir: Annotated[Path | None, typer.Option("--out", help="run directory (default runs/<timestamp>)")] = None,
    sim: Annotated[str, typer.Option("--sim", help="simulation spec the rig is diagnosed against")] = "nominal",
    set_: SetOpt = None,
    rrd: Annotated[Path | None, typer.Option("--rrd", help="recording file (default RUN/run.rrd)")] = None,
    spawn: Annotated[bool, typer.Option("--spawn", help="open a Rerun viewer")] = False,
    connect: Annotated[str | None, typer.Option("--connect", help="stream to a running viewer at URL")] = None,
    scheduler: SchedulerOpt = None,
    workers: WorkersOpt = None,
    force: ForceOpt = False,
) -> None:
    """The whole pipeline: build, campaign, calibrate, identify, export, cross-fit, diagnose, report, Rerun."""
    from . import spec as specmod
    from .clusterprocess import prestart

    specmod.load(spec, set_ or [])  # a bad spec, or one too large for this machine, fails before any work
    prestart(workers, scheduler, PIPELINE_TASKS)  # the workers start (and import every stage's tasks) while it loads
    from .executor import session
    from .rundir import check_new_run

    if out_dir is None:
        out_dir = Path("runs") / time.strftime("%Y%m%d-%H%M%S")
    check_new_run(out_dir, force)
    from .pipeline import run_pipeline

    with session(workers, scheduler):  # one cluster for every parallel step of the pipeline
        progress = _progress("run")
        result = run_pipeline(
            spec, out_dir, set_ or [], sim=sim, rrd=rrd, spawn=spawn, connect=connect, progress=progress,
            status=progress.status, force=force,  # type: ignore[attr-defined]
        )  # fmt: skip
    run_screen(result, out_dir).print(out)


def run_screen(result: PipelineResult, run_dir: Path) -> Summary:
    """What ``flexjoint run`` prints (:mod:`harness.render.summary`'s rule: one screen): the pipeline's summary and
    stages, then the diagnosis's (:func:`diagnosis_screen`) of ``run_dir``."""
    from .diagnosis.result import Diagnosis
    from .render.summary import Summary

    s = Summary("report.md")
    s.line(result.summary)
    s.line("stages: " + ", ".join(f"{k} {v:.1f} s" for k, v in result.stages.items()))
    s.extend(diagnosis_screen(Diagnosis.load(run_dir), run_dir))
    return s


@app.command()
def bench(
    out_file: Annotated[Path, typer.Option("--out", help="JSON file to write")] = Path("bench.json"),
    quick: Annotated[bool, typer.Option(help="fewer repetitions")] = False,
    table: Annotated[bool, typer.Option("--table", help="add the off-datasheet diagnosis table (~3 min)")] = False,
    blind: Annotated[
        int, typer.Option("--blind", min=0, help="add the full blind test of N rigs (~20 min for 45)")
    ] = 0,
    vs_commit: Annotated[
        str | None,
        typer.Option(
            "--vs-commit",
            help="time every command side by side with this commit of the clone (a git worktree made and removed)",
        ),
    ] = None,
    only: Annotated[
        str | None,
        typer.Option(
            help="only these, comma-separated: commands, campaign, armax, executor, parallel, unit, predict, "
            "likelihood, rule"
        ),
    ] = None,
) -> None:
    """Measure speed against the named peers (fmpy simulate_fmu, sippy-unipi, another commit) and write JSON."""
    from . import clone
    from .rundir import write_json

    bench = clone.load_package("benchmarks.bench")
    if bench is None:
        raise typer.BadParameter(
            f"the benchmarks live in a clone of the repository ({clone.ROOT / 'benchmarks'} not found)"
        )
    steps = tuple(x.strip() for x in only.split(",") if x.strip()) if only is not None else None
    result = bench.run_all(
        quick=quick, progress=_progress("bench"), table=table, blind=blind, vs_commit=vs_commit, only=steps
    )

    write_json(out_file, result)
    out.print_json(data=result)


# Ctrl-C: the first raises KeyboardInterrupt in the command (typer turns it into exit code 130, main into one line);
# another while that one is being handled (a cluster shutting down), or one while the process ends, ends it at once
# with the same line and code. ``_raised``: the first was raised; ``_said``: the line is printed; ``_ending``: at exit.
_raised = _said = _ending = False


def _say_interrupted() -> None:
    """The one line of an interrupt, printed once."""
    global _said
    if not _said:
        _said = True
        print("error: interrupted", file=sys.stderr, flush=True)


def _now_ending() -> None:
    global _ending
    _ending = True


def _quiet_workers_on_interrupt() -> None:
    """Ctrl-C reaches every process of the terminal's group: the command itself raises KeyboardInterrupt once, then
    ends at once on the next, while a forked child (the bench's machine-baseline processes) ends at once, by the
    signal, instead of printing its own traceback. Dask's workers are spawned, not forked, and do not run this: they
    get the signal too and, as of now, a worker's process prints its own KeyboardInterrupt traceback."""
    main_pid = os.getpid()

    def on_sigint(signum: int, frame: FrameType | None) -> None:
        global _raised
        if os.getpid() != main_pid:
            signal.signal(signal.SIGINT, signal.SIG_DFL)
            os.kill(os.getpid(), signal.SIGINT)
        if not (_raised or _ending):
            _raised = True
            # the client's event loop may trip over the interrupt in its own callbacks (distributed's sync() cancels
            # a future it had not assigned yet: a NameError logged by tornado): the command's one line stands alone
            logging.getLogger("tornado.application").disabled = True
            raise KeyboardInterrupt
        try:
            if _status is not None and err.is_terminal:
                sys.stderr.write("\r\x1b[2K\x1b[?25h")  # end the live status line and show the cursor it hid
            _say_interrupted()
        finally:
            os._exit(130)

    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, on_sigint)


def main() -> None:
    """Console entry point. Typer handles usage errors, --help and exit codes itself (standalone mode); a user
    error raised by the library (bad spec, bad data, a failing FMU) becomes one line on stderr and exit code 2;
    Ctrl-C one line and exit code 130, whenever it comes (``harness.__main__`` answers one while this module
    loads)."""
    global _raised, _said
    _raised = _said = False
    _quiet_workers_on_interrupt()
    try:
        try:
            app()
        except KeyboardInterrupt:  # outside typer's own handling (while it builds the command line)
            raise SystemExit(130) from None
        except Exception as e:
            if _raised:  # the library's clean-up turned the interrupt into an error of its own
                raise SystemExit(130) from None
            if not isinstance(e, _user_errors()):
                raise
            _stop_status()
            msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            print(f"error: {msg}", file=sys.stderr)
            sys.exit(2)
    except SystemExit as e:
        if e.code == 130:
            _stop_status()
            _say_interrupted()
        raise
    finally:
        _stop_status()
        atexit.unregister(_now_ending)
        atexit.register(_now_ending)  # registered last, run first: a Ctrl-C in the exit's clean-up ends it at once


if __name__ == "__main__":
    main()
