"""SemanticMap: update and probabilistic render vs the brute-force reference, closed forms, persistence."""
from __future__ import annotations

import numba
import numpy as np
import pytest

from css_ros import InputError, MapError, SemanticMap
from css_ros.engine.map_file import MapContents, write_map_file
from css_reference import kappa_reference, render_reference, update_reference
from scenes import camera, edge_case_scene, random_scene

C = 6


def ref_kappa(model, cam):
    return kappa_reference(model.means, model.scales, model.quats_wxyz, model.opacities,
                           cam.K, cam.T_map_cam, cam.width, cam.height)


def check_view(view, kap, bg, alpha, alpha_b, cam, unknown=0.5, ignore=255):
    E, V, lab, e_hat, v_hat, u_var, u_exp = render_reference(kap, bg, alpha, alpha_b)
    h, w = cam.height, cam.width
    np.testing.assert_allclose(view.expectation, e_hat.reshape(h, w), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(view.variance, v_hat.reshape(h, w), rtol=1e-5, atol=1e-12)
    np.testing.assert_allclose(view.background, bg.reshape(h, w), atol=1e-6)
    # labels: compare where the top class is not a near tie
    srt = np.sort(E, axis=1)
    clear = (srt[:, -1] - srt[:, -2] > 1e-6).reshape(h, w)
    expected = lab.reshape(h, w).copy()
    expected[bg.reshape(h, w) > unknown] = ignore
    assert clear.mean() > 0.5
    np.testing.assert_array_equal(view.labels[clear], expected[clear])
    assert view.u_var == pytest.approx(u_var, rel=1e-5)
    assert view.u_exp == pytest.approx(u_exp, rel=1e-5, abs=1e-7)
    return E


@pytest.mark.parametrize("backend", ["numba", "torch"])
@pytest.mark.parametrize("seed", [0, 1])
def test_observe_matches_reference(backend, seed):
    rng = np.random.default_rng(100 + seed)
    model = random_scene(seed)
    smap = SemanticMap(model, C, prior=1e-3, background=1e-3, backend=backend)
    alpha = np.full((model.num_gaussians, C), 1e-3)
    poses = [dict(), dict(position=(0.2, 0.1, -0.2), quat=(0.02, 0.05, 0.0, 0.998))]
    for i, pose in enumerate(poses * 2):
        cam = camera(**pose)
        labels = rng.integers(0, C, (cam.height, cam.width))
        labels[rng.random(labels.shape) < 0.1] = 255          # no label
        labels[rng.random(labels.shape) < 0.05] = C + 3       # out of range: ignored
        conf = rng.uniform(0, 1, labels.shape).astype(np.float32) if i % 2 else None
        kap, bg = ref_kappa(model, cam)
        alpha = update_reference(kap, alpha, labels, C, confidence=conf)
        view = smap.observe(cam, labels.astype(np.uint16), conf, probabilities=True)
        np.testing.assert_allclose(smap.concentrations, alpha, rtol=1e-5, atol=1e-9)
        E = check_view(view, kap, bg, alpha, 1e-3, cam)
        np.testing.assert_allclose(view.probabilities.reshape(-1, C), E, rtol=1e-5, atol=1e-7)


def test_edge_cases_render_matches_reference():
    model = edge_case_scene()
    cam = camera()
    rng = np.random.default_rng(7)
    smap = SemanticMap(model, C)
    labels = rng.integers(0, C, (cam.height, cam.width))
    kap, bg = ref_kappa(model, cam)
    alpha = update_reference(kap, np.full((model.num_gaussians, C), 1e-3), labels, C)
    view = smap.observe(cam, labels)
    np.testing.assert_allclose(smap.concentrations, alpha, rtol=1e-5, atol=1e-9)
    check_view(view, kap, bg, alpha, 1e-3, camera())


def test_update_alone_equals_observe_update_and_render_is_pure():
    model = random_scene(4)
    cam = camera()
    labels = np.random.default_rng(0).integers(0, C, (cam.height, cam.width))
    a, b = SemanticMap(model, C), SemanticMap(model, C)
    stats = a.update(cam, labels)
    b.observe(cam, labels)
    np.testing.assert_array_equal(a.concentrations, b.concentrations)
    assert stats.used == labels.size and stats.ignored == 0 and stats.out_of_range == 0
    before = a.concentrations.copy()
    a.render(camera(position=(0.1, 0, 0)))
    np.testing.assert_array_equal(a.concentrations, before)


def test_probabilities_sum_to_one_and_unobserved_is_uniform():
    model = random_scene(2)
    cam = camera()
    smap = SemanticMap(model, C)
    view = smap.render(cam, probabilities=True)
    # sum_c E_i^c = sum_n kappa_in + kappa_b = 1
    np.testing.assert_allclose(view.probabilities.sum(axis=2), 1.0, atol=1e-5)
    np.testing.assert_allclose(view.probabilities, 1.0 / C, atol=1e-6)
    np.testing.assert_allclose(view.expectation, 1.0 / C, atol=1e-6)
    assert view.u_exp == pytest.approx(1 - 1 / C, abs=1e-6)
    smap.observe(cam, np.random.default_rng(0).integers(0, C, (cam.height, cam.width)))
    np.testing.assert_allclose(smap.render(cam, probabilities=True).probabilities.sum(axis=2), 1.0, atol=1e-5)


def test_repeated_observations_shrink_variance_monotonically():
    model = random_scene(3)
    cam = camera()
    labels = np.full((cam.height, cam.width), 2)
    smap = SemanticMap(model, C)
    prev_var, prev_u = None, None
    covered = None
    for _ in range(6):
        view = smap.observe(cam, labels)
        if prev_var is not None:
            # the Gaussian part shrinks; the constant background part kappa_b^2 Var_b bounds it below
            assert np.all(view.variance[covered] <= prev_var[covered] * (1 + 1e-6))
            assert view.variance[covered].sum() < prev_var[covered].sum()
            assert view.u_var < prev_u
        covered = view.background < 0.5
        prev_var, prev_u = view.variance.copy(), view.u_var
    assert np.all(view.labels[covered] == 2)


def test_ignored_and_zero_confidence_pixels_change_nothing():
    model = random_scene(0)
    cam = camera()
    smap = SemanticMap(model, C)
    shape = (cam.height, cam.width)
    stats = smap.update(cam, np.full(shape, 255))
    assert stats.used == 0 and stats.ignored == np.prod(shape)
    stats = smap.update(cam, np.full(shape, C + 1))
    assert stats.out_of_range == np.prod(shape)
    smap.update(cam, np.zeros(shape, int), confidence=np.zeros(shape, np.float32))
    np.testing.assert_array_equal(smap.concentrations, 1e-3)


def test_confidence_scales_linearly():
    model = random_scene(1)
    cam = camera()
    labels = np.random.default_rng(3).integers(0, C, (cam.height, cam.width))
    full, half = SemanticMap(model, C), SemanticMap(model, C)
    full.update(cam, labels)
    half.update(cam, labels, confidence=np.full(labels.shape, 0.5, np.float32))
    np.testing.assert_allclose(half.concentrations - 1e-3, 0.5 * (full.concentrations - 1e-3), rtol=1e-6, atol=1e-12)


def test_bad_inputs_raise_input_error():
    model = random_scene(0)
    cam = camera()
    smap = SemanticMap(model, C)
    with pytest.raises(InputError):
        smap.update(cam, np.zeros((10, 10), int))
    with pytest.raises(InputError):
        smap.update(cam, np.zeros((cam.height, cam.width), float))
    with pytest.raises(InputError):
        smap.update(cam, np.zeros((cam.height, cam.width), int), confidence=np.ones((3, 3)))
    np.testing.assert_array_equal(smap.concentrations, 1e-3)


def test_save_load_roundtrip(tmp_path):
    model = random_scene(0)
    cam = camera()
    smap = SemanticMap(model, C, prior=2e-3, background=5e-3)
    smap.observe(cam, np.random.default_rng(0).integers(0, C, (cam.height, cam.width)))
    path = smap.save(tmp_path / "sub" / "map.npz")
    loaded = SemanticMap.load(path, model)
    np.testing.assert_array_equal(loaded.concentrations, smap.concentrations)
    assert (loaded.prior, loaded.background, loaded.num_classes, loaded.frames_observed) == (2e-3, 5e-3, C, 1)
    with np.load(path, allow_pickle=False) as data:  # plain arrays only
        assert int(data["format_version"]) == 1
    assert [p.name for p in path.parent.iterdir()] == ["map.npz"]  # no temp file left


def test_load_refuses_foreign_corrupt_or_invalid(tmp_path):
    model, other = random_scene(0), random_scene(1)
    smap = SemanticMap(model, C)
    path = smap.save(tmp_path / "map.npz")
    with pytest.raises(MapError, match="this map belongs to model"):
        SemanticMap.load(path, other)
    bad = tmp_path / "bad.npz"
    bad.write_bytes(path.read_bytes()[:200])
    with pytest.raises(MapError):
        SemanticMap.load(bad, model)
    with pytest.raises(MapError):
        SemanticMap.load(tmp_path / "missing.npz", model)
    smap.concentrations[0, 0] = np.nan
    with pytest.raises(MapError, match="must be loadable"):  # save never writes what load refuses
        smap.save(tmp_path / "nan.npz")
    assert not (tmp_path / "nan.npz").exists()
    # a file written past that check (another writer, a crafted file)
    write_map_file(tmp_path / "nan.npz", MapContents(model.fingerprint, smap.concentrations_readonly, smap.prior,
                                                     smap.background))
    with pytest.raises(MapError, match="invalid"):
        SemanticMap.load(tmp_path / "nan.npz", model)


def test_crash_during_save_keeps_last_good_file(tmp_path, monkeypatch):
    model = random_scene(0)
    smap = SemanticMap(model, C)
    path = smap.save(tmp_path / "map.npz")
    good = path.read_bytes()
    smap.concentrations += 1.0

    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez", boom)
    with pytest.raises(MapError, match="disk full"):
        smap.save(path)
    assert path.read_bytes() == good
    assert [p.name for p in tmp_path.iterdir()] == ["map.npz"]


def test_reset_returns_to_prior():
    model = random_scene(0)
    cam = camera()
    smap = SemanticMap(model, C)
    smap.observe(cam, np.zeros((cam.height, cam.width), int))
    smap.reset()
    np.testing.assert_array_equal(smap.concentrations, 1e-3)
    assert smap.frames_observed == 0


def test_fast_and_torch_paths_agree_on_a_large_scene():
    """Cross-check of the two implementations on a scene too big for the brute-force reference."""
    rng = np.random.default_rng(11)
    model = random_scene(11, n=20_000, log_scale=(-5, -2.5))
    cam = camera(width=160, height=120, f=120.0)
    fast, slow = SemanticMap(model, 8), SemanticMap(model, 8, backend="torch")
    for pose in [dict(), dict(position=(0.1, -0.1, 0.2))]:
        c = camera(width=160, height=120, f=120.0, **pose)
        labels = rng.integers(0, 8, (c.height, c.width))
        vf, vs = fast.observe(c, labels), slow.observe(c, labels)
    np.testing.assert_allclose(fast.concentrations, slow.concentrations, rtol=1e-5, atol=1e-8)
    np.testing.assert_allclose(vf.expectation, vs.expectation, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(vf.variance, vs.variance, rtol=1e-4, atol=1e-10)
    assert np.mean(vf.labels == vs.labels) > 0.999
    assert np.abs(vf.rgb.astype(int) - vs.rgb).max() <= 1
    assert vf.u_var == pytest.approx(vs.u_var, rel=1e-4)
    assert vf.u_exp == pytest.approx(vs.u_exp, rel=1e-4)
    assert cam.width == 160


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_score_views_match_reference_and_render(backend):
    """The batch scores equal the brute-force U_var/U_exp of each view and render()'s own scores."""
    rng = np.random.default_rng(7)
    model = random_scene(3)
    smap = SemanticMap(model, C, backend=backend)
    smap.concentrations += rng.uniform(0.0, 5.0, smap.concentrations.shape)
    poses = [dict(), dict(position=(0.2, 0.1, -0.2), quat=(0.02, 0.05, 0.0, 0.998)),
             dict(position=(-0.3, 0.0, 0.1), quat=(0.0, -0.08, 0.01, 0.997)), dict(width=32, height=24, f=25.0)]
    cams = [camera(**p) for p in poses]
    scores = smap.score_views(cams)
    assert scores.shape == (len(cams), 3)
    for cam, (u_var, u_exp, _) in zip(cams, scores):
        kap, bg = ref_kappa(model, cam)
        *_, ref_var, ref_exp = render_reference(kap, bg, smap.concentrations, 1e-3)
        assert u_var == pytest.approx(ref_var, rel=1e-5)
        assert u_exp == pytest.approx(ref_exp, rel=1e-5, abs=1e-7)
        view = smap.render(cam)
        assert (u_var, u_exp) == (view.u_var, view.u_exp)
    assert smap.score_views([]).shape == (0, 3)
    # one view after another (single thread) gives the same numbers as the worker pool
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        single = smap.score_views(cams)
        np.testing.assert_array_equal(single[:, :2], scores[:, :2])
        np.testing.assert_allclose(single[:, 2], scores[:, 2], rtol=1e-12)  # per-chunk sums: another order
    finally:
        numba.set_num_threads(threads)
