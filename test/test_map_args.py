"""SemanticMap's constructor, frame inputs, point queries, persistence and merge refuse bad arguments with a CssError
naming the argument (css_ros/engine/map_args.py), and accept exactly what a map file may hold."""
from __future__ import annotations

import os
import warnings
from fractions import Fraction

import numpy as np
import pytest

from css_ros import SemanticMap
from css_ros.engine import map_args
from css_ros.engine.merge import merge_maps
from css_ros.errors import CameraError, InputError, MapError, SensorModelError
from scenes import camera, random_scene

C = 4


@pytest.fixture(scope="module")
def model():
    return random_scene(7, n=60)


@pytest.fixture(scope="module")
def smap(model):
    m = SemanticMap(model, C)
    m.update(camera(), np.random.default_rng(0).integers(0, C, (48, 64)))
    return m


@pytest.mark.parametrize("kwargs, says", [
    ({"prior": 1e300}, r"prior must be in \[1e-12, 1e\+15\], got 1e\+300"), ({"prior": 1e16}, "prior must be in"),
    ({"background": 1e300}, "background must be in"), ({"prior": 0.0}, "prior must be in"),
    ({"prior": "x"}, "prior must be a real number, got str"), ({"prior": float("nan")}, "prior must be finite"),
    ({"unknown_threshold": float("nan")}, "unknown_threshold must be finite"),
    ({"unknown_threshold": -1.0}, r"unknown_threshold must be in \[0, 1\]"),
    ({"unknown_threshold": 1.5}, "unknown_threshold must be in"), ({"unknown_threshold": "a"}, "real number"),
    ({"num_classes": "abc"}, "num_classes must be an integer, got str"), ({"num_classes": None}, "num_classes must be"),
    ({"num_classes": 2.7}, "num_classes must be an integer, got 2.7"), ({"num_classes": True}, "got bool"),
    ({"num_classes": 10**7}, r"num_classes must be in 1\.\.65536"), ({"num_classes": np.int64(2**62)}, "1..65536"),
    ({"num_classes": 0}, "num_classes must be in"),
    ({"ignore_label": 1.5}, "ignore_label must be an integer"), ({"ignore_label": "x"}, "ignore_label must be"),
    ({"ignore_label": 2**40}, "ignore_label must fit int32"),
    ({"depth_scale": "1"}, "depth_scale must be a real number"), ({"depth_scale": -1.0}, "depth_scale must be a pos"),
    ({"background_rgb": (1, 2)}, r"background_rgb must be 3 numbers .* got shape \(2,\)"),
    ({"background_rgb": (float("nan"), 0, 0)}, r"background_rgb must be finite, each channel in \[0, 1\]"),
    ({"background_rgb": (2.0, 0, 0)}, "each channel in"), ({"background_rgb": ("r", "g", "b")}, "real numbers"),
    ({"backend": ["numba"]}, "backend must be a name"),
])
def test_constructor_refuses_each_bad_argument_by_name(model, kwargs, says):
    args = {"num_classes": C, **kwargs}
    with pytest.raises(MapError, match=says):
        SemanticMap(model, **args)


def test_constructor_refuses_what_is_not_a_model():
    with pytest.raises(MapError, match=r"model must be a GaussianModel \(GaussianModel.from_ply\), got NoneType"):
        SemanticMap(None, C)


def test_the_largest_prior_accepted_saves_loads_and_scores_finitely(model, tmp_path):
    """The constructor's bounds are the file's: a map built at the bound round-trips, and its gains stay finite."""
    m = SemanticMap(model, 4.0, prior=map_args.MAX_CONCENTRATION, background=map_args.MAX_CONCENTRATION)
    assert m.num_classes == 4 and isinstance(m.num_classes, int)
    back = SemanticMap.load(m.save(tmp_path / "big.npz"), model)
    assert back.prior == map_args.MAX_CONCENTRATION
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scores = back.score_views([camera()])
    assert np.all(np.isfinite(scores))


def test_unknown_threshold_bounds_keep_their_meaning(model):
    """0 marks every pixel with any background weight unknown, 1 never marks one."""
    never = SemanticMap(model, C, unknown_threshold=1.0).render(camera())
    always = SemanticMap(model, C, unknown_threshold=0.0).render(camera())
    assert not np.any(never.labels == 255)
    assert np.all((always.labels == 255) == (always.background > 0.0))


@pytest.mark.parametrize("call", ["update", "observe", "render"])
@pytest.mark.parametrize("cam", [None, "cam"])
def test_frame_calls_without_a_camera_raise_camera_error(smap, call, cam):
    labels = np.zeros((48, 64), np.int64)
    args = (cam,) if call == "render" else (cam, labels)
    with pytest.raises(CameraError, match=f"{call}: camera must be a Camera"):
        getattr(smap, call)(*args)


@pytest.mark.parametrize("confidence, says", [
    (np.full((48, 64), 0.5 + 2j), "confidence must hold real numbers.*complex"),
    (np.full((48, 64), "a"), "confidence must hold real numbers"),
    (np.ma.masked_array(np.ones((48, 64)), mask=True), "confidence is a masked array"),
])
def test_confidence_of_other_kinds_is_refused(model, confidence, says):
    m = SemanticMap(model, C)
    with pytest.raises(InputError, match=says):
        m.update(camera(), np.zeros((48, 64), np.int64), confidence)
    assert m.frames_observed == 0 and np.all(m.concentrations_readonly == m.prior)


def test_masked_labels_are_refused(model):
    labels = np.ma.masked_array(np.zeros((48, 64), np.int64), mask=True)
    with pytest.raises(InputError, match="labels is a masked array"):
        SemanticMap(model, C).update(camera(), labels)


def test_huge_confidence_counts_as_one_without_a_warning(model):
    labels = np.random.default_rng(1).integers(0, C, (48, 64))
    a, b = SemanticMap(model, C), SemanticMap(model, C)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        a.update(camera(), labels, np.full((48, 64), 1e300))
    b.update(camera(), labels, np.ones((48, 64)))
    np.testing.assert_array_equal(a.concentrations_readonly, b.concentrations_readonly)


@pytest.mark.parametrize("outputs, says", [(5, "outputs must be a collection of names, got int"),
                                           ([["labels"]], "outputs must be names \\(str\\), got a list")])
def test_outputs_of_another_type_are_refused(smap, outputs, says):
    with pytest.raises(InputError, match=says):
        smap.render(camera(), outputs=outputs)


def test_query_points_refuses_complex_huge_and_odd_weights_before_allocating(smap):
    with pytest.raises(InputError, match="real numbers, got dtype complex128"):
        smap.query_points(np.zeros((2, 3), complex))
    huge = np.broadcast_to(np.float64(0.0), (10**9, 3))  # 24 GB if it were materialised
    with pytest.raises(InputError, match="MAX_QUERY_VALUES"):
        smap.query_points(huge)
    with pytest.raises(InputError, match="background_weight must be a real number, got str"):
        smap.query_points(np.zeros((2, 3)), background_weight="a")
    with pytest.raises(MapError, match="min_evidence must be a real number"):
        smap.gaussian_semantics("a")


def test_importance_that_is_complex_or_all_nan_is_refused_without_warnings(smap):
    n = smap.model.num_gaussians
    with pytest.raises(MapError, match="importance must hold real numbers.*complex"):
        smap.score_views([camera()], importance=(1 + 5j) * np.ones(n))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(MapError, match=rf"{n} of {n} values are not, the first importance\[0\] = nan"):
            smap.score_views([camera()], importance=np.full(n, np.nan))


#: (bad array, what every caller's message says after the argument's name): engine/real_array.py is the one converter
BAD_ARRAYS = [
    (np.full(4, 0.5 + 1j), r"must hold real numbers, got dtype complex128 \(complex values\)"),
    (np.array(["1", "0", "0", "1"]), "must hold real numbers, got dtype <U1"),
    (np.array([1.0, "a", 0, 1], dtype=object), r"must hold real numbers, got dtype object \(it holds text or other"),
    (np.array([10**400, 0, 0, 1], dtype=object), "must hold real numbers within float64"),
    ([[1.0, 0.0], [1.0]], "is not an array of numbers"),
    (np.ma.masked_array(np.ones(4), mask=True), "is a masked array"),
]


@pytest.mark.parametrize("value, says", BAD_ARRAYS)
def test_one_real_array_conversion_with_each_callers_error_type(smap, value, says):
    from css_ros.engine.camera import quaternion_xyzw_to_matrix
    from css_ros.engine.final_form import image_uncertainty

    with pytest.raises(CameraError, match="quaternion " + says):
        quaternion_xyzw_to_matrix(value)
    with pytest.raises(InputError, match="image_uncertainty: expectation " + says):
        image_uncertainty(value, np.ones(4))
    with pytest.raises(MapError, match="background_rgb " + says):
        SemanticMap(smap.model, C, background_rgb=value)


def test_real_arrays_of_numbers_convert_and_a_camera_keeps_its_own_copy():
    from css_ros import Camera

    q = np.array([0, 0, 0, 1], dtype=object)   # an object array of numbers is numbers
    assert map_args.check_real_array(q, "q").dtype == np.float64
    K = np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])
    cam = Camera(K, 64, 48, np.eye(4))
    K[0, 0] = 99.0
    assert cam.fx == 50.0 and K.flags.writeable   # the camera copied K: the caller's array is not frozen or shared
    f = np.ones(3)
    assert map_args.check_real_array(f, "f") is f   # a float64 array is not copied unless asked


def test_merge_checks_every_map_and_wants_one_name_each(model):
    a = SemanticMap(model, C)
    other_prior = SemanticMap(model, C, prior=0.5)
    with pytest.raises(MapError, match="1 names for 2 maps"):
        merge_maps([a, other_prior], names=["a"])  # zip() once left the second map unchecked
    with pytest.raises(MapError, match="map a has prior"):
        merge_maps([a, other_prior], names=["map a", "map b"])
    with pytest.raises(MapError, match="names must be a sequence of str"):
        merge_maps([a, a], names=5)
    with pytest.raises(MapError, match=r"maps\[1\] is a str, not a SemanticMap"):
        merge_maps([a, "b"])


def test_merge_refuses_a_sum_no_map_file_may_hold(model):
    a, b = SemanticMap(model, C), SemanticMap(model, C)
    a.concentrations[0, 0] = b.concentrations[0, 0] = 0.75 * map_args.MAX_CONCENTRATION
    with pytest.raises(MapError, match="above 1e\\+15"):
        merge_maps([a, b])


def test_load_refuses_devices_fifos_folders_and_odd_arguments(model, smap, tmp_path):
    with pytest.raises(MapError, match="/dev/zero is not a regular file"):
        SemanticMap.load("/dev/zero", model)  # was read to its end: MemoryError
    fifo = tmp_path / "map.fifo"
    os.mkfifo(fifo)
    with pytest.raises(MapError, match="is not a regular file"):
        SemanticMap.load(fifo, model)  # opening it would block for ever
    with pytest.raises(MapError, match="is not a regular file"):
        SemanticMap.load(tmp_path, model)
    path = smap.save(tmp_path / "map.npz")
    with pytest.raises(MapError, match="expected_classes must be an integer, got str"):
        SemanticMap.load(path, model, expected_classes="4")
    with pytest.raises(MapError, match="load takes prior from the map file"):
        SemanticMap.load(path, model, prior=5)
    with pytest.raises(MapError, match="model must be a GaussianModel"):
        SemanticMap.load(path, None)
    assert SemanticMap.load(path, model, expected_classes=4.0).num_classes == C


def test_save_refuses_bad_paths_with_map_error_and_writes_nothing(smap, tmp_path):
    with pytest.raises(MapError, match="it is a directory"):
        smap.save(tmp_path)
    with pytest.raises(MapError, match="must be a str or os.PathLike, got NoneType"):
        smap.save(None)
    with pytest.raises(MapError, match="NUL"):
        smap.save(str(tmp_path / "a\0b.npz"))
    with pytest.raises(MapError, match="File name too long"):
        smap.save(tmp_path / ("m" * 300 + ".npz"))
    assert list(tmp_path.iterdir()) == []


def test_zero_d_arrays_count_as_the_numbers_they_hold(model, tmp_path):
    """What np.load(...)["prior"] gives: a 0-d array is a scalar argument, as it was before the checks."""
    smap = SemanticMap(model, np.array(4), prior=np.array(2e-3), ignore_label=np.array(255),
                       unknown_threshold=np.array(0.5), depth_scale=np.array(1.0))
    assert (smap.num_classes, smap.prior, smap.ignore_label) == (4, 2e-3, 255)
    with np.load(smap.save(tmp_path / "m.npz")) as data:
        again = SemanticMap(model, data["num_classes"], prior=data["prior"], background=data["background"])
    assert (again.num_classes, again.prior) == (4, 2e-3)
    assert smap.gaussian_semantics(np.array(0.5)).label.shape == (model.num_gaussians,)
    assert smap.select_views([camera()], np.array(1)).indices == [0]
    with pytest.raises(MapError, match="num_classes must be an integer"):
        SemanticMap(model, np.array([4]))


@pytest.mark.parametrize("prior", [1e-310, 5e-324, 1e-13])
def test_subnormal_and_tiny_priors_are_refused(model, prior):
    """A prior of 1e-310 made the numba render's expectation +inf (and U_exp -inf) with no warning."""
    with pytest.raises(MapError, match=r"prior must be in \[1e-12, 1e\+15\]"):
        SemanticMap(model, C, prior=prior)


def test_the_smallest_prior_renders_finite_moments(model):
    smap = SemanticMap(model, C, prior=map_args.MIN_CONCENTRATION, background=map_args.MIN_CONCENTRATION)
    smap.update(camera(), np.random.default_rng(2).integers(0, C, (48, 64)))
    view = smap.render(camera())
    assert np.all(np.isfinite(view.expectation)) and np.all((view.expectation >= 0) & (view.expectation <= 1))
    assert np.isfinite(view.u_var) and np.isfinite(view.u_exp)


@pytest.mark.parametrize("name, call", [
    ("prior", lambda m, c: SemanticMap(m, C, prior=10**400)),
    ("prior", lambda m, c: SemanticMap(m, C, prior=Fraction(10**400, 3))),
    ("depth_scale", lambda m, c: SemanticMap(m, C, depth_scale=-(10**400))),
    ("pixel_scale", lambda m, c: SemanticMap(m, C).score_views([c], pixel_scale=10**400)),
    ("background_weight", lambda m, c: SemanticMap(m, C).query_points(np.zeros((1, 3)), 10**400)),
    ("k", lambda m, c: SemanticMap(m, C).select_views([c], Fraction(10**400, 1))),
])
def test_numbers_beyond_float64_are_refused_by_name(model, name, call):
    with pytest.raises((MapError, InputError), match=name):
        call(model, camera())


def test_sensor_model_and_device_of_the_wrong_kind_are_refused(model, tmp_path):
    with pytest.raises(SensorModelError, match="sensor_model must be a SensorModel"):
        SemanticMap(model, C, sensor_model=str(tmp_path / "sm.yaml"))
    with pytest.raises(MapError, match="device must be None or, with backend 'cuda', a GPU index"):
        SemanticMap(model, C, device="cpu")


def test_merge_keeps_depth_scale_and_background_colour_and_refuses_other_depth_scales(model):
    labels = np.random.default_rng(3).integers(0, C, (48, 64))
    a = SemanticMap(model, C, depth_scale=0.5, background_rgb=(1.0, 1.0, 1.0))
    b = SemanticMap(model, C, depth_scale=0.5, background_rgb=(1.0, 1.0, 1.0))
    a.update(camera(), labels)
    b.update(camera(position=(0.2, 0.0, 0.0)), labels)
    merged = merge_maps([a, b])
    want, got = a.render(camera()), merged.render(camera())
    np.testing.assert_array_equal(got.depth, want.depth)   # depth in metres: the same geometry, the same scale
    np.testing.assert_array_equal(got.rgb, want.rgb)       # the white background stays white
    with pytest.raises(MapError, match="depth_scale 0.5 m per splat unit, map 2 1"):
        merge_maps([a, SemanticMap(model, C)])


def test_merge_messages_show_long_or_multi_line_names_shortened(model):
    a, b = SemanticMap(model, C), SemanticMap(model, C, prior=0.5)
    with pytest.raises(MapError) as err:
        merge_maps([a, b], names=["a", "b" * 10**6])
    assert len(str(err.value)) < 300
    with pytest.raises(MapError) as err:
        merge_maps([a, b], names=["a", "line\nbreak"])
    assert "\n" not in str(err.value)


class _BytesPath:
    def __fspath__(self):
        return b"/tmp/map.npz"


def test_odd_map_paths_are_refused_in_one_line(smap, tmp_path):
    with pytest.raises(MapError, match="names a folder, give a file name"):
        smap.save(str(tmp_path / "newdir") + os.sep)
    assert not (tmp_path / "newdir").exists()
    with pytest.raises(MapError, match="_BytesPath gives no str path"):
        smap.save(_BytesPath())
    with pytest.raises(MapError) as err:
        SemanticMap.load(tmp_path / "a\nb.npz", smap.model)
    assert "does not exist" in str(err.value) and "\n" not in str(err.value)
