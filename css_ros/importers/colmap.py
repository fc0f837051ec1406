"""COLMAP sparse models (``cameras.txt``/``images.txt`` or ``cameras.bin``/``images.bin``).

``images`` hold the WORLD-TO-CAMERA transform of each image: ``qvec`` (w, x, y, z) and ``tvec`` with
``x_cam = R(qvec) x_world + tvec`` (OpenCV camera axes). The camera-to-world pose is its inverse:
``R_map_cam = R^T``, camera centre ``-R^T tvec``. COLMAP's pixel convention puts the centre of the
top-left pixel at (0.5, 0.5), so the principal point in SPEC §2's convention is ``(cx - 0.5, cy - 0.5)``.

Only PINHOLE and SIMPLE_PINHOLE cameras are modelled; models with distortion are refused unless
``ignore_distortion`` (then their focal length / principal point are used and the distortion dropped).
Binary files: counts declared in the file are checked against the file size before anything is read.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .views import ImportFormatError, PosedView, checked_K, make_pose, sorted_views

#: model id -> (name, number of parameters) as in COLMAP's src/colmap/sensor/models.h.
CAMERA_MODELS: dict[int, tuple[str, int]] = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5), 4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5), 8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12), 11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
}
MODEL_PARAMS = {name: n for name, n in CAMERA_MODELS.values()}
#: Models whose parameters start with a single focal length f, cx, cy (the others: fx, fy, cx, cy).
SINGLE_FOCAL = ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE")
PINHOLE = ("SIMPLE_PINHOLE", "PINHOLE")
_CAMERA_HEAD = struct.Struct("<iiQQ")       # camera_id, model_id, width, height
_IMAGE_HEAD = struct.Struct("<I4d3di")      # image_id, qvec (w, x, y, z), tvec, camera_id
_POINT2D_BYTES = 24                         # x, y (float64), point3D_id (int64)


@dataclass(frozen=True)
class ColmapCamera:
    """One COLMAP camera: model name, size [px], parameters as stored (COLMAP pixel convention)."""

    model: str
    width: int
    height: int
    params: tuple[float, ...]


def load_colmap(path: str | Path, ignore_distortion: bool = False) -> list[PosedView]:
    """Posed views of a COLMAP sparse model folder (``.../sparse/0``), text or binary, ordered by image name.

    Text files are used when ``cameras.txt`` and ``images.txt`` exist, else ``cameras.bin``/``images.bin``.

    Raises:
        ImportFormatError: missing / malformed files, unknown camera ids, distortion without ``ignore_distortion``.
    """
    path = Path(path)
    if not path.is_dir():
        raise ImportFormatError(f"COLMAP model folder not found: {path}")
    if (path / "cameras.txt").is_file() and (path / "images.txt").is_file():
        cameras, images = read_cameras_txt(path / "cameras.txt"), read_images_txt(path / "images.txt")
    elif (path / "cameras.bin").is_file() and (path / "images.bin").is_file():
        cameras, images = read_cameras_bin(path / "cameras.bin"), read_images_bin(path / "images.bin")
    else:
        raise ImportFormatError(f"{path}: no cameras.txt + images.txt nor cameras.bin + images.bin "
                                "(pass the sparse model folder, e.g. sparse/0)")
    views = []
    for name, qvec, tvec, cam_id in images:
        where = f"{path} image {name}"
        if cam_id not in cameras:
            raise ImportFormatError(f"{where}: camera id {cam_id} is not in the cameras file")
        views.append(_view(name, qvec, tvec, cameras[cam_id], where, ignore_distortion))
    if not views:
        raise ImportFormatError(f"{path}: the model holds no images")
    return sorted_views(views)


def _view(name: str, qvec: np.ndarray, tvec: np.ndarray, cam: ColmapCamera, where: str,
          ignore_distortion: bool) -> PosedView:
    if cam.model not in PINHOLE and not ignore_distortion:
        raise ImportFormatError(
            f"{where}: camera model {cam.model} has lens distortion; CSS needs undistorted pinhole images "
            "(run colmap image_undistorter, which writes PINHOLE cameras) or pass --ignore-distortion to use "
            "the pinhole part only")
    p = cam.params
    fx, fy, cx, cy = (p[0], p[0], p[1], p[2]) if cam.model in SINGLE_FOCAL else (p[0], p[1], p[2], p[3])
    K = checked_K(fx, fy, cx - 0.5, cy - 0.5, cam.width, cam.height, where)
    q = np.asarray(qvec, dtype=np.float64)
    norm = float(np.linalg.norm(q))
    if not np.isfinite(norm) or abs(norm - 1.0) > 1e-3:
        raise ImportFormatError(f"{where}: qvec {q.tolist()} is not a unit quaternion")
    R_cam_map = _qvec_to_matrix(q / norm)
    R_map_cam = R_cam_map.T
    T = make_pose(R_map_cam, -R_map_cam @ np.asarray(tvec, dtype=np.float64), where)
    return PosedView(name=name, K=K, width=cam.width, height=cam.height, T_map_cam=T)


def _qvec_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of a unit quaternion in COLMAP's (w, x, y, z) order."""
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


# ---------------------------------------------------------------------------------------------- text
def _data_lines(path: Path) -> list[str]:
    try:
        return path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise ImportFormatError(f"cannot read {path}: {exc}") from None


def read_cameras_txt(path: Path) -> dict[int, ColmapCamera]:
    """``CAMERA_ID MODEL WIDTH HEIGHT PARAMS...`` per line -> {camera id: camera}."""
    cams: dict[int, ColmapCamera] = {}
    for n, line in enumerate(_data_lines(path), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        try:
            cam_id, model, width, height = int(parts[0]), parts[1].upper(), int(parts[2]), int(parts[3])
            params = tuple(float(v) for v in parts[4:])
        except (IndexError, ValueError):
            raise ImportFormatError(f"{path}:{n}: expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...'") from None
        if model not in MODEL_PARAMS:
            raise ImportFormatError(f"{path}:{n}: unknown camera model {model}")
        if len(params) != MODEL_PARAMS[model]:
            raise ImportFormatError(f"{path}:{n}: {model} needs {MODEL_PARAMS[model]} parameters, got {len(params)}")
        cams[cam_id] = ColmapCamera(model, width, height, params)
    return cams


def read_images_txt(path: Path) -> list[tuple[str, np.ndarray, np.ndarray, int]]:
    """Two lines per image (``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME``, then its 2D points, possibly
    an empty line) -> [(name, qvec (4,), tvec (3,), camera id)]."""
    lines = _data_lines(path)
    out = []
    i = 0
    while i < len(lines):
        line = lines[i].strip()
        i += 1
        if not line or line.startswith("#"):
            continue
        parts = line.split(maxsplit=9)
        try:
            vals = [float(v) for v in parts[1:8]]
            cam_id, name = int(parts[8]), parts[9].strip()
        except (IndexError, ValueError):
            raise ImportFormatError(f"{path}:{i}: expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME'") from None
        out.append((name, np.array(vals[:4]), np.array(vals[4:7]), cam_id))
        i += 1  # the POINTS2D line of this image (may be empty)
    return out


# ---------------------------------------------------------------------------------------------- binary
def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as exc:
        raise ImportFormatError(f"cannot read {path}: {exc}") from None


def _truncated(path: Path, what: str) -> ImportFormatError:
    return ImportFormatError(f"{path}: truncated or corrupt ({what} runs past the end of the file)")


def read_cameras_bin(path: Path) -> dict[int, ColmapCamera]:
    """``cameras.bin`` -> {camera id: camera}; the declared count is checked against the file size first."""
    data = _read_bytes(path)
    if len(data) < 8:
        raise _truncated(path, "the camera count")
    (count,) = struct.unpack_from("<Q", data, 0)
    if count * (_CAMERA_HEAD.size + 8 * 3) > len(data) - 8:
        raise ImportFormatError(f"{path}: declares {count} cameras but holds only {len(data)} bytes")
    off, cams = 8, {}
    for _ in range(count):
        if off + _CAMERA_HEAD.size > len(data):
            raise _truncated(path, "a camera record")
        cam_id, model_id, width, height = _CAMERA_HEAD.unpack_from(data, off)
        off += _CAMERA_HEAD.size
        if model_id not in CAMERA_MODELS:
            raise ImportFormatError(f"{path}: camera {cam_id} has unknown model id {model_id}")
        model, n = CAMERA_MODELS[model_id]
        if off + 8 * n > len(data):
            raise _truncated(path, f"camera {cam_id}'s parameters")
        params = struct.unpack_from(f"<{n}d", data, off)
        off += 8 * n
        cams[cam_id] = ColmapCamera(model, int(width), int(height), tuple(float(v) for v in params))
    return cams


def read_images_bin(path: Path) -> list[tuple[str, np.ndarray, np.ndarray, int]]:
    """``images.bin`` -> [(name, qvec (4,), tvec (3,), camera id)]; declared counts are checked against the
    file size before reading (2D points are skipped, not read)."""
    data = _read_bytes(path)
    if len(data) < 8:
        raise _truncated(path, "the image count")
    (count,) = struct.unpack_from("<Q", data, 0)
    min_record = _IMAGE_HEAD.size + 1 + 8  # head, empty name + NUL, point count
    if count * min_record > len(data) - 8:
        raise ImportFormatError(f"{path}: declares {count} images but holds only {len(data)} bytes")
    off, out = 8, []
    for _ in range(count):
        if off + _IMAGE_HEAD.size > len(data):
            raise _truncated(path, "an image record")
        head = _IMAGE_HEAD.unpack_from(data, off)
        off += _IMAGE_HEAD.size
        end = data.find(b"\x00", off)
        if end < 0:
            raise _truncated(path, f"image {head[0]}'s name")
        try:
            name = data[off:end].decode("utf-8")
        except UnicodeDecodeError:
            raise ImportFormatError(f"{path}: image {head[0]} has a name that is not UTF-8") from None
        off = end + 1
        if off + 8 > len(data):
            raise _truncated(path, f"image {name}'s point count")
        (n_points,) = struct.unpack_from("<Q", data, off)
        off += 8
        if n_points * _POINT2D_BYTES > len(data) - off:
            raise ImportFormatError(f"{path}: image {name} declares {n_points} 2D points but only "
                                    f"{len(data) - off} bytes remain")
        off += n_points * _POINT2D_BYTES
        out.append((name, np.array(head[1:5], dtype=np.float64), np.array(head[5:8], dtype=np.float64), int(head[8])))
    return out
