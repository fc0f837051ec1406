"""The label rule (:func:`css_ros.engine.label_input.pixel_vote`) compiled for the CPU: labels and confidence as they
came in, one compiled pass that gives the update kernel its class and weight planes and counts the pixels."""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from ..label_input import IGNORED, NUM_COUNTS, OUT_OF_RANGE, USED, FrameLabels, pixel_vote

_pixel_vote = njit(inline="always")(pixel_vote)


@njit(parallel=True, cache=True)
def _votes(labels, confidence, has_confidence, num_classes, ignore_label, classes, weights, counts):  # pragma: no cover
    """classes[v, u], weights[v, u] = pixel_vote(...); counts[row, status] += 1 (one row per image row)."""
    height, width = labels.shape
    for v in prange(height):
        used = 0
        ignored = 0
        oor = 0
        for u in range(width):
            conf = 1.0
            if has_confidence:
                conf = confidence[v, u]
            c, w, status = _pixel_vote(labels[v, u], conf, num_classes, ignore_label)
            classes[v, u] = c
            weights[v, u] = w
            if status == USED:
                used += 1
            elif status == IGNORED:
                ignored += 1
            else:
                oor += 1
        counts[v, USED] = used
        counts[v, IGNORED] = ignored
        counts[v, OUT_OF_RANGE] = oor


_NO_CONFIDENCE = np.zeros((1, 1), dtype=np.float32)


def votes(inputs: FrameLabels) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(classes (H, W) int32, -1 = no vote; weights (H, W) float32; counts (NUM_COUNTS,) int64: used, ignored, out of
    range, 0) of a frame, in one compiled pass over its pixels."""
    labels = inputs.labels
    height, width = labels.shape
    classes = np.empty((height, width), dtype=np.int32)
    weights = np.empty((height, width), dtype=np.float32)
    rows = np.zeros((height, NUM_COUNTS), dtype=np.int64)
    conf = _NO_CONFIDENCE if inputs.confidence is None else inputs.confidence
    _votes(labels, conf, inputs.confidence is not None, inputs.num_classes, inputs.ignore_label, classes, weights,
           rows)
    return classes, weights, rows.sum(axis=0)
