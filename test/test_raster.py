"""The compiled rasteriser against the brute-force float64 reference of SPEC §3 (and its torch twin)."""
from __future__ import annotations

import numpy as np
import pytest

from css_ros.engine.cpu.backend import NumbaBackend
from css_ros.engine.cpu.projection import GaussianGeometry, project
from css_ros.engine.cpu.raster import bin_tiles, kappa_lists
from css_ros.engine.sh import eval_sh
from css_reference import kappa_reference
from scenes import camera, edge_case_scene, random_scene


def dense_kappa(model, cam, tile_size=16):
    proj = project(GaussianGeometry.from_model(model), cam)
    bins = bin_tiles(proj, cam.width, cam.height, tile_size)
    kl = kappa_lists(proj, bins, cam.width, cam.height)
    dense = np.zeros((cam.width * cam.height, model.num_gaussians))
    np.add.at(dense, (kl.pixel, kl.gaussian), kl.kappa)
    # each (pixel, Gaussian) pair appears at most once
    assert len(set(zip(kl.pixel.tolist(), kl.gaussian.tolist()))) == len(kl.pixel)
    return dense, kl.background


def reference(model, cam):
    return kappa_reference(model.means, model.scales, model.quats_wxyz, model.opacities,
                           cam.K, cam.T_map_cam, cam.width, cam.height)


CAMERAS = [
    dict(),
    dict(position=(0.3, -0.2, -0.5), quat=(0.05, -0.08, 0.02, 0.995)),
    dict(width=37, height=29, f=30.0),               # not a multiple of the tile size
    dict(width=50, height=40, cx=10.0, cy=30.0),     # off-centre principal point
]


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("cam_kw", CAMERAS)
def test_kappa_matches_brute_force_random(seed, cam_kw):
    model = random_scene(seed)
    cam = camera(**cam_kw)
    kap, bg = dense_kappa(model, cam)
    ref_kap, ref_bg = reference(model, cam)
    np.testing.assert_allclose(kap, ref_kap, atol=1e-10)
    np.testing.assert_allclose(bg, ref_bg, atol=1e-10)
    # kappa_b = 1 - sum_n kappa_in
    np.testing.assert_allclose(bg, 1.0 - kap.sum(axis=1), atol=1e-9)
    assert kap.max() > 0.1


@pytest.mark.parametrize("cam_kw", CAMERAS[:2])
def test_kappa_matches_brute_force_edge_cases(cam_kw):
    model = edge_case_scene()
    cam = camera(**cam_kw)
    kap, bg = dense_kappa(model, cam)
    ref_kap, ref_bg = reference(model, cam)
    np.testing.assert_allclose(kap, ref_kap, atol=1e-10)
    np.testing.assert_allclose(bg, ref_bg, atol=1e-10)
    # Gaussians behind the camera / below 1/255 opacity never contribute
    assert np.all(kap[:, :3] == 0)
    z_cam = (model.means @ cam.R_cam_map.T + cam.t_cam_map)[:, 2]
    behind = z_cam <= 0.01
    assert behind.sum() >= 10
    assert np.all(kap[:, behind] == 0)


def test_early_termination_behind_opaque_sheets():
    model = edge_case_scene()
    cam = camera()
    kap, bg = dense_kappa(model, cam)
    centre = (cam.height // 2) * cam.width + cam.width // 2
    # the stack of 0.99-alpha sheets stops compositing with T >= 1e-4, so the background keeps it
    assert 1e-4 * 0.01 <= bg[centre] < 1e-2
    ordinary_far = np.flatnonzero(model.means[:, 2] > 2.6)
    assert kap[centre, ordinary_far].sum() < 1e-2


@pytest.mark.parametrize("tile_size", [4, 8, 32])
def test_tile_size_does_not_change_kappa(tile_size):
    model = random_scene(5)
    cam = camera()
    a, bg_a = dense_kappa(model, cam, 16)
    b, bg_b = dense_kappa(model, cam, tile_size)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(bg_a, bg_b)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_colour_render_matches_reference(degree):
    rng = np.random.default_rng(degree)
    base = random_scene(10 + degree)
    from css_ros import GaussianModel

    k = (degree + 1) ** 2
    sh = rng.normal(scale=0.4, size=(base.num_gaussians, k, 3)).astype(np.float32)
    model = GaussianModel(means=base.means, sh=sh, opacity_logits=base.opacity_logits,
                          log_scales=base.log_scales, rotations=base.rotations)
    cam = camera(position=(0.2, 0.1, -0.3))
    backend = NumbaBackend(model)
    buf = backend.render(backend.prepare(cam), np.ones((model.num_gaussians, 2)), 0.5, 0.0, 1.0,
                         np.array([0.2, 0.4, 0.6]), False)
    kap, bg = reference(model, cam)
    dirs = model.means.astype(np.float64) - cam.position
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    colours = np.maximum(eval_sh(sh.astype(np.float64), dirs) + 0.5, 0.0)
    ref = kap @ colours + bg[:, None] * np.array([0.2, 0.4, 0.6])
    np.testing.assert_allclose(buf.rgb.reshape(-1, 3), ref, atol=1e-5)


def test_no_dense_pixel_by_gaussian_storage():
    """The per-view state grows with contributions, not with pixels x Gaussians."""
    model = random_scene(3, n=2000, log_scale=(-5, -3))
    cam = camera(width=160, height=120)
    proj = project(GaussianGeometry.from_model(model), cam)
    bins = bin_tiles(proj, cam.width, cam.height)
    assert bins.lists.size < 0.05 * cam.width * cam.height * model.num_gaussians


@pytest.mark.parametrize("seed", [0, 1])
def test_group_culling_keeps_exactly_the_visible_gaussians(seed):
    """Whole Morton groups are skipped by a bounding-sphere test: the kept set must equal the set an
    independent per-Gaussian projection (the PyTorch twin) keeps, on a scene all around the camera."""
    from css_ros.engine.torch.raster import TorchBackend

    rng = np.random.default_rng(seed)
    from css_ros import GaussianModel
    from scenes import random_quats

    n = 6000
    model = GaussianModel.from_activated(rng.uniform(-8, 8, (n, 3)), np.exp(rng.uniform(-4, 0.5, (n, 3))),
                                         random_quats(rng, n), rng.uniform(0.01, 1, n), rng.uniform(0, 1, (n, 3)))
    cam = camera(width=80, height=60, position=(0.5, -0.3, 0.2), quat=(0.1, 0.3, -0.05, 0.95))
    geometry = GaussianGeometry.from_model(model)
    assert geometry.group_offsets.size > 20
    proj = project(geometry, cam)
    ref = TorchBackend(model).prepare(cam)
    assert 0 < proj.count < n // 2
    assert set(proj.ids.tolist()) == set(ref.ids.tolist())
    order = np.argsort(proj.ids)
    ref_order = np.argsort(ref.ids)
    np.testing.assert_allclose(proj.means2d[order], ref.means2d.numpy()[ref_order], rtol=1e-9, atol=1e-9)


def test_longest_list_sizes_the_walk_scratch():
    """The walk scratch is sized once per frame by the longest tile list (never grown in the tile loop)."""
    from numba import njit

    from css_ros.engine.cpu.composite import longest_list
    longest = njit(lambda offsets: longest_list(offsets))
    rng = np.random.default_rng(3)
    for _ in range(20):
        offsets = np.concatenate([[0], np.cumsum(rng.integers(0, 900, rng.integers(1, 50)))]).astype(np.int64)
        assert longest(offsets) == max(1, int(np.diff(offsets).max()))
    assert longest(np.zeros(1, dtype=np.int64)) == 1          # no tiles
    assert longest(np.zeros(5, dtype=np.int64)) == 1          # only empty lists


def test_long_and_uneven_tile_lists_match_brute_force():
    """Lists of several hundred entries beside short ones (the scratch of every kernel holds the longest): kappa,
    and the update + render of observe, against the brute-force reference."""
    from css_ros import SemanticMap
    from css_reference import update_reference
    model = random_scene(7, n=1500, log_scale=(-2.0, -0.6))
    cam = camera(width=80, height=40, f=20.0)      # a wide view: the scene fills the middle tiles only
    proj = project(GaussianGeometry.from_model(model), cam)
    lengths = np.diff(bin_tiles(proj, cam.width, cam.height).offsets)
    assert lengths.max() > 600 and lengths.min() < lengths.max() / 4
    kap, bg = dense_kappa(model, cam)
    ref_kap, ref_bg = reference(model, cam)
    np.testing.assert_allclose(kap, ref_kap, atol=1e-10)
    np.testing.assert_allclose(bg, ref_bg, atol=1e-10)
    labels = np.random.default_rng(8).integers(0, 5, (cam.height, cam.width))
    smap = SemanticMap(model, 5, prior=1e-3, background=1e-3)
    view = smap.observe(cam, labels)
    alpha = update_reference(ref_kap, np.full((model.num_gaussians, 5), 1e-3), labels, 5)
    np.testing.assert_allclose(smap.concentrations, alpha, rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(view.background, ref_bg.reshape(cam.height, cam.width), atol=1e-6)


@pytest.mark.parametrize("nchunks", [1, 2, 3, 5])
@pytest.mark.parametrize("tiles_x, tiles_y", [(1, 1), (7, 3), (80, 60), (4, 1), (3, 2)])
def test_work_chunks_hold_every_tile_once_in_whole_rows(nchunks, tiles_x, tiles_y):
    """The update and the render deal whole tile rows to their chunks round-robin (no image cache line shared by
    two threads); every tile belongs to exactly one chunk, in row order within it."""
    from numba import njit

    from css_ros.engine.cpu.raster import _chunk_tile, _chunk_tile_count
    count = njit(lambda ch, n, tx, t: _chunk_tile_count(ch, n, tx, t))
    tile = njit(lambda k, ch, n, tx: _chunk_tile(k, ch, n, tx))
    seen = []
    for ch in range(nchunks):
        mine = [tile(k, ch, nchunks, tiles_x) for k in range(count(ch, nchunks, tiles_x, tiles_x * tiles_y))]
        assert mine == sorted(mine)
        assert all(t // tiles_x % nchunks == ch for t in mine)              # rows ch, ch + nchunks, ...
        assert len(mine) == tiles_x * len(range(ch, tiles_y, nchunks))     # whole rows
        seen += mine
    assert sorted(seen) == list(range(tiles_x * tiles_y))


def test_pixels_beyond_the_contribution_store_are_walked_by_the_render():
    """A haze of faint Gaussians gives each pixel more contributions than the store holds on average
    (STORE_SLOTS_PER_PIXEL): the pixels that did not fit are composited again by the render of the same frame, and
    observe's map and view equal the brute-force reference either way."""
    from css_ros import GaussianModel, SemanticMap
    from css_ros.engine.cpu.raster import STORE_SLOTS_PER_PIXEL
    from css_reference import render_reference, update_reference
    from scenes import random_quats
    rng = np.random.default_rng(21)
    n = 400
    means = rng.uniform([-1.5, -1.2, 2.0], [1.5, 1.2, 5.0], (n, 3))
    model = GaussianModel.from_activated(means, np.exp(rng.uniform(-0.7, -0.2, (n, 3))), random_quats(rng, n),
                                         rng.uniform(0.01, 0.03, n), rng.uniform(0, 1, (n, 3)))
    cam = camera(width=40, height=32, f=30.0)
    kap, bg = reference(model, cam)
    assert (kap > 0).sum(axis=1).mean() > 1.5 * STORE_SLOTS_PER_PIXEL
    labels = rng.integers(0, 4, (cam.height, cam.width))
    smap = SemanticMap(model, 4, prior=1e-3, background=1e-3)
    view = smap.observe(cam, labels)
    counts = smap._backend._store.cnt
    assert (counts >= 0).any() and (counts == -1).any()     # both: replayed pixels and walked ones
    alpha = update_reference(kap, np.full((n, 4), 1e-3), labels, 4)
    np.testing.assert_allclose(smap.concentrations, alpha, rtol=1e-5, atol=1e-9)
    _, _, _, e_hat, v_hat, _, _ = render_reference(kap, bg, alpha, 1e-3)
    np.testing.assert_allclose(view.expectation, e_hat.reshape(cam.height, cam.width), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(view.variance, v_hat.reshape(cam.height, cam.width), rtol=1e-5, atol=1e-12)
