"""The built wheel works on its own: fresh virtual environment, outside the clone, FMUs compiled from its sources.

Builds the wheel (``python -m build --wheel``) from a copy of the project's files, installs it into a new
virtual environment and, from a temporary directory outside the clone, runs ``flexjoint build`` into an empty
``FLEXJOINT_CACHE``, ``flexjoint campaign lab``, a short campaign with two effects switched on and ``flexjoint
diagnose`` against the compact ``blind`` spec. Dependencies are not downloaded: the new environment sees the
running interpreter's site-packages through a ``.pth`` file written *after* the wheel is installed. Those
directories are added as plain paths, so their own ``.pth`` files (the editable install's finder among them) are
not executed and cannot shadow the wheel; the test checks that ``harness`` is imported from the new environment.
"""

from __future__ import annotations

import json
import os
import shutil
import site
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PROJECT_FILES = ("pyproject.toml", "README.md", "harness", "fmus", "specs")


def _run(cmd: list[str], cwd: Path, env: dict[str, str] | None = None, timeout: float = 300) -> str:
    t0 = time.perf_counter()
    r = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout, check=False)
    print(f"{time.perf_counter() - t0:6.1f} s  {' '.join(Path(c).name if '/' in c else c for c in map(str, cmd))}")
    assert r.returncode == 0, f"{' '.join(map(str, cmd))} -> {r.returncode}\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    return r.stdout


def _build_wheel(tmp: Path) -> Path:
    """``python -m build --wheel`` on a copy of the project (never writes build/ into the clone)."""
    src = tmp / "src"
    src.mkdir()
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.fmu", "build", "*.egg-info")
    for name in PROJECT_FILES:
        p = ROOT / name
        if p.is_dir():
            shutil.copytree(p, src / name, ignore=ignore)
        else:
            shutil.copy2(p, src / name)
    dist = tmp / "dist"
    cmd = [sys.executable, "-m", "build", "--wheel", "--outdir", str(dist), str(src)]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300, check=False)
    if r.returncode != 0:  # no index reachable for the isolated build env: build with this environment's setuptools
        r = subprocess.run([*cmd, "--no-isolation", "--skip-dependency-check"], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    (wheel,) = dist.glob("flexjoint_harness-*.whl")
    return wheel


def _fresh_venv(tmp: Path, wheel: Path) -> Path:
    """A new venv with only the wheel installed, then the running interpreter's site-packages as plain paths."""
    venv = tmp / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", str(venv)], cwd=tmp)
    py = venv / "bin" / "python"
    _run([sys.executable, "-m", "pip", "--python", str(py), "install", "--no-deps", "--no-index", str(wheel)], cwd=tmp)
    purelib = _run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], cwd=tmp).strip()
    (Path(purelib) / "zz_test_dependencies.pth").write_text("".join(f"{d}\n" for d in _dependency_dirs()))
    return venv


def _dependency_dirs() -> list[str]:
    """Where this interpreter finds the dependencies (its site dirs and whatever .pth files added), minus the
    clone (but not a virtual environment's site-packages inside it, as CI may make) and any directory that holds
    a ``harness`` package of its own."""
    user = site.getusersitepackages()
    out: list[str] = []
    for d in [*site.getsitepackages(), *([user] if os.path.isdir(user) else []), *sys.path]:
        p = Path(d or ".").resolve()
        in_clone = p == ROOT or (ROOT in p.parents and "site-packages" not in p.parts)  # a venv in the clone is fine
        if not p.is_dir() or in_clone or (p / "harness").exists() or str(p) in out:
            continue
        out.append(str(p))
    return out


def test_wheel_in_a_fresh_venv_builds_runs_a_campaign_and_diagnoses(tmp_path):
    t0 = time.perf_counter()
    wheel = _build_wheel(tmp_path)
    print(f"{time.perf_counter() - t0:6.1f} s  python -m build --wheel")
    venv = _fresh_venv(tmp_path, wheel)
    work = tmp_path / "elsewhere"  # a directory outside the clone: nothing there to import or read
    work.mkdir()
    outer_bin = str(Path(sys.prefix) / "bin")
    path = [str(venv / "bin"), *(p for p in os.environ.get("PATH", "").split(os.pathsep) if p and p != outer_bin)]
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "FLEXJOINT_FMU_SRC", "VIRTUAL_ENV")}
    env.update(PATH=os.pathsep.join(path), FLEXJOINT_CACHE=str(tmp_path / "cache"), PYTHONNOUSERSITE="1")
    py, fj = str(venv / "bin" / "python"), str(venv / "bin" / "flexjoint")

    where = json.loads(
        _run(
            [py, "-c", "import json, harness, harness.fmu.sources as b, harness.spec as s; print(json.dumps("
             "[harness.__file__, str(b.fmu_source_dir()), str(s.SPEC_DIR)]))"],
            cwd=work, env=env,
        )
    )  # fmt: skip
    site_dir = (venv / "lib").resolve()
    for p in where:  # the package, its FMU sources and its specs all come from the wheel, none from the clone
        assert site_dir in Path(p).resolve().parents, (p, where)

    built = _run([fj, "build"], cwd=work, env=env)
    cache = sorted(p.name for p in (tmp_path / "cache").glob("*.fmu"))
    assert [n.split("-")[0] for n in cache] == ["armax", "controller", "daq", "flexjoint"], built
    assert all((tmp_path / "cache" / f"{n}.sha256").is_file() for n in cache)
    assert len(list((tmp_path / "cache").glob("master-*"))) == 1, built  # the co-simulation's step loops

    # campaigns serially (no cluster start-up to pay twice); the diagnosis below runs on Dask's local workers,
    # processes that must import harness from the wheel too
    _run([fj, "campaign", "lab", "--out", "lab", "--workers", "1"], cwd=work, env=env)
    assert len(list((work / "lab" / "data").glob("*.parquet"))) == 14

    _run([fj, "init", "specs", "--spec", "blind"], cwd=work, env=env)
    _run(
        [fj, "campaign", "specs/blind.toml", "--out", "rig", "--workers", "1",
         "--set", "plant.coulomb_torque=0.03", "--set", "daq.delay_samples=1"],
        cwd=work, env=env,
    )  # fmt: skip
    _run([fj, "diagnose", "--real", "rig", "--sim", "blind"], cwd=work, env=env)
    d = json.loads((work / "rig" / "diagnosis.json").read_text())
    assert d["verdict"] not in ("none",) and d["gap"]["shrink_pct"] > 50, d["verdict"]
    print(f"wheel test: {time.perf_counter() - t0:.1f} s")
