"""The per-pixel compositing walk of the CPU kernels (SPEC §3), one definition for the update, the render and
:func:`~css_ros.engine.cpu.raster.kappa_lists`.

A tile first copies the rows of its depth-sorted list into columns (:func:`load_tile`, one cache line per Gaussian:
:attr:`~css_ros.engine.cpu.projection.ProjectedGaussians.walk`). For each pixel row of the
tile, :func:`row_candidates` keeps the entries whose alpha ellipse meets the row's segment of the tile (the minimum
of the Mahalanobis q over the segment, a clamped quadratic, is <= qmax: in trained splats about 2/3 of the entries
whose box spans the row) with their row terms (2 b dy, c dy^2), so a pixel's q is two FMAs. :func:`composite_row`
then walks the row's pixels front to back in chunks of 64 candidates: per pixel, q of the chunk (a vectorised loop)
and a bit mask of the hits (q <= qmax), the hits taken from the mask by count-trailing-zeros (their q computed
again: no per-candidate stores); the alphas of the whole row's hits in one vectorised loop (polynomial exp), then
each pixel's compositing in order. A pixel stops where its transmittance would drop below T_MIN, and the chunks
behind that point are never tested.

A pixel's result (its contributions' list positions and kappa, front to back, and its final transmittance) is
exactly the per-pixel brute force: the candidate tests are conservative and the hit test is q <= qmax as before.
"""
from __future__ import annotations

import numpy as np
from numba import njit
from numba.core import cgutils, types
from numba.extending import intrinsic

from ..spec import ALPHA_MAX, ALPHA_MIN, T_MIN

# Floating-point reassociation and contraction (FMA) for the hot loops; no-NaN/no-Inf assumptions are
# not made (inputs are sanitised, but comparisons against NaN must keep their meaning).
FAST = {"contract", "reassoc", "arcp"}
COLS = 8             # tile columns: u v a b c opacity qmax, the slope -b / a (ProjectedGaussians.walk)
CAND = 6             # row terms of a candidate: u, a, 2 b dy, c dy^2, opacity, qmax
CHUNK = 64           # candidates tested per step of a pixel's walk (one bit mask)


@intrinsic
def cttz(typingctx, x):  # pragma: no cover - compiled
    """Count of trailing zero bits of a non-zero uint64 (one instruction)."""
    sig = types.uint64(types.uint64)

    def codegen(context, builder, signature, args):
        return builder.cttz(args[0], cgutils.true_bit)
    return sig, codegen


@njit(inline="always", fastmath=FAST)
def exp_nonpositive(x):  # pragma: no cover
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


@njit(inline="always")
def longest_list(offsets):  # pragma: no cover
    """The longest tile list of a binning (``offsets`` (tiles + 1,)), at least 1: the capacity of the walk scratch."""
    longest = 1
    for t in range(offsets.shape[0] - 1):
        longest = max(longest, offsets[t + 1] - offsets[t])
    return longest


@njit(inline="always")
def new_scratch(tile, cap):  # pragma: no cover
    """Per-thread walk scratch for tile lists of up to ``cap`` entries (:func:`longest_list`): (tile columns
    (COLS, cap), candidate row terms (CAND, cap), candidate list positions (cap,) uint32, bit masks, per-pixel
    contribution positions (tile, cap) uint32 and kappas (tile, cap), counts (tile,), final transmittances (tile,),
    active pixels (tile,), the row's hits of one chunk step ((2, tile * CHUNK): q then alpha, and opacity), their
    list positions (tile * CHUNK,) uint32 and per-pixel (first hit, hit count, still walking) (3, tile). List
    positions are unsigned: numba then indexes with them without a negative-index test.

    Sized once for the whole frame, never grown: a kernel that reassigned its scratch inside the tile loop paid
    numba's reference counting of every array at each tile (atomic increments, 14 % of the update's samples)."""
    return (np.empty((COLS, cap)), np.empty((CAND, cap)), np.empty(cap, dtype=np.uint32),
            np.empty((cap + CHUNK - 1) // CHUNK, dtype=np.uint64), np.empty((tile, cap), dtype=np.uint32),
            np.empty((tile, cap)), np.empty(tile, dtype=np.int64), np.empty(tile), np.ones(tile, dtype=np.bool_),
            np.empty((2, tile * CHUNK)), np.empty(tile * CHUNK, dtype=np.uint32), np.empty((3, tile), dtype=np.int64))


@njit(inline="always")
def load_tile(walk, lists, start, end, cols):  # pragma: no cover
    """Copy the rows ``walk[lists[start:end]]`` (:attr:`ProjectedGaussians.walk`) into the tile columns ``cols``
    (COLS, >= end - start): one contiguous array per quantity, so the candidate tests vectorise."""
    for k in range(end - start):
        j = lists[start + k]
        for c in range(COLS):
            cols[c, k] = walk[j, c]


@njit(inline="always", fastmath=FAST)
def row_candidates(cols, n, v, u0, u1, cand, ridx, words):  # pragma: no cover
    """The tile entries whose alpha ellipse meets pixel row v between columns u0 and u1, front to back:
    their list positions in ``ridx[:r]`` and row terms in ``cand[:, :r]``. Returns r.

    The test is the minimum of q(u, v) over u in [u0, u1] (at the clamped vertex u* = u_c - b dy / a) against
    qmax, with a relative margin of 1e-9 so that rounding never drops a pixel the exact test keeps."""
    fv = float(v)
    fu0 = float(u0)
    fu1 = float(u1)
    gx, gy, ga, gb, gc, gq, gs = cols[0], cols[1], cols[2], cols[3], cols[4], cols[6], cols[7]
    nw = (n + CHUNK - 1) // CHUNK
    for w in range(nw):
        base = w * CHUNK
        top = min(base + CHUNK, n)
        # slices, so that the loop index is known to be >= 0 (no wraparound test: contiguous vector loads)
        x, y, a, b, c, qm, s = gx[base:top], gy[base:top], ga[base:top], gb[base:top], gc[base:top], \
            gq[base:top], gs[base:top]
        mask = np.uint64(0)
        for k in range(top - base):
            dy = fv - y[k]
            dx = min(max(x[k] + s[k] * dy, fu0), fu1) - x[k]
            qmin = (a[k] * dx + 2.0 * b[k] * dy) * dx + c[k] * dy * dy
            mask |= np.uint64(qmin <= qm[k] * (1.0 + 1e-9) + 1e-12) << np.uint64(k)
        words[w] = mask
    cx, ca, cby, ccy, co, cq = cand[0], cand[1], cand[2], cand[3], cand[4], cand[5]
    go = cols[5]
    r = 0
    for w in range(nw):
        mask = words[w]
        base = w * CHUNK
        top = min(base + CHUNK, n)
        x, y, a, b, c, o, qm = gx[base:top], gy[base:top], ga[base:top], gb[base:top], gc[base:top], \
            go[base:top], gq[base:top]
        while mask != 0:
            k = cttz(mask)  # unsigned: no negative-index test on the loads below
            mask &= mask - np.uint64(1)
            dy = fv - y[k]
            ridx[r] = np.uint32(base) + np.uint32(k)
            cx[r] = x[k]
            ca[r] = a[k]
            cby[r] = 2.0 * b[k] * dy
            ccy[r] = c[k] * dy * dy
            co[r] = o[k]
            cq[r] = qm[k]
            r += 1
    return r


@njit(inline="always", fastmath=FAST)
def composite_row(cand, ridx, r, u0, u1, active, cnt, kidx, kval, trans, chunk, hit, state):  # pragma: no cover
    """Front-to-back compositing of the pixels u0..u1 of one row over its r candidates (:func:`row_candidates`).

    The walk steps through the candidates in chunks of CHUNK. In each step every pixel still walking tests the
    chunk (q and a bit mask of the hits) and appends its hits to one buffer for the whole row; the alphas of all of
    them are computed in one loop (a loop of a few hits per pixel would wait on the exp polynomial's latency), then
    each pixel composites its hits in order and stops where its transmittance would drop below T_MIN.

    Outputs per pixel p = u - u0: cnt[p] contributions, their tile-list positions kidx[p, :cnt[p]] and kappas
    kval[p, :cnt[p]] = alpha T, front to back; trans[p] the final transmittance (kappa_b). Inactive pixels get
    cnt 0 and T 1."""
    cx, ca, cby, ccy, co, cq = cand[0], cand[1], cand[2], cand[3], cand[4], cand[5]
    hq, ho = chunk[0], chunk[1]
    first, count, walking = state[0], state[1], state[2]
    npx = u1 - u0 + 1
    for p in range(npx):
        cnt[p] = 0
        trans[p] = 1.0
        walking[p] = active[p]
    base = 0
    while base < r:
        top = min(base + CHUNK, r)
        x, a, by, cy, qm, o = cx[base:top], ca[base:top], cby[base:top], ccy[base:top], cq[base:top], co[base:top]
        rr = ridx[base:top]
        total = 0
        for p in range(npx):
            first[p] = total
            count[p] = 0
            if walking[p] == 0:
                continue
            fu = float(u0 + p)
            mask = np.uint64(0)
            for k in range(top - base):
                dx = fu - x[k]
                q = (a[k] * dx + by[k]) * dx + cy[k]
                mask |= np.uint64(q <= qm[k]) << np.uint64(k)
            while mask != 0:
                k = cttz(mask)
                mask &= mask - np.uint64(1)
                dx = fu - x[k]  # q again for the hits only: cheaper than storing the chunk's 64
                hit[total] = rr[k]
                hq[total] = (a[k] * dx + by[k]) * dx + cy[k]
                ho[total] = o[k]
                total += 1
            count[p] = total - first[p]
        for h in range(total):
            hq[h] = min(ALPHA_MAX, ho[h] * exp_nonpositive(-0.5 * hq[h]))
        alive = False
        for p in range(npx):
            if walking[p] == 0:
                continue
            t = trans[p]
            start = cnt[p]
            alphas = hq[first[p]:first[p] + count[p]]
            positions = hit[first[p]:first[p] + count[p]]
            out_k = kidx[p, start:]
            out_v = kval[p, start:]
            i = 0
            done = False
            for h in range(alphas.shape[0]):
                # branch-free skip of alpha < 1/255 (only possible by rounding at the ellipse's edge)
                alpha = alphas[h]
                ok = alpha >= ALPHA_MIN
                alpha = alpha if ok else 0.0
                test_t = t * (1.0 - alpha)
                if test_t < T_MIN:
                    done = True
                    break
                out_k[i] = positions[h]
                out_v[i] = alpha * t
                i += ok
                t = test_t
            cnt[p] = start + i
            trans[p] = t
            if done:
                walking[p] = 0
            else:
                alive = True
        if not alive:
            break
        base = top
