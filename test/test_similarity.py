"""Similarity (splat_to_map, extrinsics): parsing with named errors, algebra against matrices, moved models."""
from __future__ import annotations

import math

import numpy as np
import pytest

from css_ros.engine.camera import quaternion_xyzw_to_matrix
from css_ros.engine.similarity import Similarity, parse_extrinsics, rotation_between
from css_ros.errors import ConfigError


def random_similarity(rng: np.random.Generator) -> Similarity:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    return Similarity.from_params([float(rng.uniform(0.2, 5.0)), *rng.normal(size=3), *q])


def test_apply_inverse_compose_match_homogeneous_matrices() -> None:
    rng = np.random.default_rng(1)
    a, b = random_similarity(rng), random_similarity(rng)
    pts = rng.normal(size=(20, 3))
    hom = np.c_[pts, np.ones(20)]
    assert np.allclose(a.apply(pts), (hom @ a.matrix().T)[:, :3])
    assert np.allclose((a @ b).matrix(), a.matrix() @ b.matrix())
    assert np.allclose(a.inverse().apply(a.apply(pts)), pts)
    assert np.allclose(Similarity.from_params(a.to_params()).matrix(), a.matrix())


def test_pose_transforms_keep_a_camera_rigid() -> None:
    rng = np.random.default_rng(2)
    s = random_similarity(rng)
    p, q = s.apply_pose(np.array([1.0, 2.0, 3.0]), np.array([0.0, 0.0, 0.0, 1.0]))
    assert np.allclose(quaternion_xyzw_to_matrix(q), s.R) and np.allclose(p, s.apply([1.0, 2.0, 3.0]))
    ext = Similarity.rigid_from_params([0.1, 0.0, 0.3, -0.5, 0.5, -0.5, 0.5])
    body_q = np.array([0.0, 0.0, math.sin(0.3), math.cos(0.3)])
    cp, cq = ext.compose_pose(np.array([2.0, 1.0, 0.0]), body_q)
    T = np.eye(4)
    T[:3, :3] = quaternion_xyzw_to_matrix(body_q)
    T[:3, 3] = [2.0, 1.0, 0.0]
    expected = T @ ext.matrix()
    assert np.allclose(cp, expected[:3, 3]) and np.allclose(quaternion_xyzw_to_matrix(cq), expected[:3, :3])


@pytest.mark.parametrize("values, words", [
    ([0.0, 0, 0, 0, 0, 0, 0, 1], "scale"),
    ([-1.0, 0, 0, 0, 0, 0, 0, 1], "scale"),
    ([float("nan"), 0, 0, 0, 0, 0, 0, 1], "scale"),
    ([1.0, float("inf"), 0, 0, 0, 0, 0, 1], "translation"),
    ([1.0, 0, 0, 0, 0, 0, 0, 2], "unit quaternion"),
    ([1.0, 0, 0, 0, 0, 0, 1], "8 numbers"),
])
def test_bad_splat_to_map_names_the_parameter(values: list[float], words: str) -> None:
    with pytest.raises(ConfigError, match="splat_to_map") as exc:
        Similarity.from_params(values)
    assert words in str(exc.value)


def test_parse_extrinsics_per_camera() -> None:
    assert parse_extrinsics([], 2) == [None, None]
    exts = parse_extrinsics([0, 0, 0, 0, 0, 0, 1, 1, 2, 3, 0, 0, 0, 1], 2)
    assert np.allclose(exts[1].t, [1, 2, 3])
    with pytest.raises(ConfigError, match=r"camera_extrinsics \(camera 1\)"):
        parse_extrinsics([0, 0, 0, 0, 0, 0, 1, 1, 2, 3, 0, 0, 0, 5], 2)
    with pytest.raises(ConfigError, match="per camera"):
        parse_extrinsics([0, 0, 0, 0, 0, 0, 1], 2)


def test_rotation_between() -> None:
    for a, b in (([0, -1, 0], [0, 0, 1]), ([1, 0, 0], [-1, 0, 0]), ([0, 0, 1], [0, 0, 1])):
        R = rotation_between(np.array(a, float), np.array(b, float))
        assert np.allclose(R @ a, b) and np.allclose(R.T @ R, np.eye(3)) and np.isclose(np.linalg.det(R), 1)


def test_transform_model_moves_means_scales_and_axes() -> None:
    from css_ros.engine.gaussians import GaussianModel

    rng = np.random.default_rng(3)
    n = 10
    model = GaussianModel.from_activated(rng.normal(size=(n, 3)), rng.uniform(0.01, 0.2, (n, 3)),
                                         np.tile([1.0, 0, 0, 0], (n, 1)), np.full(n, 0.5), rng.uniform(0, 1, (n, 3)))
    s = random_similarity(rng)
    moved = s.transform_model(model)
    assert np.allclose(moved.means, s.apply(model.means), atol=1e-5)
    cov = model.covariances() if callable(getattr(model, "covariances", None)) else model.covariances
    cov2 = moved.covariances() if callable(getattr(moved, "covariances", None)) else moved.covariances
    assert np.allclose(cov2, s.scale ** 2 * s.R @ cov @ s.R.T, rtol=1e-4, atol=1e-8)
