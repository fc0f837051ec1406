"""The per-frame output images of SPEC §8, built once for css_node (publishing) and css_replay (bag writing)."""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from collections.abc import Collection

    from ..engine.classes import ClassSet
    from ..engine.semantic_map import RenderedView


def label_encoding(num_classes: int, ignore_label: int) -> str:
    """Image encoding of a label image: mono8 when every class id and the ignore label fit in 8 bits, else mono16."""
    return "mono8" if max(num_classes - 1, ignore_label) <= 255 else "mono16"


def mono_to_rgb(image: np.ndarray) -> np.ndarray:
    """(H, W) grey image -> (H, W, 3) by repeating the channel; (H, W, 3) is returned unchanged."""
    return np.repeat(image[:, :, None], 3, axis=2) if image.ndim == 2 else image


#: frame output topic -> the RenderedView images it is made from (what css_node asks the engine for)
TOPIC_IMAGES: dict[str, tuple[str, ...]] = {
    "semantic": ("labels",), "semantic_color": ("labels",), "expectation": ("expectation",),
    "variance": ("variance",), "rendered_image": ("rgb",), "confidence": ("confidence",),
    "surprise": ("surprise",),
}


def frame_output_images(view: "RenderedView", classes: "ClassSet", ignore_label: int,
                        names: "Collection[str] | None" = None) -> dict[str, tuple[np.ndarray, str]]:
    """Output name -> (array, encoding) of one rendered frame, in publishing order (SPEC §8):
    ``semantic`` (label ids), ``semantic_color`` (class colours, rgb8), ``expectation`` and ``variance``
    (32FC1, of the argmax class), ``rendered_image`` (rgb8) and, when the map's sensor model holds a calibrated
    confidence map, ``confidence`` (32FC1: probability that ``semantic`` is right; 0 where it is the ignore label)
    and, for a view of :meth:`~css_ros.engine.semantic_map.SemanticMap.observe` that made it, ``surprise`` (32FC1:
    1 - E of each pixel's observed label under the map before the frame; NaN where the pixel had no label).
    Only the outputs in ``names`` (None: all) are made; images the view does not hold (not requested from the
    engine) give no entry."""
    def want(name: str) -> bool:
        return names is None or name in names

    labels = view.labels
    out: dict[str, tuple[np.ndarray, str]] = {}
    if labels is not None:  # images the caller did not ask the engine for are None (RenderedView)
        if want("semantic"):
            out["semantic"] = (labels, label_encoding(classes.num_classes, ignore_label))
        if want("semantic_color"):
            out["semantic_color"] = (classes.colorize(labels, ignore_label=ignore_label), "rgb8")
    for name, field, encoding in (("expectation", "expectation", "32FC1"), ("variance", "variance", "32FC1"),
                                  ("rendered_image", "rgb", "rgb8"), ("confidence", "confidence", "32FC1"),
                                  ("surprise", "surprise", "32FC1")):
        array = getattr(view, field)
        if array is not None and want(name):
            out[name] = (array, encoding)
    return out
