"""Markdown tables and number formatting shared by report.md and the viewer's text panels."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .load import RunResults

__all__ = ["crossfit_table", "fmt", "fmt_any", "num", "orders", "table", "vec"]


def num(x: Any) -> float:
    """``x`` as a float, NaN when it is none."""
    try:
        return float(x)
    except (TypeError, ValueError):
        return math.nan


def fmt(x: Any, nd: int = 2) -> str:
    """A number with ``nd`` decimals ("—" for None/NaN, "yes"/"no" for booleans, no "-0.00")."""
    if x is None:
        return "—"
    if isinstance(x, bool | np.bool_):
        return "yes" if x else "no"
    if isinstance(x, int | np.integer):
        return str(int(x))
    try:
        v = float(x)
    except (TypeError, ValueError):
        return str(x)
    if not math.isfinite(v):
        return "—"
    s = f"{v:.{nd}f}"
    return s[1:] if s.startswith("-") and float(s) == 0.0 else s


def fmt_any(x: Any) -> str:
    """A JSON scalar or list for a table cell: floats to 4 significant digits."""
    if isinstance(x, float):
        return "—" if not math.isfinite(x) else f"{x:.4g}"
    if isinstance(x, list):
        return ", ".join(fmt_any(v) for v in x)
    return "—" if x is None else str(x)


def vec(x: np.ndarray) -> str:
    """A coefficient vector at 6 decimals."""
    return np.array2string(np.asarray(x, dtype=float), precision=6, max_line_width=100, suppress_small=False)


def table(header: list[str], rows: list[list[str]]) -> list[str]:
    """Markdown lines of a table (pipes in cells escaped)."""
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    out += ["| " + " | ".join(c.replace("|", "\\|") for c in r) + " |" for r in rows]
    return out


def orders(rec: Any) -> str:
    """(na,nb,nc,nk) of a model record or grid row."""
    return f"({int(rec['na'])},{int(rec['nb'])},{int(rec['nc'])},{int(rec['nk'])})"


def crossfit_table(res: RunResults) -> list[str]:
    """Markdown lines of the cross-fit table shaped like lab 1's table 2: models (rows) x datasets (numbered
    columns) + ``Average``, computed as the row mean (never copied from the file), then a dataset legend."""
    cf = res.crossfit
    if cf is None or cf.empty:
        return ["No cross-fit results yet."]
    cols = list(cf.columns)
    avg = cf.to_numpy(dtype=float).mean(axis=1)
    header = ["Models/Data Sets", *[str(j + 1) for j in range(len(cols))], "Average"]
    rows = []
    for i, name in enumerate(cf.index):
        rec = res.models.get(name, (None, None))[1]
        label = f"{name} {orders(rec)}" if rec else name
        rows.append([label, *[fmt(v) for v in cf.iloc[i].to_numpy(dtype=float)], fmt(avg[i])])
    return [
        *table(header, rows),
        "",
        "Datasets: " + ", ".join(f"{j + 1} = `{c}`" for j, c in enumerate(cols)) + ".",
    ]
