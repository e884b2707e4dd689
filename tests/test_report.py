"""report.md + figures of a real run (a short campaign, calibrated, identified, cross-fitted and diagnosed), of a
hand-built run directory whose numbers are known independently (with the real run's diagnosis), and of run
directories that hold only part of a run."""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.signal import lfilter

from benchmarks.problems import demo_system
from harness import spec as specmod
from harness.diagnosis.blindtest import campaign_spec
from harness.diagnosis.diagnose import diagnose_run
from harness.diagnosis.result import Diagnosis
from harness.ident import armax, lti
from harness.ident.calibration import calibrate_run
from harness.ident.crossfit import crossfit_run
from harness.ident.identify import prepare, run_grid, write_grid
from harness.render.analysis import estimates, measured_frf
from harness.render.gap_text import diagnosis_markdown
from harness.render.load import load_results
from harness.render.report import write_report
from harness.rig.campaign import run_campaign
from harness.rundir import RunDir, load_run, write_dataset

AF = 0.8
TS = 0.02
KP, KE, OFFSET = 35.0, -3.4, 0.1
NAMES = ("prbs_a", "prbs_b", "square_c")
N = 600
N_SAMPLES = N
REAL_EXPERIMENTS = ("prbs_small", "square_large", "chirp_slow")  # 10 s each: ~30 s to diagnose on 2 cores
REAL_GRID = {"na": [2, 4], "nb": [1, 2], "nc": [1, 2]}


def real_run(tmp_path_factory) -> Path:
    """A real run directory: the blind rig with Coulomb friction (0.05 N m) and a one-sample delay, three 10 s
    experiments, calibrated, identified on a small grid, cross-fitted through the exported FMUs and diagnosed by
    ``diagnose_run`` against the blind campaign's linear rig. Made once per test process (cached on disk)."""
    base = tmp_path_factory.getbasetemp() / "real_run"
    if (base / "diagnosis.json").exists():
        return base
    tmp = Path(tempfile.mkdtemp(dir=tmp_path_factory.getbasetemp()))
    spec = campaign_spec(quick=True, overrides=["plant.coulomb_torque=0.05", "daq.delay_samples=1", "campaign.seed=11"])
    raw = specmod.apply_overrides(spec.raw, [])
    raw["experiment"] = [dict(e, duration=10.0) for e in raw["experiment"] if e["name"] in REAL_EXPERIMENTS]
    run_campaign(specmod.from_dict(raw, spec.path), tmp, workers=1)
    cal = calibrate_run(tmp)
    ident = dict(specmod.IDENTIFY_DEFAULTS, **REAL_GRID)
    prepared = prepare(load_run(tmp), cal, float(ident["af"]), str(ident["output"]))
    write_grid(run_grid(prepared, ident, workers=1), tmp, ident, cal)
    crossfit_run(tmp)
    diagnose_run(tmp, campaign_spec(quick=True), workers=1)
    try:
        os.rename(tmp, base)
    except OSError:  # made meanwhile by another module of this process
        shutil.rmtree(tmp, ignore_errors=True)
    return base


def campaign_only(real: Path, dest: Path) -> Path:
    """A copy of the real run without identification (data, manifest, calibration and diagnosis only)."""
    shutil.copytree(real, dest, ignore=shutil.ignore_patterns("models", "grid.csv", "crossfit.csv", "figures", "*.md"))
    return dest


def exp_gap(entry: dict) -> float:
    """The diagnoser's per-experiment gap from its per-channel fits: sqrt(mean over channels (1 - fit/100)^2)."""
    fits = list(entry["fit_pct"].values())
    return math.sqrt(sum((1 - f / 100) ** 2 for f in fits) / len(fits))


def _truth_model() -> armax.ArmaxModel:
    return demo_system(TS)  # stable ARMAX(4,3,4,1) at 50 Hz with a non-minimum-phase zero


def _input(name: str, rng: np.random.Generator) -> np.ndarray:
    if name.startswith("square"):
        t = np.arange(N) * TS
        return 1.5 * np.where((t * 0.4) % 1.0 < 0.5, 1.0, -1.0)
    flips = rng.random(N) < 0.1
    return 1.5 * np.where(np.cumsum(flips) % 2 == 0, 1.0, -1.0)


def _record(name: str, m: armax.ArmaxModel, dataset: str, cv: dict[str, float], selected: bool) -> dict:
    return {
        "name": name,
        "dataset": dataset,
        **m.to_dict(),
        "fit_own": cv[dataset],
        "cv": cv,
        "cv_mean": float(np.mean(list(cv.values()))),
        "preprocessing": {"af": AF, "output": "y", "detrend": "constant", "ic": "z"},
        "selected": selected,
        "selection_rule": "simplest model within 1 fit point of the best mean",
    }


def build_run(root: Path, diagnosis: dict) -> dict:
    """Write a small synthetic run directory with ``diagnosis`` as its diagnosis.json; returns the independent
    truth (signals, models, crossfit)."""
    rng = np.random.default_rng(7)
    true = _truth_model()
    truth: dict = {"u_d": {}, "y_f": {}, "t": {}, "u": {}, "models": {}}
    for name in NAMES:
        u = _input(name, rng)
        u_d = u - u.mean()
        e = 0.02 * rng.standard_normal(N)
        e[0] = 0.0  # y_f[0] = 0: the tip starts at rest, as preprocess(initial="rest") assumes
        y_f = armax.generate(true, u_d, e)  # the identification-domain output the rig "measured"
        y_f[1:] -= y_f.sum() / (N - 1)  # zero mean and y_f[0] = 0: identical with or without detrending y_f
        y = 12.0 + lfilter([1.0, -AF], [1.0 - AF, -(1.0 - AF)], y_f)  # undo H(z): tip angle [deg], at rest
        alpha_v = OFFSET + 0.05 * np.sin(np.arange(N) * 0.3)
        theta_v = (y - KE * (alpha_v - OFFSET)) / KP
        t = np.arange(N) * TS
        cols = {"t": t, "u": u, "theta_v": theta_v, "alpha_v": alpha_v}
        write_dataset(root / "data" / f"{name}.parquet", cols)
        truth["u_d"][name], truth["y_f"][name], truth["t"][name], truth["u"][name] = u_d, y_f, t, u
    manifest = {
        "kind": "campaign",
        "spec": {"campaign": {"name": "synthetic", "sample_rate": 50.0}},
        "spec_sha256": "5e" * 32,
        "seed": 1,
        "sample_rate": 50.0,
        "fmus": {},
        "versions": {"numpy": "x"},
        "experiments": [{"name": n, "role": "identification", "n": N, "seed": 1} for n in NAMES],
    }
    (root / "manifest.json").write_text(json.dumps(manifest))
    cal = {
        "Kp": KP,
        "Ke": KE,
        "gauge_offset_v": OFFSET,
        "pot_offset_v": 0.0,
        "dead_zone_v": 0.33,
        "source": {},
    }
    (root / "calibration.json").write_text(json.dumps(cal))
    u_d, y_f = truth["u_d"], truth["y_f"]
    models = {n: armax.estimate(u_d[n], y_f[n], 2 + i, 2, 2, 1, Ts=TS) for i, n in enumerate(NAMES)}
    models["selected"] = true
    rows = {}
    for name, m in models.items():
        cv = {d: armax.compare(m, truth["u_d"][d], truth["y_f"][d]) for d in NAMES}
        own = NAMES[0] if name == "selected" else name
        rec = _record(name, m, own, cv, name == "selected")
        (root / "models").mkdir(exist_ok=True)
        (root / "models" / f"{name}.json").write_text(json.dumps(rec))
        rows[name] = cv
    cf = pd.DataFrame.from_dict(rows, orient="index")[list(NAMES)]
    avg = cf.mean(axis=1)
    avg.iloc[1] += 3.0  # a wrong average in the file, like lab 1's table 2 row 4: the report must not copy it
    cf.insert(len(NAMES), "average", avg)
    cf.index.name = "model"
    cf.to_csv(root / "crossfit.csv", float_format="%.6f")
    grid = pd.DataFrame(
        {
            "dataset": ["prbs_a"] * 4,
            "na": [1, 2, 3, 4],
            "nb": [2, 2, 2, 3],
            "nc": [1, 1, 1, 4],
            "nk": [1] * 4,
            "causal": [False, True, True, True],
            "stable": [False, True, True, True],
            "fit": [math.nan, 70.0, 92.0, 95.0],
            "survivor": [False, False, True, True],
        }
    )
    grid.to_csv(root / "grid.csv", index=False)
    (root / "diagnosis.json").write_text(json.dumps(diagnosis))
    doubled = {"experiment": "prbs_a", "fit_model_50hz_as_is": 41.5}
    (root / "doubled_rate.json").write_text(json.dumps(doubled))
    truth["models"] = models
    truth["crossfit"] = cf.drop(columns="average")
    return truth


@pytest.fixture(scope="module")
def real(tmp_path_factory, fmus) -> tuple[Path, dict]:
    path = real_run(tmp_path_factory)
    return path, json.loads(RunDir(path).diagnosis.read_text())


@pytest.fixture(scope="module")
def run(tmp_path_factory, real) -> tuple[Path, dict]:
    root = tmp_path_factory.mktemp("run")
    return root, build_run(root, real[1])


def _section(text: str, title: str) -> str:
    part = text.split(f"## {title}", 1)[1]
    return part.split("\n## ", 1)[0]


def _rows(section: str) -> list[list[str]]:
    out = []
    for line in section.splitlines():
        if line.startswith("| ") and not line.startswith("|---"):
            out.append([c.strip() for c in line.strip().strip("|").split("|")])
    return out


def test_report_links_tables_and_reproducibility(run):
    root, truth = run
    path = write_report(root)
    text = path.read_text()
    links = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text)
    assert len(links) >= 8
    for link in links:
        png = root / link
        assert not Path(link).is_absolute() and png.is_file()
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    # cross-fit table: cells are the file's numbers, Average the row mean (not the file's wrong average)
    rows = _rows(_section(text, "Cross-fit matrix"))
    header, body = rows[0], rows[1:]
    assert header[-1] == "Average" and len(header) == len(NAMES) + 2
    cf = truth["crossfit"]
    assert [r[0].split()[0] for r in body] == list(cf.index)
    for r, (_, full) in zip(body, cf.iterrows(), strict=True):
        cells = [float(c) for c in r[1:-1]]
        assert cells == pytest.approx(full.to_numpy(), abs=0.0051)
        assert float(r[-1]) == pytest.approx(round(float(full.mean()), 2), abs=1e-9)
        assert float(r[-1]) == pytest.approx(np.mean(cells), abs=0.0101)
    assert "not the mean of their row: `prbs_b`" in text

    # time responses: the report's fits equal an independent compare on the generated signals
    fits = {r[0]: float(r[1]) for r in _rows(_section(text, "Time responses per dataset"))[1:]}
    for name in NAMES:
        ref = armax.compare(truth["models"]["selected"], truth["u_d"][name], truth["y_f"][name])
        assert 80.0 < ref < 100.0
        assert fits[name] == pytest.approx(round(ref, 2), abs=0.0051)

    # calibration vs lab 1: (35 - 35.5145) / 35.5145 = -1.45 %
    cal = {r[0]: r for r in _rows(_section(text, "Calibration"))}
    assert cal["Kp"][2] == "35.0000" and cal["Kp"][3] == "35.5145" and cal["Kp"][4] == "-1.45"
    assert cal["Ke"][4] == "-1.08"  # (-3.4 + 3.3636) / 3.3636

    # grid counts; the selected ARMAX(4,3,4,1) + integrator has 5 poles, 4 zeros (lab 1 fig. 13)
    grid = {r[0]: r[1] for r in _rows(_section(text, "ARMAX grid and selection"))}
    assert grid["causal (nb + nk <= na), fitted"] == "3"
    assert grid["fit >= 89 % on own dataset"] == "2"
    assert "5 poles, 4 zeros (1 outside the unit circle" in text
    assert "## Doubled sampling rate check" in text
    figs = {p.name: p.read_bytes() for p in (root / "figures").glob("*.png")}
    write_report(root)
    assert path.read_text() == text
    assert {p.name: p.read_bytes() for p in (root / "figures").glob("*.png")} == figs
    assert not list(root.rglob("*.tmp"))


def test_parameter_deviations_and_information_criteria(run):
    """The selected model's free parameters with sqrt(diag(cov)), and MATLAB's FPE and AIC on its dataset."""
    _, truth = run
    m = truth["models"]["prbs_b"]  # estimated by PEM: it carries a covariance
    est = estimates(m, N_SAMPLES)
    assert est.names == ["a1", "a2", "a3", "b1", "b2", "c1", "c2"]
    assert est.values == pytest.approx(np.concatenate([m.A[1:], m.B[1:], m.C[1:]]), rel=1e-12)
    assert est.std == pytest.approx(np.sqrt(np.diag(m.cov)), rel=1e-12)
    N, d, V = N_SAMPLES, 7, m.loss
    assert est.fpe == pytest.approx(V * (1 + d / N) / (1 - d / N), rel=1e-12)
    assert est.aic == pytest.approx(N * math.log(V) + 2 * d, rel=1e-12)
    assert estimates(truth["models"]["selected"], N_SAMPLES) is None  # no covariance


def test_measured_frf_follows_the_true_system(run):
    """The nonparametric H1 response on the Bode plot: times H(z) it is B/A of the system that made the data."""
    root, truth = run
    frf = measured_frf(load_results(root).prepared["prbs_a"], AF)
    assert frf.f_hz.size >= 10 and np.all(frf.coherence >= 0.8)
    zi = np.exp(-2j * np.pi * frf.f_hz * TS)
    m = truth["models"]["selected"]
    ba = np.polyval(m.B[::-1], zi) / np.polyval(m.A[::-1], zi)
    h = (1 - AF) * (1 - zi) / (1 - AF * zi)
    assert np.median(np.abs(20 * np.log10(np.abs(frf.response * h / ba)))) < 1.0  # dB


def test_loader_signals_match_generated_data(run):
    root, truth = run
    res = load_results(root)
    assert list(res.prepared) == list(NAMES)
    for name in NAMES:
        p = res.prepared[name]
        assert p.u_d == pytest.approx(truth["u_d"][name], abs=1e-12)
        assert p.y_f == pytest.approx(truth["y_f"][name], abs=1e-9)


def test_bad_run_directories(tmp_path):
    with pytest.raises(ValueError, match="no such run directory"):
        write_report(tmp_path / "missing")
    with pytest.raises(ValueError, match="manifest.json"):
        write_report(tmp_path)
    (tmp_path / "manifest.json").write_text(json.dumps({"kind": "import", "sample_rate": 50.0, "experiments": []}))
    (tmp_path / "models").mkdir()
    (tmp_path / "models" / "selected.json").write_text("{not json")
    with pytest.raises(ValueError, match=r"selected\.json: not valid JSON"):
        write_report(tmp_path)
    assert not (tmp_path / "report.md").exists()


@pytest.fixture(scope="module")
def real_report(real) -> tuple[Path, dict, str]:
    root, d = real
    return root, d, write_report(root).read_text()


def test_real_report_is_compact_and_reproducible(real_report):
    """report.md of a real run: well under 25 kB, no line over 1,000 characters, no raw dictionary, every
    figure it links exists; a second write gives the same bytes (text and figures)."""
    root, _, text = real_report
    assert len(text.encode()) < 16_000 and max(len(line) for line in text.splitlines()) < 1000
    assert "{" not in text and "fit_model" not in text and "_pct" not in text and "seed 000" not in text
    links = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text)
    assert {Path(x).name for x in links} == {p.name for p in RunDir(root).figures.glob("*.png")}
    assert len(links) == 9
    figs = {p.name: p.read_bytes() for p in RunDir(root).figures.glob("*.png")}
    assert write_report(root).read_text() == text
    assert {p.name: p.read_bytes() for p in RunDir(root).figures.glob("*.png")} == figs


def test_real_report_diagnosis(real_report):
    """Roles from the diagnoser's folds, the verdict sentence with the verdict's importance and the effect that
    closed most, importance and shrink per effect, the waterfall's numbers equal to diagnosis.json's, gaps per
    experiment, recalibrated parameters, a short where table."""
    _, d, text = real_report
    sec = _section(text, "Sim-to-real gap diagnosis")
    assert d["verdict"] == "coulomb_friction" and [e["effect"] for e in d["effects"]] == ["coulomb_friction", "delay"]
    imp = {e["effect"]: e["importance_pct"] for e in d["effects"]}
    shrink = {e["effect"]: e["shrink_pct"] for e in d["effects"]}
    assert imp["coulomb_friction"] > imp["delay"] and shrink["delay"] > 90.0 > shrink["coulomb_friction"]
    assert (
        f"removing `coulomb_friction` alone from the final model reopens the most gap "
        f"({imp['coulomb_friction']:.1f} % of what the drop-one removals reopen together)" in sec
    )
    assert f"`delay`, added second, closed {shrink['delay']:.1f} % of the gap left at that point" in sec
    effects = {r[0]: r for r in _rows(sec) if r[0] in imp and len(r) == 7}
    for name, r in effects.items():
        assert (r[2], r[5], r[6]) == (f"{imp[name]:.1f}", f"{shrink[name]:.1f}", "closes the held-out gap")

    dec = d["gap"]["decomposition"]
    steps = {r[0]: r for r in _rows(sec) if len(r) == 4 and r[0] != "stage"}
    assert steps["simulation as given"][1] == f"{dec['before']:.4f}"
    assert steps["noise floor"][1] == f"{dec['noise_floor']:.4f}"
    for st in dec["steps"]:
        assert steps[st["stage"]][1:] == [f"{st['gap_after']:.4f}", f"{100 * (1 - st['gap_after']):.2f}",
                                          f"{st['closed_pct']:.1f}"]  # fmt: skip
    assert [r[0] for r in _rows(sec) if len(r) == 4 and r[0] in steps][:4] == [
        "simulation as given",
        "recalibration",
        *imp,
    ]

    folds = {n: f"fold {k}" for k in ("A", "B") for n in d["folds"][k]}
    per = {r[0]: r for r in _rows(sec) if r[0] in d["gap"]["before"]["experiments"]}
    assert set(per) == set(d["gap"]["before"]["experiments"]) == set(folds) == set(REAL_EXPERIMENTS)
    for name, r in per.items():
        assert r[1] == folds[name]  # the role, from folds (no "—")
        before = exp_gap(d["gap"]["before"]["experiments"][name])
        after = exp_gap(d["gap"]["after"]["experiments"][name])
        assert (float(r[4]), float(r[5])) == pytest.approx((before, after), abs=6e-5)
    rows = {r[0]: r for r in _rows(sec) if r[0] in d["parameters"]}
    assert set(rows) == set(d["parameters"])
    ks = d["parameters"]["plant.Ks"]
    assert rows["plant.Ks"][2] == f"{ks['nominal']:.4g}" and rows["plant.Ks"][6] == ks["finding"]
    assert rows["plant.coulomb_torque"][3] == f"{d['parameters']['plant.coulomb_torque']['fitted']:.4g}"
    where = [r for r in _rows(sec) if r[0] in ("simulation as given", "after recalibration") and len(r) == 6]
    assert 1 <= len(where) <= 4 and {r[1] for r in where} <= {"theta", "alpha"}


def test_real_report_identification(real_report):
    """Best (grid.csv, by mean CV fit) and selected model per dataset, the residual tests per dataset equal to
    armax.resid's, the statement that acceptance gates on the fit only, FPE and AIC of the selected model."""
    root, _, text = real_report
    grid = pd.read_csv(RunDir(root).grid)
    sec = _section(text, "ARMAX grid and selection")
    rows = {r[0]: r for r in _rows(sec) if r[0] in REAL_EXPERIMENTS and len(r) == 7}
    assert set(rows) == set(REAL_EXPERIMENTS)
    differs = 0
    for name, r in rows.items():
        g = grid[(grid["dataset"] == name) & grid["cv_mean"].notna()]
        b = g.loc[g["cv_mean"].idxmax()]
        assert r[1:4] == [f"({b.na},{b.nb},{b.nc},{b.nk})", f"{b.fit:.2f}", f"{b.cv_mean:.2f}"]
        rec = json.loads(RunDir(root).model(name).read_text())
        assert r[4:] == [f"({rec['na']},{rec['nb']},{rec['nc']},{rec['nk']})", f"{rec['fit_own']:.2f}",
                         f"{rec['cv_mean']:.2f}"]  # fmt: skip
        assert float(r[6]) >= float(r[3]) - 1.0  # within the tolerance of the best
        differs += r[1] != r[4]
    assert differs >= 1  # on this run the simplest within one point is not the best
    sel = json.loads(RunDir(root).model("selected").read_text())
    m = armax.ArmaxModel.from_dict(sel)
    ic = [r for r in _rows(sec) if r[0] == sel["dataset"] and len(r) == 6][0]
    est = estimates(m, int(ic[1]))
    assert ic[1:] == ["500", str(m.n_params), f"{m.loss:.6g}", f"{est.fpe:.6g}", f"{est.aic:.2f}"]

    res = load_results(root)
    resid = {r[0]: r for r in _rows(_section(text, "Residual tests"))[1:]}
    assert set(resid) == set(REAL_EXPERIMENTS)
    for name, p in res.prepared.items():
        rt = armax.resid(m, p.u_d, p.y_f, lags=25)
        assert resid[name][1] == f"{rt.n_out_acf}/25 (allowed {rt.allowed_acf})"
        assert resid[name][2] == ("yes" if rt.white else "no") and resid[name][4] == ("yes" if rt.independent else "no")
    assert "Acceptance (`flexjoint accept`) gates on the fit only" in text

    time_rows = {r[0]: r for r in _rows(_section(text, "Time responses per dataset"))[1:]}
    for name, p in res.prepared.items():
        y = armax.simulate(m, p.u_d, p.y_f, "z")
        assert time_rows[name][1] == f"{armax.fit_percent(p.y_f, y):.2f}"
        t0, t1 = (float(x) for x in time_rows[name][3].split("-"))
        assert t1 - t0 == pytest.approx(4.0 - p.Ts, abs=0.11)  # shown to 0.1 s
    poles = lti.poles(lti.with_integrator(m, AF))
    assert f"{poles.size} poles" in text


def test_diagnosis_markdown_flat_where_and_a_single_effect(real):
    """A where without the before/after split, and the verdict sentence of a lone effect."""
    d = Diagnosis.load(real[0])
    d.where = d.where["before"]
    d.effects = d.effects[:1]
    text = "\n".join(diagnosis_markdown(d))
    assert "{" not in text and "after recalibration |" not in text and "| simulation as given | theta |" in text
    share = f"{d.gap.explained_pct:.1f}"
    assert (
        f"`coulomb_friction` is the only effect found; modelled on top of the recalibrated simulation it closes "
        f"{share} %" in text
    )


def test_report_of_a_run_directory_without_models(real, tmp_path):
    """`flexjoint report DIR` on a directory with data, calibration and diagnosis only: report.md (the sections
    it has data for), figures/ and run.rrd."""
    run = campaign_only(real[0], tmp_path / "campaign")
    r = subprocess.run(
        [sys.executable, "-m", "harness.cli", "report", str(run)], capture_output=True, text=True, timeout=600
    )
    assert r.returncode == 0, r.stderr
    text = RunDir(run).report.read_text()
    assert "## Calibration" in text and "## Sim-to-real gap diagnosis" in text
    assert "## Selected model" not in text and "No `grid.csv` in this run." in text
    assert RunDir(run).recording.stat().st_size > 0 and (RunDir(run).figures / "diagnosis.png").exists()
    assert len(text.encode()) < 25_000
