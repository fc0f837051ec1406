"""The columns of the 3D semantic map cloud (``~/semantic_cloud``): one point per observed Gaussian.

ROS-free: the node packs the columns with :func:`css_ros.io.clouds.pack_cloud`. A 3M-Gaussian map
stays a reasonable message through two optional reductions, applied in this order:

- ``voxel_size`` [m] > 0: per voxel of that edge (map frame, voxels aligned to the origin) keep the
  most certain Gaussian: the one with the smallest variance of its label (ties: the larger evidence,
  then the lower index);
- ``max_points`` > 0: if more points remain, keep the ``max_points`` most certain ones (same order).

The kept points are returned in increasing Gaussian index, so consecutive clouds of a slowly
changing map list points in a stable order.
"""
from __future__ import annotations

import numpy as np

from .clouds import pack_rgb

#: Fields of ~/semantic_cloud, in order (x y z float32, rgb packed float32, label uint16, the rest float32).
SEMANTIC_CLOUD_FIELDS = ("x", "y", "z", "rgb", "label", "expectation", "variance", "evidence")


def _certainty_order(variance: np.ndarray, evidence: np.ndarray) -> np.ndarray:
    """Indices sorted most certain first: smallest variance, then largest evidence, then lowest index."""
    idx = np.arange(len(variance))
    return np.lexsort((idx, -evidence, variance))


def select_points(means: np.ndarray, variance: np.ndarray, evidence: np.ndarray, voxel_size: float = 0.0,
                  max_points: int = 0) -> np.ndarray:
    """Indices (into the given rows, increasing) kept by the voxel and count reductions (module docstring).

    Args:
        means: (M, 3) positions [m, map frame]; variance, evidence: (M,) of each row's label.
        voxel_size: voxel edge [m]; 0 = no voxel reduction.
        max_points: largest number of points; 0 = no limit.
    """
    order = _certainty_order(np.asarray(variance, np.float64), np.asarray(evidence, np.float64))
    if voxel_size > 0 and len(order):
        cells = np.floor(np.asarray(means, np.float64)[order] / voxel_size).astype(np.int64)
        _, first = np.unique(cells, axis=0, return_index=True)  # first = most certain row of each voxel
        order = order[np.sort(first)]
    if max_points > 0 and len(order) > max_points:
        order = order[:max_points]
    return np.sort(order)


def semantic_cloud_columns(means: np.ndarray, labels: np.ndarray, expectation: np.ndarray, variance: np.ndarray,
                           evidence: np.ndarray, observed: np.ndarray, palette: np.ndarray,
                           voxel_size: float = 0.0, max_points: int = 0) -> dict[str, np.ndarray]:
    """Columns of ``~/semantic_cloud`` for the observed Gaussians (:data:`SEMANTIC_CLOUD_FIELDS`).

    Args:
        means: (N, 3) Gaussian centres [m, map frame].
        labels: (N,) class id of each Gaussian (SPEC §9 label); expectation, variance: (N,) E and Var
            of that label; evidence: (N,) Dirichlet total S_n; observed: (N,) bool.
        palette: (C, 3) uint8 class colours (``rgb`` is the label's colour).
        voxel_size, max_points: reductions, see :func:`select_points`.
    """
    rows = np.flatnonzero(np.asarray(observed, bool))
    keep = rows[select_points(means[rows], variance[rows], evidence[rows], voxel_size, max_points)]
    lab = np.asarray(labels)[keep]
    palette = np.asarray(palette, np.uint8).reshape(-1, 3)
    rgb = palette[np.clip(lab, 0, len(palette) - 1)] if len(palette) else np.zeros((len(lab), 3), np.uint8)
    xyz = np.asarray(means, np.float64)[keep]
    return {
        "x": xyz[:, 0].astype(np.float32), "y": xyz[:, 1].astype(np.float32), "z": xyz[:, 2].astype(np.float32),
        "rgb": pack_rgb(rgb),
        "label": lab.astype(np.uint16),
        "expectation": np.asarray(expectation, np.float32)[keep],
        "variance": np.asarray(variance, np.float32)[keep],
        "evidence": np.asarray(evidence, np.float32)[keep],
    }
