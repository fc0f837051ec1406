"""css_node with hardware-synchronised cameras over real DDS: two cameras publish image, camera_info, confidence
and segmentation with the same stamp, back to back (demo resolution 256x192: about 0.8 MB per burst, more than
Fast DDS's default shared-memory segment), at 1 Hz with the pose at the frame stamps and at 10 Hz with poses at
200 Hz between the frames. Each camera must keep >= 99 % of its frames (docs/reliability.md,
"Synchronised cameras"); the transport choice that makes it so (css_ros/ros/transport.py)."""
from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import ros_helpers as rh

CAMERAS = ("camA", "camB")
W, H = 256, 192


class SyncClient:
    """Publishers of two synchronised cameras and one pose stream; reads css_node's /diagnostics."""

    def __init__(self, domain_id: int) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import CameraInfo, Image

        from css_ros.clients.node_link import NodeLink
        from css_ros.ros.conversions import camera_info_msg, header_msg, image_msg, pose_stamped_msg, time_msg

        self.link = NodeLink("css_sync_client", start=False, domain_id=domain_id)
        self.node = self.link.node
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        self.pubs: list[list[Any]] = []
        self.msgs: list[list[Any]] = []
        labels = rh.wall_labels(W, H)
        rgb = np.zeros((H, W, 3), dtype=np.uint8)
        rgb[..., 0] = 200
        conf = np.full((H, W), 0.8, dtype=np.float32)
        for ns in CAMERAS:  # in the order a driver publishes them
            self.pubs.append([self.node.create_publisher(Image, f"{ns}/image", qos),
                              self.node.create_publisher(CameraInfo, f"{ns}/camera_info", qos),
                              self.node.create_publisher(Image, f"{ns}/segmentation_confidence", qos),
                              self.node.create_publisher(Image, f"{ns}/segmentation", qos)])
            hdr = header_msg(0, f"{ns}_optical")
            self.msgs.append([image_msg(rgb, "rgb8", hdr), camera_info_msg(rh.scaled_K((H, W)), W, H, hdr),
                              image_msg(conf, "32FC1", hdr), image_msg(labels, "mono8", hdr)])
        self.pose_pub = self.node.create_publisher(PoseStamped, "pose", qos)
        self.pose = pose_stamped_msg((0.0, 0.0, 0.0), rh.IDENTITY, header_msg(0, "map"))
        self._time_msg = time_msg
        self.lock = threading.Lock()
        self.diag: dict[str, str] = {}
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 10)
        self.link.start()

    def _on_diag(self, msg: Any) -> None:
        for st in msg.status:
            if st.name.startswith("css_node"):
                with self.lock:
                    self.diag = {kv.key: kv.value for kv in st.values}

    def diagnostics(self) -> dict[str, str]:
        with self.lock:
            return dict(self.diag)

    def connected(self) -> bool:
        return all(p.get_subscription_count() > 0 for cam in self.pubs for p in cam) and \
            self.pose_pub.get_subscription_count() > 0

    def send_burst(self, stamp_ns: int) -> None:
        """Both cameras' image, camera_info, confidence and segmentation with one stamp, back to back."""
        stamp = self._time_msg(stamp_ns)
        for pubs, msgs in zip(self.pubs, self.msgs):
            for pub, msg in zip(pubs, msgs):
                msg.header.stamp = stamp
                pub.publish(msg)

    def send_pose(self, stamp_ns: int) -> None:
        self.pose.header.stamp = self._time_msg(stamp_ns)
        self.pose_pub.publish(self.pose)

    def close(self) -> None:
        self.link.close()


def stream(client: SyncClient, fps: float, frames: int, pose_rate: float) -> None:
    """Publish in real time: ``frames`` same-stamp bursts at ``fps``; pose_rate 0: one pose at each frame stamp
    right after the burst; else poses at ``pose_rate`` between the frame stamps (from 0.1 s before the first to
    0.3 s after the last frame)."""
    t0 = time.monotonic()
    s0 = time.time_ns()
    events = [(i / fps, "frame") for i in range(frames)]
    if pose_rate > 0:
        first = -int(0.1 * pose_rate)  # from 0.1 s before the first frame: it is bracketed by this stream's poses
        events += [((k + 0.5) / pose_rate, "pose") for k in range(first, int(((frames - 1) / fps + 0.3) * pose_rate))]
    events.sort(key=lambda e: e[0])
    for t, kind in events:
        delay = t0 + t - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        stamp = s0 + int(round(t * 1e9))
        if kind == "frame":
            client.send_burst(stamp)
            if pose_rate == 0:
                client.send_pose(stamp)
        else:
            client.send_pose(stamp)


@pytest.mark.slow
def test_synchronised_cameras_keep_every_frame(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Two cameras, same stamps back to back: each keeps >= 99 % of its frames at 1 Hz (pose at the frame stamps)
    and at 10 Hz (200 Hz poses between frames), counted from css_node's per-camera diagnostics, with the node
    receiving over UDP (CSS_NODE_TRANSPORT=udp, the setting docs/reliability.md gives for synchronised rigs)."""
    monkeypatch.setenv("CSS_NODE_TRANSPORT", "udp")
    domain = rh.next_domain_id()
    model = rh.write_wall_model(tmp_path / "wall.ply")
    node = rh.NodeProcess(dict(model_path=str(model), class_file="", num_classes=rh.NUM_CLASSES, checkpoint_path="",
                               resume=False, log_period=0.5, warn_period=0.0, cameras=list(CAMERAS),
                               max_pending_frames=64), domain, tmp_path / "node.log")
    client = SyncClient(domain)
    try:
        wait = rh.RosClient.wait_until
        assert wait(lambda: node.wait_log("inputs (", 0.1) and client.connected(), 60.0), node.log()
        time.sleep(1.0)  # the node's readers match our writers too
        keys = [f"camera[{ns}].frames_processed" for ns in CAMERAS]

        def processed() -> list[int]:
            d = client.diagnostics()
            return [int(float(d.get(k, 0))) for k in keys]
        before = [0, 0]
        for fps, frames, pose_rate in ((1.0, 15, 0.0), (10.0, 100, 200.0)):
            stream(client, fps, frames, pose_rate)
            wait(lambda f=frames, b0=before: all(n - b >= f for n, b in zip(processed(), b0)), 20.0, 0.1)
            time.sleep(1.0)  # diagnostics after the queue drained
            got = [n - b for n, b in zip(processed(), before)]
            drops = {k: v for k, v in client.diagnostics().items() if k.startswith("warn[")}
            for ns, n in zip(CAMERAS, got):
                assert n >= 0.99 * frames, (f"{fps:g} Hz: camera {ns} processed {n} of {frames} frames; "
                                            f"drops {drops}", node.log()[-3000:])
            before = processed()
    finally:
        client.close()
        assert node.stop() == 0, node.log()[-2000:]



def test_node_transport_is_udp_with_large_buffers_unless_configured(tmp_path: Path) -> None:
    """css_node receives over UDPv4 with large socket buffers; a user's Fast DDS settings, another rmw and
    localhost-only discovery (rmw_fastrtps's own transports) are left alone; a small rmem_max is a warning."""
    from css_ros.ros.transport import NODE_TRANSPORT, SOCKETS_SIZE, configure_transport

    env: dict[str, str] = {}
    line, warn = configure_transport(env, tmp_path, cap=SOCKETS_SIZE)
    assert env == {} and not warn and "CSS_NODE_TRANSPORT=udp" in line   # not the default (module docstring)
    env = {"CSS_NODE_TRANSPORT": "udp"}
    line, warn = configure_transport(env, tmp_path, cap=SOCKETS_SIZE)
    assert env["FASTDDS_BUILTIN_TRANSPORTS"] == NODE_TRANSPORT and not warn and "UDPv4" in line
    env = {"CSS_NODE_TRANSPORT": "udp", "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"}
    line, warn = configure_transport(env, tmp_path, cap=212992)
    assert env["FASTDDS_BUILTIN_TRANSPORTS"] == NODE_TRANSPORT and warn and "rmem_max=212992" in line
    for given in ({"FASTDDS_BUILTIN_TRANSPORTS": "DEFAULT"}, {"FASTRTPS_DEFAULT_PROFILES_FILE": "/p.xml"},
                  {"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"}, {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}):
        given = {"CSS_NODE_TRANSPORT": "udp", **given}
        env = dict(given)
        configure_transport(env, tmp_path, cap=SOCKETS_SIZE)
        assert env == given
    (tmp_path / "DEFAULT_FASTRTPS_PROFILES.xml").write_text("<profiles/>")
    env = {"CSS_NODE_TRANSPORT": "udp"}
    line, _ = configure_transport(env, tmp_path, cap=SOCKETS_SIZE)
    assert env == {"CSS_NODE_TRANSPORT": "udp"} and "DEFAULT_FASTRTPS_PROFILES.xml" in line
