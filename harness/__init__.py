"""flexjoint-harness: FMU co-simulation, ARMAX identification and sim-to-real diagnosis of a flexible joint.

The package follows the data flow, one subpackage per stage::

    spec -> rig (campaign on the FMU twin, or real records) -> run directory (rundir)
         -> ident (calibration, preprocessing, ARMAX grid, models exported as FMUs, cross-fit, acceptance)
         -> diagnosis (recalibration, effects, where the gap lies; blind test)
         -> render (report.md and figures, the Rerun recording)

``fmu`` holds the FMUs' build, XML reader and binding; ``pipeline`` runs every stage for ``flexjoint run``.
The names below are the public API, in that order.
"""

# ruff: noqa: I001  (the imports are in data-flow order, not alphabetical)
from ._version import __version__
from .spec import Experiment, Spec, SpecError
from .spec import load as load_spec
from .fmu.build import build_all
from .rig.signals import generate as generate_signal
from .rig.campaign import run_campaign, simulate_spec
from .rig.records import import_records
from .rundir import DataError, Manifest, RunDir, load_run, read_dataset
from .ident.calibration import Calibration, calibrate_run
from .ident.preprocess import filter_coefficients, filter_response
from .ident.armax import ArmaxModel, compare, estimate, predict, resid, simulate
from .ident.identify import prepare, run_grid
from .ident.export import export_model
from .ident.crossfit import crossfit_run
from .ident.accept import accept
from .diagnosis.diagnose import diagnose_run
from .diagnosis.result import Diagnosis
from .diagnosis.blindtest import blindtest
from .render.report import write_report
from .render.viewer import log_run
from .pipeline import identify_run, run_pipeline
from .sweep import run_sweep
from .executor import Executor

__all__ = [
    "__version__",
    "Experiment",
    "Spec",
    "SpecError",
    "load_spec",
    "build_all",
    "generate_signal",
    "run_campaign",
    "simulate_spec",
    "import_records",
    "DataError",
    "Manifest",
    "RunDir",
    "load_run",
    "read_dataset",
    "Calibration",
    "calibrate_run",
    "filter_coefficients",
    "filter_response",
    "ArmaxModel",
    "compare",
    "estimate",
    "predict",
    "resid",
    "simulate",
    "prepare",
    "run_grid",
    "export_model",
    "crossfit_run",
    "accept",
    "diagnose_run",
    "Diagnosis",
    "blindtest",
    "write_report",
    "log_run",
    "identify_run",
    "run_pipeline",
    "run_sweep",
    "Executor",
]
