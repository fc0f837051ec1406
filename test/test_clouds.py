"""PointCloud2 packing (css_ros.io.clouds): layouts, round trips through CDR, the RViz rgb convention."""
from __future__ import annotations

import struct

import numpy as np
import pytest

from css_ros.errors import InputError
from css_ros.io.bag import typestore
from css_ros.io.clouds import pack_cloud, pack_rgb, unpack_cloud, unpack_rgb


def _msg(f):
    T = typestore().types
    fields = [T["sensor_msgs/msg/PointField"](name=n, offset=o, datatype=d, count=c) for (n, o, d, c) in f["fields"]]
    hdr = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=2), frame_id="map")
    msg = T["sensor_msgs/msg/PointCloud2"](header=hdr, height=f["height"], width=f["width"], fields=fields,
                                           is_bigendian=f["is_bigendian"], point_step=f["point_step"],
                                           row_step=f["row_step"], data=f["data"], is_dense=f["is_dense"])
    store = typestore()
    raw = store.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2")
    return store.deserialize_cdr(raw, "sensor_msgs/msg/PointCloud2")


def test_layout_offsets_and_datatypes_follow_the_column_order():
    f = pack_cloud({"x": np.zeros(3, np.float32), "label": np.zeros(3, np.uint16), "e": np.zeros(3, np.float64),
                    "flag": np.zeros(3, bool)})
    assert f["fields"] == [("x", 0, 7, 1), ("label", 4, 4, 1), ("e", 6, 8, 1), ("flag", 14, 7, 1)]
    assert f["point_step"] == 18 and f["row_step"] == 54 and f["data"].size == 54


def test_bytes_of_one_point_are_little_endian_in_field_order():
    f = pack_cloud({"x": np.array([1.5], np.float32), "label": np.array([258], np.uint16)})
    assert bytes(f["data"]) == struct.pack("<fH", 1.5, 258)


def test_round_trip_through_cdr():
    rng = np.random.default_rng(0)
    cols = {"x": rng.normal(size=50).astype(np.float32), "label": rng.integers(0, 300, 50).astype(np.uint16),
            "v": rng.random(50)}
    out = unpack_cloud(_msg(pack_cloud(cols)))
    assert out.dtype.names == ("x", "label", "v")
    for k, v in cols.items():
        np.testing.assert_array_equal(out[k], v)
    sub = unpack_cloud(_msg(pack_cloud(cols)), ("v",))
    assert sub.dtype.names == ("v",)


def test_rgb_is_packed_as_rviz_reads_it():
    rgb = np.array([[255, 0, 0], [1, 2, 3], [0, 0, 255]], np.uint8)
    packed = pack_rgb(rgb)
    assert packed.dtype == np.float32
    assert packed.view(np.uint32).tolist() == [0xFF0000, 0x010203, 0x0000FF]
    np.testing.assert_array_equal(unpack_rgb(packed), rgb)


def test_errors_name_the_problem():
    with pytest.raises(InputError, match="differ in length"):
        pack_cloud({"a": np.zeros(2), "b": np.zeros(3)})
    msg = _msg(pack_cloud({"a": np.zeros(4, np.float32)}))
    with pytest.raises(InputError, match=r"lacks fields \['b'\]"):
        unpack_cloud(msg, ("b",))
    msg.data = msg.data[:-1]
    with pytest.raises(InputError, match="expected 16"):
        unpack_cloud(msg)
