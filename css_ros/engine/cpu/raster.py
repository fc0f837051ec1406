"""Stages 2-3 of the pipeline on the CPU: tile binning and the compiled per-pixel compositing kernels.

Every kernel walks a pixel's depth-sorted Gaussian list with the INRIA rules of SPEC §3 and derives
the weights kappa_in = a_n T_n on the fly; nothing of size (pixels x Gaussians) is ever stored.
A Gaussian contributes to exactly the pixels where its alpha reaches 1/255 (its binning box covers
that ellipse), so the result does not depend on the tile size and equals a per-pixel brute force.

Performance notes (see benchmarks/README.md): each tile first copies its Gaussians' packed rows
(u, v, conic, opacity, qmax) into a contiguous local block, so the per-pixel walk reads memory
sequentially; tiles are 8 x 8 px (shorter candidate lists per pixel than 16 x 16); the update pass
of ``observe`` records each pixel's (Gaussian, kappa) list in a bounded per-pixel slot buffer that
the render pass replays instead of walking and exponentiating again.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numba
import numpy as np
from numba import njit, prange

from ..buffers import RenderBuffers
from ..pixel_math import depth_bin
from ..spec import ALPHA_MAX, ALPHA_MIN, T_MIN, TILE_SIZE
from .projection import ProjectedGaussians

if TYPE_CHECKING:
    from ..sensor_model import SoftLabels

# Floating-point reassociation and contraction (FMA) for the hot loops; no-NaN/no-Inf assumptions are
# not made (inputs are sanitised, but comparisons against NaN must keep their meaning).
_FAST = {"contract", "reassoc", "arcp"}
_ROW = 7             # columns of the packed rows used by the kernels: u v a b c opacity qmax
_COLS = _ROW + 2     # tile-local columns: the _ROW ones, then the first and last pixel row of the alpha box


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


@njit(parallel=True, cache=True, nogil=True)
def _bin_kernel(bbox, depth_order, tiles_x, tiles_y, tile, parts):  # pragma: no cover
    """Parallel counting sort of (tile, depth) pairs: the depth order is cut into ``parts``
    consecutive ranges; each counts and then fills its own slice of every tile's list, part 0's
    (nearest) entries first, so every list stays front to back. Each Gaussian's tile range is
    computed once, in depth order, so both passes read it sequentially."""
    m = bbox.shape[0]
    num_tiles = tiles_x * tiles_y
    span = np.empty((m, 4), dtype=np.int32)
    for r in prange(m):
        j = depth_order[r]
        for c in range(4):
            span[r, c] = bbox[j, c] // tile
    counts = np.zeros((parts, num_tiles), dtype=np.int64)
    for p in prange(parts):
        for r in range(p * m // parts, (p + 1) * m // parts):
            for ty in range(span[r, 2], span[r, 3] + 1):
                for tx in range(span[r, 0], span[r, 1] + 1):
                    counts[p, ty * tiles_x + tx] += 1
    offsets = np.zeros(num_tiles + 1, dtype=np.int64)
    fill = np.empty((parts, num_tiles), dtype=np.int64)
    for t in range(num_tiles):
        pos = offsets[t]
        for p in range(parts):
            fill[p, t] = pos
            pos += counts[p, t]
        offsets[t + 1] = pos
    lists = np.empty(offsets[-1], dtype=np.int32)
    for p in prange(parts):
        for r in range(p * m // parts, (p + 1) * m // parts):
            j = depth_order[r]
            for ty in range(span[r, 2], span[r, 3] + 1):
                for tx in range(span[r, 0], span[r, 1] + 1):
                    t = ty * tiles_x + tx
                    lists[fill[p, t]] = j
                    fill[p, t] += 1
    return offsets, lists


def bin_tiles(proj: ProjectedGaussians, width: int, height: int, tile_size: int = TILE_SIZE) -> TileBins:
    """Counting-sort the depth-sorted Gaussians into the tiles their alpha >= 1/255 box overlaps."""
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    offsets, lists = _bin_kernel(proj.bbox, proj.depth_order, tiles_x, tiles_y, tile_size,
                                 max(1, numba.get_num_threads()))
    return TileBins(offsets, lists, tiles_x, tiles_y, tile_size)


@njit(inline="always")
def _load_rows(src, lists, start, end, local):  # pragma: no cover
    """Copy rows ``src[lists[start:end]]`` into ``local`` (grown if needed); return it."""
    n = end - start
    cols = src.shape[1]
    if n > local.shape[0]:
        local = np.empty((n, cols), dtype=src.dtype)
    for k in range(n):
        j = lists[start + k]
        for c in range(cols):
            local[k, c] = src[j, c]
    return local


@njit(inline="always")
def _load_columns(packed, bbox, lists, start, end, local):  # pragma: no cover
    """Copy the tile's packed rows transposed into ``local`` (_COLS, >= n): one contiguous array
    per quantity (u, v, a, b, c, opacity, qmax, first row, last row), so the per-pixel candidate
    test vectorises. Returns ``local`` (grown if needed)."""
    n = end - start
    if n > local.shape[1]:
        local = np.empty((_COLS, n))
    for k in range(n):
        j = lists[start + k]
        for c in range(_ROW):
            local[c, k] = packed[j, c]
        local[_ROW, k] = bbox[j, 2]
        local[_ROW + 1, k] = bbox[j, 3]
    return local


@njit(inline="always")
def _new_scratch(tile):  # pragma: no cover
    """Per-thread compositing scratch (grown per tile by _load_columns / _grow_scratch):
    tile columns, q/alpha buffers, hit indices, per-pixel contribution lists, counts, T, active."""
    return (np.empty((_COLS, 256)), np.empty((_ROW + 3, 256)), np.empty((2, 256), dtype=np.int32),
            np.empty((tile, 256), dtype=np.int32), np.empty((tile, 256)), np.empty(tile, dtype=np.int32),
            np.empty(tile), np.empty(tile, dtype=np.bool_))


@njit(inline="always")
def _grow_scratch(n, kidx, kval, qbuf, hits):  # pragma: no cover
    """Per-row compositing scratch sized for a tile list of length n (reallocated only to grow)."""
    if n > kidx.shape[1]:
        tile = kidx.shape[0]
        return (np.empty((tile, n), dtype=np.int32), np.empty((tile, n)), np.empty((_ROW + 3, n)),
                np.empty((2, n), dtype=np.int32))
    return kidx, kval, qbuf, hits


@njit(inline="always", fastmath=_FAST)
def _exp_nonpositive(x):  # pragma: no cover
    """exp(x) for -6 <= x <= 0 (relative error < 2e-14): degree-10 Taylor polynomial of x/32, squared
    five times. Plain arithmetic, so a loop of it vectorises (libm's exp is a scalar call); every
    composited x = -q/2 with q <= qmax = 2 ln(255 o) <= 11.1 lies in range."""
    y = x * 0.03125
    p = 1.0 + y * (1.0 + y * (1.0 / 2.0 + y * (1.0 / 6.0 + y * (1.0 / 24.0 + y * (
        1.0 / 120.0 + y * (1.0 / 720.0 + y * (1.0 / 5040.0 + y * (1.0 / 40320.0 + y * (
            1.0 / 362880.0 + y * (1.0 / 3628800.0))))))))))
    p = p * p
    p = p * p
    p = p * p
    p = p * p
    return p * p


@njit(cache=True, fastmath=_FAST)
def _composite_row(g, n, v, u0, u1, active, cnt, kidx, kval, trans, qbuf, hits):  # pragma: no cover
    """Front-to-back compositing of pixels (u0..u1, v) over a tile's depth-sorted list (SPEC §3).

    The candidates whose alpha box spans row v are compacted (in order) into row-local columns
    first. Per pixel, the Mahalanobis distances q of those are computed in a branch-free loop
    (SIMD), the ones with q <= qmax (alpha >= 1/255) are compacted without branches, their alphas
    computed in a second SIMD loop, and only then composited in order with early termination.

    Args:
        g: (_COLS, >= n) columns (u, v, a, b, c, opacity, qmax, first row, last row) of the tile's list.
        active: (W_row,) bool; inactive pixels are skipped (cnt 0, T 1).
        qbuf: (_ROW + 3, >= n) float scratch; hits: (2, >= n) int32 scratch.
    Outputs:
        cnt[p]: number of contributions of pixel u0 + p; kidx[p, i] / kval[p, i]: their list
        index and kappa, front to back; trans[p]: final transmittance (kappa_b).
    """
    fv = float(v)
    g_first, g_last = g[_ROW], g[_ROW + 1]
    ridx, hit = hits[0], hits[1]
    r = 0
    for k in range(n):
        ridx[r] = k
        r += (g_first[k] <= fv) & (fv <= g_last[k])
    for j in range(r):
        k = ridx[j]
        for c in range(_ROW):
            qbuf[c, j] = g[c, k]
    gx, gy, ga, gb, gc, go, gq = qbuf[0], qbuf[1], qbuf[2], qbuf[3], qbuf[4], qbuf[5], qbuf[6]
    qall, hq, ho = qbuf[_ROW], qbuf[_ROW + 1], qbuf[_ROW + 2]
    for p in range(u1 - u0 + 1):
        cnt[p] = 0
        trans[p] = 1.0
        if not active[p]:
            continue
        fu = float(u0 + p)
        for k in range(r):
            dx = fu - gx[k]
            dy = fv - gy[k]
            qall[k] = ga[k] * dx * dx + 2.0 * gb[k] * dx * dy + gc[k] * dy * dy
        m = 0
        for k in range(r):
            hit[m] = k
            hq[m] = qall[k]
            ho[m] = go[k]
            m += qall[k] <= gq[k]
        for h in range(m):
            hq[h] = min(ALPHA_MAX, ho[h] * _exp_nonpositive(-0.5 * hq[h]))
        t = 1.0
        i = 0
        for h in range(m):
            # branch-free skip of alpha < 1/255 (only possible by rounding at the box edge)
            alpha = hq[h]
            ok = alpha >= ALPHA_MIN
            alpha = alpha if ok else 0.0
            test_t = t * (1.0 - alpha)
            if test_t < T_MIN:
                break
            kidx[p, i] = ridx[hit[h]]
            kval[p, i] = alpha * t
            i += ok
            t = test_t
        cnt[p] = i
        trans[p] = t


_depth_bin = njit(inline="always")(depth_bin)


@njit(parallel=True, cache=True, fastmath=_FAST)
def _update_kernel(offsets, lists, packed, bbox, labels, weights, width, height, tile, tiles_x, acc,
                   store, st_k, st_v, pix_off, pix_cnt, pix_t, use_model, edges, base, resid, acc_base,
                   no_depth):  # pragma: no cover
    """acc[chunk, j, c] += sum over pixels labelled c of kappa_ij * weight_i (chunk-private rows).

    With ``use_model`` (a sensor model), a pixel labelled y at expected depth d = sum kappa z / sum kappa
    (depth bin b of ``edges``, splat units) adds kappa_ij * weight_i * table[r, c] to every class c instead,
    r = y * B + b, with the table split as table[r, c] = base[r] + resid[r, c]: the part common to every class
    goes to acc_base[chunk, j] (added to every class by :func:`add_increments`), the sparse rest to acc. So a
    symmetric vote (p on the label, the same small share on every other class) costs what a one-hot vote
    costs. Labelled pixels without any contribution are counted in ``no_depth[chunk]`` (they add nothing).
    Without it the arithmetic is exactly the paper's update.

    With ``store``, each labelled pixel's contributions (tile-list index, kappa) are appended to its
    chunk's row of st_k / st_v (pix_off, pix_cnt, pix_t: offset, count, final T); pixels that were
    not composited or did not fit get pix_cnt = -1.
    """
    nchunks = acc.shape[0]
    num_tiles = offsets.shape[0] - 1
    cap = st_k.shape[1]
    num_bins = edges.shape[0] - 1 if use_model else 1
    for ch in prange(nchunks):
        local, qbuf, hits, kidx, kval, cnt, trans, active = _new_scratch(tile)
        num_classes = acc.shape[2]
        num_rows = num_classes * num_bins
        # Tile-local accumulator (label row, list position): the per-contribution scatter stays in
        # cache; only the rows present in the tile are zeroed and flushed to the chunk's rows. A row is a
        # class (paper's update) or a (label, depth bin) pair whose soft label the flush applies.
        lacc = np.empty((num_rows, 256))
        lbase = np.empty(256)
        ldepth = np.empty(256)
        present = np.empty(num_rows, dtype=np.bool_)
        pos = 0
        for t in range(ch, num_tiles, nchunks):
            start, end = offsets[t], offsets[t + 1]
            n = end - start
            ty, tx = t // tiles_x, t % tiles_x
            u0 = tx * tile
            u1 = min(width, u0 + tile) - 1
            if n > 0:
                local = _load_columns(packed, bbox, lists, start, end, local)
            if n > lacc.shape[1]:
                lacc = np.empty((num_rows, n))
                lbase = np.empty(n)
                ldepth = np.empty(n)
            depth_loaded = False
            kidx, kval, qbuf, hits = _grow_scratch(n, kidx, kval, qbuf, hits)
            present[:] = False
            for v in range(ty * tile, min(height, ty * tile + tile)):
                any_active = False
                for u in range(u0, u1 + 1):
                    ok = labels[v, u] >= 0 and weights[v, u] > 0.0
                    active[u - u0] = ok
                    any_active = any_active or ok
                if not any_active:
                    if store:
                        for u in range(u0, u1 + 1):
                            pix_cnt[v * width + u] = -1
                    continue
                _composite_row(local, n, v, u0, u1, active, cnt, kidx, kval, trans, qbuf, hits)
                for u in range(u0, u1 + 1):
                    p = u - u0
                    lab = labels[v, u]
                    w = weights[v, u]
                    if lab < 0 or not (w > 0.0):
                        if store:
                            pix_cnt[v * width + u] = -1
                        continue
                    c = cnt[p]
                    row = lab
                    if use_model:
                        if not depth_loaded:  # the tile list's camera depths, contiguous
                            for k in range(n):
                                ldepth[k] = packed[lists[start + k], 7]
                            depth_loaded = True
                        zsum = 0.0
                        ksum = 0.0
                        for i in range(c):
                            kv = kval[p, i]
                            zsum += kv * ldepth[kidx[p, i]]
                            ksum += kv
                        b = 0
                        if ksum > 0.0:
                            b = _depth_bin(zsum / ksum, edges)
                        else:
                            no_depth[ch] += 1
                        row = lab * num_bins + b
                    if not present[row]:
                        present[row] = True
                        for k in range(n):
                            lacc[row, k] = 0.0
                    for i in range(c):
                        lacc[row, kidx[p, i]] += kval[p, i] * w
                    if store:
                        q = v * width + u
                        if pos + c <= cap:
                            for i in range(c):
                                st_k[ch, pos + i] = kidx[p, i]
                                st_v[ch, pos + i] = kval[p, i]
                            pix_off[q] = pos
                            pix_cnt[q] = c
                            pix_t[q] = trans[p]
                            pos += c
                        else:
                            pix_cnt[q] = -1
            if use_model:
                any_base = False
                for r in range(num_rows):
                    if present[r]:
                        b0 = base[r]
                        if b0 != 0.0:
                            if not any_base:
                                any_base = True
                                for k in range(n):
                                    lbase[k] = 0.0
                            for k in range(n):
                                lbase[k] += lacc[r, k] * b0
                        for c in range(num_classes):
                            pc = resid[r, c]
                            if pc != 0.0:
                                for k in range(n):
                                    acc[ch, lists[start + k], c] += lacc[r, k] * pc
                if any_base:
                    for k in range(n):
                        acc_base[ch, lists[start + k]] += lbase[k]
            else:
                for c in range(num_classes):
                    if present[c]:
                        for k in range(n):
                            acc[ch, lists[start + k], c] += lacc[c, k]


@njit(inline="always", fastmath=_FAST)
def _shade_pixel(v, u, ks, vs, cnt, tr, lattr, acc, e_bg, v_bg, s_bg, bg_rgb, want_probs,
                 out_label, out_exp, out_var, out_bg, out_evidence, out_rgb, out_probs, out_depth):  # pragma: no cover
    """Accumulate one pixel's contributions (tile-list indices ks, kappas vs) into the outputs.

    lattr rows are (E_0..E_{C-1}, r, g, b, S, z, Var_0..Var_{C-1}) float32: one loop over the first
    C + 5 columns accumulates expectation, colour, evidence and kappa-weighted depth (the expected depth
    sum kappa z / sum kappa, with sum kappa = 1 - T; NaN without any contribution). Contributions are taken four at a
    time, so the accumulator round trip through memory (the loop over C + 4 columns is too short
    for LLVM's wide vector body) is paid once per four.
    """
    num_classes = (lattr.shape[1] - 5) // 2
    lin = num_classes + 5
    for c in range(lin):
        acc[c] = 0.0
    i = 0
    while i + 4 <= cnt:
        k0 = ks[i]
        k1 = ks[i + 1]
        k2 = ks[i + 2]
        k3 = ks[i + 3]
        w0 = np.float32(vs[i])
        w1 = np.float32(vs[i + 1])
        w2 = np.float32(vs[i + 2])
        w3 = np.float32(vs[i + 3])
        for c in range(lin):
            acc[c] += (w0 * lattr[k0, c] + w1 * lattr[k1, c]) + (w2 * lattr[k2, c] + w3 * lattr[k3, c])
        i += 4
    while i < cnt:
        k0 = ks[i]
        w0 = np.float32(vs[i])
        for c in range(lin):
            acc[c] += w0 * lattr[k0, c]
        i += 1
    best = 0
    for c in range(1, num_classes):
        if acc[c] > acc[best]:
            best = c
    vhat = tr * tr * v_bg
    for i in range(cnt):
        kappa = vs[i]
        vhat += kappa * kappa * lattr[ks[i], lin + best]
    out_label[v, u] = best
    out_exp[v, u] = acc[best] + tr * e_bg
    out_var[v, u] = vhat
    out_bg[v, u] = tr
    out_evidence[v, u] = acc[num_classes + 3] + tr * s_bg
    out_rgb[v, u, 0] = acc[num_classes] + tr * bg_rgb[0]
    out_rgb[v, u, 1] = acc[num_classes + 1] + tr * bg_rgb[1]
    out_rgb[v, u, 2] = acc[num_classes + 2] + tr * bg_rgb[2]
    out_depth[v, u] = acc[num_classes + 4] / (1.0 - tr) if cnt > 0 else np.nan
    if want_probs:
        for c in range(num_classes):
            out_probs[v, u, c] = acc[c] + tr * e_bg


@njit(inline="always")
def _add_mass(ks, vs, cnt, lists, start, label, depth, edges, weights, mass):  # pragma: no cover
    """mass[lists[start + ks[i]]] += vs[i] * weights[label * B + b] (b: the depth bin of ``depth`` in ``edges``)."""
    if cnt == 0:
        return
    w = weights[label * (edges.shape[0] - 1) + _depth_bin(depth, edges)]
    if w == 0.0:
        return
    for i in range(cnt):
        mass[lists[start + ks[i]]] += vs[i] * w


@njit(parallel=True, cache=True, nogil=True, fastmath=_FAST)
def _render_kernel(offsets, lists, packed, bbox, attrs, e_bg, v_bg, s_bg, bg_rgb, width, height,
                   tile, tiles_x, want_probs, nchunks, use_store, st_k, st_v, pix_off, pix_cnt, pix_t,
                   out_label, out_exp, out_var, out_bg, out_evidence, out_rgb, out_probs,
                   out_depth, want_mass, mass_edges, mass_w, mass):  # pragma: no cover
    """attrs rows: (E_0..E_{C-1}, r, g, b, S, z, Var_0..Var_{C-1}). With ``use_store``,
    pixels recorded by the update pass (pix_cnt >= 0) replay their contributions.

    With ``want_mass``, mass[chunk, j] += kappa_ij * mass_w[label_i * B + b_i] over the pixels i of the view: the
    evidence observing it would add to Gaussian j (label_i = the rendered argmax, b_i the bin of the rendered depth
    in ``mass_edges``; without a sensor model B = 1 and mass_w = 1: the kappa mass)."""
    num_tiles = offsets.shape[0] - 1
    num_classes = (attrs.shape[1] - 5) // 2
    for ch in prange(nchunks):
        local, qbuf, hits, kidx, kval, cnt, trans, active = _new_scratch(tile)
        lattr = np.empty((256, attrs.shape[1]), dtype=attrs.dtype)
        eacc = np.empty(num_classes + 5, dtype=np.float32)
        for t in range(ch, num_tiles, nchunks):
            start, end = offsets[t], offsets[t + 1]
            n = end - start
            lattr = _load_rows(attrs, lists, start, end, lattr)
            loaded = False
            kidx, kval, qbuf, hits = _grow_scratch(n, kidx, kval, qbuf, hits)
            ty, tx = t // tiles_x, t % tiles_x
            u0 = tx * tile
            u1 = min(width, u0 + tile) - 1
            for v in range(ty * tile, min(height, ty * tile + tile)):
                need = False
                for u in range(u0, u1 + 1):
                    a = not use_store or pix_cnt[v * width + u] < 0
                    active[u - u0] = a
                    need = need or a
                if need:
                    if not loaded:
                        local = _load_columns(packed, bbox, lists, start, end, local)
                        loaded = True
                    _composite_row(local, n, v, u0, u1, active, cnt, kidx, kval, trans, qbuf, hits)
                for u in range(u0, u1 + 1):
                    p = u - u0
                    q = v * width + u
                    if use_store and pix_cnt[q] >= 0:
                        off = pix_off[q]
                        c = pix_cnt[q]
                        _shade_pixel(v, u, st_k[ch, off:off + c], st_v[ch, off:off + c], c, pix_t[q], lattr, eacc,
                                     e_bg, v_bg, s_bg, bg_rgb, want_probs, out_label,
                                     out_exp, out_var, out_bg, out_evidence, out_rgb, out_probs, out_depth)
                        if want_mass:
                            _add_mass(st_k[ch, off:off + c], st_v[ch, off:off + c], c, lists, start,
                                      out_label[v, u], out_depth[v, u], mass_edges, mass_w, mass[ch])
                    else:
                        _shade_pixel(v, u, kidx[p], kval[p], cnt[p], trans[p], lattr, eacc,
                                     e_bg, v_bg, s_bg, bg_rgb, want_probs, out_label, out_exp, out_var, out_bg,
                                     out_evidence, out_rgb, out_probs, out_depth)
                        if want_mass:
                            _add_mass(kidx[p], kval[p], cnt[p], lists, start, out_label[v, u], out_depth[v, u],
                                      mass_edges, mass_w, mass[ch])


@njit(cache=True)
def _kappa_kernel(offsets, lists, packed, bbox, width, height, tile, tiles_x,
                  count_only, pix, gid, kap, bg):  # pragma: no cover
    num_tiles = offsets.shape[0] - 1
    total = 0
    local, qbuf, hits, kidx, kval, cnt, trans, active = _new_scratch(tile)
    for t in range(num_tiles):
        start, end = offsets[t], offsets[t + 1]
        n = end - start
        local = _load_columns(packed, bbox, lists, start, end, local)
        kidx, kval, qbuf, hits = _grow_scratch(n, kidx, kval, qbuf, hits)
        ty, tx = t // tiles_x, t % tiles_x
        u0 = tx * tile
        u1 = min(width, u0 + tile) - 1
        for v in range(ty * tile, min(height, ty * tile + tile)):
            active[:] = True
            _composite_row(local, n, v, u0, u1, active, cnt, kidx, kval, trans, qbuf, hits)
            for u in range(u0, u1 + 1):
                p = u - u0
                if not count_only:
                    for i in range(cnt[p]):
                        pix[total + i] = v * width + u
                        gid[total + i] = lists[start + kidx[p, i]]
                        kap[total + i] = kval[p, i]
                    bg[v * width + u] = trans[p]
                total += cnt[p]
    return total


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
    args = (bins.offsets, bins.lists, proj.packed, proj.bbox, width, height, bins.tile_size, bins.tiles_x)
    n = _kappa_kernel(*args, True, np.empty(0, np.int64), np.empty(0, np.int32), np.empty(0), np.empty(0))
    pix = np.empty(n, dtype=np.int64)
    gid = np.empty(n, dtype=np.int32)
    kap = np.empty(n)
    bg = np.ones(width * height)
    _kappa_kernel(*args, False, pix, gid, kap, bg)
    return KappaLists(pix, proj.ids[gid], kap, bg)


def _num_chunks(bins: TileBins) -> int:
    """Work chunks = threads; tiles are dealt round-robin so both cores get a similar load."""
    return max(1, min(numba.get_num_threads(), bins.tiles_x * bins.tiles_y))


class ContributionStore:
    """Each pixel's (tile-list index, kappa) contributions, recorded by an update pass so that the
    render of the same frame (``SemanticMap.observe``) replays them instead of compositing again.

    Bounded: per work chunk ``STORE_SLOTS_PER_PIXEL`` x (pixels / chunks) entries (12 bytes each);
    pixels that do not fit, or that the update skipped (no label), are composited again by the
    render. ``np.empty`` buffers are reused across frames of the same size; untouched pages cost no
    memory.
    """

    def __init__(self) -> None:
        self._key: tuple[int, int] | None = None
        self.owner: object | None = None
        self.k = np.empty((1, 0), np.int32)
        self.v = np.empty((1, 0))
        self.off = np.empty(0, np.int64)
        self.cnt = np.empty(0, np.int32)
        self.t = np.empty(0)

    def reserve(self, pixels: int, nchunks: int) -> "ContributionStore":
        if self._key != (pixels, nchunks):
            cap = STORE_SLOTS_PER_PIXEL * ((pixels + nchunks - 1) // nchunks)
            self.k = np.empty((nchunks, cap), np.int32)
            self.v = np.empty((nchunks, cap))
            self.off = np.empty(pixels, np.int64)
            self.cnt = np.empty(pixels, np.int32)
            self.t = np.empty(pixels)
            self._key = (pixels, nchunks)
        return self


STORE_SLOTS_PER_PIXEL = 40
_NO_STORE = (np.empty((1, 0), np.int32), np.empty((1, 0)), np.empty(0, np.int64), np.empty(0, np.int32),
             np.empty(0))


_NO_MODEL = (np.zeros(2), np.zeros(1), np.zeros((1, 1)))
_NO_BASE = np.zeros((0, 0))


def accumulate_update(proj: ProjectedGaussians, bins: TileBins, labels: np.ndarray, weights: np.ndarray,
                      num_classes: int, store: ContributionStore | None = None,
                      soft: SoftLabels | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    """Per visible Gaussian, sum_i kappa_in * y_i^c, as per-thread partial sums.

    Args:
        labels: (H, W) int32 class id per pixel, -1 where the pixel contributes nothing.
        weights: (H, W) float32 confidence per pixel (1 without a confidence image).
        store: if given, records the contributions for a following :func:`render_semantic`.
        soft: the sensor model's tables (depth bins in splat units), or None for the paper's one-hot votes.
    Returns:
        ((chunks, M, C) float64 partial increments for the ``proj.ids`` rows of the concentrations, (chunks, M)
        increments of every class of those rows ((0, 0) without ``soft``) (apply both with :func:`add_increments`),
        labelled pixels without any contribution when ``soft`` is given (0 otherwise)).
    """
    height, width = labels.shape
    nchunks = _num_chunks(bins)
    acc = np.zeros((nchunks, proj.count, num_classes))
    arrays = _NO_STORE if store is None else (*_store_arrays(store.reserve(width * height, nchunks)),)
    no_depth = np.zeros(nchunks, dtype=np.int64)
    edges, base, resid = _NO_MODEL if soft is None else (soft.edges, soft.base, soft.resid)
    acc_base = _NO_BASE if soft is None else np.zeros((nchunks, proj.count))
    _update_kernel(bins.offsets, bins.lists, proj.packed, proj.bbox, labels, weights, width, height,
                   bins.tile_size, bins.tiles_x, acc, store is not None, *arrays, soft is not None, edges, base,
                   resid, acc_base, no_depth)
    return acc, acc_base, int(no_depth.sum())


@njit(parallel=True, cache=True)
def add_increments(concentrations, ids, acc, acc_base):  # pragma: no cover
    """concentrations[ids[j], c] += sum over chunks of acc[chunk, j, c] (+ acc_base[chunk, j] for every class
    when acc_base is not empty) (ids are unique)."""
    m, num_classes = acc.shape[1], acc.shape[2]
    with_base = acc_base.shape[0] > 0
    for j in prange(m):
        row = ids[j]
        common = 0.0
        if with_base:
            for ch in range(acc_base.shape[0]):
                common += acc_base[ch, j]
        for c in range(num_classes):
            total = 0.0
            for ch in range(acc.shape[0]):
                total += acc[ch, j, c]
            if with_base:
                total += common
            concentrations[row, c] += total


@njit(parallel=True, cache=True, nogil=True)
def dirichlet_attributes(concentrations, ids, colors, packed):  # pragma: no cover
    """Per projected Gaussian j: attrs[j] = (E_0..E_{C-1}, r, g, b, S, z, Var_0..Var_{C-1}) (SPEC §4 moments).

    Args:
        concentrations: (N, C) float64 alpha; ids: (M,) model rows; colors: (M, 3) view colours, or
            (0, 3) for zero colour (views that are only scored); packed: (M, 8) projected rows (column 7:
            camera depth z, splat units).
    Returns:
        attrs (M, 2C + 5) float32 (halves the render's memory traffic; the tile-local copies of
        these rows are all the shading reads), with E = alpha / S, Var = E (1 - E) / (1 + S).
    """
    m = ids.shape[0]
    num_classes = concentrations.shape[1]
    attrs = np.empty((m, 5 + 2 * num_classes), dtype=np.float32)
    for j in prange(m):
        row = ids[j]
        total = 0.0
        for c in range(num_classes):
            total += concentrations[row, c]
        inv = 1.0 / total
        denom = 1.0 / (1.0 + total)
        for c in range(3):
            attrs[j, num_classes + c] = np.float32(colors[j, c]) if colors.shape[0] else np.float32(0.0)
        attrs[j, num_classes + 3] = np.float32(total)
        attrs[j, num_classes + 4] = np.float32(packed[j, 7])
        for c in range(num_classes):
            e = concentrations[row, c] * inv
            attrs[j, c] = np.float32(e)
            attrs[j, 5 + num_classes + c] = np.float32(e * (1.0 - e) * denom)
    return attrs


def _store_arrays(store: ContributionStore) -> tuple[np.ndarray, ...]:
    return store.k, store.v, store.off, store.cnt, store.t


def render_semantic(proj: ProjectedGaussians, bins: TileBins, width: int, height: int,
                    attrs: np.ndarray,
                    e_bg: float, v_bg: float, s_bg: float, bg_rgb: np.ndarray,
                    want_probs: bool, store: ContributionStore | None = None,
                    mass_weights: "tuple[np.ndarray, np.ndarray] | None" = None) -> RenderBuffers:
    """Composite colour, expectation, argmax-class variance and evidence (SPEC §5).

    Args:
        store: contributions recorded by :func:`accumulate_update` at the same pose, or None.
        attrs: (M, 2C + 5) float32 rows (E[theta_n^0..C-1], r, g, b, S_n, z_n, Var[theta_n^0..C-1]) of the
            projected Gaussians (see :func:`dirichlet_attributes`).
        e_bg, v_bg, s_bg: background expectation, variance (per class) and total.
        mass_weights: (edges (B + 1,) splat units, net vote weight per (label, depth bin) (C * B,)): also return
            each projected Gaussian's evidence mass in the view (``RenderBuffers.mass``, (M,) float64).
    """
    num_classes = (attrs.shape[1] - 5) // 2
    out_label = np.empty((height, width), dtype=np.int32)
    out_exp = np.empty((height, width))
    out_var = np.empty((height, width))
    out_bg = np.empty((height, width))
    out_ev = np.empty((height, width))
    out_rgb = np.empty((height, width, 3))
    out_probs = np.empty((height, width, num_classes) if want_probs else (1, 1, num_classes))
    out_depth = np.empty((height, width))
    nchunks = _num_chunks(bins)
    want_mass = mass_weights is not None
    mass = np.zeros((nchunks, proj.count) if want_mass else (nchunks, 0))
    edges, wts = mass_weights if mass_weights is not None else (np.zeros(2), np.ones(1))
    _render_kernel(bins.offsets, bins.lists, proj.packed, proj.bbox, attrs, e_bg, v_bg, s_bg,
                   np.asarray(bg_rgb, dtype=np.float64), width, height, bins.tile_size, bins.tiles_x,
                   want_probs, nchunks, store is not None,
                   *(_NO_STORE if store is None else _store_arrays(store)),
                   out_label, out_exp, out_var, out_bg, out_ev, out_rgb, out_probs, out_depth,
                   want_mass, edges, wts, mass)
    return RenderBuffers(out_label, out_exp, out_var, out_bg, out_ev, out_rgb,
                         out_probs if want_probs else None, out_depth,
                         mass.sum(axis=0) if want_mass else None)
