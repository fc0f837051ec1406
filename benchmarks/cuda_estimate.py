"""Expected milliseconds of the CUDA backend per kernel, on paper, for the GPU target table.

No GPU needed: the sizes that drive every kernel (kept Gaussians, tile-list keys, alpha evaluations,
contributions, the update's atomics) are measured on the real benchmark scenes with the CPU engine
(same culls, same 8 x 8 tile lists), then priced by css_ros/engine/cuda/cost_model.py (bytes and
instructions per item, H100 SXM peak rates with the efficiencies it states).

    python benchmarks/cuda_estimate.py                       # 100k, 1M, 3M, biker, biker8, 256 candidates on 1M
    python benchmarks/cuda_estimate.py --scene 100k --json out.json

When a GPU is lent, ``bench_frame.py --backend cuda`` measures the same cycles; docs/cuda.md sets the two
side by side.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_frame import SCENES, build_scene, intrinsics  # noqa: E402

TARGETS_MS = {"100k": 2.5, "1M": 5.5, "3M": 18.0}   # observe-cycle targets of the GPU issue (H100)
CANDIDATE_TARGET_MS = 15.0                           # score_views of 256 views at 160x120 on 1M


def estimate_scene(name: str, candidates: int) -> dict:
    from css_ros import Camera, SemanticMap
    from css_ros.demo.trajectory import robot_trajectory
    from css_ros.engine.cuda.cost_model import frame_counts, observe_costs, score_costs

    cfg = SCENES[name]
    model, gt, cams = build_scene(cfg, 3)
    C = cfg["classes"]
    gt_map = SemanticMap(model, C)
    conc = gt_map.concentrations
    conc[...] = 1e-3
    conc[np.arange(model.num_gaussians), gt % C] = 1e3
    cam = cams[1]
    labels = gt_map.render(cam).labels.astype(int)
    labels[labels >= C] = -1
    geometry = gt_map._backend.geometry
    counts = frame_counts(geometry, [cam], C, [labels])
    costs = observe_costs(counts)
    out = dict(scene=name, counts=counts.__dict__, observe=[c.__dict__ for c in costs],
               observe_ms=sum(c.ms for c in costs), target_ms=TARGETS_MS.get(name))
    if candidates:
        K = intrinsics(160, 120, False)   # the target's 160 x 120 candidate views (75 deg horizontal FoV)
        views = [Camera(K, 160, 120, T) for T in robot_trajectory(candidates, seed=1).T_map_cam]
        ccounts = frame_counts(geometry, views, C)
        scosts = score_costs(ccounts)
        out.update(candidates=dict(views=len(views), size=f"{views[0].width}x{views[0].height}",
                                   counts=ccounts.__dict__, stages=[c.__dict__ for c in scosts],
                                   ms=sum(c.ms for c in scosts), target_ms=CANDIDATE_TARGET_MS))
    return out


def print_scene(r: dict) -> None:
    c = r["counts"]
    print(f"\n{r['scene']}: {c['gaussians']:,} Gaussians, {c['width']}x{c['height']}, C={c['classes']}, "
          f"SH K={c['sh_coeffs']}; kept {c['kept']:,}, keys {c['keys']:,}, alpha evaluations {c['walked']:,} "
          f"(upper bound), contributions {c['contributions']:,}, update atomics <= {c['label_sums']:,}")
    print(f"  {'stage':<18} {'MB':>8} {'Ginstr':>8} {'ms':>7}")
    for s in r["observe"]:
        print(f"  {s['stage']:<18} {s['bytes'] / 1e6:>8.1f} {s['instructions'] / 1e9:>8.2f} {s['ms']:>7.3f}")
    target = f" (target {r['target_ms']} ms)" if r.get("target_ms") else ""
    print(f"  observe cycle: {r['observe_ms']:.2f} ms expected{target}")
    if "candidates" in r:
        k = r["candidates"]
        print(f"  score_views of {k['views']} views at {k['size']}: {k['ms']:.2f} ms expected "
              f"(target {k['target_ms']} ms); keys {k['counts']['keys']:,}, contributions "
              f"{k['counts']['contributions']:,}")
        for s in k["stages"]:
            print(f"    {s['stage']:<16} {s['bytes'] / 1e6:>8.1f} MB {s['instructions'] / 1e9:>7.2f} Ginstr "
                  f"{s['ms']:>7.3f} ms")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", nargs="+", default=["100k", "1M", "3M", "biker", "biker8"],
                        choices=sorted(SCENES), help="scenes of bench_frame.py (default: the target table)")
    parser.add_argument("--candidates", type=int, default=256,
                        help="candidate views of 160 x 120 px scored on the 1M scene (default 256; 0 = none)")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args(argv)
    results = []
    for name in args.scene:
        r = estimate_scene(name, args.candidates if name == "1M" else 0)
        print_scene(r)
        results.append(r)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
