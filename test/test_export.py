"""css_export and the bird's-eye render: files read back with plyfile / matplotlib (independent readers)
and compared with a numpy evaluation of the SPEC §9 per-Gaussian semantics written here."""
from __future__ import annotations

import numpy as np
import pytest
from plyfile import PlyData

from css_ros import ClassSet, GaussianModel, SemanticMap
from css_ros.export import render_birdseye
from css_ros.export.cli import main
from scenes import random_quats

SH_C0 = 0.28209479177387814
C = 4
GREY = np.array([128, 128, 128])


def make_model(seed: int = 0, n: int = 200, degree_rest: int = 15) -> GaussianModel:
    rng = np.random.default_rng(seed)
    means = rng.uniform(-2, 2, (n, 3))
    sh = rng.normal(0, 0.5, (n, degree_rest + 1, 3))         # SH degree 3: f_rest must be zeroed
    return GaussianModel(means=means, sh=sh, opacity_logits=rng.normal(0, 1, n),
                         log_scales=rng.uniform(-4, -1, (n, 3)), rotations=random_quats(rng, n))


@pytest.fixture()
def scene(tmp_path):
    model = make_model()
    n = model.num_gaussians
    smap = SemanticMap(model, C)
    rng = np.random.default_rng(1)
    smap.concentrations += rng.gamma(0.5, 4.0, (n, C)) + 0.2     # evidence >= 0.8 everywhere
    unobserved = np.zeros(n, dtype=bool)
    unobserved[::5] = True
    smap.concentrations[unobserved] = smap.prior
    smap.concentrations[3, :] = smap.prior
    smap.concentrations[3, 2] += 0.3                          # below the default min_evidence 0.5
    unobserved[3] = True
    model.to_ply(tmp_path / "model.ply")
    smap.save(tmp_path / "map.npz")
    classes = ClassSet(("floor", "wall", "chair", "plant"),
                       np.array([[200, 30, 30], [30, 200, 30], [30, 30, 200], [220, 220, 0]], dtype=np.uint8))
    classes.to_yaml(tmp_path / "classes.yaml")
    return tmp_path, model, smap.concentrations.copy(), classes, unobserved


def expected_semantics(alpha: np.ndarray, prior: float, min_evidence: float = 0.5):
    s = alpha.sum(1)
    lab = alpha.argmax(1)
    e = alpha[np.arange(len(alpha)), lab] / s
    var = e * (1 - e) / (1 + s)
    evidence = s - alpha.shape[1] * prior
    observed = evidence >= min_evidence
    return np.where(observed, lab, 255), e, var, evidence, observed


def run(tmp_path, *extra):
    return main([str(tmp_path / "map.npz"), "--model", str(tmp_path / "model.ply"),
                 "--classes", str(tmp_path / "classes.yaml"), "--out", str(tmp_path / "out"), *extra])


def vertex(path):
    return PlyData.read(str(path))["vertex"].data


def decoded_rgb(v):
    return np.stack([0.5 + SH_C0 * v[f"f_dc_{j}"].astype(np.float64) for j in range(3)], axis=1) * 255.0


def test_semantic_splat(scene):
    tmp_path, model, alpha, classes, unobserved = scene
    assert run(tmp_path, "--formats", "semantic") == 0
    v = vertex(tmp_path / "out" / "map_semantic.ply")
    lab, e, var, evidence, observed = expected_semantics(alpha, 1e-3)
    np.testing.assert_array_equal(observed, ~unobserved)
    np.testing.assert_array_equal(v["class_id"], lab)
    np.testing.assert_allclose(v["expectation"], e, rtol=1e-6)
    np.testing.assert_allclose(v["variance"], var, rtol=1e-6)
    np.testing.assert_allclose(v["evidence"], evidence, rtol=1e-6, atol=1e-6)
    rgb = decoded_rgb(v)
    np.testing.assert_allclose(rgb[observed], classes.palette[lab[observed]], atol=1e-3)
    np.testing.assert_allclose(rgb[~observed], np.broadcast_to(GREY, (int((~observed).sum()), 3)), atol=1e-3)
    rest = [f for f in v.dtype.names if f.startswith("f_rest_")]
    assert len(rest) == 45 and all(np.all(v[f] == 0) for f in rest)
    for f, ref in (("x", model.means[:, 0]), ("opacity", model.opacity_logits), ("scale_1", model.log_scales[:, 1]),
                   ("rot_3", model.rotations[:, 3])):
        np.testing.assert_array_equal(v[f], ref)
    # a 3DGS reader loads it: the geometry is the model's, the colour the class colour
    back = GaussianModel.from_ply(tmp_path / "out" / "map_semantic.ply")
    np.testing.assert_array_equal(back.means, model.means)


def test_drop_unobserved(scene):
    tmp_path, model, alpha, classes, unobserved = scene
    assert run(tmp_path, "--drop-unobserved") == 0
    lab, e, var, evidence, observed = expected_semantics(alpha, 1e-3)
    for name in ("map_semantic.ply", "map_points.ply", "map_uncertainty_variance.ply"):
        v = vertex(tmp_path / "out" / name)
        assert len(v) == int(observed.sum())
        np.testing.assert_array_equal(v["x"], model.means[observed, 0])
    pts = vertex(tmp_path / "out" / "map_points.ply")
    np.testing.assert_array_equal(pts["label"], lab[observed])
    assert np.all(pts["label"] != 255)


def test_min_evidence_flag(scene):
    tmp_path, model, alpha, classes, unobserved = scene
    assert run(tmp_path, "--formats", "points", "--min-evidence", "0.2") == 0
    lab, *_ = expected_semantics(alpha, 1e-3, min_evidence=0.2)
    v = vertex(tmp_path / "out" / "map_points.ply")
    assert v["label"][3] == 2                                 # evidence 0.3 >= 0.2
    np.testing.assert_array_equal(v["label"], lab)


def test_point_cloud(scene):
    tmp_path, model, alpha, classes, unobserved = scene
    assert run(tmp_path, "--formats", "points") == 0
    v = vertex(tmp_path / "out" / "map_points.ply")
    assert list(v.dtype.names) == ["x", "y", "z", "red", "green", "blue", "label", "expectation", "variance"]
    assert all(v.dtype[c] == np.uint8 for c in ("red", "green", "blue"))
    lab, e, var, _, observed = expected_semantics(alpha, 1e-3)
    np.testing.assert_array_equal(np.stack([v["x"], v["y"], v["z"]], 1), model.means)
    rgb = np.stack([v["red"], v["green"], v["blue"]], 1)
    np.testing.assert_array_equal(rgb[observed], classes.palette[lab[observed]])
    assert np.all(rgb[~observed] == GREY)
    np.testing.assert_array_equal(v["label"], lab)
    np.testing.assert_allclose(v["expectation"], e, rtol=1e-6)
    np.testing.assert_allclose(v["variance"], var, rtol=1e-6)
    assert not (tmp_path / "out" / "map_semantic.ply").exists()


@pytest.mark.parametrize("quantity", ["variance", "evidence"])
def test_uncertainty_splat_and_colorbar(scene, quantity):
    import matplotlib
    import matplotlib.image

    tmp_path, model, alpha, classes, unobserved = scene
    assert run(tmp_path, "--formats", "uncertainty", "--uncertainty", quantity) == 0
    v = vertex(tmp_path / "out" / f"map_uncertainty_{quantity}.ply")
    lab, e, var, evidence, observed = expected_semantics(alpha, 1e-3)
    rgb = decoded_rgb(v)
    assert np.allclose(rgb[~observed], GREY, atol=1e-3)
    values = (var if quantity == "variance" else evidence)[observed]
    cmap = matplotlib.colormaps["magma" if quantity == "variance" else "viridis"]
    # the extremes of the data sit at the ends of the colour map (the scale clips at percentiles 1, 99)
    np.testing.assert_allclose(rgb[observed][np.argmax(values)], np.array(cmap(1.0)[:3]) * 255, atol=0.6)
    np.testing.assert_allclose(rgb[observed][np.argmin(values)], np.array(cmap(0.0)[:3]) * 255, atol=0.6)
    # colours rise monotonically along the colour map with the value (compare positions in its LUT)
    lut = cmap(np.linspace(0, 1, 256))[:, :3] * 255
    pos = np.argmin(((rgb[observed][:, None, :] - lut[None]) ** 2).sum(-1), axis=1)
    order = np.argsort(values)
    assert np.all(np.diff(pos[order]) >= -1)
    bar = tmp_path / "out" / f"map_uncertainty_{quantity}_colorbar.png"
    assert bar.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    img = matplotlib.image.imread(bar)
    assert img.ndim == 3 and img.shape[0] > 50 and img.shape[1] > 300


def test_num_classes_anonymous(scene):
    tmp_path, *_ = scene
    rc = main([str(tmp_path / "map.npz"), "--model", str(tmp_path / "model.ply"), "--num-classes", str(C),
               "--formats", "semantic"])
    assert rc == 0
    assert (tmp_path / "map_semantic.ply").is_file()          # default --out: the map's folder
    v = vertex(tmp_path / "map_semantic.ply")
    pal = ClassSet.default(C).palette
    obs = v["class_id"] != 255
    np.testing.assert_allclose(decoded_rgb(v)[obs], pal[v["class_id"][obs]], atol=1e-3)


def test_classes_come_from_the_map_without_a_class_file(scene):
    tmp_path, *_ = scene
    out = tmp_path / "nofile"
    assert main([str(tmp_path / "map.npz"), "--model", str(tmp_path / "model.ply"), "--formats", "semantic",
                 "--out", str(out)]) == 0
    v = vertex(out / "map_semantic.ply")
    obs = v["class_id"] != 255
    assert obs.any()
    np.testing.assert_allclose(decoded_rgb(v)[obs], ClassSet.default(C).palette[v["class_id"][obs]], atol=1e-3)


# ------------------------------------------------------------------ errors
def one_line_error(capsys, needle):
    err = capsys.readouterr().err.strip()
    assert err.startswith("css_export: error:") and "\n" not in err and needle in err, err


def test_missing_files(scene, capsys):
    tmp_path, *_ = scene
    assert main([str(tmp_path / "nope.npz"), "--model", str(tmp_path / "model.ply"), "--num-classes", "4"]) == 1
    one_line_error(capsys, "map file not found")
    assert main([str(tmp_path / "map.npz"), "--model", str(tmp_path / "nope.ply"), "--num-classes", "4"]) == 1
    one_line_error(capsys, "model file not found")
    assert main([str(tmp_path / "map.npz"), "--model", str(tmp_path / "model.ply"),
                 "--classes", str(tmp_path / "nope.yaml")]) == 1
    one_line_error(capsys, "class file not found")


def test_map_model_mismatch(scene, capsys):
    tmp_path, *_ = scene
    make_model(seed=7).to_ply(tmp_path / "other.ply")
    assert main([str(tmp_path / "map.npz"), "--model", str(tmp_path / "other.ply"), "--num-classes", "4"]) == 1
    one_line_error(capsys, "this map belongs to model")


def test_bad_class_files(scene, capsys):
    tmp_path, *_ = scene
    (tmp_path / "bad.yaml").write_text("classes: [{id: 0, name: a}]\n")
    assert main([str(tmp_path / "map.npz"), "--model", str(tmp_path / "model.ply"),
                 "--classes", str(tmp_path / "bad.yaml")]) == 1
    one_line_error(capsys, "class file")
    ClassSet.default(3).to_yaml(tmp_path / "three.yaml")
    assert main([str(tmp_path / "map.npz"), "--model", str(tmp_path / "model.ply"),
                 "--classes", str(tmp_path / "three.yaml")]) == 1
    one_line_error(capsys, "has 4 classes, expected 3")


def test_bad_formats_and_usage(scene, capsys):
    tmp_path, *_ = scene
    assert run(tmp_path, "--formats", "semantic,mesh") == 1
    one_line_error(capsys, "mesh")
    with pytest.raises(SystemExit) as exc:   # --classes and --num-classes exclude each other
        main([str(tmp_path / "map.npz"), "--model", str(tmp_path / "model.ply"), "--classes", "c.yaml",
              "--num-classes", "3"])
    assert exc.value.code == 2
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    assert "examples:" in capsys.readouterr().out


def test_corrupt_map(scene, capsys):
    tmp_path, *_ = scene
    (tmp_path / "map.npz").write_bytes(b"not a zip")
    assert run(tmp_path) == 1
    one_line_error(capsys, "is not an .npz archive")


# ------------------------------------------------------------------ bird's-eye view
def two_region_map(tmp_path):
    """A floor at z=0, x in [-2, 2], y in [-1, 1]: class 0 for x < 0, class 1 for x > 0; and an
    unobserved sheet at z=1 over all of it (must not hide the floor: only observed Gaussians render)."""
    xs, ys = np.meshgrid(np.arange(-2, 2.01, 0.05), np.arange(-1, 1.01, 0.05))
    floor = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], 1)
    roof = floor.copy()
    roof[:, 2] = 1.0
    means = np.concatenate([floor, roof])
    n = len(means)
    scales = np.tile([0.05, 0.05, 0.005], (n, 1))
    model = GaussianModel.from_activated(means, scales, np.tile([1.0, 0, 0, 0], (n, 1)), np.full(n, 0.95),
                                         np.full((n, 3), 0.5))
    smap = SemanticMap(model, 3)
    nf = len(floor)
    smap.concentrations[:nf][floor[:, 0] < 0, 0] += 20.0
    smap.concentrations[:nf][floor[:, 0] > 0, 1] += 20.0
    smap.concentrations[:nf][floor[:, 0] == 0, 2] += 20.0
    classes = ClassSet(("left", "right", "seam"), np.array([[220, 20, 20], [20, 20, 220], [20, 200, 20]], np.uint8))
    return smap, classes


def test_birdseye_looks_down_with_class_colours(tmp_path):
    import matplotlib.image

    smap, classes = two_region_map(tmp_path)
    view = render_birdseye(smap, classes, tmp_path / "bev.png", width=160)
    cam = view.camera
    np.testing.assert_allclose(cam.R_map_cam[:, 2], [0, 0, -1], atol=1e-12)    # optical axis straight down
    h, w = view.labels.shape
    assert w == 160 and 60 <= h <= 100                        # 4 m x 2 m scene
    left, right = view.labels[:, : w // 3], view.labels[:, -(w // 3):]
    assert np.mean(left == 0) > 0.8 and np.mean(right == 1) > 0.8
    png = tmp_path / "bev.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    img = np.rint(matplotlib.image.imread(png)[..., :3] * 255).astype(int).reshape(-1, 3)
    colours, counts = np.unique(img, axis=0, return_counts=True)
    keep = ~np.all(colours == 255, axis=1)                     # drop the white background
    top2 = colours[keep][np.argsort(-counts[keep])[:2]]
    assert {tuple(c) for c in top2} == {tuple(classes.palette[0]), tuple(classes.palette[1])}


def test_birdseye_image_top_is_map_plus_y(tmp_path):
    smap, classes = two_region_map(tmp_path)
    means = smap.model.means
    smap.concentrations[...] = smap.prior
    floor = means[:, 2] == 0
    smap.concentrations[floor & (means[:, 1] > 0), 0] += 20.0   # class 0 at +y
    smap.concentrations[floor & (means[:, 1] <= 0), 1] += 20.0
    view = render_birdseye(smap, classes, tmp_path / "bev.png", width=120)
    h = view.labels.shape[0]
    assert np.mean(view.labels[: h // 3] == 0) > 0.8
    assert np.mean(view.labels[-(h // 3):] == 1) > 0.8


def test_corrupt_compressed_map_is_one_line_naming_the_file(scene, capsys):
    tmp_path, *_ = scene
    with np.load(tmp_path / "map.npz", allow_pickle=False) as data:
        members = {k: data[k] for k in data.files}
    bad = tmp_path / "corrupt.npz"
    np.savez_compressed(bad, **members)
    raw = bytearray(bad.read_bytes())
    import zipfile
    with zipfile.ZipFile(bad) as zf:
        info = zf.getinfo("concentrations.npy")
    start = info.header_offset + 30 + len(info.filename.encode()) + \
        int.from_bytes(raw[info.header_offset + 28:info.header_offset + 30], "little")
    raw[start] = 0x07  # invalid deflate block type
    bad.write_bytes(bytes(raw))
    assert main([str(bad), "--model", str(tmp_path / "model.ply"), "--num-classes", "4"]) == 1
    one_line_error(capsys, f"cannot read map file {bad}")


def test_decompression_bomb_refused_from_its_header(scene, capsys):
    """A deflated map whose concentrations declare (N, 50000) float64 (80 MB of zeros, < 1 MB on disk) while
    the file records 4 classes: refused from the headers, one line naming the file and both shapes."""
    import zipfile

    tmp_path, *_ = scene
    src = tmp_path / "map.npz"
    bomb = tmp_path / "bomb.npz"
    with zipfile.ZipFile(src) as zf:
        items = {i.filename: zf.read(i) for i in zf.infolist() if i.filename != "concentrations.npy"}
    n = GaussianModel.from_ply(tmp_path / "model.ply").num_gaussians
    from numpy.lib import format as npformat
    import io
    head = io.BytesIO()
    npformat.write_array_header_1_0(head, {"descr": "<f8", "fortran_order": False, "shape": (n, 50000)})
    with zipfile.ZipFile(bomb, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, data in items.items():
            zf.writestr(name, data)
        with zf.open("concentrations.npy", "w", force_zip64=True) as fh:
            fh.write(head.getvalue())
            for _ in range(n):
                fh.write(bytes(8 * 50000))
    assert bomb.stat().st_size < 2**20
    assert main([str(bomb), "--model", str(tmp_path / "model.ply"), "--num-classes", "4"]) == 1
    one_line_error(capsys, f"map file {bomb}: concentrations have shape ({n}, 50000)")
