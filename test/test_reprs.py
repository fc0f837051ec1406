"""print(model), print(map), print(sensor_model): one line each that names the sizes, never the arrays."""
from __future__ import annotations

import numpy as np

from css_ros import GaussianModel, SemanticMap
from css_ros.engine.sensor_model import SensorModel


def _model(n: int) -> GaussianModel:
    means = np.zeros((n, 3))
    means[:, 0] = np.linspace(-1.5, 2.5, n)
    means[:, 2] = 5.0
    return GaussianModel(means=means, log_scales=np.full((n, 3), -2.0), rotations=np.tile([1.0, 0, 0, 0], (n, 1)),
                         opacity_logits=np.zeros(n), sh=np.zeros((n, 4, 3), np.float32))


def _one_line(text: str) -> None:
    assert "\n" not in text and len(text) < 200, text
    assert "array" not in text and "..." not in text, text


def test_gaussian_model_repr_names_size_degree_and_box():
    r = repr(_model(1000))
    _one_line(r)
    assert r.startswith("GaussianModel(1000 Gaussians, SH degree 1,")
    assert "[-1.5, 2.5] x [0, 0] x [5, 5] m" in r
    assert str(_model(3)) == repr(_model(3))


def test_semantic_map_repr_names_classes_frames_and_update():
    m = _model(50)
    smap = SemanticMap(m, num_classes=7)
    r = repr(smap)
    _one_line(r)
    assert "50 Gaussians x 7 classes" in r and "backend numba" in r and "0 frames observed" in r
    assert "paper update" in r
    sm = SensorModel(tuple("abcdefg"), np.array([0.0, 1.0, 2.0, 4.0]), np.full((7, 3), 0.5))
    r2 = repr(SemanticMap(m, num_classes=7, sensor_model=sm))
    assert f"sensor model {sm.fingerprint[:12]}" in r2


def test_sensor_model_repr_names_bins_and_fingerprint():
    sm = SensorModel(("a", "b"), np.array([0.0, 0.5, 1.0, 8.0]), np.full((2, 3), 0.25))
    r = repr(sm)
    _one_line(r)
    assert r == (f"SensorModel(2 classes, 3 depth bins 0-8 m, one-hot votes, no confidence map, "
                 f"fingerprint {sm.fingerprint[:12]})")
