"""Co-simulation master: the plant FMU and the DAQ FMU coupled step by step through fmpy's ``FMU2Slave``.

Every communication step k (one sample, Ts = 1/sample_rate, or a divisor of it):

1. DAQ inputs <- command u_k, plant theta and alpha_gauge at t_k; ``daq.doStep(t_k, h)``;
2. read the DAQ outputs: u_plant (the command held over [t_k, t_k + h)) and the samples theta_v, alpha_v at t_k;
3. plant input u <- u_plant (and the tip torque); ``plant.doStep(t_k, h)``.

Closed loop (:meth:`Rig.run_closed`, with the controller FMU): reference -> controller -> DAQ (DAC, delay) ->
plant -> DAQ (ADC) -> controller. Every step k:

1. DAQ inputs <- plant theta and alpha_gauge at t_k; read the DAQ's preview of the samples theta_v, alpha_v at t_k;
2. controller inputs <- ref_k and those samples; ``controller.doStep(t_k, h)``; read its command u_k;
3. DAQ input u <- u_k; ``daq.doStep(t_k, h)`` (takes the same samples, now with u_k); then the plant as above.

So u_k acts over [t_k, t_k+1) (direct feedthrough, as a lab controller that reads, computes and writes within the
sample); a DAQ delay adds its samples on top.

The hot loop calls the FMI functions of the loaded binaries directly with preallocated ctypes arrays, so one
step costs a few microseconds; status codes are checked on every call and an FMU error stops the run with the
FMU's own log message. Loading and the FMI calls are :mod:`harness.fmu.binding`'s.
"""

from __future__ import annotations

import ctypes
from pathlib import Path
from typing import Any

import numpy as np
from fmpy.fmi2 import fmi2Boolean, fmi2Real, fmi2ValueReference

from .binding import load

__all__ = ["DEG", "DIVERGED_ALPHA_DEG", "ClosedLoopError", "Rig"]

DEG = 180.0 / np.pi
DIVERGED_ALPHA_DEG = 45.0  # a closed loop whose link deflects more has diverged (a real link would break)
CALIBRATION = {"theta_gain": "pot_gain", "theta_offset": "pot_offset", "alpha_gain": "gauge_gain"}
CALIBRATION |= {"alpha_offset": "gauge_offset"}  # controller parameter <- the DAQ parameter it defaults to


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
        daq_params = {"sample_rate": 1.0 / Ts, **(daq or {})}
        stop = n * Ts
        pl, dq = self.plant, self.daq
        pl.initialize(plant or {}, stop)
        dq.initialize(daq_params, stop)

        fp, fd = pl.dll, dq.dll
        cp, cd = pl.component, dq.component
        p_set, p_get, p_step = fp.fmi2SetReal, fp.fmi2GetReal, fp.fmi2DoStep
        d_set, d_get, d_step = fd.fmi2SetReal, fd.fmi2GetReal, fd.fmi2DoStep
        p_in, p_out, d_in, d_out = self._p_in, self._p_out, self._d_in, self._d_out
        pin = (fmi2Real * 2)()
        pout = (fmi2Real * 4)()
        din = (fmi2Real * 3)()
        dout = (fmi2Real * 3)()
        true_b = fmi2Boolean(1)

        # initial plant outputs feed the DAQ's first sample
        pl.check(p_get(cp, p_out, 4, pout), "get outputs")
        din[0], din[1], din[2] = u[0], pout[0], pout[2]
        dq.check(d_set(cd, d_in, 3, din), "set inputs")
        dq.exit_initialization()
        pin[0], pin[1] = 0.0, tau[0]
        pl.check(p_set(cp, p_in, 2, pin), "set inputs")
        pl.exit_initialization()

        out = np.empty((n, 6))
        h = ctypes.c_double(Ts)
        for k in range(n):
            t = ctypes.c_double(k * Ts)
            p_get(cp, p_out, 4, pout)
            din[0], din[1], din[2] = u[k], pout[0], pout[2]
            d_set(cd, d_in, 3, din)
            s = d_step(cd, t, h, true_b)
            if s > 1:
                dq.check(s, f"doStep at t={k * Ts:.4f} s")
            d_get(cd, d_out, 3, dout)
            pin[0], pin[1] = dout[0], tau[k]
            p_set(cp, p_in, 2, pin)
            out[k] = (dout[0], dout[1], dout[2], pout[0], pout[1], pout[3])
            s = p_step(cp, t, h, true_b)
            if s > 1:
                pl.check(s, f"doStep at t={k * Ts:.4f} s")
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
        the last sample to the end (a fit's trial parameters that destabilise the loop: a large gap, not an error),
        and the result's ``diverged_at`` is that sample's index (-1 when the loop held).
        """
        if self.controller is None:
            raise ValueError("this rig was loaded without the controller FMU: Rig(plant, daq, controller)")
        ref = np.ascontiguousarray(ref, dtype=float)
        if ref.ndim != 1 or ref.size < 2 or not np.all(np.isfinite(ref)):
            raise ValueError("reference must be a 1-D array of at least 2 finite angles")
        n, stop = ref.size, ref.size * Ts
        daq_params = {"sample_rate": 1.0 / Ts, **(daq or {})}
        dq_start = self.daq.description.variables
        ctrl_params = {k: float(daq_params.get(v, dq_start[v].start)) for k, v in CALIBRATION.items()}
        ctrl_params |= {"sample_rate": 1.0 / Ts, **controller}
        bias = float(ctrl_params.pop("alpha_bias", 0.0))  # deg the controller reads on top of alpha: its zero error
        ctrl_params["alpha_offset"] -= bias / ctrl_params["alpha_gain"]
        pl, dq, ct = self.plant, self.daq, self.controller
        pl.initialize(plant or {}, stop)
        dq.initialize(daq_params, stop)
        ct.initialize(ctrl_params, stop)

        fp, fd, fc = pl.dll, dq.dll, ct.dll
        cp, cd, cc = pl.component, dq.component, ct.component
        p_in, p_out, d_in, d_out = self._p_in, self._p_out, self._d_in, self._d_out
        d_meas = (fmi2ValueReference * 2)(dq.vr("theta"), dq.vr("alpha_gauge"))
        d_samp = (fmi2ValueReference * 2)(dq.vr("theta_v"), dq.vr("alpha_v"))
        d_u = (fmi2ValueReference * 1)(dq.vr("u"))
        c_in = (fmi2ValueReference * 3)(ct.vr("ref"), ct.vr("theta_v"), ct.vr("alpha_v"))
        c_out = (fmi2ValueReference * 1)(ct.vr("u"))
        pin, pout = (fmi2Real * 2)(), (fmi2Real * 4)()
        meas, samp, cin, cu, du, dout = (
            (fmi2Real * 2)(),
            (fmi2Real * 2)(),
            (fmi2Real * 3)(),
            (fmi2Real * 1)(),
            (fmi2Real * 1)(),
            (fmi2Real * 3)(),
        )
        true_b = fmi2Boolean(1)

        # initialisation: the plant's initial outputs -> the DAQ's first samples -> the controller's first command
        pl.check(fp.fmi2GetReal(cp, p_out, 4, pout), "get outputs")
        din = (fmi2Real * 3)(0.0, pout[0], pout[2])
        dq.check(fd.fmi2SetReal(cd, d_in, 3, din), "set inputs")
        dq.exit_initialization()
        dq.check(fd.fmi2GetReal(cd, d_samp, 2, samp), "get samples")
        cin[0], cin[1], cin[2] = ref[0], samp[0], samp[1]
        ct.check(fc.fmi2SetReal(cc, c_in, 3, cin), "set inputs")
        ct.exit_initialization()
        pin[0], pin[1] = 0.0, 0.0
        pl.check(fp.fmi2SetReal(cp, p_in, 2, pin), "set inputs")
        pl.exit_initialization()

        out = np.empty((n, 7))
        h = ctypes.c_double(Ts)
        lim_alpha, lim_theta = DIVERGED_ALPHA_DEG / DEG, np.pi
        stopped = -1
        for k in range(n):
            t = ctypes.c_double(k * Ts)
            fp.fmi2GetReal(cp, p_out, 4, pout)
            if abs(pout[1]) > lim_alpha or abs(pout[0] - ref[k]) > lim_theta:
                if diverged == "hold" and k > 0:
                    out[k:] = out[k - 1]
                    stopped = k
                    break
                raise ClosedLoopError(
                    f"closed loop diverged at t = {k * Ts:.3f} s (theta {pout[0] * DEG:.1f} deg, reference "
                    f"{ref[k] * DEG:.1f} deg, alpha {pout[1] * DEG:.1f} deg): the controller destabilises the rig"
                )
            meas[0], meas[1] = pout[0], pout[2]
            fd.fmi2SetReal(cd, d_meas, 2, meas)
            fd.fmi2GetReal(cd, d_samp, 2, samp)  # the DAQ's preview of its samples at t_k
            cin[0], cin[1], cin[2] = ref[k], samp[0], samp[1]
            fc.fmi2SetReal(cc, c_in, 3, cin)
            s = fc.fmi2DoStep(cc, t, h, true_b)
            if s > 1:
                ct.check(s, f"doStep at t={k * Ts:.4f} s")
            fc.fmi2GetReal(cc, c_out, 1, cu)
            du[0] = cu[0]
            fd.fmi2SetReal(cd, d_u, 1, du)
            s = fd.fmi2DoStep(cd, t, h, true_b)
            if s > 1:
                dq.check(s, f"doStep at t={k * Ts:.4f} s")
            fd.fmi2GetReal(cd, d_out, 3, dout)
            pin[0] = dout[0]
            fp.fmi2SetReal(cp, p_in, 2, pin)
            out[k] = (cu[0], dout[0], dout[1], dout[2], pout[0], pout[1], pout[3])
            s = fp.fmi2DoStep(cp, t, h, true_b)
            if s > 1:
                pl.check(s, f"doStep at t={k * Ts:.4f} s")
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
