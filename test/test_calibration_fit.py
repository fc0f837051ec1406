"""Tests of css_ros.calibration.fit against brute-force references, scipy and closed forms."""
from __future__ import annotations

import time

import numpy as np
import pytest
from scipy.optimize import isotonic_regression

from css_ros.calibration import fit
from css_ros.calibration import (
    isotonic_fit,
    logistic_fit,
    logistic_predict,
    reliability_weight,
    smoothed_rates,
    smoothing_prior,
)


# ----------------------------------------------------------------------------------------------
# Isotonic regression
# ----------------------------------------------------------------------------------------------
def _minmax_isotonic(y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Slow reference: f_i = max_{j<=i} min_{k>=i} weighted mean(y_j..y_k) (the isotonic regression's closed form)."""
    n = y.size
    f = np.empty(n)
    for i in range(n):
        f[i] = max(min(np.dot(w[j:k + 1], y[j:k + 1]) / w[j:k + 1].sum() for k in range(i, n)) for j in range(i + 1))
    return f


@pytest.mark.parametrize("seed", range(6))
def test_pav_matches_the_minmax_formula(seed):
    rng = np.random.default_rng(seed)
    n = 30
    x = rng.permutation(n).astype(float) * 0.37  # distinct, unsorted
    y = (rng.random(n) < np.linspace(0.1, 0.9, n)[np.argsort(np.argsort(x))]).astype(float)
    if seed % 2:
        y = rng.random(n)  # fractional targets
    w = rng.uniform(0.2, 3.0, n)
    xk, yk = isotonic_fit(x, y, w, max_knots=1000)
    order = np.argsort(x)
    ref = _minmax_isotonic(y[order], w[order])
    np.testing.assert_allclose(np.interp(x[order], xk, yk), ref, atol=1e-12)


def test_pav_matches_scipy_and_optimality():
    rng = np.random.default_rng(7)
    n = 3000
    x = rng.random(n)
    y = (rng.random(n) < x**2).astype(float)
    w = rng.uniform(0.5, 2.0, n)
    xk, yk = isotonic_fit(x, y, w, max_knots=10**6)
    order = np.argsort(x)
    ref = isotonic_regression(y[order], weights=w[order]).x
    f = np.interp(x[order], xk, yk)
    np.testing.assert_allclose(f, ref, atol=1e-12)
    # optimality: each constant block holds the weighted mean of its samples
    for v in np.unique(f):
        blk = f == v
        assert np.dot(w[order][blk], y[order][blk]) / w[order][blk].sum() == pytest.approx(v, abs=1e-12)


def test_knots_are_strictly_increasing_and_monotone():
    rng = np.random.default_rng(1)
    x = rng.normal(size=20000)
    y = (rng.random(x.size) < 1 / (1 + np.exp(-2 * x))).astype(float)
    for max_knots in (2, 3, 10, 64):
        xk, yk = isotonic_fit(x, y, max_knots=max_knots)
        assert 1 <= xk.size <= max_knots
        assert np.all(np.diff(xk) > 0)
        assert np.all(np.diff(yk) >= 0)
        assert xk[0] == x.min() and xk[-1] == x.max()
    xk, yk = isotonic_fit(x, y, max_knots=64)
    xe, ye = isotonic_fit(x, y, max_knots=10**6)
    assert xe.size > 64
    # the reduced fit is close to the exact one and keeps the total (weighted mean of the fit = mean of y)
    assert np.abs(np.interp(x, xk, yk) - np.interp(x, xe, ye)).mean() < 0.02
    assert np.interp(x, xk, yk).mean() == pytest.approx(y.mean(), abs=1e-9)


def test_ties_weights_and_edge_cases():
    # equal x share a value; weights act as replication
    x = np.array([0.0, 1.0, 1.0, 2.0])
    y = np.array([1.0, 0.0, 1.0, 0.0])
    xk, yk = isotonic_fit(x, y)
    f = np.interp(x, xk, yk)
    assert f[1] == f[2]
    np.testing.assert_allclose(f, np.full(4, 0.5))
    rng = np.random.default_rng(3)
    xs, ys = rng.random(40), rng.random(40)
    reps = rng.integers(1, 4, 40)
    a = isotonic_fit(xs, ys, reps.astype(float), max_knots=1000)
    b = isotonic_fit(np.repeat(xs, reps), np.repeat(ys, reps), max_knots=1000)
    np.testing.assert_allclose(a[0], b[0])
    np.testing.assert_allclose(a[1], b[1], atol=1e-12)
    # single sample, non-finite and zero-weight samples are left out
    xk, yk = isotonic_fit(np.array([0.5, np.nan, 0.7]), np.array([1.0, 0.0, 0.0]), np.array([1.0, 1.0, 0.0]))
    assert xk.tolist() == [0.5] and yk.tolist() == [1.0]
    with pytest.raises(ValueError):
        isotonic_fit(np.array([np.nan]), np.array([1.0]))
    with pytest.raises(ValueError):
        isotonic_fit(np.array([1.0]), np.array([1.0]), max_knots=1)
    # already monotone data is reproduced exactly
    xk, yk = isotonic_fit(np.arange(5.0), np.array([0.0, 0.1, 0.1, 0.5, 1.0]), max_knots=100)
    np.testing.assert_allclose(np.interp(np.arange(5.0), xk, yk), [0.0, 0.1, 0.1, 0.5, 1.0])


def test_quantile_binning_above_the_bin_limit(monkeypatch):
    monkeypatch.setattr(fit, "ISOTONIC_BINS", 50)
    rng = np.random.default_rng(5)
    x = rng.random(5000)
    y = (rng.random(x.size) < x).astype(float)
    xk, yk = isotonic_fit(x, y, max_knots=10**6)
    assert xk.size <= 100 and np.all(np.diff(xk) > 0) and np.all(np.diff(yk) >= 0)
    # the fit is constant on each of the 50 equal-count bins (100 samples each) and holds their mean
    order = np.argsort(x)
    f = np.interp(x[order], xk, yk).reshape(50, 100)
    assert np.all(f.max(axis=1) - f.min(axis=1) < 1e-12)
    assert f.mean() == pytest.approx(y.mean(), abs=1e-12)


def test_isotonic_is_fast_on_a_million_samples():
    rng = np.random.default_rng(0)
    x = rng.random(1_000_000)
    y = (rng.random(x.size) < x).astype(float)
    t0 = time.perf_counter()
    xk, yk = isotonic_fit(x, y)
    assert time.perf_counter() - t0 < 5.0
    assert xk.size <= 64
    grid = np.linspace(0.05, 0.95, 19)
    np.testing.assert_allclose(np.interp(grid, xk, yk), grid, atol=0.03)


# ----------------------------------------------------------------------------------------------
# Logistic regression
# ----------------------------------------------------------------------------------------------
def test_logistic_recovers_known_coefficients():
    rng = np.random.default_rng(11)
    n = 20000
    X = rng.normal(size=(n, 2))
    true = np.array([1.5, -2.0, 0.5])
    y = (rng.random(n) < 1 / (1 + np.exp(-(X @ true[:2] + true[2])))).astype(float)
    coef = logistic_fit(X, y)
    assert coef.shape == (3,)
    np.testing.assert_allclose(coef, true, atol=0.12)
    p = logistic_predict(X, coef)
    assert p.shape == (n,) and np.all((p > 0) & (p < 1))


def test_logistic_optimality_weights_and_one_feature():
    rng = np.random.default_rng(2)
    n = 3000
    x = rng.normal(size=n)
    y = rng.random(n)  # fractional targets
    w = rng.uniform(0.1, 2.0, n)
    l2 = 0.05
    coef = logistic_fit(x, y, w, l2=l2)  # 1-D features: one column
    assert coef.shape == (2,)
    X = np.c_[x, np.ones(n)]
    p = logistic_predict(x, coef)
    grad = X.T @ (w * (p - y)) / w.sum() + np.array([l2, 0.0]) * coef
    np.testing.assert_allclose(grad, 0.0, atol=1e-9)
    # integer weights act as replication
    reps = rng.integers(1, 4, n)
    a = logistic_fit(x, y, reps.astype(float), l2=l2)
    b = logistic_fit(np.repeat(x, reps), np.repeat(y, reps), l2=l2)
    np.testing.assert_allclose(a, b, atol=1e-8)


def test_logistic_is_safe_on_separable_and_constant_data():
    x = np.r_[np.linspace(-3, -1, 50), np.linspace(1, 3, 50)]
    y = (x > 0).astype(float)
    coef = logistic_fit(x, y, l2=1e-6, iters=50)
    assert np.all(np.isfinite(coef))
    assert np.all(logistic_predict(x, coef)[y == 1] > 0.99)
    # a constant feature column and all-ones targets do not break the Newton system
    coef = logistic_fit(np.ones((10, 1)), np.ones(10))
    assert np.all(np.isfinite(coef)) and logistic_predict(np.ones((1, 1)), coef)[0] > 0.99
    with pytest.raises(ValueError):
        logistic_predict(np.ones((3, 2)), np.zeros(2))


# ----------------------------------------------------------------------------------------------
# Smoothed rates
# ----------------------------------------------------------------------------------------------
def _counts() -> np.ndarray:
    rng = np.random.default_rng(4)
    c = rng.integers(0, 50, size=(3, 5, 3)).astype(float)
    c[0, 2] = [999_000, 1_000, 0]  # 1e6 samples
    c[1, 3] = 0  # an empty row
    c[2] = 0  # a class never seen
    return c


def test_smoothed_rates_rows_and_limits():
    c = _counts()
    p = smoothed_rates(c, pseudo_count=200.0)
    assert p.shape == c.shape
    np.testing.assert_allclose(p.sum(axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(p[0, 2], [0.999, 0.001, 0.0], atol=1e-3)
    # the empty row (1, 3) lies between two bins with data: their midpoint (linear in bin index), not its prior
    np.testing.assert_allclose(p[1, 3], 0.5 * (p[1, 2] + p[1, 4]), atol=1e-15)
    glob = c.sum(axis=(0, 1)) / c.sum()
    np.testing.assert_allclose(p[2], np.broadcast_to(glob, (5, 3)), atol=1e-15)


def test_smoothing_prior_by_hand():
    c = _counts()
    prior = smoothing_prior(c)
    norm = lambda v: v / v.sum()
    cls1 = norm(c[1].sum(axis=0))
    np.testing.assert_allclose(prior[1, 3], 0.5 * norm(c[1, 2] + c[1, 4]) + 0.5 * cls1, atol=1e-15)
    np.testing.assert_allclose(prior[1, 0], 0.5 * norm(c[1, 1]) + 0.5 * cls1, atol=1e-15)
    # row (1, 4)'s only neighbour (1, 3) is empty: the prior is the class rate alone
    np.testing.assert_allclose(prior[1, 4], cls1, atol=1e-15)
    # p = (counts + tau prior) / (n + tau)
    p = smoothed_rates(c, 200.0)
    np.testing.assert_allclose(p[1, 1], (c[1, 1] + 200 * prior[1, 1]) / (c[1, 1].sum() + 200), atol=1e-15)


def test_smoothed_rates_degenerate_inputs():
    np.testing.assert_allclose(smoothed_rates(np.zeros((2, 3, 4))), 0.25)
    one_bin = np.array([[[3.0, 1.0]], [[0.0, 0.0]]])
    p = smoothed_rates(one_bin, pseudo_count=4.0)
    np.testing.assert_allclose(p[0, 0], [0.75, 0.25])  # B = 1: the prior is the class's own rate
    np.testing.assert_allclose(p[1, 0], [0.75, 0.25])  # unseen class: global rate
    c = _counts()
    np.testing.assert_allclose(smoothed_rates(c, pseudo_count=0.0)[0, 0], c[0, 0] / c[0, 0].sum())  # tau = 0: frequency
    p0 = smoothed_rates(c, pseudo_count=0.0)
    np.testing.assert_allclose(p0[1, 3], 0.5 * (c[1, 2] / c[1, 2].sum() + c[1, 4] / c[1, 4].sum()))  # empty: between
    with pytest.raises(ValueError):
        smoothed_rates(np.zeros((2, 3)))
    with pytest.raises(ValueError):
        smoothed_rates(-np.ones((1, 1, 2)))


def _falling_with_empty_far_bins() -> np.ndarray:
    """(2 labels, 16 bins of 0.5 m, 2 true classes) counts: label 0 right 95 % near, falling to 5 % at 3.5-7 m,
    nothing observed from 7 m on; label 1 only near (bins 0-3)."""
    c = np.zeros((2, 16, 2))
    right = np.r_[np.linspace(0.95, 0.05, 7), np.full(7, 0.05)]
    c[0, :14, 0] = 4000 * right
    c[0, :14, 1] = 4000 * (1 - right)
    c[1, :4] = [3000, 1000]
    return c


def test_empty_far_bins_follow_their_neighbours_not_the_class_rate():
    c = _falling_with_empty_far_bins()
    p = smoothed_rates(c, pseudo_count=200.0)
    last = p[0, 13]
    # before: an empty bin without a neighbour with data fell back to the class rate (about 0.3 here)
    class_rate = c[0].sum(axis=0) / c[0].sum()
    assert class_rate[0] > 0.25
    np.testing.assert_allclose(p[0, 14:], np.broadcast_to(last, (2, 2)), atol=1e-15)   # the trend held, no jump
    assert np.all(np.diff(p[0, :, 0]) <= 1e-12)                                        # monotone over every bin
    np.testing.assert_allclose(p[1, 4:], np.broadcast_to(p[1, 3], (12, 2)), atol=1e-15)
    np.testing.assert_allclose(p.sum(axis=-1), 1.0, atol=1e-12)
    # an interior gap is the linear interpolation of its two neighbours with data
    g = c.copy()
    g[0, 5:8] = 0
    q = smoothed_rates(g, pseudo_count=200.0)
    for k, b in enumerate((5, 6, 7), start=1):
        np.testing.assert_allclose(q[0, b], q[0, 4] + k / 4 * (q[0, 8] - q[0, 4]), atol=1e-14)


def test_sensor_model_and_yaml_mark_the_extrapolated_far_bins(tmp_path):
    from css_ros.calibration.learn import LabelDepthCounts, extrapolated_bins, fit_sensor_model
    from css_ros.engine.sensor_model import SensorModel, uniform_edges

    edges = uniform_edges(8.0, 0.5)
    counts = LabelDepthCounts(2, edges)
    counts.fit[...] = _falling_with_empty_far_bins().astype(np.int64)
    sensor = fit_sensor_model(counts, ["floor", "wall"])
    w = sensor.weight[0]
    assert np.all(np.diff(w) <= 1e-12) and w[14] == w[15] == w[13]    # weights never rise again
    info = extrapolated_bins(counts.fit, edges, ["floor", "wall"])
    assert info["depth_bins"] == [14, 15] and info["depths_m"] == [[7.0, 7.5], [7.5, 8.0]]
    per = extrapolated_bins(counts.fit, edges, ["floor", "wall"], per_class=True)
    assert per["per_label"] == {"floor": [14, 15], "wall": list(range(4, 16))}
    path = SensorModel(sensor.class_names, sensor.depth_edges, sensor.weight, sensor.confusion,
                       info={"extrapolated": info}).save(tmp_path / "sm.yaml")
    loaded = SensorModel.load(path)
    assert loaded.info["extrapolated"]["depth_bins"] == [14, 15]
    assert "follow the neighbouring bins" in loaded.info["extrapolated"]["rule"]


# ----------------------------------------------------------------------------------------------
# Reliability weight
# ----------------------------------------------------------------------------------------------
def test_reliability_weight():
    p = np.array([0.0, 0.3, 0.5, 0.75, 1.0, 1.2, np.nan])
    w = reliability_weight(p)
    np.testing.assert_allclose(w[:6], [0.0, 0.0, 0.0, 0.5, 1.0, 1.0])
    assert np.isnan(w[6])
    np.testing.assert_allclose(reliability_weight(p[:6], floor=0.1), [0.1, 0.1, 0.1, 0.5, 1.0, 1.0])
    assert reliability_weight(np.full((2, 3), 0.9)).shape == (2, 3)
