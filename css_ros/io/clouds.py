"""sensor_msgs/PointCloud2 packing, ROS-free: the one packer of every cloud the package publishes or writes.

A cloud is a set of named columns of equal length (one point each); :func:`pack_cloud` lays them out
little-endian, point after point, and returns the PointCloud2 fields as a plain dict (each caller
builds the message class of its own library: rclpy or rosbags). :func:`unpack_cloud` reads any
PointCloud2 back into a numpy structured array. Colours use the ``rgb`` convention RViz and
Foxglove read: one FLOAT32 field whose 4 bytes hold the integer 0x00RRGGBB (:func:`pack_rgb`).

Scored views (``~/view_uncertainty``, ``~/candidate_scores``) are clouds of one float32 point per view:
:func:`pack_scored_views` writes them, :func:`unpack_scored_views` reads either layout by field name.
"""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from ..errors import InputError

#: sensor_msgs/PointField datatype constants.
POINTFIELD_DATATYPES: dict[int, np.dtype] = {
    1: np.dtype("<i1"), 2: np.dtype("<u1"), 3: np.dtype("<i2"), 4: np.dtype("<u2"),
    5: np.dtype("<i4"), 6: np.dtype("<u4"), 7: np.dtype("<f4"), 8: np.dtype("<f8"),
}
_DATATYPE_OF: dict[np.dtype, int] = {dt: code for code, dt in POINTFIELD_DATATYPES.items()}

#: ``~/view_uncertainty`` (one point per observed frame), float32 in this order: the optical frame's position
#: [m, map frame], its (x, y, z, w) orientation, U_var, U_exp (the same tuple as css_ros.io.messages.VIEW_FIELDS).
VIEW_FIELDS = ("x", "y", "z", "qx", "qy", "qz", "qw", "u_var", "u_exp")
#: ``~/candidate_scores`` (one point per requested view, in request order): :data:`VIEW_FIELDS`, then
#: ``info_gain``, the expected reduction of the map's uncertainty if the view were observed (>= 0, bigger =
#: better next view). Appended last, so readers that look fields up by name read both layouts.
CANDIDATE_FIELDS = (*VIEW_FIELDS, "info_gain")
#: ``~/view_uncertainty`` appends ``pose_flags`` (float32 holding a small integer, bits of
#: css_ros.io.frame_gate: 1 the pose was extrapolated, 2 samples of the pose stream were missing around the stamp;
#: 0 = the interpolation of the samples around the stamp). Readers that look fields up by name are unaffected.
POSE_FLAGS_FIELD = "pose_flags"
#: What :func:`unpack_scored_views` returns (every field float32).
SCORED_VIEW_DTYPE = np.dtype([(name, "<f4") for name in CANDIDATE_FIELDS])


def pack_rgb(rgb: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 RGB -> (N,) float32 whose bits are 0x00RRGGBB (the ``rgb`` field of RViz / Foxglove)."""
    rgb = np.asarray(rgb, dtype=np.uint32).reshape(-1, 3)
    packed = (rgb[:, 0] << np.uint32(16)) | (rgb[:, 1] << np.uint32(8)) | rgb[:, 2]
    return packed.astype("<u4").view("<f4")


def unpack_rgb(values: np.ndarray) -> np.ndarray:
    """Inverse of :func:`pack_rgb`: (N,) float32 -> (N, 3) uint8."""
    bits = np.ascontiguousarray(values, dtype="<f4").view("<u4")
    return np.stack([(bits >> 16) & 0xFF, (bits >> 8) & 0xFF, bits & 0xFF], axis=1).astype(np.uint8)


def message_bytes(data: Any) -> np.ndarray:
    """The ``data`` field of a message (bytes, array.array, numpy or a list of ints) as a 1-D uint8 view."""
    if isinstance(data, np.ndarray):
        return data.view(np.uint8).reshape(-1)
    try:  # bytes, bytearray, array.array (rclpy): no copy
        return np.frombuffer(memoryview(data).cast("B"), dtype=np.uint8)
    except TypeError:  # e.g. a list of ints
        return np.asarray(data, dtype=np.uint8).reshape(-1)


def _field_dtype(a: np.ndarray) -> np.dtype:
    """The little-endian PointField type of a column (float32 for types PointField lacks, e.g. bool, int64)."""
    dt = a.dtype.newbyteorder("<")
    return dt if dt in _DATATYPE_OF else np.dtype("<f4")


def pack_cloud(columns: Mapping[str, np.ndarray]) -> dict[str, Any]:
    """Fields of an unorganised PointCloud2 (height 1) holding ``columns`` in their order.

    Args:
        columns: field name -> (N,) array; its dtype must be one of the PointField types
            (int8/16/32, uint8/16/32, float32, float64); other dtypes are converted to float32.
    Returns:
        dict(height=1, width=N, fields=[(name, offset, datatype, count=1)], is_bigendian=False,
        point_step, row_step, data (1-D uint8), is_dense=True).
    """
    names = list(columns)
    arrays = [np.asarray(columns[n]).reshape(-1) for n in names]
    n = len(arrays[0]) if arrays else 0
    if any(len(a) != n for a in arrays):
        raise InputError(f"cloud columns differ in length: {[len(a) for a in arrays]}")
    dtypes = [_field_dtype(a) for a in arrays]
    layout = np.dtype([(name, dt) for name, dt in zip(names, dtypes)])  # packed: offsets are running sums
    points = np.empty(n, dtype=layout)
    for name, a in zip(names, arrays):
        points[name] = a
    return {
        "height": 1,
        "width": n,
        "fields": [(name, layout.fields[name][1], _DATATYPE_OF[dt], 1) for name, dt in zip(names, dtypes)],
        "is_bigendian": False,
        "point_step": layout.itemsize,
        "row_step": layout.itemsize * n,
        "data": points.view(np.uint8).reshape(-1),
        "is_dense": True,
    }


def unpack_cloud(msg: Any, names: tuple[str, ...] | None = None) -> np.ndarray:
    """Any little-endian PointCloud2 -> structured (height * width,) array of its fields (or of ``names``).

    Raises:
        InputError: a requested field is missing, a field type is unknown, or the data is truncated.
    """
    fields = {f.name: (int(f.offset), int(f.datatype), int(getattr(f, "count", 1) or 1)) for f in msg.fields}
    names = tuple(fields) if names is None else names
    missing = [n for n in names if n not in fields]
    if missing:
        raise InputError(f"point cloud lacks fields {missing}")
    if getattr(msg, "is_bigendian", False):
        raise InputError("big-endian point clouds are not supported")
    m = int(msg.width) * int(msg.height)
    step = int(msg.point_step)
    raw = message_bytes(msg.data)
    if raw.size < m * step:
        raise InputError(f"point cloud data holds {raw.size} bytes, expected {m * step}")
    out_dtype = []
    for name in names:
        offset, datatype, count = fields[name]
        if datatype not in POINTFIELD_DATATYPES or count != 1:
            raise InputError(f"field {name}: unsupported datatype {datatype} x {count}")
        if offset + POINTFIELD_DATATYPES[datatype].itemsize > step:
            raise InputError(f"field {name} lies outside the point step {step}")
        out_dtype.append((name, POINTFIELD_DATATYPES[datatype]))
    rows = raw[: m * step].reshape(m, step)
    out = np.empty(m, dtype=out_dtype)
    for name, dt in out_dtype:
        offset = fields[name][0]
        out[name] = np.ascontiguousarray(rows[:, offset:offset + dt.itemsize]).view(dt).reshape(m)
    return out


def pack_scored_views(positions: np.ndarray, quats_xyzw: np.ndarray, u_var: np.ndarray, u_exp: np.ndarray,
                      info_gain: np.ndarray | None = None, pose_flags: np.ndarray | None = None) -> dict[str, Any]:
    """PointCloud2 fields (:func:`pack_cloud`) with one float32 point per scored view.

    Args:
        positions: (M, 3) view positions [m, map frame]; quats_xyzw: (M, 4) orientations of the optical frame;
        u_var, u_exp: (M,) image-level uncertainties (SPEC §6); info_gain: (M,) expected information gain, or
        None for the ``~/view_uncertainty`` layout; pose_flags: (M,) :data:`POSE_FLAGS_FIELD` values, or None.
    Returns:
        fields :data:`VIEW_FIELDS` (``info_gain`` None) or :data:`CANDIDATE_FIELDS`, in that order, then
        ``pose_flags`` when given. NaN stays NaN (a view that could not be scored).
    """
    m = len(positions)
    pos = np.asarray(positions, dtype=np.float64).reshape(m, 3)
    quats = np.asarray(quats_xyzw, dtype=np.float64).reshape(m, 4)
    columns = {name: pos[:, i] for i, name in enumerate(("x", "y", "z"))}
    columns.update({name: quats[:, i] for i, name in enumerate(("qx", "qy", "qz", "qw"))})
    columns["u_var"] = np.asarray(u_var, dtype=np.float64).reshape(m)
    columns["u_exp"] = np.asarray(u_exp, dtype=np.float64).reshape(m)
    if info_gain is not None:
        columns["info_gain"] = np.asarray(info_gain, dtype=np.float64).reshape(m)
    if pose_flags is not None:
        columns[POSE_FLAGS_FIELD] = np.asarray(pose_flags, dtype=np.float64).reshape(m)
    return pack_cloud({k: v.astype(np.float32) for k, v in columns.items()})


def unpack_scored_views(msg: Any) -> np.ndarray:
    """A ``~/view_uncertainty`` or ``~/candidate_scores`` PointCloud2 -> structured (M,) array of
    :data:`SCORED_VIEW_DTYPE` (float32), fields looked up by name wherever they lie in the point.

    ``info_gain`` is NaN when the cloud lacks it (``~/view_uncertainty``, or the answer of a css_node older
    than the field). Raises InputError when a field of :data:`VIEW_FIELDS` is missing.
    """
    present = {f.name for f in msg.fields}
    names = tuple(n for n in CANDIDATE_FIELDS if n in VIEW_FIELDS or n in present)
    rows = unpack_cloud(msg, names)
    out = np.full(len(rows), np.nan, dtype=SCORED_VIEW_DTYPE)
    for name in names:
        out[name] = rows[name]
    return out


def has_field(msg: Any, name: str) -> bool:
    """The PointCloud2 ``msg`` has a field called ``name``."""
    return any(f.name == name for f in msg.fields)
