"""Merging maps of the same splat: Dirichlet evidence is additive (SPEC §4), so maps merge exactly.

α_merged = α_0 + Σ_k (α_k - α_0): the evidence above the prior of every map is summed, in any order.
Maps of different models, class counts, priors or backgrounds describe different things and are refused.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Sequence

import numpy as np

from ..errors import MapError

if TYPE_CHECKING:
    from .semantic_map import SemanticMap

__all__ = ["check_compatible", "merge_maps", "add_evidence"]


def check_compatible(a: "SemanticMap", b: "SemanticMap", name_a: str = "first map",
                     name_b: str = "second map") -> None:
    """Raise MapError naming the first difference that makes ``a`` and ``b`` impossible to merge."""
    if a.model.fingerprint != b.model.fingerprint or a.model.num_gaussians != b.model.num_gaussians:
        raise MapError(f"{name_a} and {name_b} were made on different splat models (fingerprints "
                       f"{a.model.fingerprint[:12]}… and {b.model.fingerprint[:12]}…); transfer one first")
    if a.num_classes != b.num_classes:
        raise MapError(f"{name_a} has {a.num_classes} classes, {name_b} has {b.num_classes} classes")
    if a.prior != b.prior:
        raise MapError(f"{name_a} has prior {a.prior:g}, {name_b} {b.prior:g}: their evidence is not comparable")
    if a.background != b.background:
        raise MapError(f"{name_a} has background {a.background:g}, {name_b} {b.background:g}")
    if a.fused_sensor_model != b.fused_sensor_model:
        raise MapError(f"{name_a} and {name_b} were fused with different sensor models "
                       f"({a.fused_sensor_model[:12] or 'none'} vs {b.fused_sensor_model[:12] or 'none'}): their "
                       "evidence is weighted differently and does not add up")


def add_evidence(target: "SemanticMap", source: "SemanticMap") -> None:
    """target.α += source.α - α_0 (in place; maps must be compatible: see :func:`check_compatible`)."""
    conc = target.concentrations
    conc += np.maximum(source.concentrations - source.prior, 0.0)
    target.concentrations = conc


def merge_maps(maps: Sequence["SemanticMap"], names: Sequence[str] | None = None) -> "SemanticMap":
    """One map holding the evidence of all ``maps`` (same model, classes, prior, background).

    The result is a new map on the first map's model and backend; ``frames_observed`` is summed and
    ``sources`` is the union. Maps that list a common source are refused: that source's evidence
    is in both and would count twice.

    Raises:
        MapError: fewer than one map, incompatible maps, or a source listed by two maps.
    """
    from .semantic_map import SemanticMap

    if not maps:
        raise MapError("nothing to merge: no maps given")
    names = list(names) if names is not None else [f"map {i + 1}" for i in range(len(maps))]
    first = maps[0]
    seen: dict[str, str] = {}
    for name, m in zip(names, maps):
        check_compatible(first, m, names[0], name)
        for src in m.sources:
            if src in seen:
                raise MapError(f"{seen[src]} and {name} both hold the evidence of source {src!r}: merging "
                               "would count it twice")
            seen[src] = name
    out = SemanticMap(first.model, first.num_classes, prior=first.prior, background=first.background,
                      ignore_label=first.ignore_label, unknown_threshold=first.unknown_threshold,
                      backend=first.backend_name)
    out.fused_sensor_model = first.fused_sensor_model
    for m in maps:
        add_evidence(out, m)
    out.frames_observed = int(sum(m.frames_observed for m in maps))
    out.sources = sorted(seen)
    return out
