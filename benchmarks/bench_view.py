"""css_view at scale: load time and memory of a large map, cost and size of the live stream.

    python benchmarks/bench_view.py                      # 1M Gaussians, 16 classes; stream at 1M and 3M
    python benchmarks/bench_view.py --gaussians 500000 --browser   # also time the page in headless Chromium

Load: a synthetic model PLY and a map of N Gaussians are written to a temp folder, then timed as css_view
loads them (PLY + map + what the page draws). Stream: one ``~/view/semantics`` tick of the node
(:class:`css_ros.ros.view_publisher.ViewPublisher` minus the publish: per-Gaussian semantics, change keys,
diff against the last sent, packing at most ``view_max_changes``), after a frame changed 5 % of the Gaussians.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))

from css_ros.engine.field3d import gaussian_semantics  # noqa: E402
from css_ros.engine.gaussians import GaussianModel  # noqa: E402
from css_ros.engine.semantic_map import SemanticMap  # noqa: E402
from css_ros.io.view_stream import MODEL_CHUNK, changed_gaussians, semantic_keys, semantics_columns  # noqa: E402

MODEL_BYTES = 48       # ~/view/model per Gaussian
SEMANTIC_BYTES = 10    # ~/view/semantics per changed Gaussian
MAX_CHANGES = 262_144  # view_max_changes default


def synthetic(n: int, c: int, rng: np.random.Generator) -> tuple[GaussianModel, np.ndarray]:
    means = rng.uniform(-5, 5, (n, 3))
    model = GaussianModel.from_activated(means, rng.uniform(0.005, 0.05, (n, 3)),
                                         rng.normal(size=(n, 4)), rng.uniform(0.1, 0.99, n), rng.uniform(0, 1, (n, 3)))
    conc = np.full((n, c), 1e-3)
    seen = rng.random(n) < 0.7
    conc[seen, rng.integers(0, c, seen.sum())] += rng.uniform(0.5, 50, seen.sum())
    return model, conc


def rss_mib() -> float:
    """Current resident memory of this process [MiB]."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def bench_load(n: int, c: int, browser: bool) -> None:
    from css_ros.engine.classes import ClassSet
    from css_ros.view.data import build_view_data

    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        model, conc = synthetic(n, c, rng)
        model.to_ply(Path(tmp) / "model.ply")
        smap = SemanticMap(model, c)
        smap.concentrations = conc
        smap.save(Path(tmp) / "map.npz")
        del model, smap, conc
        import gc

        gc.collect()
        rss0 = rss_mib()
        t0 = time.perf_counter()
        model = GaussianModel.from_ply(Path(tmp) / "model.ply")
        smap = SemanticMap.load(Path(tmp) / "map.npz", model)
        data = build_view_data(smap, ClassSet.default(c))
        t_load = time.perf_counter() - t0
        print(f"load {n:,} Gaussians x {c} classes (PLY + map + page arrays): {t_load:.1f} s, "
              f"resident memory +{rss_mib() - rss0:.0f} MiB")
        if not browser:
            return
        from cdp_browser import Browser, free_port
        from css_ros.view.server import MapView

        t0 = time.perf_counter()
        view = MapView(data, port=free_port())
        t_serve = time.perf_counter() - t0
        clients = []
        view.server.on_client_connect(lambda cl: clients.append(cl))
        b = Browser(800, 500, timeout=300)
        try:
            t0 = time.perf_counter()
            b.goto(view.url)
            b.wait_for(lambda: clients, 120, "the page to connect")
            img = b.stable_screenshot(600, accept=lambda im: (np.abs(im.astype(int) - 255).sum(axis=2) > 60).mean() > 0.05)
            t_page = time.perf_counter() - t0
            heap = b.evaluate("performance.memory ? performance.memory.usedJSHeapSize : null")
            print(f"page: server set-up {t_serve:.1f} s; browser connect to a settled splat picture {t_page:.1f} s "
                  f"(headless Chromium, software WebGL); JS heap {heap / 2**20 if heap else float('nan'):.0f} MiB; "
                  f"{img.shape[1]}x{img.shape[0]} px")
        finally:
            b.close()
            view.stop()


def bench_stream(n: int, c: int) -> None:
    rng = np.random.default_rng(1)
    conc = np.full((n, c), 1e-3)
    seen = rng.random(n) < 0.7
    conc[seen, rng.integers(0, c, seen.sum())] += rng.uniform(0.5, 50, seen.sum())
    sem = gaussian_semantics(conc, 1e-3, 0.5, 255)
    sent = semantic_keys(sem.label, sem.expectation, sem.evidence)
    touched = rng.choice(n, n // 20, replace=False)      # a frame sees 5 % of the map
    conc[touched, 0] += 5.0
    changed_gaussians(np.ones((1, 1)), 1e-3, 0.5, 255, np.zeros(1, np.int64))  # compile
    times = []
    for _ in range(3):
        keys = sent.copy()
        t0 = time.perf_counter()
        changed = changed_gaussians(conc, 1e-3, 0.5, 255, keys)
        pending = max(0, len(changed) - MAX_CHANGES)
        changed = changed[:MAX_CHANGES]
        sub = gaussian_semantics(conc[changed], 1e-3, 0.5, 255)
        cols = semantics_columns(changed, sub.label, sub.expectation, sub.evidence)
        times.append(time.perf_counter() - t0)
    print(f"stream {n:,} Gaussians x {c} classes: tick {1e3 * np.median(times):.0f} ms (median of 3); "
          f"{len(changed) + pending:,} changed -> message of {len(changed):,} ({cols['data'].nbytes / 1e6:.2f} MB, "
          f"{pending:,} left for the next ticks); model once: {n * MODEL_BYTES / 1e6:.0f} MB in "
          f"{-(-n // MODEL_CHUNK)} messages; extra node memory {n * 8 / 2**20:.0f} MiB (keys last sent)")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--gaussians", type=int, default=1_000_000)
    p.add_argument("--classes", type=int, default=16)
    p.add_argument("--browser", action="store_true", help="also time the page in headless Chromium")
    args = p.parse_args()
    bench_load(args.gaussians, args.classes, args.browser)
    for n in sorted({args.gaussians, 3_000_000}):
        bench_stream(n, args.classes)


if __name__ == "__main__":
    main()
