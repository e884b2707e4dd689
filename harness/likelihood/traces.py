"""The missing force's traces stored: ``force_picture.parquet``, what the report and the recording redraw from.

One row per sample of every record of a :class:`harness.likelihood.force.ForcePicture`: ``record``, ``t`` [s],
``force`` and ``force_sd`` [N m], ``speed`` and ``speed_sd`` [deg/s], ``u`` [V], ``alpha`` [deg]; float64, zstd, no
statistics: byte-stable, and kept out of likelihood.json so that stays small.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from ..rundir import DataError, atomic_write_bytes
from .force import ForceTrace

__all__ = ["COLUMNS", "read_traces", "write_traces"]

COLUMNS = ("t", "force", "force_sd", "speed", "speed_sd", "u", "alpha")  # beside "record"


def write_traces(path: Path, traces: Sequence[ForceTrace]) -> Path:
    """Write ``traces`` to ``path`` (``force_picture.parquet``: module doc), atomically and byte-stable.

    Parameters
    ----------
    path : Path
        The file.
    traces : sequence of ForceTrace
        Each record's (:attr:`harness.likelihood.force.ForcePicture.traces`).

    Returns
    -------
    Path
        ``path``.
    """
    names = [tr.name for tr in traces for _ in range(tr.t.size)]
    cols = {c: np.concatenate([np.asarray(getattr(tr, c), dtype=float) for tr in traces]) for c in COLUMNS}
    table = pa.table({"record": pa.array(names, pa.string()).dictionary_encode(),
                      **{c: pa.array(v) for c, v in cols.items()}})  # fmt: skip
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink, compression="zstd", write_statistics=False, store_schema=False)
    atomic_write_bytes(Path(path), sink.getvalue().to_pybytes())
    return Path(path)


def read_traces(path: Path) -> tuple[ForceTrace, ...]:
    """The traces of ``path`` (:func:`write_traces`'s), by record in the file's order; a DataError line when the file
    is not one."""
    try:
        table = pq.read_table(path)
    except (OSError, pa.ArrowException) as exc:
        raise DataError(f"{path}: not a force picture ({exc})") from None
    missing = [c for c in ("record", *COLUMNS) if c not in table.column_names]
    if missing:
        raise DataError(f"{path}: missing column(s) {', '.join(missing)}")
    names = np.asarray(table.column("record").cast(pa.string()).to_pylist(), dtype=object)
    cols = {c: table.column(c).to_numpy().astype(float) for c in COLUMNS}
    return tuple(ForceTrace(str(name), *(cols[c][names == name] for c in COLUMNS)) for name in dict.fromkeys(names))
