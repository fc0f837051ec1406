"""Reliability diagrams side by side (css_replay's report, css_calibrate's figures)."""
from __future__ import annotations

from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

if TYPE_CHECKING:
    from .calibration_metrics import ReliabilityBins

#: Marker area [pt^2] of the fullest bin of a curve; a bin of n pixels gets MAX_MARKER_AREA * n / n_max.
MAX_MARKER_AREA = 150.0

#: The line through a curve's points skips bins holding less than this share of its fullest bin's pixels.
LINE_MIN_SHARE = 0.01


def marker_areas(count: np.ndarray) -> np.ndarray:
    """Marker areas [pt^2] proportional to the bins' pixel counts (the fullest bin: :data:`MAX_MARKER_AREA`)."""
    c = np.asarray(count, dtype=np.float64)
    return MAX_MARKER_AREA * c / max(float(c.max(initial=0.0)), 1.0)


def reliability_panels_figure(panels: Sequence[tuple[str, dict[str, "ReliabilityBins"]]]) -> Any:
    """One reliability diagram per (title, curves) panel, side by side, each with its pixel histogram below.

    Each curve's points have an area proportional to their bin's pixel count (a nearly empty bin is a small dot,
    not a full-size point); constrained layout leaves no blank band around the panels."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(6.2 * len(panels), 6.4), layout="constrained")
    subfigs = fig.subfigures(1, len(panels), squeeze=False)[0]
    for sub, (title, curves) in zip(subfigs, panels):
        _reliability_axes(sub, curves, title)
    return fig


def _reliability_axes(sub: Any, curves: dict[str, "ReliabilityBins"], title: str) -> None:
    from matplotlib.lines import Line2D

    ax, hist = sub.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    (diag,) = ax.plot([0, 1], [0, 1], "k--", lw=1, label="perfect calibration")
    handles = [diag]
    for k, (name, rb) in enumerate(curves.items()):
        ece = rb.ece()
        color = f"C{k}"
        full = rb.count > 0
        label = f"{name} (ECE {ece:.3f})" if np.isfinite(ece) else f"{name} (ECE n/a)"
        # the guide line joins only bins of some weight, so that a nearly empty bin stays a speck
        solid = rb.count >= LINE_MIN_SHARE * max(int(rb.count.max(initial=0)), 1)
        ax.plot(rb.mean_confidence[solid], rb.accuracy[solid], "-", color=color, lw=1, alpha=0.5)
        ax.scatter(rb.mean_confidence[full], rb.accuracy[full], s=marker_areas(rb.count)[full], color=color,
                   zorder=3)
        handles.append(Line2D([], [], color=color, marker="o", lw=1, label=label))
        centres = 0.5 * (rb.edges[:-1] + rb.edges[1:])
        hist.step(centres, np.maximum(rb.count, 1), where="mid", color=color, label=name)
    ax.set_title(title, fontsize=10)
    ax.set_ylabel("observed accuracy")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend(handles=handles, fontsize=8, loc="upper left", title="point area ~ pixels in the bin", title_fontsize=7)
    hist.set_yscale("log")
    hist.set_xlabel("predicted probability that the label is right")
    hist.set_ylabel("pixels")
