"""Time ``css_map transfer``'s engine call: a map on the demo room moved to a retrained variant of it.

The room has N Gaussians (default 1M); the variant splits 30 %, prunes 10 %, jitters every centre by 1 cm and
shuffles (test/retrain.py), so the new splat has 1.2 N. The old map holds random evidence on 80 % of the
Gaussians (fusing frames on 1M Gaussians would dominate the run and does not change the transfer's work).
Prints the seconds of the transfer (after one small warm-up call compiling the kernels) and the machine.

    python benchmarks/bench_transfer.py [--gaussians 1000000] [--classes 19]
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))
from retrain import retrained_variant  # noqa: E402

from css_ros.demo.scene import build_indoor_scene  # noqa: E402
from css_ros.engine.transfer import transfer_concentrations  # noqa: E402


def _cpu() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--gaussians", type=int, default=1_000_000)
    p.add_argument("--classes", type=int, default=19)
    args = p.parse_args()
    import numba

    small, _ = build_indoor_scene(2000, seed=0)
    transfer_concentrations(small, np.full((2000, 3), 2.0), 1e-3, retrained_variant(small, seed=1))  # compile
    t0 = time.perf_counter()
    model, _ = build_indoor_scene(args.gaussians, seed=1)
    new = retrained_variant(model, seed=2)
    t_build = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    conc = np.full((model.num_gaussians, args.classes), 1e-3)
    seen = rng.random(model.num_gaussians) < 0.8
    conc[seen] += rng.gamma(0.5, 2.0, (int(seen.sum()), args.classes))
    t0 = time.perf_counter()
    out, report = transfer_concentrations(model, conc, 1e-3, new)
    dt = time.perf_counter() - t0
    print(f"transfer {model.num_gaussians} -> {new.num_gaussians} Gaussians, C={args.classes}: {dt:.1f} s "
          f"(evidence ratio {report.ratio:.4f}; scenes built in {t_build:.1f} s)")
    print(f"machine: {_cpu()}, {os.cpu_count()} CPUs visible, numba threads {numba.get_num_threads()}")


if __name__ == "__main__":
    main()
