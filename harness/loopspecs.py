"""What a user asks of a loop and of its design, read from the command line's text.

The specs a lab states for its loop (:class:`LoopSpecs`, ``--specs``), the design methods (:data:`METHODS`), an
LQR's or LQG's weights (:class:`Weights`, ``--weights``) and which option gives a prediction's controller
(:func:`controller_source`), each read with one line naming what is wrong. Plain data
with no numerics, so that the command line checks what it is given before it loads the prediction
(:mod:`harness.prediction`) or the design (:mod:`harness.design`), which take them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

__all__ = ["METHODS", "SPEC_KEYS", "LoopSpecs", "Weights", "controller_source", "parse_weights"]

METHODS = ("lqr", "lqg", "pd")  # flexjoint design --method
# a spec's key on the command line -> (the metric it bounds, its unit, what it says)
SPEC_KEYS: dict[str, tuple[str, str, str]] = {
    "settling": ("settling_s", "s", "settling time"),
    "overshoot": ("overshoot_pct", "%", "overshoot"),
    "alpha": ("peak_alpha_deg", "deg", "peak link deflection"),
    "voltage": ("peak_u_v", "V", "peak command"),
    "stop": ("stop_error_deg", "deg", "stopping error"),
    "ring": ("ring_alpha_deg", "deg", "link ringing (RMS)"),
}


@dataclass(frozen=True)
class LoopSpecs:
    """The specs a lab states for its loop: an upper limit per metric (``limits``, metric name -> limit in its unit;
    the stopping error's on its magnitude) and the settling band ``band_pct`` [% of the step]."""

    limits: dict[str, float] = field(default_factory=dict)
    band_pct: float = 5.0

    @classmethod
    def parse(cls, text: str) -> LoopSpecs:
        """``settling=1.5,overshoot=5,alpha=15,voltage=5[,stop=1][,ring=0.5][,band=4]`` (s, %, deg, V, deg, deg,
        % of the step); one line naming what is wrong."""
        limits: dict[str, float] = {}
        band = 5.0
        for item in [s for s in str(text).replace(";", ",").split(",") if s.strip()]:
            key, eq, value = (p.strip() for p in item.partition("="))
            if not eq or key not in (*SPEC_KEYS, "band"):
                raise ValueError(f"--specs {text!r}: {key!r} is not a spec; valid: {', '.join([*SPEC_KEYS, 'band'])}")
            try:
                v = float(value)
            except ValueError:
                raise ValueError(f"--specs {text!r}: {key}={value!r} is not a number") from None
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"--specs {text!r}: {key} must be a number > 0, got {value}")
            if key == "band":
                band = v
            else:
                limits[SPEC_KEYS[key][0]] = v
        if not limits:
            raise ValueError(f"--specs {text!r}: no spec given (band sets the settling spec's band)")
        return cls(limits, band)

    def describe(self, metric: str) -> str:
        """ "settling time <= 1.5 s"."""
        key = next(k for k, v in SPEC_KEYS.items() if v[0] == metric)
        _, unit, what = SPEC_KEYS[key]
        mag = "|stopping error|" if metric == "stop_error_deg" else what
        return f"{mag} <= {self.limits[metric]:g} {unit}"


@dataclass(frozen=True)
class Weights:
    """LQR/LQG weights: ``q`` on (theta, alpha, theta_dot, alpha_dot) as read [1/rad^2, 1/(rad/s)^2], ``r`` on u
    [1/V^2], ``w`` the LQG's process noise at the plant's input [V rms] (None: searched)."""

    q: tuple[float, float, float, float]
    r: float = 1.0
    w: float | None = None

    def params(self) -> dict[str, float]:
        """The weights as the search names them: q_theta, q_alpha, q_theta_dot, q_alpha_dot, r (and w)."""
        q = dict(zip(("q_theta", "q_alpha", "q_theta_dot", "q_alpha_dot"), self.q, strict=True))
        return {**q, "r": self.r, **({"w": self.w} if self.w is not None else {})}


def parse_weights(text: str, method: str) -> Weights:
    """``q=160,60,0.25,1;r=1[;w=1]`` (the LQG's w: process noise [V rms]); one line naming what is wrong."""
    if method == "pd":
        raise ValueError("--weights: the pd method has no weights (its gains are searched; give them to predict as "
                         "--controller state_feedback:K=...)")  # fmt: skip
    args: dict[str, Any] = {}
    for item in [s for s in str(text).split(";") if s.strip()]:
        key, eq, value = (p.strip() for p in item.partition("="))
        if not eq or key not in ("q", "r", "w"):
            raise ValueError(f"--weights {text!r}: {key!r} is not a weight; give q=Q1,Q2,Q3,Q4;r=R[;w=W]")
        try:
            nums = [float(v) for v in value.split(",")]
        except ValueError:
            raise ValueError(f"--weights {text!r}: {key}={value!r} is not a number") from None
        if not all(math.isfinite(v) and v >= 0 for v in nums) or (key != "q" and (len(nums) != 1 or nums[0] <= 0)):
            raise ValueError(
                f"--weights {text!r}: {key} must be {'4 numbers >= 0' if key == 'q' else 'one number > 0'}"
            )
        if key == "q" and len(nums) != 4:
            raise ValueError(f"--weights {text!r}: q takes 4 numbers (theta, alpha, theta_dot, alpha_dot)")
        args[key] = tuple(nums) if key == "q" else nums[0]
    if "q" not in args:
        raise ValueError(f"--weights {text!r}: give q=Q1,Q2,Q3,Q4")
    if "w" in args and method != "lqg":
        raise ValueError(f"--weights {text!r}: w (process noise) is the lqg's")
    return Weights(**args)


def controller_source(text: str | None, source: str | None, record_given: bool) -> str:
    """Which option gives the controller a prediction runs: ``"controller"`` (``--controller`` KIND:...),
    ``"controller_from"`` (``--controller-from``) or ``"record"`` (``--record``'s own); one line when the first two
    are both given, or none of the three."""
    if text is not None and source is not None:
        raise ValueError("give --controller or --controller-from, not both")
    if text is not None:
        return "controller"
    if source is not None:
        return "controller_from"
    if record_given:
        return "record"
    raise ValueError("no controller: give --controller KIND:..., --controller-from DIR, or --record RUN (its own)")
