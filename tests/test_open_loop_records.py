"""Open-loop records of a rig as the labs ran them (issue 65 item 2): voltage square waves at several amplitudes and
frequencies, 1 kHz, hub and deflection in degrees in a user's CSV, no calibration given. They go through `import`,
`identify`, `crossfit`, `diagnose` and `report` with no step a user works out; every record is shown; and the where
section reads the hub's speed per volt by amplitude: it falls at small commands by the dead band Coulomb friction
makes (coulomb_torque / the drive's torque per volt), holds on a linear rig, falls at large commands under an
amplifier's saturation. Every twin is built here through the FMUs; the friction's dead band is known from its
parameters (:func:`harness.fmu.plant.motor_constants`)."""

from __future__ import annotations

import copy
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from rerun.chunk import RrdReader

from harness import spec as specmod
from harness.diagnosis.experiments import load_experiments
from harness.diagnosis.speed import (
    FALLS_LARGE,
    FALLS_SMALL,
    HOLDS,
    UNDETERMINED,
    PlateauSpeed,
    records_speed,
    speed_per_volt,
)
from harness.fmu.plant import PlantParams, motor_constants
from harness.ident.calibration import Calibration
from harness.render.summary import MAX_LINES, WIDTH
from harness.rig.campaign import run_campaign
from harness.rundir import read_dataset

KP, KE = 35.5145, -3.3636  # the twin's DAQ gains (deg/V), which the import assumes when none is given
CAL = Calibration(Kp=KP, Ke=KE)
COULOMB = 0.044  # N m
G = motor_constants(PlantParams())[0]  # N m/V: the drive's torque per volt at the load shaft
ONE_SCREEN = {"COLUMNS": str(WIDTH), "FLEXJOINT_WORKERS": "1"}


def _squares(cases: list[tuple[float, float]], seconds: float) -> list[dict]:
    return [
        dict(name=f"sq_{a:g}v_{f:g}hz".replace(".", "p"), signal="square", amplitude=a, f=f, duration=seconds)
        for a, f in cases
    ]


def _campaign(dest: Path, experiments: list[dict], rate: float, seed: int, **plant: float) -> Path:
    """The blind rig (noise on both sensors) at ``rate`` Hz running ``experiments``, no calibration experiments."""
    raw = copy.deepcopy(specmod.load("blind").raw)
    raw["calibration"] = []
    raw["campaign"].update(sample_rate=rate, seed=seed)
    raw["plant"].update(plant)
    raw["experiment"] = experiments
    run_campaign(specmod.from_dict(raw, "blind.toml"), dest, workers=1)
    return dest


def _flexjoint(*args: object) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "harness", *map(str, args)], capture_output=True, text=True,
                          timeout=600, env={**os.environ, **ONE_SCREEN})  # fmt: skip


def _on_one_screen(r: subprocess.CompletedProcess) -> None:
    assert r.returncode == 0, r.stderr
    lines = r.stdout.rstrip("\n").splitlines()
    assert 0 < len(lines) <= MAX_LINES and all(len(x.rstrip()) <= WIDTH for x in lines), r.stdout


LAB = [(0.5, 0.5), (0.5, 1.0), (1.0, 0.5), (1.0, 1.0), (2.0, 1.0), (2.0, 2.0)]  # (amplitude V, frequency Hz)


@pytest.fixture(scope="module")
def lab(tmp_path_factory, fmus) -> tuple[Path, list[str], dict[str, subprocess.CompletedProcess]]:
    """Six 3 s square waves at 1 kHz on the rig with Coulomb friction, written as a user's CSVs (time, volts, hub and
    tip in degrees as the pot and the gauge read them, the pot wrapped), then every command of a user in turn."""
    tmp = tmp_path_factory.mktemp("open_loop")
    exps = _squares(LAB, 3.0)
    twin = _campaign(tmp / "twin", exps, 1000.0, 3, coulomb_torque=COULOMB)
    files = []
    for e in exps:
        df = read_dataset(twin / "data" / f"{e['name']}.parquet")
        files.append(tmp / "csv" / f"{e['name']}.csv")
        files[-1].parent.mkdir(exist_ok=True)
        pd.DataFrame({"time": df["t"], "Vm": df["u"], "hub_deg": KP * df["theta_v"], "tip_deg": KE * df["alpha_v"]}
                     ).to_csv(files[-1], index=False, float_format="%.6f")  # fmt: skip
    run = tmp / "run"
    said = {"import": _flexjoint("import", *files, "--out", run, "--columns", "time=t,Vm=u,hub_deg=theta,tip_deg=alpha",
                                 "--units", "theta=deg,alpha=deg")}  # fmt: skip
    for cmd, args in (("identify", [run, "--workers", 1]), ("crossfit", [run]),
                      ("diagnose", ["--real", run, "--workers", 1]), ("report", [run])):  # fmt: skip
        said[cmd] = _flexjoint(cmd, *args)
    return run, [e["name"] for e in exps], said


def test_every_command_runs_and_says_what_it_assumed(lab):
    """No step to work out: each command exits 0 and fits one screen; `import` says that no calibration was given
    and what it assumed, and `identify` says so again, with the dead zone not measured (no slow ramp)."""
    _, _, said = lab
    for r in said.values():
        _on_one_screen(r)
    assert "calibration: none given; assumed lab 1's Kp 35.5145 deg/V" in said["import"].stderr
    ident = " ".join(said["identify"].stdout.split())
    assert "(lab 1's, assumed: no calibration given), dead zone not measured" in ident and "nan" not in ident


def test_every_record_is_shown(lab):
    """The cross-fit matrix, report.md and run.rrd hold every record."""
    run, names, _ = lab
    cross = pd.read_csv(run / "crossfit.csv")
    assert names == [c for c in cross.columns if c in names] and len(cross) == len(names) + 1  # + the selected model
    assert np.isfinite(cross[names].to_numpy(float)).all()
    report = (run / "report.md").read_text()
    for name in names:
        assert f"figures/data_{name}.png" in report and f"| {name} |" in report
    paths = {str(c.entity_path) for c in RrdReader(run / "run.rrd").stream()}
    for name in names:
        assert {f"/data/{name}/theta", f"/datasets/{name}/measured", f"/diagnosis/replays/{name}/theta/record"} <= paths


def test_where_reads_the_dead_band_friction_makes(lab):
    """diagnosis.json's where.speed_per_volt: the speed per volt falls at small commands, by a dead band within 20 %
    of coulomb_torque / G (0.343 V; measured 0.342 +- 0.0011 V); the share of the linear gain grows with the
    amplitude as 1 - u_db / A; said in the report and on diagnose's screen. The effect found is the friction."""
    run, names, said = lab
    d = json.loads((run / "diagnosis.json").read_text())
    sp = d["where"]["speed_per_volt"]
    truth = COULOMB / G
    assert sp["trend"] == FALLS_SMALL and sp["records"] == names and not sp["skipped"]
    assert sp["dead_band_v"] == pytest.approx(truth, rel=0.2) and sp["dead_band_v"] > 2 * sp["dead_band_se_v"]
    amps = sp["amplitudes"]
    assert [a["amplitude_v"] for a in amps] == pytest.approx([0.5, 1.0, 2.0])
    assert [a["relative"] for a in amps] == pytest.approx([1 - truth / a["amplitude_v"] for a in amps], abs=0.1)
    assert sp["line"] in " ".join((run / "report.md").read_text().split())
    screen = " ".join(said["diagnose"].stdout.split())
    assert "where, in amplitude: hub speed per volt falls at small commands" in screen
    assert [e["effect"] for e in d["effects"]][:1] == ["coulomb_friction"]


BLIND = {
    # rig, (amplitude V, frequency Hz) of each square wave, seconds, rate Hz, seed, trend, dead band or limit V
    "linear": ({}, [(0.5, 0.5), (1.0, 1.0), (2.0, 1.0), (1.0, 0.5)], 3.0, 1000.0, 5, HOLDS, 0.0),
    "friction": ({"coulomb_torque": 0.02}, [(0.4, 0.75), (0.8, 0.75), (1.6, 1.5), (0.8, 1.5)], 4.0, 500.0, 11,
                 FALLS_SMALL, 0.02 / G),
    "friction, stiction": ({"coulomb_torque": 0.03, "stiction_ratio": 1.3}, [(0.6, 1.0), (1.2, 1.0), (2.4, 2.0),
                           (1.2, 2.0)], 3.0, 500.0, 2, FALLS_SMALL, 0.03 / G),
    "saturation": ({"amp_limit": 1.2}, [(0.5, 1.0), (1.0, 1.0), (2.0, 1.0)], 3.0, 500.0, 7, FALLS_LARGE, 1.2),
}  # fmt: skip


@pytest.mark.parametrize("case", BLIND)
def test_speed_per_volt_on_rigs_built_blind(case, tmp_path, fmus):
    """Other rigs, seeds, rates and designs (plateau lengths shared by two amplitudes or not at all): a linear rig
    holds (its dead band within 2 standard errors of 0), friction falls at small commands by coulomb_torque / G
    within 20 % (breakaway above the Coulomb level included), a saturating amplifier falls at large commands, to its
    limit over the command. A PRBS beside the square waves is not read, and says why. Measured: linear -0.0004 +-
    0.0005 V; friction 0.155 V (truth 0.156), with stiction 1.3 0.207 V (truth 0.234); saturation 60 % at 2 V (1.2 V
    limit)."""
    plant, cases, seconds, rate, seed, trend, size = BLIND[case]
    exps = [*_squares(cases, seconds), dict(name="prbs", signal="prbs", B=0.1, amplitude=1.0, duration=seconds)]
    run = _campaign(tmp_path / "twin", exps, rate, seed, **plant)
    sp = records_speed(load_experiments(run, CAL, specmod.load("nominal"), 10.0))
    assert sp is not None and sp.trend == trend, sp.line
    assert sp.skipped == {"prbs": "not a square wave (plateaus of unequal length)"}
    if trend == HOLDS:
        assert abs(sp.dead_band_v) <= 2 * sp.dead_band_se_v, sp.line
    elif trend == FALLS_SMALL:
        assert sp.dead_band_v == pytest.approx(size, rel=0.2), sp.line
    else:  # the largest command's speed per volt that of the small ones capped at the limit
        assert sp.amplitudes[-1].relative == pytest.approx(size / sp.amplitudes[-1].amplitude_v, rel=0.1), sp.line


def test_speed_per_volt_recovers_a_known_law_and_says_when_it_cannot():
    """Plateaus drawn from s = k (|u| + u0 sgn u - u_db) with noise (k 100 deg/s/V for steady records, 90 at a 0.25 s
    plateau length, u0 0.02 V, u_db 0.3 V): the fit gives u_db and u0 within 3 standard errors; one amplitude, or
    two amplitudes never at one plateau length, are undetermined, and a dead band at rest is counted."""
    rng = np.random.default_rng(4)

    def record(amp: float, k: float, length: float, n: int = 8) -> list[PlateauSpeed]:
        u = amp * np.resize([1.0, -1.0], n)
        s = k * (np.abs(u) + 0.02 * np.sign(u) - 0.3)
        noisy = np.maximum(s, 0.0) + rng.normal(0.0, 0.5, n)
        return [PlateauSpeed(float(a), float(b), 0.5, length) for a, b in zip(u, noisy, strict=True)]

    per = {"a": (record(0.6, 100.0, 1.0), True), "b": (record(1.2, 100.0, 1.0), True),
           "c": (record(1.2, 90.0, 0.25), False), "d": (record(2.4, 90.0, 0.25), False)}  # fmt: skip
    sp = speed_per_volt(per)
    assert sp.trend == FALLS_SMALL and abs(sp.dead_band_v - 0.3) < 3 * sp.dead_band_se_v, sp.line
    assert sp.gains_deg_s_v == pytest.approx({"steady": 100.0, "0.25 s": 90.0}, rel=0.02)
    assert abs(sp.offset_v - 0.02) < 0.01
    assert [a.relative for a in sp.amplitudes] == pytest.approx([0.5, 0.75, 0.875], abs=0.02)
    assert speed_per_volt({"a": per["a"]}).trend == UNDETERMINED
    apart = speed_per_volt({"a": per["a"], "d": per["d"]})
    assert apart.trend == UNDETERMINED and "one amplitude per plateau length" in apart.line
    still = speed_per_volt({**per, "e": (record(0.2, 100.0, 1.0), True)})
    assert still.amplitudes[0].n_still == 8 and "the hub at rest on 8 plateaus" in still.line
    assert abs(still.dead_band_v - 0.3) < 3 * still.dead_band_se_v
