"""The ROS-free CSS engine: splat model, cameras, Dirichlet semantic map and its backends.

Nothing here imports rclpy; numba is imported when the CPU backend is first used and torch only
when the torch backend is asked for.
"""
from __future__ import annotations

from .camera import Camera, body_to_optical_rotation, intrinsics_from_fov
from .classes import ClassSet
from .field3d import FieldIndex, FieldQuery, GaussianSemantics
from .gaussians import GaussianModel
from .final_form import image_uncertainty
from .semantic_map import RenderedView, SemanticMap, UpdateStats

__all__ = ["Camera", "ClassSet", "FieldIndex", "FieldQuery", "GaussianModel", "GaussianSemantics", "RenderedView",
           "SemanticMap", "UpdateStats",
           "body_to_optical_rotation", "image_uncertainty", "intrinsics_from_fov"]
