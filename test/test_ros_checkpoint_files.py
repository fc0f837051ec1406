"""Crafted checkpoints and models are refused before anything large is read; stale temp files removed."""
from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np
import pytest

import ros_helpers as rh
from css_ros.engine.gaussians import GaussianModel
from css_ros.engine.semantic_map import SemanticMap
from css_ros.errors import MapError, ModelError
from css_ros.ros.params import NodeParams
from css_ros.ros.startup import load_engine, remove_stale_temp_files


@pytest.fixture(scope="module")
def model_path(tmp_path_factory) -> Path:
    return rh.write_wall_model(tmp_path_factory.mktemp("m") / "wall.ply")


@pytest.fixture(scope="module")
def model(model_path) -> GaussianModel:
    return GaussianModel.from_ply(model_path)


def members(model: GaussianModel, **over) -> dict:
    m = dict(format_version=np.int64(1), concentrations=np.full((model.num_gaussians, 4), 2.0),
             prior=np.float64(1e-3), background=np.float64(1e-3), num_classes=np.int64(4),
             num_gaussians=np.int64(model.num_gaussians), model_fingerprint=np.array(model.fingerprint),
             frames_observed=np.int64(3))
    m.update(over)
    return m


def write(path: Path, m: dict, compress: bool = False) -> Path:
    (np.savez_compressed if compress else np.savez)(path, **m)
    return path


def test_valid_file_loads(model, tmp_path):
    smap = SemanticMap.load(write(tmp_path / "ok.npz", members(model)), model, expected_classes=4)
    assert smap.frames_observed == 3 and smap.concentrations.max() == 2.0


@pytest.mark.parametrize("case, match", [
    ("format_version shape (2,)", "format_version has shape"),
    ("prior shape (3,)", "prior has shape"),
    ("complex concentrations", "dtype complex"),
    ("bool concentrations", "dtype bool"),
    ("1e308 concentrations", "invalid concentrations"),
    ("1e308 prior", r"prior=1e\+308 outside"),
    ("frames_observed -5", "frames_observed=-5"),
    ("other class count", "has 5 classes, expected 4"),
    ("string prior", "prior has dtype"),
])
def test_crafted_members_refused(model, tmp_path, case, match):
    G = model.num_gaussians
    over = {
        "format_version shape (2,)": dict(format_version=np.array([1, 1])),
        "prior shape (3,)": dict(prior=np.full(3, 1e-3)),
        "complex concentrations": dict(concentrations=np.full((G, 4), 2.0 + 0j)),
        "bool concentrations": dict(concentrations=np.ones((G, 4), bool)),
        "1e308 concentrations": dict(concentrations=np.full((G, 4), 1e308)),
        "1e308 prior": dict(prior=np.float64(1e308)),
        "frames_observed -5": dict(frames_observed=np.int64(-5)),
        "other class count": dict(concentrations=np.full((G, 5), 2.0), num_classes=np.int64(5)),
        "string prior": dict(prior=np.array("0.001")),
    }[case]
    with pytest.raises(MapError, match=match):
        SemanticMap.load(write(tmp_path / "bad.npz", members(model, **over)), model, expected_classes=4)


def test_plain_npy_refused(model, tmp_path):
    np.save(tmp_path / "plain.npy", np.zeros(3))
    with pytest.raises(MapError, match="not an .npz archive"):
        SemanticMap.load(tmp_path / "plain.npy", model)


def _npy_header(shape: tuple, dtype: str = "<f8") -> bytes:
    buf = io.BytesIO()
    from numpy.lib import format as npformat
    npformat.write_array_header_1_0(buf, {"descr": dtype, "fortran_order": False, "shape": shape})
    return buf.getvalue()


def test_header_declaring_huge_array_refused_before_reading(model, tmp_path):
    path = write(tmp_path / "huge.npz", members(model))
    # Replace the concentrations member with a header declaring 10^12 values over 16 bytes of data.
    with zipfile.ZipFile(path) as zf:
        items = {i.filename: zf.read(i) for i in zf.infolist() if i.filename != "concentrations.npy"}
    with zipfile.ZipFile(path, "w") as zf:
        for name, data in items.items():
            zf.writestr(name, data)
        zf.writestr("concentrations.npy", _npy_header((model.num_gaussians, 10**9)) + b"\0" * 16)
    with pytest.raises(MapError, match=r"concentrations holds 144 bytes, its header declares 2560000000128"):
        SemanticMap.load(path, model)


def test_decompression_bomb_refused_before_inflating(model, tmp_path):
    path = write(tmp_path / "bomb.npz", members(model))
    with zipfile.ZipFile(path) as zf:
        items = {i.filename: zf.read(i) for i in zf.infolist() if i.filename != "concentrations.npy"}
    bomb = _npy_header((model.num_gaussians, 4)) + b"\0" * (200 * 2**20)  # 200 MB of zeros, ~200 kB deflated
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, data in items.items():
            zf.writestr(name, data)
        zf.writestr("concentrations.npy", bomb)
    assert path.stat().st_size < 2 * 2**20
    with pytest.raises(MapError, match="holds 209715.* bytes, its header declares"):
        SemanticMap.load(path, model)


def test_ply_with_log_scale_100_refused(tmp_path):
    m = GaussianModel.from_ply(rh.write_wall_model(tmp_path / "w.ply"))
    log_scales = m.log_scales.copy()
    log_scales[0, 0] = 100.0  # sigma = e^100 m: inf in float32
    object.__setattr__(m, "log_scales", log_scales)
    m.to_ply(tmp_path / "bad.ply")
    with pytest.raises(ModelError, match="log_scales: 1 value.* above 20"):
        GaussianModel.from_ply(tmp_path / "bad.ply")


def test_node_start_up_renames_crafted_checkpoint_aside_and_starts_fresh(model, model_path, tmp_path):
    ckpt = write(tmp_path / "map.npz", members(model, frames_observed=np.int64(-5)))
    original = ckpt.read_bytes()
    warnings: list[str] = []
    p = NodeParams(model_path=str(model_path), class_file="", num_classes=4, checkpoint_path=str(ckpt))
    engine = load_engine(p, lambda s: None, warnings.append)
    assert "checkpoint refused" in engine.resume_status and "frames_observed=-5" in warnings[0]
    assert np.all(engine.smap.concentrations == p.prior) and not ckpt.exists()
    (aside,) = [q for q in tmp_path.iterdir() if q.name.startswith("map.npz.rejected-")]
    assert aside.read_bytes() == original


def test_stale_temp_files_removed_at_start(model, model_path, tmp_path):
    ckpt = tmp_path / "map.npz"
    stale = [tmp_path / ".map.npz.abc123.tmp", tmp_path / ".map.npz.x.tmp"]
    for s in stale:
        s.write_bytes(b"partial")
    other = tmp_path / ".other.npz.abc.tmp"
    other.write_bytes(b"keep")
    infos: list[str] = []
    p = NodeParams(model_path=str(model_path), class_file="", num_classes=4, checkpoint_path=str(ckpt))
    load_engine(p, infos.append, lambda s: None)
    assert not any(s.exists() for s in stale) and other.exists()
    assert "removed 2 temporary file(s)" in infos[0]
    assert remove_stale_temp_files(ckpt) == []


def test_default_checkpoint_path_differs_per_model(tmp_path, monkeypatch):
    monkeypatch.setenv("HOME", str(tmp_path))
    a = rh.write_wall_model(tmp_path / "a.ply", seed=0)
    b = rh.write_wall_model(tmp_path / "b.ply", seed=1)
    pa = load_engine(NodeParams(model_path=str(a), class_file="", num_classes=4), print, print).checkpoint_path
    pb = load_engine(NodeParams(model_path=str(b), class_file="", num_classes=4), print, print).checkpoint_path
    assert pa != pb and pa.parent == pb.parent == tmp_path / ".ros" / "css_ros" / "maps"
    assert pa.name == GaussianModel.from_ply(a).fingerprint[:16] + ".npz"


def _corrupt_deflate_stream(path: Path, member: str = "concentrations.npy", how: str = "block type") -> Path:
    """Damage the deflate stream of ``member`` in place: its first byte 0x07 (an invalid block type) or a
    run of 0xff bytes inside it (the zip headers and the declared sizes stay intact)."""
    raw = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo(member)
    name_len, extra_len = int.from_bytes(raw[info.header_offset + 26:info.header_offset + 28], "little"), \
        int.from_bytes(raw[info.header_offset + 28:info.header_offset + 30], "little")
    start = info.header_offset + 30 + name_len + extra_len
    if how == "block type":
        raw[start] = 0x07
    else:
        mid = start + info.compress_size // 2
        raw[mid:mid + 64] = b"\xff" * 64
    path.write_bytes(bytes(raw))
    return path


@pytest.mark.parametrize("how", ["block type", "0xff run"])
def test_corrupt_compressed_checkpoint_is_a_map_error_naming_the_file(model, tmp_path, how):
    rng = np.random.default_rng(0)
    path = write(tmp_path / "z.npz", members(model, concentrations=rng.uniform(1, 2, (model.num_gaussians, 4))),
                 compress=True)
    _corrupt_deflate_stream(path, how=how)
    with pytest.raises(MapError, match=f"cannot read map file {path}"):
        SemanticMap.load(path, model, expected_classes=4)
    with pytest.raises(MapError, match=str(path)):
        SemanticMap.load(path, model)


def test_corrupt_compressed_checkpoint_at_start_is_renamed_aside(model, model_path, tmp_path):
    ckpt = write(tmp_path / "map.npz", members(model), compress=True)
    _corrupt_deflate_stream(ckpt)
    warnings: list[str] = []
    p = NodeParams(model_path=str(model_path), class_file="", num_classes=4, checkpoint_path=str(ckpt))
    engine = load_engine(p, lambda s: None, warnings.append)
    assert "checkpoint refused" in engine.resume_status and str(ckpt) in warnings[0]
    assert not ckpt.exists() and [q for q in tmp_path.iterdir() if q.name.startswith("map.npz.rejected-")]
    assert np.all(engine.smap.concentrations == p.prior)


def _bomb(model: GaussianModel, path: Path, classes_declared: int, file_classes: int) -> Path:
    """A deflated map whose concentrations header declares (N, classes_declared) float64 of zeros (all
    sizes consistent, so only the class count can tell), while the file records ``file_classes``."""
    write(path, members(model, num_classes=np.int64(file_classes)))
    with zipfile.ZipFile(path) as zf:
        items = {i.filename: zf.read(i) for i in zf.infolist() if i.filename != "concentrations.npy"}
    shape = (model.num_gaussians, classes_declared)
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, data in items.items():
            zf.writestr(name, data)
        with zf.open("concentrations.npy", "w", force_zip64=True) as fh:
            fh.write(_npy_header(shape))
            zeros = b"\0" * 2**22
            left = shape[0] * shape[1] * 8
            while left > 0:
                fh.write(zeros[:min(left, len(zeros))])
                left -= len(zeros)
    return path


def test_decompression_bomb_refused_from_the_files_own_class_count(model, tmp_path, monkeypatch):
    # 400 MB declared and truly present (deflated to well under 1 MB); the file says 4 classes.
    classes = (400 * 2**20) // (8 * model.num_gaussians)
    path = _bomb(model, tmp_path / "bomb.npz", classes, 4)
    assert path.stat().st_size < 2**20
    # Refused from the headers: the concentrations are never inflated (np.load is never asked for them).
    real_load = np.load

    class Guard:
        def __init__(self, data):
            self.data = data

        def __enter__(self):
            return self

        def __exit__(self, *a):
            self.data.close()

        def __getitem__(self, key):
            assert key != "concentrations", "the bomb was decompressed"
            return self.data[key]

        @property
        def files(self):
            return self.data.files

    monkeypatch.setattr(np, "load", lambda *a, **k: Guard(real_load(*a, **k)))
    with pytest.raises(MapError, match=rf"concentrations have shape \({model.num_gaussians}, {classes}\).*"
                                       rf"num_classes .*\({model.num_gaussians}, 4\)"):
        SemanticMap.load(path, model)


def test_another_models_map_is_refused_by_fingerprint_not_by_shape(model, tmp_path):
    other = GaussianModel.from_ply(rh.write_wall_model(tmp_path / "other.ply", seed=3, depth=4.0))
    path = SemanticMap(other, 4).save(tmp_path / "other_map.npz")
    with pytest.raises(MapError, match=rf"this map belongs to model {other.fingerprint[:16]}, not .*wall.ply"):
        SemanticMap.load(path, model)


def test_checkpoint_fingerprint_reads_the_headers_only_and_refuses_what_is_no_map(tmp_path):
    """The model-watch start (newest_watched_model) reads a checkpoint's fingerprint through the map file module:
    headers and scalars only, None for anything that is no map file."""
    from css_ros.engine.map_file import check_map_headers
    from css_ros.ros.startup import checkpoint_fingerprint

    model = GaussianModel.from_ply(rh.write_wall_model(tmp_path / "wall.ply"))
    path = SemanticMap(model, 4).save(tmp_path / "map.npz")
    header = check_map_headers(path)
    assert (header.num_gaussians, header.num_classes, header.fingerprint) == (model.num_gaussians, 4, model.fingerprint)
    assert checkpoint_fingerprint(path) == model.fingerprint
    (tmp_path / "text.npz").write_text("not a map")
    with zipfile.ZipFile(tmp_path / "other.npz", "w") as zf:   # a zip without the map's members
        zf.writestr("model_fingerprint.npy", b"")
    for bad in ("missing.npz", "text.npz", "other.npz"):
        assert checkpoint_fingerprint(tmp_path / bad) is None
