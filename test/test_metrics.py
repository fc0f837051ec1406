"""Tests of css_ros.evaluation.metrics against hand-computed values, brute force and scipy."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from css_ros.evaluation.metrics import (
    DEFAULT_FRACTIONS,
    ConfusionMatrix,
    PixelSampler,
    ause,
    oracle_curve,
    psnr,
    random_curve,
    rankdata,
    sparsification_curve,
    sparsification_report,
    spearman,
)


def test_confusion_iou_accuracy_hand_example():
    # 3 classes; GT 255 pixels are ignored; a predicted 255 ("no label") is always wrong.
    gt = np.array([[0, 0, 1, 1], [2, 2, 255, 0]])
    pred = np.array([[0, 1, 1, 1], [2, 255, 0, 0]])
    cm = ConfusionMatrix(3, ignore_label=255)
    cm.update(gt, pred)
    # valid pixels: 7. correct: (0,0),(1,1),(1,1),(2,2),(0,0) = 5
    assert cm.num_pixels == 7
    assert cm.pixel_accuracy() == pytest.approx(5 / 7)
    # class 0: GT {p0,p1,p7}, pred {p0,p7 ... }: pred0 at p0, p7 (and p6 is ignored GT) -> TP=2, FN=1 (p1), FP=0 -> 2/3
    # class 1: GT {p2,p3}, pred1 at p1,p2,p3 -> TP=2, FP=1 -> 2/3
    # class 2: GT {p4,p5}, pred2 at p4 -> TP=1, FN=1 (p5 predicted no-label) -> 1/2
    np.testing.assert_allclose(cm.iou(), [2 / 3, 2 / 3, 1 / 2])
    assert cm.miou() == pytest.approx((2 / 3 + 2 / 3 + 1 / 2) / 3)


def test_miou_uses_classes_present_in_gt_or_prediction():
    cm = ConfusionMatrix(4)
    cm.update(np.array([0, 0, 1]), np.array([0, 2, 1]))
    iou = cm.iou()
    # class 0: TP 1, FN 1 -> 1/2; class 1: 1; class 2: predicted but absent -> 0; class 3: absent -> NaN
    np.testing.assert_allclose(iou[:3], [0.5, 1.0, 0.0])
    assert math.isnan(iou[3])
    assert cm.miou() == pytest.approx(0.5)
    s = cm.summary(["a", "b", "c", "d"])
    assert s["per_class_iou"]["d"] is None and s["classes_in_miou"] == 3


def test_confusion_matches_brute_force_random():
    rng = np.random.default_rng(3)
    C = 5
    gt = rng.integers(0, C, size=500)
    gt[rng.random(500) < 0.1] = 255
    pred = rng.integers(0, C + 1, size=500)  # C is out of range -> "no label"
    cm = ConfusionMatrix(C)
    cm.update(gt[:200], pred[:200])
    cm.update(gt[200:], pred[200:])
    valid = gt != 255
    assert cm.pixel_accuracy() == pytest.approx(np.mean(gt[valid] == pred[valid]))
    for c in range(C):
        inter = np.sum((gt == c) & (pred == c) & valid)
        union = np.sum(((gt == c) | (pred == c)) & valid)
        assert cm.iou()[c] == pytest.approx(inter / union)


def brute_curve(u, e, fractions, n_perm=0):
    """Sparsification by explicit sorting (no ties in the inputs used)."""
    order = np.argsort(-np.asarray(u), kind="stable")
    es = np.asarray(e, dtype=float)[order]
    out = []
    for f in fractions:
        k = min(int(round(f * len(es))), len(es) - 1)
        out.append(es[k:].mean())
    return np.array(out)


def test_sparsification_matches_brute_force_without_ties():
    rng = np.random.default_rng(0)
    u = rng.random(1000)
    e = (rng.random(1000) < u).astype(float)  # informative uncertainty
    fr = DEFAULT_FRACTIONS
    np.testing.assert_allclose(sparsification_curve(u, e, fr), brute_curve(u, e, fr))


def test_perfect_uncertainty_equals_oracle_and_reversed_is_worse():
    rng = np.random.default_rng(1)
    e = (rng.random(2000) < 0.3).astype(float)
    perfect = e + 0.01 * rng.random(2000)  # wrong pixels all more uncertain than right ones
    oracle = oracle_curve(e)
    curve = sparsification_curve(perfect, e)
    np.testing.assert_allclose(curve, oracle)
    assert ause(curve, oracle) == pytest.approx(0.0, abs=1e-12)
    reversed_curve = sparsification_curve(-perfect, e)
    assert ause(reversed_curve, oracle) > 0.2
    # oracle closed form: error after removing k of M samples with W wrong = max(W - k, 0) / (M - k)
    M, W = e.size, int(e.sum())
    k = np.rint(DEFAULT_FRACTIONS * M).astype(int)
    np.testing.assert_allclose(oracle, np.maximum(W - k, 0) / (M - k))


def test_ties_use_expected_value():
    # All tied: curve is flat at the overall error whatever the order.
    e = np.array([1, 0, 0, 0, 1, 0, 0, 0, 0, 0], dtype=float)
    curve = sparsification_curve(np.zeros(10), e, np.array([0.0, 0.5, 0.9]))
    np.testing.assert_allclose(curve, [0.2, 0.2, 0.2])


def test_ause_trapezoid_closed_form():
    fr = np.array([0.0, 0.5, 1.0])
    # differences 0, 0.2, 0.4 at x = 0, 0.5, 1: trapezoids 0.5 * (0 + 0.2) / 2 + 0.5 * (0.2 + 0.4) / 2 = 0.2
    assert ause(np.array([0.4, 0.4, 0.4]), np.array([0.4, 0.2, 0.0]), fr) == pytest.approx(0.2)


def test_sparsification_report_random_is_near_flat():
    rng = np.random.default_rng(2)
    e = (rng.random(50_000) < 0.25).astype(float)
    rep = sparsification_report({"good": e + rng.random(e.size) * 0.5}, e)
    assert rep["ause"]["oracle"] == 0.0
    assert rep["ause"]["good"] < rep["ause"]["random"]
    assert abs(rep["curves"]["random"][50] - 0.25) < 0.02
    assert set(rep["curves"]) == {"good", "random", "oracle"}


def test_spearman_against_scipy_and_known_ranks():
    np.testing.assert_allclose(rankdata([10, 20, 20, 5]), [2, 3.5, 3.5, 1])
    assert spearman([1, 2, 3, 4], [10, 20, 30, 40]) == pytest.approx(1.0)
    assert spearman([1, 2, 3, 4], [4, 3, 2, 1]) == pytest.approx(-1.0)
    rng = np.random.default_rng(4)
    x = rng.integers(0, 10, 60).astype(float)
    y = x + rng.normal(size=60)
    assert spearman(x, y) == pytest.approx(stats.spearmanr(x, y).statistic)
    assert math.isnan(spearman([1, 1, 1], [1, 2, 3]))


def test_pixel_sampler_is_uniform_and_bounded():
    s = PixelSampler(max_samples=10_000, seed=0)
    for i in range(20):
        s.push(v=np.full(5_000, i, dtype=np.int32))
    cols = s.columns()
    assert s.subsampled and cols["v"].size <= 10_000 and s.total_seen == 100_000
    counts = np.bincount(cols["v"], minlength=20)
    # uniform: every batch kept with the same probability
    expected = 5_000 * s.keep_probability
    assert np.all(np.abs(counts - expected) < 6 * np.sqrt(expected))
    small = PixelSampler(max_samples=100)
    small.push(a=np.arange(10), b=np.arange(10) * 2)
    assert not small.subsampled
    np.testing.assert_array_equal(small.columns()["b"], np.arange(10) * 2)


def test_psnr():
    a = np.zeros((4, 4, 3), np.uint8)
    b = a.copy()
    b[0, 0, 0] = 255  # mse = 255^2 / 48
    assert psnr(a, b) == pytest.approx(10 * np.log10(48))
    assert psnr(a, a) == float("inf")


def test_oracle_and_random_match_explicit_orderings():
    rng = np.random.default_rng(5)
    e = rng.random(777)  # real-valued errors (image level)
    np.testing.assert_allclose(oracle_curve(e), brute_curve(e, e, DEFAULT_FRACTIONS))
    perm = np.random.default_rng(9).permutation(e.size)
    u = np.empty(e.size)
    u[perm] = np.arange(e.size)[::-1]  # removal order = perm
    np.testing.assert_allclose(random_curve(e, seed=9), brute_curve(u, e, DEFAULT_FRACTIONS))
