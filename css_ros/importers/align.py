"""The splat's frame against the robot's map: the similarity ``splat_to_map`` from matched camera poses, and the
up direction of a trainer's cameras (css_align, css_import).

Both sides are camera poses of the same images: the trainer's (splat frame, arbitrary scale) and the robot's
(map frame, metres). The similarity map <- splat is fitted to the camera centres with Umeyama's closed form; a
least-median-of-squares search over minimal sets of 3 matches picks the model that most matches agree with, the
inliers (residual within 2.5 robust standard deviations of that model's residuals, at least
:data:`MIN_INLIER_BOUND_M`) are refitted. The camera orientations then check the result: their residual angle
R_map_cam vs R · R_splat_cam is reported, and a fit whose residuals exceed the bounds is refused.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..engine.camera import quaternion_xyzw_to_matrix
from ..engine.similarity import Similarity, rotation_between
from ..errors import InputError

#: Fewest matched cameras a similarity is fitted to (3 non-collinear points fix it).
MIN_MATCHES = 3
#: Camera centres whose second singular value is below this share of the first are (nearly) collinear.
COLLINEAR_RATIO = 1e-3
#: Smallest inlier bound [m]: exact data would otherwise reject matches for rounding.
MIN_INLIER_BOUND_M = 1e-3
#: Default refusal bounds: RMS position residual of the inliers [m] and median rotation residual [deg].
DEFAULT_MAX_RESIDUAL_M = 0.10
DEFAULT_MAX_ROTATION_DEG = 5.0
#: Axis names of ``--up-axis`` (the splat's up direction).
UP_AXES = {"x": (1, 0, 0), "y": (0, 1, 0), "z": (0, 0, 1), "-x": (-1, 0, 0), "-y": (0, -1, 0), "-z": (0, 0, -1)}
#: The mean camera "up" (-y of the optical frames) must be at least this long to tell which way is up.
MIN_UP_CONSISTENCY = 0.5


class AlignError(InputError):
    """The poses cannot give a trustworthy similarity (too few, degenerate, or residuals above the bounds)."""


@dataclass(frozen=True)
class Alignment:
    """A fitted ``splat_to_map`` and how well it fits.

    ``inliers``: (N,) bool; residuals of the inliers: ``rms_m`` and ``max_m`` [m, map frame] of the camera
    centres, ``rot_median_deg`` and ``rot_max_deg`` of the camera orientations (NaN without orientations).
    """

    similarity: Similarity
    inliers: np.ndarray
    rms_m: float
    max_m: float
    rot_median_deg: float
    rot_max_deg: float

    @property
    def num_inliers(self) -> int:
        return int(np.count_nonzero(self.inliers))


def umeyama(src: np.ndarray, dst: np.ndarray) -> Similarity:
    """The least-squares similarity with dst ≈ s R src + t (Umeyama 1991); (N, 3) each, N >= 3."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    xs, xd = src - mu_s, dst - mu_d
    var_s = float(np.mean(np.sum(xs * xs, axis=1)))
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    scale = float(np.trace(np.diag(D) @ S) / var_s) if var_s > 0 else 1.0
    return Similarity(scale, R, mu_d - scale * R @ mu_s)


def _collinear(points: np.ndarray) -> bool:
    sv = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    return bool(sv[0] == 0 or sv[1] / sv[0] < COLLINEAR_RATIO)


def _rotation_residuals_deg(sim: Similarity, R_splat: np.ndarray | None, R_map: np.ndarray | None) -> np.ndarray:
    if R_splat is None or R_map is None:
        return np.full(0, np.nan)
    E = np.einsum("nji,jk,nkl->nil", R_map, sim.R, R_splat)   # R_map^T (R R_splat): identity when they agree
    cos = np.clip((np.trace(E, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    return np.degrees(np.arccos(cos))


def fit_splat_to_map(splat_positions: np.ndarray, map_positions: np.ndarray,
                     splat_rotations: np.ndarray | None = None, map_rotations: np.ndarray | None = None,
                     max_residual_m: float = DEFAULT_MAX_RESIDUAL_M,
                     max_rotation_deg: float = DEFAULT_MAX_ROTATION_DEG, seed: int = 0,
                     max_trials: int = 2000) -> Alignment:
    """Fit x_map = s R x_splat + t to matched camera centres (N, 3) with outlier rejection (module docstring).

    ``*_rotations``: (N, 3, 3) camera orientations (optical frame in splat / map), used to check the fit.

    Raises:
        AlignError: fewer than :data:`MIN_MATCHES` matches, collinear centres, or residuals above the bounds.
    """
    src = np.asarray(splat_positions, dtype=np.float64).reshape(-1, 3)
    dst = np.asarray(map_positions, dtype=np.float64).reshape(-1, 3)
    n = len(src)
    if n != len(dst):
        raise AlignError(f"{n} trainer cameras but {len(dst)} robot poses")
    if n < MIN_MATCHES:
        raise AlignError(f"only {n} matched camera(s): at least {MIN_MATCHES} (not on one line) are needed")
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        raise AlignError("non-finite camera positions")
    if _collinear(src) or _collinear(dst):
        raise AlignError(f"the {n} matched camera positions lie (nearly) on one line: the rotation about that line "
                         "is undetermined; use images from a path that turns")
    rng = np.random.default_rng(seed)
    best, best_med = None, math.inf
    trials = min(max_trials, math.comb(n, 3))
    combos = [tuple(rng.choice(n, 3, replace=False)) for _ in range(trials)] if n > 12 else \
        [c for c in _all_triples(n)][:max_trials]
    for idx in combos:
        idx = list(idx)
        if _collinear(src[idx]) or _collinear(dst[idx]):
            continue
        sim = umeyama(src[idx], dst[idx])
        if not (math.isfinite(sim.scale) and sim.scale > 0):
            continue
        med = float(np.median(np.linalg.norm(sim.apply(src) - dst, axis=1)))
        if med < best_med:
            best, best_med = sim, med
    if best is None:
        raise AlignError("every set of 3 matches is (nearly) collinear: no similarity can be fitted")
    res = np.linalg.norm(best.apply(src) - dst, axis=1)
    bound = max(MIN_INLIER_BOUND_M, 2.5 * 1.4826 * float(np.median(res)))
    inliers = res <= bound
    if np.count_nonzero(inliers) >= MIN_MATCHES and not _collinear(src[inliers]):
        best = umeyama(src[inliers], dst[inliers])
        res = np.linalg.norm(best.apply(src) - dst, axis=1)
        inliers = res <= bound
    rms = float(np.sqrt(np.mean(res[inliers] ** 2))) if np.any(inliers) else math.inf
    rot = _rotation_residuals_deg(best, None if splat_rotations is None else np.asarray(splat_rotations)[inliers],
                                  None if map_rotations is None else np.asarray(map_rotations)[inliers])
    result = Alignment(best, inliers, rms, float(res[inliers].max()) if np.any(inliers) else math.inf,
                       float(np.median(rot)) if rot.size else math.nan, float(rot.max()) if rot.size else math.nan)
    if result.num_inliers < MIN_MATCHES:
        raise AlignError(f"only {result.num_inliers} of {n} matches agree on one similarity")
    if rms > max_residual_m:
        raise AlignError(f"position residual {rms:.3f} m (RMS of {result.num_inliers} inliers) above the bound "
                         f"{max_residual_m:g} m: the poses do not describe the same images (--max-residual)")
    if rot.size and result.rot_median_deg > max_rotation_deg:
        raise AlignError(f"rotation residual {result.rot_median_deg:.2f} deg (median) above the bound "
                         f"{max_rotation_deg:g} deg: wrong camera extrinsics or optical-frame convention? "
                         "(--max-rotation-residual)")
    return result


def _all_triples(n: int):  # noqa: ANN202 - generator of index triples
    for i in range(n):
        for j in range(i + 1, n):
            for k in range(j + 1, n):
                yield (i, j, k)


def camera_up(rotations: np.ndarray) -> np.ndarray:
    """The mean "up" direction (unit (3,)) of cameras with optical-frame rotations (N, 3, 3): the mean of their
    -y axes (OpenCV optical frames: y points down in the image, so people and robots hold -y up).

    Raises:
        AlignError: the cameras disagree (mean shorter than :data:`MIN_UP_CONSISTENCY`): pass ``--up-axis``.
    """
    ups = -np.asarray(rotations, dtype=np.float64)[:, :, 1]
    mean = ups.mean(axis=0)
    if np.linalg.norm(mean) < MIN_UP_CONSISTENCY:
        raise AlignError(f"the cameras do not agree on which way is up (mean of their -y axes has length "
                         f"{np.linalg.norm(mean):.2f} < {MIN_UP_CONSISTENCY}); pass --up-axis")
    return mean / np.linalg.norm(mean)


def up_alignment(rotations: np.ndarray, up_axis: str = "auto") -> Similarity:
    """A rotation-only ``splat_to_map`` that makes the map z-up: the splat's up (``up_axis``, or from the cameras
    with "auto") onto +z. ``up_axis`` "none" gives the identity."""
    if up_axis == "none":
        return Similarity.identity()
    up = camera_up(rotations) if up_axis == "auto" else np.array(UP_AXES[up_axis], dtype=np.float64)
    return Similarity(1.0, rotation_between(up, np.array([0.0, 0.0, 1.0])), np.zeros(3))


def rotations_of(quats_xyzw: np.ndarray) -> np.ndarray:
    """(N, 4) xyzw -> (N, 3, 3)."""
    return quaternion_xyzw_to_matrix(np.asarray(quats_xyzw, dtype=np.float64))
