"""The blind test's design family: its rigs, its scores, and one case end to end."""

from __future__ import annotations

import json
import subprocess
import sys

from harness.diagnosis import blindtest as bt
from harness.diagnosis.blinddesign import BAND_METRICS, design_group, true_seed


def test_design_rigs_are_wrong_sheet_rigs_of_their_own():
    cases = bt.plan(6, 0, ("design",))
    assert [c["family"] for c in cases] == ["design"] * 6 and [c["case"] for c in cases] == list(range(6))
    assert sum(c["kind"] == "single" for c in cases) == 3 and sum(c["kind"] == "none" for c in cases) == 3
    for c in cases:
        for k, (lo, hi) in bt.WRONG_SHEET.items():
            assert lo <= c["sheet_factors"][k] <= hi
    ws = bt.plan(6, 0, ("wrong_sheet",))
    assert [c["sheet_factors"] for c in ws] != [c["sheet_factors"] for c in cases]  # a stream of their own
    mixed = bt.plan(5, 0, ("twin", "design"))
    assert [c["family"] for c in mixed] == ["twin", "design", "twin", "design", "twin"]
    assert bt.campaign_spec(True, [], "design").calibration == []  # the lab never recalibrated


def test_each_true_rig_runs_with_noise_of_its_own():
    """The true rigs of two blind-test seeds do not share their noise (case k of seed 0 and of seed 1 once ran the one
    seed 4242 + k), nor take their campaign's."""
    cases = bt.plan(5, 0, ("design",)) + bt.plan(5, 1, ("design",))
    seeds = [true_seed(c) for c in cases]
    assert len(set(seeds)) == len(cases) and all(0 <= s < 2**31 - 1 for s in seeds)
    assert not set(seeds) & {c["campaign_seed"] for c in cases}
    assert seeds == [true_seed(c) for c in bt.plan(5, 0, ("design",)) + bt.plan(5, 1, ("design",))]


def _scored(identified: bool, sheet: bool, hits: int) -> dict:
    band = {m: i < hits for i, m in enumerate(BAND_METRICS)}
    return {"score": {"design": {"identified_met": identified, "sheet_met": sheet, "band_hits": band}}}


def test_design_shares():
    cases = [_scored(True, False, 6), _scored(True, True, 5), _scored(False, False, 6), {"score": {}}]
    g = design_group(cases, bt._share)
    assert g["n"] == 3
    assert (g["specs_met_identified"]["k"], g["specs_met_identified"]["n"]) == (2, 3)
    assert (g["specs_met_sheet"]["k"], g["specs_met_sheet"]["n"]) == (1, 3)
    assert (g["band_coverage"]["k"], g["band_coverage"]["n"]) == (17, 18)
    assert g["band_coverage_per_metric"][BAND_METRICS[-1]]["k"] == 2


def test_cli_runs_the_design_family(tmp_path):
    """One quick case: the rig logged under the sheet's LQR, diagnosed, an LQR designed on the identified twin, both
    run on the true rig; blindtest.json's totals.families.design.design holds the three shares."""
    r = subprocess.run([sys.executable, "-m", "harness.cli", "blindtest", "--n", "1", "--seed", "3", "--quick",
                        "--workers", "1", "--family", "design", "--out", str(tmp_path)],
                       capture_output=True, text=True, timeout=900)  # fmt: skip
    assert r.returncode == 0, r.stderr
    doc = json.loads((tmp_path / "blindtest.json").read_text())
    case = doc["cases"][0]
    assert case["family"] == "design" and case["sheet_controller"]["kind"] == "state_feedback"
    d = case["score"]["design"]
    assert set(d["band_hits"]) == set(BAND_METRICS) and d["identified_controller"]["source"] == "designed"
    shares = doc["totals"]["families"]["design"]["design"]
    assert {"specs_met_identified", "specs_met_sheet", "band_coverage"} <= set(shares)
    assert shares["band_coverage"]["n"] == len(BAND_METRICS)
    assert "design: true metrics" in r.stdout and "design: sheet design" in r.stdout
