"""css_node's input gate and css_replay's frame source accept exactly the same frames of the same messages.

One bag holds a sequence of frames with the defects that used to be treated differently (NaN/inf
confidence, an all-zero K, fx = 1e300, a NaN pose, a non-unit quaternion, a size mismatch, a bad
encoding). The same rosbags messages go through the node's gate (duck-typed, no DDS needed) and through
css_replay's FrameSource; both must keep the frames this test expects from the policy in
css_ros/io/frames.py, with the same confidence values.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from css_ros.evaluation.config import ReplayConfig
from css_ros.evaluation.source import FrameSource
from css_ros.io.bag import BagWriter
from css_ros.ros.gate import InputGate
from css_ros.ros.params import NodeParams
from css_ros.ros.work import WarnLimiter
from test_replay import H, W, cameras, camera_info_msg, image_msg, pose_msg, stamp_of

#: frame index -> defect; frames not listed are clean.
DEFECTS = {1: "nan_confidence", 2: "zero_K", 3: "huge_fx", 4: "nan_pose", 5: "quat_norm_2", 6: "small_seg",
           7: "bad_encoding"}
#: frames the shared policy keeps: non-finite confidence pixels count as 0; an invalid camera_info is refused
#: and the previous one stays; a bad pose sample is dropped and its frame takes the pose interpolated between
#: the neighbouring samples (frames 4 and 5: between frames 3 and 6); a size mismatch and a bad encoding drop
#: the frame.
EXPECTED_KEPT = [0, 1, 2, 3, 4, 5, 8]


def _messages() -> list[tuple[str, object]]:
    msgs = []
    for i, cam in enumerate(cameras(9)):
        s = stamp_of(i)
        defect = DEFECTS.get(i)
        info = camera_info_msg(s)
        if defect == "zero_K":
            info.k = np.zeros(9)
        if defect == "huge_fx":
            info.k = np.array([1e300, 0, (W - 1) / 2, 0, 1e300, (H - 1) / 2, 0, 0, 1])
        pose = pose_msg(cam, s)
        if defect == "nan_pose":
            pose.pose.position.x = float("nan")
        if defect == "quat_norm_2":
            q = pose.pose.orientation
            q.x, q.y, q.z, q.w = 2 * q.x, 2 * q.y, 2 * q.z, 2 * q.w
        labels = np.full((H, W), 1, np.uint8)
        if defect == "small_seg":
            labels = labels[: H // 2]
        seg = image_msg(labels, "mono8", s)
        if defect == "bad_encoding":
            seg.encoding = "weird8"
        conf = np.full((H, W), 0.75, np.float32)
        if defect == "nan_confidence":
            conf[0, :3] = [np.nan, np.inf, -np.inf]
        msgs += [("/camera_info", info), ("/pose", pose), ("/segmentation_confidence", image_msg(conf, "32FC1", s)),
                 ("/segmentation", seg)]
    return msgs


def _replay_frames(tmp_path: Path, messages: list | None = None) -> dict[int, tuple]:
    """stamp -> (confidence, position_map, quat_map) of the frames css_replay's source keeps."""
    bag = tmp_path / "bag"
    types = {"/camera_info": "sensor_msgs/msg/CameraInfo", "/pose": "geometry_msgs/msg/PoseStamped"}
    with BagWriter(bag) as w:
        for k, item in enumerate(messages or [(stamp_of(0) + k, *m) for k, m in enumerate(_messages())]):
            t, topic, msg = item  # log time = arrival time
            w.write(topic, types.get(topic, "sensor_msgs/msg/Image"), msg, t)
    topics = {"image": "", "segmentation": "/segmentation", "confidence": "/segmentation_confidence",
              "camera_info": "/camera_info", "pose": "/pose", "gt": ""}
    src = FrameSource(ReplayConfig(bag=bag, model=tmp_path / "m.ply", classes=None, out=tmp_path, topics=topics))
    src.check()
    return {f.stamp_ns: (f.confidence, f.position_map, f.quat_map) for f in src.frames()}


def _node_frames(messages: list | None = None) -> dict[int, tuple]:
    """The same through the node's gate, its clock following the messages' arrival times."""
    lines: list[str] = []
    clock = [0.0]
    gate = InputGate(NodeParams(), WarnLimiter(lines.append, 0.0), lambda *a: None, lambda: 0, lambda: True,
                     lines.append, monotonic=lambda: clock[0])
    jobs = []
    for t, topic, msg in messages or [(stamp_of(0) + k, *m) for k, m in enumerate(_messages())]:
        clock[0] = t * 1e-9
        jobs += gate.poll()
        if topic == "/camera_info":
            gate.on_camera_info(msg)
        elif topic == "/pose":
            jobs += gate.on_pose(msg)
        elif topic == "/segmentation_confidence":
            jobs += gate.on_confidence(msg)
        else:
            jobs += gate.on_segmentation(msg)
    frames = [j.frame for j in jobs] + gate.frames.flush()   # the bag's end: nothing waits any more
    return {f.stamp_ns: (f.confidence, f.position_map, f.quat_map) for f in frames}


def test_node_and_replay_keep_the_same_frames_with_the_same_confidence(tmp_path):
    replay, node = _replay_frames(tmp_path), _node_frames()
    expected = [stamp_of(i) for i in EXPECTED_KEPT]
    assert sorted(replay) == expected
    assert sorted(node) == expected
    for s in expected:
        for a, b in zip(node[s], replay[s]):
            np.testing.assert_array_equal(a, b)
    conf = node[stamp_of(1)][0]
    assert conf[0, :3].tolist() == [0.0, 0.0, 0.0] and conf[0, 3] == np.float32(0.75)  # NaN/inf count as 0
    truth = cameras(9)
    for i in (0, 1, 2, 3, 8):   # frames with their own valid pose sample: exactly that pose
        np.testing.assert_array_equal(node[stamp_of(i)][1], truth[i].position)


def _robot_messages() -> tuple[list, list]:
    """A robot-like stream: poses at 200 Hz between the camera stamps (each arriving 2 ms after its stamp), image
    and camera_info at the camera stamp, the segmentation and its confidence 300 ms late; 10 frames at 5 Hz.
    The camera moves linearly (x, 1 m/s) and yaws at 45 deg/s, so interpolation is exact; also returns the
    exact optical pose (position, quaternion) at each frame stamp."""
    from css_ros.engine.camera import matrix_to_quaternion_xyzw, quaternion_xyzw_to_matrix
    from test_replay import T

    def truth(t: float) -> tuple[np.ndarray, np.ndarray]:
        yaw = np.radians(45.0) * t
        q_yaw = np.array([0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)])
        R = quaternion_xyzw_to_matrix(q_yaw) @ quaternion_xyzw_to_matrix([-0.5, 0.5, -0.5, 0.5])
        return np.array([1.0 * t, 0.2, 0.1]), matrix_to_quaternion_xyzw(R)

    def pose_at(t_ns: int):
        p, q = truth((t_ns - t0) * 1e-9)
        return T["geometry_msgs/msg/PoseStamped"](
            header=header_of(t_ns), pose=T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2]),
                orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])))

    def header_of(t_ns: int):
        return pose_msg(cameras(1)[0], t_ns).header

    t0 = stamp_of(0)
    msgs, exact = [], []
    for k in range(0, 2 * 200 + 1):       # 2 s of poses at 200 Hz, offset 2.5 ms from the camera stamps
        t = t0 + 2_500_000 + k * 5_000_000
        msgs.append((t + 2_000_000, "/pose", pose_at(t)))
    for i in range(10):
        s = t0 + 50_000_000 + i * 200_000_000
        labels = np.full((H, W), 1, np.uint8)
        msgs.append((s, "/camera_info", camera_info_msg(s)))
        msgs.append((s + 300_000_000, "/segmentation_confidence",
                     image_msg(np.full((H, W), 0.75, np.float32), "32FC1", s)))
        msgs.append((s + 300_000_001, "/segmentation", image_msg(labels, "mono8", s)))
        exact.append((s, *truth((s - t0) * 1e-9)))
    msgs.sort(key=lambda m: m[0])
    return msgs, exact


def test_robot_timing_node_and_replay_interpolate_the_same_poses(tmp_path):
    """Odometry at 200 Hz between the camera stamps and a segmentation 300 ms late: every frame is kept by both,
    with the same pose, interpolated to well under 1 mm / 0.01 deg of the exact one."""
    msgs, exact = _robot_messages()
    replay, node = _replay_frames(tmp_path, msgs), _node_frames(msgs)
    stamps = [s for s, _, _ in exact]
    assert sorted(node) == stamps and sorted(replay) == stamps
    for s, p, q in exact:
        for a, b in zip(node[s], replay[s]):
            np.testing.assert_array_equal(a, b)
        assert np.linalg.norm(node[s][1] - p) < 1e-4
        angle = 2 * np.degrees(np.arccos(min(1.0, abs(float(np.dot(node[s][2], q))))))
        assert angle < 0.01
