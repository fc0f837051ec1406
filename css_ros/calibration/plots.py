"""css_calibrate's figures: reliability vs depth per class, confusion per depth band, reliability diagrams."""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..engine.atomic import atomic_file
from ..evaluation.calibration_plots import reliability_panels_figure

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


def reliability_by_depth_figure(model: "SensorModel", counts: np.ndarray, classes: "ClassSet") -> Any:
    """p(label right | label, depth) per class (solid; marker size ~ pixels) and the vote weight w (dashed)."""
    plt = _plt()
    c = model.num_classes
    centres = 0.5 * (model.depth_edges[:-1] + model.depth_edges[1:])
    p = model.label_distribution()[np.arange(c), :, np.arange(c)] if model.confusion is not None else None
    n = counts.sum(axis=2)
    raw = np.where(n > 0, counts[np.arange(c), :, np.arange(c)] / np.maximum(n, 1), np.nan)
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.8), sharex=True)
    order = np.argsort(-n.sum(axis=1))
    for y in order:
        if n[y].sum() == 0:
            continue
        color = np.asarray(classes.palette[y]) / 255.0
        axes[0].plot(centres, raw[y], "o", color=color, markersize=3, alpha=0.6)
        axes[0].plot(centres, p[y] if p is not None else raw[y], "-", color=color, label=classes.names[y])
        axes[1].plot(centres, model.weight[y], "-", color=color, label=classes.names[y])
    axes[0].set_title("p(label right | label, depth): dots measured, lines smoothed")
    axes[0].set_ylabel("fraction of pixels whose label is right")
    axes[1].set_title("vote weight w(label, depth) used by the update")
    axes[1].set_ylabel("w")
    for ax in axes:
        ax.set_xlabel("rendered depth [m]")
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=7, ncol=2, loc="lower left")
    fig.tight_layout()
    return fig


def confusion_bands_figure(counts: np.ndarray, edges: np.ndarray, classes: "ClassSet", bands: int = 3) -> Any:
    """Row-normalised confusion (label -> true class) in ``bands`` depth bands of about equal pixel count."""
    plt = _plt()
    per_bin = counts.sum(axis=(0, 2)).astype(np.float64)
    cum = np.cumsum(per_bin) / max(per_bin.sum(), 1.0)
    cuts = [0] + [int(np.searchsorted(cum, k / bands)) + 1 for k in range(1, bands)] + [len(per_bin)]
    cuts = sorted(set(min(max(v, 0), len(per_bin)) for v in cuts))
    fig, axes = plt.subplots(1, len(cuts) - 1, figsize=(5.2 * (len(cuts) - 1), 5), squeeze=False)
    names = list(classes.names)
    for ax, lo, hi in zip(axes[0], cuts[:-1], cuts[1:]):
        m = counts[:, lo:hi, :].sum(axis=1).astype(np.float64)
        rows = m.sum(axis=1, keepdims=True)
        img = np.where(rows > 0, m / np.maximum(rows, 1.0), np.nan)
        im = ax.imshow(img, vmin=0, vmax=1, cmap="viridis")
        ax.set_title(f"depth {edges[lo]:g}-{edges[hi]:g} m ({int(m.sum())} px)", fontsize=9)
        ax.set_xticks(range(len(names)), names, rotation=90, fontsize=6)
        ax.set_yticks(range(len(names)), names, fontsize=6)
        ax.set_xlabel("true class")
        ax.set_ylabel("input label")
    fig.colorbar(im, ax=axes[0].tolist(), shrink=0.8, label="p(true class | label)")
    return fig


