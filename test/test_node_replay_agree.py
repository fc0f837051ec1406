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
#: and the previous one stays; a bad pose, a size mismatch and a bad encoding drop the frame.
EXPECTED_KEPT = [0, 1, 2, 3, 8]


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


def _replay_frames(tmp_path: Path) -> dict[int, np.ndarray]:
    bag = tmp_path / "bag"
    types = {"/camera_info": "sensor_msgs/msg/CameraInfo", "/pose": "geometry_msgs/msg/PoseStamped"}
    with BagWriter(bag) as w:
        for k, (topic, msg) in enumerate(_messages()):  # log times in message order
            w.write(topic, types.get(topic, "sensor_msgs/msg/Image"), msg, stamp_of(0) + k)
    topics = {"image": "", "segmentation": "/segmentation", "confidence": "/segmentation_confidence",
              "camera_info": "/camera_info", "pose": "/pose", "gt": ""}
    src = FrameSource(ReplayConfig(bag=bag, model=tmp_path / "m.ply", classes=None, out=tmp_path, topics=topics))
    src.check()
    return {f.stamp_ns: f.confidence for f in src.frames()}


def _node_frames() -> dict[int, np.ndarray]:
    lines: list[str] = []
    gate = InputGate(NodeParams(), WarnLimiter(lines.append, 0.0), lambda *a: None, lambda: 0, lambda: True,
                     lines.append)
    jobs = []
    for topic, msg in _messages():
        if topic == "/camera_info":
            gate.on_camera_info(msg)
        elif topic == "/pose":
            jobs += gate.on_pose(msg)
        elif topic == "/segmentation_confidence":
            jobs += gate.on_confidence(msg)
        else:
            jobs += gate.on_segmentation(msg)
    return {j.stamp_ns: j.confidence for j in jobs}


def test_node_and_replay_keep_the_same_frames_with_the_same_confidence(tmp_path):
    replay, node = _replay_frames(tmp_path), _node_frames()
    expected = [stamp_of(i) for i in EXPECTED_KEPT]
    assert sorted(replay) == expected
    assert sorted(node) == expected
    for s in expected:
        np.testing.assert_array_equal(node[s], replay[s])
    conf = node[stamp_of(1)]
    assert conf[0, :3].tolist() == [0.0, 0.0, 0.0] and conf[0, 3] == np.float32(0.75)  # NaN/inf count as 0
