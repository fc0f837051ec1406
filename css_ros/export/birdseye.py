"""A bird's-eye picture of the semantic map: the engine's label render from straight above, with a legend."""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..engine.camera import Camera
from ..engine.classes import ClassSet
from ..engine.semantic_map import SemanticMap
from ..engine.similarity import Similarity
from ..engine.spec import DEFAULT_MIN_EVIDENCE
from ..errors import MapError
from .files import atomic_binary

EMPTY_RGB = (255, 255, 255)     # pixels where the render is unknown (empty space from above)
DISTANCE_FACTOR = 20.0          # camera height above the scene top, in scene widths (near-orthographic)


@dataclass(frozen=True)
class BirdseyeView:
    """The rendered top-down view.

    Attributes:
        path: the PNG written (image + legend + axes in metres).
        camera: the pinhole camera used: optical axis straight down (−z of the map), image right =
            map +x, image up = map +y.
        labels: (H, W) int32 rendered labels (``ignore_label`` where empty).
        rgb: (H, W, 3) uint8 class colours, ``EMPTY_RGB`` where empty.
        extent: (x_min, x_max, y_min, y_max) map-frame metres covered by the image at the scene top.
    """

    path: Path
    camera: Camera
    labels: np.ndarray
    rgb: np.ndarray
    extent: tuple[float, float, float, float]


def _submap(smap: SemanticMap, keep: np.ndarray) -> SemanticMap:
    if keep.all():
        return smap
    sub = SemanticMap(smap.model.select(keep), smap.num_classes, prior=smap.prior, background=smap.background,
                      ignore_label=smap.ignore_label, unknown_threshold=smap.unknown_threshold,
                      backend=smap.backend_name)
    sub.concentrations[...] = smap.concentrations[keep]
    return sub


def birdseye_camera(means: np.ndarray, width: int, margin: float = 0.05) -> tuple[Camera, tuple[float, ...]]:
    """A camera high above the box of ``means`` ((N, 3), map frame, m; 0.5–99.5 percentiles), looking
    straight down, its focal length fitting the box (plus ``margin`` on each side) at the box top."""
    lo = np.percentile(means, 0.5, axis=0)
    hi = np.percentile(means, 99.5, axis=0)
    ext = np.maximum(hi - lo, 1e-3)
    span_x, span_y = ext[0] * (1 + 2 * margin), ext[1] * (1 + 2 * margin)
    height = int(np.clip(round(width * span_y / span_x), 16, 4 * width))
    span_x = max(span_x, span_y * width / height)
    span_y = span_x * height / width
    distance = DISTANCE_FACTOR * max(span_x, span_y)
    f = width * distance / span_x
    centre = (lo + hi) / 2.0
    K = np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    eye = np.array([centre[0], centre[1], hi[2] + distance])
    cam = Camera.look_at(eye, [centre[0], centre[1], lo[2]], K, width, height, up=(0.0, 1.0, 0.0))
    extent = (centre[0] - span_x / 2, centre[0] + span_x / 2, centre[1] - span_y / 2, centre[1] + span_y / 2)
    return cam, tuple(float(v) for v in extent)


#: Legend entry of the white pixels.
EMPTY_LABEL = "white: unobserved"


def birdseye_figure(rgb: np.ndarray, extent: tuple[float, ...], classes: ClassSet, order: list[int],
                    title: str | None = None, dpi: int = 100) -> Any:
    """The picture's figure: ``rgb`` (H, W, 3) uint8 over ``extent`` (x_min, x_max, y_min, y_max) m, a legend of
    the classes ``order`` (ids, most pixels first) and of the white :data:`EMPTY_RGB` pixels, axes in metres."""
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    h, w = rgb.shape[:2]
    fig = Figure(figsize=(w / dpi + 2.6, h / dpi + 0.9), dpi=dpi)
    ax = fig.add_axes((0.6 / (w / dpi + 2.6), 0.6 / (h / dpi + 0.9), (w / dpi) / (w / dpi + 2.6),
                       (h / dpi) / (h / dpi + 0.9)))
    ax.imshow(rgb, extent=extent, origin="upper", interpolation="nearest")
    ax.set_xlabel("x [m] (map frame)", fontsize=8)
    ax.set_ylabel("y [m]", fontsize=8)
    ax.tick_params(labelsize=7)
    if title:
        ax.set_title(title, fontsize=9)
    handles = [Patch(facecolor=classes.palette[i] / 255.0, edgecolor="black", label=classes.names[i])
               for i in order]
    handles.append(Patch(facecolor=np.asarray(EMPTY_RGB) / 255.0, edgecolor="black", label=EMPTY_LABEL))
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, frameon=False,
              borderaxespad=0.0)
    return fig


def render_birdseye(smap: SemanticMap, classes: ClassSet, path_png: str | os.PathLike[str], width: int = 800,
                    min_evidence: float = DEFAULT_MIN_EVIDENCE, observed_only: bool = True,
                    max_height: float | None = None, title: str | None = None, dpi: int = 100,
                    splat_to_map: Similarity | None = None) -> BirdseyeView:
    """Render the map's labels from straight above and write a PNG with a legend of class names.

    Args:
        smap: the semantic map (map frame: z up, metres).
        classes: names and colours (C must equal ``smap.num_classes``).
        path_png: output PNG, written atomically.
        width: image width in pixels; the height follows the scene's x/y aspect ratio.
        min_evidence: threshold of SPEC §9 for ``observed_only``.
        observed_only: render only observed Gaussians (unobserved ones, e.g. a never-seen ceiling,
            would otherwise hide what was seen under them).
        max_height: also leave out Gaussians whose centre z exceeds this (m), e.g. an indoor ceiling.
        title: figure title.
        splat_to_map: the similarity taking the splat into the map frame (z up); None: the splat is in it.
            The picture looks down the map's -z; ``BirdseyeView.camera`` is in the map frame.
    Raises:
        MapError: class count mismatch, or no Gaussian left to render.
    """
    if classes.num_classes != smap.num_classes:
        raise MapError(f"{classes.num_classes} classes given for a map of {smap.num_classes} classes")
    sim = splat_to_map if splat_to_map is not None and not splat_to_map.is_identity else None
    means_map = smap.model.means.astype(np.float64) if sim is None else sim.apply(smap.model.means)
    keep = np.ones(smap.model.num_gaussians, dtype=bool)
    if observed_only:
        keep &= smap.gaussian_semantics(min_evidence).observed
    if max_height is not None:
        keep &= means_map[:, 2] <= max_height
    if not np.any(keep):
        raise MapError("bird's-eye view: no Gaussian left to render (none observed / all above max_height)")
    sub = _submap(smap, keep)
    camera, extent = birdseye_camera(means_map[keep], int(width))
    if sim is None:
        view = sub.render(camera)
    else:
        pos, quat = sim.inverse().apply_pose(camera.position, camera.quaternion_xyzw)
        view = sub.render(Camera.from_pose(camera.K, camera.width, camera.height, pos, quat))
    labels = view.labels
    rgb = np.empty(labels.shape + (3,), dtype=np.uint8)
    rgb[...] = np.asarray(EMPTY_RGB, dtype=np.uint8)
    valid = (labels >= 0) & (labels < classes.num_classes) & (labels != smap.ignore_label)
    rgb[valid] = classes.palette[labels[valid]]

    ids, counts = np.unique(labels[valid], return_counts=True)
    order = [int(i) for i in ids[np.argsort(-counts, kind="stable")]]
    fig = birdseye_figure(rgb, extent, classes, order, title, dpi)
    with atomic_binary(path_png) as fh:
        fig.savefig(fh, format="png", dpi=dpi)
    return BirdseyeView(Path(path_png), camera, labels, rgb, extent)
