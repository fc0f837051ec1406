"""The per-frame images the live page can show beside the splat (css_view --live): the node's ``~/surprise``.

The surprise of a pixel is 1 - E of its observed label under the map before the frame's update (0: expected, near 1:
the map expected another class there); NaN where the segmentation had no label.
"""
from __future__ import annotations

import numpy as np

from ..export.colormap import UNKNOWN_RGB
from .coloring import ColorBar

#: choices of the page's "Frame image" control, in menu order ("none": no image)
FRAME_IMAGES = ("none", "surprise")
FRAME_IMAGE_LABELS = {"none": "None", "surprise": "Surprise of the last frame"}
#: colour map of the surprise image, on the fixed range [0, 1]
SURPRISE_BAR = ColorBar("inferno", 0.0, 1.0, False, "surprise: 1 - E of the observed label before the frame")


def surprise_rgb(surprise: np.ndarray) -> np.ndarray:
    """(H, W) float surprise in [0, 1] -> (H, W, 3) uint8 in :data:`SURPRISE_BAR`'s colour map; NaN (no label) is
    the grey of unobserved Gaussians; values outside [0, 1] are clipped."""
    import matplotlib

    s = np.asarray(surprise, dtype=np.float64)
    if s.ndim != 2:
        raise ValueError(f"a surprise image is (H, W), got shape {s.shape}")
    labelled = np.isfinite(s)
    t = np.clip(np.where(labelled, s, 0.0), SURPRISE_BAR.vmin, SURPRISE_BAR.vmax)
    rgb = np.round(matplotlib.colormaps[SURPRISE_BAR.cmap](t)[..., :3] * 255.0).astype(np.uint8)
    rgb[~labelled] = UNKNOWN_RGB
    return rgb


def surprise_caption(surprise: np.ndarray, stamp_ns: int, topic: str) -> str:
    """Markdown under the image: its topic and stamp, and the mean over the labelled pixels."""
    finite = np.isfinite(surprise)
    mean = f"{float(np.mean(surprise[finite])):.3f}" if finite.any() else "n/a (no labelled pixel)"
    return (f"`{topic}` at {stamp_ns * 1e-9:.3f} s: mean surprise {mean} over {int(finite.sum())} labelled pixels "
            f"of {surprise.size}")
