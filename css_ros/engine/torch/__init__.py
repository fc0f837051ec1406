"""The plain PyTorch twin of the rasteriser (imports only the SPEC constants, never numba code)."""
