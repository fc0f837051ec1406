"""Write a semantic map's viewer files in one call: used by ``css_export`` and by ``css_replay``."""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Literal, Sequence

from .colormap import class_colors, uncertainty_colors, write_colorbar
from .plys import write_point_cloud, write_semantic_splat, write_uncertainty_splat

if TYPE_CHECKING:
    from ..engine.classes import ClassSet
    from ..engine.semantic_map import SemanticMap
    from ..engine.similarity import Similarity

#: The files css_export can write (see :func:`export_map`).
FORMATS = ("semantic", "uncertainty", "points")


def export_map(smap: "SemanticMap", classes: "ClassSet", out: Path, stem: str, formats: Sequence[str] = FORMATS,
               uncertainty: Literal["variance", "evidence"] = "variance", cmap: str | None = None,
               min_evidence: float | None = None, drop_unobserved: bool = False,
               splat_to_map: "Similarity | None" = None) -> list[Path]:
    """Write the chosen viewer files of ``smap`` into ``out``; return the paths written.

    - ``semantic``: ``<stem>_semantic.ply``, the splat coloured by class (unobserved: grey, label 255);
    - ``uncertainty``: ``<stem>_uncertainty_<quantity>.ply`` coloured by the label's variance or the
      evidence through a colour map, and ``..._colorbar.png`` beside it;
    - ``points``: ``<stem>_points.ply``, x y z rgb label expectation variance for point-cloud tools.

    With ``splat_to_map`` the files are written in the map frame (the splat moved by the similarity, see
    :meth:`~css_ros.engine.similarity.Similarity.transform_model`).
    """
    sem = smap.gaussian_semantics() if min_evidence is None else smap.gaussian_semantics(min_evidence)
    model = smap.model
    if splat_to_map is not None and not splat_to_map.is_identity:
        model = splat_to_map.transform_model(model)
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    if "semantic" in formats or "points" in formats:
        rgb = class_colors(sem.label, classes, smap.ignore_label)
        if "semantic" in formats:
            written.append(write_semantic_splat(out / f"{stem}_semantic.ply", model, sem, rgb, drop_unobserved))
        if "points" in formats:
            written.append(write_point_cloud(out / f"{stem}_points.ply", model, sem, rgb, drop_unobserved))
    if "uncertainty" in formats:
        values = sem.variance if uncertainty == "variance" else sem.evidence
        colors = uncertainty_colors(values, uncertainty, mask=sem.observed, cmap=cmap)
        base = out / f"{stem}_uncertainty_{uncertainty}"
        written.append(write_uncertainty_splat(base.with_suffix(".ply"), model, sem, colors.rgb, drop_unobserved))
        bar = base.parent / f"{base.name}_colorbar.png"
        write_colorbar(bar, colors)
        written.append(bar)
    return written
