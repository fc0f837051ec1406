"""Reliability diagrams side by side (css_replay's report, css_calibrate's figures)."""
from __future__ import annotations

from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

if TYPE_CHECKING:
    from .calibration_metrics import ReliabilityBins


def reliability_panels_figure(panels: Sequence[tuple[str, dict[str, "ReliabilityBins"]]]) -> Any:
    """One reliability diagram per (title, curves) panel, side by side."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(6.2 * len(panels), 6.2))
    subfigs = fig.subfigures(1, len(panels), squeeze=False)[0]
    for sub, (title, curves) in zip(subfigs, panels):
        _reliability_axes(sub, curves, title)
    return fig


def _reliability_axes(sub: Any, curves: dict[str, "ReliabilityBins"], title: str) -> None:
    ax, hist = sub.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    ax.plot([0, 1], [0, 1], "k--", lw=1, label="perfect calibration")
    for name, rb in curves.items():
        ece = rb.ece()
        ax.plot(rb.mean_confidence, rb.accuracy, "o-", label=f"{name} (ECE {ece:.3f})" if np.isfinite(ece)
                else f"{name} (ECE n/a)")
        centres = 0.5 * (rb.edges[:-1] + rb.edges[1:])
        hist.step(centres, np.maximum(rb.count, 1), where="mid", label=name)
    ax.set_title(title, fontsize=10)
    ax.set_ylabel("observed accuracy")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    hist.set_yscale("log")
    hist.set_xlabel("predicted probability that the label is right")
    hist.set_ylabel("pixels")
