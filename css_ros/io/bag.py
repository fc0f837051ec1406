"""rosbag2 input/output, the one reader and writer of the package: read any bag (sqlite3 or MCAP), write MCAP/sqlite3 bags."""
from __future__ import annotations

import functools
import shutil
import sqlite3
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator, Literal, Sequence

import numpy as np
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag2 import CompressionFormat, CompressionMode, ReaderError, StoragePlugin, Writer, WriterError
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, get_typestore

from ..errors import BagError
from .messages import array_to_image_fields, ns_to_sec_nanosec, pack_view_points
from .topics import CAMERA_INFO_TYPE, IMAGE_TYPE, POINTCLOUD2_TYPE, POSE_STAMPED_TYPE, TF_TYPE

if TYPE_CHECKING:
    from rosbags.interfaces import Connection
    from rosbags.typesys.store import Typestore

#: Exceptions rosbags raises for unreadable bags (truncated, corrupt, wrong format); translated to BagError.
ROSBAGS_ERRORS: tuple[type[BaseException], ...] = (AnyReaderError, ReaderError, SerdeError, WriterError, sqlite3.Error)


def typestore() -> "Typestore":
    """The ROS 2 Jazzy type store used for reading (fallback for bags without definitions) and writing."""
    return get_typestore(Stores.ROS2_JAZZY)


@dataclass(frozen=True)
class BagMessage:
    """One deserialised message: its topic, bag log time [ns] and the rosbags message object."""

    topic: str
    log_time_ns: int
    msg: Any


class InputBag:
    """Read-only view of a rosbag2 directory (sqlite3 or MCAP; rosbag1 files work too).

    Use as a context manager. Every rosbags failure (missing path, truncated or corrupt file,
    undecodable message) is raised as :class:`BagError` with the bag path in the message.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise BagError(f"bag not found: {self.path}")
        self._reader: AnyReader | None = None
        #: topic -> number of messages skipped because they could not be deserialised.
        self.undecodable: dict[str, int] = {}

    def __enter__(self) -> "InputBag":
        try:
            self._reader = AnyReader([self.path], default_typestore=typestore())
            self._reader.open()
        except ROSBAGS_ERRORS as exc:
            raise BagError(f"cannot open bag {self.path}: {_msg(exc)}") from None
        except (OSError, ValueError, KeyError, IndexError, EOFError) as exc:
            raise BagError(f"cannot open bag {self.path}: {type(exc).__name__}: {exc}") from None
        return self

    def __exit__(self, *exc: object) -> None:
        if self._reader is not None:
            try:
                self._reader.close()
            except Exception:  # noqa: BLE001 - closing a broken bag must not mask the real error
                pass
            self._reader = None

    @property
    def reader(self) -> AnyReader:
        if self._reader is None:
            raise BagError("bag is not open (use InputBag as a context manager)")
        return self._reader

    def topics(self) -> dict[str, tuple[str, int]]:
        """topic -> (message type, message count)."""
        out: dict[str, tuple[str, int]] = {}
        for conn in self.reader.connections:
            typ, count = out.get(conn.topic, (conn.msgtype, 0))
            out[conn.topic] = (typ, count + int(conn.msgcount))
        return out

    def check_topic(self, topic: str, msgtype: str, required: bool) -> bool:
        """True if ``topic`` exists with type ``msgtype``.

        Raises:
            BagError: the topic is required and missing, or it exists with another type.
        """
        topics = self.topics()
        if topic not in topics:
            if required:
                have = ", ".join(f"{t} [{ty}]" for t, (ty, _) in sorted(topics.items())) or "none"
                raise BagError(f"bag {self.path} has no topic '{topic}' ({msgtype}); topics in the bag: {have}")
            return False
        if topics[topic][0] != msgtype:
            raise BagError(f"bag {self.path}: topic '{topic}' has type {topics[topic][0]}, expected {msgtype}")
        return True

    def messages(self, topics: Sequence[str]) -> Iterator[BagMessage]:
        """Deserialised messages of ``topics`` in log-time order.

        A message that cannot be deserialised is skipped and counted in :attr:`undecodable`.

        Raises:
            BagError: on a truncated / corrupt bag (the storage itself cannot be read).
        """
        conns: list[Connection] = [c for c in self.reader.connections if c.topic in set(topics)]
        if not conns:
            return
        iterator = self.reader.messages(connections=conns)
        while True:
            try:
                conn, log_time, raw = next(iterator)
            except StopIteration:
                return
            except ROSBAGS_ERRORS as exc:
                raise BagError(f"bag {self.path} is corrupt or truncated: {_msg(exc)}") from None
            except (OSError, ValueError, KeyError, IndexError, EOFError, AssertionError) as exc:
                raise BagError(f"bag {self.path} is corrupt or truncated: {type(exc).__name__}: {exc}") from None
            try:
                msg = self.reader.deserialize(raw, conn.msgtype)
            except (*ROSBAGS_ERRORS, ValueError, IndexError, KeyError, AssertionError, TypeError):
                self.undecodable[conn.topic] = self.undecodable.get(conn.topic, 0) + 1
                continue
            yield BagMessage(conn.topic, int(log_time), msg)


def _msg(exc: BaseException) -> str:
    text = " ".join(str(a) for a in exc.args) if exc.args else ""
    return text or type(exc).__name__


class BagWriter:
    """Writes a new rosbag2 bag (format version 9): the one writer of the package (replay outputs, demo
    generator, importers).

    MCAP storage with zstd-compressed chunks (readable by ``ros2 bag`` and every MCAP reader) or
    sqlite3. Connections are added on first use, so the connection order is the order of first
    writes (a deterministic writer gives a byte-identical bag). Message header stamps equal the bag
    log times. Use as a context manager: an existing directory at ``path`` is replaced; an exception
    inside the ``with`` block aborts the bag (no half-written metadata).

    Args:
        path: bag directory to create.
        storage: ``"mcap"`` or ``"sqlite3"``.
        compress: zstd chunk compression (MCAP only).
        zstd_level: zstd level of the MCAP chunks (None = the library default). Skipped silently when
            the installed rosbags has no hook for it.
    """

    def __init__(self, path: str | Path, storage: Literal["mcap", "sqlite3"] = "mcap", compress: bool = True,
                 zstd_level: int | None = None) -> None:
        self.path = Path(path)
        self.storage = storage
        self.compress = compress and storage == "mcap"
        self.zstd_level = zstd_level
        self.store = typestore()
        self._writer: Writer | None = None
        self._conns: dict[str, Connection] = {}
        self._custom: dict[str, str] = {}
        self.count = 0

    def set_custom_data(self, key: str, value: str) -> None:
        """Store a string in the bag's metadata (``custom_data``)."""
        self._custom[key] = value
        if self._writer is not None:
            self._writer.set_custom_data(key, value)

    def __enter__(self) -> "BagWriter":
        if self.path.exists():
            shutil.rmtree(self.path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        plugin = StoragePlugin.MCAP if self.storage == "mcap" else StoragePlugin.SQLITE3
        try:
            self._writer = Writer(self.path, version=9, storage_plugin=plugin)
            if self.compress:
                self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
            self._writer.open()
        except ROSBAGS_ERRORS as exc:
            raise BagError(f"cannot create bag {self.path}: {_msg(exc)}") from None
        if self.compress and self.zstd_level is not None:
            _set_zstd_level(self._writer, self.zstd_level)
        for key, value in self._custom.items():
            self._writer.set_custom_data(key, value)
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        if self._writer is None:
            return
        writer, self._writer = self._writer, None
        if exc_type is not None and hasattr(writer, "abort"):
            writer.abort()
            shutil.rmtree(self.path, ignore_errors=True)
        else:
            writer.close()

    def _conn(self, topic: str, msgtype: str) -> "Connection":
        if topic not in self._conns:
            assert self._writer is not None
            self._conns[topic] = self._writer.add_connection(topic, msgtype, typestore=self.store)
        return self._conns[topic]

    def header(self, stamp_ns: int, frame_id: str) -> Any:
        """A std_msgs/Header (rosbags type) with the stamp [ns] and frame id."""
        sec, nanosec = ns_to_sec_nanosec(stamp_ns)
        types = self.store.types
        return types["std_msgs/msg/Header"](
            stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id
        )

    def write(self, topic: str, msgtype: str, msg: Any, stamp_ns: int) -> None:
        """Serialise a rosbags message of ``msgtype`` onto ``topic`` at log time ``stamp_ns``."""
        if self._writer is None:
            raise BagError("bag is not open (use BagWriter as a context manager)")
        data = self.store.serialize_cdr(msg, msgtype)
        self._writer.write(self._conn(topic, msgtype), int(stamp_ns), data)
        self.count += 1

    def write_image(self, topic: str, array: np.ndarray, encoding: str, stamp_ns: int, frame_id: str) -> None:
        """Write ``array`` as a sensor_msgs/Image."""
        f = array_to_image_fields(array, encoding)
        msg = self.store.types[IMAGE_TYPE](
            header=self.header(stamp_ns, frame_id),
            height=f["height"], width=f["width"], encoding=f["encoding"],
            is_bigendian=int(f["is_bigendian"]), step=f["step"], data=f["data"],
        )
        self.write(topic, IMAGE_TYPE, msg, stamp_ns)

    def write_camera_info(self, topic: str, K: np.ndarray, width: int, height: int, stamp_ns: int,
                          frame_id: str) -> None:
        """Write a rectified pinhole sensor_msgs/CameraInfo (K (3, 3) in pixels, no distortion)."""
        T = self.store.types
        P = np.zeros((3, 4))
        P[:, :3] = K
        roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        msg = T[CAMERA_INFO_TYPE](header=self.header(stamp_ns, frame_id), height=int(height), width=int(width),
                                  distortion_model="plumb_bob", d=np.zeros(5),
                                  k=np.asarray(K, dtype=np.float64).reshape(-1), r=np.eye(3).reshape(-1),
                                  p=P.reshape(-1), binning_x=0, binning_y=0, roi=roi)
        self.write(topic, CAMERA_INFO_TYPE, msg, stamp_ns)

    def write_pose(self, topic: str, position: np.ndarray, quat_xyzw: np.ndarray, stamp_ns: int,
                   frame_id: str) -> None:
        """Write a geometry_msgs/PoseStamped (position [m], quaternion x, y, z, w)."""
        T = self.store.types
        pose = T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=float(position[0]), y=float(position[1]), z=float(position[2])),
            orientation=T["geometry_msgs/msg/Quaternion"](x=float(quat_xyzw[0]), y=float(quat_xyzw[1]),
                                                          z=float(quat_xyzw[2]), w=float(quat_xyzw[3])))
        self.write(topic, POSE_STAMPED_TYPE, T[POSE_STAMPED_TYPE](header=self.header(stamp_ns, frame_id), pose=pose),
                   stamp_ns)

    def write_tf(self, topic: str, log_ns: int,
                 transforms: "list[tuple[str, str, int, np.ndarray, np.ndarray]]") -> None:
        """A tf2_msgs/TFMessage of (parent, child, stamp [ns], translation (3,) [m], quaternion x, y, z, w)
        entries (``/tf`` or ``/tf_static``), logged at ``log_ns``."""
        T = self.store.types
        out = []
        for parent, child, stamp, p, q in transforms:
            out.append(T["geometry_msgs/msg/TransformStamped"](
                header=self.header(stamp, parent), child_frame_id=child,
                transform=T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](x=float(p[0]), y=float(p[1]), z=float(p[2])),
                    rotation=T["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                                               w=float(q[3])))))
        self.write(topic, TF_TYPE, T[TF_TYPE](transforms=out), log_ns)

    def write_view_points(self, topic: str, positions: np.ndarray, quats_xyzw: np.ndarray, u_var: np.ndarray,
                          u_exp: np.ndarray, stamp_ns: int, frame_id: str) -> None:
        """Write a PointCloud2 with one point per scored view (SPEC §8 ``view_uncertainty`` layout)."""
        f = pack_view_points(positions, quats_xyzw, u_var, u_exp)
        types = self.store.types
        fields = [types["sensor_msgs/msg/PointField"](name=n, offset=o, datatype=d, count=c)
                  for (n, o, d, c) in f["fields"]]
        msg = types[POINTCLOUD2_TYPE](
            header=self.header(stamp_ns, frame_id), height=f["height"], width=f["width"], fields=fields,
            is_bigendian=bool(f["is_bigendian"]), point_step=f["point_step"], row_step=f["row_step"],
            data=f["data"], is_dense=bool(f["is_dense"]),
        )
        self.write(topic, POINTCLOUD2_TYPE, msg, stamp_ns)


def _set_zstd_level(writer: Any, level: int) -> None:
    """Compress MCAP chunks at ``level`` (rosbags uses zstd's default level; 19 makes the demo ~20 % smaller)."""
    storage = getattr(writer, "storage", None)
    if not callable(getattr(storage, "compressor", None)):
        return
    try:
        from compression import zstd  # Python >= 3.14
    except ImportError:
        try:
            from backports import zstd
        except ImportError:
            return
    storage.compressor = functools.partial(zstd.compress, level=level)
