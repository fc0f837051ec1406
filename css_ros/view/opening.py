"""The page's opening view: the map's up axis, a ceiling cut along it, and a start pose that shows the observed
surfaces from where they were observed.

Indoor maps are closed rooms: a view from outside shows the outer side of walls and a never-observed (grey)
ceiling. So the page opens inside: over the shoulder of a fused frame or, without a trajectory, at the in-room
viewpoint that shows the most of the observed map, and the ceiling is cut away along the up axis.

The up axis comes, in this order, from ``--up``, from the trajectory (the dominant surface axis closest to the
cameras' mean up, -y of the optical frame), else from the surfaces alone: flat Gaussians' normals cluster on the
room's three axes (floor/ceiling, two wall directions); the axis along which the map is thinnest is vertical
(a room is lower than it is wide) unless an axis nearly as thin has ends that differ much more in how much of them
was observed (a corridor: the floor was seen, the ceiling not). Up points from the better observed end (the
floor) or, when both ends were seen alike, away from the side where the observed Gaussians crowd (floor and
furniture). Everything is in the map frame of :class:`~css_ros.view.data.ViewData` (metres).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .data import ViewData

OPENING_FOV_Y = math.radians(60.0)   # vertical field of view of the opening view [rad]
SCORE_GRID = (40, 40)                # (columns, rows) of the coarse image the start poses are scored on: square,
                                     # the part of the view that every window shape shows
MIN_CLASS_SHARE = 0.02               # a class counts as shown when it covers this share of that image
MAX_SCORED_GAUSSIANS = 150_000       # the scoring and the axis estimate use at most this many Gaussians
MAX_SCORED_FRAMES = 40               # and at most this many trajectory frames (evenly spread)
FLAT_RATIO = 0.35                    # flat Gaussian: smallest std. dev. <= this x the middle one (it has a normal)
AXIS_COS = math.cos(math.radians(12.0))   # normals within 12 degrees of an axis belong to it
SNAP_COS = math.cos(math.radians(2.0))    # an up axis within 2 degrees of a frame axis is snapped onto it
CEILING_SLAB = 0.08                  # the top slab (share of the height range) where a ceiling is looked for
CLOSE_EXTENT = 1.5                   # axes thinner than this x the thinnest may be vertical (a corridor) ...
STRONG_ASYMMETRY = 0.3               # ... and the one whose ends differ most in observed share is (floor vs ceiling)
CEILING_SHARE = 0.2                  # a ceiling: the top slab holds this share of the horizontal surface area
CUT_BELOW_TOP = 0.12                 # default cut: this share of the height range below the top
STEP_BACK = 0.6                      # a frame's opening view starts this far [m] behind the frame's camera ...
STEP_UP = 0.4                        # ... and this much higher (over its shoulder: the frame's frustum in sight)
FRAME_TARGET = 1.5                   # ... looking at the point this far [m] ahead of the frame's camera
TRAJECTORY_PREFERENCE = 2.0          # a fused frame wins unless an in-room viewpoint scores this many times more
MIN_OPACITY = 0.1                    # fainter Gaussians neither show nor hide anything in the scoring

AXIS_NAMES = {"+x": (1.0, 0.0, 0.0), "-x": (-1.0, 0.0, 0.0), "+y": (0.0, 1.0, 0.0), "-y": (0.0, -1.0, 0.0),
              "+z": (0.0, 0.0, 1.0), "-z": (0.0, 0.0, -1.0)}
#: ``--up`` values: the six axis names of :data:`AXIS_NAMES` and x, y, z for their + ones
UP_CHOICES = sorted(AXIS_NAMES) + ["x", "y", "z"]


def up_vector(name: str | None) -> np.ndarray | None:
    """The ``--up`` axis as a (3,) vector, None when not given."""
    if name is None:
        return None
    return np.asarray(AXIS_NAMES[name if name[0] in "+-" else "+" + name], np.float64)


@dataclass(frozen=True)
class OpeningView:
    """Where the page opens and how it cuts the map.

    Attributes:
        up: (3,) unit up axis of the map frame; up_source: "--up", "trajectory", "surfaces" or "default".
        low, high: 1st and 99th percentiles of the Gaussians' heights along ``up`` [m].
        top: the largest height [m]; cut: default "cut above" height [m] (None: the map has no ceiling, nothing cut).
        position, look_at: (3,) camera position and orbit centre [m]; fov_y: vertical field of view [rad].
        source: "trajectory frame i", "a viewpoint inside the observed box" (or, for a map without extent,
            "a view from outside (the map has no extent)").
        classes_shown, coverage: classes on >= MIN_CLASS_SHARE and share of the coarse image in class colours,
            as scored for the chosen pose.
    """

    up: np.ndarray
    up_source: str
    low: float
    high: float
    top: float
    cut: float | None
    position: np.ndarray
    look_at: np.ndarray
    fov_y: float
    source: str
    classes_shown: int
    coverage: float


def axis_label(up: np.ndarray) -> str:
    """"+z" for a frame axis, else the vector with two decimals."""
    for name, v in AXIS_NAMES.items():
        if np.allclose(up, v, atol=1e-9):
            return name
    return "({:.2f}, {:.2f}, {:.2f})".format(*up)


def _sample(n: int, limit: int) -> np.ndarray:
    """Row indices: all of ``n``, or ``limit`` of them (seeded, sorted)."""
    if n <= limit:
        return np.arange(n)
    return np.sort(np.random.default_rng(0).choice(n, limit, replace=False))


def surface_normals(covariances: np.ndarray, opacity: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(normals (M, 3), area weights (M,), largest std. dev. (M,) [m]) of Gaussians (M, 3, 3) [m^2]: the normal is
    the axis of the smallest variance, the weight opacity x the in-plane area (0 for Gaussians that are not flat)."""
    evals, evecs = np.linalg.eigh(np.asarray(covariances, np.float64))
    s = np.sqrt(np.maximum(evals, 1e-18))
    flat = s[:, 0] <= FLAT_RATIO * s[:, 1]
    return evecs[:, :, 0], np.where(flat, s[:, 1] * s[:, 2] * np.asarray(opacity, np.float64), 0.0), s[:, 2]


def _refine(normals: np.ndarray, weights: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Weighted mean of the normals within AXIS_COS of ``axis`` (signs aligned), unit length."""
    d = normals @ axis
    near = np.abs(d) >= AXIS_COS
    v = ((np.sign(d[near]) * weights[near])[:, None] * normals[near]).sum(axis=0)
    n = np.linalg.norm(v)
    return v / n if n > 0 else axis


def _densest(normals: np.ndarray, weights: np.ndarray) -> np.ndarray | None:
    """The normal direction with the most area within AXIS_COS of it (one of up to 2000 seeded samples), refined."""
    if not np.any(weights > 0):
        return None
    rows = np.flatnonzero(weights > 0)
    rows = rows[_sample(len(rows), 2000)]
    n, w = normals[rows], weights[rows]
    density = (np.abs(n @ n.T) >= AXIS_COS).astype(np.float64) @ w
    return _refine(normals, weights, n[int(np.argmax(density))])


def dominant_axes(normals: np.ndarray, weights: np.ndarray, centers: np.ndarray) -> np.ndarray:
    """(3, 3) orthonormal rows: the map's surface axes (the densest normal direction, the densest one perpendicular
    to it, their cross product); the principal axes of the centres when too few Gaussians are flat."""
    first = _densest(normals, weights) if np.count_nonzero(weights) >= 50 else None
    if first is None:
        c = centers - centers.mean(axis=0)
        return np.linalg.eigh(c.T @ c)[1].T
    perp = np.abs(normals @ first) <= math.sin(math.radians(12.0))
    second = _densest(normals, np.where(perp, weights, 0.0))
    if second is None:
        second = np.cross(first, [1.0, 0.0, 0.0] if abs(first[0]) < 0.9 else [0.0, 1.0, 0.0])
    second = second - (second @ first) * first
    second /= np.linalg.norm(second)
    return np.stack([first, second, np.cross(first, second)])


def _snap(up: np.ndarray) -> np.ndarray:
    for v in AXIS_NAMES.values():
        if float(up @ np.asarray(v)) >= SNAP_COS:
            return np.asarray(v, np.float64)
    return up / np.linalg.norm(up)


def estimate_up(data: ViewData, normals: np.ndarray, weights: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, str]:
    """(up (3,), source) of the map: from the trajectory when it has one, else from the surfaces (module doc).
    ``normals`` / ``weights`` are :func:`surface_normals` of the Gaussians ``rows`` of ``data``."""
    centers = data.centers[rows].astype(np.float64)
    axes = dominant_axes(normals, weights, centers)
    if data.trajectory:
        cam_up = -np.mean([np.asarray(t[0], np.float64)[:3, 1] for t in data.trajectory], axis=0)
        if np.linalg.norm(cam_up) > 0.3:
            dots = axes @ cam_up
            k = int(np.argmax(np.abs(dots)))
            return _snap(axes[k] * np.sign(dots[k])), "trajectory"
    h = centers @ axes.T                                                    # (M, 3)
    lo, hi = np.percentile(h, 2, axis=0), np.percentile(h, 98, axis=0)
    extent = hi - lo
    observed = data.semantics.observed[rows]
    asym = np.array([end_asymmetry(h[:, j], observed, lo[j], hi[j]) for j in range(3)])
    close = np.flatnonzero(extent <= CLOSE_EXTENT * extent.min())
    k = int(np.argmin(extent))
    if len(close) > 1 and np.abs(asym[close]).max() >= STRONG_ASYMMETRY:
        k = int(close[np.argmax(np.abs(asym[close]))])
    if abs(asym[k]) >= STRONG_ASYMMETRY:
        sign = float(np.sign(asym[k]))
    else:
        mass = h[observed, k] if np.count_nonzero(observed) >= 10 else h[:, k]
        sign = 1.0 if np.median(mass) <= 0.5 * (lo[k] + hi[k]) else -1.0
    return _snap(axes[k] * sign), "surfaces"


def end_asymmetry(h: np.ndarray, observed: np.ndarray, lo: float, hi: float) -> float:
    """Observed share of the Gaussians in the bottom slab (CEILING_SLAB of ``lo``..``hi``) minus that of the top
    slab, along one axis with heights ``h`` (M,) [m]: near 1 for floor (seen) against ceiling (never seen), near 0
    for two opposite walls."""
    slab = CEILING_SLAB * (hi - lo)
    bottom, top = observed[h <= lo + slab], observed[h >= hi - slab]
    return (float(bottom.mean()) if len(bottom) else 0.0) - (float(top.mean()) if len(top) else 0.0)


def ceiling_cut(heights: np.ndarray, normals: np.ndarray, weights: np.ndarray, up: np.ndarray,
                low: float, high: float) -> float | None:
    """Default cut height [m]: CUT_BELOW_TOP of the height range below ``high`` when the top slab holds a
    ceiling (CEILING_SHARE of the horizontal surface area), else None."""
    horizontal = (weights > 0) & (np.abs(normals @ up) >= AXIS_COS)
    total = weights[horizontal].sum()
    if total <= 0 or high <= low:
        return None
    top = horizontal & (heights >= high - CEILING_SLAB * (high - low))
    if weights[top].sum() < CEILING_SHARE * total:
        return None
    return float(high - CUT_BELOW_TOP * (high - low))


def camera_axes(forward: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(right, down, forward) unit vectors of a level camera looking along ``forward`` with ``up`` up (the optical
    frame's x, y, z)."""
    f = forward / np.linalg.norm(forward)
    right = np.cross(f, up)
    if np.linalg.norm(right) < 1e-6:
        right = np.cross(f, [1.0, 0.0, 0.0] if abs(f[0]) < 0.9 else [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    return right, np.cross(f, right), f


def view_score(position: np.ndarray, forward: np.ndarray, up: np.ndarray, points: np.ndarray, labels: np.ndarray,
               sigma: np.ndarray, num_classes: int, fov_y: float = OPENING_FOV_Y,
               grid: tuple[int, int] = SCORE_GRID) -> tuple[int, float, float]:
    """(classes shown, coverage, median depth [m]) of a view drawn as a coarse z-buffer of Gaussian footprints.

    Args:
        points: (M, 3) centres [m]; labels: (M,) class of observed Gaussians, -1 for unobserved ones (they hide
            what is behind them but show no class colour); sigma: (M,) largest std. dev. [m] (footprint).
    A class is shown on >= MIN_CLASS_SHARE of the cells; coverage is the share of cells in class colours.
    """
    right, down, f = camera_axes(forward, up)
    rel = points - position
    z = rel @ f
    w, h = grid
    fpx = (h / 2.0) / math.tan(fov_y / 2.0)
    front = z > 0.05
    z, rel, lab, sig = z[front], rel[front], labels[front], sigma[front]
    u = np.floor(rel @ right / z * fpx + w / 2.0).astype(np.int64)
    v = np.floor(rel @ down / z * fpx + h / 2.0).astype(np.int64)
    r = np.clip(np.round(2.0 * sig * fpx / z), 0, 2).astype(np.int64)
    cells, depth, cls = [], [], []
    for dv in range(-2, 3):
        for du in range(-2, 3):
            m = (r >= max(abs(du), abs(dv))) & (u + du >= 0) & (u + du < w) & (v + dv >= 0) & (v + dv < h)
            cells.append((v[m] + dv) * w + u[m] + du)
            depth.append(z[m])
            cls.append(lab[m])
    c, d, k = np.concatenate(cells), np.concatenate(depth), np.concatenate(cls)
    if len(c) == 0:
        return 0, 0.0, 1.0
    order = np.lexsort((d, c))
    _, first = np.unique(c[order], return_index=True)
    near_lab, near_d = k[order][first], d[order][first]
    shown = near_lab >= 0
    counts = np.bincount(near_lab[shown], minlength=num_classes)
    classes = int(np.count_nonzero(counts >= MIN_CLASS_SHARE * w * h))
    depth_med = float(np.median(near_d[shown])) if np.any(shown) else float(np.median(near_d))
    return classes, float(np.count_nonzero(shown)) / (w * h), depth_med


def candidate_views(data: ViewData, points: np.ndarray, observed: np.ndarray, up: np.ndarray, low: float,
                    ceiling: float) -> list[tuple[np.ndarray, np.ndarray, str, bool]]:
    """(position, forward, source, from a fused frame) of the start poses to score: over the shoulder of fused
    frames (STEP_BACK behind, STEP_UP above, below ``ceiling``, looking at FRAME_TARGET ahead of the frame) and, in
    the observed box, its four corners and four edge middles at two heights, looking at the box centre near the
    floor."""
    out = []
    traj = data.trajectory
    for i in np.unique(np.linspace(0, len(traj) - 1, min(len(traj), MAX_SCORED_FRAMES)).astype(int)) if traj else []:
        T = np.asarray(traj[i][0], np.float64)
        f = T[:3, 2]
        level = f - (f @ up) * up
        back = level / np.linalg.norm(level) if np.linalg.norm(level) > 1e-6 else np.zeros(3)
        pos = T[:3, 3] - STEP_BACK * back + STEP_UP * up
        pos += (min(pos @ up, ceiling - 0.1) - pos @ up) * up
        target = T[:3, 3] + FRAME_TARGET * f
        if np.linalg.norm(target - pos) > 1e-3:
            out.append((pos, target - pos, f"trajectory frame {i}", True))
    pts = points[observed] if np.count_nonzero(observed) >= 10 else points
    flat = pts - np.outer(pts @ up, up)
    c0 = flat.mean(axis=0)
    e = np.linalg.eigh((flat - c0).T @ (flat - c0))[1]
    e1 = e[:, 2] - (e[:, 2] @ up) * up
    if np.linalg.norm(e1) < 1e-6:           # no horizontal spread: any level direction
        e1 = camera_axes(up, up)[0]
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    a, b = (flat - c0) @ e1, (flat - c0) @ e2
    alo, ahi = np.percentile(a, [2, 98])
    blo, bhi = np.percentile(b, [2, 98])
    centre = c0 + 0.5 * (alo + ahi) * e1 + 0.5 * (blo + bhi) * e2
    target = centre + (low + 0.2 * (ceiling - low)) * up
    for fa, fb in ((0.1, 0.1), (0.1, 0.9), (0.9, 0.1), (0.9, 0.9), (0.5, 0.1), (0.5, 0.9), (0.1, 0.5), (0.9, 0.5)):
        ground = c0 + (alo + fa * (ahi - alo)) * e1 + (blo + fb * (bhi - blo)) * e2
        for share in (0.55, 0.85):
            pos = ground + (low + share * (ceiling - low)) * up
            if np.linalg.norm(target - pos) > 1e-3:
                out.append((pos, target - pos, "a viewpoint inside the observed box", False))
    if not out:   # a map without extent (every Gaussian in one place): from 3 m away, a little above
        out.append((target - 3.0 * e1 + 1.0 * up, 3.0 * e1 - 1.0 * up, "a view from outside (the map has no extent)",
                    False))
    return out


def opening_view(data: ViewData, up: np.ndarray | None = None) -> OpeningView:
    """The opening view of ``data`` (module doc); ``up`` forces the up axis (``--up``)."""
    n = len(data.centers)
    if n == 0:
        z = np.array([0.0, 0.0, 1.0])
        return OpeningView(z, "default", 0.0, 0.0, 0.0, None, np.array([-3.0, -3.0, 3.0]), np.zeros(3),
                           OPENING_FOV_Y, "empty map", 0, 0.0)
    rows = _sample(n, MAX_SCORED_GAUSSIANS)
    rows = rows[data.opacity[rows] >= MIN_OPACITY] if np.count_nonzero(data.opacity[rows] >= MIN_OPACITY) else rows
    normals, weights, sigma = surface_normals(data.covariances[rows], data.opacity[rows])
    if up is not None:
        up_axis, source = np.asarray(up, np.float64) / np.linalg.norm(up), "--up"
    else:
        up_axis, source = estimate_up(data, normals, weights, rows)
    points = data.centers[rows].astype(np.float64)
    heights = points @ up_axis
    low, high = (float(v) for v in np.percentile(heights, [1, 99]))
    cut = ceiling_cut(heights, normals, weights, up_axis, low, high)
    observed = data.semantics.observed[rows]
    labels = np.where(observed, data.semantics.label[rows], -1).astype(np.int64)
    shown = heights <= (cut if cut is not None else np.inf)
    best = None
    for pos, fwd, name, framed in candidate_views(data, points, observed, up_axis, low, cut if cut else high):
        k, cov, depth = view_score(pos, fwd, up_axis, points[shown], labels[shown], sigma[shown],
                                   data.classes.num_classes)
        score = cov * min(k, 8) * (TRAJECTORY_PREFERENCE if framed else 1.0)
        if best is None or score > best[0]:
            best = (score, pos, fwd, name, k, cov, depth)
    assert best is not None
    _, pos, fwd, name, k, cov, depth = best
    look_at = pos + fwd / np.linalg.norm(fwd) * max(depth, 0.5)
    return OpeningView(up_axis, source, low, high, float(heights.max()), cut, pos, look_at, OPENING_FOV_Y, name,
                       k, cov)
