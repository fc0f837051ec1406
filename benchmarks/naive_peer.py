"""The observe cycle against a straightforward numba implementation of the same maths, timed in one process.

The peer (written for this comparison only, not used by the package) is what a first numba port of the paper looks
like: EWA projection of every Gaussian, a depth sort, then per image row the Gaussians whose alpha box covers the
row, and per pixel one walk of the Gaussians whose box covers it (alpha, transmittance, early termination), once for
the update (kappa-weighted votes into per-thread (M, C) accumulators) and once for the render (E, Var of the argmax
class, colour, evidence, depth); U_var and U_exp with numpy. No tiles, no stored contributions, no SIMD-minded
layout; colour from the degree-0 SH term. Its concentrations agree with the package's to 1e-9 (checked on every run;
Gaussians at exactly equal depth may be composited in the other order).

    python benchmarks/naive_peer.py                       # biker-close and the 500k room, 10 frames each
    python benchmarks/naive_peer.py --scene biker --frames 20

Frames alternate (package, peer, peer, package, ...) so that a noisy machine affects both alike; the ratio is the
median of the per-frame ratios. Scenes and cameras are bench_frame.py's.
"""
from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from numba import njit, prange

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

NEAR, DILATION, A_MIN, A_MAX, T_MIN, FOV = 0.01, 0.3, 1.0 / 255.0, 0.99, 1e-4, 0.3


@njit(parallel=True, cache=True)
def peer_project(means, cov, opac, rot, trans, fx, fy, cx, cy, width, height, out):  # pragma: no cover
    """out[i] = (u, v, conic a, b, c, opacity, depth, u_min, u_max, v_min, v_max, kept) per Gaussian."""
    tan_x, tan_y = width / (2 * fx), height / (2 * fy)
    lo_x, hi_x = -(cx + 0.5) / fx - FOV * tan_x, (width - 0.5 - cx) / fx + FOV * tan_x
    lo_y, hi_y = -(cy + 0.5) / fy - FOV * tan_y, (height - 0.5 - cy) / fy + FOV * tan_y
    for i in prange(means.shape[0]):
        out[i, 11] = 0.0
        o = opac[i]
        if o < A_MIN:
            continue
        x = rot[0, 0] * means[i, 0] + rot[0, 1] * means[i, 1] + rot[0, 2] * means[i, 2] + trans[0]
        y = rot[1, 0] * means[i, 0] + rot[1, 1] * means[i, 1] + rot[1, 2] * means[i, 2] + trans[1]
        z = rot[2, 0] * means[i, 0] + rot[2, 1] * means[i, 1] + rot[2, 2] * means[i, 2] + trans[2]
        if z <= NEAR:
            continue
        u, v = fx * x / z + cx, fy * y / z + cy
        tx, ty = min(max(x / z, lo_x), hi_x), min(max(y / z, lo_y), hi_y)
        m0 = (fx / z * rot[0, 0] - fx * tx / z * rot[2, 0], fx / z * rot[0, 1] - fx * tx / z * rot[2, 1],
              fx / z * rot[0, 2] - fx * tx / z * rot[2, 2])
        m1 = (fy / z * rot[1, 0] - fy * ty / z * rot[2, 0], fy / z * rot[1, 1] - fy * ty / z * rot[2, 1],
              fy / z * rot[1, 2] - fy * ty / z * rot[2, 2])
        ca, cb, cc = DILATION, 0.0, DILATION
        for p in range(3):
            for q in range(3):
                ca += m0[p] * cov[i, p, q] * m0[q]
                cb += m0[p] * cov[i, p, q] * m1[q]
                cc += m1[p] * cov[i, p, q] * m1[q]
        det = ca * cc - cb * cb
        if det <= 0:
            continue
        mid = 0.5 * (ca + cc)
        r = math.ceil(3 * math.sqrt(mid + math.sqrt(max(0.0, mid * mid - det))))  # SPEC: 3-sigma square cull
        if u + r < -0.5 or u - r > width - 0.5 or v + r < -0.5 or v - r > height - 0.5:
            continue
        qmax = 2 * math.log(255 * o)
        hx, hy = math.sqrt(qmax * ca), math.sqrt(qmax * cc)
        umin, umax = max(0.0, math.ceil(u - hx)), min(width - 1.0, math.floor(u + hx))
        vmin, vmax = max(0.0, math.ceil(v - hy)), min(height - 1.0, math.floor(v + hy))
        if umin > umax or vmin > vmax:
            continue
        out[i, 0], out[i, 1], out[i, 2], out[i, 3], out[i, 4] = u, v, cc / det, -cb / det, ca / det
        out[i, 5], out[i, 6] = o, z
        out[i, 7], out[i, 8], out[i, 9], out[i, 10], out[i, 11] = umin, umax, vmin, vmax, 1.0


@njit(cache=True)
def peer_rows(g, order, height):  # pragma: no cover
    """Per image row, the Gaussians whose box covers it, front to back (CSR: rows[off[v]:off[v + 1]])."""
    off = np.zeros(height + 1, np.int64)
    for j in order:
        for v in range(int(g[j, 9]), int(g[j, 10]) + 1):
            off[v + 1] += 1
    for v in range(height):
        off[v + 1] += off[v]
    fill = off[:-1].copy()
    rows = np.empty(off[-1], np.int64)
    for j in order:
        for v in range(int(g[j, 9]), int(g[j, 10]) + 1):
            rows[fill[v]] = j
            fill[v] += 1
    return off, rows


@njit(cache=True)
def _row_lists(g, row, width, cnt, off, lst):  # pragma: no cover
    """Per pixel of a row (``row``: the Gaussians covering it, front to back), the Gaussians whose box covers the
    pixel: lst[off[u]:off[u] + cnt[u]]."""
    cnt[:] = 0
    for j in row:
        for u in range(int(g[j, 7]), int(g[j, 8]) + 1):
            cnt[u] += 1
    total = 0
    for u in range(width):
        off[u] = total
        total += cnt[u]
    if total > lst.shape[0]:
        lst = np.empty(2 * total, np.int64)
    cnt[:] = 0
    for j in row:
        for u in range(int(g[j, 7]), int(g[j, 8]) + 1):
            lst[off[u] + cnt[u]] = j
            cnt[u] += 1
    return lst


@njit(parallel=True, cache=True)
def peer_update(g, row_off, rows, labels, num_classes, ignore, nthreads, acc):  # pragma: no cover
    """acc[thread, j, c] += kappa_j over the pixels labelled c (rows dealt round-robin to the threads)."""
    height, width = labels.shape
    for t in prange(nthreads):
        cnt = np.zeros(width, np.int64)
        off = np.zeros(width, np.int64)
        lst = np.empty(1024, np.int64)
        for v in range(t, height, nthreads):
            lst = _row_lists(g, rows[row_off[v]:row_off[v + 1]], width, cnt, off, lst)
            for u in range(width):
                lab = labels[v, u]
                if lab == ignore or lab < 0 or lab >= num_classes:
                    continue
                T = 1.0
                for k in range(off[u], off[u] + cnt[u]):
                    j = lst[k]
                    dx, dy = u - g[j, 0], v - g[j, 1]
                    alpha = min(A_MAX, g[j, 5] * math.exp(-0.5 * (g[j, 2] * dx * dx + 2 * g[j, 3] * dx * dy
                                                                   + g[j, 4] * dy * dy)))
                    if alpha < A_MIN:
                        continue
                    if T * (1 - alpha) < T_MIN:
                        break
                    acc[t, j, lab] += alpha * T
                    T *= 1 - alpha


@njit(parallel=True, cache=True)
def peer_render(g, row_off, rows, attrs, colors, e_bg, v_bg, s_bg, height, width, nthreads,
                out_e, out_var, out_rgb, out_ev, out_depth, out_bg):  # pragma: no cover
    """Per pixel: E and Var of the argmax class, colour, evidence, depth, kappa_b (attrs: E per class, Var per
    class, S of each Gaussian)."""
    num_classes = (attrs.shape[1] - 1) // 2
    for t in prange(nthreads):
        cnt = np.zeros(width, np.int64)
        off = np.zeros(width, np.int64)
        lst = np.empty(1024, np.int64)
        e = np.empty(num_classes)
        for v in range(t, height, nthreads):
            lst = _row_lists(g, rows[row_off[v]:row_off[v + 1]], width, cnt, off, lst)
            for u in range(width):
                e[:] = 0.0
                T = 1.0
                rgb0 = rgb1 = rgb2 = ev = dep = 0.0
                for k in range(off[u], off[u] + cnt[u]):
                    j = lst[k]
                    dx, dy = u - g[j, 0], v - g[j, 1]
                    alpha = min(A_MAX, g[j, 5] * math.exp(-0.5 * (g[j, 2] * dx * dx + 2 * g[j, 3] * dx * dy
                                                                   + g[j, 4] * dy * dy)))
                    if alpha < A_MIN:
                        continue
                    if T * (1 - alpha) < T_MIN:
                        break
                    kap = alpha * T
                    for c in range(num_classes):
                        e[c] += kap * attrs[j, c]
                    rgb0 += kap * colors[j, 0]
                    rgb1 += kap * colors[j, 1]
                    rgb2 += kap * colors[j, 2]
                    ev += kap * attrs[j, 2 * num_classes]
                    dep += kap * g[j, 6]
                    T *= 1 - alpha
                best = np.argmax(e)
                var = T * T * v_bg
                T2 = 1.0
                for k in range(off[u], off[u] + cnt[u]):  # the argmax class's variance: a second walk
                    j = lst[k]
                    dx, dy = u - g[j, 0], v - g[j, 1]
                    alpha = min(A_MAX, g[j, 5] * math.exp(-0.5 * (g[j, 2] * dx * dx + 2 * g[j, 3] * dx * dy
                                                                   + g[j, 4] * dy * dy)))
                    if alpha < A_MIN:
                        continue
                    if T2 * (1 - alpha) < T_MIN:
                        break
                    kap = alpha * T2
                    var += kap * kap * attrs[j, num_classes + best]
                    T2 *= 1 - alpha
                out_e[v, u] = e[best] + T * e_bg
                out_var[v, u] = var
                out_rgb[v, u, 0], out_rgb[v, u, 1], out_rgb[v, u, 2] = rgb0, rgb1, rgb2
                out_ev[v, u] = ev + T * s_bg
                out_depth[v, u] = dep / (1 - T) if T < 1 else np.nan
                out_bg[v, u] = T


class NaivePeer:
    """The peer's map: its own (N, C) float64 concentrations, updated and rendered like SemanticMap.observe."""

    def __init__(self, model, num_classes: int, prior: float = 1e-3, background: float = 1e-3) -> None:
        self.means = np.asarray(model.means, dtype=np.float64)
        self.cov = np.ascontiguousarray(model.covariances(), dtype=np.float64)
        self.opac = np.asarray(model.opacities, dtype=np.float64)
        self.colors = np.maximum(np.asarray(model.sh, dtype=np.float64)[:, 0, :] * 0.28209479177387814 + 0.5, 0.0)
        self.conc = np.full((model.num_gaussians, num_classes), prior)
        self.num_classes = num_classes
        self.background = background
        self.threads = 2

    def observe(self, cam, labels: np.ndarray, ignore: int = 255) -> tuple[float, float]:
        import numba

        self.threads = numba.get_num_threads()
        w2c = np.asarray(cam.world_to_cam, dtype=np.float64)
        K = np.asarray(cam.K, dtype=np.float64)
        out = np.empty((len(self.means), 12))
        peer_project(self.means, self.cov, self.opac, np.ascontiguousarray(w2c[:3, :3]), w2c[:3, 3].copy(),
                     K[0, 0], K[1, 1], K[0, 2], K[1, 2], float(cam.width), float(cam.height), out)
        ids = np.flatnonzero(out[:, 11] > 0)
        g = np.ascontiguousarray(out[ids])
        order = np.argsort(g[:, 6], kind="stable")
        row_off, rows = peer_rows(g, order, cam.height)
        acc = np.zeros((self.threads, len(ids), self.num_classes))
        peer_update(g, row_off, rows, np.asarray(labels, dtype=np.int64), self.num_classes, ignore, self.threads, acc)
        self.conc[ids] += acc.sum(axis=0)
        alpha = self.conc[ids]
        s = alpha.sum(axis=1, keepdims=True)
        e = alpha / s
        attrs = np.concatenate([e, e * (1 - e) / (1 + s), s], axis=1)
        c = self.num_classes
        s_bg = c * self.background
        e_bg = 1.0 / c
        v_bg = e_bg * (1 - e_bg) / (1 + s_bg)
        h, w = cam.height, cam.width
        out_e, out_var, out_ev, out_depth, out_bg = (np.empty((h, w)) for _ in range(5))
        out_rgb = np.empty((h, w, 3))
        peer_render(g, row_off, rows, attrs, self.colors[ids], e_bg, v_bg, s_bg, h, w, self.threads,
                    out_e, out_var, out_rgb, out_ev, out_depth, out_bg)
        u_var = float(np.exp(np.mean(np.log(np.maximum(out_var, 1e-30)))))
        return u_var, float(1.0 - out_e.mean())


def run(scene: str, frames: int) -> dict:
    import bench_frame as bf
    from css_ros import SemanticMap

    cfg = dict(bf.SCENES[scene])
    model, gt, cams = bf.build_scene(cfg, frames + 2)
    num_classes = cfg["classes"]
    labels = bf.truth_labels(model, gt, num_classes, cams)
    smap = SemanticMap(model, num_classes)
    peer = NaivePeer(model, num_classes)
    for i in range(2):  # compile / load the caches
        smap.observe(cams[i], labels[i])
        peer.observe(cams[i], labels[i])
    ours, theirs = [], []
    for i in range(2, frames + 2):
        for who in (("ours", "peer") if i % 2 else ("peer", "ours")):
            t0 = time.perf_counter()
            if who == "ours":
                view = smap.observe(cams[i], labels[i])
                ours.append(time.perf_counter() - t0)
            else:
                u_var, u_exp = peer.observe(cams[i], labels[i])
                theirs.append(time.perf_counter() - t0)
    # the same maths: equal concentrations but for Gaussians at exactly equal depth (duplicates in a trained file),
    # whose order the two sorts break differently
    off = ~np.isclose(peer.conc, smap.concentrations, rtol=1e-9, atol=1e-12).all(axis=1)
    assert off.mean() < 1e-3, f"{off.sum()} of {off.size} Gaussians differ"
    assert abs(view.u_exp - u_exp) < 1e-6, (view.u_exp, u_exp)
    ratios = [b / a for a, b in zip(ours, theirs)]
    return dict(scene=scene, ours_ms=1e3 * statistics.median(ours), peer_ms=1e3 * statistics.median(theirs),
                ratio=statistics.median(ratios), ratio_lo=min(ratios), ratio_hi=max(ratios))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", action="append", help="bench_frame.py scene(s) (default: biker-close, 500k)")
    p.add_argument("--frames", type=int, default=10)
    args = p.parse_args(argv)
    import numba

    for scene in args.scene or ["biker-close", "500k"]:
        r = run(scene, args.frames)
        print(f"{r['scene']:>12}: observe {r['ours_ms']:.1f} ms, naive peer {r['peer_ms']:.1f} ms, "
              f"peer / observe {r['ratio']:.2f} (per-frame {r['ratio_lo']:.2f}-{r['ratio_hi']:.2f}), "
              f"numba threads {numba.get_num_threads()}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
