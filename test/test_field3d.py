"""SPEC §9: per-Gaussian semantics and the continuous semantic field at 3D points.

Every expectation is computed independently here: a brute-force float64 loop over all Gaussians
(covariances inverted with numpy, no spatial index) and closed forms for single Gaussians.
"""
from __future__ import annotations

import numpy as np
import pytest

from css_ros import GaussianModel, InputError, MapError, SemanticMap
from css_ros.engine.field3d import FieldIndex, query_field
from css_ros.engine.spec import (DEFAULT_MIN_EVIDENCE, DEFAULT_QUERY_BACKGROUND_WEIGHT,
                                 QUERY_MAHALANOBIS_CUTOFF)
from scenes import random_quats

W_B = DEFAULT_QUERY_BACKGROUND_WEIGHT


# ------------------------------------------------------------------ independent reference
def brute_force_field(model: GaussianModel, alpha: np.ndarray, alpha_b: float, points: np.ndarray,
                      w_b: float = W_B):
    """SPEC §9 in float64 with a loop over points and all Gaussians at once (no index)."""
    cov = model.covariances()
    inv = np.linalg.inv(cov)
    o = model.opacities.astype(np.float64)
    s = alpha.sum(1)
    e_n = alpha / s[:, None]
    v_n = e_n * (1 - e_n) / (1 + s[:, None])
    c = alpha.shape[1]
    e_b = 1.0 / c
    v_b = e_b * (1 - e_b) / (1 + c * alpha_b)
    E = np.empty((len(points), c))
    V = np.empty((len(points), c))
    KB = np.empty(len(points))
    for i, x in enumerate(points):
        d = x[None, :] - model.means.astype(np.float64)
        m2 = np.einsum("ni,nij,nj->n", d, inv, d)
        w = np.where(m2 <= QUERY_MAHALANOBIS_CUTOFF ** 2, o * np.exp(-0.5 * m2), 0.0)
        denom = w.sum() + w_b
        k = w / denom
        kb = w_b / denom
        E[i] = k @ e_n + kb * e_b
        V[i] = (k ** 2) @ v_n + kb ** 2 * v_b
        KB[i] = kb
    return E, V, KB


def random_model(seed: int, n: int, spread: float = 3.0, log_scale=(-3.0, -0.7)) -> GaussianModel:
    rng = np.random.default_rng(seed)
    means = rng.uniform(-spread, spread, (n, 3))
    scales = np.exp(rng.uniform(*log_scale, (n, 3)))          # anisotropic
    return GaussianModel.from_activated(means, scales, random_quats(rng, n), rng.uniform(0.05, 1.0, n),
                                        rng.uniform(0, 1, (n, 3)))


def random_map(model: GaussianModel, c: int, seed: int, **kw) -> SemanticMap:
    smap = SemanticMap(model, c, **kw)
    rng = np.random.default_rng(seed)
    smap.concentrations[...] = rng.gamma(0.7, 3.0, (model.num_gaussians, c)) + smap.prior
    return smap


def check_against_reference(smap: SemanticMap, points: np.ndarray) -> None:
    q = smap.query_points(points)
    E, V, KB = brute_force_field(smap.model, smap.concentrations, smap.background, points)
    np.testing.assert_allclose(q.expectation, E, rtol=2e-6, atol=1e-7)
    np.testing.assert_allclose(q.variance, V, rtol=2e-6, atol=1e-9)
    np.testing.assert_allclose(q.background, KB, rtol=2e-6, atol=1e-7)
    srt = np.sort(E, axis=1)
    clear = (srt[:, -1] - srt[:, -2]) > 1e-5                 # no near-ties in the reference argmax
    ref = np.argmax(E, axis=1)
    ref[KB > smap.unknown_threshold] = smap.ignore_label
    np.testing.assert_array_equal(q.labels[clear], ref[clear])
    assert q.labels.dtype == np.int32


# ------------------------------------------------------------------ against brute force
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_scene_matches_brute_force(seed):
    model = random_model(seed, 400)
    smap = random_map(model, 5, seed + 10)
    rng = np.random.default_rng(seed + 100)
    near = model.means[rng.integers(0, 400, 300)] + rng.normal(0, 0.1, (300, 3))
    anywhere = rng.uniform(-4, 4, (300, 3))                   # includes empty space
    far = rng.uniform(20, 30, (20, 3))
    check_against_reference(smap, np.concatenate([near, anywhere, far]))


def test_points_overlapping_many_gaussians():
    rng = np.random.default_rng(3)
    n = 300
    means = rng.normal(0, 0.05, (n, 3))                       # a dense clump of large Gaussians
    scales = np.exp(rng.uniform(-1.5, 0.0, (n, 3)))
    model = GaussianModel.from_activated(means, scales, random_quats(rng, n), rng.uniform(0.05, 1, n),
                                         np.full((n, 3), 0.5))
    smap = random_map(model, 4, 4)
    points = rng.normal(0, 0.3, (200, 3))
    check_against_reference(smap, points)
    E, V, KB = brute_force_field(model, smap.concentrations, smap.background, points[:5])
    assert np.all(KB < 0.01)                                  # really many Gaussians at each point


def test_mixed_sizes_and_far_floaters():
    """Tiny, huge (coarse levels) and far-away Gaussians (outside the grid domain: clamped cells)."""
    rng = np.random.default_rng(5)
    parts = [(rng.uniform(-2, 2, (300, 3)), np.exp(rng.uniform(-6, -3, (300, 3)))),
             (rng.uniform(-2, 2, (10, 3)), np.exp(rng.uniform(0.5, 2.0, (10, 3)))),
             (rng.uniform(40, 60, (5, 3)) * rng.choice([-1, 1], (5, 3)), np.exp(rng.uniform(0, 1.5, (5, 3))))]
    means = np.concatenate([p[0] for p in parts])
    scales = np.concatenate([p[1] for p in parts])
    n = len(means)
    model = GaussianModel.from_activated(means, scales, random_quats(rng, n), rng.uniform(0.05, 1, n),
                                         np.full((n, 3), 0.5))
    smap = random_map(model, 3, 6)
    idx = FieldIndex.from_model(model)
    assert len(idx.cell_size) > 2                              # several levels in use
    pts = np.concatenate([means[:300] + rng.normal(0, 0.01, (300, 3)), rng.uniform(-8, 8, (200, 3)),
                          means[310:] + rng.normal(0, 1.0, (5, 3)), rng.uniform(-70, 70, (100, 3))])
    check_against_reference(smap, pts)


def test_chunking_does_not_change_results():
    model = random_model(7, 200)
    smap = random_map(model, 3, 8)
    pts = np.random.default_rng(9).uniform(-3, 3, (257, 3))
    e_b, v_b, _ = smap._background_moments()
    idx = FieldIndex.from_model(model)
    a = query_field(idx, smap.concentrations, pts, W_B, (e_b, v_b), 0.5, 255)
    b = query_field(idx, smap.concentrations, pts, W_B, (e_b, v_b), 0.5, 255, chunk=7)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)


# ------------------------------------------------------------------ closed forms
def lone_gaussian(opacity=0.8, scales=(0.3, 0.1, 0.05), quat=(0.9, 0.1, -0.3, 0.2)):
    return GaussianModel.from_activated(np.array([[1.0, -2.0, 0.5]]), np.array([scales]),
                                        np.array([quat]), np.array([opacity]), np.array([[0.5, 0.5, 0.5]]))


def test_point_at_lone_gaussian_centre():
    model = lone_gaussian()
    smap = SemanticMap(model, 3)
    smap.concentrations[0] = [7.0, 2.0, 1.0]
    o = float(model.opacities[0])
    q = smap.query_points(model.means.astype(np.float64))
    kappa, kb = o / (o + W_B), W_B / (o + W_B)
    s = 10.0
    e_n = np.array([0.7, 0.2, 0.1])
    v_n = e_n * (1 - e_n) / (1 + s)
    e_b = 1 / 3
    v_b = e_b * (1 - e_b) / (1 + 3 * smap.background)
    np.testing.assert_allclose(q.expectation[0], kappa * e_n + kb * e_b, rtol=1e-6)
    np.testing.assert_allclose(q.variance[0], kappa ** 2 * v_n + kb ** 2 * v_b, rtol=1e-6)
    np.testing.assert_allclose(q.background[0], kb, rtol=1e-6)
    assert q.labels[0] == 0


def test_far_point_is_unknown_with_uniform_expectation():
    smap = random_map(random_model(11, 100), 4, 12)
    q = smap.query_points(np.array([[100.0, 100.0, 100.0], [-1e6, 0.0, 3.0]]))
    assert np.all(q.labels == smap.ignore_label)
    assert np.all(q.expectation == np.float32(0.25))
    assert np.all(q.background == 1.0)
    v_b = 0.25 * 0.75 / (1 + 4 * smap.background)
    np.testing.assert_allclose(q.variance, v_b, rtol=1e-6)


def test_mahalanobis_cutoff_along_principal_axis():
    """Along the longest axis r·s·u has Mahalanobis distance r: kernel at 2.99, nothing at 3.01."""
    quat = np.array([0.9, 0.1, -0.3, 0.2])
    model = lone_gaussian(quat=quat)
    smap = SemanticMap(model, 2)
    smap.concentrations[0] = [9.0, 1.0]
    axis = model.covariances()[0]
    vals, vecs = np.linalg.eigh(axis)
    u, s = vecs[:, -1], np.sqrt(vals[-1])
    centre = model.means[0].astype(np.float64)
    pts = np.stack([centre + 2.99 * s * u, centre - 3.01 * s * u])
    q = smap.query_points(pts)
    o = float(model.opacities[0])
    w = o * np.exp(-0.5 * 2.99 ** 2)
    np.testing.assert_allclose(q.background, [W_B / (w + W_B), 1.0], rtol=1e-6)


def test_unknown_threshold_and_background_weight():
    model = lone_gaussian(opacity=0.5)
    smap = SemanticMap(model, 2, unknown_threshold=0.5)
    smap.concentrations[0] = [1.0, 5.0]
    o = float(model.opacities[0])
    centre = model.means.astype(np.float64)
    assert smap.query_points(centre, background_weight=0.4 * o).labels[0] == 1   # κ_b = 0.4/1.4
    assert smap.query_points(centre, background_weight=2.0 * o).labels[0] == 255  # κ_b = 2/3


def test_index_is_built_once_per_map():
    smap = random_map(random_model(13, 50), 2, 14)
    smap.query_points(np.zeros((1, 3)))
    idx = smap._field_index
    smap.concentrations[:, 0] += 5.0                         # the index depends on geometry only
    q = smap.query_points(np.zeros((1, 3)))
    assert smap._field_index is idx
    E, _, _ = brute_force_field(smap.model, smap.concentrations, smap.background, np.zeros((1, 3)))
    np.testing.assert_allclose(q.expectation, E, rtol=2e-6)


def test_bad_points_are_refused():
    smap = random_map(random_model(15, 20), 2, 16)
    with pytest.raises(InputError):
        smap.query_points(np.zeros((4, 2)))
    # Non-finite points: exactly the answer of a point far from every Gaussian (one rule for "unknown").
    q = smap.query_points(np.array([[1e9, 1e9, 1e9], [0.0, np.nan, 0.0], [np.inf, 0.0, 0.0]]))
    assert q.background.tolist() == [1.0, 1.0, 1.0] and q.labels.tolist() == [smap.ignore_label] * 3
    np.testing.assert_array_equal(q.expectation[1:], q.expectation[[0, 0]])
    np.testing.assert_array_equal(q.variance[1:], q.variance[[0, 0]])
    np.testing.assert_allclose(q.expectation, 0.5, rtol=1e-6)  # E = 1/C with C = 2
    with pytest.raises(InputError):
        smap.query_points(np.zeros((1, 3)), background_weight=0.0)
    assert smap.query_points(np.zeros((0, 3))).expectation.shape == (0, 2)


# ------------------------------------------------------------------ per-Gaussian semantics
def test_gaussian_semantics_matches_numpy_moments():
    model = random_model(17, 500)
    smap = random_map(model, 6, 18)
    unobserved = np.arange(0, 500, 7)
    smap.concentrations[unobserved] = smap.prior
    g = smap.gaussian_semantics()
    a = smap.concentrations
    s = a.sum(1)
    lab = a.argmax(1)
    e = a[np.arange(500), lab] / s
    observed = s - 6 * smap.prior >= DEFAULT_MIN_EVIDENCE
    np.testing.assert_array_equal(g.observed, observed)
    assert not g.observed[unobserved].any()
    np.testing.assert_array_equal(g.label[observed], lab[observed])
    assert np.all(g.label[~observed] == smap.ignore_label)
    assert g.label.dtype == np.int32 and g.expectation.dtype == np.float32 and g.variance.dtype == np.float32
    np.testing.assert_allclose(g.expectation, e, rtol=1e-6)
    np.testing.assert_allclose(g.variance, e * (1 - e) / (1 + s), rtol=1e-6)
    np.testing.assert_allclose(g.total, s, rtol=1e-15)
    np.testing.assert_allclose(g.expectation[unobserved], 1 / 6, rtol=1e-6)


def test_observed_flag_threshold():
    model = random_model(19, 4)
    smap = SemanticMap(model, 3)
    smap.concentrations[:, 0] += [0.0, 0.49, 0.51, 2.0]       # evidence S_n - C alpha_0
    np.testing.assert_array_equal(smap.gaussian_semantics().observed, [False, False, True, True])
    np.testing.assert_array_equal(smap.gaussian_semantics(min_evidence=0.25).observed, [False, True, True, True])
    np.testing.assert_allclose(smap.gaussian_semantics().evidence, [0.0, 0.49, 0.51, 2.0], atol=1e-12)
    with pytest.raises(MapError):
        smap.gaussian_semantics(min_evidence=-1.0)


# ------------------------------------------------------------------ scale
def _scene_of(n: int, seed: int) -> SemanticMap:
    rng = np.random.default_rng(seed)
    side = 20.0 * (n / 1e6) ** (1 / 3)                        # constant density: ~1 per 8 dm^3
    means = rng.uniform(0, side, (n, 3))
    scales = np.exp(rng.uniform(-4.0, -1.5, (n, 3)))
    scales[: max(1, n // 10000)] = 5.0                        # a few huge ones
    model = GaussianModel.from_activated(means, scales, random_quats(rng, n), rng.uniform(0.05, 1, n),
                                         np.full((n, 3), 0.5))
    smap = SemanticMap(model, 8)
    smap.concentrations += rng.uniform(0, 3, (n, 8))
    return smap


def _check_index_bounds(smap: SemanticMap) -> None:
    idx = smap._field_index
    n = smap.model.num_gaussians
    assert idx.items.size <= 8 * n                            # <= 2 cells per axis per Gaussian
    assert idx.cell_start.size <= 2 * (1 << 22) + 2
    assert idx.nbytes <= 200 * n + 70 * 2 ** 20


def test_medium_scene_bounded_index_and_spot_check():
    smap = _scene_of(50_000, 21)
    pts = np.random.default_rng(22).uniform(0, 20 * 0.05 ** (1 / 3), (50_000, 3))
    q = smap.query_points(pts)
    _check_index_bounds(smap)
    E, V, KB = brute_force_field(smap.model, smap.concentrations, smap.background, pts[:40])
    np.testing.assert_allclose(q.expectation[:40], E, rtol=2e-6, atol=1e-7)
    np.testing.assert_allclose(q.variance[:40], V, rtol=2e-6, atol=1e-9)


@pytest.mark.slow
def test_million_gaussians_million_points():
    smap = _scene_of(1_000_000, 23)
    pts = np.random.default_rng(24).uniform(0, 20.0, (1_000_000, 3))
    q = smap.query_points(pts)
    _check_index_bounds(smap)
    assert q.expectation.shape == (1_000_000, 8)
    E, _, KB = brute_force_field(smap.model, smap.concentrations, smap.background, pts[:5])
    np.testing.assert_allclose(q.expectation[:5], E, rtol=2e-6, atol=1e-7)
