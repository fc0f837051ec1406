"""Brute-force float64 reference of SPEC §3-6, written independently of the engine's kernels.

No tiles, no bounding boxes, no early outs except the SPEC's own rules: every pixel is tested
against every Gaussian. Only usable on small scenes (it builds dense pixels x Gaussians arrays).
"""
from __future__ import annotations

import math

import numpy as np


def quat_to_rot(q):
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def project_reference(means, scales, quats_wxyz, opacities, K, T_map_cam, width, height):
    """Per Gaussian: (kept, depth, mean2d, inverse 2D covariance, opacity) following SPEC §3."""
    w2c = np.linalg.inv(np.asarray(T_map_cam, dtype=np.float64))
    Rw, tw = w2c[:3, :3], w2c[:3, 3]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    tan_x, tan_y = width / (2 * fx), height / (2 * fy)
    out = []
    for i in range(len(means)):
        p = Rw @ np.asarray(means[i], dtype=np.float64) + tw
        x, y, z = p
        if z <= 0.01:
            out.append(None)
            continue
        mean2d = np.array([fx * x / z + cx, fy * y / z + cy])
        xz = np.clip(x / z, -(cx + 0.5) / fx - 0.3 * tan_x, (width - 0.5 - cx) / fx + 0.3 * tan_x)
        yz = np.clip(y / z, -(cy + 0.5) / fy - 0.3 * tan_y, (height - 0.5 - cy) / fy + 0.3 * tan_y)
        J = np.array([[fx / z, 0.0, -fx * xz / z], [0.0, fy / z, -fy * yz / z]])
        R = quat_to_rot(quats_wxyz[i])
        S = np.diag(np.asarray(scales[i], dtype=np.float64))
        sigma = R @ S @ S.T @ R.T
        cov2d = J @ Rw @ sigma @ Rw.T @ J.T + 0.3 * np.eye(2)
        if np.linalg.det(cov2d) <= 0:
            out.append(None)
            continue
        r = math.ceil(3.0 * math.sqrt(np.linalg.eigvalsh(cov2d).max()))
        if (mean2d[0] + r < -0.5 or mean2d[0] - r > width - 0.5
                or mean2d[1] + r < -0.5 or mean2d[1] - r > height - 0.5):
            out.append(None)
            continue
        out.append((z, mean2d, np.linalg.inv(cov2d), float(opacities[i])))
    return out


def kappa_reference(means, scales, quats_wxyz, opacities, K, T_map_cam, width, height):
    """Dense kappa (H*W, N) and background weight (H*W,) by brute force over all pixels and Gaussians."""
    proj = project_reference(means, scales, quats_wxyz, opacities, K, T_map_cam, width, height)
    n = len(means)
    kept = [i for i in range(n) if proj[i] is not None]
    kept.sort(key=lambda i: proj[i][0])
    vs, us = np.mgrid[0:height, 0:width]
    pix = np.stack([us.ravel(), vs.ravel()], axis=1).astype(np.float64)
    kappa = np.zeros((width * height, n))
    trans = np.ones(width * height)
    done = np.zeros(width * height, dtype=bool)
    for i in kept:
        _, mean2d, conic, o = proj[i]
        d = pix - mean2d
        q = np.einsum("pi,ij,pj->p", d, conic, d)
        a = np.minimum(0.99, o * np.exp(-0.5 * q))
        active = (a >= 1.0 / 255.0) & ~done
        test = trans * (1.0 - a)
        stop = active & (test < 1e-4)
        done |= stop
        use = active & ~stop
        kappa[use, i] = a[use] * trans[use]
        trans = np.where(use, test, trans)
    return kappa, trans


def moments(alpha):
    s = alpha.sum(axis=1, keepdims=True)
    e = alpha / s
    return e, e * (1 - e) / (1 + s), s[:, 0]


def render_reference(kappa, background, alpha, alpha_b):
    """Per pixel E (P, C) and Var (P, C) of SPEC §5, plus argmax labels and image-level U (SPEC §6)."""
    c = alpha.shape[1]
    e_n, v_n, _ = moments(alpha)
    e_b = 1.0 / c
    v_b = e_b * (1 - e_b) / (1 + c * alpha_b)
    E = kappa @ e_n + background[:, None] * e_b
    V = (kappa ** 2) @ v_n + (background ** 2)[:, None] * v_b
    labels = E.argmax(axis=1)
    e_hat = E[np.arange(len(E)), labels]
    v_hat = V[np.arange(len(V)), labels]
    u_var = math.exp(np.mean(np.log(v_hat)))
    u_exp = 1.0 - e_hat.mean()
    return E, V, labels, e_hat, v_hat, u_var, u_exp


def update_reference(kappa, alpha, labels, num_classes, ignore_label=255, confidence=None):
    """alpha + kappa^T y with y the one-hot labels (times confidence), ignoring invalid ids."""
    lab = np.asarray(labels).ravel().astype(np.int64)
    y = np.zeros((lab.size, num_classes))
    valid = (lab != ignore_label) & (lab >= 0) & (lab < num_classes)
    y[np.flatnonzero(valid), lab[valid]] = 1.0
    if confidence is not None:
        y *= np.asarray(confidence, dtype=np.float64).ravel()[:, None]
    return alpha + kappa.T @ y


def camera_depths(means, T_map_cam):
    """(N,) camera-frame z of the Gaussians' means (optical frame: z forward), splat units."""
    T = np.asarray(T_map_cam, dtype=np.float64)
    return ((np.asarray(means, dtype=np.float64) - T[:3, 3]) @ T[:3, :3])[:, 2]


def change_update_reference(kappa, background, alpha, labels, num_classes, z_m, depth=None, transient=(),
                            tol_abs=0.05, tol_rel=0.03, decay=1.0, prior=1.0, ignore_label=255, confidence=None):
    """The changing-world update pixel by pixel (css_ros.engine.change_rules, written out independently):
    (new alpha, counts (used, ignored, out_of_range, transient, occluded), surprise (P,) float64 NaN without label).
    kappa (P, N) dense, background (P,) kappa_b, z_m (N,) camera depth of each Gaussian in metres, depth (P,) metres."""
    lab = np.asarray(labels).ravel().astype(np.int64)
    conf = None if confidence is None else np.asarray(confidence, dtype=np.float64).ravel()
    e_pre = alpha / alpha.sum(axis=1, keepdims=True)
    inc = np.zeros_like(alpha)
    counts = dict(used=0, ignored=0, out_of_range=0, transient=0, occluded=0)
    surprise = np.full(lab.size, np.nan)
    for i in range(lab.size):
        y = lab[i]
        if y == ignore_label:
            counts["ignored"] += 1
            continue
        if y < 0 or y >= num_classes:
            counts["out_of_range"] += 1
            continue
        w = 1.0 if conf is None else min(max(np.nan_to_num(conf[i], nan=0.0), 0.0), 1.0)
        if not w > 0:
            counts["ignored"] += 1
            continue
        k = kappa[i]
        surprise[i] = 1.0 - (k @ e_pre[:, y] + background[i] / num_classes)
        if y in transient:
            counts["transient"] += 1
            continue
        keep = k > 0
        d = np.nan if depth is None else float(depth[i])
        if np.isfinite(d) and d > 0 and k.sum() > 0:
            tol = max(tol_abs, tol_rel * d)
            rendered = (k @ z_m) / k.sum()
            if d < rendered - tol:
                counts["occluded"] += 1
                continue
            if rendered < d - tol:   # the splat's surface in front of the measured one: what is in front is gone
                keep &= z_m >= d - tol
        counts["used"] += 1
        inc[:, y] += np.where(keep, k, 0.0) * w
    out = alpha.copy()
    got = (inc != 0).any(axis=1)
    out[got] = prior + (out[got] - prior) * decay + inc[got]
    return out, counts, surprise
