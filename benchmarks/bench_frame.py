"""Benchmark of the per-frame CSS cycle (SemanticMap.observe) and of query views.

Scenes are the procedural indoor room of css_ros.demo.scene (Gaussians on surfaces at realistic
sizes), viewed along the demo robot trajectory. Each scene runs in its own subprocess so the peak
resident memory reported is that scene's alone (model + map + buffers + interpreter).

    python benchmarks/bench_frame.py                   # the three scenes of the README + candidates + torch ratio
    python benchmarks/bench_frame.py --scene 100k      # one scene
    python benchmarks/bench_frame.py --gaussians 200000 --width 640 --height 480 --classes 28

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
}


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


def run_scene(cfg: dict, frames: int, warmup: int, candidates: int, cand_w: int, cand_h: int,
              torch_frames: int) -> dict:
    from css_ros import Camera, SemanticMap
    from css_ros.demo.scene import build_indoor_scene
    from css_ros.engine.cpu.projection import project
    from css_ros.engine.cpu.raster import (ContributionStore, accumulate_update, add_increments, bin_tiles,
                                dirichlet_attributes, render_semantic)
    from css_ros.engine.semantic_map import image_uncertainty
    from css_ros.demo.trajectory import robot_trajectory

    t0 = time.perf_counter()
    model, gt = build_indoor_scene(cfg["gaussians"], seed=0)
    model = with_view_dependent_colour(model, cfg.get("sh_degree", 3))
    build_s = time.perf_counter() - t0
    C = cfg["classes"]
    K = intrinsics(cfg["width"], cfg["height"], cfg["kitti"])
    traj = robot_trajectory(frames + warmup + 1, seed=0)
    cams = [Camera(K, cfg["width"], cfg["height"], T) for T in traj.T_map_cam]

    # segmentations: the ground truth rendered at each pose (outside the timings)
    gt_map = SemanticMap(model, C)
    gt_map.concentrations[...] = 1e-3
    gt_map.concentrations[np.arange(model.num_gaussians), gt % C] = 1e3
    labels = [gt_map.render(c).labels for c in cams]
    del gt_map

    smap = SemanticMap(model, C)
    t0 = time.perf_counter()
    smap.observe(cams[0], labels[0])  # compiles (or loads cached) numba kernels
    first_s = time.perf_counter() - t0

    store = ContributionStore()
    cycle, stages = [], {k: [] for k in ("project", "bin", "update", "moments", "render", "uncertainty")}
    backend = smap._backend
    for i in range(1, frames + warmup + 1):
        cam, lab = cams[i], labels[i]
        t_start = time.perf_counter()
        smap.observe(cam, lab)
        t_cycle = time.perf_counter() - t_start
        # the same stages, timed one by one (a second pass at the same pose, on a copy of the map)
        conc = smap.concentrations.copy()
        t = [time.perf_counter()]
        proj = project(backend.geometry, cam)
        t.append(time.perf_counter())
        bins = bin_tiles(proj, cam.width, cam.height)
        t.append(time.perf_counter())
        lab32, w32, _ = smap._prepare_labels(cam, lab, None)
        acc = accumulate_update(proj, bins, lab32, w32, C, store)
        add_increments(conc, proj.ids, acc)
        t.append(time.perf_counter())
        attrs = dirichlet_attributes(conc, proj.ids, proj.colors)
        t.append(time.perf_counter())
        buf = render_semantic(proj, bins, cam.width, cam.height, attrs, 1 / C, 0.0, 1.0,
                              np.zeros(3), False, store)
        t.append(time.perf_counter())
        image_uncertainty(buf.expectation, buf.variance)
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
    result = dict(cfg, build_s=build_s, first_frame_s=first_s,
                  visible=int(len(project(backend.geometry, cams[-1]).ids)),
                  cycle_ms=1e3 * statistics.median(cycle), fps=1.0 / statistics.median(cycle),
                  query_ms=1e3 * statistics.median(query), query_fps=1.0 / statistics.median(query),
                  stages_ms={k: 1e3 * statistics.median(v) for k, v in stages.items()})
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
    print("per-stage median ms of the observe cycle (update includes adding into the map; moments = E, Var per"
          " visible Gaussian; render replays the update's contributions):")
    for r in results:
        s = r["stages_ms"]
        print(f"{r['name']:>6}: " + "  ".join(f"{k}={v:.1f}" for k, v in s.items())
              + f"   | first frame (compile/cache load) {r['first_frame_s']:.2f} s, scene build {r['build_s']:.1f} s")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", choices=sorted(SCENES), action="append",
                   help="scene(s) to run (default: all three)")
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
    p.add_argument("--_child", help=argparse.SUPPRESS)
    args = p.parse_args(argv)

    if args._child:
        cfg = json.loads(args._child)
        res = run_scene(cfg, args.frames, args.warmup, cfg.pop("candidates", 0), 160, 120, cfg.pop("torch_frames", 0))
        print("RESULT " + json.dumps(res))
        return 0

    if args.gaussians:
        jobs = {"custom": dict(gaussians=args.gaussians, width=args.width, height=args.height,
                               classes=args.classes, kitti=False)}
    else:
        jobs = {k: dict(SCENES[k]) for k in (args.scene or list(SCENES))}
    results = []
    for name, cfg in jobs.items():
        cfg = dict(cfg, name=name, sh_degree=args.sh_degree)
        if name == "500k":
            cfg["candidates"] = 0 if args.no_candidates else 16
            cfg["torch_frames"] = 0 if args.no_torch else 3
        print(f"[{name}] {cfg['gaussians']} Gaussians (SH degree {cfg['sh_degree']}), {cfg['width']}x{cfg['height']}, {cfg['classes']} classes ...",
              flush=True)
        out = subprocess.run([sys.executable, __file__, "--frames", str(args.frames), "--warmup", str(args.warmup),
                              "--_child", json.dumps(cfg)], capture_output=True, text=True)
        lines = [ln for ln in out.stdout.splitlines() if ln.startswith("RESULT ")]
        if out.returncode != 0 or not lines:
            print(out.stdout, out.stderr, file=sys.stderr)
            return 1
        res = json.loads(lines[-1][7:])
        res["name"] = name
        results.append(res)
        print(f"    {res['fps']:.2f} frames/s, {res['query_fps']:.2f} views/s, peak {res['peak_rss_mib']:.0f} MiB",
              flush=True)
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
