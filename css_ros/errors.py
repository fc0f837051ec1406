"""Exception types raised by the css_ros engine; callers catch these, not bare Exception."""
from __future__ import annotations


class CssError(Exception):
    """Base class of every error css_ros raises on purpose."""


class ModelError(CssError):
    """A splat model file is missing, malformed or holds invalid values."""


class CameraError(CssError):
    """Camera intrinsics or pose are invalid (non-finite, bad quaternion, bad size)."""


class MapError(CssError):
    """A semantic map cannot be built, saved or loaded (bad checkpoint, wrong model)."""


class InputError(CssError):
    """An input frame (image, segmentation, confidence) is malformed."""


class BagError(CssError):
    """A rosbag2 bag is missing, unreadable, lacks a topic or holds the wrong message type."""


class ConfigError(CssError):
    """A parameter, command-line option or configuration file holds an invalid value."""


class SensorModelError(CssError):
    """A sensor-model file is missing, malformed, holds invalid values or does not fit the map's classes."""
