"""Blind test: the draws, the scoring rules, and a small blind run on the shortened campaign."""

from __future__ import annotations

import json
import math

import pytest

from harness import blindtest as bt


def test_plan_is_deterministic_and_covers_every_kind():
    a, b = bt.plan(20, 5), bt.plan(20, 5)
    assert a == b
    assert a != bt.plan(20, 6)
    kinds = [c["kind"] for c in a]
    assert {k: kinds.count(k) for k in set(kinds)} == {"none": 2, "two": 2, "out": 3, "single": 13}
    singles = {c["truth_effects"][0] for c in a if c["kind"] == "single"}
    assert singles == set(bt.RANGES)  # 13 singles cycle through all 7 library effects
    for c in a:
        for eff in c["truth_effects"]:
            if eff in bt.RANGES:
                param, lo, hi, _ = bt.RANGES[eff]
                assert lo <= c["truth_params"][param] <= hi
        if c["kind"] == "two":
            assert len(set(c["truth_effects"])) == 2
        if c["kind"] == "none":
            assert c["truth_params"] == {} and c["post"] == {}
    with pytest.raises(ValueError, match="positive"):
        bt.plan(0, 1)


def _diag(verdict, effects, shrink):
    return {
        "verdict": verdict,
        "effects": [{"effect": e, "params": p} for e, p in effects],
        "gap": {"shrink_pct": shrink},
    }


def test_scoring_rules():
    single = {"kind": "single", "truth_effects": ["backlash"], "truth_params": {"plant.backlash": 0.005}}
    s = bt.score_case(single, _diag("backlash", [("backlash", {"plant.backlash": 0.0059})], 80.0))
    assert s["top1"] and s["param_ok"] and s["param_error"] == pytest.approx(0.18)
    s = bt.score_case(single, _diag("backlash", [("backlash", {"plant.backlash": 0.0061})], 80.0))
    assert s["top1"] and not s["param_ok"]
    s = bt.score_case(single, _diag("delay", [("delay", {"daq.delay_samples": 1})], 30.0))
    assert not s["top1"] and not s["param_ok"] and math.isinf(s["param_error"])
    none = {"kind": "none", "truth_effects": [], "truth_params": {}}
    assert bt.score_case(none, _diag("none", [], 0.0))["correct"]
    s = bt.score_case(none, _diag("backlash", [("backlash", {"plant.backlash": 0.001})], 20.0))
    assert s["turned_into_effect"] and not s["correct"]
    assert not bt.score_case(none, _diag("unexplained", [], 0.0))["turned_into_effect"]
    out = {"kind": "out", "truth_effects": ["third_mode"], "truth_params": {"plant.n_modes": 3}}
    assert bt.score_case(out, _diag("unexplained", [], 0.0))["correct"]
    assert bt.score_case(out, _diag("second_mode", [("second_mode", {"plant.n_modes": 2})], 60.0))["correct"]
    assert not bt.score_case(out, _diag("second_mode", [("second_mode", {"plant.n_modes": 2})], 40.0))["correct"]
    assert not bt.score_case(out, _diag("none", [], 0.0))["correct"]


def test_small_blind_run_scores(tmp_path, fmus):
    # seed 6 draws: saturation, coulomb friction, backlash, none, delay + friction, a drifting gauge
    res = bt.blindtest(6, seed=6, out=tmp_path, workers=2, keep=True, quick=True)
    doc = json.loads((tmp_path / "blindtest.json").read_text())
    assert len(doc["cases"]) == 6 and doc["totals"]["n_cases"] == 6
    tot = res["totals"]
    assert {c["kind"] for c in doc["cases"]} == {"single", "none", "two", "out"}
    assert tot["single"]["top1_pct"] == 100.0
    assert tot["single"]["param_within_20pct_pct"] == 100.0
    assert tot["none"]["turned_into_effect"] == 0 and tot["none"]["correct_pct"] == 100.0
    assert tot["two"]["both_found_pct"] == 100.0
    drift = [c for c in doc["cases"] if c["truth_effects"] == ["gauge_drift"]]
    assert len(drift) == 1 and drift[0]["score"]["verdict"] == "unexplained"
    # the diagnoser saw no truth: every case manifest carries the blind spec's own rig tables
    base = bt.campaign_spec(quick=True).raw
    for c in doc["cases"]:
        m = json.loads((tmp_path / "blind_cases" / f"case_{c['case']:03d}" / "manifest.json").read_text())
        assert m["spec"]["plant"] == base["plant"] and m["spec"]["daq"] == base["daq"]
