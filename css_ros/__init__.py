"""css_ros: Continuous Semantic Splatting — a probabilistic semantic map on a pretrained 3D Gaussian Splatting model."""
from __future__ import annotations

from .camera import Camera
from .classes import ClassSet
from .errors import CameraError, CssError, InputError, MapError, ModelError
from .gaussians import GaussianModel
from .semantic_map import RenderedView, SemanticMap, UpdateStats, image_uncertainty

__all__ = [
    "Camera",
    "CameraError",
    "ClassSet",
    "CssError",
    "GaussianModel",
    "InputError",
    "MapError",
    "ModelError",
    "RenderedView",
    "SemanticMap",
    "UpdateStats",
    "image_uncertainty",
]
__version__ = "0.1.0"
