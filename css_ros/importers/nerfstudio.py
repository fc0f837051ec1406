"""nerfstudio / instant-ngp ``transforms.json``.

Format: shared intrinsics at the top level (``fl_x fl_y cx cy w h`` and optionally ``camera_model``
and distortion ``k1 k2 k3 k4 p1 p2``), each of which a frame may override, and ``frames``: a list of
``{file_path, transform_matrix}``. ``transform_matrix`` is the (4, 4) camera-to-world pose of the
OpenGL/Blender camera (x right, y up, z backward); the OpenCV optical frame is obtained by flipping
its y and z axes: ``T_map_cam = transform_matrix @ diag(1, -1, -1, 1)``.

nerfstudio casts rays through pixel centres at ``pixel + 0.5`` (the centre of the top-left pixel is
(0.5, 0.5)), so the principal point in SPEC §2's convention is ``(cx - 0.5, cy - 0.5)``.

Distortion is not modelled by the CSS rasteriser: a non-pinhole ``camera_model`` or a non-zero
distortion coefficient is refused unless ``ignore_distortion`` (then the pinhole part is used).
The poses are used as written: if the splat was trained with nerfstudio's dataparser transform
(``dataparser_transforms.json``: orientation + scale), the model and the poses must be in one frame.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from .inria import _read_json
from .views import ImportFormatError, PosedView, checked_K, image_name, image_size, make_pose, sorted_views

#: OpenGL camera axes (x right, y up, z back) -> OpenCV optical axes (x right, y down, z forward).
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2")
PINHOLE_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE")  # nerfstudio writes OPENCV for a pinhole + k/p
REFUSED_MODELS = ("EQUIRECTANGULAR", "OMNIDIRECTIONALSTEREO_L", "OMNIDIRECTIONALSTEREO_R", "VR180_L", "VR180_R")
INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h")


def load_nerfstudio(path: str | Path, ignore_distortion: bool = False) -> list[PosedView]:
    """Posed views of a ``transforms.json`` (or of the folder holding it), ordered by image name.

    Raises:
        ImportFormatError: unreadable file, missing intrinsics, distortion without ``ignore_distortion``.
    """
    path = Path(path)
    if path.is_dir():
        path = path / "transforms.json"
    data = _read_json(path)
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list) or not data["frames"]:
        raise ImportFormatError(f"{path}: expected a JSON object with a non-empty 'frames' list (transforms.json)")
    views = []
    for i, frame in enumerate(data["frames"]):
        where = f"{path} frame {i}"
        if not isinstance(frame, dict):
            raise ImportFormatError(f"{where}: expected an object")
        merged = {**{k: v for k, v in data.items() if k != "frames"}, **frame}
        views.append(_view(merged, where, ignore_distortion))
    return sorted_views(views)


def _view(f: dict[str, Any], where: str, ignore_distortion: bool) -> PosedView:
    if "fl_x" in f and "fl_y" not in f:
        f = {**f, "fl_y": f["fl_x"]}
    missing = [k for k in (*INTRINSIC_KEYS, "file_path", "transform_matrix") if k not in f]
    if missing:
        raise ImportFormatError(f"{where}: missing {', '.join(missing)} (neither in the frame nor at the top level)")
    model = str(f.get("camera_model", "OPENCV")).upper()
    if model in REFUSED_MODELS:
        raise ImportFormatError(f"{where}: camera_model {model} is not a pinhole camera; CSS needs rectified "
                                "pinhole images")
    distortion = {k: float(f[k]) for k in DISTORTION_KEYS if k in f and float(f[k]) != 0.0}
    if (model not in PINHOLE_MODELS or distortion) and not ignore_distortion:
        detail = ", ".join(f"{k}={v:g}" for k, v in distortion.items())
        raise ImportFormatError(
            f"{where}: camera_model {model}" + (f" with distortion {detail}" if detail else "")
            + " is not an undistorted pinhole camera; undistort the images (e.g. colmap image_undistorter) "
              "or pass --ignore-distortion to use the pinhole part only")
    name = image_name(f["file_path"], "file_path", where)
    width, height = image_size(f["w"], "w", where), image_size(f["h"], "h", where)
    try:
        fx, fy, cx, cy = (float(f[k]) for k in ("fl_x", "fl_y", "cx", "cy"))
        M = np.asarray(f["transform_matrix"], dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as exc:
        raise ImportFormatError(f"{where}: bad intrinsics or transform_matrix ({exc})") from None
    K = checked_K(fx, fy, cx - 0.5, cy - 0.5, width, height, where)
    if M.shape == (3, 4):
        M = np.vstack([M, [0.0, 0.0, 0.0, 1.0]])
    if M.shape != (4, 4):
        raise ImportFormatError(f"{where}: transform_matrix must be 4x4 (or 3x4), got {M.shape}")
    T_cv = M @ GL_TO_CV
    T = make_pose(T_cv[:3, :3], T_cv[:3, 3], where)
    return PosedView(name=name, K=K, width=width, height=height, T_map_cam=T)
