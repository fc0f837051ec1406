"""The semantic map in 3D (SPEC §9): per-Gaussian semantics and the continuous field at points.

Two jobs, both pure computation on a :class:`~css_ros.engine.semantic_map.SemanticMap`'s arrays:

* :func:`gaussian_semantics` — label, E and Var of the label, total S_n and the *observed* flag of
  every Gaussian (moments of SPEC §4).
* :func:`query_field` — the field at 3D points (map frame, metres): every Gaussian's 3D kernel
  w_n(x) = o_n exp(-1/2 d²), d the Mahalanobis distance (w_n = 0 for d > 3), normalised together
  with the background weight w_b into κ_n(x), κ_b(x), then E^c(x), Var^c(x) as in SPEC §9.

The Gaussians are found through a :class:`FieldIndex`: a hierarchy of uniform grids over the
axis-aligned boxes of the 3σ ellipsoids, built once per model (compiled with numba). Each Gaussian
lives in exactly one level, the finest whose cubic cells are at least as wide as its box, so it
touches at most 2 cells per axis (≤ 8 cells: the index holds ≤ 8 N entries whatever the sizes);
a query point visits one cell per level. Cell coordinates are clamped to the grid, which keeps the
lookup exact for points and boxes outside it (clamping is monotone: a box that contains a point
covers the point's clamped cell). Memory: O(N) for the index plus O(chunk · C) scratch per call.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from ..errors import InputError, MapError
from .gaussians import rotation_matrices_wxyz
from .spec import QUERY_MAHALANOBIS_CUTOFF

if TYPE_CHECKING:
    from .gaussians import GaussianModel

__all__ = ["FieldIndex", "GaussianSemantics", "FieldQuery", "gaussian_semantics", "query_field",
           "DEFAULT_QUERY_CHUNK"]

DEFAULT_QUERY_CHUNK = 65536     # query points per compiled call (bounds the float64 scratch)
MAX_LEVEL0_CELLS = 1 << 22      # cells of the finest grid level, at most (32 MiB of offsets)
DOMAIN_PERCENTILES = (0.5, 99.5)  # grid domain: this range of the centres (floaters go to border cells)


# ---------------------------------------------------------------------------------------------
# per-Gaussian semantics
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class GaussianSemantics:
    """SPEC §9 semantics of every Gaussian n of the model (N = number of Gaussians).

    Attributes:
        label: (N,) int32 argmax_c E[θ_n^c] (ties: lowest class id); ``ignore_label`` for
            Gaussians that are not observed (their E is the uniform prior 1/C: nothing to argmax).
        expectation: (N,) float32 E[θ_n^ĉ] of the argmax class (also for unobserved ones: 1/C
            for a Gaussian still at the prior).
        variance: (N,) float32 Var[θ_n^ĉ] = E (1 - E) / (1 + S_n) of the argmax class.
        total: (N,) float64 S_n = Σ_c α_n^c.
        evidence: (N,) float64 S_n - C α_0, the κ-weighted label count fused so far (pixels).
        observed: (N,) bool, evidence >= min_evidence.
    """

    label: np.ndarray
    expectation: np.ndarray
    variance: np.ndarray
    total: np.ndarray
    evidence: np.ndarray
    observed: np.ndarray


def gaussian_semantics(concentrations: np.ndarray, prior: float, min_evidence: float,
                       ignore_label: int, chunk: int = 1 << 18) -> GaussianSemantics:
    """Per-Gaussian label, E, Var, S_n and observed flag (SPEC §4 moments, SPEC §9 threshold).

    Args:
        concentrations: (N, C) float64 Dirichlet concentrations α.
        prior: α_0 per class (the map's prior).
        min_evidence: a Gaussian is observed when S_n - C α_0 >= this (finite, >= 0).
        ignore_label: label given to unobserved Gaussians.
        chunk: rows processed at a time (bounds temporaries to O(chunk · C)).
    """
    if not (np.isfinite(min_evidence) and min_evidence >= 0):
        raise MapError(f"min_evidence must be a finite number >= 0, got {min_evidence}")
    alpha = np.asarray(concentrations)
    n, c = alpha.shape
    label = np.empty(n, dtype=np.int32)
    expectation = np.empty(n, dtype=np.float32)
    variance = np.empty(n, dtype=np.float32)
    total = np.empty(n, dtype=np.float64)
    for a in range(0, n, chunk):
        b = min(n, a + chunk)
        block = alpha[a:b]
        s = block.sum(axis=1)
        best = np.argmax(block, axis=1)
        e = block[np.arange(b - a), best] / s
        total[a:b] = s
        label[a:b] = best
        expectation[a:b] = e
        variance[a:b] = e * (1.0 - e) / (1.0 + s)
    evidence = total - c * float(prior)
    observed = evidence >= float(min_evidence)
    label[~observed] = int(ignore_label)
    return GaussianSemantics(label, expectation, variance, total, evidence, observed)


# ---------------------------------------------------------------------------------------------
# spatial index
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FieldIndex:
    """Geometry of the 3D kernels and the multi-level grid over their 3σ boxes (map frame, metres).

    Attributes (N Gaussians, L levels, K cells over all levels, P index entries <= 8 N):
        means: (N, 3) float64 centres μ_n [m].
        inv_cov: (N, 6) float64 upper triangle (xx, xy, xz, yy, yz, zz) of Σ_n⁻¹ = R S⁻² Rᵀ [m⁻²].
        opacities: (N,) float64 o_n in (0, 1).
        origin: (3,) float64 lower corner of every level's grid [m].
        cell_size: (L,) float64 cubic cell edge per level [m] (doubling from level to level).
        dims: (L, 3) int64 cells per axis per level (the last level is a single cell).
        level_offsets: (L + 1,) int64 first global cell id of each level.
        cell_start: (K + 1,) int64 CSR offsets of each cell's entries in ``items``.
        items: (P,) int32 Gaussian ids, grouped by cell.
        cutoff: Mahalanobis distance beyond which w_n = 0.
    """

    means: np.ndarray
    inv_cov: np.ndarray
    opacities: np.ndarray
    origin: np.ndarray
    cell_size: np.ndarray
    dims: np.ndarray
    level_offsets: np.ndarray
    cell_start: np.ndarray
    items: np.ndarray
    cutoff: float

    @property
    def num_gaussians(self) -> int:
        return int(self.means.shape[0])

    @property
    def nbytes(self) -> int:
        """Bytes held by the index arrays."""
        return int(sum(a.nbytes for a in (self.means, self.inv_cov, self.opacities, self.cell_start,
                                          self.items, self.dims, self.cell_size, self.level_offsets)))

    @classmethod
    def from_model(cls, model: "GaussianModel", cutoff: float = QUERY_MAHALANOBIS_CUTOFF,
                   max_level0_cells: int = MAX_LEVEL0_CELLS) -> "FieldIndex":
        """Build the index of ``model`` (O(N) time and memory)."""
        means = np.ascontiguousarray(model.means, dtype=np.float64)
        n = means.shape[0]
        inv_cov = np.empty((n, 6))
        half = np.empty((n, 3))
        all_scales = model.scales                           # (N, 3) float32 std devs, as the renderer uses
        for a in range(0, n, 1 << 18):                      # bounded temporaries for large models
            b = min(n, a + (1 << 18))
            R = rotation_matrices_wxyz(_unit(model.rotations[a:b]))
            scales = all_scales[a:b].astype(np.float64)
            M = R / scales[:, None, :]                      # R S⁻¹
            A = M @ np.swapaxes(M, 1, 2)                    # Σ⁻¹ = R S⁻² Rᵀ
            inv_cov[a:b] = np.stack([A[:, 0, 0], A[:, 0, 1], A[:, 0, 2], A[:, 1, 1], A[:, 1, 2], A[:, 2, 2]], 1)
            cov_diag = np.einsum("nij,nij->ni", R * scales[:, None, :], R * scales[:, None, :])  # Σ_ii
            half[a:b] = cutoff * np.sqrt(cov_diag) * (1.0 + 1e-9)  # half widths of the 3σ boxes [m] (+ pad)
        box_lo = means - half
        box_hi = means + half
        opac = np.ascontiguousarray(np.asarray(model.opacities, dtype=np.float64))

        lo = np.percentile(means, DOMAIN_PERCENTILES[0], axis=0)
        hi = np.percentile(means, DOMAIN_PERCENTILES[1], axis=0)
        extent = np.maximum(hi - lo, 0.0)
        width = 2.0 * half.max(axis=1)
        h0 = float(np.median(width))
        h0 = max(h0, 1e-9 * max(1.0, float(extent.max())))
        budget = int(min(max(4096, 2 * n), max_level0_cells))
        while np.prod(np.maximum(1, np.ceil(extent / h0))) > budget:
            h0 *= 1.25
        sizes = [h0]
        while np.any(np.ceil(extent / sizes[-1]) > 1):
            sizes.append(sizes[-1] * 2.0)
        cell_size = np.asarray(sizes, dtype=np.float64)
        dims = np.maximum(1, np.ceil(extent[None, :] / cell_size[:, None])).astype(np.int64)
        level_offsets = np.concatenate([[0], np.cumsum(np.prod(dims, axis=1))]).astype(np.int64)
        nlev = len(sizes)
        level = np.zeros(n, dtype=np.int64)
        big = width > h0
        level[big] = np.ceil(np.log2(width[big] / h0)).astype(np.int64)
        level = np.clip(level, 0, nlev - 1)
        # guard against log2 rounding: move up while the box would exceed the cell width
        while True:
            bump = (width > cell_size[level]) & (level < nlev - 1)
            if not np.any(bump):
                break
            level[bump] += 1
        cell_start, items = _build_cells(box_lo, box_hi, level, lo, cell_size, dims, level_offsets)
        return cls(means=means, inv_cov=inv_cov, opacities=opac, origin=np.asarray(lo, dtype=np.float64),
                   cell_size=cell_size, dims=dims, level_offsets=level_offsets, cell_start=cell_start,
                   items=items, cutoff=float(cutoff))


def _unit(q: np.ndarray) -> np.ndarray:
    """(N, 4) float64 unit quaternions from raw ones."""
    q = q.astype(np.float64)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _build_cells(box_lo: np.ndarray, box_hi: np.ndarray, level: np.ndarray, origin: np.ndarray,
                 cell_size: np.ndarray, dims: np.ndarray, level_offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """CSR lists of the Gaussians whose box touches each cell (clamped cell ranges, <= 2 per axis)."""
    h = cell_size[level][:, None]
    d = dims[level]
    lo = np.clip(np.floor((box_lo - origin) / h), 0, d - 1).astype(np.int64)
    hi = np.clip(np.floor((box_hi - origin) / h), 0, d - 1).astype(np.int64)
    hi = np.maximum(hi, lo)
    total = int(level_offsets[-1])
    counts = np.zeros(total, dtype=np.int64)
    from .field3d_kernels import count_cells, fill_cells  # numba: imported on first use

    count_cells(lo, hi, level, dims, level_offsets, counts)
    start = np.zeros(total + 1, dtype=np.int64)
    np.cumsum(counts, out=start[1:])
    items = np.empty(int(start[-1]), dtype=np.int32)
    fill_cells(lo, hi, level, dims, level_offsets, start[:-1].copy(), items)
    return start, items



# ---------------------------------------------------------------------------------------------
# queries
# ---------------------------------------------------------------------------------------------
class FieldQuery(NamedTuple):
    """The semantic field at M points (SPEC §9).

    Attributes:
        labels: (M,) int32 argmax_c E^c(x); ``ignore_label`` where κ_b(x) > the unknown threshold.
        expectation: (M, C) float32 E^c(x).
        variance: (M, C) float32 Var^c(x).
        background: (M,) float32 κ_b(x) = w_b / (Σ_n w_n(x) + w_b).
    """

    labels: np.ndarray
    expectation: np.ndarray
    variance: np.ndarray
    background: np.ndarray


def query_field(index: FieldIndex, concentrations: np.ndarray, points: np.ndarray, background_weight: float,
                background_moments: tuple[float, float], unknown_threshold: float, ignore_label: int,
                chunk: int = DEFAULT_QUERY_CHUNK) -> FieldQuery:
    """Evaluate the SPEC §9 field at ``points``.

    Args:
        index: the model's :class:`FieldIndex`.
        concentrations: (N, C) float64 α of the map.
        points: (M, 3) points in the map frame [m]. A non-finite point is "far from every Gaussian":
            it gets exactly what a point beyond every Gaussian's support gets (κ_b = 1, E = E[θ_b],
            Var = Var[θ_b], ``ignore_label``), so there is one rule for points that cannot be located.
        background_weight: w_b > 0.
        background_moments: (E[θ_b^c], Var[θ_b^c]) of the background Dirichlet (same for every c).
        unknown_threshold: labels are ``ignore_label`` where κ_b(x) exceeds this.
        ignore_label: the "no label" value.
        chunk: points per compiled call; scratch is 2 · chunk · C float64.
    Raises:
        InputError: points not an (M, 3) array of numbers, or a non-positive background weight.
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3 or not np.issubdtype(pts.dtype, np.number):
        raise InputError(f"points must be an (M, 3) array of numbers, got shape {pts.shape} dtype {pts.dtype}")
    if not (np.isfinite(background_weight) and background_weight > 0):
        raise InputError(f"background_weight must be a positive finite number, got {background_weight}")
    from .field3d_kernels import query_kernel  # numba: imported on first use

    alpha = np.ascontiguousarray(concentrations, dtype=np.float64)
    if alpha.shape[0] != index.num_gaussians:
        raise MapError(f"concentrations have {alpha.shape[0]} rows, the index {index.num_gaussians} Gaussians")
    totals = alpha.sum(axis=1)
    m, c = pts.shape[0], alpha.shape[1]
    labels = np.empty(m, dtype=np.int32)
    expectation = np.empty((m, c), dtype=np.float32)
    variance = np.empty((m, c), dtype=np.float32)
    background = np.empty(m, dtype=np.float32)
    chunk = max(1, int(chunk))
    size = min(chunk, m)
    buf_e = np.empty((size, c))
    buf_v = np.empty((size, c))
    buf_kb = np.empty(size)
    e_b, v_b = (float(v) for v in background_moments)
    cut2 = index.cutoff * index.cutoff
    for a in range(0, m, chunk):
        b = min(m, a + chunk)
        block = np.array(pts[a:b], dtype=np.float64)
        lost = ~np.all(np.isfinite(block), axis=1)
        block[lost] = 0.0  # evaluated, then overwritten below with the far-point answer
        be, bv, bk = buf_e[: b - a], buf_v[: b - a], buf_kb[: b - a]
        query_kernel(block, index.means, index.inv_cov, index.opacities, alpha, totals, index.origin,
                      index.cell_size, index.dims, index.level_offsets, index.cell_start, index.items,
                      cut2, float(background_weight), e_b, v_b, be, bv, bk)
        be[lost], bv[lost], bk[lost] = e_b, v_b, 1.0
        lab = np.argmax(be, axis=1).astype(np.int32)
        lab[bk > unknown_threshold] = int(ignore_label)
        labels[a:b] = lab
        expectation[a:b] = be
        variance[a:b] = bv
        background[a:b] = bk
    return FieldQuery(labels, expectation, variance, background)
