"""Tests for css_ros.engine.gaussians: INRIA PLY loading, validation, round-trips and activations."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from numpy.lib.recfunctions import repack_fields
from plyfile import PlyData, PlyElement

from css_ros.errors import ModelError
from css_ros.engine.gaussians import SH_C0, GaussianModel

DATA = Path(__file__).resolve().parent / "data"
REAL_PLY = DATA / "pc_short.ply"


def inria_fields(degree: int, normals: bool = True) -> list[str]:
    """INRIA field order, written out independently of the module under test."""
    k = (degree + 1) ** 2
    names = ["x", "y", "z"] + (["nx", "ny", "nz"] if normals else [])
    names += ["f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(3 * (k - 1))]
    return names + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


def random_record(n: int, degree: int, rng: np.random.Generator, normals: bool = True,
                  extra: list[tuple[str, str]] | None = None, byte_order: str = "<") -> np.ndarray:
    names = inria_fields(degree, normals)
    dtype = [(f, byte_order + "f4") for f in names] + list(extra or [])
    rec = np.zeros(n, dtype=dtype)
    for f in names:
        rec[f] = rng.normal(size=n).astype(np.float32)
    for f, _ in extra or []:
        rec[f] = rng.integers(0, 100, size=n)
    return rec


def write_ply(path: Path, rec: np.ndarray, text: bool = False, byte_order: str = "<",
              element: str = "vertex") -> Path:
    PlyData([PlyElement.describe(rec, element)], text=text, byte_order=byte_order).write(str(path))
    return path


def bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float32).view(np.uint32)


def assert_models_bit_equal(a: GaussianModel, b: GaussianModel) -> None:
    for name in ("means", "sh", "opacity_logits", "log_scales", "rotations", "normals"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.shape == y.shape, name
        assert np.array_equal(bits(x), bits(y)), name
    assert a.fingerprint == b.fingerprint


def header_length(path: Path) -> int:
    raw = path.read_bytes()
    return raw.index(b"end_header\n") + len(b"end_header\n")


# ---------------------------------------------------------------------------------------------- real file
def test_real_file_loads():
    m = GaussianModel.from_ply(REAL_PLY)
    assert m.num_gaussians == 100
    assert m.sh_degree == 3
    assert m.sh.shape == (100, 16, 3)
    for arr in (m.means, m.sh, m.opacity_logits, m.log_scales, m.rotations, m.normals):
        assert arr.dtype == np.float32 and arr.flags.c_contiguous
    # values equal the raw file columns (read independently with plyfile)
    raw = PlyData.read(str(REAL_PLY))["vertex"].data
    assert np.array_equal(m.means[:, 1], raw["y"])
    assert np.array_equal(m.sh[:, 0, 2], raw["f_dc_2"])
    assert np.array_equal(m.sh[:, 1, 0], raw["f_rest_0"])    # R, coefficient 1
    assert np.array_equal(m.sh[:, 15, 0], raw["f_rest_14"])  # R, coefficient 15
    assert np.array_equal(m.sh[:, 1, 1], raw["f_rest_15"])   # G, coefficient 1
    assert np.array_equal(m.sh[:, 15, 2], raw["f_rest_44"])  # B, coefficient 15
    assert np.array_equal(m.rotations[:, 0], raw["rot_0"])
    # activations
    o = m.opacities
    assert o.dtype == np.float32 and np.all((o > 0) & (o < 1))
    np.testing.assert_allclose(o, 1.0 / (1.0 + np.exp(-raw["opacity"].astype(np.float64))), rtol=1e-6)
    np.testing.assert_allclose(m.scales, np.exp(m.log_scales.astype(np.float64)), rtol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(m.quats_wxyz, axis=1), 1.0, atol=1e-12)
    assert len(m.fingerprint) == 64


def test_real_file_round_trip_binary_is_byte_identical_prefix(tmp_path):
    m = GaussianModel.from_ply(REAL_PLY)
    out = tmp_path / "out.ply"
    m.to_ply(out)
    written = out.read_bytes()
    original = REAL_PLY.read_bytes()
    # the original carries trailing bytes after the declared vertices; everything up to there is identical
    assert len(written) == header_length(REAL_PLY) + 100 * 62 * 4
    assert original[: len(written)] == written
    assert_models_bit_equal(m, GaussianModel.from_ply(out))
    assert [p.name for p in tmp_path.iterdir()] == ["out.ply"]  # no temp file left behind


def test_real_file_round_trip_ascii(tmp_path):
    m = GaussianModel.from_ply(REAL_PLY)
    out = tmp_path / "out_ascii.ply"
    m.to_ply(out, binary=False)
    assert out.read_bytes().startswith(b"ply\nformat ascii 1.0\n")
    assert_models_bit_equal(m, GaussianModel.from_ply(out))


# ---------------------------------------------------------------------------------------------- synthetic
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("binary", [True, False])
def test_every_degree_round_trips(tmp_path, degree, binary):
    rng = np.random.default_rng(degree)
    n, k = 37, (degree + 1) ** 2
    m = GaussianModel(means=rng.normal(size=(n, 3)), sh=rng.normal(size=(n, k, 3)),
                      opacity_logits=rng.normal(size=n), log_scales=rng.normal(size=(n, 3)) - 3,
                      rotations=rng.normal(size=(n, 4)), normals=rng.normal(size=(n, 3)))
    assert m.sh_degree == degree
    path = tmp_path / f"d{degree}.ply"
    m.to_ply(path, binary=binary)
    raw = PlyData.read(str(path))["vertex"].data
    assert list(raw.dtype.names) == inria_fields(degree)
    assert all(raw.dtype[f] == np.dtype("<f4") for f in raw.dtype.names)
    assert_models_bit_equal(m, GaussianModel.from_ply(path))


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_f_rest_is_channel_major(tmp_path, degree):
    k = (degree + 1) ** 2
    rec = random_record(5, degree, np.random.default_rng(0))
    for i in range(3 * (k - 1)):
        rec[f"f_rest_{i}"] = 1000 + i
    m = GaussianModel.from_ply(write_ply(tmp_path / "cm.ply", rec))
    for c in range(3):
        for kk in range(1, k):
            assert np.all(m.sh[:, kk, c] == 1000 + c * (k - 1) + kk - 1)


def test_big_endian_and_no_normals_and_extra_fields(tmp_path):
    rng = np.random.default_rng(1)
    rec = random_record(20, 1, rng, normals=False,
                        extra=[("semantic", "u1"), ("count", ">i4")], byte_order=">")
    path = write_ply(tmp_path / "be.ply", rec, byte_order=">")
    m = GaussianModel.from_ply(path)
    assert m.num_gaussians == 20 and m.sh_degree == 1
    assert np.all(m.normals == 0)
    assert np.array_equal(m.means[:, 0], rec["x"].astype(np.float32))
    assert np.array_equal(m.log_scales[:, 2], rec["scale_2"].astype(np.float32))


def test_extra_fields_ignored_on_load_and_written_with_dtype(tmp_path):
    m = GaussianModel.from_ply(REAL_PLY)
    labels = np.arange(100, dtype=np.uint8)
    ids = np.arange(100, dtype=np.int32) - 50
    prob = np.linspace(0, 1, 100).astype(np.float32)
    out = tmp_path / "sem.ply"
    m.to_ply(out, extra_fields={"semantic_label": labels, "instance": ids, "confidence": prob})
    raw = PlyData.read(str(out))["vertex"].data
    assert raw.dtype.names[-3:] == ("semantic_label", "instance", "confidence")
    assert raw.dtype["semantic_label"] == np.uint8 and raw.dtype["instance"] == np.int32
    assert np.array_equal(raw["semantic_label"], labels)
    assert np.array_equal(raw["instance"], ids)
    assert np.array_equal(raw["confidence"], prob)
    assert_models_bit_equal(m, GaussianModel.from_ply(out))
    # ASCII too
    out2 = tmp_path / "sem_ascii.ply"
    m.to_ply(out2, binary=False, extra_fields={"semantic_label": labels})
    assert_models_bit_equal(m, GaussianModel.from_ply(out2))


def test_to_ply_rejects_bad_extra_fields(tmp_path):
    m = GaussianModel.from_ply(REAL_PLY)
    with pytest.raises(ModelError, match="shape"):
        m.to_ply(tmp_path / "a.ply", extra_fields={"lab": np.zeros(99, np.uint8)})
    with pytest.raises(ModelError, match="clashes"):
        m.to_ply(tmp_path / "a.ply", extra_fields={"opacity": np.zeros(100, np.uint8)})
    with pytest.raises(ModelError, match="property name"):
        m.to_ply(tmp_path / "a.ply", extra_fields={"bad name": np.zeros(100, np.uint8)})
    assert list(tmp_path.iterdir()) == []


def test_to_ply_overwrites_atomically(tmp_path):
    m = GaussianModel.from_ply(REAL_PLY)
    out = tmp_path / "m.ply"
    out.write_bytes(b"old")
    m.to_ply(out)
    assert_models_bit_equal(m, GaussianModel.from_ply(out))
    assert [p.name for p in tmp_path.iterdir()] == ["m.ply"]


def test_from_activated_closed_form():
    rng = np.random.default_rng(2)
    n = 50
    means = rng.normal(size=(n, 3))
    scales = rng.uniform(0.01, 0.5, size=(n, 3))
    q = rng.normal(size=(n, 4))
    o = rng.uniform(0.01, 0.99, size=n)
    colors = rng.uniform(0, 1, size=(n, 3))
    m = GaussianModel.from_activated(means, scales, q, o, colors)
    assert m.sh_degree == 0 and m.sh.shape == (n, 1, 3)
    np.testing.assert_allclose(m.means, means, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(m.scales, scales, rtol=1e-6)
    np.testing.assert_allclose(m.opacities, o, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(m.quats_wxyz, q / np.linalg.norm(q, axis=1, keepdims=True), atol=1e-6)
    np.testing.assert_allclose(SH_C0 * m.sh[:, 0, :].astype(np.float64) + 0.5, colors, atol=1e-6)
    np.testing.assert_allclose(m.base_colors, colors, atol=1e-6)
    # extreme opacities are clipped, never infinite logits
    m2 = GaussianModel.from_activated(means, scales, q, np.r_[0.0, 1.0, o[2:]], colors)
    assert np.all(np.isfinite(m2.opacity_logits))
    np.testing.assert_allclose(m2.opacities[:2], [1e-6, 1 - 1e-6], atol=1e-7)


def test_covariances_closed_form():
    # rotation of 90 degrees about z: (w, x, y, z) = (cos 45, 0, 0, sin 45) swaps the x and y variances
    s = np.array([[0.1, 0.2, 0.3]])
    q = np.array([[np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)]])
    m = GaussianModel.from_activated(np.zeros((1, 3)), s, q, np.array([0.5]), np.full((1, 3), 0.5))
    np.testing.assert_allclose(m.covariances()[0], np.diag([0.04, 0.01, 0.09]), atol=1e-8)


def test_fingerprint_identifies_content():
    m = GaussianModel.from_ply(REAL_PLY)
    same = GaussianModel(m.means.copy(), m.sh.copy(), m.opacity_logits.copy(), m.log_scales.copy(),
                         m.rotations.copy(), normals=None)  # normals do not matter
    assert same.fingerprint == m.fingerprint
    means = m.means.copy()
    means.view(np.uint32)[3, 1] ^= 1  # flip one bit
    other = GaussianModel(means, m.sh, m.opacity_logits, m.log_scales, m.rotations)
    assert other.fingerprint != m.fingerprint
    assert m.select(np.arange(50)).num_gaussians == 50


def test_constructor_validates_shapes():
    n = 4
    ok = dict(means=np.zeros((n, 3)), sh=np.zeros((n, 1, 3)), opacity_logits=np.zeros(n),
              log_scales=np.zeros((n, 3)), rotations=np.tile([1.0, 0, 0, 0], (n, 1)))
    GaussianModel(**ok)
    for key, bad in (("means", np.zeros((n, 2))), ("sh", np.zeros((n, 2, 3))), ("opacity_logits", np.zeros(n + 1)),
                     ("log_scales", np.zeros((n, 4))), ("rotations", np.zeros((n, 3))),
                     ("rotations", np.zeros((n, 4))), ("means", np.full((n, 3), np.nan))):
        with pytest.raises(ModelError, match=key):
            GaussianModel(**{**ok, key: bad})


# ---------------------------------------------------------------------------------------------- bad files
def test_missing_field(tmp_path):
    rec = random_record(10, 3, np.random.default_rng(3))
    names = [f for f in rec.dtype.names if f != "scale_2"]
    path = write_ply(tmp_path / "noscale2.ply", repack_fields(rec[names]))
    with pytest.raises(ModelError, match=r"noscale2\.ply.*'scale_2'"):
        GaussianModel.from_ply(path)


@pytest.mark.parametrize("field,value", [("opacity", np.nan), ("rot_1", np.inf), ("f_rest_44", -np.inf),
                                          ("x", np.nan)])
@pytest.mark.parametrize("text", [False, True])
def test_non_finite_values(tmp_path, field, value, text):
    rec = random_record(10, 3, np.random.default_rng(4))
    rec[field][[2, 7]] = value
    path = write_ply(tmp_path / "nonfinite.ply", rec, text=text)
    with pytest.raises(ModelError, match=rf"nonfinite\.ply.*'{field}'.*2 non-finite"):
        GaussianModel.from_ply(path)


def test_truncated_binary_real_file(tmp_path):
    raw = REAL_PLY.read_bytes()
    cut = header_length(REAL_PLY) + 50 * 62 * 4 + 17  # half the vertices, mid-record
    path = tmp_path / "trunc.ply"
    path.write_bytes(raw[:cut])
    with pytest.raises(ModelError, match=r"trunc\.ply.*truncated"):
        GaussianModel.from_ply(path)


def test_truncated_ascii(tmp_path):
    m = GaussianModel.from_ply(REAL_PLY)
    full = tmp_path / "full.ply"
    m.to_ply(full, binary=False)
    lines = full.read_bytes().split(b"\n")
    path = tmp_path / "trunc_ascii.ply"
    path.write_bytes(b"\n".join(lines[: len(lines) - 40]) + b"\n")  # drops the last vertices
    with pytest.raises(ModelError, match=r"trunc_ascii\.ply"):
        GaussianModel.from_ply(path)
    # cut in the middle of a line as well
    path.write_bytes(full.read_bytes()[:-500])
    with pytest.raises(ModelError, match=r"trunc_ascii\.ply"):
        GaussianModel.from_ply(path)


def test_zero_vertices(tmp_path):
    rec = random_record(0, 0, np.random.default_rng(5))
    path = write_ply(tmp_path / "empty.ply", rec)
    with pytest.raises(ModelError, match=r"empty\.ply.*zero vertices"):
        GaussianModel.from_ply(path)


def test_nonexistent_path(tmp_path):
    with pytest.raises(ModelError, match=r"nope\.ply.*does not exist"):
        GaussianModel.from_ply(tmp_path / "nope.ply")
    with pytest.raises(ModelError, match="does not exist"):
        GaussianModel.from_ply(tmp_path)  # a directory


def test_wrong_f_rest_count(tmp_path):
    rec = random_record(6, 1, np.random.default_rng(6))
    names = [f for f in rec.dtype.names if f != "f_rest_8"]  # 8 instead of 9
    path = write_ply(tmp_path / "rest8.ply", repack_fields(rec[names]))
    with pytest.raises(ModelError, match=r"rest8\.ply.*f_rest.*8"):
        GaussianModel.from_ply(path)


def test_f_rest_gap(tmp_path):
    rec = random_record(6, 1, np.random.default_rng(7), extra=[("f_rest_20", "<f4")])
    names = [f for f in rec.dtype.names if f != "f_rest_3"]  # 9 fields, but f_rest_3 missing
    path = write_ply(tmp_path / "gap.ply", repack_fields(rec[names]))
    with pytest.raises(ModelError, match=r"gap\.ply.*'f_rest_3'"):
        GaussianModel.from_ply(path)


def test_no_vertex_element_and_garbage(tmp_path):
    rec = random_record(3, 0, np.random.default_rng(8))
    path = write_ply(tmp_path / "points.ply", rec, element="point")
    with pytest.raises(ModelError, match=r"points\.ply.*'vertex'"):
        GaussianModel.from_ply(path)
    junk = tmp_path / "junk.ply"
    junk.write_bytes(b"\x00\x01not a ply at all\n" * 10)
    with pytest.raises(ModelError, match=r"junk\.ply"):
        GaussianModel.from_ply(junk)
    bad_header = tmp_path / "badheader.ply"
    bad_header.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty floot x\nend_header\n")
    with pytest.raises(ModelError, match=r"badheader\.ply"):
        GaussianModel.from_ply(bad_header)


@pytest.mark.parametrize("index,match", [
    (np.array([1000]), r"indices must be in \[0, 100\), got values in \[1000, 1000\]"),
    (np.array([-1]), r"indices must be in \[0, 100\)"),
    (np.array([np.iinfo(np.uint64).max]), r"indices must be in \[0, 100\)"),
    (np.array([1.0, 2.0]), "bool mask or integer indices, got ndarray of dtype float64"),
    (None, "got NoneType"),
    (["a"], "bool mask or integer indices"),
    (np.ones(5, dtype=bool), "bool mask has length 5, the model has 100 Gaussians"),
    (np.zeros((2, 2), dtype=int), "must be 1-D"),
    (np.zeros(100, dtype=bool), "selects no Gaussian"),
    ([], "selects no Gaussian"),
])
def test_select_refuses_bad_indices(index, match):
    m = GaussianModel.from_ply(REAL_PLY).select(np.arange(100))
    with pytest.raises(ModelError, match=match):
        m.select(index)


def test_select_masks_and_indices():
    m = GaussianModel.from_ply(REAL_PLY).select(np.arange(100))
    mask = np.zeros(100, dtype=bool)
    mask[[3, 7]] = True
    np.testing.assert_array_equal(m.select(mask).means, m.means[[3, 7]])
    np.testing.assert_array_equal(m.select([7, 7, 0]).means, m.means[[7, 7, 0]])
    np.testing.assert_array_equal(m.select(np.array([99], dtype=np.uint64)).means, m.means[[99]])


def test_select_refuses_mixed_bool_int_lists_and_more_indices_than_gaussians():
    model = GaussianModel.from_activated(np.zeros((4, 3)), np.ones((4, 3)), np.tile([1.0, 0, 0, 0], (4, 1)),
                                         np.full(4, 0.5), np.full((4, 3), 0.5))
    with pytest.raises(ModelError, match="mixes bools and integers"):
        model.select([True, 2])
    with pytest.raises(ModelError, match="5 indices for a model of 4 Gaussians"):
        model.select(np.broadcast_to(np.int64(0), (5,)))
    with pytest.raises(ModelError, match="indices for a model of 4 Gaussians"):
        model.select(np.broadcast_to(np.int64(0), (10**9,)))   # 17.9 GiB of copies once asked for
    assert model.select(np.array([3, 3, 0])).num_gaussians == 3
