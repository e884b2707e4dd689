"""Markdown tables and number formatting shared by report.md and the viewer's text panels."""

from __future__ import annotations

import math
import re
from typing import Any

import numpy as np

from .load import RunResults

__all__ = ["MAX_LINE", "crossfit_table", "fmt", "fmt_any", "num", "orders", "table", "vec", "wrap_prose"]

MAX_LINE = 200  # characters: the longest line of prose report.md has (a table's row is one line, however long)
_BREAKS = (r"(?<=[.!?])\s+", r"(?<=;)\s+", r"(?<=:)\s+", r"(?<=,)\s+", r"\s+")  # where a line breaks, the best first
_BLOCK_START = re.compile(r"([-+*>#|]|\d+[.)]|`{3}|~{3}|=+$)(\s|$)")  # a line that starts a block, not a paragraph's
_LIST_ITEM = re.compile(r"\s*([-+*]|\d+[.)])\s+")


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


def _pieces(text: str, level: int) -> list[str]:
    """``text`` cut at each break of ``_BREAKS[level]``, a piece that would start a block (a list item, a table
    row, a heading) kept with the one before it."""
    out: list[str] = []
    start = 0
    for m in [*re.finditer(_BREAKS[level], text), None]:
        piece = text[start : m.start() if m else len(text)]
        if out and _BLOCK_START.match(piece):
            out[-1] += " " + piece
        else:
            out.append(piece)
        start = m.end() if m else start
    return [p for p in out if p]


def _wrap(text: str, width: int, level: int = 0) -> list[str]:
    """``text`` in lines of at most ``width`` characters, cut at sentences first, then at clauses, commas, spaces
    (a word longer than ``width`` is left whole)."""
    if len(text) <= width or level == len(_BREAKS):
        return [text]
    lines: list[str] = []
    for piece in _pieces(text, level):
        parts = _wrap(piece, width, level + 1) if len(piece) > width else [piece]
        if lines and len(lines[-1]) + 1 + len(parts[0]) <= width:
            lines[-1] += " " + parts.pop(0)
        lines += parts
    return lines


def wrap_prose(lines: list[str], width: int = MAX_LINE) -> list[str]:
    """Markdown ``lines`` with each line of prose longer than ``width`` characters cut into lines of a paragraph
    (Markdown joins them again): at sentences where it can, at clauses, commas or spaces where a sentence is longer,
    a list item's lines indented under its text. Tables, headings, images and code blocks are left as they are."""
    out: list[str] = []
    fenced = False
    for line in lines:
        if line.lstrip().startswith(("```", "~~~")):
            fenced = not fenced
        if fenced or len(line) <= width or line.lstrip().startswith(("|", "#", "![", "```", "~~~")):
            out.append(line)
            continue
        item = _LIST_ITEM.match(line)
        indent = len(item.group(0)) if item else len(line) - len(line.lstrip())
        first, *rest = _wrap(line[indent:], width - indent)
        out += [line[:indent] + first, *(" " * indent + r for r in rest)]
    return out
