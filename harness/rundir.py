"""The run directory: its layout (:class:`RunDir`, every path named once), its datasets (Parquet files with
columns ``t, u, theta_v, alpha_v``, + ``theta, alpha`` in degrees: the true angles of simulated data, the
recorded ones of imports) and atomic, byte-stable writes. Real records are read and normalised by
:mod:`harness.rig.records`.

Layout::

    manifest.json           what the run holds: its kind, spec and experiments (name, role, signal)
    data/<name>.parquet     one dataset per experiment
    calibration.json        Kp, Ke, dead zone (harness.ident.calibration.Calibration)
    models/<name>.json      identified ARMAX models (+ selected.json); models/<name>.fmu their FMUs
    grid.csv                the order grid's fits;   crossfit.csv  the cross-fit matrix
    doubled_rate.json       the selected orders re-identified at twice the sample rate
    diagnosis.json          the diagnosis (harness.diagnosis.result.Diagnosis); diagnosis.timing.json its wall times
    diagnosis.replays.parquet  its replays beside the record, per stage (harness.diagnosis.replays)
    likelihood.json         the likelihood engine's fit (diagnose --engine likelihood; harness.likelihood.unit)
    force_picture.parquet   its missing force smoothed per record, force_picture.png drawn (harness.render.force)
    report.md, figures/     the report;   run.rrd  the Rerun recording
    run.timing.json         flexjoint run's wall time per stage (timings apart: every other file is byte-stable)

A new run (campaign, import, ``flexjoint run``) is written aside, in a hidden sibling directory, and moved into place
when it is complete (:func:`new_run`); over an existing run only with ``force``, which removes every artefact of
the old run first and lists them in the manifest's ``removed``. Each derived artefact records the sha256 of its
inputs in the manifest's ``artefacts`` when it is written (:func:`record_inputs`), so that :func:`stale_artefacts`
can tell which were made from other data than the directory now holds.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
import numbers
import os
import shutil
import tempfile
import types
import typing
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from .spec import Spec, from_dict
from .spec import load as load_spec

REQUIRED = ("t", "u", "theta_v", "alpha_v")
CHECKED = ("ref",)  # optional columns that must be finite where present: a closed-loop record's reference [deg]
T = TypeVar("T")


@dataclass(frozen=True)
class RunDir:
    """Paths of a run directory ``root`` (nothing is created or read)."""

    root: Path

    def __post_init__(self) -> None:
        object.__setattr__(self, "root", Path(self.root))

    @property
    def manifest(self) -> Path:
        return self.root / "manifest.json"

    @property
    def data(self) -> Path:
        return self.root / "data"

    def dataset(self, name: str) -> Path:
        """The dataset of experiment ``name``."""
        return self.data / f"{name}.parquet"

    @property
    def calibration(self) -> Path:
        return self.root / "calibration.json"

    @property
    def models(self) -> Path:
        return self.root / "models"

    def model(self, name: str, suffix: str = ".json") -> Path:
        """Model ``name``'s record (``.json``) or FMU (``.fmu``)."""
        return self.models / f"{name}{suffix}"

    @property
    def grid(self) -> Path:
        return self.root / "grid.csv"

    @property
    def crossfit(self) -> Path:
        return self.root / "crossfit.csv"

    @property
    def doubled_rate(self) -> Path:
        return self.root / "doubled_rate.json"

    @property
    def diagnosis(self) -> Path:
        return self.root / "diagnosis.json"

    @property
    def diagnosis_timing(self) -> Path:
        return self.root / "diagnosis.timing.json"

    @property
    def diagnosis_replays(self) -> Path:
        return self.root / "diagnosis.replays.parquet"

    @property
    def likelihood(self) -> Path:
        return self.root / "likelihood.json"

    @property
    def force_traces(self) -> Path:
        return self.root / "force_picture.parquet"

    @property
    def force_figure(self) -> Path:
        return self.root / "force_picture.png"

    @property
    def run_timing(self) -> Path:
        return self.root / "run.timing.json"

    @property
    def report(self) -> Path:
        return self.root / "report.md"

    @property
    def figures(self) -> Path:
        return self.root / "figures"

    @property
    def recording(self) -> Path:
        return self.root / "run.rrd"

    def derived(self) -> list[Path]:
        """Every artefact made from the data (everything of the layout but manifest.json and data/)."""
        return [self.calibration, self.models, self.grid, self.crossfit, self.doubled_rate, self.diagnosis,
                self.diagnosis_replays, self.diagnosis_timing, self.likelihood, self.force_traces,
                self.force_figure, self.run_timing, self.report, self.figures, self.recording]  # fmt: skip


class DataError(ValueError):
    """A dataset that cannot be used; the message is one line meant for the user."""


# ----------------------------------------------------------------------------------------------- typed JSON files
def _key(f: dataclasses.Field) -> str:
    """The JSON key of a dataclass field (``metadata["key"]`` when the key is not a Python name)."""
    return f.metadata.get("key", f.name)


def to_plain(obj: Any) -> Any:
    """JSON content of a dataclass tree: fields under their keys (``metadata["key"]`` where the key is not a
    Python name), optional fields (default None) left out when None."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        out = {}
        for f in dataclasses.fields(obj):
            v = getattr(obj, f.name)
            if v is None and f.default is None:
                continue
            out[_key(f)] = to_plain(v)
        return out
    if isinstance(obj, dict):
        return {k: to_plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_plain(v) for v in obj]
    return obj


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    """The resolved field types of a dataclass."""
    return typing.get_type_hints(cls)


def from_plain(cls: type[T], doc: Any, where: str) -> T:
    """Dataclass ``cls`` from JSON object ``doc``, every value checked against its field's type; ``where`` (its
    place in the file) starts the one-line :class:`DataError` of a missing key, an unknown one or a wrong type."""
    if not isinstance(doc, dict):
        raise DataError(f"{where}: expected an object, got {type(doc).__name__}")
    klass: type = cls  # the dataclass itself (type[T] is not Hashable to a type checker, a class is)
    hints = _hints(klass)
    fs = dataclasses.fields(klass)
    keys = {_key(f) for f in fs}
    unknown = sorted(set(doc) - keys)
    if unknown:
        raise DataError(f"{where}: unknown key(s) {', '.join(unknown)}")
    kw = {}
    for f in fs:
        k = _key(f)
        if k in doc:
            kw[f.name] = _plain_value(hints[f.name], doc[k], f"{where}.{k}")
        elif f.default is not dataclasses.MISSING:
            kw[f.name] = f.default
        else:
            raise DataError(f"{where}: missing key {k!r}")
    return cls(**kw)


def _plain_value(tp: Any, v: Any, where: str) -> Any:
    """JSON value ``v`` checked against type ``tp`` (dataclass, list[...], dict[str, ...], float, int, str, bool,
    Any, X | None); numbers are kept as written (an int stays an int), null in a float becomes NaN."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        inner = [a for a in args if a is not type(None)]
        return _plain_value(inner[0], v, where)
    if tp is Any:
        return v
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        return from_plain(tp, v, where)
    if origin is list:
        if not isinstance(v, list):
            raise DataError(f"{where}: expected a list, got {type(v).__name__}")
        return [_plain_value(args[0], x, f"{where}[{i}]") for i, x in enumerate(v)]
    if origin is dict:
        if not isinstance(v, dict):
            raise DataError(f"{where}: expected an object, got {type(v).__name__}")
        return {k: _plain_value(args[1], x, f"{where}.{k}") for k, x in v.items()}
    if tp is float:
        if v is None:
            return math.nan
        if isinstance(v, bool) or not isinstance(v, numbers.Real):
            raise DataError(f"{where}: expected a number, got {v!r}")
        return v
    if tp is int and (isinstance(v, bool) or not isinstance(v, numbers.Integral)):
        raise DataError(f"{where}: expected an integer, got {v!r}")
    if tp in (str, bool) and not isinstance(v, tp):
        raise DataError(f"{where}: expected {tp.__name__}, got {v!r}")
    return v


# ----------------------------------------------------------------------------------------------- manifest.json
@dataclass
class ExperimentEntry:
    """One experiment of a run (its dataset is ``data/<name>.parquet``): ``role`` "identification",
    "validation" or "calibration"; ``n`` samples. A campaign adds the command ``signal`` and the experiment's
    random ``seed``; an import its ``sample_rate`` [Hz], the record's ``columns`` and ``units`` per channel, the
    largest clock-jitter correction [s] and, for encoder counts, the angle lattice [deg] per channel.

    A closed-loop experiment has ``loop`` "closed", its dataset a ``ref`` column (the reference of theta [deg]) and
    its ``controller`` (:class:`harness.rig.controller.Controller` as a dict: kind, gains, source, R^2 when
    identified). ``theta_sensor`` is "pot" (default) or "encoder" with ``counts_per_rev``. An import names each
    sensor fault it found (:class:`harness.rig.faults.Fault` as a dict, with its ``line``) in ``faults`` and the
    samples it masked per channel, [first, end) ranges, in ``masked``: the identification and the diagnosis leave
    them out."""

    name: str
    role: str = "identification"
    signal: str | None = None
    n: int | None = None
    seed: int | None = None
    sample_rate: float | None = None
    columns: dict[str, str] | None = None
    units: dict[str, str] | None = None
    jitter_corrected_s: float | None = None
    lattice_deg: dict[str, float] | None = None
    loop: str | None = None
    controller: dict[str, Any] | None = None
    theta_sensor: str | None = None
    counts_per_rev: float | None = None
    faults: list[dict[str, Any]] | None = None
    masked: dict[str, list[list[int]]] | None = None


@dataclass
class Manifest:
    """``manifest.json``: what a run directory holds. ``kind`` "campaign" (simulated from ``spec``, the spec's
    table as run, with its file name, sha256 and random ``seed``, the FMUs' files and sha256, the versions) or
    "import" (real records: their ``sources`` and whether the ``calibration`` was "given" or "assumed").
    ``sample_rate`` [Hz] is None for records at different rates; ``generator`` names a simulator other than the
    twin (e.g. tests/indeprig.py, with its ``noise_seed``). ``artefacts``: per derived artefact (calibration.json,
    models, grid.csv, crossfit.csv, doubled_rate.json, diagnosis.json) the sha256 of each input it was made from
    ("data" and the artefacts it read); ``removed``: what ``--force`` removed of the run this one replaced."""

    kind: str
    experiments: list[ExperimentEntry]
    sample_rate: float | None
    spec: dict[str, Any] | None = None
    spec_file: str | None = None
    spec_sha256: str | None = None
    seed: int | None = None
    fmus: dict[str, dict[str, str]] | None = None
    versions: dict[str, str] | None = None
    generator: str | None = None
    noise_seed: int | None = None
    sources: dict[str, dict[str, Any]] | None = None
    calibration: str | None = None
    artefacts: dict[str, dict[str, str]] | None = None
    removed: list[str] | None = None

    @classmethod
    def load(cls, run: Path) -> Manifest:
        """The manifest of run directory ``run``; one :class:`DataError` line when there is none or it is not
        a manifest."""
        p = RunDir(run).manifest
        if not p.exists():
            raise DataError(f"{run}: not a run directory (no manifest.json)")
        try:
            return from_plain(cls, json.loads(p.read_text(encoding="utf-8")), "manifest")
        except json.JSONDecodeError as exc:
            raise DataError(f"{p}: not valid JSON ({exc})") from None
        except DataError as exc:
            raise DataError(f"{p}: {exc}") from None

    def write(self, run: Path) -> None:
        """Write ``manifest.json`` of run directory ``run`` (atomic, sorted keys: byte-stable)."""
        write_json(RunDir(run).manifest, to_plain(self))

    def entries(self, role: str | None = None) -> list[ExperimentEntry]:
        """The experiments in manifest order, optionally only those of one role."""
        return [e for e in self.experiments if role is None or e.role == role]

    def entry(self, name: str) -> ExperimentEntry | None:
        """Experiment ``name``'s entry (None when the run has no such experiment)."""
        return next((e for e in self.experiments if e.name == name), None)


def check_rig(rig: str | Path) -> Spec | None:
    """Refuse, in one line, a ``RIG`` (``flexjoint predict``, ``design``) that names no rig: a directory without a
    diagnosis (no model of the rig to close a loop on), or a spec that does not load; cheap, so that a command says
    so before it starts a cluster.

    Returns
    -------
    Spec or None
        The spec ``rig`` names; None for a diagnosis directory.

    Raises
    ------
    DataError
        A directory without diagnosis.json.
    """
    p = Path(rig)
    if not p.is_dir():
        return load_spec(rig)
    if not RunDir(p).diagnosis.is_file():
        what = "a run without a diagnosis" if RunDir(p).manifest.is_file() else "no diagnosis"
        raise DataError(
            f"RIG {rig}: {what}, so no closed-loop model of the rig: run `flexjoint diagnose --real {rig}` first, "
            "or give a spec"
        )
    return None


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (temp file in the same directory, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the file the usual permissions
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def write_json(path: Path, obj: Any) -> None:
    """Atomic, byte-stable JSON (sorted keys, full-precision floats, NaN written as null)."""
    atomic_write_text(path, json.dumps(_json_safe(obj), indent=2, sort_keys=True, allow_nan=False) + "\n")


def _json_safe(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _json_safe(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if np.isfinite(v) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, Path):
        return str(obj)
    return obj


def write_dataset(path: Path, columns: dict[str, np.ndarray]) -> None:
    """Write a dataset as Parquet, atomically and byte-for-byte reproducibly."""
    table = pa.table({k: pa.array(np.asarray(v, dtype=float)) for k, v in columns.items()})
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink, compression="zstd", write_statistics=False, store_schema=False)
    atomic_write_bytes(path, sink.getvalue().to_pybytes())


def validate(df: pd.DataFrame, name: str) -> pd.DataFrame:
    """Check a dataset: required columns (and a closed-loop record's reference ``ref``) finite numbers, uniform
    strictly increasing time."""
    missing = [c for c in REQUIRED if c not in df.columns]
    if missing:
        raise DataError(f"{name}: missing column(s) {', '.join(missing)}; need {', '.join(REQUIRED)}")
    if len(df) < 16:
        raise DataError(f"{name}: only {len(df)} rows; need at least 16 samples")
    for c in (*REQUIRED, *(c for c in CHECKED if c in df.columns)):
        col = pd.to_numeric(df[c], errors="coerce").to_numpy(dtype=float)
        bad = np.flatnonzero(~np.isfinite(col))
        if bad.size:
            raise DataError(f"{name}: column {c!r} has {bad.size} NaN/non-numeric value(s), first at row {bad[0]}")
    t = df["t"].to_numpy(dtype=float)
    dt = np.diff(t)
    Ts = float(np.median(dt))
    if not Ts > 0 or np.any(dt <= 0):
        raise DataError(f"{name}: time column t is not strictly increasing")
    if np.max(np.abs(dt - Ts)) > 1e-6 * max(Ts, 1e-12) + 1e-9:
        k = int(np.argmax(np.abs(dt - Ts)))
        raise DataError(f"{name}: non-uniform sampling: step {dt[k]:.6g} s at row {k + 1}, median {Ts:.6g} s")
    return df


def read_dataset(path: Path) -> pd.DataFrame:
    """Read and check one dataset.

    Parameters
    ----------
    path : Path
        A ``data/<experiment>.parquet`` file.

    Returns
    -------
    pandas.DataFrame
        Columns ``t`` [s], ``u`` [V], ``theta_v``, ``alpha_v`` [V], and ``theta``, ``alpha`` [deg] (the true angles
        of simulated data, the recorded ones of an import), ``ref`` [deg] for a closed loop; finite numbers, time
        uniform and strictly increasing.

    Raises
    ------
    harness.DataError
        A missing file or column, a non-numeric value, a non-uniform time.
    """
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such dataset")
    return validate(pq.read_table(path).to_pandas(), path.name)


def sample_time(df: pd.DataFrame) -> float:
    """Sampling period Ts [s] of a validated dataset."""
    return float(np.median(np.diff(df["t"].to_numpy())))


def recorded_spec(run: Path) -> Spec | None:
    """The spec recorded in a campaign's manifest (None for imported data)."""
    m = Manifest.load(run)
    return from_dict(m.spec, m.spec_file or "") if m.kind == "campaign" and m.spec is not None else None


def load_run(run: Path, role: str | None = "identification") -> dict[str, pd.DataFrame]:
    """The datasets of a run directory, in manifest order.

    Parameters
    ----------
    run : Path
        The run directory.
    role : str or None
        Only the experiments of this role ("identification", "validation", "calibration"); None: all.

    Returns
    -------
    dict of str to pandas.DataFrame
        ``{experiment: dataset}``, each checked as :func:`read_dataset` does.
    """
    out = {e.name: read_dataset(RunDir(run).dataset(e.name)) for e in Manifest.load(run).entries(role)}
    if not out:
        raise DataError(f"{run}: no {role or ''} datasets in manifest.json")
    return out


# ----------------------------------------------------------------------------------------------- provenance
# each derived artefact: the inputs whose sha256 it records, how it is named, what it was done by, the command that
# makes it again
INPUTS: dict[str, tuple[str, ...]] = {
    "calibration.json": ("data",),
    "models": ("data", "calibration.json"),
    "grid.csv": ("data", "calibration.json"),
    "doubled_rate.json": ("data", "calibration.json", "models"),
    "crossfit.csv": ("data", "models"),
    "diagnosis.json": ("data", "calibration.json"),
}
_ARTEFACT = {
    "calibration.json": ("calibration.json", "was made", "identify"),
    "models": ("models/", "were identified", "identify"),
    "grid.csv": ("grid.csv", "was computed", "identify"),
    "doubled_rate.json": ("doubled_rate.json", "was computed", "identify"),
    "crossfit.csv": ("crossfit.csv", "was computed", "crossfit"),
    "diagnosis.json": ("diagnosis.json", "was made", "diagnose"),
}
_INPUT = {
    "data": ("data", "data/"),
    "calibration.json": ("calibration", "calibration.json"),
    "models": ("models", "models/"),
}


def _file_sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def input_sha256(run: Path, name: str) -> str | None:
    """sha256 of one input of the derived artefacts: "data" (the manifest's datasets, name and bytes, in manifest
    order), "calibration.json" or "models" (models/*.json by name); None when the directory has none."""
    paths = RunDir(run)
    if name == "data":
        if not paths.manifest.exists():
            return None
        h = hashlib.sha256()
        for e in Manifest.load(run).experiments:
            p = paths.dataset(e.name)
            h.update(f"{e.name}\0{_file_sha256(p) if p.exists() else 'missing'}\n".encode())
        return h.hexdigest()
    if name == "models":
        files = sorted(paths.models.glob("*.json")) if paths.models.is_dir() else []
        if not files:
            return None
        h = hashlib.sha256()
        for p in files:
            h.update(f"{p.name}\0{_file_sha256(p)}\n".encode())
        return h.hexdigest()
    p = paths.root / name
    return _file_sha256(p) if p.is_file() else None


def record_inputs(run: Path, artefact: str, source: Path | None = None) -> None:
    """Record in ``run``'s manifest the sha256 of the inputs ``artefact`` (a key of :data:`INPUTS`) was just made
    from, read in ``source`` (default ``run``; a diagnosis written to another directory: the real run), with
    ``source``'s path relative to ``run`` when it is another directory. Nothing when ``run`` is no run directory."""
    run = Path(run)
    if not RunDir(run).manifest.exists():
        return
    source = Path(source) if source is not None else run
    entry = {k: input_sha256(source, k) or "none" for k in INPUTS[artefact]}
    if source.resolve() != run.resolve():
        entry["run"] = os.path.relpath(source, run)
    m = Manifest.load(run)
    m.artefacts = {**(m.artefacts or {}), artefact: entry}
    m.write(run)


def _exists(run: Path, artefact: str) -> bool:
    p = RunDir(run).root / artefact
    return p.is_dir() and any(p.glob("*.json")) if artefact == "models" else p.is_file()


def stale_artefacts(run: Path) -> dict[str, str]:
    """The derived artefacts of ``run`` made from other inputs than it now holds (a diagnosis of another run: from
    other data than these), or from an input that is itself stale, each with one line saying so and which command
    makes it again (an artefact whose inputs were not recorded, by an older version, is not judged)."""
    run = Path(run)
    recorded = Manifest.load(run).artefacts or {}
    now: dict[str, str | None] = {}
    out = {}
    for artefact, inputs in INPUTS.items():
        rec = recorded.get(artefact)
        if rec is None or not _exists(run, artefact):
            continue
        label, verb, command = _ARTEFACT[artefact]
        for name in inputs:
            if name in out:  # made from an input that is itself stale
                out[artefact] = (f"{label} {verb} from {_INPUT[name][1]}, which is stale: re-run flexjoint "
                                 f"{_ARTEFACT[name][2]}")  # fmt: skip
                break
            if name not in now:
                now[name] = input_sha256(run, name) or "none"
            if rec.get(name) != now[name]:
                what, where = _INPUT[name]
                out[artefact] = (
                    f"{label} {verb} from the data of another run ({rec['run']}), not from data/ here: re-run "
                    f"flexjoint {command} on this directory"
                    if "run" in rec
                    else f"{label} {verb} from other {what} than {where} now holds: re-run flexjoint {command}"
                )
                break
    return out


def check_fresh(run: Path, artefacts: tuple[str, ...]) -> None:
    """One :class:`DataError` line when one of ``artefacts`` was made from other inputs than ``run`` now holds."""
    stale = stale_artefacts(run)
    for a in artefacts:
        if a in stale:
            raise DataError(stale[a])


# ----------------------------------------------------------------------------------------------- a new run
def _held(out: Path) -> list[str]:
    """The parts of the run layout an existing directory ``out`` holds (folders with a trailing /)."""
    paths = RunDir(out)
    parts = [paths.manifest, paths.data, *paths.derived()]
    return [p.name + ("/" if p.is_dir() else "") for p in parts if p.exists()]


def check_new_run(out: Path, force: bool = False) -> None:
    """Refuse, before any work, to write a new run into ``out`` when it is a file or already holds a run (unless
    ``force``): one line naming a fresh ``--out`` and ``--force``."""
    out = Path(out)
    for p in (out, *out.parents):
        if p.exists() and not p.is_dir():
            where = "" if p == out else f" ({p} is a file)"
            raise NotADirectoryError(f"--out {out}: not a directory{where}; give a new or existing directory")
    held = _held(out) if out.is_dir() else []
    if held and not force:
        raise FileExistsError(
            f"--out {out} already holds a run ({', '.join(held[:4])}{', ...' if len(held) > 4 else ''}): give a fresh "
            "--out, or --force (force=True) to replace it (every file of that run is removed)"
        )


@contextmanager
def new_run(out: Path, force: bool = False) -> Iterator[Path]:
    """Write a new run aside and move it into ``out`` when complete. Yields the directory to write into (a hidden
    sibling of ``out``, the run under its own name); on success an existing run in ``out`` (only with ``force``,
    :func:`check_new_run`) is removed first, layout entries only, and what was removed is listed in the new
    manifest's ``removed``. On any error or Ctrl-C the aside is removed and ``out`` stays as it was."""
    check_new_run(Path(out), force)
    out = Path(out).resolve()  # ".", "..": the aside goes beside the directory itself
    out.parent.mkdir(parents=True, exist_ok=True)
    aside = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.", suffix=".new"))
    work = aside / out.name
    try:
        work.mkdir()
        yield work
        held = _held(out) if out.is_dir() else []
        if held:
            m = Manifest.load(work)
            m.removed = sorted(h for h in held if h != "manifest.json")
            m.write(work)
            paths = RunDir(out)
            for p in (paths.manifest, paths.data, *paths.derived()):
                if p.is_dir():
                    shutil.rmtree(p)
                else:
                    p.unlink(missing_ok=True)
        if out.is_dir():
            for p in sorted(work.iterdir(), key=lambda q: (q.name == "manifest.json", q.name)):  # manifest last
                os.replace(p, out / p.name)
        else:
            os.replace(work, out)
    finally:
        shutil.rmtree(aside, ignore_errors=True)
