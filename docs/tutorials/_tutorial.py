"""What each tutorial's hidden first cell calls when the manual is built: the page runs in a fresh directory of its
own, where the clone's real records are at ``tests/fixtures/real/`` as they are at a clone's root, so that every
command on the page is the one a reader types at the root of a clone."""

from __future__ import annotations

import atexit
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

from IPython import get_ipython
from IPython.display import Image, display

ROOT = Path(__file__).resolve().parents[2]


def workdir() -> Path:
    """A new empty directory (removed when the page's kernel ends) made the current one, with the clone's
    ``tests/fixtures/real`` linked in; returns it."""
    d = Path(tempfile.mkdtemp(prefix="flexjoint-docs-"))
    atexit.register(shutil.rmtree, d, ignore_errors=True)
    (d / "tests" / "fixtures").mkdir(parents=True)
    (d / "tests" / "fixtures" / "real").symlink_to(ROOT / "tests" / "fixtures" / "real", target_is_directory=True)
    os.chdir(d)
    get_ipython().register_magic_function(bash, "cell", "bash")
    return d


def bash(line: str, cell: str) -> None:
    """The pages' ``%%bash`` cells: the cell run by ``bash -e`` (a failing command fails the build), its output
    and errors printed as they come, as a pipe shows them (the kernel's FORCE_COLOR would make the commands draw
    a terminal's live status line). IPython's own ``%%bash`` has hung a build after its command ended."""
    plain = {k: v for k, v in os.environ.items() if k not in ("FORCE_COLOR", "CLICOLOR", "CLICOLOR_FORCE")}
    p = subprocess.Popen(
        ["bash", "-e", "-c", cell], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=plain
    )
    assert p.stdout is not None
    for text in p.stdout:
        print(text, end="", flush=True)
    if p.wait():
        raise subprocess.CalledProcessError(p.returncode, cell)


def show(*paths: str | Path, width: int = 900) -> None:
    """Display figures a command wrote (PNG), each in the page."""
    for p in paths:
        display(Image(filename=str(p), width=width))
