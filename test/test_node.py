"""End-to-end tests of css_node over real DDS: outputs, convergence, candidate queries, services, bad input."""
from __future__ import annotations

import itertools
import time
from typing import Any, Iterator

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

import ros_helpers as rh  # noqa: E402
from css_ros.io.messages import image_to_array, stamp_to_ns, unpack_view_points  # noqa: E402

C = rh.NUM_CLASSES
ALPHA_B = 1e-3
# Background Dirichlet Dir(alpha_b 1): E = 1/C, Var = E (1 - E) / (1 + C alpha_b) (SPEC §5).
BG_VAR = (1 / C) * (1 - 1 / C) / (1 + C * ALPHA_B)


class Live:
    """One css_node process + test client shared by the tests of this module."""

    def __init__(self, tmp: Any) -> None:
        self.domain = rh.next_domain_id()
        self.model = rh.write_wall_model(tmp / "wall.ply")
        self.node = rh.NodeProcess(dict(model_path=str(self.model), class_file="", num_classes=C,
                                        background=ALPHA_B, checkpoint_path=str(tmp / "map.npz"),
                                        checkpoint_period=0.0, resume=False, log_period=0.3, warn_period=0.0),
                                   self.domain, tmp / "node.log")
        self.client = rh.RosClient(self.domain)
        self._stamps = itertools.count(1)
        if not self.client.wait_connected(60.0):
            raise RuntimeError(f"css_node did not come up:\n{self.node.log()}")
        time.sleep(0.5)  # let both ends of every reader/writer pair match

    def stamp(self) -> int:
        """A fresh stamp, 0.5 s after the previous one."""
        return next(self._stamps) * 500_000_000

    def frame(self, labels: np.ndarray | None = None, **kwargs: Any) -> int:
        """Send one good frame and wait until it was processed; returns its stamp."""
        stamp = self.stamp()
        self.client.send_frame(stamp, labels, **kwargs)
        assert self.client.wait_stamp("view_uncertainty", stamp), f"frame {stamp} not processed\n{self.tail()}"
        self.last_frame = stamp
        return stamp

    def query(self, positions: np.ndarray, quats: np.ndarray, frame_id: str = "map") -> tuple[Any, np.ndarray]:
        stamp = self.stamp()
        self.client.send_candidates(stamp, positions, quats, frame_id)
        msg = self.client.wait_stamp("candidate_scores", stamp)
        assert msg is not None, f"no answer to candidate request {stamp}\n{self.tail()}"
        return msg, unpack_view_points(msg)

    def tail(self) -> str:
        return self.node.log()[-3000:]


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Live]:
    lv = Live(tmp_path_factory.mktemp("css_node"))
    # Missing camera_info: the node has not received any yet. Inputs are best effort, so a first message can
    # still be lost to discovery: send again (a fresh stamp each time) until the node has warned once.
    for _ in range(5):
        lv.no_info_stamp = lv.stamp()
        lv.client.send_pose(lv.no_info_stamp)
        lv.client.send_image("segmentation", lv.no_info_stamp, rh.wall_labels(), "mono8")
        if lv.client.wait_diag("warn[segmentation: no camera_info received yet]", 1, timeout=4.0) >= 1:
            break
    yield lv
    lv.client.close()
    code = lv.node.stop()
    assert code == 0, lv.tail()


def test_missing_camera_info_dropped_then_frames_work(live: Live) -> None:
    assert float(live.client.diagnostics().get("warn[segmentation: no camera_info received yet]", 0)) >= 1
    assert live.client.wait_stamp("view_uncertainty", live.no_info_stamp, timeout=0.1) is None
    live.frame()
    assert "[segmentation] no camera_info received yet" in live.node.log()


def test_every_output_arrives_with_encoding_size_stamp(live: Live) -> None:
    stamps = [live.frame(rgb=np.full((rh.HEIGHT, rh.WIDTH, 3), 128, np.uint8)) for _ in range(3)]
    expected = {"semantic": "mono8", "semantic_color": "rgb8", "expectation": "32FC1", "variance": "32FC1",
                "rendered_image": "rgb8"}
    for stamp in stamps:
        for name, encoding in expected.items():
            msg = live.client.wait_stamp(name, stamp, timeout=5.0)
            assert msg is not None, name
            assert msg.encoding == encoding and (msg.width, msg.height) == (rh.WIDTH, rh.HEIGHT)
            assert msg.header.frame_id == "camera"  # the segmentation's (camera) frame
            arr = image_to_array(msg)
            assert arr.shape[:2] == (rh.HEIGHT, rh.WIDTH)
        cloud = live.client.wait_stamp("view_uncertainty", stamp)
        assert cloud.header.frame_id == "map" and cloud.width * cloud.height == 1
        pt = unpack_view_points(cloud)[0]
        assert (pt["x"], pt["y"], pt["z"], pt["qw"]) == (0.0, 0.0, 0.0, 1.0)
        assert np.isfinite(pt["u_var"]) and 0 <= pt["u_exp"] <= 1
    # One view_uncertainty per observed frame, never duplicated.
    seen = [stamp_to_ns(m.header.stamp) for m in live.client.messages("view_uncertainty")]
    assert all(seen.count(s) == 1 for s in stamps)


def test_labels_converge_and_uncertainty_falls(live: Live) -> None:
    live.client.call(live.client.reset_client)
    stamps = [live.frame() for _ in range(6)]
    u = [unpack_view_points(live.client.wait_stamp("view_uncertainty", s))[0] for s in stamps]
    u_var = [p["u_var"] for p in u]
    assert all(b < a for a, b in zip(u_var, u_var[1:])), u_var  # more evidence, less variance
    sem = image_to_array(live.client.wait_stamp("semantic", stamps[-1]))
    gt = rh.wall_labels()
    assert np.mean(sem == gt) > 0.95
    exp = image_to_array(live.client.wait_stamp("expectation", stamps[-1]))
    var = image_to_array(live.client.wait_stamp("variance", stamps[-1]))
    assert np.all((exp >= 0) & (exp <= 1)) and np.all((var >= 0) & (var <= 0.25))
    assert np.median(exp) > 0.9  # every pixel saw the same class several times


def test_candidate_scores_in_request_order_with_request_header(live: Live) -> None:
    live.frame()
    positions = np.array([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [0.0, -0.2, 0.5], [0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    quats = np.array([rh.IDENTITY, rh.IDENTITY, rh.yaw_quat(0.2), rh.yaw_quat(np.pi), [np.nan, 0, 0, 1]])
    msg, pts = live.query(positions, quats, frame_id="map")
    assert msg.header.frame_id == "map" and len(pts) == len(positions)
    got = np.stack([pts[k] for k in ("x", "y", "z")], axis=1)
    np.testing.assert_allclose(got, positions.astype(np.float32))
    np.testing.assert_allclose(np.stack([pts[k] for k in ("qx", "qy", "qz", "qw")], 1)[:4],
                               quats[:4].astype(np.float32))
    # Looking away from the wall only the background Dirichlet is seen: closed-form U.
    assert pts["u_var"][3] == pytest.approx(BG_VAR, rel=1e-4)
    assert pts["u_exp"][3] == pytest.approx(1 - 1 / C, abs=1e-5)
    # The observed view is far more certain than empty space; the invalid pose is scored NaN.
    assert pts["u_var"][0] < 0.01 * BG_VAR
    assert np.isnan(pts["u_var"][4]) and np.isnan(pts["u_exp"][4])
    # Several requests in flight are answered each with its own header.
    stamps = [live.stamp() for _ in range(3)]
    for s in stamps:
        live.client.send_candidates(s, positions[:2], quats[:2], frame_id=f"req{s}")
    for s in stamps:
        reply = live.client.wait_stamp("candidate_scores", s)
        assert reply is not None and reply.header.frame_id == f"req{s}" and reply.width == 2
    empty, pts = live.query(np.zeros((0, 3)), np.zeros((0, 4)))
    assert len(pts) == 0


def test_candidate_info_gain_matches_the_engine_on_the_same_map(live: Live, tmp_path_factory: Any) -> None:
    """~/candidate_scores carries info_gain (after the 9 view fields) per candidate in request order: finite and
    >= 0 where the pose is valid, NaN where not, and equal to SemanticMap.score_views(...)[:, 2] of the map the
    node held (saved through ~/save_map right before the request; the node scores at candidate_scale 0.25)."""
    from css_ros.engine.camera import Camera
    from css_ros.engine.gaussians import GaussianModel
    from css_ros.engine.semantic_map import SemanticMap
    from css_ros.io.clouds import CANDIDATE_FIELDS, unpack_scored_views

    live.frame()
    assert live.client.call(live.client.save_client).success
    smap = SemanticMap.load(live.node.log_path.parent / "map.npz", GaussianModel.from_ply(live.model))
    positions = np.array([[0.0, 0.0, 0.0], [0.6, 0.0, 0.0], [-0.5, 0.3, 1.0], [0.0, 0.0, 0.0], [0.2, -0.4, -1.0],
                          [0.0, 0.0, 0.0]])
    quats = np.array([rh.IDENTITY, rh.IDENTITY, rh.yaw_quat(0.3), rh.yaw_quat(np.pi), rh.yaw_quat(-0.2),
                      [np.nan, 0.0, 0.0, 1.0]])
    msg, _ = live.query(positions, quats)
    assert [f.name for f in msg.fields] == list(CANDIDATE_FIELDS)
    pts = unpack_scored_views(msg)
    np.testing.assert_allclose(np.stack([pts[k] for k in ("x", "y", "z")], 1), positions.astype(np.float32))
    cams = [Camera.from_pose(rh.K, rh.WIDTH, rh.HEIGHT, p, q).scaled(0.25) for p, q in zip(positions[:5], quats[:5])]
    ref = smap.score_views(cams, pixel_scale=1 / 0.25 ** 2)   # the node counts candidates at full resolution
    assert ref.shape == (5, 3), "SemanticMap.score_views returns no info_gain column"
    gain = pts["info_gain"].astype(np.float64)
    assert np.all(np.isfinite(gain[:5])) and np.all(gain[:5] >= 0) and np.isnan(gain[5])
    np.testing.assert_allclose(gain[:5], ref[:, 2], rtol=1e-6, atol=1e-30)
    np.testing.assert_allclose(np.c_[pts["u_var"], pts["u_exp"]][:5], ref[:, :2], rtol=1e-6)
    assert gain[0] > 0 and gain[3] < gain[0]   # the mapped wall can still teach something; empty space less


def test_reset_map_returns_to_prior(live: Live) -> None:
    live.frame()
    _, before = live.query(np.zeros((1, 3)), rh.IDENTITY[None])
    assert before["u_exp"][0] < 0.5
    res = live.client.call(live.client.reset_client)
    assert res.success
    _, after = live.query(np.zeros((1, 3)), rh.IDENTITY[None])
    # Uniform prior everywhere: E_i = sum_n kappa_in / C + kappa_b / C = 1 / C for every pixel.
    assert after["u_exp"][0] == pytest.approx(1 - 1 / C, abs=1e-5)


def test_save_map_service_writes_loadable_checkpoint(live: Live, tmp_path_factory: Any) -> None:
    from css_ros.engine.gaussians import GaussianModel
    from css_ros.engine.semantic_map import SemanticMap

    live.frame()
    res = live.client.call(live.client.save_client)
    assert res.success, res.message
    path = live.model.parent / "map.npz"
    smap = SemanticMap.load(path, GaussianModel.from_ply(live.model))
    assert smap.num_classes == C and smap.concentrations.max() > 1.0  # observations were fused


# ------------------------------------------------------------------------------------------- bad input
def _bad_segmentation(live: Live, stamp: int, **fields: Any) -> None:
    live.client.send_pose(stamp)
    live.client.send_image("segmentation", stamp, rh.wall_labels(), "mono8", overrides=fields)


BAD_INPUTS = {
    # name: (send function, diagnostics key, log text)
    "wrong encoding": (lambda lv, s: _bad_segmentation(lv, s, encoding="rgb8"),
                       "segmentation: bad segmentation", "not accepted here"),
    "unknown encoding": (lambda lv, s: _bad_segmentation(lv, s, encoding="yuv422_weird"),
                         "segmentation: bad segmentation", "unsupported encoding"),
    "empty image": (lambda lv, s: _bad_segmentation(lv, s, height=0, width=0, step=0, data=b""),
                    "segmentation: bad segmentation", "empty image"),
    "truncated data": (lambda lv, s: _bad_segmentation(lv, s, data=b"\x01" * 10),
                       "segmentation: bad segmentation", "data holds 10 bytes"),
    "size mismatch": (lambda lv, s: (lv.client.send_pose(s), lv.client.send_image(
        "segmentation", s, np.ones((rh.HEIGHT // 2, rh.WIDTH), np.uint8), "mono8")),
        "segmentation: size mismatch with camera_info", "size mismatch with camera_info"),
    "nan position": (lambda lv, s: (lv.client.send_pose(s, position=(np.nan, 0, 0)),
                                    lv.client.send_image("segmentation", s, rh.wall_labels(), "mono8")),
                     "pose: invalid pose", "[pose] invalid pose: non-finite position"),
    "nan quaternion": (lambda lv, s: lv.client.send_pose(s, quat=(np.nan, 0, 0, 1)),
                       "pose: invalid pose", "[pose] invalid pose: non-finite quaternion"),
    "non-unit quaternion": (lambda lv, s: lv.client.send_pose(s, quat=(0, 0, 0, 2.0)),
                            "pose: invalid pose", "has norm 2 outside"),
    "zero quaternion": (lambda lv, s: lv.client.send_pose(s, quat=(0, 0, 0, 0)),
                        "pose: invalid pose", "has norm 0 outside"),
    "stamp out of order": (lambda lv, s: (lv.client.send_pose(lv.last_frame - 10**8), lv.client.send_image(
        "segmentation", lv.last_frame - 10**8, rh.wall_labels(), "mono8")),
        "segmentation: stamp out of order", "stamp out of order"),
    "pose gap": (lambda lv, s: (lv.client.send_image("segmentation", s, rh.wall_labels(), "mono8"),
                                time.sleep(0.1), lv.client.send_pose(s + 2_500_000_000)),
                 "segmentation: pose gap", "not interpolated across"),
    "stamp in the future": (lambda lv, s: (lv.client.send_pose(time.time_ns() + 3600 * 10**9), lv.client.send_image(
        "segmentation", time.time_ns() + 3600 * 10**9, rh.wall_labels(), "mono8")),
        "segmentation: stamp in the future", "ahead of the node clock"),
    "invalid camera_info": (lambda lv, s: lv.client.send_camera_info(s, K_=np.zeros((3, 3))),
                            "camera_info: invalid camera_info", "keeping the previous one"),
    "bad colour image": (lambda lv, s: lv.client.send_image("image", s, np.zeros((3, 3), np.float32), "32FC1"),
                         "image: bad image", "[image] bad image"),
}


@pytest.mark.parametrize("case", list(BAD_INPUTS))
def test_bad_input_warned_counted_and_next_frame_processed(live: Live, case: str) -> None:
    send, key, text = BAD_INPUTS[case]
    before = float(live.client.diagnostics().get(f"warn[{key}]", 0))
    bad_stamp = live.stamp()
    for _ in range(5):
        live.stamp()  # leave room after the bad stamp (the "pose gap" case sends a pose at bad_stamp + 2.5 s)
    send(live, bad_stamp)
    assert live.client.wait_diag(f"warn[{key}]", before + 1) >= before + 1, live.tail()
    assert text in live.node.log()
    assert live.client.wait_stamp("view_uncertainty", bad_stamp, timeout=0.2) is None
    live.frame()  # a good frame afterwards is processed
    assert live.node.proc.poll() is None


def test_label_ids_beyond_classes_ignored_but_frame_processed(live: Live) -> None:
    live.client.call(live.client.reset_client)
    labels = np.full((rh.HEIGHT, rh.WIDTH), 200, np.uint8)  # every id >= C
    key = "warn[segmentation: class ids >= num_classes]"
    before = float(live.client.diagnostics().get(key, 0))
    live.frame(labels)  # processed (SPEC §4: ids >= C contribute nothing and are counted)
    assert live.client.wait_diag(key, before + 1) >= before + 1
    # Nothing was fused: the map is still the uniform prior.
    _, pts = live.query(np.zeros((1, 3)), rh.IDENTITY[None])
    assert pts["u_exp"][0] == pytest.approx(1 - 1 / C, abs=1e-5)
    live.frame()


def test_confidence_is_synchronised_and_weights_the_update(live: Live) -> None:
    live.client.call(live.client.reset_client)
    conf_pub = live.client.confidence_publisher()
    assert rh.RosClient.wait_until(lambda: conf_pub.get_subscription_count() > 0, 10.0)
    time.sleep(0.5)
    # Zero confidence everywhere: frames are processed but add nothing (y_i scaled by 0).
    for _ in range(2):
        stamp = live.stamp()
        live.client.send_image("segmentation_confidence", stamp, np.zeros((rh.HEIGHT, rh.WIDTH), np.float32),
                               "32FC1")
        live.client.send_frame(stamp)
        assert live.client.wait_stamp("view_uncertainty", stamp), live.tail()
    _, pts = live.query(np.zeros((1, 3)), rh.IDENTITY[None])
    assert pts["u_exp"][0] == pytest.approx(1 - 1 / C, abs=1e-5)
    # A bad confidence image is warned about and its frame never completes.
    key = "warn[segmentation_confidence: bad confidence]"
    stamp = live.stamp()
    live.client.send_image("segmentation_confidence", stamp, np.zeros((rh.HEIGHT, rh.WIDTH), np.uint8), "mono8")
    live.client.send_frame(stamp)
    assert live.client.wait_diag(key, 1) >= 1
    # Full confidence: the map learns again.
    stamp = live.stamp()
    live.client.send_image("segmentation_confidence", stamp, np.ones((rh.HEIGHT, rh.WIDTH), np.float32), "32FC1")
    live.client.send_frame(stamp)
    assert live.client.wait_stamp("view_uncertainty", stamp), live.tail()
    _, pts = live.query(np.zeros((1, 3)), rh.IDENTITY[None])
    assert pts["u_exp"][0] < 0.5
    # Without a confidence publisher the node stops waiting for confidence.
    live.client.node.destroy_publisher(conf_pub)
    live.client._conf_pub = None
    time.sleep(1.0)
    live.frame()


def run_nbv_client(live: Live, *args: str) -> tuple[Any, Any, np.ndarray]:
    """css_nbv_client --once (7 candidates, yaws within +-150 deg) around a pose published every 0.1 s.

    Returns (the finished process, the PoseStamped it published on next_best_view, the scores of its request)."""
    import subprocess
    import sys
    import threading

    from geometry_msgs.msg import PoseStamped

    from css_ros.io.clouds import unpack_scored_views

    nbv: list[Any] = []
    sub = live.client.node.create_subscription(PoseStamped, "next_best_view", nbv.append, 10)
    live.frame()
    stop = False

    def keep_publishing_pose() -> None:
        while not stop:
            live.client.send_pose(live.stamp())
            time.sleep(0.1)

    th = threading.Thread(target=keep_publishing_pose, daemon=True)
    th.start()
    try:
        proc = subprocess.run([sys.executable, "-m", "css_ros.clients.nbv_client", "--once", "--num-candidates", "7",
                               "--yaw-range", "150", "--timeout", "20", *args], env=rh.node_env(live.domain),
                              capture_output=True, text=True, timeout=60)
    finally:
        stop = True
        th.join()
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "next best view" in proc.stdout + proc.stderr
    assert rh.RosClient.wait_until(lambda: nbv, 5.0)
    live.client.node.destroy_subscription(sub)
    best = nbv[-1]
    reply = live.client.wait_stamp("candidate_scores", stamp_to_ns(best.header.stamp))
    pts = unpack_scored_views(reply)
    assert len(pts) == 7
    return proc, best, pts


def assert_pose_of_row(pose_msg: Any, pts: np.ndarray, i: int) -> None:
    from css_ros.io.messages import pose_to_arrays

    position, quat = pose_to_arrays(pose_msg.pose)
    np.testing.assert_allclose(position, [pts["x"][i], pts["y"][i], pts["z"][i]], atol=1e-6)
    np.testing.assert_allclose(quat, [pts["qx"][i], pts["qy"][i], pts["qz"][i], pts["qw"][i]], atol=1e-6)


def test_nbv_client_publishes_most_uncertain_candidate(live: Live) -> None:
    _, best, pts = run_nbv_client(live, "--metric", "u_var")
    i = int(np.nanargmax(pts["u_var"]))
    assert_pose_of_row(best, pts, i)
    # Turning away from the mapped wall is more uncertain than the current view (candidate 0).
    assert i != 0 and pts["u_var"][i] > pts["u_var"][0]


def test_nbv_client_picks_the_largest_info_gain_by_default(live: Live) -> None:
    import json

    proc, best, pts = run_nbv_client(live, "--json")
    gain = pts["info_gain"].astype(np.float64)
    assert np.all(np.isfinite(gain)) and np.all(gain >= 0)
    i = int(np.argmax(gain))
    assert_pose_of_row(best, pts, i)
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["metric"] == "info_gain" and out["index"] == i and out["stamp_ns"] == stamp_to_ns(best.header.stamp)
    assert out["info_gain"] == pytest.approx(gain[i], rel=1e-6)
    assert out["current_info_gain"] == pytest.approx(gain[0], rel=1e-6)
    assert f"info gain {gain[i]:.4g}" in proc.stderr + proc.stdout


def test_nbv_client_takes_the_pose_type_of_the_node(live: Live) -> None:
    """css_nbv_client --pose-type odometry reads nav_msgs/Odometry (here remapped to its own topic)."""
    import subprocess
    import sys
    import threading

    from nav_msgs.msg import Odometry

    from css_ros.ros.conversions import header_msg

    pub = live.client.node.create_publisher(Odometry, "odom_for_nbv", 10)
    stop = False

    def keep_publishing() -> None:
        while not stop:
            msg = Odometry(header=header_msg(live.stamp(), "map"), child_frame_id="base_link")
            msg.pose.pose.orientation.w = 1.0
            pub.publish(msg)
            time.sleep(0.1)

    th = threading.Thread(target=keep_publishing, daemon=True)
    th.start()
    try:
        proc = subprocess.run([sys.executable, "-m", "css_ros.clients.nbv_client", "--once", "--num-candidates", "3",
                               "--timeout", "20", "--pose-type", "odometry", "--ros-args", "-r", "pose:=odom_for_nbv"],
                              env=rh.node_env(live.domain), capture_output=True, text=True, timeout=60)
    finally:
        stop = True
        th.join()
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "next best view" in proc.stdout + proc.stderr


def test_clock_reset_accepted_after_consecutive_old_stamps(live: Live) -> None:
    """A replay restarted with older stamps: a few frames are dropped as out of order, then accepted."""
    from css_ros.ros.gate import STAMP_RESET_COUNT

    live.frame()
    old = [live.last_frame // 2 + 12_345_678 + k * 10**8 for k in range(STAMP_RESET_COUNT)]  # unused stamps
    for s in old:
        live.client.send_frame(s)
        time.sleep(0.05)
    assert live.client.wait_stamp("view_uncertainty", old[-1]), live.tail()
    assert all(live.client.wait_stamp("view_uncertainty", s, timeout=0.05) is None for s in old[:-1])
    assert "assuming the clock was reset" in live.node.log()
    live.frame()
