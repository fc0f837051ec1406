"""Kernel warm-up, shared by css_node (before subscribing) and css_replay (before timing).

numba compiles a kernel once per argument types, not per data, so one pass of the per-frame cycle on a
throwaway tiny map compiles (or loads from the cache) every kernel that any model and map will use: the
model has SH degree 3 so the view-dependent colour kernel is included (degrees 1-3 share its types;
degree 0 needs no kernel).
"""
from __future__ import annotations

import time

import numpy as np

from .camera import Camera, intrinsics_from_fov
from .gaussians import GaussianModel
from .semantic_map import SemanticMap
from ..errors import CssError

#: Size of the warm-up view [px].
WARMUP_WIDTH, WARMUP_HEIGHT = 16, 12


def warm_up_kernels(backend: str = "numba", num_classes: int = 2) -> float:
    """Run observe (with and without confidence), update, render at two sizes and score_views once on an
    8-Gaussian SH-degree-3 map seen at 16 x 12 px, 2 m in front of the camera; returns the seconds taken.

    Raises:
        CssError: the backend cannot be created or its kernels fail (e.g. ``cuda`` without numba-cuda or a
            GPU, numba-cuda with an unsupported numpy): one line naming cause and fix, never another type.
    """
    try:
        return _warm_up(backend, num_classes)
    except CssError:
        raise
    except Exception as exc:  # a broken kernel stack must not escape as a traceback
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        raise CssError(f"kernel warm-up on backend '{backend}' failed ({type(exc).__name__}: {first[:200]}); "
                       "fix: reinstall with pip install -e . (numpy<2.4 with numba), or choose another backend") from exc


def _warm_up(backend: str, num_classes: int) -> float:
    t0 = time.perf_counter()
    xy = np.stack(np.meshgrid([-0.2, 0.2], [-0.3, 0.0, 0.3, 0.1])[::-1], -1).reshape(-1, 2)[:8]
    n = len(xy)
    sh = np.zeros((n, 16, 3), np.float32)
    sh[:, 1:, :] = 0.01
    model = GaussianModel(means=np.column_stack([xy, np.full(n, 2.0)]), sh=sh,
                          opacity_logits=np.full(n, 2.0), log_scales=np.full((n, 3), np.log(0.1)),
                          rotations=np.tile([1.0, 0, 0, 0], (n, 1)))
    smap = SemanticMap(model, num_classes=max(1, int(num_classes)), backend=backend)  # type: ignore[arg-type]  # checked by make_backend
    cam = Camera(K=intrinsics_from_fov(WARMUP_WIDTH, WARMUP_HEIGHT, 60.0), width=WARMUP_WIDTH,
                 height=WARMUP_HEIGHT, T_map_cam=np.eye(4))
    labels = np.zeros((WARMUP_HEIGHT, WARMUP_WIDTH), dtype=np.int32)
    smap.observe(cam, labels, np.ones(labels.shape, dtype=np.float32))
    smap.observe(cam, labels, None)
    smap.update(cam, labels, None)
    smap.render(cam)
    smap.render(cam.scaled(0.5))
    smap.score_views([cam, cam.scaled(0.5)])
    return time.perf_counter() - t0
