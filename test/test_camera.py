"""Tests for css_ros.engine.camera: quaternion helpers, pose conventions, projection, resizing and validation."""
from __future__ import annotations

import math

import numpy as np
import pytest

from css_ros.engine.camera import (Camera, body_to_optical_rotation, intrinsics_from_fov, matrix_to_quaternion_xyzw,
                            quaternion_xyzw_to_matrix)
from css_ros.errors import CameraError

K = np.array([[500.0, 0.0, 319.5], [0.0, 480.0, 239.5], [0.0, 0.0, 1.0]])
W, H = 640, 480


def rot_axis_angle(axis, angle: float) -> np.ndarray:
    """Rodrigues' formula (independent of the quaternion code)."""
    a = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    S = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * S + (1 - math.cos(angle)) * S @ S


def random_unit_quats(n: int, seed: int = 0) -> np.ndarray:
    q = np.random.default_rng(seed).normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


# ---------------------------------------------------------------------------------------------- quaternions
def test_quaternion_round_trip_random():
    q = random_unit_quats(2000)
    R = quaternion_xyzw_to_matrix(q)
    assert R.shape == (2000, 3, 3)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    q2 = matrix_to_quaternion_xyzw(R)
    sign = np.where(q[:, 3:4] < 0, -1.0, 1.0)
    np.testing.assert_allclose(q2, q * sign, atol=1e-12)
    assert np.all(q2[:, 3] >= 0)
    # single-matrix path
    np.testing.assert_allclose(matrix_to_quaternion_xyzw(R[5]), q[5] * sign[5], atol=1e-12)


@pytest.mark.parametrize("axis", [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, -2, 3)])
@pytest.mark.parametrize("angle_deg", [0.0, 30.0, 90.0, 179.9, 180.0, -90.0])
def test_known_rotations(axis, angle_deg):
    ang = math.radians(angle_deg)
    a = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    q = np.r_[a * math.sin(ang / 2), math.cos(ang / 2)]
    R_expected = rot_axis_angle(axis, ang)
    np.testing.assert_allclose(quaternion_xyzw_to_matrix(q), R_expected, atol=1e-12)
    q_back = matrix_to_quaternion_xyzw(R_expected)
    # q and -q are the same rotation; 180 degrees has w = 0 so compare up to sign
    assert min(np.abs(q_back - q).max(), np.abs(q_back + q).max()) < 1e-9


def test_ninety_about_z_maps_x_to_y():
    s = math.sqrt(0.5)
    R = quaternion_xyzw_to_matrix([0.0, 0.0, s, s])
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(R @ [0, 1, 0], [-1, 0, 0], atol=1e-15)


def test_quaternion_helper_rejects_bad_input():
    with pytest.raises(CameraError):
        quaternion_xyzw_to_matrix([0, 0, 0, 0])
    with pytest.raises(CameraError):
        quaternion_xyzw_to_matrix([0, 0, np.nan, 1])
    with pytest.raises(CameraError):
        quaternion_xyzw_to_matrix([0, 0, 1])


def test_body_to_optical_rotation():
    R = body_to_optical_rotation()
    # optical z (forward) = body x; optical x (right) = body -y; optical y (down) = body -z
    np.testing.assert_array_equal(R @ [0, 0, 1], [1, 0, 0])
    np.testing.assert_array_equal(R @ [1, 0, 0], [0, -1, 0])
    np.testing.assert_array_equal(R @ [0, 1, 0], [0, 0, -1])
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(matrix_to_quaternion_xyzw(R), [-0.5, 0.5, -0.5, 0.5], atol=1e-15)
    # a body-frame robot at the origin looking along map +x: a point 2 m ahead and 1 m left projects left
    # of the principal point and on its row
    T_map_body = np.eye(4)
    T_opt = np.eye(4)
    T_opt[:3, :3] = R
    cam = Camera(K, W, H, T_map_body @ T_opt)
    uv, z = cam.project([[2.0, 1.0, 0.0]])
    assert z[0] == pytest.approx(2.0)
    np.testing.assert_allclose(uv[0], [319.5 - 500.0 * 0.5, 239.5], atol=1e-12)


# ---------------------------------------------------------------------------------------------- cameras
def test_from_pose_projects_known_point():
    q = random_unit_quats(1, seed=3)[0]
    pos = np.array([1.0, -2.0, 0.5])
    cam = Camera.from_pose(K, W, H, pos, q)
    # build a point from known camera coordinates and map it to the map frame with T_map_cam
    p_cam = np.array([0.3, -0.2, 4.0])
    p_map = cam.T_map_cam[:3, :3] @ p_cam + pos
    expected = (K[0, 0] * 0.3 / 4.0 + K[0, 2], K[1, 1] * -0.2 / 4.0 + K[1, 2])
    uv, z = cam.project(p_map[None])
    np.testing.assert_allclose(uv[0], expected, atol=1e-9)
    assert z[0] == pytest.approx(4.0)
    # same via K @ (R_cam_map p + t)
    pc = cam.R_cam_map @ p_map + cam.t_cam_map
    uvw = K @ pc
    np.testing.assert_allclose(uvw[:2] / uvw[2], expected, atol=1e-9)
    np.testing.assert_allclose(cam.world_to_cam @ cam.T_map_cam, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(cam.position, pos)
    sign = 1.0 if q[3] >= 0 else -1.0
    np.testing.assert_allclose(cam.quaternion_xyzw, sign * q, atol=1e-12)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (500.0, 480.0, 319.5, 239.5)


def test_from_pose_identity_optical_axis_is_map_z():
    cam = Camera.from_pose(K.reshape(-1), W, H, [0, 0, 0], [0, 0, 0, 1])  # CameraInfo.k form
    uv, z = cam.project([[0.0, 0.0, 3.0], [1.0, 0.0, 2.0], [0.0, 1.0, 2.0]])
    np.testing.assert_allclose(uv, [[319.5, 239.5], [569.5, 239.5], [319.5, 479.5]])
    cam2 = Camera.from_camera_info_k(list(K.reshape(-1)), W, H, (0, 0, 0), (0, 0, 0, 1))
    np.testing.assert_array_equal(cam2.K, K)


def test_from_pose_normalises_slightly_off_quaternion():
    q = np.array([0.1, 0.2, 0.3, 0.9])
    q /= np.linalg.norm(q)
    cam = Camera.from_pose(K, W, H, [0, 0, 0], q * 1.05)
    np.testing.assert_allclose(cam.quaternion_xyzw, q, atol=1e-12)


def test_look_at_puts_target_at_principal_point():
    rng = np.random.default_rng(2)
    for _ in range(50):
        pos = rng.normal(size=3) * 5
        tgt = rng.normal(size=3) * 5
        cam = Camera.look_at(pos, tgt, K, W, H)
        uv, z = cam.project(tgt[None])
        np.testing.assert_allclose(uv[0], [cam.cx, cam.cy], atol=1e-9)
        assert z[0] == pytest.approx(np.linalg.norm(tgt - pos))
        # a point above the target (map +z) appears above the principal point (smaller v)
        uv_up, _ = cam.project((tgt + [0, 0, 0.1])[None])
        assert uv_up[0, 1] < cam.cy


def test_look_at_along_x_is_body_to_optical():
    cam = Camera.look_at([0, 0, 0], [5, 0, 0], K, W, H)
    np.testing.assert_allclose(cam.R_map_cam, body_to_optical_rotation(), atol=1e-15)


def test_look_at_degenerate():
    with pytest.raises(CameraError):
        Camera.look_at([0, 0, 1], [0, 0, 1], K, W, H)
    with pytest.raises(CameraError, match="parallel"):
        Camera.look_at([0, 0, 5], [0, 0, 0], K, W, H)  # looking straight down with up = +z
    cam = Camera.look_at([0, 0, 5], [0, 0, 0], K, W, H, up=(1, 0, 0))
    np.testing.assert_allclose(cam.project([[0.0, 0.0, 0.0]])[0][0], [319.5, 239.5], atol=1e-9)


@pytest.mark.parametrize("factor", [0.5, 0.25, 2.0, 1 / 3, 0.37])
def test_scaled_preserves_pixel_centre_convention(factor):
    cam = Camera.look_at([0, 0, 1], [4, 1, 0.5], K, W, H)
    small = cam.scaled(factor)
    w2, h2 = max(1, round(W * factor)), max(1, round(H * factor))
    assert (small.width, small.height) == (w2, h2)
    sx, sy = w2 / W, h2 / H
    np.testing.assert_array_equal(small.T_map_cam, cam.T_map_cam)
    pts = np.random.default_rng(3).normal(size=(100, 3)) + [4, 1, 0.5]
    uv, z = cam.project(pts)
    uv2, z2 = small.project(pts)
    # resizing maps the continuous image coordinate x_edge = u + 0.5 to x_edge * s
    np.testing.assert_allclose(uv2[:, 0] + 0.5, (uv[:, 0] + 0.5) * sx, atol=1e-9)
    np.testing.assert_allclose(uv2[:, 1] + 0.5, (uv[:, 1] + 0.5) * sy, atol=1e-9)
    np.testing.assert_allclose(z2, z)
    # image edges map to image edges: principal point at the centre stays at the centre
    assert small.cx == pytest.approx((w2 - 1) / 2)
    assert small.cy == pytest.approx((h2 - 1) / 2)


def test_scaled_tiny_and_invalid():
    cam = Camera(K, W, H, np.eye(4))
    t = cam.scaled(1e-6)
    assert (t.width, t.height) == (1, 1)
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(CameraError):
            cam.scaled(bad)


def test_intrinsics_from_fov():
    Kf = intrinsics_from_fov(640, 480, 90.0)
    assert Kf[0, 0] == pytest.approx(320.0) and Kf[1, 1] == pytest.approx(320.0)
    assert (Kf[0, 2], Kf[1, 2]) == (319.5, 239.5)


def test_camera_is_frozen_and_readonly():
    cam = Camera(K, W, H, np.eye(4))
    with pytest.raises(Exception):
        cam.width = 3  # type: ignore[misc]
    with pytest.raises(ValueError):
        cam.K[0, 0] = 1.0
    k_in = K.copy()
    cam2 = Camera(k_in, W, H, np.eye(4))
    k_in[0, 0] = 1.0
    assert cam2.fx == 500.0  # defensive copy


# ---------------------------------------------------------------------------------------------- invalid input
@pytest.mark.parametrize("pos,q,match", [
    ([np.nan, 0, 0], [0, 0, 0, 1], "position"),
    ([0, np.inf, 0], [0, 0, 0, 1], "position"),
    ([0, 0, 0], [0, 0, 0, 0], "not a unit quaternion"),
    ([0, 0, 0], [0, 0, 0, 2], "not a unit quaternion"),
    ([0, 0, 0], [0, 0, 0.5, 0.5], "not a unit quaternion"),
    ([0, 0, 0], [0, np.nan, 0, 1], "quaternion"),
    ([0, 0], [0, 0, 0, 1], "position"),
    ([0, 0, 0], [0, 0, 1], "quaternion"),
])
def test_from_pose_rejects_bad_pose(pos, q, match):
    with pytest.raises(CameraError, match=match):
        Camera.from_pose(K, W, H, pos, q)


@pytest.mark.parametrize("k", [
    np.where(np.eye(3, dtype=bool), np.nan, K),
    np.array([[500.0, 0, np.inf], [0, 480, 239.5], [0, 0, 1]]),
    np.array([[-500.0, 0, 319.5], [0, 480, 239.5], [0, 0, 1]]),
    np.array([[500.0, 0, 319.5], [0, 0.0, 239.5], [0, 0, 1]]),
    np.array([[500.0, 0, 319.5], [0, 480, 239.5], [0, 0, 2]]),
    np.array([[500.0, 1.0, 319.5], [0, 480, 239.5], [0, 0, 1]]),
    np.zeros(8),
])
def test_rejects_bad_intrinsics(k):
    with pytest.raises(CameraError):
        Camera.from_pose(k, W, H, [0, 0, 0], [0, 0, 0, 1])


@pytest.mark.parametrize("w,h", [(-640, 480), (640, 0), (0, 0), (640.5, 480), (True, 480), ("640", 480)])
def test_rejects_bad_size(w, h):
    with pytest.raises(CameraError):
        Camera(K, w, h, np.eye(4))


def test_rejects_non_rigid_pose():
    T = np.eye(4)
    T[:3, :3] *= 1.01  # scaled
    with pytest.raises(CameraError, match="orthonormal"):
        Camera(K, W, H, T)
    T = np.diag([1.0, 1.0, -1.0, 1.0])  # reflection
    with pytest.raises(CameraError, match="determinant"):
        Camera(K, W, H, T)
    T = np.eye(4)
    T[3, 0] = 0.5
    with pytest.raises(CameraError, match="last row"):
        Camera(K, W, H, T)
    T = np.eye(4)
    T[0, 3] = np.nan
    with pytest.raises(CameraError, match="non-finite"):
        Camera(K, W, H, T)
    with pytest.raises(CameraError):
        Camera(K, W, H, np.eye(3))
