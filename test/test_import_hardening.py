"""css_import refuses cameras the node would refuse, and leaves OUT complete or untouched (full disk, SIGTERM)."""
from __future__ import annotations

import json
import os
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from css_ros.importers.cli import main
from css_ros.io.frames import FrameRejected, INTRINSICS_BOUND, decode_camera_info
from test_importers import DEMO, _label_dir, synthetic_cameras, write_colmap_bin, write_inria, write_nerfstudio

MODEL = DEMO / "model.ply"
pytestmark = pytest.mark.skipif(not MODEL.is_file(), reason="demo model not available")


def _args(poses: Path, labels: Path, out: Path) -> list[str]:
    return [str(poses), "--model", str(MODEL), "--labels", str(labels), "--num-classes", "3", "--out", str(out),
            "--quiet"]


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("css_import: error: "), err
    return err


def _nerfstudio_text(tmp_path: Path, cams, **frame0) -> Path:
    """transforms.json with frame 0's keys overridden; values are raw JSON text (NaN, 1e999, null)."""
    path = tmp_path / "transforms.json"
    write_nerfstudio(path, cams)
    data = json.loads(path.read_text())
    for key in frame0:
        data["frames"][0][key] = f"@@{key}@@"
        data.pop(key, None)
    text = json.dumps(data)
    for key, raw in frame0.items():
        text = text.replace(f'"@@{key}@@"', raw)
    path.write_text(text)
    return path


@pytest.mark.parametrize("override, reason", [
    (dict(cx="NaN"), "non-finite"),
    (dict(cx="1e300"), "beyond 1e+07 px"),
    (dict(fl_x="1e300"), "beyond 1e+07 px"),
    (dict(fl_y="-5"), "focal lengths must be > 0"),
    (dict(w="1e999"), "w must be a positive integer number of pixels, got inf"),
    (dict(w="256.9"), "w must be a positive integer number of pixels, got 256.9"),
    (dict(h="0"), "h must be a positive integer"),
    (dict(w="5000", h="5000"), "image too large"),
    (dict(file_path="null"), "file_path must be a non-empty file name, got None"),
])
def test_nerfstudio_bad_cameras_refused_naming_the_file(tmp_path, capsys, override, reason):
    cams = synthetic_cameras(2)
    path = _nerfstudio_text(tmp_path, cams, **override)
    assert main(_args(path, _label_dir(tmp_path, cams), tmp_path / "out")) == 1
    err = _one_line(capsys)
    assert f"{path} frame 0" in err and reason in err, err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("key, raw, reason", [
    ("img_name", "null", "img_name must be a non-empty file name, got None"),
    ("width", "1e999", "width must be a positive integer number of pixels, got inf"),
    ("width", "64.5", "width must be a positive integer"),
    ("fx", "1e300", "beyond 1e+07 px"),
    ("fy", "Infinity", "non-finite"),
])
def test_inria_bad_cameras_refused_naming_the_file(tmp_path, capsys, key, raw, reason):
    cams = synthetic_cameras(2)
    path = tmp_path / "cameras.json"
    write_inria(path, cams)
    data = json.loads(path.read_text())
    data[0][key] = "@@"
    path.write_text(json.dumps(data).replace('"@@"', raw))
    assert main(_args(path, _label_dir(tmp_path, cams), tmp_path / "out")) == 1
    err = _one_line(capsys)
    assert f"{path} entry 0" in err and reason in err, err


def test_colmap_bin_inf_principal_point_refused(tmp_path, capsys):
    cams = synthetic_cameras(2)
    K = cams[0][1].copy()
    K[0, 2] = np.inf
    cams[0] = (cams[0][0], K, cams[0][2])
    write_colmap_bin(tmp_path / "sparse", cams)
    assert main(_args(tmp_path / "sparse", _label_dir(tmp_path, cams), tmp_path / "out")) == 1
    err = _one_line(capsys)
    assert str(tmp_path / "sparse") in err and "non-finite" in err


@pytest.mark.parametrize("fx", [1.0, 0.5 * INTRINSICS_BOUND, INTRINSICS_BOUND, 1.0001 * INTRINSICS_BOUND, 0.0])
def test_import_and_node_apply_the_same_camera_bounds(tmp_path, capsys, fx):
    """Whatever css_node's camera_info decoder accepts, css_import accepts, and vice versa."""
    cams = [(n, np.array([[fx, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]]), T) for n, _, T in synthetic_cameras(2)]
    write_colmap_bin(tmp_path / "sparse", cams)
    imported = main(_args(tmp_path / "sparse", _label_dir(tmp_path, cams), tmp_path / "out")) == 0
    capsys.readouterr()
    msg = SimpleNamespace(k=cams[0][1].ravel().tolist(), width=64, height=48)
    try:
        decode_camera_info(msg)
        node_accepts = True
    except FrameRejected:
        node_accepts = False
    assert imported == node_accepts == (0 < fx <= INTRINSICS_BOUND)


# ------------------------------------------------------------------ OUT complete or untouched
def _snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _import_subprocess(args: list[str], fsize: int | None = None, **kw) -> subprocess.Popen:
    def limit() -> None:
        if fsize is not None:  # a "disk" that takes at most fsize bytes per file: writes beyond fail (EFBIG)
            signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
            resource.setrlimit(resource.RLIMIT_FSIZE, (fsize, fsize))
    code = "import sys; from css_ros.importers.cli import main; sys.exit(main(sys.argv[1:]))"
    return subprocess.Popen([sys.executable, "-c", code, *args], preexec_fn=limit, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kw)


def test_full_disk_names_the_destination_and_leaves_out_as_it_was(tmp_path):
    cams = synthetic_cameras(4)
    write_colmap_bin(tmp_path / "sparse", cams)
    labels = _label_dir(tmp_path, cams)
    out = tmp_path / "out"
    assert main(_args(tmp_path / "sparse", labels, out)) == 0      # an earlier, complete import
    before = _snapshot(out)
    assert set(before) >= {"model.ply", "classes.yaml", "bag/metadata.yaml"}
    model_size = MODEL.stat().st_size
    # The second import (another class count) hits a per-file limit while copying the model.
    args = _args(tmp_path / "sparse", labels, out)
    args[args.index("--num-classes") + 1] = "4"
    proc = _import_subprocess(args, fsize=model_size // 2)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 1, err
    line = err.strip()
    assert line.count("\n") == 0 and f"writing the import into {out} failed: File too large" in line, line
    assert _snapshot(out) == before
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".out.")] == []
    # Into a new folder: it does not appear at all.
    proc = _import_subprocess(_args(tmp_path / "sparse", labels, tmp_path / "new"), fsize=model_size // 2)
    assert proc.wait(timeout=120) == 1 and not (tmp_path / "new").exists()
    # Without the limit the second import replaces the first one completely.
    assert main(args) == 0
    assert "class_3" in (out / "classes.yaml").read_text() and (out / "model.ply").stat().st_size == model_size


@pytest.mark.parametrize("sig, code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_sigterm_during_import_cleans_up_like_sigint(tmp_path, sig, code):
    cams = synthetic_cameras(6)
    write_colmap_bin(tmp_path / "sparse", cams)
    labels = _label_dir(tmp_path, cams)
    # Frame 3's label file is a FIFO: reading it blocks until the signal arrives (frames 0-2 are written).
    (labels / "frame_003.png").unlink()
    os.mkfifo(labels / "frame_003.png")
    proc = _import_subprocess(_args(tmp_path / "sparse", labels, tmp_path / "out"))
    try:
        deadline = time.monotonic() + 60
        while not any(tmp_path.glob(".out.css_import-*/bag/*.mcap")):
            assert proc.poll() is None and time.monotonic() < deadline, "the import did not reach frame 3"
            time.sleep(0.05)
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=30)
    finally:
        proc.kill()
    assert proc.returncode == code, err
    assert err.strip().splitlines()[-1] == ("css_import: terminated" if sig == signal.SIGTERM
                                             else "css_import: interrupted")
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob(".out.*"))
