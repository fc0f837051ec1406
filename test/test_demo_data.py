"""Tests of the demo data generator: procedural scene, trajectory, segmentation noise and the written bag."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from css_ros.engine.camera import Camera, intrinsics_from_fov, quaternion_xyzw_to_matrix
from css_ros.engine.classes import ClassSet
from css_ros.demo.scene import (CLASS_NAMES, ROOM_MAX, ROOM_MIN, build_indoor_scene, build_scene_arrays,
                                demo_class_set, obstacle_footprints)
from css_ros.demo.segmentation_noise import SegmentationNoise, confusion_matrix
from css_ros.demo.trajectory import robot_trajectory

REPO = Path(__file__).resolve().parents[1]
CID = {n: i for i, n in enumerate(CLASS_NAMES)}


@pytest.fixture(scope="module")
def scene():
    return build_scene_arrays(20_000, seed=3)


# ------------------------------------------------------------------------------------------------ scene
def test_scene_has_all_classes_and_exact_count(scene):
    assert len(CLASS_NAMES) >= 12
    assert scene.means.shape == (20_000, 3)
    counts = np.bincount(scene.class_ids, minlength=len(CLASS_NAMES))
    assert len(counts) == len(CLASS_NAMES) and np.all(counts > 0), dict(zip(CLASS_NAMES, counts))
    assert np.all(np.isfinite(scene.means)) and np.all(scene.scales > 0)
    # everything is inside the room (plus the millimetre normal noise)
    assert np.all(scene.means >= ROOM_MIN - 0.01) and np.all(scene.means <= ROOM_MAX + 0.01)


def _axes(quats_wxyz: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) from (w, x, y, z) quaternions (columns = the Gaussian's principal axes)."""
    return quaternion_xyzw_to_matrix(np.concatenate([quats_wxyz[:, 1:], quats_wxyz[:, :1]], axis=1))


def test_gaussians_are_flat_and_aligned_with_their_surface(scene):
    s = scene.scales
    ratio = s[:, 2] / s[:, :2].max(axis=1)
    assert np.all(ratio < 0.35) and np.median(ratio) < 0.1
    R = _axes(scene.quats_wxyz)
    normal_axis = R[:, :, 2]  # the axis of scale_2 (the small one)
    leaves = np.array([p.foliage for p in scene.primitives])[scene.primitive_ids]
    for k, p in enumerate(scene.primitives):
        sel = (scene.primitive_ids == k)
        if not sel.any() or p.foliage:
            continue
        x = scene.means[sel] - p.center
        local = x @ p.frame  # coordinates along e1, e2, e3
        if p.kind == "rect":
            n = p.frame[:, 2]
            assert np.all(np.abs(local[:, 2]) < 0.008), p.name                 # on the plane
            assert np.all(np.abs(local[:, 0]) <= p.size[0] + 1e-6), p.name    # inside the rectangle
            assert np.all(np.abs(local[:, 1]) <= p.size[1] + 1e-6), p.name
            assert np.all(np.abs(normal_axis[sel] @ n) > 0.999), p.name       # flat side along the normal
        elif p.kind == "cylinder":
            radial = np.hypot(local[:, 0], local[:, 1])
            assert np.all(np.abs(radial - p.size[0]) < 0.008), p.name
            assert np.all(np.abs(local[:, 2]) <= p.size[1] + 1e-6), p.name
            radial_dir = (local[:, 0:1] * p.frame[:, 0] + local[:, 1:2] * p.frame[:, 1]) / radial[:, None]
            assert np.all(np.abs(np.sum(normal_axis[sel] * radial_dir, axis=1)) > 0.99), p.name
        elif p.kind == "disc":
            assert np.all(np.abs(local[:, 2]) < 0.008), p.name
            assert np.all(np.hypot(local[:, 0], local[:, 1]) <= p.size[0] + 1e-6), p.name
    assert leaves.any()  # the plants' leaves are the only volumetric part


def test_floor_holes_and_known_objects(scene):
    floor = scene.class_ids == CID["floor"]
    assert np.all(np.abs(scene.means[floor, 2]) < 0.008)
    # no floor Gaussians hidden under the rug (a pretrained splat has none there)
    x0, y0, x1, y1 = obstacle_footprints()["rug"]
    under = floor & (scene.means[:, 0] > x0 + 0.1) & (scene.means[:, 0] < x1 - 0.1) & \
        (scene.means[:, 1] > y0 + 0.1) & (scene.means[:, 1] < y1 - 0.1)
    assert not under.any()
    ceiling = scene.class_ids == CID["ceiling"]
    assert np.all(np.abs(scene.means[ceiling, 2] - ROOM_MAX[2]) < 0.008)
    outlets = scene.means[scene.class_ids == CID["outlet"]]
    assert np.all(outlets[:, 2] < 1.3)  # outlets sit low on the walls
    # thin lamp poles are still covered densely enough (spacing below their diameter)
    pole = [k for k, p in enumerate(scene.primitives) if p.name.endswith("_pole")]
    assert np.all(np.bincount(scene.primitive_ids, minlength=len(scene.primitives))[pole] > 50)


def test_appearance_is_textured_and_opacity_spread(scene):
    o = scene.opacities
    assert np.all((o > 0) & (o < 1))
    assert np.median(o) > 0.75 and np.mean(o < 0.5) > 0.02
    for name in ("floor", "wall", "sofa", "rug"):
        col = scene.colors[scene.class_ids == CID[name]]
        assert col.std(axis=0).mean() > 0.02, name  # not one flat colour per class
    assert np.all((scene.colors >= 0) & (scene.colors <= 1))


def test_scene_is_deterministic_and_seeded():
    a = build_scene_arrays(3000, seed=5)
    b = build_scene_arrays(3000, seed=5)
    c = build_scene_arrays(3000, seed=6)
    for f in ("means", "scales", "quats_wxyz", "opacities", "colors", "class_ids"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    assert not np.array_equal(a.means, c.means)
    np.testing.assert_array_equal(a.class_ids, c.class_ids)  # same layout, same allocation


def test_build_indoor_scene_returns_model_and_labels():
    model, labels = build_indoor_scene(4000, seed=1)
    assert model.num_gaussians == 4000 and labels.shape == (4000,)
    assert np.issubdtype(labels.dtype, np.integer) and labels.min() >= 0 and labels.max() < len(CLASS_NAMES)
    ref = build_scene_arrays(4000, seed=1)
    np.testing.assert_allclose(model.means, ref.means, atol=1e-6)
    np.testing.assert_allclose(model.scales, ref.scales, rtol=1e-5)
    np.testing.assert_allclose(model.opacities, np.clip(ref.opacities, 1e-6, 1 - 1e-6), atol=1e-5)


def test_class_file_matches_scene():
    cs = ClassSet.from_yaml(REPO / "config" / "demo_classes.yaml")
    ref = demo_class_set()
    assert cs.names == ref.names == CLASS_NAMES
    np.testing.assert_array_equal(cs.palette, ref.palette)
    assert len({tuple(c) for c in cs.palette}) == cs.num_classes  # distinct colours


# ------------------------------------------------------------------------------------------------ rendering
def _renderer(num_gaussians: int = 30_000):
    from css_ros.demo.renderer import DemoRenderer

    s = build_scene_arrays(num_gaussians, seed=0)
    model, _ = build_indoor_scene(num_gaussians, seed=0)
    return s, DemoRenderer(model, s.class_ids, len(CLASS_NAMES))


@pytest.fixture(scope="module")
def renderer():
    return _renderer()


def test_surfaces_are_covered_without_holes(renderer):
    _, r = renderer
    tr = robot_trajectory(12)
    K = intrinsics_from_fov(128, 96, 64.0)
    for i in range(0, 12, 3):
        view = r.smap.render(Camera(K, 128, 96, tr.T_map_cam[i]))
        assert np.mean(view.background > 0.5) == 0.0
        assert view.background.mean() < 0.08


def test_gt_labels_match_the_visible_surface_looking_down_at_the_rug_corner(renderer):
    """Camera 1 m above the floor looking straight down at the rug's north-west corner: each pixel's label must
    be the class of the first surface hit by its ray (rug inside the rectangle, floor outside)."""
    _, r = renderer
    W, H = 96, 72
    K = intrinsics_from_fov(W, H, 64.0)
    pos = np.array([0.6, -0.4, 1.0])
    cam = Camera.look_at(pos, pos - [0, 0, 1.0], K, W, H, up=(0.0, 1.0, 0.0))
    _, gt, biased = r.render(cam)
    np.testing.assert_array_equal(gt, biased)  # no systematic rule active
    # ray / ground-plane intersection per pixel (brute force)
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, dtype=float)], -1)
    d = rays @ cam.R_map_cam.T
    t = -pos[2] / d[..., 2]
    hit = pos + t[..., None] * d
    x0, y0, x1, y1 = obstacle_footprints()["rug"]
    inside = (hit[..., 0] > x0) & (hit[..., 0] < x1) & (hit[..., 1] > y0) & (hit[..., 1] < y1)
    expected = np.where(inside, CID["rug"], CID["floor"])
    edge_dist = np.minimum(np.abs(hit[..., 0] - x0), np.abs(hit[..., 1] - y1))  # metres to the rug edges in view
    far = edge_dist > 0.06  # ~4 px at this distance: Gaussians blur the edge
    assert inside.any() and (~inside).any()
    assert np.mean(gt[far] == expected[far]) > 0.98
    assert set(np.unique(gt)) <= {CID["rug"], CID["floor"]}


def test_systematic_rules_relabel_only_their_objects():
    from css_ros.demo.renderer import DemoRenderer, systematic_rule_masks
    from css_ros.demo.segmentation_noise import DEFAULT_SYSTEMATIC

    s = build_scene_arrays(30_000, seed=0)
    model, _ = build_indoor_scene(30_000, seed=0)
    masks, targets = systematic_rule_masks(s, CLASS_NAMES, DEFAULT_SYSTEMATIC)
    assert all(m.any() for m in masks)
    r = DemoRenderer(model, s.class_ids, len(CLASS_NAMES), masks, targets)
    K = intrinsics_from_fov(96, 72, 64.0)
    cam = Camera.look_at((1.4, 1.0, 1.0), (1.4, 3.0, 0.6), K, 96, 72)  # facing the cabinet
    _, gt, biased = r.render(cam, [True, False, False, False, False])
    cab = gt == CID["cabinet"]
    assert cab.sum() > 100
    assert np.all(biased[cab] == CID["shelf"])
    np.testing.assert_array_equal(biased[~cab], gt[~cab])


# ------------------------------------------------------------------------------------------------ trajectory
def test_trajectory_is_smooth_safe_and_at_robot_height():
    tr = robot_trajectory(120)
    p = tr.positions
    assert np.all(p[:, 2] > 0.9) and np.all(p[:, 2] < 1.2)
    assert np.all(p[:, :2] > ROOM_MIN[:2] + 0.8) and np.all(p[:, :2] < ROOM_MAX[:2] - 0.8)
    for name, (x0, y0, x1, y1) in obstacle_footprints().items():
        if name == "rug":
            continue  # a robot drives over the rug
        dx = np.maximum(np.maximum(x0 - p[:, 0], p[:, 0] - x1), 0.0)
        dy = np.maximum(np.maximum(y0 - p[:, 1], p[:, 1] - y1), 0.0)
        assert np.min(np.hypot(dx, dy)) > 0.25, name
    R = tr.T_map_cam[:, :3, :3]
    np.testing.assert_allclose(R @ np.transpose(R, (0, 2, 1)), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)
    # optical frame: the image's "down" (y) points downwards in the map, pitch within +-25 deg
    assert np.all(R[:, 2, 1] < 0)
    assert np.all(np.abs(np.degrees(np.arcsin(R[:, 2, 2]))) < 25)
    step = np.linalg.norm(np.diff(p, axis=0), axis=1)
    turn = np.degrees(np.arccos(np.clip(np.einsum("fi,fi->f", R[1:, :, 2], R[:-1, :, 2]), -1, 1)))
    assert step.max() < 0.35 and turn.max() < 20.0
    # accelerations of a mobile robot (< 1 m/s^2; the times are uniform)
    dt = tr.times[1] - tr.times[0]
    assert np.max(np.linalg.norm(np.diff(p, n=2, axis=0), axis=1)) / dt ** 2 < 1.0
    # quaternions agree with the matrices
    np.testing.assert_allclose(quaternion_xyzw_to_matrix(tr.quaternions_xyzw), R, atol=1e-9)
    assert np.all(np.diff(tr.times) > 0)


def _in_view(tr, points: np.ndarray, W: int = 160, H: int = 120) -> np.ndarray:
    K = intrinsics_from_fov(W, H, 64.0)
    out = np.zeros(len(tr), dtype=bool)
    for i in range(len(tr)):
        uv, z = Camera(K, W, H, tr.T_map_cam[i]).project(points)
        ok = (z > 0.1) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        out[i] = ok.mean() > 0.5
    return out


def test_trajectory_has_a_late_part_and_revisits(scene):
    tr = robot_trajectory(120)
    shelf = scene.means[scene.class_ids == CID["shelf"]]
    seen = _in_view(tr, shelf)
    assert seen.any()
    first = int(np.argmax(seen))
    assert first > 0.6 * len(tr) and np.all(tr.phase[seen] == 3)
    sofa = scene.means[scene.class_ids == CID["sofa"]]
    s = _in_view(tr, sofa)
    # the sofa is seen in at least two separate stretches at least 20 frames apart
    idx = np.nonzero(s)[0]
    assert idx.size and np.max(np.diff(idx)) > 20


# ------------------------------------------------------------------------------------------------ noise
def _synthetic_gt(H: int = 120, W: int = 160) -> np.ndarray:
    gt = np.full((H, W), CID["wall"], dtype=np.uint8)
    gt[:15] = CID["ceiling"]
    gt[80:] = CID["floor"]
    gt[30:80, 10:40] = CID["door"]
    gt[25:45, 60:90] = CID["picture"]
    gt[70:74, 100:103] = CID["outlet"]
    gt[60:100, 110:150] = CID["table"]
    gt[85:110, 60:90] = CID["chair"]
    gt[100:, :20] = CID["rug"]
    gt[:4, -6:] = 255
    return gt


def test_noise_error_rate_confusions_and_confidence():
    gt = _synthetic_gt()
    noise = SegmentationNoise(CLASS_NAMES, seed=1)
    C = len(CLASS_NAMES)
    P = confusion_matrix(CLASS_NAMES)
    errs, pairs, wrong_conf, right_conf = [], np.zeros((C, C)), [], []
    outlet_missing = 0
    for t in range(24):
        lab, conf = noise.apply(gt, t)
        assert lab.dtype == np.uint8 and conf.dtype == np.float32 and lab.shape == gt.shape == conf.shape
        assert np.all((conf >= 0) & (conf <= 1))
        np.testing.assert_array_equal(lab == 255, gt == 255)
        valid = gt != 255
        e = (lab != gt) & valid
        errs.append(e.sum() / valid.sum())
        np.add.at(pairs, (gt[e].astype(int), lab[e].astype(int)), 1)
        wrong_conf.append(conf[e])
        right_conf.append(conf[valid & ~e])
        outlet_missing += np.mean(lab[gt == CID["outlet"]] == CID["wall"]) > 0.5
    errs = np.array(errs)
    assert 0.05 < errs.mean() < 0.35, errs
    assert errs.max() > 1.3 * errs.min()  # some frames are worse than others
    on_pairs = pairs[P > 0].sum() / pairs.sum()
    density = (P > 0).sum() / (C * C - C)
    assert on_pairs > 3 * density, (on_pairs, density)  # confusions follow the look-alike table
    assert np.mean(np.concatenate(wrong_conf)) < np.mean(np.concatenate(right_conf)) - 0.1
    assert outlet_missing >= 3  # the small outlet vanishes into the wall in some frames


def test_noise_is_deterministic_random_access_and_temporally_coherent():
    gt = _synthetic_gt()
    a = SegmentationNoise(CLASS_NAMES, seed=4)
    b = SegmentationNoise(CLASS_NAMES, seed=4)
    lab7, conf7 = a.apply(gt, 7)
    b.apply(gt, 3)  # order of calls does not matter
    lab7b, conf7b = b.apply(gt, 7)
    np.testing.assert_array_equal(lab7, lab7b)
    np.testing.assert_array_equal(conf7, conf7b)
    other, _ = SegmentationNoise(CLASS_NAMES, seed=5).apply(gt, 7)
    assert not np.array_equal(lab7, other)

    def err(t):
        return a.apply(gt, t)[0] != gt

    def iou(x, y):
        return (x & y).sum() / max(1, (x | y).sum())

    near = np.mean([iou(err(t), err(t + 1)) for t in range(0, 40, 8)])
    far = np.mean([iou(err(t), err(t + 30)) for t in range(0, 40, 8)])
    assert near > far + 0.1, (near, far)


def test_noise_ignores_unknown_class_names():
    P = confusion_matrix(["a", "wall", "ceiling"])
    np.testing.assert_allclose(P, [[0, 0, 0], [0, 0, 1], [0, 1, 0]])
    lab, conf = SegmentationNoise(["a", "b"], seed=0).apply(np.zeros((40, 50), dtype=np.uint8), 0)
    assert lab.shape == (40, 50) and np.all(lab < 2)


# ------------------------------------------------------------------------------------------------ bag
@pytest.fixture(scope="module")
def tiny_demo(tmp_path_factory):
    from css_ros.demo.make_demo import make_demo

    out = tmp_path_factory.mktemp("demo")
    stats = make_demo(out, num_gaussians=3000, frames=4, width=64, height=48, seed=0, progress=False)
    return out, stats


def test_tiny_bag_reads_back_with_all_topics(tiny_demo):
    from rosbags.highlevel import AnyReader

    from css_ros.engine.gaussians import GaussianModel
    from css_ros.io.messages import image_to_array, stamp_to_ns

    out, stats = tiny_demo
    assert (out / "bag" / "metadata.yaml").is_file() and list((out / "bag").glob("*.mcap"))
    expected = {
        "/image": ("sensor_msgs/msg/Image", "rgb8"),
        "/segmentation": ("sensor_msgs/msg/Image", "mono8"),
        "/segmentation_confidence": ("sensor_msgs/msg/Image", "32FC1"),
        "/segmentation_gt": ("sensor_msgs/msg/Image", "mono8"),
        "/camera_info": ("sensor_msgs/msg/CameraInfo", None),
        "/pose": ("geometry_msgs/msg/PoseStamped", None),
    }
    stamps: dict[str, list[int]] = {t: [] for t in expected}
    arrays: dict[str, list[np.ndarray]] = {t: [] for t in expected}
    poses = []
    with AnyReader([out / "bag"]) as reader:
        assert {c.topic: c.msgtype for c in reader.connections} == {t: v[0] for t, v in expected.items()}
        for conn, log_ns, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            ns = stamp_to_ns(msg.header.stamp)
            assert ns == log_ns
            stamps[conn.topic].append(ns)
            enc = expected[conn.topic][1]
            if enc is not None:
                assert msg.encoding == enc and msg.header.frame_id == "camera_optical"
                assert (msg.width, msg.height) == (64, 48)
                arrays[conn.topic].append(image_to_array(msg))
            elif conn.topic == "/camera_info":
                assert (msg.width, msg.height) == (64, 48) and msg.header.frame_id == "camera_optical"
                K = np.asarray(msg.k).reshape(3, 3)
                np.testing.assert_allclose(K, intrinsics_from_fov(64, 48, 64.0))
            else:
                assert msg.header.frame_id == "map"
                q = msg.pose.orientation
                assert abs(math.sqrt(q.x ** 2 + q.y ** 2 + q.z ** 2 + q.w ** 2) - 1) < 1e-9
                poses.append((msg.pose.position, q))
    ref = stamps["/image"]
    assert len(ref) == 4 and len(set(ref)) == 4 and ref == sorted(ref)
    for t in expected:
        assert stamps[t] == ref, t  # every topic once per frame, same stamps
    for seg, gt, conf in zip(arrays["/segmentation"], arrays["/segmentation_gt"], arrays["/segmentation_confidence"]):
        assert seg.dtype == np.uint8 and conf.dtype == np.float32
        assert set(np.unique(gt)) <= set(range(len(CLASS_NAMES))) | {255}
        assert np.all((conf >= 0) & (conf <= 1))
    # the poses are the trajectory's optical-frame poses T_map_cam
    traj = robot_trajectory(4, seed=0)
    for i, (p, q) in enumerate(poses):
        np.testing.assert_allclose([p.x, p.y, p.z], traj.positions[i], atol=1e-12)
        np.testing.assert_allclose(quaternion_xyzw_to_matrix([q.x, q.y, q.z, q.w]), traj.T_map_cam[i][:3, :3],
                                   atol=1e-9)
    model = GaussianModel.from_ply(out / "model.ply")
    assert model.num_gaussians == 3000
    np.testing.assert_allclose(np.linalg.norm(model.normals, axis=1), 1.0, atol=1e-5)
    cs = ClassSet.from_yaml(out / "classes.yaml")
    assert cs.names == CLASS_NAMES
    assert (out / "README.md").read_text().count("/segmentation_gt") >= 1
    assert stats.frames == 4 and 0.0 <= stats.noisy_pixel_error < 1.0


def test_generator_output_is_byte_identical(tiny_demo, tmp_path):
    from css_ros.demo.make_demo import make_demo

    out, _ = tiny_demo
    again = tmp_path / out.name
    make_demo(again, num_gaussians=3000, frames=4, width=64, height=48, seed=0, progress=False)
    for rel in ("model.ply", "classes.yaml", "bag/metadata.yaml", "bag/bag.mcap"):
        assert (out / rel).read_bytes() == (again / rel).read_bytes(), rel


def test_cli_refuses_to_overwrite_and_writes_sqlite3(tiny_demo, tmp_path, capsys):
    from rosbags.highlevel import AnyReader

    from css_ros.demo.make_demo import main

    out, _ = tiny_demo
    assert main(["--out", str(out), "--num-gaussians", "3000", "--frames", "2", "--quiet"]) == 2
    assert "exists" in capsys.readouterr().err
    dst = tmp_path / "sq"
    assert main(["--out", str(dst), "--num-gaussians", "3000", "--frames", "2", "--width", "32", "--height", "24",
                 "--storage", "sqlite3", "--quiet"]) == 0
    assert list((dst / "bag").glob("*.db3"))
    with AnyReader([dst / "bag"]) as reader:
        assert sum(c.msgcount for c in reader.connections) == 12


def test_size_estimate_announces_raw_and_bag_size():
    from css_ros.demo.make_demo import size_estimate

    line = size_estimate(1000, 10, 100, 50)  # 10 x 100 x 50 px x (3 + 1 + 1 + 4) bytes = 450 kB
    assert line == "css_make_demo: 10 frames of 100x50 from 1000 Gaussians: 0 MB of images, a bag of about 0 MB"
    big = size_estimate(10**6, 10_000, 1000, 1000)  # 90 GB raw
    assert "90000 MB of images, a bag of about 14400 MB (large" in big
