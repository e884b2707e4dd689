"""Blind test of the diagnoser: rigs with hidden effects, diagnosed against the textbook simulation, scored.

Each case draws a rig from ``specs/blind.toml`` (textbook linear rig + measurement noise, a compact campaign):

- ``none``: the rig as it is (noise only);
- ``single``: one in-library effect at a physically meaningful magnitude for this campaign (table
  :data:`RANGES`; continuous magnitudes log-uniform);
- ``two``: two different in-library effects at once;
- ``out``: an effect outside the candidate library: ``third_mode`` (plant.n_modes = 3, while the library's
  second_mode is n_modes = 2), ``gauge_drift`` (the strain-gauge gain drifting linearly in time by +10..+30 %
  over every non-calibration experiment, applied to alpha_v after the campaign, about the gauge offset; the
  comb calibration is left intact), ``beq_x2`` (viscous damping Beq 2..3x the textbook value).

The campaign runs with a per-case seed (new noise), the truth is removed from the run's manifest (its spec
tables are those of blind.toml), and :func:`harness.diagnose.diagnose_run` judges it against blind.toml.
Scores (the MISSION's): top-1 effect on single cases, fitted magnitude within 20 % (integers: exact) on single
cases, ``none`` never turned into an effect, out-of-library cases answered ``unexplained`` or with a candidate
that closes most (>= 50 %) of the held-out gap, both effects found on two-effect cases.
"""

from __future__ import annotations

import math
import shutil
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from . import spec as specmod
from .data import load_manifest, read_dataset, write_dataset, write_json
from .diagnose import EFFECTS

Progress = Callable[[str], None]

BLIND_SPEC = specmod.SPEC_DIR / "blind.toml"

# in-library effect -> (parameter, low, high, kind): magnitudes that matter on the blind campaign
RANGES: dict[str, tuple[str, float, float, str]] = {
    "coulomb_friction": ("plant.coulomb_torque", 0.02, 0.08, "log"),
    "backlash": ("plant.backlash", 0.002, 0.01, "log"),
    "saturation": ("plant.amp_limit", 1.2, 2.2, "log"),  # below the 2.5 V square and 3 V PRBS
    "second_mode": ("plant.n_modes", 2, 2, "int"),
    "delay": ("daq.delay_samples", 1, 3, "int"),
    "quantization": ("daq.adc_bits", 8, 12, "int"),
    "gauge_nonlinearity": ("daq.gauge_cubic", 0.02, 0.1, "log"),
}
OUT_OF_LIBRARY = ("third_mode", "gauge_drift", "beq_x2")
MAG_TOL = 0.20  # fitted magnitude within 20 %
MOST = 50.0  # an out-of-library answer naming a candidate counts when it shrinks the held-out gap >= 50 %


def _draw_value(rng: np.random.Generator, effect: str) -> float | int:
    _, lo, hi, kind = RANGES[effect]
    if kind == "int":
        return int(rng.integers(int(lo), int(hi) + 1))
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def plan(n: int, seed: int) -> list[dict[str, Any]]:
    """The cases: ~12 % none, ~12 % two effects, ~16 % out of library, the rest single effects (cycling
    through the library), in a shuffled order; each with its hidden truth and a campaign seed."""
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"n must be a positive number of cases, got {n!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    rng = np.random.Generator(np.random.PCG64(seed))
    n_none = max(1, round(0.12 * n)) if n >= 4 else 0
    n_two = max(1, round(0.12 * n)) if n >= 4 else 0
    n_out = max(1, round(0.16 * n)) if n >= 4 else 0
    n_single = n - n_none - n_two - n_out
    lib = list(RANGES)
    kinds = [("single", lib[i % len(lib)]) for i in range(n_single)]
    kinds += [("none", None)] * n_none + [("two", None)] * n_two
    first = int(rng.integers(len(OUT_OF_LIBRARY)))
    kinds += [("out", OUT_OF_LIBRARY[(first + i) % len(OUT_OF_LIBRARY)]) for i in range(n_out)]
    order = rng.permutation(len(kinds))
    cases = []
    for i, j in enumerate(order):
        kind, what = kinds[int(j)]
        truth: dict[str, Any] = {}
        effects: list[str] = []
        if kind == "single":
            effects = [what]
        elif kind == "two":
            a, b = rng.choice(len(lib), size=2, replace=False)
            effects = [lib[int(a)], lib[int(b)]]
        for e in effects:
            truth[RANGES[e][0]] = _draw_value(rng, e)
        extra: dict[str, Any] = {}
        if what == "third_mode":
            truth["plant.n_modes"] = 3
        elif what == "beq_x2":
            beq = float(specmod.fmu_parameters("flexjoint")["Beq"][1])
            truth["plant.Beq"] = beq * float(rng.uniform(2.0, 3.0))
        elif what == "gauge_drift":
            extra["gauge_drift"] = float(rng.uniform(0.10, 0.30))
        cases.append(
            {
                "case": i,
                "kind": kind,
                "truth_effects": effects if kind != "out" else [what],
                "truth_params": truth,
                "post": extra,
                "campaign_seed": int(rng.integers(1, 2**31 - 1)),
            }
        )
    return cases


def campaign_spec(quick: bool = False, overrides: list[str] | None = None) -> specmod.Spec:
    """The blind campaign (specs/blind.toml) with ``--set``-style overrides; ``quick`` shortens every
    experiment to 12 s and the multisine to 5 periods of 4 s (same commands and levels: for tests)."""
    base = specmod.load(BLIND_SPEC)
    raw = base.raw
    if quick:
        raw = specmod.apply_overrides(raw, [])  # a deep copy
        for e in raw["experiment"]:
            if e["signal"] == "multisine":
                e.update(period=4.0, duration=20.0)
            else:
                e["duration"] = 12.0
    return specmod.from_dict(specmod.apply_overrides(raw, overrides or []), str(BLIND_SPEC))


def make_rig_run(case: dict[str, Any], dest: Path, fmus: dict[str, Path] | None = None, quick: bool = False) -> Path:
    """Run the case's hidden rig on the blind campaign into ``dest`` and hide the truth from its manifest."""
    from .campaign import run_campaign

    base = campaign_spec(quick)
    sets = [f"{k}={v}" for k, v in case["truth_params"].items()]
    sets.append(f"campaign.seed={case['campaign_seed']}")
    spec = campaign_spec(quick, sets)
    run_campaign(spec, dest, fmus=fmus, workers=1)
    drift = case.get("post", {}).get("gauge_drift")
    manifest = load_manifest(dest)
    if drift:
        off = float(spec.daq.get("gauge_offset", specmod.fmu_parameters("daq")["gauge_offset"][1]))
        for e in manifest["experiments"]:
            if e["role"] == "calibration":
                continue
            p = dest / "data" / f"{e['name']}.parquet"
            df = read_dataset(p)
            t = df["t"].to_numpy()
            gain = 1.0 + drift * (t - t[0]) / max(t[-1] - t[0], 1e-12)
            cols = {c: df[c].to_numpy(float) for c in df.columns}
            cols["alpha_v"] = off + (cols["alpha_v"] - off) * gain
            write_dataset(p, cols)
    hidden = specmod.apply_overrides(base.raw, [f"campaign.seed={case['campaign_seed']}"])
    manifest["spec"] = hidden
    manifest["spec_sha256"] = "hidden"
    write_json(dest / "manifest.json", manifest)
    return dest


def _rel_err(true: float, fitted: float | None) -> float:
    if fitted is None:
        return math.inf
    return abs(float(fitted) - float(true)) / abs(float(true))


def score_case(case: dict[str, Any], diag: dict[str, Any]) -> dict[str, Any]:
    """Score one diagnosis against the hidden truth."""
    verdict = diag["verdict"]
    found = [e["effect"] for e in diag.get("effects", [])]
    fitted = {k: v for e in diag.get("effects", []) for k, v in e["params"].items()}
    shrink = float(diag["gap"]["shrink_pct"])
    out: dict[str, Any] = {"verdict": verdict, "found": found, "fitted": fitted, "shrink_pct": shrink}
    kind = case["kind"]
    if kind == "single":
        eff = case["truth_effects"][0]
        param = EFFECTS[eff].param
        err = _rel_err(case["truth_params"][param], fitted.get(param) if eff in found else None)
        out.update(top1=verdict == eff, param_error=err, param_ok=bool(err <= MAG_TOL + 1e-12))
    elif kind == "none":
        out.update(correct=verdict == "none", turned_into_effect=verdict in EFFECTS)
    elif kind == "two":
        effs = case["truth_effects"]
        errs = {
            EFFECTS[e].param: _rel_err(case["truth_params"][EFFECTS[e].param], fitted.get(EFFECTS[e].param))
            if e in found else math.inf
            for e in effs
        }  # fmt: skip
        out.update(both=all(e in found for e in effs), top1_in_truth=verdict in effs, param_errors=errs)
    else:
        ok = verdict == "unexplained" or (verdict in EFFECTS and shrink >= MOST)
        out.update(correct=bool(ok))
    return out


def totals(cases: list[dict[str, Any]]) -> dict[str, Any]:
    """Pooled scores with the MISSION's targets."""

    def share(xs: list[bool]) -> float:
        return 100.0 * float(np.mean(xs)) if xs else math.nan

    single = [c for c in cases if c["kind"] == "single"]
    none = [c for c in cases if c["kind"] == "none"]
    two = [c for c in cases if c["kind"] == "two"]
    out = [c for c in cases if c["kind"] == "out"]
    per_effect = {}
    for eff in RANGES:
        cs = [c for c in single if c["truth_effects"][0] == eff]
        if cs:
            per_effect[eff] = {
                "n": len(cs),
                "top1_pct": share([c["score"]["top1"] for c in cs]),
                "param_ok_pct": share([c["score"]["param_ok"] for c in cs]),
                "median_shrink_pct": float(np.median([c["score"]["shrink_pct"] for c in cs])),
            }
    res = {
        "n_cases": len(cases),
        "single": {
            "n": len(single),
            "top1_pct": share([c["score"]["top1"] for c in single]),
            "param_within_20pct_pct": share([c["score"]["param_ok"] for c in single]),
            "median_shrink_pct": float(np.median([c["score"]["shrink_pct"] for c in single])) if single else math.nan,
            "per_effect": per_effect,
        },
        "none": {
            "n": len(none),
            "correct_pct": share([c["score"]["correct"] for c in none]),
            "turned_into_effect": int(sum(c["score"]["turned_into_effect"] for c in none)),
        },
        "two": {
            "n": len(two),
            "both_found_pct": share([c["score"]["both"] for c in two]),
            "top1_in_truth_pct": share([c["score"]["top1_in_truth"] for c in two]),
            "params_within_20pct_pct": share(
                [err <= MAG_TOL + 1e-12 for c in two for err in c["score"]["param_errors"].values()]
            ),
        },
        "out_of_library": {"n": len(out), "correct_pct": share([c["score"]["correct"] for c in out])},
        "targets": {
            "single_top1_pct": 90.0,
            "single_param_within_20pct_pct": 80.0,
            "none_turned_into_effect": 0,
            "out_of_library_correct_pct": 75.0,
        },
    }
    res["passed"] = bool(
        (res["single"]["top1_pct"] >= 90.0 or not single)
        and (res["single"]["param_within_20pct_pct"] >= 80.0 or not single)
        and res["none"]["turned_into_effect"] == 0
        and (res["out_of_library"]["correct_pct"] >= 75.0 or not out)
    )
    return res


def blindtest(
    n: int = 40,
    seed: int = 0,
    out: Path = Path("."),
    progress: Progress | None = None,
    workers: int | None = None,
    keep: bool = False,
    quick: bool = False,
) -> dict[str, Any]:
    """Run ``n`` blind cases drawn with ``seed``; writes ``out/blindtest.json`` (every case and the totals) and
    returns it. ``workers``: processes per diagnosis (default 2); ``keep`` keeps the case run directories
    under ``out/blind_cases/``; ``quick`` runs the shortened campaign of :func:`campaign_spec`."""
    from .build import build_all
    from .diagnose import diagnose_run

    say = progress or (lambda _m: None)
    t0 = time.perf_counter()
    cases = plan(n, seed)
    sim = campaign_spec(quick)
    fmus = build_all()
    out = Path(out)
    root = out / "blind_cases" if keep else Path(tempfile.mkdtemp(prefix="flexjoint-blind-"))
    results = []
    try:
        for case in cases:
            d = root / f"case_{case['case']:03d}"
            if d.exists():
                shutil.rmtree(d)
            tc = time.perf_counter()
            make_rig_run(case, d, fmus, quick)
            diag = diagnose_run(d, sim, d, workers=workers)
            sc = score_case(case, diag)
            results.append({**case, "score": sc, "timing_s": time.perf_counter() - tc})
            say(
                f"case {case['case']}: {case['kind']} {case['truth_effects']} {case['truth_params']} "
                f"-> {sc['verdict']} {sc['fitted']} shrink {sc['shrink_pct']:.1f} %"
            )
    finally:
        if not keep:
            shutil.rmtree(root, ignore_errors=True)
    doc = {
        "n": n,
        "seed": seed,
        "spec": BLIND_SPEC.name,
        "quick": quick,
        "cases": sorted(results, key=lambda c: c["case"]),
        "totals": totals(results),
        "timing_s": time.perf_counter() - t0,
    }
    write_json(out / "blindtest.json", doc)
    return doc
