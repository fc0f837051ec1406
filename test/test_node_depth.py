"""css_node in a changing world over real DDS: a depth camera at 30 Hz beside a 5 Hz segmentation (robot timing:
latency and jitter, the depth arriving before the segmentation for half the frames and after it for the others,
when the depth 33 ms earlier is already there: each frame must take the depth of its own stamp), in 16UC1 and 32FC1.
Someone 1 m in front of the wall hides a block of the view: those pixels are counted occluded and add no evidence
(the map equals the engine's with that block unlabelled); a person labelled as such (transient_classes by name) adds
none either; ~/surprise comes with each frame, NaN where the segmentation has no label; a depth stream in another
encoding is warned once (rate-limited) and dropped, its frames fused without depth at once."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

import ros_helpers as rh
from css_ros.io.messages import stamp_to_ns

pytestmark = pytest.mark.slow

NAMES = ("floor", "wall_left", "wall_right", "person")   # wall_labels: left 1, right 2
BLOCK = (slice(10, 26), slice(8, 22))       # someone 1 m away hides this block (labelled as the wall)
PERSON = (slice(4, 30), slice(36, 42))      # labelled person (transient), at the wall's depth
UNLABELLED = slice(0, 3)                    # rows without a label
FPS, DEPTH_FPS, DURATION = 5.0, 30.0, 4.0
BLOCK_PIXELS = 16 * 14


def scene_labels() -> np.ndarray:
    labels = rh.wall_labels().astype(np.uint8)
    labels[PERSON] = NAMES.index("person")
    labels[UNLABELLED] = 255
    return labels


def scene_depth_m(block: bool = True) -> np.ndarray:
    """The measured depth [m]: the wall at 3 m, the block at 1 m (``block``), holes (no measurement) outside it."""
    d = np.full((rh.HEIGHT, rh.WIDTH), 3.0)
    if block:
        d[BLOCK] = 1.0
    holes = np.random.default_rng(1).random(d.shape) < 0.03
    holes[BLOCK] = False
    d[holes] = 0.0
    return d


def depth_array(encoding: str, block: bool = True) -> np.ndarray:
    d = scene_depth_m(block)
    if encoding == "16UC1":
        return np.round(d * 1000).astype(np.uint16)
    return np.where(d > 0, d, np.nan).astype(np.float32)


def write_classes(path: Path) -> Path:
    path.write_text("classes:\n" + "".join(f"  - {{id: {i}, name: {n}, color: [{40 * i}, 90, 200]}}\n"
                                          for i, n in enumerate(NAMES)))
    return path


def robot_events(t0: float) -> tuple[list[tuple[float, str, int]], list[float]]:
    """(arrival [s], kind, index) of a DURATION s stream and the segmentation stamps [s] (from ``t0``). Depth k at
    t0 + k / 30; segmentation i at the stamp of depth 6 i, 100-140 ms late. The depth stream is in order (one
    camera's topic) with a latency of 20-40 ms in the first half (before its segmentation) and 250-270 ms in the second
    (after it, when the depth 33 ms earlier has long arrived). Poses at 100 Hz between the stamps, camera_info at each
    segmentation stamp."""
    rng = np.random.default_rng(0)
    per = int(DEPTH_FPS / FPS)
    events: list[tuple[float, str, int]] = []
    seg_stamps = []
    for k in range(int(DURATION * DEPTH_FPS)):
        t = t0 + k / DEPTH_FPS
        if k % per == 0:
            seg_stamps.append(t)
            events += [(t, "info", k), (t + rng.uniform(0.10, 0.14), "seg", k)]
        latency = 0.02 if t - t0 < DURATION / 2 else 0.25
        events.append((t + latency + rng.uniform(0.0, 0.02), "depth", k))
    events += [(t0 - 0.05 + j / 100.0 + 0.005, "pose", j) for j in range(int((DURATION + 0.5) * 100))]
    return sorted(events), seg_stamps


class DepthRobot:
    """The test client's publishers: poses, camera_info, segmentation and depth, timed like a robot's."""

    def __init__(self, client: rh.RosClient) -> None:
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import Image

        self.client = client
        self.depth_pub = client.node.create_publisher(Image, "depth",
                                                      QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
        self.labels = scene_labels()

    def publishers(self) -> list:
        return [*self.client.pub.values(), self.depth_pub]

    def send_depth(self, stamp_ns: int, array: np.ndarray, encoding: str) -> None:
        from css_ros.ros.conversions import header_msg, image_msg

        self.depth_pub.publish(image_msg(array, encoding, header_msg(stamp_ns, "camera")))

    def stream(self, encoding: str) -> list[int]:
        """Publish the robot stream in real time; returns the segmentation stamps [ns]."""
        wall0, stamp0 = time.monotonic(), time.time_ns() * 1e-9
        events, seg_stamps = robot_events(0.3)
        # only the depths at a segmentation's stamp show the block: a frame given a neighbour (33 ms off) shows none
        depth, between = depth_array(encoding), depth_array(encoding, block=False)
        per = int(DEPTH_FPS / FPS)
        ns = lambda t: int(round((stamp0 + t) * 1e9))   # noqa: E731
        for t, kind, k in events:
            delay = wall0 + t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            stamp = ns(0.3 + k / DEPTH_FPS) if kind != "pose" else ns(t - 0.005)
            if kind == "pose":
                self.client.send_pose(stamp)
            elif kind == "info":
                self.client.send_camera_info(stamp)
            elif kind == "seg":
                self.client.send_image("segmentation", stamp, self.labels, "mono8")
            else:
                self.send_depth(stamp, depth if k % per == 0 else between, encoding)
        return [ns(t) for t in seg_stamps]


def reference_map(model_path: Path, with_depth: int, without_depth: int) -> np.ndarray:
    """The engine's map of the frames fused: with depth the block (where measured) is unlabelled; transient person."""
    from css_ros.engine.camera import Camera
    from css_ros.engine.gaussians import GaussianModel
    from css_ros.engine.semantic_map import SemanticMap

    smap = SemanticMap(GaussianModel.from_ply(model_path), len(NAMES), transient_classes=[NAMES.index("person")])
    cam = Camera.from_pose(rh.K, rh.WIDTH, rh.HEIGHT, np.zeros(3), rh.IDENTITY)
    hidden = scene_labels()
    hidden[BLOCK] = 255
    for labels, n in ((hidden, with_depth), (scene_labels(), without_depth)):
        for _ in range(n):
            smap.update(cam, labels)
    return np.array(smap.concentrations)


def surprise_subscription(client: rh.RosClient) -> dict[int, object]:
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    got: dict[int, object] = {}

    def keep(msg: object) -> None:
        got[stamp_to_ns(msg.header.stamp)] = msg  # type: ignore[attr-defined]
    client.node.create_subscription(Image, "/css_node/surprise", keep,
                                    QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
    return got


def accounted(client: rh.RosClient) -> int:
    """Segmentations processed or counted as not processed, whatever the reason (the node never stalls)."""
    d = client.diagnostics()
    return sum(int(float(d.get(k, 0))) for k in ("frames_processed", "dropped[segmentation]", "frames_dropped_busy",
                                                 "segmentation_lost"))


@pytest.mark.parametrize("encoding", ["16UC1", "32FC1"])
def test_depth_and_transient_classes_at_robot_timing(tmp_path, encoding):
    from css_ros.engine.semantic_map import SemanticMap
    from css_ros.engine.gaussians import GaussianModel
    from css_ros.io.messages import image_to_array

    domain = rh.next_domain_id()
    model_path = rh.write_wall_model(tmp_path / "wall.ply")
    node = rh.NodeProcess(dict(model_path=str(model_path), class_file=str(write_classes(tmp_path / "classes.yaml")),
                               checkpoint_path=str(tmp_path / "map.npz"), checkpoint_period=0.0, resume=False,
                               log_period=0.5, warn_period=60.0, depth_topic="depth", transient_classes="[person]"),
                          domain, tmp_path / "node.log")
    client = rh.RosClient(domain)
    try:
        robot = DepthRobot(client)
        surprise = surprise_subscription(client)
        assert client.wait_until(lambda: node.wait_log("inputs (", 0.1) and all(
            p.get_subscription_count() > 0 for p in robot.publishers()), rh.NODE_START_S), node.log()[-3000:]
        assert "transient classes 3:person" in node.log()
        assert client.wait_outputs_heard(("surprise", "semantic")), (client.diagnostics(), node.log()[-3000:])
        stamps = robot.stream(encoding)
        assert client.wait_until(lambda: accounted(client) >= len(stamps), 30.0), (client.diagnostics(),
                                                                                   node.log()[-3000:])
        d = client.diagnostics()
        processed, with_d, without_d = (int(float(d.get(k, 0))) for k in ("frames_processed", "frames_with_depth",
                                                                           "frames_without_depth"))
        print(f"\n{encoding}: {processed}/{len(stamps)} frames fused, {with_d} with depth; occluded "
              f"{d['label_pixels_occluded']}, transient {d['label_pixels_transient']}, last mean surprise "
              f"{d['last_surprise_mean']}")
        assert processed >= 0.8 * len(stamps) and with_d + without_d == processed, d
        assert with_d >= 0.8 * processed, (d, node.log()[-3000:])       # late depths were waited for
        block = int(np.count_nonzero(scene_depth_m()[BLOCK] > 0))
        person = int(np.count_nonzero(scene_labels() == NAMES.index("person")))
        assert int(d["label_pixels_occluded"]) == block * with_d and int(d["label_pixels_transient"]) == person * processed
        assert int(d["last_pixels_transient"]) == person and 0.0 <= float(d["last_surprise_mean"]) < 1.0

        res = client.call(client.save_client)
        assert res.success, res.message
        saved = SemanticMap.load(tmp_path / "map.npz", GaussianModel.from_ply(model_path)).concentrations
        np.testing.assert_allclose(saved, reference_map(model_path, with_d, without_d), rtol=1e-9, atol=0)

        labelled = scene_labels() != 255
        mine = [s for s in stamps if s in surprise]
        assert len(mine) >= 0.8 * processed, (len(mine), processed)
        for s in mine:
            msg = surprise[s]
            img = image_to_array(msg)
            assert msg.encoding == "32FC1" and msg.header.frame_id == "camera" and img.shape == labelled.shape
            np.testing.assert_array_equal(np.isnan(img), ~labelled)
            assert np.all((img[labelled] >= 0) & (img[labelled] <= 1))
        bad_encoding_is_warned_once_and_dropped(client, robot, node, with_d, without_d)
    finally:
        client.close()
        assert node.stop() == 0, node.log()[-2000:]


def bad_encoding_is_warned_once_and_dropped(client: rh.RosClient, robot: DepthRobot, node: rh.NodeProcess,
                                            with_d: int, without_d: int) -> None:
    """Five frames whose depth comes as mono8: each depth refused (one warning line within warn_period), each
    frame fused without depth and without waiting for one; then a good depth is used again."""
    t0 = time.time_ns() + 10**8
    before, processed = accounted(client), int(float(client.diagnostics()["frames_processed"]))
    for i in range(5):
        s = t0 + i * 2 * 10**8
        client.send_pose(s - 10**7)
        client.send_pose(s + 10**7)
        client.send_camera_info(s)
        robot.send_depth(s, np.full((rh.HEIGHT, rh.WIDTH), 30, np.uint8), "mono8")
        client.send_image("segmentation", s, robot.labels, "mono8")
        time.sleep(0.2)
    assert client.wait_until(lambda: accounted(client) >= before + 5, 20.0), client.diagnostics()
    d = client.diagnostics()
    assert int(d["warn[depth: bad depth]"]) >= 1 and node.log().count("[depth] bad depth") == 1, node.log()[-3000:]
    new_frames = int(d["frames_processed"]) - processed
    assert int(d["frames_without_depth"]) - without_d == new_frames >= 4 and int(d["frames_with_depth"]) == with_d
    assert "dropped[depth]" in d
    s = t0 + 2 * 10**9
    client.send_pose(s - 10**7)
    client.send_pose(s + 10**7)
    client.send_camera_info(s)
    robot.send_depth(s, depth_array("16UC1"), "16UC1")
    client.send_image("segmentation", s, robot.labels, "mono8")
    assert client.wait_until(lambda: int(float(client.diagnostics().get("frames_with_depth", 0))) == with_d + 1,
                             20.0), client.diagnostics()


@pytest.mark.parametrize("params, message", [
    (dict(transient_classes="[persn]"), "cannot start: parameter transient_classes: 'persn' is no class name nor id "
                                        "in 0..3 (classes: 0 floor, 1 wall_left, 2 wall_right, 3 person)"),
    (dict(evidence_half_life=10.0, publish_evidence=True), "cannot start: parameter evidence_half_life=10.0: with a "
                                                           "half-life the map's evidence is no longer additive")])
def test_start_up_errors_name_the_parameter(tmp_path, params, message):
    node = rh.NodeProcess(dict(model_path=str(rh.write_wall_model(tmp_path / "wall.ply")), checkpoint_path="",
                               class_file=str(write_classes(tmp_path / "classes.yaml")), warmup=False, **params),
                          rh.next_domain_id(), tmp_path / "node.log")
    try:
        assert node.proc.wait(120) == 2, node.log()[-3000:]
    finally:
        node.stop()
    assert message in node.log(), node.log()[-3000:]


def test_each_camera_reads_its_own_depth(tmp_path):
    """cameras [front, left], depth_topic depth: front/depth hides the block of front's frames only; each camera's
    ~/<ns>/surprise comes with its frames."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CameraInfo, Image

    from css_ros.ros.conversions import camera_info_msg, header_msg, image_msg

    domain = rh.next_domain_id()
    node = rh.NodeProcess(dict(model_path=str(rh.write_wall_model(tmp_path / "wall.ply")), class_file="",
                               num_classes=rh.NUM_CLASSES, checkpoint_path="", log_period=0.5, input_qos="reliable",
                               cameras=["front", "left"], depth_topic="depth", max_pending_frames=16),
                          domain, tmp_path / "node.log")
    client = rh.RosClient(domain)
    try:
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        pubs = {ns: [client.node.create_publisher(t, f"{ns}/{k}", qos) for t, k in
                     ((CameraInfo, "camera_info"), (Image, "depth"), (Image, "segmentation"))] for ns in ("front", "left")}
        got: dict[str, set[int]] = {"front": set(), "left": set()}
        for ns in got:
            client.node.create_subscription(Image, f"/css_node/{ns}/surprise",
                                            lambda m, ns=ns: got[ns].add(stamp_to_ns(m.header.stamp)), qos)
        everything = [p for v in pubs.values() for p in v] + [client.pub["pose"]]
        assert client.wait_until(lambda: node.wait_log("inputs (", 0.1) and all(
            p.get_subscription_count() > 0 for p in everything), rh.NODE_START_S), node.log()[-3000:]
        assert client.wait_outputs_heard(("front/surprise", "left/surprise")), client.diagnostics()
        wall = np.full((rh.HEIGHT, rh.WIDTH), 3000, np.uint16)
        blocked = wall.copy()
        blocked[BLOCK] = 1000
        stamps = [time.time_ns() + i * 10**8 for i in range(8)]
        for i, s in enumerate(stamps):
            ns = ("front", "left")[i % 2]
            client.send_pose(s - 10**7)
            client.send_pose(s + 10**7)
            info, depth, seg = pubs[ns]
            info.publish(camera_info_msg(rh.K, rh.WIDTH, rh.HEIGHT, header_msg(s, f"{ns}_optical")))
            seg.publish(image_msg(rh.wall_labels(), "mono8", header_msg(s, f"{ns}_optical")))
            depth.publish(image_msg(blocked if ns == "front" else wall, "16UC1", header_msg(s, f"{ns}_optical")))
            time.sleep(0.1)
        assert client.wait_diag("frames_processed", 8, 30.0) == 8, (client.diagnostics(), node.log()[-3000:])
        d = client.diagnostics()
        assert int(d["frames_with_depth"]) == 8 and int(d["label_pixels_occluded"]) == 4 * BLOCK_PIXELS, d
        assert client.wait_until(lambda: got["front"] == set(stamps[0::2]) and got["left"] == set(stamps[1::2]), 10.0), got
    finally:
        client.close()
        assert node.stop() == 0, node.log()[-2000:]
