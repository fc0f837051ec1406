"""rosbag2 input/output for css_replay: read any bag (sqlite3 or MCAP) and write the node's output topics."""
from __future__ import annotations

import shutil
import sqlite3
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator, Sequence

import numpy as np
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag2 import CompressionFormat, CompressionMode, ReaderError, StoragePlugin, Writer, WriterError
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, get_typestore

from ..errors import BagError, CssError
from .messages import array_to_image_fields, ns_to_sec_nanosec, pack_view_points

if TYPE_CHECKING:
    from rosbags.interfaces import Connection
    from rosbags.typesys.store import Typestore

#: Exceptions rosbags raises for unreadable bags (truncated, corrupt, wrong format); translated to BagError.
ROSBAGS_ERRORS: tuple[type[BaseException], ...] = (AnyReaderError, ReaderError, SerdeError, WriterError, sqlite3.Error)

IMAGE_TYPE = "sensor_msgs/msg/Image"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
POSE_STAMPED_TYPE = "geometry_msgs/msg/PoseStamped"
POINTCLOUD2_TYPE = "sensor_msgs/msg/PointCloud2"


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


class OutputBag:
    """Writes the node's output topics (SPEC §8) into a new rosbag2 bag (MCAP storage, format version 9, zstd chunks).

    Every message's header stamp and the bag log time are the input frame's stamp. Use as a context
    manager; an existing bag directory at ``path`` is replaced.
    """

    def __init__(self, path: str | Path, namespace: str = "/css_node", compress: bool = True) -> None:
        self.path = Path(path)
        self.compress = compress
        self.namespace = namespace.rstrip("/")
        self.store = typestore()
        self._writer: Writer | None = None
        self._conns: dict[str, Connection] = {}
        self.count = 0

    def topic(self, name: str) -> str:
        """Full output topic name, e.g. ``/css_node/semantic``."""
        return f"{self.namespace}/{name}"

    def __enter__(self) -> "OutputBag":
        if self.path.exists():
            shutil.rmtree(self.path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self._writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
            if self.compress:  # zstd-compressed MCAP chunks (readable by ros2 bag / any MCAP reader)
                self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
            self._writer.open()
        except ROSBAGS_ERRORS as exc:
            raise BagError(f"cannot create output bag {self.path}: {_msg(exc)}") from None
        return self

    def __exit__(self, *exc: object) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    def _conn(self, name: str, msgtype: str) -> "Connection":
        topic = self.topic(name)
        if topic not in self._conns:
            assert self._writer is not None
            self._conns[topic] = self._writer.add_connection(topic, msgtype, typestore=self.store)
        return self._conns[topic]

    def _header(self, stamp_ns: int, frame_id: str) -> Any:
        sec, nanosec = ns_to_sec_nanosec(stamp_ns)
        types = self.store.types
        return types["std_msgs/msg/Header"](
            stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id
        )

    def _write(self, name: str, msgtype: str, msg: Any, stamp_ns: int) -> None:
        if self._writer is None:
            raise BagError("output bag is not open")
        data = self.store.serialize_cdr(msg, msgtype)
        self._writer.write(self._conn(name, msgtype), int(stamp_ns), data)
        self.count += 1

    def write_image(self, name: str, array: np.ndarray, encoding: str, stamp_ns: int, frame_id: str) -> None:
        """Write ``array`` as a sensor_msgs/Image on ``<namespace>/<name>``."""
        f = array_to_image_fields(array, encoding)
        msg = self.store.types[IMAGE_TYPE](
            header=self._header(stamp_ns, frame_id),
            height=f["height"], width=f["width"], encoding=f["encoding"],
            is_bigendian=int(f["is_bigendian"]), step=f["step"], data=f["data"],
        )
        self._write(name, IMAGE_TYPE, msg, stamp_ns)

    def write_view_points(self, name: str, positions: np.ndarray, quats_xyzw: np.ndarray, u_var: np.ndarray,
                          u_exp: np.ndarray, stamp_ns: int, frame_id: str) -> None:
        """Write a PointCloud2 with one point per scored view (SPEC §8 ``view_uncertainty`` layout)."""
        f = pack_view_points(positions, quats_xyzw, u_var, u_exp)
        types = self.store.types
        fields = [types["sensor_msgs/msg/PointField"](name=n, offset=o, datatype=d, count=c)
                  for (n, o, d, c) in f["fields"]]
        msg = types[POINTCLOUD2_TYPE](
            header=self._header(stamp_ns, frame_id), height=f["height"], width=f["width"], fields=fields,
            is_bigendian=bool(f["is_bigendian"]), point_step=f["point_step"], row_step=f["row_step"],
            data=f["data"], is_dense=bool(f["is_dense"]),
        )
        self._write(name, POINTCLOUD2_TYPE, msg, stamp_ns)
