"""The compiled CPU path (numba): projection, tile binning, compositing kernels and their backend."""
