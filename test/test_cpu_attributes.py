"""The numba backend's per-Gaussian passes against closed forms: the increments of each thread (Gaussian-major,
(chunks, M, C)) added into the concentrations, and the render's attribute rows (SPEC §4 moments) with every column
written."""
from __future__ import annotations

import numpy as np
import pytest

from css_ros.engine.cpu.increments import Increments, add_increments
from css_ros.engine.cpu.raster import SHORT_COLS, _dirichlet_kernel, add_increments_and_attributes, linear_width


def _inputs(num_classes: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    n, m = 50, 30
    conc = 1.0 + rng.gamma(0.5, 4.0, size=(n, num_classes))
    ids = rng.permutation(n)[:m].astype(np.int64)
    colors = rng.random((m, 3))
    packed = rng.random((m, 8)) * 5.0
    return rng, conc, ids, colors, packed


def _expected_rows(conc_rows: np.ndarray, colors: np.ndarray, packed: np.ndarray) -> np.ndarray:
    """(M, linear_width + C) float64: E, rgb, S, z, zero padding, Var = E (1 - E) / (1 + S)."""
    m, c = conc_rows.shape
    lin = linear_width(c)
    s = conc_rows.sum(axis=1)
    e = conc_rows / s[:, None]
    out = np.zeros((m, lin + c))
    out[:, :c] = e
    out[:, c:c + 3] = colors
    out[:, c + 3] = s
    out[:, c + 4] = packed[:, 7]
    out[:, lin:] = e * (1.0 - e) / (1.0 + s[:, None])
    return out


def _expected_short(conc_rows: np.ndarray, colors: np.ndarray, packed: np.ndarray) -> np.ndarray:
    """(M, SHORT_COLS) float64: E and Var of the most likely class g, rgb, S, z, g."""
    m, c = conc_rows.shape
    full = _expected_rows(conc_rows, colors, packed)
    g = conc_rows.argmax(axis=1)
    r = np.arange(m)
    return np.column_stack([full[r, g], full[r, linear_width(c) + g], full[:, c:c + 5], g])


@pytest.mark.parametrize("num_classes", [3, 20, 28])
def test_attribute_rows_write_every_column(num_classes):
    _, conc, ids, colors, packed = _inputs(num_classes)
    lin = linear_width(num_classes)
    conc[ids[0], :2] = conc[ids[0]].max() + 1.0   # equal maxima: the first is the most likely class
    attrs = np.full((ids.shape[0], lin + num_classes), np.nan, dtype=np.float32)
    short = np.full((ids.shape[0], SHORT_COLS), np.nan, dtype=np.float32)
    _dirichlet_kernel(conc, ids, colors, packed, attrs, short)
    assert np.all(np.isfinite(attrs)) and np.all(np.isfinite(short))
    np.testing.assert_allclose(attrs, _expected_rows(conc[ids], colors, packed), rtol=1e-6, atol=1e-7)
    assert np.all(attrs[:, num_classes + 5:lin] == 0.0)
    np.testing.assert_allclose(short, _expected_short(conc[ids], colors, packed), rtol=1e-6, atol=1e-7)
    assert short[0, 7] == 0.0


@pytest.mark.parametrize("with_base", [False, True])
@pytest.mark.parametrize("decay", [1.0, 0.5])
def test_increments_are_summed_over_threads_then_added(with_base, decay):
    num_classes, prior = 7, 1.0
    rng, conc, ids, colors, packed = _inputs(num_classes, seed=3)
    m = ids.shape[0]
    acc = rng.random((2, m, num_classes))
    acc[:, :5] = 0.0                       # five Gaussians get nothing in this frame
    base = rng.random((2, m)) if with_base else np.zeros((0, 0))
    if with_base:
        base[:, :5] = 0.0
    want = conc.copy()
    inc = acc.sum(axis=0) + (base.sum(axis=0)[:, None] if with_base else 0.0)
    received = np.any(inc != 0.0, axis=1)
    rows = want[ids]
    rows[received] = prior + (rows[received] - prior) * decay
    want[ids] = rows + inc

    got = conc.copy()
    inc = Increments.dense(acc, base)
    attrs = add_increments_and_attributes(got, ids, inc, decay, prior, colors, packed)
    np.testing.assert_allclose(got, want, rtol=1e-12)
    assert not acc.any() and not base.any() and not inc.marks.any()     # left zero for the next frame
    np.testing.assert_allclose(attrs.full, _expected_rows(want[ids], colors, packed), rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(attrs.short, _expected_short(want[ids], colors, packed), rtol=1e-6, atol=1e-7)

    # add_increments alone: the same concentrations
    acc2 = rng.random((2, m, num_classes))
    plain = conc.copy()
    want2 = conc.copy()
    want2[ids] += acc2.sum(axis=0)
    add_increments(plain, ids, Increments.dense(acc2, np.zeros((0, 0))))
    np.testing.assert_allclose(plain, want2, rtol=1e-12)
    assert not acc2.any()


def test_kept_rows_are_reused_grown_with_headroom_and_remade_for_another_class_count():
    from css_ros.engine.cpu.kept import HEADROOM, Kept
    from css_ros.engine.cpu.raster import new_attribute_rows
    kept = Kept(new_attribute_rows)
    full, short = kept.take(100, 5)
    assert full.shape == (100, linear_width(5) + 5) and short.shape == (100, SHORT_COLS)
    again, _ = kept.take(int(100 * (1 + HEADROOM)), 5)          # within the headroom: the same memory
    assert np.shares_memory(full, again) and again.shape[0] == 125
    grown, _ = kept.take(200, 5)
    assert not np.shares_memory(full, grown) and grown.flags.c_contiguous
    other, _ = kept.take(50, 9)                                  # another class count: new rows
    assert other.shape == (50, linear_width(9) + 9)


def test_views_rendered_one_after_another_into_kept_rows_equal_fresh_renders():
    """observe, then query views at other poses (the backend's kept attribute rows rewritten each time): every
    view equals the one a fresh map with the same concentrations renders."""
    from css_ros import SemanticMap
    from scenes import camera, random_scene
    model = random_scene(11, n=600)
    labels = np.random.default_rng(1).integers(0, 4, (48, 64))
    smap = SemanticMap(model, 4)
    smap.observe(camera(width=64, height=48, f=40.0), labels)
    for f in (30.0, 55.0, 40.0):       # fewer, more, then as many visible Gaussians as the first view
        cam = camera(width=64, height=48, f=f)
        got = smap.render(cam)
        fresh = SemanticMap(model, 4)
        fresh.concentrations[:] = smap.concentrations
        want = fresh.render(cam)
        np.testing.assert_array_equal(got.labels, want.labels)
        np.testing.assert_array_equal(got.expectation, want.expectation)
        np.testing.assert_array_equal(got.variance, want.variance)
