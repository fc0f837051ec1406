"""INRIA 3DGS ``cameras.json`` (written by the reference trainer next to its ``point_cloud/``).

Format: a JSON list of ``{id, img_name, width, height, position, rotation, fx, fy}``:
``position`` is the camera centre in the world [model units], ``rotation`` the (3, 3) camera-to-world
rotation of the OpenCV camera (x right, y down, z forward), ``fx fy`` focal lengths [px]. The file
holds no principal point: the INRIA trainer renders a symmetric frustum, i.e. the principal point is
the image centre, which is ((W - 1) / 2, (H - 1) / 2) with pixel centres at integers (SPEC §2).
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from .views import ImportFormatError, PosedView, checked_K, image_name, image_size, make_pose, sorted_views

#: Largest cameras.json read [bytes] (a 10 000-camera file is about 5 MB).
MAX_FILE_BYTES = 512 * 1024 * 1024


def load_inria(path: str | Path) -> list[PosedView]:
    """Posed views of an INRIA ``cameras.json``, ordered by image name.

    Raises:
        ImportFormatError: unreadable file, missing keys, bad values (message names the entry).
    """
    path = Path(path)
    data = _read_json(path)
    if not isinstance(data, list) or not data:
        raise ImportFormatError(f"{path}: expected a non-empty JSON list of cameras (INRIA cameras.json)")
    views = []
    for i, cam in enumerate(data):
        where = f"{path} entry {i}"
        try:
            name = image_name(cam["img_name"], "img_name", where)
            width, height = image_size(cam["width"], "width", where), image_size(cam["height"], "height", where)
            fx, fy = float(cam["fx"]), float(cam["fy"])
            rotation, position = cam["rotation"], cam["position"]
        except (KeyError, TypeError, ValueError, OverflowError) as exc:
            raise ImportFormatError(f"{where}: needs img_name, width, height, fx, fy, position, rotation "
                                    f"({type(exc).__name__}: {exc})") from None
        K = checked_K(fx, fy, (width - 1) / 2.0, (height - 1) / 2.0, width, height, where)
        T = make_pose(_floats(rotation, where), _floats(position, where), where)
        views.append(PosedView(name=name, K=K, width=width, height=height, T_map_cam=T))
    return sorted_views(views)


def _floats(x: Any, where: str) -> np.ndarray:
    """float64 array of ``x`` (ImportFormatError naming ``where`` if it holds non-numbers)."""
    try:
        return np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise ImportFormatError(f"{where}: pose values must be numbers") from None


def _read_json(path: Path) -> Any:
    """Parsed JSON of ``path`` (size checked first)."""
    if not path.is_file():
        raise ImportFormatError(f"file not found: {path}")
    size = path.stat().st_size
    if size > MAX_FILE_BYTES:
        raise ImportFormatError(f"{path}: {size} bytes is larger than the {MAX_FILE_BYTES} accepted")
    try:
        return json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ImportFormatError(f"{path}: not valid JSON ({exc})") from None
