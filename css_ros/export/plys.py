"""PLY writers of the semantic map in 3D: viewer-ready splats and a plain point cloud (map frame, metres).

* :func:`write_semantic_splat` — the model with each Gaussian's colour replaced by its class colour
  (any 3DGS viewer then shows the semantic map) and the per-Gaussian fields ``class_id``,
  ``expectation``, ``variance``, ``evidence``.
* :func:`write_uncertainty_splat` — the same, coloured by an uncertainty quantity.
* :func:`write_point_cloud` — ``x y z red green blue label expectation variance`` per Gaussian
  centre, for CloudCompare / Open3D.

Colours are written as the SH DC term, f_dc = (rgb − 0.5) / SH_C0 (rgb in [0, 1]), with every
higher-order coefficient ``f_rest_*`` zeroed, so a viewer's colour 0.5 + SH_C0 · f_dc is the class
colour from every direction. Unobserved Gaussians carry ``ignore_label`` and grey, or are dropped.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..engine.field3d import GaussianSemantics
from ..engine.gaussians import GaussianModel
from ..engine.sh import SH_C0
from ..errors import MapError
from .files import atomic_binary


def semantic_splat_model(model: GaussianModel, rgb: np.ndarray) -> GaussianModel:
    """A copy of ``model`` whose view-independent colour is ``rgb`` ((N, 3) uint8): f_dc = (rgb/255 − 0.5)/SH_C0,
    f_rest = 0 (the SH degree and all geometry are kept)."""
    rgb = np.asarray(rgb)
    if rgb.shape != (model.num_gaussians, 3):
        raise MapError(f"colours have shape {rgb.shape}, expected ({model.num_gaussians}, 3)")
    sh = np.zeros_like(model.sh)
    sh[:, 0, :] = (rgb.astype(np.float64) / 255.0 - 0.5) / SH_C0
    return GaussianModel(means=model.means, sh=sh, opacity_logits=model.opacity_logits,
                         log_scales=model.log_scales, rotations=model.rotations, normals=model.normals)


def _select(model: GaussianModel, sem: GaussianSemantics, rgb: np.ndarray,
            drop_unobserved: bool) -> tuple[GaussianModel, np.ndarray, dict[str, np.ndarray]]:
    keep = sem.observed if drop_unobserved else np.ones(model.num_gaussians, dtype=bool)
    if not np.any(keep):
        raise MapError("nothing to export: no Gaussian is observed (lower --min-evidence, or keep unobserved ones)")
    fields = {
        "class_id": sem.label[keep].astype(np.int32),
        "expectation": sem.expectation[keep].astype(np.float32),
        "variance": sem.variance[keep].astype(np.float32),
        "evidence": sem.evidence[keep].astype(np.float32),
    }
    sub = model if keep.all() else model.select(keep)
    return sub, np.asarray(rgb)[keep], fields


def write_semantic_splat(path: str | os.PathLike[str], model: GaussianModel, sem: GaussianSemantics,
                         rgb: np.ndarray, drop_unobserved: bool = False) -> Path:
    """Write the splat coloured by ``rgb`` ((N, 3) uint8, e.g. class colours) with the per-Gaussian
    fields ``class_id`` (int32, ignore_label if unobserved), ``expectation``, ``variance`` and
    ``evidence`` (float32, S_n − C α_0) appended; atomically. Returns the path.

    Raises:
        MapError: colours of the wrong shape, or nothing left to write.
    """
    sub, colors, fields = _select(model, sem, rgb, drop_unobserved)
    semantic_splat_model(sub, colors).to_ply(path, extra_fields=fields)
    return Path(path)


def write_uncertainty_splat(path: str | os.PathLike[str], model: GaussianModel, sem: GaussianSemantics,
                            rgb: np.ndarray, drop_unobserved: bool = False) -> Path:
    """Same layout as :func:`write_semantic_splat`, with ``rgb`` the uncertainty colours."""
    return write_semantic_splat(path, model, sem, rgb, drop_unobserved)


def write_point_cloud(path: str | os.PathLike[str], model: GaussianModel, sem: GaussianSemantics,
                      rgb: np.ndarray, drop_unobserved: bool = False) -> Path:
    """Write one point per Gaussian centre: ``x y z`` (float32, map frame, m), ``red green blue``
    (uint8), ``label`` (int32), ``expectation``, ``variance`` (float32); binary little endian,
    atomically. An empty cloud (all dropped) is written as a valid PLY with zero vertices."""
    from plyfile import PlyData, PlyElement

    keep = sem.observed if drop_unobserved else np.ones(model.num_gaussians, dtype=bool)
    rgb = np.asarray(rgb)
    rec = np.empty(int(np.count_nonzero(keep)), dtype=[
        ("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1"),
        ("label", "<i4"), ("expectation", "<f4"), ("variance", "<f4")])
    for j, axis in enumerate("xyz"):
        rec[axis] = model.means[keep, j]
    for j, channel in enumerate(("red", "green", "blue")):
        rec[channel] = rgb[keep, j]
    rec["label"] = sem.label[keep]
    rec["expectation"] = sem.expectation[keep]
    rec["variance"] = sem.variance[keep]
    ply = PlyData([PlyElement.describe(rec, "vertex")], byte_order="<")
    with atomic_binary(path) as fh:
        ply.write(fh)
    return Path(path)
