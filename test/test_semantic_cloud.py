"""Columns of ~/semantic_cloud: observed Gaussians only, voxel reduction keeps the most certain, count bound."""
from __future__ import annotations

import numpy as np

from css_ros.io.clouds import unpack_rgb
from css_ros.io.semantic_cloud import SEMANTIC_CLOUD_FIELDS, select_points, semantic_cloud_columns


def _brute_select(means, var, ev, voxel, max_points):
    """Independent reference: loop over voxels, pick the best by (var, -ev, index); then a global cut."""
    best = {}
    for i in range(len(means)):
        key = tuple(np.floor(means[i] / voxel).astype(int)) if voxel > 0 else (i,)
        rank = (var[i], -ev[i], i)
        if key not in best or rank < best[key][0]:
            best[key] = (rank, i)
    kept = sorted(best.values())
    if max_points:
        kept = kept[:max_points]
    return sorted(i for _, i in kept)


def test_select_matches_brute_force():
    rng = np.random.default_rng(3)
    means = rng.uniform(-1, 1, (400, 3))
    var = rng.choice([0.1, 0.2, 0.3], 400)  # ties exercise the evidence / index tie breaks
    ev = rng.choice([1.0, 2.0], 400)
    for voxel, cap in ((0.0, 0), (0.5, 0), (0.25, 0), (0.0, 37), (0.5, 5)):
        assert select_points(means, var, ev, voxel, cap).tolist() == _brute_select(means, var, ev, voxel, cap)


def test_columns_hold_observed_gaussians_with_class_colours():
    means = np.array([[0.0, 0, 0], [1, 1, 1], [2, 2, 2], [0.01, 0, 0]])
    labels = np.array([1, 0, 2, 1])
    e = np.array([0.9, 0.5, 0.7, 0.95])
    v = np.array([0.01, 0.1, 0.05, 0.001])
    s = np.array([10.0, 2, 5, 30])
    observed = np.array([True, False, True, True])
    palette = np.array([[10, 20, 30], [200, 0, 0], [0, 0, 255]], np.uint8)
    cols = semantic_cloud_columns(means, labels, e, v, s, observed, palette)
    assert tuple(cols) == SEMANTIC_CLOUD_FIELDS
    assert cols["label"].tolist() == [1, 2, 1]  # unobserved Gaussian 1 left out, index order kept
    np.testing.assert_array_equal(unpack_rgb(cols["rgb"]), palette[[1, 2, 1]])
    np.testing.assert_allclose(cols["x"], [0, 2, 0.01], rtol=1e-6)
    cols = semantic_cloud_columns(means, labels, e, v, s, observed, palette, voxel_size=0.5)
    assert cols["label"].tolist() == [2, 1] and cols["variance"][1] == np.float32(0.001)  # Gaussian 3 wins its voxel
    cols = semantic_cloud_columns(means, labels, e, v, s, observed, palette, max_points=1)
    assert cols["evidence"].tolist() == [30.0]
