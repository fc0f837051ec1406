"""Array <-> ROS message conversion shared by the node (rclpy) and the bag tools (rosbags).

Every function is duck-typed on the message's field names, so the same code reads rclpy messages and
rosbags-deserialised messages. Builders return plain dicts of fields; each caller constructs the
message class of its own library from them.
"""
from __future__ import annotations

import struct
from typing import Any

import numpy as np

from ..errors import InputError
from .clouds import VIEW_FIELDS, message_bytes, pack_scored_views, unpack_cloud

#: encoding -> (numpy dtype, channels)
IMAGE_ENCODINGS: dict[str, tuple[np.dtype, int]] = {
    "rgb8": (np.dtype(np.uint8), 3),
    "bgr8": (np.dtype(np.uint8), 3),
    "rgba8": (np.dtype(np.uint8), 4),
    "bgra8": (np.dtype(np.uint8), 4),
    "mono8": (np.dtype(np.uint8), 1),
    "8UC1": (np.dtype(np.uint8), 1),
    "mono16": (np.dtype(np.uint16), 1),
    "16UC1": (np.dtype(np.uint16), 1),
    "32FC1": (np.dtype(np.float32), 1),
}
COLOR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8", "mono8")
LABEL_ENCODINGS = ("mono8", "8UC1", "mono16", "16UC1")
CONFIDENCE_ENCODINGS = ("32FC1",)
#: depth images: 16UC1 in millimetres, 32FC1 in metres (REP 118)
DEPTH_ENCODINGS = ("16UC1", "32FC1")

#: PointCloud2 layout of ~/view_uncertainty and ~/candidate_scores (all float32).
VIEW_DTYPE = np.dtype([(name, "<f4") for name in VIEW_FIELDS])


def image_to_array(msg: Any, allowed: tuple[str, ...] | None = None) -> np.ndarray:
    """Decode a sensor_msgs/Image into an array.

    Returns:
        rgb8/bgr8/rgba8/bgra8: (H, W, 3) uint8 RGB (alpha dropped, BGR swapped);
        mono8/8UC1: (H, W) uint8; mono16/16UC1: (H, W) uint16; 32FC1: (H, W) float32.
    Raises:
        InputError: unknown or disallowed encoding, empty image, or a data/step size that does not
            match height x width.
    """
    encoding = str(msg.encoding)
    if encoding not in IMAGE_ENCODINGS:
        raise InputError(f"unsupported encoding '{encoding}'")
    if allowed is not None and encoding not in allowed:
        raise InputError(f"encoding '{encoding}' not accepted here (expected one of {', '.join(allowed)})")
    height, width = int(msg.height), int(msg.width)
    if height <= 0 or width <= 0:
        raise InputError(f"empty image ({width}x{height})")
    dtype, channels = IMAGE_ENCODINGS[encoding]
    row_bytes = width * channels * dtype.itemsize
    step = int(msg.step)
    if step < row_bytes:
        raise InputError(f"step {step} smaller than width*channels*itemsize = {row_bytes}")
    raw = message_bytes(msg.data)
    if raw.size < step * height:
        raise InputError(f"data holds {raw.size} bytes, expected step*height = {step * height}")
    rows = raw[: step * height].reshape(height, step)[:, :row_bytes]
    big = bool(getattr(msg, "is_bigendian", False))
    dt = dtype.newbyteorder(">" if big else "<") if dtype.itemsize > 1 else dtype
    array = np.ascontiguousarray(rows).view(dt).reshape(height, width, channels).astype(dtype, copy=False)
    if channels == 1:
        return array[:, :, 0]
    if encoding.startswith("bgr"):
        array = array[:, :, 2::-1]
    return np.ascontiguousarray(array[:, :, :3])


def array_to_image_fields(array: np.ndarray, encoding: str) -> dict[str, Any]:
    """Fields of a sensor_msgs/Image holding ``array`` (little endian, tightly packed).

    Args:
        array: (H, W) for single-channel encodings, (H, W, 3|4) for colour ones; converted to the
            encoding's dtype (uint8 / uint16 / float32).
        encoding: one of :data:`IMAGE_ENCODINGS`.
    Returns:
        dict(height, width, encoding, is_bigendian, step, data) with ``data`` a 1-D uint8 array.
    """
    if encoding not in IMAGE_ENCODINGS:
        raise InputError(f"unsupported encoding '{encoding}'")
    dtype, channels = IMAGE_ENCODINGS[encoding]
    array = np.asarray(array)
    if channels == 1 and array.ndim != 2 or channels > 1 and (array.ndim != 3 or array.shape[2] != channels):
        raise InputError(f"array of shape {array.shape} does not fit encoding '{encoding}'")
    array = np.ascontiguousarray(array.astype(dtype.newbyteorder("<"), copy=False))
    height, width = array.shape[:2]
    return {
        "height": int(height),
        "width": int(width),
        "encoding": encoding,
        "is_bigendian": False,
        "step": int(width * channels * dtype.itemsize),
        "data": array.view(np.uint8).reshape(-1),
    }


#: CDR encapsulation header of a little-endian plain-CDR (XCDR1) message, as ROS 2's rmw implementations write it.
CDR_LE_HEADER = b"\x00\x01\x00\x00"


def _cdr_string(text: str, offset: int) -> tuple[bytes, int]:
    """A CDR string at body offset ``offset``: uint32 length (with the NUL), UTF-8 bytes, NUL; returns (bytes, new
    offset). ``offset`` must be 4-aligned."""
    raw = text.encode("utf-8") + b"\x00"
    return struct.pack("<I", len(raw)) + raw, offset + 4 + len(raw)


def image_cdr(array: np.ndarray, encoding: str, stamp_ns: int, frame_id: str) -> bytes:
    """A sensor_msgs/Image holding ``array`` serialised as a ROS 2 rmw serialises it (plain CDR, little endian),
    ready for ``Publisher.publish(bytes)``: the pixels are copied once, straight from ``array`` into the message.

    Layout after :data:`CDR_LE_HEADER`: header (int32 sec, uint32 nanosec, string frame_id), uint32 height, uint32
    width, string encoding, uint8 is_bigendian, uint32 step, uint8[] data (uint32 length, bytes); each 4-byte field
    aligned to 4 from the start of the body, padding zero.

    Args:
        array, encoding: as :func:`array_to_image_fields` (same checks and conversion).
        stamp_ns: header stamp [ns]; frame_id: header frame id.
    """
    f = array_to_image_fields(array, encoding)
    sec, nanosec = ns_to_sec_nanosec(stamp_ns)
    parts = [CDR_LE_HEADER, struct.pack("<iI", sec, nanosec)]
    frame, offset = _cdr_string(str(frame_id), 8)
    parts += [frame, b"\x00" * (-offset % 4), struct.pack("<II", f["height"], f["width"])]
    enc, offset = _cdr_string(f["encoding"], offset + (-offset % 4) + 8)
    offset += 1   # is_bigendian
    parts += [enc, b"\x00", b"\x00" * (-offset % 4), struct.pack("<II", f["step"], f["data"].size), f["data"]]
    return b"".join(parts)


def stamp_to_ns(stamp: Any) -> int:
    """builtin_interfaces/Time -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_sec_nanosec(ns: int) -> tuple[int, int]:
    """Integer nanoseconds -> (sec, nanosec) of builtin_interfaces/Time."""
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return int(sec), int(nanosec)


def pose_to_arrays(pose: Any) -> tuple[np.ndarray, np.ndarray]:
    """geometry_msgs/Pose -> (position (3,) float64 [m], quaternion (4,) float64 in x, y, z, w order)."""
    p, q = pose.position, pose.orientation
    return (np.array([p.x, p.y, p.z], dtype=np.float64),
            np.array([q.x, q.y, q.z, q.w], dtype=np.float64))


def camera_info_to_intrinsics(msg: Any) -> tuple[np.ndarray, int, int]:
    """sensor_msgs/CameraInfo -> (K (3, 3) float64 [px], width, height). Distortion is ignored (rectified)."""
    k = np.asarray(msg.k, dtype=np.float64).reshape(-1)
    if k.size != 9:
        raise InputError(f"camera_info.k has {k.size} values, expected 9")
    return k.reshape(3, 3), int(msg.width), int(msg.height)


def pack_view_points(positions: np.ndarray, quats_xyzw: np.ndarray, u_var: np.ndarray,
                     u_exp: np.ndarray) -> dict[str, Any]:
    """PointCloud2 fields with one point per scored view (SPEC §8 ``view_uncertainty`` / ``candidate_scores``).

    Args:
        positions: (M, 3) view positions [m, map frame]; quats_xyzw: (M, 4) orientations of the optical
        frame; u_var, u_exp: (M,) image-level uncertainties. Every field is float32 (:data:`VIEW_FIELDS`).
    """
    return pack_scored_views(positions, quats_xyzw, u_var, u_exp)


def unpack_view_points(msg: Any) -> np.ndarray:
    """PointCloud2 of scored views -> structured (M,) array with :data:`VIEW_FIELDS` (float32)."""
    return unpack_cloud(msg, VIEW_FIELDS).astype(VIEW_DTYPE)
