"""The view-scoring API refuses bad arguments with a CssError naming the argument (css_ros/engine/view_args.py):
score_views, select_views, task_importance, class_importance."""
from __future__ import annotations

import numpy as np
import pytest

from css_ros import SemanticMap
from css_ros.engine import view_args
from css_ros.errors import CameraError, CssError, MapError
from scenes import camera, random_scene

C = 4


@pytest.fixture(scope="module")
def smap():
    m = SemanticMap(random_scene(4, n=80), C)
    m.update(camera(), np.random.default_rng(0).integers(0, C, (48, 64)))
    return m


@pytest.fixture(scope="module")
def cams():
    return [camera(), camera(position=(0.3, 0.1, -0.2)), camera(position=(-0.4, 0.0, 0.3))]


@pytest.mark.parametrize("k, says", [(-2, "k must be >= 1"), (0, "k must be >= 1"),
                                     (float("nan"), "k must be an integer"), (2.5, "k must be an integer"),
                                     ("3", "k must be an integer, got str"), (None, "k must be an integer"),
                                     (True, "k must be an integer, got bool")])
def test_select_views_refuses_a_bad_k(smap, cams, k, says):
    with pytest.raises(MapError, match=says):
        smap.select_views(cams, k)


def test_integral_k_of_any_type_selects_the_same_views(smap, cams):
    want = smap.select_views(cams, 2)
    for k in (np.int64(2), 2.0, np.float32(2.0)):
        got = smap.select_views(cams, k)
        np.testing.assert_array_equal(got.indices, want.indices)
        np.testing.assert_array_equal(got.gains, want.gains)


@pytest.mark.parametrize("importance, says", [
    ("1e308", "importance must be finite and in \\[0, 1e\\+15\\]"),
    ("nan", "importance must be finite"), ("-1", "importance must be finite"),
    ("short", "importance must have shape \\(80,\\)"), ("text", "importance must hold real numbers"),
])
def test_importance_out_of_bounds_is_refused_where_it_gave_inf_or_nan_gains(smap, cams, importance, says):
    """1e308 on one Gaussian turned finite inputs into inf / NaN gains; now every entry point refuses it by name."""
    n = smap.model.num_gaussians
    imp = {"1e308": np.r_[1e308, np.ones(n - 1)], "nan": np.r_[np.nan, np.ones(n - 1)],
           "-1": np.r_[-1.0, np.ones(n - 1)], "short": np.ones(n - 1), "text": ["a"] * n}[importance]
    with pytest.raises(MapError, match=says):
        smap.score_views(cams, importance=imp)
    with pytest.raises(MapError, match=says):
        smap.select_views(cams, 2, importance=imp)
    ok = np.full(n, view_args.MAX_IMPORTANCE)
    assert np.all(np.isfinite(smap.score_views(cams, importance=ok)))
    assert np.all(np.isfinite(smap.select_views(cams, 3, importance=ok).gains))


@pytest.mark.parametrize("scale, says", [(1e300, "pixel_scale must be finite and in \\(0, 1e\\+06\\]"),
                                         (0.0, "pixel_scale must be finite"), (float("inf"), "pixel_scale must be"),
                                         ("1", "pixel_scale must be a real number, got str"),
                                         (None, "pixel_scale must be a real number")])
def test_pixel_scale_out_of_bounds_is_refused(smap, cams, scale, says):
    with pytest.raises(MapError, match=says):
        smap.score_views(cams, pixel_scale=scale)
    with pytest.raises(MapError, match=says):
        smap.select_views(cams, 1, pixel_scale=scale)
    assert np.all(np.isfinite(smap.score_views(cams, pixel_scale=view_args.MAX_PIXEL_SCALE)))


@pytest.mark.parametrize("bad, says", [
    (None, "cameras must be a sequence of Camera, got NoneType"),
    ("cam", "cameras must be a sequence of Camera, got str"),
    ("one camera", "cameras must be a sequence of Camera, got Camera"),
    ("poses", "cameras\\[1\\] is a ndarray, not a Camera"),
])
def test_wrong_camera_types_are_refused_by_name(smap, cams, bad, says):
    arg = {"one camera": cams[0], "poses": [cams[0], np.zeros(7)]}.get(bad, bad)
    for call, name in ((lambda a: smap.score_views(a), "score_views"), (lambda a: smap.select_views(a, 1), "select_views"),
                       (lambda a: smap.task_importance(a), "task_importance")):
        expect = says.replace("cameras", "task_cameras") if name == "task_importance" else says
        with pytest.raises(CameraError, match=f"{name}: {expect}"):
            call(arg)


@pytest.mark.parametrize("class_id, says", [(C, "class_id 4 outside 0..3"), (-1, "class_id -1 outside"),
                                            (float("nan"), "class_id must be an integer"),
                                            ("1", "class_id must be an integer, got str")])
def test_class_importance_refuses_a_bad_class_id(smap, class_id, says):
    with pytest.raises(MapError, match=says):
        smap.class_importance(class_id)


def test_select_views_takes_at_most_the_documented_number_of_candidates(smap, cams):
    """More than MAX_SELECT_CANDIDATES cameras are refused before any is rendered (the greedy batch keeps every
    candidate's evidence, memory linear in the candidates); exactly that many are accepted."""
    many = [cams[0]] * (view_args.MAX_SELECT_CANDIDATES + 1)
    with pytest.raises(CameraError, match=f"more than {view_args.MAX_SELECT_CANDIDATES} cameras"):
        smap.select_views(many, 2)
    small = camera(width=8, height=6, f=6.0)
    got = smap.select_views([small] * view_args.MAX_SELECT_CANDIDATES, 2)
    assert len(got.indices) == 2
    assert issubclass(CameraError, CssError)
