"""Colours of the exported maps: class palette colours and uncertainty colour maps with a colour bar."""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Literal

import numpy as np

from ..engine.classes import ClassSet
from ..errors import ConfigError
from .files import atomic_binary

UNKNOWN_RGB = (128, 128, 128)   # colour of unobserved Gaussians / unknown points (uint8 RGB)

UncertaintyQuantity = Literal["variance", "evidence"]

#: colour-bar label (with units) of each uncertainty quantity
QUANTITY_LABELS = {
    "variance": "Var[θ] of the map label (dimensionless, log scale; bright = uncertain)",
    "evidence": "evidence S_n − C·α₀ (κ-weighted label count in pixels, log scale)",
}


def class_colors(labels: np.ndarray, classes: ClassSet, ignore_label: int = 255,
                 unknown_rgb: tuple[int, int, int] = UNKNOWN_RGB) -> np.ndarray:
    """(N, 3) uint8 RGB: the class palette colour of each label, ``unknown_rgb`` for ``ignore_label``
    and any id outside 0..C-1."""
    labels = np.asarray(labels)
    out = np.empty(labels.shape + (3,), dtype=np.uint8)
    out[...] = np.asarray(unknown_rgb, dtype=np.uint8)
    valid = (labels >= 0) & (labels < classes.num_classes) & (labels != ignore_label)
    out[valid] = classes.palette[labels[valid]]
    return out


@dataclass(frozen=True)
class UncertaintyColors:
    """Colours of one uncertainty quantity and the scale that made them.

    Attributes:
        rgb: (N, 3) uint8 colours (``UNKNOWN_RGB`` where the value was masked out).
        quantity: "variance" or "evidence".
        vmin, vmax: ends of the logarithmic colour scale (values beyond are clipped).
        cmap: matplotlib colour map name.
        label: colour-bar label with units.
    """

    rgb: np.ndarray
    quantity: str
    vmin: float
    vmax: float
    cmap: str
    label: str


def uncertainty_colors(values: np.ndarray, quantity: UncertaintyQuantity, mask: np.ndarray | None = None,
                       cmap: str | None = None) -> UncertaintyColors:
    """Colour ``values`` (N,) through a matplotlib colour map on a log scale.

    The scale spans the 1st to 99th percentile of the positive values under ``mask`` (the observed
    Gaussians), so a few outliers do not wash out the picture. Default colour maps: "magma" for
    variance (bright = uncertain), "viridis" for evidence (bright = well observed).
    """
    import matplotlib
    from matplotlib.colors import LogNorm

    if quantity not in QUANTITY_LABELS:
        raise ConfigError(f"unknown uncertainty quantity {quantity!r} (variance or evidence)")
    cmap = cmap or ("magma" if quantity == "variance" else "viridis")
    try:
        cm = matplotlib.colormaps[cmap]
    except KeyError:
        raise ConfigError(f"unknown matplotlib colour map {cmap!r}") from None
    values = np.asarray(values, dtype=np.float64)
    mask = np.ones(values.shape, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    pos = values[mask & (values > 0) & np.isfinite(values)]
    if pos.size:
        vmin, vmax = (float(v) for v in np.percentile(pos, [1.0, 99.0]))
    else:
        vmin, vmax = 1e-6, 1.0
    if not vmax > vmin:
        vmin, vmax = vmin / 2.0, vmin * 2.0
    norm = LogNorm(vmin=vmin, vmax=vmax, clip=True)
    scaled = norm(np.clip(values, vmin, vmax))
    rgb = np.clip(np.rint(cm(np.asarray(scaled))[:, :3] * 255.0), 0, 255).astype(np.uint8)
    rgb[~mask] = np.asarray(UNKNOWN_RGB, dtype=np.uint8)
    return UncertaintyColors(rgb, quantity, vmin, vmax, cmap, QUANTITY_LABELS[quantity])


def write_colorbar(path: str | os.PathLike[str], colors: UncertaintyColors, dpi: int = 150) -> None:
    """Write the colour bar of ``colors`` (log scale, labelled with units) as a PNG, atomically."""
    import matplotlib
    from matplotlib.colors import LogNorm
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.0, 1.3), dpi=dpi)
    ax = fig.add_axes((0.05, 0.55, 0.9, 0.25))
    sm = matplotlib.cm.ScalarMappable(norm=LogNorm(colors.vmin, colors.vmax), cmap=colors.cmap)
    bar = fig.colorbar(sm, cax=ax, orientation="horizontal")
    bar.set_label(colors.label + "; grey = unobserved", fontsize=8)
    bar.ax.tick_params(labelsize=7)
    with atomic_binary(path) as fh:
        fig.savefig(fh, format="png")
