"""One unit's records under two controllers (P only on a small reference, P + tip feedback on a large one) from a
CU arm whose drive is off the sheet by 2x, with an effect, imported as a lab logs them and diagnosed against the
sheet; and the same unit with what real records show besides: each gauge reading its own zero, a link still ringing
when a record starts, a command offset, a lightly damped link, and a loop that hunts."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
from shared_runs import perturbed_copy, shared_dir

from harness import spec as specmod
from harness.diagnosis.diagnose import diagnose_run
from harness.diagnosis.result import Diagnosis
from harness.diagnosis.simulation import link_keys, offset_key
from harness.rig.campaign import run_campaign
from harness.rig.records import ImportOptions, import_records
from harness.rig.signals import square
from harness.rundir import Manifest, read_dataset

WRONG_DRIVE = {"kt": 0.0214, "Jeq": 0.003, "Ks": 1.79584}  # kt x2, Jeq x1.5, Ks x0.8 of cu_flexible_arm
DRIVE_GAIN = 1.8847  # rad/(V s): the truth's, against the sheet's 1.841 (the drive's time constant 0.103 s: 0.54x)
RECORDS = [  # name, controller, reference amplitude [deg], seed
    ("p_only", {"kind": "pid", "kp": 6.0}, 5.7, 11),
    ("p_tip", {"kind": "state_feedback", "K": [6.0, 2.0, 0.0, 0.0]}, 17.19, 12),
]
FRICTION = {"coulomb_torque": 0.03, "stiction_ratio": 1.3, "stribeck_speed": 0.02}


def _record(
    tmp: Path,
    name: str,
    controller: dict[str, Any],
    amplitude: float,
    seed: int,
    plant: dict,
    gauge_deg: float = 0.0,
    ring_deg: float = 0.0,
    drive: dict | None = None,
    f: float = 0.1,
    phase: float = 0.0,
) -> Path:
    """One 10 s closed-loop record at 1 kHz with 2 mV of sensor noise, as a lab logs it: a CSV of the sensors'
    volts, the reference [deg] (a square wave of ``f`` [Hz] and ``phase`` [rad]: at 0.1 Hz and phase 0 one period
    with one step, down at 5 s; at phase -pi/2 a step up at 2.5 s and down at 7.5 s) and the command [V], the hub at
    its reference when it starts. ``gauge_deg``: the gauge's zero error, which the lab's controller acts on;
    ``ring_deg``: the link's deflection at the record's start."""
    raw = specmod.load("cu_flexible_arm").raw
    gauge_gain = specmod.fmu_value({}, "daq", "gauge_gain")
    raw["campaign"] = {**raw["campaign"], "seed": seed}
    raw["plant"] = {**raw["plant"], **(WRONG_DRIVE if drive is None else drive), **plant}
    raw["daq"] = {"noise_theta": 0.002, "noise_alpha": 0.002, "gauge_offset": gauge_deg / gauge_gain}
    raw["controller"] = {**controller, "cutoff": 25.0, "alpha_bias": gauge_deg}
    first = float(square(1, 1e-3, f, amplitude, phase=phase)[0])  # the reference's first level [deg]
    start = {"theta_start": math.radians(first), "alpha_start": math.radians(ring_deg)}
    raw["experiment"] = [
        {"name": name, "loop": "closed", "signal": "square", "f": f, "amplitude": amplitude, "phase": phase,
         "duration": 10.0, "plant": start}
    ]  # fmt: skip
    run_campaign(specmod.from_dict(raw, str(specmod.resolve_path("cu_flexible_arm"))), tmp / name, workers=1)
    d = pd.read_parquet(tmp / name / "data" / f"{name}.parquet")
    path = tmp / f"{name}.csv"
    d[["t", "theta_v", "alpha_v", "ref", "u"]].rename(columns={"theta_v": "theta", "alpha_v": "alpha"}).to_csv(
        path, index=False
    )
    return path


def _import_unit(tmp: Path, plant: dict[str, float], zero: bool = False, f: float = 0.1, **kw: Any) -> Path:
    files = [_record(tmp, *r, plant, f=f, **{k: v[i] for k, v in kw.items()}) for i, r in enumerate(RECORDS)]
    import_records(files, tmp / "unit", ImportOptions(units={"theta": "V", "alpha": "V", "ref": "deg"},
                                                      zero_alpha=zero))  # fmt: skip
    return tmp / "unit"


def _diagnose_unit(tmp: Path, plant: dict[str, float], f: float = 0.1) -> Diagnosis:
    return diagnose_run(_import_unit(tmp, plant, f=f), "cu_flexible_arm", tmp / "diag", workers=1)


def _diagnose_friction_and_limit(path: Path) -> None:
    path.mkdir()
    _diagnose_unit(path, {**FRICTION, "coulomb_torque": 0.02, "amp_limit": 1.5}, f=0.2)


@pytest.fixture(scope="session")
def friction_and_limit(tmp_path_factory) -> tuple[Path, Diagnosis]:
    """The unit with friction (0.02 N m) and an amplifier limit (1.5 V) beside the drive off by 2x, each record two
    periods of its reference (0.2 Hz): its imported run (copy it to write into it) and its diagnosis, made once for
    the test processes that read them."""
    path = shared_dir(tmp_path_factory, "friction_and_limit", _diagnose_friction_and_limit)
    return path / "unit", Diagnosis.load(path / "diag")


def _misses_allowed(n: int, coverage: float = 0.95, level: float = 0.02) -> int:
    """The fewest misses k of ``n`` bands of ``coverage`` that a right model exceeds with probability below
    ``level`` (the binomial tail): 1 of 4 at 95 % (more: 1.4 %)."""
    miss = 1.0 - coverage
    k = 0
    while sum(math.comb(n, j) * miss**j * coverage ** (n - j) for j in range(k + 1, n + 1)) >= level:
        k += 1
    return k


def _held_out_fits(d: Diagnosis) -> tuple[float, float]:
    """The held-out fit [%] recalibrated alone and with the effects."""
    dec = d.gap.decomposition
    return 100.0 * (1.0 - dec.after_recalibration), 100.0 * (1.0 - dec.after_effects)


def test_friction_beside_a_drive_off_by_twice_is_found_by_refitting_every_candidate_jointly(tmp_path):
    """Hub friction (0.03 N m, breakaway 1.3x, Stribeck 0.02 rad/s): the linear model alone fits the held-out
    records worse than the sheet (each record pulls the drive its own way), and each effect alone on a rig that far
    off shows nothing; refitted jointly with the linear parameters, friction closes the gap: the drive gain and Ks
    within 2 % and 1 % of the truth, the torque within 5 %."""
    d = _diagnose_unit(tmp_path, FRICTION)
    assert d.verdict == "coulomb_friction"
    assert d.fitted_effect_params()["plant.coulomb_torque"] == pytest.approx(0.03, rel=0.05)
    assert d.parameters["rig.drive_gain"].fitted == pytest.approx(DRIVE_GAIN, rel=0.02)
    assert d.parameters["plant.Ks"].fitted == pytest.approx(1.79584, rel=0.01)
    recalibrated, with_effects = _held_out_fits(d)
    assert recalibrated < 50.0 and with_effects > 97.0


def test_a_limit_one_record_hardly_reaches_is_fitted_from_the_other_folds_start(tmp_path):
    """An amplifier limit of 1.0 V: the P-only record's command reaches -1.2 V, the other's -3.6 V. Fitted on the
    P-only record alone the limit has nothing to move it; refitted from the other fold's fit, which costs it less, it
    is found: within 3 %, the held-out fit above 97 %."""
    d = _diagnose_unit(tmp_path, {"amp_limit": 1.0})
    assert d.verdict == "saturation"
    assert d.fitted_effect_params()["plant.amp_limit"] == pytest.approx(1.0, rel=0.03)
    assert d.parameters["rig.drive_gain"].fitted == pytest.approx(DRIVE_GAIN, rel=0.03)
    recalibrated, with_effects = _held_out_fits(d)
    assert recalibrated < 50.0 and with_effects > 97.0


@pytest.mark.xdist_group("friction_and_limit")  # one test process makes the shared diagnosis
def test_a_limit_only_one_record_reaches_is_named_beside_friction(friction_and_limit):
    """Friction (0.02 N m) and an amplifier limit (1.5 V) that only the P + tip record reaches, beside the drive off
    by 2x: the limit is named and sized within 5 %; each effect's held-out fits record by record are its gaps."""
    _, d = friction_and_limit
    assert "saturation" in d.effect_names
    assert d.fitted_effect_params()["plant.amp_limit"] == pytest.approx(1.5, rel=0.05)
    for e in d.effects:  # each record's held-out fit before and after: the same gaps, record by record
        fits = e.held_out_fit_pct or {}
        assert sorted(fits) == ["p_only", "p_tip"]
        for k, gap in ((0, e.gap_before), (1, e.gap_after)):
            assert math.sqrt(np.mean([(1.0 - f[k] / 100.0) ** 2 for f in fits.values()])) == pytest.approx(gap)


@pytest.mark.xdist_group("friction_and_limit")  # one test process makes the shared diagnosis
def test_two_effects_that_each_close_little_alone_are_refitted_together(friction_and_limit):
    """Friction (0.02 N m) and an amplifier limit (1.5 V) beside the drive off by 2x, in records that each repeat
    their reference and are split between the folds: both are found, within 2 % and 5 %, the drive gain within 2 %,
    the held-out fit within a point of what a right model leaves (98.9 against 99.0 %; with records of one period
    each, held out whole, the limit was undetermined on the P-only record's fold and friction was found or lost by
    rounding)."""
    _, d = friction_and_limit
    assert {e.effect for e in d.effects} == {"coulomb_friction", "saturation"}
    fitted = d.fitted_effect_params()
    assert fitted["plant.amp_limit"] == pytest.approx(1.5, rel=0.02)
    assert fitted["plant.coulomb_torque"] == pytest.approx(0.02, rel=0.05)
    assert d.parameters["rig.drive_gain"].fitted == pytest.approx(DRIVE_GAIN, rel=0.02)
    _, with_effects = _held_out_fits(d)
    assert with_effects > 100.0 * (1.0 - d.gap.decomposition.noise_floor) - 1.0
    friction = next(e for e in d.effects if e.effect == "coulomb_friction").held_out_fit_pct or {}
    assert all(after > before for before, after in friction.values())  # the hub sticks in both records


def test_a_unit_logged_as_labs_log_it_gives_back_its_sensors_and_its_behaviour(tmp_path):
    """The friction unit with what real records carry: gauges reading 3 and -1.5 deg at rest (which the lab's
    controller acts on), links still ringing 1.0 and 0.6 deg when the records start, an amplifier offset of -0.12 V,
    a link damped at 0.004, imported with --zero-alpha (which zeroes each record on its quietest stretch). Before the
    sensors were fitted: 32.1 -> 6.7 -> 60.2 % held out (its gauge zeroed on a point of the swing, the offset and the
    ring unmodelled). Now each record's gauge offset comes back within 0.01 deg of the truth in the record's own zero,
    each link's start within 0.05 deg, the offset within 0.005 V, the damping within 10 %, the friction within 5 %,
    and the record's stopping errors and ringing lie inside the replays' bands as a right model's do."""
    gauges, rings = (3.0, -1.5), (1.0, 0.6)
    plant = {**FRICTION, "zeta_link": 0.004, "u_offset": -0.12}
    run = _import_unit(tmp_path, plant, zero=True, gauge_deg=gauges, ring_deg=rings)
    d = diagnose_run(run, "cu_flexible_arm", tmp_path / "diag", workers=1)
    assert d.verdict == "coulomb_friction" and [e.effect for e in d.effects] == ["coulomb_friction"]
    assert d.fitted_effect_params()["plant.coulomb_torque"] == pytest.approx(0.03, rel=0.05)
    over = d.rig.overrides
    entries = {e.name: e for e in Manifest.load(run).experiments}
    for (name, *_), gauge, ring in zip(RECORDS, gauges, rings, strict=True):
        zero = float(entries[name].controller["alpha_bias"])  # what --zero-alpha took off the record
        assert over[offset_key(name)] == pytest.approx(gauge - zero, abs=0.01), name
        assert over[link_keys(name)[0]] == pytest.approx(ring, abs=0.05), name
        assert d.sensors[name].gauge_offset_deg[0] == pytest.approx(over[offset_key(name)])
    assert over["plant.u_offset"] == pytest.approx(-0.12, abs=0.005)
    assert d.parameters["plant.zeta_link"].fitted == pytest.approx(0.004, rel=0.1)
    # one replay of a loop that sticks and slips, held out: where it sticks moves with rounding (94.3-98.7 % over
    # perturbation draws at 1e-12 and both integrations of the RK4 step), against 60.2 % before the sensors
    assert _held_out_fits(d)[1] > 93.0
    # each 95 % band holds a right model's metric with probability 0.95, so not all N of them together (0.95^N):
    # no more misses than a right model exceeds with probability 2 %, each by less than half its band's width
    bands = [(name, step.start_s, m, step.metrics[m]) for name, rb in d.behaviour.items() for step in rb.steps
             for m in ("stop_error_deg", "ring_alpha_deg") if math.isfinite(step.metrics[m].lo)]  # fmt: skip
    missed = [(*where, b) for *where, b in bands if not b.inside]
    assert len(bands) == 4 and len(missed) <= _misses_allowed(len(bands)), missed  # two records, a step each
    assert all(min(abs(b.measured - b.lo), abs(b.measured - b.hi)) < 0.5 * (b.hi - b.lo) for *_, b in missed), missed


def test_a_loop_that_hunts_is_friction_not_a_play(tmp_path):
    """A P + tip loop with a stiff proportional gain (15 V/rad) on a hub with breakaway friction (0.04 N m, 1.5x,
    Stribeck 0.02 rad/s) and a link damped at 0.004, stepped up at 2.5 s and down at 7.5 s: after each step the hub
    creeps to its reference in jumps while the link swings (stick-slip where the noise decides), which no replay
    follows sample by sample (a right model's replay against another noise draw of itself fits 28 %). Scored against
    the spread its own noise sets, friction explains it and is sized within 10 % (campaign seeds 21-24: 0.0398-0.0406
    N m, held out 98.9-99.2 % against floors of 97.9-99.2 %); a gear's play is not chosen. Logged with one step (down
    at 5 s), the cut puts it in one fold, and a caveat says so (test_honest_output)."""
    controller = {"kind": "state_feedback", "K": [15.0, 2.0, 0.0, 0.0]}
    plant = {"coulomb_torque": 0.04, "stiction_ratio": 1.5, "stribeck_speed": 0.02, "zeta_link": 0.004}
    f = _record(
        tmp_path, "hunt", controller, 10.0, 21, plant, gauge_deg=2.0, ring_deg=0.8, drive={}, phase=-math.pi / 2
    )
    th = read_dataset(tmp_path / "hunt" / "data" / "hunt.parquet")["theta"].to_numpy()
    for step in (th[2500:6500], th[7500:10000]):
        moving = (np.abs(np.diff(step)) / 1e-3 > 0.5).astype(int)
        assert np.count_nonzero(np.diff(moving) == 1) >= 3  # it hunts: several bursts of motion after each step
    import_records([f], tmp_path / "unit", ImportOptions(units={"theta": "V", "alpha": "V", "ref": "deg"}))
    d = diagnose_run(tmp_path / "unit", "cu_flexible_arm", tmp_path / "diag", workers=1)
    assert d.verdict == "coulomb_friction" and "backlash" not in d.effect_names, (d.verdict, d.effect_names)
    assert d.fitted_effect_params()["plant.coulomb_torque"] == pytest.approx(0.04, rel=0.1)
    dec = d.gap.decomposition
    assert dec.after_effects <= dec.noise_floor + 0.02  # within 2 points of what a right model leaves
    assert not [c for c in d.caveats or [] if "holds no step" in c]


@pytest.mark.xdist_group("friction_and_limit")  # one test process makes the shared diagnosis
@pytest.mark.parametrize("draw", [1, 12])
def test_the_same_records_perturbed_at_1e_12_give_the_same_verdict(friction_and_limit, tmp_path, draw):
    """Rounding another CPU's BLAS does differently must not flip a verdict: the friction-and-limit unit's records
    perturbed by a relative 1e-12 give the same verdict and effects (the order they entered in may differ: the
    search's path, a single and then another, or the two as a pair), and every fitted parameter inside the first
    diagnosis's 95 % interval."""
    shared, first = friction_and_limit
    run = perturbed_copy(shared, tmp_path / "unit", draw)
    again = diagnose_run(run, "cu_flexible_arm", tmp_path / "again", workers=1, force=True)
    assert again.verdict == first.verdict and sorted(again.effect_names) == sorted(first.effect_names)
    assert again.importance_pct() == pytest.approx(first.importance_pct(), abs=1.0)  # the rig's, not a basin of a fold
    for name, p in first.parameters.items():
        lo, hi = p.ci95
        if math.isfinite(lo) and math.isfinite(hi):
            assert lo <= again.parameters[name].fitted <= hi, name
