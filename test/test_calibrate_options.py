"""css_calibrate's options are checked when parsed (named, exit 2, before any file is read), and when no frame can
be counted it says why, per reason (css_ros/calibration/cli.py)."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from css_ros.calibration.cli import main
from css_ros.engine.classes import ClassSet
from css_ros.engine.sensor_model import MAX_DEPTH_BINS
from css_ros.io.bag import BagWriter
from test_replay import H, W, cameras, gt_labels, make_model


@pytest.mark.parametrize("option, value, says", [
    ("--max-depth", "1e6", "outside (0, 1000]"),
    ("--max-depth", "inf", "outside (0, 1000]"),
    ("--max-depth", "nan", "outside (0, 1000]"),
    ("--max-depth", "-2", "outside (0, 1000]"),
    ("--bin-width", "0", "outside (0, 1000]"),
    ("--bin-width", "1e-9", f"more than {MAX_DEPTH_BINS}"),
    ("--bin-width", "0.01", f"800 depth bins, more than {MAX_DEPTH_BINS}"),
    ("--bin-width", "9", "must be larger than --bin-width 9"),
    # 8 / 1e-320 and 1000 / 4e-306 overflow to inf: math.ceil raised OverflowError, a traceback with exit 1
    ("--bin-width", "1e-320", f"gives far more than {MAX_DEPTH_BINS} depth bins"),
    ("--bin-width", "4e-306", f"gives far more than {MAX_DEPTH_BINS} depth bins"),
    ("--pseudo-count", "inf", "outside [0, 1e+09]"),
    ("--pseudo-count", "-1", "outside [0, 1e+09]"),
    ("--weight-floor", "nan", "outside [0, 1]"),
    ("--weight-floor", "1.5", "outside [0, 1]"),
    ("--heldout-every", "-3", "outside [0, 1e+06]"),
    ("--heldout-every", "2.5", "'2.5' is not an integer"),
    ("--heldout-every", "1", "--heldout-every must be 0 (none) or >= 2"),
    ("--out", "x.txt", "expected a .yaml file"),
])
def test_every_option_is_checked_when_parsed(tmp_path, capsys, option, value, says):
    """A bad value is a usage error naming the option (exit 2 at once): the bag does not even exist, so nothing
    else could have refused it; --max-depth 1e6 and --bin-width 1e-9 no longer run for minutes or allocate GBs."""
    argv = [str(tmp_path / "no_such_bag"), "--out", str(tmp_path / "sm.yaml"), option, value]
    if option == "--out":
        argv = argv[:2] + [str(tmp_path / value)]
    start = time.monotonic()
    assert main(argv) == 2
    assert time.monotonic() - start < 5.0
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("css_calibrate: error:") and option in err[-1] and says in err[-1], err[-1]
    assert list(tmp_path.iterdir()) == []


def _bag(root: Path, gt_kind: str, n: int = 3) -> Path:
    """test_replay's wall scene (3 classes), its ground truth made unusable in one way per bag."""
    root.mkdir(parents=True)
    make_model().to_ply(root / "model.ply")
    ClassSet(("l", "m", "r"), np.array([[200, 0, 0], [0, 200, 0], [0, 0, 200]], np.uint8)).to_yaml(root / "classes.yaml")
    with BagWriter(root / "bag") as bag:
        for i, cam in enumerate(cameras(n)):
            s = 1_700_000_000 * 10**9 + i * 100_000_000
            seg = gt_labels(cam)
            gt, encoding = seg.copy(), "mono8"
            if gt_kind == "ids >= C":
                gt[...] = 7
            elif gt_kind == "rgb8":
                gt, encoding = np.repeat(seg[:, :, None], 3, axis=2), "rgb8"
            elif gt_kind == "aspect":
                gt = np.repeat(seg, 2, axis=0)                 # twice as tall: another aspect ratio
            bag.write_camera_info("/camera_info", cam.K, W, H, s, "camera_optical")
            bag.write_pose("/pose", cam.position, cam.quaternion_xyzw, s, "map")
            bag.write_image("/segmentation", seg, "mono8", s, "camera_optical")
            bag.write_image("/segmentation_gt", gt, encoding, s, "camera_optical")
    return root / "bag"


@pytest.mark.parametrize("gt_kind, reason", [
    ("ids >= C", "3 frames: ground truth holds no class id below 3 (ids 7)"),
    ("rgb8", "3 frames without a ground-truth image (none matched, or it was dropped); 3 messages dropped while "
             "reading (bad gt, e.g. /segmentation_gt: "),
    ("aspect", "3 messages dropped while reading (a ground truth or colour image of another aspect ratio than the "
               "segmentation)"),
])
def test_when_no_frame_counts_the_refusal_says_why_per_reason(tmp_path, capsys, gt_kind, reason):
    bag = _bag(tmp_path / "scene", gt_kind)
    assert main([str(bag), "--out", str(tmp_path / "sm.yaml"), "--quiet", "--no-confidence"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "too few labelled pixels to calibrate: 0" in err[0], err
    assert f"skipped: {reason}" in err[0], err[0]
    assert not (tmp_path / "sm.yaml").exists()
