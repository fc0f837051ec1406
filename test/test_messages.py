"""Message <-> array conversion on rosbags message classes (the same duck-typed code serves rclpy)."""
from __future__ import annotations

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from css_ros.errors import InputError
from css_ros.io.messages import (array_to_image_fields, camera_info_to_intrinsics, image_cdr, image_to_array,
                              ns_to_sec_nanosec, pack_view_points, stamp_to_ns, unpack_view_points)

TS = get_typestore(Stores.ROS2_JAZZY)
Image = TS.types["sensor_msgs/msg/Image"]
Header = TS.types["std_msgs/msg/Header"]
Time = TS.types["builtin_interfaces/msg/Time"]
PointCloud2 = TS.types["sensor_msgs/msg/PointCloud2"]
PointField = TS.types["sensor_msgs/msg/PointField"]


def make_image(array, encoding):
    return Image(header=Header(stamp=Time(sec=1, nanosec=2), frame_id="cam"), **array_to_image_fields(array, encoding))


def roundtrip_cdr(msg, typename):
    return TS.deserialize_cdr(TS.serialize_cdr(msg, typename), typename)


@pytest.mark.parametrize("encoding,dtype,shape", [
    ("mono8", np.uint8, (5, 7)), ("8UC1", np.uint8, (5, 7)), ("mono16", np.uint16, (5, 7)),
    ("16UC1", np.uint16, (4, 3)), ("32FC1", np.float32, (6, 2)), ("rgb8", np.uint8, (5, 7, 3)),
])
def test_image_roundtrip_through_cdr(encoding, dtype, shape):
    rng = np.random.default_rng(0)
    array = (rng.random(shape) * 200).astype(dtype)
    back = image_to_array(roundtrip_cdr(make_image(array, encoding), "sensor_msgs/msg/Image"))
    assert back.dtype == dtype
    np.testing.assert_array_equal(back, array)


@pytest.mark.parametrize("frame_id", ["", "a", "ab", "abc", "cam_optical", "kamera_ä"])
@pytest.mark.parametrize("encoding,dtype,shape", [
    ("mono8", np.uint8, (3, 5)), ("mono16", np.uint16, (3, 5)), ("32FC1", np.float32, (2, 3)),
    ("rgb8", np.uint8, (1, 1, 3)), ("mono8", np.int32, (2, 7)),   # int32 labels go out as mono8, as image_msg does
])
def test_image_cdr_is_the_message_rosbags_serialises(frame_id, encoding, dtype, shape):
    """Byte for byte the CDR of rosbags' own serialiser (every alignment of the strings; padding zero in both)."""
    array = (np.random.default_rng(1).random(shape) * 250).astype(dtype)
    stamp_ns = 1_700_000_123 * 10**9 + 456_789
    want = Image(header=Header(stamp=Time(sec=1_700_000_123, nanosec=456_789), frame_id=frame_id),
                 **array_to_image_fields(array, encoding))
    got = image_cdr(array, encoding, stamp_ns, frame_id)
    assert got == bytes(TS.serialize_cdr(want, "sensor_msgs/msg/Image"))
    back = TS.deserialize_cdr(got, "sensor_msgs/msg/Image")
    assert back.header.frame_id == frame_id and back.encoding == encoding
    np.testing.assert_array_equal(image_to_array(back), array.astype(image_to_array(want).dtype))


def test_image_cdr_refuses_what_image_fields_refuse():
    with pytest.raises(InputError, match="does not fit"):
        image_cdr(np.zeros((2, 3, 3), np.uint8), "mono8", 0, "cam")
    with pytest.raises(InputError, match="unsupported encoding"):
        image_cdr(np.zeros((2, 3), np.uint8), "yuv422", 0, "cam")


def test_bgr_and_alpha_encodings_become_rgb():
    rgb = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    np.testing.assert_array_equal(image_to_array(make_image(rgb[:, :, ::-1], "bgr8")), rgb)
    rgba = np.concatenate([rgb, np.full((2, 3, 1), 9, np.uint8)], axis=2)
    np.testing.assert_array_equal(image_to_array(make_image(rgba, "rgba8")), rgb)
    bgra = np.concatenate([rgb[:, :, ::-1], np.full((2, 3, 1), 9, np.uint8)], axis=2)
    np.testing.assert_array_equal(image_to_array(make_image(bgra, "bgra8")), rgb)


def test_padded_step_and_big_endian():
    a = np.array([[1, 2, 3], [400, 500, 600]], dtype=np.uint16)
    be = a.astype(">u2")
    rows = np.zeros((2, 8), np.uint8)
    rows[:, :6] = be.view(np.uint8).reshape(2, 6)
    msg = Image(header=Header(stamp=Time(sec=0, nanosec=0), frame_id=""), height=2, width=3,
                encoding="mono16", is_bigendian=True, step=8, data=rows.reshape(-1))
    np.testing.assert_array_equal(image_to_array(msg), a)


def test_bad_images_raise():
    good = make_image(np.zeros((4, 4), np.uint8), "mono8")
    for change, match in [(dict(encoding="yuv422"), "unsupported"), (dict(height=0), "empty"),
                          (dict(height=10), "bytes"), (dict(step=2), "step")]:
        fields = {k: getattr(good, k) for k in ("header", "height", "width", "encoding", "is_bigendian", "step", "data")}
        fields.update(change)
        with pytest.raises(InputError, match=match):
            image_to_array(Image(**fields))
    with pytest.raises(InputError, match="not accepted"):
        image_to_array(good, allowed=("32FC1",))


def test_stamps_and_camera_info():
    assert stamp_to_ns(Time(sec=3, nanosec=5)) == 3_000_000_005
    assert ns_to_sec_nanosec(3_000_000_005) == (3, 5)
    CameraInfo = TS.types["sensor_msgs/msg/CameraInfo"]
    RoI = TS.types["sensor_msgs/msg/RegionOfInterest"]
    k = np.array([100.0, 0, 31.5, 0, 101.0, 23.5, 0, 0, 1])
    info = CameraInfo(header=Header(stamp=Time(sec=0, nanosec=0), frame_id=""), height=48, width=64,
                      distortion_model="plumb_bob", d=np.zeros(5), k=k, r=np.eye(3).ravel(), p=np.zeros(12),
                      binning_x=0, binning_y=0, roi=RoI(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
    K, w, h = camera_info_to_intrinsics(roundtrip_cdr(info, "sensor_msgs/msg/CameraInfo"))
    np.testing.assert_array_equal(K, k.reshape(3, 3))
    assert (w, h) == (64, 48)


def test_view_points_roundtrip():
    rng = np.random.default_rng(1)
    pos, quat = rng.normal(size=(4, 3)), rng.normal(size=(4, 4))
    uv, ue = rng.random(4), rng.random(4)
    f = pack_view_points(pos, quat, uv, ue)
    msg = PointCloud2(header=Header(stamp=Time(sec=0, nanosec=0), frame_id="map"), height=f["height"],
                      width=f["width"], fields=[PointField(name=n, offset=o, datatype=d, count=c) for n, o, d, c in f["fields"]],
                      is_bigendian=False, point_step=f["point_step"], row_step=f["row_step"], data=f["data"], is_dense=True)
    pts = unpack_view_points(roundtrip_cdr(msg, "sensor_msgs/msg/PointCloud2"))
    np.testing.assert_allclose(np.stack([pts["x"], pts["y"], pts["z"]], 1), pos, rtol=1e-6)
    np.testing.assert_allclose(np.stack([pts[k] for k in ("qx", "qy", "qz", "qw")], 1), quat, rtol=1e-6)
    np.testing.assert_allclose(pts["u_var"], uv, rtol=1e-6)
    np.testing.assert_allclose(pts["u_exp"], ue, rtol=1e-6)
