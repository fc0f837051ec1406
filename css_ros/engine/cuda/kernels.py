"""numba-cuda kernels of the CUDA backend: projection, tile-key emission, Dirichlet moments, the
update and the render (SPEC §3-6). Imported only by :mod:`.backend` (it imports ``numba.cuda``).

Pipeline per batch of views (one view for ``observe`` / ``render``, all candidates for
``score_views``), each stage one launch over all views:

1. :func:`project_kernel`: one thread per (Gaussian, view), the views of a Gaussian on neighbouring
   lanes: EWA projection, SPEC §3 culls, exact
   alpha >= 1/255 box, view-dependent colour; kept pairs are appended through an atomic counter.
2. (array library) prefix sum of the number of tiles each kept pair's box overlaps.
3. Order: one stable radix sort of the kept pairs by their float32 depth (32-bit keys), then
   :func:`emit_keys_kernel` writes one int32 key ``view * T + tile`` and its pair index per (pair,
   tile) in that depth order, and one stable radix sort of these 32-bit keys gives every tile its
   front-to-back list (equal float32 depths keep their emission order); searchsorted its range. Two
   4-pass sorts of 32-bit keys move less than half the bytes of one 8-pass sort of 64-bit
   ``(view, tile) << 32 | depth`` keys.
4. :func:`moments_kernel`: E, Var, S per visible Gaussian in float32, once per frame.
5. update / render kernels (:func:`make_update_kernel`, :func:`make_render_kernel`): one block per
   tile, one thread per pixel; the tile's list is staged through shared memory in batches, pixels
   composite front to back with the INRIA rules (float32 walk), the block stops when all
   its pixels are done; the update sums kappa * weight per (Gaussian, class) in shared memory and
   adds each sum once with a float64 atomic (with a sensor model, a kernel variant walks each tile twice:
   expected depth first, then the votes per (label, depth bin) row, the table applied at the flush); the
   render also gives the expected depth sum kappa z / sum kappa per pixel.

Pixel (u, v) centres are integers (u right, v down); lengths in pixels, depths in metres.
"""
from __future__ import annotations

import math
from functools import lru_cache
from typing import Any

from numba import cuda, float32, float64, int32

from ..change_rules import depth_gate
from ..label_input import IGNORED, NO_DEPTH, OCCLUDED, OUT_OF_RANGE, TRANSIENT, USED, pixel_vote, transient_status
from ..pixel_math import confidence_score, depth_bin, interp, to_byte
from ..sh import sh_polynomial
from .arrays import simulator_enabled
from .layout import (PL_BG, PL_CONFIDENCE, PL_DEPTH, PL_E, PL_EVIDENCE, PL_LABELS, PL_PROBS, PL_RGB,  # noqa: F401
                     PL_VAR, NUM_PLANES, HEADER_WORDS)
from ..spec import ALPHA_MAX, ALPHA_MIN, COV2D_DILATION, NEAR_PLANE, RENDER_CLASS_CHUNK, T_MIN, VAR_FLOOR
from ..splat_math import ewa_splat, fov_limits, store_splat, view_direction

if simulator_enabled():  # the simulator has no warp intrinsics; add exact block-barrier versions
    from .simwarp import install

    install()

PACK_COLS = 8   # per kept pair: u, v, conic a, b, c, opacity, qmax, depth
# The update's staged rows hold a float32 sum per class: up to C = 40 a batch of 64 Gaussians fits in
# 12 KiB; beyond, the batch shrinks so that 12 blocks (37.5 % occupancy) stay resident on an sm_80 SM.
UPDATE_SHARED_BUDGET = 12 * 1024
# Registers per thread of the update (test/test_cuda_ptx.py's budget). The variants with the changing world's rules
# tell ptxas through launch bounds (left alone it gives them 72 on sm_80; with the bound 60, no spills); the
# paper's update is compiled as it always was.
UPDATE_MAX_REGISTERS = 64
REGISTERS_PER_SM = 65536


def update_launch_bounds(tile: int) -> tuple[int, int]:
    """(threads per block, resident blocks) that hold the update to :data:`UPDATE_MAX_REGISTERS` registers."""
    nt = tile * tile
    return nt, max(1, REGISTERS_PER_SM // (UPDATE_MAX_REGISTERS * nt))


def _update_jit(tile: int, with_rules: bool) -> Any:
    """``cuda.jit`` of an update kernel: with launch bounds for a variant with rules (not under the simulator, which
    has none)."""
    if with_rules and not simulator_enabled():
        return cuda.jit(launch_bounds=update_launch_bounds(tile))  # type: ignore[call-arg]  # (mypy sees the simulator)
    return cuda.jit


_fov_limits = cuda.jit(device=True, inline=True)(fov_limits)
_ewa_splat = cuda.jit(device=True, inline=True)(ewa_splat)
_store_splat = cuda.jit(device=True, inline=True)(store_splat)
_view_direction = cuda.jit(device=True, inline=True)(view_direction)
_sh_polynomial = cuda.jit(device=True, inline=True)(sh_polynomial)
_to_byte = cuda.jit(device=True, inline=True)(to_byte)
_depth_bin = cuda.jit(device=True, inline=True)(depth_bin)
_interp = cuda.jit(device=True, inline=True)(interp)
_confidence_score = cuda.jit(device=True, inline=True)(confidence_score)
_pixel_vote = cuda.jit(device=True, inline=True)(pixel_vote)
_transient_status = cuda.jit(device=True, inline=True)(transient_status)
_depth_gate = cuda.jit(device=True, inline=True)(depth_gate)


@cuda.jit(device=True, inline=True)
def pixel_input(labels, confidence, has_confidence, num_classes, ignore_label, u, v):  # pragma: no cover
    """(class or -1, float32 weight, status; -1 outside the image) of pixel (u, v) under the label rule
    (:func:`css_ros.engine.label_input.pixel_vote`), read from the labels and confidence as they came in."""
    height, width = labels.shape
    if u >= width or v >= height:
        return int32(-1), float32(0.0), -1
    conf = 1.0
    if has_confidence:
        conf = float64(confidence[v, u])
    c, w, status = _pixel_vote(labels[v, u], conf, num_classes, ignore_label)
    return int32(c), w, status


@cuda.jit(device=True, inline=True)
def overflowed(sizes, packed, order):  # pragma: no cover
    """True when the frame's pairs or keys (sizes (2,) i64, written by the projection and the key emission) did not
    fit its buffers: the frame's lists are incomplete, and an update must add nothing (it is done again)."""
    return sizes[0] > packed.shape[0] or sizes[1] > order.shape[0]


@cuda.jit(device=True, inline=True)
def count_pixels(status, counts):  # pragma: no cover
    """Add the block's pixel counts (used, ignored, out of range) to ``counts`` with one atomic each (a barrier:
    every thread of the block must call it)."""
    used = cuda.syncthreads_count(1 if status == USED else 0)
    ignored = cuda.syncthreads_count(1 if status == IGNORED else 0)
    oor = cuda.syncthreads_count(1 if status == OUT_OF_RANGE else 0)
    if cuda.threadIdx.x == 0:
        if used:
            cuda.atomic.add(counts, USED, used)
        if ignored:
            cuda.atomic.add(counts, IGNORED, ignored)
        if oor:
            cuda.atomic.add(counts, OUT_OF_RANGE, oor)


@cuda.jit(device=True, inline=True)
def _surely_culled(cam, means, i, max_std, width, height):  # pragma: no cover
    """A cheap float32 test, before the float64 EWA projection, that is True only where :func:`ewa_splat` would
    surely cull the pair: the centre behind the near plane, or farther outside the image than the early cull's
    3-sigma bound (computed with the same bound on the screen covariance). Every float32 rounding is covered by
    margins (the z test by 1e-6 of the terms' magnitudes, the lateral test only where z is known to 0.1 % and with
    1 % + 2 px + 0.2 % f slack), so a pair it culls is one the float64 path culls too: the kept pairs are exactly
    the CPU's (tested against the numba projection)."""
    mx = float32(means[i, 0])
    my = float32(means[i, 1])
    mz = float32(means[i, 2])
    tx = float32(cam[0]) * mx + float32(cam[1]) * my + float32(cam[2]) * mz + float32(cam[9])
    ty = float32(cam[3]) * mx + float32(cam[4]) * my + float32(cam[5]) * mz + float32(cam[10])
    tz = float32(cam[6]) * mx + float32(cam[7]) * my + float32(cam[8]) * mz + float32(cam[11])
    mag = abs(mx) + abs(my) + abs(mz) + float32(1.0)
    scale = float32(3.0) * mag + abs(float32(cam[9])) + abs(float32(cam[10])) + abs(float32(cam[11]))
    tol = float32(1e-6) * scale  # > 4x the rounding of the float32 transform (rows of R are unit vectors)
    if tz < float32(NEAR_PLANE) - tol:
        return True
    if not (tz > float32(NEAR_PLANE) + tol and tol < float32(1e-3) * tz):
        return False  # z not known well enough: leave it to the float64 path
    fx = float32(cam[12])
    fy = float32(cam[13])
    cx = float32(cam[14])
    cy = float32(cam[15])
    _, _, _, _, jac_sq = _fov_limits(cam, width, height)  # the early cull's bound on ||J||_F^2 z^2
    ms = float32(max_std)
    bound = float32(1.01) * (float32(3.0) * math.sqrt(float32(jac_sq) * ms * ms / (tz * tz)
                                                      + float32(COV2D_DILATION)) + float32(1.0))
    u = fx * tx / tz + cx
    v = fy * ty / tz + cy
    slack_u = float32(0.01) * abs(u - cx) + float32(0.002) * fx + float32(2.0)
    slack_v = float32(0.01) * abs(v - cy) + float32(0.002) * fy + float32(2.0)
    w = float32(width)
    h = float32(height)
    return (u < float32(-0.5) - bound - slack_u or u > w - float32(0.5) + bound + slack_u
            or v < float32(-0.5) - bound - slack_v or v > h - float32(0.5) + bound + slack_v)


@cuda.jit
def project_kernel(means, cov3d, opac, max_std, sh, cams, width, height, tile, want_color, capacity,
                   counter, out_packed, out_bbox, out_id, out_view, out_ntiles, out_color,
                   out_depth):  # pragma: no cover
    """Project every (view, Gaussian) pair (:func:`css_ros.engine.splat_math.ewa_splat`, the CPU's
    maths); append the kept ones at ``counter`` (atomic).

    Args:
        means (N, 3) f64 [m, map]; cov3d (N, 6) f64 upper triangle [m^2]; opac (N,) f64;
        max_std (N,) f64 [m]; sh (N, K, 3) f32; cams (V, CAM_COLS) f64 camera rows; width, height [px]
        (float); tile [px]; want_color: evaluate SH (else colours are 0); capacity: rows of the outputs.
    Outputs (row = slot, valid below min(counter, capacity)):
        out_packed (cap, 8) f64 (u, v, a, b, c, opacity, qmax, depth); out_bbox (cap, 4) i32 inclusive
        pixel box (u0, u1, v0, v1) of the alpha >= 1/255 ellipse; out_id / out_view (cap,) i32;
        out_ntiles (cap,) i32 tiles the box overlaps; out_color (cap, 3) f32; out_depth (cap,) f32 the camera
        depth rounded to float32 (the depth sort's key; rows past the count keep what they held, +inf for the
        single-view plan). counter[0] ends as the number of kept pairs, also where it exceeds ``capacity``.
    """
    n_views = cams.shape[0]
    total = means.shape[0] * n_views
    start = cuda.grid(1)
    stride = cuda.gridsize(1)
    for flat in range(start, total, stride):
        # consecutive threads take the views of one Gaussian: its 88 bytes come from DRAM once per batch
        # of views (L1 serves the rest), not once per view (a 1M model is 88 MB, more than the L2)
        i = flat // n_views
        view = flat - i * n_views
        cam = cams[view]
        if _surely_culled(cam, means, i, max_std[i], width, height):
            continue
        lo_x, hi_x, lo_y, hi_y, jac_sq = _fov_limits(cam, width, height)
        splat = _ewa_splat(cam, means, cov3d, i, opac[i], max_std[i], width, height, lo_x, hi_x, lo_y, hi_y, jac_sq)
        if not splat[0]:
            continue
        slot = cuda.atomic.add(counter, 0, 1)
        if slot >= capacity:
            continue  # the host grows the buffers and projects again
        _store_splat(out_packed, out_bbox, slot, splat, opac[i])
        bu0 = int32(splat[8])
        bu1 = int32(splat[9])
        bv0 = int32(splat[10])
        bv1 = int32(splat[11])
        out_id[slot] = i
        out_view[slot] = view
        out_depth[slot] = float32(splat[7])
        out_ntiles[slot] = (bu1 // tile - bu0 // tile + 1) * (bv1 // tile - bv0 // tile + 1)
        if want_color:
            x, y, z = _view_direction(cam, means, i)
            k = sh.shape[1]
            for ch in range(3):
                out_color[slot, ch] = max(_sh_polynomial(sh[i, :, ch], k, x, y, z) + 0.5, 0.0)
        else:
            for ch in range(3):
                out_color[slot, ch] = 0.0


@cuda.jit
def emit_keys_kernel(bbox, view, by_depth, ends, counter, tile, tiles_x, tiles_per_view, keys,
                     pairs):  # pragma: no cover
    """Tile keys in depth order: for the r-th nearest pair j = by_depth[r] (r < min(counter[0], rows)) and the k-th
    tile of its box, keys[ends[r] - n_j + k] = view_j * T + tile_k (int32) and pairs[...] = j, n_j the tiles of
    j's box and ends the inclusive prefix sum of the tile counts in depth order. The keys are written front to
    back, so a stable sort of these 32-bit keys alone gives every (view, tile) its front-to-back list. The last
    pair's thread sets counter[1] to the number of keys; pairs whose keys would pass the end of ``keys`` write none
    (the single-view plan sees counter[1] > its capacity and renders the frame again with more room)."""
    start = cuda.grid(1)
    stride = cuda.gridsize(1)
    num_pairs = min(counter[0], by_depth.shape[0])
    for r in range(start, num_pairs, stride):
        j = by_depth[r]
        end = ends[r]
        if r == num_pairs - 1:
            counter[1] = end
        if end > keys.shape[0]:
            continue
        pos = end - (bbox[j, 1] // tile - bbox[j, 0] // tile + 1) * (bbox[j, 3] // tile - bbox[j, 2] // tile + 1)
        base = view[j] * tiles_per_view
        for ty in range(bbox[j, 2] // tile, bbox[j, 3] // tile + 1):
            for tx in range(bbox[j, 0] // tile, bbox[j, 1] // tile + 1):
                keys[pos] = int32(base + ty * tiles_x + tx)
                pairs[pos] = j
                pos += 1


@cuda.jit
def moments_kernel(concentrations, rows, count, out):  # pragma: no cover
    """out[r] = (E_0..E_{C-1}, Var_0..Var_{C-1}, S) in float32 for Gaussian rows[r], r < min(count[0], rows)
    (SPEC §4):
    S = sum_c alpha^c, E = alpha / S, Var = E (1 - E) / (1 + S) (computed in float64).

    One thread per (row, class), the classes of a row on neighbouring lanes: each thread sums its row's C
    concentrations (the lanes of a row read the same addresses: broadcast, one or two cache lines per row) and
    writes its class's E and Var next to its neighbours' (coalesced), the row's first lane S. A thread per row would
    read and write C strided values per lane (uncoalesced: each warp instruction touching 32 rows' cache lines)."""
    num_classes = concentrations.shape[1]
    start = cuda.grid(1)
    stride = cuda.gridsize(1)
    for flat in range(start, min(count[0], rows.shape[0]) * num_classes, stride):
        r = flat // num_classes
        c = flat - r * num_classes
        n = rows[r]
        total = 0.0
        for k in range(num_classes):
            total += concentrations[n, k]
        e = concentrations[n, c] / total
        out[r, c] = e
        out[r, num_classes + c] = e * (1.0 - e) / (1.0 + total)
        if c == 0:
            out[r, 2 * num_classes] = total


def batch_size(bytes_per_gaussian: int, threads: int, budget: int) -> int:
    """Gaussians staged per batch: one per thread, fewer if their shared rows exceed ``budget`` bytes."""
    return max(1, min(threads, budget // bytes_per_gaussian))


FULL_MASK = 0xFFFFFFFF
WARP = 32
# Early termination threshold of the float32 walk. Two alpha = 0.99 (clamped) layers leave T = 1e-4
# (1 + 2e-16) in float64, which continues, but 9.99998e-5 in float32, which would stop: a slack of
# 2e-5 relative (above float32 rounding over a few dozen steps) keeps the float64 decision there.
T_MIN_WALK = T_MIN * (1.0 - 2e-5)
STAGE_COLS = 7  # staged geometry per Gaussian, float32: u, v, conic a, b, c, opacity, qmax
RENDER_ATTR_COLS = 5  # the render's other staged columns per Gaussian, float32: r, g, b, S, camera depth z
RENDER_OUT_COLS = 9  # per pixel: label, E, Var, kappa_b, evidence, r, g, b, depth


@cuda.jit(device=True, inline=True)
def warp_sum_shuffles(x):  # pragma: no cover
    """Sum of ``x`` over the 32 lanes of a full warp, in x's own type (float32 or float64; every lane
    gets it): an xor butterfly of five shuffles."""
    off = 16
    while off > 0:
        x += cuda.shfl_xor_sync(FULL_MASK, x, off)
        off //= 2
    return x


if simulator_enabled():
    # The same butterfly on the 32 values of one exchange (five exchanges of 32 Python threads each cost the
    # simulator ~5x more); test_cuda_sim checks that both give bit-identical sums.
    from .simwarp import warp_xor_sum as warp_sum
else:
    warp_sum = warp_sum_shuffles


@cuda.jit(device=True, inline=True)
def stage_geometry(s_g, slot, packed, j):  # pragma: no cover
    """Copy pair j's (u, v, a, b, c, opacity, qmax) into shared row ``slot`` as float32."""
    for c in range(STAGE_COLS):
        s_g[slot, c] = float32(packed[j, c])


@cuda.jit(device=True, inline=True)
def pixel_alpha(s_g, k, fu, fv):  # pragma: no cover
    """float32 alpha of staged Gaussian k at pixel centre (fu, fv), 0 where the INRIA rules skip it
    (q > qmax, i.e. alpha < 1/255 before the clamp; or alpha < 1/255)."""
    dx = fu - s_g[k, 0]
    dy = fv - s_g[k, 1]
    q = s_g[k, 2] * dx * dx + float32(2.0) * s_g[k, 3] * dx * dy + s_g[k, 4] * dy * dy
    if not (q <= s_g[k, 6]):
        return float32(0.0)
    alpha = min(float32(ALPHA_MAX), s_g[k, 5] * math.exp(float32(-0.5) * q))
    if alpha < float32(ALPHA_MIN):
        return float32(0.0)
    return alpha


@cuda.jit(device=True, inline=True)
def walk_step(s_g, k, fu, fv, trans):  # pragma: no cover
    """One front-to-back compositing step of a pixel over staged Gaussian k (SPEC §3, float32), the
    one definition the update and render kernels share.

    Returns:
        (kappa, trans_next, stop): kappa = alpha T, the Gaussian's weight in the pixel (0 where the
        INRIA rules skip it); the transmittance after it; stop True when compositing it would take T
        below T_MIN (the Gaussian is then not composited: kappa 0, T unchanged; the walk ends).
    """
    alpha = pixel_alpha(s_g, k, fu, fv)
    if alpha == float32(0.0):
        return float32(0.0), trans, False
    test_t = trans * (float32(1.0) - alpha)
    if test_t < float32(T_MIN_WALK):
        return float32(0.0), trans, True
    return alpha * trans, test_t, False


@cuda.jit(device=True, inline=True)
def count_changes(status, counts):  # pragma: no cover
    """Add the block's TRANSIENT and OCCLUDED pixels to ``counts`` (:mod:`css_ros.engine.change_rules`), one atomic
    each (a barrier: every thread of the block must call it)."""
    transient = cuda.syncthreads_count(1 if status == TRANSIENT else 0)
    occluded = cuda.syncthreads_count(1 if status == OCCLUDED else 0)
    if cuda.threadIdx.x == 0:
        if transient:
            cuda.atomic.add(counts, TRANSIENT, transient)
        if occluded:
            cuda.atomic.add(counts, OCCLUDED, occluded)


@cuda.jit(device=True, inline=True)
def measured_depth(depth, u, v):  # pragma: no cover
    """The measured depth of pixel (u, v) in metres as float64 (NaN outside the image: no measurement)."""
    height, width = depth.shape
    if u >= width or v >= height:
        return math.nan
    return float64(depth[v, u])


@cuda.jit(device=True, inline=True)
def gate_pixel(status, measured, zsum, ksum, tol_abs, tol_rel, depth_scale):  # pragma: no cover
    """(status, front) of a pixel after the measured-depth rule (:func:`css_ros.engine.change_rules.depth_gate`):
    OCCLUDED for a USED pixel whose measurement is nearer than its rendered depth sum kappa z / sum kappa (splat
    units, times ``depth_scale``: metres) by more than the tolerance; ``front``: float32, in splat units, the camera
    depth of the Gaussians whose contributions add no evidence when nearer (-inf: none dropped; the voting walk then
    compares it with the staged float32 z, a register fewer than the float64 metres)."""
    if status != USED:
        return status, float32(-math.inf)
    rendered = math.nan
    if ksum > float32(0.0):
        rendered = float64(zsum) / float64(ksum) * depth_scale
    occluded, front = _depth_gate(measured, rendered, tol_abs, tol_rel)
    if occluded:
        return OCCLUDED, float32(-math.inf)
    return status, float32(front / depth_scale)


@cuda.jit(device=True, inline=True)
def write_surprise(surprise, u, v, esum, trans, num_classes):  # pragma: no cover
    """surprise[v, u] = 1 - E^y with E^y = sum_n kappa_n E_n^y (``esum``: NaN for a pixel without a vote, which
    makes its surprise NaN) + kappa_b / C before the update; nothing outside the image."""
    height, width = surprise.shape
    if u < width and v < height:
        surprise[v, u] = float32(1.0 - (float64(esum) + float64(trans) / num_classes))


@cuda.jit(device=True, inline=True)
def first_walk(s_g, s_z, s_row, order, packed, pair_row, mom, start, end, batch, tid, fu, fv, walking, lab,
               want_e):  # pragma: no cover
    """A pixel's walk of its tile's list before the votes: (sum kappa z (splat units), sum kappa, and with
    ``want_e`` sum kappa E_n^lab from the pre-update moments ``mom`` (rows ``pair_row``), the final transmittance),
    float32, for the pixels ``walking`` (the others get zeros and 1). Every thread of the block must call it
    (barriers); the next walk's first barrier orders its staging after this walk."""
    done = not walking
    trans = float32(1.0)
    zsum = float32(0.0)
    ksum = float32(0.0)
    esum = float32(0.0)
    for b0 in range(start, end, batch):
        if cuda.syncthreads_count(0 if done else 1) == 0:
            break
        n = min(batch, end - b0)
        if tid < n:
            j = order[b0 + tid]
            stage_geometry(s_g, tid, packed, j)
            s_z[tid] = float32(packed[j, 7])
            if want_e:
                s_row[tid] = pair_row[j]
        cuda.syncthreads()
        if not done:
            for k in range(n):
                kappa, trans, done = walk_step(s_g, k, fu, fv, trans)
                if done:
                    break
                zsum += kappa * s_z[k]
                ksum += kappa
                if want_e and kappa != float32(0.0):
                    esum += kappa * mom[s_row[k], lab]
    return zsum, ksum, esum, trans


@cuda.jit(device=True, inline=True)
def vote(s_acc, k, contrib, key, lane):  # pragma: no cover
    """Add a pixel's contribution to staged Gaussian k under its key (class or row slot) in the block's shared
    sums: a warp whose contributing lanes share one key sums them with shuffles and one lane adds the sum, else each
    lane adds its own. Every lane of the warp must call it."""
    active = cuda.ballot_sync(FULL_MASK, contrib != float32(0.0))
    if active != 0:
        lead = cuda.shfl_sync(FULL_MASK, key, cuda.ffs(active) - 1)
        if cuda.all_sync(FULL_MASK, contrib == float32(0.0) or key == lead):
            total = warp_sum(contrib)
            if lane == 0:
                cuda.atomic.add(s_acc, (k, lead), total)
        elif contrib != float32(0.0):
            cuda.atomic.add(s_acc, (k, key), contrib)


@cuda.jit(device=True, inline=True)
def flush_sums(s_acc, s_id, n, num_classes, tid, nt, target):  # pragma: no cover
    """Add each nonzero (staged Gaussian, class) sum of the block to target[s_id[k], c] with one float64 atomic."""
    for idx in range(tid, n * num_classes, nt):
        k = idx // num_classes
        c = idx - k * num_classes
        val = s_acc[k, c]
        if val != float32(0.0):
            cuda.atomic.add(target, (s_id[k], c), float64(val))


@lru_cache(maxsize=None)
def make_update_kernel(num_classes: int, tile: int, with_model: bool = False, num_bins: int = 1,
                       with_depth: bool = False, with_surprise: bool = False, with_transient: bool = False) -> Any:
    """Update kernel for C = ``num_classes`` and ``tile`` x ``tile`` px tiles (compile-time constants);
    with ``with_model``, the sensor-model variant for ``num_bins`` depth bins (:func:`_make_model_update_kernel`).
    Without it ``num_bins`` is not used, and the kernel is the paper's update, unchanged by the variant. The rules
    of a changing world (:mod:`css_ros.engine.change_rules`) are compiled in only where a frame uses them:
    ``with_transient`` (transient classes), ``with_depth`` (a measured depth image: one more walk per pixel with a
    measurement, for its rendered depth), ``with_surprise`` (the surprise image). Forgetting needs no variant: the
    backend points ``target`` at a per-pair scratch (``ids`` = the pair rows) and :func:`apply_increments_kernel`
    applies it.

    Launch: grid = tiles of the view, block = tile * tile threads (a multiple of 32). Kernel arguments:
    offsets (T + 1,) i64 tile ranges in ``order``; order (P,) i32 pair of each sorted key; packed (M, 8) f64;
    ids (M,) i32 rows of ``target``; labels (H, W) uint8 / uint16 / int32 / int64 as they came in; confidence (H, W)
    f32 / f64 (any (1, 1) array when has_confidence is False); has_confidence; ignore_label; tiles_x;
    target (N, C) f64 (the concentrations), to which sum_i kappa_in * weight_i is added at [ids[j], class_i];
    counts (NUM_COUNTS,) i32, to which the image's pixels are added by status (the label rule,
    :func:`pixel_input`, then the transient and depth rules); sizes (2,) i64 the frame's (pairs, keys): beyond the
    frame's buffers (:func:`overflowed`) nothing is added; transient (C,) bool; depth (H, W) f32 metres;
    tol_abs [m], tol_rel, depth_scale [m per splat unit]; pair_row (M,) i32 the row of each pair in ``mom``;
    mom (R, 2C + 1) f32 the moments before the update (:func:`moments_kernel`); surprise (H, W) f32 out. The
    arguments of a rule not compiled in may be any array of their dtype and rank.

    The pixel walk is float32 (alpha, transmittance, kappa * weight); per staged Gaussian a warp
    whose contributing lanes share one label sums them with shuffles and one lane adds the sum to
    the block's float32 shared accumulator (else each lane adds its own); each nonzero (Gaussian,
    class) sum of the tile then goes to the float64 map with one global atomic.
    """
    if with_model:
        return _make_model_update_kernel(num_classes, tile, num_bins, with_depth, with_surprise, with_transient)
    nt = tile * tile
    if nt % WARP:
        raise ValueError(f"tile {tile}: the update kernel needs tile * tile to be a multiple of {WARP}")
    C = num_classes
    batch = batch_size(4 * STAGE_COLS + 4 + 4 * C + 4 * with_depth + 4 * with_surprise, nt, UPDATE_SHARED_BUDGET)
    z_rows = batch if with_depth else 1
    e_rows = batch if with_surprise else 1
    gated = with_depth or with_transient

    @_update_jit(tile, gated or with_surprise)
    def update_kernel(offsets, order, packed, ids, labels, confidence, has_confidence, ignore_label, tiles_x,
                      target, counts, sizes, transient, depth, tol_abs, tol_rel, depth_scale, pair_row, mom,
                      surprise):  # pragma: no cover
        if overflowed(sizes, packed, order):
            return
        t = cuda.blockIdx.x
        tid = cuda.threadIdx.x
        lane = tid % WARP
        ty = t // tiles_x
        tx = t - ty * tiles_x
        u = tx * tile + tid % tile
        v = ty * tile + tid // tile
        # the shared arrays before the first barrier: the simulator makes a block's shared array when its first
        # thread reaches the line, and threads released together by a barrier could each make their own
        s_g = cuda.shared.array((batch, STAGE_COLS), float32)
        s_acc = cuda.shared.array((batch, C), float32)
        s_id = cuda.shared.array(batch, int32)
        s_z = cuda.shared.array(z_rows, float32)
        s_row = cuda.shared.array(e_rows, int32)
        lab, w, status = pixel_input(labels, confidence, has_confidence, C, ignore_label, u, v)
        asked = status == USED  # a vote before the rules of a changing world: it has a surprise
        fu = float32(u)
        fv = float32(v)
        start = offsets[t]
        end = offsets[t + 1]
        if with_transient:
            status = _transient_status(lab, status, transient)
        front = float32(-math.inf)
        if with_depth:  # walk 1 (pixels with a measurement): the rendered depth of the gate
            measured = measured_depth(depth, u, v)
            zsum, ksum, _, _ = first_walk(s_g, s_z, s_row, order, packed, pair_row, mom, start, end, batch, tid, fu,
                                          fv, status == USED and measured > 0.0, lab, False)
            status, front = gate_pixel(status, measured, zsum, ksum, tol_abs, tol_rel, depth_scale)
        count_pixels(status, counts)
        if gated:
            count_changes(status, counts)
        done = status != USED
        esum = float32(0.0)
        if with_surprise:  # pixels with a vote walk for their surprise, those the rules stopped vote nothing
            done = not asked
            if status != USED:
                w = float32(0.0)
            if not asked:
                esum = float32(math.nan)
        trans = float32(1.0)
        for b0 in range(start, end, batch):
            if cuda.syncthreads_count(0 if done else 1) == 0:
                break  # every labelled pixel of the tile has terminated
            n = min(batch, end - b0)
            if tid < n:
                j = order[b0 + tid]
                stage_geometry(s_g, tid, packed, j)
                s_id[tid] = ids[j]
                if with_depth:
                    s_z[tid] = float32(packed[j, 7])
                if with_surprise:
                    s_row[tid] = pair_row[j]
            for idx in range(tid, batch * C, nt):
                s_acc[idx // C, idx % C] = float32(0.0)
            cuda.syncthreads()
            for k in range(n):  # every lane walks every Gaussian: the warp shuffles need all 32
                contrib = float32(0.0)
                if not done:
                    kappa, trans, done = walk_step(s_g, k, fu, fv, trans)
                    contrib = kappa * w
                    if with_surprise and kappa != float32(0.0):
                        esum += kappa * mom[s_row[k], lab]
                    if with_depth and s_z[k] < front:
                        contrib = float32(0.0)  # in front of the measured surface: no evidence
                vote(s_acc, k, contrib, lab, lane)
            cuda.syncthreads()
            flush_sums(s_acc, s_id, n, C, tid, nt, target)
        if with_surprise:
            write_surprise(surprise, u, v, esum, trans, C)
    return update_kernel


@cuda.jit
def apply_increments_kernel(increments, ids, sizes, packed, order, decay, prior, concentrations):  # pragma: no cover
    """Forgetting (:mod:`css_ros.engine.change_rules`): for each kept pair j < min(sizes[0], rows) whose frame
    increment increments[j] (C,) f64 is non-zero in some class, concentrations[ids[j]] <- prior + (alpha - prior)
    * decay + increment; the pair's increments are zeroed again for the next frame (one thread per pair: a
    Gaussian has one pair per view). Nothing when the frame overflowed its buffers (its update added nothing)."""
    if overflowed(sizes, packed, order):
        return
    num_classes = increments.shape[1]
    start = cuda.grid(1)
    stride = cuda.gridsize(1)
    for j in range(start, min(sizes[0], increments.shape[0]), stride):
        touched = False
        for c in range(num_classes):
            if increments[j, c] != 0.0:
                touched = True
        if not touched:
            continue
        n = ids[j]
        for c in range(num_classes):
            concentrations[n, c] = prior + (concentrations[n, c] - prior) * decay + increments[j, c]
            increments[j, c] = 0.0


def model_update_layout(num_classes: int, tile: int, num_bins: int, with_surprise: bool = False) -> tuple[int, int]:
    """(staged Gaussians per batch, row slots per Gaussian) of the sensor-model update kernel.

    A tile's labelled pixels vote into at most min(tile^2, C B) distinct (label, depth bin) rows; each staged
    Gaussian gets one float32 sum per such row slot. The per-pixel slot arrays (2 tile^2 int32) and the slots'
    rows (int32) come off the same 12 KiB budget as the paper's update, so its occupancy floor holds (with the
    surprise, 4 bytes more per staged Gaussian: its moments row)."""
    nt = tile * tile
    slots = min(nt, num_classes * num_bins)
    fixed = 4 * (2 * nt + slots)
    return batch_size(4 * STAGE_COLS + 4 + 4 + 4 * slots + 4 * with_surprise, nt, UPDATE_SHARED_BUDGET - fixed), slots


@cuda.jit(device=True, inline=True)
def assign_slots(s_key, s_slot, s_row, row, tid):  # pragma: no cover
    """(slot of the pixel's row or -1, slots in use) of the block: the first pixel of each distinct row >= 0 leads
    it; slots numbered in pixel order, s_row[slot] = its row. Every thread of the block must call it (barriers)."""
    s_key[tid] = row
    cuda.syncthreads()
    first = tid
    if row >= 0:
        for q in range(tid):
            if s_key[q] == row:
                first = q
                break
    lead = row >= 0 and first == tid
    cuda.syncthreads()
    s_key[tid] = 1 if lead else 0
    cuda.syncthreads()
    slot = -1
    if lead:
        slot = 0
        for q in range(tid):
            slot += s_key[q]
        s_slot[tid] = slot
        s_row[slot] = row
    nr = cuda.syncthreads_count(1 if lead else 0)
    if row >= 0 and not lead:
        slot = s_slot[first]
    return slot, nr


@cuda.jit(device=True, inline=True)
def flush_table(s_acc, s_id, s_row, n, nr, num_classes, tid, nt, table, target):  # pragma: no cover
    """Per (staged Gaussian, class) one float64 sum over the block's slots of sum x table[row, c], added to
    target[s_id[k], c] with one atomic when non-zero."""
    for idx in range(tid, n * num_classes, nt):
        k = idx // num_classes
        c = idx - k * num_classes
        acc = float64(0.0)
        for sl in range(nr):
            val = s_acc[k, sl]
            if val != float32(0.0):
                acc += float64(val) * table[s_row[sl], c]
        if acc != float64(0.0):
            cuda.atomic.add(target, (s_id[k], c), acc)


def _make_model_update_kernel(num_classes: int, tile: int, num_bins: int, with_depth: bool = False,
                              with_surprise: bool = False, with_transient: bool = False) -> Any:
    """Update kernel with a sensor model (docs/spec.md "Sensor model"; the CPU's ``_update_kernel`` with
    ``use_model``): a labelled pixel (label y, weight w > 0) at expected depth d = sum kappa z / sum kappa
    (bin b: the largest with edges[b] <= d, clipped to [0, B - 1]) adds kappa * w * table[y B + b, c] to
    every class c of every Gaussian it composites.

    Kernel arguments: those of the paper's update, then edges (B + 1,) f64 (splat units), table (C B, C) f64; the
    labelled pixels without any contribution (they add nothing) are added to counts[NO_DEPTH].

    Per tile, two walks over its list: the first sums kappa z and kappa per pixel (float32; z is the staged camera
    depth), which gives each pixel's row r = y B + b, the measured-depth gate its rendered depth and, with the
    surprise, sum kappa E^y; the tile's distinct rows get slots (at most min(tile^2, C B)); the second walk is the
    paper's voting walk with the slot in place of the label (warp shuffles, then float32 shared sums per (staged
    Gaussian, slot)). The flush applies the table: per (Gaussian, class) one float64 sum over the tile's slots of
    sum x table[r, c], added with one atomic.
    """
    nt = tile * tile
    if nt % WARP:
        raise ValueError(f"tile {tile}: the update kernel needs tile * tile to be a multiple of {WARP}")
    if num_bins < 1:
        raise ValueError(f"num_bins must be >= 1, got {num_bins}")
    C = num_classes
    B = num_bins
    batch, S = model_update_layout(C, tile, B, with_surprise)
    e_rows = batch if with_surprise else 1
    gated = with_depth or with_transient

    @_update_jit(tile, gated or with_surprise)
    def update_model_kernel(offsets, order, packed, ids, labels, confidence, has_confidence, ignore_label, tiles_x,
                            target, counts, sizes, transient, depth, tol_abs, tol_rel, depth_scale, pair_row, mom,
                            surprise, edges, table):  # pragma: no cover
        if overflowed(sizes, packed, order):
            return
        t = cuda.blockIdx.x
        tid = cuda.threadIdx.x
        lane = tid % WARP
        ty = t // tiles_x
        tx = t - ty * tiles_x
        u = tx * tile + tid % tile
        v = ty * tile + tid // tile
        s_g = cuda.shared.array((batch, STAGE_COLS), float32)   # (before the first barrier: see update_kernel)
        s_z = cuda.shared.array(batch, float32)
        s_acc = cuda.shared.array((batch, S), float32)
        s_id = cuda.shared.array(batch, int32)
        s_key = cuda.shared.array(nt, int32)     # per pixel: its row, then whether it leads its row's slot
        s_slot = cuda.shared.array(nt, int32)    # per leading pixel: its slot
        s_row = cuda.shared.array(S, int32)      # per slot: its (label, depth bin) row of the table
        s_mrow = cuda.shared.array(e_rows, int32)  # per staged Gaussian: its row of the moments (surprise)
        lab, w, status = pixel_input(labels, confidence, has_confidence, C, ignore_label, u, v)
        asked = status == USED
        if with_transient:
            status = _transient_status(lab, status, transient)
        fu = float32(u)
        fv = float32(v)
        start = offsets[t]
        end = offsets[t + 1]
        # walk 1: the expected depth of every labelled pixel (and the surprise's sum)
        walking = asked if with_surprise else status == USED
        zsum, ksum, esum, trans = first_walk(s_g, s_z, s_mrow, order, packed, pair_row, mom, start, end, batch, tid,
                                             fu, fv, walking, lab, with_surprise)
        front = float32(-math.inf)
        if with_depth:
            status, front = gate_pixel(status, measured_depth(depth, u, v), zsum, ksum, tol_abs, tol_rel,
                                       depth_scale)
        if with_surprise:
            if not asked:
                esum = float32(math.nan)
            write_surprise(surprise, u, v, esum, trans, C)
        count_pixels(status, counts)  # (barriers: also, walk 1 is over)
        if gated:
            count_changes(status, counts)
        labelled = status == USED
        row = -1
        if labelled and ksum > float32(0.0):
            row = lab * B + _depth_bin(float64(zsum) / float64(ksum), edges)
        missing = cuda.syncthreads_count(1 if labelled and row < 0 else 0)
        if tid == 0 and missing > 0:
            cuda.atomic.add(counts, NO_DEPTH, missing)
        slot, nr = assign_slots(s_key, s_slot, s_row, row, tid)
        # walk 2: the paper's voting walk, summed per (staged Gaussian, slot)
        done = row < 0
        trans = float32(1.0)
        for b0 in range(start, end, batch):
            if cuda.syncthreads_count(0 if done else 1) == 0:
                break
            n = min(batch, end - b0)
            if tid < n:
                j = order[b0 + tid]
                stage_geometry(s_g, tid, packed, j)
                s_id[tid] = ids[j]
                if with_depth:
                    s_z[tid] = float32(packed[j, 7])
            for idx in range(tid, n * nr, nt):
                s_acc[idx // nr, idx % nr] = float32(0.0)
            cuda.syncthreads()
            for k in range(n):
                contrib = float32(0.0)
                if not done:
                    kappa, trans, done = walk_step(s_g, k, fu, fv, trans)
                    contrib = kappa * w
                    if with_depth and s_z[k] < front:
                        contrib = float32(0.0)  # in front of the measured surface: no evidence
                vote(s_acc, k, contrib, slot, lane)
            cuda.syncthreads()
            flush_table(s_acc, s_id, s_row, n, nr, C, tid, nt, table, target)
    return update_model_kernel




def render_layout(num_classes: int, tile: int, chunk: int = RENDER_CLASS_CHUNK,
                  score: bool = False) -> tuple[int, int, int]:
    """(staged Gaussians per batch, classes per pass, static shared bytes per block) of the render
    kernel: per-pixel E and Var sums of one pass's classes (2 x classes x tile^2 float32) plus the
    staged rows (geometry, colour, S, camera depth (not for ``score``), row); the class moments are read
    from global memory (every lane of a warp reads the same row: one broadcast transaction, L1-resident
    for the block's batch)."""
    nt = tile * tile
    per_pass = min(num_classes, chunk)
    acc = 2 * per_pass * nt * 4
    row = 4 * STAGE_COLS + 4 * (4 if score else RENDER_ATTR_COLS) + 4
    return nt, per_pass, acc + nt * row


# The render's scalar parameters (one float64 array): background moments, background colour, the unknown threshold,
# metres per splat unit, the ignore label and the confidence map's logistic coefficients.
P_EBG, P_VBG, P_SBG, P_RGB, P_THRESHOLD, P_DEPTH_SCALE, P_IGNORE, P_COEF = 0, 1, 2, 3, 6, 7, 8, 9
RENDER_PARAMS = 12


@cuda.jit(device=True, inline=True)
def _write_final(out_i32, out_f32, out_u8, planes, params, knots, pix, best, e_hat, v_hat, tr, ev, cr, cg, cb, dz,
                 ks):  # pragma: no cover
    """Write one pixel's requested outputs in final form at their planes' offsets (see make_render_kernel)."""
    ignore = int32(params[P_IGNORE])
    label = best
    if tr > params[P_THRESHOLD]:
        label = ignore
    evidence = float64(ev) + tr * params[P_SBG]
    if planes[PL_LABELS] >= 0:
        out_i32[planes[PL_LABELS] + pix] = label
    if planes[PL_E] >= 0:
        out_f32[planes[PL_E] + pix] = float32(e_hat)
    if planes[PL_VAR] >= 0:
        out_f32[planes[PL_VAR] + pix] = float32(v_hat)
    if planes[PL_BG] >= 0:
        out_f32[planes[PL_BG] + pix] = float32(tr)
    if planes[PL_EVIDENCE] >= 0:
        out_f32[planes[PL_EVIDENCE] + pix] = float32(evidence)
    if planes[PL_DEPTH] >= 0:
        depth = math.nan
        if ks > float32(0.0):
            depth = float64(dz) / float64(ks) * params[P_DEPTH_SCALE]
        out_f32[planes[PL_DEPTH] + pix] = float32(depth)
    if planes[PL_CONFIDENCE] >= 0:
        conf = 0.0
        if label != ignore:
            conf = _interp(_confidence_score(e_hat, evidence, params[P_COEF], params[P_COEF + 1], params[P_COEF + 2]),
                           knots[0], knots[1])
        out_f32[planes[PL_CONFIDENCE] + pix] = float32(conf)
    if planes[PL_RGB] >= 0:
        base = planes[PL_RGB] + 3 * pix
        out_u8[base] = _to_byte(float64(cr) + tr * params[P_RGB])
        out_u8[base + 1] = _to_byte(float64(cg) + tr * params[P_RGB + 1])
        out_u8[base + 2] = _to_byte(float64(cb) + tr * params[P_RGB + 2])


@cuda.jit(device=True, inline=True)
def _mass_walk(s_g, s_row, order, packed, start, end, batch, tid, fu, fv, w, mass):  # pragma: no cover
    """The info gain's second walk of a tile's list: mass[j] += kappa_ij * w over the block's pixels (w: each
    pixel's net vote weight, 0 for pixels that add nothing), summed per warp, one float64 atomic per warp and pair.
    Every thread of the block must call it (barriers and warp shuffles)."""
    done = not (w != float32(0.0))
    trans = float32(1.0)
    lane = tid % WARP
    for b0 in range(start, end, batch):
        if cuda.syncthreads_count(0 if done else 1) == 0:
            break
        n = min(batch, end - b0)
        if tid < n:
            j = order[b0 + tid]
            stage_geometry(s_g, tid, packed, j)
            s_row[tid] = j
        cuda.syncthreads()
        for k in range(n):  # every lane walks every Gaussian: the warp sums need all 32
            contrib = float32(0.0)
            if not done:
                kappa, trans, done = walk_step(s_g, k, fu, fv, trans)
                contrib = kappa * w
            total = warp_sum(contrib)
            if lane == 0 and total != float32(0.0):
                cuda.atomic.add(mass, s_row[k], float64(total))


# The render kernel's modes (make_render_kernel):
# - score False (one view): the view's outputs in final form, each requested plane written at its offset (labels
#   int32 with the ignore label where kappa_b > threshold; E, Var, kappa_b, evidence float32; depth sum kappa z /
#   sum kappa times the depth scale (NaN without any contribution); the calibrated confidence (0 on unknown pixels);
#   colour uint8; with probs the (H, W, C) float32 E_i^c) and out_f64[0:2] += (sum_i log max(Var_i, VAR_FLOOR),
#   sum_i E_i), reduced per warp, one float64 atomic per warp.
# - score True: scores (V, 2) f64 += the same two sums per view. With with_mass also mass[j] += sum_i kappa_ij
#   mass_w[label_i B + b_i] per pair j (label_i the pixel's argmax class, b_i the bin of its expected depth in
#   mass_edges, splat units): a second walk of the pixel's list (_mass_walk).
# The pixel walk is float32; each pixel's E and Var sums of the classes of one pass live in shared memory (column
# tid of a (2 chunk, tile^2) array: no runtime-indexed local arrays, no bank conflicts). Up to chunk classes take
# one pass; more classes walk the tile's list again per pass, carrying the running argmax (first maximum, as the
# CPU) and its Var in registers, so shared memory and occupancy do not depend on C beyond chunk.
@lru_cache(maxsize=None)
def make_render_kernel(num_classes: int, tile: int, score: bool, probs: bool,
                       chunk: int = RENDER_CLASS_CHUNK, with_mass: bool = False) -> Any:
    """Render kernel for C = ``num_classes`` (compile-time constants: C, tile, mode, classes per pass; the modes
    in the comment above).

    Launch: grid = views * tiles, block = tile * tile threads (a multiple of 32). Kernel arguments:
    offsets (V T + 1,) i64; order (P,) i32 pair of each sorted key; packed (M, 8) f64; colors (M, 3) f32;
    pair_row (M,) i32 row of each pair in ``mom``; mom (R, 2C + 1) f32 moments; params (RENDER_PARAMS,) f64
    (``P_*``); knots (2, K) f64 the confidence map's isotonic knots; planes (NUM_PLANES,) i64 (``PL_*``);
    width, height [px]; tiles_x, tiles_per_view; out_i32, out_f32, out_u8, out_f64: views of one output buffer;
    scores (V, 2) f64; mass_w (C B,) f64, mass_edges (B + 1,) f64, mass (M,) f64.
    """
    nt = tile * tile
    if nt % WARP:
        raise ValueError(f"tile {tile}: the render kernel needs tile * tile to be a multiple of {WARP}")
    if with_mass and not score:
        raise ValueError("the evidence mass is a scoring output (score=True)")
    C = num_classes
    batch, per_pass, _ = render_layout(C, tile, chunk, score and not with_mass)
    n_acc = 2 * per_pass  # shared array shapes must be compile-time constants
    n_pass = -(-C // per_pass)
    with_depth = with_mass or not score
    attr_cols = RENDER_ATTR_COLS if with_depth else 4  # the views' plain scores need no depth

    @cuda.jit
    def render_kernel(offsets, order, packed, colors, pair_row, mom, params, knots, planes, width, height,
                      tiles_x, tiles_per_view, out_i32, out_f32, out_u8, out_f64, scores, mass_w, mass_edges,
                      mass):  # pragma: no cover
        b = cuda.blockIdx.x
        tid = cuda.threadIdx.x
        view = b // tiles_per_view
        t = b - view * tiles_per_view
        ty = t // tiles_x
        tx = t - ty * tiles_x
        u = tx * tile + tid % tile
        v = ty * tile + tid // tile
        inside = u < width and v < height
        pix = v * width + u
        e_bg = params[P_EBG]
        s_g = cuda.shared.array((batch, STAGE_COLS), float32)
        s_a = cuda.shared.array((batch, attr_cols), float32)  # r, g, b, S (, z)
        s_row = cuda.shared.array(batch, int32)
        acc = cuda.shared.array((n_acc, nt), float32)
        cr = float32(0.0)
        cg = float32(0.0)
        cb = float32(0.0)
        ev = float32(0.0)
        dz = float32(0.0)   # sum kappa z
        ks = float32(0.0)   # sum kappa (= 1 - T, summed: no cancellation where T is near 1)
        fu = float32(u)
        fv = float32(v)
        trans = float32(1.0)
        best = 0
        best_e = float32(0.0)
        best_v = float32(0.0)
        start = offsets[b]
        end = offsets[b + 1]
        for p in range(n_pass):
            c0 = p * per_pass
            nc = min(per_pass, C - c0)
            for c in range(n_acc):
                acc[c, tid] = float32(0.0)
            first = p == 0
            done = not inside
            trans = float32(1.0)
            for b0 in range(start, end, batch):
                if cuda.syncthreads_count(0 if done else 1) == 0:
                    break
                n = min(batch, end - b0)
                if tid < n:
                    j = order[b0 + tid]
                    stage_geometry(s_g, tid, packed, j)
                    row = pair_row[j]
                    s_row[tid] = row
                    s_a[tid, 0] = colors[j, 0]
                    s_a[tid, 1] = colors[j, 1]
                    s_a[tid, 2] = colors[j, 2]
                    s_a[tid, 3] = mom[row, 2 * C]
                    if with_depth:
                        s_a[tid, 4] = float32(packed[j, 7])
                cuda.syncthreads()
                if not done:
                    for k in range(n):
                        w1, trans, done = walk_step(s_g, k, fu, fv, trans)
                        if done:
                            break
                        if w1 == float32(0.0):
                            continue
                        w2 = w1 * w1
                        row = s_row[k]
                        for c in range(nc):
                            acc[c, tid] += w1 * mom[row, c0 + c]
                            acc[per_pass + c, tid] += w2 * mom[row, C + c0 + c]
                        if first:
                            cr += w1 * s_a[k, 0]
                            cg += w1 * s_a[k, 1]
                            cb += w1 * s_a[k, 2]
                            ev += w1 * s_a[k, 3]
                            if with_depth:  # (a compile-time constant)
                                dz += w1 * s_a[k, 4]
                                ks += w1
            for c in range(nc):
                e = acc[c, tid]
                if (first and c == 0) or e > best_e:
                    best = c0 + c
                    best_e = e
                    best_v = acc[per_pass + c, tid]
            if probs and not score and inside and planes[PL_PROBS] >= 0:
                tr_p = float64(trans)
                base = planes[PL_PROBS] + pix * C
                for c in range(nc):
                    out_f32[base + c0 + c] = float32(float64(acc[c, tid]) + tr_p * e_bg)
            if n_pass > 1:
                # Not needed for correctness (the next pass stages its rows only after its syncthreads_count);
                # it bounds live ranges: without it ptxas gives the C = 150 kernels 64-80 registers, not 37-72.
                cuda.syncthreads()
        tr = float64(trans)
        e_hat = float64(best_e) + tr * e_bg
        v_hat = float64(best_v) + tr * tr * params[P_VBG]
        lv = 0.0
        le = 0.0
        if inside:
            lv = math.log(max(v_hat, VAR_FLOOR))
            le = e_hat
        lv = warp_sum(lv)
        le = warp_sum(le)
        if score:
            if tid % WARP == 0:
                cuda.atomic.add(scores, (view, 0), lv)
                cuda.atomic.add(scores, (view, 1), le)
        else:
            if tid % WARP == 0:
                cuda.atomic.add(out_f64, 0, lv)
                cuda.atomic.add(out_f64, 1, le)
            if inside:
                _write_final(out_i32, out_f32, out_u8, planes, params, knots, pix, best, e_hat, v_hat, tr, ev, cr, cg,
                             cb, dz, ks)
        if with_mass:
            # second walk: each contribution's kappa times the pixel's net vote weight, summed per warp and pair
            w = float32(0.0)
            if inside and ks > float32(0.0):
                w = float32(mass_w[best * (mass_edges.shape[0] - 1) + _depth_bin(float64(dz) / float64(ks),
                                                                                 mass_edges)])
            _mass_walk(s_g, s_row, order, packed, start, end, batch, tid, fu, fv, w, mass)
    return render_kernel


@cuda.jit
def view_gain_kernel(mass, views, ids, sq, importance, scale, gains):  # pragma: no cover
    """gains[views[j]] += importance[ids[j]] * (V(S, Q) - E[V after m]) over the pairs j with mass m = scale *
    mass[j] > 0 (the closed form of :mod:`css_ros.engine.info_gain`; sq (N, 2) f64 the (S, Q) of each Gaussian
    with the scoring prior; importance (N,) f64, or empty for 1)."""
    start = cuda.grid(1)
    stride = cuda.gridsize(1)
    use_imp = importance.shape[0] > 0
    for j in range(start, mass.shape[0], stride):
        m = scale * mass[j]
        if not (m > 0.0):
            continue
        n = ids[j]
        s = sq[n, 0]
        q = sq[n, 1]
        before = (1.0 - q / (s * s)) / (s + 1.0)
        t = s + m
        q2 = q + 2.0 * m * q / s + m * m
        drop = max(before - (1.0 - q2 / (t * t)) / (t + 1.0), 0.0)
        if use_imp:
            drop *= importance[n]
        cuda.atomic.add(gains, views[j], drop)


@cuda.jit
def moment_sums_kernel(concentrations, prior_total, sq):  # pragma: no cover
    """sq[n] = (S, Q) of alpha_n + prior_total / C per class (info_gain.MomentSums.of), float64."""
    num_classes = concentrations.shape[1]
    extra = prior_total / num_classes
    start = cuda.grid(1)
    stride = cuda.gridsize(1)
    for n in range(start, concentrations.shape[0], stride):
        total = 0.0
        squares = 0.0
        for c in range(num_classes):
            a = concentrations[n, c]
            total += a
            squares += a * a
        sq[n, 0] = total + prior_total
        sq[n, 1] = squares + 2.0 * extra * total + num_classes * extra * extra


@cuda.jit
def observe_expected_kernel(mass, views, ids, chosen, scale, sq):  # pragma: no cover
    """alpha_n += m_n E[theta_n] for the pairs of view ``chosen`` (info_gain.MomentSums.observe_expected): S += m,
    Q += 2 m Q / S + m^2 Q / S^2 (a Gaussian has one pair per view: no two threads write one row)."""
    start = cuda.grid(1)
    stride = cuda.gridsize(1)
    for j in range(start, mass.shape[0], stride):
        if views[j] != chosen:
            continue
        m = scale * mass[j]
        if not (m > 0.0):
            continue
        n = ids[j]
        s = sq[n, 0]
        q = sq[n, 1]
        sq[n, 1] = q + 2.0 * m * q / s + m * m * q / (s * s)
        sq[n, 0] = s + m


def launch_1d(total: int, simulated: bool) -> tuple[int, int]:
    """(blocks, threads) of a grid-stride launch over ``total`` items (few threads in the simulator,
    where each GPU thread is a Python thread)."""
    if simulated:
        return 1, max(1, min(32, total))
    threads = 256
    return max(1, min((total + threads - 1) // threads, 16 * 1024)), threads
