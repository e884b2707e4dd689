"""Datasets: Parquet round trip, byte-stable writes, validation with clear rejections."""

import numpy as np
import pandas as pd
import pytest

from harness import rundir as data
from harness.rig import records


def _csv(path, n=100, Ts=0.02, **overrides):
    t = np.arange(n) * Ts
    df = pd.DataFrame({"t": t, "u": np.sin(t), "theta_v": 0.1 * t, "alpha_v": np.cos(t)})
    for k, v in overrides.items():
        if v is None:
            df = df.drop(columns=k)
        else:
            df[k] = v
    df.to_csv(path, index=False)
    return path


def test_write_dataset_is_byte_stable_and_round_trips(tmp_path):
    cols = {"t": np.arange(50) * 0.02, "u": np.linspace(-1, 1, 50), "theta_v": np.zeros(50), "alpha_v": np.ones(50)}
    data.write_dataset(tmp_path / "a.parquet", cols)
    data.write_dataset(tmp_path / "b.parquet", cols)
    assert (tmp_path / "a.parquet").read_bytes() == (tmp_path / "b.parquet").read_bytes()
    df = data.read_dataset(tmp_path / "a.parquet")
    np.testing.assert_array_equal(df["u"].to_numpy(), cols["u"])
    assert data.sample_time(df) == pytest.approx(0.02)


def test_imported_run_has_the_dataset_layout(tmp_path):
    """An import (harness.rig.records; its hostile cases are in test_import.py) reads back through load_run."""
    src = _csv(tmp_path / "rig1.csv")
    out = tmp_path / "run"
    written = records.import_records([src], out)
    assert written == [out / "data" / "rig1.parquet"]
    runs = data.load_run(out)
    assert list(runs) == ["rig1"] and len(runs["rig1"]) == 100
    assert list(runs["rig1"].columns) == ["t", "u", "theta_v", "alpha_v", "theta", "alpha"]
    assert data.Manifest.load(out).kind == "import"


@pytest.mark.parametrize(
    "overrides, message",
    [
        ({"alpha_v": None}, "missing column"),
        ({"u": [np.nan] + [0.0] * 99}, "NaN"),
        ({"t": np.r_[np.arange(50) * 0.02, 1.0 + np.arange(50) * 0.03]}, "non-uniform sampling"),
        ({"t": np.r_[np.arange(50) * 0.02, np.arange(50) * 0.02]}, "not strictly increasing"),
    ],
)
def test_validate_rejects_bad_datasets(tmp_path, overrides, message):
    bad = pd.read_csv(_csv(tmp_path / "bad.csv", **overrides))
    with pytest.raises(data.DataError, match=message) as exc:
        data.validate(bad, "bad.csv")
    assert "\n" not in str(exc.value)


def test_write_json_is_stable_and_nan_safe(tmp_path):
    data.write_json(tmp_path / "x.json", {"b": np.float64(np.nan), "a": np.arange(3)})
    assert (tmp_path / "x.json").read_text() == '{\n  "a": [\n    0,\n    1,\n    2\n  ],\n  "b": null\n}\n'
