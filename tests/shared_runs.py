"""The runs several test files read, as they are made: each is made once per session by a fixture of conftest.py
(``lab_campaign``, ``diagnosed_run``, ``quanser_run``, ``cu_lone_run``) and shared, read-only, by every test process
(:func:`shared_dir`, which a test file's own shared run uses too)."""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from harness import spec as specmod
from harness.diagnosis.blindtest import campaign_spec
from harness.diagnosis.diagnose import diagnose_run
from harness.ident.calibration import calibrate_run
from harness.ident.crossfit import crossfit_run
from harness.ident.identify import prepare, run_grid, write_grid
from harness.rig.campaign import run_campaign
from harness.rig.records import ImportOptions, import_records
from harness.rundir import Manifest, load_run, read_dataset, write_dataset

try:
    import fcntl
except ImportError:  # Windows: each test process makes its own
    fcntl = None  # type: ignore[assignment]

REAL = Path(__file__).parent / "fixtures" / "real"
CU = [REAL / "flexibleArm_test_3.txt", REAL / "flexibleArm_test_4.txt"]
CU_IMPORT = ImportOptions(  # the fixture README's import command
    columns={"0": "t", "1": "theta", "2": "-alpha", "5": "ref", "6": "u"},
    units={"t": "ms", "theta": "rad", "alpha": "m", "ref": "rad"},
    link_length=0.45,
    zero_alpha=True,
)
QUANSER = [REAL / "rfl_lqr_sqwave_pm30deg_500Hz.csv", REAL / "rfl_lqr_sqwave_pm30deg_500Hz_aux.csv"]
QUANSER_COLUMNS = {"u": "u", "theta_deg": "theta", "alpha_deg": "alpha", "theta_ref_deg": "ref"}
QUANSER_IMPORT = ImportOptions(  # the fixture README's import command: t is in both files, named by its file's
    columns={f"{QUANSER[0].stem}:t": "t", **QUANSER_COLUMNS},
    units={"theta": "deg", "alpha": "deg", "ref": "deg"},
    theta_sensor="encoder",
    counts_per_rev=4096,
)
REAL_EXPERIMENTS = ("prbs_small", "square_large", "chirp_slow")  # 10 s each: ~30 s to diagnose on 2 cores
REAL_GRID = {"na": [2, 4], "nb": [1, 2], "nc": [1, 2]}


def make_lab_campaign(path: Path, fmus: dict[str, Path]) -> None:
    """The default spec's campaign (specs/lab.toml: its calibration experiments and 9 identification experiments),
    simulated serially."""
    run_campaign(specmod.load("lab"), path, fmus=fmus, workers=1)


def make_quanser_run(path: Path) -> None:
    """The Quanser record (:data:`QUANSER`, its two files joined on t) imported as the fixture README says and
    diagnosed against the nominal spec (serially), its diagnosis.json in the run directory."""
    import_records([f"quanser={QUANSER[0]}+{QUANSER[1]}"], path, QUANSER_IMPORT)
    diagnose_run(path, "nominal", path, workers=1)


def make_cu_lone_run(path: Path) -> None:
    """The CU unit's first record (:data:`CU` [0]) alone, imported as the fixture README says into ``path/run`` and
    diagnosed there against its lab sheet (specs/cu_flexible_arm.toml, serially); the Diagnosis that
    :func:`diagnose_run` returned, written by itself, is ``path/returned.json``."""
    import_records([CU[0]], path / "run", CU_IMPORT)
    diagnose_run(path / "run", "cu_flexible_arm", workers=1).write(path / "returned.json")


def make_diagnosed_run(path: Path) -> None:
    """A run through every stage: the blind rig with Coulomb friction (0.05 N m) and a one-sample delay, the three
    10 s experiments :data:`REAL_EXPERIMENTS`, calibrated, identified on the small grid :data:`REAL_GRID`,
    cross-fitted through the exported FMUs and diagnosed (serially) against the blind campaign's linear rig."""
    spec = campaign_spec(quick=True, overrides=["plant.coulomb_torque=0.05", "daq.delay_samples=1", "campaign.seed=11"])
    raw = specmod.apply_overrides(spec.raw, [])
    raw["experiment"] = [dict(e, duration=10.0) for e in raw["experiment"] if e["name"] in REAL_EXPERIMENTS]
    run_campaign(specmod.from_dict(raw, spec.path), path, workers=1)
    cal = calibrate_run(path)
    ident = dict(specmod.IDENTIFY_DEFAULTS, **REAL_GRID)
    prepared = prepare(load_run(path), cal, float(ident["af"]), str(ident["output"]))
    write_grid(run_grid(prepared, ident, workers=1), path, ident, cal)
    crossfit_run(path)
    diagnose_run(path, campaign_spec(quick=True), workers=1)


def perturbed_copy(src: Path, dst: Path, draw: int) -> Path:
    """A copy of run directory ``src`` at ``dst`` whose records' logged volts and command are multiplied by
    1 + 1e-12 x a standard normal draw (numpy's generator seeded ``draw``): what another CPU's rounding does."""
    shutil.copytree(src, dst)
    rng = np.random.default_rng(draw)
    for e in Manifest.load(dst).experiments:
        path = dst / "data" / f"{e.name}.parquet"
        d = read_dataset(path)
        cols = {c: d[c].to_numpy() for c in d.columns}
        for c in ("theta_v", "alpha_v", "u"):
            cols[c] = cols[c] * (1.0 + 1e-12 * rng.standard_normal(cols[c].size))
        write_dataset(path, cols)
    return dst


def shared_dir(tmp_path_factory: pytest.TempPathFactory, name: str, make: Callable[[Path], None]) -> Path:
    """The directory ``name`` that ``make(path)`` fills (``path`` does not exist yet), made once for the whole
    session: by the first test process that asks for it while the others (xdist's workers) wait for it on a lock
    file, in the directory their temporary directories share. Read-only for the tests: one that writes into it
    copies it first."""
    base = tmp_path_factory.getbasetemp()
    if fcntl is not None and os.environ.get("PYTEST_XDIST_WORKER"):
        base = base.parent
    path = base / name
    with open(base / f"{name}.lock", "w") as lock:
        if fcntl is not None:
            fcntl.flock(lock, fcntl.LOCK_EX)
        if not path.is_dir():
            work = Path(tempfile.mkdtemp(prefix=f".{name}-", dir=base))
            try:
                make(work / name)
                (work / name).rename(path)
            finally:
                shutil.rmtree(work, ignore_errors=True)
    return path
