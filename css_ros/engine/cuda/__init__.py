"""CUDA backend (numba-cuda kernels). Nothing here is imported unless ``backend="cuda"`` is asked
for; see docs/cuda.md."""
