"""The CUDA backend's output buffer: where the render kernel writes each requested plane of a view, and how the
host reads the one copy back as the view's images (no numba here; :mod:`.kernels` imports the plane indices).

One int32 buffer per frame: 16 header words (two float64 sums: sum log max(Var, floor) and sum E, for U_var and
U_exp; the pixel counts of the update before the render; the frame's pair and key counts), then the requested
planes packed in a fixed order, each (H, W) plane H W words (int32 labels, float32 E, Var, kappa_b, evidence,
depth [m], confidence), the colour (H, W, 3) uint8 in ceil(3 H W / 4) words, the probabilities (H, W, C) float32,
and last the update's (H', W') float32 surprise when that update made one (its own image size: the update before
the render). Only requested planes take space, so the copy moves only requested bytes.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..final_form import FrameImages, RenderSettings, uncertainty_from_sums

PL_LABELS, PL_E, PL_VAR, PL_BG, PL_EVIDENCE, PL_DEPTH, PL_CONFIDENCE, PL_RGB, PL_PROBS = range(9)
NUM_PLANES = 9
#: int32 words before the planes: two float64 U sums (words 0-3), an update's NUM_COUNTS int32 pixel counts
#: (words COUNT_WORDS.., see :class:`~css_ros.engine.cuda.backend.DeviceCounts`; an image has at most
#: MAX_CAMERA_PIXELS < 2^31 pixels), the frame's (pairs, keys) as int64 (words SIZE_WORDS..: a single-view plan's
#: frame learns there whether it fitted)
HEADER_WORDS = 16
COUNT_WORDS = 4
SIZE_WORDS = 12
#: image name -> (plane index, numpy dtype) of the (H, W) planes
_PLANES: dict[str, tuple[int, type]] = {
    "labels": (PL_LABELS, np.int32), "expectation": (PL_E, np.float32), "variance": (PL_VAR, np.float32),
    "background": (PL_BG, np.float32), "evidence": (PL_EVIDENCE, np.float32), "depth": (PL_DEPTH, np.float32),
    "confidence": (PL_CONFIDENCE, np.float32),
}


@dataclass(frozen=True)
class PlaneLayout:
    """Offsets of a frame's requested planes in the output buffer.

    Attributes:
        planes: (NUM_PLANES,) int64 offsets (-1: not requested): int32 / float32 element offsets, the colour's in
            bytes.
        words: the buffer's length in int32 words (header included): the bytes the one copy moves, / 4.
        surprise: word offset of the update's surprise image (-1: none), which the backend copies in, not the
            render kernel.
    """

    planes: np.ndarray
    words: int
    surprise: int = -1

    def images(self, host: np.ndarray, height: int, width: int, num_classes: int) -> FrameImages:
        """The view's images as numpy views into ``host`` (the copied words), U from the header."""
        sums = host[:HEADER_WORDS].view(np.float64)
        u_var, u_exp = uncertainty_from_sums(float(sums[0]), float(sums[1]), height * width)
        out = FrameImages(u_var=u_var, u_exp=u_exp)
        hw = height * width
        for name, (idx, dtype) in _PLANES.items():
            off = int(self.planes[idx])
            if off >= 0:
                setattr(out, name, host[off:off + hw].view(dtype).reshape(height, width))
        off = int(self.planes[PL_RGB])
        if off >= 0:
            out.rgb = host.view(np.uint8)[off:off + 3 * hw].reshape(height, width, 3)
        off = int(self.planes[PL_PROBS])
        if off >= 0:
            out.probabilities = host[off:off + hw * num_classes].view(np.float32).reshape(height, width, num_classes)
        return out


    def surprise_image(self, host: np.ndarray, shape: tuple[int, int]) -> np.ndarray | None:
        """The update's (H', W') float32 surprise as a view into ``host``, or None without one."""
        if self.surprise < 0:
            return None
        return host[self.surprise:self.surprise + shape[0] * shape[1]].view(np.float32).reshape(shape)


def plane_layout(height: int, width: int, num_classes: int, settings: RenderSettings,
                 surprise_pixels: int = 0) -> PlaneLayout:
    """The packed layout of the outputs ``settings`` asks for (planes in the order of ``_PLANES``, then colour and
    probabilities), then ``surprise_pixels`` words for an update's surprise image (0: none)."""
    hw = height * width
    planes = np.full(NUM_PLANES, -1, dtype=np.int64)
    words = HEADER_WORDS
    for name, (idx, _) in _PLANES.items():
        if settings.wants(name):
            planes[idx] = words
            words += hw
    if settings.wants("rgb"):
        planes[PL_RGB] = 4 * words
        words += -(-3 * hw // 4)
    if settings.probabilities:
        planes[PL_PROBS] = words
        words += hw * num_classes
    surprise = -1
    if surprise_pixels > 0:
        surprise = words
        words += int(surprise_pixels)
    return PlaneLayout(planes, words, surprise)
