"""Co-simulation master: the plant FMU and the DAQ FMU coupled step by step through fmpy's ``FMU2Slave``.

Every communication step k (one sample, Ts = 1/sample_rate, or a divisor of it):

1. DAQ inputs <- command u_k, plant theta and alpha_gauge at t_k; read u_plant (the command over [t_k, t_k + h));
   ``daq.doStep(t_k, h)``; read the samples theta_v, alpha_v taken at t_k;
2. plant input u <- u_plant (and the tip torque); ``plant.doStep(t_k, h)``.

Closed loop (:meth:`Rig.run_closed`, with the controller FMU): reference -> controller -> DAQ (DAC, delay) ->
plant -> DAQ (ADC) -> controller. Every step k:

1. DAQ inputs <- plant theta and alpha_gauge at t_k; read the DAQ's preview of the samples theta_v, alpha_v at t_k;
2. controller inputs <- ref_k and those samples; ``controller.doStep(t_k, h)``; read its command u_k;
3. DAQ input u <- u_k; read u_plant; ``daq.doStep(t_k, h)`` (takes the same samples, now with u_k); then the plant
   as above.

So u_k acts over [t_k, t_k+1) (direct feedthrough, as a lab controller that reads, computes and writes within the
sample); a DAQ delay adds its samples on top.

Loading, parameters and initialisation go through :mod:`harness.fmu.binding`; the per-sample loops run in C
(``fmus/master/master.c``, built once into the FMU cache), which calls the FMI functions of the loaded binaries
through their function pointers in exactly this order, with the same results to the bit as the same calls from
Python (their speed: the manual's validation page). A doStep status above fmi2Warning stops the run with the FMU's
own log message.
"""

from __future__ import annotations

import ctypes
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
from fmpy.fmi2 import fmi2Real, fmi2ValueReference

from .binding import Instance, load
from .build import build_master

__all__ = ["DEG", "DIVERGED_ALPHA_DEG", "ClosedLoopError", "Rig", "controller_parameters"]

DEG = 180.0 / np.pi
DIVERGED_ALPHA_DEG = 45.0  # a closed loop whose link deflects more has diverged (a real link would break)
CALIBRATION = {"theta_gain": "pot_gain", "theta_offset": "pot_offset", "alpha_gain": "gauge_gain"}
CALIBRATION |= {"alpha_offset": "gauge_offset"}  # controller parameter <- the DAQ parameter it defaults to
DONE, FAIL_PLANT, FAIL_DAQ, FAIL_CONTROLLER, DIVERGED = range(5)  # what fmus/master/master.c's loops return


class _Unit(ctypes.Structure):
    """master.c's ``Unit``: one FMU instance's component and its fmi2GetReal, fmi2SetReal, fmi2DoStep."""

    _fields_ = [("component", ctypes.c_void_p), ("get", ctypes.c_void_p), ("set", ctypes.c_void_p)]
    _fields_ += [("step", ctypes.c_void_p)]


def _unit(fmu: Instance) -> _Unit:
    f = fmu.dll
    addr = [ctypes.cast(fn, ctypes.c_void_p).value for fn in (f.fmi2GetReal, f.fmi2SetReal, f.fmi2DoStep)]
    return _Unit(fmu.component, *addr)


@cache
def _master() -> ctypes.CDLL:
    """The co-simulation master's step loops (fmus/master/master.c), built once into the FMU cache."""
    lib = ctypes.CDLL(str(build_master()))
    ptr, n, real = ctypes.c_void_p, ctypes.c_long, ctypes.c_double  # pointers: units, value references, arrays
    lib.run_open.argtypes = [*[ptr] * 8, n, real, *[ptr] * 3]
    lib.run_closed.argtypes = [*[ptr] * 12, n, real, real, real, *[ptr] * 4]
    lib.run_open.restype = lib.run_closed.restype = ctypes.c_int
    return lib


def _doubles(a: np.ndarray) -> int:
    """The address of a C-contiguous float64 array's data (the loops read and write it in place)."""
    assert a.dtype == np.float64 and a.flags.c_contiguous
    return int(a.__array_interface__["data"][0])


def controller_parameters(
    controller: dict[str, Any], daq: dict[str, Any], daq_variables: dict[str, Any], Ts: float
) -> dict[str, Any]:
    """The controller FMU's parameters of a closed loop sampled at ``Ts`` [s]: ``controller`` (with its
    ``alpha_bias`` [deg] folded into alpha_offset) on top of the angle calibration of the DAQ's parameters ``daq``
    (their start values in ``daq_variables``, name -> variable with ``.start``)."""
    params = {k: float(daq.get(v, daq_variables[v].start)) for k, v in CALIBRATION.items()}
    params |= {"sample_rate": 1.0 / Ts, **controller}
    bias = float(params.pop("alpha_bias", 0.0))  # deg the controller reads on top of alpha: its zero error
    params["alpha_offset"] -= bias / params["alpha_gain"]
    return params


class ClosedLoopError(ValueError):
    """A closed loop diverged: its controller destabilises the rig."""


class Rig:
    """The rig twin: plant and DAQ FMUs (and the controller FMU for closed loops) loaded once and re-run for each
    experiment.

    ``Rig(plant_fmu, daq_fmu)`` then ``rig.run(u, Ts, plant={...}, daq={...})``; ``Rig(plant_fmu, daq_fmu,
    controller_fmu)`` also ``rig.run_closed(ref, Ts, controller={...}, plant=..., daq=...)``. Use as a context
    manager or call :meth:`close`.
    """

    def __init__(self, plant_fmu: Path, daq_fmu: Path, controller_fmu: Path | None = None) -> None:
        self.plant = load(Path(plant_fmu), "plant")
        self.daq = load(Path(daq_fmu), "daq")
        self.controller = load(Path(controller_fmu), "controller") if controller_fmu is not None else None
        p, d = self.plant, self.daq
        self._p_in = (fmi2ValueReference * 2)(p.vr("u"), p.vr("tau_tip"))
        self._p_out = (fmi2ValueReference * 4)(p.vr("theta"), p.vr("alpha"), p.vr("alpha_gauge"), p.vr("theta_dot"))
        self._d_in = (fmi2ValueReference * 3)(d.vr("u"), d.vr("theta"), d.vr("alpha_gauge"))
        self._d_out = (fmi2ValueReference * 3)(d.vr("u_plant"), d.vr("theta_v"), d.vr("alpha_v"))
        self._master = _master()
        self._units = [_unit(x) for x in (p, d, self.controller) if x is not None]
        if self.controller is not None:  # a closed loop's value references: DAQ in, samples, command; controller
            c = self.controller
            self._d_meas = (fmi2ValueReference * 2)(d.vr("theta"), d.vr("alpha_gauge"))
            self._d_samp = (fmi2ValueReference * 2)(d.vr("theta_v"), d.vr("alpha_v"))
            self._d_u = (fmi2ValueReference * 1)(d.vr("u"))
            self._c_in = (fmi2ValueReference * 3)(c.vr("ref"), c.vr("theta_v"), c.vr("alpha_v"))
            self._c_out = (fmi2ValueReference * 1)(c.vr("u"))

    def _check_master(self, code: int, k: int, status: int, Ts: float) -> None:
        """Raise the FMU's own error when the master's step loop stopped at sample ``k`` on a refused doStep."""
        fmu = {FAIL_PLANT: self.plant, FAIL_DAQ: self.daq, FAIL_CONTROLLER: self.controller}.get(code)
        if fmu is not None:
            fmu.check(status, f"doStep at t={k * Ts:.4f} s")
        elif code != DONE:
            raise RuntimeError(f"co-simulation master returned {code}")

    def __enter__(self) -> Rig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self.plant.free()
        self.daq.free()
        if self.controller is not None:
            self.controller.free()

    def run(
        self,
        u: np.ndarray,
        Ts: float,
        plant: dict[str, Any] | None = None,
        daq: dict[str, Any] | None = None,
        tau_tip: np.ndarray | None = None,
    ) -> dict[str, np.ndarray]:
        """Run one experiment: command ``u`` [V] sampled at ``Ts`` [s], optional tip torque [N m] per sample.

        Returns arrays of length ``len(u)``: ``t`` [s], ``u`` [V], ``u_plant`` [V], ``theta_v``, ``alpha_v`` [V]
        (what the DAQ measured at t_k) and the true ``theta``, ``alpha`` [deg] and ``theta_dot`` [deg/s] at t_k.
        """
        u = np.ascontiguousarray(u, dtype=float)
        n = u.size
        if not np.all(np.isfinite(u)):
            raise ValueError("command u contains NaN or inf")
        tau = np.zeros(n) if tau_tip is None else np.ascontiguousarray(tau_tip, dtype=float)
        if tau.shape != (n,):
            raise ValueError(f"tip torque has {tau.size} samples, the command {n}")
        daq_params = {"sample_rate": 1.0 / Ts, **(daq or {})}
        stop = n * Ts
        pl, dq = self.plant, self.daq
        pl.initialize(plant or {}, stop)
        dq.initialize(daq_params, stop)

        fp, fd = pl.dll, dq.dll
        cp, cd = pl.component, dq.component
        pout = (fmi2Real * 4)()

        # initial plant outputs feed the DAQ's first sample
        pl.check(fp.fmi2GetReal(cp, self._p_out, 4, pout), "get outputs")
        din = (fmi2Real * 3)(u[0], pout[0], pout[2])
        dq.check(fd.fmi2SetReal(cd, self._d_in, 3, din), "set inputs")
        dq.exit_initialization()
        pin = (fmi2Real * 2)(0.0, tau[0])
        pl.check(fp.fmi2SetReal(cp, self._p_in, 2, pin), "set inputs")
        pl.exit_initialization()

        out = np.empty((n, 6))
        at, status = ctypes.c_long(0), ctypes.c_int(0)
        plant_unit, daq_unit = (ctypes.byref(x) for x in self._units[:2])
        code = self._master.run_open(
            plant_unit, daq_unit, self._p_in, self._p_out, self._d_in, self._d_out, _doubles(u), _doubles(tau), n,
            Ts, _doubles(out), ctypes.byref(at), ctypes.byref(status),
        )  # fmt: skip
        self._check_master(code, at.value, status.value, Ts)
        return {
            "t": np.arange(n) * Ts,
            "u": u,
            "u_plant": out[:, 0],
            "theta_v": out[:, 1],
            "alpha_v": out[:, 2],
            "theta": out[:, 3] * DEG,
            "alpha": out[:, 4] * DEG,
            "theta_dot": out[:, 5] * DEG,
        }

    def run_closed(
        self,
        ref: np.ndarray,
        Ts: float,
        controller: dict[str, Any],
        plant: dict[str, Any] | None = None,
        daq: dict[str, Any] | None = None,
        diverged: str = "raise",
    ) -> dict[str, np.ndarray]:
        """Run one closed-loop experiment: the shaft angle tracks ``ref`` [rad per sample at ``Ts`` s] under the
        controller FMU with parameters ``controller`` (:meth:`harness.rig.controller.Controller.fmu_parameters`; its
        angle calibration theta_gain/theta_offset/alpha_gain/alpha_offset defaults to the DAQ's pot and gauge
        parameters, the lab's own calibration of its rig; an ``alpha_bias`` [deg] is the zero error of the deflection
        the controller reads, folded into its alpha_offset).

        Returns the keys of :meth:`run` (``u`` the controller's command [V]) plus ``ref`` [deg]. When the loop
        diverges (the link deflects more than DIVERGED_ALPHA_DEG or the shaft strays more than half a turn from the
        reference) ``diverged="raise"`` raises :class:`ClosedLoopError` (one line); ``"hold"`` stops there and holds
        the last sample to the end (a fit's trial parameters that destabilise the loop: a large gap, not an error;
        zeros where it diverged at its start),
        and the result's ``diverged_at`` is that sample's index (-1 when the loop held).
        """
        if self.controller is None:
            raise ValueError("this rig was loaded without the controller FMU: Rig(plant, daq, controller)")
        ref = np.ascontiguousarray(ref, dtype=float)
        if ref.ndim != 1 or ref.size < 2 or not np.all(np.isfinite(ref)):
            raise ValueError("reference must be a 1-D array of at least 2 finite angles")
        n, stop = ref.size, ref.size * Ts
        daq_params = {"sample_rate": 1.0 / Ts, **(daq or {})}
        ctrl_params = controller_parameters(controller, daq_params, self.daq.description.variables, Ts)
        pl, dq, ct = self.plant, self.daq, self.controller
        pl.initialize(plant or {}, stop)
        dq.initialize(daq_params, stop)
        ct.initialize(ctrl_params, stop)

        fp, fd, fc = pl.dll, dq.dll, ct.dll
        cp, cd, cc = pl.component, dq.component, ct.component
        d_samp, c_in = self._d_samp, self._c_in
        pout, samp = (fmi2Real * 4)(), (fmi2Real * 2)()

        # initialisation: the plant's initial outputs -> the DAQ's first samples -> the controller's first command
        pl.check(fp.fmi2GetReal(cp, self._p_out, 4, pout), "get outputs")
        din = (fmi2Real * 3)(0.0, pout[0], pout[2])
        dq.check(fd.fmi2SetReal(cd, self._d_in, 3, din), "set inputs")
        dq.exit_initialization()
        dq.check(fd.fmi2GetReal(cd, d_samp, 2, samp), "get samples")
        cin = (fmi2Real * 3)(ref[0], samp[0], samp[1])
        ct.check(fc.fmi2SetReal(cc, c_in, 3, cin), "set inputs")
        ct.exit_initialization()
        pin = (fmi2Real * 2)(0.0, 0.0)
        pl.check(fp.fmi2SetReal(cp, self._p_in, 2, pin), "set inputs")
        pl.exit_initialization()

        out = np.empty((n, 7))
        at, status, div = ctypes.c_long(0), ctypes.c_int(0), (ctypes.c_double * 3)()
        units = [ctypes.byref(x) for x in self._units]
        code = self._master.run_closed(
            *units, self._p_in, self._p_out, self._d_meas, d_samp, self._d_u, self._d_out, c_in, self._c_out,
            _doubles(ref), n, Ts, DIVERGED_ALPHA_DEG / DEG, np.pi, _doubles(out), ctypes.byref(at),
            ctypes.byref(status), div,
        )  # fmt: skip
        stopped = -1
        if code == DIVERGED:
            k = at.value
            if diverged == "hold":
                out[k:] = out[k - 1] if k > 0 else 0.0  # diverged from its start: nothing to hold but zeros
                stopped = k
            else:
                raise ClosedLoopError(
                    f"closed loop diverged at t = {k * Ts:.3f} s (theta {div[0] * DEG:.1f} deg, reference "
                    f"{div[1] * DEG:.1f} deg, alpha {div[2] * DEG:.1f} deg): the controller destabilises the rig"
                )
        else:
            self._check_master(code, at.value, status.value, Ts)
        return {
            "t": np.arange(n) * Ts,
            "u": out[:, 0],
            "u_plant": out[:, 1],
            "theta_v": out[:, 2],
            "alpha_v": out[:, 3],
            "theta": out[:, 4] * DEG,
            "alpha": out[:, 5] * DEG,
            "theta_dot": out[:, 6] * DEG,
            "ref": ref * DEG,
            "diverged_at": np.array(stopped),
        }
