"""Point queries over topics, ROS-free: the request cloud (x y z) in, the answer cloud's columns out.

A request is a PointCloud2 with float fields ``x y z`` (map frame, metres); its header stamp is the
request id and is echoed by the answer. The answer holds, per requested point and in request order,
``x y z label expectation variance`` and then one float32 field per class holding E of that class
(SPEC §9), named after the class (:func:`class_field_names`).
"""
from __future__ import annotations

import re
import struct
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from ..errors import InputError
from .clouds import unpack_cloud

#: Fields of an answer before the per-class ones.
ANSWER_FIELDS = ("x", "y", "z", "label", "expectation", "variance")


def class_field_names(class_names: Sequence[str]) -> list[str]:
    """PointField names of the per-class columns: the class name in lower case with every run of
    characters other than letters, digits and '_' replaced by '_'; a name that is empty, starts with a
    digit, repeats an earlier one or clashes with :data:`ANSWER_FIELDS` gets the prefix ``class<id>_``."""
    out: list[str] = []
    for i, name in enumerate(class_names):
        field = re.sub(r"[^0-9a-zA-Z_]+", "_", str(name).strip()).strip("_").lower()
        if not field or field[0].isdigit() or field in out or field in ANSWER_FIELDS:
            field = f"class{i}_{field}".rstrip("_")
        out.append(field)
    return out


#: PointField datatypes accepted for x, y, z of a request: FLOAT32, FLOAT64.
COORDINATE_DATATYPES = (7, 8)


def declared_points(msg: Any) -> int:
    """Number of points a request cloud declares (width x height), read from its header only.

    Raises:
        InputError: width/height/point_step not non-negative integers.
    """
    try:
        width, height, step = int(msg.width), int(msg.height), int(msg.point_step)
    except (AttributeError, TypeError, ValueError) as exc:
        raise InputError(f"unreadable cloud header: {exc}") from None
    if min(width, height, step) < 0:
        raise InputError(f"negative cloud size {width}x{height}, point_step {step}")
    return width * height


@dataclass(frozen=True)
class CloudHead:
    """What a serialized PointCloud2 declares before its fields and data: the header and the point count."""

    sec: int
    nanosec: int
    frame_id: str
    height: int
    width: int

    @property
    def points(self) -> int:
        return self.height * self.width


def cloud_head(raw: bytes) -> CloudHead:
    """The header, height and width of a CDR-serialized sensor_msgs/PointCloud2 (what rclpy hands a raw
    subscription), read without deserializing the message: a request declaring more than max_query_points is
    answered without its (possibly huge) data ever becoming a Python object.

    Layout: 4-byte encapsulation (byte 1: 1 little endian, 0 big endian), then, aligned to 4 from the end of the
    encapsulation: int32 sec, uint32 nanosec, uint32 length + frame_id bytes (NUL included), uint32 height, width.

    Raises:
        InputError: truncated, or not CDR.
    """
    if len(raw) < 4 or raw[0] != 0 or raw[1] not in (0, 1):
        raise InputError("not a CDR-serialized message")
    endian = "<" if raw[1] == 1 else ">"
    body = memoryview(raw)[4:]
    try:
        sec, nanosec, n = struct.unpack_from(endian + "iII", body, 0)
        if n > len(body) - 12:
            raise InputError("truncated cloud header")
        frame_id = bytes(body[12:12 + n]).rstrip(b"\0").decode("utf-8", "replace")
        off = (12 + n + 3) & ~3
        height, width = struct.unpack_from(endian + "II", body, off)
    except struct.error:
        raise InputError("truncated cloud header") from None
    return CloudHead(sec, nanosec, frame_id, height, width)


def request_points(msg: Any) -> np.ndarray:
    """(M, 3) float64 query points [m, map frame] of a request cloud (rows may be non-finite: they are
    answered as unknown, as points far from every Gaussian).

    Raises:
        InputError: fields x, y, z missing, not FLOAT32/FLOAT64 or at offsets that are not a multiple of
            their size, a field name occurring twice, or truncated data.
    """
    fields = list(msg.fields)
    names = [f.name for f in fields]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(f"point cloud names fields {dup} more than once")
    for f in fields:
        if f.name in ("x", "y", "z"):
            if int(f.datatype) not in COORDINATE_DATATYPES:
                raise InputError(f"field {f.name} has datatype {int(f.datatype)}; x y z must be FLOAT32 (7) or "
                                 "FLOAT64 (8)")
            size = 4 if int(f.datatype) == 7 else 8
            if int(f.offset) % size:
                raise InputError(f"field {f.name} at offset {int(f.offset)} is not aligned to its {size} bytes")
    pts = unpack_cloud(msg, ("x", "y", "z"))
    return np.stack([pts["x"], pts["y"], pts["z"]], axis=1).astype(np.float64).reshape(-1, 3)


def answer_columns(xyz: np.ndarray, labels: np.ndarray, expectation: np.ndarray, variance: np.ndarray,
                   class_names: Sequence[str]) -> dict[str, np.ndarray]:
    """Columns of the answer cloud.

    Args:
        xyz: (M, 3) query points [m]; labels: (M,) label of each point (ignore label = unknown);
        expectation, variance: (M, C) E and Var of every class at each point (SPEC §9). The answer's
        ``expectation``/``variance`` are those of the argmax class, also where the label is unknown
        (as the render's E and Var images).
    """
    m = len(xyz)
    lab = np.asarray(labels).reshape(m)
    top = np.argmax(expectation, axis=1)  # the label before the unknown test, as the render's E/Var images
    rows = np.arange(m)
    e_top, v_top = expectation[rows, top], variance[rows, top]
    cols: dict[str, np.ndarray] = {
        "x": xyz[:, 0].astype(np.float32), "y": xyz[:, 1].astype(np.float32), "z": xyz[:, 2].astype(np.float32),
        "label": lab.astype(np.uint16),
        "expectation": e_top.astype(np.float32),
        "variance": v_top.astype(np.float32),
    }
    for c, name in enumerate(class_field_names(class_names)):
        cols[name] = expectation[:, c].astype(np.float32)
    return cols
