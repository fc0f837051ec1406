"""The numba render's short shading path (``raster._shade_majority``): a pixel whose contributions all have the same
most likely class g holding more than half of its expectation mass is shaded from 32-byte rows. Checked against
closed forms on hand-made pixels, and end to end against the full path (which a render asking for the class
probabilities always takes) on a mapped random scene."""
from __future__ import annotations

import numpy as np
import pytest
from numba import njit

from css_ros import SemanticMap
from css_ros.engine.cpu.raster import MAJORITY_MARGIN, SHORT_COLS, SHORT_MIN_COLUMNS, _shade_majority, linear_width
from scenes import camera, random_scene

E_BG, V_BG, S_BG = 0.25, 0.01, 0.004
BG_RGB = np.array([0.1, 0.2, 0.3])


@njit
def _one_pixel(ks, vs, tr, short, tile_list):  # pragma: no cover
    """(how, label, E, Var, evidence, r, g, b, depth) of one pixel through the short path (NaN where not written)."""
    lab = np.full((1, 1), -1, dtype=np.int32)
    exp = np.full((1, 1), np.nan)
    var = np.full((1, 1), np.nan)
    bg = np.full((1, 1), np.nan)
    ev = np.full((1, 1), np.nan)
    rgb = np.full((1, 1, 3), np.nan)
    depth = np.full((1, 1), np.nan)
    acc = np.empty(SHORT_COLS, dtype=np.float32)
    how = _shade_majority(0, 0, ks, vs, ks.shape[0], tr, short, tile_list, acc, E_BG, V_BG, S_BG, BG_RGB, lab, exp,
                          var, bg, ev, rgb, depth)
    return how, lab[0, 0], exp[0, 0], var[0, 0], ev[0, 0], rgb[0, 0, 0], rgb[0, 0, 1], rgb[0, 0, 2], depth[0, 0]


def _pixel(alphas: np.ndarray, e_top: np.ndarray, top: np.ndarray, seed: int = 0):
    """Contributions kappa_i = alpha_i T_i front to back (so sum kappa = 1 - T), short rows of their Gaussians
    reached through a shuffled tile list."""
    rng = np.random.default_rng(seed)
    n = alphas.shape[0]
    t = np.concatenate([[1.0], np.cumprod(1.0 - alphas)])
    kappa = alphas * t[:-1]
    short = np.zeros((n + 3, SHORT_COLS), dtype=np.float32)
    tile_list = rng.permutation(n + 3).astype(np.int32)
    ks = np.arange(n, dtype=np.uint16)
    rows = tile_list[:n]
    short[rows, 0] = e_top
    short[rows, 1] = rng.uniform(0.001, 0.05, n)
    short[rows, 2:5] = rng.uniform(0, 1, (n, 3))
    short[rows, 5] = rng.uniform(1, 50, n)
    short[rows, 6] = rng.uniform(0.5, 8, n)
    short[rows, 7] = top
    return ks, kappa.astype(np.float32), float(t[-1]), short, tile_list, short[rows].astype(np.float64)


def test_a_majority_pixel_is_shaded_from_its_short_rows():
    alphas = np.array([0.3, 0.5, 0.2, 0.6, 0.4, 0.35])   # six contributions: a group of four and a remainder of two
    ks, kappa, tr, short, tiles, rows = _pixel(alphas, np.full(6, 0.8), np.full(6, 3))
    k = kappa.astype(np.float64)
    how, lab, e, var, ev, r, g, b, depth = _one_pixel(ks, kappa, tr, short, tiles)
    assert how == 1 and lab == 3
    assert e == pytest.approx(k @ rows[:, 0] + tr * E_BG, rel=1e-6)
    assert var == pytest.approx(tr * tr * V_BG + (k * k) @ rows[:, 1], rel=1e-6)
    assert (r, g, b) == pytest.approx(tuple(k @ rows[:, 2:5] + tr * BG_RGB), rel=1e-6)
    assert ev == pytest.approx(k @ rows[:, 5] + tr * S_BG, rel=1e-6)
    assert depth == pytest.approx((k @ rows[:, 6]) / (1.0 - tr), rel=1e-6)


def test_the_short_path_refuses_what_it_cannot_decide():
    alphas = np.array([0.3, 0.5, 0.2, 0.6, 0.4])
    # another most likely class behind the front: nothing written, the full path decides
    top = np.array([1, 1, 1, 1, 2])
    ks, kappa, tr, short, tiles, _ = _pixel(alphas, np.full(5, 0.9), top)
    out = _one_pixel(ks, kappa, tr, short, tiles)
    assert out[0] == 2 and out[1] == -1 and np.isnan(out[2])
    # the class holds exactly half of the mass (E = 1/2 everywhere): not more than half by the margin
    ks, kappa, tr, short, tiles, _ = _pixel(alphas, np.full(5, 0.5), np.full(5, 1))
    short[tiles[:5][0], 0] = 0.5 + 1e-6                # tried (front above one half), the sum is not enough
    assert _one_pixel(ks, kappa, tr, short, tiles)[0] == 2
    # a share just above the margin passes
    e = 0.5 * (1.0 + 2.0 * MAJORITY_MARGIN)
    ks, kappa, tr, short, tiles, _ = _pixel(alphas, np.full(5, e), np.full(5, 1))
    assert _one_pixel(ks, kappa, tr, short, tiles)[:2] == (1, 1)
    # not tried: the front Gaussian's class has at most one half, or the pixel has no contribution
    ks, kappa, tr, short, tiles, _ = _pixel(alphas, np.array([0.5, 0.99, 0.99, 0.99, 0.99]), np.full(5, 1))
    assert _one_pixel(ks, kappa, tr, short, tiles)[0] == 0
    assert _one_pixel(ks[:0], kappa[:0], 1.0, short, tiles)[0] == 0


@pytest.mark.parametrize("num_classes", [28, 40])
def test_renders_equal_the_full_path_where_the_short_one_applies(num_classes):
    """A mapped scene rendered twice: asking for the probabilities takes the full path for every pixel; without
    them the short path shades the pixels it applies to (a tenth of the covered ones at least, so the
    comparison is not vacuous). Labels are equal; the values agree to float32 rounding."""
    assert linear_width(num_classes) >= SHORT_MIN_COLUMNS   # the short path is tried for this many classes
    rng = np.random.default_rng(4)
    model = random_scene(7, n=400, log_scale=(-3.0, -1.0))
    smap = SemanticMap(model, num_classes)
    cams = [camera(96, 72, 70.0, position=(x, 0.0, 0.0)) for x in (-0.2, 0.0, 0.2)]
    truth = rng.integers(0, num_classes, 400)
    for cam in cams * 2:   # labels of the Gaussian nearest each pixel's ray: coherent, as a segmentation is
        view = smap.render(cam, outputs={"depth"})
        labels = np.full((cam.height, cam.width), 255, dtype=np.uint8)
        u, v = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
        x = (u - cam.cx) / cam.fx * view.depth + cam.position[0]
        y = (v - cam.cy) / cam.fy * view.depth + cam.position[1]
        ok = np.isfinite(view.depth)
        pts = np.stack([x[ok], y[ok], view.depth[ok]], axis=1)
        near = np.argmin(((pts[:, None, :] - np.asarray(model.means)[None]) ** 2).sum(axis=2), axis=1)
        labels[ok] = truth[near]
        smap.update(cam, labels)
    cam = cams[1]
    short = smap.render(cam)
    full = smap.render(cam, probabilities=True)
    covered = full.background < 0.5
    e_bg = 1.0 / num_classes
    share = (full.expectation - full.background * e_bg) > 0.5 * (1.0 - full.background) * (1.0 + 2 * MAJORITY_MARGIN)
    assert covered.mean() > 0.5 and (share & covered).sum() > 0.1 * covered.sum()
    np.testing.assert_array_equal(short.labels, full.labels)
    for name in ("expectation", "variance", "evidence", "background", "depth"):
        np.testing.assert_allclose(getattr(short, name), getattr(full, name), rtol=2e-6, atol=1e-7, equal_nan=True,
                                   err_msg=name)
    assert np.abs(short.rgb.astype(int) - full.rgb.astype(int)).max() <= 1   # bytes: rounding at a boundary
