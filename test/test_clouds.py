"""PointCloud2 packing (css_ros.io.clouds): layouts, round trips through CDR, the RViz rgb convention."""
from __future__ import annotations

import struct

import numpy as np
import pytest

from css_ros.errors import InputError
from css_ros.io.bag import typestore
from css_ros.io.clouds import (CANDIDATE_FIELDS, VIEW_FIELDS, pack_cloud, pack_rgb, pack_scored_views, unpack_cloud,
                                unpack_rgb, unpack_scored_views)


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


def _views(m: int = 3):
    rng = np.random.default_rng(1)
    pos, quats = rng.normal(size=(m, 3)), rng.normal(size=(m, 4))
    return pos, quats / np.linalg.norm(quats, axis=1, keepdims=True), rng.random(m), rng.random(m)


def test_scored_view_layouts_append_info_gain_last():
    """~/view_uncertainty keeps its 9 float32 fields; ~/candidate_scores adds info_gain after them."""
    from css_ros.io.messages import VIEW_FIELDS as MESSAGE_VIEW_FIELDS

    assert VIEW_FIELDS == MESSAGE_VIEW_FIELDS == ("x", "y", "z", "qx", "qy", "qz", "qw", "u_var", "u_exp")
    assert CANDIDATE_FIELDS == (*VIEW_FIELDS, "info_gain")
    pos, quats, u_var, u_exp = _views()
    frame = pack_scored_views(pos, quats, u_var, u_exp)
    assert frame["fields"] == [(n, 4 * i, 7, 1) for i, n in enumerate(VIEW_FIELDS)] and frame["point_step"] == 36
    cand = pack_scored_views(pos, quats, u_var, u_exp, np.array([0.5, np.nan, 2.0]))
    assert cand["fields"] == [(n, 4 * i, 7, 1) for i, n in enumerate(CANDIDATE_FIELDS)] and cand["point_step"] == 40


def test_scored_views_read_by_name_in_both_layouts_and_by_old_readers():
    from css_ros.io.messages import pack_view_points, unpack_view_points

    pos, quats, u_var, u_exp = _views()
    gain = np.array([0.5, np.nan, 2.0])
    cand = unpack_scored_views(_msg(pack_scored_views(pos, quats, u_var, u_exp, gain)))
    np.testing.assert_array_equal(cand["info_gain"], gain.astype(np.float32))
    np.testing.assert_array_equal(cand["u_exp"], u_exp.astype(np.float32))
    np.testing.assert_array_equal(np.stack([cand[k] for k in ("qx", "qy", "qz", "qw")], 1), quats.astype(np.float32))
    # a reader that predates info_gain (looks its 9 fields up by name) reads the candidate layout unchanged
    old = unpack_view_points(_msg(pack_scored_views(pos, quats, u_var, u_exp, gain)))
    for name in VIEW_FIELDS:
        np.testing.assert_array_equal(old[name], cand[name])
    # the frame layout (and an older node's answer): the same rows, info_gain NaN
    for f in (pack_scored_views(pos, quats, u_var, u_exp), pack_view_points(pos, quats, u_var, u_exp)):
        rows = unpack_scored_views(_msg(f))
        assert rows.dtype.names == CANDIDATE_FIELDS and np.all(np.isnan(rows["info_gain"]))
        for name in VIEW_FIELDS:
            np.testing.assert_array_equal(rows[name], cand[name])
    # fields are found wherever they lie in the point (another writer's order, extra fields)
    other = pack_cloud({"info_gain": gain.astype(np.float32), "extra": np.arange(3, dtype=np.uint8),
                        **{n: cand[n] for n in reversed(VIEW_FIELDS)}})
    got = unpack_scored_views(_msg(other))
    for name in CANDIDATE_FIELDS:
        np.testing.assert_array_equal(got[name], cand[name])
    with pytest.raises(InputError, match="u_exp"):
        unpack_scored_views(_msg(pack_cloud({n: cand[n] for n in VIEW_FIELDS if n != "u_exp"})))
