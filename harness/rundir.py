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
    report.md, figures/     the report;   run.rrd  the Rerun recording
"""

from __future__ import annotations

import json
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from .spec import Spec, from_dict

REQUIRED = ("t", "u", "theta_v", "alpha_v")


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
    def report(self) -> Path:
        return self.root / "report.md"

    @property
    def figures(self) -> Path:
        return self.root / "figures"

    @property
    def recording(self) -> Path:
        return self.root / "run.rrd"


class DataError(ValueError):
    """A dataset that cannot be used; the message is one line meant for the user."""


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
    """Check a dataset: required columns, finite numbers, uniform strictly increasing time."""
    missing = [c for c in REQUIRED if c not in df.columns]
    if missing:
        raise DataError(f"{name}: missing column(s) {', '.join(missing)}; need {', '.join(REQUIRED)}")
    if len(df) < 16:
        raise DataError(f"{name}: only {len(df)} rows; need at least 16 samples")
    for c in REQUIRED:
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
    """Read and validate one dataset (Parquet)."""
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such dataset")
    return validate(pq.read_table(path).to_pandas(), path.name)


def sample_time(df: pd.DataFrame) -> float:
    """Sampling period Ts [s] of a validated dataset."""
    return float(np.median(np.diff(df["t"].to_numpy())))


def load_manifest(run: Path) -> dict[str, Any]:
    p = RunDir(run).manifest
    if not p.exists():
        raise DataError(f"{run}: not a run directory (no manifest.json)")
    return json.loads(p.read_text())


def load_spec(run: Path) -> Spec | None:
    """The spec recorded in a campaign's manifest (None for imported data)."""
    m = load_manifest(run)
    return from_dict(m["spec"], m.get("spec_file", "")) if m.get("kind") == "campaign" else None


def load_run(run: Path, role: str | None = "identification") -> dict[str, pd.DataFrame]:
    """Datasets of a run directory in manifest order, optionally only those of one role."""
    manifest = load_manifest(run)
    out = {}
    for e in manifest["experiments"]:
        if role is None or e.get("role", "identification") == role:
            out[e["name"]] = read_dataset(RunDir(run).dataset(e["name"]))
    if not out:
        raise DataError(f"{run}: no {role or ''} datasets in manifest.json")
    return out
