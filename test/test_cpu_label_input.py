"""The numba update takes uint8 / uint16 / int32 / int64 labels and float32 / float64 confidence as they come (no copy,
no conversion) and applies the label rule inside its compiled pass: its pixel counts and concentrations equal a brute
force built with the numpy twin of the rule (label_input.count_votes) and the float64 kappa reference."""
from __future__ import annotations

import numpy as np
import pytest

from css_ros import SemanticMap
from css_ros.engine.cpu.backend import NumbaBackend
from css_ros.engine.label_input import count_votes
from css_reference import kappa_reference, update_reference
from scenes import camera, random_scene

C = 5
IGNORE = 255


def frame_inputs(dtype, conf_dtype, shape, rng):
    """Labels of ``dtype`` with every kind of pixel: valid classes, the ignore value, ids >= C (and negative ones for
    signed dtypes); confidence of ``conf_dtype`` (or None) with NaN, +-inf, values above 1, zero, negative and a
    float64 value that is 0 in float32."""
    info = np.iinfo(dtype)
    labels = rng.integers(0, C, shape).astype(dtype)
    flat = labels.reshape(-1)
    specials = [IGNORE, C, C + 7, info.max] + ([-1, -3, info.min] if info.min < 0 else [])
    for k, value in enumerate(specials):
        flat[k * 7::53] = value
    if conf_dtype is None:
        return labels, None
    conf = rng.uniform(0.0, 1.0, shape).astype(conf_dtype)
    cf = conf.reshape(-1)
    for k, value in enumerate([np.nan, np.inf, -np.inf, 1.7, 0.0, -0.3, 1e-50]):
        cf[3 + k * 5::47] = value
    return labels, conf


# every label dtype, and each confidence dtype once (each pair is one compiled specialisation of the update kernel)
CASES = [(np.uint8, None), (np.uint16, None), (np.int32, None), (np.int64, None), (np.uint8, np.float32),
         (np.int64, np.float64)]


@pytest.mark.parametrize(("dtype", "conf_dtype"), CASES)
def test_update_reads_labels_and_confidence_as_given(dtype, conf_dtype, monkeypatch):
    rng = np.random.default_rng(3)
    model = random_scene(5)
    cam = camera()
    seen = []
    update = NumbaBackend.update

    def spy(self, frame, inputs, concentrations, soft=None):
        seen.append(inputs)
        return update(self, frame, inputs, concentrations, soft)

    monkeypatch.setattr(NumbaBackend, "update", spy)
    smap = SemanticMap(model, C, prior=1e-3, ignore_label=IGNORE)
    alpha = np.full((model.num_gaussians, C), 1e-3)
    for pose in (dict(), dict(position=(0.2, 0.1, -0.2), quat=(0.02, 0.05, 0.0, 0.998))):
        cam = camera(**pose)
        labels, conf = frame_inputs(dtype, conf_dtype, (cam.height, cam.width), rng)
        stats = smap.update(cam, labels, conf)
        # the backend got the caller's arrays themselves
        assert seen[-1].labels is labels
        assert (seen[-1].confidence is None) if conf is None else (seen[-1].confidence is conf)
        classes, weights, counts = count_votes(labels, conf, C, IGNORE)
        assert (stats.used, stats.ignored, stats.out_of_range) == tuple(int(c) for c in counts)
        assert min(counts) > 0  # every kind of pixel is there
        kap, _ = kappa_reference(model.means, model.scales, model.quats_wxyz, model.opacities,
                                 cam.K, cam.T_map_cam, cam.width, cam.height)
        alpha = update_reference(kap, alpha, classes, C, ignore_label=-1, confidence=weights)
        np.testing.assert_allclose(smap.concentrations, alpha, rtol=1e-5, atol=1e-9)
