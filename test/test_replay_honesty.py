"""css_replay never silently lies: out-of-range labels, contradicting options, misspelled topics, bag folders,
timings without compilation. Each behaviour is checked by its exact message and exit code."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from css_ros.engine.classes import ClassSet
from css_ros.evaluation import cli
from css_ros.evaluation.cli import build_parser, main, resolve_paths
from css_ros.io.bag import BagWriter
from test_replay import C, W, H, cameras, gt_labels, make_model, write_scene

ROOT = Path(__file__).resolve().parents[1]
BAD_ID = 7
BAD_PER_FRAME = 5


def write_bad_gt_scene(root: Path, n: int = 3) -> Path:
    """Like test_replay's scene, but every GT image holds BAD_PER_FRAME pixels with id BAD_ID (not a class)."""
    root.mkdir(parents=True, exist_ok=True)
    make_model().to_ply(root / "model.ply")
    ClassSet(("l", "m", "r"), np.array([[200, 0, 0], [0, 200, 0], [0, 0, 200]], np.uint8)).to_yaml(root / "classes.yaml")
    with BagWriter(root / "bag") as bag:
        for i, cam in enumerate(cameras(n)):
            s = 1_700_000_000 * 10**9 + i * 100_000_000
            gt = gt_labels(cam)
            seg = gt.copy()
            gt = gt.copy()
            gt[0, :BAD_PER_FRAME] = BAD_ID
            bag.write_camera_info("/camera_info", cam.K, W, H, s, "camera_optical")
            bag.write_pose("/pose", cam.position, cam.quaternion_xyzw, s, "map")
            bag.write_image("/segmentation", seg, "mono8", s, "camera_optical")
            bag.write_image("/segmentation_gt", gt, "mono8", s, "camera_optical")
    return root / "bag"


def _run(bag, out, *extra) -> int:
    return main([str(bag), "--out", str(out), "--quiet", "--no-output-bag", "--examples", "0", *extra])


# -------------------------------------------------------------------------------- out-of-range labels
def test_out_of_range_gt_below_threshold_warns_and_is_reported(tmp_path, capsys):
    bag = write_bad_gt_scene(tmp_path / "s")
    assert _run(bag, tmp_path / "o") == 0
    n_bad, n_all = 3 * BAD_PER_FRAME, 3 * W * H
    err = capsys.readouterr().err
    assert (f"css_replay: warning: label ids >= 3 (not a class; ignore_label 255 excluded) in gt: {n_bad} px "
            f"({100 * n_bad / n_all:.2f} % of labelled pixels; ids {BAD_ID}); GT pixels with such ids are excluded "
            "from the metrics, input pixels count as wrong") in err
    m = json.loads((tmp_path / "o" / "metrics.json").read_text())
    oor = m["frames"]["out_of_range_labels"]
    assert oor["kinds"]["gt"] == {"pixels": n_bad, "labelled_pixels": n_all, "share": n_bad / n_all,
                                  "ids": {str(BAD_ID): n_bad}}
    assert oor["kinds"]["segmentation"]["pixels"] == 0 and oor["max_share"] == 0.01
    assert m["segmentation"]["input"]["num_pixels"] == n_all - n_bad  # the excluded pixels are exactly those
    report = (tmp_path / "o" / "report.md").read_text()
    assert f"**out-of-range labels** (gt): {n_bad} of {n_all} labelled pixels" in report


def test_out_of_range_above_threshold_fails_unless_allowed(tmp_path, capsys):
    bag = write_scene(tmp_path / "s", n_frames=3)  # labels 0..2; with 2 classes id 2 is out of range (~1/3)
    assert _run(bag, tmp_path / "o", "--classes", "", "--num-classes", "2") == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0
    assert err.startswith("css_replay: error: label ids >= 2 (not a class; ignore_label 255 excluded) in "
                          "segmentation: ")
    assert err.endswith("more than 1 % of the labelled pixels, so the class file does not fit this bag (GT pixels "
                        "would be dropped from the metrics); fix --classes / --num-classes or --ignore-label, or "
                        "pass --allow-out-of-range")
    assert not (tmp_path / "o" / "metrics.json").exists()
    assert _run(bag, tmp_path / "o", "--classes", "", "--num-classes", "2", "--allow-out-of-range") == 0
    assert "css_replay: warning: label ids >= 2" in capsys.readouterr().err
    m = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert m["frames"]["out_of_range_labels"]["allowed"] is True
    assert m["frames"]["out_of_range_labels"]["kinds"]["gt"]["share"] > 0.2


# ---------------------------------------------------------------------------------- classes options
def test_num_classes_contradicting_class_file_is_an_error(tmp_path, capsys):
    bag = write_scene(tmp_path / "s", n_frames=2)
    assert _run(bag, tmp_path / "o", "--num-classes", "5") == 1
    assert capsys.readouterr().err.strip() == (
        f"css_replay: error: --num-classes 5 contradicts the class file {tmp_path / 's' / 'classes.yaml'} "
        "(3 classes); drop --num-classes or pass --classes ''")
    assert _run(bag, tmp_path / "o", "--num-classes", "3") == 0  # agreeing is fine


def test_anonymous_classes_need_num_classes(tmp_path, capsys):
    bag = write_scene(tmp_path / "s", n_frames=2)
    assert _run(bag, tmp_path / "o", "--classes", "") == 1
    assert capsys.readouterr().err.strip() == "css_replay: error: --classes '' (anonymous classes) needs --num-classes N"
    assert _run(bag, tmp_path / "o", "--classes", "", "--num-classes", str(C)) == 0
    m = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert m["classes"] == ["class_0", "class_1", "class_2"]


# ------------------------------------------------------------------------------------------ topics
@pytest.mark.parametrize("opt,kind", [("--gt-topic", "gt"), ("--confidence-topic", "confidence"),
                                      ("--image-topic", "image")])
def test_misspelled_optional_topic_is_an_error(tmp_path, capsys, opt, kind):
    bag = write_scene(tmp_path / "s", n_frames=2)
    assert _run(bag, tmp_path / "o", opt, "/typo") == 1
    assert capsys.readouterr().err.strip() == (
        f"css_replay: error: {opt} /typo: no such topic in bag {bag}; topics in the bag: /camera_info, /image, "
        "/pose, /segmentation, /segmentation_confidence, /segmentation_gt ('' disables it)")
    assert _run(bag, tmp_path / "o", opt, "") == 0
    m = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert m["frames"]["topics_used"][kind] is None


def test_absent_default_optional_topic_is_still_optional(tmp_path):
    bag = write_scene(tmp_path / "s", n_frames=2, drop_topics=("/image",))
    assert _run(bag, tmp_path / "o") == 0


# -------------------------------------------------------------------------------------- bag folders
def test_folder_holding_one_bag_is_used(tmp_path):
    root = tmp_path / "s"
    write_scene(root, n_frames=2)
    cfg = resolve_paths(build_parser().parse_args([str(root)]))
    assert cfg.bag == root / "bag" and cfg.model == (root / "model.ply").resolve()
    assert _run(root, tmp_path / "o") == 0


def test_demo_folder_finds_its_bag():
    demo = ROOT / "bags" / "demo"
    if not (demo / "bag").is_dir():
        pytest.skip("demo bag not available")
    assert resolve_paths(build_parser().parse_args([str(demo)])).bag == demo / "bag"


def test_folder_with_several_bags_asks(tmp_path, capsys):
    root = tmp_path / "s"
    write_scene(root, n_frames=2)
    write_scene(tmp_path / "t", n_frames=2)
    (tmp_path / "t" / "bag").rename(root / "bag2")
    assert _run(root, tmp_path / "o") == 1
    assert capsys.readouterr().err.strip() == (
        f"css_replay: error: {root} is not a bag but holds several: did you mean {root / 'bag'} or {root / 'bag2'}?")
    empty = tmp_path / "empty"
    empty.mkdir()
    assert _run(empty, tmp_path / "o") == 1
    assert capsys.readouterr().err.strip() == (
        f"css_replay: error: {empty} is not a rosbag2 bag (no metadata.yaml, .mcap or .db3 file) and holds none")


# ------------------------------------------------------------------------------------------ timings
def test_timings_exclude_compilation_and_notice(tmp_path, capsys, monkeypatch):
    bag = write_scene(tmp_path / "s", n_frames=2)
    monkeypatch.setattr(cli, "numba_cache_is_cold", lambda: True)
    assert main([str(bag), "--out", str(tmp_path / "o"), "--no-output-bag"]) == 0
    err = capsys.readouterr().err
    assert err.splitlines()[0] == "css_replay: compiling kernels (first run, ~1 min)"
    m = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert m["timing"]["compilation_excluded"] is True and m["timing"]["warmup_s"] > 0
    assert "warmup_s" not in m["config"]
    assert "timings exclude kernel compilation (kernels warmed up on a tiny frame beforehand" in \
        (tmp_path / "o" / "report.md").read_text()
    assert _run(bag, tmp_path / "o") == 0  # --quiet: no notice
    assert "compiling kernels" not in capsys.readouterr().err
    monkeypatch.setattr(cli, "numba_cache_is_cold", lambda: False)
    assert main([str(bag), "--out", str(tmp_path / "o"), "--no-output-bag"]) == 0
    assert "compiling kernels" not in capsys.readouterr().err
