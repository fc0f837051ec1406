"""Benchmark of the per-frame CSS cycle (SemanticMap.observe) and of query views.

Scenes are the procedural indoor room of css_ros.demo.scene (Gaussians on surfaces at realistic
sizes), viewed along the demo robot trajectory. Each scene runs in its own subprocess so the peak
resident memory reported is that scene's alone (model + map + buffers + interpreter).

    python benchmarks/bench_frame.py                   # the three scenes of the README + candidates + torch ratio
    python benchmarks/bench_frame.py --scene 100k      # one scene
    python benchmarks/bench_frame.py --gaussians 200000 --width 640 --height 480 --classes 28
    python benchmarks/bench_frame.py --backend cuda            # the GPU table (docs/cuda.md), needs a GPU
    python benchmarks/bench_frame.py --backend cuda --simulate # the same code path on a tiny scene, no GPU

Real-density scenes (when /work/shared/data/real-ply/biker.ply or $CSS_BIKER_PLY exists): "biker" (the
trained splat alone, orbiting camera, 640x480, C=20) and "biker8" (8 copies in a 4 x 2 grid 2 m
apart, 1.22 M Gaussians, orbiting camera, 1280x720, C=28).

Prints frames/s (median over the timed frames, after warm-up; numba compile time reported
separately), per-stage milliseconds and peak RSS.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

SCENES = {
    "100k": dict(gaussians=100_000, width=320, height=240, classes=20, kitti=False),
    "500k": dict(gaussians=500_000, width=640, height=480, classes=28, kitti=False),
    "1M": dict(gaussians=1_000_000, width=1241, height=376, classes=19, kitti=True),
    "3M": dict(gaussians=3_000_000, width=1280, height=720, classes=40, kitti=False),
    "biker": dict(gaussians=152_746, width=640, height=480, classes=20, kitti=False, ply="biker", copies=1),
    # the same splat seen whole from close by: the orbit's radius sweeps 1.3-2.2 x the median distance of the
    # means from their median (0.73 m), so the object fills the view
    "biker-close": dict(gaussians=152_746, width=640, height=480, classes=20, kitti=False, ply="biker", copies=1,
                        close=True),
    "biker8": dict(gaussians=8 * 152_746, width=1280, height=720, classes=28, kitti=False, ply="biker", copies=8),
    # the code path of --simulate (numba-cuda simulator: each GPU thread is a Python thread, and every warp
    # intrinsic a barrier of the block's threads): the smallest demo room, of which 200 Gaussians are kept
    "tiny": dict(gaussians=1400, width=16, height=12, classes=4, kitti=False, keep=200),
}
DEFAULT_SCENES = {"numba": ["100k", "500k", "1M", "biker", "biker-close", "biker8"],
                  "cuda": ["100k", "500k", "1M", "3M", "biker", "biker8"]}
BIKER_PLY = Path(os.environ.get("CSS_BIKER_PLY", "/work/shared/data/real-ply/biker.ply"))


def biker_model(copies: int):
    """biker.ply alone, or ``copies`` (8) copies in a 4 x 2 grid 2 m apart in the x-z plane (y is down
    in that capture). Returns (model, centre [m], orbit radius [m])."""
    from css_ros import GaussianModel

    base = GaussianModel.from_ply(BIKER_PLY)
    centre = np.median(np.asarray(base.means, dtype=np.float64), axis=0)
    if copies == 1:
        return base, centre, 2.2
    offsets = [np.array([2.0 * (i % 4) - 3.0, 0.0, 2.0 * (i // 4) - 1.0]) for i in range(copies)]
    cat = lambda f: np.concatenate([f(o) for o in offsets])  # noqa: E731
    model = GaussianModel(means=cat(lambda o: np.asarray(base.means) + o.astype(np.float32)),
                          sh=cat(lambda o: base.sh), opacity_logits=cat(lambda o: base.opacity_logits),
                          log_scales=cat(lambda o: base.log_scales), rotations=cat(lambda o: base.rotations))
    return model, centre, 6.5


def orbit_cameras(centre: np.ndarray, radius: "float | tuple[float, float]", count: int, K: np.ndarray, width: int,
                  height: int) -> list:
    """Cameras on a circle around ``centre`` in the x-z plane, 0.4 m above it (y down), looking at it. A (near, far)
    ``radius`` sweeps the distance between the two along the orbit (twice round)."""
    from css_ros import Camera

    near, far = (radius, radius) if isinstance(radius, float) else radius
    cams = []
    for i in range(count):
        a = 2.0 * math.pi * i / max(count, 1)
        r = near + (far - near) * 0.5 * (1.0 - math.cos(2.0 * a))
        pos = centre + np.array([r * math.cos(a), -0.4, r * math.sin(a)])
        cams.append(Camera.look_at(pos, centre, K, width, height, up=(0.0, -1.0, 0.0)))
    return cams


def build_scene(cfg: dict, num_cams: int) -> tuple:
    """(model, ground-truth class per Gaussian, cameras) of a benchmark scene."""
    from css_ros import Camera
    from css_ros.demo.scene import build_indoor_scene
    from css_ros.demo.trajectory import robot_trajectory

    K = intrinsics(cfg["width"], cfg["height"], cfg["kitti"])
    if cfg.get("ply"):
        model, centre, radius = biker_model(cfg["copies"])
        means = np.asarray(model.means, dtype=np.float64)
        if cfg.get("close"):
            median = float(np.median(np.linalg.norm(means - centre, axis=1)))
            radius = (1.3 * median, 2.2 * median)
        gt = (np.floor(means[:, 0] / 0.25) + 3 * np.floor(means[:, 1] / 0.25) + 7 * np.floor(means[:, 2] / 0.25))
        return model, gt.astype(np.int64) % cfg["classes"], orbit_cameras(centre, radius, num_cams, K,
                                                                           cfg["width"], cfg["height"])
    model, gt = build_indoor_scene(cfg["gaussians"], seed=0)
    if cfg.get("keep"):
        keep = np.sort(np.random.default_rng(0).choice(model.num_gaussians, cfg["keep"], replace=False))
        model, gt = model.select(keep), gt[keep]
    model = with_view_dependent_colour(model, cfg.get("sh_degree", 3))
    traj = robot_trajectory(num_cams, seed=0)
    return model, gt, [Camera(K, cfg["width"], cfg["height"], T) for T in traj.T_map_cam]


def truth_labels(model, gt: np.ndarray, num_classes: int, cams: list) -> list[np.ndarray]:
    """The segmentations a benchmark feeds: the ground truth (class ``gt % num_classes`` per Gaussian, near-certain)
    rendered at each camera."""
    from css_ros import SemanticMap

    truth = SemanticMap(model, num_classes)
    truth.concentrations[...] = 1e-3
    truth.concentrations[np.arange(model.num_gaussians), gt % num_classes] = 1e3
    return [truth.render(c).labels for c in cams]


def intrinsics(width: int, height: int, kitti: bool) -> np.ndarray:
    if kitti:  # KITTI odometry camera 2
        return np.array([[718.856, 0.0, 607.19], [0.0, 718.856, 185.22], [0.0, 0.0, 1.0]])
    f = width / (2.0 * math.tan(math.radians(75.0) / 2.0))
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def with_view_dependent_colour(model, degree: int):
    """The procedural room has SH degree 0; trained 3DGS models carry degree 3, whose evaluation is
    part of every view's cost. Adds small random higher-order coefficients up to ``degree``."""
    from css_ros import GaussianModel

    k = (degree + 1) ** 2
    if k <= model.sh.shape[1]:
        return model
    rng = np.random.default_rng(1)
    rest = rng.normal(scale=0.05, size=(model.num_gaussians, k - model.sh.shape[1], 3)).astype(np.float32)
    return GaussianModel(means=model.means, sh=np.concatenate([model.sh, rest], axis=1),
                         opacity_logits=model.opacity_logits, log_scales=model.log_scales,
                         rotations=model.rotations)


def synthetic_sensor_model(num_classes: int, kind: str):
    """A sensor model for timing (``kind``: none, weights, symmetric, confusion): 0.5 m bins to 10 m, random
    weights in [0.2, 1]; ``symmetric``: css_calibrate's default votes; ``confusion``: dense random confusion rows
    (the worst case: every class a different non-zero share)."""
    if kind == "none":
        return None
    from css_ros.engine.sensor_model import SensorModel, uniform_edges

    rng = np.random.default_rng(7)
    edges = uniform_edges(10.0, 0.5)
    bins = edges.size - 1
    weight = rng.uniform(0.2, 1.0, (num_classes, bins))
    confusion = None
    if kind == "confusion":
        confusion = rng.uniform(0.0, 1.0, (num_classes, bins, num_classes))
        confusion /= confusion.sum(axis=2, keepdims=True)
    elif kind == "symmetric":
        from css_ros.calibration.learn import symmetric_votes

        confusion = symmetric_votes(rng.uniform(0.3, 1.0, (num_classes, bins)))
    return SensorModel(tuple(f"class{i}" for i in range(num_classes)), edges, weight, confusion)


def run_scene(cfg: dict, frames: int, warmup: int, candidates: int, cand_w: int, cand_h: int,
              torch_frames: int) -> dict:
    from css_ros import SemanticMap
    from css_ros.engine.cpu.projection import project
    from css_ros.engine.cpu.raster import bin_tiles, dirichlet_attributes, render_semantic
    from css_ros.engine.final_form import image_uncertainty

    t0 = time.perf_counter()
    model, gt, cams = build_scene(cfg, frames + warmup + 1)
    build_s = time.perf_counter() - t0
    C = cfg["classes"]

    labels = truth_labels(model, gt, C, cams)  # outside the timings

    sensor = synthetic_sensor_model(C, cfg.get("sensor_model", "none"))
    soft = None if sensor is None else sensor.soft_labels()
    smap = SemanticMap(model, C, sensor_model=sensor)
    t0 = time.perf_counter()
    smap.observe(cams[0], labels[0])  # compiles (or loads cached) numba kernels
    first_s = time.perf_counter() - t0

    cycle, stages = [], {k: [] for k in ("project", "bin", "update", "moments", "render", "uncertainty")}
    walking: list[float] = []
    backend = smap._backend
    for i in range(1, frames + warmup + 1):
        cam, lab = cams[i], labels[i]
        t_start = time.perf_counter()
        smap.observe(cam, lab)
        t_cycle = time.perf_counter() - t_start
        # the same stages, timed one by one (a second pass at the same pose, on a copy of the map)
        conc = smap.concentrations.copy()
        t = [time.perf_counter()]
        proj = project(backend.geometry, cam, backend._scratch)   # its kept buffers, as observe does
        t.append(time.perf_counter())
        bins = bin_tiles(proj, cam.width, cam.height, kept=backend._lists)
        t.append(time.perf_counter())
        inputs = smap._frame_labels(cam, lab, None)   # as observe with its default outputs (no surprise)
        backend.update((proj, bins, cam), inputs, conc, soft)
        t.append(time.perf_counter())
        attrs = dirichlet_attributes(conc, proj.ids, proj.colors, proj.packed, backend._rows)
        t.append(time.perf_counter())
        buf = render_semantic(proj, bins, cam.width, cam.height, attrs, 1 / C, 0.0, 1.0, np.zeros(3), False,
                              store=backend._store)
        t.append(time.perf_counter())
        image_uncertainty(buf.expectation, buf.variance)
        t.append(time.perf_counter())
        # the same render walking every pixel itself (as a query view does): the walk the update did for both
        w0 = time.perf_counter()
        render_semantic(proj, bins, cam.width, cam.height, attrs, 1 / C, 0.0, 1.0, np.zeros(3), False)
        w1 = time.perf_counter()
        if i > warmup:
            cycle.append(t_cycle)
            for k, (a, b) in zip(stages, zip(t[:-1], t[1:])):
                stages[k].append(b - a)
            walking.append(w1 - w0)
    query = []
    for cam in cams[warmup + 1:]:
        t0 = time.perf_counter()
        smap.render(cam)
        query.append(time.perf_counter() - t0)
    result = dict(cfg, build_s=build_s, first_frame_s=first_s,
                  visible=int(len(project(backend.geometry, cams[-1]).ids)),
                  cycle_ms=1e3 * statistics.median(cycle), fps=1.0 / statistics.median(cycle),
                  query_ms=1e3 * statistics.median(query), query_fps=1.0 / statistics.median(query),
                  stages_ms={k: 1e3 * statistics.median(v) for k, v in stages.items()},
                  render_walking_ms=1e3 * statistics.median(walking))
    if candidates:
        cand = [c.scaled(cand_w / c.width) for c in cams[1:candidates + 1]]
        smap.score_views(cand[:2])
        times = []
        for _ in range(5):
            t0 = time.perf_counter()
            smap.score_views(cand)
            times.append(time.perf_counter() - t0)
        result["candidate_views_per_s"] = len(cand) / statistics.median(times)
        result["candidate_size"] = f"{cand[0].width}x{cand[0].height}"
    if torch_frames:
        slow = SemanticMap(model, C, backend="torch")
        slow.observe(cams[1], labels[1])
        times = []
        for i in range(2, 2 + torch_frames):
            t0 = time.perf_counter()
            slow.observe(cams[i], labels[i])
            times.append(time.perf_counter() - t0)
        result["torch_cycle_ms"] = 1e3 * statistics.median(times)
        result["torch_ratio"] = result["torch_cycle_ms"] / result["cycle_ms"]
    result["peak_rss_mib"] = peak_rss_mib()
    return result


def print_table(results: list[dict]) -> None:
    print()
    print(f"{'scene':>6} {'res':>10} {'C':>3} {'visible':>8} {'cycle fps':>9} {'query v/s':>9} "
          f"{'peak MiB':>8} {'cand v/s':>8} {'torch x':>7}")
    for r in results:
        print(f"{r['name']:>6} {r['width']}x{r['height']:<5} {r['classes']:>3} {r['visible']:>8} "
              f"{r['fps']:>9.2f} {r['query_fps']:>9.2f} {r['peak_rss_mib']:>8.0f} "
              f"{r.get('candidate_views_per_s', float('nan')):>8.1f} {r.get('torch_ratio', float('nan')):>7.1f}")
    print()
    print("per-stage median ms of the observe cycle (update = the frame's one compositing walk + the votes + adding"
          " into the map; moments = E, Var per visible Gaussian; render replays the update's contributions; walking ="
          " the same render compositing every pixel itself, as a query view does):")
    for r in results:
        s = r["stages_ms"]
        print(f"{r['name']:>6}: " + "  ".join(f"{k}={v:.1f}" for k, v in s.items())
              + (f" (walking {r['render_walking_ms']:.1f})" if "render_walking_ms" in r else "")
              + f"   | first frame (compile/cache load) {r['first_frame_s']:.2f} s, scene build {r['build_s']:.1f} s")


def run_scene_cuda(cfg: dict, frames: int, warmup: int, candidates: int, cand_w: int, cand_h: int) -> dict:
    """The observe cycle, a query view and (optionally) a score_views batch on backend "cuda".

    Every timing ends with the outputs on the host (the backend's one download per frame), so no
    extra synchronisation is needed; per-stage times synchronise after each stage. Kernel compiles
    happen in the untimed first frame (and first batch).
    """
    from css_ros import SemanticMap

    t0 = time.perf_counter()
    model, gt, cams = build_scene(cfg, frames + warmup + 1)
    build_s = time.perf_counter() - t0
    C = cfg["classes"]
    if cfg.get("stub_device"):  # the host's own work per frame, no GPU (benchmarks/cuda_host.py)
        return host_time(model, cams, C, cfg, max(frames, 50))
    gt_map = SemanticMap(model, C, backend="cuda")   # ground-truth segmentations, outside the timings
    conc = np.full((model.num_gaussians, C), 1e-3)
    conc[np.arange(model.num_gaussians), gt % C] = 1e3
    gt_map.concentrations = conc
    labels = [gt_map.render(c).labels for c in cams]
    del gt_map, conc
    gpu_memory_reset()

    smap = SemanticMap(model, C, backend="cuda")
    t0 = time.perf_counter()
    smap.observe(cams[0], labels[0])  # compiles the kernels
    first_s = time.perf_counter() - t0
    backend = smap._backend
    sync = backend.ops.synchronize
    settings = smap.render_settings()
    cycle, stages = [], {k: [] for k in ("prepare", "update", "render")}
    for i in range(1, frames + warmup + 1):
        cam, lab = cams[i], labels[i]
        sync()
        t_start = time.perf_counter()
        smap.observe(cam, lab)
        t_cycle = time.perf_counter() - t_start
        # the stages one by one, a second pass at the same pose (the map receives the frame twice)
        inputs = smap._frame_labels(cam, lab, None)
        t = [time.perf_counter()]
        frame = backend.prepare(cam)
        sync()
        t.append(time.perf_counter())
        backend.update(frame, inputs, smap._concentrations).get()
        sync()
        t.append(time.perf_counter())
        backend.render_view(frame, smap._concentrations, settings)  # moments, render, U, the one copy
        t.append(time.perf_counter())
        if i > warmup:
            cycle.append(t_cycle)
            for k, (a, b) in zip(stages, zip(t[:-1], t[1:])):
                stages[k].append(b - a)
    query = []
    for cam in cams[warmup + 1:]:
        t0 = time.perf_counter()
        smap.render(cam)
        query.append(time.perf_counter() - t0)
    result = dict(cfg, build_s=build_s, first_frame_s=first_s, visible=int(backend.prepare(cams[-1]).num_pairs),
                  cycle_ms=1e3 * statistics.median(cycle), fps=1.0 / statistics.median(cycle),
                  query_ms=1e3 * statistics.median(query), query_fps=1.0 / statistics.median(query),
                  stages_ms={k: 1e3 * statistics.median(v) for k, v in stages.items()})
    if candidates:
        from css_ros.demo.trajectory import robot_trajectory

        if cfg.get("ply"):
            cand = [c.scaled(cand_w / c.width) for c in cams] * (candidates // len(cams) + 1)
        else:
            K = intrinsics(cfg["width"], cfg["height"], cfg["kitti"])
            from css_ros import Camera

            cand = [Camera(K, cfg["width"], cfg["height"], T).scaled(cand_w / cfg["width"])
                    for T in robot_trajectory(candidates, seed=1).T_map_cam]
        cand = cand[:candidates]
        smap.score_views(cand)  # compiles the batched kernels
        times = []
        for _ in range(max(5, frames // 4)):
            t0 = time.perf_counter()
            smap.score_views(cand)
            times.append(time.perf_counter() - t0)
        result["score_ms"] = 1e3 * statistics.median(times)
        result["candidates"] = len(cand)
        result["candidate_size"] = f"{cand[0].width}x{cand[0].height}"
    result.update(gpu_memory())
    result.update(gsplat_anchor(model, gt, cams[warmup + 1:], C, cfg["width"], cfg["height"]))
    result.update(paper_estimate(model, C, cams[1], labels[1], cand if candidates else None))
    result.update(host_time(model, cams, C, cfg, max(frames, 50)))
    result["peak_rss_mib"] = peak_rss_mib()
    return result


def host_time(model, cams: list, num_classes: int, cfg: dict, frames: int) -> dict:
    """The host's own work per observe and per query render with the stub device of benchmarks/cuda_host.py
    (uint8 labels, as a mono8 segmentation arrives): ms, launches and synchronisations per frame."""
    from cuda_host import measure

    rng = np.random.default_rng(0)
    labels = [rng.integers(0, num_classes, (cfg["height"], cfg["width"])).astype(np.uint8) for _ in cams[:8]]
    r = measure(model, cams[:8], labels, num_classes, frames)
    return {"host_" + k: v for k, v in r.items()}


def paper_estimate(model, num_classes: int, cam, labels, candidates) -> dict:
    """The cost model's expected ms (docs/cuda.md, benchmarks/cuda_estimate.py) for the first timed pose and the
    candidate batch, counted with the CPU engine, to print beside the measured times."""
    from css_ros.engine.cpu.projection import GaussianGeometry
    from css_ros.engine.cuda.cost_model import bench_stages, frame_counts, observe_costs, score_costs

    geometry = GaussianGeometry.from_model(model)
    lab = np.asarray(labels).astype(np.int64)
    lab[lab >= num_classes] = -1
    stages = bench_stages(observe_costs(frame_counts(geometry, [cam], num_classes, [lab])))
    out = {"paper_stages_ms": stages, "paper_cycle_ms": sum(stages.values())}
    if candidates:
        out["paper_score_ms"] = sum(c.ms for c in score_costs(frame_counts(geometry, list(candidates), num_classes)))
    return out


def gsplat_anchor(model, gt: np.ndarray, cams: list, num_classes: int, width: int, height: int) -> dict:
    """gsplat's C-channel render on the same scene and cameras, in the same process (an optional dependency: {} when
    gsplat is not importable or there is no GPU). Median ms of ``forward`` (a render of per-Gaussian C-vectors: what
    a query render computes) and ``forward+backward`` (the gradient w.r.t. the per-Gaussian features is the
    kappa-weighted sum of the pixels' one-hot labels: one observe's update, after its render), each synchronised."""
    try:
        import torch
        from gsplat import rasterization
    except ImportError:
        return {}
    if not torch.cuda.is_available():
        return {}
    dev = torch.device("cuda")
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32, device=dev)  # noqa: E731
    means, quats, scales, opac = t(model.means), t(model.quats_wxyz), t(model.scales), t(model.opacities)
    features = torch.nn.functional.one_hot(torch.as_tensor(gt % num_classes, device=dev).long(),
                                           num_classes).float()

    def views(cam):
        return t(cam.world_to_cam)[None], t(cam.K)[None]

    def forward(cam, feats):
        vm, k = views(cam)
        return rasterization(means, quats, scales, opac, feats, vm, k, width, height, packed=False)[0]

    def forward_backward(cam, target):
        feats = torch.zeros_like(features, requires_grad=True)
        (forward(cam, feats) * target).sum().backward()

    def timed(fn, *a) -> float:
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn(*a)
        torch.cuda.synchronize()
        return 1e3 * (time.perf_counter() - t0)

    targets = [torch.nn.functional.one_hot(forward(c, features)[0].argmax(-1), num_classes).float()[None]
               for c in cams]
    forward(cams[0], features)            # gsplat's first call builds / loads its CUDA extension
    forward_backward(cams[0], targets[0])
    fwd = [timed(forward, c, features) for c in cams]
    fwd_bwd = [timed(forward_backward, c, y) for c, y in zip(cams, targets)]
    import gsplat

    return dict(gsplat_version=getattr(gsplat, "__version__", "?"), gsplat_fwd_ms=statistics.median(fwd),
                gsplat_fwd_bwd_ms=statistics.median(fwd_bwd))


def gpu_memory_reset() -> None:
    try:
        import torch

        if torch.cuda.is_available():
            torch.cuda.synchronize()
            torch.cuda.empty_cache()
            torch.cuda.reset_peak_memory_stats()
    except ImportError:
        pass


def gpu_memory() -> dict:
    """Peak device memory of this process since the reset after the ground-truth render (the backend
    allocates every device array through torch), MiB; NaN in the simulator."""
    try:
        import torch

        if torch.cuda.is_available():
            return dict(gpu_peak_alloc_mib=torch.cuda.max_memory_allocated() / 2**20,
                        gpu_peak_reserved_mib=torch.cuda.max_memory_reserved() / 2**20,
                        device_name=torch.cuda.get_device_name())
    except ImportError:
        pass
    return dict(gpu_peak_alloc_mib=float("nan"), gpu_peak_reserved_mib=float("nan"), device_name="simulator")


CUDA_TARGETS_MS = {"100k": 2.5, "1M": 5.5, "3M": 18.0}


def print_host_table(results: list[dict]) -> None:
    """The host's own time per frame (stub device) of every scene that measured it."""
    hosted = [r for r in results if "host_observe_ms" in r]
    if hosted:
        print()
        print("host time per frame (stub device: the backend's Python with no kernel run; target <= 0.5 ms per "
              "observe at 1M):")
        for r in hosted:
            print(f"{r['name']:>7}: observe {r['host_observe_ms']:.3f} ms (p90 {r['host_observe_p90_ms']:.3f}), query "
                  f"{r['host_query_ms']:.3f} ms; per observe {r['host_launches_per_observe']:.0f} launches, "
                  f"{r['host_syncs_per_observe']:.0f} synchronisation, {r['host_array_ops_per_observe']:.0f} array ops")


def print_cuda_table(results: list[dict]) -> None:
    if all("cycle_ms" not in r for r in results):
        print_host_table(results)
        return
    print()
    print(f"{'scene':>7} {'Gaussians':>9} {'res':>10} {'C':>3} {'pairs':>8} {'cycle ms':>8} {'paper':>6} "
          f"{'target':>6} {'query ms':>8} {'peak GPU MiB':>12} {'score ms':>12}")
    for r in results:
        target = CUDA_TARGETS_MS.get(r["name"])
        print(f"{r['name']:>7} {r['gaussians']:>9} {r['width']}x{r['height']:<5} {r['classes']:>3} {r['visible']:>8} "
              f"{r['cycle_ms']:>8.2f} {r.get('paper_cycle_ms', float('nan')):>6.2f} "
              f"{'' if target is None else f'<={target:g}':>6} {r['query_ms']:>8.2f} "
              f"{r['gpu_peak_alloc_mib']:>12.0f} {r.get('score_ms', float('nan')):>12.2f}")
    print()
    print("per-stage median ms, measured / on paper (cost_model.py; prepare = project + sort + bin; render includes "
          "the moments, the final form, U and the one copy):")
    for r in results:
        paper = r.get("paper_stages_ms", {})
        print(f"{r['name']:>7}: " + "  ".join(f"{k}={v:.2f}/{paper.get(k, float('nan')):.2f}"
                                              for k, v in r["stages_ms"].items())
              + f"   | first frame (kernel compile) {r['first_frame_s']:.2f} s, device {r['device_name']}")
    anchored = [r for r in results if "gsplat_fwd_ms" in r]
    if anchored:
        print()
        print(f"gsplat {anchored[0]['gsplat_version']} on the same scenes and cameras, same run (C-channel render; "
              "targets: observe <= 1.0 x forward+backward, query <= 1.5 x forward):")
        print(f"{'scene':>7} {'observe':>8} {'gsplat f+b':>10} {'ratio':>6} {'query':>8} {'gsplat fwd':>10} {'ratio':>6}")
        for r in anchored:
            print(f"{r['name']:>7} {r['cycle_ms']:>8.2f} {r['gsplat_fwd_bwd_ms']:>10.2f} "
                  f"{r['cycle_ms'] / r['gsplat_fwd_bwd_ms']:>6.2f} {r['query_ms']:>8.2f} {r['gsplat_fwd_ms']:>10.2f} "
                  f"{r['query_ms'] / r['gsplat_fwd_ms']:>6.2f}")
    print_host_table(results)
    for r in results:
        if "score_ms" in r:
            print(f"score_views: {r['candidates']} views at {r['candidate_size']} on {r['name']}: "
                  f"{r['score_ms']:.2f} ms, {r.get('paper_score_ms', float('nan')):.2f} ms on paper "
                  "(target <= 15 ms on 1M)")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", choices=sorted(SCENES), action="append",
                   help="scene(s) to run (default: the backend's list; biker scenes when the file exists)")
    p.add_argument("--backend", choices=("numba", "cuda"), default="numba")
    p.add_argument("--simulate", action="store_true",
                   help="with --backend cuda: run the tiny scene under the numba-cuda simulator (no GPU; checks "
                        "the code path, timings meaningless)")
    p.add_argument("--stub-device", action="store_true",
                   help="with --backend cuda: only the host's own time per observe and query render, measured on "
                        "the CPU with a stub device (benchmarks/cuda_host.py; no GPU needed)")
    p.add_argument("--gaussians", type=int, help="custom scene: number of Gaussians")
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--classes", type=int, default=20)
    p.add_argument("--sh-degree", type=int, default=3, choices=(0, 1, 2, 3),
                   help="SH degree of the scene's colours (default 3, as trained 3DGS models)")
    p.add_argument("--frames", type=int, default=20, help="timed frames (after warm-up)")
    p.add_argument("--warmup", type=int, default=3)
    p.add_argument("--no-candidates", action="store_true", help="skip the 16-candidate batch on the 500k scene")
    p.add_argument("--no-torch", action="store_true", help="skip the PyTorch-path comparison on the 500k scene")
    p.add_argument("--json", type=Path, help="also write the results as JSON here")
    p.add_argument("--sensor-model", choices=("none", "weights", "symmetric", "confusion"), default="none",
                   help="update with a synthetic sensor model: 0.5 m depth bins, random weights; 'symmetric' adds "
                        "css_calibrate's default votes (p on the label, the rest evenly), 'confusion' dense random "
                        "confusion rows (the worst case) (default none: the paper's update)")
    p.add_argument("--_child", help=argparse.SUPPRESS)
    args = p.parse_args(argv)

    if args._child:
        cfg = json.loads(args._child)
        if cfg.pop("backend", "numba") == "cuda":
            cand_w = cfg.pop("candidate_width", 160)
            res = run_scene_cuda(cfg, args.frames, args.warmup, cfg.pop("candidates", 0), cand_w, cand_w * 3 // 4)
            print("RESULT " + json.dumps(res))
            return 0
        res = run_scene(cfg, args.frames, args.warmup, cfg.pop("candidates", 0), 160, 120, cfg.pop("torch_frames", 0))
        print("RESULT " + json.dumps(res))
        return 0

    if args.gaussians:
        jobs = {"custom": dict(gaussians=args.gaussians, width=args.width, height=args.height,
                               classes=args.classes, kitti=False)}
    else:
        names = args.scene or (["tiny"] if args.simulate else DEFAULT_SCENES[args.backend])
        names = [n for n in names if not SCENES[n].get("ply") or BIKER_PLY.exists()]
        jobs = {k: dict(SCENES[k]) for k in names}
    env = dict(os.environ)
    if args.simulate or args.stub_device:
        env["NUMBA_ENABLE_CUDASIM"] = "1"   # the stub device needs numba.cuda importable, nothing more
    if args.simulate:
        args.frames, args.warmup = min(args.frames, 2), min(args.warmup, 1)
    results = []
    for name, cfg in jobs.items():
        cfg = dict(cfg, name=name, sh_degree=args.sh_degree, backend=args.backend, sensor_model=args.sensor_model)
        if args.backend == "cuda" and args.stub_device:
            cfg["stub_device"] = True
        elif args.backend == "cuda":
            if name in ("1M", "tiny"):
                cfg["candidates"] = 0 if args.no_candidates else (8 if args.simulate else 256)
                if args.simulate:
                    cfg["candidate_width"] = cfg["width"]  # simulated threads are Python threads
        elif name == "500k":
            cfg["candidates"] = 0 if args.no_candidates else 16
            cfg["torch_frames"] = 0 if args.no_torch else 3
        print(f"[{name}] {cfg.get('keep', cfg['gaussians'])} Gaussians (SH degree {cfg['sh_degree']}), "
              f"{cfg['width']}x{cfg['height']}, {cfg['classes']} classes ...",
              flush=True)
        out = subprocess.run([sys.executable, __file__, "--frames", str(args.frames), "--warmup", str(args.warmup),
                              "--_child", json.dumps(cfg)], capture_output=True, text=True, env=env)
        lines = [ln for ln in out.stdout.splitlines() if ln.startswith("RESULT ")]
        if out.returncode != 0 or not lines:
            print(out.stdout, out.stderr, file=sys.stderr)
            return 1
        res = json.loads(lines[-1][7:])
        res["name"] = name
        results.append(res)
        if "fps" in res:
            print(f"    {res['fps']:.2f} frames/s, {res['query_fps']:.2f} views/s, peak {res['peak_rss_mib']:.0f} MiB",
                  flush=True)
    if args.backend == "cuda":
        print_cuda_table(results)
        if args.simulate:
            print("(simulator: numba-cuda runs each GPU thread as a Python thread; these timings mean nothing)")
    else:
        print_table(results)
    print(f"machine: {os.cpu_count()} cores, {cpu_model()}, numba threads {numba_threads()}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))
    return 0


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return "unknown CPU"


def numba_threads() -> int:
    import numba

    return numba.get_num_threads()


if __name__ == "__main__":
    sys.exit(main())
