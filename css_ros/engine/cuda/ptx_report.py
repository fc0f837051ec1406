"""What the GPU will pay for, read off the CUDA compiler without a GPU: every kernel of
:mod:`.kernels` compiled to PTX by numba-cuda and assembled by ``ptxas -v`` for sm_80 / sm_90;
registers, stack (local memory), spills and static shared memory per kernel, and the theoretical
occupancy those give (docs/cuda.md; test/test_cuda_ptx.py holds the budgets).

Run it in a fresh process (it must set ``NUMBA_FORCE_CUDA_CC`` before numba is imported)::

    python -m css_ros.engine.cuda.ptx_report --classes 20 40

Needs numba-cuda and CUDA's ``ptxas`` and ``libdevice`` (``/usr/local/cuda`` or ``CUDA_HOME``); no GPU,
no libnvrtc.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

#: Per-SM limits used for the occupancy (CUDA occupancy calculator, compute capability 8.0 / 9.0).
SM_LIMITS = {
    (8, 0): dict(regs=65536, smem=167936, threads=2048, blocks=32),   # A100: 164 KiB shared per SM
    (9, 0): dict(regs=65536, smem=233472, threads=2048, blocks=32),   # H100: 228 KiB shared per SM
}
REG_ALLOC_UNIT = 256         # registers are allocated per warp in units of 256
SMEM_ALLOC_UNIT = 128        # bytes
SMEM_RESERVED_PER_BLOCK = 1024  # bytes the driver reserves per block (cc >= 8.0)
#: Depth bins of the sensor-model update variant compiled here (the kernel's slot count is min(64, C B): 4 bins
#: give the full 64 slots from C = 16 up, the largest shared layout of the variant)
MODEL_BINS = 4


@dataclass
class KernelStats:
    """ptxas -v figures of one kernel for one architecture; ``threads`` is its launch block size."""

    name: str
    cc: tuple[int, int]
    threads: int
    registers: int
    stack: int
    spill_stores: int
    spill_loads: int
    shared: int

    @property
    def occupancy(self) -> float:
        """Theoretical occupancy: resident warps / the SM's maximum (64), from registers, shared
        memory, the block and thread limits."""
        lim = SM_LIMITS[self.cc]
        warps = -(-self.threads // 32)
        regs_per_block = warps * (-(-self.registers * 32 // REG_ALLOC_UNIT) * REG_ALLOC_UNIT)
        by_regs = lim["regs"] // max(regs_per_block, 1)
        smem = -(-self.shared // SMEM_ALLOC_UNIT) * SMEM_ALLOC_UNIT + SMEM_RESERVED_PER_BLOCK
        by_smem = lim["smem"] // smem
        by_threads = lim["threads"] // (warps * 32)
        blocks = min(by_regs, by_smem, by_threads, lim["blocks"])
        return blocks * warps / (lim["threads"] // 32)


def cuda_home() -> Path | None:
    """The CUDA toolkit with ptxas and libdevice (``CUDA_HOME``, else /usr/local/cuda), or None."""
    for root in (os.environ.get("CUDA_HOME"), os.environ.get("CUDA_PATH"), "/usr/local/cuda"):
        if root and (Path(root) / "bin" / "ptxas").is_file():
            return Path(root)
    found = shutil.which("ptxas")
    return Path(found).resolve().parents[1] if found else None


def _use_toolkit_libdevice(home: Path) -> None:
    """numba-cuda finds libdevice through libnvrtc's location; point it at the toolkit's file."""
    from numba.cuda.cudadrv import nvvm

    path = next(iter(sorted((home / "nvvm" / "libdevice").glob("libdevice*.bc"))), None)
    if path is None:
        raise FileNotFoundError(f"no libdevice*.bc under {home / 'nvvm' / 'libdevice'}")
    data = path.read_bytes()
    nvvm.get_libdevice = lambda: str(path)
    nvvm.open_libdevice = lambda: data


def kernel_signatures(num_classes: int, tile: int) -> list[tuple[str, Any, tuple, int]]:
    """(name, python function, numba argument types, block size) of every kernel, with the types the
    backend launches them with (C-contiguous device arrays; Python ints int64, floats float64); the launch bounds
    a kernel is compiled with are :func:`launch_bounds`'s."""
    from numba import boolean, float32, float64, int32, int64, uint8

    from . import kernels as k

    f64_2, f32_2, i32_2 = float64[:, ::1], float32[:, ::1], int32[:, ::1]
    i32_1, i64_1, f64_1, f32_1 = int32[::1], int64[::1], float64[::1], float32[::1]
    nt = tile * tile
    out = [
        ("project", k.project_kernel.py_func,
         (f64_2, f64_2, f64_1, f64_1, float32[:, :, ::1], f64_2, float64, float64, int64, boolean, int64, i64_1,
          f64_2, i32_2, i32_1, i32_1, i32_1, f32_2, f32_1), 256),
        ("emit_keys", k.emit_keys_kernel.py_func, (i32_2, i32_1, i64_1, i64_1, i64_1, int64, int64, int64, i32_1,
                                                   i32_1), 256),
        ("moments", k.moments_kernel.py_func, (f64_2, i32_1, i64_1, f32_2), 256),
    ]
    # the update reads the labels as the segmentation topic carries them (here uint8, mono8) and a float32 confidence;
    # then the changing world's arguments (transient mask, depth, tolerances, depth scale, pair rows, moments,
    # surprise); "_world" variants compile all of its rules in (measured depth, surprise, transient classes)
    update_args = (i64_1, i32_1, f64_2, i32_1, uint8[:, ::1], f32_2, boolean, int64, int64, f64_2, i32_1, i64_1,
                   boolean[::1], f32_2, float64, float64, float64, i32_1, f32_2, f32_2)
    for world, label in ((False, ""), (True, "_world")):
        out += [(f"update{label}_C{num_classes}",
                 k.make_update_kernel(num_classes, tile, False, 1, world, world, world).py_func, update_args, nt),
                (f"update_model{label}_C{num_classes}",
                 k.make_update_kernel(num_classes, tile, True, MODEL_BINS, world, world, world).py_func,
                 (*update_args, f64_1, f64_2), nt)]
    out.append(("apply_increments", k.apply_increments_kernel.py_func,
                (f64_2, i32_1, i64_1, f64_2, i32_1, float64, float64, f64_2), 256))
    render_sig = (i64_1, i32_1, f64_2, f32_2, i32_1, f32_2, f64_1, f64_2, i64_1, int64, int64, int64, int64,
                  i32_1, float32[::1], uint8[::1], f64_1, f64_2, f64_1, f64_1, f64_1)
    for score, probs, mass, label in ((False, False, False, "render"), (False, True, False, "render_probs"),
                                      (True, False, False, "score"), (True, False, True, "score_gain")):
        out.append((f"{label}_C{num_classes}",
                    k.make_render_kernel(num_classes, tile, score, probs, with_mass=mass).py_func, render_sig, nt))
    out += [("view_gain", k.view_gain_kernel.py_func, (f64_1, i32_1, i32_1, f64_2, f64_1, float64, f64_1), 256),
            ("observe_expected", k.observe_expected_kernel.py_func, (f64_1, i32_1, i32_1, int64, float64, f64_2),
             256)]
    return out


def launch_bounds(name: str, tile: int) -> tuple[int, int] | None:
    """The launch bounds the backend compiles kernel ``name`` with (the update variants with the changing world's
    rules: :func:`~css_ros.engine.cuda.kernels.update_launch_bounds`), else None."""
    from . import kernels as k

    return k.update_launch_bounds(tile) if name.startswith(("update_world", "update_model_world")) else None


_REGS = re.compile(r"Used (\d+) registers")
_STACK = re.compile(r"(\d+) bytes stack frame, (\d+) bytes spill stores, (\d+) bytes spill loads")
_SMEM = re.compile(r"(\d+) bytes smem")


def assemble(ptx: str, cc: tuple[int, int], home: Path) -> tuple[int, int, int, int, int]:
    """(registers, stack, spill stores, spill loads, static shared bytes) from ``ptxas -v``."""
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "k.ptx"
        src.write_text(ptx)
        res = subprocess.run([str(home / "bin" / "ptxas"), "-v", f"-arch=sm_{cc[0]}{cc[1]}", str(src),
                              "-o", str(Path(tmp) / "k.cubin")], capture_output=True, text=True, timeout=300)
    if res.returncode != 0:
        raise RuntimeError(f"ptxas failed for sm_{cc[0]}{cc[1]}: {res.stderr.strip()[-2000:]}")
    log = res.stdout + res.stderr
    regs, stack, smem = _REGS.search(log), _STACK.search(log), _SMEM.search(log)
    if regs is None or stack is None:
        raise RuntimeError(f"unexpected ptxas -v output: {log[-2000:]}")
    return (int(regs.group(1)), int(stack.group(1)), int(stack.group(2)), int(stack.group(3)),
            int(smem.group(1)) if smem else 0)


def report(classes: list[int], ccs: list[tuple[int, int]], tile: int) -> list[KernelStats]:
    """Compile and assemble every kernel for every C in ``classes`` and architecture in ``ccs``."""
    home = cuda_home()
    if home is None:
        raise FileNotFoundError("CUDA's ptxas was not found (set CUDA_HOME)")
    _use_toolkit_libdevice(home)
    from numba import cuda
    from numba.cuda import config

    stats: list[KernelStats] = []
    seen: set[tuple[str, tuple[int, int]]] = set()
    for num_classes in classes:
        for name, func, sig, threads in kernel_signatures(num_classes, tile):
            for cc in ccs:
                if (name, cc) in seen:
                    continue
                seen.add((name, cc))
                config.FORCE_CUDA_CC = cc  # type: ignore[attr-defined]  # without libnvrtc: the target
                ptx, _ = cuda.compile_ptx(func, sig, cc=cc,  # type: ignore[call-arg]  # numba-cuda >= 0.20
                                          launch_bounds=launch_bounds(name, tile))
                stats.append(KernelStats(name, cc, threads, *assemble(ptx, cc, home)))
    return stats


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m css_ros.engine.cuda.ptx_report", description=__doc__.split("\n\n")[0])
    parser.add_argument("--classes", type=int, nargs="+", default=[20], help="C values to compile (default 20)")
    parser.add_argument("--cc", nargs="+", default=["8.0", "9.0"], help="compute capabilities (default 8.0 9.0)")
    parser.add_argument("--tile", type=int, default=8, help="tile edge [px] (default 8)")
    parser.add_argument("--json", action="store_true", help="one JSON object per kernel and architecture")
    args = parser.parse_args(argv)
    ccs = [tuple(int(x) for x in c.split(".")) for c in args.cc]
    try:
        rows = report(args.classes, ccs, args.tile)  # type: ignore[arg-type]
    except (FileNotFoundError, RuntimeError, ImportError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.json:
        for s in rows:
            print(json.dumps(dict(asdict(s), occupancy=s.occupancy)))
        return 0
    print("| kernel | sm | threads | registers | stack B | spills B | static shared B | occupancy |")
    print("|---|---|---|---|---|---|---|---|")
    for s in rows:
        print(f"| {s.name} | {s.cc[0]}{s.cc[1]} | {s.threads} | {s.registers} | {s.stack} | "
              f"{s.spill_stores + s.spill_loads} | {s.shared} | {s.occupancy:.0%} |")
    return 0


if __name__ == "__main__":
    os.environ.setdefault("NUMBA_FORCE_CUDA_CC", "9.0")
    sys.exit(main())
