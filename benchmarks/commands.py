"""Whole commands as a user starts them, timed from outside, side by side with another commit (``flexjoint bench
--vs-commit REV``).

Each command is ``python -m harness ARGS`` in a fresh process whose package is a source tree's own: this clone's, and
with ``vs_commit`` a git worktree of that commit made for the bench (and removed after it), so that both run on the
same machine in the same minutes. The pairs are interleaved (this then the other, the other then this on the next
round) and the ratio is taken pair by pair, so a machine whose speed drifts (other jobs on a shared machine) moves
both sides of a pair alike. Every tree is prepared before the clock: its FMUs built (they are cached by a hash of
their sources), its byte-code compiled (a user's second run finds it), the lab campaign simulated for ``identify``
and the CU records imported for the unit's ``diagnose``.

Per command and tree: wall time [s] (min, median, max over the rounds), the CPU seconds of the process and every
process it waited for (the cluster's included), and for ``flexjoint run`` each stage's wall time
from its ``run.timing.json`` and the time outside the stages (interpreter, imports, cluster start and close).
"""

from __future__ import annotations

import contextlib
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from harness import clone

__all__ = ["COMMANDS", "Command", "Tree", "bench_commands", "checkout"]

CLEARED_ENV = ("FLEXJOINT_WORKERS", "FLEXJOINT_SCHEDULER", "PYTHONDONTWRITEBYTECODE", "PYTHONPATH")
CU_IMPORT = ["--columns", "0=t,1=theta,2=-alpha,5=ref,6=u", "--units", "t=ms,theta=rad,alpha=m,ref=rad",
             "--link-length", "0.45", "--zero-alpha"]  # fmt: skip


@dataclass(frozen=True)
class Tree:
    """A source tree whose package the commands run (``label``: ``this`` or ``vs``), at ``commit``."""

    label: str
    root: Path
    commit: str

    def env(self) -> dict[str, str]:
        """The environment of its commands: the tree's root first on the path; no worker count, scheduler or
        byte-code setting inherited from the caller's shell."""
        env = {k: v for k, v in os.environ.items() if k not in CLEARED_ENV}
        env["PYTHONPATH"] = str(self.root)
        return env

    def python(self, args: list[str], check: bool = True) -> subprocess.CompletedProcess:
        """``python ARGS`` in the tree's root with its environment, output captured."""
        proc = subprocess.run(
            [sys.executable, *args], cwd=self.root, env=self.env(), capture_output=True, text=True, check=False
        )
        if check and proc.returncode != 0:
            last = (proc.stderr.strip().splitlines() or ["no output"])[-1]
            raise RuntimeError(f"{self.label} tree ({self.commit[:9]}): python {' '.join(args)} failed: {last}")
        return proc


def _commit(root: Path, rev: str = "HEAD") -> str:
    out = subprocess.run(["git", "-C", str(root), "rev-parse", "--verify", f"{rev}^{{commit}}"], capture_output=True,
                         text=True, check=False)  # fmt: skip
    if out.returncode != 0:
        raise ValueError(f"--vs-commit {rev}: not a commit of {root} ({out.stderr.strip() or 'git failed'})")
    return out.stdout.strip()


def this_tree(root: Path) -> Tree:
    """The clone the bench runs from; its commit is HEAD, with ``+changes`` when its files differ from it."""
    try:
        commit = _commit(root)
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, check=False).stdout.strip()  # fmt: skip
    except (OSError, ValueError):
        return Tree("this", root, "unknown")
    return Tree("this", root, commit + ("+changes" if dirty else ""))


@contextlib.contextmanager
def checkout(root: Path, rev: str) -> Iterator[Tree]:
    """A detached git worktree of commit ``rev`` of the clone ``root`` in a scratch directory, removed (and
    pruned from the clone's worktree list) when the ``with`` ends."""
    if not (root / ".git").exists():
        raise ValueError(f"--vs-commit needs a git clone of the repository; {root} is not one")
    commit = _commit(root, rev)
    scratch = Path(tempfile.mkdtemp(prefix="flexjoint-vs-"))
    path = scratch / commit[:12]
    try:
        subprocess.run(["git", "-C", str(root), "worktree", "add", "--detach", str(path), commit], capture_output=True,
                       check=True)  # fmt: skip
        yield Tree("vs", path, commit)
    finally:
        subprocess.run(["git", "-C", str(root), "worktree", "remove", "--force", str(path)], capture_output=True,
                       check=False)  # fmt: skip
        subprocess.run(["git", "-C", str(root), "worktree", "prune"], capture_output=True, check=False)
        shutil.rmtree(scratch, ignore_errors=True)


@dataclass(frozen=True)
class Command:
    """One command of the bench: its name, its arguments after ``python -m harness`` given the run's scratch
    directory ``out`` and the tree's prepared inputs ``inputs`` (``campaign``, ``unit``), and what is put in ``out``
    before the clock (``seed``: the input copied there, for a command that writes into its run)."""

    name: str
    args: Callable[[Path, dict[str, Path]], list[str]]
    seed: str | None = None


COMMANDS = (
    Command("run_serial", lambda out, _: ["run", "--spec", "lab", "--out", str(out), "--workers", "1"]),
    Command("run_2_workers", lambda out, _: ["run", "--spec", "lab", "--out", str(out), "--workers", "2"]),
    Command("identify_serial", lambda out, _: ["identify", str(out), "--workers", "1"], seed="campaign"),
    Command("identify_2_workers", lambda out, _: ["identify", str(out), "--workers", "2"], seed="campaign"),
    Command("diagnose_unit_2_workers", lambda out, i: ["diagnose", "--real", str(i["unit"]), "--sim",
                                                       "cu_flexible_arm", "--out", str(out), "--workers", "2"]),
    Command("version", lambda out, _: ["--version"]),
    Command("help", lambda out, _: ["--help"]),
)  # fmt: skip


def prepare(tree: Tree, work: Path) -> dict[str, Path]:
    """Before any clock: the tree's FMUs built and its modules compiled, the lab campaign (the input of
    ``identify``) and the CU unit (three records at 1 kHz: test_3 cut in two, and test_4) in ``work``."""
    work.mkdir(parents=True, exist_ok=True)
    tree.python(["-c", "from harness.fmu.build import build_all, build_master; build_all(); build_master()"])
    tree.python(["-m", "compileall", "-q", "harness"])
    campaign = work / "campaign"
    tree.python(["-m", "harness", "campaign", "lab", "--out", str(campaign), "--workers", "1"])
    fixtures = tree.root / "tests" / "fixtures" / "real"
    lines = (fixtures / "flexibleArm_test_3.txt").read_text().splitlines(keepends=True)
    half = (len(lines) + 1) // 2
    files = [work / "test_3a.txt", work / "test_3b.txt", fixtures / "flexibleArm_test_4.txt"]
    files[0].write_text("".join(lines[:half]))
    files[1].write_text("".join(lines[:1] + lines[half:]))
    unit = work / "unit"
    tree.python(["-m", "harness", "import", *map(str, files), "--out", str(unit), *CU_IMPORT])
    return {"campaign": campaign, "unit": unit}


def _children_cpu_s() -> float:
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def measure(tree: Tree, cmd: Command, inputs: dict[str, Path], out: Path) -> dict[str, Any]:
    """One timed run of ``cmd`` on ``tree`` into the fresh directory ``out``: wall [s], CPU [s] of every process it
    waited for, and a ``flexjoint run``'s stages [s] from its run.timing.json."""
    if cmd.seed is not None:
        shutil.copytree(inputs[cmd.seed], out)
    args = ["-m", "harness", *cmd.args(out, inputs)]
    cpu0 = _children_cpu_s()
    t0 = time.perf_counter()
    proc = tree.python(args, check=False)
    wall = time.perf_counter() - t0
    cpu1 = _children_cpu_s()
    if proc.returncode != 0:
        last = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        raise RuntimeError(f"{tree.label} tree ({tree.commit[:9]}): flexjoint {' '.join(args[2:])} failed: {last}")
    row: dict[str, Any] = {"wall_s": wall, "cpu_s": cpu1 - cpu0}
    timing = out / "run.timing.json"
    if timing.is_file():
        doc = json.loads(timing.read_text())
        row["stages_s"] = doc["stages_s"]
        row["outside_stages_s"] = wall - doc["total_s"]
    return row


def _spread(xs: list[float]) -> dict[str, float]:
    return {"median": statistics.median(xs), "min": min(xs), "max": max(xs)}


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """A tree's runs of one command: wall and CPU as min, median, max; the stages' and the outside's medians; every
    run as measured (:func:`measure`), in order."""
    out: dict[str, Any] = {
        "wall_s": _spread([r["wall_s"] for r in rows]),
        "cpu_s": _spread([r["cpu_s"] for r in rows]),
        "runs": rows,
    }
    if rows and "stages_s" in rows[0]:
        stages = [s for s in rows[0]["stages_s"] if all(s in r["stages_s"] for r in rows)]
        out["stages_s"] = {s: statistics.median(r["stages_s"][s] for r in rows) for s in stages}
        out["outside_stages_s"] = statistics.median(r["outside_stages_s"] for r in rows)
    return out


def bench_commands(
    vs_commit: str | None = None,
    rounds: int = 3,
    root: Path | None = None,
    names: tuple[str, ...] | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Every command of :data:`COMMANDS` (or those ``names``) ``rounds`` times on this clone and, with
    ``vs_commit``, on that commit, the pairs interleaved; per command each tree's summary (:func:`summarise`) and
    ``ratio_this_over_vs``: the median of the pairs' wall-time ratios (< 1: this tree is faster), with each pair's
    ratio. ``speedup_2_workers``: each tree's serial median over its 2-worker median, for ``run`` and ``identify``."""
    if isinstance(rounds, bool) or not isinstance(rounds, int) or rounds < 1:
        raise ValueError(f"rounds must be an integer >= 1, got {rounds!r}")
    cmds = [c for c in COMMANDS if names is None or c.name in names]
    if names is not None and len(cmds) != len(set(names)):
        unknown = sorted(set(names) - {c.name for c in COMMANDS})
        raise ValueError(f"unknown command(s) {', '.join(unknown)}; known: {', '.join(c.name for c in COMMANDS)}")
    say = progress or (lambda _m: None)
    root = Path(root or clone.ROOT)
    with contextlib.ExitStack() as stack:
        trees = [this_tree(root)]
        if vs_commit is not None:
            trees.append(stack.enter_context(checkout(root, vs_commit)))
        scratch = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="flexjoint-bench-")))
        inputs = {}
        for tree in trees:
            say(f"preparing {tree.label!r}: {tree.commit[:9]}")
            inputs[tree.label] = prepare(tree, scratch / tree.label / "inputs")
        load = [os.getloadavg()[0]]
        rows: dict[str, dict[str, list[dict[str, Any]]]] = {c.name: {t.label: [] for t in trees} for c in cmds}
        for r in range(rounds):
            for cmd in cmds:
                for tree in trees if r % 2 == 0 else trees[::-1]:
                    out = scratch / tree.label / f"{cmd.name}-{r}"
                    row = measure(tree, cmd, inputs[tree.label], out)
                    shutil.rmtree(out, ignore_errors=True)
                    rows[cmd.name][tree.label].append(row)
                    say(f"{cmd.name} on {tree.label} [{r + 1}/{rounds}]: {row['wall_s']:.1f} s")
            load.append(os.getloadavg()[0])
    result: dict[str, Any] = {
        "rounds": rounds,
        "trees": {t.label: {"commit": t.commit, "root": str(t.root)} for t in trees},
        "load_average_1min": {"before": load[0], "after_each_round": load[1:]},
    }
    for cmd in cmds:
        entry: dict[str, Any] = {"args": cmd.args(Path("OUT"), {"campaign": Path("CAMPAIGN"), "unit": Path("UNIT")})}
        for tree in trees:
            entry[tree.label] = summarise(rows[cmd.name][tree.label])
        if vs_commit is not None:
            ratios = [a["wall_s"] / b["wall_s"] for a, b in zip(rows[cmd.name]["this"], rows[cmd.name]["vs"],
                                                                 strict=True)]  # fmt: skip
            entry["ratio_this_over_vs"] = statistics.median(ratios)
            entry["ratios"] = ratios
            if "stages_s" in entry["this"] and "stages_s" in entry["vs"]:
                entry["stage_ratio_this_over_vs"] = {
                    s: entry["this"]["stages_s"][s] / entry["vs"]["stages_s"][s]
                    for s in entry["this"]["stages_s"]
                    if entry["vs"]["stages_s"].get(s)
                }
        result[cmd.name] = entry
    result["speedup_2_workers"] = {
        kind: {
            t.label: result[f"{kind}_serial"][t.label]["wall_s"]["median"]
            / result[f"{kind}_2_workers"][t.label]["wall_s"]["median"]
            for t in trees
        }
        for kind in ("run", "identify")
        if f"{kind}_serial" in result and f"{kind}_2_workers" in result
    }
    result["target"] = ("flexjoint run <= 0.5x c9334bf's wall time; identify on 2 workers >= 1.6x serial; the 3-record "
                        "unit's diagnosis <= 0.5x c9334bf's; --version well under 1 s")  # fmt: skip
    return result
