"""Benchmark of candidate-view scoring: SemanticMap.score_views (U_var, U_exp, info_gain) against the U-only
scoring of earlier versions, and the greedy batch SemanticMap.select_views.

    python benchmarks/bench_scores.py                       # 500k Gaussians, 256 candidates at 160x120, k = 8
    python benchmarks/bench_scores.py --gaussians 100000 --candidates 64 --repeats 3

The map is the procedural indoor room (css_ros.demo.scene) with evidence on about 60 % of the Gaussians; the
candidates are poses along the demo robot trajectory, scaled to the candidate size. Prints the median wall time of
``--repeats`` calls of each (after one warm-up call that compiles / loads the kernels) and the ratio.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--gaussians", type=int, default=500_000)
    p.add_argument("--classes", type=int, default=28)
    p.add_argument("--candidates", type=int, default=256)
    p.add_argument("--width", type=int, default=160, help="candidate image width (height = 3/4 of it)")
    p.add_argument("--k", type=int, default=8, help="views of the greedy batch")
    p.add_argument("--repeats", type=int, default=5)
    args = p.parse_args(argv)

    from css_ros import Camera, SemanticMap
    from css_ros.demo.renderer import camera_k
    from css_ros.demo.scene import build_indoor_scene
    from css_ros.demo.trajectory import robot_trajectory

    t0 = time.perf_counter()
    model, gt = build_indoor_scene(args.gaussians, seed=0)
    rng = np.random.default_rng(0)
    smap = SemanticMap(model, args.classes)
    observed = rng.random(model.num_gaussians) < 0.6
    smap.concentrations[observed] += rng.gamma(0.5, 4.0, (int(observed.sum()), args.classes))
    w, h = args.width, args.width * 3 // 4
    traj = robot_trajectory(args.candidates, seed=1)
    cams = [Camera(camera_k(w, h), w, h, T) for T in traj.T_map_cam]
    print(f"{model.num_gaussians} Gaussians, C = {args.classes}, {len(cams)} candidates at {w}x{h} "
          f"(scene built in {time.perf_counter() - t0:.1f} s)", flush=True)

    backend = smap._backend
    e_b, v_b, s_b = smap._background_moments()

    def u_only() -> None:
        backend.score_views(cams, smap._concentrations, e_b, v_b, s_b)

    def with_gain() -> None:
        smap.score_views(cams)

    def batch() -> None:
        smap.select_views(cams, args.k)

    results = {}
    for name, fn in (("U_var + U_exp only (earlier score_views)", u_only), ("score_views with info_gain", with_gain),
                     (f"select_views, k = {args.k}", batch)):
        fn()  # warm-up
        times = []
        for _ in range(args.repeats):
            t = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t)
        results[name] = statistics.median(times)
        print(f"  {name}: {results[name]:.3f} s median of {args.repeats} "
              f"(min {min(times):.3f}, max {max(times):.3f})", flush=True)
    base, gain = list(results.values())[:2]
    print(f"info gain costs {100 * (gain / base - 1):+.1f} % over U-only scoring; machine: {os.cpu_count()} cores")
    return 0


if __name__ == "__main__":
    sys.exit(main())
