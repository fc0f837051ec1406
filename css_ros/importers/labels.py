"""Per-image label, ground-truth, confidence and colour images from folders, matched to views by file stem.

Label / GT images (PNG):
    * 8-bit grey (``L``), 16-bit grey (``I;16``) or palette (``P``: the palette index is the class id)
      PNGs hold class ids directly;
    * RGB / RGBA PNGs hold colours: each colour is mapped to the class with that colour in the class
      file. A colour that is no class colour is an error (``unknown_colors="error"``) or becomes
      ``ignore_label`` (``unknown_colors="ignore"``, counted).
    An optional remap (YAML ``remap: {source id: target id}``) is then applied to the ids (ids not
    listed are kept), e.g. to move a dataset's "unlabelled" 0 to the ignore label 255.
Confidence images: ``<stem>.npy`` holding a (H, W) float32/float64 array in [0, 1] (read with
    ``allow_pickle=False``), or a grey PNG scaled to [0, 1] (8-bit / 255, 16-bit / 65535).
Colour images: any format Pillow reads, converted to RGB.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Sequence

import numpy as np
import yaml

from .views import ImportFormatError

LABEL_EXTENSIONS = (".png",)
CONFIDENCE_EXTENSIONS = (".npy", ".png")
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
#: Largest accepted image [pixels] (a 16k x 16k image; guards against decompression bombs).
MAX_PIXELS = 16384 * 16384


def index_folder(folder: str | Path, extensions: Sequence[str], what: str) -> dict[str, Path]:
    """stem -> file of ``folder`` with one of ``extensions`` (earlier extensions win).

    Raises:
        ImportFormatError: the folder does not exist.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ImportFormatError(f"{what} folder not found: {folder}")
    out: dict[str, Path] = {}
    for ext in reversed(extensions):
        for p in sorted(folder.glob(f"*{ext}")):
            out[p.stem] = p
    return out


def _open_image(path: Path):  # noqa: ANN202 - PIL.Image.Image
    from PIL import Image

    try:
        img = Image.open(path)
        if img.width * img.height > MAX_PIXELS:
            raise ImportFormatError(f"{path}: {img.width}x{img.height} is larger than {MAX_PIXELS} pixels")
        img.load()
        return img
    except (OSError, ValueError, Image.DecompressionBombError) as exc:
        raise ImportFormatError(f"cannot read image {path}: {exc}") from None


def read_rgb(path: str | Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB image."""
    return np.asarray(_open_image(Path(path)).convert("RGB"), dtype=np.uint8)


def load_remap(path: str | Path) -> dict[int, int]:
    """``remap: {source id: target id}`` from a YAML file (ids are integers >= 0).

    Raises:
        ImportFormatError: unreadable file or non-integer / negative ids.
    """
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ImportFormatError(f"cannot read remap file {path}: {exc}") from None
    table = data.get("remap") if isinstance(data, dict) else None
    if not isinstance(table, dict) or not table:
        raise ImportFormatError(f"remap file {path}: expected a non-empty 'remap: {{source id: target id}}' mapping")
    out = {}
    for k, v in table.items():
        if not (isinstance(k, int) and isinstance(v, int)) or isinstance(k, bool) or isinstance(v, bool) \
                or k < 0 or v < 0 or k > 65535 or v > 65535:
            raise ImportFormatError(f"remap file {path}: '{k}: {v}' is not a pair of ids in 0..65535")
        out[k] = v
    return out


@dataclass
class LabelDecoder:
    """Turns label PNGs into (H, W) uint16 class ids.

    Attributes:
        palette: (C, 3) uint8 class colours (row c = colour of class c) used for RGB PNGs, or None.
        remap: {source id: target id} applied after decoding (ids not listed are kept).
        ignore_label: id given to unknown colours when ``unknown_colors == "ignore"``.
        unknown_colors: "error" or "ignore".
        unknown_color_pixels: pixels of unknown colour seen so far (with ``unknown_colors == "ignore"``).
    """

    palette: np.ndarray | None = None
    remap: dict[int, int] = field(default_factory=dict)
    ignore_label: int = 255
    unknown_colors: Literal["error", "ignore"] = "error"
    unknown_color_pixels: int = 0

    def __post_init__(self) -> None:
        self._lut = None
        if self.remap:
            self._lut = np.arange(65536, dtype=np.uint16)
            for k, v in self.remap.items():
                self._lut[k] = v
        self._colour_ids: dict[int, int] = {}
        if self.palette is not None:
            pal = np.asarray(self.palette, dtype=np.int64).reshape(-1, 3)
            keys = (pal[:, 0] << 16) | (pal[:, 1] << 8) | pal[:, 2]
            for c, key in enumerate(keys.tolist()):
                self._colour_ids.setdefault(int(key), c)  # first class wins on duplicate colours

    def read(self, path: str | Path) -> np.ndarray:
        """(H, W) uint16 class ids of the label PNG at ``path`` (after colour mapping and remap)."""
        path = Path(path)
        img = _open_image(path)
        if img.mode in ("L", "P", "I;16", "I;16B", "I;16L", "I"):
            ids = np.asarray(img, dtype=np.int64)  # P: the palette index is the id
            if ids.min(initial=0) < 0 or ids.max(initial=0) > 65535:
                raise ImportFormatError(f"{path}: label ids must be in 0..65535")
            ids = ids.astype(np.uint16)
        elif img.mode in ("RGB", "RGBA"):
            ids = self._from_colours(np.asarray(img.convert("RGB"), dtype=np.int64), path)
        else:
            raise ImportFormatError(f"{path}: PNG mode {img.mode} is not a label image "
                                    "(use 8/16-bit grey ids or RGB class colours)")
        return self._lut[ids] if self._lut is not None else ids

    def _from_colours(self, rgb: np.ndarray, path: Path) -> np.ndarray:
        if self.palette is None:
            raise ImportFormatError(f"{path}: colour label PNG but no class file with colours (pass --classes)")
        keys = (rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2]
        uniq, inverse = np.unique(keys, return_inverse=True)
        ids_of_uniq = np.array([self._colour_ids.get(int(k), -1) for k in uniq], dtype=np.int64)
        unknown = ids_of_uniq < 0
        if unknown.any():
            if self.unknown_colors == "error":
                shown = ", ".join(f"({k >> 16}, {(k >> 8) & 255}, {k & 255})" for k in uniq[unknown][:5].tolist())
                raise ImportFormatError(
                    f"{path}: {int(unknown.sum())} colour(s) are no class colour of the class file, e.g. {shown} "
                    "(pass --unknown-colors ignore to map them to the ignore label)")
            self.unknown_color_pixels += int(np.isin(inverse, np.flatnonzero(unknown)).sum())
            ids_of_uniq[unknown] = self.ignore_label
        return ids_of_uniq[inverse.reshape(keys.shape)].astype(np.uint16)


def read_confidence(path: str | Path) -> np.ndarray:
    """(H, W) float32 confidence in [0, 1] from ``.npy`` (float array, no pickle) or a grey PNG (scaled).

    Raises:
        ImportFormatError: wrong dtype / shape, values outside [0, 1] (npy) or an unsupported PNG mode.
    """
    path = Path(path)
    if path.suffix == ".npy":
        try:
            arr = np.load(path, allow_pickle=False, mmap_mode="r")
        except (OSError, ValueError) as exc:
            raise ImportFormatError(f"cannot read confidence {path}: {exc}") from None
        if arr.dtype not in (np.float32, np.float64) or arr.ndim != 2:
            raise ImportFormatError(f"{path}: confidence must be a 2-D float32/float64 array, got "
                                    f"{arr.dtype} {arr.shape}")
        conf = np.asarray(arr, dtype=np.float32)
        finite = conf[np.isfinite(conf)]
        if finite.size and (finite.min() < 0.0 or finite.max() > 1.0):
            raise ImportFormatError(f"{path}: confidence values must lie in [0, 1] "
                                    f"(found {finite.min():g}..{finite.max():g})")
        return conf
    img = _open_image(path)
    if img.mode == "L":
        return np.asarray(img, dtype=np.float32) / 255.0
    if img.mode in ("I;16", "I;16B", "I;16L", "I"):
        arr = np.asarray(img, dtype=np.float64)
        if arr.min(initial=0) < 0 or arr.max(initial=0) > 65535:
            raise ImportFormatError(f"{path}: 16-bit confidence values must be in 0..65535")
        return (arr / 65535.0).astype(np.float32)
    raise ImportFormatError(f"{path}: confidence PNG must be 8- or 16-bit grey, got mode {img.mode}")
