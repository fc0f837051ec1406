"""css_replay in a changing world, end to end on tiny rosbag2 bags: the measured depth topic, --transient-classes,
--evidence-half-life and the report's changing-world figures, checked against counts made here.

The scene is test_replay's wall (three vertical bands of classes) with two more classes: "person" (a 20 x 20 pixel
rectangle 1.5 m from the camera in some frames, in the segmentation and the depth image, never in the splat or the
ground truth) and "crate" (the right band's class from frame CHANGE on, in the segmentation and the ground truth;
/segmentation_gt_changed marks the right band with it in every frame).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from css_ros.engine.camera import Camera
from css_ros.engine.classes import ClassSet
from css_ros.engine.gaussians import GaussianModel
from css_ros.engine.semantic_map import SemanticMap
from css_ros.evaluation.cli import build_parser, main
from css_ros.io.bag import BagWriter
from test_replay import H, W, WALL_X, cameras, gt_labels, make_model

NAMES = ("left", "middle", "right", "person", "crate")
PERSON, CRATE, RIGHT = 3, 4, 2
N = 8
CHANGE = 5                                   # first frame of the class change
PERSON_FRAMES = (0, 1, 2, 3, 4, 6, 7)         # not the change frame: its surprise compares the crate with the wall
ROWS, COLS = slice(14, 34), slice(22, 42)     # the person's rectangle (400 pixels)
PERSON_DEPTH = 1.5                            # m


def wall_depth(cam: Camera, scale: int = 1) -> np.ndarray:
    """Independent depth along the optical axis [m] of the wall plane x = WALL_X, for the camera's image made
    ``scale`` times larger (pixel centres at integers)."""
    K = Camera(cam.K, W, H, cam.T_map_cam).resized(W * scale, H * scale).K
    u, v = np.meshgrid(np.arange(W * scale), np.arange(H * scale))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(u.shape)], axis=-1)
    return ((WALL_X - cam.position[0]) / (rays @ cam.R_map_cam.T)[..., 0]).astype(np.float32)


def frame_images(i: int, cam: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(segmentation, static ground truth, changed-class ground truth, person mask) of frame ``i``."""
    band = gt_labels(cam)
    gt = np.where((band == RIGHT) & (i >= CHANGE), CRATE, band).astype(np.uint8)
    changed = np.where(band == RIGHT, CRATE, 255).astype(np.uint8)
    person = np.zeros((H, W), bool)
    if i in PERSON_FRAMES:
        person[ROWS, COLS] = True
    return np.where(person, PERSON, gt).astype(np.uint8), gt, changed, person


def write_bag(root: Path, depth_encoding: str | None = "32FC1", depth_scale: int = 1) -> Path:
    """model.ply, classes.yaml and bag/ under ``root``; the depth image ``depth_scale`` times the segmentation's
    size (None: no depth topic). Returns the bag folder."""
    root.mkdir(parents=True)
    make_model().to_ply(root / "model.ply")
    palette = np.array([[200, 50, 50], [50, 200, 50], [50, 50, 200], [255, 0, 255], [150, 100, 50]], np.uint8)
    ClassSet(NAMES, palette).to_yaml(root / "classes.yaml")
    with BagWriter(root / "bag", storage="sqlite3") as bag:
        for i, cam in enumerate(cameras(N)):
            s = 1_700_000_000 * 10**9 + i * 100_000_000
            seg, gt, changed, _ = frame_images(i, cam)
            bag.write_camera_info("/camera_info", cam.K, W, H, s, "camera_optical")
            bag.write_pose("/pose", cam.position, cam.quaternion_xyzw, s, "map")
            bag.write_image("/segmentation", seg, "mono8", s, "camera_optical")
            bag.write_image("/segmentation_gt", gt, "mono8", s, "camera_optical")
            bag.write_image("/segmentation_gt_changed", changed, "mono8", s, "camera_optical")
            if depth_encoding is not None:
                depth = wall_depth(cam, depth_scale)
                if i in PERSON_FRAMES:
                    rows = slice(ROWS.start * depth_scale, ROWS.stop * depth_scale)
                    depth[rows, COLS.start * depth_scale:COLS.stop * depth_scale] = PERSON_DEPTH
                if depth_encoding == "16UC1":
                    depth = np.rint(depth * 1000).astype(np.uint16)
                bag.write_image("/depth", depth, depth_encoding, s + 3_000_000, "camera_optical")  # 3 ms late
    return root / "bag"


def replay(bag: Path, out: Path, *extra: str) -> dict:
    assert main([str(bag), "--out", str(out), "--quiet", "--no-output-bag", *extra]) == 0
    return json.loads((out / "metrics.json").read_text())


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    root = tmp_path_factory.mktemp("changes")
    return {"depth": write_bag(root / "depth"), "mm2x": write_bag(root / "mm2x", "16UC1", 2),
            "none": write_bag(root / "none", None), "root": root}


@pytest.fixture(scope="module")
def runs(bags):
    root = bags["root"]
    return {"paper": (replay(bags["none"], root / "paper"), root / "paper"),
            "transient": (replay(bags["none"], root / "transient", "--transient-classes", "person"), None),
            "depth": (replay(bags["depth"], root / "depth_run"), None),
            "mm2x": (replay(bags["mm2x"], root / "mm2x_run"), None),
            "forget": (replay(bags["none"], root / "forget", "--evidence-half-life", "0.5"), root / "forget")}


PERSON_PIXELS = len(PERSON_FRAMES) * 400


def test_depth_holds_back_exactly_the_person_pixels(runs):
    """Every fused person pixel is nearer than the wall by far more than the tolerance (1.5 m against ~3 m): the
    update counts all of them occluded, none else; 16UC1 millimetres at twice the size (nearest neighbour) give the
    same; without depth nothing is occluded, with --transient-classes they are transient instead."""
    for key in ("depth", "mm2x"):
        cw = runs[key][0]["changing_world"]
        assert cw["fused_pixels_without_evidence"] == {"transient": 0, "occluded": PERSON_PIXELS}, key
        assert cw["rules"]["depth_topic"] == "/depth"
    assert runs["paper"][0]["changing_world"]["fused_pixels_without_evidence"] == {"transient": 0, "occluded": 0}
    assert runs["paper"][0]["changing_world"]["rules"]["depth_topic"] is None
    held = runs["transient"][0]["changing_world"]["fused_pixels_without_evidence"]
    assert held == {"transient": PERSON_PIXELS, "occluded": 0}


def test_transient_share_with_and_without_the_rules(runs):
    """The person stands in 7 of 8 frames at one place: the paper's map shows it there; with the person transient or
    held back by depth no Gaussian ever gets a person vote, so not one rendered pixel is a person."""
    paper = runs["paper"][0]["changing_world"]["transient_share"]
    assert paper["classes"] == ["person"] and "static ground truth never does" in paper["basis"]
    assert paper["value"] > 0.5 * 400 / (W * H)
    for key in ("transient", "depth", "mm2x"):
        ts = runs[key][0]["changing_world"]["transient_share"]
        assert ts["value"] == 0.0 and ts["pixels"] == 0, key
    assert runs["transient"][0]["changing_world"]["transient_share"]["basis"].startswith("the map's transient")


def _recount(out: Path) -> dict:
    """The figures counted here: the saved final map rendered at every frame's pose."""
    model = GaussianModel.from_ply(out.parent / "none" / "model.ply")
    smap = SemanticMap.load(out / "map.npz", model)
    n = {k: np.zeros(2, np.int64) for k in ("static", "others", "changed", "after")}
    for i, cam in enumerate(cameras(N)):
        lab = smap.render(cam, outputs=("labels",)).labels
        _, gt, changed, _ = frame_images(i, cam)
        obj = changed != 255
        for key, mask, truth in (("static", np.ones_like(obj), gt), ("others", ~obj, gt), ("changed", obj, changed),
                                 ("after", obj & (gt == changed), changed)):
            n[key] += (int(((lab == truth) & mask).sum()), int(mask.sum()))
    return {k: v[0] / v[1] for k, v in n.items()}


@pytest.mark.parametrize("run", ["paper", "forget"])
def test_accuracies_match_a_frame_by_frame_count(runs, run):
    metrics, out = runs[run]
    cw = metrics["changing_world"]
    expect = _recount(out)
    assert cw["static_accuracy"]["value"] == pytest.approx(expect["static"], abs=1e-12)
    assert cw["others_accuracy"]["value"] == pytest.approx(expect["others"], abs=1e-12)
    assert cw["changed_accuracy"]["value"] == pytest.approx(expect["changed"], abs=1e-12)
    assert cw["changed_accuracy_after"]["value"] == pytest.approx(expect["after"], abs=1e-12)
    assert cw["static_accuracy"]["value"] == pytest.approx(metrics["segmentation"]["css"]["pixel_accuracy"])


def test_forgetting_follows_the_change_and_the_paper_does_not(runs):
    """5 frames of "right", then 3 of "crate": the paper's evidence keeps the old class; with a half-life of half an
    observation the old evidence is gone after the change."""
    paper = runs["paper"][0]["changing_world"]["changed_accuracy_after"]["value"]
    forget = runs["forget"][0]["changing_world"]["changed_accuracy_after"]["value"]
    assert paper < 0.5 and forget >= 0.9, (paper, forget)
    assert runs["forget"][0]["changing_world"]["rules"]["evidence_half_life"] == 0.5


def test_surprise_auroc_at_the_first_changed_frame(runs):
    """Frame CHANGE is the first to show the crate: with the person kept off the map its crate pixels (the right
    band, counted here) are more surprising than every other pixel. The paper's map holds the person where it
    stood, so the wall seen there again is surprising too and the AUROC drops below 1."""
    cam = cameras(N)[CHANGE]
    band = gt_labels(cam)
    for key in ("paper", "transient", "depth", "mm2x"):
        sa = runs[key][0]["changing_world"]["surprise_auroc"]
        assert sa["frame"] == CHANGE
        assert sa["changed_pixels"] == int((band == RIGHT).sum())
        assert sa["other_pixels"] == int((band != RIGHT).sum())
        if key != "paper":
            assert sa["value"] == 1.0, key
    paper = runs["paper"][0]["changing_world"]["surprise_auroc"]["value"]
    assert 0.95 <= paper < 1.0


def test_report_states_the_figures_and_the_missing_ones(runs, bags):
    metrics, out = runs["paper"]
    text = (out / "report.md").read_text()
    cw = metrics["changing_world"]
    assert "## A changing world" in text
    assert f"| accuracy vs the static ground truth | {100 * cw['static_accuracy']['value']:.2f} % |" in text
    assert f"| surprise AUROC (frame {CHANGE}) | {cw['surprise_auroc']['value']:.3f} |" in text
    # a bag without the changed-class topic: the figures that need it are n/a with the reason, never left out
    m = replay(bags["none"], bags["root"] / "no_changed", "--gt-changed-topic", "")
    cw = m["changing_world"]
    for key in ("changed_accuracy", "changed_accuracy_after", "others_accuracy", "surprise_auroc"):
        assert cw[key]["value"] is None and "--gt-changed-topic" in cw[key]["reason"], key
    text = (bags["root"] / "no_changed" / "report.md").read_text()
    assert "| changed objects in their new class | n/a (no changed-class ground truth (--gt-changed-topic)" in text


@pytest.mark.parametrize("argv, code, says", [
    (["--transient-classes", "people"], 1, "--transient-classes: 'people' is no class name nor id in 0..4 "
                                           "(classes: 0 left, 1 middle, 2 right, 3 person, 4 crate)"),
    (["--transient-classes", "5"], 1, "'5' is no class name nor id in 0..4"),
    (["--evidence-half-life", "0"], 1, "--evidence-half-life: evidence_half_life must be in [0.01, 1e+09]"),
    (["--evidence-half-life", "soon"], 2, "argument --evidence-half-life: invalid float value: 'soon'"),
    (["--depth-tolerance", "-1"], 1, "--depth-tolerance must be in [0, 100], got -1.0"),
    (["--depth-tolerance-relative", "11"], 1, "--depth-tolerance-relative must be in [0, 10], got 11.0"),
    (["--depth-topic", "/no_depth"], 1, "--depth-topic /no_depth: no such topic in bag"),
])
def test_option_errors_exit_with_one_line(bags, tmp_path, capsys, argv, code, says):
    assert main([str(bags["depth"]), "--out", str(tmp_path / "o"), "--quiet", *argv]) == code
    err = capsys.readouterr().err.strip().splitlines()
    assert says in err[-1], err
    assert not (tmp_path / "o" / "metrics.json").exists()


def test_transient_classes_take_names_and_ids(bags):
    from css_ros.evaluation.cli import resolve_paths

    args = build_parser().parse_args([str(bags["depth"]), "--transient-classes", "person", "4", "3"])
    assert resolve_paths(args).transient_classes == [3, 4]


def test_help_names_the_changing_world_options():
    text = " ".join(build_parser().format_help().split())
    for opt in ("--depth-topic", "--transient-classes", "--evidence-half-life", "--depth-tolerance",
                "--depth-tolerance-relative", "--gt-changed-topic", "16UC1 millimetres or 32FC1 metres"):
        assert opt in text, opt


def test_in_front_of_map_is_the_engines_depth_gate():
    """The calibration's vectorised test equals change_rules.depth_gate pixel by pixel (including no measurement,
    no rendered depth and the relative tolerance)."""
    from css_ros.calibration.learn import in_front_of_map
    from css_ros.engine.change_rules import depth_gate

    rng = np.random.default_rng(3)
    measured = rng.uniform(-1, 6, 4000).astype(np.float32)
    rendered = rng.uniform(0.2, 6, 4000).astype(np.float32)
    measured[::7], measured[1::11], rendered[2::13] = np.nan, np.inf, np.nan
    measured[3::17] = rendered[3::17] - 0.05          # on the tolerance's edge
    got = in_front_of_map(measured, rendered, 0.05, 0.03)
    want = [depth_gate(float(m), float(r), 0.05, 0.03)[0] for m, r in zip(measured, rendered)]
    np.testing.assert_array_equal(got, want)
    assert got.any() and not got.all()


def test_calibrate_leaves_out_what_stands_in_front_of_the_map(bags, tmp_path, capsys):
    """css_calibrate on the wall bag: with its /depth the person pixels (7 frames x 400, counted here) are left out
    of the label statistics, and the confidence pass fuses with the depth; --depth-topic '' counts them."""
    from css_ros.calibration.cli import main as calibrate
    from css_ros.engine.sensor_model import SensorModel

    common = ["--quiet", "--heldout-every", "0", "--bin-width", "1", "--max-depth", "4"]
    assert calibrate([str(bags["depth"]), "--out", str(tmp_path / "d.yaml"), *common]) == 0
    assert f"{PERSON_PIXELS} were in front of the map's surface" in capsys.readouterr().out
    assert calibrate([str(bags["depth"]), "--out", str(tmp_path / "n.yaml"), "--depth-topic", "", *common]) == 0
    with_depth = SensorModel.load(tmp_path / "d.yaml", NAMES).info
    without = SensorModel.load(tmp_path / "n.yaml", NAMES).info
    assert with_depth["pixels_in_front_of_the_map"] == PERSON_PIXELS and without["pixels_in_front_of_the_map"] == 0
    assert without["pixels_fit"] - with_depth["pixels_fit"] == PERSON_PIXELS == 7 * 400
    assert with_depth["pixels_fit"] == N * W * H - PERSON_PIXELS
