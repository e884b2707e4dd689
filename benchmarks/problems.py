"""Demo problems for the benchmarks and the tests: a known ARMAX system and data generated from it."""

from __future__ import annotations

import math

import numpy as np

from harness.ident.armax import ArmaxModel, generate


def demo_system(Ts: float = 0.02) -> ArmaxModel:
    """A stable ARMAX(4,3,4,1) shaped like the differentiated, low-passed flexible joint at 50 Hz.

    Poles: the link mode (3 Hz, damping 0.08), the H(z) filter pole af = 0.8 and a motor pole 0.6; B has one
    non-minimum-phase zero (tip whiplash); C has roots 0.7 exp(+-0.6j), 0.5, -0.3 (clearly coloured noise).
    """
    w = 2 * math.pi * 3.0
    zeta = 0.08
    r = math.exp(-zeta * w * Ts)
    ang = w * Ts * math.sqrt(1 - zeta**2)
    A = np.real(np.poly([r * np.exp(1j * ang), r * np.exp(-1j * ang), 0.8, 0.6]))
    B = np.array([0.0, 0.10, 0.05, -0.12])
    C = np.real(np.poly([0.7 * np.exp(0.6j), 0.7 * np.exp(-0.6j), 0.5, -0.3]))
    return ArmaxModel(A=A, B=B, C=C, na=4, nb=3, nc=4, nk=1, Ts=Ts)


def demo_problem(seed: int, n: int = 1500, noise_std: float = 0.02) -> tuple[ArmaxModel, np.ndarray, np.ndarray]:
    """(true model, u, y): PRBS-like +-1 input (switching probability 0.5 per sample) through ``demo_system``."""
    rng = np.random.default_rng(seed)
    flips = rng.random(n) < 0.5
    u = np.where(np.cumsum(flips) % 2 == 0, 1.0, -1.0)
    e = noise_std * rng.standard_normal(n)
    true = demo_system()
    return true, u, generate(true, u, e)
