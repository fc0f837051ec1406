"""css_node with ``pose_source: tf`` over real DDS, fed like a robot stack feeds it: /tf at 50-200 Hz with jitter,
/tf_static published once before the node starts and once after, the chain map -> odom -> base_link -> camera_link
-> camera_optical_frame with a jump of map -> odom, late segmentation, two cameras, a lookup that must wait and ones
that must be refused. Every pose the node used (~/view_uncertainty) is checked against the transforms composed in
numpy (tf_reference.brute_chain) within 1e-6 m and 1e-6 rad (the output is float32: ~1e-7 at these distances)."""
from __future__ import annotations

import importlib.util
import math
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import ros_helpers as rh
from css_ros.io.messages import stamp_to_ns, unpack_view_points
from tf_reference import brute_chain, mat, pose_errors

pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(importlib.util.find_spec("tf2_msgs") is None,
                                 reason="tf2_msgs is not importable: run msg_packages/build_tf2_msgs.py (README "
                                        "command 1 and .ci/run do)")]

C = rh.NUM_CLASSES
OPTICAL_IN_LINK = np.array([-0.5, 0.5, -0.5, 0.5])   # REP-103 body -> optical frame
TOL_M, TOL_RAD = 1e-6, 1e-6


def _start(tmp: Path, domain: int, name: str, **params) -> rh.NodeProcess:
    model = rh.write_wall_model(tmp / "wall.ply")
    base = dict(model_path=str(model), class_file="", num_classes=C, checkpoint_path=str(tmp / f"{name}.npz"),
                checkpoint_period=0.0, resume=False, log_period=0.5, warn_period=0.0, pose_source="tf",
                input_qos="reliable", max_pending_frames=64)
    base.update(params)
    return rh.NodeProcess(base, domain, tmp / f"{name}.log")


class TfClient:
    """Publishers of /tf and /tf_static (tf2_ros's QoS), camera_info and segmentation per camera, the node's
    view_uncertainty per camera; every transform sent is recorded for the brute force."""

    def __init__(self, client: rh.RosClient, cameras: list[str]) -> None:
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import CameraInfo, Image, PointCloud2
        from tf2_msgs.msg import TFMessage

        node = client.node
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        self.client = client
        self.tf = node.create_publisher(TFMessage, "/tf", qos)
        self.tf_static = node.create_publisher(TFMessage, "/tf_static", QoSProfile(
            depth=100, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.tf_static_volatile = node.create_publisher(TFMessage, "/tf_static", qos)  # not tf2_ros's QoS
        self.cams = {ns: (node.create_publisher(CameraInfo, f"{ns + '/' if ns else ''}camera_info", qos),
                          node.create_publisher(Image, f"{ns + '/' if ns else ''}segmentation", qos))
                     for ns in cameras}
        self.poses: dict[str, dict[int, np.ndarray]] = {ns: {} for ns in cameras}
        self.results: list = []   # the subscriptions of each camera's view_uncertainty
        self.result_names = [f"{ns + '/' if ns else ''}view_uncertainty" for ns in cameras]
        for ns, name in zip(cameras, self.result_names):
            self.results.append(node.create_subscription(PointCloud2, f"/css_node/{name}", self._recorder(ns),
                                                         QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)))
        self.dynamic: dict[str, list] = {}
        self.static: dict[str, np.ndarray] = {}
        self.parents: dict[str, str] = {}

    def _recorder(self, ns: str):
        def record(msg) -> None:
            pt = unpack_view_points(msg)[0]
            self.poses[ns][stamp_to_ns(msg.header.stamp)] = np.array(
                [pt["x"], pt["y"], pt["z"], pt["qx"], pt["qy"], pt["qz"], pt["qw"]], dtype=np.float64)
        return record

    def publishers(self) -> list:
        return [self.tf, self.tf_static, self.tf_static_volatile] + [p for pair in self.cams.values() for p in pair]

    def send_tf(self, entries, static: bool = False, volatile: bool = False) -> None:
        """entries: (parent, child, stamp [ns], xyz, xyzw) -> one TFMessage (``volatile``: /tf_static published
        without transient-local durability, as a hand-written publisher may do)."""
        from geometry_msgs.msg import TransformStamped
        from tf2_msgs.msg import TFMessage

        from css_ros.ros.conversions import header_msg

        msg = TFMessage()
        for parent, child, stamp, p, q in entries:
            t = TransformStamped(header=header_msg(stamp, parent), child_frame_id=child)
            t.transform.translation.x, t.transform.translation.y, t.transform.translation.z = (float(v) for v in p)
            (t.transform.rotation.x, t.transform.rotation.y, t.transform.rotation.z,
             t.transform.rotation.w) = (float(v) for v in q)
            msg.transforms.append(t)
            self.parents[child] = parent
            if static:
                self.static[child] = mat(p, q)
            else:
                self.dynamic.setdefault(child, []).append((stamp, np.asarray(p, float), np.asarray(q, float)))
        (self.tf_static_volatile if volatile else self.tf_static if static else self.tf).publish(msg)

    def send_frame(self, ns: str, stamp: int, frame_id: str, labels: np.ndarray) -> None:
        from css_ros.ros.conversions import camera_info_msg, header_msg, image_msg

        info, seg = self.cams[ns]
        info.publish(camera_info_msg(rh.K, rh.WIDTH, rh.HEIGHT, header_msg(stamp, frame_id)))
        seg.publish(image_msg(labels, "mono8", header_msg(stamp, frame_id)))

    def check(self, ns: str, stamp: int, frame_id: str) -> tuple[float, float]:
        """(position error [m], angle error [rad]) of the pose the node used against the brute force."""
        got = self.poses[ns][stamp]
        T = brute_chain(frame_id, "map", stamp, self.parents, self.dynamic, self.static)
        return pose_errors(got[:3], got[3:], T)


def base_in_odom(t: float) -> tuple[np.ndarray, np.ndarray]:
    """base_link in odom at t [s]: sliding sideways, panning slowly, its x axis along the map's +z (the wall)."""
    rot = Rotation.from_rotvec([0.0, math.radians(-90.0 + 4.0 * t), 0.0]) * \
        Rotation.from_rotvec([0.0, 0.0, 0.02 * math.sin(2.0 * t)])
    return np.array([0.15 * t - 0.3, 0.05 + 0.02 * math.sin(t), 0.0]), rot.as_quat()


def map_odom(jumped: bool) -> tuple[np.ndarray, np.ndarray]:
    """map -> odom before / after a localisation correction."""
    if jumped:
        return np.array([0.25, -0.08, 0.02]), Rotation.from_rotvec([0.0, 0.03, 0.0]).as_quat()
    return np.array([0.05, 0.0, 0.0]), np.array([0.0, 0.0, 0.0, 1.0])


def _wait_ready(client: rh.RosClient, node: rh.NodeProcess, tfc: TfClient) -> None:
    """The node is up, has matched every input publisher of ``tfc``, and its view_uncertainty writers have matched
    ``tfc``'s readers (its diagnostics say so: a result published before that is lost on a loaded host)."""
    assert client.wait_until(lambda: node.wait_log("inputs (", 0.1) and all(
        p.get_subscription_count() > 0 for p in tfc.publishers()) and all(
        r.get_publisher_count() > 0 for r in tfc.results) and client.outputs_heard(tuple(tfc.result_names)),
        rh.NODE_START_S), node.log()[-3000:]


def test_robot_tf_stream_with_a_map_odom_jump_and_late_segmentation(tmp_path):
    domain = rh.next_domain_id()
    client = rh.RosClient(domain, topics={"pose": "unused_pose"})
    tfc = TfClient(client, [""])
    node = None
    try:
        rng = np.random.default_rng(3)
        stamp0 = time.time_ns()
        # /tf_static before the node starts (transient local: the node gets it when it joins)
        tfc.send_tf([("base_link", "camera_link", stamp0, [0.10, 0.0, 0.05],
                      Rotation.from_rotvec([0, 0, math.radians(3.0)]).as_quat())], static=True)
        node = _start(tmp_path, domain, "tf_robot")
        _wait_ready(client, node, tfc)
        # ... and once more after it started (the optical frame; the URDF's second publisher)
        tfc.send_tf([("camera_link", "camera_optical_frame", stamp0, [0.0, 0.0, 0.0], OPTICAL_IN_LINK)], static=True)
        time.sleep(0.3)
        duration, fps, latency, t_jump = 6.0, 5.0, 0.3, 3.0
        events = []
        t = 0.0
        while t < duration + latency + 0.4:   # odom -> base_link at 150 Hz +-30 %
            events.append((t, "odom"))
            t += (1 / 150.0) * (1 + 0.3 * rng.uniform(-1, 1))
        t = 0.0
        while t < duration + latency + 0.4:   # map -> odom at 50 Hz +-20 %
            events.append((t, "map"))
            t += (1 / 50.0) * (1 + 0.2 * rng.uniform(-1, 1))
        frames = [0.2 + i / fps for i in range(int(duration * fps))]
        events += [(f + latency, "seg") for f in frames]
        events.sort(key=lambda e: e[0])
        start = time.monotonic()
        stamp0 = time.time_ns()
        labels = rh.wall_labels()
        stamps = [stamp0 + int(round(f * 1e9)) for f in frames]
        seg_index = 0
        for t, kind in events:
            delay = start + t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            stamp = stamp0 + int(round(t * 1e9))
            if kind == "odom":
                tfc.send_tf([("odom", "base_link", stamp, *base_in_odom(t))])
            elif kind == "map":
                tfc.send_tf([("map", "odom", stamp, *map_odom(t >= t_jump))])
            else:
                tfc.send_frame("", stamps[seg_index], "camera_optical_frame", labels)
                seg_index += 1
        assert client.wait_until(lambda: len(tfc.poses[""]) >= len(stamps), 30.0), \
            (len(tfc.poses[""]), node.log()[-3000:])
        assert sorted(tfc.poses[""]) == stamps                     # every frame mapped
        jump_stamp = next(s for s, _, _ in tfc.dynamic["odom"] if s >= stamp0 + int(t_jump * 1e9))
        after = 0
        for s in stamps:
            dp, da = tfc.check("", s, "camera_optical_frame")
            assert dp < TOL_M and da < TOL_RAD, (s, dp, da)
            if s > jump_stamp:   # after the correction: the new map -> odom, not the old one
                after += 1
                T_odom = brute_chain("camera_optical_frame", "odom", s, tfc.parents, tfc.dynamic, tfc.static)
                old = mat(*map_odom(False)) @ T_odom
                assert np.linalg.norm(tfc.poses[""][s][:3] - old[:3, 3]) > 0.1
        assert after >= 10
        diag = client.diagnostics()
        assert float(diag.get("frames_processed", 0)) >= len(stamps) - 1
    finally:
        client.close()
        if node is not None:
            assert node.stop() == 0, node.log()[-2000:]


def test_two_cameras_wait_for_late_tf_and_unanswerable_lookups_are_refused(tmp_path):
    """Two cameras by their frame ids (static transforms from a volatile /tf_static publisher); TF lags 0.2 s behind
    the segmentations, so every lookup must wait (within pose_wait); a frame in an unknown frame and one past the
    last transform are refused with their reasons."""
    domain = rh.next_domain_id()
    client = rh.RosClient(domain, topics={"pose": "unused_pose"})
    tfc = TfClient(client, ["front", "left"])
    node = _start(tmp_path, domain, "tf_two", cameras=["front", "left"])
    try:
        _wait_ready(client, node, tfc)
        stamp0 = time.time_ns()
        tfc.send_tf([("base_link", "front_optical", stamp0, [0.1, 0.0, 0.0], OPTICAL_IN_LINK),
                     ("base_link", "left_optical", stamp0, [0.0, 0.1, 0.0],
                      (Rotation.from_rotvec([0, 0, 0.2]) * Rotation.from_quat(OPTICAL_IN_LINK)).as_quat())],
                    static=True, volatile=True)
        time.sleep(0.3)
        rng = np.random.default_rng(5)
        lag, duration = 0.2, 4.0
        events = []
        t = 0.0
        while t < duration:   # map -> base_link published 0.2 s after its stamp, 100 Hz +-30 %
            events.append((t + lag, "tf", t))
            t += 0.01 * (1 + 0.3 * rng.uniform(-1, 1))
        last_tf = max(e[2] for e in events)
        frames = [(0.3 + 0.2 * i, "front" if i % 2 == 0 else "left") for i in range(int((duration - 0.6) / 0.2))]
        events += [(f, "seg", (f, ns)) for f, ns in frames]
        events.append((1.0, "ghost", 1.0))
        events.append((duration + 0.1, "future", last_tf + 1.0))
        events.sort(key=lambda e: e[0])
        start = time.monotonic()
        stamp0 = time.time_ns()
        labels = rh.wall_labels()
        for t_pub, kind, arg in events:
            delay = start + t_pub - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            if kind == "tf":
                stamp = stamp0 + int(round(arg * 1e9))
                tfc.send_tf([("map", "base_link", stamp, *base_in_odom(arg))])
            elif kind == "seg":
                f, ns = arg
                tfc.send_frame(ns, stamp0 + int(round(f * 1e9)), f"{ns}_optical", labels)
            elif kind == "ghost":
                tfc.send_frame("left", stamp0 + int(round(arg * 1e9)) + 1000, "ghost_optical", labels)
            else:
                tfc.send_frame("front", stamp0 + int(round(arg * 1e9)), "front_optical", labels)
        want = {ns: sorted(stamp0 + int(round(f * 1e9)) for f, n in frames if n == ns) for ns in ("front", "left")}
        assert client.wait_until(lambda: all(len(tfc.poses[ns]) >= len(want[ns]) for ns in want), 30.0), \
            ({ns: len(v) for ns, v in tfc.poses.items()}, node.log()[-3000:])
        for ns in want:
            assert sorted(tfc.poses[ns]) == want[ns]
            for s in want[ns]:
                dp, da = tfc.check(ns, s, f"{ns}_optical")
                assert dp < TOL_M and da < TOL_RAD, (ns, s, dp, da)
        key_ghost = "warn[left/segmentation: tf unknown frame]"
        key_future = "warn[front/segmentation: tf extrapolation into the future]"
        assert client.wait_diag(key_ghost, 1, 15.0) == 1, client.diagnostics()
        assert client.wait_diag(key_future, 1, 15.0) == 1, client.diagnostics()
        diag = client.diagnostics()
        assert float(diag["camera[front].frames_processed"]) == len(want["front"])
        assert float(diag["camera[left].frames_processed"]) == len(want["left"])
    finally:
        client.close()
        assert node.stop() == 0, node.log()[-2000:]
