"""Small synthetic scenes for the engine tests (random clouds and structured edge cases)."""
from __future__ import annotations

import numpy as np

from css_ros import Camera, GaussianModel


def random_quats(rng, n):
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def random_scene(seed: int, n: int = 150, depth=(0.5, 6.0), log_scale=(-4.0, -0.5)) -> GaussianModel:
    """Gaussians in front of (and around) a camera at the origin looking along +z."""
    rng = np.random.default_rng(seed)
    means = rng.uniform([-3, -2.5, depth[0]], [3, 2.5, depth[1]], (n, 3))
    scales = np.exp(rng.uniform(*log_scale, (n, 3)))
    return GaussianModel.from_activated(means, scales, random_quats(rng, n), rng.uniform(0.02, 1.0, n),
                                        rng.uniform(0, 1, (n, 3)))


def edge_case_scene(seed: int = 0) -> GaussianModel:
    """Behind the camera, at the near plane, straddling every image border, huge and tiny ones,
    opaque walls (early termination) and a few fully transparent ones."""
    rng = np.random.default_rng(seed)
    parts = []
    # behind the camera and at/near the near plane
    parts.append((rng.uniform([-1, -1, -3], [1, 1, 0.011], (20, 3)), np.exp(rng.uniform(-3, 0, (20, 3)))))
    # straddling the four borders (camera: 64x48, f=50 -> half FoV ~0.64 x 0.48 at z=1)
    border = np.array([[0.64, 0, 1], [-0.64, 0, 1], [0, 0.48, 1], [0, -0.48, 1],
                       [0.64, 0.48, 1], [-0.64, -0.48, 1], [0.9, 0.0, 1.0], [0.0, -0.7, 1.0]])
    parts.append((border * rng.uniform(1, 4, (8, 1)), np.exp(rng.uniform(-3, -1, (8, 3)))))
    # huge (covering the whole view) and tiny (sub-pixel)
    parts.append((np.array([[0.0, 0.0, 3.0], [0.5, -0.2, 8.0]]), np.array([[5.0, 4.0, 0.1], [30.0, 30.0, 30.0]])))
    parts.append((rng.uniform([-1, -1, 1], [1, 1, 5], (20, 3)), np.exp(rng.uniform(-9, -7, (20, 3)))))
    # a stack of opaque sheets facing the camera: drives transmittance below 1e-4
    sheets = np.array([[0.0, 0.0, z] for z in np.linspace(2.0, 2.5, 12)])
    parts.append((sheets, np.tile([1.0, 1.0, 0.01], (12, 1))))
    # ordinary ones
    parts.append((rng.uniform([-2, -1.5, 0.5], [2, 1.5, 6], (60, 3)), np.exp(rng.uniform(-4, -1, (60, 3)))))
    means = np.concatenate([p[0] for p in parts])
    scales = np.concatenate([p[1] for p in parts])
    n = len(means)
    opac = rng.uniform(0.05, 1.0, n)
    opac[-72:-60] = 0.999       # the opaque sheets
    opac[:3] = 0.002            # below 1/255: never contribute
    quats = random_quats(rng, n)
    quats[-72:-60] = [1, 0, 0, 0]
    return GaussianModel.from_activated(means, scales, quats, opac, rng.uniform(0, 1, (n, 3)))


def camera(width: int = 64, height: int = 48, f: float = 50.0, position=(0, 0, 0), quat=(0, 0, 0, 1),
           cx: float | None = None, cy: float | None = None) -> Camera:
    K = np.array([[f, 0, (width - 1) / 2 if cx is None else cx], [0, f * 1.05, (height - 1) / 2 if cy is None else cy],
                  [0, 0, 1.0]])
    return Camera.from_pose(K, width, height, np.asarray(position, float), np.asarray(quat, float))


def small_wall(tmp_path, n: int) -> GaussianModel:
    """A flat wall of ``n`` Gaussians at z = 3 m (map frame), written to and read back from ``tmp_path``/wall.ply (the
    model a node would load: same fingerprint)."""
    side = int(np.ceil(np.sqrt(n)))
    xs, ys = np.meshgrid(np.linspace(-2, 2, side), np.linspace(-1.5, 1.5, side))
    pos = np.c_[xs.ravel(), ys.ravel(), np.full(side * side, 3.0)][:n]
    GaussianModel.from_activated(pos, np.full((n, 3), 0.05), np.tile([1.0, 0, 0, 0], (n, 1)), np.full(n, 0.9),
                                 np.random.default_rng(0).uniform(0.1, 0.9, (n, 3))).to_ply(tmp_path / "wall.ply")
    return GaussianModel.from_ply(tmp_path / "wall.ply")
