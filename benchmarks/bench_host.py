"""Host time per frame of the GPU path after its device work, on the CPU, with arrays of the real sizes.

The CUDA backend's frame ends with one copy from the device; what the host does after it is plain numpy, so it is
timed here without a GPU. Two forms of that host work, per scene size (the bench_frame / GPU-table scenes):

- ``interleaved`` (the earlier form): one (H, W, 9) float32 buffer comes back; the host splits it into contiguous
  float64 planes, applies the unknown threshold, converts E / Var / kappa_b / evidence to float32, rounds and clips
  the colour to uint8, scales the depth, reduces U_var / U_exp, and (with a sensor model) evaluates the confidence
  map.
- ``final`` (the current form): the device wrote the requested planes in final dtypes and the U sums into a header;
  the host builds numpy views into the one copy (:class:`css_ros.engine.cuda.layout.PlaneLayout`).

The copy itself is not counted in either (a memcpy from device to page-locked memory on the GPU machine); the
bytes it moves are printed. With ``--node``, a second table times what css_node adds to a frame beyond the observe:
turning a view into its image messages (``~/semantic`` ids, ``~/semantic_color``, ``~/expectation``,
``~/variance``, ``~/rendered_image``, ``~/confidence``: io/outputs.frame_output_images + ros/conversions.image_msg).
Usage: ``python benchmarks/bench_host.py [--repeat 30] [--confidence] [--node]``.
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from css_ros.engine.cuda.layout import plane_layout
from css_ros.engine.final_form import IMAGE_OUTPUTS, RenderSettings, image_uncertainty, to_bytes
from css_ros.engine.sensor_model import ConfidenceMap

SCENES = {"100k": (320, 240, 20), "biker": (640, 480, 20), "1M": (1241, 376, 19), "3M": (1280, 720, 40)}
CMAP = ConfidenceMap(np.array([1.2, 0.3, -0.4]), np.array([0.0, 0.5, 1.0]), np.array([0.05, 0.6, 0.97]))


def interleaved_host(buf: np.ndarray, confidence: bool) -> tuple:
    """The earlier host work on one (H, W, 9) float32 download (label, E, Var, kappa_b, evidence, r, g, b, depth)."""
    f64 = lambda a: np.ascontiguousarray(a, dtype=np.float64)  # noqa: E731
    labels = np.ascontiguousarray(buf[..., 0], dtype=np.int32)
    e, var, bg, ev, rgb, depth = (f64(buf[..., 1]), f64(buf[..., 2]), f64(buf[..., 3]), f64(buf[..., 4]),
                                  f64(buf[..., 5:8]), f64(buf[..., 8]))
    labels[bg > 0.5] = 255
    u = image_uncertainty(e, var)
    out = (labels, e.astype(np.float32), var.astype(np.float32), bg.astype(np.float32), ev.astype(np.float32),
           to_bytes(rgb), (depth * 1.0).astype(np.float32), u)
    if confidence:
        conf = CMAP(e, ev)
        conf[labels == 255] = 0.0
        out += (conf,)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeat", type=int, default=30, help="timed repetitions per scene (median reported)")
    p.add_argument("--confidence", action="store_true", help="with a sensor model's confidence map")
    p.add_argument("--node", action="store_true", help="also time css_node's message conversions per frame")
    args = p.parse_args()
    rng = np.random.default_rng(0)
    print("| scene | pixels | interleaved host [ms] | final host [ms] | bytes copied: interleaved / final (all images)"
          " / final (labels only) |")
    print("|---|---|---|---|---|")
    for name, (w, h, c) in SCENES.items():
        buf = rng.random((h, w, 9), dtype=np.float32)
        buf[..., 0] = rng.integers(0, c, (h, w))
        settings = RenderSettings(0.05, 0.01, 0.02, (0, 0, 0), 0.5, 255, 1.0, CMAP if args.confidence else None,
                                  frozenset(IMAGE_OUTPUTS), False)
        layout = plane_layout(h, w, c, settings)
        words = rng.integers(0, 2 ** 20, layout.words, dtype=np.int64).astype(np.int32)
        only_labels = plane_layout(h, w, c, RenderSettings(0.05, 0.01, 0.02, (0, 0, 0), 0.5, 255, 1.0, None,
                                                           frozenset({"labels"}), False))
        old, new = [], []
        for _ in range(args.repeat):
            t = time.perf_counter()
            interleaved_host(buf, args.confidence)
            old.append(time.perf_counter() - t)
            t = time.perf_counter()
            layout.images(words, h, w, c)
            new.append(time.perf_counter() - t)
        print(f"| {name} | {w}x{h} | {1e3 * statistics.median(old):.2f} | {1e3 * statistics.median(new):.3f} | "
              f"{buf.nbytes / 1e6:.1f} MB / {4 * layout.words / 1e6:.1f} MB / {4 * only_labels.words / 1e6:.1f} MB |")
    if args.node:
        node_conversions(args.repeat, args.confidence)


def node_conversions(repeat: int, confidence: bool) -> None:
    """Median ms per frame of css_node's image messages from a view in final form, per scene size."""
    from css_ros import RenderedView
    from css_ros.engine.classes import ClassSet
    from css_ros.io.outputs import frame_output_images
    from css_ros.ros import conversions as rc

    rng = np.random.default_rng(1)
    print()
    print("| scene | pixels | css_node's image messages, all topics [ms] |")
    print("|---|---|---|")
    for name, (w, h, c) in SCENES.items():
        f32 = lambda h=h, w=w: rng.random((h, w), dtype=np.float32)  # noqa: E731
        view = RenderedView(rng.integers(0, c, (h, w)).astype(np.int32), f32(), f32(), f32(), f32(),
                            rng.integers(0, 256, (h, w, 3)).astype(np.uint8), 0.1, 0.5,
                            confidence=f32() if confidence else None)
        classes = ClassSet.default(c)
        header = rc.header_msg(123, "camera")
        times = []
        for _ in range(repeat):
            t = time.perf_counter()
            for array, encoding in frame_output_images(view, classes, 255).values():
                rc.image_msg(array, encoding, header)
            times.append(time.perf_counter() - t)
        print(f"| {name} | {w}x{h} | {1e3 * statistics.median(times):.2f} |")


if __name__ == "__main__":
    main()
