"""Bags with poses on /tf and /tf_static only: css_replay's frame source resolves each frame's camera pose as the TF
lookup map <- the segmentation's frame_id at its stamp (checked against a numpy brute force), and ``css_make_demo
--robot --tf`` replays like the pose-topic robot demo."""
from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from css_ros.evaluation.cli import build_parser, resolve_paths
from css_ros.evaluation.source import FrameSource
from css_ros.demo.robot_demo import make_robot_demo
from css_ros.errors import BagError
from css_ros.io.bag import BagWriter
from css_ros.io.messages import array_to_image_fields
from css_ros.io.topics import BAG_START_NS
from tf_reference import brute_chain, mat, pose_errors

S = 1_000_000_000
PARENTS = {"odom": "map", "base_link": "odom", "camera_link": "base_link", "camera_optical_frame": "camera_link"}


def _tf(writer: BagWriter, topic: str, log_ns: int, entries) -> None:
    T = writer.store.types
    msgs = [T["geometry_msgs/msg/TransformStamped"](
        header=writer.header(stamp, parent), child_frame_id=child,
        transform=T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=float(p[0]), y=float(p[1]), z=float(p[2])),
            rotation=T["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))))
        for parent, child, stamp, p, q in entries]
    writer.write(topic, "tf2_msgs/msg/TFMessage", T["tf2_msgs/msg/TFMessage"](transforms=msgs), log_ns)


def write_tf_bag(path: Path, seed: int = 0):
    """A 2 s bag: map->odom at 50 Hz with a jump at 1 s, odom->base_link at 200 Hz with +-30 % jitter, the camera's
    static chain logged 0.5 s in (after the first segmentations), frames every 0.1 s arriving 0.3 s late, one frame
    in an unknown frame. Returns (dynamic samples per child, static transforms, frames [(stamp, frame_id)])."""
    rng = np.random.default_rng(seed)
    dyn: dict[str, list] = {"odom": [], "base_link": []}
    events = []
    t = BAG_START_NS
    while t < BAG_START_NS + 2 * S + S // 10:
        jumped = t >= BAG_START_NS + S
        p = np.array([0.4, -0.2, 0.0]) if jumped else np.array([0.01, 0.0, 0.0])
        q = Rotation.from_rotvec([0, 0, 0.25 if jumped else 0.01]).as_quat()
        dyn["odom"].append((t, p, q))
        events.append((t + S // 1000, ("map", "odom", t, p, q)))
        t += S // 50
    t = BAG_START_NS
    while t < BAG_START_NS + 2 * S + S // 10:
        s = (t - BAG_START_NS) / S
        p = np.array([0.5 * s, 0.2 * np.sin(s), 0.0])
        q = Rotation.from_rotvec([0.02 * np.sin(3 * s), 0.0, 0.6 * s]).as_quat()
        dyn["base_link"].append((t, p, q))
        events.append((t + S // 500, ("odom", "base_link", t, p, q)))
        t += int(S / 200 * (1 + 0.3 * rng.uniform(-1, 1)))
    static = {"camera_link": (np.array([0.2, 0.0, 1.0]), Rotation.from_euler("zy", [10, 12], degrees=True).as_quat()),
              "camera_optical_frame": (np.zeros(3), np.array([-0.5, 0.5, -0.5, 0.5]))}
    frames = [(BAG_START_NS + S // 20 + k * S // 10, "camera_optical_frame") for k in range(19)]
    frames[7] = (frames[7][0], "ghost_optical")
    K = np.array([[20.0, 0, 15.5], [0, 20.0, 11.5], [0, 0, 1]])
    with BagWriter(path) as w:
        _tf(w, "/tf_static", BAG_START_NS + S // 2,
            [(PARENTS[c], c, BAG_START_NS, *static[c]) for c in static])
        log = sorted([(lg, "tf", e) for lg, e in events] + [(st + 3 * S // 10, "seg", (st, fid)) for st, fid in frames],
                     key=lambda e: e[0])
        for lg, kind, e in log:
            if kind == "tf":
                _tf(w, "/tf", lg, [e])
            else:
                st, fid = e
                w.write_camera_info("/camera_info", K, 32, 24, st, fid)
                for topic in ("/segmentation", "/segmentation_gt"):  # stamped with the image time, logged late
                    f = array_to_image_fields(np.full((24, 32), 1, np.uint8), "mono8")
                    msg = w.store.types["sensor_msgs/msg/Image"](
                        header=w.header(st, fid), height=f["height"], width=f["width"], encoding=f["encoding"],
                        is_bigendian=int(f["is_bigendian"]), step=f["step"], data=f["data"])
                    w.write(topic, "sensor_msgs/msg/Image", msg, lg)
    return dyn, {c: mat(*v) for c, v in static.items()}, frames


def _source(bag: Path, tmp: Path, *extra: str) -> FrameSource:
    (tmp / "model.ply").write_text("unused by the frame source")
    cfg = resolve_paths(build_parser().parse_args([str(bag), "--model", str(tmp / "model.ply"), "--classes", "",
                                                   "--num-classes", "3", "--quiet", *extra]))
    src = FrameSource(cfg)
    src.check()
    return src


def test_a_bag_with_only_tf_gives_every_frame_the_composed_pose(tmp_path: Path) -> None:
    dyn, static, frames = write_tf_bag(tmp_path / "bag")
    src = _source(tmp_path / "bag", tmp_path)
    assert src.pose_source == "tf" and src.present["pose"] is False
    got = {f.stamp_ns: f for f in src.frames()}
    known = [(st, fid) for st, fid in frames if fid != "ghost_optical"]
    assert sorted(got) == [st for st, _ in known]               # every frame with a TF path is mapped
    assert dict(src.skips) == {"tf_unknown_frame": 1}             # the other one says why
    worst = (0.0, 0.0)
    for st, fid in known:
        T = brute_chain(fid, "map", st, PARENTS, dyn, static)
        dp, da = pose_errors(got[st].position_map, got[st].quat_map, T)
        worst = (max(worst[0], dp), max(worst[1], da))
        # the map->odom jump at 1 s: frames after its first sample use the new transform
        if st > BAG_START_NS + S:
            T_odom = brute_chain(fid, "odom", st, PARENTS, dyn, static)
            new, old = mat(*dyn["odom"][-1][1:]), mat(*dyn["odom"][0][1:])
            assert pose_errors(got[st].position_map, got[st].quat_map, new @ T_odom)[0] < 1e-9
            assert pose_errors(got[st].position_map, got[st].quat_map, old @ T_odom)[0] > 0.1
        assert np.allclose(got[st].camera.T_map_cam, T, atol=1e-9)  # identity splat_to_map: the camera is T
    assert worst[0] < 1e-9 and worst[1] < 1e-9


def test_pose_source_options_and_refusals(tmp_path: Path) -> None:
    dyn, static, frames = write_tf_bag(tmp_path / "bag")
    with pytest.raises(BagError, match="no topic '/pose'"):
        _source(tmp_path / "bag", tmp_path, "--pose-source", "topic")
    src = _source(tmp_path / "bag", tmp_path, "--pose-source", "tf", "--map-frame", "odom")
    for f in src.frames():  # the lookup target is map_frame
        dp, da = pose_errors(f.position_map, f.quat_map, brute_chain(f.camera_frame, "odom", f.stamp_ns, PARENTS, dyn,
                                                                      static))
        assert dp < 1e-9 and da < 1e-9 and f.map_frame == "odom"
    # a tf_buffer_s shorter than the segmentation latency: the past is gone when the late frames arrive
    src = _source(tmp_path / "bag", tmp_path, "--tf-buffer-s", "0.1")
    assert list(src.frames()) == [] and src.skips["tf_extrapolation_into_the_past"] == 18


def test_pose_source_tf_on_a_bag_without_tf_and_bad_tf_options_are_refused(tmp_path: Path, capsys) -> None:
    from css_ros.errors import ConfigError
    from css_ros.evaluation.cli import main as replay_main

    demo = Path(__file__).resolve().parents[1] / "bags" / "demo" / "bag"
    with pytest.raises(BagError, match="pose_source tf needs /tf or /tf_static"):
        _source(demo, tmp_path, "--pose-source", "tf")
    assert _source(demo, tmp_path).pose_source == "topic"   # auto: the bag's pose topic
    params = tmp_path / "p.yaml"
    params.write_text("css_node:\n  ros__parameters:\n    tf_buffer_s: -1.0\n")
    with pytest.raises(ConfigError, match="tf_buffer_s must be"):
        _source(demo, tmp_path, "--params", str(params))
    params.write_text("css_node:\n  ros__parameters:\n    pose_source: odometry\n")
    assert replay_main([str(demo), "--params", str(params), "--quiet"]) == 1   # a CssError: one line, exit 1
    assert "pose_source 'odometry': expected auto or one of topic, tf" in capsys.readouterr().err


@pytest.mark.slow
def test_the_tf_robot_demo_replays_like_the_pose_topic_robot_demo(tmp_path: Path) -> None:
    for name, tf in (("pose", False), ("tf", True)):
        make_robot_demo(tmp_path / name, num_gaussians=3000, frames=6, width=64, height=48, progress=False, tf=tf)
    a = _source(tmp_path / "pose" / "bag", tmp_path)
    b = _source(tmp_path / "tf" / "bag", tmp_path)
    assert (a.pose_source, b.pose_source) == ("topic", "tf")
    fa, fb = list(a.frames()), list(b.frames())
    assert len(fa) == len(fb) == 12 and not a.skips and not b.skips
    for x, y in zip(fa, fb):
        assert (x.stamp_ns, x.camera_index) == (y.stamp_ns, y.camera_index)
        dp, da = pose_errors(y.position_map, y.quat_map, mat(x.position_map, x.quat_map))
        assert dp < 1e-9 and da < 1e-9
    metrics = []
    for name in ("pose", "tf"):
        res = subprocess.run([sys.executable, "-m", "css_ros.evaluation.cli", str(tmp_path / name / "bag"), "--out",
                              str(tmp_path / f"out_{name}"), "--quiet", "--no-output-bag"], capture_output=True,
                             text=True, timeout=600)
        assert res.returncode == 0, res.stderr
        metrics.append(json.loads((tmp_path / f"out_{name}" / "metrics.json").read_text()))
    assert metrics[1]["config"]["pose_source"] == "tf"
    assert metrics[0]["frames"]["processed"] == metrics[1]["frames"]["processed"] == 12
    for metric in ("miou", "pixel_accuracy"):
        for what in ("input", "css"):
            assert abs(metrics[0]["segmentation"][what][metric] - metrics[1]["segmentation"][what][metric]) < 1e-9
    # css_calibrate reads the labelled TF bag the same way: the same sensor model (fingerprint of its tables)
    fingerprints = []
    for name in ("pose", "tf"):
        res = subprocess.run([sys.executable, "-m", "css_ros.calibration.cli", str(tmp_path / name / "bag"), "--out",
                              str(tmp_path / f"{name}_sensor.yaml"), "--quiet"], capture_output=True, text=True,
                             timeout=600)
        assert res.returncode == 0, res.stderr
        fingerprints.append(re.search(r"fingerprint ([0-9a-f]{12})", res.stdout + res.stderr).group(1))
    assert fingerprints[0] == fingerprints[1]
