"""Honest output on real data (issue 16, item 6): a parameter at its search bound or not identifiable is said so
and caveats the verdict; a lone record is split in time so that its held-out figures are held out; a record's own
quantization step is in the noise floor; what recalibration alone fitted is shown beside the joint fit; how each
experiment was replayed is in diagnosis.json and the report."""

from __future__ import annotations

import copy
import math
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
from shared_runs import REAL
from test_diagnosis_result import minimal_doc

from harness import spec as specmod
from harness.diagnosis import blindtest as bt
from harness.diagnosis import diagnose as dg
from harness.diagnosis import experiments as ex
from harness.diagnosis import recalibrate as recal
from harness.diagnosis.diagnose import diagnose_run
from harness.diagnosis.experiments import RigExperiment, load_experiments
from harness.diagnosis.noise import noise_floor, value_step
from harness.diagnosis.result import Diagnosis, FittedParameter
from harness.diagnosis.search import combine
from harness.ident.calibration import load_calibration
from harness.render.gap_text import diagnosis_markdown
from harness.rig import records
from harness.rig.campaign import run_campaign
from harness.rig.records import ImportOptions, import_records
from harness.rundir import DataError, write_json

RATIO = 0.5468  # a hub-to-link inertia ratio to scale from (the Quanser datasheet's)


# ----------------------------------------------------------------------------------------------- bounds, intervals


def test_a_parameter_at_its_bound_is_flagged_and_said_in_words():
    """The walls are far (a factor 20 on the drive's combos): a fit that ends there says the spec does not describe
    the rig."""
    assert recal.at_bound("rig.inertia_ratio", RATIO, 20 * RATIO) == "upper"
    assert recal.at_bound("rig.inertia_ratio", RATIO, 19.8 * RATIO) == "upper"  # within 2 % (in log) of the bound
    assert recal.at_bound("rig.inertia_ratio", RATIO, 15 * RATIO) is None
    assert recal.at_bound("rig.drive_gain", 1.758, 0.05 * 1.758) == "lower"
    assert recal.at_bound("plant.backlash", 0.0, 0.006) is None  # not a linear parameter
    text = recal.finding("rig.inertia_ratio", RATIO, 20 * RATIO, (15 * RATIO, 25 * RATIO))
    assert text == (
        "hub-to-link inertia ratio at its upper bound (20x the spec: 0.5468 -> 10.94): the spec may not describe this "
        "rig"
    )


def test_an_interval_over_orders_of_magnitude_is_not_identifiable():
    """Today's `link damping ratio matches the spec (0.01, fitted 0.002) (95 % interval 1.854e-08..215.7)`."""
    ci = (1.854e-08, 215.7)
    assert not recal.identifiable(ci) and not recal.identifiable((0.0, 0.1))
    assert recal.identifiable((0.009, 0.011)) and recal.identifiable((0.001, 0.0999))
    text = recal.finding("plant.zeta_link", 0.01, 0.012, ci)
    assert "matches" not in text
    assert text == (
        "link damping ratio is not identifiable from these data (fitted 0.012, 95 % interval 1.85e-08..216; spec 0.01)"
    )
    # at its lower bound (0.05x): said as a bound, and still flagged unidentifiable
    assert recal.finding("plant.zeta_link", 0.01, 5e-4, ci).startswith("link damping ratio at its lower bound (0.05x")
    row = FittedParameter(0.01, 0.012, list(ci), 20.0, "1", text, identifiable=False)
    assert not row.off_spec  # not a finding that the rig differs from the spec
    # a prior: an interval about as wide as the prior's (damping, a factor 3 on every sheet) is said to be the prior's
    sd = math.log(3.0) / 1.96
    held = recal.finding("plant.zeta_link", 0.01, 0.011, (0.00345, 0.031), sd)
    assert held == (
        "link damping ratio is not determined by these data: it stays near the spec's 0.01 within its prior (fitted "
        "0.011, 95 % interval 0.00345..0.031)"
    )
    assert recal.finding("plant.zeta_link", 0.01, 0.02, (0.018, 0.022), sd) == (
        "link damping ratio is 100 % higher than the spec (0.01 -> 0.02)"
    )


def test_a_verdict_reached_at_a_bound_carries_caveats():
    words = recal.finding("rig.inertia_ratio", RATIO, 20 * RATIO, (15 * RATIO, 25 * RATIO))
    ratio = FittedParameter(RATIO, 20 * RATIO, [15 * RATIO, 25 * RATIO], 1900.0, "1", words, at_bound="upper")
    words = recal.finding("plant.zeta_link", 0.01, 0.012, (1e-6, 1.0))
    zeta = FittedParameter(0.01, 0.012, [1e-6, 1.0], 20.0, "1", words, identifiable=False)
    ks = FittedParameter(1.3, 1.31, [1.28, 1.34], 0.8, "N m/rad", recal.finding("plant.Ks", 1.3, 1.31, (1.28, 1.34)))
    caveats = dg._caveats({"rig.inertia_ratio": ratio, "plant.zeta_link": zeta, "plant.Ks": ks}, "coulomb_friction")
    assert caveats == [
        f"the spec's {recal.DRIVE} does not describe this rig: hub-to-link inertia ratio (20x the spec, upper) ends at "
        "its search bound; measure it before trusting an effect's share of the gap",
        "verdict 'coulomb_friction' reached with hub-to-link inertia ratio at its upper bound (20x the spec: 0.5468 -> "
        "10.94): the spec may not describe this rig",
        "link damping ratio is not identifiable from these data (fitted 0.012, 95 % interval 1e-06..1; spec 0.01)",
    ]
    assert dg._caveats({"plant.Ks": ks}, "none") is None  # nothing limits it: the key is left out


def test_which_part_of_the_spec_is_wrong_is_said_once_per_part():
    """A rig whose drive the sheet gets wrong beyond the walls (two drive combos at their bounds, the link fine): one
    sentence names the drive and its two parameters; a link at its bound gets its own."""
    rows = {"rig.drive_tau": (0.189, 3.78), "rig.inertia_ratio": (0.141, 2.82), "plant.Ks": (2.2448, 2.3),
            "plant.zeta_link": (0.01, 0.05)}  # fmt: skip
    assert recal.parts_at_bound(rows) == [
        f"the spec's {recal.DRIVE} does not describe this rig: drive time constant (20x the spec, upper) and "
        "hub-to-link inertia ratio (20x the spec, upper) end at their search bounds; measure them before trusting an "
        "effect's share of the gap"
    ]
    rows["plant.Ks"] = (1.3, 0.13)
    assert recal.parts_at_bound(rows)[1] == (
        f"the spec's {recal.LINK} does not describe this rig: link stiffness (0.1x the spec, lower) ends at its search "
        "bound; measure it before trusting an effect's share of the gap"
    )
    assert recal.parts_at_bound({"plant.Ks": (1.3, 1.5)}) == []


# ----------------------------------------------------------------------------------------------- a lone record


def _record(seconds: float, rate: float = 1000.0, quiet: tuple[float, float] | None = None) -> RigExperiment:
    """A closed-loop-like record: theta and alpha move everywhere but in ``quiet`` [s] (held still there)."""
    Ts = 1.0 / rate
    t = np.arange(int(round(seconds * rate))) * Ts
    theta = 20.0 * np.sin(2 * np.pi * 0.7 * t) + 3.0 * np.sin(2 * np.pi * 3.1 * t)
    alpha = 2.0 * np.sin(2 * np.pi * 3.1 * t + 0.4)
    if quiet is not None:
        i, j = np.searchsorted(t, quiet)
        theta[i:j], alpha[i:j] = theta[i], 0.0
    ref = np.where(np.sin(2 * np.pi * 0.2 * t) >= 0, 30.0, -30.0)
    x = RigExperiment(name="square", kind="imported", Ts=Ts, t=t, u=0.1 * theta, theta=theta, alpha=alpha,
                      theta_v=theta / 35.5, alpha_v=alpha / -3.36, ref=ref, controller={"kind": "state_feedback"},
                      replay="closed", replay_reason="a closed-loop record with its controller (identified, R^2 0.98)",
                      encoder=True, lattice_deg={"theta": 0.0573})  # fmt: skip
    x.valid["theta"][100:120] = False
    return x


def test_a_lone_record_is_split_in_time_at_a_quiet_point():
    x = _record(10.0, quiet=(5.45, 5.55))
    m = ex.split_point(x)
    assert 5450 <= m <= 5550  # inside the only still stretch of the middle fifth
    experiments, folds = ex.fold_experiments({"square": x})
    names = [f"square (0-{m / 1000:.4g} s)", f"square ({m / 1000:.4g}-10 s)"]
    assert list(experiments) == names
    assert (folds.A, folds.B) == ([names[0]], [names[1]])  # each half held out by a fit on the other
    assert folds.scheme.endswith(
        f"the lone record 'square' split in time at {m / 1000:.4g} s into two halves, one per fold"
    )
    first, second = experiments.values()
    assert (first.u.size, second.u.size) == (m, 10000 - m)
    for k in ("t", "u", "theta", "alpha", "theta_v", "alpha_v", "ref"):  # every array sliced alike
        np.testing.assert_array_equal(np.r_[getattr(first, k), getattr(second, k)], getattr(x, k))
    np.testing.assert_array_equal(np.r_[first.valid["theta"], second.valid["theta"]], x.valid["theta"])
    assert int(np.sum(~first.valid["theta"])) == 20 and second.valid["alpha"].all()
    for h in (first, second):
        assert (h.replay, h.controller, h.encoder, h.lattice_deg) == ("closed", x.controller, True, x.lattice_deg)
        assert h.sst["theta"] == pytest.approx(float(np.sum((h.theta - h.theta.mean()) ** 2)))
        assert h.n_fit == h.u.size  # shorter than FIT_SECONDS: the whole half is fitted
    assert second.theta[0] == x.theta[m] and second.t[0] == pytest.approx(m / 1000)
    assert dg._replays(experiments) == {n: {"replay": "closed", "reason": x.replay_reason} for n in names}
    plain = RigExperiment(name="prbs", kind="prbs", Ts=0.02, t=x.t[:500], u=x.u[:500], theta=x.theta[:500],
                          alpha=x.alpha[:500], theta_v=x.theta_v[:500], alpha_v=x.alpha_v[:500])  # fmt: skip
    assert dg._replays({"prbs": plain}) == {
        "prbs": {"replay": "open", "reason": "an open-loop experiment: its command replayed as logged"}
    }


def test_the_split_point_stays_in_the_middle_and_keeps_whole_periods():
    moving = _record(10.0)
    assert 4000 <= ex.split_point(moving) <= 6000
    assert ex.split_point(_record(10.0, quiet=(1.0, 2.0))) != 1500  # not outside the middle fifth
    periodic = _record(10.0)
    periodic.period = 800  # 12.5 periods: the whole number nearest the middle is 6 x 800
    halves, m = ex.halves(periodic)
    assert m == 4800 and [h.period for h in halves.values()] == [800, 800]
    assert ex.split_point(_record(2.0)) == 1000  # the shortest record import allows: cut in the middle


def test_a_record_too_short_for_two_folds_is_one_line():
    assert records.MIN_RECORD_SECONDS == 2 * ex.MIN_FOLD_SECONDS  # import refuses what cannot be split
    with pytest.raises(DataError, match="too short for two folds") as err:
        ex.fold_experiments({"square": _record(1.5)})
    assert "\n" not in str(err.value) and "1500 samples (1.5 s)" in str(err.value)
    with pytest.raises(DataError, match="2000 samples"):
        ex.split_point(_record(1.999))
    many = {"a": _record(1.5), "b": _record(1.5)}  # two experiments: the folds are the experiments, none is cut
    experiments, folds = ex.fold_experiments(many)
    assert experiments is many and (folds.A, folds.B) == (["a"], ["b"])


def _square_loop(seconds: float, f_ref: float, rate: float = 1000.0) -> RigExperiment:
    """A closed-loop record of a square reference at ``f_ref`` [Hz] (+-30 deg): the shaft follows each step with a
    damped swing of the link and is still before the next."""
    Ts = 1.0 / rate
    t = np.arange(int(round(seconds * rate))) * Ts
    ref = np.where(np.sin(2 * np.pi * f_ref * t + 1e-9) >= 0, 30.0, -30.0)
    since = t - np.floor(2 * f_ref * t) / (2 * f_ref)  # time since the last step [s]
    theta = ref - np.sign(ref) * 60.0 * np.exp(-since / 0.05) * (t >= 1 / (2 * f_ref))
    alpha = 4.0 * np.exp(-since / 0.08) * np.sin(2 * np.pi * 6.0 * since) * np.sign(ref)
    return RigExperiment(name="loop", kind="imported", Ts=Ts, t=t, u=0.2 * (ref - theta), theta=theta, alpha=alpha,
                         theta_v=theta / 35.5, alpha_v=alpha / -3.36, ref=ref, controller={"kind": "state_feedback"},
                         replay="closed", replay_reason="a closed-loop record with its controller (spec)")  # fmt: skip


def test_a_fold_without_a_step_of_the_reference_is_a_caveat():
    """A lone 10 s record of a 0.1 Hz square that starts at its reference holds one step, down at 5 s; the cut
    before it leaves fold A none, and a caveat says that fold A's fit is scored on a step response it never saw. At
    0.2 Hz both folds hold steps (1 and 2): no caveat."""
    one, two = _square_loop(10.0, 0.1), _square_loop(10.0, 0.2)
    experiments, folds = ex.fold_experiments({"loop": one})
    assert ex.fold_steps(experiments, folds) == (0, 1)
    (caveat,) = dg._caveats({}, "unexplained", folds, steps=ex.fold_steps(experiments, folds)) or []
    assert caveat.startswith(f"fold A ({folds.A[0]}) holds no step of its reference, fold B 1: the fit on fold A")
    experiments, folds = ex.fold_experiments({"loop": two})
    assert ex.fold_steps(experiments, folds) == (1, 2)
    assert dg._caveats({}, "unexplained", folds, steps=ex.fold_steps(experiments, folds)) is None


def test_records_that_repeat_their_reference_are_split_between_the_folds():
    """A unit of two closed-loop records that each hold two periods of their reference or more (8 s at 0.25 Hz, 6 s
    at 0.5 Hz) and one that does not (6 s at 0.1 Hz, one step): each of the first two cut at a quiet point into
    blocks that alternate between the folds, their first blocks in different folds, so that both folds hold both
    controllers' conditions; the third goes whole to one fold, and every sample is in one fold only."""
    a, b, one = (replace(_square_loop(s, f), name=n, record=n)
                 for s, f, n in ((8.0, 0.25, "p_only"), (6.0, 0.5, "p_tip"), (6.0, 0.1, "slow")))  # fmt: skip
    assert ex.repeats(a) and ex.repeats(b) and not ex.repeats(one)
    experiments, folds = ex.fold_experiments({"p_only": a, "p_tip": b, "slow": one})
    names = list(experiments)
    assert names[-1] == "slow" and experiments["slow"] is one
    by_record = {r: [n for n in names if experiments[n].record == r] for r in ("p_only", "p_tip")}
    assert [len(v) for v in by_record.values()] == [2, 2]
    (a0, a1), (b0, b1) = by_record.values()
    assert set(folds.A) | set(folds.B) == set(names) and not set(folds.A) & set(folds.B)
    assert {a0, b1} <= set(folds.A) and {a1, b0} <= set(folds.B)  # each record in both folds, starts apart
    for r, x in (("p_only", a), ("p_tip", b)):
        parts = [experiments[n] for n in by_record[r]]
        np.testing.assert_array_equal(np.concatenate([p.theta for p in parts]), x.theta)
        cut = parts[0].u.size
        assert abs(x.theta[cut] - x.ref[cut]) < 0.1 and abs(x.alpha[cut]) < 0.1  # still there
        assert min(p.u.size for p in parts) >= ex.SPLIT_ZONE[0] * x.u.size  # near its middle
    assert "('p_only', 'p_tip') each cut in time" in folds.scheme


def test_a_lone_closed_loop_record_is_cut_into_blocks_that_alternate_between_the_folds():
    """12 s of a 1 Hz square reference: 6 blocks (the most, MAX_BLOCKS) of at least one reference period, cut
    where the shaft is still, 1st, 3rd, ... in fold A, 2nd, 4th, ... in fold B; each block a closed-loop replay that
    starts at rest at the measured angle."""
    x = _square_loop(12.0, 1.0)
    assert ex.shown_period(x) == 1000 and ex.block_length(x) == 1000 and ex.block_count(x) == ex.MAX_BLOCKS == 6
    experiments, folds = ex.fold_experiments({"loop": x})
    parts = list(experiments.values())
    names = list(experiments)
    assert len(parts) == 6 and (folds.A, folds.B) == (names[0::2], names[1::2])
    sizes = [p.u.size for p in parts]
    assert sum(sizes) == x.u.size and min(sizes) >= 1000 and max(sizes) <= 2800  # 2 s +- 20 % of 2 s either end
    edges = np.cumsum([0, *sizes])
    for k, cut in enumerate(edges[1:-1], start=1):
        assert abs(cut - 2000 * k) <= 400, (k, cut)
        assert abs(x.theta[cut] - x.ref[cut]) < 0.1 and abs(x.alpha[cut]) < 0.1, (k, cut)  # still there
    for k in ("t", "u", "theta", "alpha", "ref"):
        np.testing.assert_array_equal(np.concatenate([getattr(p, k) for p in parts]), getattr(x, k))
    assert names[1] == f"loop ({edges[1] / 1000:.4g}-{edges[2] / 1000:.4g} s)"
    assert all(p.plant == {} and p.replay == "closed" for p in parts)  # at rest at the measured angle
    lengths = np.diff(edges) / 1000
    assert folds.scheme == (
        "2-fold cross-fit: fit on A score on B, and back; the lone record 'loop' cut in time at quiet points into 6 "
        f"blocks of {lengths.min():.3g}-{lengths.max():.3g} s, alternating between the folds (A the 1st, 3rd, ...; B "
        "the 2nd, 4th, ...)"
    )
    # 3 s: three periods hold no four blocks of one period each: two halves, as before
    short, _ = ex.fold_experiments({"loop": _square_loop(3.0, 1.0)})
    assert len(short) == 2
    # a periodic command (a shooting replay) is cut at whole periods, its periods shared out evenly
    shot = replace(x, replay="shooting", period=1000)
    assert ex.block_cuts(shot, 8) == [2000, 3000, 4000, 6000, 8000, 9000, 10000]  # 12 periods in 8 blocks


def test_a_lone_open_loop_record_stays_in_halves_and_its_second_half_starts_from_the_measured_state():
    """An open-loop replay is not pulled back to the record: its second half starts from the rig's measured state
    (angle, deflection and their rates), not from rest, and the record is cut once (each cut adds a start transient
    of what the record does not measure)."""
    x = replace(_record(10.0), replay="open", ref=None, controller=None)
    x.period = 0
    assert ex.block_count(x) == 2
    parts, folds = ex.fold_experiments({"square": x})
    first, second = parts.values()
    m = first.u.size
    state = ex.measured_state(x)[m]
    assert first.measured_start is None and second.measured_start == pytest.approx(
        {
            "theta_start": math.radians(x.theta[m]),
            "alpha_start": math.radians(x.alpha[m]),
            "theta_dot_start": state[2],
            "alpha_dot_start": state[3],
        }  # fmt: skip
    )
    assert second.start_state == second.measured_start and first.plant == second.plant == {}
    assert abs(second.start_state["theta_dot_start"]) > 0.1  # [rad/s]: the shaft moves there


def test_a_lone_open_loop_record_cut_at_a_command_step_is_replayed_from_where_the_rig_was(tmp_path):
    """The lab twin with a 0.004 rad gear play, its 0.3 Hz square alone (60 s, open loop), cut in two at a whole
    period: where the command steps and the hub runs at full speed. Its second half replayed from rest at the
    measured angle fitted alpha 87.6 % (the first 97.3 %), held out 93.65 % as given, and the play closed 9.9 %;
    replayed from the measured state, 93.8 %, 96.59 %, and the play closes 24 % (32 % before each model was judged
    against its own floor and a play was refitted in an open loop), under the 25 % it would enter with, sized 0.004
    within 20 % (the second mode and the friction's state at the cut are not measured)."""
    spec = specmod.load("lab", ["plant.backlash=0.004"])
    alone = [e for e in spec.raw["experiment"] if e["name"] == "square_030"]
    run_campaign(specmod.from_dict({**spec.raw, "experiment": alone}, spec.path), tmp_path / "run", workers=1)
    d = diagnose_run(tmp_path / "run", "lab", tmp_path / "out", workers=1)
    assert d.folds.scheme.endswith("the lone record 'square_030' split in time at 30 s into two halves, one per fold")
    first, second = (d.gap.before.experiments[n].fit_pct["alpha"] for n in (*d.folds.A, *d.folds.B))
    assert first > 97.0 and second > 93.0, (first, second)
    assert 100 * (1 - d.gap.decomposition.before) > 96.0
    (play,) = [c for c in d.rounds[0] if c["effect"] == "backlash"]
    assert play["held_out_share_pct"] > 20.0, play
    assert play["params"]["plant.backlash"] == pytest.approx(0.004, rel=0.2)  # under min_gain: a candidate only


def test_the_period_a_record_shows_is_found_through_a_lead_in_and_jitter():
    """The Quanser reference: +-30 deg steps every 379 samples after 0.2 s at 0 (its period 758 samples, found to a
    sample); white noise and a PRBS-like signal show none. The Quanser record (5 s, 3.3 periods) stays in halves."""
    ref = pd.read_csv(REAL / "rfl_lqr_sqwave_pm30deg_500Hz_aux.csv")["theta_ref_deg"].to_numpy()
    assert abs(ex.signal_period(ref) - 758) <= 1 and ref.size // ex.signal_period(ref) < 4
    rng = np.random.default_rng(3)
    assert ex.signal_period(rng.standard_normal(5000)) == 0
    assert ex.signal_period(np.repeat(rng.choice([-1.0, 1.0], 500), 10)) == 0


def test_records_at_different_rates_are_refused_before_anything_is_written(tmp_path):
    """A record at 500 Hz and one at 1 kHz imported into one run: the diagnosis says so in one line naming both,
    and writes nothing."""
    paths = []
    for name, rate in (("slow", 500.0), ("fast", 1000.0)):
        t = np.arange(int(2.5 * rate)) / rate
        u = np.sin(2 * np.pi * 0.8 * t)
        rec = pd.DataFrame({"t": t, "u": u, "theta": 20.0 * np.sin(2 * np.pi * 0.8 * t - 0.5),
                            "alpha": 1.5 * np.sin(2 * np.pi * 0.8 * t + 0.3)})  # fmt: skip
        paths.append(tmp_path / f"{name}.csv")
        rec.to_csv(paths[-1], index=False)
    run = tmp_path / "run"
    import_records(paths, run, ImportOptions(units={"theta": "deg", "alpha": "deg"}))
    before = sorted(p.relative_to(run) for p in run.rglob("*"))
    with pytest.raises(DataError) as err:
        dg.diagnose_run(run, "nominal", workers=1)
    assert str(err.value) == (
        "records at different sample rates ('slow' at 500 Hz; 'fast' at 1000 Hz): the diagnosis replays every "
        "record on one rig at one rate; import and diagnose each rate's records as a run of its own"
    )
    assert sorted(p.relative_to(run) for p in run.rglob("*")) == before and not (run / "diagnosis.json").exists()
    with pytest.raises(DataError, match="different sample rates"):
        dg.diagnose_run(run, "nominal", tmp_path / "out", workers=1)
    assert not (tmp_path / "out").exists()


# ----------------------------------------------------------------------------------------------- quantized record


def test_a_record_on_0_001_rad_steps_has_its_step_in_the_noise_floor(tmp_path):
    """Third differences of a slow angle printed to 0.001 rad are mostly zero (its MAD is 0): its floor is the
    step's, step / sqrt(12)."""
    t = np.arange(5000) * 1e-3
    theta = 0.3 * np.sin(2 * np.pi * 0.05 * t)  # a step every >= 10 samples: most third differences are 0
    alpha = 1.5 * np.sin(2 * np.pi * 0.2 * t + 0.3)
    rec = pd.DataFrame({"t": t, "u": np.sin(2 * np.pi * 0.2 * t), "theta": theta, "alpha": alpha})
    path = tmp_path / "slow.csv"
    rec.assign(theta=rec["theta"].map(lambda v: f"{v:.3f}")).to_csv(path, index=False)
    import_records([path], tmp_path / "run", ImportOptions(units={"theta": "rad", "alpha": "deg"}))
    run = tmp_path / "run"
    cal = load_calibration(run)
    exps = load_experiments(run, cal, specmod.load("nominal"), 10.0)
    step = math.degrees(0.001)
    assert exps["slow"].lattice_deg["theta"] == pytest.approx(step)
    floor, e_noise = noise_floor(exps, 10.0, cal)
    assert floor.estimated_deg["theta"] == 0.0  # the estimate alone: nothing, a fit of 100 %
    assert floor.theta_deg == pytest.approx(step / math.sqrt(12.0), rel=0.10)
    assert e_noise > 0 and floor.fit_pct < 100.0 and "step^2 / 12" in floor.method
    # gap scored on the halves the diagnosis fits, the noise estimated on the whole record
    halves, _ = ex.halves(exps["slow"])
    same, e_halves = noise_floor(exps, 10.0, cal, halves)
    assert same.theta_deg == floor.theta_deg and same.sources == ["slow"]
    sigma = {"theta": floor.theta_deg, "alpha": floor.alpha_deg}
    q = [h.u.size * sigma[c] ** 2 / float(np.sum((y - y.mean()) ** 2))
         for h in halves.values() for c, y in (("theta", h.theta), ("alpha", h.alpha))]  # fmt: skip
    assert e_halves == pytest.approx(float(np.mean(q)), rel=1e-12)


def test_a_lattice_converted_between_units_is_found_from_the_values(tmp_path):
    """Angles taken on 0.001 rad steps and written in degrees (0.057296, 0.114592, ...: no round last decimal) sit
    on a lattice all the same: its step is the common step of the values, and the noise floor holds its step^2/12
    (read from the printed decimals, the step was 1e-6 deg and the floor a fit of 100.00 %)."""
    t = np.arange(5000) * 1e-3
    theta = np.round(0.3 * np.sin(2 * np.pi * 0.05 * t), 3)  # rad, on 0.001 rad steps
    alpha = 1.5 * np.sin(2 * np.pi * 0.2 * t + 0.3)
    rec = pd.DataFrame({"t": t, "u": np.sin(2 * np.pi * 0.2 * t), "theta": np.degrees(theta), "alpha": alpha})
    path = tmp_path / "deg.csv"
    rec.assign(theta=rec["theta"].map(lambda v: f"{v:.6f}")).to_csv(path, index=False)
    import_records([path], tmp_path / "run", ImportOptions(units={"theta": "deg", "alpha": "deg"}))
    cal = load_calibration(tmp_path / "run")
    exps = load_experiments(tmp_path / "run", cal, specmod.load("nominal"), 10.0)
    step = math.degrees(0.001)
    assert exps["deg"].lattice_deg["theta"] == pytest.approx(step, rel=1e-6)
    floor, _ = noise_floor(exps, 10.0, cal)
    assert floor.theta_deg == pytest.approx(step / math.sqrt(12.0), rel=0.10)
    assert floor.fit_pct < 100.0 - 1e-3


def test_value_step_is_the_common_step_of_the_values():
    rng = np.random.default_rng(7)
    counts = np.round(30.0 * rng.standard_normal(2000) / (360 / 4096)) * (360 / 4096)
    assert value_step(counts) == pytest.approx(360 / 4096, rel=1e-12)  # an encoder's count in degrees
    printed = np.round(rng.standard_normal(2000), 3)
    assert value_step(printed) == pytest.approx(1e-3, rel=1e-9)  # the last printed decimal
    converted = np.round(np.degrees(np.round(rng.standard_normal(2000), 3)), 6)
    assert value_step(converted) == pytest.approx(math.degrees(1e-3), rel=1e-6)  # 0.001 rad written in deg
    assert value_step(rng.standard_normal(2000)) == 0.0  # continuous values: no lattice
    assert value_step(np.array([0.0, 1.0])) == 0.0  # too few levels to tell


# ----------------------------------------------------------------------------------------------- recalibration alone


def test_recalibration_alone_is_the_folds_geometric_mean_and_an_offset_their_mean():
    """Two folds' fits made one: a ratio's geometric mean (a factor either way is as far), an offset's mean (it may be
    0 or negative), an effect's own rule (an integer's common value)."""
    assert combine("plant.Ks", [1.2, 1.5]) == pytest.approx(math.sqrt(1.2 * 1.5))
    assert combine("rig.drive_tau", [0.06, 0.096]) == pytest.approx(0.0758947)
    assert combine("plant.u_offset", [-0.1, 0.04]) == pytest.approx(-0.03)
    assert combine("daq.delay_samples", [2, 2]) == 2


def _honest_doc() -> dict:
    doc = copy.deepcopy(minimal_doc())
    ks = doc["parameters"]["plant.Ks"]
    ks.update(recalibrated=1.8)  # recalibration alone pushed Ks far, the joint refit brought it to 1.5
    beq = doc["parameters"]["plant.Beq"]
    beq.update(recalibrated=0.0041)  # within 3 % of the joint fit: not a move worth a word
    jeq = {"change_pct": 60.0, "ci95": [0.0032, 0.0034], "fitted": 0.003339, "nominal": 0.002087, "unit": "kg m^2",
           "at_bound": "upper", "recalibrated": 0.003339,
           "finding": "hub inertia at its upper bound (1.6x the spec: 0.002087 -> 0.003339 kg m^2): the spec may not "
           "describe this rig"}  # fmt: skip
    zeta = {"change_pct": 20.0, "ci95": [1.854e-08, 215.7], "fitted": 0.012, "nominal": 0.01, "unit": "1",
            "identifiable": False, "finding": "link damping ratio is not identifiable from these data"}  # fmt: skip
    doc["parameters"].update({"plant.Jeq": jeq, "plant.zeta_link": zeta})
    doc["caveats"] = ["verdict 'backlash' reached with " + jeq["finding"]]
    doc["replays"] = {
        "square (0-5.5 s)": {"replay": "closed", "reason": "a closed-loop record with its controller (spec)"},
        "square (5.5-10 s)": {"replay": "closed", "reason": "a closed-loop record with its controller (spec)"},
    }
    doc["folds"] = {"A": ["square (0-5.5 s)"], "B": ["square (5.5-10 s)"],
                    "scheme": "2-fold cross-fit: fit on A score on B, and back; the lone record 'square' split in "
                    "time at 5.5 s into two halves, one per fold"}  # fmt: skip
    return doc


def test_new_fields_round_trip_and_old_files_still_load(tmp_path):
    write_json(tmp_path / "old.json", minimal_doc())  # a diagnosis.json written before these fields
    old = Diagnosis.load(tmp_path / "old.json")
    assert old.caveats is None and old.replays is None
    assert all(
        p.at_bound is None and p.identifiable is None and p.recalibrated is None for p in old.parameters.values()
    )
    old.write(tmp_path / "old_again.json")
    assert (tmp_path / "old_again.json").read_bytes() == (tmp_path / "old.json").read_bytes()
    write_json(tmp_path / "new.json", _honest_doc())
    d = Diagnosis.load(tmp_path / "new.json")
    d.write(tmp_path / "new_again.json")
    assert (tmp_path / "new_again.json").read_bytes() == (tmp_path / "new.json").read_bytes()
    assert d.parameters["plant.Jeq"].at_bound == "upper" and d.parameters["plant.zeta_link"].identifiable is False
    assert d.parameters["plant.Ks"].recalibrated == 1.8
    # the unidentifiable one is not an off-spec finding; the one at its bound is
    assert d.off_spec_findings() == [d.parameters["plant.Jeq"].finding, d.parameters["plant.Ks"].finding]
    assert d.recalibration_moves() == [
        "link stiffness 1.8 (1.4x the spec) by recalibration alone, 1.5 (1.2x) with the effects"
    ]


def test_the_report_says_caveats_replays_and_recalibration_alone():
    d = Diagnosis.from_dict(_honest_doc())
    text = "\n".join(diagnosis_markdown(d))
    assert "Caveats:\n\n- verdict 'backlash' reached with hub inertia at its upper bound (1.6x the spec" in text
    assert "- closed (a closed-loop record with its controller (spec)): `square (0-5.5 s)`, `square (5.5-10 s)`" in text
    header = "| parameter | unit | nominal | fitted | 95 % interval | change [%] | finding | recalibration alone |"
    assert header in text
    ks = "| plant.Ks | N m/rad | 1.3 | 1.5 | ± 1.3 % | 15.0 | link stiffness is 15 % higher than the spec (1.3 -> 1.5 "
    ks += "N m/rad) | 1.8 |"
    assert ks in text
    assert "| plant.zeta_link | 1 | 0.01 | 0.012 |" in text and text.count(" | — |\n") >= 2  # none for these
    assert "link stiffness 1.8 (1.4x the spec) by recalibration alone, 1.5 (1.2x) with the effects." in text
    assert "the lone record 'square' split in time at 5.5 s into two halves, one per fold" in text
    assert "in sample (one experiment" not in text and "are in-sample" not in text
    # an older file whose lone experiment was both folds: its held-out figures are called in-sample
    old = copy.deepcopy(minimal_doc())
    old["folds"] = {"A": ["a"], "B": ["a"], "scheme": "2-fold cross-fit: fit on A score on B, and back"}
    lines = "\n".join(diagnosis_markdown(Diagnosis.from_dict(old)))
    assert "| in sample (one experiment in both folds) |" in lines and "figures of this file are in-sample" in lines
    assert "recalibration alone" not in lines  # an old file has no such values: the table keeps its columns


# ----------------------------------------------------------------------------------------------- a real lone record


def test_a_lone_real_record_is_diagnosed_on_its_halves(cu_lone_run):
    """One of the lab's closed-loop records alone (10 s at 1 kHz, theta printed to 0.001 rad): cut in time, fitted
    on one half and scored on the other, the record's step in the floor, no parameter held by a wall (the rig
    identified in its combos under the lab sheet's priors), and what recalibration alone fitted beside the joint
    fit. The session's ``cu_lone_run`` (tests/shared_runs.py), which test_real_design's held-out prediction reads."""
    run = cu_lone_run / "run"
    d = Diagnosis.load(run)
    a, b = d.folds.A, d.folds.B
    assert len(a) == len(b) == 1 and a != b and a[0].startswith("flexibleArm_test_3 (0-")
    assert "split in time" in d.folds.scheme and set(d.replays) == {a[0], b[0]}
    assert {r["replay"] for r in d.replays.values()} == {"closed"}
    dec = d.gap.decomposition
    assert 100 * (1 - dec.before) < 70.0 < 100 * (1 - dec.after_recalibration) <= 100 * (1 - dec.after_effects)
    # measured 81.9 % held out, 65.3 % as given, the gauge read 59 ms late (75.4 and 35.9 % with it on time)
    assert 100 * (1 - dec.after_effects) >= 80.0 and d.calibration.gauge_delay_s == pytest.approx(0.059, abs=0.002)
    assert d.noise_floor.theta_deg == pytest.approx(math.degrees(0.001) / math.sqrt(12.0), rel=0.10)
    assert d.noise_floor.fit_pct < 99.5
    assert not [k for k, p in d.parameters.items() if p.at_bound]
    assert all(p.recalibrated is not None for k, p in d.parameters.items() if k in recal.LINEAR)
    # what diagnose_run returned (written by itself in the fixture) is what the file holds
    assert (cu_lone_run / "returned.json").read_bytes() == (run / "diagnosis.json").read_bytes()


def test_linear_parameters_a_recalibration_that_did_not_pay_leaves_at_the_spec(tmp_path):
    """A rig that is its spec (the twin, no effect, a quick campaign): recalibrating its linear parameters does not
    improve the held-out fit, so the waterfall does not apply it. The parameter table then keeps the spec's values,
    says why and gives no interval, where a final refit used to fit them anyway and report, e.g., viscous damping 27 %
    off the spec of a closed-loop rig that was its spec, with an interval of +-0.15 %."""
    case = {"case": 2, "family": "twin", "kind": "none", "nuisance": {}, "truth_params": {}, "truth_effects": [],
            "sensor": {}, "campaign_seed": 12}  # fmt: skip
    bt.make_rig_run(case, tmp_path / "run", quick=True)
    d = diagnose_run(tmp_path / "run", bt.campaign_spec(True), tmp_path / "out", workers=1)
    assert d.verdict == "none" and not d.recalibration_applied
    for name, p in d.parameters.items():
        assert p.fitted == p.nominal and p.kept and p.change_pct == 0.0, (name, p)
        assert p.finding.endswith("recalibrating did not improve the held-out fit"), p.finding
        assert p.recalibrated != p.nominal  # what the folds fitted, shown beside it
    assert Diagnosis.load(tmp_path / "out" / "diagnosis.json").parameters["plant.Ks"].kept  # NaN interval round-trips
    text = "\n".join(diagnosis_markdown(d))
    assert "The linear parameters keep the spec's values" in text and "traded off against the effects" not in text


def test_a_record_starts_in_motion_only_when_its_first_rate_stands_out_of_its_noise():
    """A closed-loop record at rest at its start (its hub still, 0.05 deg of noise, a slow square whose rate RMS is
    small) keeps the rest start; one whose hub turns at 3 rad/s from its first sample starts from its measured state;
    one driven from rest by its reference's step at t = 0 keeps the rest start, a fast drive's too (its hub's first
    10 ms are no parabola: a parabola's slope at the first sample read 1.5 rad/s)."""
    rate, n = 500.0, 5000
    t = np.arange(n) / rate
    rng = np.random.default_rng(3)
    ref = np.where((t % 8.0) < 4.0, 10.0, -10.0)
    slow = np.where(t < 4.0, 0.0, -10.0 * np.minimum((t - 4.0) / 2.0, 1.0)) + rng.normal(0, 0.05, n)
    moving = np.degrees(3.0) * t[:n] * (t < 0.5) + np.degrees(1.5) * (t >= 0.5) + rng.normal(0, 0.02, n)
    stepped = 10.0 * np.minimum(t / 0.3, 1.0) ** 2 + rng.normal(0, 0.05, n)
    s = t % 2.0  # a drive of 40 rad/s and 10 ms from rest at each step, held at 40 deg
    fast = np.degrees(np.minimum(40.0 * (s - 0.01 * (1.0 - np.exp(-s / 0.01))), 0.7)) * np.where(t % 4.0 < 2.0, 1, -1)

    def rec(theta: np.ndarray, r: np.ndarray) -> RigExperiment:
        return RigExperiment(name="r", kind="square", Ts=1 / rate, t=t, u=np.zeros(n), theta=theta,
                             alpha=rng.normal(0, 0.01, n), theta_v=theta / 35.5, alpha_v=np.zeros(n), ref=r,
                             replay="closed")  # fmt: skip

    assert rec(slow, ref).start_state == {}
    state = rec(moving, np.full(n, 30.0)).start_state
    assert state["theta_dot_start"] == pytest.approx(3.0, rel=0.05)
    assert rec(stepped, np.full(n, 10.0)).start_state == {}
    assert rec(fast + rng.normal(0, 0.01, n), np.full(n, 40.0)).start_state == {}


def test_a_lone_record_cut_where_a_soft_link_still_swings_starts_its_part_there(tmp_path):
    """The CU twin with a link 4x softer than its sheet (first clamped mode 0.9 Hz), one 10 s record: the cut between
    its halves finds the hub slow but the link 9 deg deflected (from the gauge's median reading: a zero offset is
    none). The second half's replay starts from that measured state (alpha_start, its rate, the hub's rate), not at
    rest, as the true angles its sensors' fitted gains read so, the rates from the widest cubic that agrees with the
    narrower ones: held-out fit 42.9 % from rest (the second half fitted a gauge gain of 0.47 to make up the
    missing swing), 88.9 % with the readings as true angles and 20 ms rates (the sensor gains 0.83 and 0.86 for
    it), 83.6 % with the gains read through and 20 ms rates (the hub's rate 0.31 rad/s where it was 0.07: the drive
    gain of the second half 3.4 rad/(V s), its link damping 0.089), 98.1 % now; Ks within 0.2 % of the truth, both
    sensors' gains within 1 % of 1."""
    from harness.diagnosis.experiments import fold_experiments
    from harness.rig.campaign import run_campaign

    truth = 2.2448 / 4
    sheet = specmod.load("cu_flexible_arm")
    run = tmp_path / "run"
    run_campaign(
        specmod.load("cu_flexible_arm", [f"plant.Ks={truth}", "daq.noise_theta=0.002", "daq.noise_alpha=0.002"]),
        run,
        workers=1,
    )
    parts, _ = fold_experiments(load_experiments(run, load_calibration(run), sheet, 10.0))
    first, second = parts.values()
    assert first.start_state == {}
    assert replace(first, alpha=first.alpha + 10.0).start_state == {}  # a gauge's zero offset is no deflection
    assert abs(math.degrees(second.start_state["alpha_start"])) > 5.0
    assert second.start_state["alpha_start"] == pytest.approx(math.radians(second.alpha[0]), rel=0.02)
    d = diagnose_run(run, sheet, tmp_path / "diag", workers=1)
    assert 100 * (1 - d.gap.decomposition.after_recalibration) > 97.0
    assert d.parameters["plant.Ks"].fitted == pytest.approx(truth, rel=0.002)
    for gain in ("sensor.theta_gain", "sensor.alpha_gauge_gain"):
        assert d.parameters[gain].fitted == pytest.approx(1.0, abs=0.01)
    assert abs(second.start_state["theta_dot_start"] - 0.07) < 0.02  # rad/s: the hub's rate there (centred: 0.07)
