"""Information gain of a view: the closed form against enumeration, score_views against a brute force, the actual
change of the map, importance and the greedy batch."""
from __future__ import annotations

import numpy as np
import pytest

from css_ros import MapError, SemanticMap
from css_ros.engine.info_gain import MomentSums, expected_variance_after, summed_variance
from css_ros.engine.sensor_model import SensorModel
from css_reference import kappa_reference
from scenes import camera, random_scene

C = 4


def total_variance(alpha: np.ndarray) -> np.ndarray:
    """sum_c Var[theta^c] of Dirichlet rows, from the per-class variances (SPEC §4)."""
    s = alpha.sum(axis=1, keepdims=True)
    e = alpha / s
    return (e * (1 - e) / (1 + s)).sum(axis=1)


def enumerated_drop(alpha: np.ndarray, mass: np.ndarray, scoring_prior: float = 1.0) -> np.ndarray:
    """V(a) - sum_c p_c V(a + m e_c) with a = alpha + scoring_prior / C, by enumerating the label c (p = a / S)."""
    alpha = alpha + scoring_prior / alpha.shape[1]
    p = alpha / alpha.sum(axis=1, keepdims=True)
    after = np.zeros(len(alpha))
    for c in range(alpha.shape[1]):
        a = alpha.copy()
        a[:, c] += mass
        after += p[:, c] * total_variance(a)
    return total_variance(alpha) - after


def test_closed_form_equals_enumeration():
    rng = np.random.default_rng(0)
    alpha = rng.uniform(1e-3, 30.0, (500, 6)) ** rng.uniform(0.5, 1.5, (500, 1))
    mass = rng.uniform(0.0, 20.0, 500)
    s, q = alpha.sum(axis=1), (alpha ** 2).sum(axis=1)
    np.testing.assert_allclose(summed_variance(s, q), total_variance(alpha), rtol=1e-12)
    drop = summed_variance(s, q) - expected_variance_after(s, q, mass)
    np.testing.assert_allclose(drop, enumerated_drop(alpha, mass, 0.0), rtol=1e-9, atol=1e-15)
    assert np.all(drop >= -1e-15)
    # diminishing returns: the same evidence teaches less about a Gaussian observed more
    more = alpha * 10
    assert np.all(enumerated_drop(more, mass, 0.0) <= drop + 1e-15)
    # the scoring prior: the moments of alpha + 1/C per class, from alpha's own sums
    ms = MomentSums.of(alpha, 1.0)
    np.testing.assert_allclose(ms.total, (alpha + 1 / 6).sum(axis=1), rtol=1e-12)
    np.testing.assert_allclose(ms.sq_sum, ((alpha + 1 / 6) ** 2).sum(axis=1), rtol=1e-12)


def brute_gain(smap: SemanticMap, cam, weights=None) -> float:
    model = smap.model
    kap, _ = kappa_reference(model.means, model.scales, model.quats_wxyz, model.opacities, cam.K, cam.T_map_cam,
                             cam.width, cam.height)
    w = np.ones(kap.shape[0]) if weights is None else weights.ravel()
    mass = kap.T @ w
    seen = mass > 0
    return float(enumerated_drop(smap.concentrations[seen], mass[seen]).sum())


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_score_views_gain_matches_brute_force(backend):
    rng = np.random.default_rng(1)
    smap = SemanticMap(random_scene(2, n=80), C, backend=backend)
    smap.concentrations += rng.uniform(0.0, 4.0, smap.concentrations.shape) * (rng.random((80, 1)) < 0.6)
    cams = [camera(), camera(position=(0.3, 0.1, -0.2)), camera(width=32, height=24, f=25.0)]
    gains = smap.score_views(cams)[:, 2]
    for cam, g in zip(cams, gains):
        assert g == pytest.approx(brute_gain(smap, cam), rel=1e-9)


def test_sensor_model_weights_the_evidence_by_depth():
    """With a sensor model the view's evidence is kappa * the net vote weight at the rendered label and depth."""
    smap0 = SemanticMap(random_scene(3, n=80, depth=(0.5, 6.0)), C)
    rng = np.random.default_rng(2)
    smap0.concentrations += rng.uniform(0.0, 3.0, smap0.concentrations.shape)
    weight = np.array([[1.0, 0.25]] * C)
    sensor = SensorModel(tuple("abcd"), np.array([0.0, 2.5, 50.0]), weight)
    smap = SemanticMap(smap0.model, C, sensor_model=sensor)
    smap.concentrations[...] = smap0.concentrations
    cam = camera()
    depth = smap.render(cam).depth
    pixel_w = np.where(np.nan_to_num(depth, nan=0.0) >= 2.5, 0.25, 1.0)
    assert 0.05 < (pixel_w < 1).mean() < 0.95
    assert smap.score_views([cam])[0, 2] == pytest.approx(brute_gain(smap, cam, pixel_w), rel=1e-9)
    assert smap.score_views([cam])[0, 2] < smap0.score_views([cam])[0, 2]


def test_gain_is_the_expected_actual_drop_of_the_map():
    """Every Gaussian has the same class probabilities p, also with the scoring prior (its concentrations are
    multiples of p with the prior's share removed): observing the view with label c everywhere happens with
    probability p_c, so the p-weighted mean of the map's actual drops of summed variance (with the scoring prior),
    over the C possible observations made with SemanticMap.update, is the predicted gain."""
    rng = np.random.default_rng(3)
    model = random_scene(4, n=60)
    p = np.array([0.5, 0.3, 0.15, 0.05])
    base = SemanticMap(model, C)
    base.concentrations[...] = rng.uniform(8.0, 20.0, (60, 1)) * p - 1.0 / C
    assert np.all(base.concentrations > 0)
    cam = camera()
    gain = base.score_views([cam])[0, 2]
    scored = 1.0 / C  # the scoring prior, per class
    before = total_variance(base.concentrations + scored).sum()
    expected_drop = 0.0
    for c in range(C):
        smap = SemanticMap(model, C)
        smap.concentrations[...] = base.concentrations
        smap.update(cam, np.full((cam.height, cam.width), c, dtype=np.int64))
        expected_drop += p[c] * (before - total_variance(smap.concentrations + scored).sum())
    assert gain > 0 and gain == pytest.approx(expected_drop, rel=1e-9)
    # observing it taught the map: the same view is then worth less
    smap = SemanticMap(model, C)
    smap.concentrations[...] = base.concentrations
    smap.update(cam, np.zeros((cam.height, cam.width), dtype=np.int64))
    assert smap.score_views([cam])[0, 2] < gain


def test_importance_and_the_greedy_batch():
    rng = np.random.default_rng(5)
    smap = SemanticMap(random_scene(5, n=80), C)
    smap.concentrations += rng.uniform(0.0, 2.0, smap.concentrations.shape)
    cams = [camera(position=(x, 0.0, 0.0), width=32, height=24, f=25.0) for x in (-0.6, -0.55, 0.0, 0.6)]
    scores = smap.score_views(cams)
    model = smap.model

    def kappa(cam):
        return kappa_reference(model.means, model.scales, model.quats_wxyz, model.opacities, cam.K, cam.T_map_cam,
                               cam.width, cam.height)[0]

    # task importance: the kappa mass in the task views; a Gaussian no task view sees counts 0
    imp = smap.task_importance([cams[3], cams[2]])
    np.testing.assert_allclose(imp, kappa(cams[3]).sum(axis=0) + kappa(cams[2]).sum(axis=0), rtol=1e-9, atol=1e-15)
    assert 0 < np.count_nonzero(imp) < 80
    task_scores = smap.score_views(cams, importance=imp)[:, 2]
    for cam, g in zip(cams, task_scores):
        mass = kappa(cam).sum(axis=0)
        seen = mass > 0
        assert g == pytest.approx(float((imp[seen] * enumerated_drop(smap.concentrations[seen], mass[seen])).sum()),
                                  rel=1e-9, abs=1e-15)
    assert np.all(smap.score_views(cams, importance=np.zeros(80))[:, 2] == 0)
    # class importance: the map's probability of that class
    np.testing.assert_allclose(smap.class_importance(2), smap.concentrations[:, 2] / smap.concentrations.sum(1))
    with pytest.raises(MapError):
        smap.score_views(cams, importance=np.ones(3))
    # greedy batch: first = the best single view; the second is scored as if the first were observed
    sel = smap.select_views(cams, 3)
    assert sel.indices[0] == int(np.argmax(scores[:, 2])) and sel.gains[0] == pytest.approx(scores[:, 2].max())
    first = sel.indices[0]
    mass = kappa(cams[first]).sum(axis=0)
    after = SemanticMap(model, C)
    scored = smap.concentrations + 1.0 / C
    after.concentrations[...] = smap.concentrations + mass[:, None] * scored / scored.sum(1, keepdims=True)
    expected_second = after.score_views(cams)[:, 2]
    expected_second[first] = -np.inf
    assert sel.indices[1] == int(np.argmax(expected_second))
    assert sel.gains[1] == pytest.approx(expected_second.max(), rel=1e-9)
    assert len(set(sel.indices.tolist())) == 3


def test_pixel_scale_counts_a_small_render_as_the_full_observation():
    """A view scored at half size with pixel_scale 4 carries (nearly) the evidence of the full-size view: its gain is
    close to the full view's, closer than plain half-size scoring."""
    rng = np.random.default_rng(9)
    smap = SemanticMap(random_scene(6, n=80), C)
    smap.concentrations += rng.uniform(0.0, 2.0, smap.concentrations.shape)
    full = camera(width=64, height=48, f=50.0)
    half = full.scaled(0.5)
    g_full = smap.score_views([full])[0, 2]
    g_half = smap.score_views([half])[0, 2]
    g_scaled = smap.score_views([half], pixel_scale=4.0)[0, 2]
    # within the resampling (the 0.3 px^2 dilation of SPEC §3 widens small splats more at low resolution)
    assert abs(g_scaled - g_full) < 0.2 * g_full and abs(g_scaled - g_full) < abs(g_half - g_full)
    with pytest.raises(MapError):
        smap.score_views([half], pixel_scale=float("nan"))


def test_greedy_batch_equals_rescoring_every_view_each_round():
    """select_views re-scores only the views sharing a Gaussian with the last pick: the batch (indices and gains,
    bit for bit) equals a greedy that re-scores every remaining view each round from the same masses, on views that
    overlap in part and views that see disjoint surfaces, with and without importance."""
    from css_ros.engine.info_gain import view_gain

    rng = np.random.default_rng(21)
    model = random_scene(12, n=150)
    smap = SemanticMap(model, C)
    smap.concentrations += rng.uniform(0.0, 3.0, smap.concentrations.shape)
    yaws = np.radians([-50.0, -25.0, -8.0, 0.0, 8.0, 25.0, 50.0])
    cams = [camera(position=(0.0, y, 0.0), quat=(0.0, np.sin(a / 2), 0.0, np.cos(a / 2)), width=32, height=24)
            for a in yaws for y in (-0.3, 0.3)]
    masses = list(smap._backend.view_masses(cams, smap._concentrations, *smap._background_moments(),
                                            smap._mass_weights()))
    shared = [[np.intersect1d(a, b).size > 0 for b, _ in masses] for a, _ in masses]
    assert not all(map(all, shared)) and sum(map(sum, shared)) > 2 * len(cams)   # disjoint and overlapping pairs
    for imp in (None, rng.uniform(0.0, 1.0, model.num_gaussians)):
        moments = MomentSums.of(smap.concentrations)
        chosen, gains = [], []
        for _ in range(6):
            scores = np.array([-np.inf if i in chosen else view_gain(moments, ids, mass, imp)
                               for i, (ids, mass) in enumerate(masses)])
            chosen.append(int(np.argmax(scores)))
            gains.append(float(scores[chosen[-1]]))
            moments.observe_expected(*masses[chosen[-1]])
        sel = smap.select_views(cams, 6, importance=imp)
        assert sel.indices.tolist() == chosen
        np.testing.assert_array_equal(sel.gains, gains)
