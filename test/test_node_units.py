"""Unit tests of css_node's ROS-free parts: work queue, warning limiter, pose conversion, parameters."""
from __future__ import annotations

import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from css_ros.engine.camera import body_to_optical_rotation, quaternion_xyzw_to_matrix
from css_ros.errors import CssError
from css_ros.io.paths import resolve_data_path
from css_ros.io.frames import FrameRejected, decode_pose
from css_ros.engine.camera import Camera
from css_ros.engine.similarity import Similarity
from css_ros.io.frame_gate import GateFrame
from css_ros.ros.params import NodeParams, check_params
from css_ros.ros.work import FrameJob, WarnLimiter, WorkQueue

#: camera_extrinsics of an optical frame at a REP-103 body's origin (the former body_to_optical: true).
BODY_TO_OPTICAL_EXTRINSICS = [0.0, 0.0, 0.0, -0.5, 0.5, -0.5, 0.5]


def _frame(i: int, cam: int = 0) -> FrameJob:
    z = np.zeros(3)
    camera = Camera(K=np.eye(3), width=1, height=1, T_map_cam=np.eye(4))
    return FrameJob(GateFrame(cam, i, "cam", "map", np.zeros((1, 1), np.int32), None, None, camera, z,
                              np.array([0.0, 0, 0, 1]), "exact", 0.0), 0.0)


def test_work_queue_newest_frames_win():
    q = WorkQueue(max_frames=2)
    dropped = [q.put_frame(_frame(i)) for i in range(5)]
    assert [d.stamp_ns for d in dropped if d is not None] == [0, 1, 2]
    assert [q.get(0).stamp_ns, q.get(0).stamp_ns] == [3, 4]
    assert q.get(0.01) is None


def test_work_queue_alternates_so_nothing_starves():
    q = WorkQueue(max_frames=10, max_requests=10)
    for i in range(3):
        q.put_frame(_frame(i))
        q.put_request(f"req{i}")  # type: ignore[arg-type]
    order = [q.get(0) for _ in range(6)]
    kinds = ["f" if isinstance(j, FrameJob) else "r" for j in order]
    # A request never waits behind more than one frame, and frames keep flowing between requests.
    assert kinds == ["f", "r", "f", "r", "f", "r"]


def test_work_queue_serves_cameras_round_robin():
    """A camera sending 6x as many frames does not starve the other: each get alternates between cameras."""
    q = WorkQueue(max_frames=2)
    for i in range(12):
        q.put_frame(_frame(i, cam=0))
        if i % 6 == 0:
            q.put_frame(_frame(100 + i, cam=1))
    got = [q.get(0) for _ in range(4)]
    assert [j.camera_index for j in got] == [0, 1, 0, 1]
    assert [j.stamp_ns for j in got] == [10, 100, 11, 106]   # newest wins per camera (2 kept each)


def test_work_queue_close_wakes_consumer():
    q = WorkQueue(max_frames=1)
    out = []
    t = threading.Thread(target=lambda: out.append(q.get(10.0)))
    t.start()
    time.sleep(0.05)
    q.close()
    t.join(2.0)
    assert not t.is_alive() and out == [None]


def test_warn_limiter_counts_everything_logs_rarely():
    lines: list[str] = []
    warn = WarnLimiter(lines.append, period=60.0)
    for _ in range(5):
        warn("pose", "non-unit quaternion", "x")
    warn("segmentation", "bad segmentation")
    warn("pose", "frame_id differs", dropped=False)
    counts, dropped = warn.snapshot()
    assert counts["pose: non-unit quaternion"] == 5
    assert dropped == {"pose": 5, "segmentation": 1}
    assert len(lines) == 3  # one per key within the period
    assert lines[0].startswith("[pose] non-unit quaternion")


def test_warn_limiter_reports_suppressed_after_period():
    lines: list[str] = []
    warn = WarnLimiter(lines.append, period=0.05)
    for _ in range(4):
        warn("image", "bad image")
    time.sleep(0.06)
    warn("image", "bad image")
    assert len(lines) == 2 and "+3 similar" in lines[1]


def test_body_to_optical_extrinsics_match_rep103():
    """The README's migration of body_to_optical: these extrinsics are REP-103's optical frame in the body."""
    ext = Similarity.rigid_from_params(BODY_TO_OPTICAL_EXTRINSICS)
    # Body frame = map frame (identity): the optical axes in the map are z fwd = +x, x right = -y, y down = -z.
    _, q = ext.compose_pose(np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]))
    R = quaternion_xyzw_to_matrix(q)
    np.testing.assert_allclose(R, body_to_optical_rotation(), atol=1e-12)
    np.testing.assert_allclose(R[:, 2], [1, 0, 0], atol=1e-12)
    # A body yawed by 90 degrees (facing +y) looks along +y.
    yaw = np.array([0.0, 0.0, np.sin(np.pi / 4), np.cos(np.pi / 4)])
    R = quaternion_xyzw_to_matrix(ext.compose_pose(np.zeros(3), yaw)[1])
    np.testing.assert_allclose(R[:, 2], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(R[:, 1], [0, 0, -1], atol=1e-12)


@pytest.mark.parametrize("q, ok", [((0, 0, 0, 1), True), ((0, 0, 0, 1.05), True), ((0, 0, 0, 2), False),
                                   ((0, 0, 0, 0), False), ((np.nan, 0, 0, 1), False)])
def test_pose_quaternion_rule(q, ok):
    """The quaternion rule of the shared decoder (norm within QUATERNION_NORM_TOLERANCE, finite)."""
    o = SimpleNamespace(x=q[0], y=q[1], z=q[2], w=q[3])
    msg = SimpleNamespace(pose=SimpleNamespace(position=SimpleNamespace(x=0.0, y=0.0, z=0.0), orientation=o))
    try:
        decode_pose(msg)
        accepted = True
    except FrameRejected:
        accepted = False
    assert accepted == ok


@pytest.mark.parametrize("field, value", [("input_qos", "fast"), ("backend", "opencl"), ("prior", 0.0),
                                          ("queue_size", 0), ("sync_slop", -1.0), ("output_scale", float("nan")),
                                          ("camera_extrinsics", [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 2.0]),
                                          ("camera_extrinsics", [0.0, 1.0]),
                                          ("splat_to_map", [0.0, 0, 0, 0, 0, 0, 0, 1]),
                                          ("splat_to_map", [float("inf"), 0, 0, 0, 0, 0, 0, 1]),
                                          ("pose_type", "tf"), ("pose_wait", float("nan")), ("max_pose_gap", 0.0),
                                          ("cameras", ["front", "front"]), ("cameras", []),
                                          ("cameras", ["1bad"])])
def test_check_params_rejects(field, value):
    p = NodeParams()
    setattr(p, field, value)
    with pytest.raises(CssError, match=field):
        check_params(p)


def test_resolve_data_path(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "m.ply").write_text("x")
    assert resolve_data_path("m.ply") == tmp_path / "m.ply"
    # Relative to the source tree when not in the working directory.
    assert resolve_data_path("css_ros/node.py") == Path(__file__).resolve().parents[1] / "css_ros" / "node.py"
    assert resolve_data_path(str(tmp_path / "abs.ply")) == tmp_path / "abs.ply"


@pytest.mark.parametrize("case", ["missing model", "corrupt model", "missing class file", "bad parameter",
                                  "wrong parameter type"])
def test_start_up_errors_are_clean_fatal_exits(tmp_path, case):
    import subprocess
    import sys

    import ros_helpers as rh

    model = rh.write_wall_model(tmp_path / "wall.ply")
    params = {"model_path": str(model), "class_file": "", "num_classes": "3", "warmup": "false",
              "checkpoint_path": ""}
    expect = ""
    if case == "missing model":
        params["model_path"] = expect = str(tmp_path / "nope" / "model.ply")
    elif case == "corrupt model":
        bad = tmp_path / "corrupt.ply"
        bad.write_bytes(model.read_bytes()[:400])
        params["model_path"] = expect = str(bad)
    elif case == "missing class file":
        params["class_file"] = expect = str(tmp_path / "classes.yaml")
    elif case == "bad parameter":
        params["input_qos"], expect = "fastest", "input_qos"
    else:
        params["prior"], expect = "lots", "prior"
    args = [sys.executable, "-m", "css_ros.node", "--ros-args"]
    for k, v in params.items():
        args += ["-p", f"{k}:={v if v != '' else chr(39) * 2}"]
    res = subprocess.run(args, env=rh.node_env(rh.next_domain_id()), capture_output=True, text=True, timeout=120)
    out = res.stdout + res.stderr
    assert res.returncode == 2, out
    assert "FATAL" in out and expect in out and "Traceback" not in out


class _AnswerNode:
    """What OutputPublisher uses of an rclpy Node: publishers whose subscriber count the test sets."""

    def __init__(self) -> None:
        self.subscribers = 0
        self.published: dict[str, list] = {}
        self.fail = False

    def get_clock(self):
        return None

    def create_timer(self, _period, _callback):
        return None

    def create_publisher(self, _type, name, _qos, event_callbacks=None):
        topic = name.removeprefix("~/")
        self.published[topic] = []

        def publish(msg) -> None:
            if self.fail:
                raise RuntimeError("writer gone")
            self.published[topic].append(msg)
        return SimpleNamespace(publish=publish, get_subscription_count=lambda: self.subscribers)


def test_answers_wait_for_a_reader_and_every_one_ends_in_a_counter(monkeypatch):
    """No reader matched: an answer is held (answers_held), written in order once one matches (<kind>_served), given
    up after ANSWER_HOLD_S or beyond request_queue_size held (<kind>_unanswered[...]); a publish that raises is counted
    unanswered, not raised. Served + unanswered = answers made, whatever happens."""
    pytest.importorskip("rclpy")
    from css_ros.engine.classes import ClassSet
    from css_ros.ros import outputs as out
    from css_ros.ros.diagnostics import Stats

    clock = [100.0]
    monkeypatch.setattr(out.time, "monotonic", lambda: clock[0])
    stats = Stats()
    node = _AnswerNode()
    p = NodeParams(request_queue_size=3, cloud_period=0.0)
    pub = out.OutputPublisher(node, p, ClassSet.default(4), count=stats.count)

    def answer(i: int) -> None:
        header = SimpleNamespace(stamp=SimpleNamespace(sec=0, nanosec=i), frame_id="map")
        pub.publish_scores(header, np.zeros((1, 3)), np.array([[0.0, 0, 0, 1]]), *(np.zeros(1),) * 3)

    def ids() -> list[int]:
        return [m.header.stamp.nanosec for m in node.published["candidate_scores"]]

    for i in range(1, 6):                   # 5 answers, 3 may wait: the 2 oldest are given up
        answer(i)
    counts = stats.snapshot()[0]
    assert pub.held_answers() == 3 and counts["answers_held[candidate_scores]"] == 5
    assert counts[f"requests_unanswered[{out.NO_SUBSCRIBER}]"] == 2 and ids() == []
    node.subscribers = 1
    pub.release_answers()                   # a reader matched (the matched event calls it)
    assert ids() == [3, 4, 5] and stats.snapshot()[0]["requests_served"] == 3 and pub.held_answers() == 0
    answer(6)                               # a reader is there: written at once
    assert ids() == [3, 4, 5, 6]
    node.subscribers = 0
    answer(7)
    clock[0] += out.ANSWER_HOLD_S + 0.5
    pub.release_answers()                   # the timer: held too long
    node.fail = True
    node.subscribers = 1
    answer(8)                               # the middleware refuses the write
    counts = stats.snapshot()[0]
    assert counts[f"requests_unanswered[{out.NO_SUBSCRIBER}]"] == 3
    assert counts[f"requests_unanswered[{out.PUBLISH_FAILED}]"] == 1
    assert counts["requests_served"] + 3 + 1 == 8 and pub.held_answers() == 0
