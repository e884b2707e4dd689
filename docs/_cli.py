"""The command reference, generated from the command line on every build: each command's ``--help`` as
``flexjoint COMMAND --help`` prints it (docs/reference/cli.md includes what this writes)."""

from __future__ import annotations

from pathlib import Path

import typer.main

from harness.cli import app

WIDTH = 110  # characters a line of help is wrapped to


def write_cli_page(path: Path) -> None:
    """Write the MyST fragment: ``flexjoint --help``, then one section per command with its help."""
    group = typer.main.get_command(app)
    ctx = group.make_context("flexjoint", [], resilient_parsing=True, terminal_width=WIDTH, max_content_width=WIDTH)
    parts = ["```text\n" + group.get_help(ctx) + "\n```\n"]
    for name in group.list_commands(ctx):
        cmd = group.get_command(ctx, name)
        sub = cmd.make_context(name, [], parent=ctx, resilient_parsing=True)
        parts.append(f"## flexjoint {name}\n\n```text\n{cmd.get_help(sub)}\n```\n")
    text = "\n".join(parts)
    if not path.exists() or path.read_text(encoding="utf-8") != text:
        path.write_text(text, encoding="utf-8")
