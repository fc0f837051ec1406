"""What the viewer shows of a map: per-Gaussian geometry and SPEC §9 semantics, and the informative subset.

All arrays are per displayed Gaussian, in the map frame (metres): the splat moved by ``splat_to_map`` (the
node's parameter of that name) when one is given, else the splat's own frame.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..engine.classes import ClassSet
from ..engine.field3d import GaussianSemantics
from ..engine.semantic_map import SemanticMap
from ..engine.similarity import Similarity
from ..engine.spec import DEFAULT_MIN_EVIDENCE
from ..errors import CssError


@dataclass
class ViewData:
    """Everything the page draws.

    Attributes:
        index: (M,) int64 indices of the displayed Gaussians in the model (M <= N).
        centers: (M, 3) float32 means [m]; covariances: (M, 3, 3) float32 [m^2].
        rgb: (M, 3) float32 degree-0 colour in [0, 1]; opacity: (M,) float32 in (0, 1).
        classes: names and palette of the C classes.
        semantics: SPEC §9 per-Gaussian label / E / Var / evidence / observed of the displayed Gaussians.
        num_gaussians: N, the model's size.
        trajectory: list of (T_map_cam (4, 4), fov_y [rad], aspect, u_var or NaN) of observed frames.
    """

    index: np.ndarray
    centers: np.ndarray
    covariances: np.ndarray
    rgb: np.ndarray
    opacity: np.ndarray
    classes: ClassSet
    semantics: GaussianSemantics
    num_gaussians: int
    trajectory: list = field(default_factory=list)


def informative_order(semantics: GaussianSemantics, opacity: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """Indices of Gaussians from most to least informative: observed ones first, by evidence S_n − Cα₀
    (how much the map knows there), then the rest by visual weight (opacity × largest standard deviation)."""
    weight = opacity.astype(np.float64) * scales.max(axis=1).astype(np.float64)
    # lexsort: last key is primary
    return np.lexsort((-weight, -semantics.evidence, ~semantics.observed))


def subset_semantics(sem: GaussianSemantics, index: np.ndarray) -> GaussianSemantics:
    """The rows ``index`` of ``sem``."""
    return GaussianSemantics(sem.label[index], sem.expectation[index], sem.variance[index], sem.total[index],
                             sem.evidence[index], sem.observed[index])


def build_view_data(smap: SemanticMap, classes: ClassSet, max_gaussians: int | None = None,
                    min_evidence: float = DEFAULT_MIN_EVIDENCE, splat_to_map: Similarity | None = None) -> ViewData:
    """Per-Gaussian arrays of ``smap`` for the page, keeping the ``max_gaussians`` most informative ones;
    centres and covariances moved into the map frame by ``splat_to_map`` when given."""
    model = smap.model
    if classes.num_classes != smap.num_classes:
        raise CssError(f"the map has {smap.num_classes} classes but the class file has {classes.num_classes}")
    sem = smap.gaussian_semantics(min_evidence)
    opacity = model.opacities
    n = model.num_gaussians
    if max_gaussians is not None and 0 < max_gaussians < n:
        index = np.sort(informative_order(sem, opacity, model.scales)[:max_gaussians])
    else:
        index = np.arange(n)
    sub = model if len(index) == n else model.select(index)
    if splat_to_map is not None and not splat_to_map.is_identity:
        sub = splat_to_map.transform_model(sub)
    return ViewData(index=index, centers=sub.means.astype(np.float32),
                    covariances=sub.covariances().astype(np.float32), rgb=sub.base_colors,
                    opacity=sub.opacities, classes=classes,
                    semantics=sem if len(index) == n else subset_semantics(sem, index), num_gaussians=n)


def classes_for_map(smap: SemanticMap, class_file: Path | None) -> ClassSet:
    """The class file's classes, or anonymous ``class_i`` ones when none is given."""
    if class_file is None:
        return ClassSet.default(smap.num_classes)
    if not class_file.is_file():
        raise CssError(f"class file not found: {class_file}")
    return ClassSet.from_yaml(class_file)
