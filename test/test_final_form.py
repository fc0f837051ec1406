"""Final-form outputs (engine/final_form.py, engine/pixel_math.py, the numba backend's finalize pass): the values
a view delivers against independent numpy forms, the ``outputs`` argument, and views that stay valid."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
from numba import njit

from css_ros import SemanticMap
from css_ros.engine.final_form import DEFAULT_OUTPUTS, IMAGE_OUTPUTS, check_outputs, image_uncertainty
from css_ros.engine.pixel_math import confidence_score, interp, to_byte
from css_ros.engine.sensor_model import ConfidenceMap, SensorModel
from css_ros.errors import InputError
from scenes import camera, random_scene

C = 5
CMAP = ConfidenceMap(np.array([1.5, 0.4, -1.0]), np.array([0.0, 0.3, 0.6, 1.0]), np.array([0.05, 0.2, 0.7, 0.99]))


def test_to_byte_is_numpys_rint_and_clip():
    rng = np.random.default_rng(0)
    halves = (np.arange(0, 256) + 0.5) / 255.0                    # exact ties of x * 255 round half to even
    xs = np.concatenate([rng.uniform(-0.2, 1.2, 2000), halves, np.arange(256) / 255.0, [0.0, -0.0, 1.0, 7.0,
                                                                                         np.inf, -np.inf]])
    want = np.clip(np.rint(xs * 255.0), 0, 255).astype(np.uint8)
    assert [to_byte(float(x)) for x in xs] == want.tolist()
    assert to_byte(float("nan")) == 0
    compiled = njit(to_byte)  # the CPU final form's rounding (llvm.rint), the same ties
    assert [compiled(float(x)) for x in xs] == want.tolist()
    assert compiled(float("nan")) == 0


def test_interp_and_confidence_score_are_numpys():
    rng = np.random.default_rng(1)
    xs = np.concatenate([rng.uniform(-0.1, 1.1, 500), CMAP.knots_x])
    got = [interp(float(x), CMAP.knots_x, CMAP.knots_y) for x in xs]
    np.testing.assert_allclose(got, np.interp(xs, CMAP.knots_x, CMAP.knots_y), rtol=0, atol=1e-15)
    e = np.concatenate([rng.uniform(0, 1, 300), [0.0, 1.0, 1e-9]])
    ev = rng.uniform(-1, 100, e.size)
    got = [confidence_score(float(a), float(b), *CMAP.coef) for a, b in zip(e, ev)]
    np.testing.assert_allclose(got, CMAP.score(e, ev), rtol=1e-12, atol=1e-15)


def test_check_outputs():
    assert check_outputs(None) == frozenset(IMAGE_OUTPUTS) - {"surprise"} == frozenset(DEFAULT_OUTPUTS)
    assert check_outputs(["labels", "rgb"]) == {"labels", "rgb"}
    with pytest.raises(InputError, match="unknown output.*colour"):
        check_outputs(["colour"])
    with pytest.raises(InputError, match="not the string"):
        check_outputs("labels")


def _map(backend: str = "numba", with_confidence: bool = True) -> tuple[SemanticMap, object]:
    model = random_scene(7, n=250)
    sensor = SensorModel(tuple(f"c{i}" for i in range(C)), np.array([0.0, 50.0]), np.ones((C, 1)), None,
                         CMAP if with_confidence else None)
    smap = SemanticMap(model, C, backend=backend, unknown_threshold=0.6, background_rgb=(0.1, 0.5, 0.9),
                       sensor_model=sensor, depth_scale=2.5)
    cam = camera(width=40, height=30, f=30.0)
    rng = np.random.default_rng(3)
    for i in range(3):
        smap.observe(camera(width=40, height=30, f=30.0, position=(0.05 * i, 0.0, 0.0)), rng.integers(0, C, (30, 40)))
    return smap, cam


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_final_outputs_against_the_raw_render(backend):
    """Every image against the backend's raw float64 buffers, transformed here with plain numpy."""
    smap, cam = _map(backend)
    view = smap.render(cam, probabilities=True)
    e_b, v_b, s_b = smap._background_moments()
    raw = smap._backend.render(smap._backend.prepare(cam), smap._concentrations, e_b, v_b, s_b,
                               smap.background_rgb, True)
    unknown = raw.background > 0.6
    assert 0 < unknown.sum() < unknown.size                          # the threshold is exercised
    want_labels = np.where(unknown, 255, raw.labels)
    np.testing.assert_array_equal(view.labels, want_labels)
    assert view.labels.dtype == np.int32 and view.rgb.dtype == np.uint8
    for name in ("expectation", "variance", "background", "evidence"):
        got = getattr(view, name)
        assert got.dtype == np.float32
        np.testing.assert_array_equal(got, getattr(raw, name).astype(np.float32), err_msg=name)
    np.testing.assert_array_equal(view.rgb, np.clip(np.rint(raw.rgb * 255), 0, 255).astype(np.uint8))
    np.testing.assert_array_equal(view.depth, (raw.depth * 2.5).astype(np.float32))
    e = np.clip(raw.expectation, 1e-6, 1 - 1e-6)
    z = 1.5 * np.log(e / (1 - e)) + 0.4 * np.log1p(raw.evidence) - 1.0
    conf = np.interp(1 / (1 + np.exp(-z)), CMAP.knots_x, CMAP.knots_y)
    conf[want_labels == 255] = 0.0
    np.testing.assert_allclose(view.confidence, conf, rtol=1e-6, atol=1e-7)
    lv = np.log(np.maximum(raw.variance, 1e-30))
    assert view.u_var == pytest.approx(np.exp(lv.mean()), rel=1e-12)
    assert view.u_exp == pytest.approx(1 - raw.expectation.mean(), rel=1e-12)
    np.testing.assert_array_equal(view.probabilities, raw.probabilities.astype(np.float32))
    assert (view.u_var, view.u_exp) == pytest.approx(image_uncertainty(raw.expectation, raw.variance), rel=1e-12)


def test_only_requested_outputs_are_delivered_and_views_stay_valid():
    smap, cam = _map()
    full = smap.render(cam)
    part = smap.render(cam, outputs=("labels", "depth"))
    np.testing.assert_array_equal(part.labels, full.labels)
    np.testing.assert_array_equal(part.depth, full.depth)
    for name in set(IMAGE_OUTPUTS) - {"labels", "depth"}:
        assert getattr(part, name) is None, name
    assert (part.u_var, part.u_exp) == (full.u_var, full.u_exp)
    kept = full.expectation.copy()
    smap.observe(cam, np.zeros((30, 40), dtype=np.int64))   # a later frame changes the map, not the old view
    np.testing.assert_array_equal(full.expectation, kept)
    assert not np.array_equal(smap.render(cam).expectation, kept)
    with pytest.raises(InputError):
        smap.render(cam, outputs=("labels", "nope"))


def test_no_confidence_map_gives_no_confidence_image():
    smap, cam = _map(with_confidence=False)
    assert smap.render(cam).confidence is None


def test_colorize_is_the_palette_with_black_for_invalid_ids():
    from css_ros.engine.classes import ClassSet

    classes = ClassSet.default(5)
    labels = np.array([[0, 4, 5, -1], [255, 2, 3, 1000]])
    got = classes.colorize(labels, ignore_label=255)
    assert got.dtype == np.uint8 and got.shape == (2, 4, 3)
    for (v, u), lab in np.ndenumerate(labels):
        want = classes.palette[lab] if 0 <= lab < 5 else np.zeros(3)
        np.testing.assert_array_equal(got[v, u], want)
    # an ignore label inside 0..C-1 is black too
    np.testing.assert_array_equal(classes.colorize(np.array([[2]]), ignore_label=2)[0, 0], [0, 0, 0])


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.int16, np.int32, np.int64, np.uint64])
def test_colorize_agrees_with_a_per_pixel_lookup_for_every_integer_dtype(dtype):
    from css_ros.engine.classes import ClassSet

    classes = ClassSet.default(7)
    rng = np.random.default_rng(3)
    info = np.iinfo(dtype)
    values = np.array([0, 1, 6, 7, 9, 200, info.max, info.min], dtype=dtype)
    labels = rng.choice(values, (9, 11)).astype(dtype)[:, ::2]   # a strided view, as a caller may hand over
    got = classes.colorize(labels, ignore_label=6)
    assert got.dtype == np.uint8 and got.shape == labels.shape + (3,)
    for (v, u), lab in np.ndenumerate(labels):
        lab = int(lab)
        want = classes.palette[lab] if 0 <= lab < 7 and lab != 6 else (0, 0, 0)
        np.testing.assert_array_equal(got[v, u], want)


def test_node_image_messages_only_for_the_wanted_topics():
    from css_ros.engine.classes import ClassSet
    from css_ros.io.outputs import frame_output_images

    smap, cam = _map()
    view = smap.render(cam)
    classes = ClassSet.default(C)
    allowed = frame_output_images(view, classes, 255)
    assert list(allowed) == ["semantic", "semantic_color", "expectation", "variance", "rendered_image", "confidence"]
    some = frame_output_images(view, classes, 255, {"semantic_color", "variance"})
    assert list(some) == ["semantic_color", "variance"]
    np.testing.assert_array_equal(some["semantic_color"][0], allowed["semantic_color"][0])
    part = smap.render(cam, outputs=("labels",))
    assert list(frame_output_images(part, classes, 255)) == ["semantic", "semantic_color"]


@pytest.mark.parametrize("e,var,match", [
    (np.full((4, 4), 0.5), np.full((2, 2), 0.01), r"expectation \(4, 4\) and variance \(2, 2\) differ in shape"),
    (None, None, r"expectation must hold real numbers, got dtype object \(it holds text or other objects\)"),
    (np.full((2, 2), 0.5), None, "variance must hold real numbers"),
    (np.zeros((0, 0)), np.zeros((0, 0)), "empty images"),
    (np.full((2, 2), 5.0), np.ones((2, 2)), r"expectation must be in \[0, 1\], got values in \[5, 5\]"),
    (np.full((2, 2), -1e-3), np.ones((2, 2)), r"expectation must be in \[0, 1\]"),
    (np.full((2, 2), 0.5), np.full((2, 2), -0.01), "variance must be >= 0, got a minimum of -0.01"),
    (np.full((2, 2), 0.5 + 2j), np.ones((2, 2)), r"expectation must hold real numbers, got dtype complex128 \(complex values\)"),
    (np.full((2, 2), 0.5), np.full((2, 2), 0.1 + 1j), r"variance must hold real numbers.*\(complex values\)"),
    (np.full((2, 2), np.nan), np.ones((2, 2)), "expectation holds non-finite values"),
    (np.full((2, 2), 0.5), np.full((2, 2), np.inf), "variance holds non-finite values"),
    (np.full((2, 2), "a"), np.ones((2, 2)), "expectation must hold real numbers, got dtype <U1"),
    ([[0.5, 0.5], [0.5]], np.ones((2, 2)), "expectation is not an array of numbers"),
])
def test_image_uncertainty_refuses_bad_images(e, var, match):
    with pytest.raises(InputError, match=match):
        image_uncertainty(e, var)


def test_image_uncertainty_values_and_rounding_tolerance():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        # closed form: U_var = geometric mean of max(Var, 1e-30), U_exp = 1 - mean(E)
        u_var, u_exp = image_uncertainty(np.array([[0.25, 0.75]]), np.array([[0.01, 0.04]]))
        assert u_var == pytest.approx(0.02, rel=1e-12) and u_exp == pytest.approx(0.5, rel=1e-12)
        # within the 1e-6 rounding tolerance: used as given (Var floored at VAR_FLOOR)
        u_var, u_exp = image_uncertainty(np.full((2, 2), 1.0 + 1e-9), np.full((2, 2), -1e-9))
        assert u_var == pytest.approx(1e-30) and u_exp == pytest.approx(-1e-9, rel=1e-6)
        assert image_uncertainty(np.float32([[0.5]]), np.float32([[0.01]])) == pytest.approx((0.01, 0.5), rel=1e-6)


def test_image_uncertainty_refuses_more_values_than_the_largest_image():
    from css_ros.engine.camera import MAX_CAMERA_PIXELS

    huge = np.broadcast_to(np.float32(0.5), (MAX_CAMERA_PIXELS + 1,))   # a view of one value, 537 MB once copied
    with pytest.raises(InputError, match="more than an image of the largest camera"):
        image_uncertainty(huge, huge)
