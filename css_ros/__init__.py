"""css_ros: Continuous Semantic Splatting — a probabilistic semantic map on a pretrained 3D Gaussian Splatting model.

The package root re-exports the public engine API and the error tree, nothing else.
"""
from __future__ import annotations

from .engine.camera import Camera, body_to_optical_rotation, intrinsics_from_fov
from .engine.classes import ClassSet
from .engine.gaussians import GaussianModel
from .engine.final_form import image_uncertainty
from .engine.semantic_map import RenderedView, SemanticMap, UpdateStats
from .errors import BagError, CameraError, ConfigError, CssError, InputError, MapError, ModelError

__all__ = [
    "BagError",
    "Camera",
    "CameraError",
    "ClassSet",
    "ConfigError",
    "CssError",
    "GaussianModel",
    "InputError",
    "MapError",
    "ModelError",
    "RenderedView",
    "SemanticMap",
    "UpdateStats",
    "body_to_optical_rotation",
    "image_uncertainty",
    "intrinsics_from_fov",
]
__version__ = "0.1.0"
