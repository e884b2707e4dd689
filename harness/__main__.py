"""The ``flexjoint`` console script and ``python -m harness``: the command line of :mod:`harness.cli`, with a Ctrl-C
while the command line itself is still loading answered like one during a command: one line, exit code 130."""

from __future__ import annotations

import atexit
import gc
import sys

from .numerics import pin_numerics


def main() -> None:
    """Load the command line and run it; an interrupt while loading it is one line on stderr and exit code 130.
    At exit, once every other exit handler has run (this one, registered first, runs last), what is still alive is
    frozen (:func:`gc.freeze`): the interpreter's final collections skip it instead of traversing every module's
    objects. numpy's and OpenBLAS's kernels are pinned first (:func:`harness.numerics.pin_numerics`): the same bytes
    on any x86-64 CPU with AVX2."""
    pin_numerics()
    atexit.register(gc.freeze)
    try:
        from .cli import main as cli_main
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        raise SystemExit(130) from None
    cli_main()


if __name__ == "__main__":
    main()
