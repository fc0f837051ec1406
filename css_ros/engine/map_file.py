"""What a saved map file holds, read without its splat model (``css_map info``, merge checks).

Every member is checked from its npy header (dtype, shape, byte count) before any data is read; no
pickles (``allow_pickle=False``).
"""
from __future__ import annotations

import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import MapError
from .semantic_map import _check_map_headers

__all__ = ["MapInfo", "read_map_info"]

#: Largest byte count of the scalar ``num_gaussians`` member (read before the other headers are checked).
_SCALAR_MEMBER_MAX_BYTES = 1024


@dataclass(frozen=True)
class MapInfo:
    """Summary of one map file.

    Attributes:
        path: the file.
        fingerprint: SHA-256 of the splat model the map was made on (``GaussianModel.fingerprint``).
        num_gaussians: N.
        num_classes: C.
        prior: α_0 per class.
        background: α_b per class.
        frames_observed: frames fused into the map (summed over merged maps).
        sources: origin ids of the css_node sources whose evidence the map holds (sorted; may be empty).
        evidence_total: Σ_n Σ_c (α_n^c - α_0): the κ-weighted label count fused so far [pixels].
        evidence_per_class: (C,) float64 the same per class.
        observed_gaussians: Gaussians whose evidence S_n - C α_0 is > 0.
        evidence_max: largest per-Gaussian evidence S_n - C α_0.
        sensor_model: fingerprint of the sensor model the evidence was fused with ("" = the paper's update).
    """

    path: Path
    fingerprint: str
    num_gaussians: int
    num_classes: int
    prior: float
    background: float
    frames_observed: int
    sources: list[str]
    evidence_total: float
    evidence_per_class: np.ndarray = field(repr=False)
    observed_gaussians: int
    evidence_max: float
    sensor_model: str = ""


def _read_num_gaussians(path: Path) -> int:
    if not zipfile.is_zipfile(path):
        raise MapError(f"map file {path} is not an .npz archive")
    with zipfile.ZipFile(path) as zf:
        try:
            info = zf.getinfo("num_gaussians.npy")
        except KeyError:
            raise MapError(f"map file {path} lacks num_gaussians") from None
        if info.file_size > _SCALAR_MEMBER_MAX_BYTES:
            raise MapError(f"map file {path}: num_gaussians holds {info.file_size} bytes (a scalar expected)")
    with np.load(path, allow_pickle=False) as data:
        value = data["num_gaussians"]
    if value.shape != () or value.dtype.kind not in "iu" or int(value) < 1:
        raise MapError(f"map file {path}: num_gaussians is not a positive integer scalar")
    return int(value)


def read_map_info(path: str | os.PathLike[str]) -> MapInfo:
    """Read and check a map file written by :meth:`SemanticMap.save`, without its model.

    Raises:
        MapError: unreadable, corrupt or crafted file; invalid values.
    """
    path = Path(path)
    if path.is_dir():
        raise MapError(f"{path} is a folder, not a map file (a css_replay output folder holds map.npz)")
    if not path.is_file():
        raise MapError(f"map file not found: {path}")
    try:
        n = _read_num_gaussians(path)
        _check_map_headers(path, n)
        with np.load(path, allow_pickle=False) as data:
            fingerprint = str(data["model_fingerprint"])
            c = int(data["num_classes"])
            prior = float(data["prior"])
            background = float(data["background"])
            frames = int(data["frames_observed"]) if "frames_observed" in data.files else 0
            sources = sorted(str(v) for v in data["sources"]) if "sources" in data.files else []
            sensor_model = str(data["sensor_model"]) if "sensor_model" in data.files else ""
            conc = np.asarray(data["concentrations"], dtype=np.float64)
    except MapError:
        raise
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        raise MapError(f"cannot read map file {path}: {exc}") from exc
    if conc.shape != (n, c) or not np.all(np.isfinite(conc)) or np.any(conc <= 0):
        raise MapError(f"map file {path} holds invalid concentrations (shape {conc.shape}, expected ({n}, {c}), "
                       "all finite and > 0)")
    if not (np.isfinite(prior) and prior > 0 and np.isfinite(background) and background > 0):
        raise MapError(f"map file {path}: prior {prior!r} / background {background!r} not positive finite")
    evidence = conc - prior
    per_gaussian = evidence.sum(axis=1)
    return MapInfo(path=path, fingerprint=fingerprint, num_gaussians=n, num_classes=c, prior=prior,
                   background=background, frames_observed=frames, sources=sources,
                   evidence_total=float(per_gaussian.sum()), evidence_per_class=evidence.sum(axis=0),
                   observed_gaussians=int(np.count_nonzero(per_gaussian > 0)),
                   evidence_max=float(per_gaussian.max()), sensor_model=sensor_model)
