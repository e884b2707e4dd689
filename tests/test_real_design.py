"""The labs' Part II on the bundled real records (tests/fixtures/real/): the Quanser rig's twin as diagnosed, an LQR to
the courseware's specs on it, predicted with bands; and each record's own controller predicted against what it did,
the CU unit's from a diagnosis of its other record (held out)."""

from __future__ import annotations

import json

import pytest
from shared_runs import CU, CU_IMPORT

from harness import spec as specmod
from harness.design import design
from harness.diagnosis.rigmodel import combos
from harness.loopspecs import LoopSpecs
from harness.prediction import predict, reference_from
from harness.rig.records import import_records
from harness.twin import load_record, twin_of_diagnosis

COURSEWARE = "settling=1.5,overshoot=5,band=4"  # Quanser's rotary flexible link courseware
HELD = ("settling_s", "peak_alpha_deg", "ring_alpha_deg")  # inside the band or within 20 % of the median, both units


def _held(pred, names):
    bands = pred.metric_bands()
    return {m: bands[m].holds(bands[m].measured, 0.20) for m in names}


@pytest.fixture(scope="module")
def cu(tmp_path_factory, cu_lone_run):
    """The CU unit's two records, apart: test_3 diagnosed against the lab sheet (the session's ``cu_lone_run``),
    test_4 held out."""
    held = tmp_path_factory.mktemp("cu") / "cu4"
    import_records([CU[1]], held, CU_IMPORT)
    return [cu_lone_run / "run", held]


def test_an_lqr_to_the_courseware_specs_on_the_quanser_twin(quanser_run):
    twin = twin_of_diagnosis(quanser_run)
    fitted = json.loads((quanser_run / "diagnosis.json").read_text())["parameters"]["rig.drive_gain"]["fitted"]
    assert twin.overrides["rig.drive_gain"] == fitted != combos(twin.plant)["rig.drive_gain"]  # the rig, not its sheet
    rec = load_record(quanser_run)
    d = design(twin, "lqr", reference_from(None, twin.sample_rate, rec), LoopSpecs.parse(COURSEWARE), n=100, workers=1)
    assert d.passed and d.margins["disk_margin"] > 0.5
    bands = d.prediction.metric_bands()
    assert bands["settling_s"].hi <= 1.5 and bands["overshoot_pct"].hi <= 5.0
    assert bands["settling_s"].lo > 0.1  # a loop that moves the hub, not a band of nothing


def test_the_quanser_records_own_controller_predicted_against_what_it_did(quanser_run):
    """Its theta fit ~97 %, alpha ~92 %; its settling, peak deflection and ringing inside the bands or within 20 % of
    the median. Not its overshoot (0.54 % against 2.3..2.9 %) and stopping error (+0.59 deg, short of the reference
    both ways, against -0.2..-0.1: the diagnosis holds the hub with a command offset where the record shows friction),
    nor its peak command (6.2 V against 4.3..4.6 V: the logged voltage exceeds the identified controller's own law on
    the record by 0.7 V at the steps)."""
    twin = twin_of_diagnosis(quanser_run)
    rec = load_record(quanser_run)
    pred = predict(twin, rec.controller, reference_from(None, twin.sample_rate, rec), n=100, record=rec, workers=1)
    assert pred.fit_pct["theta"] > 90.0 and pred.fit_pct["alpha"] > 85.0
    assert all(_held(pred, HELD).values()), pred.metric_bands()


def test_the_cu_units_held_out_record_predicted_from_the_other(cu):
    """Diagnosed from flexibleArm_test_3 alone, the twin predicts flexibleArm_test_4 under its controller: theta fit
    ~97 %, alpha ~83 % (its gauge read at the record's own zero, -4.1 deg: the importer leaves alpha as read where the
    link never rests; at the twin's zero alpha's fit was -93 %); settling, stopping error, peak deflection and ringing
    inside the bands or within 20 % of the median. Not its peak command (5.3 V against 4.2..4.4 V: at each step the
    logged voltage kicks 1 V beyond the identified controller's law)."""
    twin = twin_of_diagnosis(cu[0], spec=specmod.load("cu_flexible_arm"))
    rec = load_record(cu[1])
    pred = predict(twin, rec.controller, reference_from(None, twin.sample_rate, rec), n=100, record=rec, workers=1)
    assert pred.fit_pct["theta"] > 90.0 and pred.fit_pct["alpha"] > 70.0
    assert all(_held(pred, (*HELD, "stop_error_deg")).values()), pred.metric_bands()
