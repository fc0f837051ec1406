"""Raw per-pixel render outputs shared by every backend (no numba, no torch)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class RenderBuffers:
    """Raw per-pixel outputs of a backend's render (see SemanticMap.render for meaning)."""

    labels: np.ndarray        # (H, W) int32
    expectation: np.ndarray   # (H, W) float64
    variance: np.ndarray      # (H, W) float64
    background: np.ndarray    # (H, W) float64
    evidence: np.ndarray      # (H, W) float64
    rgb: np.ndarray           # (H, W, 3) float64 in [0, inf)
    probabilities: np.ndarray | None  # (H, W, C) float64
    depth: np.ndarray | None = None   # (H, W) float64 expected depth sum kappa z / sum kappa [splat units], NaN: none
    mass: np.ndarray | None = None    # (M,) float64 evidence each visible Gaussian would get from this view (scoring)
