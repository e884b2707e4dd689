"""Blind test: the draws, the scoring rules, and a small blind run on the shortened campaign."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest
from test_diagnosis_result import minimal_doc

from harness.diagnosis import blindtest as bt
from harness.diagnosis.effects import EFFECTS
from harness.diagnosis.result import Diagnosis

OPEN = ("twin", "nuisance", "independent")  # the open-loop families (the closed one has its own measurement)


def test_plan_is_deterministic_and_covers_every_kind():
    a, b = bt.plan(20, 5), bt.plan(20, 5)
    assert a == b
    assert a != bt.plan(20, 6)
    kinds = [c["kind"] for c in a]
    assert {k: kinds.count(k) for k in set(kinds)} == {"none": 2, "two": 2, "out": 3, "single": 13}
    singles = {c["truth_effects"][0] for c in a if c["kind"] == "single"}
    assert singles == set(EFFECTS)  # 13 singles cycle through all 7 library effects
    for c in a:
        for eff in c["truth_effects"]:
            if eff in EFFECTS:
                lo, hi = EFFECTS[eff].blind
                assert lo <= c["truth_params"][EFFECTS[eff].param] <= hi
        if c["kind"] == "two":
            assert len(set(c["truth_effects"])) == 2
        if c["kind"] == "none":
            assert c["truth_params"] == {} and c["sensor"] == {}
    with pytest.raises(ValueError, match="positive"):
        bt.plan(0, 1)


def test_draws_are_those_of_the_effect_table_before_it_moved():
    """The first cases of seed 5, as drawn before the effect table left the diagnoser: the same seed gives the same
    rigs (and blindtest.json the same bytes)."""
    a = bt.plan(20, 5)[:3]
    assert [c["truth_params"] for c in a] == [
        {"daq.adc_bits": 12},
        {"plant.coulomb_torque": 0.03445729209826801},
        {"plant.n_modes": 2, "daq.gauge_cubic": 0.022056127732092503},
    ]
    assert [c["campaign_seed"] for c in a] == [1713023723, 1812972347, 1453179317]


def _diag(verdict, effects, shrink, parameters=None):
    """A diagnosis with this verdict, these (effect, params) found and this held-out shrink [%]."""
    doc = minimal_doc()
    found = doc["effects"][0]
    doc.update(verdict=verdict, effects=[{**found, "effect": e, "params": p} for e, p in effects])
    doc["gap"]["shrink_pct"] = shrink
    if parameters is not None:
        doc["parameters"] = {k: {**doc["parameters"]["plant.Ks"], "fitted": v} for k, v in parameters.items()}
    return Diagnosis.from_dict(doc)


def test_scoring_rules():
    single = {"kind": "single", "truth_effects": ["backlash"], "truth_params": {"plant.backlash": 0.005}}
    s = bt.score_case(single, _diag("backlash", [("backlash", {"plant.backlash": 0.0062})], 80.0))
    assert s["top1"] and s["param_ok"] and not s["param_ok_20"] and s["param_error"] == pytest.approx(0.24)
    s = bt.score_case(single, _diag("backlash", [("backlash", {"plant.backlash": 0.0063})], 80.0))
    assert s["top1"] and not s["param_ok"]
    s = bt.score_case(single, _diag("delay", [("delay", {"daq.delay_samples": 1})], 30.0))
    assert not s["top1"] and not s["param_ok"] and math.isinf(s["param_error"])
    none = {"kind": "none", "truth_effects": [], "truth_params": {}}
    assert bt.score_case(none, _diag("none", [], 0.0))["correct"]
    s = bt.score_case(none, _diag("backlash", [("backlash", {"plant.backlash": 0.001})], 20.0))
    assert s["turned_into_effect"] and not s["correct"]
    assert not bt.score_case(none, _diag("unexplained", [], 0.0))["turned_into_effect"]
    out = {"kind": "out", "truth_effects": ["gauge_drift"], "truth_params": {}}
    assert bt.score_case(out, _diag("unexplained", [], 0.0))["correct"]
    assert not bt.score_case(out, _diag("gauge_nonlinearity", [("gauge_nonlinearity", {})], 90.0))["correct"]
    assert not bt.score_case(out, _diag("none", [], 0.0))["correct"]
    # recalibration: Ks within 10 % and Beq within 25 % of the rig's (nuisance) values
    nuis = {**none, "nuisance": {"plant.Ks": 1.5, "plant.Beq": 0.008}}
    diag = _diag("none", [], 0.0, {"plant.Ks": 1.64, "plant.Beq": 0.0099})
    s = bt.score_case(nuis, diag)
    assert s["ks_error"] == pytest.approx(0.14 / 1.5) and s["recal_ok"]
    diag.parameters["plant.Beq"].fitted = 0.0101
    assert not bt.score_case(nuis, diag)["recal_ok"]


def test_wilson_interval():
    lo, hi = bt.wilson(9, 10)
    assert lo == pytest.approx(59.6, abs=0.1) and hi == pytest.approx(98.2, abs=0.1)  # the textbook values
    assert bt.wilson(0, 5)[0] == 0.0 and bt.wilson(5, 5)[1] == 100.0


def test_families_draw_nuisance_within_a_real_rigs_spread():
    cases = bt.plan(30, 2, bt.FAMILIES)
    assert {c["family"] for c in cases} == set(bt.FAMILIES)
    assert [c["family"] for c in cases[:4]] == list(bt.FAMILIES) == [*OPEN, "closed"]
    for c in cases:
        if c["family"] == "twin":
            assert c["nuisance"] == {}
            continue
        assert set(c["nuisance"]) == set(bt.NUISANCE)
        for p, (lo, hi, _) in bt.NUISANCE.items():
            assert lo <= c["nuisance"][p] / bt._textbook(p) <= hi
    with pytest.raises(ValueError, match="unknown family"):
        bt.plan(5, 1, ("twin", "cousin"))


def test_out_of_library_sensor_effects_change_the_data(tmp_path, fmus):
    """The sensor errors sit in the DAQ: the pot's bow changes every reading by the bow's formula (the shaft moves as
    without it, in open loop), the gauge's drift grows over each identification experiment and leaves the comb as it
    was; the manifest keeps the truth hidden."""
    case = {"case": 0, "family": "twin", "kind": "out", "truth_effects": ["pot_nonlinearity"], "truth_params": {},
            "nuisance": {}, "sensor": {"pot_nonlinearity": 0.02}, "campaign_seed": 3}  # fmt: skip
    bent = bt.make_rig_run(case, tmp_path / "bent", quick=True)
    plain = bt.make_rig_run({**case, "sensor": {}}, tmp_path / "plain", quick=True)
    drift = bt.make_rig_run({**case, "sensor": {"gauge_drift": 0.2}}, tmp_path / "drift", quick=True)

    def col(run, name, c):
        return pd.read_parquet(run / "data" / f"{name}.parquet")[c].to_numpy()

    b = col(plain, "prbs_large", "theta")  # the true shaft angle [deg], the same on both rigs
    np.testing.assert_array_equal(col(bent, "prbs_large", "theta"), b)
    w = np.clip(np.mod(b + 180.0, 360.0) - 180.0, -176.0, 176.0)  # wrapped, held in the 8 deg dead band
    a_v, b_v = col(bent, "prbs_large", "theta_v"), col(plain, "prbs_large", "theta_v")
    np.testing.assert_allclose(a_v - b_v, 0.02 * 180.0 * np.sin(np.radians(w)) / 35.5145, rtol=0, atol=1e-3)
    t = col(plain, "prbs_large", "t")
    gain = 1.0 + 0.2 * t / 12.0  # +20 % over the 12 s experiment, the noise (2 mV rms) added after it
    np.testing.assert_allclose(col(drift, "prbs_large", "alpha_v"), col(plain, "prbs_large", "alpha_v") * gain,
                               rtol=0, atol=0.003)  # fmt: skip
    np.testing.assert_array_equal(col(drift, "comb", "alpha_v"), col(plain, "comb", "alpha_v"))  # the comb intact
    m = json.loads((bent / "manifest.json").read_text())
    assert m["spec_sha256"] == "hidden" and "generator" not in m
    assert "pot_bow" not in json.dumps(m["spec"]) and "gauge_drift" not in json.dumps(m["spec"])


def test_small_blind_run_scores(tmp_path, fmus):
    # seed 6, three families: rigs from our twin, our twin off the datasheet and the independent simulator
    res = bt.blindtest(6, seed=6, out=tmp_path, workers=1, keep=True, quick=True, families=OPEN)
    doc = json.loads((tmp_path / "blindtest.json").read_text())
    assert len(doc["cases"]) == 6 and doc["totals"]["n_cases"] == 6
    assert {c["family"] for c in doc["cases"]} == set(OPEN) and doc["skipped"] == []
    tot = res["totals"]
    assert set(tot["families"]) == set(OPEN)
    assert tot["single"]["top1"]["pct"] == 100.0
    assert tot["single"]["param_within_25pct"]["pct"] == 100.0
    assert tot["none"]["turned_into_effect"] == 0
    assert tot["recalibration"]["ks_within_10pct_and_beq_within_25pct"]["pct"] == 100.0
    # the diagnoser saw no truth: every case manifest carries the blind spec's own rig tables
    base = bt.campaign_spec(quick=True).raw
    for c in doc["cases"]:
        m = json.loads((tmp_path / "blind_cases" / f"case_{c['case']:03d}" / "manifest.json").read_text())
        assert m["spec"]["plant"] == base["plant"] and m["spec"]["daq"] == base["daq"]


def test_a_target_is_not_met_on_one_case_nor_on_none():
    """The console said a target was "(met)" on 1 of 1 case and on no case at all: below MIN_TARGET_CASES a score's
    interval is too wide to tell, and the caption says so with the count."""
    from rich.console import Console

    from harness.cli import blindtest_table

    single = {"kind": "single", "truth_effects": ["backlash"], "truth_params": {"plant.backlash": 0.005}}
    s = bt.score_case(single, _diag("backlash", [("backlash", {"plant.backlash": 0.0051})], 80.0))
    tot = bt.totals([{**single, "family": "twin", "case": 0, "score": s}])
    assert tot["targets"]["single top-1 %"]["n"] == 1 and not tot["targets"]["single top-1 %"]["enough"]
    console = Console(width=200, record=True)
    console.print(blindtest_table(tot))
    text = console.export_text()
    assert "single top-1 % >= 90 (too few cases to tell: 1)" in text
    assert "none answered none % >= 90 (no cases)" in text and "(met)" not in text
    many = bt.totals([{**single, "family": "twin", "case": i, "score": s} for i in range(bt.MIN_TARGET_CASES)])
    console = Console(width=200, record=True)
    console.print(blindtest_table(many))
    assert "single top-1 % >= 90 (met)" in console.export_text()
