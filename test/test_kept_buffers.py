"""The numba backend's work arrays kept between frames (engine/cpu/kept_buffers.py): reused, grown when needed, and
never visible in what a view delivers."""
from __future__ import annotations

import numpy as np

from css_ros import SemanticMap
from css_ros.engine.cpu.kept_buffers import RenderPlanes, RowBuffers
from scenes import camera, random_scene


def test_row_buffers_reuse_their_storage_and_grow_by_a_quarter():
    kept = RowBuffers()
    full, short = kept.take(100, 40, 8)
    assert full.shape == (100, 40) and short.shape == (100, 8)
    assert full.flags.c_contiguous and short.flags.c_contiguous and full.dtype == short.dtype == np.float32
    again, again_short = kept.take(80, 40, 8)            # fewer rows: the same storage
    assert np.shares_memory(again, full) and np.shares_memory(again_short, short)
    assert np.shares_memory(kept.take(125, 40, 8)[0], full)  # the quarter's headroom
    bigger, _ = kept.take(126, 40, 8)
    assert not np.shares_memory(bigger, full) and bigger.shape == (126, 40)
    wider, _ = kept.take(60, 200, 8)                       # more columns (classes) than the storage holds
    assert wider.shape == (60, 200) and not np.shares_memory(wider, bigger)


def test_render_planes_are_kept_per_image_size():
    kept = RenderPlanes()
    planes = kept.take(30, 40)
    assert [p.shape for p in planes] == [(30, 40)] * 5 + [(30, 40, 3), (30, 40)]
    assert planes[0].dtype == np.int32 and all(p.dtype == np.float64 for p in planes[1:])
    assert all(a is b for a, b in zip(kept.take(30, 40), planes))
    other = kept.take(15, 20)
    assert other[1].shape == (15, 20) and not np.shares_memory(other[1], planes[1])


def test_observe_renders_into_kept_planes_and_views_keep_their_values():
    model = random_scene(4, n=300)
    smap = SemanticMap(model, 4)
    rng = np.random.default_rng(0)
    big, small = camera(width=40, height=30, f=30.0), camera(width=20, height=15, f=15.0)
    first = smap.observe(big, rng.integers(0, 4, (30, 40)))
    planes = smap._backend._planes.take(30, 40)
    kept = {name: getattr(first, name).copy() for name in ("labels", "expectation", "variance", "rgb")}
    second = smap.observe(big, rng.integers(0, 4, (30, 40)))
    assert all(a is b for a, b in zip(smap._backend._planes.take(30, 40), planes))   # no fresh planes
    for name, values in kept.items():                      # the first view's arrays are its own
        np.testing.assert_array_equal(getattr(first, name), values, err_msg=name)
        assert not np.shares_memory(getattr(second, name), planes[0]) and \
            not any(np.shares_memory(getattr(second, name), p) for p in planes)
    # another size in between, then the first again: each view equals a render with fresh buffers
    query = smap.render(small)
    fresh = smap._backend.render(smap._backend.prepare(small), smap._concentrations, *smap._background_moments(),
                                 smap.background_rgb, False)
    np.testing.assert_array_equal(query.expectation, fresh.expectation.astype(np.float32))
    again = smap.render(big)
    fresh = smap._backend.render(smap._backend.prepare(big), smap._concentrations, *smap._background_moments(),
                                 smap.background_rgb, False)
    np.testing.assert_array_equal(again.variance, fresh.variance.astype(np.float32))
