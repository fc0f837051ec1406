"""Compiled kernels of the map transfer (numba): nearest old Gaussian, overlap denominators, gathering.

Called through :mod:`css_ros.engine.transfer`, which documents the maths and the data layout. Every kernel
visits, for each new Gaussian j, the old Gaussians g of the SPEC §9 grid cells holding μ_j (old boxes
widened by the tolerance) whose widened 3σ ellipsoid contains μ_j, and keeps the pairs whose overlap o_gj is > 0.
"""
from __future__ import annotations

import math

from numba import njit, prange

from .field3d_kernels import cell_coord
from .kernel_cache import bind_sources

__all__ = ["nearest_old", "overlap_denominators", "gather_mass"]


@njit(inline="always")
def _cell(px, py, pz, lv, origin, cell_size, dims, level_offsets):  # pragma: no cover - compiled
    h = cell_size[lv]
    dx, dy, dz = dims[lv, 0], dims[lv, 1], dims[lv, 2]
    ix = cell_coord(px, origin[0], h, dx)
    iy = cell_coord(py, origin[1], h, dy)
    iz = cell_coord(pz, origin[2], h, dz)
    return level_offsets[lv] + (ix * dy + iy) * dz + iz


@njit(inline="always")
def _inside(g, px, py, pz, old_means, old_inv, cut2):  # pragma: no cover - compiled
    """μ_j inside old g's widened ellipsoid: (μ_j - μ_g)ᵀ Σ'_g⁻¹ (μ_j - μ_g) <= cut2 (cheap pre-filter)."""
    ax = px - old_means[g, 0]
    ay = py - old_means[g, 1]
    az = pz - old_means[g, 2]
    d2 = (old_inv[g, 0] * ax * ax + old_inv[g, 3] * ay * ay + old_inv[g, 5] * az * az
          + 2.0 * (old_inv[g, 1] * ax * ay + old_inv[g, 2] * ax * az + old_inv[g, 4] * ay * az))
    return d2 <= cut2


@njit(inline="always")
def _overlap(g, j, new_means, new_cov, new_det, new_opac, old_means, old_cov, cut2):  # pragma: no cover
    """o_gj = o_j sqrt(|Σ_j| / |A|) exp(-q/2), q = Δᵀ A⁻¹ Δ, A = Σ'_g + Σ_j; 0 where q > cut2."""
    dx = new_means[j, 0] - old_means[g, 0]
    dy = new_means[j, 1] - old_means[g, 1]
    dz = new_means[j, 2] - old_means[g, 2]
    a0 = old_cov[g, 0] + new_cov[j, 0]
    a1 = old_cov[g, 1] + new_cov[j, 1]
    a2 = old_cov[g, 2] + new_cov[j, 2]
    a3 = old_cov[g, 3] + new_cov[j, 3]
    a4 = old_cov[g, 4] + new_cov[j, 4]
    a5 = old_cov[g, 5] + new_cov[j, 5]
    c00 = a3 * a5 - a4 * a4
    c01 = a2 * a4 - a1 * a5
    c02 = a1 * a4 - a2 * a3
    det = a0 * c00 + a1 * c01 + a2 * c02
    if not det > 0.0:
        return 0.0
    c11 = a0 * a5 - a2 * a2
    c12 = a1 * a2 - a0 * a4
    c22 = a0 * a3 - a1 * a1
    q = (c00 * dx * dx + c11 * dy * dy + c22 * dz * dz + 2.0 * (c01 * dx * dy + c02 * dx * dz + c12 * dy * dz)) / det
    if q > cut2:
        return 0.0
    return new_opac[j] * math.sqrt(new_det[j] / det) * math.exp(-0.5 * q)


@njit(parallel=True, cache=True, nogil=True)
def nearest_old(new_means, new_cov, new_det, new_opac, old_means, old_cov, old_inv, origin, cell_size, dims,
                level_offsets, cell_start, items, cut2, out_best):  # pragma: no cover - compiled
    """out_best[j] = the overlapping old Gaussian whose centre is nearest to μ_j (ties: lowest id); -1: none."""
    nlev = cell_size.shape[0]
    for j in prange(new_means.shape[0]):
        px, py, pz = new_means[j, 0], new_means[j, 1], new_means[j, 2]
        best = -1
        best_d = 1e300
        for lv in range(nlev):
            cell = _cell(px, py, pz, lv, origin, cell_size, dims, level_offsets)
            for k in range(cell_start[cell], cell_start[cell + 1]):
                g = items[k]
                if not _inside(g, px, py, pz, old_means, old_inv, cut2):
                    continue
                if _overlap(g, j, new_means, new_cov, new_det, new_opac, old_means, old_cov, cut2) > 0.0:
                    d = (px - old_means[g, 0]) ** 2 + (py - old_means[g, 1]) ** 2 + (pz - old_means[g, 2]) ** 2
                    if d < best_d or (d == best_d and g < best):
                        best_d = d
                        best = g
        out_best[j] = best


@njit(parallel=True, cache=True, nogil=True)
def overlap_denominators(new_means, new_cov, new_det, new_opac, old_means, old_cov, old_inv, origin, cell_size, dims,
                         level_offsets, cell_start, items, cut2, eligible, partial,
                         out_denominator):  # pragma: no cover - compiled
    """out_denominator[g] = Σ_j o_gj over the new Gaussians j with ``eligible[j]``.

    ``partial``: (T, N_old) float64 zeros, one row per block of new Gaussians (no shared writes).
    """
    n_new = new_means.shape[0]
    nthreads = partial.shape[0]
    nlev = cell_size.shape[0]
    per = (n_new + nthreads - 1) // nthreads
    for t in prange(nthreads):
        for j in range(t * per, min(n_new, (t + 1) * per)):
            if not eligible[j]:
                continue
            px, py, pz = new_means[j, 0], new_means[j, 1], new_means[j, 2]
            for lv in range(nlev):
                cell = _cell(px, py, pz, lv, origin, cell_size, dims, level_offsets)
                for k in range(cell_start[cell], cell_start[cell + 1]):
                    g = items[k]
                    if not _inside(g, px, py, pz, old_means, old_inv, cut2):
                        continue
                    partial[t, g] += _overlap(g, j, new_means, new_cov, new_det, new_opac, old_means, old_cov, cut2)
    for g in prange(old_means.shape[0]):
        s = 0.0
        for t in range(nthreads):
            s += partial[t, g]
        out_denominator[g] = s


@njit(parallel=True, cache=True, nogil=True)
def gather_mass(new_means, new_cov, new_det, new_opac, old_means, old_cov, old_inv, origin, cell_size, dims,
                level_offsets, cell_start, items, cut2, eligible, denominator, old_mass,
                out_mass):  # pragma: no cover - compiled
    """out_mass[j] = Σ_g (o_gj / denominator[g]) old_mass[g] for eligible j (0 otherwise)."""
    nlev = cell_size.shape[0]
    for j in prange(new_means.shape[0]):
        mass = 0.0
        if eligible[j]:
            px, py, pz = new_means[j, 0], new_means[j, 1], new_means[j, 2]
            for lv in range(nlev):
                cell = _cell(px, py, pz, lv, origin, cell_size, dims, level_offsets)
                for k in range(cell_start[cell], cell_start[cell + 1]):
                    g = items[k]
                    if old_mass[g] > 0.0 and denominator[g] > 0.0 and _inside(g, px, py, pz, old_means, old_inv,
                                                                               cut2):
                        o = _overlap(g, j, new_means, new_cov, new_det, new_opac, old_means, old_cov, cut2)
                        mass += o / denominator[g] * old_mass[g]
        out_mass[j] = mass


bind_sources(globals())  # cached kernels recompile when any module they are built from changes
