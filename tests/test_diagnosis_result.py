"""diagnosis.json as dataclasses: a file read and written back keeps its bytes, a broken file is one line naming
where, and the helpers readers use give the numbers of the file. (The round trip of a real diagnosis is in
test_diagnose.py, on the run it makes.)"""

from __future__ import annotations

import copy
import math
from typing import Any

import pytest

from harness.diagnosis.result import Decomposition, Diagnosis, FittedParameter, round_floats
from harness.rundir import DataError, write_json


def minimal_doc() -> dict[str, Any]:
    """A small but complete diagnosis.json content: two effects (the second found by its ADC signature, so its
    importance is null), a candidate not tried, a linear finding and an effect parameter without one."""
    exp = {"fit_pct": {"theta": 90.0, "alpha": 80.0}, "rms_deg": {"theta": 0.5, "alpha": 0.1}}
    after = {"fit_pct": {"theta": 99.0, "alpha": None}, "rms_deg": {"theta": 0.05, "alpha": 0.0}}
    return {
        "calibration": {"Ke": -3.36, "Kp": 35.5, "gauge_offset_v": 0.001},
        "candidates": [
            {
                "effect": "backlash",
                "gap_after": 0.05,
                "held_out_share_pct": 80.0,
                "params": {"plant.backlash": 0.006},
                "refit": "jointly with the linear parameters",
                "shrink_pct": 50.0,
            },
            {"effect": "second_mode", "held_out_share_pct": None, "note": "already in the simulation", "params": {}},
        ],  # fmt: skip
        "effects": [
            {
                "effect": "backlash",
                "fit_pct_after": 95.0,
                "fit_pct_before": 90.0,
                "fitted_on": [["a"], ["b"]],
                "gap_after": 0.05,
                "gap_before": 0.1,
                "held_out": [["b"], ["a"]],
                "importance_pct": 100.0,
                "params": {"plant.backlash": 0.006},
                "params_folds": [{"plant.backlash": 0.0059}, {"plant.backlash": 0.0061}],
                "selected_by": "held-out closure",
                "shrink_pct": 50.0,
            },
            {
                "effect": "quantization",
                "fit_pct_after": 95.1,
                "fit_pct_before": 95.0,
                "fitted_on": [["a"], ["b"]],
                "gap_after": 0.049,
                "gap_before": 0.05,
                "held_out": [["b"], ["a"]],
                "importance_pct": None,
                "params": {"daq.adc_bits": 12},
                "params_folds": [{"daq.adc_bits": 12}, {"daq.adc_bits": 12}],
                "selected_by": "adc lattice in the data",
                "shrink_pct": 2.0,
            },
        ],  # fmt: skip
        "folds": {"A": ["a"], "B": ["b"], "scheme": "2-fold"},
        "gap": {
            "after": {"experiments": {"a": after, "b": after}, "fit_pct": 95.1, "gap": 0.049, "rms_deg": {"theta": 1}},
            "before": {"experiments": {"a": exp, "b": exp}, "fit_pct": 80.0, "gap": 0.2, "rms_deg": {"theta": 2}},
            "decomposition": {
                "after_effects": 0.049,
                "after_recalibration": 0.1,
                "before": 0.2,
                "definition": "held out",
                "noise_floor": 0.01,
                "resolution": 0.001,
                "steps": [
                    {"applied": True, "closed_pct": 75.0, "gap_after": 0.1, "stage": "recalibration"},
                    {"applied": True, "closed_pct": 76.0, "gap_after": 0.05, "stage": "backlash"},
                    {"applied": True, "closed_pct": 1.0, "gap_after": 0.049, "stage": "quantization"},
                ],
            },  # fmt: skip
            "definition": "gap",
            "explained_pct": None,
            "held_out": {"fit_pct_after": 95.1, "fit_pct_before": 80.0, "gap_after": 0.049, "gap_before": 0.2},
            "shrink_pct": 75.5,
            "shrink_pct_in_sample": 75.0,
        },
        "noise_floor": {
            "adc_lattice_bits": 12,
            "alpha_deg": 0.01,
            "estimated_deg": {"alpha": 0.008, "theta": 0.09},
            "fit_pct": 99.0,
            "from": ["a"],
            "gap": 0.01,
            "method": "period-to-period",
            "theta_deg": 0.1,
        },  # fmt: skip
        "parameters": {
            "plant.Ks": {
                "change_pct": 15.0,
                "ci95": [1.48, 1.52],
                "finding": "link stiffness is 15 % higher than the spec (1.3 -> 1.5 N m/rad)",
                "fitted": 1.5,
                "nominal": 1.3,
                "unit": "N m/rad",
            },
            "plant.Beq": {
                "change_pct": 0.1,
                "ci95": [0.0039, 0.0041],
                "finding": "viscous damping matches the spec",
                "fitted": 0.004,
                "nominal": 0.004,
                "unit": "N m s/rad",
            },
            "plant.backlash": {
                "change_pct": None,
                "ci95": [0.0058, 0.0062],
                "fitted": 0.006,
                "nominal": 0.0,
                "unit": "rad",
            },
        },  # fmt: skip
        "real": ".",
        "recalibration_applied": True,
        "rounds": [[{"effect": "backlash", "held_out_share_pct": 80.0}]],
        "sim_spec": "nominal",
        "sim_spec_file": "nominal.toml",
        "thresholds": {"explained": 0.5, "meaning": "...", "min_gain": 0.25, "none_level": 1.0, "resolution": 0.001},
        "verdict": "backlash",
        "where": {"masked": {"alpha": 0.0, "theta": 0.01}},
    }


def test_a_file_read_and_written_back_keeps_its_bytes(tmp_path):
    write_json(tmp_path / "diagnosis.json", minimal_doc())
    d = Diagnosis.load(tmp_path)  # a run directory: its diagnosis.json
    d.write(tmp_path / "again.json")
    assert (tmp_path / "again.json").read_bytes() == (tmp_path / "diagnosis.json").read_bytes()
    # ints stay ints (12 bits, not 12.0), null reads as NaN in a float and None in an optional key
    assert d.effects[1].params == {"daq.adc_bits": 12} and d.noise_floor.adc_lattice_bits == 12
    assert math.isnan(d.gap.explained_pct) and math.isnan(d.effects[1].importance_pct)
    assert d.parameters["plant.backlash"].finding is None and d.candidates[1].gap_after is None
    assert d.noise_floor.sources == ["a"] and d.noise_floor.estimated_deg == {"alpha": 0.008, "theta": 0.09}
    assert round_floats({"x": [1.23456789012345, 7, math.nan]}) == {
        "x": [1.23456789, 7, pytest.approx(math.nan, nan_ok=True)]
    }


def test_helpers_give_the_files_numbers():
    d = Diagnosis.from_dict(minimal_doc())
    assert d.effect_names == ["backlash", "quantization"]
    assert d.fitted_effect_params() == {"plant.backlash": 0.006, "daq.adc_bits": 12}
    imp = d.importance_pct()
    assert imp["backlash"] == 100.0 and math.isnan(imp["quantization"])
    assert d.waterfall()[0][:2] == ("simulation as given", 0.2) and math.isnan(d.waterfall()[0][2])
    assert d.waterfall()[1:] == [("recalibration", 0.1, 75.0), ("backlash", 0.05, 76.0), ("quantization", 0.049, 1.0)]
    assert d.off_spec_findings() == ["link stiffness is 15 % higher than the spec (1.3 -> 1.5 N m/rad)"]
    assert [c.tried for c in d.candidates] == [True, False]
    # an experiment's gap: sqrt(mean over its moving channels of (1 - fit/100)^2); alpha without motion skipped
    rows = d.gap.per_experiment()
    assert rows[0][0] == "a" and rows[0][1] == pytest.approx(math.sqrt((0.1**2 + 0.2**2) / 2))
    assert rows[0][2] == pytest.approx(0.01)
    assert [d.folds.role(n) for n in ("a", "b", "c")] == ["fold A", "fold B", "—"]


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (lambda doc: doc.pop("verdict"), "diagnosis: missing key 'verdict'"),
        (lambda doc: doc["gap"]["decomposition"]["steps"][1].pop("stage"), "gap.decomposition.steps[1]: missing"),
        (lambda doc: doc["effects"][0].update(gap_after="small"), "effects[0].gap_after: expected a number"),
        (lambda doc: doc["noise_floor"].update(adc_lattice_bits=12.0), "noise_floor.adc_lattice_bits: expected an"),
        (lambda doc: doc.update(extra=1), "diagnosis: unknown key(s) extra"),
        (lambda doc: doc.update(folds=[]), "folds: expected an object"),
    ],
)
def test_a_malformed_file_is_one_line_naming_where(tmp_path, damage, message):
    doc = copy.deepcopy(minimal_doc())
    damage(doc)
    write_json(tmp_path / "diagnosis.json", doc)
    with pytest.raises(DataError, match=message.replace("(", r"\(").replace(")", r"\)").replace("[", r"\[")) as err:
        Diagnosis.load(tmp_path / "diagnosis.json")
    assert "\n" not in str(err.value) and str(tmp_path) in str(err.value)


def test_a_missing_or_broken_file_is_one_line(tmp_path):
    with pytest.raises(DataError, match="no such diagnosis") as err:
        Diagnosis.load(tmp_path)
    assert "\n" not in str(err.value)
    (tmp_path / "diagnosis.json").write_text('{"verdict": \n')
    with pytest.raises(DataError, match="not valid JSON") as err:
        Diagnosis.load(tmp_path)
    assert "\n" not in str(err.value)


def test_fits_are_apart_only_when_their_intervals_exclude_each_other_and_they_differ_by_5_pct():
    row = FittedParameter(nominal=1.3, fitted=1.5, ci95=[1.49, 1.51], change_pct=15.4, unit="N m/rad")
    assert not row.folds_disagree  # no per-fold fits
    row.folds = [[1.50, 1.49, 1.51], [1.505, 1.50, 1.52]]
    assert not row.folds_disagree  # overlapping: noise can separate them
    row.folds = [[1.45, 1.44, 1.46], [1.55, 1.54, 1.56]]
    assert row.folds_disagree
    row.folds = [[1.50, 1.499, 1.501], [1.52, 1.519, 1.521]]
    assert not row.folds_disagree  # excluding each other, but 1.3 % apart: under APART_MIN, one rig for any use
    row.records = {"a": [1.50, 1.499, 1.501], "b": [1.52, 1.519, 1.521], "c": [1.40, 1.39, 1.41]}
    assert row.records_apart == [("a", "c"), ("b", "c")]


def test_a_gap_left_within_the_replays_spread_is_not_put_in_a_channel():
    """Where what is left is within the replays' own spread (the search says so: ``within_noise``), the worse channel
    is noise, not a place, and the report says so instead of naming it; otherwise it names the channel that fits
    worse."""
    from harness.render.gap_text import diagnosis_markdown

    doc = minimal_doc()
    doc["gap"]["decomposition"]["channels"] = {"after_effects": {"theta": 98.6, "alpha": 98.9}}
    doc["gap"]["decomposition"]["within_noise"] = True
    d = Diagnosis.from_dict(doc)
    assert d.gap.decomposition.gap_channel() == "theta"
    assert any("within the replays' own spread" in line for line in diagnosis_markdown(d))
    d.gap.decomposition.within_noise = False
    assert any("the gap is in theta" in line for line in diagnosis_markdown(d))
