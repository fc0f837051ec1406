"""Sensor model: the update against a brute-force reference, the depth image, the paper's update bit for bit,
file checks, map files and merges."""
from __future__ import annotations

import numpy as np
import pytest

from css_ros import MapError, SemanticMap
from css_ros.engine.merge import merge_maps
from css_ros.engine.sensor_model import ConfidenceMap, SensorModel
from css_ros.errors import SensorModelError
from css_reference import kappa_reference, update_reference
from scenes import camera, random_scene

C = 5
NAMES = tuple(f"c{i}" for i in range(C))


def ref_kappa(model, cam):
    return kappa_reference(model.means, model.scales, model.quats_wxyz, model.opacities,
                           cam.K, cam.T_map_cam, cam.width, cam.height)


def camera_depths(model, cam) -> np.ndarray:
    """(N,) camera z of every Gaussian mean, computed from the pose (independent of the engine's projection)."""
    w2c = np.linalg.inv(cam.T_map_cam)
    return model.means @ w2c[2, :3] + w2c[2, 3]


def random_sensor(rng, bins_edges, confusion=True) -> SensorModel:
    b = len(bins_edges) - 1
    weight = rng.uniform(0.05, 1.0, (C, b))
    conf = None
    if confusion == "symmetric":  # css_calibrate's default votes: the CPU kernel adds the shared part once
        from css_ros.calibration.learn import symmetric_votes

        conf = symmetric_votes(rng.uniform(0.3, 1.0, (C, b)))
    elif confusion:
        conf = rng.uniform(0.0, 1.0, (C, b, C)) ** 3
        conf /= conf.sum(axis=2, keepdims=True)
    return SensorModel(NAMES, np.asarray(bins_edges, float), weight, conf)


def sensor_update_reference(kappa, z, alpha, labels, model: SensorModel, confidence=None):
    """alpha + sum_i kappa_in * conf_i * w(y_i, b_i) * p(. | y_i, b_i) with d_i = sum kappa z / sum kappa."""
    lab = labels.ravel().astype(np.int64)
    ksum = kappa.sum(axis=1)
    depth = np.where(ksum > 0, (kappa @ z) / np.where(ksum > 0, ksum, 1.0), np.nan)
    b = model.bin_of(depth)
    valid = (lab >= 0) & (lab < C)
    y = np.zeros((lab.size, C))
    dist = model.label_distribution()
    y[valid] = model.weight[lab[valid], b[valid], None] * dist[lab[valid], b[valid]]
    if confidence is not None:
        y *= confidence.ravel()[:, None]
    return alpha + kappa.T @ y, depth, int(np.count_nonzero(valid & ~(ksum > 0)))


@pytest.mark.parametrize("backend", ["numba", "torch"])
@pytest.mark.parametrize("confusion", [True, False, "symmetric"])
def test_update_matches_brute_force(backend, confusion):
    rng = np.random.default_rng(3)
    model = random_scene(4, n=40, depth=(0.5, 6.0))
    sensor = random_sensor(rng, [0.0, 1.5, 2.5, 3.5, 5.0], confusion)
    smap = SemanticMap(model, C, backend=backend, sensor_model=sensor)
    alpha = np.full((model.num_gaussians, C), 1e-3)
    for i, pose in enumerate([dict(), dict(position=(0.3, -0.1, 0.4), quat=(0.03, -0.04, 0.0, 0.998))]):
        cam = camera(**pose)
        labels = rng.integers(0, C, (cam.height, cam.width))
        labels[rng.random(labels.shape) < 0.1] = 255
        conf = rng.uniform(0, 1, labels.shape).astype(np.float32) if i else None
        kap, _ = ref_kappa(model, cam)
        alpha, depth, no_depth = sensor_update_reference(kap, camera_depths(model, cam), alpha, labels, sensor, conf)
        stats = smap.update(cam, labels, conf)
        np.testing.assert_allclose(smap.concentrations, alpha, rtol=1e-9, atol=1e-12)
        assert stats.no_depth == no_depth
        assert no_depth > 0  # the random scene leaves empty pixels: they are counted, and add nothing


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_depth_image_is_kappa_weighted_camera_z(backend):
    model = random_scene(5, n=40)
    cam = camera(position=(0.1, 0.0, -0.3))
    kap, _ = ref_kappa(model, cam)
    z = camera_depths(model, cam)
    ksum = kap.sum(axis=1)
    expected = np.where(ksum > 0, (kap @ z) / np.where(ksum > 0, ksum, 1), np.nan).reshape(cam.height, cam.width)
    assert np.isnan(expected).any() and not np.isnan(expected).all()
    for scale in (1.0, 2.5):  # metres per splat unit
        view = SemanticMap(model, C, backend=backend, depth_scale=scale).render(cam)
        assert view.depth.dtype == np.float32
        np.testing.assert_array_equal(np.isnan(view.depth), np.isnan(expected))
        np.testing.assert_allclose(view.depth, scale * expected, rtol=1e-5, equal_nan=True)


def test_identity_sensor_model_is_the_paper_update_bit_for_bit():
    """One bin, weight 1, no confusion: the sensor-model path reduces exactly to alpha += kappa y; and without a
    sensor model the update equals the brute-force paper update."""
    rng = np.random.default_rng(8)
    model = random_scene(6)
    identity = SensorModel(NAMES, np.array([0.0, 100.0]), np.ones((C, 1)))
    paper = SemanticMap(model, C)
    with_model = SemanticMap(model, C, sensor_model=identity)
    alpha = np.full((model.num_gaussians, C), 1e-3)
    for pose in (dict(), dict(position=(0.2, 0.2, 0.1))):
        cam = camera(**pose)
        labels = rng.integers(0, C, (cam.height, cam.width))
        conf = rng.uniform(0, 1, labels.shape).astype(np.float32)
        paper.update(cam, labels, conf)
        with_model.update(cam, labels, conf)
        alpha = update_reference(ref_kappa(model, cam)[0], alpha, labels, C, confidence=conf)
    assert np.array_equal(paper.concentrations, with_model.concentrations)
    np.testing.assert_allclose(paper.concentrations, alpha, rtol=1e-9)
    assert paper.fused_sensor_model == ""


def test_far_labels_with_zero_weight_add_nothing():
    """A closed form: weight 0 beyond 2 m means Gaussians seen only beyond 2 m keep their prior."""
    model = random_scene(7, depth=(0.5, 6.0))
    sensor = SensorModel(NAMES, np.array([0.0, 2.0, 50.0]), np.array([[1.0, 0.0]] * C))
    smap = SemanticMap(model, C, sensor_model=sensor)
    cam = camera()
    smap.update(cam, np.zeros((cam.height, cam.width), dtype=np.int64))
    kap, _ = ref_kappa(model, cam)
    ksum = kap.sum(axis=1)
    depth = (kap @ camera_depths(model, cam)) / np.maximum(ksum, 1e-300)
    near_pixels = (ksum > 0) & (depth < 2.0)
    touched_near = kap[near_pixels].sum(axis=0) > 0
    gained = smap.concentrations.sum(axis=1) - C * 1e-3
    assert np.all(gained[~touched_near] == 0)
    assert np.all(gained[touched_near] > 0)


def test_file_roundtrip_and_fingerprint(tmp_path):
    rng = np.random.default_rng(1)
    sensor = random_sensor(rng, [0.0, 1.0, 3.0])
    sensor = SensorModel(sensor.class_names, sensor.depth_edges, sensor.weight, sensor.confusion,
                         ConfidenceMap(np.array([1.2, 0.3, -0.5]), np.array([0.0, 0.4, 1.0]),
                                       np.array([0.1, 0.5, 0.97])), {"bags": ["x"]})
    path = sensor.save(tmp_path / "sm.yaml")
    back = SensorModel.load(path, NAMES)
    assert back.fingerprint == sensor.fingerprint
    assert np.array_equal(back.weight, sensor.weight) and np.array_equal(back.confusion, sensor.confusion)
    e, ev = rng.uniform(0, 1, 100), rng.uniform(0, 50, 100)
    np.testing.assert_array_equal(back.confidence(e, ev), sensor.confidence(e, ev))
    # the confidence map does not change the fingerprint (it only changes what is published)
    assert SensorModel(NAMES, sensor.depth_edges, sensor.weight, sensor.confusion).fingerprint == sensor.fingerprint


def test_confidence_map_is_the_documented_formula_and_monotone():
    cmap = ConfidenceMap(np.array([1.5, 0.4, -1.0]), np.array([0.0, 0.3, 0.6, 1.0]), np.array([0.05, 0.2, 0.7, 0.99]))
    e = np.linspace(0.05, 0.99, 50)
    ev = np.full(50, 3.0)
    z = 1.5 * np.log(e / (1 - e)) + 0.4 * np.log1p(3.0) - 1.0
    expected = np.interp(1 / (1 + np.exp(-z)), cmap.knots_x, cmap.knots_y)
    np.testing.assert_allclose(cmap(e, ev), expected, rtol=1e-6)
    assert np.all(np.diff(cmap(e, ev)) >= 0)


def _write(tmp_path, sensor: SensorModel, edit) -> str:
    import yaml

    d = sensor.to_dict()
    d.pop("fingerprint")
    edit(d)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(d))
    return str(path)


@pytest.mark.parametrize("edit, message", [
    (lambda d: d["weight"][0].__setitem__(0, float("nan")), "weight entries must be finite"),
    (lambda d: d["weight"][1].__setitem__(1, -0.2), "weight entries must be finite and in [0, 1]"),
    (lambda d: d["confusion"][0][0].__setitem__(0, 5.0), "sums to"),
    (lambda d: d.__setitem__("depth_edges", [0.0, 3.0, 1.0]), "strictly increasing"),
    (lambda d: d.__setitem__("classes", list(NAMES[:-1])), "weight has shape"),
    (lambda d: d.__setitem__("format", "something else"), "not a css_ros sensor model"),
    (lambda d: d.__setitem__("weight", [[1.0, 2.0], [3.0]]), "nested lists of numbers"),
])
def test_bad_files_are_refused_in_one_line(tmp_path, edit, message):
    sensor = random_sensor(np.random.default_rng(2), [0.0, 1.0, 3.0])
    path = _write(tmp_path, sensor, edit)
    with pytest.raises(SensorModelError, match=message.replace("[", r"\[").replace("]", r"\]")) as info:
        SensorModel.load(path)
    assert "\n" not in str(info.value) and path in str(info.value)


def test_other_classes_missing_file_ply_and_tampered_file_are_refused(tmp_path):
    sensor = random_sensor(np.random.default_rng(2), [0.0, 1.0, 3.0])
    path = sensor.save(tmp_path / "sm.yaml")
    with pytest.raises(SensorModelError, match="class 2 is 'c2', the map's class file says 'wall'"):
        SensorModel.load(path, ["c0", "c1", "wall", "c3", "c4"])
    with pytest.raises(SensorModelError, match="is for 5 classes, the map has 6"):
        SensorModel.load(path, [*NAMES, "extra"])
    with pytest.raises(SensorModelError, match="does not exist"):
        SensorModel.load(tmp_path / "missing.yaml")
    ply = tmp_path / "model.ply"
    ply.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nend_header\n\x00\x01\xff\xfe")
    with pytest.raises(SensorModelError, match="not"):
        SensorModel.load(ply)
    text = path.read_text().replace("depth_edges: [0.0, 1.0, 3.0]", "depth_edges: [0.0, 1.5, 3.0]", 1)
    assert text != path.read_text()
    path.write_text(text)
    with pytest.raises(SensorModelError, match="do not match its fingerprint"):
        SensorModel.load(path)
    with pytest.raises(SensorModelError, match="is for 5 classes, the map has 4"):
        SemanticMap(random_scene(0, n=10), 4, sensor_model=sensor)


def test_map_files_keep_the_sensor_model_and_merges_refuse_mixed(tmp_path):
    rng = np.random.default_rng(4)
    model = random_scene(9)
    sensor = random_sensor(rng, [0.0, 2.0, 9.0])
    cam = camera()
    labels = rng.integers(0, C, (cam.height, cam.width))
    a = SemanticMap(model, C, sensor_model=sensor)
    a.update(cam, labels)
    a.save(tmp_path / "a.npz")
    b = SemanticMap(model, C)
    b.update(cam, labels)
    b.save(tmp_path / "b.npz")
    loaded = SemanticMap.load(tmp_path / "a.npz", model)  # no sensor model named: kept from the file
    assert loaded.fused_sensor_model == sensor.fingerprint
    assert SemanticMap.load(tmp_path / "a.npz", model, sensor_model=sensor).fused_sensor_model == sensor.fingerprint
    with pytest.raises(MapError, match="was fused with sensor model .* this map uses the paper's update"):
        SemanticMap.load(tmp_path / "a.npz", model, sensor_model=None)
    with pytest.raises(MapError, match="fused with different sensor models"):
        merge_maps([loaded, SemanticMap.load(tmp_path / "b.npz", model)])
    merged = merge_maps([loaded, SemanticMap.load(tmp_path / "a.npz", model)])
    assert merged.fused_sensor_model == sensor.fingerprint
    from css_ros.engine.map_file import read_map_info

    assert read_map_info(tmp_path / "a.npz").sensor_model == sensor.fingerprint
    assert read_map_info(tmp_path / "b.npz").sensor_model == ""
