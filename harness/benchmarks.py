"""Timing and accuracy benchmarks (``flexjoint bench``)."""

from __future__ import annotations

import contextlib
import io
import statistics
import time
import warnings
from typing import Any

import numpy as np


def bench_armax(n_fits: int = 20) -> dict[str, Any]:
    """ARMAX(4,3,4,1) on 1500 samples of ``armax.demo_problem(seed)``, seeds 0..n_fits-1: ours vs sippy-unipi.

    The peer is sippy-unipi's ARMAX ``ILLS`` (iterative linear least squares; optional extra ``bench``,
    imported lazily; ``"peer": None`` when it is not installed). Times are wall-clock ms per fit, data generation
    excluded, one untimed warm-up fit each. Parameter error: ||theta_hat - theta|| / ||theta|| over
    [a.., b.., c..], median and mean over the fits.
    """
    from .armax import demo_problem, demo_system, estimate

    if isinstance(n_fits, bool) or not isinstance(n_fits, int) or n_fits < 1:
        raise ValueError(f"n_fits must be an integer >= 1, got {n_fits!r}")
    true = demo_system()
    problems = [demo_problem(seed) for seed in range(n_fits)]
    theta = true.theta
    tnorm = float(np.linalg.norm(theta))

    def summary(ms: list[float], errs: list[float]) -> dict[str, float]:
        return {
            "mean_ms": statistics.fmean(ms),
            "median_ms": statistics.median(ms),
            "median_rel_error": statistics.median(errs),
            "mean_rel_error": statistics.fmean(errs),
        }

    _, u0, y0 = problems[0]
    estimate(u0, y0, 4, 3, 4, 1, Ts=true.Ts)  # warm-up
    ms, errs = [], []
    for _, u, y in problems:
        t0 = time.perf_counter()
        m = estimate(u, y, 4, 3, 4, 1, Ts=true.Ts)
        ms.append(1e3 * (time.perf_counter() - t0))
        errs.append(float(np.linalg.norm(m.theta - theta)) / tnorm)
    ours = summary(ms, errs)

    peer: dict[str, Any] | None = None
    try:
        import sippy_unipi
        from sippy_unipi import system_identification
    except ImportError:
        sippy_unipi = None
    if sippy_unipi is not None:

        def sippy_fit(u: np.ndarray, y: np.ndarray) -> np.ndarray:
            # sippy's delay theta = 0 means b1 multiplies u(t-1), i.e. our nk = 1
            with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
                warnings.simplefilter("ignore")
                s = system_identification(y, u, "ARMAX", ARMAX_orders=[4, 3, 4, 0], ARMAX_mod="ILLS", tsample=true.Ts)
            a = np.asarray(s.DENOMINATOR[0][0], dtype=float)[1:5]
            b = np.asarray(s.NUMERATOR[0][0], dtype=float)[0:3]
            c = np.asarray(s.NUMERATOR_H[0][0], dtype=float)[1:5]
            return np.concatenate([a, b, c])

        sippy_fit(u0, y0)  # warm-up (sippy's first call pays its lazy imports)
        ms_p, errs_p = [], []
        for _, u, y in problems:
            t0 = time.perf_counter()
            th = sippy_fit(u, y)
            ms_p.append(1e3 * (time.perf_counter() - t0))
            errs_p.append(float(np.linalg.norm(th - theta)) / tnorm)
        try:
            from importlib.metadata import version

            ver = version("sippy-unipi")
        except Exception:  # noqa: BLE001 - metadata is informative only
            ver = "?"
        peer = {"name": f"sippy-unipi {ver} ARMAX ILLS"}
        peer.update(summary(ms_p, errs_p))

    return {
        "problem": {
            "model": "ARMAX(4,3,4,1)",
            "n_samples": int(problems[0][1].size),
            "n_fits": n_fits,
            "theta_true": theta.tolist(),
        },
        "ours": {"name": "harness.armax.estimate (PEM, analytic Gauss-Newton)", **ours},
        "peer": peer,
        "speed_ratio": (peer["median_ms"] / ours["median_ms"]) if peer else None,
    }
