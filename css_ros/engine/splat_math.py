"""The per-Gaussian projection maths (SPEC §3), written once for both compiled targets.

These are plain scalar Python functions: no numba decorator here. ``engine/cpu/projection.py`` compiles
them with ``numba.njit(inline="always")`` and ``engine/cuda/kernels.py`` with
``numba.cuda.jit(device=True, inline=True)``; both inline them into their kernels, so the shared
definition costs nothing. The rules that keep them compilable by both: ``math`` functions and arithmetic
only, arrays indexed (never allocated or sliced with steps), module-level scalars as constants, one
return type per function on every path.

The SH colour polynomial lives beside its constants in :func:`css_ros.engine.sh.sh_polynomial` (the same
rules, and numpy / torch arrays too).

What is deliberately *not* shared: the per-pixel compositing walk. The CPU walks a row of pixels in
float64 with branch-free compaction and a polynomial exp (vectorised by LLVM); the GPU walks one pixel
per lane in float32 with the hardware exp (``engine/cuda/kernels.py``: one ``walk_step`` used by the
update and render kernels). One scalar function would force one of them off its fast form; they share
the rule constants (``spec.ALPHA_MIN``, ``ALPHA_MAX``, ``T_MIN``) and the tests against the float64
reference instead.

Camera rows (``CAM_COLS`` float64 per view, map frame -> camera frame, OpenCV axes: x right, y down,
z forward): R_cam_map row-major (0-8), t_cam_map (9-11) [m], fx, fy, cx, cy (12-15) [px], camera
centre in the map frame (16-18) [m].
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from .spec import ALPHA_MIN, COV2D_DILATION, FOV_CLAMP, NEAR_PLANE

if TYPE_CHECKING:
    from .camera import Camera

CAM_COLS = 19
NO_SPLAT = (False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


def camera_row(camera: "Camera", out: np.ndarray | None = None) -> np.ndarray:
    """The (CAM_COLS,) float64 row of ``camera`` (layout in the module docstring); written into ``out``
    when given."""
    row = np.empty(CAM_COLS) if out is None else out
    w2c = np.asarray(camera.world_to_cam, dtype=np.float64)
    k = np.asarray(camera.K, dtype=np.float64)
    row[0:9] = w2c[:3, :3].ravel()
    row[9:12] = w2c[:3, 3]
    row[12:16] = (k[0, 0], k[1, 1], k[0, 2], k[1, 2])
    row[16:19] = np.asarray(camera.position, dtype=np.float64)
    return row


def fov_limits(cam, width, height):  # type: ignore[no-untyped-def]
    """Per-view constants of the EWA Jacobian clamp (SPEC §3).

    Args:
        cam: (CAM_COLS,) camera row; width, height: image size [px] (floats).
    Returns:
        (lo_x, hi_x, lo_y, hi_y, jac_sq): the range of x/z and y/z the Jacobian is evaluated in (the
        image's FoV widened by FOV_CLAMP on each side), and the largest ||J||_F^2 z^2 over that range
        [px^2] (bounds lambda_max of the screen covariance for the early cull).
    """
    fx, fy, cx, cy = cam[12], cam[13], cam[14], cam[15]
    tan_x = width / (2.0 * fx)
    tan_y = height / (2.0 * fy)
    lo_x = -(cx + 0.5) / fx - FOV_CLAMP * tan_x
    hi_x = (width - 0.5 - cx) / fx + FOV_CLAMP * tan_x
    lo_y = -(cy + 0.5) / fy - FOV_CLAMP * tan_y
    hi_y = (height - 0.5 - cy) / fy + FOV_CLAMP * tan_y
    jac_sq = fx * fx * (1.0 + max(lo_x * lo_x, hi_x * hi_x)) + fy * fy * (1.0 + max(lo_y * lo_y, hi_y * hi_y))
    return lo_x, hi_x, lo_y, hi_y, jac_sq


def ewa_splat(cam, means, cov3d, i, opacity, max_std, width, height,  # type: ignore[no-untyped-def]
              lo_x, hi_x, lo_y, hi_y, jac_sq):
    """EWA projection of Gaussian ``i`` with the SPEC §3 culls.

    Args:
        cam: (CAM_COLS,) camera row; means (N, 3) [m, map frame]; cov3d (N, 6) upper triangle
        (xx, xy, xz, yy, yz, zz) [m^2]; i: row; opacity: its activated opacity; max_std: its largest
        axis std [m]; width, height [px] (floats); lo_x .. jac_sq: :func:`fov_limits` of the view.
    Returns:
        (keep, u, v, a, b, c, qmax, depth, u_min, u_max, v_min, v_max): keep is False when the
        Gaussian cannot reach alpha >= 1/255 inside the image (behind the near plane, opacity below
        1/255, its 3-sigma square or its alpha box outside the image, degenerate covariance), and the
        other fields are then 0. (u, v) projected centre [px] (pixel centres at integers); (a, b, c)
        the inverse screen covariance [1/px^2] (+0.3 px^2 dilation before inverting); qmax =
        2 ln(255 o), the largest Mahalanobis q with alpha >= 1/255; depth camera z [m]; the inclusive
        pixel box of that ellipse, clipped to the image (integral floats).
    """
    if not (opacity >= ALPHA_MIN):
        return NO_SPLAT  # alpha <= opacity can never reach the 1/255 threshold
    px, py, pz = means[i, 0], means[i, 1], means[i, 2]
    x = cam[0] * px + cam[1] * py + cam[2] * pz + cam[9]
    y = cam[3] * px + cam[4] * py + cam[5] * pz + cam[10]
    z = cam[6] * px + cam[7] * py + cam[8] * pz + cam[11]
    if not (z > NEAR_PLANE):
        return NO_SPLAT
    fx, fy, cx, cy = cam[12], cam[13], cam[14], cam[15]
    u = fx * x / z + cx
    v = fy * y / z + cy
    # Conservative early cull before the covariance maths: lambda_max(Sigma') <= ||J||_F^2 s_max^2 + 0.3
    # with |t| bounded by the clamp, so a centre farther outside the image than 3 sqrt(that) + 1 px cannot
    # have its 3-sigma square touch the image.
    bound = 3.0 * math.sqrt(jac_sq * max_std * max_std / (z * z) + COV2D_DILATION) + 1.0
    if u < -0.5 - bound or u > width - 0.5 + bound or v < -0.5 - bound or v > height - 0.5 + bound:
        return NO_SPLAT
    txz = min(max(x / z, lo_x), hi_x)
    tyz = min(max(y / z, lo_y), hi_y)
    # J = [[fx/z, 0, -fx*txz/z], [0, fy/z, -fy*tyz/z]];  M = J @ R_cam_map  (2 x 3)
    j00 = fx / z
    j02 = -fx * txz / z
    j11 = fy / z
    j12 = -fy * tyz / z
    m00 = j00 * cam[0] + j02 * cam[6]
    m01 = j00 * cam[1] + j02 * cam[7]
    m02 = j00 * cam[2] + j02 * cam[8]
    m10 = j11 * cam[3] + j12 * cam[6]
    m11 = j11 * cam[4] + j12 * cam[7]
    m12 = j11 * cam[5] + j12 * cam[8]
    sxx, sxy, sxz = cov3d[i, 0], cov3d[i, 1], cov3d[i, 2]
    syy, syz, szz = cov3d[i, 3], cov3d[i, 4], cov3d[i, 5]
    # rows of M @ Sigma, then M Sigma M^T + dilation
    a0 = m00 * sxx + m01 * sxy + m02 * sxz
    a1 = m00 * sxy + m01 * syy + m02 * syz
    a2 = m00 * sxz + m01 * syz + m02 * szz
    b0 = m10 * sxx + m11 * sxy + m12 * sxz
    b1 = m10 * sxy + m11 * syy + m12 * syz
    b2 = m10 * sxz + m11 * syz + m12 * szz
    ca = a0 * m00 + a1 * m01 + a2 * m02 + COV2D_DILATION
    cb = a0 * m10 + a1 * m11 + a2 * m12
    cc = b0 * m10 + b1 * m11 + b2 * m12 + COV2D_DILATION
    det = ca * cc - cb * cb
    if not (det > 0.0):
        return NO_SPLAT
    mid = 0.5 * (ca + cc)
    lam = mid + math.sqrt(max(0.0, mid * mid - det))
    r = math.ceil(3.0 * math.sqrt(lam))
    if u + r < -0.5 or u - r > width - 0.5 or v + r < -0.5 or v - r > height - 0.5:
        return NO_SPLAT
    qmax = 2.0 * math.log(255.0 * opacity)
    # Exact axis-aligned box of the ellipse d^T Sigma'^-1 d <= qmax (tiny margin for rounding).
    hx = math.sqrt(qmax * ca) * (1.0 + 1e-9) + 1e-9
    hy = math.sqrt(qmax * cc) * (1.0 + 1e-9) + 1e-9
    umin = max(0.0, math.ceil(u - hx))
    umax = min(width - 1.0, math.floor(u + hx))
    vmin = max(0.0, math.ceil(v - hy))
    vmax = min(height - 1.0, math.floor(v + hy))
    if umin > umax or vmin > vmax:
        return NO_SPLAT
    return (True, u, v, cc / det, -cb / det, ca / det, qmax, z, umin, umax, vmin, vmax)


def store_splat(packed, bbox, row, splat, opacity):  # type: ignore[no-untyped-def]
    """Write a kept :func:`ewa_splat` result into ``packed[row, 0:8]`` (u, v, a, b, c, opacity, qmax, depth)
    and ``bbox[row]`` (int32 u_min, u_max, v_min, v_max: the inclusive pixel box)."""
    packed[row, 0] = splat[1]
    packed[row, 1] = splat[2]
    packed[row, 2] = splat[3]
    packed[row, 3] = splat[4]
    packed[row, 4] = splat[5]
    packed[row, 5] = opacity
    packed[row, 6] = splat[6]
    packed[row, 7] = splat[7]
    bbox[row, 0] = int(splat[8])
    bbox[row, 1] = int(splat[9])
    bbox[row, 2] = int(splat[10])
    bbox[row, 3] = int(splat[11])


def view_direction(cam, means, i):  # type: ignore[no-untyped-def]
    """Unit direction (x, y, z) from the camera centre to Gaussian ``i``'s centre (map frame), the
    argument of the SH colour."""
    dx = means[i, 0] - cam[16]
    dy = means[i, 1] - cam[17]
    dz = means[i, 2] - cam[18]
    norm = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)
    return dx / norm, dy / norm, dz / norm
