"""Co-simulation master: the plant FMU and the DAQ FMU coupled step by step through fmpy's ``FMU2Slave``.

Every communication step k (one sample, Ts = 1/sample_rate, or a divisor of it):

1. DAQ inputs <- command u_k, plant theta and alpha_gauge at t_k; ``daq.doStep(t_k, h)``;
2. read the DAQ outputs: u_plant (the command held over [t_k, t_k + h)) and the samples theta_v, alpha_v at t_k;
3. plant input u <- u_plant (and the tip torque); ``plant.doStep(t_k, h)``.

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

__all__ = ["DEG", "Rig"]

DEG = 180.0 / np.pi


class Rig:
    """The rig twin: plant and DAQ FMUs loaded once and re-run for each experiment.

    ``Rig(plant_fmu, daq_fmu)`` then ``rig.run(u, Ts, plant={...}, daq={...})``. Use as a context manager or
    call :meth:`close`.
    """

    def __init__(self, plant_fmu: Path, daq_fmu: Path) -> None:
        self.plant = load(Path(plant_fmu), "plant")
        self.daq = load(Path(daq_fmu), "daq")
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
