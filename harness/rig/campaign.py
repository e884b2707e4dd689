"""Campaigns: run every experiment of a spec on the rig twin and write a run directory.

``run_campaign(spec, out)`` writes ``out/data/<experiment>.parquet`` (columns ``t, u, theta_v, alpha_v`` and
the true ``theta, alpha`` [deg]; a comb experiment adds ``tau_tip`` [N m] and ``comb_angle`` [deg, NaN between
holds]; a closed-loop experiment adds its reference ``ref`` [deg], and its ``u`` is the controller's command) and
``out/manifest.json`` (resolved spec, its hash, FMU hashes, seeds, versions). The same spec gives the same bytes.
"""

from __future__ import annotations

import importlib.metadata
import platform
import zlib
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import fmpy
import numpy as np
import pandas
import pyarrow
import scipy

from .._version import __version__
from ..executor import Executor, FmuBytes, fmu_bytes, worker_rig
from ..fmu.build import build_all
from ..fmu.plant import PlantParams, mass_stiffness
from ..rundir import ExperimentEntry, Manifest, RunDir, new_run, write_dataset
from ..spec import Experiment, Spec
from .controller import Controller, delayed
from .signals import generate

Progress = Callable[[str], None]


def experiment_seed(spec: Spec, exp: Experiment) -> int:
    """Seed of one experiment's signal and noise: stable in the spec seed and the experiment name."""
    return (spec.seed * 1_000_003 + zlib.crc32(exp.name.encode())) % (2**31 - 1)


def comb_schedule(exp: Experiment, Ts: float, plant: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Tip-torque schedule of a comb calibration: smooth ramps between static holds at each comb deflection.

    The comb holds the tip at l [cm] from rest at D [cm]: angle = -atan(l / D) (lab 1's table 1). The torque
    is the static torque giving that deflection on the twin (clamped hub). Returns (tau_tip [N m], comb_angle
    [deg], NaN outside the settled part of each hold).
    """

    p = exp.params
    ls = np.asarray(p.get("deflections_cm", [-3.7, -3.05, -2.4, -1.8, -1.1, -0.5, 0, 0.6, 1.4, 2, 2.65, 3.3, 3.9]))
    D, hold, ramp = float(p.get("D_cm", 40.0)), float(p.get("hold", 3.0)), float(p.get("ramp", 1.0))
    n = int(round(exp.duration / Ts))
    angles = -np.degrees(np.arctan(ls / D))
    pp = PlantParams(**{k: v for k, v in plant.items() if k in PlantParams.__dataclass_fields__})
    K = mass_stiffness(pp)[1]
    compliance = float(np.sum(1.0 / np.diag(K)[1:]))  # clamped hub: a_i = tau / k_i, alpha = sum a_i [rad/N m]
    torques = np.radians(angles) / compliance
    tau = np.zeros(n)
    comb = np.full(n, np.nan)
    t = np.arange(n) * Ts
    prev = 0.0
    start = 0.0
    for a, q in zip(angles, torques, strict=True):
        in_ramp = (t >= start) & (t < start + ramp)
        s = (t[in_ramp] - start) / ramp
        tau[in_ramp] = prev + (q - prev) * 0.5 * (1 - np.cos(np.pi * s))
        in_hold = (t >= start + ramp) & (t < start + ramp + hold)
        tau[in_hold] = q
        comb[in_hold] = a
        prev, start = q, start + ramp + hold
    if start > exp.duration + 1e-9:
        raise ValueError(f"experiment {exp.name!r}: duration {exp.duration} s too short for {len(ls)} holds")
    tau[t >= start] = prev
    return tau, comb


def experiment_inputs(spec: Spec, exp: Experiment) -> tuple[np.ndarray, dict, dict, np.ndarray | None, Any]:
    """One experiment's signal (command [V], or the reference [deg] of a closed loop), plant and DAQ parameters (the
    DAQ's seed drawn for the experiment), tip torque [N m] and comb angles [deg] of a comb calibration (else None)."""
    Ts = spec.Ts
    n = int(round(exp.duration * spec.sample_rate))
    seed = experiment_seed(spec, exp)
    plant = {"internal_step": spec.internal_step, **spec.plant, **exp.plant}
    daq = {**spec.daq, **exp.daq}
    daq["seed"] = (int(daq.get("seed", 0)) * 7919 + seed) % (2**31 - 1)  # FMI Integer is 32-bit
    if exp.signal == "comb":
        plant["hub_locked"] = 1
        tau, comb = comb_schedule(exp, Ts, plant)
        return np.zeros(n), plant, daq, tau, comb
    u = generate(exp.signal, n, Ts, exp.params, seed)
    return u, plant, daq, None, None


def reference_rad(controller: Controller, ref_deg: np.ndarray) -> np.ndarray:
    """What the controller acts on [rad]: a closed-loop experiment's reference [deg] (the log's) delayed by the
    controller's ref_delay samples."""
    return np.radians(delayed(ref_deg, controller.ref_delay))


def simulate_experiment(rig: Any, spec: Spec, exp: Experiment) -> dict[str, np.ndarray]:
    """Run one experiment of a spec on a loaded :class:`harness.fmu.cosim.Rig`; returns the dataset columns."""
    u, plant, daq, tau, comb = experiment_inputs(spec, exp)
    if exp.loop == "closed":
        c = spec.controller
        if c is None:  # the spec refuses a closed-loop experiment without a [controller]
            raise ValueError(f"experiment {exp.name!r} runs closed loop but the spec has no [controller] table")
        ref = reference_rad(c, u)
        res = rig.run_closed(ref, spec.Ts, c.fmu_parameters(spec.sample_rate), plant=plant, daq=daq)
        return {**{k: res[k] for k in ("t", "u", "theta_v", "alpha_v", "theta", "alpha")}, "ref": u}
    res = rig.run(u, spec.Ts, plant=plant, daq=daq, tau_tip=tau)
    cols = {k: res[k] for k in ("t", "u", "theta_v", "alpha_v", "theta", "alpha")}
    if tau is not None:
        cols["tau_tip"] = tau
        cols["comb_angle"] = comb
    return cols


def _simulate_task(exp: Experiment, spec: Spec, fmus: Mapping[str, FmuBytes]) -> dict[str, np.ndarray]:
    """One experiment on this worker's rig (loaded once per worker process)."""
    return simulate_experiment(worker_rig(fmus), spec, exp)


def simulate_spec(
    spec: Spec,
    fmus: Mapping[str, Path | FmuBytes],
    experiments: list[Experiment] | None = None,
    workers: int | None = None,
    progress: Progress | None = None,
    scheduler: str | None = None,
) -> dict[str, dict[str, np.ndarray]]:
    """Simulate a spec's experiments and return their columns, without writing anything.

    Experiments are tasks of a :class:`harness.Executor`; the FMUs travel as bytes and each worker loads the rig
    once. Results do not depend on where they ran.

    Parameters
    ----------
    spec : Spec
        The campaign.
    fmus : mapping of str to Path or FmuBytes
        The built plant, DAQ (and controller) FMUs (:func:`harness.build_all`).
    experiments : list of Experiment, optional
        Which to run; default all of the spec's, calibration experiments first.
    workers, scheduler : optional
        Where to run (:class:`harness.Executor`): None the default cluster, 1 serial, or a scheduler's address.
    progress : callable, optional
        Called with one line of text as each experiment is done.

    Returns
    -------
    dict of str to dict of str to numpy.ndarray
        ``{experiment: {column: values}}`` in spec order: ``t`` [s], ``u`` [V], ``theta_v``, ``alpha_v`` [V] as
        the DAQ measured them, the true ``theta``, ``alpha`` [deg], and ``ref`` [deg] for a closed loop.
    """
    exps = spec.all_experiments() if experiments is None else experiments
    shipped = {k: v if isinstance(v, FmuBytes) else fmu_bytes(v) for k, v in fmus.items()}
    if len(exps) <= 1 and scheduler is None:
        workers = 1  # one task: a cluster would only add its start-up
    with Executor(workers, scheduler, progress) as ex:
        cols = ex.map(_simulate_task, exps, spec, shipped, labels=[e.name for e in exps])
    return {e.name: c for e, c in zip(exps, cols, strict=True)}


def versions() -> dict[str, str]:
    return {
        "harness": __version__,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "fmpy": fmpy.__version__,
        "control": importlib.metadata.version("control"),  # not imported: 1.1 s of a worker's 1.75 s start
        "pandas": pandas.__version__,
        "pyarrow": pyarrow.__version__,
    }


def run_campaign(
    spec: Spec,
    out: Path,
    fmus: dict[str, Path] | None = None,
    workers: int | None = None,
    progress: Progress | None = None,
    scheduler: str | None = None,
    force: bool = False,
) -> Manifest:
    """Run a spec's experiments on the rig twin into a new run directory.

    The experiments are simulated by :func:`simulate_spec`; the run is written by this process only, aside, and
    moved into place when complete (:func:`harness.rundir.new_run`).

    Parameters
    ----------
    spec : Spec
        The campaign (:func:`harness.load_spec`).
    out : Path
        The run directory to write: ``manifest.json`` and ``data/<experiment>.parquet``.
    fmus : dict of str to Path, optional
        The built FMUs; default :func:`harness.build_all`.
    workers : int, optional
        Local worker processes (None: the default cluster or the enclosing session's; 1: serial, in-process).
    progress : callable, optional
        Called with one line of text as each experiment is done.
    scheduler : str, optional
        A Dask scheduler's address (``tcp://HOST:8786``) to run on instead.
    force : bool
        Replace a run already in ``out`` (every file of it removed).

    Returns
    -------
    Manifest
        The run's manifest, as written.
    """
    with new_run(out, force) as work:
        return _campaign(spec, work, fmus, workers, progress, scheduler)


def _campaign(
    spec: Spec,
    out: Path,
    fmus: dict[str, Path] | None,
    workers: int | None,
    progress: Progress | None,
    scheduler: str | None,
) -> Manifest:
    closed = any(e.loop == "closed" for e in spec.all_experiments())
    fmus = {k: v for k, v in (fmus or build_all()).items() if k != "controller" or closed}  # the FMUs it runs
    shipped = {k: fmu_bytes(v) for k, v in fmus.items()}  # read and hashed once: the tasks' bytes, the manifest's sha
    data = simulate_spec(spec, shipped, workers=workers, progress=progress, scheduler=scheduler)
    for name, cols in data.items():
        write_dataset(RunDir(out).dataset(name), cols)
    manifest = Manifest(
        kind="campaign",
        spec=spec.raw,
        spec_file=Path(spec.path).name,
        spec_sha256=spec.sha256(),
        seed=spec.seed,
        sample_rate=spec.sample_rate,
        fmus={k: {"file": Path(v).name, "sha256": shipped[k].sha256} for k, v in fmus.items()},
        versions=versions(),
        experiments=[
            ExperimentEntry(
                name=e.name,
                role=e.role,
                signal=e.signal,
                n=int(round(e.duration * spec.sample_rate)),
                seed=experiment_seed(spec, e),
                loop="closed" if e.loop == "closed" else None,
                controller=spec.controller.to_dict() if e.loop == "closed" and spec.controller else None,
            )
            for e in spec.all_experiments()
        ],
    )
    manifest.write(out)
    return manifest
