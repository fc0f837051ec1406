"""ROS-free export of the semantic map in 3D (SPEC §9): splat PLYs, point clouds, bird's-eye pictures.

Modules: :mod:`.colormap` (colours), :mod:`.plys` (PLY writers), :mod:`.birdseye` (top-down render),
:mod:`.files` (atomic writes), :mod:`.cli` (the ``css_export`` command). See docs/map3d.md.
"""
from __future__ import annotations

from .birdseye import BirdseyeView, render_birdseye
from .colormap import UNKNOWN_RGB, UncertaintyColors, class_colors, uncertainty_colors, write_colorbar
from .plys import semantic_splat_model, write_point_cloud, write_semantic_splat, write_uncertainty_splat

__all__ = ["BirdseyeView", "UNKNOWN_RGB", "UncertaintyColors", "class_colors", "render_birdseye",
           "semantic_splat_model", "uncertainty_colors", "write_colorbar", "write_point_cloud",
           "write_semantic_splat", "write_uncertainty_splat"]
