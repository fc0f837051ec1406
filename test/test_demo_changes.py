"""css_make_demo's changing world (css_ros/demo/changes.py): walking people, a class change and the depth topic,
checked on a small generated bag against the splat rendered here and against brute-force geometry."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from css_ros.demo.changes import (PERSON_CLASS, PERSON_RADII, ClassChange, Walker, ellipsoid_depth, encode_depth,
                                  walkers)
from css_ros.demo.make_demo import WorldOptions, main, make_demo
from css_ros.demo.scene import CLASS_NAMES
from css_ros.engine.camera import Camera, intrinsics_from_fov
from css_ros.engine.classes import ClassSet
from css_ros.engine.gaussians import GaussianModel
from css_ros.engine.semantic_map import SemanticMap
from css_ros.errors import CssError
from css_ros.evaluation.config import ReplayConfig
from css_ros.evaluation.source import FrameSource
from css_ros.io.frames import decode_depth

FRAMES = 40
CHANGE = 3                     # the sofa shows in frames 2 and 3 (and later ones) of this 40-frame path


def ply_class_ids(path: Path) -> np.ndarray:
    from plyfile import PlyData

    return np.asarray(PlyData.read(str(path))["vertex"]["class_id"], dtype=np.int64)
SOFA, BOX = CLASS_NAMES.index("sofa"), CLASS_NAMES.index("box")


# ------------------------------------------------------------------------------------------------ geometry
def test_walker_goes_to_and_fro_along_its_path_at_its_speed():
    w = Walker((0.0, 0.0), (3.0, 4.0), speed=1.0, offset=0.0)     # a 5 m path: back at the start after 10 s
    np.testing.assert_allclose(w.position(0.0), [0.0, 0.0, PERSON_RADII[2]])
    np.testing.assert_allclose(w.position(5.0)[:2], [3.0, 4.0])
    np.testing.assert_allclose(w.position(10.0)[:2], [0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(w.position(2.5)[:2], w.position(7.5)[:2])
    ts = np.linspace(0, 30, 601)
    p = np.array([w.position(t)[:2] for t in ts])
    assert np.all(np.abs(p[:, 0] * 4 - p[:, 1] * 3) < 1e-9) and p.min() >= -1e-12 and p[:, 0].max() <= 3 + 1e-12
    step = np.linalg.norm(np.diff(p, axis=0), axis=1)
    assert np.all(step <= 0.05 + 1e-9) and np.median(step) == pytest.approx(0.05)   # 1 m/s, 0.05 s apart
    np.testing.assert_allclose([k.offset for k in walkers("room", 4)], [0.0, 3.7, 7.4, 11.1])


def _camera(w: int = 40, h: int = 30) -> Camera:
    return Camera.look_at(np.array([0.0, -3.0, 1.2]), np.array([0.3, 0.0, 0.9]), intrinsics_from_fov(w, h, 60.0),
                          w, h)


def test_ellipsoid_depth_is_the_first_hit_of_each_ray():
    """Brute force: march every pixel's ray in 1 mm steps of camera z; the first point inside the ellipsoid lies at
    the computed depth (to the step), and rays that never enter it get inf."""
    cam = _camera()
    centre, radii = np.array([0.2, 0.0, 0.87]), np.array(PERSON_RADII)
    got = ellipsoid_depth(cam, centre, radii)
    u, v = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
    rays = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones(u.shape)], axis=-1) @ cam.R_map_cam.T
    zs = np.arange(0.001, 6.0, 0.001)
    first = np.full(u.shape, np.inf)
    for z in zs[::-1]:
        inside = np.sum(((cam.position + z * rays - centre) / radii) ** 2, axis=-1) <= 1.0
        first[inside] = z
    hit = np.isfinite(first)
    assert hit.any() and (~hit).any()
    np.testing.assert_array_equal(np.isfinite(got), hit)
    np.testing.assert_allclose(got[hit], first[hit], atol=1.5e-3)


def test_depth_encodings_read_back_with_the_replay_decoder():
    class Msg:  # a sensor_msgs/Image as the decoder reads it
        def __init__(self, a: np.ndarray, enc: str) -> None:
            self.encoding, self.height, self.width, self.is_bigendian = enc, a.shape[0], a.shape[1], 0
            self.step, self.data = a.shape[1] * a.itemsize, a.tobytes()

    depth = np.array([[0.5, 1.2344, np.nan], [np.inf, 70.0, 2.0]])
    mm = encode_depth(depth, "16UC1")
    assert mm.dtype == np.uint16 and mm.tolist() == [[500, 1234, 0], [0, 65535, 2000]]
    back = decode_depth(Msg(mm, "16UC1")).metres()
    np.testing.assert_allclose(back[~np.isnan(back)], [0.5, 1.234, 65.535, 2.0], rtol=1e-6)
    assert np.isnan(back[0, 2]) and np.isnan(back[1, 0])
    m = decode_depth(Msg(encode_depth(depth, "32FC1"), "32FC1")).metres()
    np.testing.assert_array_equal(np.isnan(m), [[False, False, True], [True, False, False]])
    np.testing.assert_allclose(m[0, :2], [0.5, 1.2344], rtol=1e-6)
    with pytest.raises(CssError, match="--depth-encoding"):
        encode_depth(depth, "mono8")


@pytest.mark.parametrize("text, frame, says", [
    ("sofa", None, "expected FROM:TO"), ("sofa:sofa", None, "two different classes"),
    ("sofa:person", None, "two different classes"), ("sofa:box", 0, "--change-frame must be in 1..9"),
    ("sofa:box", 10, "--change-frame must be in 1..9")])
def test_class_change_refusals(text, frame, says):
    with pytest.raises(CssError, match=says):
        ClassChange.parse(text, CLASS_NAMES, frame, 10)
    assert ClassChange.parse("sofa:box", CLASS_NAMES, None, 10) == ClassChange(SOFA, BOX, 5)


# ------------------------------------------------------------------------------------------------ the bag
@pytest.fixture(scope="module")
def world(tmp_path_factory):
    root = tmp_path_factory.mktemp("world")
    stats = make_demo(root, num_gaussians=6000, frames=FRAMES, width=64, height=48, seed=0, progress=False,
                      world=WorldOptions(people=3, change="sofa:box", change_frame=CHANGE, depth="32FC1"))
    classes = ClassSet.from_yaml(root / "classes.yaml")
    cfg = ReplayConfig(bag=root / "bag", model=root / "model.ply", classes=root / "classes.yaml", out=root / "x",
                       num_classes=classes.num_classes, quiet=True, output_bag=False)
    source = FrameSource(cfg)
    source.check()
    return root, stats, classes, list(source.frames())


def test_person_class_is_added_and_never_in_the_splat_or_the_static_truth(world):
    root, stats, classes, frames = world
    assert classes.names == (*CLASS_NAMES, PERSON_CLASS) and stats.num_classes == len(CLASS_NAMES) + 1
    person = len(CLASS_NAMES)
    assert ply_class_ids(root / "model.ply").max() < person
    assert len(frames) == FRAMES and all(f.gt is not None and f.depth is not None for f in frames)
    assert not any((f.gt == person).any() for f in frames)
    shown = [f for f in frames if (f.labels == person).any()]
    assert len(shown) == stats.person_frames >= 2
    assert sum(int((f.labels == person).sum()) for f in frames) == pytest.approx(stats.person_share * FRAMES * 64 * 48)


def test_depth_is_the_splats_own_with_the_people_in_front(world):
    """Where no person is, /depth equals the splat's expected depth rendered here (the map's own RenderedView.depth);
    on every person pixel it is nearer than that (or the splat has none there)."""
    root, _, classes, frames = world
    smap = SemanticMap(GaussianModel.from_ply(root / "model.ply"), classes.num_classes)
    person = len(CLASS_NAMES)
    for f in frames:
        room = smap.render(f.camera, outputs=("depth",)).depth
        mask = f.labels == person
        assert f.depth is not None and room is not None
        np.testing.assert_array_equal(f.depth[~mask], room[~mask])
        nearer = f.depth[mask] < room[mask]
        assert np.all(nearer | np.isnan(room[mask]))
        assert np.all(f.depth[mask] > 0.05)
        # people drawn in the colour image too, never beyond the depth of the room behind them
        assert f.confidence is not None and np.all(f.confidence[mask] == np.float32(0.9))


def test_the_sofa_becomes_a_box_half_way(world):
    """/segmentation_gt_changed marks the sofa's pixels (rendered here from the PLY's class ids) with "box" in every
    frame; the static ground truth shows the sofa there before frame CHANGE and the box from it on (and no sofa
    anywhere after it)."""
    root, stats, classes, frames = world
    assert stats.change_frame == CHANGE
    model = GaussianModel.from_ply(root / "model.ply")
    ids = ply_class_ids(root / "model.ply")
    truth = SemanticMap(model, len(CLASS_NAMES), prior=1e-3, unknown_threshold=0.5)
    truth.concentrations[np.arange(model.num_gaussians), ids] = 1e4
    seen, sofa_before = [0, 0], 0
    for f in frames:
        assert f.gt_changed is not None and set(np.unique(f.gt_changed)) <= {BOX, 255}
        sofa = truth.render(f.camera, outputs=("labels",)).labels == SOFA
        obj = f.gt_changed == BOX
        assert (obj ^ sofa).sum() <= 0.02 * max(1, sofa.sum()) + 2    # edges: the renderer drops the prior share
        if f.index >= CHANGE:
            assert np.all(f.gt[obj] == BOX)
        else:   # the sofa, and at a few edge pixels a neighbour that the sofa's share turns into "box" at the end
            assert not (f.gt[obj] == BOX).any()
            sofa_before += int((f.gt[obj] == SOFA).sum())
        assert not (f.gt == SOFA)[~obj].any() if f.index >= CHANGE else True
        seen[f.index >= CHANGE] += int(obj.sum())
    assert seen[0] > 20 and seen[1] > 100 and sofa_before >= 0.9 * seen[0]


def test_readme_and_metadata_say_what_changes(world):
    root, stats, _, _ = world
    text = (root / "README.md").read_text()
    assert f"--people 3 --change-class sofa:box --change-frame {CHANGE} --depth --overwrite" in text
    assert f"from frame {CHANGE} on, every Gaussian of class `sofa` has class `box`" in text
    assert "| `/depth` | sensor_msgs/Image 32FC1 |" in text and "| `/segmentation_gt_changed` |" in text
    assert f"they show in {stats.person_frames} of {FRAMES} frames" in text
    meta = (root / "bag" / "metadata.yaml").read_text()
    assert '\\"people\\": 3' in meta or '"people": 3' in meta


@pytest.mark.parametrize("argv, says", [
    (["--change-frame", "3"], "--change-frame needs --change-class"),
    (["--people", "1", "--robot"], "--robot supports only"),
    (["--change-class", "sofa:nope"], "expected FROM:TO"),
    (["--change-class", "cabinet:box"], "relabelled by a systematic rule"),
    (["--people", "-1"], "--people must be >= 0"),
])
def test_cli_refusals(tmp_path, capsys, argv, says):
    assert main(["--out", str(tmp_path / "d"), "--num-gaussians", "1500", "--frames", "4", "--width", "32",
                 "--height", "24", "--quiet", *argv]) == 2
    assert says in capsys.readouterr().err
    assert not (tmp_path / "d" / "bag").exists()


def test_cli_writes_16uc1_depth(tmp_path):
    from rosbags.highlevel import AnyReader

    out = tmp_path / "d"
    assert main(["--out", str(out), "--num-gaussians", "1500", "--frames", "3", "--width", "32", "--height", "24",
                 "--quiet", "--people", "1", "--depth", "--depth-encoding", "16UC1"]) == 0
    with AnyReader([Path(out / "bag")]) as reader:
        msgs = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages()
                if c.topic == "/depth"]
    assert len(msgs) == 3 and {m.encoding for m in msgs} == {"16UC1"}
    depth = decode_depth(msgs[0]).metres()
    assert np.nanmin(depth) > 0.1 and np.nanmax(depth) < 12.0
