"""The changing-world rules (css_ros.engine.change_rules) in the numba backend against a brute-force reference:
transient classes, measured depth (occluded pixels, Gaussians in front of the measured surface), forgetting and
surprise."""
from __future__ import annotations

import numpy as np
import pytest

from css_ros.engine.final_form import IMAGE_OUTPUTS
from css_ros import MapError, SemanticMap
from css_reference import camera_depths, change_update_reference, kappa_reference
from scenes import camera, random_scene

C = 5
PRIOR = 0.5


def _setup(seed=3, n=150, **kwargs):
    model = random_scene(seed, n=n)
    cam = camera()
    kap, bg = kappa_reference(model.means, model.scales, model.quats_wxyz, model.opacities, cam.K, cam.T_map_cam,
                              cam.width, cam.height)
    smap = SemanticMap(model, C, prior=PRIOR, **kwargs)
    return model, cam, kap, bg, smap


def _counts(stats):
    return dict(used=stats.used, ignored=stats.ignored, out_of_range=stats.out_of_range, transient=stats.transient,
                occluded=stats.occluded)


def _labels(rng, cam):
    labels = rng.integers(0, C, (cam.height, cam.width)).astype(np.uint8)
    labels[rng.random(labels.shape) < 0.1] = 255
    labels[rng.random(labels.shape) < 0.05] = C + 2
    return labels


def test_transient_pixels_add_nothing_and_are_counted():
    rng = np.random.default_rng(0)
    model, cam, kap, bg, smap = _setup(transient_classes=[1, 3])
    labels = _labels(rng, cam)
    view = smap.observe(cam, labels, outputs=IMAGE_OUTPUTS)
    alpha, counts, surprise = change_update_reference(kap, bg, np.full((model.num_gaussians, C), PRIOR), labels, C,
                                                      np.zeros(model.num_gaussians), transient=(1, 3))
    np.testing.assert_allclose(smap.concentrations, alpha, rtol=1e-9, atol=1e-12)
    assert np.all(smap.concentrations[:, [1, 3]] == PRIOR)
    assert _counts(smap.last_update) == counts
    assert counts["transient"] == int(np.isin(labels, [1, 3]).sum()) > 0
    assert sum(counts.values()) == labels.size
    np.testing.assert_allclose(view.surprise.ravel(), surprise, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("depth_scale", [1.0, 2.5])
def test_measured_depth_blocks_nearer_pixels_and_drops_gaussians_in_front(depth_scale):
    rng = np.random.default_rng(1)
    model, cam, kap, bg, smap = _setup(depth_scale=depth_scale)
    z_m = camera_depths(model.means, cam.T_map_cam) * depth_scale
    has = kap.sum(axis=1) > 0
    rendered = np.where(has, (kap @ z_m) / np.maximum(kap.sum(axis=1), 1e-300), np.nan)
    # a quarter of the pixels see something 1 m nearer than the splat, a quarter a surface 0.5 m behind the splat's
    # (what the splat holds in front of it is gone), a quarter the splat's own surface (all its Gaussians vote), the
    # rest no measurement (NaN, 0, inf)
    pick = rng.integers(0, 4, rendered.size)
    depth = np.where(pick == 0, rendered - 1.0, np.where(pick == 1, rendered + 0.5,
                                                         np.where(pick == 2, rendered, np.nan)))
    depth[rng.random(depth.size) < 0.05] = 0.0
    depth[rng.random(depth.size) < 0.05] = np.inf
    labels = _labels(rng, cam)
    smap.observe(cam, labels, depth=depth.reshape(cam.height, cam.width).astype(np.float32))
    alpha, counts, _ = change_update_reference(kap, bg, np.full((model.num_gaussians, C), PRIOR), labels, C, z_m,
                                               depth=depth.astype(np.float32))
    np.testing.assert_allclose(smap.concentrations, alpha, rtol=1e-9, atol=1e-12)
    assert _counts(smap.last_update) == counts
    assert counts["occluded"] > 0.15 * labels.size * (has.mean())
    # the gate took effect: without depth the map gets more evidence
    plain = SemanticMap(model, C, prior=PRIOR, depth_scale=depth_scale)
    plain.observe(cam, labels)
    assert plain.concentrations.sum() > smap.concentrations.sum() + 1.0


def test_no_measurement_is_the_same_as_no_depth_image():
    rng = np.random.default_rng(2)
    model, cam, _, _, smap = _setup()
    labels = _labels(rng, cam)
    depth = np.zeros(labels.shape, np.float32)
    depth[::2] = np.nan
    depth[1::4] = np.inf
    view = smap.observe(cam, labels, depth=depth, outputs=IMAGE_OUTPUTS)
    plain = SemanticMap(model, C, prior=PRIOR)
    plain_view = plain.observe(cam, labels, outputs=IMAGE_OUTPUTS)
    np.testing.assert_array_equal(smap.concentrations, plain.concentrations)
    np.testing.assert_array_equal(view.surprise, plain_view.surprise)
    assert smap.last_update == plain.last_update and smap.last_update.occluded == 0


def test_half_life_follows_the_closed_form():
    """The same frame k times: alpha - prior = inc * sum_{i<k} f^i for every Gaussian it reaches, f = 2^(-1/h)."""
    rng = np.random.default_rng(4)
    model, cam, kap, bg, smap = _setup(evidence_half_life=3.0)
    labels = _labels(rng, cam)
    conf = rng.uniform(0, 1, labels.shape).astype(np.float32)
    once, _, _ = change_update_reference(kap, bg, np.full((model.num_gaussians, C), PRIOR), labels, C,
                                         np.zeros(model.num_gaussians), confidence=conf)
    inc = once - PRIOR
    f = 2.0 ** (-1.0 / 3.0)
    for k in range(1, 7):
        smap.observe(cam, labels, conf)
        np.testing.assert_allclose(smap.concentrations - PRIOR, inc * (1 - f ** k) / (1 - f), rtol=1e-9, atol=1e-12)
    # towards the fixed point inc / (1 - f): a changed class overtakes the old one within a few half-lives
    plain = SemanticMap(model, C, prior=PRIOR)
    for _ in range(6):
        plain.observe(cam, labels, conf)
    np.testing.assert_allclose(plain.concentrations - PRIOR, 6 * inc, rtol=1e-9, atol=1e-12)


def test_half_life_leaves_gaussians_without_evidence_alone():
    rng = np.random.default_rng(5)
    model, cam, kap, bg, smap = _setup(evidence_half_life=1.0)
    labels = _labels(rng, cam)
    smap.observe(cam, labels)
    before = smap.concentrations.copy()
    blank = np.full(labels.shape, 255, np.uint8)
    smap.observe(cam, blank)   # no evidence anywhere: nothing decays
    np.testing.assert_array_equal(smap.concentrations, before)
    other = camera(position=(2.0, 0, 0))
    smap.observe(other, labels)
    alpha, _, _ = change_update_reference(*kappa_reference(model.means, model.scales, model.quats_wxyz,
                                                           model.opacities, other.K, other.T_map_cam, other.width,
                                                           other.height), before, labels, C,
                                          np.zeros(model.num_gaussians), decay=0.5, prior=PRIOR)
    np.testing.assert_allclose(smap.concentrations, alpha, rtol=1e-9, atol=1e-12)


def test_surprise_is_one_minus_the_prior_expectation_of_the_label():
    rng = np.random.default_rng(6)
    model, cam, kap, bg, smap = _setup()
    first = _labels(rng, cam)
    smap.observe(cam, first)
    before = smap.render(cam, probabilities=True).probabilities
    labels = _labels(rng, cam)
    view = smap.observe(cam, labels, outputs=IMAGE_OUTPUTS)
    valid = labels < C
    v, u = np.nonzero(valid)
    np.testing.assert_allclose(view.surprise[valid], 1.0 - before[v, u, labels[valid]], rtol=1e-5, atol=1e-6)
    assert np.all(np.isnan(view.surprise[~valid]))
    assert view.surprise.dtype == np.float32
    assert smap.observe(cam, labels, outputs=("labels",)).surprise is None
    assert smap.observe(cam, labels).surprise is None           # not among the default outputs: asked for by name
    assert smap.render(cam).surprise is None


def test_sensor_model_and_depth_together_match_the_plain_rule_on_one_bin():
    """With a sensor model the depth gate applies before the soft vote: occluded pixels add nothing at all, and the
    others add what the plain rule adds (an identity sensor model)."""
    from css_ros.engine.sensor_model import SensorModel

    rng = np.random.default_rng(7)
    model, cam, kap, bg, _ = _setup()
    sm = SensorModel([f"c{i}" for i in range(C)], np.array([0.0, 100.0]), np.ones((C, 1)))  # one-hot, one bin
    smap = SemanticMap(model, C, prior=PRIOR, sensor_model=sm)
    z_m = camera_depths(model.means, cam.T_map_cam)
    depth = np.full(kap.shape[0], 0.1, np.float32)   # everything nearer: all occluded where the splat renders
    labels = _labels(rng, cam)
    depth[rng.random(depth.size) < 0.5] = np.nan          # half without measurement: voted as usual
    smap.observe(cam, labels, depth=depth.reshape(labels.shape))
    alpha, counts, _ = change_update_reference(kap, bg, np.full((model.num_gaussians, C), PRIOR), labels, C, z_m,
                                               depth=depth)
    assert _counts(smap.last_update) == counts and counts["occluded"] > 0
    np.testing.assert_allclose(smap.concentrations, alpha, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("kwargs, message", [
    (dict(transient_classes=[C]), "outside"), (dict(transient_classes="person"), "list of class ids"),
    (dict(transient_classes=[1.5]), "integers"), (dict(evidence_half_life=0.0), "evidence_half_life"),
    (dict(evidence_half_life=float("nan")), "evidence_half_life"), (dict(depth_tolerance=-1), "depth_tolerance"),
    (dict(depth_tolerance_relative=float("inf")), "depth_tolerance_relative")])
def test_bad_arguments_are_refused(kwargs, message):
    with pytest.raises(MapError, match=message):
        SemanticMap(random_scene(0, n=10), C, **kwargs)


def test_half_life_is_kept_in_the_map_file_and_refuses_merges(tmp_path):
    from css_ros.engine.merge import merge_maps

    model = random_scene(0, n=20)
    smap = SemanticMap(model, C, evidence_half_life=5.0)
    path = smap.save(tmp_path / "forgets.npz")
    loaded = SemanticMap.load(path, model)
    assert loaded.evidence_half_life == 5.0 and loaded.change_rules.decay == pytest.approx(2 ** -0.2)
    assert SemanticMap.load(path, model, evidence_half_life=None).evidence_half_life is None
    plain = SemanticMap(model, C)
    assert SemanticMap.load(plain.save(tmp_path / "plain.npz"), model).evidence_half_life is None
    with pytest.raises(MapError, match="not additive"):
        merge_maps([plain, loaded])
    with pytest.raises(MapError, match="not additive"):
        merge_maps([loaded, plain])
