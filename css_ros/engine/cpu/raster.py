"""Stages 2-3 of the pipeline on the CPU: tile binning and the compiled per-pixel kernels (update, render, kappa).

Every kernel walks each pixel's depth-sorted candidates with the INRIA rules of SPEC §3 through one compositing walk
(:mod:`.composite`) and derives the weights kappa_in = a_n T_n on the fly; nothing of size (pixels x Gaussians) is
ever stored. A Gaussian contributes to exactly the pixels where its alpha reaches 1/255 (its binning box covers
that ellipse), so the result does not depend on the tile size and equals a per-pixel brute force.

The update applies the label rule (:func:`css_ros.engine.label_input.pixel_vote`) to the labels and confidence as
they came in, inside its own pass, and counts the pixels there; in ``observe`` it also records each voting pixel's
contributions (6 bytes each, :class:`ContributionStore`), which the render of the same frame replays instead of
walking again (benchmarks/README.md).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple

import numba
import numpy as np
from numba import njit, prange

from ..buffers import RenderBuffers
from ..change_rules import depth_gate
from ..label_input import (IGNORED, NO_DEPTH, NUM_COUNTS, OCCLUDED, OUT_OF_RANGE, TRANSIENT, USED, FrameLabels,
                           pixel_vote, transient_status)
from ..pixel_math import depth_bin
from ..spec import TILE_SIZE
from .composite import FAST, composite_row, load_tile, longest_list, new_scratch, row_candidates
from .borrowed import borrow, keep_alive
from .kept import Kept
from .increments import SLOTS, Increments, UpdateWorkspace, add_increment_row, add_to, class_mark, classes_per_mark
from .prefetch import prefetch_ahead
from .row_vector import add_row, add_rows4
from .projection import ProjectedGaussians
from ..kernel_cache import bind_sources

if TYPE_CHECKING:
    from ..sensor_model import SoftLabels

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
def _bin_count(bbox, depth_order, tiles_x, tiles_y, tile, parts):  # pragma: no cover
    """First half of a parallel counting sort of (tile, depth) pairs: the depth order is cut into ``parts``
    consecutive ranges, each counting its entries of every tile. Returns (offsets (T + 1,), each Gaussian's tile
    range in depth order (m, 4), where each part's entries of each tile start (parts, T)): part 0's (nearest) entries
    first, so every list stays front to back. Each Gaussian's tile range is computed once, in depth order, so both
    halves read it sequentially."""
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
    return offsets, span, fill


@njit(parallel=True, cache=True, nogil=True)
def _bin_fill(depth_order, span, tiles_x, fill, lists):  # pragma: no cover
    """Second half (:func:`_bin_count`): each part writes its own slice of every tile's list."""
    m = span.shape[0]
    parts = fill.shape[0]
    for p in prange(parts):
        for r in range(p * m // parts, (p + 1) * m // parts):
            j = depth_order[r]
            for ty in range(span[r, 2], span[r, 3] + 1):
                for tx in range(span[r, 0], span[r, 1] + 1):
                    t = ty * tiles_x + tx
                    lists[fill[p, t]] = j
                    fill[p, t] += 1


def new_lists(n: int) -> tuple[np.ndarray]:
    """An uninitialised (n,) int32 tile-list array (also the maker of a :class:`~.kept.Kept` of them)."""
    return (np.empty(n, dtype=np.int32),)


def bin_tiles(proj: ProjectedGaussians, width: int, height: int, tile_size: int = TILE_SIZE,
              kept: Kept | None = None) -> TileBins:
    """Counting-sort the depth-sorted Gaussians into the tiles their alpha >= 1/255 box overlaps.

    ``kept``: the lists' array kept between frames (a :class:`~.kept.Kept` of :func:`new_lists`; the bins are valid
    until its next use), or None for a fresh one."""
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    offsets, span, fill = _bin_count(proj.bbox, proj.depth_order, tiles_x, tiles_y, tile_size,
                                     max(1, numba.get_num_threads()))
    total = int(offsets[-1])
    (lists,) = new_lists(total) if kept is None else kept.take(total)
    _bin_fill(proj.depth_order, span, tiles_x, fill, lists)
    return TileBins(offsets, lists, tiles_x, tiles_y, tile_size)


def linear_width(num_classes: int) -> int:
    """Columns of the part of an attribute row the shading accumulates for every contribution (E_0..E_{C-1}, r, g,
    b, S, z: C + 5), padded with zeros so that the loop over them runs in whole 16-wide vector steps, or in 8-wide
    ones when that pads less: a scalar remainder per contribution cost more than the padding (benchmarks/README.md).
    The C variances follow the padding."""
    lin = num_classes + 5
    wide = -(-lin // 16) * 16
    return wide if wide - lin <= 8 else -(-lin // 8) * 8


def attribute_classes(width: int) -> int:
    """C of attribute rows ``width`` wide (:func:`dirichlet_attributes`)."""
    for c in range(1, width):
        if linear_width(c) + c == width:
            return c
    raise ValueError(f"no class count gives attribute rows {width} wide")


_linear_width = njit(inline="always")(linear_width)
_depth_bin = njit(inline="always")(depth_bin)
_pixel_vote = njit(inline="always")(pixel_vote)
_transient_status = njit(inline="always")(transient_status)
_depth_gate = njit(inline="always")(depth_gate)


@njit(inline="always")
def _row_votes(row_labels, row_conf, has_confidence, num_classes, ignore_label, transient, want_surprise, vote,
               weight, active, kind):  # pragma: no cover
    """:func:`~css_ros.engine.label_input.pixel_vote` and :func:`~css_ros.engine.label_input.transient_status` of a
    tile row's pixels: vote[p] (the class, also of a transient pixel), weight[p], kind[p] (the status), active[p]
    (USED, or TRANSIENT when the surprise is wanted: walked); returns the row's (used, ignored, out of range,
    transient) counts."""
    used = 0
    ignored = 0
    out_of_range = 0
    transients = 0
    for p in range(row_labels.shape[0]):
        conf = 1.0
        if has_confidence:
            conf = row_conf[p]
        c, w, status = _pixel_vote(row_labels[p], conf, num_classes, ignore_label)
        status = _transient_status(c, status, transient)
        used += status == USED
        ignored += status == IGNORED
        out_of_range += status == OUT_OF_RANGE
        transients += status == TRANSIENT
        vote[p] = c
        weight[p] = w
        kind[p] = status
        active[p] = status == USED or (want_surprise and status == TRANSIENT)
    return used, ignored, out_of_range, transients


@njit(inline="always", fastmath=FAST)
def _pixel_surprise(kidx, kval, c, t, ecol, inv_c):  # pragma: no cover
    """1 - E^y of one pixel before the update: sum kappa E_n^y + kappa_b / C, with ``ecol`` the tile list's E^y
    (:func:`_tile_expectations`)."""
    e = t * inv_c
    for i in range(c):
        e += kval[i] * ecol[kidx[i]]
    return np.float32(1.0 - e)


@njit(inline="always")
def _tile_expectations(e_pre, tile_list, label, ecache, eloaded):  # pragma: no cover
    """The tile list's pre-update E of class ``label`` as one contiguous row of ``ecache`` (gathered from ``e_pre``
    once per tile and class: a tile has few classes, a pixel's walk many contributions)."""
    row = ecache[label]
    if not eloaded[label]:
        col = e_pre[label]
        for k in range(tile_list.shape[0]):
            row[k] = col[tile_list[k]]
        eloaded[label] = True
    return row


@njit(inline="always", fastmath=FAST)
def _rendered_depth(kidx, kval, c, ldepth):  # pragma: no cover
    """(sum kappa z / sum kappa, sum kappa) of one pixel's contributions (z from ``ldepth``, splat units); NaN
    depth without any."""
    zsum = 0.0
    ksum = 0.0
    for i in range(c):
        kv = kval[i]
        zsum += kv * ldepth[kidx[i]]
        ksum += kv
    return (zsum / ksum if ksum > 0.0 else np.nan), ksum


@njit(inline="always", fastmath=FAST)
def _flush_tile(tile_list, touched, lacc, present, use_model, base, resid, lbase, inc, ch, rows):  # pragma: no cover
    """Add a tile's accumulator rows (the present ones) into chunk ``ch``'s increments (:class:`Increments`, through
    :func:`~css_ros.engine.cpu.increments.add_to`): a class row as it is; with a sensor model, each (label, depth bin)
    row r through its table, base[r] into inc.base[ch] and resid[r, c] into class c. Only list positions with
    ``touched[k]`` (a vote reached them) are added; the others hold zeros (Gaussians behind saturated pixels, or
    whose alpha ellipse misses the tile's voting pixels). ``rows`` is scratch for the present rows' ids."""
    n = tile_list.shape[0]
    acc, marks, slot_class, slot_value = inc.acc[ch], inc.marks[ch], inc.slot_class[ch], inc.slot_value[ch]
    num_classes = acc.shape[1]
    per_mark = classes_per_mark(num_classes)
    if not use_model:
        npres = 0
        for c in range(num_classes):
            if present[c]:
                rows[npres] = c
                npres += 1
        for k in range(n):
            if not touched[k]:
                continue
            j = tile_list[k]
            for i in range(npres):
                c = rows[i]
                add_to(slot_class, slot_value, acc, marks, j, c, lacc[c, k], per_mark)
        return
    # a tile with a row that spreads over more classes than a Gaussian has slots (confusion rows) writes the dense
    # rows directly: through the slots it would fill them and overflow anyway (1.4x the update with dense rows)
    widest = 0
    mark = np.uint64(0)
    for r in range(present.shape[0]):
        if present[r]:
            spread = 0
            for c in range(num_classes):
                if resid[r, c] != 0.0:
                    spread += 1
                    mark |= class_mark(c, per_mark)
            widest = max(widest, spread)
    dense = widest > SLOTS
    if dense:
        for k in range(n):
            if touched[k]:
                marks[tile_list[k]] |= mark
    any_base = False
    for r in range(present.shape[0]):
        if present[r]:
            b0 = base[r]
            if b0 != 0.0:
                if not any_base:
                    any_base = True
                    for k in range(n):
                        lbase[k] = 0.0
                for k in range(n):
                    if touched[k]:
                        lbase[k] += lacc[r, k] * b0
            for c in range(num_classes):
                pc = resid[r, c]
                if pc == 0.0:
                    continue
                if dense:
                    for k in range(n):
                        if touched[k]:
                            acc[tile_list[k], c] += lacc[r, k] * pc
                else:
                    for k in range(n):
                        if touched[k]:
                            add_to(slot_class, slot_value, acc, marks, tile_list[k], c, lacc[r, k] * pc, per_mark)
    if any_base:
        out = inc.base[ch]
        for k in range(n):
            if touched[k]:
                out[tile_list[k]] += lbase[k]


@njit(inline="always", fastmath=FAST)
def _evidence_row(kp, vp, c, label, used, need_depth, has_depth, use_model, measured, ldepth, depth_scale, tol_abs,
                  tol_rel, edges, num_bins):  # pragma: no cover
    """Where a pixel's vote goes: (scatter, accumulator row, front, occluded, no depth). ``used``: the pixel votes
    (a transient class does not); the depth gate of :mod:`css_ros.engine.change_rules` may drop it (occluded = 1)
    or give ``front``, the measured depth [m] in front of which its contributions add nothing (-inf: none); with a
    sensor model the row is (label, depth bin of the rendered depth), no depth = 1 when the pixel has no
    contribution."""
    scatter = used
    row = label
    front = -np.inf
    occluded = 0
    no_depth = 0
    if scatter and need_depth:
        rendered, ksum = _rendered_depth(kp, vp, c, ldepth)
        if has_depth:
            occ, front = _depth_gate(np.float64(measured), rendered * depth_scale, tol_abs, tol_rel)
            if occ:
                occluded = 1
                scatter = False
        if scatter and use_model:
            b = 0
            if ksum > 0.0:
                b = _depth_bin(rendered, edges)
            else:
                no_depth = 1
            row = row * num_bins + b
    return scatter, row, front, occluded, no_depth


@njit(inline="always", fastmath=FAST)
def _scatter_votes(kp, vp, c, lrow, w, front, depth_scale, ldepth, touched):  # pragma: no cover
    """lrow[kp[i]] += vp[i] * w over a pixel's contributions, marking touched[kp[i]]; with a finite ``front`` [m]
    (the depth gate), only those of Gaussians not in front of it (camera depth ``ldepth`` in splat units)."""
    if front > -np.inf:
        lim = front / depth_scale
        for i in range(c):
            k = kp[i]
            if ldepth[k] >= lim:
                lrow[k] += vp[i] * w
                touched[k] = True
    else:
        for i in range(c):
            k = kp[i]
            lrow[k] += vp[i] * w
            touched[k] = True


# _update_kernel with ``use_model`` (a sensor model): a pixel labelled y at expected depth d = sum kappa z / sum kappa
# (depth bin b of ``edges``, splat units) adds kappa_ij * weight_i * table[r, c] to every class c instead, r = y * B + b,
# with the table split as table[r, c] = base[r] + resid[r, c]: the part common to every class goes to base[chunk, j]
# of the increments (added to every class by add_increments), the sparse rest to the classes. So a symmetric vote (p
# on the label, the same small share on every other class) costs what a one-hot vote costs. Voting pixels without any
# contribution are counted as "no depth" (they add nothing). Without it the arithmetic is exactly the paper's update.
# With ``store``, each voting pixel's contributions (tile-list position as uint16, kappa as float32) are appended to its
# chunk's row of st_k / st_v (pix_off, pix_cnt, pix_t: offset, count, final T) for the render of the same frame;
# the pixel records are tile-major (tile t's row r starts at t * tile^2 + r * tile: a tile's records are one run,
# where rows of the image put each tile row on a cache line of its own: 0.93-0.97 of update + render, 500k room);
# pixels not composited, or that did not fit, get pix_cnt = -1.
@njit(inline="always")
def _write_counts(row, used, ignored, out_of_range, no_depth, transients, occluded):  # pragma: no cover
    """A chunk's pixel counts into its (NUM_COUNTS,) row."""
    row[USED] = used
    row[IGNORED] = ignored
    row[OUT_OF_RANGE] = out_of_range
    row[NO_DEPTH] = no_depth
    row[TRANSIENT] = transients
    row[OCCLUDED] = occluded


def chunk_tile_count(ch: int, nchunks: int, tiles_x: int, num_tiles: int) -> int:
    """How many tiles work chunk ``ch`` of ``nchunks`` has: the whole tile rows ch, ch + nchunks, ... A tile's
    horizontal neighbours are then its own chunk's, so no cache line of an image row is written by two threads
    (tiles dealt one by one put an 8-pixel tile row of int32 labels on a line shared with the other thread: the
    render scaled 1.57x from one thread to two on the 500k room, 1.83x with whole rows; observe 0.96 of its time)."""
    rows = num_tiles // tiles_x
    return max(0, (rows - ch + nchunks - 1) // nchunks) * tiles_x


_chunk_tile_count = njit(inline="always")(chunk_tile_count)


@njit(inline="always")
def _chunk_tile(k, ch, nchunks, tiles_x):  # pragma: no cover
    """The k-th tile of work chunk ``ch`` (:func:`chunk_tile_count`)."""
    return (ch + nchunks * (k // tiles_x)) * tiles_x + k % tiles_x


@njit(inline="always")
def _record_row(t, row, tile):  # pragma: no cover
    """Index of the first pixel record of row ``row`` (0 <= row < tile) of tile t: the records are tile-major."""
    return t * tile * tile + row * tile


@njit(inline="always")
def _list_rows(num_rows, surprise_rows, cap):  # pragma: no cover
    """A chunk's rows indexed by tile-list position (``cap`` entries): the tile-local accumulator (num_rows, cap) (label
    row, list position: the per-contribution scatter stays in cache; only the rows present in the tile are zeroed and
    flushed to the chunk's rows; a row is a class (paper's update) or a (label, depth bin) pair whose soft label the
    flush applies), the flush's base sums, touched (np.zeros here indexed out of bounds under NUMBA_BOUNDSCHECK in
    prange), the list's camera depths and the surprise's expectations (surprise_rows, cap) float32."""
    return (np.empty((num_rows, cap)), np.empty(cap), np.empty(cap, dtype=np.bool_), np.empty(cap),
            np.empty((surprise_rows, cap), dtype=np.float32))


@njit(parallel=True, cache=True, nogil=True, fastmath=FAST)
def _update_kernel(offsets, lists, walk, packed, labels_arg, confidence, has_confidence, ignore_label, width, height,
                   tile, tiles_x, inc, use_model, edges, base, resid, counts,
                   store, st_k_arg, st_v_arg, pix_off, pix_cnt, pix_t, gate):  # pragma: no cover
    """The chunk's increments of Gaussian j and class c (``inc``: :class:`Increments`, chunk-private) += sum over
    the pixels voting c of kappa_ij * weight_i; counts[chunk] = (used,
    ignored, out of range, no depth, transient, occluded) of the chunk's pixels. Each pixel's vote is
    :func:`~css_ros.engine.label_input.pixel_vote` of ``labels[v, u]`` (any integer dtype) and
    ``confidence[v, u]`` (float32 / float64; 1 without ``has_confidence``), taken as it comes: no class or weight
    planes. Only rows of a tile with a voting pixel are composited, only those pixels walked. With a sensor model
    and with a store: see the comment above.

    ``gate`` = (depth (H, W) float32 metres, has_depth, tol_abs, tol_rel, depth_scale, transient (C,) bool,
    want_surprise, e_pre (C, M) float32 E before the update, surprise (H, W) float32 out): the rules of
    :mod:`css_ros.engine.change_rules` (transient classes, measured depth, surprise)."""
    depth, has_depth, tol_abs, tol_rel, depth_scale, transient, want_surprise, e_pre, surprise = gate
    # arrays viewed per row or pixel, borrowed (engine/cpu/borrowed.py): arguments, alive for the whole call
    labels = borrow(labels_arg)
    st_k = borrow(st_k_arg)
    st_v = borrow(st_v_arg)
    nchunks = inc.acc.shape[0]
    num_tiles = offsets.shape[0] - 1
    num_classes = inc.acc.shape[2]
    num_bins = edges.shape[0] - 1 if use_model else 1
    num_rows = num_classes * num_bins
    cap = st_k.shape[1]
    need_depth = use_model or has_depth
    inv_c = 1.0 / num_classes
    longest = longest_list(offsets)
    for ch in prange(nchunks):
        pos = 0
        owned = new_scratch(tile, longest)   # kept alive to the chunk's end (keep_alive) for its borrowed copy
        scratch = borrow(owned)
        vote = np.empty(tile, dtype=np.int64)
        kind = np.empty(tile, dtype=np.int64)
        weight = np.empty(tile)
        lrows = _list_rows(num_rows, num_classes if want_surprise else 1, longest)
        lacc, lbase, touched, ldepth, ecache = borrow(lrows)
        present = np.empty(num_rows, dtype=np.bool_)
        present_rows = np.empty(num_rows, dtype=np.int64)
        eloaded = np.zeros(num_classes, dtype=np.bool_)
        used = 0
        ignored = 0
        out_of_range = 0
        no_depth = 0
        transients = 0
        occluded = 0
        for kk in range(_chunk_tile_count(ch, nchunks, tiles_x, num_tiles)):
            t = _chunk_tile(kk, ch, nchunks, tiles_x)
            start, end = offsets[t], offsets[t + 1]
            n = end - start
            tile_list = lists[start:end]
            ty, tx = t // tiles_x, t % tiles_x
            u0 = tx * tile
            u1 = min(width, u0 + tile) - 1
            loaded = False
            depth_loaded = False
            for v in range(ty * tile, min(height, ty * tile + tile)):
                active = scratch[8]
                row_conf = confidence[v, u0:u1 + 1] if has_confidence else confidence[0, 0:1]
                n_used, n_ignored, n_out, n_trans = _row_votes(labels[v, u0:u1 + 1], row_conf, has_confidence,
                                                               num_classes, ignore_label, transient, want_surprise,
                                                               vote, weight, active, kind)
                used += n_used
                ignored += n_ignored
                out_of_range += n_out
                transients += n_trans
                qt = _record_row(t, v - ty * tile, tile)
                if store:
                    pix_cnt[qt:qt + u1 - u0 + 1] = -1
                if not (n_used > 0 or (want_surprise and n_trans > 0)):
                    continue
                if not loaded:
                    load_tile(walk, lists, start, end, scratch[0])
                    present[:] = False
                    eloaded[:] = False
                    touched[:n] = False
                    loaded = True
                cols, cand, ridx, words, kidx, kval, cnt, trans, active, chunk, hit, state = scratch
                r = row_candidates(cols, n, v, u0, u1, cand, ridx, words)
                composite_row(cand, ridx, r, u0, u1, active, cnt, kidx, kval, trans, chunk, hit, state)
                if need_depth and not depth_loaded:  # the tile list's camera depths, contiguous
                    for k in range(n):
                        ldepth[k] = packed[tile_list[k], 7]
                    depth_loaded = True
                for p in range(u1 - u0 + 1):
                    if not active[p]:
                        continue
                    c = cnt[p]
                    kp = kidx[p]
                    vp = kval[p]
                    keep = store and pos + c <= cap and n <= _STORE_MAX_LIST
                    if keep:
                        q = qt + p
                        pix_off[q] = pos
                        pix_cnt[q] = c
                        pix_t[q] = trans[p]
                    ecol = ecache[0]
                    if want_surprise:
                        ecol = _tile_expectations(e_pre, tile_list, vote[p], ecache, eloaded)
                    w = weight[p]
                    scatter, row, front, occ, nod = _evidence_row(kp, vp, c, vote[p], kind[p] == USED, need_depth,
                                                                  has_depth, use_model, depth[v, u0 + p] if has_depth
                                                                  else 0.0, ldepth, depth_scale, tol_abs, tol_rel,
                                                                  edges, num_bins)
                    occluded += occ
                    used -= occ
                    no_depth += nod
                    if scatter and not present[row]:
                        present[row] = True
                        for k in range(n):
                            lacc[row, k] = 0.0
                    if scatter and keep and front == -np.inf:
                        # the common case in one pass over the contributions: store, surprise, votes (the
                        # separate loops of the branch below cost 8-10 % more of the update on the 500k room)
                        lrow = lacc[row]
                        sk = st_k[ch, pos:pos + c]
                        sv = st_v[ch, pos:pos + c]
                        e = trans[p] * inv_c
                        for i in range(c):
                            k = kp[i]
                            x = vp[i]
                            sk[i] = np.uint16(k)
                            sv[i] = np.float32(x)
                            if want_surprise:
                                e += x * ecol[k]
                            lrow[k] += x * w
                            touched[k] = True
                        if want_surprise:
                            surprise[v, u0 + p] = np.float32(1.0 - e)
                    else:
                        if keep:
                            for i in range(c):
                                st_k[ch, pos + i] = np.uint16(kp[i])
                                st_v[ch, pos + i] = np.float32(vp[i])
                        if want_surprise:
                            surprise[v, u0 + p] = _pixel_surprise(kp, vp, c, trans[p], ecol, inv_c)
                        if scatter:
                            _scatter_votes(kp, vp, c, lacc[row], w, front, depth_scale, ldepth, touched)
                    if keep:
                        pos += c
            if loaded:
                _flush_tile(tile_list, touched, lacc, present, use_model, base, resid, lbase, inc, ch, present_rows)
        _write_counts(counts[ch], used, ignored, out_of_range, no_depth, transients, occluded)
        keep_alive(owned)
        keep_alive(lrows)


#: Columns of a Gaussian's short shading row (:func:`dirichlet_attributes`): E and Var of its most likely class,
#: r, g, b, S, z, and that class (a float32 holding an integer).
SHORT_COLS = 8
#: The short path's margin: the guessed class's share of a pixel's expectation mass must exceed one half by this
#: relative amount, far above the float32 rounding of the rows' sums (C x 2^-24) and of the accumulation.
MAJORITY_MARGIN = 1e-3
#: Short-path misses after which the render stops trying it for the rest of a tile (a tile of mixed classes or
#: little evidence misses pixel after pixel, each miss paying the short pass and then the full one).
SHORT_MISSES = 4
#: The short path is tried only where the full rows' linear part is at least this wide (C >= 28 classes): measured
#: with 28 classes (40 columns) it made the 500k room's render 20 % faster, with 20 (32 columns: two cache lines, four
#: vector steps per contribution) biker's 13-16 % slower (benchmarks/README.md).
SHORT_MIN_COLUMNS = 40


@njit(inline="always", fastmath=FAST)
def _write_pixel(v, u, label, e, vhat, tr, acc, k, cnt, e_bg, s_bg, bg_rgb, out_label, out_exp, out_var, out_bg,
                 out_evidence, out_rgb, out_depth):  # pragma: no cover
    """One pixel's outputs from its sums over its contributions (both shading paths): the label, E = e + T e_bg, Var
    (``vhat``, the background's share included), T, and from acc[k:k + 5] (the kappa-weighted sums of r, g, b, S, z)
    the colour and evidence with the background's share and the depth sum kappa z / (1 - T) (NaN without any
    contribution)."""
    out_label[v, u] = label
    out_exp[v, u] = e + tr * e_bg
    out_var[v, u] = vhat
    out_bg[v, u] = tr
    out_evidence[v, u] = acc[k + 3] + tr * s_bg
    out_rgb[v, u, 0] = acc[k] + tr * bg_rgb[0]
    out_rgb[v, u, 1] = acc[k + 1] + tr * bg_rgb[1]
    out_rgb[v, u, 2] = acc[k + 2] + tr * bg_rgb[2]
    out_depth[v, u] = acc[k + 4] / (1.0 - tr) if cnt > 0 else np.nan


@njit(inline="always", fastmath=FAST)
def _shade_majority(v, u, ks, vs, cnt, tr, short, tile_list, acc, e_bg, v_bg, s_bg, bg_rgb, out_label, out_exp, out_var,
                    out_bg, out_evidence, out_rgb, out_depth):  # pragma: no cover
    """The short path of :func:`_shade_pixel`: when every contribution's Gaussian has the same most likely class
    g (``short`` rows) and g holds more than half of the pixel's expectation mass (sum kappa E^g > (1 + margin)
    (1 - T) / 2, while the classes' E of a Gaussian sum to 1 and the kappas to 1 - T), g is the pixel's argmax
    whatever the other classes hold, so E, Var of g, colour, evidence and depth need one 32-byte row per
    contribution instead of the full attribute row.

    Returns 1 where it wrote the pixel, 2 where it found that this does not hold (nothing written), 0 where it did
    not try (no contribution, or the front contribution's E^g is at most one half). ``acc``: (>= SHORT_COLS,)
    float32 scratch; every column is accumulated with weight kappa, four contributions at a time as in the full
    path, in one 8-wide vector step (:mod:`.row_vector`: written as a loop over the columns, LLVM left it scalar,
    8 loads, 32 FMAs and 8 stores; the render's replay took 1.28x as long), the variance apart with kappa^2."""
    if cnt == 0 or short[tile_list[ks[0]], 0] <= 0.5:
        return 0
    fg = short[tile_list[ks[0]], 7]
    for c in range(SHORT_COLS):
        acc[c] = 0.0
    vhat = tr * tr * v_bg
    i = 0
    while i + 4 <= cnt:
        j0 = tile_list[ks[i]]
        j1 = tile_list[ks[i + 1]]
        j2 = tile_list[ks[i + 2]]
        j3 = tile_list[ks[i + 3]]
        if (short[j0, 7] != fg) | (short[j1, 7] != fg) | (short[j2, 7] != fg) | (short[j3, 7] != fg):
            return 2
        k0 = vs[i]
        k1 = vs[i + 1]
        k2 = vs[i + 2]
        k3 = vs[i + 3]
        add_rows4(acc, short, j0, j1, j2, j3, np.float32(k0), np.float32(k1), np.float32(k2), np.float32(k3))
        vhat += k0 * k0 * short[j0, 1]
        vhat += k1 * k1 * short[j1, 1]
        vhat += k2 * k2 * short[j2, 1]
        vhat += k3 * k3 * short[j3, 1]
        i += 4
    while i < cnt:
        j0 = tile_list[ks[i]]
        if short[j0, 7] != fg:
            return 2
        k0 = vs[i]
        add_row(acc, short, j0, np.float32(k0))
        vhat += k0 * k0 * short[j0, 1]
        i += 1
    if not 2.0 * acc[0] > (1.0 - tr) * (1.0 + MAJORITY_MARGIN):  # sum kappa = 1 - T (the walk telescopes)
        return 2
    _write_pixel(v, u, np.int32(fg), acc[0], vhat, tr, acc, 2, cnt, e_bg, s_bg, bg_rgb, out_label, out_exp, out_var,
                 out_bg, out_evidence, out_rgb, out_depth)
    return 1


@njit(inline="always", fastmath=FAST)
def _shade_pixel(v, u, ks, vs, cnt, tr, attrs, short, num_classes, tile_list, acc, e_bg, v_bg, s_bg, bg_rgb,
                 want_probs, try_short, out_label, out_exp, out_var, out_bg, out_evidence, out_rgb, out_probs,
                 out_depth):  # pragma: no cover
    """Accumulate one pixel's contributions (tile-list positions ks, kappas vs) into the outputs: by
    :func:`_shade_majority` where it applies (not with ``want_probs``), else over the full attribute rows.

    attrs rows (``attrs[tile_list[k]]``, :func:`dirichlet_attributes`) are read in place (a tile-local copy of the
    rows cost more than it saved): one loop over the first :func:`linear_width` columns accumulates expectation,
    colour, evidence and kappa-weighted depth (the expected depth sum kappa z / sum kappa, with sum kappa = 1 - T;
    NaN without any contribution). Contributions are taken four at a time, so the accumulator round trip through
    memory (the loop over the columns is too short for LLVM's wide vector body) is paid once per four.
    """
    missed = 0
    if try_short and not want_probs:
        how = _shade_majority(v, u, ks, vs, cnt, tr, short, tile_list, acc, e_bg, v_bg, s_bg, bg_rgb, out_label, out_exp,
                              out_var, out_bg, out_evidence, out_rgb, out_depth)
        if how == 1:
            return 0
        missed = how // 2
    lin = _linear_width(num_classes)
    for c in range(lin):
        acc[c] = 0.0
    i = 0
    while i + 4 <= cnt:
        r0 = attrs[tile_list[ks[i]]]
        r1 = attrs[tile_list[ks[i + 1]]]
        r2 = attrs[tile_list[ks[i + 2]]]
        r3 = attrs[tile_list[ks[i + 3]]]
        w0 = np.float32(vs[i])
        w1 = np.float32(vs[i + 1])
        w2 = np.float32(vs[i + 2])
        w3 = np.float32(vs[i + 3])
        for c in range(lin):
            acc[c] += (w0 * r0[c] + w1 * r1[c]) + (w2 * r2[c] + w3 * r3[c])
        i += 4
    while i < cnt:
        r0 = attrs[tile_list[ks[i]]]
        w0 = np.float32(vs[i])
        for c in range(lin):
            acc[c] += w0 * r0[c]
        i += 1
    best = 0
    top = acc[0]
    for c in range(1, num_classes):  # branch-free argmax (the first of equal maxima)
        x = acc[c]
        better = x > top
        best = c if better else best
        top = x if better else top
    vhat = tr * tr * v_bg
    for i in range(cnt):
        kappa = vs[i]
        vhat += kappa * kappa * attrs[tile_list[ks[i]], lin + best]
    _write_pixel(v, u, best, acc[best], vhat, tr, acc, num_classes, cnt, e_bg, s_bg, bg_rgb, out_label, out_exp,
                 out_var, out_bg, out_evidence, out_rgb, out_depth)
    if want_probs:
        for c in range(num_classes):
            out_probs[v, u, c] = acc[c] + tr * e_bg
    return missed


@njit(inline="always")
def _add_mass(ks, vs, cnt, tile_list, label, depth, edges, weights, mass):  # pragma: no cover
    """mass[tile_list[ks[i]]] += vs[i] * weights[label * B + b] (b: the depth bin of ``depth`` in ``edges``)."""
    if cnt == 0:
        return
    w = weights[label * (edges.shape[0] - 1) + _depth_bin(depth, edges)]
    if w == 0.0:
        return
    for i in range(cnt):
        mass[tile_list[ks[i]]] += vs[i] * w


@njit(parallel=True, cache=True, nogil=True, fastmath=FAST)
def _render_kernel(offsets, lists, walk, attrs_arg, short, short_ok, num_classes, e_bg, v_bg, s_bg, bg_rgb, width,
                   height, tile, tiles_x, want_probs, nchunks, use_store, st_k_arg, st_v_arg, pix_off, pix_cnt, pix_t,
                   out_label, out_exp, out_var, out_bg, out_evidence, out_rgb,
                   out_probs, out_depth, want_mass, mass_edges, mass_w, mass):  # pragma: no cover
    """attrs rows: :func:`dirichlet_attributes`. With ``use_store``, the pixels the update of the
    same frame recorded (pix_cnt >= 0) replay their contributions; the others are composited.

    With ``want_mass``, mass[chunk, j] += kappa_ij * mass_w[label_i * B + b_i] over the pixels i of the view: the
    evidence observing it would add to Gaussian j (label_i = the rendered argmax, b_i the bin of the rendered depth
    in ``mass_edges``; without a sensor model B = 1 and mass_w = 1: the kappa mass)."""
    num_tiles = offsets.shape[0] - 1
    # arrays viewed per pixel or contribution, borrowed (engine/cpu/borrowed.py)
    attrs = borrow(attrs_arg)
    st_k = borrow(st_k_arg)
    st_v = borrow(st_v_arg)
    longest = longest_list(offsets)
    for ch in prange(nchunks):
        owned = new_scratch(tile, longest)   # kept alive to the chunk's end (keep_alive) for its borrowed copy
        scratch = borrow(owned)
        eacc = np.empty(_linear_width(num_classes), dtype=np.float32)
        for kk in range(_chunk_tile_count(ch, nchunks, tiles_x, num_tiles)):
            t = _chunk_tile(kk, ch, nchunks, tiles_x)
            start, end = offsets[t], offsets[t + 1]
            n = end - start
            tile_list = lists[start:end]
            loaded = False
            misses = 0 if short_ok else SHORT_MISSES
            ty, tx = t // tiles_x, t % tiles_x
            u0 = tx * tile
            u1 = min(width, u0 + tile) - 1
            for v in range(ty * tile, min(height, ty * tile + tile)):
                active = scratch[8]
                walked = False
                qt = _record_row(t, v - ty * tile, tile)
                for p in range(u1 + 1 - u0):
                    a = not use_store or pix_cnt[qt + p] < 0
                    active[p] = a
                    walked |= a
                if walked:
                    if not loaded:
                        load_tile(walk, lists, start, end, scratch[0])
                        loaded = True
                    cols, cand, ridx, words, kidx, kval, cnt, trans, active, chunk, hit, state = scratch
                    r = row_candidates(cols, n, v, u0, u1, cand, ridx, words)
                    composite_row(cand, ridx, r, u0, u1, active, cnt, kidx, kval, trans, chunk, hit, state)
                kidx, kval, cnt, trans = scratch[4], scratch[5], scratch[6], scratch[7]
                for u in range(u0, u1 + 1):
                    p = u - u0
                    if active[p]:
                        misses += _shade_pixel(v, u, kidx[p], kval[p], cnt[p], trans[p], attrs, short, num_classes,
                                               tile_list, eacc, e_bg, v_bg, s_bg, bg_rgb, want_probs,
                                               misses < SHORT_MISSES, out_label, out_exp, out_var, out_bg,
                                               out_evidence, out_rgb, out_probs, out_depth)
                        if want_mass:
                            _add_mass(kidx[p], kval[p], cnt[p], tile_list, out_label[v, u], out_depth[v, u],
                                      mass_edges, mass_w, mass[ch])
                    else:
                        q = qt + p
                        off = pix_off[q]
                        c = pix_cnt[q]
                        misses += _shade_pixel(v, u, st_k[ch, off:off + c], st_v[ch, off:off + c], c, pix_t[q], attrs,
                                               short, num_classes, tile_list, eacc, e_bg, v_bg, s_bg, bg_rgb,
                                               want_probs, misses < SHORT_MISSES, out_label, out_exp,
                                               out_var, out_bg, out_evidence, out_rgb, out_probs, out_depth)
        keep_alive(owned)


@njit(cache=True, fastmath=FAST)
def _kappa_kernel(offsets, lists, walk, width, height, tile, tiles_x,
                  count_only, pix, gid, kap, bg):  # pragma: no cover
    num_tiles = offsets.shape[0] - 1
    total = 0
    scratch = new_scratch(tile, longest_list(offsets))
    for t in range(num_tiles):
        start, end = offsets[t], offsets[t + 1]
        n = end - start
        load_tile(walk, lists, start, end, scratch[0])
        cols, cand, ridx, words, kidx, kval, cnt, trans, active, chunk, hit, state = scratch
        ty, tx = t // tiles_x, t % tiles_x
        u0 = tx * tile
        u1 = min(width, u0 + tile) - 1
        for v in range(ty * tile, min(height, ty * tile + tile)):
            r = row_candidates(cols, n, v, u0, u1, cand, ridx, words)
            composite_row(cand, ridx, r, u0, u1, active, cnt, kidx, kval, trans, chunk, hit, state)
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
    args = (bins.offsets, bins.lists, proj.walk, width, height, bins.tile_size, bins.tiles_x)
    n = _kappa_kernel(*args, True, np.empty(0, np.int64), np.empty(0, np.int32), np.empty(0), np.empty(0))
    pix = np.empty(n, dtype=np.int64)
    gid = np.empty(n, dtype=np.int32)
    kap = np.empty(n)
    bg = np.ones(width * height)
    _kappa_kernel(*args, False, pix, gid, kap, bg)
    return KappaLists(pix, proj.ids[gid], kap, bg)


def _num_chunks(bins: TileBins) -> int:
    """Work chunks = threads; tile rows are dealt round-robin (:func:`_chunk_tile`) so both cores get a similar
    load and no cache line of an output row is written by two threads."""
    return max(1, min(numba.get_num_threads(), bins.tiles_x * bins.tiles_y))


class ContributionStore:
    """Each voting pixel's contributions (tile-list position uint16, kappa float32: 6 bytes), recorded by an update
    so that the render of the same frame (``SemanticMap.observe``) replays them instead of walking again.

    ``pixels``: the records' count, tiles x tile^2 (tile-major, see ``_update_kernel``). Bounded: per work chunk
    ``STORE_SLOTS_PER_PIXEL`` x ``chunk_pixels`` (the largest chunk's pixel records) entries; pixels that do not fit,
    that the update did not composite (no vote) or whose tile list is longer than 65535 are walked by the render. The
    ``np.empty`` buffers (untouched pages cost no memory) are kept from frame to frame, so a frame's store holds
    the pages its contributions touched (6 bytes each: ~37 MB at 640x480 with 20 contributions a pixel); taking
    fresh ones each frame cost their page faults, about 10 % of a biker frame. :meth:`release` gives them back.
    One per thread of use, like :class:`UpdateWorkspace`.
    """

    def __init__(self) -> None:
        self.release()

    def release(self) -> None:
        """Drop the buffers (and the frame they belong to)."""
        self._key: tuple[int, int, int] | None = None
        self.owner: object | None = None
        self.k = np.empty((1, 0), np.uint16)
        self.v = np.empty((1, 0), np.float32)
        self.off = np.empty(0, np.int64)
        self.cnt = np.empty(0, np.int32)
        self.t = np.empty(0)

    def reserve(self, pixels: int, nchunks: int, chunk_pixels: int) -> "ContributionStore":
        if self._key != (pixels, nchunks, chunk_pixels):
            cap = STORE_SLOTS_PER_PIXEL * chunk_pixels
            self.k = np.empty((nchunks, cap), np.uint16)
            self.v = np.empty((nchunks, cap), np.float32)
            self.off = np.empty(pixels, np.int64)
            self.cnt = np.empty(pixels, np.int32)
            self.t = np.empty(pixels)
            self._key = (pixels, nchunks, chunk_pixels)
        return self

    @property
    def nchunks(self) -> int:
        return int(self.k.shape[0])

    def arrays(self) -> tuple[np.ndarray, ...]:
        return self.k, self.v, self.off, self.cnt, self.t


STORE_SLOTS_PER_PIXEL = 40
_STORE_MAX_LIST = 65535       # tile-list positions are stored as uint16
_NO_STORE = (np.empty((1, 0), np.uint16), np.empty((1, 0), np.float32), np.empty(0, np.int64),
             np.empty(0, np.int32), np.empty(0))
_NO_MODEL = (np.zeros(2), np.zeros(1), np.zeros((1, 1)))
_NO_CONFIDENCE = np.zeros((1, 1), dtype=np.float32)
_NO_PLANE = np.zeros((1, 1), dtype=np.float32)
_NO_TRANSIENT = np.zeros(0, dtype=np.bool_)


def accumulate_update(proj: ProjectedGaussians, bins: TileBins, inputs: FrameLabels,
                      soft: SoftLabels | None = None, workspace: UpdateWorkspace | None = None,
                      store: ContributionStore | None = None, concentrations: np.ndarray | None = None
                      ) -> tuple[Increments, np.ndarray, np.ndarray | None]:
    """Per visible Gaussian, sum_i kappa_in * y_i^c, as per-thread partial sums, with the frame's pixel counts.

    Args:
        inputs: the frame's labels and optional confidence as they came in (:class:`FrameLabels`); each pixel's
            vote is :func:`~css_ros.engine.label_input.pixel_vote`, applied inside the compiled pass.
        soft: the sensor model's tables (depth bins in splat units), or None for the paper's one-hot votes.
        workspace: accumulators kept between frames (call its ``done`` after
            :func:`~css_ros.engine.cpu.increments.add_increments`), or None for fresh ones.
        store: if given, records the contributions for a following :func:`render_semantic`.
        concentrations: (N, C) float64 alpha before the update; needed only for the surprise
            (``inputs.want_surprise``).
    Returns:
        (the partial increments for the ``proj.ids`` rows of the concentrations (:class:`Increments`: the (chunks,
        M, C) classes', the (chunks, M) of every class ((0, 0) without ``soft``), the marks of the entries written),
        applied by :func:`~css_ros.engine.cpu.increments.add_increments`; (NUM_COUNTS,) int64 pixel counts:
        used, ignored, out of range, no depth (0 without ``soft``), transient, occluded; the (H, W) float32
        surprise image, or None when not asked for).
    """
    height, width = inputs.labels.shape
    nchunks = _num_chunks(bins)
    inc = (workspace or UpdateWorkspace()).take(nchunks, inputs.num_classes, proj.count, soft is not None)
    counts = np.zeros((nchunks, NUM_COUNTS), dtype=np.int64)
    edges, base, resid = _NO_MODEL if soft is None else (soft.edges, soft.base, soft.resid)
    conf = _NO_CONFIDENCE if inputs.confidence is None else inputs.confidence
    rules = inputs.rules
    want_surprise = inputs.want_surprise and concentrations is not None
    surprise = np.full((height, width), np.nan, dtype=np.float32) if want_surprise else _NO_PLANE
    e_pre = _expectations(concentrations, proj.ids) if want_surprise else _NO_PLANE
    transient = rules.transient if rules.transient.shape[0] == inputs.num_classes else _NO_TRANSIENT
    gate = (_NO_PLANE if inputs.depth is None else inputs.depth, inputs.depth is not None, float(rules.tol_abs),
            float(rules.tol_rel), float(rules.depth_scale), transient, want_surprise, e_pre, surprise)
    records = (bins.offsets.shape[0] - 1) * bins.tile_size ** 2   # _record_row's range
    # the largest chunk's records (chunk 0 has as many tile rows as any)
    chunk_records = chunk_tile_count(0, nchunks, bins.tiles_x, bins.tiles_x * bins.tiles_y) * bins.tile_size ** 2
    _update_kernel(bins.offsets, bins.lists, proj.walk, proj.packed, inputs.labels, conf,
                   inputs.confidence is not None, inputs.ignore_label, width, height, bins.tile_size, bins.tiles_x,
                   inc, soft is not None, edges, base, resid, counts, store is not None,
                   *(_NO_STORE if store is None else store.reserve(records, nchunks, chunk_records).arrays()), gate)
    return inc, counts.sum(axis=0), surprise if want_surprise else None


@njit(parallel=True, cache=True, nogil=True, fastmath=FAST)
def _expectations(concentrations, ids):  # pragma: no cover
    """(C, M) float32 E[theta] = alpha / S of the projected Gaussians' rows ``ids`` (for the surprise), class-major:
    a tile gathers one class of its list, whose entries lie in a few runs of neighbouring rows."""
    m = ids.shape[0]
    num_classes = concentrations.shape[1]
    out = np.empty((num_classes, m), dtype=np.float32)
    for j in prange(m):
        prefetch_ahead(concentrations, ids, j)
        row = ids[j]
        total = 0.0
        for c in range(num_classes):
            total += concentrations[row, c]
        inv = 1.0 / total
        for c in range(num_classes):
            out[c, j] = np.float32(concentrations[row, c] * inv)
    return out


@njit(inline="always", fastmath=FAST)
def _attribute_row(concentrations, row, j, colors, packed, attrs, short):  # pragma: no cover
    """attrs[j] and short[j] of :func:`dirichlet_attributes` from row ``row`` of the concentrations, every column
    written (the padding zero), so the rows can be taken with ``np.empty``."""
    num_classes = concentrations.shape[1]
    lin = _linear_width(num_classes)
    total = 0.0
    top = 0
    for c in range(num_classes):
        x = concentrations[row, c]
        total += x
        top = c if x > concentrations[row, top] else top
    inv = 1.0 / total
    denom = 1.0 / (1.0 + total)
    for c in range(3):
        attrs[j, num_classes + c] = np.float32(colors[j, c]) if colors.shape[0] else np.float32(0.0)
    attrs[j, num_classes + 3] = np.float32(total)
    attrs[j, num_classes + 4] = np.float32(packed[j, 7])
    for c in range(num_classes + 5, lin):
        attrs[j, c] = np.float32(0.0)
    for c in range(num_classes):
        e = concentrations[row, c] * inv
        attrs[j, c] = np.float32(e)
        attrs[j, lin + c] = np.float32(e * (1.0 - e) * denom)
    short[j, 0] = attrs[j, top]
    short[j, 1] = attrs[j, lin + top]
    for c in range(5):
        short[j, 2 + c] = attrs[j, num_classes + c]
    short[j, 7] = np.float32(top)


@njit(parallel=True, cache=True, nogil=True, fastmath=FAST)
def _dirichlet_kernel(concentrations, ids, colors, packed, attrs, short):  # pragma: no cover
    """attrs[j], short[j] of :func:`dirichlet_attributes` for every projected Gaussian j."""
    for j in prange(ids.shape[0]):
        prefetch_ahead(concentrations, ids, j)  # the rows lie scattered in the model's order
        _attribute_row(concentrations, ids[j], j, colors, packed, attrs, short)


@njit(parallel=True, cache=True, nogil=True, fastmath=FAST)
def _add_and_attribute_kernel(concentrations, ids, acc, acc_base, marks, slot_class, slot_value, decay, prior, colors,
                              packed, attrs, short):  # pragma: no cover
    """:func:`~css_ros.engine.cpu.increments.add_increments` and then :func:`_dirichlet_kernel` of each row while it
    is in cache (one gather of the visible Gaussians' concentration rows instead of two)."""
    for j in prange(ids.shape[0]):
        prefetch_ahead(concentrations, ids, j)  # the rows lie scattered in the model's order
        add_increment_row(concentrations, ids[j], j, acc, acc_base, marks, slot_class, slot_value, decay, prior)
        _attribute_row(concentrations, ids[j], j, colors, packed, attrs, short)


class AttributeRows(NamedTuple):
    """What the shading reads of each projected Gaussian (:func:`dirichlet_attributes`)."""

    full: np.ndarray   #: (M, linear_width(C) + C) float32: E_0..E_{C-1}, r, g, b, S, z, 0.., Var_0..Var_{C-1}
    short: np.ndarray  #: (M, SHORT_COLS) float32: E, Var of the most likely class, r, g, b, S, z, that class


def new_attribute_rows(m: int, num_classes: int) -> AttributeRows:
    """Uninitialised attribute rows of m projected Gaussians (also the maker of a :class:`~.kept.Kept` of them)."""
    return AttributeRows(np.empty((m, linear_width(num_classes) + num_classes), dtype=np.float32),
                         np.empty((m, SHORT_COLS), dtype=np.float32))


def add_increments_and_attributes(concentrations: np.ndarray, ids: np.ndarray, inc: Increments, decay: float,
                                  prior: float, colors: np.ndarray, packed: np.ndarray,
                                  kept: Kept | None = None) -> AttributeRows:
    """:func:`~css_ros.engine.cpu.increments.add_increments` then :func:`dirichlet_attributes` of the updated rows, in
    one pass (``observe``); into ``kept``'s rows when given."""
    rows = new_attribute_rows(ids.shape[0], concentrations.shape[1]) if kept is None else \
        AttributeRows(*kept.take(ids.shape[0], concentrations.shape[1]))
    _add_and_attribute_kernel(concentrations, ids, inc.acc, inc.base, inc.marks, inc.slot_class, inc.slot_value,
                              float(decay), float(prior), colors, packed, *rows)
    return rows


def dirichlet_attributes(concentrations: np.ndarray, ids: np.ndarray, colors: np.ndarray,
                         packed: np.ndarray, kept: Kept | None = None) -> AttributeRows:
    """Per projected Gaussian j: full[j] = (E_0..E_{C-1}, r, g, b, S, z, 0.., Var_0..Var_{C-1}) (SPEC §4 moments),
    the variances from column :func:`linear_width` on, and short[j] = (E^g, Var^g, r, g, b, S, z, g) with g its
    most likely class (the first of equal maxima), for the shading's short path (:func:`_shade_majority`).

    Args:
        concentrations: (N, C) float64 alpha; ids: (M,) model rows; colors: (M, 3) view colours, or
            (0, 3) for zero colour (views that are only scored); packed: (M, 8) projected rows (column 7:
            camera depth z, splat units); kept: rows kept between frames (a :class:`~.kept.Kept` of
            :func:`new_attribute_rows`), or None for fresh ones.
    Returns:
        float32 rows (halves the render's memory traffic; these rows are all the shading reads), with
        E = alpha / S, Var = E (1 - E) / (1 + S).
    """
    rows = new_attribute_rows(ids.shape[0], concentrations.shape[1]) if kept is None else \
        AttributeRows(*kept.take(ids.shape[0], concentrations.shape[1]))
    _dirichlet_kernel(concentrations, ids, colors, packed, *rows)
    return rows


def render_semantic(proj: ProjectedGaussians, bins: TileBins, width: int, height: int,
                    attrs: AttributeRows,
                    e_bg: float, v_bg: float, s_bg: float, bg_rgb: np.ndarray,
                    want_probs: bool, mass_weights: "tuple[np.ndarray, np.ndarray] | None" = None,
                    store: ContributionStore | None = None) -> RenderBuffers:
    """Composite colour, expectation, argmax-class variance and evidence (SPEC §5).

    Args:
        store: contributions recorded by :func:`accumulate_update` at the same pose, or None.
        attrs: the projected Gaussians' rows (:func:`dirichlet_attributes`).
        e_bg, v_bg, s_bg: background expectation, variance (per class) and total.
        mass_weights: (edges (B + 1,) splat units, net vote weight per (label, depth bin) (C * B,)): also return
            each projected Gaussian's evidence mass in the view (``RenderBuffers.mass``, (M,) float64).
    """
    num_classes = attribute_classes(attrs.full.shape[1])
    out_label = np.empty((height, width), dtype=np.int32)
    out_exp = np.empty((height, width))
    out_var = np.empty((height, width))
    out_bg = np.empty((height, width))
    out_ev = np.empty((height, width))
    out_rgb = np.empty((height, width, 3))
    out_probs = np.empty((height, width, num_classes) if want_probs else (1, 1, num_classes))
    out_depth = np.empty((height, width))
    nchunks = _num_chunks(bins) if store is None else store.nchunks
    want_mass = mass_weights is not None
    mass = np.zeros((nchunks, proj.count) if want_mass else (nchunks, 0))
    edges, wts = mass_weights if mass_weights is not None else (np.zeros(2), np.ones(1))
    short_ok = linear_width(num_classes) >= SHORT_MIN_COLUMNS
    _render_kernel(bins.offsets, bins.lists, proj.walk, attrs.full, attrs.short, short_ok, num_classes, e_bg, v_bg, s_bg,
                   np.asarray(bg_rgb, dtype=np.float64), width, height, bins.tile_size, bins.tiles_x,
                   want_probs, nchunks, store is not None, *(_NO_STORE if store is None else store.arrays()),
                   out_label, out_exp, out_var, out_bg, out_ev, out_rgb, out_probs, out_depth,
                   want_mass, edges, wts, mass)
    return RenderBuffers(out_label, out_exp, out_var, out_bg, out_ev, out_rgb,
                         out_probs if want_probs else None, out_depth,
                         mass.sum(axis=0) if want_mass else None)


bind_sources(globals())  # cached kernels recompile when any module they are built from changes
