"""Where one observed frame's time goes on the CPU: each stage of ``SemanticMap.observe`` and the parts of the update,
as CPU seconds of the process (``time.process_time``), so that other work on a shared machine inflates them far less
than wall-clock times.

    NUMBA_NUM_THREADS=1 python benchmarks/profile_frame.py --scene 500k --scene biker-close
    NUMBA_NUM_THREADS=2 python benchmarks/profile_frame.py --scene biker      # + the threading layer's share

Rows (median over the frames, milliseconds of CPU time):
- ``observe``: the whole default observe (every default output: all images but the surprise);
- ``project``, ``bin``: stage 1 (projection with SH colour, tile lists);
- ``walk only``: compositing every pixel's list and nothing else (``kappa_lists``' counting pass, one thread);
- ``update``: the update as observe runs it (walk of the labelled pixels, the votes into the tile accumulators, their
  flush, the contribution store), then ``update - store`` without the store and ``+ surprise`` what asking for the
  surprise image adds;
- ``add + moments``: the increments into the map and the render's attribute rows, in observe's single pass
  (``add`` and ``moments`` apart for comparison);
- ``render replay`` / ``render walk``: the render with the update's stored contributions / compositing again;
- ``finalize``: the requested images in their final dtypes and U_var, U_exp.
Scenes and cameras are bench_frame.py's. With 2 threads, a stage's CPU time above its 1-thread figure is what the
threads cost (waiting at the parallel regions' ends, the threading layer).
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

ROWS = ("observe", "project", "bin", "walk only", "update", "update - store", "+ surprise", "add",
        "moments", "add + moments", "render replay", "render walk", "finalize")


def profile(scene: str, frames: int) -> dict[str, float]:
    """Median CPU milliseconds per row of :data:`ROWS` over ``frames`` frames of ``scene``."""
    import bench_frame as bf
    from css_ros import SemanticMap
    from css_ros.engine.cpu import raster
    from css_ros.engine.cpu.increments import UpdateWorkspace, add_increments
    from css_ros.engine.cpu.finalize import finalize
    from css_ros.engine.cpu.projection import ProjectionScratch, project

    cfg = dict(bf.SCENES[scene])
    model, gt, cams = bf.build_scene(cfg, frames + 2)
    c = cfg["classes"]
    labels = bf.truth_labels(model, gt, c, cams)
    smap = SemanticMap(model, c)
    backend = smap._backend
    settings = smap.render_settings()
    e_bg, v_bg, s_bg = smap._background_moments()
    ws, store = UpdateWorkspace(), raster.ContributionStore()
    conc = np.empty_like(smap.concentrations)  # one buffer: a fresh copy per frame would page-fault
    scratch = ProjectionScratch()  # kept between frames, as observe keeps its own (fresh ones page-fault)
    times: dict[str, list[float]] = {k: [] for k in ROWS}
    for i in range(frames + 2):
        cam, lab = cams[i], labels[i]
        np.copyto(conc, smap.concentrations)  # the stages below start from the map observe starts from (untimed)
        clock = [time.process_time()]
        smap.observe(cam, lab)
        clock.append(time.process_time())
        proj = project(backend.geometry, cam, scratch)
        clock.append(time.process_time())
        bins = raster.bin_tiles(proj, cam.width, cam.height)
        clock.append(time.process_time())
        raster._kappa_kernel(bins.offsets, bins.lists, proj.walk, cam.width, cam.height, bins.tile_size,
                             bins.tiles_x, True, np.empty(0, np.int64), np.empty(0, np.int32), np.empty(0),
                             np.empty(0))
        clock.append(time.process_time())
        plain = smap._frame_labels(cam, lab, None)
        surprising = smap._frame_labels(cam, lab, None, None, True)
        for inputs, kept in ((plain, store), (plain, None), (surprising, store)):
            inc, _, _ = raster.accumulate_update(proj, bins, inputs, None, ws, kept, conc)
            clock.append(time.process_time())
            add_increments(conc, proj.ids, inc)  # untimed: leaves the workspace zero
            ws.done()
            clock.append(time.process_time())
        add_s = clock[-1] - clock[-2]   # the last add_increments, timed as "add"
        attrs = raster.dirichlet_attributes(conc, proj.ids, proj.colors, proj.packed)
        clock.append(time.process_time())
        inc, _, _ = raster.accumulate_update(proj, bins, plain, None, ws, store, conc)
        t0 = time.process_time()
        raster.add_increments_and_attributes(conc, proj.ids, inc, 1.0, 1.0, proj.colors, proj.packed)
        ws.done()
        fused_s = time.process_time() - t0
        t0 = time.process_time()
        buf = raster.render_semantic(proj, bins, cam.width, cam.height, attrs, e_bg, v_bg, s_bg, np.zeros(3),
                                     False, store=store)
        replay_s = time.process_time() - t0
        t0 = time.process_time()
        raster.render_semantic(proj, bins, cam.width, cam.height, attrs, e_bg, v_bg, s_bg, np.zeros(3), False)
        walk_s = time.process_time() - t0
        t0 = time.process_time()
        finalize(buf, settings)
        final_s = time.process_time() - t0
        if i < 2:
            continue   # compiling / loading the caches, first page faults
        d = np.diff(clock)
        full_s, no_store_s, surprise_s = d[4], d[6], d[8]
        row = (d[0], d[1], d[2], d[3], full_s, full_s - no_store_s, surprise_s - full_s, add_s, d[10],
               fused_s, replay_s, walk_s, final_s)
        for k, v in zip(ROWS, row):
            times[k].append(v)
    return {k: 1e3 * statistics.median(v) for k, v in times.items()}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", action="append", help="bench_frame.py scene(s) (default: biker, biker-close, 500k)")
    p.add_argument("--frames", type=int, default=6, help="frames profiled (after two warm-up frames)")
    args = p.parse_args(argv)
    import numba

    scenes = args.scene or ["biker", "biker-close", "500k"]
    results = {s: profile(s, args.frames) for s in scenes}
    print(f"CPU ms per frame, median of {args.frames}, numba threads {numba.get_num_threads()}")
    print(f"| stage | {' | '.join(scenes)} |")
    print(f"|---|{'---|' * len(scenes)}")
    for k in ROWS:
        label = k if k not in ("update - store", "update - surprise") else f"of which {k.split(' - ')[1]}"
        print(f"| {label} | {' | '.join(f'{results[s][k]:.1f}' for s in scenes)} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
