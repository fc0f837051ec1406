"""Stage 1 of the pipeline: project 3D Gaussians to screen-space ellipses (EWA splatting, SPEC §3).

Numba kernel; float64 throughout so the result matches a float64 reference to rounding. The
per-Gaussian maths (:mod:`css_ros.engine.splat_math`, :func:`css_ros.engine.sh.sh_polynomial`) is
shared with the CUDA kernels; this module adds the CPU's group culling, ordering and gathers.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numba import njit, prange

from ..sh import eval_sh, sh_polynomial
from ..spec import COV2D_DILATION, NEAR_PLANE
from ..splat_math import camera_row, ewa_splat, fov_limits, store_splat, view_direction
from .kept import Kept
from .prefetch import prefetch_ahead
from ..kernel_cache import bind_sources

if TYPE_CHECKING:
    from ..camera import Camera
    from ..gaussians import GaussianModel

GROUP_SIZE = 128            # Gaussians per culling group (consecutive rows in Morton order)
BLOCK = 32                  # px; screen blocks that order the projected rows for cache locality


@dataclass(frozen=True)
class GaussianGeometry:
    """Per-model quantities that do not depend on the camera, computed once per model.

    Rows are stored in Morton (Z-curve) order of the centres and cut into groups of
    ``GROUP_SIZE`` consecutive, spatially close Gaussians; each group's bounding sphere lets the
    projection skip whole groups outside the view. ``perm`` maps rows back to model indices.

    Attributes (N = Gaussians, G = groups):
        perm: (N,) int64 model index of each row.
        means: (N, 3) float64 centres [m, map frame].
        cov3d: (N, 6) float64 upper triangle (xx, xy, xz, yy, yz, zz) of R S S^T R^T [m^2].
        opacities: (N,) float64 activated opacities in (0, 1).
        sh: (N, K, 3) float32 SH coefficients (K = (degree + 1)^2).
        max_std: (N,) float64 largest axis standard deviation [m] (for conservative frustum culling).
        base_rgb: (N, 3) float64 max(0, SH_0 + 0.5): the colour when the SH degree is 0
            (view-independent, so computed once).
        group_offsets: (G + 1,) int64 row ranges of the groups.
        group_spheres: (G, 5) float64 (centre x, y, z, radius of the centres, largest std) [m].
    """

    perm: np.ndarray
    means: np.ndarray
    cov3d: np.ndarray
    opacities: np.ndarray
    sh: np.ndarray
    max_std: np.ndarray
    base_rgb: np.ndarray
    group_offsets: np.ndarray
    group_spheres: np.ndarray

    @classmethod
    def from_model(cls, model: "GaussianModel") -> "GaussianGeometry":
        means = np.asarray(model.means, dtype=np.float64)
        perm = _morton_order(means)
        cov = model.covariances()[perm]
        cov3d = np.stack([cov[:, 0, 0], cov[:, 0, 1], cov[:, 0, 2],
                          cov[:, 1, 1], cov[:, 1, 2], cov[:, 2, 2]], axis=1)
        means = np.ascontiguousarray(means[perm])
        max_std = np.ascontiguousarray(np.max(np.asarray(model.scales, dtype=np.float64), axis=1)[perm])
        offsets = np.arange(0, len(perm) + GROUP_SIZE, GROUP_SIZE).clip(max=len(perm))
        offsets = np.unique(offsets)
        lo = np.minimum.reduceat(means, offsets[:-1], axis=0)
        hi = np.maximum.reduceat(means, offsets[:-1], axis=0)
        spheres = np.concatenate([(lo + hi) / 2, np.linalg.norm(hi - lo, axis=1, keepdims=True) / 2,
                                  np.maximum.reduceat(max_std, offsets[:-1])[:, None]], axis=1)
        sh = np.asarray(model.sh, dtype=np.float32)[perm]
        return cls(
            perm=perm.astype(np.int64),
            means=means,
            cov3d=np.ascontiguousarray(cov3d),
            opacities=np.ascontiguousarray(np.asarray(model.opacities, dtype=np.float64)[perm]),
            sh=np.ascontiguousarray(sh),
            max_std=max_std,
            base_rgb=np.ascontiguousarray(np.maximum(eval_sh(sh[:, :1].astype(np.float64), None) + 0.5, 0.0)),
            group_offsets=offsets.astype(np.int64),
            group_spheres=np.ascontiguousarray(spheres),
        )

    @property
    def num_gaussians(self) -> int:
        return int(self.means.shape[0])


def _morton_order(points: np.ndarray) -> np.ndarray:
    """Permutation sorting (N, 3) points along a 3D Z-order curve (10 bits per axis)."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    q = ((points - lo) / np.maximum(hi - lo, 1e-12) * 1023).astype(np.uint64)
    code = np.zeros(len(points), dtype=np.uint64)
    for bit in range(10):
        for axis in range(3):
            code |= ((q[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    return np.argsort(code, kind="stable")


@dataclass(frozen=True)
class ProjectedGaussians:
    """Gaussians that can touch the image.

    Rows are stored in screen-space order (by the 32 x 32 px block of the projected centre) so
    that the per-tile lists of neighbouring tiles touch neighbouring rows (cache locality in the
    kernels); ``depth_order`` gives the front-to-back order.

    Attributes (M = number kept):
        ids: (M,) int64 indices into the model.
        depth_order: (M,) int32 row indices sorted front to back by camera depth.
        packed: (M, 8) float64 rows (u, v, a, b, c, opacity, qmax, depth), one cache line per
            Gaussian for the compositing kernels: (u, v) projected centre [px] (u right, v down,
            pixel centres at integers); (a, b, c) inverse screen covariance [1/px^2]; qmax the
            largest Mahalanobis q = d^T conic d at which alpha >= 1/255; depth camera z [m].
        bbox: (M, 4) int32 inclusive pixel box (u_min, u_max, v_min, v_max) of that ellipse.
        colors: (M, 3) float64 view-dependent RGB in [0, inf) (SH + 0.5, clamped at 0).
        walk: (M, 8) float64 rows (u, v, a, b, c, opacity, qmax, -b / a): what the compositing walk reads of a
            Gaussian, one cache line (:mod:`.composite`).
    """

    ids: np.ndarray
    depth_order: np.ndarray
    packed: np.ndarray
    bbox: np.ndarray
    colors: np.ndarray
    walk: np.ndarray

    @property
    def count(self) -> int:
        return int(self.ids.shape[0])

    @property
    def means2d(self) -> np.ndarray:
        return self.packed[:, 0:2]

    @property
    def conics(self) -> np.ndarray:
        return self.packed[:, 2:5]

    @property
    def opacities(self) -> np.ndarray:
        return self.packed[:, 5]

    @property
    def qmax(self) -> np.ndarray:
        return self.packed[:, 6]


_fov_limits = njit(inline="always")(fov_limits)
_ewa_splat = njit(inline="always")(ewa_splat)
_store_splat = njit(inline="always")(store_splat)
_view_direction = njit(inline="always")(view_direction)
_sh_polynomial = njit(inline="always")(sh_polynomial)


@njit(parallel=True, cache=True, nogil=True)
def _project_kernel(means, cov3d, opac, max_std, base_rgb, group_offsets, group_spheres,
                    cam, width, height, out, out_bbox, out_valid):  # pragma: no cover
    """Project every group that can touch the image (:func:`css_ros.engine.splat_math.ewa_splat` per
    Gaussian); cam is the view's (CAM_COLS,) row."""
    lo_x, hi_x, lo_y, hi_y, jac_sq = _fov_limits(cam, width, height)
    fx, fy, cx, cy = cam[12], cam[13], cam[14], cam[15]
    # Group test, implied by the per-Gaussian early cull of ewa_splat: that cull keeps a Gaussian only
    # if its centre lies within `bound` px of the image, bound <= 3 sqrt(jac_sq) s / z + MARGIN_PX,
    # i.e. x <= (t + MARGIN_PX / f) z + 3 sqrt(jac_sq) / f * s for the right edge slope t (likewise
    # for the other edges). A group whose bounding sphere of centres violates one of these for its
    # largest std s can be skipped as a whole; so can one entirely behind the near plane.
    margin_px = 3.0 * math.sqrt(COV2D_DILATION) + 1.0
    kx = 3.0 * math.sqrt(jac_sq) / fx
    ky = 3.0 * math.sqrt(jac_sq) / fy
    right = (width - 0.5 - cx) / fx + margin_px / fx
    left = -(cx + 0.5) / fx - margin_px / fx
    bottom = (height - 0.5 - cy) / fy + margin_px / fy
    top = -(cy + 0.5) / fy - margin_px / fy
    for g in prange(group_offsets.shape[0] - 1):
        gx, gy, gz = group_spheres[g, 0], group_spheres[g, 1], group_spheres[g, 2]
        rad, s_max = group_spheres[g, 3], group_spheres[g, 4]
        x = cam[0] * gx + cam[1] * gy + cam[2] * gz + cam[9]
        y = cam[3] * gx + cam[4] * gy + cam[5] * gz + cam[10]
        z = cam[6] * gx + cam[7] * gy + cam[8] * gz + cam[11]
        if z + rad <= NEAR_PLANE:
            continue
        if x - right * z - rad * math.sqrt(1.0 + right * right) > kx * s_max:
            continue
        if x - left * z + rad * math.sqrt(1.0 + left * left) < -kx * s_max:
            continue
        if y - bottom * z - rad * math.sqrt(1.0 + bottom * bottom) > ky * s_max:
            continue
        if y - top * z + rad * math.sqrt(1.0 + top * top) < -ky * s_max:
            continue
        for i in range(group_offsets[g], group_offsets[g + 1]):
            splat = _ewa_splat(cam, means, cov3d, i, opac[i], max_std[i], width, height, lo_x, hi_x, lo_y, hi_y, jac_sq)
            if not splat[0]:
                continue
            _store_splat(out, out_bbox, i, splat, opac[i])
            out[i, 8] = base_rgb[i, 0]
            out[i, 9] = base_rgb[i, 1]
            out[i, 10] = base_rgb[i, 2]
            out_valid[i] = True


class ProjectionScratch:
    """Per-Gaussian output buffers of the projection kernel, and the projected rows' arrays (:mod:`.kept`), reused
    across frames (fresh allocations of N x 8 doubles would page-fault every frame). One per thread of use: a
    :class:`ProjectedGaussians` made with a scratch is valid until the next :func:`project` with it."""

    def __init__(self) -> None:
        self.n = -1
        self.out = np.empty((0, 11))
        self.bbox = np.empty((0, 4), dtype=np.int32)
        self.valid = np.empty(0, dtype=np.bool_)
        self.rows = Kept(_new_rows)

    def get(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if n != self.n:
            self.out = np.empty((n, 11))
            self.bbox = np.empty((n, 4), dtype=np.int32)
            self.valid = np.empty(n, dtype=np.bool_)
            self.n = n
        return self.out, self.bbox, self.valid


def _new_rows(m: int) -> tuple[np.ndarray, ...]:
    """Uninitialised (packed, walk, colors, bbox, view colours) arrays of m projected rows."""
    return np.empty((m, 8)), np.empty((m, 8)), np.empty((m, 3)), np.empty((m, 4), dtype=np.int32), np.empty((m, 3))


@njit(cache=True, nogil=True)
def _block_order(ids, bbox, block_x, num_blocks):  # pragma: no cover
    """Stable counting sort of the kept ids by the screen block of their box centre."""
    m = ids.shape[0]
    keys = np.empty(m, dtype=np.int64)
    counts = np.zeros(num_blocks + 1, dtype=np.int64)
    for r in range(m):
        i = ids[r]
        key = ((bbox[i, 2] + bbox[i, 3]) // (2 * BLOCK)) * block_x + (bbox[i, 0] + bbox[i, 1]) // (2 * BLOCK)
        keys[r] = key
        counts[key + 1] += 1
    for b in range(num_blocks):
        counts[b + 1] += counts[b]
    ordered = np.empty(m, dtype=np.int64)
    for r in range(m):
        ordered[counts[keys[r]]] = ids[r]
        counts[keys[r]] += 1
    return ordered


@njit(parallel=True, cache=True, nogil=True)
def _gather(ids, out, bbox, packed, walk, colors, boxes):  # pragma: no cover
    """The kernel's rows ``ids`` into the projected rows' arrays (:class:`ProjectedGaussians`)."""
    m = ids.shape[0]
    for r in prange(m):
        prefetch_ahead(out, ids, r)  # block order: the rows lie scattered
        prefetch_ahead(bbox, ids, r)
        i = ids[r]
        for c in range(8):
            packed[r, c] = out[i, c]
        for c in range(7):
            walk[r, c] = out[i, c]
        walk[r, 7] = -out[i, 3] / out[i, 2]
        for c in range(3):
            colors[r, c] = out[i, 8 + c]
        for c in range(4):
            boxes[r, c] = bbox[i, c]


@njit(cache=True, nogil=True)
def _argsort_positive(values):  # pragma: no cover
    """Stable argsort of positive float64 values. LSD radix sort (2 x 16 bits) of the IEEE bits of
    their float32 roundings, which order like the values for positive floats; rounding to float32
    is monotone, so only runs of equal float32 keys can be out of order, and a final stable
    insertion pass over the float64 values puts those right (O(m) when such runs are short)."""
    m = values.shape[0]
    keys = values.astype(np.float32).view(np.uint32)
    order = np.arange(m).astype(np.int32)
    tmp = np.empty(m, dtype=np.int32)
    counts = np.empty(65537, dtype=np.int64)
    for shift in range(0, 32, 16):
        counts[:] = 0
        for r in range(m):
            counts[((keys[r] >> np.uint32(shift)) & np.uint32(0xFFFF)) + 1] += 1
        if counts[1 + ((keys[0] >> np.uint32(shift)) & np.uint32(0xFFFF))] == m:
            continue  # every key has the same digit: nothing to do
        for b in range(65536):
            counts[b + 1] += counts[b]
        for r in range(m):
            d = (keys[order[r]] >> np.uint32(shift)) & np.uint32(0xFFFF)
            tmp[counts[d]] = order[r]
            counts[d] += 1
        order, tmp = tmp, order
    for r in range(1, m):
        j = order[r]
        x = values[j]
        s = r
        while s > 0 and values[order[s - 1]] > x:
            order[s] = order[s - 1]
            s -= 1
        order[s] = j
    return order


def project(geometry: GaussianGeometry, camera: "Camera", scratch: ProjectionScratch | None = None,
            view_colors: bool = True) -> ProjectedGaussians:
    """Project, cull (near plane, 3-sigma square outside the image, alpha never >= 1/255) and
    depth-sort the Gaussians for ``camera``; evaluate their view-dependent colours.

    Args:
        scratch: per-Gaussian buffers reused across calls (one per thread); the result lives in it, valid until
            the next call with the same scratch (None: fresh arrays).
        view_colors: False skips the SH degree >= 1 evaluation (colours are then the degree-0
            term), for views whose colour is not rendered.
    """
    out, out_bbox, out_valid = (scratch or ProjectionScratch()).get(geometry.num_gaussians)
    cam = camera_row(camera)
    out_valid[:] = False
    _project_kernel(geometry.means, geometry.cov3d, geometry.opacities, geometry.max_std, geometry.base_rgb,
                    geometry.group_offsets, geometry.group_spheres, cam,
                    float(camera.width), float(camera.height), out, out_bbox, out_valid)
    block_x = (int(camera.width) + BLOCK - 1) // BLOCK
    block_y = (int(camera.height) + BLOCK - 1) // BLOCK
    rows = _block_order(np.flatnonzero(out_valid), out_bbox, block_x, block_x * block_y)
    packed, walk, colors, bbox, sh_colors = _new_rows(len(rows)) if scratch is None else scratch.rows.take(len(rows))
    _gather(rows, out, out_bbox, packed, walk, colors, bbox)
    depth_order = _argsort_positive(np.ascontiguousarray(packed[:, 7])) if len(rows) else np.empty(0, np.int32)
    if view_colors and geometry.sh.shape[1] > 1:  # view-dependent colour; degree 0 came with the kernel's rows
        colors = sh_colors
        _view_colors_kernel(geometry.sh, geometry.means, rows, cam, colors)
    return ProjectedGaussians(ids=geometry.perm[rows], depth_order=depth_order, packed=packed, bbox=bbox, colors=colors,
                              walk=walk)


@njit(parallel=True, cache=True, nogil=True)
def _view_colors_kernel(sh, means, rows, cam, out):  # pragma: no cover
    """out = (M, 3) float64 colour max(0, SH(d) + 0.5) of the geometry ``rows``, d = unit direction camera ->
    Gaussian (:func:`css_ros.engine.sh.sh_polynomial`, fused with the gather and the clamp: numpy's
    version allocates a temporary per term, ~25 ms for 50k degree-3 Gaussians).

    Args:
        sh: (N, K, 3) float32 coefficients; means: (N, 3) map frame; rows: (M,) rows to evaluate;
        cam: the view's (CAM_COLS,) row (its centre, map frame).
    """
    m = rows.shape[0]
    k = sh.shape[1]
    flat = sh.reshape((sh.shape[0], k * 3))
    for r in prange(m):
        prefetch_ahead(flat, rows, r)  # block order: the rows lie scattered
        prefetch_ahead(means, rows, r)
        i = rows[r]
        x, y, z = _view_direction(cam, means, i)
        for c in range(3):
            out[r, c] = max(_sh_polynomial(sh[i, :, c], k, x, y, z) + 0.5, 0.0)


bind_sources(globals())  # cached kernels recompile when any module they are built from changes
