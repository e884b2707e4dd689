"""The armax FMU and harness.ident.export against the Python simulation, python-control and fmpy's own master."""

from __future__ import annotations

import re
import zipfile
from pathlib import Path

import control
import numpy as np
import pytest
from fmpy import read_model_description, simulate_fmu
from fmpy.validation import validate_fmu

from benchmarks.problems import demo_problem
from harness.fmu.binding import FMUError
from harness.fmu.build import build_fmu
from harness.fmu.sources import fmu_source_dir
from harness.ident import armax as ax
from harness.ident import export, lti

TS = 0.02
# lab 1's printed model (two digits): |pole| = 1.17, unstable
LAB1_A = [1.0, -4.33, 7.64, -6.87, 3.16, -0.59]
LAB1_B = [0.0, -0.05, 0.14, -0.09]


@pytest.fixture(scope="module")
def generic() -> Path:
    return build_fmu("armax")


@pytest.fixture(scope="module")
def identified() -> ax.ArmaxModel:
    _, u, y = demo_problem(5, n=800)
    return ax.estimate(u, y, 4, 3, 4, 1, Ts=TS)


def _starts(fmu: Path) -> dict[str, float]:
    md = read_model_description(str(fmu), validate=True)
    return {v.name: float(v.start) for v in md.modelVariables if v.causality == "parameter"}


def _random_model(seed: int, na: int, nb: int, nk: int) -> ax.ArmaxModel:
    """A stable ARMAX model with random poles of radius 0.3..0.97 (conjugate pairs) and a random B."""
    rng = np.random.default_rng(seed)
    poles: list[complex] = []
    while len(poles) < na:
        r, ang = rng.uniform(0.3, 0.97), rng.uniform(0.05, 3.0)
        poles += [r * np.exp(1j * ang), r * np.exp(-1j * ang)] if na - len(poles) >= 2 else [complex(r)]
    A = np.real(np.poly(poles))
    B = np.concatenate([np.zeros(nk), rng.normal(0.0, 0.2, nb)])
    return ax.ArmaxModel(A=A, B=B, C=np.array([1.0, 0.3]), na=na, nb=nb, nc=1, nk=nk, Ts=TS)


def _square_prbs(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.where(np.cumsum(rng.random(n) < 0.1) % 2 == 0, 1.0, -1.0)


def test_config_h_and_template_agree_with_the_exporter(generic):
    """NMAX of config.h is the exporter's (value references: tests/test_fmu_config.py)."""
    cfg = (fmu_source_dir() / "armax" / "config.h").read_text()
    assert int(re.search(r"^#define\s+NMAX\s+(\d+)", cfg, re.M).group(1)) == export.NMAX
    assert len(_starts(generic)) == 8 + 3 * export.NMAX + 1  # Ts, orders, af, u_offset, y0; a, b (from 0), c
    assert validate_fmu(str(generic)) == []
    # the generic binary's compiled defaults are the template's start values
    with export.ModelFMU(generic) as m:
        assert m.parameters() == _starts(generic)


def test_identified_model_fmu_matches_python_and_python_control(identified, tmp_path):
    m = identified
    af, u_offset, y0 = 0.8, 0.25, 12.5
    fmu = export.export_model(m, tmp_path / "m.fmu", af=af, u_offset=u_offset, y0=y0)
    assert validate_fmu(str(fmu)) == []
    # start values in the XML and the values the binary runs with are the coefficients, bit for bit
    starts = _starts(fmu)
    with export.ModelFMU(fmu) as runner:
        held = runner.parameters()
    for name, value in export.fmu_parameters(m, af=af, u_offset=u_offset, y0=y0).items():
        assert starts[name] == value and held[name] == value, name
    assert [starts[f"a[{i}]"] for i in range(1, 5)] == m.A[1:].tolist()
    assert [starts[f"b[{j}]"] for j in range(4)] == m.B.tolist()

    u_d = _square_prbs(900, 7)
    with export.ModelFMU(fmu) as runner:
        out = runner.run(u_d + u_offset, TS)  # raw command = detrended + offset
    y_f = ax.simulate(m, u_d)
    assert np.max(np.abs(out["y_f"] - y_f)) < 1e-9
    t = np.arange(u_d.size) * TS
    y = y0 + control.forced_response(lti.with_integrator(m, af), t, u_d).outputs
    assert out["y"][0] == y0
    assert np.max(np.abs(out["y"] - y)) < 1e-9 * max(1.0, np.max(np.abs(y)))
    assert np.ptp(y) > 10.0  # a real response, not a flat line
    # another master (fmpy's simulate_fmu, no start values passed) runs the same model
    rows = list(zip(t[:300], u_d[:300] + u_offset, strict=True))
    sig = np.array(rows, dtype=[("time", float), ("u", float)])
    res = simulate_fmu(str(fmu), stop_time=t[299], output_interval=TS, input=sig, output=["y_f", "y"])
    assert np.max(np.abs(res["y_f"] - y_f[:300])) < 1e-9


CASES = [(1, 1, 1, 0.0), (3, 2, 2, 0.5), (8, 4, 1, 0.8), (8, 3, 3, 0.9)]


@pytest.mark.parametrize(("na", "nb", "nk", "af"), CASES)
def test_orders_up_to_eight(na, nb, nk, af, tmp_path):
    m = _random_model(na * 10 + nk, na, nb, nk)
    fmu = export.export_model(m, tmp_path / "m.fmu", af=af)
    u = _square_prbs(600, na)
    with export.ModelFMU(fmu) as runner:
        out = runner.run(u, TS)
    assert np.max(np.abs(out["y_f"] - ax.simulate(m, u))) < 1e-9
    y = control.forced_response(lti.with_integrator(m, af), np.arange(u.size) * TS, u).outputs
    assert np.max(np.abs(out["y"] - y)) < 1e-9 * max(1.0, np.max(np.abs(y)))
    assert np.all(out["y_f"][:nk] == 0.0) and out["y_f"][nk] != 0.0  # the delay nk, exactly


def test_exported_bytes_are_deterministic_and_not_rewritten(identified, tmp_path):
    rec = {"name": "x", "dataset": "prbs", **identified.to_dict(), "preprocessing": {"af": 0.8}}
    a = export.export_model(rec, tmp_path / "a.fmu")
    b = export.export_model(identified, tmp_path / "b.fmu", af=0.8)
    assert a.read_bytes() != b.read_bytes()  # the description names the model and its dataset
    c = export.export_model(dict(rec), tmp_path / "c.fmu")
    assert a.read_bytes() == c.read_bytes()
    before = a.stat().st_mtime_ns
    export.export_model(rec, a)
    assert a.stat().st_mtime_ns == before
    with zipfile.ZipFile(a) as zf:
        infos = zf.infolist()
    assert [i.filename for i in infos] == sorted(i.filename for i in infos)
    assert {i.date_time for i in infos} == {(1980, 1, 1, 0, 0, 0)}
    assert "resources/coefficients.txt" in {i.filename for i in infos}


def test_multi_sample_communication_steps(identified, generic):
    u = _square_prbs(400, 3)[::2]
    with export.ModelFMU(generic) as runner:
        p = export.fmu_parameters(identified, af=0.8)
        out = runner.run(u, 2 * TS, parameters=p)
        # two model samples per step with the input held
        assert np.max(np.abs(out["y_f"] - ax.simulate(identified, np.repeat(u, 2))[::2])) < 1e-9
        with pytest.raises(FMUError, match="not a whole multiple of Ts"):
            runner.run(u, 1.5 * TS, parameters=p)


@pytest.mark.parametrize(
    ("params", "message"),
    [
        (
            {"na": 5, "nb": 3, **{f"a[{i}]": v for i, v in enumerate(LAB1_A) if i}, "b[1]": -0.05},
            "model is unstable",
        ),
        ({"nk": 0}, "nk = 0: must be >= 1"),
        ({"af": 1.0}, "af = 1: must be in"),
        ({"b[0]": 0.1}, r"b\[0\] = 0.1: must be 0 outside"),
        ({"a[2]": 0.1}, r"a\[2\] = 0.1: must be 0 beyond na = 1"),
        ({"na": 17}, "na = 17"),
        ({"Ts": 0.0}, "Ts = 0"),
    ],
)
def test_fmu_refuses_bad_parameters_at_initialisation(generic, params, message):
    with export.ModelFMU(generic) as runner:
        with pytest.raises(FMUError, match=message):
            runner.run(np.ones(10), parameters=params)


def test_schur_cohn_boundary_matches_numpy_roots(generic):
    """A pole pair at radius 0.999 runs, at 1.001 it is refused: the FMU's test agrees with the roots."""
    for r, ok in ((0.999, True), (1.001, False)):
        a = np.real(np.poly([r * np.exp(0.3j), r * np.exp(-0.3j), 0.5]))
        assert (np.max(np.abs(np.roots(a))) < 1.0) == ok
        params = {"na": 3, "a[1]": a[1], "a[2]": a[2], "a[3]": a[3]}
        with export.ModelFMU(generic) as runner:
            if ok:
                runner.run(np.ones(10), parameters=params)
            else:
                with pytest.raises(FMUError, match="model is unstable"):
                    runner.run(np.ones(10), parameters=params)


def test_export_refuses_models_the_fmu_cannot_run(identified, tmp_path):
    lab1 = ax.ArmaxModel(A=np.array(LAB1_A), B=np.array(LAB1_B), C=np.ones(1), na=5, nb=3, nc=0, nk=1, Ts=TS)
    with pytest.raises(ValueError, match=r"unstable \(largest \|pole\| = 1\.168"):
        export.export_model(lab1, tmp_path / "s.fmu", af=0.8)
    A, B, C = np.array([1.0, -0.5]), np.array([0.3]), np.ones(1)
    m0 = ax.ArmaxModel(A=A, B=B, C=C, na=1, nb=1, nc=0, nk=0, Ts=TS)
    with pytest.raises(ValueError, match="nk >= 1"):
        export.export_model(m0, tmp_path / "k.fmu", af=0.8)
    with pytest.raises(ValueError, match="preprocessing.af"):
        export.export_model(identified.to_dict(), tmp_path / "n.fmu")
    assert not any(tmp_path.iterdir())


def test_libcosim_runs_the_exported_model_without_parameters(identified, tmp_path):
    """A second importer (libcosim) runs the exported FMU as is: the coefficients travel inside the FMU."""
    try:
        from libcosimpy.CosimEnums import CosimVariableType
        from libcosimpy.CosimExecution import CosimExecution
        from libcosimpy.CosimLogging import CosimLogLevel, log_output_level
        from libcosimpy.CosimObserver import CosimObserver
        from libcosimpy.CosimSlave import CosimLocalSlave
    except (ImportError, OSError) as e:  # pragma: no cover - platform without libcosim
        pytest.skip(f"libcosimpy cannot load on this platform: {e}")
    log_output_level(CosimLogLevel.ERROR)
    fmu = export.export_model(identified, tmp_path / "m.fmu", af=0.8)
    n, step_ns = 100, 20_000_000
    ex = CosimExecution.from_step_size(step_ns)
    idx = ex.add_local_slave(CosimLocalSlave(fmu_path=str(fmu), instance_name="m"))
    ex.real_initial_value(idx, 10, 1.0)  # u = 1 V step; nothing else set
    obs = CosimObserver.create_time_series()
    ex.add_observer(obs)
    obs.start_time_series(idx, 11, CosimVariableType.REAL)  # y_f
    assert ex.simulate_until(n * step_ns)
    _, _, values = obs.time_series_real_samples(idx, 11, from_step=1, sample_count=n)
    ref = ax.simulate(identified, np.ones(n + 1))[1:]
    assert len(values) == n and np.max(np.abs(np.asarray(values) - ref)) < 1e-9
