"""The diagnosis's replays beside the record: ``diagnosis.replays.parquet``, what the report and the viewer draw.

One row per sample of every experiment: ``experiment``, ``t`` [s], the record's ``theta``/``alpha`` [deg] (as the
diagnosis compared them: calibrated, theta unwrapped), ``theta_valid``/``alpha_valid`` (the samples that measure the
shaft) and the simulation's angles for each stage of :data:`STAGES` (``theta_given``, ``alpha_given``, ...; theta NaN
where the simulated pot is off its track).
float32 (a figure's resolution), zstd, no statistics: byte-stable, and kept out of diagnosis.json so that stays small.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from ..rundir import DataError, atomic_write_bytes
from .experiments import CHANNELS, RigExperiment

__all__ = ["STAGES", "Replay", "read_replays", "write_replays"]

STAGES = {
    "given": "simulation as given",
    "recalibrated": "recalibrated",
    "effects": "recalibrated, with the effects",
}  # stage -> label, in the order of the diagnosis


@dataclass(frozen=True)
class Replay:
    """One experiment: time ``t`` [s], the record per channel [deg] (NaN where a sample is not valid), the simulation
    per stage and channel [deg] (``sim[stage][channel]``) and the record's sum of squares about its mean per channel
    ``sst`` [deg^2] (over every sample, as the diagnosis normalises its gap)."""

    t: np.ndarray
    record: dict[str, np.ndarray]
    sim: dict[str, dict[str, np.ndarray]]
    sst: dict[str, float]


def write_replays(
    path: Path, experiments: dict[str, RigExperiment], traces: dict[str, dict[str, dict[str, np.ndarray]]]
) -> None:
    """Write ``traces`` ({stage: {experiment: {channel: simulated [deg]}}}, stages of :data:`STAGES`) beside the
    records of ``experiments`` to ``path``, atomically."""
    cols: dict[str, list[np.ndarray]] = {"t": [], **{c: [] for c in CHANNELS}}
    cols.update({f"{c}_{s}": [] for s in STAGES for c in CHANNELS})
    valid: dict[str, list[np.ndarray]] = {f"{c}_valid": [] for c in CHANNELS}
    names: list[str] = []
    for name, x in experiments.items():
        n = x.t.size
        names += [name] * n
        cols["t"].append(x.t - x.t[0])
        for c in CHANNELS:
            cols[c].append((x.theta if c == "theta" else x.alpha)[:n])
            valid[f"{c}_valid"].append(np.asarray(x.valid[c][:n], dtype=bool))
            for s in STAGES:
                y = np.full(n, np.nan)
                sim = traces[s][name][c]
                y[: min(n, sim.size)] = sim[:n]
                cols[f"{c}_{s}"].append(y)
    table = pa.table(
        {
            "experiment": pa.array(names, pa.string()).dictionary_encode(),
            **{k: pa.array(np.concatenate(v).astype(np.float32)) for k, v in cols.items()},
            **{k: pa.array(np.concatenate(v)) for k, v in valid.items()},
        }
    )
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink, compression="zstd", write_statistics=False, store_schema=False)
    atomic_write_bytes(path, sink.getvalue().to_pybytes())


def read_replays(path: Path) -> dict[str, Replay]:
    """The replays of ``path`` by experiment, in the file's order; a DataError line when the file is not one."""
    try:
        df = pq.read_table(path).to_pandas()
    except (OSError, pa.ArrowException) as exc:
        raise DataError(f"{path}: not a replay file ({exc})") from None
    need = [
        "experiment",
        "t",
        *CHANNELS,
        *(f"{c}_valid" for c in CHANNELS),
        *(f"{c}_{s}" for s in STAGES for c in CHANNELS),
    ]
    missing = [c for c in need if c not in df.columns]
    if missing:
        raise DataError(f"{path}: missing column(s) {', '.join(missing)}")
    out = {}
    for name in dict.fromkeys(df["experiment"].astype(str)):
        g = df[df["experiment"].astype(str) == name]
        col = {k: g[k].to_numpy(dtype=bool if k.endswith("_valid") else float) for k in need[1:]}
        out[name] = Replay(
            t=col["t"],
            record={c: np.where(col[f"{c}_valid"], col[c], np.nan) for c in CHANNELS},
            sim={s: {c: col[f"{c}_{s}"] for c in CHANNELS} for s in STAGES},
            sst={c: float(np.sum((col[c] - np.mean(col[c])) ** 2)) for c in CHANNELS},
        )
    return out
