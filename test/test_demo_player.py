"""css_demo's first-hour behaviour: clear exits and messages, --save with --start-node, --save-frames."""
from __future__ import annotations

import shutil
import subprocess
import sys

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

import ros_helpers as rh  # noqa: E402

REPO = rh.REPO


def _demo(*args, domain=None, timeout=300):
    return subprocess.run([sys.executable, "-m", "css_ros.demo.player", *args],
                          env=rh.node_env(domain or rh.next_domain_id()), capture_output=True, text=True,
                          timeout=timeout)


def test_no_node_exits_1_and_names_the_topics_without_subscriber():
    res = _demo(str(REPO / "bags/demo/bag"), "--wait", "1.5")
    assert res.returncode == 1, res.stderr  # not SIGABRT (134) from a spin thread left in rcl
    assert "no subscriber on /camera_info, /pose, /image, /segmentation_confidence, /segmentation" in res.stderr


def test_start_node_refuses_a_bag_without_class_file(tmp_path):
    shutil.copytree(REPO / "bags/demo/bag", tmp_path / "bag")
    shutil.copy(REPO / "bags/demo/model.ply", tmp_path / "model.ply")
    res = _demo(str(tmp_path / "bag"), "--start-node", "--wait", "1")
    assert res.returncode == 2
    assert f"class file not found: {tmp_path / 'classes.yaml'} (pass --classes FILE or --num-classes N)" in res.stderr


@pytest.mark.slow
def test_start_node_save_and_save_frames(tmp_path):
    from matplotlib.image import imread

    from css_ros.engine.classes import ClassSet

    demo = tmp_path / "demo"
    made = subprocess.run([sys.executable, "-m", "css_ros.demo.make_demo", "--out", str(demo), "--num-gaussians",
                           "3000", "--frames", "4", "--width", "48", "--height", "36", "--quiet"],
                          env=rh.node_env(0), capture_output=True, text=True, timeout=300)
    assert made.returncode == 0, made.stderr
    frames, npz = tmp_path / "frames", tmp_path / "map.npz"
    res = _demo(str(demo / "bag"), "--start-node", "--rate", "8", "--node-param", "warmup:=false", "--save",
                "--map", str(npz), "--save-frames", str(frames), "--quiet")
    assert res.returncode == 0, res.stdout + res.stderr
    assert "css_node answered 4;" in res.stdout
    assert "save_map: " in res.stdout and npz.is_file()
    data = np.load(npz, allow_pickle=False)
    assert data["concentrations"].shape == (3000, ClassSet.from_yaml(demo / "classes.yaml").num_classes)
    pngs = sorted(p.name for p in frames.iterdir())
    assert pngs == [f"frame_{i:04d}_{k}.png" for i in range(4) for k in ("rendered_image", "semantic_color")]
    palette = {tuple(c) for c in ClassSet.from_yaml(demo / "classes.yaml").palette.tolist()} | {(0, 0, 0)}
    img = np.rint(imread(frames / "frame_0003_semantic_color.png")[..., :3] * 255).astype(int)
    assert img.shape == (36, 48, 3)
    assert {tuple(c) for c in img.reshape(-1, 3).tolist()} <= palette  # only class colours (or black: no label)
