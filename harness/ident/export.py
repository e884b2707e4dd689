"""Identified ARMAX models back as FMI 2.0 co-simulation FMUs (``fmus/armax``), and running them through fmpy.

One generic binary serves every model: ``harness.fmu.build.build_fmu("armax")`` compiles ``fmus/armax`` once
(cached by source hash); an exported FMU is that FMU with a generated ``modelDescription.xml`` whose
parameter start values are the model's coefficients at full precision (``repr`` of each double), and the
same values in ``resources/coefficients.txt``, which the binary reads at instantiation. So the FMU runs the
identified model with no parameter set by the importer. The zip has a fixed entry order and timestamps:
same model and same binary give the same bytes. All FMUs share the generic GUID (the binary checks it).

FMU parameters (names as in ``harness.ident.armax``): ``Ts`` [s]; ``na``, ``nb``, ``nc``, ``nk`` (Integer, orders up
to ``NMAX``, nk >= 1); ``a[1..NMAX]``, ``b[0..NMAX]`` (B with its nk leading zeros), ``c[1..NMAX]`` (stored,
unused); ``af`` (pole of H(z) = (1 - af)(z - 1)/(z - af)); ``u_offset`` [V] subtracted from the input;
``y0`` [deg]. Input ``u`` [V]. Outputs ``y_f`` = B/A (u - u_offset) (units of y per sample) and ``y`` [deg] =
y0 + H^-1(z) y_f. Timing: outputs after initialisation are those at t_0; ``doStep(t_k, h)`` with u(t_k) set
gives the outputs at t_k + h; h must be a whole multiple of Ts.

Run directories: ``harness.ident.crossfit.crossfit_run`` writes ``models/<name>.fmu`` for every stable
``models/<name>.json`` with ``u_offset = 0`` and ``y0 = 0``: the cross-fit feeds each dataset's *detrended*
command u_d, so one FMU serves every dataset (to drive it with a raw command, set ``u_offset`` to that record's
command mean).
"""

from __future__ import annotations

import ctypes
import io
import json
import math
import re
import zipfile
from pathlib import Path
from typing import Any
from xml.sax.saxutils import escape

import numpy as np

from ..fmu.binding import FMUError, Instance, load
from ..fmu.build import build_fmu
from ..rundir import atomic_write_bytes
from .armax import ArmaxModel

__all__ = [
    "NMAX",
    "FMUError",
    "ModelFMU",
    "coefficient_file",
    "export_model",
    "fmu_parameters",
    "model_fmu_bytes",
    "model_records",
]

NMAX = 16  # must equal NMAX in fmus/armax/config.h (tests check it)
COEFFICIENT_FILE = "resources/coefficients.txt"
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)


# ----------------------------------------------------------------------------------------------- parameters
def _as_model(record: dict[str, Any] | ArmaxModel) -> tuple[ArmaxModel, dict[str, Any]]:
    if isinstance(record, ArmaxModel):
        return record, {}
    if not isinstance(record, dict):
        raise ValueError(f"expected a model record (dict) or an ArmaxModel, got {type(record).__name__}")
    return ArmaxModel.from_dict(record), record


def _record_af(meta: dict[str, Any]) -> float:
    try:
        return float(meta["preprocessing"]["af"])
    except (KeyError, TypeError, ValueError):
        raise ValueError("af not given and the model record has no preprocessing.af") from None


def fmu_parameters(model: ArmaxModel, *, af: float, u_offset: float = 0.0, y0: float = 0.0) -> dict[str, Any]:
    """Every parameter of the armax FMU for ``model`` (name -> value), coefficients at full precision.

    ``af`` in [0, 1) (preprocessing filter pole), ``u_offset`` [V], ``y0`` [deg]. Raises ValueError for what
    the FMU cannot run: nk < 1, orders above NMAX, non-finite numbers, an unstable A.
    """
    na, nb, nc, nk = model.na, model.nb, model.nc, model.nk
    if nk < 1:
        raise ValueError(f"model has nk = {nk}: the FMU needs nk >= 1 (a causal model)")
    if na > NMAX or nc > NMAX or nk + nb - 1 > NMAX:
        raise ValueError(f"model orders na={na}, nb={nb}, nc={nc}, nk={nk} exceed the FMU's NMAX = {NMAX}")
    for name, v in (("af", af), ("u_offset", u_offset), ("y0", y0), ("Ts", model.Ts)):
        number = isinstance(v, int | float | np.floating | np.integer) and not isinstance(v, bool)
        if not (number and math.isfinite(v)):
            raise ValueError(f"{name} must be a finite number, got {v!r}")
    if not 0.0 <= af < 1.0:
        raise ValueError(f"af must be in [0, 1), got {af!r}")
    if not model.Ts > 0:
        raise ValueError(f"model Ts must be > 0 s, got {model.Ts!r}")
    coeffs = np.concatenate([model.A, model.B, model.C])
    if not np.all(np.isfinite(coeffs)):
        raise ValueError("model has non-finite coefficients")
    if not model.stable:
        rmax = np.max(np.abs(model.poles))
        raise ValueError(f"model is unstable (largest |pole| = {rmax:.4g}): not exported")
    p: dict[str, int | float] = {"Ts": float(model.Ts), "na": na, "nb": nb, "nc": nc, "nk": nk}
    p.update({"af": float(af), "u_offset": float(u_offset), "y0": float(y0)})
    for i in range(1, NMAX + 1):
        p[f"a[{i}]"] = float(model.A[i]) if i <= na else 0.0
    for j in range(NMAX + 1):
        p[f"b[{j}]"] = float(model.B[j]) if j < model.B.size else 0.0
    for i in range(1, NMAX + 1):
        p[f"c[{i}]"] = float(model.C[i]) if i <= nc else 0.0
    return p


def _fmt(v: int | float) -> str:
    return str(v) if isinstance(v, int) else repr(float(v))


def coefficient_file(params: dict[str, int | float], title: str = "") -> str:
    """Text of ``resources/coefficients.txt``: one ``name value`` line per parameter (repr of each double)."""
    head = "# start values of the armax FMU (name value), read by its binary at instantiation"
    lines = [head] + ([f"# {title}"] if title else []) + [f"{k} {_fmt(v)}" for k, v in params.items()]
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------------------------- packing
def _with_start_values(xml: str, params: dict[str, int | float], description: str) -> str:
    """The generic modelDescription.xml with the start values of ``params`` and a new description."""
    for name, value in params.items():
        var = r'(<ScalarVariable name="' + re.escape(name) + r'"(?:(?!</ScalarVariable>).)*?\bstart=")'
        pat = re.compile(var + r'[^"]*(")', re.DOTALL)
        xml, n = pat.subn(r"\g<1>" + _fmt(value) + r"\g<2>", xml)  # a number: no backslash, no group reference
        if n != 1:
            raise RuntimeError(f"fmus/armax/modelDescription.xml: no single start value for {name!r}")
    text = escape(description, {'"': "&quot;"})
    pat = re.compile(r'(<fmiModelDescription\b[^>]*?\bdescription=")[^"]*(")')
    xml, n = pat.subn(lambda m: m.group(1) + text + m.group(2), xml, count=1)
    if n != 1:
        raise RuntimeError("fmus/armax/modelDescription.xml: no description attribute")
    return xml


def zip_bytes(files: dict[str, bytes]) -> bytes:
    """Deterministic zip: sorted entries, fixed timestamp and permissions, deflate level 9."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for arc in sorted(files):
            zi = zipfile.ZipInfo(arc, date_time=_ZIP_DATE)
            zi.compress_type = zipfile.ZIP_DEFLATED
            zi.create_system = 3
            zi.external_attr = 0o644 << 16
            zf.writestr(zi, files[arc], compresslevel=9)
    return buf.getvalue()


def model_fmu_bytes(
    record: dict[str, Any] | ArmaxModel, *, af: float | None = None, u_offset: float = 0.0, y0: float = 0.0
) -> bytes:
    """The bytes of the exported FMU (see :func:`export_model`)."""
    model, meta = _as_model(record)
    af = _record_af(meta) if af is None else af
    params = fmu_parameters(model, af=af, u_offset=u_offset, y0=y0)
    name = str(meta.get("name", "model"))
    orders = f"ARMAX({model.na},{model.nb},{model.nc},{model.nk})"
    where = f" identified on {meta['dataset']}" if meta.get("dataset") else ""
    desc = (
        f"{orders} model {name!r}{where}, Ts = {model.Ts!r} s, af = {af!r}: y_f = B/A (u - u_offset), "
        f"y = y0 + (z - af) / ((1 - af)(z - 1)) y_f"
    )
    with zipfile.ZipFile(build_fmu("armax")) as zf:  # the generic armax FMU
        files = {n: zf.read(n) for n in zf.namelist() if not n.endswith("/")}
    xml = _with_start_values(files["modelDescription.xml"].decode(), params, desc)
    files["modelDescription.xml"] = xml.encode()
    files[COEFFICIENT_FILE] = coefficient_file(params, desc).encode()
    return zip_bytes(files)


def export_model(
    record: dict[str, Any] | ArmaxModel,
    path: Path,
    *,
    af: float | None = None,
    u_offset: float = 0.0,
    y0: float = 0.0,
) -> Path:
    """Write the FMU of one identified model, atomically (rewritten only when its bytes change).

    Parameters
    ----------
    record : dict or ArmaxModel
        A ``models/<name>.json`` record, or a bare model.
    path : Path
        The ``.fmu`` to write.
    af : float, optional
        The preprocessing filter's pole; default the record's ``preprocessing.af`` (required for a bare model).
    u_offset : float
        Subtracted from the input ``u`` [V].
    y0 : float
        The initial angle [deg].

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    ValueError
        A model the FMU cannot run (unstable, nk < 1, orders above its maximum).
    """
    path = Path(path)
    data = model_fmu_bytes(record, af=af, u_offset=u_offset, y0=y0)
    if not (path.is_file() and path.read_bytes() == data):
        atomic_write_bytes(path, data)
    return path


def model_records(run: Path) -> dict[str, dict[str, Any]]:
    """{name: record} of every ``models/<name>.json`` of a run, sorted by name."""
    mdir = Path(run) / "models"
    paths = sorted(mdir.glob("*.json")) if mdir.is_dir() else []
    if not paths:
        raise ValueError(f"{run}: no models/*.json; run `flexjoint identify {run}` first")
    out = {}
    for p in paths:
        try:
            out[p.stem] = json.loads(p.read_text())
        except json.JSONDecodeError as e:
            raise ValueError(f"{p}: not valid JSON ({e.msg}, line {e.lineno})") from None
    return out


# ----------------------------------------------------------------------------------------------- running
class ModelFMU:
    """An armax FMU loaded once through fmpy's ``FMU2Slave`` and re-run with :meth:`run` (reset in between).

    Use as a context manager or call :meth:`close`.
    """

    def __init__(self, fmu: Path) -> None:
        self.inst: Instance = load(Path(fmu), "armax")
        self._vr_in = (ctypes.c_uint * 1)(self.inst.vr("u"))
        self._vr_out = (ctypes.c_uint * 2)(self.inst.vr("y_f"), self.inst.vr("y"))
        Ts = self.inst.variables["Ts"].start
        if Ts is None:
            raise RuntimeError(f"{fmu}: the model's Ts has no start value")
        self.Ts = float(Ts)

    def __enter__(self) -> ModelFMU:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self.inst.free()

    def parameters(self) -> dict[str, float | int]:
        """Current parameter values as the binary holds them (name -> value), after a reset."""
        self.inst.reset()
        return self.inst.get(list(self.inst.description.parameters()))

    def run(
        self, u: np.ndarray, Ts: float | None = None, parameters: dict[str, Any] | None = None
    ) -> dict[str, np.ndarray]:
        """Outputs ``{"y_f", "y"}`` at t_k = k Ts, k = 0..len(u)-1, for the input ``u`` [V] sampled at ``Ts``
        [s] (default: the FMU's own Ts; a whole multiple of it runs several model samples per step, input
        held). u[k] is applied over [t_k, t_{k+1}). ``parameters`` overrides start values by name."""
        u = np.ascontiguousarray(u, dtype=float)
        if u.ndim != 1 or u.size == 0:
            raise ValueError(f"u must be a non-empty 1-D array, got shape {u.shape}")
        if not np.all(np.isfinite(u)):
            raise ValueError("u contains NaN or inf")
        h = self.Ts if Ts is None else float(Ts)
        if not (math.isfinite(h) and h > 0):
            raise ValueError(f"Ts must be > 0 s, got {Ts!r}")
        inst = self.inst
        f, c = inst.dll, inst.component
        n = u.size
        inst.initialize(parameters or {}, n * h)
        inst.exit_initialization()
        out = np.empty((n, 2))
        buf_in = (ctypes.c_double * 1)()
        buf_out = (ctypes.c_double * 2)()
        vr_in, vr_out = self._vr_in, self._vr_out
        set_real, get_real, do_step = f.fmi2SetReal, f.fmi2GetReal, f.fmi2DoStep
        inst.check(get_real(c, vr_out, 2, buf_out), "get outputs")
        out[0] = buf_out[0], buf_out[1]
        for k in range(n - 1):
            buf_in[0] = u[k]
            set_real(c, vr_in, 1, buf_in)
            s = do_step(c, k * h, h, 1)
            if s > 1:
                inst.check(s, f"doStep at t={k * h:.6g} s")
            get_real(c, vr_out, 2, buf_out)
            out[k + 1] = buf_out[0], buf_out[1]
        inst.terminate()
        return {"y_f": out[:, 0].copy(), "y": out[:, 1].copy()}
