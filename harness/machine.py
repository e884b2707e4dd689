"""What this machine offers the harness: its memory (for the campaign's memory check) and how many worker
processes a parallel command starts on it by default (``FLEXJOINT_WORKERS``, else min(2, cpu count)). Kept apart
from :mod:`harness.executor` so that a spec can be checked without loading Dask."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["WORKERS_ENV", "default_workers", "env_workers", "machine_memory"]

WORKERS_ENV = "FLEXJOINT_WORKERS"


def env_workers() -> int | None:
    """``FLEXJOINT_WORKERS`` as a positive integer, None when unset or blank."""
    text = os.environ.get(WORKERS_ENV, "").strip()
    if not text:
        return None
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise ValueError(f"{WORKERS_ENV} must be a positive integer, got {os.environ[WORKERS_ENV]!r}")
    return n


def default_workers() -> int:
    """Worker processes an :class:`Executor` given no ``workers`` starts on this machine (outside a session, without
    a scheduler): ``FLEXJOINT_WORKERS`` when set, else min(2, cpu count); 1 runs serially, in the calling process."""
    env = env_workers()
    return env if env is not None else min(2, os.cpu_count() or 1)


def machine_memory() -> int | None:
    """Physical memory of this machine in bytes (``os.sysconf``), lowered to a cgroup memory limit when one is
    set; ``None`` when the platform does not say."""
    try:
        total = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None
    for limit_file in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            text = Path(limit_file).read_text().strip()
        except OSError:
            continue
        if text.isdigit() and 0 < int(text) < total:
            total = int(text)
    return total if total > 0 else None
