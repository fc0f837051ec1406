"""css_calibrate's figures: reliability vs depth per class, confusion per depth band, reliability diagrams."""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..engine.atomic import atomic_file
from ..evaluation.calibration_plots import reliability_panels_figure

#: Font size of the class names on the confusion panels' axes [pt].
TICK_FONTSIZE = 8

__all__ = ["confusion_bands_figure", "reliability_by_depth_figure", "reliability_panels_figure", "save_figure"]

if TYPE_CHECKING:
    from ..engine.classes import ClassSet
    from ..engine.sensor_model import SensorModel


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Any, path: Path, dpi: int = 110) -> None:
    """Write ``fig`` as PNG atomically (engine.atomic.atomic_file) and close it."""
    try:
        with atomic_file(path) as fh:
            fig.savefig(fh, format="png", dpi=dpi, bbox_inches="tight")
    finally:
        _plt().close(fig)


def _rows_identical(a: np.ndarray) -> bool:
    """True when every row of ``a`` (C, B) equals the first (a per-depth model: one curve for all labels)."""
    return bool(np.all(a == a[:1]))


def reliability_by_depth_figure(model: "SensorModel", counts: np.ndarray, classes: "ClassSet") -> Any:
    """Left: the measured right-label rate per label and depth bin (one dot per label and bin, the label's colour,
    size ~ pixels) and the model's smoothed rate p; right: the vote weight w the update uses. A per-depth model
    (the same p and w for every label) is one black curve, a per-label model one curve per label. Depth bins of
    the fitting data without any labelled pixel are shaded: their values are extrapolated from the neighbouring
    bins. Legends below the panels, never over them."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    plt = _plt()
    c = model.num_classes
    edges = model.depth_edges
    centres = 0.5 * (edges[:-1] + edges[1:])
    p = model.label_distribution()[np.arange(c), :, np.arange(c)] if model.confusion is not None else None
    n = counts.sum(axis=2)
    raw = np.where(n > 0, counts[np.arange(c), :, np.arange(c)] / np.maximum(n, 1), np.nan)
    fig, axes = plt.subplots(1, 2, figsize=(13, 5.6), sharex=True, layout="constrained")
    seen = [y for y in np.argsort(-n.sum(axis=1), kind="stable") if n[y].sum() > 0]
    size = 4.0 + 60.0 * n / max(float(n.max()), 1.0)   # marker area [pt^2] ~ pixels of the (label, bin)
    for y in seen:
        color = np.asarray(classes.palette[y]) / 255.0
        ok = n[y] > 0
        axes[0].scatter(centres[ok], raw[y, ok], s=size[y, ok], color=color, alpha=0.7, edgecolors="none",
                        label=classes.names[y])
    line_handles = []
    curves = [(axes[1], model.weight, "vote weight w")] + ([(axes[0], p, "smoothed p")] if p is not None else [])
    for ax, values, what in curves:
        if _rows_identical(values):   # a per-depth model: the same curve for every label, drawn once
            (line,) = ax.plot(centres, values[0], "-", color="black", lw=2, label=f"{what} (every label)")
            line_handles.append(line)
        else:
            for y in seen:
                ax.plot(centres, values[y], "-", color=np.asarray(classes.palette[y]) / 255.0,
                        label=f"{what}, {classes.names[y]}")
            line_handles.append(Line2D([], [], color="0.3", label=f"{what} (one line per label, its colour)"))
    empty = np.flatnonzero(n.sum(axis=0) == 0)
    for ax in axes:
        for b in empty:
            ax.axvspan(edges[b], edges[b + 1], facecolor="0.85", edgecolor="0.6", hatch="//", lw=0, zorder=0)
    axes[0].set_title("p(label right | depth): dots measured per label, line the model")
    axes[0].set_ylabel("fraction of pixels whose label is right")
    axes[1].set_title("vote weight w(label, depth) used by the update")
    axes[1].set_ylabel("w")
    for ax in axes:
        ax.set_xlabel("rendered depth [m]")
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
    extra = [Patch(facecolor="0.85", edgecolor="0.6", hatch="//", label="no data: extrapolated")] if empty.size else []
    dots = [Line2D([], [], ls="", marker="o", color=np.asarray(classes.palette[y]) / 255.0,
                   label=classes.names[y]) for y in seen]
    fig.legend(handles=line_handles + extra + dots, loc="outside lower center", ncol=min(6, len(dots) + 3),
               fontsize=8, frameon=False, title="dots: measured rate per input label (size ~ pixels)",
               title_fontsize=8)
    return fig


def confusion_bands_figure(counts: np.ndarray, edges: np.ndarray, classes: "ClassSet", bands: int = 3) -> Any:
    """Row-normalised confusion (label -> true class) in ``bands`` depth bands of about equal pixel count.

    The panels share the label axis (its names only on the first), the figure grows with the number of classes
    (cells of about 0.3 inch) and constrained layout keeps every title and tick label clear of its neighbours."""
    plt = _plt()
    per_bin = counts.sum(axis=(0, 2)).astype(np.float64)
    cum = np.cumsum(per_bin) / max(per_bin.sum(), 1.0)
    cuts = [0] + [int(np.searchsorted(cum, k / bands)) + 1 for k in range(1, bands)] + [len(per_bin)]
    cuts = sorted(set(min(max(v, 0), len(per_bin)) for v in cuts))
    names = list(classes.names)
    panels = len(cuts) - 1
    longest = max((len(n) for n in names), default=1)
    side = max(3.0, 0.3 * len(names)) + 0.09 * longest   # one panel [inch], tick labels included
    fig, axes = plt.subplots(1, panels, figsize=(side * panels + 1.2, side + 0.8), squeeze=False, sharey=True,
                             layout="constrained")
    im = None
    for k, (ax, lo, hi) in enumerate(zip(axes[0], cuts[:-1], cuts[1:])):
        m = counts[:, lo:hi, :].sum(axis=1).astype(np.float64)
        rows = m.sum(axis=1, keepdims=True)
        img = np.where(rows > 0, m / np.maximum(rows, 1.0), np.nan)
        im = ax.imshow(img, vmin=0, vmax=1, cmap="viridis")
        ax.set_title(f"depth {edges[lo]:g}-{edges[hi]:g} m ({int(m.sum())} px)", fontsize=10)
        ax.set_xticks(range(len(names)), names, rotation=90, fontsize=TICK_FONTSIZE)
        ax.set_yticks(range(len(names)), names, fontsize=TICK_FONTSIZE)
        ax.tick_params(axis="y", labelleft=k == 0)
        ax.set_xlabel("true class")
        if k == 0:
            ax.set_ylabel("input label")
    fig.colorbar(im, ax=axes[0].tolist(), shrink=0.8, label="p(true class | label)")
    return fig
