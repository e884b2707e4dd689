"""The missing force drawn: its figure and the report's lines (issue 63).

:func:`harness.likelihood.force.force_picture` smooths an unknown torque on the hub through each record;
:func:`write_force_views` stores its traces as ``force_picture.parquet`` (:mod:`harness.likelihood.traces`) and draws
``force_picture.png`` beside ``likelihood.json``: the force against the hub's speed, the command, the deflection and
time, each record its own colour, the +-2 standard deviation band over time, the classifier's verdict in the title.
The report and the recording read the parquet (:func:`harness.likelihood.traces.read_traces`) without refitting.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from matplotlib.figure import Figure

from ..likelihood.force import EffectCurve, ForcePicture, ForceTrace, MissingForce
from ..likelihood.traces import write_traces
from ..rundir import RunDir
from .figures import new_figure, save_figure

__all__ = ["force_figure", "force_markdown", "write_force_views"]

PANELS = (  # the figure's panels: the trace's field on x, its axis label
    ("speed", "hub speed [deg/s]"),
    ("u", "command u [V]"),
    ("alpha", "deflection alpha [deg]"),
    ("t", "t [s]"),
)
FORCE_LABEL = "missing force [N m]"
COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:gray")


def force_figure(traces: Sequence[ForceTrace], verdict: str, curve: EffectCurve | None = None) -> Figure:
    """The missing force of each record against the hub's speed, the command, the deflection and time (with its +-2
    standard deviation band), the classifier's ``verdict`` (:meth:`MissingForce.words`) in the title, and the
    effect that entered drawn over its panel (``curve``, black).

    Parameters
    ----------
    traces : sequence of ForceTrace
        Each record's smoothed force and what it is drawn against.
    verdict : str
        The classifier's verdict.
    curve : EffectCurve, optional
        The effect that entered, drawn over the panel of its ``x``.

    Returns
    -------
    Figure
        Four axes in the order of :data:`PANELS`; on each, one line per record (the force against the panel's x, in
        the order of ``traces``), then the curve's where it is drawn; the time panel's bands as its collections.
    """
    fig = new_figure(10.0, 7.5)
    axes = fig.subplots(2, 2, sharey=True).ravel()
    for i, tr in enumerate(traces):
        color = COLORS[i % len(COLORS)]
        for ax, (x, _) in zip(axes, PANELS, strict=True):
            style = {"lw": 0.8} if x == "t" else {"ls": "none", "marker": ".", "ms": 1.5, "alpha": 0.5}
            ax.plot(getattr(tr, x), tr.force, color=color, label=tr.name, **style)
        lo, hi = tr.force - 2.0 * tr.force_sd, tr.force + 2.0 * tr.force_sd
        axes[3].fill_between(tr.t, lo, hi, color=color, alpha=0.2, lw=0)
    if curve is not None:
        ax = axes[[x for x, _ in PANELS].index(curve.x)]
        ax.plot(curve.xs, curve.ys, color="k", lw=1.5, label=curve.label)
        ax.legend(loc="best", fontsize=8)
    for ax, (_, label) in zip(axes, PANELS, strict=True):
        ax.set_xlabel(label)
        ax.grid(alpha=0.3)
        ax.axhline(0.0, color="0.5", lw=0.6)
    for ax in axes[::2]:
        ax.set_ylabel(FORCE_LABEL)
    axes[3].set_title("over time, +-2 sd band", fontsize=9)
    legend = axes[0].legend(loc="best", fontsize=8, markerscale=6)
    for handle in legend.legend_handles:
        if handle is not None:
            handle.set_alpha(1.0)
    fig.suptitle(f"missing force on the hub (likelihood engine, smoothed): {verdict}", fontsize=11)
    fig.tight_layout()
    return fig


def write_force_views(
    out: Path, picture: ForcePicture, verdict: str, curve: EffectCurve | None = None
) -> tuple[Path, Path]:
    """Write ``out/force_picture.parquet`` (:func:`write_traces`) and ``out/force_picture.png``
    (:func:`force_figure`, ``curve`` over it), each atomically, and return their paths."""
    paths = RunDir(out)
    traces = write_traces(paths.force_traces, picture.traces)
    png = paths.force_figure
    save_figure(force_figure(picture.traces, verdict, curve), png)
    return traces, png


def force_markdown(mf: MissingForce, traces: Sequence[ForceTrace], png: str | None) -> list[str]:
    """The report's "Missing force" lines (under 200 characters each): the classifier's verdict, the samples at
    rest, the figure ``png`` linked.

    Parameters
    ----------
    mf : MissingForce
        The classifier's verdict (likelihood.json's ``missing_force``).
    traces : sequence of ForceTrace
        The traces the figure draws (their records and samples).
    png : str or None
        The figure's path relative to the report (None: not linked).

    Returns
    -------
    list of str
    """
    n = sum(tr.t.size for tr in traces)
    names = ", ".join(f"`{tr.name}`" for tr in traces[:5]) + (f" and {len(traces) - 5} more" if len(traces) > 5 else "")
    return [
        "### Missing force",
        "",
        f"The likelihood engine's unknown torque on the hub, smoothed through {len(traces)} records ({names}; "
        "`likelihood.json`, traces in `force_picture.parquet`).",
        "",
        f"- shape: **{mf.words()}**",
        f"- samples at rest (hub speed within three standard deviations of zero): {mf.samples_near_zero} of {n}",
        "",
        *([f"![missing force against hub speed, command, deflection and time]({png})", ""] if png else []),
    ]  # fmt: skip
