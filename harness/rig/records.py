"""Real records in the forms labs keep them, normalised into a run directory.

Formats: CSV (separator ``,`` ``;`` tab or spaces and the decimal comma detected; an optional header, an
optional units row under it; ``#``/``%`` comment lines), MATLAB .mat v5 (scipy) and v7.3 (HDF5, h5py) with one
vector per channel or one N x k matrix, and Parquet. One record may be spread over several files that share its
time base, ``[NAME=]FILE+FILE+...`` (what a QUARC or Simulink model writes: a To File block per scope, each its own
time column then its signals): their columns are joined, a headerless file's addressed as ``STEM:POSITION``
(``data_theta:2``), the files' time columns checked to be one clock, the dataset named NAME (default: the files'
common stem, else the first's; one file alike, ``NAME=FILE``). Channels: time ``t``, command ``u`` [V], shaft angle
``theta`` and link deflection ``alpha``, found by name (``t``/``time``, ``u``/``Vm``, ``theta_deg``, ``alpha_v``,
``theta [rad]`` ...) or given with a map (``{"time": "t", "Vm": "u", "hub": "theta", "tip": "alpha"}``;
positions ``{"0": "t", ...}`` for a headerless file; ``-alpha`` for a channel recorded with the opposite sign: alpha
is the link's deflection behind the hub, positive when the hub accelerates negatively). Units: t in s, ms or us;
u in V; theta in V, deg, rad or encoder counts; alpha in V, deg, rad, counts or m (mm) of tip deflection,
alpha = atan(d / link_length).

Rules, no silent guesses:

- time without a unit: a median sample interval <= 0.1 is seconds (>= 10 Hz); 1 <= interval <= 100 is
  milliseconds (10 Hz - 1 kHz), converted with a note; anything else is refused (0.1-1 could be 1-10 Hz in s
  or 1-10 kHz in ms; > 100 would be < 10 Hz in ms) and ``units={"t": ...}`` decides;
- whatever the time unit, the sample rate must be >= ``MIN_RATE`` (10 Hz), and nothing assumes 50 Hz: the rate is
  read off ``t`` (50 Hz, 500 Hz, 1 kHz records alike);
- a record must be long enough for two folds (the diagnosis splits a lone record in time): at least
  ``MIN_RECORD_SECONDS`` (2 s: each half >= 1 s, one multiple-shooting window, >= 3 periods of the link's first
  mode) and ``2 * MIN_FOLD_SAMPLES`` (100) samples;
- host-clock jitter: time stamps within ``JITTER_LIMIT`` (10 %) of a sample interval of the least-squares
  uniform grid are resampled onto it by linear interpolation (the pot's wrap jumps are not interpolated
  across: the nearer sample is taken) and the largest correction is reported; beyond that: refused;
- no calibration given: lab 1's Kp and Ke are assumed and a note says so;
- sensor faults (:mod:`harness.rig.faults`), each said in one ``fault: RECORD: ...`` line (channel, kind, time, row,
  size, what was done) and kept in the manifest (the experiment's ``faults``), none fitted across: a jump of theta
  no hub makes in one sample (the drive's fastest motion, or half a turn) is a pot's wrap when it is a turn less
  the dead band through the calibration, and unwrapped; any other cuts the record into ``NAME_1``, ``NAME_2``, ...
  (each kept if long enough for two folds; none: refused); a run of identical samples of theta or alpha that its
  noise makes improbable while another channel moves, at the channel's extreme (a rail) or not (stuck), is masked:
  kept in the dataset, listed in the manifest's ``masked``, left out by the identification and the diagnosis;
- ``zero_alpha``: the deflection is zeroed on the record's quietest ``ZERO_SECONDS`` (the shaft at rest there, the
  link too: its deflection varies no more than ``REST_SIGMAS`` times its noise), as labs zero their gauge, with a
  note; where the link never rests, a warning says so and the record is left as read (the diagnosis fits each
  record's gauge offset anyway); a closed-loop record's controller keeps the zero error it acted with
  (``alpha_bias``).

Closed-loop records (every public record of a flexible link is one: the logged ``u`` is a controller's output):
a reference column given the role ``ref`` (``{"theta_ref_deg": "ref"}``, in deg, rad, counts or the pot's volts)
becomes the dataset's ``ref`` [deg] and makes the experiment closed loop. Its controller is the one given
(``ImportOptions.controller``) or identified from the record
(:func:`harness.rig.controller.identify_controller`, both kinds tried, the better R^2 kept); below
``R2_MIN`` it is recorded with its R^2 and a warning, and the diagnosis then replays the record open loop by
multiple shooting. A given controller is checked against the logged command (its R^2 said, a warning below
``R2_MIN``) and kept as given; given for a record without a reference: refused. A reference of another length than
the record or with NaN: refused, one line naming the file and the column. ``theta_sensor="encoder"`` (or theta in
encoder counts, or ``counts_per_rev`` given for a theta in deg or rad) with ``counts_per_rev`` > 0: theta has no pot
wrap or dead band (resampling does not treat its jumps as wraps) and its step is the count, 360 / counts_per_rev deg
(``lattice_deg``), whatever unit it was written in.

The dataset written (``data/<name>.parquet``) is the same whatever the format: ``t`` [s], ``u`` [V],
``theta_v``, ``alpha_v`` [V] as the lab's DAQ reads them (angles converted with the calibration: theta_v =
theta / Kp + pot_offset_v, alpha_v = alpha / Ke + gauge_offset_v; an encoder angle is not wrapped like a pot),
and ``theta``, ``alpha`` [deg] as recorded (through the calibration for a volts record).
"""

from __future__ import annotations

import hashlib
import math
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import scipy.io

from ..diagnosis.experiments import MIN_FOLD_SAMPLES, MIN_FOLD_SECONDS
from ..diagnosis.noise import decimal_resolution, value_step
from ..fmu.modeldesc import source_model
from ..ident.calibration import LAB1_CALIBRATION, Calibration, alpha_deg, theta_deg
from ..rundir import (
    DataError,
    ExperimentEntry,
    Manifest,
    RunDir,
    check_new_run,
    new_run,
    record_inputs,
    validate,
    write_dataset,
)
from .controller import IDENTIFIABLE, R2_MIN, Controller, command_r2, identify_controller
from .faults import Fault, fastest_step_deg, impossible_jumps, is_turn, mask, pinned_runs

__all__ = [
    "CHANNELS",
    "JITTER_LIMIT",
    "MIN_RATE",
    "MIN_RECORD_SECONDS",
    "ImportOptions",
    "RawTable",
    "calibration_option",
    "import_records",
    "parse_map",
    "read_record",
    "read_table",
    "record_files",
]

Note = Callable[[str], None]
CHANNELS = ("t", "u", "theta", "alpha")
OPTIONAL = ("ref",)  # channels a record may have: the closed loop's reference of theta
THETA_SENSORS = ("pot", "encoder")
MIN_RATE = 10.0  # Hz: slower records cannot show the link's first mode (~3-4.5 Hz)
MIN_RECORD_SECONDS = 2 * MIN_FOLD_SECONDS  # s: the shortest record imported (n Ts, n samples at interval Ts)
JITTER_LIMIT = 0.1  # largest time-stamp correction resampled, as a share of the sample interval
ZERO_SECONDS = 0.25  # s: a deflection is zeroed on its quietest stretch of ZERO_SECONDS at rest
AT_REST_DEG = 0.5  # deg: the shaft moves less than this over those samples: at rest
REST_SIGMAS = 3.0  # ... and the deflection's RMS about its mean there is within this many times its noise
UNITS = {
    "t": ("s", "ms", "us"),
    "u": ("V",),
    "theta": ("V", "deg", "rad", "counts"),
    "alpha": ("V", "deg", "rad", "counts", "m", "mm"),
    "ref": ("V", "deg", "rad", "counts"),
}
_UNIT_NAMES = {
    "s": "s", "sec": "s", "secs": "s", "second": "s", "seconds": "s",
    "ms": "ms", "msec": "ms", "millisecond": "ms", "milliseconds": "ms",
    "us": "us", "µs": "us", "usec": "us", "microseconds": "us",
    "v": "V", "volt": "V", "volts": "V",
    "deg": "deg", "degree": "deg", "degrees": "deg", "°": "deg",
    "rad": "rad", "radian": "rad", "radians": "rad",
    "counts": "counts", "count": "counts", "cnt": "counts", "ticks": "counts",
    "m": "m", "metre": "m", "meter": "m", "metres": "m", "meters": "m", "mm": "mm",
}  # fmt: skip
_ALIASES = {
    "t": "t", "time": "t",
    "u": "u", "vm": "u", "v_m": "u", "command": "u", "cmd": "u",
    "theta": "theta", "alpha": "alpha",
    "ref": "ref", "reference": "ref", "theta_ref": "ref", "setpoint": "ref",
}  # fmt: skip
_TIME_FACTOR = {"s": 1.0, "ms": 1e-3, "us": 1e-6}
_SUFFIXES = sorted(_UNIT_NAMES, key=len, reverse=True)


@dataclass(frozen=True)
class ImportOptions:
    """How to read records: ``columns`` source column (name or position) -> channel (t, u, theta, alpha,
    theta_v, alpha_v or with a unit suffix, theta_deg); ``units`` channel or column -> unit; ``link_length``
    [m] for tip deflections; ``counts_per_rev`` of an encoder; ``calibration`` to carry (None: assume lab 1's);
    ``controller`` of a closed-loop record (None: identified from it); ``theta_sensor`` "pot" or "encoder" (None:
    an encoder when theta is in counts, else a pot); ``zero_alpha``: zero the deflection on the record's quietest
    ``ZERO_SECONDS`` at rest (a record whose link never rests is left as read, with a warning)."""

    columns: dict[str, str] = field(default_factory=dict)
    units: dict[str, str] = field(default_factory=dict)
    link_length: float | None = None
    counts_per_rev: float | None = None
    calibration: Calibration | None = None
    controller: Controller | None = None
    theta_sensor: str | None = None
    zero_alpha: bool = False


@dataclass
class RawTable:
    """Numeric columns read from one file (NaN where a cell is missing or not a number), in file order.

    ``units``: column -> unit named in the file (units row, ``name [unit]``); ``bad``: column -> (data row,
    file line, text) of its first cell that is not a number; ``header``: False for a headerless matrix."""

    file: str
    form: str
    names: list[str]
    values: list[np.ndarray]
    units: dict[str, str] = field(default_factory=dict)
    bad: dict[str, tuple[int, int, str]] = field(default_factory=dict)
    header: bool = True
    notes: list[str] = field(default_factory=list)
    others: dict[str, int] = field(default_factory=dict)  # vectors left out for their length: name -> samples

    def found(self) -> str:
        """What was found, for messages: the columns and the form."""
        cols = ", ".join(self.names) if self.header else f"{len(self.names)} numeric columns, no header"
        return f"found {cols} ({self.form})"


# ----------------------------------------------------------------------------------------------- units
def unit_name(text: str) -> str | None:
    """Canonical unit ("s", "ms", "us", "V", "deg", "rad", "counts", "m", "mm") of ``text``, or None."""
    s = str(text).strip().strip("[]()").strip().lower()
    return _UNIT_NAMES.get(s)


def _split_name(name: str) -> tuple[str, str | None]:
    """(base name, unit) of a column name: ``theta [deg]``, ``theta (rad)``, ``theta_deg``, ``time_ms``."""
    s = str(name).strip()
    m = re.match(r"^(.*?)\s*[\[(]\s*([^\])]*)\s*[\])]\s*$", s)
    if m and unit_name(m.group(2)):
        return m.group(1).strip(), unit_name(m.group(2))
    low = s.lower()
    for sfx in _SUFFIXES:
        if low.endswith("_" + sfx) and len(low) > len(sfx) + 1:
            return s[: -len(sfx) - 1], _UNIT_NAMES[sfx]
    return s, None


def _channel(name: str) -> tuple[str | None, str | None]:
    """(channel, unit) a column name stands for by itself: ``alpha_v`` -> (alpha, V), ``Vm`` -> (u, None)."""
    base, unit = _split_name(name)
    return _ALIASES.get(re.sub(r"[\s\-]+", "_", base.lower())), unit


def parse_map(text: str | None, what: str) -> dict[str, str]:
    """``"a=b,c=d"`` -> {"a": "b", "c": "d"}; ``what`` names the option in the error."""
    out: dict[str, str] = {}
    for item in [s for s in (text or "").split(",") if s.strip()]:
        key, sep, val = item.partition("=")
        if not sep or not key.strip() or not val.strip():
            example = "time=t,Vm=u,hub=theta,tip=alpha" if what == "--columns" else "theta=deg,alpha=rad,t=s"
            raise DataError(f"{what} {text!r}: expected NAME=VALUE pairs separated by commas, e.g. {example}")
        out[key.strip()] = val.strip()
    return out


# ----------------------------------------------------------------------------------------------- readers
def read_table(path: Path) -> RawTable:
    """Read one record file by its suffix: .csv/.txt/.dat/.tsv, .mat (v5 or v7.3), .parquet."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix in (".csv", ".txt", ".dat", ".tsv"):
        return _read_csv(path)
    if suffix == ".mat":
        return _read_mat(path)
    if suffix in (".parquet", ".pq"):
        return _read_parquet(path)
    raise DataError(f"{path.name}: unknown record format {path.suffix!r}; use .csv, .txt, .tsv, .mat or .parquet")


def record_files(arg: str | Path) -> tuple[str, list[Path]]:
    """(dataset name, files) of a record argument: an existing file (named by its stem), or ``[NAME=]FILE+FILE+...``,
    one record in one file or spread over several (named NAME, else the files' common stem, else the first file's).
    """
    text = str(arg)
    if Path(text).is_file():
        return Path(text).stem, [Path(text)]
    name, eq, rest = text.partition("=")
    if not eq or "+" in name or "/" in name:
        name, rest = "", text
    if not name and "+" not in rest:
        return Path(rest).stem, [Path(rest)]  # one file, unnamed: read_table says if it is missing
    files = [Path(f) for f in rest.split("+")]
    if len(files) == 1 and not files[0].name:
        raise DataError(f"{text}: no file after NAME= (a named record is NAME=FILE or NAME=FILE+FILE+...)")
    if any(not f.name for f in files):
        raise DataError(f"{text}: a record of several files is FILE+FILE+... (an empty name between the '+')")
    missing = [f for f in files if not f.is_file()]
    if missing:
        raise DataError(f"{missing[0]}: no such file (in the record {text})")
    if len({f.stem for f in files}) < len(files):
        raise DataError(f"{text}: the same file name twice in one record")
    common = _common_stem([f.stem for f in files])
    return name.strip() or common or files[0].stem, files


def _common_stem(stems: list[str]) -> str:
    """The stems' common prefix up to its last separator: data_vm, data_theta -> data."""
    prefix = stems[0]
    for s in stems[1:]:
        while not s.startswith(prefix):
            prefix = prefix[:-1]
    return re.sub(r"[_\-. ]+[^_\-. ]*$", "", prefix) if prefix and prefix not in stems else prefix.rstrip("_-. ")


def read_record(files: list[Path]) -> RawTable:
    """The columns of one record: :func:`read_table` of its file, or of each of its files joined (see the module):
    a column named like the same column of another file, and every column of a headerless file, takes the
    file's stem as a prefix (``data_theta:2``); the files must have as many rows, and their time columns (named t or
    time, or the first column of a headerless file when it increases) must agree to a millionth of a sample."""
    tables = [read_table(f) for f in files]
    if len(tables) == 1:
        return tables[0]
    rows = {t.file: t.values[0].size if t.values else 0 for t in tables}
    if len(set(rows.values())) > 1:
        listed = ", ".join(f"{f} {n}" for f, n in rows.items())
        raise DataError(f"{' + '.join(rows)}: one record's files must have as many rows ({listed}): a column of "
                        "another length")  # fmt: skip
    _same_clock(tables)
    seen = [n for t in tables if t.header for n in t.names]
    out = RawTable(" + ".join(t.file for t in tables), " + ".join(f"{t.file}: {t.form}" for t in tables), [], [])
    out.header = any(t.header for t in tables)
    for t in tables:
        stem = Path(t.file).stem
        for name, values in zip(t.names, t.values, strict=True):
            key = name if t.header and seen.count(name) == 1 else f"{stem}:{name}"
            out.names.append(key)
            out.values.append(values)
            if name in t.units:
                out.units[key] = t.units[name]
            if name in t.bad:
                out.bad[key] = t.bad[name]
        out.notes += [f"{t.file}: {n}" for n in t.notes]
        out.others.update({f"{stem}:{k}": v for k, v in t.others.items()})
    return out


def _clock(t: RawTable) -> np.ndarray | None:
    """A file's time column: named t or time, else the first column of a headerless file when it increases."""
    for name, values in zip(t.names, t.values, strict=True):
        if t.header and _channel(name)[0] == "t":
            return values
    if not t.header and t.values and t.values[0].size > 1 and bool(np.all(np.diff(t.values[0]) > 0)):
        return t.values[0]
    return None


def _same_clock(tables: list[RawTable]) -> None:
    """Refuse files of one record whose time columns differ by more than a millionth of a sample."""
    clocks = [(t.file, c) for t in tables if (c := _clock(t)) is not None]
    if len(clocks) < 2:
        return
    (f0, c0), rest = clocks[0], clocks[1:]
    dt = float(np.median(np.diff(c0)))
    for f, c in rest:
        off = np.flatnonzero(np.abs(c - c0) > 1e-6 * abs(dt))
        if off.size:
            k = int(off[0])
            raise DataError(f"{f0} and {f}: their time columns differ from row {k} on ({c0[k]:g} and {c[k]:g}): not "
                            "one record's files (give them as separate records)")  # fmt: skip


def _lines(path: Path) -> list[tuple[int, str]]:
    raw = path.read_bytes()
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")
    return [(i, s.strip()) for i, s in enumerate(text.splitlines(), 1) if s.strip() and s.strip()[0] not in "#%"]


def _split(line: str, sep: str) -> list[str]:
    return line.split() if sep == " " else [c.strip().strip('"').strip() for c in line.split(sep)]


_NUM = re.compile(r"^[+-]?(\d+([.,]\d*)?|[.,]\d+)([eE][+-]?\d+)?$|^[+-]?(nan|inf|infinity)$", re.IGNORECASE)


def _sniff(path: Path, lines: list[tuple[int, str]]) -> tuple[str, str]:
    """(separator, decimal mark) from the first 50 lines: the first of tab, ';', ',', spaces that splits
    them all into the same number (>= 2) of fields; a decimal comma when cells read like ``1,23``."""
    sample = [s for _, s in lines[:50]]
    for sep in ("\t", ";", ",", " "):
        counts = {len(_split(s, sep)) for s in sample}
        if len(counts) == 1 and counts.pop() >= 2:
            cells = [c for s in sample[1:] for c in _split(s, sep)]
            comma = sep != "," and any(re.match(r"^[+-]?\d*,\d+([eE][+-]?\d+)?$", c) for c in cells)
            return sep, "," if comma else "."
    fields = sorted({len(_split(s, sep)) for s in sample for sep in (",", ";")})
    raise DataError(
        f"{path.name}: cannot tell the columns apart: the first {len(sample)} lines split into "
        f"{'/'.join(map(str, fields))} fields with ',' or ';' and unevenly with tabs or spaces"
    )


def _is_num(cell: str, dec: str) -> bool:
    return bool(_NUM.match(cell)) and (dec == "," or "," not in cell)


def _read_csv(path: Path) -> RawTable:
    lines = _lines(path)
    if len(lines) < 2:
        raise DataError(f"{path.name}: {len(lines)} line(s) of data; need a header and at least 16 samples")
    sep, dec = _sniff(path, lines)
    sep_name = {"\t": "tab", " ": "spaces"}.get(sep, repr(sep))
    form = f"CSV, separator {sep_name}" + (", decimal comma" if dec == "," else "")
    rows = [_split(s, sep) for _, s in lines]
    header = not all(_is_num(c, dec) for c in rows[0])
    start = 1 if header else 0
    names = [c or f"column {j}" for j, c in enumerate(rows[0])] if header else [str(j) for j in range(len(rows[0]))]
    units: dict[str, str] = {}
    notes: list[str] = [f"read as {form}"] if sep != "," or dec == "," else []
    if header:
        for name in names:
            _, unit = _split_name(name)
            if unit:
                units[name] = unit
    if header and len(rows) > 1 and not any(_is_num(c, dec) for c in rows[1]):
        cells = rows[1]
        if all(unit_name(c) for c in cells if c):
            units.update({n: u for n, c in zip(names, cells, strict=True) if c and (u := unit_name(c))})
            notes.append(f"line {lines[1][0]} under the header read as units: {', '.join(cells)}")
            start = 2
        else:
            raise DataError(
                f"{path.name}: line {lines[1][0]} under the header is neither numbers nor units "
                f"({', '.join(repr(c) for c in cells[:6])}); {form}, columns {', '.join(names)}; "
                f"known units: s, ms, us, V, deg, rad, counts, m, mm"
            )
    body = rows[start:]
    long = next((k for k, r in enumerate(body) if len(r) > len(names)), None)
    if long is not None:
        raise DataError(f"{path.name}: line {lines[start + long][0]} has {len(body[long])} fields, the header "
                        f"{len(names)} ({', '.join(names)}); {form}")  # fmt: skip
    body = [r + [""] * (len(names) - len(r)) for r in body]  # a short row: its last columns are missing
    table = pd.DataFrame(body, columns=names, dtype=str) if body else pd.DataFrame(columns=names)
    values, bad = [], {}
    for name in names:
        col = table[name].fillna("")
        text = col.str.replace(",", ".", regex=False) if dec == "," else col
        num = pd.to_numeric(text, errors="coerce").to_numpy(dtype=float)
        wrong = np.flatnonzero(np.isnan(num) & ~col.str.lower().isin(["nan", "-nan", "+nan"]).to_numpy())
        if wrong.size:
            k = int(wrong[0])
            bad[name] = (k, lines[start + k][0], col.iloc[k])
        values.append(num)
    return RawTable(path.name, form, names, values, units, bad, header, notes)


def _is_vector(v: np.ndarray) -> bool:
    return v.ndim == 1 or (v.ndim == 2 and min(v.shape) == 1)


def _mat_columns(items: dict[str, np.ndarray], path: Path, form: str, variables: list[str]) -> RawTable:
    """One column per numeric vector (the most common length, >= 16), or the columns of a lone N x k matrix."""
    vectors = {k: v.ravel() for k, v in items.items() if _is_vector(v) and v.size >= 16}
    if vectors:
        sizes = [v.size for v in vectors.values()]
        n = max(set(sizes), key=lambda s: (sizes.count(s), s))
        names = [k for k, v in vectors.items() if v.size == n]
        other = [k for k in vectors if k not in names]
        notes = [f"ignored vectors of another length: {', '.join(other)}"] if other else []
        return RawTable(path.name, form, names, [vectors[k] for k in names], notes=notes,
                        others={k: vectors[k].size for k in other})  # fmt: skip
    mats = {k: v for k, v in items.items() if v.ndim == 2 and min(v.shape) >= 2}
    if len(mats) == 1:
        ((name, m),) = mats.items()
        m = m if m.shape[0] >= m.shape[1] else m.T
        cols = [str(j) for j in range(m.shape[1])]
        return RawTable(path.name, f"{form}, matrix {name!r} {m.shape[0]} x {m.shape[1]}", cols,
                        [m[:, j] for j in range(m.shape[1])], header=False)  # fmt: skip
    raise DataError(
        f"{path.name}: no numeric vectors of >= 16 samples nor a single matrix in this {form} file "
        f"(variables: {', '.join(variables) or 'none'})"
    )


def _flatten(prefix: str, obj: Any, out: dict[str, np.ndarray], seen: list[str]) -> None:
    if isinstance(obj, dict):
        for k, v in obj.items():
            _flatten(f"{prefix}{k}.", v, out, seen)
        return
    name = prefix[:-1]
    arr = np.asarray(obj)
    seen.append(f"{name} ({arr.dtype.kind}{'x'.join(map(str, arr.shape))})")
    if arr.dtype.kind in "biuf" and arr.size:
        out[name] = arr.astype(float)


def _leaf_names(items: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Struct fields by their last name (``rec.theta`` -> ``theta``) when that is unambiguous."""
    leaves = [k.rsplit(".", 1)[-1] for k in items]
    return {(k.rsplit(".", 1)[-1] if leaves.count(k.rsplit(".", 1)[-1]) == 1 else k): v for k, v in items.items()}


def _first_line(exc: BaseException) -> str:
    """An exception's first line of text (its type's name when it has none), for a one-line error."""
    return str(exc).splitlines()[0] if str(exc).strip() else type(exc).__name__


def _read_mat(path: Path) -> RawTable:
    items: dict[str, np.ndarray] = {}
    seen: list[str] = []
    try:
        form = _read_mat_items(path, items, seen)
    except DataError:
        raise
    except Exception as exc:  # noqa: BLE001 - scipy and h5py raise many types (IndexError, KeyError...) on a bad file
        raise DataError(f"{path.name}: not a readable MATLAB .mat file ({_first_line(exc)})") from None
    return _mat_columns(_leaf_names(items), path, form, seen)


def _read_mat_items(path: Path, items: dict[str, np.ndarray], seen: list[str]) -> str:
    """Fill ``items`` (numeric arrays by dotted name) and ``seen`` (every variable, for messages) from a .mat file;
    returns its form."""
    if h5py.is_hdf5(path):
        form = "MATLAB v7.3 (HDF5)"
        with h5py.File(path, "r") as f:

            def visit(group: Any, prefix: str) -> None:
                for key, obj in group.items():
                    if key.startswith("#"):
                        continue
                    cls = obj.attrs.get("MATLAB_class", b"")
                    cls = cls.decode() if isinstance(cls, bytes) else str(cls)
                    if isinstance(obj, h5py.Group):
                        visit(obj, f"{prefix}{key}.")
                    elif cls in ("double", "single", "int8", "int16", "int32", "int64", "uint8", "uint16",
                                 "uint32", "uint64", ""):  # fmt: skip
                        arr = np.asarray(obj[()])
                        seen.append(f"{prefix}{key}")
                        if arr.dtype.kind in "biuf" and arr.size:
                            items[f"{prefix}{key}"] = arr.T.astype(float)  # MATLAB stores column-major
                    else:
                        seen.append(f"{prefix}{key} ({cls})")

            visit(f, "")
    else:
        form = "MATLAB v5"
        mat = scipy.io.loadmat(path, simplify_cells=True)
        for k, v in mat.items():
            if not k.startswith("__"):
                _flatten(f"{k}.", v, items, seen)
    return form


def _read_parquet(path: Path) -> RawTable:
    try:
        df = pq.read_table(path).to_pandas()
    except Exception as exc:  # noqa: BLE001 - pyarrow raises several types for a bad file
        raise DataError(f"{path.name}: not a readable Parquet file ({_first_line(exc)})") from None
    names = [str(c) for c in df.columns]
    values, bad = [], {}
    for name, col in zip(names, df.columns, strict=True):
        num = pd.to_numeric(df[col], errors="coerce").to_numpy(dtype=float)
        wrong = np.flatnonzero(np.isnan(num) & df[col].notna().to_numpy())
        if wrong.size:
            bad[name] = (int(wrong[0]), 0, str(df[col].iloc[int(wrong[0])]))
        values.append(num)
    units = {n: u for n in names if (u := _split_name(n)[1])}
    return RawTable(path.name, "Parquet", names, values, units, bad)


# ----------------------------------------------------------------------------------------------- channels
@dataclass
class Channel:
    """A channel as found: its column in the file, values, unit."""

    column: str
    values: np.ndarray
    unit: str | None


def _lookup(table: RawTable, key: str) -> int | None:
    if key in table.names:
        return table.names.index(key)
    low = [n.lower() for n in table.names]
    if key.lower() in low:
        return low.index(key.lower())
    bases = [_split_name(n)[0].lower() for n in table.names]
    if bases.count(key.lower()) == 1:
        return bases.index(key.lower())
    if key.isdigit() and int(key) < len(table.names):
        return int(key)
    return None


def resolve(table: RawTable, opts: ImportOptions) -> dict[str, Channel]:
    """The t, u, theta, alpha channels of ``table`` with their units (map, then names; volts preferred)."""
    picked: dict[str, list[tuple[int, str | None, bool]]] = {c: [] for c in (*CHANNELS, *OPTIONAL)}
    mapped: set[int] = set()
    negated: set[int] = set()  # columns mapped as -ROLE: recorded with the opposite sign convention
    for key, target in opts.columns.items():
        ch, unit = _channel(target.removeprefix("-"))
        if ch is None:
            raise DataError(f"--columns {key}={target}: unknown channel {target!r}; use t, u, theta, alpha, ref, "
                            f"theta_v, alpha_v (or a unit suffix: theta_deg)")  # fmt: skip
        j = _lookup(table, key)
        if j is None and key in table.others:
            raise DataError(f"{table.file}: column {key!r} ({ch}) has {table.others[key]} samples, the record's other "
                            f"columns {table.values[0].size}: a column of another length")  # fmt: skip
        if j is None:
            raise DataError(f"{table.file}: --columns names {key!r}, not in the file: {table.found()}")
        picked[ch].append((j, unit, True))
        mapped.add(j)
        if target.startswith("-"):
            negated.add(j)
    for j, name in enumerate(table.names):
        ch, unit = _channel(name) if table.header else (None, None)
        if j not in mapped and ch is not None and not any(m for *_, m in picked[ch]):
            picked[ch].append((j, unit, False))
    out: dict[str, Channel] = {}
    for ch in (*CHANNELS, *OPTIONAL):
        cands = picked[ch]
        if not cands and ch in OPTIONAL:
            continue
        if not cands:
            if not table.header:
                first = ", ".join(f"{n} {v[0]:g}" if ":" in n else f"{v[0]:g}" for n, v in zip(table.names[:6],
                                  table.values[:6], strict=True))  # fmt: skip
                example = (f"{table.names[0]}=t,{table.names[1]}=u,..." if ":" in table.names[0] else
                           "0=t,1=u,2=theta_v,3=alpha_v")  # fmt: skip
                raise DataError(
                    f"{table.file}: no header: {len(table.names)} numeric columns found (first row {first}); name "
                    f"them by position, e.g. --columns {example}"
                )
            raise DataError(f"{table.file}: no column for {ch}; {table.found()}; name it with --columns NAME={ch}")
        if len(cands) > 1:
            volts = [c for c in cands if _unit_of(table, ch, c, opts) == "V"]
            if len(volts) != 1:
                names = " and ".join(repr(table.names[c[0]]) for c in cands)
                raise DataError(f"{table.file}: several columns for {ch}: {names}; choose one with --columns")
            table.notes.append(
                f"{ch}: used the volts column {table.names[volts[0][0]]!r}, ignored "
                + ", ".join(repr(table.names[c[0]]) for c in cands if c is not volts[0])
            )
            cands = volts
        j, _, _ = cands[0]
        values = -table.values[j] if j in negated else table.values[j]
        out[ch] = Channel(table.names[j], values, _unit_of(table, ch, cands[0], opts))
    return out


def _unit_of(table: RawTable, ch: str, cand: tuple[int, str | None, bool], opts: ImportOptions) -> str | None:
    """Unit of a channel: --units (by channel or column), the map's suffix, the file, the name, the default."""
    j, map_unit, _ = cand
    name = table.names[j]
    given = opts.units.get(ch) or opts.units.get(name)
    if given is not None:
        unit = unit_name(given)
        if unit is None:
            raise DataError(f"--units {ch}={given}: unknown unit; use one of {', '.join(UNITS[ch])}")
        return unit
    return map_unit or table.units.get(name) or _split_name(name)[1] or ("V" if ch == "u" else None)


# ----------------------------------------------------------------------------------------------- normalising
def _bad_cells(table: RawTable, chans: dict[str, Channel]) -> None:
    """Refuse a channel with a cell that is not a finite number, in one line naming the column, the first such row
    and what it holds (the text of a cell that is not a number, an empty cell, or nan, inf, -inf); a column whose
    cells are only missing at its end is said to be shorter than the record."""
    for ch, c in chans.items():
        raw = table.values[table.names.index(c.column)]  # as in the file: before a -ROLE map flips its sign
        nan = np.flatnonzero(~np.isfinite(raw))
        n = raw.size
        bad = table.bad.get(c.column)
        short = 0 < nan.size < n and nan[0] == n - nan.size and bool(np.isnan(raw[nan]).all())
        if short and (bad is None or not bad[2].strip()):
            raise DataError(
                f"{table.file}: column {c.column!r} ({ch}) ends at row {nan[0]}: {n - nan.size} values for the "
                f"record's {n} rows (a column of another length); {table.form}"
            )
        if nan.size:
            row = int(nan[0])
            if bad is not None and bad[0] == row:  # the first is a cell that is not a number: its text
                line, held = bad[1], repr(bad[2]) if bad[2].strip() else "an empty cell"
            else:  # a number that is not finite
                line, held = 0, f"{raw[row]:g}"
            where = f"row {row}" + (f" (line {line})" if line else "")
            kinds = "infinite/NaN/missing/non-numeric" if np.isinf(raw).any() else "NaN/missing/non-numeric"
            raise DataError(
                f"{table.file}: column {c.column!r} ({ch}) has {nan.size} {kinds} value(s), first at {where}: {held}; "
                f"{table.form}"
            )


def _command_in_range(u: Channel, file: str) -> None:
    """Refuse a command [V] that no DAQ of the twin can carry: beyond the range the DAQ FMU declares for its clamp
    (``daq.out_limit``)."""
    top = source_model("daq").variables["out_limit"].max
    k = int(np.argmax(np.abs(u.values)))
    if top is not None and abs(u.values[k]) > top:
        raise DataError(
            f"{file}: the command (column {u.column!r}) reaches {u.values[k]:.3g} V at row {k}, beyond the +-{top:g} V "
            "a DAQ of the twin can carry (a command in mV, or a corrupt cell?)"
        )


def time_seconds(t: np.ndarray, unit: str | None, table: RawTable, column: str, note: Note) -> tuple[np.ndarray, str]:
    """(time [s], unit it was in) from a column in ``unit``; without one, by the sample-interval rule of the
    module docstring."""
    if unit is not None:
        if unit not in _TIME_FACTOR:
            raise DataError(f"{table.file}: time column {column!r} in {unit}; use s, ms or us")
        return t * _TIME_FACTOR[unit], unit
    dt = float(np.median(np.diff(t))) if t.size > 1 else math.nan
    if 0 < dt <= 0.1:
        return t, "s"
    if 1 - 1e-6 <= dt <= 100:  # 1 kHz in ms: 1 Hz in s would be below MIN_RATE anyway
        note(f"time column {column!r} has a sample interval of {dt:g}: taken as milliseconds ({1000 / dt:g} Hz); "
             f"--units t=s refuses this, t=ms silences it")  # fmt: skip
        return t * 1e-3, "ms"
    if not dt > 0:
        return t, "s"  # not increasing: uniform_time names the row
    reason = (
        f"{1 / dt:.3g} Hz in seconds (too slow for the link's ~3 Hz mode) or {1000 / dt:.3g} Hz in milliseconds"
        if dt <= 1
        else f"{1000 / dt:.3g} Hz in milliseconds (too slow for the link's ~3 Hz mode)"
    )
    raise DataError(
        f"{table.file}: time column {column!r} has a sample interval of {dt:g}: {reason}; "
        f"say which with --units t=s, t=ms or t=us"
    )


def _grid(t: np.ndarray) -> tuple[np.ndarray, float, int]:
    """Least-squares uniform grid a + k Ts of time stamps ``t`` [s] (integer rate when as good); returns
    (grid, largest |t - grid| [s], its row)."""
    k = np.arange(t.size, dtype=float)
    Ts, a = np.polyfit(k, t - t[0], 1)
    best = a + t[0] + k * Ts
    rate = round(1.0 / Ts)
    if rate > 0:
        nice = t[0] + float(np.mean(t - t[0] - k / rate)) + k / rate
        if np.max(np.abs(t - nice)) <= 1.5 * np.max(np.abs(t - best)):
            best = nice
    err = np.abs(t - best)
    return best, float(err.max()), int(err.argmax())


def _resample(t: np.ndarray, grid: np.ndarray, v: np.ndarray, wraps: bool) -> np.ndarray:
    """Linear interpolation onto ``grid``; with ``wraps`` (a pot's volts) jumps larger than half the span are
    not interpolated across (the nearer sample is taken)."""
    out = np.interp(grid, t, v)
    if wraps and v.size > 1:
        jumps = np.flatnonzero(np.abs(np.diff(v)) > max(0.5 * float(np.ptp(v)), 2.0))
        for i in jumps:
            inside = (grid > t[i]) & (grid < t[i + 1])
            near = np.where(grid[inside] - t[i] <= t[i + 1] - grid[inside], v[i], v[i + 1])
            out[inside] = near
    return out


def uniform_time(t: np.ndarray, table: RawTable, column: str) -> tuple[np.ndarray | None, float, float]:
    """(grid or None when ``t`` [s] is uniform already, largest correction [s], Ts [s]); refuses what is not
    increasing or strays more than JITTER_LIMIT of a sample from a uniform grid."""
    dt = np.diff(t)
    bad = np.flatnonzero(dt <= 0)
    if bad.size:
        k = int(bad[0]) + 1
        raise DataError(
            f"{table.file}: time column {column!r} is not strictly increasing: row {k} has t = {t[k]:g} s "
            f"after {t[k - 1]:g} s; {table.form}"
        )
    Ts = float(np.median(dt))
    if np.max(np.abs(dt - Ts)) <= 1e-6 * Ts + 1e-9:
        return None, 0.0, Ts
    grid, worst, row = _grid(t)
    Ts = float((grid[-1] - grid[0]) / (grid.size - 1))
    if worst > JITTER_LIMIT * Ts:
        first = int(np.argmax(np.abs(t - grid) > JITTER_LIMIT * Ts))
        raise DataError(
            f"{table.file}: non-uniform sampling: time stamps stray up to {1e3 * worst:.3g} ms (row {row}) from "
            f"the uniform {1 / Ts:.6g} Hz grid, first beyond {100 * JITTER_LIMIT:g} % of the "
            f"{1e3 * Ts:.4g} ms interval at row {first}; gaps and clock jumps are not resampled"
        )
    return grid, worst, Ts


def _angle(ch: str, c: Channel, opts: ImportOptions, file: str) -> np.ndarray:
    """Angle [deg] of a theta/alpha channel recorded in deg, rad, counts or m/mm of tip deflection."""
    if c.unit == "deg":
        return c.values
    if c.unit == "rad":
        return np.degrees(c.values)
    if c.unit == "counts":
        if not opts.counts_per_rev:
            raise DataError(f"{file}: {ch} column {c.column!r} is in encoder counts: give --counts-per-rev (e.g. 4096)")
        return c.values * (360.0 / float(opts.counts_per_rev))
    length = opts.link_length
    if not length:
        raise DataError(f"{file}: {ch} column {c.column!r} is a tip deflection in {c.unit}: give --link-length "
                        f"in m (e.g. 0.419)")  # fmt: skip
    d = c.values * (1e-3 if c.unit == "mm" else 1.0)
    return np.degrees(np.arctan2(d, float(length)))


class _Cut(Exception):  # noqa: N818 - not an error: a record to be cut at its jumps
    """A record's theta jumps where no hub moves and no pot wraps: cut it at ``rows`` (the first sample of each part
    after the first); ``jumps`` (row, time [s], jump [deg], limit [deg]) per cut."""

    def __init__(self, rows: list[int], jumps: list[tuple[int, float, float, float]], need: int) -> None:
        super().__init__(f"cut at rows {rows}")
        self.rows, self.jumps, self.need = rows, jumps, need


def _faults(
    name: str, chans: dict[str, Channel], cols: dict[str, np.ndarray], t: np.ndarray, cal: Calibration, encoder: bool
) -> tuple[list[Fault], dict[str, list[list[int]]], list[tuple[int, float, float, float]]]:
    """A record's sensor faults (:mod:`harness.rig.faults`): (the wraps and the pinned runs found, the masked sample
    ranges [first, end) per channel, the jumps to cut at as (row, time [s], jump [deg], limit [deg])). ``cols`` are
    the dataset's angle columns before resampling, at times ``t`` [s]; a wrap is unwrapped in place
    (``cols["theta"]``, by :func:`harness.ident.calibration.theta_deg`, as the diagnosis and the identification read
    theta). A pinned run is found first: where it lets go, theta's jump is the fault's, not the hub's."""
    Ts, u = float(np.median(np.diff(t))), chans["u"].values
    faults: list[Fault] = []
    masked: dict[str, list[list[int]]] = {}
    for ch, other in (("alpha", "theta"),) if encoder else (("theta", "alpha"), ("alpha", "theta")):
        c = chans[ch]  # an encoder's count has no noise to lose nor a rail: its runs at rest say nothing
        for kind, spans in pinned_runs(c.values, [u, cols[other]]):
            a, count = spans[0][0], sum(e - s for s, e in spans)
            runs = f" in {len(spans)} runs" if len(spans) > 1 else ""
            what = "its extreme: a rail (an ADC's clamp, a pot's track end)" if kind == "rail" else (
                "while the other channels move: stuck")  # fmt: skip
            size = f"{count} samples{runs} ({count * Ts:.3g} s) held at {float(c.values[a]):.6g} {c.unit or ''}, {what}"
            done = "masked (left out of the identification and the diagnosis), not deleted"
            faults.append(Fault(name, ch, kind, a, float(t[a]), count, size, done))
            masked.setdefault(ch, []).extend([s, e] for s, e in spans)
    held = mask(t.size, [(a, b) for a, b in masked.get("theta", [])])
    reading = theta_deg(cols["theta_v"], cal, unwrap=False)  # the pot's angle as read: its wraps in it
    limit = fastest_step_deg(Ts, float(np.max(np.abs(u))))
    cuts: list[tuple[int, float, float, float]] = []
    wrapped = False
    for i in impossible_jumps(reading, limit):
        jump = float(reading[i + 1] - reading[i])
        k = int(i) + 1
        if held[i] or held[k]:
            continue  # a pinned run letting go
        if encoder or not is_turn(jump, limit):
            cuts.append((k, float(t[k]), jump, limit))
            continue
        wrapped = True
        volts = f" ({float(cols['theta_v'][k] - cols['theta_v'][i]):+.4g} V)" if chans["theta"].unit == "V" else ""
        size = f"a jump of {jump:+.4g} deg{volts} in one sample, beyond the {limit:.3g} deg a hub turns in one: a wrap"
        done = f"unwrapped by one turn (360 deg = {360.0 / cal.Kp:.4g} V through Kp {cal.Kp:.4g} deg/V)"
        faults.append(Fault(name, "theta", "wrap", k, float(t[k]), 1, size, done))
    if wrapped and not cuts:
        cols["theta"] = theta_deg(cols["theta_v"], cal)
    return sorted(faults, key=lambda f: (f.row, f.channel)), masked, cuts


def normalise(
    table: RawTable,
    opts: ImportOptions,
    cal: Calibration,
    note: Note,
    name: str = "",
    rows: tuple[int, int] | None = None,
) -> tuple[dict, dict]:
    """(dataset columns, {"entry": manifest entry, "form", "notes"}) of one record: channels resolved, units
    converted, time checked and made uniform, angles turned into the DAQ's volts with ``cal``, sensor faults found
    (:func:`_faults`: a wrap unwrapped, a pinned run masked, each said as a ``fault: `` line). ``note`` receives each
    remark, prefixed with the file name (a warning as ``warning: <file>: ...``). ``name``: the dataset's (for the
    faults' lines); ``rows``: only the table's rows first..end-1 (a part of a record cut at a jump). A jump of theta
    that is no wrap raises :class:`_Cut` (:func:`_normalise_record` cuts the record there)."""
    notes: list[str] = []

    def remark(msg: str) -> None:
        notes.append(msg)
        note(f"{table.file}: {msg}")

    def warn(msg: str) -> None:
        notes.append(f"warning: {msg}")
        note(f"warning: {table.file}: {msg}")

    for msg in table.notes:
        remark(msg)
    table.notes = []
    chans = resolve(table, opts)
    for msg in table.notes:
        remark(msg)
    if opts.controller is not None and "ref" not in chans:
        raise DataError(f"{table.file}: --controller given, but the record has no reference column: map it with "
                        f"--columns NAME=ref (a closed-loop record's reference of theta)")  # fmt: skip
    sensor = _theta_sensor(chans, opts, table.file)
    if "ref" in chans and chans["ref"].unit is None:
        chans["ref"].unit = chans["theta"].unit
        remark(f"reference {chans['ref'].column!r}: no unit given, taken as theta's ({chans['theta'].unit})")
    for ch, c in chans.items():
        if c.unit is None and ch != "t":
            raise DataError(
                f"{table.file}: unit of {ch} (column {c.column!r}) not known; give --units {ch}=UNIT with UNIT one "
                f"of {', '.join(UNITS[ch])}"
            )
        if ch != "t" and c.unit not in UNITS[ch]:
            raise DataError(f"{table.file}: {ch} (column {c.column!r}) in {c.unit}; use {', '.join(UNITS[ch])}")
    if table.values[0].size < 16:
        raise DataError(f"{table.file}: only {table.values[0].size} rows; need at least 16 samples")
    _bad_cells(table, chans)
    _command_in_range(chans["u"], table.file)
    if rows is not None:
        chans = {ch: replace(c, values=c.values[rows[0] : rows[1]]) for ch, c in chans.items()}
    t, chans["t"].unit = time_seconds(chans["t"].values, chans["t"].unit, table, chans["t"].column, remark)
    grid, worst, Ts = uniform_time(t, table, chans["t"].column)
    if Ts > 1.0 / MIN_RATE:
        raise DataError(
            f"{table.file}: time column {chans['t'].column!r} in {chans['t'].unit} has a sample interval of "
            f"{Ts:g} s ({1 / Ts:.3g} Hz): below {MIN_RATE:g} Hz, too slow for the link's ~3 Hz mode; "
            f"is it in ms (--units t=ms)?"
        )
    need = max(2 * MIN_FOLD_SAMPLES, math.ceil(MIN_RECORD_SECONDS / Ts - 1e-6))
    if t.size < need:
        raise DataError(
            f"{table.file}: {t.size} samples at {1 / Ts:.6g} Hz ({t.size * Ts:.4g} s): too short for two folds; "
            f"need at least {need} samples ({MIN_RECORD_SECONDS:g} s and {2 * MIN_FOLD_SAMPLES} samples: "
            f"{MIN_FOLD_SECONDS:g} s and {MIN_FOLD_SAMPLES} samples per fold)"
        )
    cols: dict[str, np.ndarray] = {}
    for ch in ("theta", "alpha"):
        c = chans[ch]
        if c.unit == "V":
            cols[f"{ch}_v"] = c.values
            cols[ch] = theta_deg(c.values, cal) if ch == "theta" else alpha_deg(c.values, cal)
        else:
            deg = _angle(ch, c, opts, table.file)
            off, gain = (cal.pot_offset_v, cal.Kp) if ch == "theta" else (cal.gauge_offset_v, cal.Ke)
            cols[f"{ch}_v"], cols[ch] = deg / gain + off, deg
    faults, masked, cuts = _faults(name or table.file, chans, cols, t, cal, bool(sensor))
    if cuts:
        raise _Cut([k for k, *_ in cuts], cuts, need)
    for f in faults:
        notes.append(f.line())
        note(f.line())
    zero = 0.0
    if opts.zero_alpha:
        zero, where = _gauge_zero(cols, Ts)
        if math.isfinite(zero):
            cols["alpha"] = cols["alpha"] - zero
            cols["alpha_v"] = cols["alpha"] / cal.Ke + cal.gauge_offset_v
            remark(f"alpha zeroed: it read {zero:.4g} deg over {where} (the gauge's zero)")
        else:
            warn(f"--zero-alpha: {where}; alpha left as read (the diagnosis fits its gauge offset)")
            zero = 0.0
    if "ref" in chans:
        c = chans["ref"]
        cols["ref"] = theta_deg(c.values, cal) if c.unit == "V" else _angle("ref", c, opts, table.file)
    cols = {"t": t, "u": chans["u"].values, **cols}
    if grid is not None:
        wrapped = chans["theta"].unit == "V" and not sensor  # a pot's volts wrap; an encoder's angle does not
        cols = {k: _resample(t, grid, v, wrapped and k == "theta_v") for k, v in cols.items() if k != "t"}
        cols = {"t": grid, **cols}
        if wrapped:
            cols["theta"] = theta_deg(cols["theta_v"], cal)
        remark(f"host-clock jitter up to {1e6 * worst:.3g} us ({100 * worst / Ts:.2g} % of the {1e3 * Ts:.4g} ms "
               f"interval): resampled onto the uniform {1 / Ts:.6g} Hz grid by linear interpolation")  # fmt: skip
    order = ("t", "u", "theta_v", "alpha_v", "theta", "alpha", *(k for k in OPTIONAL if k in cols))
    cols = {k: np.asarray(cols[k], dtype=float) for k in order}
    validate(pd.DataFrame(cols), table.file)
    rate = 1.0 / Ts
    rate = float(round(rate)) if abs(rate - round(rate)) <= 1e-9 * rate else rate
    entry = {
        "role": "identification",
        "signal": "imported",
        "n": int(t.size),
        "sample_rate": rate,
        "columns": {ch: c.column for ch, c in chans.items()},
        "units": {ch: c.unit for ch, c in chans.items()},
        "jitter_corrected_s": worst,
    }
    lattice: dict[str, float] = {}  # the angle step [deg] per channel recorded on one
    for ch in ("theta", "alpha"):
        step = _step_deg(chans[ch], opts)
        if step:
            lattice[ch] = step
    if sensor:  # an encoder's count is theta's step (its angle printed finer or not)
        step = 360.0 / sensor["counts_per_rev"]
        found = lattice.get("theta", 0.0)
        lattice["theta"] = found if found > step * (1 + 1e-6) else step  # the count, unless printed coarser
        off = _off_lattice(cols["theta"], step)
        printed = _step_deg(chans["theta"], opts) if chans["theta"].unit in ("deg", "rad") else 0.0
        if off > 0.01 + 0.5 * printed / step:  # an angle printed to few decimals is that far off by its rounding
            remark(f"theta is not on the encoder's {step:.6g} deg steps (up to {off:.2g} of a step off: filtered or "
                   f"resampled?); its step is recorded as {step:.6g} deg all the same")  # fmt: skip
    if lattice:
        entry["lattice_deg"] = lattice
    if faults:
        entry["faults"] = [f.to_dict() for f in faults]
    if masked:
        entry["masked"] = masked
    entry.update(sensor)
    if "ref" in cols:
        entry["loop"] = "closed"
        entry["controller"] = _controller(cols, Ts, opts, remark, zero, warn, table.file).to_dict()
    return cols, {"entry": entry, "form": table.form, "notes": notes}


def _step_deg(c: Channel, opts: ImportOptions) -> float:
    """The angle step [deg] an angle channel is recorded on: an encoder's count, or the common step of the values of
    an angle in deg, rad or a tip deflection (their last printed decimal, or a lattice converted between units); 0 for
    volts, whose ADC lattice the diagnosis finds itself, or none."""
    if c.unit == "counts":
        return 360.0 / float(opts.counts_per_rev or 1)
    if c.unit == "V":
        return 0.0
    res, step = decimal_resolution(c.values), value_step(c.values)
    if res and (not step or abs(step - res) <= 1e-6 * res):
        step = res  # the printed decimal itself, exactly
    if not step:
        return 0.0
    if c.unit in ("m", "mm"):
        return math.degrees(math.atan(step * (1e-3 if c.unit == "mm" else 1.0) / float(opts.link_length or 1.0)))
    return math.degrees(step) if c.unit == "rad" else step


def _theta_sensor(chans: dict[str, Channel], opts: ImportOptions, file: str) -> dict[str, Any]:
    """The manifest's ``theta_sensor`` (and ``counts_per_rev``) of a record: an encoder when said, when theta is in
    counts, or when ``counts_per_rev`` is given for a theta in deg or rad (and no other channel is in counts); a
    ``counts_per_rev`` that can describe nothing (a pot's theta, no channel in counts) is refused."""
    theta, counted = chans["theta"], any(c.unit == "counts" for c in chans.values())
    implied = bool(opts.counts_per_rev) and theta.unit != "V" and not counted
    sensor = opts.theta_sensor or ("encoder" if theta.unit == "counts" or implied else "pot")
    if sensor not in THETA_SENSORS:
        raise DataError(f"--theta-sensor {sensor!r}: use {' or '.join(THETA_SENSORS)}")
    if sensor == "pot":
        if opts.counts_per_rev and not counted:
            why = "theta is in volts, a pot's" if opts.theta_sensor is None else "--theta-sensor pot"
            raise DataError(f"{file}: --counts-per-rev {opts.counts_per_rev:g} describes no channel ({why}, none in "
                            "counts); an encoder theta is --theta-sensor encoder")  # fmt: skip
        return {}
    if not opts.counts_per_rev and theta.unit == "counts":
        raise DataError(f"{file}: theta column {theta.column!r} is in encoder counts: give --counts-per-rev "
                        "(e.g. 4096)")  # fmt: skip
    if not opts.counts_per_rev:
        raise DataError(f"{file}: an encoder theta needs --counts-per-rev (e.g. 4096)")
    return {"theta_sensor": "encoder", "counts_per_rev": float(opts.counts_per_rev)}


def _off_lattice(theta: np.ndarray, step: float) -> float:
    """Largest distance of ``theta`` [deg] from the lattice of ``step`` [deg] through its first sample, in steps."""
    k = (np.asarray(theta, dtype=float) - float(theta[0])) / step
    return float(np.max(np.abs(k - np.round(k)))) if k.size else 0.0


def _gauge_zero(cols: dict[str, np.ndarray], Ts: float) -> tuple[float, str]:
    """The deflection's zero [deg] and what it was read on: its median over the record's quietest stretch of
    ZERO_SECONDS where the shaft is at rest (it moves less than AT_REST_DEG) and the link too (its deflection's RMS
    about its mean within REST_SIGMAS times its noise: the MAD of its third differences, at least the step between
    its values there / sqrt 12: a lattice's, uniform or not, as a length read as an angle); (NaN, why) where the
    link never rests."""
    th, al = cols["theta"], cols["alpha"]
    n = max(4, int(round(ZERO_SECONDS / Ts)))
    if al.size < 2 * n:
        return math.nan, f"the record is shorter than two stretches of {ZERO_SECONDS:g} s"
    d3 = np.diff(al, 3)
    sigma = 1.4826 * float(np.median(np.abs(d3 - np.median(d3)))) / math.sqrt(20.0)
    starts = np.arange(0, al.size - n + 1, max(1, n // 2))
    still = [a for a in starts if float(np.ptp(th[a : a + n])) < AT_REST_DEG]
    if not still:
        return math.nan, f"the shaft never rests for {ZERO_SECONDS:g} s"
    quiet = min(still, key=lambda a: (float(np.std(al[a : a + n])), a))
    rms = float(np.std(al[quiet : quiet + n]))
    levels = np.unique(al[quiet : quiet + n])
    if levels.size > 1:  # its resolution there (continuous values: far below their noise)
        sigma = max(sigma, float(np.median(np.diff(levels))) / math.sqrt(12.0))
    if rms > REST_SIGMAS * sigma:
        return math.nan, (f"the link never rests: its quietest {ZERO_SECONDS:g} s (at {quiet * Ts:.3g} s) swings "
                          f"{rms:.3g} deg RMS, {rms / max(sigma, 1e-12):.0f}x its noise")  # fmt: skip
    return float(np.median(al[quiet : quiet + n])), f"its quietest {ZERO_SECONDS:g} s at rest, at {quiet * Ts:.3g} s"


def _controller(
    cols: dict[str, np.ndarray],
    Ts: float,
    opts: ImportOptions,
    remark: Note,
    zero: float = 0.0,
    warn: Note | None = None,
    file: str = "",
) -> Controller:
    """A closed-loop record's controller: the one given (with how much of the logged command its law explains), or
    identified from it (both kinds, the better R^2; below ``R2_MIN`` kept with a warning: the diagnosis then replays
    the record by multiple shooting), on the deflection as the controller read it (``zero`` [deg] removed from the
    data: its ``alpha_bias``). Angles of ``cols`` in deg, ``Ts`` [s]."""
    warn = warn or remark
    ref, th = np.radians(cols["ref"]), np.radians(cols["theta"])
    if opts.controller is not None:
        given = opts.controller if opts.controller.alpha_bias or not zero else replace(opts.controller, alpha_bias=zero)
        if given.sample_rate and abs(given.sample_rate * Ts - 1.0) > 1e-6:
            remark(f"the given controller runs at {given.sample_rate:g} Hz, the record at {1 / Ts:.6g} Hz: its law is "
                   "not checked against the logged command")  # fmt: skip
            return given
        r2 = command_r2(given, ref, th, np.radians(cols["alpha"]), cols["u"], Ts)
        if math.isfinite(r2) and r2 < R2_MIN:
            warn(f"the given controller explains R^2 {r2:.3f} < {R2_MIN} of the logged command (gains in V/rad, "
                 "V s/rad? their signs?); it is used as given")  # fmt: skip
        else:
            remark(f"the given controller explains R^2 {r2:.3f} of the logged command")
        return given
    al = np.radians(cols["alpha"] + zero)
    try:
        found = [identify_controller(ref, th, al, cols["u"], Ts, kind) for kind in IDENTIFIABLE]
    except ValueError as e:
        raise DataError(f"{file}: closed-loop record: {e}") from None
    best = replace(max(found, key=lambda c: c.r2 or -math.inf), alpha_bias=zero)
    gains = ", ".join(f"{v:.4g}" for v in best.K) if best.kind == "state_feedback" else (
        f"kp {best.kp:.4g}, ki {best.ki:.4g}, kd {best.kd:.4g}")  # fmt: skip
    limit = f", output limit {best.u_limit:g} V" if best.u_limit else ""
    remark(f"controller identified from the record: {best.kind} ({gains}), velocity filter {best.cutoff:g} Hz, "
           f"reference delay {best.ref_delay} sample(s){limit}, R^2 {best.r2:.3f}")  # fmt: skip
    if (best.r2 or 0.0) < R2_MIN:
        warn(f"R^2 {best.r2:.3f} < {R2_MIN}: this controller does not explain the logged command; no closed-loop "
             "replay: the diagnosis replays the record open loop by multiple shooting")  # fmt: skip
    return best


# ----------------------------------------------------------------------------------------------- entry point
def calibration_option(kp: float | None, ke: float | None, file: Path | None) -> Calibration | None:
    """The calibration given at import: ``kp`` and ``ke`` [deg/V] together, or a calibration.json ``file``;
    None when nothing is given."""
    if file is not None:
        if kp is not None or ke is not None:
            raise DataError("give either --kp/--ke or --calibration FILE, not both")
        if not Path(file).is_file():
            raise DataError(f"--calibration {file}: no such file")
        cal = Calibration.from_json(file)
        cal.source = {**cal.source, "imported_from": Path(file).name}
        return cal
    if (kp is None) != (ke is None):
        raise DataError(f"--kp and --ke go together (got only {'--kp' if kp is not None else '--ke'})")
    if kp is None or ke is None:
        return None
    why = {"method": "given at import (--kp/--ke)"}
    return Calibration(Kp=kp, Ke=ke, source={"Kp": why, "Ke": why})


def _calibration(opts: ImportOptions) -> Calibration:
    if opts.calibration is not None:
        return opts.calibration
    s = LAB1_CALIBRATION
    why = {"method": "assumed at import: lab 1's value (no calibration given)"}
    return Calibration(Kp=s["Kp"], Ke=s["Ke"], source={"Kp": why, "Ke": why, "assumed": True})


def import_records(
    paths: Sequence[Path | str],
    out: Path,
    opts: ImportOptions | None = None,
    note: Note | None = None,
    force: bool = False,
) -> list[Path]:
    """Import real records into a new run directory, as they were recorded.

    Every file is read and checked before anything is written; the run is written aside and moved into place
    (:func:`harness.rundir.new_run`). The rules (formats, units, time, encoders, closed loops) are in the module
    docstring of :mod:`harness.rig.records`.

    Parameters
    ----------
    paths : sequence of str or Path
        The records: a file each, or ``[NAME=]FILE+FILE+...`` for one record written as several files that share
        its time base (:func:`record_files`).
    out : Path
        The run directory to write: ``data/<name>.parquet``, ``calibration.json``, a ``manifest.json`` of kind
        "import" (each record's files and their sha256, units, sensors, controller).
    opts : ImportOptions, optional
        Column map, units, link length, encoder counts, calibration, controller (``flexjoint import``'s options).
    note : callable, optional
        Called with each one-line remark (units taken, resampling, the calibration assumed, a warning).
    force : bool
        Replace a run already in ``out``.

    Returns
    -------
    list of Path
        The datasets written.

    Raises
    ------
    harness.DataError
        One line naming the file, the column and the row of what cannot be read; nothing is written.
    """
    opts = opts or ImportOptions()
    say = note or (lambda _m: None)
    if not paths:
        raise DataError("no record files given")
    records = [record_files(p) for p in paths]
    stems = [name for name, _ in records]
    dup = sorted({s for s in stems if stems.count(s) > 1})
    if dup:
        raise DataError(f"two records named {dup[0]!r}: dataset names come from the file names, rename one "
                        "(or name it: NAME=FILE, NAME=FILE+FILE for a record of several files)")  # fmt: skip
    out = Path(out)
    check_new_run(out, force)
    _check_options(opts)
    cal = _calibration(opts)
    done: dict[str, tuple[list[Path], dict, dict]] = {}
    for name, files in records:
        for part, cols, info in _normalise_record(name, read_record(files), opts, cal, say):
            if part in done or part in stems and part != name:
                raise DataError(f"two records named {part!r}: a part of the record {name!r} cut at a jump of theta "
                                "and another record; rename one (NAME=FILE)")  # fmt: skip
            done[part] = (files, cols, info)
    if opts.calibration is None:
        say(f"calibration: none given; assumed lab 1's Kp {cal.Kp:g} deg/V, Ke {cal.Ke:g} deg/V, gauge offset 0 V "
            f"(give --kp/--ke or --calibration FILE)")  # fmt: skip
    with new_run(out, force) as work:
        _write_import(work, done, cal, opts, say)
    return [RunDir(out).dataset(name) for name in done]


def _normalise_record(
    name: str, table: RawTable, opts: ImportOptions, cal: Calibration, say: Note
) -> list[tuple[str, dict, dict]]:
    """[(dataset name, columns, info)] of one record (:func:`normalise`): the record itself, or where theta jumps
    as no hub moves and no pot wraps, the parts it is cut into there, named ``NAME_1``, ``NAME_2``, ... in time order,
    each kept if it is long enough for two folds; the jump is said in one ``fault: `` line, and a record of which no
    part is long enough is refused."""
    held: list[str] = []
    read_notes = list(table.notes)
    try:
        cols, info = normalise(table, opts, cal, held.append, name)
    except _Cut as cut:
        edges = [0, *cut.rows, table.values[0].size]
        spans = list(zip(edges[:-1], edges[1:], strict=True))
        names = [f"{name}_{k + 1}" for k in range(len(spans))]
        kept = [(n, a, b) for n, (a, b) in zip(names, spans, strict=True) if b - a >= cut.need]
        said = ", ".join(f"{n} (rows {a}-{b - 1})" for n, a, b in kept) or "no part"
        short = len(spans) - len(kept)
        done = (f"cut there into {len(spans)} parts, kept {said}"
                + (f"; {short} shorter than {cut.need} samples dropped" if short else ""))  # fmt: skip
        why = "and no turn of the pot (an encoder's, or a span the calibration does not give)"
        lines = [
            Fault(name, "theta", "jump", k, time, 1, f"a jump of {jump:+.4g} deg in one sample, beyond the {limit:.3g} "
                  f"deg a hub turns in one, {why}", done).to_dict()
            for k, time, jump, limit in cut.jumps
        ]  # fmt: skip
        if not kept:
            raise DataError(f"{table.file}: {lines[0]['line']}: nothing left to import") from None
        for f in lines:
            say(str(f["line"]))
        out = []
        for n, a, b in kept:
            part = replace(table, file=f"{table.file} rows {a}-{b - 1}", notes=list(read_notes))
            cols, info = normalise(part, opts, cal, say, n, (a, b))
            info["entry"]["faults"] = [*lines, *info["entry"].get("faults", [])]
            info["notes"] = [str(f["line"]) for f in lines] + info["notes"]
            out.append((n, cols, info))
        return out
    for m in held:
        say(m)
    return [(name, cols, info)]


def _write_import(out: Path, done: dict, cal: Calibration, opts: ImportOptions, say: Note) -> None:
    """Write the normalised records ``done`` (name -> (files, columns, info)) as run directory ``out``."""
    for name, (_, cols, _) in done.items():
        write_dataset(RunDir(out).dataset(name), cols)
    cal.to_json(RunDir(out).calibration)
    rates = sorted({info["entry"]["sample_rate"] for _, _, info in done.values()})
    if len(rates) > 1:
        say(f"records at different sample rates ({', '.join(f'{r:g}' for r in rates)} Hz): identify them apart")
    Manifest(
        kind="import",
        sample_rate=rates[0] if len(rates) == 1 else None,
        sources={
            name: {
                "file": "+".join(f.name for f in files),
                "sha256": "+".join(_sha256(f) for f in files),
                "format": info["form"],
                "notes": info["notes"],
            }
            for name, (files, _, info) in done.items()
        },
        calibration="assumed" if opts.calibration is None else "given",
        experiments=[ExperimentEntry(name=name, **info["entry"]) for name, (_, _, info) in done.items()],
    ).write(out)
    record_inputs(out, "calibration.json")


def _check_options(opts: ImportOptions) -> None:
    """Refuse options that cannot describe a record, before any file is read: ``counts_per_rev`` and
    ``link_length`` [m] finite and > 0, ``theta_sensor`` pot or encoder."""
    for name, value in (("--counts-per-rev", opts.counts_per_rev), ("--link-length", opts.link_length)):
        if value is not None and not (math.isfinite(float(value)) and float(value) > 0):
            raise DataError(f"{name} {value:g}: must be a number > 0")
    if opts.theta_sensor is not None and opts.theta_sensor not in THETA_SENSORS:
        raise DataError(f"--theta-sensor {opts.theta_sensor!r}: use {' or '.join(THETA_SENSORS)}")


def _sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()
