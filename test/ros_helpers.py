"""Helpers for the css_node tests: a tiny scene, the node as a subprocess, and an rclpy test client."""
from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

REPO = Path(__file__).resolve().parents[1]
_domain_counter = itertools.count()

# Scene: a wall of Gaussians 3 m in front of a camera at the origin looking along +z of the map
# (identity quaternion = optical frame aligned with the map). Left half class 1, right half class 2.
WIDTH, HEIGHT = 48, 36
K = np.array([[40.0, 0.0, (WIDTH - 1) / 2], [0.0, 40.0, (HEIGHT - 1) / 2], [0.0, 0.0, 1.0]])
NUM_CLASSES = 4
IDENTITY = np.array([0.0, 0.0, 0.0, 1.0])

#: the least time [s] a test waits for a started css_node to be connected (see RosClient.wait_connected)
NODE_START_S = 180.0
#: seconds a service request may go unanswered before the test client sends it again (RosClient.call)
SERVICE_ATTEMPT_S = 20.0


def next_domain_id() -> int:
    """A ROS_DOMAIN_ID unique within this process and unlikely to clash with other runs.

    By default in 1..101; ``CSS_TEST_DOMAINS=FIRST:COUNT`` confines it to FIRST..FIRST+COUNT-1 so that test runs
    started side by side on one host (several checkouts) never share a DDS domain. Under pytest-xdist the range
    is cut into one disjoint slice per worker (``PYTEST_XDIST_WORKER`` gwK of ``PYTEST_XDIST_WORKER_COUNT``), so
    tests running at the same time in two workers never share a domain either.
    """
    first, count = (int(v) for v in os.environ.get("CSS_TEST_DOMAINS", "1:101").split(":"))
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
    if workers > 1 and worker[2:].isdigit():
        count //= workers
        first += int(worker[2:]) * count
    return first + (os.getpid() * 7 + next(_domain_counter) * 37) % count


class BusyLoops:
    """``n`` processes spinning a CPU each (``while True: pass``) while in the ``with`` block: the load of a robot's
    computer, where SLAM, planners and a segmentation network share the cores with css_node. Ended by their pids."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.procs: list[subprocess.Popen] = []

    def __enter__(self) -> "BusyLoops":
        self.procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(self.n)]
        return self

    def __exit__(self, *exc: Any) -> None:
        for proc in self.procs:
            proc.kill()
            proc.wait(10)


def write_wall_model(path: Path, seed: int = 0, depth: float = 3.0) -> Path:
    """Write a PLY with a 20 x 16 grid of opaque Gaussians on the plane z = depth (map frame, metres)."""
    from css_ros.engine.gaussians import GaussianModel

    rng = np.random.default_rng(seed)
    xs, ys = np.meshgrid(np.linspace(-2.2, 2.2, 20), np.linspace(-1.7, 1.7, 16))
    n = xs.size
    means = np.c_[xs.ravel(), ys.ravel(), np.full(n, depth)]
    model = GaussianModel.from_activated(means, np.full((n, 3), 0.15), np.tile([1.0, 0, 0, 0], (n, 1)),
                                         np.full(n, 0.95), rng.uniform(0.1, 0.9, (n, 3)))
    model.to_ply(path)
    return path


def wall_labels(width: int = WIDTH, height: int = HEIGHT) -> np.ndarray:
    """Ground-truth segmentation of the wall seen from the origin: class 1 left of centre, 2 right."""
    labels = np.full((height, width), 2, dtype=np.uint8)
    labels[:, : width // 2] = 1
    return labels


def node_env(domain_id: int) -> dict[str, str]:
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(domain_id)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    env["PYTHONUNBUFFERED"] = "1"
    env["RCUTILS_COLORIZED_OUTPUT"] = "0"
    return env


class NodeProcess:
    """css_node running as a subprocess (``python -m css_ros.node --ros-args -p ...``); log in a file."""

    def __init__(self, params: dict[str, Any], domain_id: int, log_path: Path,
                 remaps: dict[str, str] | None = None) -> None:
        args = [sys.executable, "-m", "css_ros.node", "--ros-args"]
        for key, value in params.items():
            if isinstance(value, bool):
                value = "true" if value else "false"
            elif isinstance(value, str) and value == "":
                value = "''"
            args += ["-p", f"{key}:={value}"]
        for src, dst in (remaps or {}).items():
            args += ["-r", f"{src}:={dst}"]
        self.log_path = log_path
        self._log = open(log_path, "ab")
        self.proc = subprocess.Popen(args, env=node_env(domain_id), stdout=self._log, stderr=subprocess.STDOUT,
                                     cwd=str(log_path.parent))

    @property
    def pid(self) -> int:
        return self.proc.pid

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def wait_log(self, text: str, timeout: float = 60.0) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if text in self.log():
                return True
            if self.proc.poll() is not None:
                return text in self.log()
            time.sleep(0.1)
        return False

    def rss_mb(self) -> float:
        """Resident set size of the node process [MB] (from /proc)."""
        for line in Path(f"/proc/{self.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
        return float("nan")

    def kill9(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(10)
        self._log.close()

    def stop(self, timeout: float = 20.0) -> int:
        """SIGINT, then SIGKILL after ``timeout`` s; returns the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self._log.close()
        return self.proc.returncode


class RosClient:
    """An rclpy node on its own context/domain with an executor thread; records every output message."""

    OUTPUTS = ("semantic", "semantic_color", "expectation", "variance", "rendered_image", "view_uncertainty",
               "candidate_scores")

    def __init__(self, domain_id: int, node_ns: str = "/css_node", input_reliable: bool = True,
                 topics: dict[str, str] | None = None) -> None:
        """``node_ns``: css_node's full name (outputs live below it); ``topics``: input topic names by kind."""
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseArray, PoseStamped
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import CameraInfo, Image, PointCloud2
        from std_srvs.srv import Trigger

        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node(f"css_test_client_{os.getpid()}", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.lock = threading.Lock()
        self.received: dict[str, list[Any]] = {name: [] for name in (*self.OUTPUTS, "diagnostics")}
        qos_in = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE if input_reliable
                            else ReliabilityPolicy.BEST_EFFORT)
        self.topics = {k: k for k in ("image", "segmentation", "segmentation_confidence", "camera_info", "pose",
                                      "candidates")}
        self.topics.update(topics or {})
        self.node_ns = node_ns
        t = self.topics
        self.pub = {
            "image": self.node.create_publisher(Image, t["image"], qos_in),
            "segmentation": self.node.create_publisher(Image, t["segmentation"], qos_in),
            "camera_info": self.node.create_publisher(CameraInfo, t["camera_info"], qos_in),
            "pose": self.node.create_publisher(PoseStamped, t["pose"], qos_in),
            "candidates": self.node.create_publisher(PoseArray, t["candidates"], 10),
        }
        self._conf_pub = None
        self._qos_in = qos_in
        qos_out = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        self.subs: dict[str, Any] = {}
        for name in self.OUTPUTS:
            typ = PointCloud2 if name in ("view_uncertainty", "candidate_scores") else Image
            self.subs[name] = self.node.create_subscription(typ, f"{node_ns}/{name}", self._recorder(name), qos_out)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._recorder("diagnostics"), qos_out)
        self.save_client = self.node.create_client(Trigger, f"{node_ns}/save_map")
        self.reset_client = self.node.create_client(Trigger, f"{node_ns}/reset_map")
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        from rclpy.executors import ExternalShutdownException

        try:
            while self.context.ok():
                self.executor.spin_once(timeout_sec=0.05)
        except (ExternalShutdownException, Exception):  # noqa: BLE001 - shutting down
            pass

    def _recorder(self, name: str) -> Callable[[Any], None]:
        def record(msg: Any) -> None:
            with self.lock:
                self.received[name].append(msg)
        return record

    def confidence_publisher(self) -> Any:
        from sensor_msgs.msg import Image

        if self._conf_pub is None:
            self._conf_pub = self.node.create_publisher(Image, self.topics["segmentation_confidence"], self._qos_in)
        return self._conf_pub

    def close(self) -> None:
        import rclpy

        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
        self._thread.join(5.0)

    # ---------------------------------------------------------------- waiting
    def messages(self, name: str) -> list[Any]:
        with self.lock:
            return list(self.received[name])

    def clear(self) -> None:
        with self.lock:
            for v in self.received.values():
                v.clear()

    @staticmethod
    def wait_until(cond: Callable[[], Any], timeout: float, period: float = 0.02) -> Any:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            value = cond()
            if value:
                return value
            time.sleep(period)
        return cond()

    def wait_connected(self, timeout: float = 30.0) -> bool:
        """Wait until the node subscribes to our inputs and publishes the outputs we listen to, matched at both ends:
        our readers have matched its writers, and its diagnostics (published by the node whenever a subscriber of an
        output matches) count at least as many subscribers of each output as this client knows of. Without the
        node's side, an output published before its writer matched this reader is lost on a loaded host.

        A node's start on a fresh clone includes numba's first compiles, which on a loaded 2-core host can take more
        than a minute: the wait is at least NODE_START_S [s] (it returns as soon as the node is up)."""
        timeout = max(timeout, NODE_START_S)
        outputs = ("semantic", "view_uncertainty", "candidate_scores")

        def ok() -> bool:
            subs = all(p.get_subscription_count() > 0 for p in self.pub.values())
            # matched (not only discovered): css_node's outputs come from another participant than its inputs
            pubs = all(self.subs[n].get_publisher_count() > 0 for n in outputs)
            return subs and pubs and self.outputs_heard(outputs) and self.save_client.service_is_ready()
        return bool(self.wait_until(ok, timeout, 0.05))

    def outputs_heard(self, outputs: tuple[str, ...]) -> bool:
        """The node's writers of ``outputs`` (names below the node, e.g. ``view_uncertainty``) have matched every
        subscriber of them this client knows of (its own included): its diagnostics ``subscribers[<output>]``,
        published by the node whenever one matches, count at least that many."""
        diag = self.diagnostics()
        return all(int(diag.get(f"subscribers[{n}]", 0)) >= self.node.count_subscribers(f"{self.node_ns}/{n}")
                   for n in outputs)

    def wait_outputs_heard(self, outputs: tuple[str, ...], timeout: float = 30.0) -> bool:
        """Wait until :meth:`outputs_heard` (after creating a subscriber of an output, before the frames it must
        see: an answer published before the node's writer matched it is lost)."""
        return bool(self.wait_until(lambda: self.outputs_heard(outputs), timeout, 0.05))

    def wait_stamp(self, name: str, stamp_ns: int, timeout: float = 20.0) -> Any:
        """The first message on output ``name`` whose header stamp equals ``stamp_ns`` (or None)."""
        from css_ros.io.messages import stamp_to_ns

        def find() -> Any:
            for m in self.messages(name):
                if stamp_to_ns(m.header.stamp) == stamp_ns:
                    return m
            return None
        return self.wait_until(find, timeout)

    def diagnostics(self) -> dict[str, str]:
        """Key/values of the latest diagnostics status of css_node (empty if none yet)."""
        for arr in reversed(self.messages("diagnostics")):
            for st in arr.status:
                if st.name.startswith(f"{self.node_ns}: "):   # this node's (several may share the domain)
                    return {kv.key: kv.value for kv in st.values}
        return {}

    def wait_diag(self, key: str, at_least: float, timeout: float = 20.0) -> float:
        """Wait until diagnostics report ``key`` >= ``at_least``; return the last value seen (0 if absent)."""
        def value() -> float:
            return float(self.diagnostics().get(key, 0))
        self.wait_until(lambda: value() >= at_least, timeout, 0.1)
        return value()

    def call(self, client: Any, timeout: float = 90.0) -> Any:
        """Call a Trigger service of the node (save_map, reset_map, load_map) and return its response. A request
        whose answer has not come after SERVICE_ATTEMPT_S is sent again: an answer written before the node's response
        writer matched this client's reader is lost on a loaded host, and each of these services does the same thing
        when called twice."""
        from std_srvs.srv import Trigger

        if not client.wait_for_service(timeout_sec=timeout):
            raise TimeoutError("service not available")
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            future = client.call_async(Trigger.Request())
            attempt_end = min(end, time.monotonic() + SERVICE_ATTEMPT_S)
            while not future.done() and time.monotonic() < attempt_end:
                time.sleep(0.02)
            if future.done():
                return future.result()
            remove = getattr(client, "remove_pending_request", None)
            if remove is not None:
                remove(future)
        raise TimeoutError("service call timed out")

    # ---------------------------------------------------------------- sending
    def send_camera_info(self, stamp_ns: int = 0, K_: np.ndarray = K, width: int = WIDTH,
                         height: int = HEIGHT) -> None:
        from css_ros.ros.conversions import camera_info_msg, header_msg

        self.pub["camera_info"].publish(camera_info_msg(K_, width, height, header_msg(stamp_ns, "camera")))

    def send_pose(self, stamp_ns: int, position: Any = (0.0, 0.0, 0.0), quat: Any = IDENTITY,
                  frame_id: str = "map") -> None:
        from css_ros.ros.conversions import header_msg, pose_stamped_msg

        self.pub["pose"].publish(pose_stamped_msg(position, quat, header_msg(stamp_ns, frame_id)))

    def send_image(self, topic: str, stamp_ns: int, array: np.ndarray, encoding: str,
                   overrides: dict[str, Any] | None = None) -> None:
        """Publish ``array`` as an Image; ``overrides`` sets raw message fields afterwards (bad input)."""
        from css_ros.ros.conversions import header_msg, image_msg

        msg = image_msg(array, encoding, header_msg(stamp_ns, "camera"))
        for key, value in (overrides or {}).items():
            setattr(msg, key, value)
        pub = self.confidence_publisher() if topic == "segmentation_confidence" else self.pub[topic]
        pub.publish(msg)

    def send_frame(self, stamp_ns: int, labels: np.ndarray | None = None, position: Any = (0.0, 0.0, 0.0),
                   quat: Any = IDENTITY, rgb: np.ndarray | None = None) -> None:
        """camera_info, pose, (image) and segmentation with one stamp."""
        labels = wall_labels() if labels is None else labels
        self.send_camera_info(stamp_ns, width=labels.shape[1], height=labels.shape[0],
                              K_=K if labels.shape == (HEIGHT, WIDTH) else scaled_K(labels.shape))
        self.send_pose(stamp_ns, position, quat)
        if rgb is not None:
            self.send_image("image", stamp_ns, rgb, "rgb8")
        self.send_image("segmentation", stamp_ns, labels, "mono8")

    def send_frame_until_processed(self, stamp_ns: int, labels: np.ndarray | None = None,
                                   position: Any = (0.0, 0.0, 0.0), quat: Any = IDENTITY, output: str = "semantic",
                                   first_timeout: float = 60.0, retry_timeout: float = 15.0, attempts: int = 3) -> Any:
        """Send a frame and wait for its ``output``; send it again if it was lost (best-effort inputs can go out
        before the node's reader has matched this writer). A copy that arrives after the first was processed is
        dropped by the node as out of order, so the map never takes a frame twice. The first wait allows a
        kernel compile (nodes started with ``warmup: false``). Returns the output message (None if none came)."""
        deadline = time.monotonic() + first_timeout   # resends of frames never received, until then
        k = 0
        while True:
            seen, before = len(self.messages("diagnostics")), self._segmentations_received()
            self.send_frame(stamp_ns, labels, position, quat)
            if time.monotonic() < deadline and self._lost(seen, before, output, stamp_ns):
                continue
            msg = self.wait_stamp(output, stamp_ns, first_timeout if k == 0 else retry_timeout)
            if msg is not None:
                return msg
            k += 1
            if k >= attempts:
                return None

    def _segmentations_received(self) -> float:
        return float(self.diagnostics().get("segmentations_received", 0))

    def _lost(self, seen: int, before: float, output: str, stamp_ns: int, statuses: int = 3,
              no_diagnostics_s: float = 10.0) -> bool:
        """True when ``statuses`` diagnostics of the node published after the send still count no new segmentation
        (the frame went out before the node's reader had matched this writer: send it again now); False when the
        output came, the count grew, or no diagnostics of the node came within ``no_diagnostics_s`` (then only
        the long wait can tell). ``seen``: diagnostics messages received before the send."""
        def mine() -> int:
            return sum(1 for arr in self.messages("diagnostics")[seen:] for st in arr.status
                       if st.name.startswith(f"{self.node_ns}: "))
        end = time.monotonic() + no_diagnostics_s
        while True:
            if self.wait_stamp(output, stamp_ns, 0.05) is not None or self._segmentations_received() > before:
                return False
            n = mine()
            if n >= statuses:
                return True
            if n == 0 and time.monotonic() > end:
                return False

    def send_candidates(self, stamp_ns: int, positions: np.ndarray, quats: np.ndarray,
                        frame_id: str = "map") -> None:
        from css_ros.ros.conversions import header_msg, pose_array_msg

        self.pub["candidates"].publish(pose_array_msg(positions, quats, header_msg(stamp_ns, frame_id)))


def scaled_K(shape: tuple[int, int]) -> np.ndarray:
    """Intrinsics of the test camera for an image of ``shape`` (H, W) with the same field of view."""
    h, w = shape
    s = w / WIDTH
    return np.array([[K[0, 0] * s, 0, (w - 1) / 2], [0, K[1, 1] * s, (h - 1) / 2], [0, 0, 1]])


def yaw_quat(angle: float) -> np.ndarray:
    """(x, y, z, w) rotation by ``angle`` [rad] about the optical y axis (= map y here): turns the view."""
    return np.array([0.0, np.sin(angle / 2), 0.0, np.cos(angle / 2)])
