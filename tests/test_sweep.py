"""``flexjoint sweep``: draws that follow their distributions, the statistics it reports, and a small sweep that
gives the same bytes serially and on a real Dask cluster, even when a worker is killed in the middle."""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import sys
import tempfile
import tomllib

import numpy as np
import pandas as pd
import pytest
from scipy import stats
from test_executor import TINY_SPEC, DaskCluster, tiny_spec

from harness import spec as specmod
from harness.sweep import draw, parse_vary, pass_interval, sensitivity

OUTPUTS = ("sweep.parquet", "sweep.json", "report.md", "figures/sweep_fit.png", "figures/sweep_scatter.png")


def test_draws_follow_the_stated_distributions():
    varies = [
        parse_vary("plant.Ks=normal(1.3,0.05)"),
        parse_vary("plant.Beq=uniform(0.003,0.006)"),
        parse_vary("plant.Jeq=triangular(0.001976,0.00208,0.002184)"),
        parse_vary("plant.Rm=lognormal(2.6,0.1)"),
        parse_vary("plant.n_modes=uniform(1,2)"),
    ]
    n = 200
    d = draw(varies, n, seed=7)
    assert list(d.columns) == ["plant.Ks", "plant.Beq", "plant.Jeq", "plant.Rm", "plant.n_modes"]
    assert d["plant.Beq"].between(0.003, 0.006).all() and d["plant.Jeq"].between(0.001976, 0.002184).all()
    assert (d["plant.Rm"] > 0).all() and set(d["plant.n_modes"]) == {1.0, 2.0}
    # Latin hypercube: each of the n equal-probability strata of every distribution holds exactly one draw
    cdfs = {
        "plant.Ks": stats.norm(1.3, 0.05).cdf,
        "plant.Beq": stats.uniform(0.003, 0.003).cdf,
        "plant.Jeq": stats.triang(0.5, loc=0.001976, scale=0.000208).cdf,
        "plant.Rm": stats.lognorm(0.1, scale=2.6).cdf,
    }
    for col, cdf in cdfs.items():
        strata = np.floor(cdf(d[col].to_numpy()) * n).astype(int)
        assert sorted(strata) == list(range(n)), col
    assert d["plant.Ks"].mean() == pytest.approx(1.3, abs=0.002)
    assert draw(varies, n, seed=7).equals(d) and not draw(varies, n, seed=8).equals(d)
    sob = draw(varies[:2], 64, seed=1, sampler="sobol")
    assert sob["plant.Beq"].between(0.003, 0.006).all() and len(sob) == 64


@pytest.mark.parametrize(
    "text, words",
    [
        ("plant.Kss=normal(1,0.1)", ["Kss", "Ks", "Beq"]),
        ("plant.Ks=gauss(1,0.1)", ["gauss", "normal", "triangular"]),
        ("plant.Ks=uniform(2,1)", ["lo < hi"]),
        ("plant.Ks=normal(1)", ["2 finite numbers"]),
        ("rig.Ks=normal(1,0.1)", ["plant or daq"]),
    ],
)
def test_bad_vary_names_what_is_valid(text, words):
    with pytest.raises(specmod.SpecError) as e:
        parse_vary(text)
    assert all(w in str(e.value) for w in words), str(e.value)


def test_pass_interval_and_sensitivity_numbers():
    lo, hi = pass_interval(8, 10)
    z = stats.norm.ppf(0.975)  # Wilson: (p + z^2/2n -+ z sqrt(p(1-p)/n + z^2/4n^2)) / (1 + z^2/n)
    c, h = (0.8 + z**2 / 20) / (1 + z**2 / 10), z * math.sqrt(0.8 * 0.2 / 10 + z**2 / 400) / (1 + z**2 / 10)
    assert (lo, hi) == pytest.approx((c - h, c + h), abs=1e-12)
    rng = np.random.default_rng(0)
    x = pd.DataFrame({"a": rng.uniform(size=100), "b": rng.uniform(size=100)})
    y = 90 - 10 * x["a"].to_numpy() + 0.05 * rng.normal(size=100)
    y[3] = np.nan  # a rig without a model ranks lowest
    s = sensitivity(x, y)
    a, b = s["ranking"]
    assert (a["param"], b["param"]) == ("a", "b") and a["s1"] > 0.85 and a["srrc"] < -0.9
    assert b["s1"] < 0.25 and abs(b["srrc"]) < 0.1 and s["r2_rank"] > 0.85 and s["bins"] == 10
    # a fit that peaks at the nominal value of b: no monotone trend (SRRC ~ 0), yet b explains most of it
    y = 90 - 40 * (x["b"].to_numpy() - 0.5) ** 2 - 0.5 * x["a"].to_numpy()
    b, a = sensitivity(x, y)["ranking"]
    assert b["param"] == "b" and b["s1"] > 0.8 and abs(b["srrc"]) < 0.2 and a["s1"] < 0.2


def test_a_rig_is_calibrated_in_memory_as_calibrate_run_calibrates_its_campaign(tmp_path, fmus, monkeypatch):
    """A sweep task calibrates its rig from the columns it simulated, writing no file (no scratch run directory, no
    temporary file), and gets to the last bit what calibrate_run gets from that rig's campaign on disk."""
    from harness import sweep
    from harness.executor import fmu_bytes, worker_rig
    from harness.ident.calibration import calibrate_run
    from harness.rig.campaign import run_campaign

    raw = tomllib.loads(TINY_SPEC)  # + slow up/down ramps through a Coulomb dead zone: all three calibrations
    raw["plant"]["coulomb_torque"] = 0.044
    raw["calibration"] += [
        {"name": f"deadzone_{d}", "signal": "ramp", "slope": k * 0.05, "duration": 12.0}
        for d, k in (("up", 1), ("down", -1))
    ]
    base = specmod.from_dict(raw, str(tmp_path / "tiny.toml"))
    shipped = {k: fmu_bytes(v) for k, v in fmus.items()}
    plan = sweep.Plan(base, {**base.identify, "na": 3, "nb": 1, "nc": 1}, None, shipped)  # one model: a short grid
    params, seed = {"plant.Ks": 1.4}, sweep.rig_seed(5, 0)
    worker_rig(shipped)  # this process's rig loaded (its FMUs unpacked) before temporary files are watched
    made: list[str] = []
    for name in ("mkdtemp", "mkstemp", "TemporaryDirectory", "NamedTemporaryFile", "TemporaryFile"):
        real = getattr(tempfile, name)
        monkeypatch.setattr(tempfile, name, lambda *a, _f=real, _n=name, **k: made.append(_n) or _f(*a, **k))
    row = sweep.run_rig((0, params, seed), plan)
    monkeypatch.undo()
    assert made == [] and not hasattr(sweep, "tempfile")

    run_campaign(sweep.rig_spec(base, params, seed), tmp_path / "rig", fmus=fmus, workers=1)
    cal = calibrate_run(tmp_path / "rig")
    assert (row["Kp"], row["Ke"], row["dead_zone_v"]) == (cal.Kp, cal.Ke, cal.dead_zone_v)  # the same bits
    assert cal.source["dead_zone_v"]["experiments"] == ["deadzone_up", "deadzone_down"]
    assert 30 < cal.Kp < 40 and -4 < cal.Ke < -3 and 0.2 < cal.dead_zone_v < 0.5  # measured, not lab 1's stand-ins


def _selected_model(run, spec_path, fmus):
    """Identify the tiny campaign once (serially) and return models/selected.json."""
    from harness.ident.calibration import calibrate_run
    from harness.ident.identify import prepare, run_grid, write_grid
    from harness.rig.campaign import run_campaign
    from harness.rundir import load_run

    spec = specmod.load(spec_path)
    run_campaign(spec, run, fmus=fmus, workers=1)
    cal = calibrate_run(run)
    res = run_grid(prepare(load_run(run), cal, 0.8, "y"), spec.identify, workers=1)
    return write_grid(res, run, spec.identify, cal)["selected"]


def _cli(monkeypatch, *args):
    from harness import cli

    monkeypatch.setattr(sys, "argv", ["flexjoint", *map(str, args)])
    with pytest.raises(SystemExit) as e:
        cli.main()
    assert e.value.code in (0, None)


def test_sweep_same_bytes_serial_and_on_a_cluster_that_loses_a_worker(tmp_path, fmus, monkeypatch):
    from harness.sweep import run_sweep

    n = 12
    spec = tiny_spec(tmp_path)
    vary = ["--vary", "plant.Ks=uniform(1.3,1.8)", "--vary", "plant.amp_limit=uniform(20,30)"]
    with DaskCluster(2) as cluster:
        model = _selected_model(tmp_path / "run", spec, fmus)
        common = [*vary, "--n", n, "--seed", 5, "--model", model, "--set", "accept.min_average_fit=92"]
        _cli(monkeypatch, "sweep", spec, "--out", tmp_path / "serial", *common, "--workers", 1)
        addr = cluster.wait()
        _cli(monkeypatch, "sweep", spec, "--out", tmp_path / "remote", *common, "--scheduler", addr)
        done: list[str] = []

        def kill_one_worker_midway(msg: str) -> None:
            done.append(msg)
            if len(done) == 3:
                os.killpg(cluster.workers[0].pid, signal.SIGKILL)

        s = specmod.load(spec, ["accept.min_average_fit=92"])
        run_sweep(
            s, vary[1::2], n, 5, tmp_path / "killed", model=model, scheduler=addr, progress=kill_one_worker_midway
        )
        assert cluster.workers[0].wait(timeout=10) == -signal.SIGKILL  # it really died mid-sweep
    assert len(done) == n and sorted(int(m.split()[1]) for m in done) == list(range(n))
    for f in OUTPUTS:
        ref = (tmp_path / "serial" / f).read_bytes()
        assert (tmp_path / "remote" / f).read_bytes() == ref, f
        assert (tmp_path / "killed" / f).read_bytes() == ref, f

    table = pd.read_parquet(tmp_path / "serial" / "sweep.parquet")
    doc = json.loads((tmp_path / "serial" / "sweep.json").read_text())
    assert table["rig"].tolist() == list(range(n))  # every rig once
    assert table["plant.Ks"].between(1.3, 1.8).all() and table["plant.amp_limit"].between(20, 30).all()
    fits = table[["fit_prbs", "fit_square"]].to_numpy()
    passed = (fits >= 80).all(axis=1) & (fits.mean(axis=1) >= 92)
    assert table["passed"].tolist() == passed.tolist() and 0 < passed.sum() < n  # the threshold splits the rigs
    p = doc["summary"]["pass"]
    assert p["passed"] == passed.sum() and p["rate"] == passed.sum() / n
    assert p["ci95"][0] < p["rate"] < p["ci95"][1]
    # only Ks moves the fit (an amplifier limit of 20-30 V never acts on 1.5 V commands): Ks ranks first
    rank = doc["summary"]["sensitivity"]["ranking"]
    assert rank[0]["param"] == "plant.Ks" and rank[0]["s1"] > 0.8 and rank[0]["srrc"] < -0.8
    assert rank[1]["s1"] < 0.3 and abs(rank[1]["srrc"]) < 0.3
    # the Rerun recording carries the same numbers: mean fit per rig on the rig timeline, |SRRC| bars
    from rerun.chunk import RrdReader

    chunks: dict[str, list[dict]] = {}
    for c in RrdReader(tmp_path / "serial" / "sweep.rrd").stream():
        chunks.setdefault(c.entity_path, []).append(c.to_record_batch().to_pydict())
    mean = next(d for d in chunks["/rigs/fit/mean"] if "Scalars:scalars" in d)
    assert mean["rig"] == list(range(n))
    assert [v[0] for v in mean["Scalars:scalars"]] == table["fit_mean"].tolist()
    # the S1 bars in 2D, each parameter named under its bar, its value over it
    names = next(d for d in chunks["/sensitivity/categories"] if "Points2D:labels" in d)["Points2D:labels"][0]
    assert names == [r["param"] for r in rank]
    values = next(d for d in chunks["/sensitivity/S1/values"] if "Points2D:labels" in d)["Points2D:labels"][0]
    assert values == [f"{r['s1']:.3f}" for r in rank]
    assert "Pass rate" in (tmp_path / "serial" / "report.md").read_text()


def test_report_of_a_sweep_rewrites_its_report_with_titled_figures(tmp_path, fmus, monkeypatch):
    """`flexjoint report DIR` on a sweep's output: report.md, figures/ and sweep.rrd written again from sweep.json
    and sweep.parquet (the same report.md bytes); each figure titled, the varied parameters with the units their
    FMU declares, whole rigs on the histogram's count axis."""
    from matplotlib.ticker import MaxNLocator

    from harness import sweep as sw

    out = tmp_path / "sweep"
    sw.run_sweep(tiny_spec(tmp_path), ["plant.Ks=uniform(1.2,1.4)", "plant.Beq=uniform(0.004,0.006)"], 5, 1, out,
                 orders="2,1,1", workers=1, rrd=False)  # fmt: skip
    first = (out / "report.md").read_bytes()
    (out / "report.md").unlink()
    shutil.rmtree(out / "figures")
    drawn = {}
    save = sw.save_figure
    monkeypatch.setattr(sw, "save_figure", lambda fig, path: (drawn.setdefault(path.name, fig), save(fig, path)))
    _cli(monkeypatch, "report", out)
    assert (out / "report.md").read_bytes() == first and (out / "sweep.rrd").stat().st_size > 0
    assert set(drawn) == {"sweep_fit.png", "sweep_scatter.png", "sweep_sensitivity.png"}
    hist = drawn["sweep_fit.png"].axes[0]
    assert hist.get_title().startswith("mean fit of 5 rigs") and hist.get_ylabel() == "rigs [count]"
    assert isinstance(hist.yaxis.get_major_locator(), MaxNLocator)
    assert all(float(t).is_integer() for t in hist.get_yticks())
    scatter = drawn["sweep_scatter.png"].axes
    assert [a.get_xlabel() for a in scatter] == ["plant.Ks [N.m/rad]", "plant.Beq [N.m.s/rad]"]
    assert all(a.get_title() and a.get_ylabel() == "mean fit [%]" for a in scatter)
    sens = drawn["sweep_sensitivity.png"].axes[0]
    assert sens.get_title() and sens.get_xlabel().endswith("[1]")
    assert {t.get_text().split(" (")[0] for t in sens.get_yticklabels()} == {
        "plant.Ks [N.m/rad]",
        "plant.Beq [N.m.s/rad]",
    }


def test_two_rigs_say_n_is_too_small_for_sensitivity_not_nan(tmp_path, fmus, monkeypatch, capsys):
    """n = 2 gives no first-order index (nan): the console said "S1 nan"; it now says n is too small."""
    spec = tiny_spec(tmp_path)
    model = _selected_model(tmp_path / "run", spec, fmus)
    capsys.readouterr()
    _cli(monkeypatch, "sweep", spec, "--vary", "plant.Ks=uniform(1.3,1.8)", "--n", 2, "--model", model,
         "--out", tmp_path / "sw", "--workers", 1)  # fmt: skip
    line = " ".join(capsys.readouterr().out.split())  # one line, however the terminal wrapped it
    assert "S1 nan" not in line and "sensitivity indices: n = 2 rigs too few" in line, line
