"""Argument checks of css_ros.engine.camera (probe findings E5, E10, E14): the image-size bound, rotation helpers
that refuse what is not a rotation and survive huge magnitudes, and look_at / intrinsics_from_fov / scaled /
resized refusing bad arguments with CameraError naming them."""
from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from css_ros.engine.camera import (MAX_CAMERA_PIXELS, Camera, intrinsics_from_fov, matrix_to_quaternion_xyzw,
                                   quaternion_xyzw_to_matrix)
from css_ros.errors import CameraError
from css_ros.io.frames import DEFAULT_MAX_IMAGE_PIXELS

K = np.array([[60.0, 0.0, 31.5], [0.0, 60.0, 23.5], [0.0, 0.0, 1.0]])
W, H = 64, 48

# 180 degrees about (1, 1, 0) / sqrt(2): R = 2 a a^T - I with a = (1, 1, 0) / sqrt(2)
R_180_XY = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


@pytest.fixture(autouse=True)
def _warnings_are_errors():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        yield


# ---------------------------------------------------------------------------------------------- E5 image size
def test_bound_admits_the_node_default_and_8k():
    assert DEFAULT_MAX_IMAGE_PIXELS <= MAX_CAMERA_PIXELS
    assert MAX_CAMERA_PIXELS == 8192 * 8192
    for w, h in ((4096, 4096), (7680, 4320), (8192, 4320), (8192, 8192), (MAX_CAMERA_PIXELS, 1)):
        cam = Camera(K, w, h, np.eye(4))
        assert (cam.width, cam.height) == (w, h)


@pytest.mark.parametrize("w,h", [(100000, 100000), (8193, 8192), (2**63, 1), (np.uint64(2**64 - 1), 48),
                                 (np.int64(2**40), 2**40), (1e300, 1),
                                 pytest.param(10**400, 1, id="10**400")])
def test_camera_refuses_images_above_the_bound(w, h):
    with pytest.raises(CameraError, match="exceeds MAX_CAMERA_PIXELS"):
        Camera(K, w, h, np.eye(4))


@pytest.mark.parametrize("w,h,match", [(True, 48, "width must be an integer"), (64, np.bool_(True), "height"),
                                       (64.5, 48, "width must be an integer"), (64, 0, "positive"),
                                       (-64, 48, "positive"), (64, "48", "height must be an integer")])
def test_camera_refuses_non_integral_sizes(w, h, match):
    with pytest.raises(CameraError, match=match):
        Camera(K, w, h, np.eye(4))


def test_scaled_and_resized_respect_the_bound():
    cam = Camera(K, W, H, np.eye(4))
    for factor in (1e6, 1e300, 1e308, 2**2000):
        with pytest.raises(CameraError, match="scale factor .*MAX_CAMERA_PIXELS|scale factor must be finite"):
            cam.scaled(factor)
    with pytest.raises(CameraError, match="exceeds MAX_CAMERA_PIXELS"):
        cam.resized(2**40, 2**40)
    with pytest.raises(CameraError, match="exceeds MAX_CAMERA_PIXELS"):
        cam.resized(np.uint64(2**64 - 1), 48)
    big = cam.scaled(128.0)  # 8192 x 6144: within the bound
    assert (big.width, big.height) == (8192, 6144)


# ---------------------------------------------------------------------------------------------- E10 rotations
@pytest.mark.parametrize("scale", [1.0, 1e-6, 1e150, 1e300, 1.7e308])
def test_quaternion_to_matrix_any_magnitude(scale):
    np.testing.assert_allclose(quaternion_xyzw_to_matrix([scale, scale, 0.0, 0.0]), R_180_XY, atol=1e-15)


def test_quaternion_to_matrix_batch_of_mixed_magnitudes():
    s = math.sqrt(0.5)
    R = quaternion_xyzw_to_matrix([[1e300, 1e300, 0, 0], [0, 0, s, s], [0, 0, 1e-9, 1e-9]])
    ninety_z = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(R, [R_180_XY, ninety_z, ninety_z], atol=1e-15)


@pytest.mark.parametrize("q,match", [("abcd", "real numbers"), ([1j, 0, 0, 1], "complex"), ([None, 0, 0, 1], "quaternion"),
                                     ([np.inf, 0, 0, 1], "non-finite"), ([0, 0, 0, 0], "zero quaternion"),
                                     ([1e-13, 0, 0, 0], "zero quaternion"), ([[0, 0, 0, 1], [0, 0, 0, 0]], "zero"),
                                     ([0, 0, 1], "4 components")])
def test_quaternion_to_matrix_refuses(q, match):
    with pytest.raises(CameraError, match=match):
        quaternion_xyzw_to_matrix(q)


@pytest.mark.parametrize("R,match", [
    (np.diag([1.0, 1.0, -1.0]), "determinant -1"),       # a reflection (orthonormal)
    (np.zeros((3, 3)), "not a rotation matrix"),
    (5.0 * np.eye(3), "not a rotation matrix"),
    (np.eye(3) * 1.01, "not a rotation matrix"),
    (np.full((3, 3), np.nan), "non-finite"),
    (np.stack([np.eye(3), -np.eye(3)]), "determinant -1"),  # one bad matrix in a batch
    (np.eye(2), "must be"),
    (np.eye(3) + 1j, "complex"),
])
def test_matrix_to_quaternion_refuses_non_rotations(R, match):
    with pytest.raises(CameraError, match=match):
        matrix_to_quaternion_xyzw(R)


def test_matrix_to_quaternion_accepts_rounded_rotations():
    # 180 degrees about (1, 1, 0): q = (1, 1, 0, 0) / sqrt(2) (w = 0, so either sign)
    q = matrix_to_quaternion_xyzw(R_180_XY)
    assert min(np.abs(q - [math.sqrt(0.5), math.sqrt(0.5), 0, 0]).max(),
               np.abs(q + [math.sqrt(0.5), math.sqrt(0.5), 0, 0]).max()) < 1e-15
    # a rotation rounded to 4 decimals (text formats; the importers accept |R^T R - I| <= 1e-4) still converts
    c, s = math.cos(0.3), math.sin(0.3)
    Rz = np.round(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), 4)
    np.testing.assert_allclose(matrix_to_quaternion_xyzw(Rz), [0, 0, math.sin(0.15), math.cos(0.15)], atol=1e-4)


# ---------------------------------------------------------------------------------------------- E14 look_at
@pytest.mark.parametrize("far", [1e200, 1e300, 1.7e308])
def test_look_at_from_far_away(far):
    cam = Camera.look_at([far, 0.0, 0.0], [0.0, 0.0, 0.0], K, W, H)
    # looking along -x with up = +z: columns optical x (right) = +y, y (down) = -z, z (forward) = -x
    np.testing.assert_allclose(cam.R_map_cam, [[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]], atol=1e-15)
    assert cam.position[0] == far


def test_look_at_across_the_float_range_and_huge_up():
    cam = Camera.look_at([-1.7e308, 0.0, 0.0], [1.7e308, 0.0, 0.0], K, W, H, up=(0.0, 0.0, 1e300))
    np.testing.assert_allclose(cam.R_map_cam[:, 2], [1.0, 0.0, 0.0], atol=1e-15)
    tiny_up = Camera.look_at([0, 0, 0], [5, 0, 0], K, W, H, up=(0.0, 0.0, 1e-300))
    np.testing.assert_allclose(tiny_up.R_map_cam, Camera.look_at([0, 0, 0], [5, 0, 0], K, W, H).R_map_cam)


@pytest.mark.parametrize("kw,match", [
    (dict(position=[0, 0]), "position must have 3 components"),
    (dict(target=[0, 0, 0, 0]), "target must have 3 components"),
    (dict(up=[[0, 0, 1, 0]]), "up must have 3 components"),
    (dict(position=[0, np.nan, 0]), "position holds non-finite"),
    (dict(target=[np.inf, 0, 0]), "target holds non-finite"),
    (dict(position="abc"), "position must hold real numbers"),
    (dict(position=[1j, 0, 0]), r"position must hold real numbers, got dtype complex128 \(complex values\)"),
    (dict(up=(0.0, 0.0, 0.0)), "up must be a non-zero vector"),
    (dict(target=[0, 0, 5]), "position and target coincide"),
    (dict(target=[1, 0, 5], up=(2.0, 0.0, 0.0)), "parallel to 'up'"),
])
def test_look_at_refuses(kw, match):
    args = dict(position=[0.0, 0.0, 5.0], target=[1.0, 1.0, 0.0], up=(0.0, 0.0, 1.0))
    args.update(kw)
    with pytest.raises(CameraError, match=match):
        Camera.look_at(args["position"], args["target"], K, W, H, up=args["up"])


# ---------------------------------------------------------------------------------------------- E14 fov / scaled
@pytest.mark.parametrize("args,match", [
    ((-5, 48, 60.0), "positive"),
    ((64, 0, 60.0), "positive"),
    (("a", 48, 60.0), "width must be an integer"),
    ((64.5, 48, 60.0), "width must be an integer"),
    ((64, 48, "60"), "fov_x_deg must be a real number"),
    ((64, 48, True), "fov_x_deg must be a real number"),
    ((64, 48, 0.0), r"fov_x_deg must be in \(0, 180\)"),
    ((64, 48, 180.0), r"fov_x_deg must be in \(0, 180\)"),
    ((64, 48, -30.0), r"fov_x_deg must be in \(0, 180\)"),
    ((64, 48, float("nan")), r"fov_x_deg must be in \(0, 180\)"),
    ((64, 48, 1e-320), "focal length"),
    ((100000, 100000, 60.0), "exceeds MAX_CAMERA_PIXELS"),
])
def test_intrinsics_from_fov_refuses(args, match):
    with pytest.raises(CameraError, match=match):
        intrinsics_from_fov(*args)


def test_intrinsics_from_fov_numpy_scalars():
    Kf = intrinsics_from_fov(np.int64(640), np.uint16(480), np.float32(90.0))
    assert Kf[0, 0] == pytest.approx(320.0) and (Kf[0, 2], Kf[1, 2]) == (319.5, 239.5)


@pytest.mark.parametrize("factor", [None, "2", True, 2 + 0j, [2.0], np.array([0.5])])
def test_scaled_refuses_non_numbers(factor):
    cam = Camera(K, W, H, np.eye(4))
    with pytest.raises(CameraError, match="scale factor must be a real number"):
        cam.scaled(factor)


def test_scaled_accepts_numpy_and_int_factors():
    cam = Camera(K, W, H, np.eye(4))
    assert (cam.scaled(np.float32(0.5)).width, cam.scaled(2).width, cam.scaled(np.int64(3)).height) == (32, 128, 144)


@pytest.mark.parametrize("w,h,match", [(None, 48, "width must be an integer"), (64, "48", "height must be an integer"),
                                       (True, 48, "width must be an integer"), (0, 48, "positive")])
def test_resized_refuses_bad_sizes(w, h, match):
    with pytest.raises(CameraError, match=match):
        Camera(K, W, H, np.eye(4)).resized(w, h)


def test_from_pose_refuses_complex_and_text():
    with pytest.raises(CameraError, match=r"intrinsics K must hold real numbers.*\(complex values\)"):
        Camera.from_pose(K + 1j, W, H, [0, 0, 0], [0, 0, 0, 1])
    with pytest.raises(CameraError, match="position must hold real numbers, got dtype <U1"):
        Camera.from_pose(K, W, H, ["0", "0", "0"], [0, 0, 0, 1])
    with pytest.raises(CameraError, match=r"T_map_cam must hold real numbers.*\(complex values\)"):
        Camera(K, W, H, np.eye(4) + 0j)


def test_object_arrays_holding_text_are_not_read_as_numbers():
    with pytest.raises(CameraError, match=r"quaternion must hold real numbers, got dtype object \(it holds text"):
        quaternion_xyzw_to_matrix(np.array(["1", 0, 0, 1], dtype=object))
    np.testing.assert_allclose(quaternion_xyzw_to_matrix(np.array([0, 0, 0, 1], dtype=object)), np.eye(3))
