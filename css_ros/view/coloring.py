"""Colours and filters of the page's modes: RGB, semantic class, E of the argmax class, Var, evidence."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..export.colormap import UNKNOWN_RGB, class_colors, uncertainty_colors
from .data import ViewData

MODES = ("rgb", "semantic", "expectation", "variance", "evidence")
MODE_LABELS = {"rgb": "RGB", "semantic": "Semantic class", "expectation": "E of the argmax class",
               "variance": "Var of the argmax class", "evidence": "Evidence (how well observed)"}
#: colour map of each continuous mode and whether its scale is logarithmic
CONTINUOUS = {"expectation": ("viridis", False), "variance": ("magma", True), "evidence": ("viridis", True)}


@dataclass(frozen=True)
class ColorBar:
    """Scale of a continuous mode: colour map, value range, log scale flag, label with units."""

    cmap: str
    vmin: float
    vmax: float
    log: bool
    label: str

    def stops(self, n: int = 9) -> list[tuple[int, int, int]]:
        """``n`` RGB uint8 colours from vmin to vmax (for a CSS gradient)."""
        import matplotlib

        cm = matplotlib.colormaps[self.cmap]
        return [tuple(int(round(255 * v)) for v in cm(t)[:3]) for t in np.linspace(0.0, 1.0, n)]


def mode_colors(data: ViewData, mode: str) -> tuple[np.ndarray, ColorBar | None]:
    """(M, 3) float32 colours in [0, 1] of the displayed Gaussians in ``mode`` and the colour bar (None for
    RGB and semantic). Unobserved Gaussians are grey in every mode but RGB."""
    sem = data.semantics
    if mode == "rgb":
        return data.rgb, None
    if mode == "semantic":
        return class_colors(sem.label, data.classes).astype(np.float32) / 255.0, None
    if mode == "expectation":
        import matplotlib

        c = data.classes.num_classes
        vmin, vmax = 1.0 / c, 1.0  # E of the argmax class is never below 1/C
        t = np.clip((sem.expectation.astype(np.float64) - vmin) / max(vmax - vmin, 1e-12), 0.0, 1.0)
        rgb = matplotlib.colormaps["viridis"](t)[:, :3].astype(np.float32)
        rgb[~sem.observed] = np.asarray(UNKNOWN_RGB, np.float32) / 255.0
        return rgb, ColorBar("viridis", vmin, vmax, False, "E of the argmax class (probability)")
    if mode in ("variance", "evidence"):
        values = sem.variance if mode == "variance" else sem.evidence
        uc = uncertainty_colors(values, mode, mask=sem.observed)
        return uc.rgb.astype(np.float32) / 255.0, ColorBar(uc.cmap, uc.vmin, uc.vmax, True, uc.label)
    raise ValueError(f"unknown mode {mode!r} (one of {', '.join(MODES)})")


def visible_mask(data: ViewData, hidden_classes: set[int], observed_only: bool, uncertain_only: bool,
                 var_threshold: float) -> np.ndarray:
    """(M,) bool: Gaussians to draw. Hidden classes are dropped (by their label; unobserved ones have the
    ignore label and are dropped by ``observed_only``); ``uncertain_only`` keeps Var >= ``var_threshold``."""
    sem = data.semantics
    keep = np.ones(len(sem.label), dtype=bool)
    if hidden_classes:
        keep &= ~np.isin(sem.label, np.fromiter(hidden_classes, dtype=np.int64))
    if observed_only:
        keep &= sem.observed
    if uncertain_only:
        keep &= sem.variance >= var_threshold
    return keep
