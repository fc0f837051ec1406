"""css_node's frame images as serialised bytes (ros/conversions.image_bytes) are the messages rclpy would send."""
from __future__ import annotations

import numpy as np
import pytest

rclpy_serialization = pytest.importorskip("rclpy.serialization")

from sensor_msgs.msg import Image  # noqa: E402

from css_ros.ros import conversions as rc  # noqa: E402


def test_the_running_rmw_reads_the_bytes_as_the_message():
    assert rc.serialised_images_supported()


@pytest.mark.parametrize("encoding,array", [
    ("mono8", np.arange(35, dtype=np.int32).reshape(5, 7)),
    ("rgb8", np.arange(45, dtype=np.uint8).reshape(3, 5, 3)),
    ("32FC1", np.linspace(0, 1, 6, dtype=np.float32).reshape(2, 3)),
])
def test_image_bytes_deserialise_to_image_msg(encoding, array):
    stamp_ns, frame_id = 1_700_000_000_000_000_001, "camera_optical"
    raw = rc.image_bytes(array, encoding, stamp_ns, frame_id)
    want = rc.image_msg(array, encoding, rc.header_msg(stamp_ns, frame_id))
    assert rclpy_serialization.deserialize_message(raw, Image) == want
    assert len(raw) == len(rclpy_serialization.serialize_message(want))


def test_image_msg_holds_the_pixels_once_copied():
    array = np.arange(12, dtype=np.float32).reshape(3, 4)
    msg = rc.image_msg(array, "32FC1", rc.header_msg(5, "cam"))
    assert bytes(msg.data) == array.tobytes() and msg.step == 16 and (msg.height, msg.width) == (3, 4)
    array[0, 0] = 99.0   # the message owns its bytes
    assert np.frombuffer(bytes(msg.data), np.float32)[0] == 0.0
