"""``css_make_demo --robot``: the bag is what a robot stack publishes, checked against the generator's closed forms,
and css_replay maps it with the css_node.yaml written beside it."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from css_ros.demo.robot_demo import (CAMERAS, ODOM_RATE_HZ, SEGMENTATION_LATENCY_S, base_path, camera_extrinsics,
                                     splat_to_map)
from css_ros.demo.scene import build_scene_arrays
from css_ros.engine.gaussians import GaussianModel
from css_ros.engine.similarity import Similarity
from css_ros.io.bag import InputBag
from css_ros.io.messages import stamp_to_ns
from css_ros.io.params_file import read_params_file
from css_ros.io.pose_history import PoseHistory, PosePolicy

pytestmark = pytest.mark.slow

N_GAUSSIANS, FRAMES = 8000, 8


@pytest.fixture(scope="module")
def demo(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("robot_demo")
    res = subprocess.run([sys.executable, "-m", "css_ros.demo.make_demo", "--robot", "--out", str(out), "--frames",
                          str(FRAMES), "--width", "64", "--height", "48", "--num-gaussians", str(N_GAUSSIANS),
                          "--quiet"], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert "replay it with css_replay" in res.stdout
    return out


def test_topics_rates_and_latency_are_robot_like(demo: Path) -> None:
    with InputBag(demo / "bag") as bag:
        topics = bag.topics()
        assert topics["/pose"][0] == "nav_msgs/msg/Odometry"
        odom = [m for m in bag.messages(["/pose"])]
        stamps = np.array([stamp_to_ns(m.msg.header.stamp) for m in odom])
        assert abs(np.median(np.diff(stamps)) * 1e-9 - 1 / ODOM_RATE_HZ) < 1e-6
        assert odom[0].msg.child_frame_id == "base_link"
        for ns in CAMERAS:
            for kind in ("image", "segmentation", "segmentation_confidence", "camera_info", "segmentation_gt"):
                assert topics[f"/{ns}/{kind}"][1] == FRAMES
            for m in bag.messages([f"/{ns}/segmentation"]):
                late = (m.log_time_ns - stamp_to_ns(m.msg.header.stamp)) * 1e-9
                assert abs(late - SEGMENTATION_LATENCY_S) < 1e-6
        front = [stamp_to_ns(m.msg.header.stamp) for m in bag.messages(["/front/segmentation"])]
        left = [stamp_to_ns(m.msg.header.stamp) for m in bag.messages(["/left/segmentation"])]
        assert not set(front) & set(left)   # each camera on its own clock


def test_odometry_with_the_extrinsics_gives_each_frames_camera_pose(demo: Path) -> None:
    """Interpolating the bag's odometry at a segmentation stamp and composing with the written extrinsics gives the
    optical pose the frame was rendered from (the generator's closed form), to 1 mm / 0.05 deg."""
    params = read_params_file(demo / "css_node.yaml")
    assert params["pose_type"] == "odometry" and params["cameras"] == list(CAMERAS)
    ext = params["camera_extrinsics"]
    path = base_path(0)
    history = PoseHistory(PosePolicy(buffer=1e4, max_samples=10**6))  # the whole bag at once
    with InputBag(demo / "bag") as bag:
        for m in bag.messages(["/pose"]):
            p = m.msg.pose.pose
            history.add(stamp_to_ns(m.msg.header.stamp), np.array([p.position.x, p.position.y, p.position.z]),
                        np.array([p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w]))
        t0 = history.oldest_ns
        for c, ns in enumerate(CAMERAS):
            E = Similarity.rigid_from_params(ext[7 * c:7 * c + 7])
            np.testing.assert_allclose(ext[7 * c:7 * c + 7], camera_extrinsics(ns))
            for m in bag.messages([f"/{ns}/segmentation"]):
                s = stamp_to_ns(m.msg.header.stamp)
                look = history.lookup(s, waited=True)
                p, q = E.compose_pose(look.position, look.quat)
                p_true, q_true = path.camera_pose((s - t0) * 1e-9, ns)
                assert np.linalg.norm(p - p_true) < 1e-3
                assert np.degrees(2 * np.arccos(min(1.0, abs(float(np.dot(q, q_true)))))) < 0.05


def test_the_splat_is_in_its_own_frame_and_splat_to_map_brings_it_back(demo: Path) -> None:
    params = read_params_file(demo / "css_node.yaml")
    sim = Similarity.from_params(params["splat_to_map"])
    np.testing.assert_allclose(sim.matrix(), splat_to_map().matrix(), atol=1e-12)
    model = GaussianModel.from_ply(demo / "model.ply")
    truth = build_scene_arrays(N_GAUSSIANS, 0).means
    assert np.max(np.abs(model.means - truth)) > 0.5                      # not the map frame
    np.testing.assert_allclose(sim.apply(model.means), truth, atol=1e-4)  # splat_to_map puts it back


def _replay(bag: Path, out: Path, *extra: str) -> dict:
    res = subprocess.run([sys.executable, "-m", "css_ros.evaluation.cli", str(bag), "--out", str(out), "--quiet",
                          "--no-output-bag", *extra], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr
    return json.loads((out / "metrics.json").read_text())


def test_css_replay_maps_every_frame_of_both_cameras_as_with_the_splat_in_the_map_frame(demo: Path,
                                                                                        tmp_path: Path) -> None:
    """css_replay picks up css_node.yaml and maps every frame; the result equals a replay of the splat moved into
    the map frame with splat_to_map = identity (the frame of the splat does not change what is mapped)."""
    m = _replay(demo / "bag", tmp_path / "own")
    assert m["frames"]["processed"] == 2 * FRAMES and sum(m["frames"]["skipped"].values()) == 0
    assert m["config"]["pose_type"] == "odometry" and m["config"]["cameras"] == list(CAMERAS)
    how = m["frames"]["sync_counts"]   # the first front frame shares the first odometry stamp; the rest interpolate
    assert how.get("pose_exact", 0) + how.get("pose_interpolated", 0) == 2 * FRAMES and how["pose_interpolated"] > 0
    model = GaussianModel.from_ply(demo / "model.ply")
    splat_to_map().transform_model(model).to_ply(tmp_path / "map_frame.ply")
    ref = _replay(demo / "bag", tmp_path / "map", "--model", str(tmp_path / "map_frame.ply"), "--splat-to-map",
                  "1", "0", "0", "0", "0", "0", "0", "1")
    # The input is identical; the renders agree except where the two frames differ on purpose (docs/spec.md "The
    # splat in the map"): the near-plane cull is in splat units (0.01 splat = 2.5 cm here), plus float32 storage.
    for metric in ("miou", "pixel_accuracy"):
        assert m["segmentation"]["input"][metric] == ref["segmentation"]["input"][metric]
        assert abs(m["segmentation"]["css"][metric] - ref["segmentation"]["css"][metric]) < 5e-3
