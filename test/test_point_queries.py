"""Point-query request parsing and answer columns (css_ros.io.point_queries)."""
from __future__ import annotations

import numpy as np
import pytest

from css_ros.errors import InputError
from css_ros.io.clouds import pack_cloud
from css_ros.io.point_queries import ANSWER_FIELDS, answer_columns, class_field_names, request_points
from test_clouds import _msg


def test_class_field_names_are_valid_unique_and_never_clash():
    names = class_field_names(["Wall", "traffic light", "wall", "x", "", "3d-thing", "Road/Street"])
    assert names == ["wall", "traffic_light", "class2_wall", "class3_x", "class4", "class5_3d_thing", "road_street"]
    assert len(set(names) | set(ANSWER_FIELDS)) == len(names) + len(ANSWER_FIELDS)


def test_request_points_reads_float32_and_float64():
    xyz = np.array([[1.0, 2, 3], [4, 5, np.nan]])
    for dt in (np.float32, np.float64):
        msg = _msg(pack_cloud({"x": xyz[:, 0].astype(dt), "y": xyz[:, 1].astype(dt), "z": xyz[:, 2].astype(dt),
                               "extra": np.zeros(2, np.uint8)}))
        np.testing.assert_array_equal(request_points(msg), xyz)
    with pytest.raises(InputError, match=r"lacks fields \['z'\]"):
        request_points(_msg(pack_cloud({"x": np.zeros(1), "y": np.zeros(1)})))


def test_answer_columns_in_request_order_with_the_argmax_moments():
    xyz = np.array([[0.0, 0, 0], [1, 1, 1], [2, 2, 2]])
    E = np.array([[0.2, 0.8], [0.6, 0.4], [0.5, 0.5]])
    V = np.array([[0.01, 0.02], [0.03, 0.04], [0.05, 0.06]])
    cols = answer_columns(xyz, np.array([1, 0, 255]), E, V, ["floor", "chair"])
    assert list(cols) == [*ANSWER_FIELDS, "floor", "chair"]
    assert cols["label"].tolist() == [1, 0, 255]
    np.testing.assert_allclose(cols["expectation"], [0.8, 0.6, 0.5])
    np.testing.assert_allclose(cols["variance"], [0.02, 0.03, 0.05])
    np.testing.assert_allclose(cols["chair"], E[:, 1])


def test_request_points_refuses_integer_duplicated_or_misaligned_coordinates():
    from css_ros.io.point_queries import declared_points

    xyz = np.arange(6, dtype=np.float32).reshape(2, 3)
    good = pack_cloud({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]})
    assert declared_points(_msg(good)) == 2
    for dt, code in ((np.int32, 5), (np.uint8, 2)):
        f = pack_cloud({"x": xyz[:, 0].astype(dt), "y": xyz[:, 1], "z": xyz[:, 2]})
        with pytest.raises(InputError, match=rf"field x has datatype {code}; x y z must be FLOAT32"):
            request_points(_msg(f))
    dup = dict(good, fields=good["fields"] + [("z", 0, 7, 1)])
    with pytest.raises(InputError, match=r"names fields \['z'\] more than once"):
        request_points(_msg(dup))
    # x y z float32 at offsets 1, 5, 9 of a 13-byte point: misaligned.
    raw = np.zeros((2, 13), np.uint8)
    raw[:, 1:13] = xyz.view(np.uint8).reshape(2, 12)
    shifted = dict(good, fields=[("x", 1, 7, 1), ("y", 5, 7, 1), ("z", 9, 7, 1)], point_step=13, row_step=26,
                   data=raw.reshape(-1))
    with pytest.raises(InputError, match="field x at offset 1 is not aligned to its 4 bytes"):
        request_points(_msg(shifted))
