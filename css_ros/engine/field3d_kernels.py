"""Compiled kernels of the SPEC §9 field (numba): grid cell lists and the per-point evaluation.

Called through :mod:`css_ros.engine.field3d`, which documents the data layout.
"""
from __future__ import annotations

import math

from numba import njit, prange
from .kernel_cache import bind_sources

__all__ = ["cell_coord", "count_cells", "fill_cells", "query_kernel"]


@njit(inline="always")
def cell_coord(v, origin, h, d):  # pragma: no cover - compiled
    """Index of the grid cell of coordinate ``v`` along one axis (cells of size h from origin), clamped to 0..d-1."""
    k = math.floor((v - origin) / h)
    if k < 0:
        return 0
    if k > d - 1:
        return d - 1
    return int(k)


@njit(cache=True, nogil=True)
def count_cells(lo, hi, level, dims, level_offsets, counts):  # pragma: no cover - compiled
    for g in range(lo.shape[0]):
        lv = level[g]
        dy, dz = dims[lv, 1], dims[lv, 2]
        for ix in range(lo[g, 0], hi[g, 0] + 1):
            for iy in range(lo[g, 1], hi[g, 1] + 1):
                for iz in range(lo[g, 2], hi[g, 2] + 1):
                    counts[level_offsets[lv] + (ix * dy + iy) * dz + iz] += 1


@njit(cache=True, nogil=True)
def fill_cells(lo, hi, level, dims, level_offsets, fill, items):  # pragma: no cover - compiled
    for g in range(lo.shape[0]):
        lv = level[g]
        dy, dz = dims[lv, 1], dims[lv, 2]
        for ix in range(lo[g, 0], hi[g, 0] + 1):
            for iy in range(lo[g, 1], hi[g, 1] + 1):
                for iz in range(lo[g, 2], hi[g, 2] + 1):
                    cell = level_offsets[lv] + (ix * dy + iy) * dz + iz
                    items[fill[cell]] = g
                    fill[cell] += 1


@njit(parallel=True, cache=True, nogil=True)
def query_kernel(points, means, inv_cov, opac, alpha, totals, origin, cell_size, dims, level_offsets,
                 cell_start, items, cut2, w_b, e_b, v_b, out_e, out_v, out_kb):  # pragma: no cover
    m = points.shape[0]
    c = alpha.shape[1]
    nlev = cell_size.shape[0]
    for i in prange(m):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        for k in range(c):
            out_e[i, k] = 0.0
            out_v[i, k] = 0.0
        wsum = 0.0
        for lv in range(nlev):
            h = cell_size[lv]
            dx, dy, dz = dims[lv, 0], dims[lv, 1], dims[lv, 2]
            ix = cell_coord(px, origin[0], h, dx)
            iy = cell_coord(py, origin[1], h, dy)
            iz = cell_coord(pz, origin[2], h, dz)
            cell = level_offsets[lv] + (ix * dy + iy) * dz + iz
            for j in range(cell_start[cell], cell_start[cell + 1]):
                g = items[j]
                ax = px - means[g, 0]
                ay = py - means[g, 1]
                az = pz - means[g, 2]
                d2 = (inv_cov[g, 0] * ax * ax + inv_cov[g, 3] * ay * ay + inv_cov[g, 5] * az * az
                      + 2.0 * (inv_cov[g, 1] * ax * ay + inv_cov[g, 2] * ax * az + inv_cov[g, 4] * ay * az))
                if d2 > cut2:
                    continue
                w = opac[g] * math.exp(-0.5 * d2)
                wsum += w
                s = totals[g]
                inv_s = 1.0 / s
                w2 = w * w / (1.0 + s)
                for k in range(c):
                    e = alpha[g, k] * inv_s
                    out_e[i, k] += w * e
                    out_v[i, k] += w2 * e * (1.0 - e)
        denom = wsum + w_b
        inv = 1.0 / denom
        kb = w_b * inv
        for k in range(c):
            out_e[i, k] = out_e[i, k] * inv + kb * e_b
            out_v[i, k] = out_v[i, k] * inv * inv + kb * kb * v_b
        out_kb[i] = kb


bind_sources(globals())  # cached kernels recompile when any module they are built from changes
