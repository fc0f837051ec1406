"""css_node: the rclpy node that maps segmentations onto a splat model and scores candidate views (SPEC §7-8)."""
from __future__ import annotations

import os
import sys
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from ..engine.camera import QUATERNION_NORM_TOLERANCE, Camera, matrix_to_quaternion_xyzw, quaternion_xyzw_to_matrix
from ..engine.classes import ClassSet
from ..errors import CameraError, CssError, InputError, MapError, ModelError
from ..io.messages import (COLOR_ENCODINGS, CONFIDENCE_ENCODINGS, LABEL_ENCODINGS, camera_info_to_intrinsics,
                       image_to_array, pose_to_arrays, stamp_to_ns)
from ..io.paths import resolve_data_path
from ..io.sync import FrameSynchronizer

NODE_NAME = "css_node"
#: Relative input topic names (remappable) and the node-private outputs / services of SPEC §8.
INPUT_TOPICS = ("image", "segmentation", "segmentation_confidence", "camera_info", "pose", "candidates")
OUTPUT_TOPICS = ("semantic", "semantic_color", "expectation", "variance", "rendered_image",
                 "view_uncertainty", "candidate_scores")
DEFAULT_MODEL = "bags/demo/model.ply"
DEFAULT_CLASSES = "bags/demo/classes.yaml"
DEFAULT_CHECKPOINT = "~/.ros/css_ros/semantic_map.npz"
#: Quaternion (x, y, z, w) of the optical frame in a REP-103 body frame (camera.body_to_optical_rotation()).
BODY_TO_OPTICAL_XYZW = (-0.5, 0.5, -0.5, 0.5)
#: Consecutive segmentations older than the last frame after which the node assumes the clock was reset.
STAMP_RESET_COUNT = 5


# --------------------------------------------------------------------------------------------- parameters
@dataclass
class NodeParams:
    """Parameters of css_node (see config/css_node.yaml and the README for each one)."""

    model_path: str = DEFAULT_MODEL
    class_file: str = DEFAULT_CLASSES
    num_classes: int = 0
    prior: float = 1e-3
    background: float = 1e-3
    ignore_label: int = 255
    unknown_threshold: float = 0.5
    backend: str = "numba"
    sync_slop: float = 0.05
    max_stamp_future: float = 10.0
    input_qos: str = "sensor_data"
    queue_size: int = 10
    max_pending_frames: int = 2
    use_confidence: bool = True
    output_scale: float = 1.0
    candidate_scale: float = 0.25
    max_candidates: int = 256
    body_to_optical: bool = False
    body_to_optical_quaternion: list[float] = field(default_factory=lambda: list(BODY_TO_OPTICAL_XYZW))
    map_frame: str = "map"
    checkpoint_path: str = DEFAULT_CHECKPOINT
    checkpoint_period: float = 60.0
    resume: bool = True
    publish_semantic: bool = True
    publish_semantic_color: bool = True
    publish_expectation: bool = True
    publish_variance: bool = True
    publish_rendered_image: bool = True
    publish_view_uncertainty: bool = True
    publish_diagnostics: bool = True
    log_period: float = 10.0
    warn_period: float = 5.0
    warmup: bool = True

    DESCRIPTIONS = {
        "model_path": "3DGS PLY of the scene (map frame); relative paths are tried against the working "
                      "directory, the package share directory and the source tree",
        "class_file": "class YAML (classes: [{id, name, color}]); empty: num_classes anonymous classes",
        "num_classes": "number of classes C when class_file is empty (0: take it from class_file)",
        "prior": "initial Dirichlet concentration per class and Gaussian (alpha_0)",
        "background": "background Dirichlet concentration per class (alpha_b)",
        "ignore_label": "segmentation value meaning 'no label'; also published for unknown pixels",
        "unknown_threshold": "background weight kappa_b above which a pixel is published as ignore_label "
                             "(1.0: never)",
        "backend": "rasteriser backend: numba or torch",
        "sync_slop": "maximum stamp difference [s] between segmentation, pose and confidence of one frame",
        "max_stamp_future": "drop inputs stamped more than this [s] ahead of the node clock (0: off)",
        "input_qos": "QoS of the sensor inputs: sensor_data (best effort) or reliable",
        "queue_size": "subscription depth and synchroniser buffer per input",
        "max_pending_frames": "synchronised frames waiting for the worker; the oldest is dropped when full",
        "use_confidence": "synchronise segmentation_confidence whenever it has a publisher",
        "output_scale": "resolution scale of the published renders (the update uses full resolution)",
        "candidate_scale": "resolution scale at which candidate views are rendered",
        "max_candidates": "largest PoseArray accepted on candidates",
        "body_to_optical": "poses are of a body frame (x fwd, y left, z up): apply body_to_optical_quaternion",
        "body_to_optical_quaternion": "rotation (x, y, z, w) of the optical frame in the body frame",
        "map_frame": "frame of the splat model; frame_id of ~/view_uncertainty",
        "checkpoint_path": "semantic map checkpoint (.npz); empty disables saving and resuming",
        "checkpoint_period": "seconds between automatic checkpoints (0: only on ~/save_map and shutdown)",
        "resume": "load checkpoint_path at start if it matches the model",
        "publish_diagnostics": "publish counters on diagnostics (diagnostic_msgs/DiagnosticArray)",
        "log_period": "seconds between status log lines and diagnostics messages",
        "warn_period": "minimum seconds between two warnings of the same topic and reason",
        "warmup": "compile the rasteriser kernels before subscribing",
    }


def _coerce(name: str, value: Any, default: Any) -> Any:
    """Convert a parameter value to the type of its default (int -> float allowed); CssError otherwise."""
    def bad() -> CssError:
        return CssError(f"parameter {name}={value!r}: expected {type(default).__name__}"
                        + (" of numbers" if isinstance(default, list) else ""))

    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise bad()
        return value
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise bad()
        return float(value)
    if isinstance(default, int):
        if isinstance(value, bool) or not (isinstance(value, int) or (isinstance(value, float)
                                                                       and float(value).is_integer())):
            raise bad()
        return int(value)
    if isinstance(default, str):
        if not isinstance(value, str):
            raise bad()
        return value
    if isinstance(default, list):
        try:
            values = list(value)
        except TypeError:
            raise bad() from None
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
            raise bad()
        return [float(v) for v in values]
    return value


def declare_params(node: Any) -> NodeParams:
    """Declare every NodeParams field as a read-only ROS parameter and return their values.

    Parameters are declared with dynamic typing and converted here, so ``-p prior:=1`` (an integer for a
    float parameter) works and a wrong type is a clear CssError naming the parameter.
    """
    from rcl_interfaces.msg import ParameterDescriptor

    defaults = NodeParams()
    values: dict[str, Any] = {}
    for name in NodeParams.__dataclass_fields__:
        default = getattr(defaults, name)
        desc = ParameterDescriptor(description=NodeParams.DESCRIPTIONS.get(name, name.replace("_", " ")),
                                   read_only=True, dynamic_typing=True)
        value = node.declare_parameter(name, default, desc).value
        values[name] = _coerce(name, value, default)
    return NodeParams(**values)


def check_params(p: NodeParams) -> None:
    """Raise CssError naming the parameter when a value is out of range."""
    def bad(name: str, why: str) -> CssError:
        return CssError(f"parameter {name}={getattr(p, name)!r}: {why}")

    if p.input_qos not in ("sensor_data", "reliable"):
        raise bad("input_qos", "expected 'sensor_data' or 'reliable'")
    if p.backend not in ("numba", "torch"):
        raise bad("backend", "expected 'numba' or 'torch'")
    for name in ("prior", "background", "unknown_threshold", "output_scale", "candidate_scale"):
        if not (np.isfinite(getattr(p, name)) and getattr(p, name) > 0):
            raise bad(name, "must be finite and > 0")
    for name in ("sync_slop", "max_stamp_future", "checkpoint_period", "log_period", "warn_period"):
        if not (np.isfinite(getattr(p, name)) and getattr(p, name) >= 0):
            raise bad(name, "must be finite and >= 0")
    for name in ("queue_size", "max_pending_frames", "max_candidates"):
        if getattr(p, name) < 1:
            raise bad(name, "must be >= 1")
    if not 0 <= p.ignore_label <= 65535:
        raise bad("ignore_label", "must be in 0..65535")
    q = np.asarray(p.body_to_optical_quaternion, dtype=np.float64)
    if q.shape != (4,) or not np.all(np.isfinite(q)) or abs(np.linalg.norm(q) - 1) > 1e-3:
        raise bad("body_to_optical_quaternion", "expected a unit quaternion [x, y, z, w]")
    if p.log_period == 0:
        p.log_period = 1e9


# --------------------------------------------------------------------------------------------- helpers
class WarnLimiter:
    """Counts bad inputs per (topic, reason) and logs at most one warning per key and ``period`` seconds."""

    def __init__(self, log: Callable[[str], None], period: float) -> None:
        self._log = log
        self.period = period
        self.counts: Counter[str] = Counter()
        self.dropped: Counter[str] = Counter()
        self._last: dict[str, float] = {}
        self._suppressed: Counter[str] = Counter()
        self._lock = threading.Lock()

    def __call__(self, topic: str, reason: str, detail: str = "", dropped: bool = True) -> None:
        """Count and (rate-limited) log a problem with ``topic``; ``dropped``: the message was discarded."""
        key = f"{topic}: {reason}"
        now = time.monotonic()
        with self._lock:
            self.counts[key] += 1
            if dropped:
                self.dropped[topic] += 1
            last = self._last.get(key)
            if last is not None and now - last < self.period:
                self._suppressed[key] += 1
                return
            self._last[key] = now
            extra = f" (+{self._suppressed.pop(key)} similar since last warning)" if self._suppressed.get(key) else ""
        self._log(f"[{topic}] {reason}{': ' + detail if detail else ''}; total {self.counts[key]}{extra}")

    def snapshot(self) -> tuple[dict[str, int], dict[str, int]]:
        """(counts per 'topic: reason', dropped messages per topic)."""
        with self._lock:
            return dict(self.counts), dict(self.dropped)


@dataclass
class FrameJob:
    """A synchronised observed frame waiting for the worker."""

    stamp_ns: int
    frame_id: str
    labels: np.ndarray            # (H, W) uint8/uint16 class ids
    confidence: np.ndarray | None  # (H, W) float32 in [0, 1]
    image: np.ndarray | None      # (H, W, 3) uint8 RGB (diagnostics only)
    K: np.ndarray                 # (3, 3) px
    position: np.ndarray          # (3,) m, as received
    quat_in: np.ndarray           # (4,) xyzw, as received (normalised)
    quat_optical: np.ndarray      # (4,) xyzw of the optical frame
    t_received: float             # time.monotonic() of the segmentation


@dataclass
class CandidateJob:
    """A PoseArray of candidate views waiting for the worker."""

    header: Any
    K: np.ndarray
    width: int
    height: int
    positions: np.ndarray         # (M, 3)
    quats_in: np.ndarray          # (M, 4) as received
    quats_optical: np.ndarray     # (M, 4); rows of invalid poses are NaN
    t_received: float


class WorkQueue:
    """Bounded queues between the executor (producers) and the worker thread (consumer).

    Frames: newest wins (the oldest pending frame is dropped when full). Candidate requests have their
    own queue and are served between frames; when both are waiting the worker alternates, so neither
    stream starves the other.
    """

    def __init__(self, max_frames: int, max_requests: int = 8) -> None:
        self.frames: deque[FrameJob] = deque()
        self.requests: deque[CandidateJob] = deque()
        self.max_frames = max_frames
        self.max_requests = max_requests
        self._cond = threading.Condition()
        self._last_was_frame = False
        self.closed = False

    def put_frame(self, job: FrameJob) -> FrameJob | None:
        """Queue a frame; returns the frame dropped to make room, if any."""
        with self._cond:
            dropped = self.frames.popleft() if len(self.frames) >= self.max_frames else None
            self.frames.append(job)
            self._cond.notify()
        return dropped

    def put_request(self, job: CandidateJob) -> CandidateJob | None:
        """Queue a candidate request; returns the (oldest) request dropped to make room, if any."""
        with self._cond:
            dropped = self.requests.popleft() if len(self.requests) >= self.max_requests else None
            self.requests.append(job)
            self._cond.notify()
        return dropped

    def get(self, timeout: float) -> FrameJob | CandidateJob | None:
        """Next job (None after ``timeout`` s or when closed)."""
        with self._cond:
            if not self.frames and not self.requests and not self.closed:
                self._cond.wait(timeout)
            if self.closed:
                return None
            if self.requests and (not self.frames or self._last_was_frame):
                self._last_was_frame = False
                return self.requests.popleft()
            if self.frames:
                self._last_was_frame = True
                return self.frames.popleft()
            return None

    def close(self) -> None:
        with self._cond:
            self.closed = True
            self._cond.notify_all()

    def sizes(self) -> tuple[int, int]:
        with self._cond:
            return len(self.frames), len(self.requests)


def body_to_optical(quats_xyzw: np.ndarray, q_body_optical: np.ndarray) -> np.ndarray:
    """Orientation of the optical frame: R_map_optical = R_map_body @ R_body_optical; (M, 4) -> (M, 4) xyzw."""
    R = quaternion_xyzw_to_matrix(quats_xyzw) @ quaternion_xyzw_to_matrix(q_body_optical)
    return matrix_to_quaternion_xyzw(R)


def check_quaternion(q: np.ndarray) -> str | None:
    """Reason why ``q`` (x, y, z, w) is unusable as an orientation, or None.

    Same rule as Camera.from_pose: finite, norm within QUATERNION_NORM_TOLERANCE (then normalised).
    """
    if not np.all(np.isfinite(q)):
        return "non-finite quaternion"
    lo, hi = QUATERNION_NORM_TOLERANCE
    if not lo <= float(np.linalg.norm(q)) <= hi:
        return "non-unit quaternion"
    return None


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR [dB] of two uint8 images of equal shape."""
    mse = float(np.mean((a.astype(np.float32) - b.astype(np.float32)) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(255.0 ** 2 / mse)


# --------------------------------------------------------------------------------------------- the node
def _make_node_class() -> type:
    """Build the Node subclass (rclpy is imported only when the node is used)."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from geometry_msgs.msg import PoseArray, PoseStamped
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy, HistoryPolicy, qos_profile_sensor_data
    from sensor_msgs.msg import CameraInfo, Image, PointCloud2
    from std_srvs.srv import Trigger

    from . import conversions as rc

    class CssNode(Node):
        """Continuous Semantic Splatting mapping node (see the module docstring and SPEC §7-8)."""

        def __init__(self, **kwargs: Any) -> None:
            super().__init__(NODE_NAME, **kwargs)
            log = self.get_logger()
            self.p = p = declare_params(self)
            check_params(p)
            self.warn = WarnLimiter(log.warning, p.warn_period)
            self._stats_lock = threading.Lock()
            self.stats: Counter[str] = Counter()
            self._frame_ms: deque[float] = deque(maxlen=200)
            self._request_ms: deque[float] = deque(maxlen=200)
            self._last_u: tuple[float, float] = (float("nan"), float("nan"))
            self._last_psnr = float("nan")
            self._last_log = (time.monotonic(), 0)
            self._last_problems: dict[str, int] = {}
            self._q_b2o = np.asarray(p.body_to_optical_quaternion, dtype=np.float64)

            # ---- engine: model, classes, map (fatal errors propagate to main())
            self.smap, self.classes, self.model_path = self._load_engine()
            self.C = self.smap.num_classes
            self._label_encoding = "mono8" if max(self.C - 1, p.ignore_label) <= 255 else "mono16"
            self._map_lock = threading.Lock()
            self._dirty = 0
            self._last_save = time.monotonic()
            if p.warmup:
                self._warm_up()

            # ---- inputs
            self._camera_info: tuple[np.ndarray, int, int] | None = None
            self._images: deque[tuple[int, np.ndarray]] = deque(maxlen=p.queue_size)
            self._last_frame_ns: int | None = None
            self._stale_run = 0
            self._sync_kinds: tuple[str, ...] = ()
            self.sync = self._make_sync(("segmentation", "pose", "confidence") if p.use_confidence
                                        else ("segmentation", "pose"))
            self._confidence_topic = self.resolve_topic_name("segmentation_confidence")
            #: last messages pushed per non-anchor kind (re-offered to the synchroniser after a clock reset)
            self._recent: dict[str, deque[tuple[int, Any]]] = {
                k: deque(maxlen=p.queue_size) for k in self._sync_kinds if k != "segmentation"}
            self._sync_counts: Counter[str] = Counter()
            self.queue = WorkQueue(p.max_pending_frames)
            if p.input_qos == "reliable":
                qos_in = QoSProfile(depth=p.queue_size, reliability=ReliabilityPolicy.RELIABLE,
                                    history=HistoryPolicy.KEEP_LAST)
            else:
                qos_in = QoSProfile(depth=p.queue_size, reliability=qos_profile_sensor_data.reliability,
                                    durability=qos_profile_sensor_data.durability,
                                    history=HistoryPolicy.KEEP_LAST)
            qos_req = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
            # camera_info first: when several messages are ready the executor takes them in this order.
            self.create_subscription(CameraInfo, "camera_info", self._on_camera_info, qos_in)
            self.create_subscription(PoseStamped, "pose", self._on_pose, qos_in)
            self.create_subscription(Image, "image", self._on_image, qos_in)
            self.create_subscription(Image, "segmentation_confidence", self._on_confidence, qos_in)
            self.create_subscription(Image, "segmentation", self._on_segmentation, qos_in)
            self.create_subscription(PoseArray, "candidates", self._on_candidates, qos_req)

            # ---- outputs
            self.pubs: dict[str, Any] = {}
            for name, typ, flag in (("semantic", Image, p.publish_semantic),
                                    ("semantic_color", Image, p.publish_semantic_color),
                                    ("expectation", Image, p.publish_expectation),
                                    ("variance", Image, p.publish_variance),
                                    ("rendered_image", Image, p.publish_rendered_image),
                                    ("view_uncertainty", PointCloud2, p.publish_view_uncertainty),
                                    ("candidate_scores", PointCloud2, True)):
                if flag:
                    self.pubs[name] = self.create_publisher(typ, f"~/{name}", 10)
            self._diag_pub = (self.create_publisher(DiagnosticArray, "/diagnostics", 10)
                              if p.publish_diagnostics else None)
            self._diag_types = (DiagnosticArray, DiagnosticStatus, KeyValue)
            self.create_service(Trigger, "~/save_map", self._on_save_map)
            self.create_service(Trigger, "~/reset_map", self._on_reset_map)
            self.create_timer(p.log_period, self._on_log_timer)

            self._worker = threading.Thread(target=self._work_loop, name="css_worker", daemon=True)
            self._worker.start()
            self._log_start()

        # ------------------------------------------------------------------ start-up
        def _load_engine(self) -> tuple[Any, ClassSet, Path]:
            from ..engine.gaussians import GaussianModel
            from ..engine.semantic_map import SemanticMap

            p, log = self.p, self.get_logger()
            model_path = resolve_data_path(p.model_path)
            if not model_path.is_file():
                raise ModelError(f"model file not found: {model_path} (parameter model_path={p.model_path!r})")
            model = GaussianModel.from_ply(model_path)
            if p.class_file:
                class_path = resolve_data_path(p.class_file)
                classes = ClassSet.from_yaml(class_path)
                if p.num_classes and p.num_classes != classes.num_classes:
                    log.warning(f"num_classes={p.num_classes} ignored: class file {class_path} defines "
                                f"{classes.num_classes} classes")
            elif p.num_classes > 0:
                classes = ClassSet.default(p.num_classes)
            else:
                raise CssError("set class_file or num_classes > 0")
            C = classes.num_classes
            kwargs = dict(ignore_label=p.ignore_label, unknown_threshold=p.unknown_threshold, backend=p.backend)
            smap = None
            ckpt = self._checkpoint_path()
            self.resume_status = "fresh map"
            if ckpt is not None and p.resume and ckpt.exists():
                try:
                    smap = SemanticMap.load(ckpt, model, **kwargs)
                    if smap.num_classes != C:
                        raise MapError(f"it has {smap.num_classes} classes, the class setup has {C}")
                    self.resume_status = f"resumed from {ckpt} ({smap.frames_observed} frames observed)"
                    if (smap.prior, smap.background) != (p.prior, p.background):
                        log.warning(f"checkpoint prior/background ({smap.prior:g}, {smap.background:g}) "
                                    f"override the parameters ({p.prior:g}, {p.background:g})")
                except MapError as exc:
                    smap = None
                    aside = ckpt.with_name(ckpt.name + f".rejected-{time.strftime('%Y%m%d-%H%M%S')}")
                    try:
                        os.replace(ckpt, aside)
                        moved = f"; kept it as {aside}"
                    except OSError:
                        moved = ""
                    self.resume_status = f"starting fresh: checkpoint refused: {exc}{moved}"
                    log.warning(self.resume_status)
            elif ckpt is not None and p.resume:
                self.resume_status = f"fresh map (no checkpoint at {ckpt} yet)"
            if smap is None:
                smap = SemanticMap(model, num_classes=C, prior=p.prior, background=p.background, **kwargs)
            return smap, classes, model_path

        def _checkpoint_path(self) -> Path | None:
            if not self.p.checkpoint_path:
                return None
            return Path(os.path.expanduser(self.p.checkpoint_path)).absolute()

        def _warm_up(self) -> None:
            """Run the kernels once on a tiny view so the first real frame is not slowed by JIT compilation."""
            t0 = time.perf_counter()
            model = self.smap.model
            centre = np.median(np.asarray(model.means, dtype=np.float64), axis=0)
            extent = float(np.max(np.ptp(model.means, axis=0))) if model.num_gaussians > 1 else 1.0
            K = np.array([[16.0, 0, 7.5], [0, 16.0, 5.5], [0, 0, 1]])
            cam = Camera.from_pose(K, 16, 12, centre - np.array([0, 0, extent + 1.0]), (0, 0, 0, 1))
            labels = np.full((12, 16), self.p.ignore_label, dtype=np.int32)
            frames_observed = getattr(self.smap, "frames_observed", None)
            try:
                before = self.smap.concentrations.copy()
                self.smap.update(cam, labels)  # all pixels "no label": compiles the update, adds nothing
                self.smap.render(cam)
                self.smap.render(cam.scaled(0.5))
                if not np.array_equal(before, self.smap.concentrations):
                    self.smap.concentrations[...] = before
                if frames_observed is not None:
                    self.smap.frames_observed = frames_observed
            except CssError as exc:
                self.get_logger().warning(f"warm-up failed ({exc}); first frame will compile the kernels")
            self.get_logger().info(f"rasteriser warm-up ({self.p.backend}) took {time.perf_counter() - t0:.2f} s")

        def _log_start(self) -> None:
            p, m = self.p, self.smap.model
            names = ", ".join(f"{i}:{n}" for i, n in enumerate(self.classes.names))
            ins = ", ".join(self.resolve_topic_name(t) for t in INPUT_TOPICS)
            outs = ", ".join(self.resolve_topic_name(f"~/{t}") for t in self.pubs)
            self.get_logger().info(
                f"model {self.model_path}: {m.num_gaussians} Gaussians, SH degree {m.sh_degree}, "
                f"fingerprint {m.fingerprint[:12]}; {self.C} classes [{names}]; backend {p.backend}; "
                f"{self.resume_status}")
            self.get_logger().info(f"inputs ({p.input_qos} QoS; candidates reliable): {ins}")
            self.get_logger().info(
                f"outputs: {outs}; services: {self.resolve_topic_name('~/save_map')}, "
                f"{self.resolve_topic_name('~/reset_map')}; checkpoint "
                + (f"{self._checkpoint_path()} every {p.checkpoint_period:g} s" if self._checkpoint_path()
                   else "disabled")
                + f"; sync slop {p.sync_slop * 1e3:g} ms")

        # ------------------------------------------------------------------ input callbacks
        def _make_sync(self, kinds: Sequence[str]) -> FrameSynchronizer:
            self._sync_kinds = tuple(kinds)
            self._sync_counts = Counter()
            return FrameSynchronizer(kinds, slop_ns=int(round(self.p.sync_slop * 1e9)),
                                     anchor="segmentation", queue_size=self.p.queue_size)

        def _confidence_published(self) -> bool:
            """True while segmentation_confidence has a publisher: frames then wait for a confidence image."""
            return self.count_publishers(self._confidence_topic) > 0

        def _count(self, key: str, n: int = 1) -> None:
            with self._stats_lock:
                self.stats[key] += n

        def _stamp_ok(self, topic: str, stamp_ns: int) -> bool:
            if self.p.max_stamp_future > 0:
                now = self.get_clock().now().nanoseconds
                if now > 0 and stamp_ns > now + self.p.max_stamp_future * 1e9:
                    self.warn(topic, "stamp in the future",
                              f"{(stamp_ns - now) * 1e-9:.3f} s ahead of the node clock (max_stamp_future)")
                    return False
            return True

        def _size_ok(self, topic: str, shape: tuple[int, ...]) -> bool:
            """Image size check against the latest camera_info (deferred to the frame if none yet)."""
            info = self._camera_info
            if info is None:
                return True
            K, w, h = info
            if shape[:2] != (h, w):
                self.warn(topic, "size mismatch with camera_info",
                          f"image {shape[1]}x{shape[0]}, camera_info {w}x{h}; frame dropped")
                return False
            return True

        def _on_camera_info(self, msg: Any) -> None:
            try:
                K, w, h = camera_info_to_intrinsics(msg)
                Camera(K=K, width=w, height=h, T_map_cam=np.eye(4))  # validates K and size
            except (InputError, CameraError) as exc:
                self.warn("camera_info", "invalid camera_info", f"{exc}; keeping the previous one")
                return
            self._camera_info = (K, w, h)

        def _on_image(self, msg: Any) -> None:
            stamp = stamp_to_ns(msg.header.stamp)
            try:
                rgb = image_to_array(msg, allowed=COLOR_ENCODINGS)
            except InputError as exc:
                self.warn("image", "bad image", f"{exc}; ignored")
                return
            if rgb.ndim == 2:
                rgb = np.repeat(rgb[:, :, None], 3, axis=2)
            if not self._size_ok("image", rgb.shape) or not self._stamp_ok("image", stamp):
                return
            self._images.append((stamp, rgb))

        def _on_confidence(self, msg: Any) -> None:
            topic = "segmentation_confidence"
            stamp = stamp_to_ns(msg.header.stamp)
            try:
                conf = image_to_array(msg, allowed=CONFIDENCE_ENCODINGS)
            except InputError as exc:
                self.warn(topic, "bad confidence image", f"{exc}; dropped")
                return
            if not np.all(np.isfinite(conf)):
                self.warn(topic, "non-finite confidence values", "dropped")
                return
            if not self._size_ok(topic, conf.shape) or not self._stamp_ok(topic, stamp):
                return
            if self.p.use_confidence:
                self._push("confidence", topic, stamp, np.clip(conf, 0.0, 1.0))

        def _on_pose(self, msg: Any) -> None:
            stamp = stamp_to_ns(msg.header.stamp)
            position, quat = pose_to_arrays(msg.pose)
            if not np.all(np.isfinite(position)):
                self.warn("pose", "non-finite position", "dropped")
                return
            reason = check_quaternion(quat)
            if reason is not None:
                self.warn("pose", reason, f"{quat.tolist()} (norm {np.linalg.norm(quat):.4g}); dropped")
                return
            if msg.header.frame_id and msg.header.frame_id.lstrip("/") != self.p.map_frame:
                self.warn("pose", "frame_id differs from map_frame",
                          f"'{msg.header.frame_id}' != '{self.p.map_frame}' (no tf here): used as map frame",
                          dropped=False)
            if not self._stamp_ok("pose", stamp):
                return
            quat = quat / np.linalg.norm(quat)
            quat_opt = body_to_optical(quat, self._q_b2o) if self.p.body_to_optical else quat
            self._push("pose", "pose", stamp, (position, quat, quat_opt))

        def _on_segmentation(self, msg: Any) -> None:
            topic = "segmentation"
            stamp = stamp_to_ns(msg.header.stamp)
            self._count("segmentations_received")
            try:
                labels = image_to_array(msg, allowed=LABEL_ENCODINGS)
            except InputError as exc:
                self.warn(topic, "bad segmentation", f"{exc}; frame dropped")
                return
            if not self._size_ok(topic, labels.shape) or not self._stamp_ok(topic, stamp):
                return
            if self._last_frame_ns is not None and stamp <= self._last_frame_ns:
                self._stale_run += 1
                if self._stale_run < STAMP_RESET_COUNT:
                    self.warn(topic, "stamp out of order",
                              f"{(self._last_frame_ns - stamp) * 1e-9:.3f} s older than the last frame; dropped")
                    return
                self.get_logger().warning(
                    f"[{topic}] {self._stale_run} consecutive stamps older than the last frame: assuming the "
                    f"clock was reset (bag restarted?), accepting the new stamps")
                old_last = self._last_frame_ns
                self._last_frame_ns = None
                self._stale_run = 0
                self._images.clear()
                self.sync = self._make_sync(self._sync_kinds)
                # The poses / confidences of the new time line were refused as stale: offer them again
                # (those still stamped after the old last frame belong to the old time line).
                slop = int(round(self.p.sync_slop * 1e9))
                for kind, recent in self._recent.items():
                    for t, payload in sorted(recent, key=lambda e: e[0]):
                        if stamp - slop <= t < old_last:
                            self.sync.push(kind, t, payload)
                self._sync_counts = Counter(self.sync.counts)
            else:
                self._stale_run = 0
            if "confidence" in self._sync_kinds and not self._confidence_published():
                # Nobody publishes confidence: complete the frame with "no confidence" (weight 1).
                self._push("confidence", "segmentation_confidence", stamp, None)
            self._push("segmentation", topic, stamp, (labels, msg.header.frame_id, time.monotonic()))

        def _push(self, kind: str, topic: str, stamp: int, payload: Any) -> None:
            if kind != "segmentation":
                self._recent[kind].append((stamp, payload))
            frames = self.sync.push(kind, stamp, payload)
            # Report what the synchroniser dropped (stale, unmatched, overflow) under the topic concerned.
            counts = self.sync.counts
            for key, value in counts.items():
                n = value - self._sync_counts.get(key, 0)
                if n <= 0 or key == "frames" or key.startswith("reordered_"):
                    continue
                if key == "unmatched":
                    others = "pose" + (" or segmentation_confidence" if "confidence" in self._sync_kinds
                                       and self._confidence_published() else "")
                    self.warn("segmentation", "no matching stamp",
                              f"no {others} within sync_slop={self.p.sync_slop:g} s of the segmentation; "
                              "frame dropped")
                elif key == "overflow_confidence" and not self._confidence_published():
                    continue  # placeholders of segmentations that never matched a pose
                else:
                    what, _, k = key.partition("_")
                    name = {"confidence": "segmentation_confidence"}.get(k, k)
                    reason = {"stale": "stamp older than the last frame",
                              "overflow": "synchroniser buffer full"}.get(what, what)
                    self.warn(name, reason, "dropped")
            self._sync_counts = Counter(counts)
            for frame in frames:
                self._enqueue_frame(frame)

        def _enqueue_frame(self, frame: Any) -> None:
            info = self._camera_info
            labels, frame_id, t_recv = frame.items["segmentation"]
            position, quat_in, quat_opt = frame.items["pose"]
            if info is None:
                self.warn("segmentation", "no camera_info received yet", "frame dropped")
                return
            sizes = [("segmentation", labels.shape)]
            if frame.items.get("confidence") is not None:
                sizes.append(("segmentation_confidence", frame.items["confidence"].shape))
            for topic, shape in sizes:
                if shape[:2] != (info[2], info[1]):
                    self.warn(topic, "size mismatch with camera_info",
                              f"image {shape[1]}x{shape[0]}, camera_info {info[1]}x{info[2]}; frame dropped")
                    return
            self._last_frame_ns = frame.stamp_ns
            image = None
            slop = self.p.sync_slop * 1e9
            best = None
            for stamp, rgb in self._images:
                d = abs(stamp - frame.stamp_ns)
                if d <= slop and (best is None or d < best[0]):
                    best = (d, rgb)
            if best is not None and best[1].shape[:2] == labels.shape:
                image = best[1]
            job = FrameJob(frame.stamp_ns, frame_id, labels, frame.items.get("confidence"), image,
                           info[0], position, quat_in, quat_opt, t_recv)
            self._count("frames_synchronised")
            dropped = self.queue.put_frame(job)
            if dropped is not None:
                self._count("frames_dropped_busy")
                self.warn("worker", "busy", "mapping slower than the input: oldest pending frame dropped "
                                            "(newest frames win)")

        def _on_candidates(self, msg: Any) -> None:
            topic = "candidates"
            info = self._camera_info
            m = len(msg.poses)
            if info is None:
                # Answer anyway (NaN scores) so that a client waiting for this request id is not left hanging.
                self.warn(topic, "no camera_info received yet", "cannot render: answered with NaN scores",
                          dropped=False)
                positions = np.array([pose_to_arrays(p)[0] for p in msg.poses]).reshape(m, 3)
                quats = np.array([pose_to_arrays(p)[1] for p in msg.poses]).reshape(m, 4)
                nan = np.full(m, np.nan)
                self.pubs["candidate_scores"].publish(
                    rc.view_points_msg(rc.copy_header(msg.header), positions, quats, nan, nan))
                return
            if m > self.p.max_candidates:
                self.warn(topic, "too many candidates", f"{m} > max_candidates={self.p.max_candidates}; "
                                                        "request dropped")
                return
            if msg.header.frame_id and msg.header.frame_id.lstrip("/") != self.p.map_frame:
                self.warn(topic, "frame_id differs from map_frame",
                          f"'{msg.header.frame_id}' != '{self.p.map_frame}' (no tf here): used as map frame",
                          dropped=False)
            positions = np.zeros((m, 3))
            quats = np.zeros((m, 4))
            optical = np.full((m, 4), np.nan)
            bad = 0
            for i, pose in enumerate(msg.poses):
                positions[i], quats[i] = pose_to_arrays(pose)
                if not np.all(np.isfinite(positions[i])) or check_quaternion(quats[i]) is not None:
                    bad += 1
                    continue
                q = quats[i] / np.linalg.norm(quats[i])
                optical[i] = body_to_optical(q, self._q_b2o) if self.p.body_to_optical else q
            if bad:
                self.warn(topic, "invalid candidate poses", f"{bad} of {m} non-finite or non-unit: scored NaN",
                          dropped=False)
            header = rc.copy_header(msg.header)
            job = CandidateJob(header, info[0], info[1], info[2], positions, quats, optical, time.monotonic())
            self._count("requests_received")
            if self.queue.put_request(job) is not None:
                self._count("requests_dropped_busy")
                self.warn(topic, "request queue full", "oldest pending request dropped")

        # ------------------------------------------------------------------ services
        def _on_save_map(self, request: Any, response: Any) -> Any:
            path = self._checkpoint_path()
            if path is None:
                response.success, response.message = False, "checkpoint_path is empty: saving is disabled"
                return response
            try:
                dt = self._save(path)
                response.success = True
                response.message = f"saved {self.smap.model.num_gaussians}x{self.C} concentrations to {path} " \
                                   f"in {dt:.2f} s"
            except (MapError, OSError) as exc:
                response.success, response.message = False, f"saving {path} failed: {exc}"
                self.get_logger().error(response.message)
            return response

        def _on_reset_map(self, request: Any, response: Any) -> Any:
            with self._map_lock:
                self.smap.reset()
                self._dirty += 1
            self._count("resets")
            response.success = True
            response.message = f"all {self.smap.model.num_gaussians} Gaussians reset to the prior"
            self.get_logger().info(response.message)
            return response

        def _save(self, path: Path) -> float:
            t0 = time.perf_counter()
            path.parent.mkdir(parents=True, exist_ok=True)
            with self._map_lock:
                self.smap.save(path)
                self._dirty = 0
            self._last_save = time.monotonic()
            self._count("checkpoints")
            return time.perf_counter() - t0

        def save_checkpoint(self, reason: str) -> None:
            """Save the map to checkpoint_path (if set and changed since the last save)."""
            path = self._checkpoint_path()
            if path is None or not self._dirty:
                return
            try:
                dt = self._save(path)
                self.get_logger().info(f"checkpoint ({reason}) written to {path} in {dt:.2f} s")
            except (MapError, OSError) as exc:
                self.get_logger().error(f"checkpoint ({reason}) to {path} failed: {exc}")

        # ------------------------------------------------------------------ worker
        def _work_loop(self) -> None:
            while not self.queue.closed:
                job = self.queue.get(timeout=0.5)
                try:
                    if isinstance(job, FrameJob):
                        self._process_frame(job)
                    elif isinstance(job, CandidateJob):
                        self._process_request(job)
                except Exception as exc:  # noqa: BLE001 - the worker must survive anything one frame does
                    self._count("worker_errors")
                    self.warn("worker", "processing failed", f"{type(exc).__name__}: {exc}")
                period = self.p.checkpoint_period
                if period > 0 and self._dirty and time.monotonic() - self._last_save >= period:
                    self.save_checkpoint("periodic")

        def _process_frame(self, job: FrameJob) -> None:
            p = self.p
            try:
                cam = Camera.from_pose(job.K, job.labels.shape[1], job.labels.shape[0], job.position,
                                       job.quat_optical)
            except CameraError as exc:
                self.warn("pose", "invalid camera", f"{exc}; frame dropped")
                return
            labels = job.labels
            valid = labels != p.ignore_label
            out_of_range = int(np.count_nonzero(valid & (labels >= self.C)))
            if out_of_range:
                self._count("label_pixels_out_of_range", out_of_range)
                self.warn("segmentation", "class ids >= num_classes",
                          f"{out_of_range} pixels with ids >= {self.C} (max {int(labels.max())}) treated as "
                          "no label", dropped=False)
            with self._map_lock:
                if p.output_scale == 1.0:
                    view = self.smap.observe(cam, labels, confidence=job.confidence)
                else:
                    self.smap.update(cam, labels, confidence=job.confidence)
                    view = self.smap.render(cam.scaled(p.output_scale))
                self._dirty += 1
            self._publish_view(job, view)
            if job.image is not None and view.rgb.shape == job.image.shape:
                self._last_psnr = psnr(view.rgb, job.image)
            self._last_u = (float(view.u_var), float(view.u_exp))
            with self._stats_lock:
                self.stats["frames_processed"] += 1
                self._frame_ms.append((time.monotonic() - job.t_received) * 1e3)

        def _publish_view(self, job: FrameJob, view: Any) -> None:
            header = rc.header_msg(job.stamp_ns, job.frame_id)
            pubs = self.pubs
            if "semantic" in pubs:
                pubs["semantic"].publish(rc.image_msg(view.labels, self._label_encoding, header))
            if "semantic_color" in pubs:
                color = self.classes.colorize(view.labels, ignore_label=self.p.ignore_label)
                pubs["semantic_color"].publish(rc.image_msg(color, "rgb8", header))
            if "expectation" in pubs:
                pubs["expectation"].publish(rc.image_msg(view.expectation, "32FC1", header))
            if "variance" in pubs:
                pubs["variance"].publish(rc.image_msg(view.variance, "32FC1", header))
            if "rendered_image" in pubs:
                pubs["rendered_image"].publish(rc.image_msg(view.rgb, "rgb8", header))
            if "view_uncertainty" in pubs:
                cloud = rc.view_points_msg(rc.header_msg(job.stamp_ns, self.p.map_frame), job.position[None],
                                           job.quat_in[None], np.array([view.u_var]), np.array([view.u_exp]))
                pubs["view_uncertainty"].publish(cloud)

        def _process_request(self, job: CandidateJob) -> None:
            m = len(job.positions)
            u_var = np.full(m, np.nan)
            u_exp = np.full(m, np.nan)
            base = None
            cams, scored = [], []
            for i in range(m):
                if not np.all(np.isfinite(job.quats_optical[i])):
                    continue
                try:
                    cam = Camera.from_pose(job.K, job.width, job.height, job.positions[i], job.quats_optical[i])
                    if base is None:
                        base = cam.scaled(self.p.candidate_scale)
                    cams.append(Camera(K=base.K, width=base.width, height=base.height, T_map_cam=cam.T_map_cam))
                    scored.append(i)
                except CameraError as exc:
                    self.warn("candidates", "invalid candidate pose", f"{exc}; scored NaN", dropped=False)
            if cams:
                with self._map_lock:
                    scores = self.smap.score_views(cams)
                u_var[scored], u_exp[scored] = scores[:, 0], scores[:, 1]
            self.pubs["candidate_scores"].publish(
                rc.view_points_msg(job.header, job.positions, job.quats_in, u_var, u_exp))
            with self._stats_lock:
                self.stats["requests_served"] += 1
                self.stats["candidate_views"] += m
                self._request_ms.append((time.monotonic() - job.t_received) * 1e3)

        # ------------------------------------------------------------------ status
        def status(self) -> dict[str, Any]:
            """Counters and rates (also published as diagnostics)."""
            with self._stats_lock:
                stats = dict(self.stats)
                frame_ms = list(self._frame_ms)
                req_ms = list(self._request_ms)
            problems, dropped = self.warn.snapshot()
            now = time.monotonic()
            t_last, n_last = self._last_log
            processed = stats.get("frames_processed", 0)
            rate = (processed - n_last) / max(now - t_last, 1e-9)
            pending = self.queue.sizes()
            out: dict[str, Any] = {
                **stats,
                "frames_processed": processed,
                "rate_hz": rate,
                "pending_frames": pending[0],
                "pending_requests": pending[1],
                "frame_latency_ms_median": float(np.median(frame_ms)) if frame_ms else float("nan"),
                "request_latency_ms_median": float(np.median(req_ms)) if req_ms else float("nan"),
                "last_u_var": self._last_u[0],
                "last_u_exp": self._last_u[1],
                "last_psnr_db": self._last_psnr,
            }
            out.update({f"dropped[{k}]": v for k, v in dropped.items()})
            out.update({f"warn[{k}]": v for k, v in problems.items()})
            return out

        def _on_log_timer(self) -> None:
            s = self.status()
            self._last_log = (time.monotonic(), s["frames_processed"])
            dropped = {k[8:-1]: v for k, v in s.items() if k.startswith("dropped[")}
            problems = {k[5:-1]: v for k, v in s.items() if k.startswith("warn[")}
            new = {k: v - self._last_problems.get(k, 0) for k, v in problems.items()
                   if v != self._last_problems.get(k, 0)}
            self._last_problems = problems
            if s["frames_processed"] == 0 and not s.get("requests_served") and not new:
                self.get_logger().info(
                    "waiting for input: no frame yet (needs segmentation and pose with matching stamps, "
                    "segmentation_confidence too while it has a publisher, and camera_info); segmentations "
                    f"received {s.get('segmentations_received', 0)}")
            else:
                self.get_logger().info(
                    f"frames processed {s['frames_processed']} ({s['rate_hz']:.2f} Hz, median latency "
                    f"{s['frame_latency_ms_median']:.0f} ms), pending {s['pending_frames']}, dropped "
                    f"{dropped or 0}; candidate requests served {s.get('requests_served', 0)} (median "
                    f"{s['request_latency_ms_median']:.0f} ms); last U_var {s['last_u_var']:.4g} "
                    f"U_exp {s['last_u_exp']:.4g}; PSNR {s['last_psnr_db']:.1f} dB"
                    + (f"; new input problems: {new}" if new else ""))
            if self._diag_pub is not None:
                DiagnosticArray, DiagnosticStatus, KeyValue = self._diag_types
                level = DiagnosticStatus.WARN if new else DiagnosticStatus.OK
                st = DiagnosticStatus(level=level, name=f"{self.get_name()}: semantic map",
                                      message="; ".join(new) if new else "ok", hardware_id=str(self.model_path))
                st.values = [KeyValue(key=str(k), value=f"{v:.6g}" if isinstance(v, float) else str(v))
                             for k, v in s.items()]
                arr = DiagnosticArray(status=[st])
                arr.header.stamp = self.get_clock().now().to_msg()
                self._diag_pub.publish(arr)

        def shutdown(self) -> None:
            """Stop the worker and write a final checkpoint."""
            self.queue.close()
            self._worker.join(timeout=30.0)
            self.save_checkpoint("shutdown")

    return CssNode


def main(args: Sequence[str] | None = None) -> int:
    """Console entry point ``css_node``; returns the process exit code.

    SIGINT / SIGTERM stop the node cleanly: the worker finishes its job and a final checkpoint is written
    before the ROS context shuts down.
    """
    import signal

    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as exc:  # noqa: BLE001 - rcl reports bad --ros-args as a generic RCLError
        print(f"{NODE_NAME}: cannot initialise ROS (check the --ros-args): {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    node = None
    try:
        try:
            node = _make_node_class()()
        except CssError as exc:  # ModelError, MapError, bad parameters, class file
            rclpy.logging.get_logger(NODE_NAME).fatal(f"cannot start: {exc}")
            return 2
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        while not stop.is_set() and rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.get_logger().info("shutting down")
            node.shutdown()
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
