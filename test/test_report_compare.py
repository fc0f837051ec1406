"""report.md: the paper's update and the sensor model side by side (one run), the explanations of the uncertainty
numbers and plots, and one default output folder per update."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from css_ros.engine.classes import ClassSet
from css_ros.evaluation import report
from css_ros.evaluation.calibration_metrics import calibration_summary
from css_ros.evaluation.comparison import comparison_rows
from css_ros.evaluation.replay import default_out_dir
from test_report import full_metrics


def _cal(ece_e, ece_c=None):
    rec = {"expectation": {"ece": ece_e, "brier": 0.1, "mean_confidence": 0.8, "accuracy": 0.7}, "confidence": None}
    if ece_c is not None:
        rec["confidence"] = {"ece": ece_c, "brier": 0.1, "mean_confidence": 0.7, "accuracy": 0.7}
    return rec


def with_paper(names):
    m = full_metrics(names)
    seg = m["segmentation"]
    seg["css_online"] = {"miou": 0.55, "pixel_accuracy": 0.64, "per_class_iou": {}}
    m["pixel_sparsification"]["ause"]["confidence"] = 0.02
    m["calibration"] = {"online": _cal(0.133, 0.029), "fused": _cal(0.14, 0.034)}
    m["paper_update"] = {
        "segmentation": {"online": {"miou": 0.5, "pixel_accuracy": 0.605}, "fused": {"miou": 0.45,
                                                                                     "pixel_accuracy": 0.659}},
        "pixel_sparsification": {"ause": {"expectation": 0.197, "variance": 0.212, "evidence": 0.005,
                                          "random": 0.27, "oracle": 0.0}},
        "calibration": {"online": _cal(0.186), "fused": _cal(0.2)},
    }
    return m


def _rows(lines):
    return {r.split(" | ")[0].lstrip("| "): [c.strip(" |") for c in r.split(" | ")[1:]] for r in lines[2:]}


def test_comparison_rows_put_each_measure_side_by_side():
    m = with_paper(["a", "b"])
    lines = comparison_rows(m)
    assert lines[0] == "| measure | input segmentation | paper update | sensor model |"
    rows = _rows(lines)
    # input: only the online measures exist (its labels are the online input); bold: the better update
    assert rows["online pixel accuracy (the per-frame `~/semantic`), %"] == ["80.0", "60.5", "**64.0**"]
    assert rows["fused pixel accuracy (every pose rendered with the final map), %"] == ["—", "65.9", "**90.0**"]
    assert rows["fused mIoU, %"] == ["—", "45.0", "**60.0**"]
    assert rows["pixel AUSE of E (fused renders)"] == ["—", "0.1970", "**0.0100**"]   # lower is better
    assert rows["pixel AUSE of the observation count (-evidence)"] == ["—", "**0.0050**", "0.0300"]
    assert rows["pixel AUSE of the calibrated confidence"] == ["—", "—", "0.0200"]
    assert rows["pixel AUSE of a random ordering (reference)"] == ["—", "0.2700", "0.0500"]  # never bold
    assert rows["ECE of E, online renders"] == ["—", "0.1860", "**0.1330**"]
    assert rows["ECE of the calibrated `~/confidence`, online renders"] == ["—", "—", "0.0290"]
    assert rows["ECE of the calibrated `~/confidence`, fused renders"] == ["—", "—", "0.0340"]
    assert len(rows) == 13


def test_no_comparison_without_the_paper_baseline(tmp_path: Path):
    m = full_metrics(["a", "b"])
    assert comparison_rows(m) == []
    text = report.write_markdown(tmp_path, m, []).read_text()
    assert "Paper update vs the sensor model" not in text


def test_report_explains_the_uncertainty_numbers_and_plots(tmp_path: Path):
    names = [f"class_{i}" for i in range(3)]
    m = with_paper(names)
    rng = np.random.default_rng(0)
    conf = rng.uniform(0, 1, 5000)
    real = calibration_summary(conf, rng.uniform(0, 1, 5000) < conf)
    m["calibration"] = {"online": {"expectation": real, "confidence": real}, "fused": {"expectation": real}}
    plots = report.make_plots(tmp_path, m, [], ClassSet.default(3), 255)
    plots.insert(0, ("from above", "birdseye.png"))
    text = report.write_markdown(tmp_path, m, plots).read_text()
    assert "### Paper update vs the sensor model (same frames, one run)" in text
    guide = text[text.index("## How to read the uncertainty numbers"):]
    for term in ("**U_var**", "**U_exp**", "**evidence**", "**E**", "**Var**", "**Sparsification**", "**AUSE**",
                 "**Reliability diagram**", "**ECE**"):
        assert term in guide, term
    assert "Good:" in guide and "0.05" in guide   # what a good value is
    for fname in ("sparsification.png", "image_uncertainty.png", "reliability.png", "birdseye.png"):
        after = text[text.index(f"]({fname})"):]
        caption = after.split("\n\n")[1]
        assert caption and not caption.startswith("#"), fname
    assert "white is unobserved" in text


def test_default_output_folder_is_named_for_the_update(tmp_path: Path):
    bag = tmp_path / "demo_range" / "bag"
    bag.mkdir(parents=True)
    assert default_out_dir(bag) == Path("out/replay_demo_range")
    assert default_out_dir(bag, Path("models/sensor_model.yaml")) == Path("out/replay_demo_range_sensor_model")
    assert default_out_dir(tmp_path / "demo_range") == Path("out/replay_demo_range")
