"""Hostile bytes at ``flexjoint import``: the two inputs a newcomer found (a truncated .mat, a command of 1e300 V)
and a property-based test (hypothesis) that random and mutated CSV, .mat and Parquet files end the command either
imported (exit 0) or in one ``error:`` line and exit 2, never a traceback."""

from __future__ import annotations

import contextlib
import io
import signal
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import scipy.io
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from harness import cli

MAT_HEADER = b"MATLAB 5.0 MAT-file"


def _record(n: int = 120, Ts: float = 0.02) -> pd.DataFrame:
    """A valid record (2.4 s at 50 Hz, volts): what the mutations start from."""
    t = np.arange(n) * Ts
    u = np.where(np.random.default_rng(3).random(n) < 0.5, 1.0, -1.0)
    return pd.DataFrame({"t": t, "u": u, "theta_v": 0.05 * np.sin(t), "alpha_v": 0.01 * np.cos(3 * t)})


def _csv_bytes(df: pd.DataFrame) -> bytes:
    return df.to_csv(index=False).encode()


def _mat_bytes(df: pd.DataFrame) -> bytes:
    buf = io.BytesIO()
    scipy.io.savemat(buf, {k: df[k].to_numpy() for k in df.columns})
    return buf.getvalue()


def _parquet_bytes(df: pd.DataFrame) -> bytes:
    buf = io.BytesIO()
    df.to_parquet(buf, index=False)
    return buf.getvalue()


VALID = {".csv": _csv_bytes(_record()), ".mat": _mat_bytes(_record()), ".parquet": _parquet_bytes(_record())}


def run_import(path: Path, out: Path) -> tuple[int, str]:
    """``flexjoint import PATH --out OUT`` in this process: (exit code, stderr). An exception the command line does
    not turn into its one line escapes from here, as its traceback would from the command."""
    err = io.StringIO()
    argv, handler = sys.argv, signal.getsignal(signal.SIGINT)
    sys.argv = ["flexjoint", "import", str(path), "--out", str(out), "--kp", "35.5", "--ke", "-3.36"]
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            cli.main()
        code = 0
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else 1
    finally:
        sys.argv = argv
        signal.signal(signal.SIGINT, handler)  # main() installs its own
    return code, err.getvalue()


def assert_imported_or_one_line(path: Path, out: Path) -> None:
    code, stderr = run_import(path, out)
    errors = [x for x in stderr.splitlines() if x.startswith("error: ")]
    assert "Traceback" not in stderr, stderr
    if code == 0:
        assert errors == [] and (out / "manifest.json").is_file(), stderr
    else:
        assert code == 2 and len(errors) == 1 and stderr.strip().splitlines()[-1] == errors[0], (code, stderr)
        assert not out.exists()  # nothing written


@pytest.mark.parametrize(
    "name, data, message",
    [
        ("trunc.mat", MAT_HEADER + bytes(50), "trunc.mat: not a readable MATLAB .mat file"),
        ("trunc2.mat", VALID[".mat"][: len(VALID[".mat"]) // 2], "trunc2.mat: not a readable MATLAB .mat file"),
        ("empty.parquet", b"PAR1", "empty.parquet: not a readable Parquet file"),
        (
            "huge.csv",
            _csv_bytes(_record().assign(u=lambda d: np.where(d.index == 40, 1e300, d.u))),
            "huge.csv: the command (column 'u') reaches 1e+300 V at row 40, beyond the +-1000 V a DAQ of the twin",
        ),
    ],
    ids=["truncated-mat", "half-mat", "empty-parquet", "huge-command"],  # the bytes vary (a .mat header's clock)
)
def test_named_hostile_files_end_in_one_line(tmp_path, name, data, message):
    (tmp_path / name).write_bytes(data)
    code, stderr = run_import(tmp_path / name, tmp_path / "run")
    assert (code, stderr.count("\n")) == (2, 1) and stderr.startswith(f"error: {message}"), stderr
    assert not (tmp_path / "run").exists()


def test_the_valid_files_import():
    """The files the mutations start from import: a refusal below is the mutation's doing."""
    for ext, data in VALID.items():
        with tempfile.TemporaryDirectory() as d:
            (Path(d) / f"rec{ext}").write_bytes(data)
            assert run_import(Path(d) / f"rec{ext}", Path(d) / "run") == (0, "")  # no note: Kp, Ke given


CELLS = st.sampled_from(["", "nan", "inf", "-inf", "1e300", "-1e300", "1e-320", "x", "1,5", "0x10", "--", " ", '"'])


@st.composite
def mutated(draw: st.DrawFn, ext: str) -> bytes:
    """A valid file of ``ext`` with a few of its bytes changed, cut, repeated or inserted; a CSV also with cells
    replaced by hostile numbers and text."""
    data = bytearray(VALID[ext])
    for _ in range(draw(st.integers(1, 4))):
        kind = draw(st.sampled_from(["flip", "cut", "insert", "repeat", "cell"] if ext == ".csv" else
                                    ["flip", "cut", "insert", "repeat"]))  # fmt: skip
        i = draw(st.integers(0, max(len(data) - 1, 0)))
        if kind == "flip" and data:
            data[i] = draw(st.integers(0, 255))
        elif kind == "cut":
            j = draw(st.integers(i, min(len(data), i + 400)))
            del data[i:j]
        elif kind == "insert":
            data[i:i] = draw(st.binary(min_size=1, max_size=16))
        elif kind == "repeat":
            j = draw(st.integers(i, min(len(data), i + 200)))
            data[j:j] = data[i:j]
        else:
            lines = data.decode().split("\n")
            k = draw(st.integers(0, len(lines) - 1))
            cells = lines[k].split(",")
            cells[draw(st.integers(0, len(cells) - 1))] = draw(CELLS)
            lines[k] = ",".join(cells)
            data = bytearray("\n".join(lines).encode())
    return bytes(data)


def _random(ext: str) -> st.SearchStrategy[bytes]:
    """Bytes that only start like a file of ``ext``, or CSV-like text."""
    if ext == ".mat":
        return st.binary(max_size=300).map(lambda b: MAT_HEADER + b)
    if ext == ".parquet":
        return st.binary(max_size=300).map(lambda b: b"PAR1" + b + b"PAR1")
    text = st.text(st.sampled_from("0123456789.,;\t -+eE\nabtuhl_x"), max_size=600)
    return st.one_of(st.binary(max_size=300), text.map(str.encode))


@pytest.mark.parametrize("ext", [".csv", ".mat", ".parquet"])
@settings(max_examples=60, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_random_and_mutated_files_import_or_end_in_one_line(tmp_path, ext, data):
    raw = data.draw(st.one_of(mutated(ext), _random(ext)), label="file")
    case = Path(tempfile.mkdtemp(dir=tmp_path))  # one per example: hypothesis reuses tmp_path
    (case / f"rec{ext}").write_bytes(raw)
    assert_imported_or_one_line(case / f"rec{ext}", case / "run")
