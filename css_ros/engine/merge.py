"""Merging maps of the same splat: Dirichlet evidence is additive (SPEC §4), so maps merge exactly.

α_merged = α_0 + Σ_k (α_k - α_0): the evidence above the prior of every map is summed, in any order.
Maps of different models, class counts, priors, backgrounds or depth scales describe different things and are refused.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Sequence

import numpy as np

from ..errors import MapError
from .map_args import MAX_CONCENTRATION, shown
from .spec import MAX_FRAMES

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
    if a.depth_scale != b.depth_scale:
        raise MapError(f"{name_a} has depth_scale {a.depth_scale:g} m per splat unit, {name_b} {b.depth_scale:g}: their "
                       "depths (and a sensor model's depth bins) are in other units")
    for m, name in ((a, name_a), (b, name_b)):
        if m.evidence_half_life is not None:
            raise MapError(f"{name} forgets its evidence (evidence_half_life {m.evidence_half_life:g} observations): "
                           "its evidence is not additive, so it cannot be merged or exchanged (fuse without a "
                           "half-life to merge)")
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
    """One map holding the evidence of all ``maps`` (same model, classes, prior, background, depth_scale).

    The result is a new map on the first map's model, backend, background colour, depth_scale and sensor model;
    ``frames_observed`` is summed and ``sources`` is the union. Maps that list a common source are refused: that source's evidence
    is in both and would count twice.

    Raises:
        MapError: fewer than one map, something that is not a SemanticMap, not one name per map, incompatible maps,
            a source listed by two maps, or a sum a map file cannot hold (MAX_CONCENTRATION, MAX_FRAMES).
    """
    from .semantic_map import SemanticMap

    if isinstance(maps, (str, bytes)) or not hasattr(maps, "__iter__"):
        raise MapError(f"maps must be a sequence of SemanticMap, got {type(maps).__name__}")
    maps = list(maps)
    if not maps:
        raise MapError("nothing to merge: no maps given")
    for i, m in enumerate(maps):
        if not isinstance(m, SemanticMap):
            raise MapError(f"maps[{i}] is a {type(m).__name__}, not a SemanticMap")
    if names is None:
        names = [f"map {i + 1}" for i in range(len(maps))]
    elif isinstance(names, (str, bytes)) or not hasattr(names, "__iter__"):
        raise MapError(f"names must be a sequence of str (one per map), got {type(names).__name__}")
    names = [shown(str(n), 80) for n in names]
    if len(names) != len(maps):
        # zip() would stop at the shorter one and leave the other maps unchecked
        raise MapError(f"{len(names)} names for {len(maps)} maps: give one name per map")
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
                      backend=first.backend_name, background_rgb=tuple(first.background_rgb),
                      depth_scale=first.depth_scale, sensor_model=first.sensor_model)
    out.fused_sensor_model = first.fused_sensor_model
    for m in maps:
        add_evidence(out, m)
    if float(out.concentrations_readonly.max()) > MAX_CONCENTRATION:
        raise MapError(f"the merged map would hold a concentration above {MAX_CONCENTRATION:g} (MAX_CONCENTRATION), "
                       "which no map file may hold")
    frames = int(sum(m.frames_observed for m in maps))
    if frames > MAX_FRAMES:
        raise MapError(f"the merged map would count {frames} frames, more than MAX_FRAMES ({MAX_FRAMES})")
    out.frames_observed = frames
    out.sources = sorted(seen)
    return out
