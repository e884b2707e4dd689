"""What a command prints when its work is done, made to fit one screen (issue 65): at most :data:`MAX_LINES` lines of
at most :data:`WIDTH` characters, tables included. One rule for every command: a list longer than :data:`MAX_ITEMS`
shows its first items and "and N more (see FILE)", FILE the file that holds them all (:func:`cut`); a note longer
than :data:`NOTE_CHARS` (a caveat) its first sentence and where the rest is (:func:`brief`); a summary still longer
than :data:`MAX_LINES` keeps its first lines and its closing ones (where the detail is), the lines between said as
"and N more lines (see FILE)" (:class:`Summary`). The files a command writes keep everything."""

from __future__ import annotations

import textwrap
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from rich.text import Text

if TYPE_CHECKING:
    from rich.console import Console

__all__ = ["MAX_ITEMS", "MAX_LINES", "MAX_ROWS", "NOTE_CHARS", "WIDTH", "Summary", "brief", "cut", "joined", "more"]

MAX_LINES = 40  # a command's summary, tables included
WIDTH = 100  # characters of a line, at most (fewer on a narrower terminal)
MAX_ITEMS = 5  # items of a list shown before "and N more"
MAX_ROWS = 10  # a matrix's rows and columns (the cross-validation's), the first ones of more
NOTE_CHARS = 200  # a note (a caveat) longer than this is cut to its first sentence
INDENT = 4  # a wrapped line's continuation, under its text
NBSP = "\u00a0"  # where a line is not broken


def more(n: int, where: str) -> str:
    """The words that stand for ``n`` items left out: "and 3 more (see diagnosis.json)".

    Parameters
    ----------
    n : int
        How many items are left out.
    where : str
        The file that holds them all.

    Returns
    -------
    str
        The phrase.
    """
    return f"and {n} more (see {where})"


def cut(items: Iterable[str], where: str, limit: int = MAX_ITEMS) -> list[str]:
    """A list for the terminal: whole when it has at most ``limit`` items, else its first ``limit`` and
    :func:`more` for the rest.

    Parameters
    ----------
    items : iterable of str
        The list, in the order to show it.
    where : str
        The file that holds every item.
    limit : int
        The most items shown.

    Returns
    -------
    list of str
        At most ``limit + 1`` items.
    """
    items = list(items)
    if len(items) <= limit:
        return items
    return [*items[:limit], more(len(items) - limit, where)]


def joined(items: Iterable[str], where: str, sep: str = ", ", limit: int = MAX_ITEMS) -> str:
    """:func:`cut`'s items on one line, separated by ``sep``.

    Parameters
    ----------
    items : iterable of str
        The list.
    where : str
        The file that holds every item.
    sep : str
        Between two items.
    limit : int
        The most items shown.

    Returns
    -------
    str
        The items joined.
    """
    return sep.join(cut(items, where, limit))


def brief(text: str, where: str, chars: int = NOTE_CHARS) -> str:
    """A note for the terminal: whole when it has at most ``chars`` characters, else its first sentence (up to the
    first ". ", each aside in parentheses longer than 60 characters said as "(...)") cut, when still too long, at
    the last "; ", ", " or space before ``chars``, then "... (see WHERE)".

    Parameters
    ----------
    text : str
        The note.
    where : str
        The file that holds it whole.
    chars : int
        The longest note kept whole.

    Returns
    -------
    str
        The note, at most ``chars`` characters and the pointer.
    """
    text = " ".join(text.split())
    if len(text) <= chars:
        return text
    short = _without_long_asides(text)
    if len(short) <= chars:
        return f"{short} (see {where})"
    head = short.split(". ", 1)[0]
    if len(head) > chars:
        window = head[:chars]
        for sep in ("; ", ", ", " "):
            if (i := window.rfind(sep)) > chars // 3:
                head = window[:i]
                break
        else:
            head = window
        if head.count("(") > head.count(")"):  # an aside left open: cut before it
            head = head[: head.rfind("(")]
    return f"{head.rstrip(' .,;:')} ... (see {where})"


def _without_long_asides(text: str, longest: int = 60) -> str:
    """``text`` with each parenthesised aside longer than ``longest`` characters (a list of records' values) said as
    "(...)": what comes after it (the conclusion) stays."""
    out, depth, start = [], 0, 0
    for i, ch in enumerate(text):
        if ch == "(":
            if depth == 0:
                out.append(text[start:i])
                start = i
            depth += 1
        elif ch == ")" and depth:
            depth -= 1
            if depth == 0:
                aside = text[start : i + 1]
                out.append(aside if len(aside) <= longest else "(...)")
                start = i + 1
    out.append(text[start:])
    return "".join(out)


@dataclass
class _Line:
    text: str
    indent: int = 0


@dataclass
class Summary:
    """A command's summary for the terminal: lines of text (each wrapped to the width, its continuation indented
    under its text) and tables, then its closing lines (where the detail is), printed by :meth:`print` within
    :data:`MAX_LINES` lines of at most :data:`WIDTH` characters. ``where``: the file that holds what is left out.

    ``str(summary)`` is its text lines unwrapped, one per line (tables left out): what a test or a script reads."""

    where: str
    parts: list[_Line | Any] = field(default_factory=list)
    closing: list[_Line] = field(default_factory=list)

    def line(self, text: str, indent: int = 0) -> None:
        """Add a line of text (``indent`` spaces before it and its wrapped continuation)."""
        self.parts.append(_Line(text, indent))

    def lines(self, texts: Iterable[str], indent: int = 0) -> None:
        """Add lines of text, each as :meth:`line`."""
        for text in texts:
            self.line(text, indent)

    def items(self, texts: Sequence[str], indent: int = 0, where: str | None = None) -> None:
        """Add a list, one item a line, cut by :func:`cut` (``where``: the file that holds them all, default the
        summary's)."""
        self.lines(cut(texts, where or self.where), indent)

    def table(self, renderable: Any) -> None:
        """Add a rich table (or any renderable), counted by the lines it takes."""
        self.parts.append(renderable)

    def close(self, text: str, indent: int = 0) -> None:
        """Add a closing line: printed last, never left out (where the full detail is)."""
        self.closing.append(_Line(text, indent))

    def extend(self, other: Summary) -> None:
        """Add another summary's parts and closing lines after this one's."""
        self.parts += other.parts
        self.closing += other.closing

    def __str__(self) -> str:
        return "\n".join(" " * p.indent + p.text for p in (*self.parts, *self.closing) if isinstance(p, _Line))

    def rendered(self, console: Console) -> list[Text]:
        """The summary's lines as ``console`` prints them: at most :data:`MAX_LINES`, each at most
        ``min(console.width, WIDTH)`` characters.

        Parameters
        ----------
        console : rich.console.Console
            The console it is printed on (its width, its colours).

        Returns
        -------
        list of rich.text.Text
            One per terminal line.
        """
        width = min(console.width, WIDTH)

        def wrap(p: _Line) -> list[Text]:
            pad = " " * p.indent
            text = p.text.replace(" %", NBSP + "%")  # a number stays with its unit
            rows = textwrap.wrap(text, width, initial_indent=pad, subsequent_indent=pad + " " * INDENT,
                                 break_on_hyphens=False)  # fmt: skip
            return [Text(r.replace(NBSP, " ")) for r in rows] or [Text("")]

        blocks: list[list[Text]] = []
        for p in self.parts:
            if isinstance(p, _Line):
                blocks.append(wrap(p))
            else:
                with console.capture() as cap:
                    console.print(p, width=width)
                blocks.append(list(Text.from_ansi(cap.get().rstrip("\n")).split("\n")))
        tail = [t for p in self.closing for t in wrap(p)]
        room, left = MAX_LINES - len(tail), 0
        while blocks and sum(map(len, blocks)) + (left > 0) > room:  # the last parts out, whole
            left += len(blocks.pop())
        body = [t for b in blocks for t in b]
        if left:
            body.append(Text(f"and {left} more lines (see {self.where})"))
        return [*body, *tail]

    def print(self, console: Console) -> None:
        """Print the summary on ``console`` (:meth:`rendered`), each line as it is, never wrapped again.

        Parameters
        ----------
        console : rich.console.Console
            Where it goes (the command's stdout).
        """
        for row in self.rendered(console):
            console.print(row, soft_wrap=True, highlight=False)
