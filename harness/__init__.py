"""flexjoint-harness: FMU co-simulation, ARMAX identification and sim-to-real diagnosis of a flexible joint.

The package follows the data flow, one subpackage per stage::

    spec -> rig (campaign on the FMU twin, or real records) -> run directory (rundir)
         -> ident (calibration, preprocessing, ARMAX grid, models exported as FMUs, cross-fit, acceptance)
         -> diagnosis (recalibration, effects, where the gap lies; blind test)
         -> twin, predict, design (the labs' Part II: a controller on the identified rig, its loop with bands)
         -> render (report.md and figures, the Rerun recording)

``fmu`` holds the FMUs' build, XML reader and binding; ``pipeline`` runs every stage for ``flexjoint run``.
The names below are the public API, in that order. They are imported on first use (PEP 562), so that
``import harness.ident.armax`` or a Dask worker unpickling a task loads only the stages it needs.
"""

from __future__ import annotations

import importlib
from typing import Any

from ._version import __version__

# public name -> (module of the package, attribute), in data-flow order
_API: dict[str, tuple[str, str]] = {
    "Experiment": ("spec", "Experiment"),
    "Spec": ("spec", "Spec"),
    "SpecError": ("spec", "SpecError"),
    "load_spec": ("spec", "load"),
    "build_all": ("fmu.build", "build_all"),
    "generate_signal": ("rig.signals", "generate"),
    "run_campaign": ("rig.campaign", "run_campaign"),
    "simulate_spec": ("rig.campaign", "simulate_spec"),
    "import_records": ("rig.records", "import_records"),
    "Controller": ("rig.controller", "Controller"),
    "parse_controller": ("rig.controller", "parse_controller"),
    "DataError": ("rundir", "DataError"),
    "Manifest": ("rundir", "Manifest"),
    "RunDir": ("rundir", "RunDir"),
    "load_run": ("rundir", "load_run"),
    "read_dataset": ("rundir", "read_dataset"),
    "Calibration": ("ident.calibration", "Calibration"),
    "calibrate_run": ("ident.calibration", "calibrate_run"),
    "filter_coefficients": ("ident.preprocess", "filter_coefficients"),
    "filter_response": ("ident.preprocess", "filter_response"),
    "ArmaxModel": ("ident.armax", "ArmaxModel"),
    "compare": ("ident.armax", "compare"),
    "estimate": ("ident.armax", "estimate"),
    "predict": ("ident.armax", "predict"),
    "resid": ("ident.armax", "resid"),
    "simulate": ("ident.armax", "simulate"),
    "prepare": ("ident.identify", "prepare"),
    "run_grid": ("ident.identify", "run_grid"),
    "export_model": ("ident.export", "export_model"),
    "crossfit_run": ("ident.crossfit", "crossfit_run"),
    "accept": ("ident.accept", "accept"),
    "diagnose_run": ("diagnosis.diagnose", "diagnose_run"),
    "Diagnosis": ("diagnosis.result", "Diagnosis"),
    "blindtest": ("diagnosis.blindtest", "blindtest"),
    "Twin": ("twin", "Twin"),
    "load_twin": ("twin", "load_twin"),
    "LoopSpecs": ("loopspecs", "LoopSpecs"),
    "reference_from": ("prediction", "reference_from"),
    "Prediction": ("prediction", "Prediction"),
    "predict_loop": ("prediction", "predict"),  # harness.predict is ARMAX's k-step predictor (MATLAB's predict)
    "accept_prediction": ("prediction", "accept_prediction"),
    "Design": ("design", "Design"),
    "design_controller": ("design", "design"),  # harness.design is the module
    "write_report": ("render.report", "write_report"),
    "log_run": ("render.viewer", "log_run"),
    "report_directory": ("render.directory", "report_directory"),
    "write_prediction": ("render.prediction", "write_prediction"),
    "write_design": ("render.prediction", "write_design"),
    "identify_run": ("ident.identify", "identify_run"),
    "run_pipeline": ("pipeline", "run_pipeline"),
    "run_sweep": ("sweep", "run_sweep"),
    "Executor": ("executor", "Executor"),
    "pin_numerics": ("numerics", "pin_numerics"),  # standard library only: callable before numpy loads
}

__all__ = ["__version__", *_API]


def __getattr__(name: str) -> Any:
    """The public name ``name``, imported from its module on first use."""
    if name not in _API:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    module, attr = _API[name]
    value = getattr(importlib.import_module(f"{__name__}.{module}"), attr)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_API})
