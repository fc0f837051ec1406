"""The changing-world rules (css_ros.engine.change_rules) in the torch twin: transient classes, measured depth,
forgetting and surprise against a brute-force per-pixel reference written here, closed forms, and the map's own
rendered probabilities."""
from __future__ import annotations

import math

import numpy as np
import pytest

from css_ros.engine.final_form import IMAGE_OUTPUTS
from css_ros import GaussianModel, SemanticMap
from css_ros.engine.sensor_model import SensorModel
from css_reference import kappa_reference
from scenes import camera, random_quats, random_scene

C = 5
PRIOR = 1e-3
IGNORE = 255
NAMES = tuple(f"c{i}" for i in range(C))
COUNT_NAMES = ("used", "ignored", "out_of_range", "no_depth", "transient", "occluded")


def ref_kappa(model, cam):
    return kappa_reference(model.means, model.scales, model.quats_wxyz, model.opacities,
                           cam.K, cam.T_map_cam, cam.width, cam.height)


def camera_z(model, cam) -> np.ndarray:
    """(N,) camera z of every Gaussian mean (splat units), from the pose alone."""
    w2c = np.linalg.inv(cam.T_map_cam)
    return model.means @ w2c[2, :3] + w2c[2, 3]


def stats_tuple(stats) -> tuple[int, ...]:
    return tuple(getattr(stats, name) for name in COUNT_NAMES)


def change_reference(kappa, background, z, alpha, labels, *, confidence=None, depth=None, transient=(),
                     tol_abs=0.05, tol_rel=0.03, depth_scale=1.0, half_life=None, sensor=None):
    """The rules written out pixel by pixel: (alpha after the frame, counts in COUNT_NAMES order, surprise (H*W,)).

    kappa (P, N), background (P,) from the brute-force compositing; z (N,) camera z in splat units; alpha (N, C)
    before the frame; labels (H, W); confidence in (0, 1] or 0 (no vote); depth (H, W) metres or None."""
    q = 1.0 if half_life is None else 0.5 ** (1.0 / half_life)
    lab = np.asarray(labels).ravel().astype(np.int64)
    conf = None if confidence is None else np.asarray(confidence, dtype=np.float32).ravel()
    meas = None if depth is None else np.asarray(depth, dtype=np.float32).ravel()
    z_m = z * depth_scale
    mean_theta = alpha / alpha.sum(axis=1, keepdims=True)
    increment = np.zeros_like(alpha)
    counts = dict.fromkeys(COUNT_NAMES, 0)
    surprise = np.full(lab.size, np.nan)
    for i, y in enumerate(lab):
        if y == IGNORE:
            counts["ignored"] += 1
            continue
        if not 0 <= y < C:
            counts["out_of_range"] += 1
            continue
        w = 1.0 if conf is None else float(conf[i])
        if not w > 0:
            counts["ignored"] += 1
            continue
        k = kappa[i]
        ksum = k.sum()
        surprise[i] = 1.0 - (k @ mean_theta[:, y] + background[i] / C)
        if y in transient:
            counts["transient"] += 1
            continue
        rendered = (k @ z_m) / ksum if ksum > 0 else math.nan
        d = math.nan if meas is None else float(meas[i])
        keep = np.ones(len(z), dtype=bool)
        if math.isfinite(d) and d > 0:
            tau = max(tol_abs, tol_rel * d)
            if ksum > 0 and d < rendered - tau:
                counts["occluded"] += 1
                continue
            if ksum > 0 and rendered < d - tau:    # the splat's surface in front of the measured one
                keep = z_m >= d - tau
        counts["used"] += 1
        if sensor is None:
            vote = np.eye(C)[y] * w
        else:
            b = int(sensor.bin_of(np.array([rendered]))[0])
            vote = w * sensor.weight[y, b] * sensor.label_distribution()[y, b]
            counts["no_depth"] += int(not ksum > 0)
        increment += np.outer(k * keep, vote)
    touched = (increment != 0).any(axis=1)
    out = alpha.copy()
    out[touched] = PRIOR + (alpha[touched] - PRIOR) * q + increment[touched]
    return out, tuple(counts[name] for name in COUNT_NAMES), surprise


def random_depth(rng, kappa, z, shape, depth_scale) -> np.ndarray:
    """A measured depth image around the rendered one (factor 0.5..1.5: some nearer than the surface, some behind
    Gaussians), with NaN, 0, -1 and inf (no measurement) sprinkled in; float32 metres."""
    ksum = kappa.sum(axis=1)
    rendered = np.where(ksum > 0, (kappa @ z) / np.where(ksum > 0, ksum, 1.0), 3.0) * depth_scale
    d = rendered * rng.uniform(0.5, 1.5, rendered.size)
    pick = rng.random(d.size)
    d[pick < 0.04] = np.nan
    d[(pick >= 0.04) & (pick < 0.06)] = 0.0
    d[(pick >= 0.06) & (pick < 0.08)] = -1.0
    d[(pick >= 0.08) & (pick < 0.10)] = np.inf
    return d.reshape(shape).astype(np.float32)


def random_labels(rng, shape) -> np.ndarray:
    labels = rng.integers(0, C, shape)
    labels[rng.random(shape) < 0.1] = IGNORE
    labels[rng.random(shape) < 0.05] = C + 2
    return labels


CASES = {
    "transient": dict(transient=(1, 3)),
    "depth": dict(depth=True),
    "all_rules_scaled": dict(transient=(2,), depth=True, depth_scale=2.5, half_life=1.5, confidence=True),
    "sensor_model": dict(transient=(0,), depth=True, half_life=3.0, sensor=True, tol_abs=0.2, tol_rel=0.0),
}


@pytest.mark.parametrize("case", list(CASES))
def test_rules_match_brute_force(case):
    opts = CASES[case]
    rng = np.random.default_rng(11)
    model = random_scene(4, n=40, depth=(0.5, 6.0))
    scale = opts.get("depth_scale", 1.0)
    sensor = None
    if opts.get("sensor"):
        dist = rng.uniform(0.0, 1.0, (C, 3, C)) ** 3
        sensor = SensorModel(NAMES, np.array([0.0, 3.0, 6.0, 12.0]) * scale, rng.uniform(0.05, 1.0, (C, 3)),
                             dist / dist.sum(axis=2, keepdims=True))
    tol_abs, tol_rel = opts.get("tol_abs", 0.05), opts.get("tol_rel", 0.03)
    smap = SemanticMap(model, C, prior=PRIOR, backend="torch", depth_scale=scale, sensor_model=sensor,
                       transient_classes=list(opts.get("transient", ())), evidence_half_life=opts.get("half_life"),
                       depth_tolerance=tol_abs, depth_tolerance_relative=tol_rel)
    alpha = np.full((model.num_gaussians, C), PRIOR)
    totals = np.zeros(6, dtype=np.int64)
    for i, pose in enumerate([dict(), dict(position=(0.3, -0.1, 0.4), quat=(0.03, -0.04, 0.0, 0.998))] * 2):
        cam = camera(**pose)
        labels = random_labels(rng, (cam.height, cam.width))
        conf = None
        if opts.get("confidence"):
            conf = rng.uniform(0, 1, labels.shape).astype(np.float32)
            conf[rng.random(labels.shape) < 0.05] = 0.0
        kap, bg = ref_kappa(model, cam)
        z = camera_z(model, cam)
        depth = random_depth(rng, kap, z, labels.shape, scale) if opts.get("depth") else None
        alpha, counts, surprise = change_reference(
            kap, bg, z, alpha, labels, confidence=conf, depth=depth, transient=opts.get("transient", ()),
            tol_abs=tol_abs, tol_rel=tol_rel, depth_scale=scale, half_life=opts.get("half_life"), sensor=sensor)
        view = smap.observe(cam, labels.astype(np.uint16), conf, depth=depth, outputs=IMAGE_OUTPUTS)
        np.testing.assert_allclose(smap.concentrations, alpha, rtol=1e-9, atol=1e-12)
        assert stats_tuple(smap.last_update) == counts
        got = smap.last_update
        assert got.used + got.ignored + got.out_of_range + got.transient + got.occluded == labels.size
        assert view.surprise is not None and view.surprise.dtype == np.float32
        np.testing.assert_array_equal(np.isnan(view.surprise), np.isnan(surprise.reshape(labels.shape)))
        np.testing.assert_allclose(view.surprise, surprise.reshape(labels.shape), atol=1e-5, equal_nan=True)
        totals += counts
    # every rule of the case was exercised
    assert totals[0] > 0
    assert (totals[4] > 0) == bool(opts.get("transient"))
    assert (totals[5] > 0) == bool(opts.get("depth"))
    if sensor is not None:
        assert totals[3] > 0


def test_transient_pixels_add_nothing_and_are_counted():
    rng = np.random.default_rng(2)
    model = random_scene(3, n=60)
    cam = camera()
    labels = random_labels(rng, (cam.height, cam.width))
    gated = SemanticMap(model, C, prior=PRIOR, backend="torch", transient_classes=[1, 4])
    stats = gated.update(cam, labels)
    # the same frame with the transient pixels unlabelled: the same evidence
    plain = SemanticMap(model, C, prior=PRIOR, backend="torch")
    is_transient = np.isin(labels, [1, 4])
    plain_stats = plain.update(cam, np.where(is_transient, IGNORE, labels))
    np.testing.assert_allclose(gated.concentrations, plain.concentrations, rtol=1e-12, atol=0)
    assert stats.transient == int(is_transient.sum()) > 0
    assert plain_stats.ignored - stats.ignored == stats.transient
    assert stats.used == plain_stats.used and stats.occluded == 0
    # only transient labels: the map does not change at all
    only = SemanticMap(model, C, prior=PRIOR, backend="torch", transient_classes=[2])
    stats = only.update(cam, np.full(labels.shape, 2))
    np.testing.assert_array_equal(only.concentrations, np.full((model.num_gaussians, C), PRIOR))
    assert (stats.used, stats.transient) == (0, labels.size)


def two_layers() -> tuple[GaussianModel, np.ndarray]:
    """A wall of broad opaque Gaussians at z = 3 m covering the default camera's view, and six translucent ones
    at z = 1.5 m in front of it; returns the model and the near ones' mask."""
    xs, ys = np.meshgrid(np.linspace(-2.2, 2.2, 9), np.linspace(-1.6, 1.6, 7))
    wall = np.c_[xs.ravel(), ys.ravel(), np.full(xs.size, 3.0)]
    near = np.c_[np.linspace(-0.7, 0.7, 6), np.tile([-0.2, 0.25], 3), np.full(6, 1.5)]
    means = np.concatenate([wall, near])
    scales = np.concatenate([np.tile([0.35, 0.35, 0.01], (len(wall), 1)), np.tile([0.12, 0.12, 0.01], (6, 1))])
    n = len(means)
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    opac = np.concatenate([np.full(len(wall), 0.9), np.full(6, 0.5)])
    model = GaussianModel.from_activated(means, scales, quats, opac, np.full((n, 3), 0.5))
    return model, np.arange(n) >= len(wall)


def test_nearer_depth_blocks_the_pixel_and_farther_depth_drops_the_gaussians_in_front():
    model, near = two_layers()
    cam = camera()
    h, w = cam.height, cam.width
    kap, _ = ref_kappa(model, cam)
    covered = (kap.sum(axis=1) > 0).reshape(h, w)
    assert covered.all()
    near_px = (kap[:, near].sum(axis=1) > 0).reshape(h, w)
    left = np.zeros((h, w), dtype=bool)
    left[:, : w // 2] = True
    assert near_px[left].any() and near_px[~left].any()       # the near layer is seen on both sides
    labels = np.full((h, w), 3)
    depth = np.where(left, 0.8, 3.0).astype(np.float32)     # left: a person at 0.8 m; right: the wall, nothing before it
    smap = SemanticMap(model, C, prior=PRIOR, backend="torch")
    stats = smap.update(cam, labels, depth=depth)
    assert (stats.occluded, stats.used) == (int(left.sum()), int((~left).sum()))
    alpha = smap.concentrations
    # on the right, where the near layer pulls the rendered depth in front of the wall by more than the tolerance,
    # it is no longer there: it gets nothing from those pixels (only the faint edges, where the rendered depth
    # agrees with the wall, still vote for it); the wall gets the right half's kappa unchanged
    z = camera_z(model, cam)
    rendered = (kap @ z) / kap.sum(axis=1)
    gone = (~left).ravel() & (rendered < 3.0 - 0.09)
    assert kap[gone][:, near].sum() > 0.5 * kap[(~left).ravel()][:, near].sum()
    expected_near = PRIOR + kap[(~left).ravel() & ~gone][:, near].sum(axis=0)
    np.testing.assert_allclose(alpha[near, 3], expected_near, rtol=1e-9)
    expected = PRIOR + kap[(~left).ravel()][:, ~near].sum(axis=0)
    np.testing.assert_allclose(alpha[~near, 3], expected, rtol=1e-9)
    np.testing.assert_array_equal(np.delete(alpha, 3, axis=1), PRIOR)
    # without the depth image the near layer does get evidence (the check above is not empty)
    plain = SemanticMap(model, C, prior=PRIOR, backend="torch")
    plain.update(cam, labels)
    assert (plain.concentrations[near, 3] > PRIOR + 1.0).all()


def test_invalid_depth_is_no_measurement():
    rng = np.random.default_rng(5)
    model = random_scene(7, n=60)
    cam = camera()
    labels = random_labels(rng, (cam.height, cam.width))
    plain = SemanticMap(model, C, prior=PRIOR, backend="torch", evidence_half_life=2.0, transient_classes=[0])
    plain_stats = plain.update(cam, labels)
    fills = [np.nan, 0.0, np.inf, -np.inf, -2.0]
    mixed = np.asarray(fills, dtype=np.float32)[rng.integers(0, len(fills), labels.shape)]
    for depth in [np.full(labels.shape, f, dtype=np.float32) for f in fills] + [mixed]:
        smap = SemanticMap(model, C, prior=PRIOR, backend="torch", evidence_half_life=2.0, transient_classes=[0])
        stats = smap.update(cam, labels, depth=depth)
        np.testing.assert_array_equal(smap.concentrations, plain.concentrations)
        assert stats == plain_stats and stats.occluded == 0


def test_half_life_closed_form_over_repeated_frames():
    """Frame 1 labels everything class 0, frames 2..k+1 class 1, same pose: with q = 2^(-1/h),
    alpha^0 - alpha_0 = K q^k and alpha^1 - alpha_0 = K (1 - q^k) / (1 - q), K the Gaussian's kappa sum; Gaussians
    no frame reaches keep what they had (here: evidence from another view, observed first)."""
    seen = random_scene(8, n=40)
    other = random_scene(9, n=20)
    model = GaussianModel.from_activated(
        np.concatenate([seen.means, other.means + [40.0, 0.0, 0.0]]), np.concatenate([seen.scales, other.scales]),
        np.concatenate([seen.quats_wxyz, other.quats_wxyz]), np.concatenate([seen.opacities, other.opacities]),
        np.full((60, 3), 0.5))
    cam, away = camera(), camera(position=(40.0, 0.0, 0.0))
    kap, _ = ref_kappa(model, cam)
    k_sum = kap.sum(axis=0)
    hit = k_sum > 0
    assert hit[:40].sum() > 10 and not hit[40:].any()
    h, k = 2.0, 5
    q = 0.5 ** (1.0 / h)
    smap = SemanticMap(model, C, prior=PRIOR, backend="torch", evidence_half_life=h)
    shape = (cam.height, cam.width)
    smap.update(away, np.full(shape, 4))
    before_away = smap.concentrations[40:].copy()
    assert (before_away[:, 4] > PRIOR).any()
    smap.update(cam, np.zeros(shape, dtype=np.int64))
    for _ in range(k):
        smap.update(cam, np.ones(shape, dtype=np.int64))
    alpha = smap.concentrations
    np.testing.assert_allclose(alpha[hit, 0] - PRIOR, k_sum[hit] * q ** k, rtol=1e-9)
    np.testing.assert_allclose(alpha[hit, 1] - PRIOR, k_sum[hit] * (1 - q ** k) / (1 - q), rtol=1e-9)
    np.testing.assert_allclose(alpha[hit][:, 2:], PRIOR, rtol=1e-12)
    np.testing.assert_array_equal(alpha[40:], before_away)     # untouched by the frames that do not reach them
    np.testing.assert_array_equal(alpha[:40][~hit[:40]], PRIOR)
    # after h frames of class 1, half of class 0's evidence is left (the half-life's meaning)
    assert (alpha[hit, 0] - PRIOR) == pytest.approx(k_sum[hit] * 0.5 ** (k / h), rel=1e-9)


def test_surprise_is_one_minus_the_probability_rendered_before_the_update():
    rng = np.random.default_rng(4)
    model = random_scene(10, n=80)
    smap = SemanticMap(model, C, prior=PRIOR, backend="torch", transient_classes=[2], evidence_half_life=4.0)
    for i, pose in enumerate([dict(), dict(position=(0.2, 0.0, -0.1)), dict()]):
        cam = camera(**pose)
        labels = random_labels(rng, (cam.height, cam.width))
        conf = rng.uniform(0, 1, labels.shape).astype(np.float32)
        conf[rng.random(labels.shape) < 0.05] = 0.0
        kap, _ = ref_kappa(model, cam)
        depth = random_depth(rng, kap, camera_z(model, cam), labels.shape, 1.0)
        probs = smap.render(cam, probabilities=True).probabilities
        view = smap.observe(cam, labels, conf, depth=depth, outputs=("labels", "surprise"))
        voted = (labels >= 0) & (labels < C) & (conf > 0)
        expected = np.full(labels.shape, np.nan)
        vv, uu = np.nonzero(voted)
        expected[vv, uu] = 1.0 - probs[vv, uu, labels[vv, uu]]
        assert view.surprise.dtype == np.float32
        np.testing.assert_array_equal(np.isnan(view.surprise), ~voted)   # NaN exactly where no vote
        np.testing.assert_allclose(view.surprise, expected, atol=1e-5, equal_nan=True)
        assert smap.last_update.transient > 0 and smap.last_update.occluded > 0   # these pixels have a surprise too
    assert smap.observe(cam, labels, outputs=("labels",)).surprise is None


def test_uncovered_pixel_surprise_is_one_minus_one_over_c():
    model = GaussianModel.from_activated(np.array([[0.0, 0.0, 2.0]]), np.full((1, 3), 0.05),
                                         random_quats(np.random.default_rng(0), 1), np.array([0.9]), np.ones((1, 3)))
    cam = camera()
    smap = SemanticMap(model, C, prior=PRIOR, backend="torch")
    view = smap.observe(cam, np.full((cam.height, cam.width), 1), outputs=("surprise",))
    kap, _ = ref_kappa(model, cam)
    empty = (kap.sum(axis=1) == 0).reshape(cam.height, cam.width)
    assert empty.any() and not empty.all()
    np.testing.assert_allclose(view.surprise[empty], 1.0 - 1.0 / C, rtol=1e-6)


@pytest.mark.parametrize("sensor", [False, True])
def test_torch_and_numba_agree(sensor):
    """The twin and the compiled CPU backend under every rule at once: counts exactly, concentrations to 1e-9
    relative, surprise to 1e-5; on a random scene and one with early termination (opaque sheets) and off-screen
    Gaussians."""
    from scenes import edge_case_scene

    rng = np.random.default_rng(21)
    scale = 1.7
    sensor_model = None
    if sensor:
        dist = rng.uniform(0.0, 1.0, (C, 3, C)) ** 3
        sensor_model = SensorModel(NAMES, np.array([0.0, 2.0, 4.0, 10.0]) * scale, rng.uniform(0.05, 1.0, (C, 3)),
                                   dist / dist.sum(axis=2, keepdims=True))
    for model in (random_scene(12, n=150), edge_case_scene(3)):
        maps = [SemanticMap(model, C, prior=PRIOR, backend=b, depth_scale=scale, sensor_model=sensor_model,
                            transient_classes=[3], evidence_half_life=2.5, depth_tolerance=0.1,
                            depth_tolerance_relative=0.02) for b in ("torch", "numba")]
        poses = [dict(), dict(position=(0.3, -0.1, 0.4), quat=(0.03, -0.04, 0.0, 0.998)), dict(position=(0, 0.1, 0))]
        occluded = 0
        for pose in poses:
            cam = camera(**pose)
            labels = random_labels(rng, (cam.height, cam.width)).astype(np.uint8)
            conf = rng.uniform(0, 1.2, labels.shape).astype(np.float32)
            conf[rng.random(labels.shape) < 0.05] = np.nan
            kap, _ = ref_kappa(model, cam)
            depth = random_depth(rng, kap, camera_z(model, cam), labels.shape, scale)
            views = [m.observe(cam, labels, conf, depth=depth, outputs=("surprise",)) for m in maps]
            assert stats_tuple(maps[0].last_update) == stats_tuple(maps[1].last_update)
            np.testing.assert_allclose(maps[0].concentrations, maps[1].concentrations, rtol=1e-9, atol=0)
            np.testing.assert_array_equal(np.isnan(views[0].surprise), np.isnan(views[1].surprise))
            np.testing.assert_allclose(views[0].surprise, views[1].surprise, atol=1e-5, equal_nan=True)
            occluded += maps[0].last_update.occluded
        assert occluded > 0 and maps[0].last_update.transient > 0
