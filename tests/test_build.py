"""FMU build: validation, cache behaviour, errors, self-contained sources, a second importer."""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from fmpy.validation import validate_fmu

from harness.fmu import build, modeldesc, sources
from harness.fmu.build import BuildError, build_fmu, fmu_sha256, source_hash


def test_fmus_validate_with_zero_problems(fmus):
    assert set(fmus) == {"flexjoint", "daq", "controller"}
    for path in (*fmus.values(), build_fmu("armax"), build_fmu("signal")):
        assert validate_fmu(str(path)) == [], path.name


def test_built_fmu_carries_the_source_xml_and_hash_in_name(fmus):
    for name, path in fmus.items():
        built, source = modeldesc.read(path), modeldesc.source_model(name)
        assert built.variables == source.variables and built.guid == source.guid
        assert built.variables["u"].value_reference == (40 if name == "controller" else 30)  # its output, their input
        # the controller's 18 and its LQG's 191 matrix entries (A 10x10, B, C, K, L, N, X), each a parameter
        assert len(built.parameters()) == {"flexjoint": 30, "daq": 22, "controller": 18 + 191}[name]
        assert path.name == f"{name}-{source_hash(name)[:12]}.fmu"
        assert fmu_sha256(path) == hashlib.sha256(path.read_bytes()).hexdigest()


def test_fmu_contains_sources_and_rebuilds_from_them(fmus, tmp_path):
    """Another tool can rebuild the binary from the FMU's own sources (fmpy, FMI 2 SourceFiles)."""
    from fmpy import read_model_description
    from fmpy.build import build_platform_binary

    with zipfile.ZipFile(fmus["daq"]) as zf:
        names = zf.namelist()
        zf.extractall(tmp_path / "daq")
    for f in ("sources/model.c", "sources/fmi2common.c", "sources/fmi2Functions.h", "modelDescription.xml"):
        assert f in names
    md = read_model_description(str(fmus["daq"]))
    assert sorted(md.buildConfigurations[0].sourceFileSets[0].sourceFiles) == ["fmi2common.c", "model.c"]
    shutil.rmtree(tmp_path / "daq" / "binaries")
    opts = {} if sys.platform == "win32" else {"CMAKE_C_STANDARD_LIBRARIES:STRING": "-lm"}
    (tmp_path / "b").mkdir()
    r = subprocess.run(
        [sys.executable, "-c", f"import fmpy.build as b; b.build_platform_binary({str(tmp_path / 'daq')!r}, "
         f"build_dir={str(tmp_path / 'b')!r}, cmake_options={opts!r})"],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    assert any((tmp_path / "daq" / "binaries").rglob("daq.*"))
    assert build_platform_binary  # imported: the same tool the harness uses


@pytest.fixture
def src_copy(tmp_path, monkeypatch):
    """A private copy of fmus/ and an empty cache."""
    src = tmp_path / "fmus"
    shutil.copytree(sources.fmu_source_dir(), src, ignore=shutil.ignore_patterns("build", "*.fmu"))
    monkeypatch.setenv("FLEXJOINT_FMU_SRC", str(src))
    monkeypatch.setenv("FLEXJOINT_CACHE", str(tmp_path / "cache"))
    return src


def test_cache_reuses_and_rebuilds_on_change(src_copy):
    p1 = build_fmu("daq")
    assert p1.parent == Path(os.environ["FLEXJOINT_CACHE"])
    m1 = p1.stat().st_mtime_ns
    assert build_fmu("daq") == p1 and p1.stat().st_mtime_ns == m1  # not rebuilt
    with open(src_copy / "daq" / "model.c", "a") as f:
        f.write("\n/* changed */\n")
    p2 = build_fmu("daq")
    assert p2 != p1 and p2.is_file() and p1.stat().st_mtime_ns == m1
    assert validate_fmu(str(p2)) == []
    assert build_fmu("daq", force=True) == p2


def test_concurrent_builds_do_not_corrupt_the_cache(src_copy):
    code = "from harness.fmu.build import build_fmu; print(build_fmu('flexjoint'))"
    procs = [
        subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for _ in range(2)
    ]
    outs = [p.communicate(timeout=120) for p in procs]
    assert all(p.returncode == 0 for p in procs), outs
    paths = {o[0].strip() for o in outs}
    assert len(paths) == 1
    path = paths.pop()
    assert validate_fmu(path) == []
    with zipfile.ZipFile(path) as zf:
        assert zf.testzip() is None
    leftovers = [p for p in Path(os.environ["FLEXJOINT_CACHE"]).iterdir() if not p.name.startswith(".flexjoint")]
    name = Path(path).name
    assert sorted(p.name for p in leftovers) == [name, f"{name}.sha256"]  # the FMU, its hash, no temp files
    assert build.cached_fmu_ok(Path(path))


def test_compile_error_is_one_clear_line(src_copy):
    model = src_copy / "daq" / "model.c"
    model.write_text(model.read_text() + "\nint broken( {\n")
    with pytest.raises(BuildError) as e:
        build_fmu("daq")
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith("building daq failed: model.c:") and "error" in msg


def test_unknown_model_and_guid_mismatch(src_copy):
    with pytest.raises(ValueError, match="unknown FMU 'nope'.*daq, flexjoint"):
        build_fmu("nope")
    cfg = src_copy / "daq" / "config.h"
    cfg.write_text(cfg.read_text().replace("a3d5e7f9", "00000000"))
    with pytest.raises(BuildError, match="guid"):
        build_fmu("daq")


def test_libcosim_runs_the_same_fmu_as_fmpy(fmus, fmu_runner):
    """A second FMI importer (libcosim via libcosimpy) gives the same step response as fmpy."""
    try:
        from libcosimpy.CosimEnums import CosimVariableType
        from libcosimpy.CosimExecution import CosimExecution
        from libcosimpy.CosimLogging import CosimLogLevel, log_output_level
        from libcosimpy.CosimObserver import CosimObserver
        from libcosimpy.CosimSlave import CosimLocalSlave
    except (ImportError, OSError) as e:  # pragma: no cover - platform without libcosim
        pytest.skip(f"libcosimpy cannot load on this platform: {e}")
    log_output_level(CosimLogLevel.ERROR)
    vr = {n: v.value_reference for n, v in modeldesc.read(fmus["flexjoint"]).variables.items()}
    n, step_ns = 100, 20_000_000
    ex = CosimExecution.from_step_size(step_ns)
    idx = ex.add_local_slave(CosimLocalSlave(fmu_path=str(fmus["flexjoint"]), instance_name="plant"))
    ex.integer_initial_value(idx, vr["n_modes"], 2)
    ex.real_initial_value(idx, vr["u"], 2.0)
    obs = CosimObserver.create_time_series()
    ex.add_observer(obs)
    for name in ("theta", "alpha"):
        obs.start_time_series(idx, vr[name], CosimVariableType.REAL)
    assert ex.simulate_until(n * step_ns)
    ref = fmu_runner["flexjoint"].run({"n_modes": 2}, {"u": 2.0}, ["theta", "alpha"], 0.02, n)
    for name in ("theta", "alpha"):
        # from step 1: libcosimpy trims at step number 0, so ask for the n samples after the start
        t, steps, values = obs.time_series_real_samples(idx, vr[name], from_step=1, sample_count=n)
        assert len(values) == n and t[0] == step_ns and steps[-1] == n
        np.testing.assert_allclose(values, ref[name], rtol=1e-12, atol=1e-14)
    assert abs(ref["theta"][-1]) > 1.0


def test_packaged_fmu_tree_lists_every_model_directory():
    """Each directory under fmus/ ships in the wheel: pyproject lists it as a package with the files the build
    stages (C sources and headers, modelDescription.xml; a model's readme.md is documentation and need not ship)."""
    import tomllib

    cfg = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert cfg["package-dir"] == {"harness._fmus": "fmus", "harness._specs": "specs"}
    dirs = sorted(p.name for p in sources.bundled_dir("fmus").iterdir() if p.is_dir() and p.name != "__pycache__")
    shipped = sorted(n.removeprefix("harness._fmus.") for n in cfg["packages"] if n.startswith("harness._fmus."))
    assert shipped == dirs
    for d in dirs:
        patterns = cfg["package-data"][f"harness._fmus.{d}"]
        files = [p for p in (sources.bundled_dir("fmus") / d).iterdir() if p.is_file()]
        exts = {p.suffix for p in files if p.suffix in (".c", ".h") or p.name == "modelDescription.xml"}
        assert ".c" in exts
        assert exts <= {Path(x).suffix for x in patterns}, (d, exts, patterns)
    assert cfg["package-data"]["harness._specs"] == ["*.toml"]


def test_source_tree_is_the_bundled_one_unless_overridden(monkeypatch, tmp_path):
    monkeypatch.delenv("FLEXJOINT_FMU_SRC", raising=False)
    assert sources.fmu_source_dir() == sources.bundled_dir("fmus")
    assert sources.available_models() == ["armax", "controller", "daq", "flexjoint", "signal"]
    monkeypatch.setenv("FLEXJOINT_FMU_SRC", str(tmp_path))
    assert sources.fmu_source_dir() == tmp_path and sources.available_models() == []
    with pytest.raises(ValueError, match=r"unknown FMU 'daq': expected one of \(none\)"):
        build_fmu("daq")
    monkeypatch.setenv("FLEXJOINT_FMU_SRC", str(tmp_path / "nowhere"))
    with pytest.raises(BuildError, match=r"nowhere \(\$FLEXJOINT_FMU_SRC\) does not exist"):
        build_fmu("daq")


def _fill_cache(fmus, cache: Path, names=("flexjoint", "daq")) -> dict[str, Path]:
    """Copy the session's built FMUs and their recorded hashes into an empty cache."""
    cache.mkdir(parents=True, exist_ok=True)
    out = {}
    for name in names:
        src = fmus[name]
        shutil.copy2(src, cache / src.name)
        shutil.copy2(src.with_name(src.name + ".sha256"), cache / (src.name + ".sha256"))
        out[name] = cache / src.name
    return out


@pytest.mark.parametrize("damage", ["truncate", "garble", "no_hash"])
def test_damaged_cached_fmu_is_rebuilt(fmus, tmp_path, monkeypatch, damage):
    """An interrupted build or a full disk leaves a bad zip: it is detected by its recorded hash and rebuilt."""
    monkeypatch.setenv("FLEXJOINT_CACHE", str(tmp_path / "cache"))
    path = _fill_cache(fmus, tmp_path / "cache", ["daq"])["daq"]
    good = fmu_sha256(path)
    assert build.cached_fmu_ok(path) and build_fmu("daq") == path and fmu_sha256(path) == good  # reused as is
    if damage == "truncate":
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    elif damage == "garble":
        data = bytearray(path.read_bytes())
        data[len(data) // 2] ^= 0xFF
        path.write_bytes(bytes(data))
    else:
        path.with_name(path.name + ".sha256").unlink()
    assert not build.cached_fmu_ok(path)
    assert build_fmu("daq") == path
    assert build.cached_fmu_ok(path)
    with zipfile.ZipFile(path) as zf:
        assert zf.testzip() is None
    assert validate_fmu(str(path)) == []
