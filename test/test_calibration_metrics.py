"""Tests of css_ros.evaluation.calibration_metrics against closed forms and hand-computed values."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from css_ros.evaluation.calibration_metrics import (
    DEFAULT_ECE_BINS,
    ReliabilityBins,
    brier_score,
    calibration_summary,
    expected_calibration_error,
    reliability_bins,
    reliability_figure,
)


def test_perfectly_calibrated_data_has_small_ece():
    rng = np.random.default_rng(0)
    conf = rng.random(1_000_000)
    correct = rng.random(conf.size) < conf
    assert expected_calibration_error(conf, correct) < 0.01


def test_constant_confidence_one_with_accuracy_0_7():
    conf = np.ones(1000)
    correct = np.r_[np.ones(700, bool), np.zeros(300, bool)]
    rb = reliability_bins(conf, correct)
    assert rb.count[-1] == 1000 and rb.count[:-1].sum() == 0  # 1.0 falls in the last bin
    assert expected_calibration_error(conf, correct) == pytest.approx(0.3, abs=1e-12)


def test_two_bin_example_by_hand():
    conf = np.array([0.1, 0.2, 0.4, 0.6, 0.9, 0.5])
    correct = np.array([0, 1, 0, 1, 1, 0])
    rb = reliability_bins(conf, correct, bins=2)
    np.testing.assert_allclose(rb.edges, [0.0, 0.5, 1.0])
    # bin 0 = [0, 0.5): 0.1, 0.2, 0.4 -> conf 0.7/3, acc 1/3; bin 1 = [0.5, 1]: 0.6, 0.9, 0.5 -> conf 2/3, acc 2/3
    assert rb.count.tolist() == [3, 3] and rb.count.dtype == np.int64
    np.testing.assert_allclose(rb.mean_confidence, [0.7 / 3, 2.0 / 3])
    np.testing.assert_allclose(rb.accuracy, [1 / 3, 2 / 3])
    ece = 0.5 * abs(1 / 3 - 0.7 / 3) + 0.5 * abs(2 / 3 - 2 / 3)
    assert expected_calibration_error(conf, correct, bins=2) == pytest.approx(ece, abs=1e-15)
    assert rb.ece() == pytest.approx(ece, abs=1e-15)


def test_nan_handling_and_empty_bins():
    conf = np.array([np.nan, 0.95, 0.95, np.nan, 0.05])
    correct = np.array([1, 1, 0, 0, 0])
    rb = reliability_bins(conf, correct, bins=10)
    assert rb.dropped == 2 and rb.n == 3
    assert np.isnan(rb.accuracy[3]) and np.isnan(rb.mean_confidence[3])
    assert expected_calibration_error(conf, correct, bins=10) == pytest.approx((2 * 0.45 + 0.05) / 3)
    js = rb.to_json()
    json.dumps(js, allow_nan=False)
    assert js["accuracy"][3] is None and js["dropped"] == 2 and len(js["edges"]) == 11
    # nothing valid: NaN scores, a summary that is still valid JSON
    assert np.isnan(expected_calibration_error(np.array([np.nan]), np.array([1])))
    assert np.isnan(brier_score(np.array([]), np.array([])))
    s = calibration_summary(np.array([np.nan, np.nan]), np.array([0, 1]))
    json.dumps(s, allow_nan=False)
    assert s["ece"] is None and s["n"] == 0 and s["dropped"] == 2
    with pytest.raises(ValueError):
        reliability_bins(np.zeros(3), np.zeros(4))


def test_brier_closed_form_and_summary():
    conf = np.array([0.9, 0.6, 0.2, 1.0])
    correct = np.array([True, False, False, True])
    expect = (0.01 + 0.36 + 0.04 + 0.0) / 4
    assert brier_score(conf, correct) == pytest.approx(expect, abs=1e-15)
    s = calibration_summary(conf, correct)
    json.dumps(s, allow_nan=False)
    assert s["brier"] == pytest.approx(expect)
    assert s["mean_confidence"] == pytest.approx(0.675) and s["accuracy"] == pytest.approx(0.5)
    assert s["n"] == 4 and s["dropped"] == 0
    assert s["ece"] == pytest.approx(expected_calibration_error(conf, correct))
    assert len(s["bins"]["count"]) == DEFAULT_ECE_BINS


def test_reliability_figure(tmp_path):
    rng = np.random.default_rng(1)
    conf = rng.random(5000)
    curves: dict[str, ReliabilityBins] = {
        "calibrated confidence": reliability_bins(conf, rng.random(conf.size) < conf),
        "raw expectation": reliability_bins(conf, rng.random(conf.size) < conf**2),
        "empty": reliability_bins(np.array([np.nan]), np.array([1])),
    }
    fig = reliability_figure(curves, "reliability")
    try:
        labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
        assert labels[0] == "perfect calibration"
        assert labels[1].startswith("calibrated confidence (ECE 0.0")
        assert labels[3] == "empty (ECE n/a)"
        assert fig.axes[1].get_xlabel() == "predicted probability that the label is right"
        assert fig.axes[0].get_ylabel() == "observed accuracy"
        fig.savefig(tmp_path / "rel.png")
        assert (tmp_path / "rel.png").stat().st_size > 0
    finally:
        import matplotlib.pyplot as plt

        plt.close(fig)


def test_import_does_not_load_matplotlib():
    code = "import sys, css_ros.evaluation.calibration_metrics\nprint('matplotlib' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"
