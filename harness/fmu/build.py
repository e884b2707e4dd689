"""Build the rig-twin FMUs (FMI 2.0 co-simulation, C sources) with fmpy's CMake tooling.

``fmus/common`` (the generic FMI 2.0 layer) and ``fmus/<name>`` (config.h, model.c,
modelDescription.xml) are staged into a temporary FMU tree, compiled with
``fmpy.build.build_platform_binary`` and zipped, sources included, into
``<cache>/<name>-<sha256 of the staged sources[:12]>.fmu``.  The cache is ``$FLEXJOINT_CACHE`` or
``~/.cache/flexjoint-harness``; the source tree is ``$FLEXJOINT_FMU_SRC``, else the sources shipped inside the
installed package (``harness/_fmus``, read with :mod:`importlib.resources`), else the clone's ``fmus/``.
An FMU is rebuilt only when its sources change; the zip is written to a temporary file and moved in
place with ``os.replace`` under a per-model file lock, so concurrent builds cannot corrupt the cache.
The sha256 of each zip is recorded beside it at build time (``<fmu>.sha256``); a cached FMU whose bytes no
longer match (an interrupted copy, a full disk, a hand edit) is rebuilt instead of being handed to fmpy.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import subprocess
import sys
import tempfile
import xml.etree.ElementTree as ET
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import ModuleType

import cmake
import fmpy
from fmpy.build import build_platform_binary

from . import modeldesc
from .sources import available_models, fmu_source_dir

fcntl: ModuleType | None
try:
    import fcntl
except ImportError:  # Windows
    fcntl = None

BUILD_TAG = "flexjoint-harness-build-1"  # bump when the staging or compile recipe changes
MODELS = ("flexjoint", "daq", "controller")
FMI_HEADERS = ("fmi2Functions.h", "fmi2FunctionTypes.h", "fmi2TypesPlatform.h")


class BuildError(RuntimeError):
    """An FMU could not be staged, compiled or packed."""


def cache_dir() -> Path:
    """The FMU cache: ``$FLEXJOINT_CACHE`` or ``~/.cache/flexjoint-harness``."""
    env = os.environ.get("FLEXJOINT_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "flexjoint-harness"


def _fmpy_headers() -> dict[str, bytes]:
    cdir = Path(fmpy.__file__).parent / "c-code"
    return {h: (cdir / h).read_bytes() for h in FMI_HEADERS}


def _read_description(name: str, xml: str) -> tuple[modeldesc.ModelDescription, bool]:
    """The model description (:func:`harness.fmu.modeldesc.parse`, the one reader) and whether its CoSimulation
    element already lists SourceFiles; an unreadable XML is a :class:`BuildError`."""
    try:
        root = ET.fromstring(xml)
        md = modeldesc.parse(xml)
    except (ET.ParseError, StopIteration, ValueError) as exc:
        raise BuildError(f"{name}: modelDescription.xml cannot be read: {exc or type(exc).__name__}") from None
    return md, root.find("CoSimulation/SourceFiles") is not None


def _with_source_files(xml: str, sources: list[str], listed: bool = False) -> str:
    """Add the FMI 2.0 ``<SourceFiles>`` list (what fmpy's build reads) to the CoSimulation element (the text is
    edited, so that the rest of the file stays byte for byte); ``listed``: the source already has a list."""
    files = "".join(f'\n      <File name="{s}"/>' for s in sources)
    block = f"\n    <SourceFiles>{files}\n    </SourceFiles>\n  "
    if listed:
        raise BuildError("modelDescription.xml must not list SourceFiles: the build adds them")
    new, n = re.subn(r"(<CoSimulation\b[^>]*?)\s*/>", lambda m: m.group(1) + ">" + block + "</CoSimulation>", xml)
    if n == 0:
        new, n = re.subn(r"</CoSimulation>", block.lstrip("\n") + "</CoSimulation>", xml, count=1)
    if n != 1:
        raise BuildError("modelDescription.xml has no CoSimulation element")
    return new


def _staged_files(name: str) -> dict[str, bytes]:
    """All files of the FMU except the binary, as {path inside the FMU: content}."""
    root = fmu_source_dir()
    if not root.is_dir():
        how = "$FLEXJOINT_FMU_SRC" if os.environ.get("FLEXJOINT_FMU_SRC") else "the package's bundled sources"
        raise BuildError(f"FMU source tree {root} ({how}) does not exist")
    model_dir, common_dir = root / name, root / "common"
    if name == "common" or not (model_dir / "modelDescription.xml").is_file():
        raise ValueError(f"unknown FMU {name!r}: expected one of {', '.join(available_models()) or '(none)'}")
    if not common_dir.is_dir():
        raise BuildError(f"missing shared FMI layer {common_dir}")
    files: dict[str, bytes] = {}
    for d in (common_dir, model_dir):
        for p in sorted(d.iterdir()):
            if p.suffix in (".c", ".h"):
                if f"sources/{p.name}" in files:
                    raise BuildError(f"{p.name} exists in both fmus/common and fmus/{name}")
                files[f"sources/{p.name}"] = p.read_bytes()
    for h, content in _fmpy_headers().items():
        files.setdefault(f"sources/{h}", content)
    xml = (model_dir / "modelDescription.xml").read_text(encoding="utf-8")
    md, listed = _read_description(name, xml)
    _check_guid(name, md, files)
    c_sources = sorted(k.removeprefix("sources/") for k in files if k.endswith(".c"))
    files["modelDescription.xml"] = _with_source_files(xml, c_sources, listed).encode("utf-8")
    return files


def _check_guid(name: str, md: modeldesc.ModelDescription, files: dict[str, bytes]) -> None:
    """The XML's guid equals config.h's MODEL_GUID (the C side, a preprocessor line), and the CoSimulation
    modelIdentifier the directory name."""
    cfg = files.get("sources/config.h", b"").decode("utf-8", "replace")
    m_c = re.search(r'#define\s+MODEL_GUID\s+"([^"]+)"', cfg)
    if not (md.guid and m_c and md.guid == m_c.group(1)):
        raise BuildError(f"{name}: guid in modelDescription.xml and MODEL_GUID in config.h differ")
    if md.model_identifier != name:
        raise BuildError(f"{name}: modelIdentifier must equal the directory name {name!r}")


def source_hash(name: str) -> str:
    """sha256 (hex) of everything that goes into the FMU of ``name`` besides the binary."""
    h = hashlib.sha256(BUILD_TAG.encode())
    for arc, content in sorted(_staged_files(name).items()):
        h.update(arc.encode() + b"\0" + len(content).to_bytes(8, "little") + content)
    return h.hexdigest()


def fmu_sha256(path: str | os.PathLike) -> str:
    """sha256 (hex) of a file, e.g. a built FMU."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


@contextmanager
def _file_lock(path: Path) -> Iterator[None]:
    if fcntl is None:  # Windows: os.replace alone keeps the cache consistent
        yield
        return
    with open(path, "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def _ensure_cmake_on_path() -> None:
    if shutil.which("cmake"):
        return
    os.environ["PATH"] = cmake.CMAKE_BIN_DIR + os.pathsep + os.environ.get("PATH", "")


def _first_error_line(log: str) -> str:
    lines = [ln.strip() for ln in log.splitlines() if ln.strip()]
    for pat in (r"\berror\b", r"\bError\b", r"(?i)fatal", r"(?i)not found"):
        for ln in lines:
            if re.search(pat, ln):
                return ln
    return lines[-1] if lines else "no output"


def _compile(stage: Path, build_dir: Path, name: str) -> str:
    """Run fmpy's CMake build with stdout/stderr captured; return the log, raise BuildError on failure."""

    _ensure_cmake_on_path()
    options = {} if sys.platform == "win32" else {"CMAKE_C_STANDARD_LIBRARIES:STRING": "-lm"}
    error: BaseException | None = None
    with tempfile.TemporaryFile() as log:
        sys.stdout.flush()
        sys.stderr.flush()
        saved = (os.dup(1), os.dup(2))
        try:
            os.dup2(log.fileno(), 1)
            os.dup2(log.fileno(), 2)
            build_platform_binary(stage, build_dir=build_dir, all_warnings=True, cmake_options=options)
        except Exception as e:  # CalledProcessError, a missing cmake, a broken tree: all reported below
            error = e
        finally:
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])
        log.seek(0)
        text = log.read().decode("utf-8", "replace")
    if error is not None:
        detail = _first_error_line(text) if isinstance(error, subprocess.CalledProcessError) else str(error)
        detail = detail.replace(f"{(stage / 'sources').as_posix()}/", "")  # model.c:12:5: error: ...
        raise BuildError(f"building {name} failed: {detail}")
    return text


def _hash_file(fmu: Path) -> Path:
    return fmu.with_name(fmu.name + ".sha256")


def cached_fmu_ok(fmu: Path) -> bool:
    """True when ``fmu`` exists and its sha256 equals the one recorded when it was built."""
    try:
        recorded = _hash_file(fmu).read_text().split()[0]
    except (OSError, IndexError):
        return False
    return fmu.is_file() and fmu_sha256(fmu) == recorded


def _target_dir(out_dir: Path | None) -> Path:
    """``out_dir`` or the cache, created; a directory that cannot be made is a :class:`BuildError`."""
    target_dir = Path(out_dir) if out_dir is not None else cache_dir()
    try:
        target_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise BuildError(f"cannot create the FMU cache {target_dir}: {e.strerror or e}") from None
    return target_dir


def build_fmu(name: str, out_dir: Path | None = None, force: bool = False) -> Path:
    """Build (or reuse) the FMU ``name`` ('flexjoint', 'daq', ...) and return its path.

    ``out_dir`` replaces the cache directory; ``force`` rebuilds even when a cached FMU exists. A cached FMU is
    reused only when its sha256 matches the one recorded at build time; otherwise it is rebuilt.
    """
    files = _staged_files(name)
    digest = source_hash(name)
    target_dir = _target_dir(out_dir)
    target = target_dir / f"{name}-{digest[:12]}.fmu"
    if not force and cached_fmu_ok(target):
        return target
    with _file_lock(target_dir / f".{name}.lock"):
        if not force and cached_fmu_ok(target):  # built by another process meanwhile
            return target
        with tempfile.TemporaryDirectory(prefix=f".{name}-", dir=target_dir) as tmp:
            stage, build_dir = Path(tmp) / "fmu", Path(tmp) / "build"
            build_dir.mkdir()
            for arc, content in files.items():
                p = stage / arc
                p.parent.mkdir(parents=True, exist_ok=True)
                p.write_bytes(content)
            _compile(stage, build_dir, name)
            bin_dir = stage / "binaries"
            binaries = [p for p in bin_dir.rglob("*") if p.is_file()] if bin_dir.is_dir() else []
            if not binaries:
                raise BuildError(f"building {name} failed: no binary was produced")
            tmp_zip, tmp_hash = Path(tmp) / "out.fmu", Path(tmp) / "out.sha256"
            try:
                with zipfile.ZipFile(tmp_zip, "w", zipfile.ZIP_DEFLATED) as zf:
                    for arc in sorted(files):
                        zf.write(stage / arc, arc)
                    for p in sorted(binaries):
                        zf.write(p, p.relative_to(stage).as_posix())
                tmp_hash.write_text(f"{fmu_sha256(tmp_zip)}  {target.name}\n")
                # the FMU first, then its hash: a stop in between leaves a mismatch (a rebuild), never a bad FMU
                os.replace(tmp_zip, target)
                os.replace(tmp_hash, _hash_file(target))
            except OSError as e:
                raise BuildError(f"writing {target} failed: {e.strerror or e}") from None
    return target


MASTER_SOURCES = ("master.c", "kalman.c")  # the co-simulation's step loops, the likelihood engine's Kalman filter
MASTER_CMAKE = """cmake_minimum_required(VERSION 3.10)
project(flexjoint_master C)
add_library(master SHARED master.c kalman.c)
if(NOT WIN32)
  target_link_libraries(master m)
endif()
"""


def master_sources() -> dict[str, bytes]:
    """The C sources of the compiled loops (``fmus/master/``: :data:`MASTER_SOURCES`) by file name."""
    out = {}
    for name in MASTER_SOURCES:
        path = fmu_source_dir() / "master" / name
        try:
            out[name] = path.read_bytes()
        except OSError as e:
            raise BuildError(f"missing the co-simulation master {path}: {e.strerror or e}") from None
    return out


def build_master(out_dir: Path | None = None, force: bool = False) -> Path:
    """Build (or reuse) the compiled loops' shared library (:mod:`harness.fmu.cosim` calls its step loops,
    :mod:`harness.likelihood.kalman` its filter) and return its path: ``<cache>/master-<sha256 of the sources[:12]>.so``
    (``.dll``, ``.dylib``), compiled with CMake in Release mode, moved in place atomically under a file lock like the
    FMUs; ``force`` rebuilds it."""
    sources = master_sources()
    digest = hashlib.sha256(BUILD_TAG.encode() + MASTER_CMAKE.encode() + b"".join(sources.values())).hexdigest()
    suffix = {"win32": ".dll", "darwin": ".dylib"}.get(sys.platform, ".so")
    target_dir = _target_dir(out_dir)
    target = target_dir / f"master-{digest[:12]}{suffix}"
    if target.is_file() and not force:
        return target
    with _file_lock(target_dir / ".master.lock"):
        if target.is_file() and not force:
            return target
        _ensure_cmake_on_path()
        with tempfile.TemporaryDirectory(prefix=".master-", dir=target_dir) as tmp:
            src, build = Path(tmp) / "src", Path(tmp) / "build"
            src.mkdir()
            for name, text in sources.items():
                (src / name).write_bytes(text)
            (src / "CMakeLists.txt").write_text(MASTER_CMAKE)
            for cmd in (
                ["cmake", "-S", str(src), "-B", str(build), "-DCMAKE_BUILD_TYPE=Release"],
                ["cmake", "--build", str(build), "--config", "Release"],
            ):
                done = subprocess.run(cmd, capture_output=True, text=True)
                if done.returncode != 0:
                    detail = _first_error_line(done.stdout + done.stderr)
                    raise BuildError(f"building the co-simulation master failed: {detail}")
            built = [p for p in build.rglob(f"*master{suffix}") if p.is_file()]
            if not built:
                raise BuildError("building the co-simulation master failed: no library was produced")
            os.replace(built[0], target)
    return target


def install_master(name: str, data: bytes) -> Path:
    """Put a master library built elsewhere (it travelled as bytes to a worker without a compiler) into this
    machine's cache as ``name`` (``master-<digest>.so``), atomically, unless it is there already: :func:`build_master`
    then finds it when this machine's source has the same digest, and builds its own otherwise."""
    if not re.fullmatch(r"master-[0-9a-f]{12}\.(so|dll|dylib)", name):
        raise ValueError(f"not a master library's name: {name!r}")
    target_dir = _target_dir(None)
    target = target_dir / name
    if target.is_file():
        return target
    with _file_lock(target_dir / ".master.lock"), tempfile.NamedTemporaryFile(dir=target_dir, delete=False) as f:
        f.write(data)
    os.replace(f.name, target)
    return target


def build_all(out_dir: Path | None = None, force: bool = False) -> dict[str, Path]:
    """Build the rig twin's FMUs (plant, DAQ, controller), each only when its sources changed.

    Parameters
    ----------
    out_dir : Path, optional
        Where to put the FMUs; default the cache (``~/.cache/flexjoint-harness`` or ``$FLEXJOINT_CACHE``).
    force : bool
        Rebuild even when a cached FMU matches its sources.

    Returns
    -------
    dict of str to Path
        ``{"flexjoint": Path, "daq": Path, "controller": Path}``.
    """
    return {name: build_fmu(name, out_dir=out_dir, force=force) for name in MODELS}
