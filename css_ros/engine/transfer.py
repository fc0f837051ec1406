"""Moving a semantic map to another splat of the same scene (retrained, densified, pruned, reordered).

The maths is docs/spec.md "Transfer of a map to another splat". In short, with ε_g = α_g - α_0 the evidence
of old Gaussian g (C-vector, ≥ 0) and Σ'_g = Σ_g + τ² I its covariance widened by the tolerance τ:

    o_gj = o_j sqrt(|Σ_j| / |Σ'_g + Σ_j|) exp(-½ Δᵀ (Σ'_g + Σ_j)⁻¹ Δ),   Δ = μ_j - μ_g
           (0 beyond Mahalanobis distance 3, or where μ_j is outside g's widened 3σ ellipsoid)
    α_j   = α_0 + Σ_g (o_gj / Σ_k o_gk) ε_g

Each old Gaussian hands all its evidence to the new Gaussians that overlap it, in proportion to how much
of their (opacity-weighted) kernel lies inside it: the total evidence is conserved wherever an old
Gaussian has a new counterpart. Old Gaussians with none lose their evidence (counted in the report);
new Gaussians that overlap no observed old one keep the prior. Runs in O(N_old + N_new) through the
SPEC §9 grid index (:class:`~css_ros.engine.field3d.FieldIndex`) over the observed old Gaussians, with
two compiled passes (denominators, then gathering).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Sequence

import numba
import numpy as np

from ..errors import MapError
from .field3d import FieldIndex
from .gaussians import GaussianModel, rotation_matrices_wxyz
from .spec import DEFAULT_TRANSFER_TOLERANCE, TRANSFER_CUTOFF

if TYPE_CHECKING:
    from .semantic_map import SemanticMap

__all__ = ["TransferReport", "transfer_concentrations", "transfer_map"]

_CHUNK = 1 << 18  # Gaussians per block when building covariances (bounds the (n, 3, 3) temporaries)


@dataclass(frozen=True)
class TransferReport:
    """What a transfer moved (evidence in κ-weighted label counts, i.e. pixels).

    Attributes:
        evidence_old: Σ of the old map's evidence above the prior.
        evidence_new: Σ of the new map's evidence above the prior (= evidence_old - evidence_lost, up to rounding).
        evidence_lost: evidence of old Gaussians that no new Gaussian overlaps (dropped).
        ratio: evidence_new / evidence_old (1.0 for an empty old map).
        old_observed: old Gaussians holding evidence.
        old_dropped: of those, the ones whose evidence was dropped.
        new_observed: new Gaussians that received evidence.
        new_at_prior: new Gaussians that overlap no observed old Gaussian (they keep the prior).
        tolerance: τ used [m].
    """

    evidence_old: float
    evidence_new: float
    evidence_lost: float
    ratio: float
    old_observed: int
    old_dropped: int
    new_observed: int
    new_at_prior: int
    tolerance: float


def _covariance_rows(model: GaussianModel, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """(N, 6) upper triangles (xx, xy, xz, yy, yz, zz) of Σ + τ² I [m²] and (N,) determinants |Σ + τ² I|."""
    n = model.num_gaussians
    rows = np.empty((n, 6))
    det = np.empty(n)
    scales = model.scales
    for a in range(0, n, _CHUNK):
        b = min(n, a + _CHUNK)
        q = model.rotations[a:b].astype(np.float64)
        R = rotation_matrices_wxyz(q / np.linalg.norm(q, axis=1, keepdims=True))
        var = scales[a:b].astype(np.float64) ** 2 + tolerance * tolerance   # R (S² + τ²) Rᵀ = Σ + τ² I
        M = R * np.sqrt(var)[:, None, :]
        cov = M @ np.swapaxes(M, 1, 2)
        rows[a:b] = np.stack([cov[:, 0, 0], cov[:, 0, 1], cov[:, 0, 2], cov[:, 1, 1], cov[:, 1, 2], cov[:, 2, 2]], 1)
        det[a:b] = np.prod(var, axis=1)
    return rows, det


def _widened(model: GaussianModel, tolerance: float) -> GaussianModel:
    """The model with every standard deviation widened to sqrt(σ² + τ²) (the index's boxes)."""
    log_scales = 0.5 * np.log(np.exp(2.0 * model.log_scales.astype(np.float64)) + tolerance * tolerance)
    return GaussianModel(model.means, model.sh[:, :1], model.opacity_logits, log_scales, model.rotations)


def transfer_concentrations(old_model: GaussianModel, old_concentrations: np.ndarray, prior: float,
                            new_model: GaussianModel,
                            tolerance: float = DEFAULT_TRANSFER_TOLERANCE) -> tuple[np.ndarray, TransferReport]:
    """See :func:`_transfer` (without parts)."""
    out, report, _ = _transfer(old_model, old_concentrations, prior, new_model, tolerance, ())
    return out, report


def _transfer(old_model: GaussianModel, old_concentrations: np.ndarray, prior: float, new_model: GaussianModel,
              tolerance: float, parts: Sequence[np.ndarray]) -> tuple[np.ndarray, TransferReport, list[np.ndarray]]:
    """α of ``new_model``'s Gaussians from the map ``old_concentrations`` on ``old_model`` (both in one frame).

    Args:
        old_model: the splat the map was made on (N_old Gaussians; map frame, metres).
        old_concentrations: (N_old, C) float64 α of the old map.
        prior: α_0 of the map (kept for the new one).
        new_model: the other splat of the same scene (N_new Gaussians, same frame).
        tolerance: τ [m] ≥ 0, how far a retrained Gaussian may have moved.
        parts: (N_old, C) non-negative parts of the evidence α − α_0 (e.g. what each peer of the evidence exchange
            contributed). Each is moved with the map's own factors: new Gaussian j takes part[best_j] · m_j /
            |ε_best_j|, so the moved parts add up to the moved evidence exactly as the parts did.
    Returns:
        ((N_new, C) float64 α, :class:`TransferReport`, the moved parts (N_new, C) float64).
    Raises:
        MapError: shapes that do not match, a bad tolerance.
    """
    alpha = np.asarray(old_concentrations, dtype=np.float64)
    if alpha.ndim != 2 or alpha.shape[0] != old_model.num_gaussians:
        raise MapError(f"concentrations of shape {alpha.shape} do not fit the old model "
                       f"({old_model.num_gaussians} Gaussians)")
    if not (np.isfinite(tolerance) and tolerance >= 0):
        raise MapError(f"tolerance must be a finite number >= 0 [m], got {tolerance}")
    c = alpha.shape[1]
    evidence = np.maximum(alpha - prior, 0.0)
    per_old = evidence.sum(axis=1)
    observed = np.flatnonzero(per_old > 0)
    n_new = new_model.num_gaussians
    out = np.full((n_new, c), float(prior))
    total_old = float(per_old.sum())
    moved = [np.zeros((n_new, c)) for _ in parts]
    if observed.size == 0:
        return out, TransferReport(0.0, 0.0, 0.0, 1.0, 0, 0, 0, n_new, float(tolerance)), moved

    from .transfer_kernels import gather_mass, nearest_old, overlap_denominators  # numba: compiled on first use

    index = FieldIndex.from_model(_widened(old_model, tolerance), cutoff=TRANSFER_CUTOFF)
    old_cov, _ = _covariance_rows(old_model, tolerance)
    new_cov, new_det = _covariance_rows(new_model, 0.0)
    new_means = np.ascontiguousarray(new_model.means, dtype=np.float64)
    new_opac = np.ascontiguousarray(new_model.opacities, dtype=np.float64)
    geometry = (new_means, new_cov, new_det, new_opac, index.means, old_cov, index.inv_cov, index.origin, index.cell_size,
                index.dims, index.level_offsets, index.cell_start, index.items, TRANSFER_CUTOFF ** 2)
    best = np.empty(n_new, dtype=np.int64)
    nearest_old(*geometry, best)
    eligible = best >= 0
    eligible[eligible] = per_old[best[eligible]] > 0     # j descends from an observed old Gaussian
    partial = np.zeros((max(1, numba.get_num_threads()), old_model.num_gaussians))
    denominator = np.zeros(old_model.num_gaussians)
    overlap_denominators(*geometry, eligible, partial, denominator)
    del partial
    mass = np.zeros(n_new)
    gather_mass(*geometry, eligible, denominator, per_old, mass)
    for a in range(0, n_new, _CHUNK):  # α_j = α_0 + m_j ε_best / |ε_best|, in blocks (bounded temporaries)
        sel = np.flatnonzero(eligible[a:a + _CHUNK]) + a
        g = best[sel]
        factor = (mass[sel] / per_old[g])[:, None]
        out[sel] += evidence[g] * factor
        for part, dst in zip(parts, moved):
            dst[sel] = np.asarray(part)[g] * factor
    dropped = (per_old > 0) & (denominator <= 0)
    lost = float(per_old[dropped].sum())
    total_new = float(mass.sum())
    report = TransferReport(evidence_old=total_old, evidence_new=total_new, evidence_lost=lost,
                            ratio=total_new / total_old, old_observed=int(observed.size),
                            old_dropped=int(np.count_nonzero(dropped)),
                            new_observed=int(np.count_nonzero(mass > 0)),
                            new_at_prior=int(n_new - np.count_nonzero(mass > 0)), tolerance=float(tolerance))
    return out, report, moved


def transfer_map(smap: "SemanticMap", new_model: GaussianModel,
                 tolerance: float = DEFAULT_TRANSFER_TOLERANCE) -> tuple["SemanticMap", TransferReport]:
    """A new :class:`SemanticMap` on ``new_model`` carrying ``smap``'s evidence (same classes, prior,
    background, rendering options and backend; frames and sources kept). See :func:`transfer_concentrations`.

    The evidence-exchange bookkeeping moves too: each received source's evidence is moved with the same factors
    (so what is the node's own stays its own, and a peer's evidence is never re-published as this node's), out of
    step (its next snapshot re-states it); the origin id and epoch are kept."""
    from .map_file import SourceEvidence
    from .semantic_map import SemanticMap

    names = sorted(smap.received)
    conc, report, moved = _transfer(smap.model, smap.concentrations, smap.prior, new_model, tolerance,
                                    [smap.received[n].evidence for n in names])
    out = SemanticMap(new_model, smap.num_classes, prior=smap.prior, background=smap.background,
                      ignore_label=smap.ignore_label, unknown_threshold=smap.unknown_threshold,
                      backend=smap.backend_name, background_rgb=tuple(smap.background_rgb))
    out.concentrations[...] = conc
    out.frames_observed = smap.frames_observed
    out.sources = list(smap.sources)
    out.fused_sensor_model = smap.fused_sensor_model
    out.evidence_origin, out.evidence_epoch = smap.evidence_origin, smap.evidence_epoch
    out.received = {n: SourceEvidence(ev, epoch=int(smap.received[n].epoch), last_seq=int(smap.received[n].last_seq),
                                      frames=int(smap.received[n].frames), in_step=False)
                    for n, ev in zip(names, moved)}
    return out, report
