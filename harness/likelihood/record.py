"""A record as the filter reads it: the logged command, the two readings in degrees and which samples measure.

The command is the one logged (open loop: the excitation; closed loop: the controller's output, so that no
controller is replayed: the direct method), the readings the calibrated angles of
:class:`harness.diagnosis.experiments.RigExperiment`, masked where its samples say nothing of the shaft (a pot's
dead band, a rail).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..diagnosis.experiments import RigExperiment

__all__ = ["Record"]


@dataclass(frozen=True)
class Record:
    """One record of a unit: ``name``, sample time ``Ts`` [s], command ``u`` [V] (n), readings ``y`` [deg]
    (n x 2: theta, alpha), ``mask`` (n x 2, True where a reading measures) and the angle step ``lattice`` [deg] each
    reading was written on (0: none known)."""

    name: str
    Ts: float
    u: np.ndarray
    y: np.ndarray
    mask: np.ndarray
    lattice: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        n = self.u.shape[0]
        if self.u.shape != (n,) or self.y.shape != (n, 2) or self.mask.shape != (n, 2):
            raise ValueError(f"record {self.name}: command {self.u.shape}, readings {self.y.shape} and mask "
                             f"{self.mask.shape} do not match")  # fmt: skip
        if not (np.all(np.isfinite(self.u)) and np.all(np.isfinite(self.y[self.mask]))):
            raise ValueError(f"record {self.name}: a command or a measuring reading is not a number")

    @property
    def n(self) -> int:
        """Samples."""
        return int(self.u.shape[0])

    def delayed(self, samples: int) -> np.ndarray:
        """The command as the plant receives it ``samples`` later, none before the record (the rig at rest before it
        is logged: the DAQ's delay line holds zeros, as the DAQ FMU's does)."""
        if samples <= 0:
            return self.u
        return np.concatenate([np.zeros(samples), self.u[:-samples]])

    def gauge_late(self, samples: int) -> Record:
        """The record with its gauge read ``samples`` late put back in time: the gauge's reading logged at sample
        k + samples is the link's at k (the joint likelihood of the readings does not depend on the order the filter
        takes them in); the last ``samples`` samples have no gauge reading."""
        if samples <= 0:
            return self
        y, mask = self.y.copy(), self.mask.copy()
        y[:-samples, 1], mask[:-samples, 1] = self.y[samples:, 1], self.mask[samples:, 1]
        y[-samples:, 1], mask[-samples:, 1] = 0.0, False
        return Record(self.name, self.Ts, self.u, y, mask, self.lattice)

    def clamped(self, limit: float) -> Record:
        """The record with its command as the DAQ's output stage passes it on, clamped at +-``limit`` [V] (the DAQ's
        ``out_limit``; 0 or less: none): a logged command beyond it (a closed loop's controller asking more) never
        reaches the amplifier."""
        if limit <= 0.0 or not np.any(np.abs(self.u) > limit):
            return self
        return Record(self.name, self.Ts, np.clip(self.u, -limit, limit), self.y, self.mask, self.lattice)

    def halves(self) -> tuple[Record, Record]:
        """The record's first and second half in time, each its own record (``name/1``, ``name/2``): the folds of a
        unit of one record."""
        h = self.n // 2
        first = Record(f"{self.name}/1", self.Ts, self.u[:h], self.y[:h], self.mask[:h], self.lattice)
        return first, Record(f"{self.name}/2", self.Ts, self.u[h:], self.y[h:], self.mask[h:], self.lattice)

    @classmethod
    def from_experiment(cls, exp: RigExperiment) -> Record:
        """The record of an experiment as :func:`harness.diagnosis.experiments.load_experiments` loads it."""
        y = np.column_stack([exp.theta, exp.alpha])
        mask = np.column_stack([exp.valid["theta"], exp.valid["alpha"]])
        lat = exp.lattice_deg or {}
        return cls(exp.name, exp.Ts, np.asarray(exp.u, dtype=float), y, mask,
                   (float(lat.get("theta", 0.0)), float(lat.get("alpha", 0.0))))  # fmt: skip
