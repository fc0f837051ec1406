"""Stages 2-3 of the pipeline on the CPU: tile binning and the compiled per-pixel compositing kernels.

Every kernel walks a pixel's depth-sorted Gaussian list with the INRIA rules of SPEC §3 and derives
the weights kappa_in = a_n T_n on the fly; nothing of size (pixels x Gaussians) is ever stored.
A Gaussian contributes to exactly the pixels where its alpha reaches 1/255 (its binning box covers
that ellipse), so the result does not depend on the tile size and equals a per-pixel brute force.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
from numba import njit, prange

from .projection import ALPHA_MAX, ALPHA_MIN, T_MIN, ProjectedGaussians

TILE_SIZE = 16  # px


@dataclass(frozen=True)
class TileBins:
    """Per-tile Gaussian lists (front to back), CSR layout.

    Attributes:
        offsets: (T + 1,) int64; tile t's list is ``lists[offsets[t]:offsets[t + 1]]``.
        lists: (P,) int32 indices into the ProjectedGaussians arrays (not model ids).
        tiles_x, tiles_y: tile grid size; tile t covers columns [tx*S, tx*S+S) and rows [ty*S, ty*S+S).
    """

    offsets: np.ndarray
    lists: np.ndarray
    tiles_x: int
    tiles_y: int
    tile_size: int


@njit(cache=True)
def _bin_kernel(bbox, tiles_x, tiles_y, tile):  # pragma: no cover
    m = bbox.shape[0]
    num_tiles = tiles_x * tiles_y
    offsets = np.zeros(num_tiles + 1, dtype=np.int64)
    for j in range(m):
        for ty in range(bbox[j, 2] // tile, bbox[j, 3] // tile + 1):
            for tx in range(bbox[j, 0] // tile, bbox[j, 1] // tile + 1):
                offsets[ty * tiles_x + tx + 1] += 1
    for t in range(num_tiles):
        offsets[t + 1] += offsets[t]
    fill = offsets[:-1].copy()
    lists = np.empty(offsets[-1], dtype=np.int32)
    for j in range(m):  # j ascends in depth, so each tile list is front to back
        for ty in range(bbox[j, 2] // tile, bbox[j, 3] // tile + 1):
            for tx in range(bbox[j, 0] // tile, bbox[j, 1] // tile + 1):
                t = ty * tiles_x + tx
                lists[fill[t]] = j
                fill[t] += 1
    return offsets, lists


def bin_tiles(proj: ProjectedGaussians, width: int, height: int, tile_size: int = TILE_SIZE) -> TileBins:
    """Counting-sort the depth-sorted Gaussians into the tiles their alpha >= 1/255 box overlaps."""
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    offsets, lists = _bin_kernel(proj.bbox, tiles_x, tiles_y, tile_size)
    return TileBins(offsets, lists, tiles_x, tiles_y, tile_size)


@njit(inline="always")
def _alpha(u, v, j, xy, conic, opac, qmax):  # pragma: no cover
    dx = u - xy[j, 0]
    dy = v - xy[j, 1]
    q = conic[j, 0] * dx * dx + 2.0 * conic[j, 1] * dx * dy + conic[j, 2] * dy * dy
    if q > qmax[j]:
        return 0.0
    return min(ALPHA_MAX, opac[j] * math.exp(-0.5 * q))


@njit(parallel=True, cache=True)
def _update_kernel(offsets, lists, xy, conic, opac, qmax, labels, weights, width, height,
                   tile, tiles_x, acc):  # pragma: no cover
    """acc[chunk, j, c] += sum over pixels (labelled c) of kappa_ij * weight_i; chunk-private rows."""
    nchunks = acc.shape[0]
    num_tiles = offsets.shape[0] - 1
    for ch in prange(nchunks):
        for t in range(ch, num_tiles, nchunks):
            start, end = offsets[t], offsets[t + 1]
            if start == end:
                continue
            ty, tx = t // tiles_x, t % tiles_x
            for v in range(ty * tile, min(height, ty * tile + tile)):
                for u in range(tx * tile, min(width, tx * tile + tile)):
                    lab = labels[v, u]
                    w = weights[v, u]
                    if lab < 0 or not (w > 0.0):
                        continue
                    trans = 1.0
                    for k in range(start, end):
                        j = lists[k]
                        a = _alpha(u, v, j, xy, conic, opac, qmax)
                        if a < ALPHA_MIN:
                            continue
                        test_t = trans * (1.0 - a)
                        if test_t < T_MIN:
                            break
                        acc[ch, j, lab] += a * trans * w
                        trans = test_t


@njit(parallel=True, cache=True)
def _render_kernel(offsets, lists, xy, conic, opac, qmax, colors, expect, var, totals,
                   e_bg, v_bg, s_bg, bg_rgb, width, height, tile, tiles_x, want_probs,
                   out_label, out_exp, out_var, out_bg, out_evidence, out_rgb, out_probs):  # pragma: no cover
    num_tiles = offsets.shape[0] - 1
    num_classes = expect.shape[1]
    for t in prange(num_tiles):
        start, end = offsets[t], offsets[t + 1]
        n = max(end - start, 1)
        kbuf = np.empty(n)
        jbuf = np.empty(n, dtype=np.int32)
        eacc = np.empty(num_classes)
        ty, tx = t // tiles_x, t % tiles_x
        for v in range(ty * tile, min(height, ty * tile + tile)):
            for u in range(tx * tile, min(width, tx * tile + tile)):
                eacc[:] = 0.0
                r = 0.0
                g = 0.0
                b = 0.0
                evidence = 0.0
                trans = 1.0
                cnt = 0
                for k in range(start, end):
                    j = lists[k]
                    a = _alpha(u, v, j, xy, conic, opac, qmax)
                    if a < ALPHA_MIN:
                        continue
                    test_t = trans * (1.0 - a)
                    if test_t < T_MIN:
                        break
                    kappa = a * trans
                    r += kappa * colors[j, 0]
                    g += kappa * colors[j, 1]
                    b += kappa * colors[j, 2]
                    evidence += kappa * totals[j]
                    for c in range(num_classes):
                        eacc[c] += kappa * expect[j, c]
                    kbuf[cnt] = kappa
                    jbuf[cnt] = j
                    cnt += 1
                    trans = test_t
                best = 0
                for c in range(1, num_classes):
                    if eacc[c] > eacc[best]:
                        best = c
                vhat = trans * trans * v_bg
                for m in range(cnt):
                    vhat += kbuf[m] * kbuf[m] * var[jbuf[m], best]
                out_label[v, u] = best
                out_exp[v, u] = eacc[best] + trans * e_bg
                out_var[v, u] = vhat
                out_bg[v, u] = trans
                out_evidence[v, u] = evidence + trans * s_bg
                out_rgb[v, u, 0] = r + trans * bg_rgb[0]
                out_rgb[v, u, 1] = g + trans * bg_rgb[1]
                out_rgb[v, u, 2] = b + trans * bg_rgb[2]
                if want_probs:
                    for c in range(num_classes):
                        out_probs[v, u, c] = eacc[c] + trans * e_bg


@njit(cache=True)
def _kappa_kernel(offsets, lists, xy, conic, opac, qmax, width, height, tile, tiles_x,
                  count_only, pix, gid, kap, bg):  # pragma: no cover
    num_tiles = offsets.shape[0] - 1
    p = 0
    for t in range(num_tiles):
        start, end = offsets[t], offsets[t + 1]
        ty, tx = t // tiles_x, t % tiles_x
        for v in range(ty * tile, min(height, ty * tile + tile)):
            for u in range(tx * tile, min(width, tx * tile + tile)):
                trans = 1.0
                for k in range(start, end):
                    j = lists[k]
                    a = _alpha(u, v, j, xy, conic, opac, qmax)
                    if a < ALPHA_MIN:
                        continue
                    test_t = trans * (1.0 - a)
                    if test_t < T_MIN:
                        break
                    if not count_only:
                        pix[p] = v * width + u
                        gid[p] = j
                        kap[p] = a * trans
                    p += 1
                    trans = test_t
                if not count_only:
                    bg[v * width + u] = trans
    return p


@dataclass(frozen=True)
class KappaLists:
    """Sparse kappa of one view (COO): kappa[p] is the weight of Gaussian ``gaussian[p]`` (model id)
    in pixel ``pixel[p]`` (= v * W + u); ``background`` (H*W,) is kappa_b = final transmittance."""

    pixel: np.ndarray
    gaussian: np.ndarray
    kappa: np.ndarray
    background: np.ndarray


def kappa_lists(proj: ProjectedGaussians, bins: TileBins, width: int, height: int) -> KappaLists:
    """All non-zero kappa_in of a view as sparse lists (for analysis and tests; O(contributions))."""
    args = (bins.offsets, bins.lists, proj.means2d, proj.conics, proj.opacities, proj.qmax,
            width, height, bins.tile_size, bins.tiles_x)
    empty_i = np.empty(0, dtype=np.int64)
    n = _kappa_kernel(*args, True, empty_i, np.empty(0, np.int32), np.empty(0), np.empty(0))
    pix = np.empty(n, dtype=np.int64)
    gid = np.empty(n, dtype=np.int32)
    kap = np.empty(n)
    bg = np.ones(width * height)
    _kappa_kernel(*args, False, pix, gid, kap, bg)
    return KappaLists(pix, proj.ids[gid], kap, bg)


def accumulate_update(proj: ProjectedGaussians, bins: TileBins, labels: np.ndarray, weights: np.ndarray,
                      num_classes: int) -> np.ndarray:
    """Per visible Gaussian, sum_i kappa_in * y_i^c.

    Args:
        labels: (H, W) int32 class id per pixel, -1 where the pixel contributes nothing.
        weights: (H, W) float32 confidence per pixel (1 without a confidence image).
    Returns:
        (M, C) float64 increments for ``proj.ids`` rows of the concentrations.
    """
    height, width = labels.shape
    nchunks = max(1, min(numba.get_num_threads(), bins.tiles_x * bins.tiles_y))
    acc = np.zeros((nchunks, proj.count, num_classes), dtype=np.float32)
    _update_kernel(bins.offsets, bins.lists, proj.means2d, proj.conics, proj.opacities, proj.qmax,
                   labels, weights, width, height, bins.tile_size, bins.tiles_x, acc)
    return acc.sum(axis=0, dtype=np.float64)


@dataclass
class RenderBuffers:
    """Raw per-pixel outputs of the render kernel (see SemanticMap.render for meaning)."""

    labels: np.ndarray        # (H, W) int32
    expectation: np.ndarray   # (H, W) float64
    variance: np.ndarray      # (H, W) float64
    background: np.ndarray    # (H, W) float64
    evidence: np.ndarray      # (H, W) float64
    rgb: np.ndarray           # (H, W, 3) float64 in [0, inf)
    probabilities: np.ndarray | None  # (H, W, C) float64


def render_semantic(proj: ProjectedGaussians, bins: TileBins, width: int, height: int,
                    expect: np.ndarray, var: np.ndarray, totals: np.ndarray,
                    e_bg: float, v_bg: float, s_bg: float, bg_rgb: np.ndarray,
                    want_probs: bool) -> RenderBuffers:
    """Composite colour, expectation, argmax-class variance and evidence (SPEC §5).

    Args:
        expect, var: (M, C) float64 E[theta_n^c] and Var[theta_n^c] of the projected Gaussians.
        totals: (M,) float64 Dirichlet totals S_n.
        e_bg, v_bg, s_bg: background expectation, variance (per class) and total.
    """
    num_classes = expect.shape[1]
    out_label = np.empty((height, width), dtype=np.int32)
    out_exp = np.empty((height, width))
    out_var = np.empty((height, width))
    out_bg = np.empty((height, width))
    out_ev = np.empty((height, width))
    out_rgb = np.empty((height, width, 3))
    out_probs = np.empty((height, width, num_classes) if want_probs else (1, 1, num_classes))
    _render_kernel(bins.offsets, bins.lists, proj.means2d, proj.conics, proj.opacities, proj.qmax,
                   proj.colors, expect, var, totals, e_bg, v_bg, s_bg,
                   np.asarray(bg_rgb, dtype=np.float64), width, height, bins.tile_size, bins.tiles_x,
                   want_probs, out_label, out_exp, out_var, out_bg, out_ev, out_rgb, out_probs)
    return RenderBuffers(out_label, out_exp, out_var, out_bg, out_ev, out_rgb,
                         out_probs if want_probs else None)
