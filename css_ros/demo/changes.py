"""The demo's changing world (``css_make_demo --people N --change-class FROM:TO --depth``): people walking through
the room, an object whose class changes part way, and the depth image a depth camera would give.

- **People** belong to a class the static room never has (:data:`PERSON_CLASS`, appended to the class file). Each
  is an upright ellipsoid (:data:`PERSON_RADII`, feet on the floor) walking to and fro along a straight path of
  the layout (:data:`WALKER_PATHS`) at :data:`WALKING_SPEED`. Where its surface is nearer than the room's, it is in
  the segmentation (class person, confidence :data:`PERSON_CONFIDENCE`), in the colour image and in the depth image;
  it is never in the splat (``model.ply``) nor in the static ground truth (``/segmentation_gt`` shows the room
  behind it: what the map should show).
- **A class change**: every Gaussian of one class (one object in the room: the sofa by default) takes another class
  from a frame on (same geometry, same colour): in the segmentation and in ``/segmentation_gt`` from that frame, and
  ``/segmentation_gt_changed`` gives, in every frame, the object's pixels with the class it has at the end.
- **Depth** (``/depth``): the splat's expected depth along the optical axis (the engine's ``RenderedView.depth`` of
  the same model: the map's own rendered depth, so the static room agrees with it exactly), with the people in front.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Sequence

import numpy as np

from ..engine.classes import ClassSet
from ..errors import CssError

if TYPE_CHECKING:
    from ..engine.camera import Camera

#: the class of the people (appended after the room's classes; the static room never has it)
PERSON_CLASS = "person"
PERSON_COLOR = (255, 0, 255)          #: palette entry of the person class (RGB)
PERSON_RADII = (0.24, 0.24, 0.87)     #: ellipsoid semi-axes [m] (x, y, z): 1.74 m tall, 0.48 m wide
PERSON_CONFIDENCE = 0.9               #: confidence of the person pixels in /segmentation_confidence
WALKING_SPEED = 0.9                   #: [m/s]
#: straight walking paths (x0, y0) -> (x1, y1) [m, map frame] per layout: 0.3 m or more from the furniture, and the
#: body's centre 0.7 m or more from the robot's camera along its path (the shipped path, 120 frames); walker k uses
#: path k mod len(paths), starting k x WALKER_OFFSET_S into its walk
WALKER_PATHS: dict[str, tuple[tuple[tuple[float, float], tuple[float, float]], ...]] = {
    "room": (((-2.8, -1.9), (0.2, -1.7)), ((3.5, 0.6), (3.5, -1.8)), ((-3.0, -1.5), (-0.5, -2.5))),
    "studio": (((1.0, -1.7), (3.0, -1.7)), ((-1.9, 1.25), (-3.3, 1.25))),
}
WALKER_OFFSET_S = 3.7                 #: start of walker k along its path: k x this [s]
#: the default class change (--change-class without a value) and where it happens (--change-frame: frames // 2)
DEFAULT_CHANGE = "sofa:box"
#: the depth encodings css_make_demo writes (REP 118): metres in float32, or millimetres in uint16 (0 = none)
DEPTH_ENCODINGS = ("32FC1", "16UC1")


def demo_class_set_with_people(classes: ClassSet) -> ClassSet:
    """``classes`` with :data:`PERSON_CLASS` appended (its id is the old number of classes)."""
    return ClassSet((*classes.names, PERSON_CLASS), np.vstack([classes.palette, np.array([PERSON_COLOR],
                                                                                           dtype=np.uint8)]))


@dataclass(frozen=True)
class Walker:
    """One person walking to and fro between ``start`` and ``end`` (x, y) [m] at ``speed`` [m/s], ``offset`` [s]
    into the walk at t = 0."""

    start: tuple[float, float]
    end: tuple[float, float]
    speed: float = WALKING_SPEED
    offset: float = 0.0

    def position(self, t: float) -> np.ndarray:
        """(3,) centre of the body [m] at time ``t`` [s] (feet on the floor)."""
        a, b = np.asarray(self.start, float), np.asarray(self.end, float)
        length = float(np.linalg.norm(b - a))
        s = ((t + self.offset) * self.speed) % (2 * length)
        f = (s if s <= length else 2 * length - s) / length
        xy = a + f * (b - a)
        return np.array([xy[0], xy[1], PERSON_RADII[2]])


def walkers(layout: str, count: int) -> list[Walker]:
    """``count`` walkers of ``layout`` (see :data:`WALKER_PATHS`)."""
    paths = WALKER_PATHS[layout]
    return [Walker(*paths[k % len(paths)], offset=k * WALKER_OFFSET_S) for k in range(count)]


def ellipsoid_depth(camera: "Camera", centre: np.ndarray, radii: Sequence[float]) -> np.ndarray:
    """(H, W) float64 depth along the optical axis [m] of the nearest hit of each pixel's ray (pixel centres at
    integers) with the axis-aligned ellipsoid (``centre`` (3,), ``radii`` (3,), map frame); inf where it misses or
    the hit is behind the camera."""
    h, w = int(camera.height), int(camera.width)
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rays = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)], axis=-1)
    T = np.asarray(camera.T_map_cam, dtype=np.float64)
    r = np.asarray(radii, dtype=np.float64)
    e = (rays @ T[:3, :3].T) / r                      # ray direction per unit of camera z, in ellipsoid units
    o = (T[:3, 3] - np.asarray(centre, dtype=np.float64)) / r
    a = np.sum(e * e, axis=-1)
    b = 2.0 * (e @ o)
    c = float(o @ o) - 1.0
    disc = b * b - 4.0 * a * c
    out = np.full((h, w), np.inf)
    hit = disc >= 0
    root = np.sqrt(np.where(hit, disc, 0.0))
    near = (-b - root) / (2.0 * a)
    far = (-b + root) / (2.0 * a)
    z = np.where(near > 0, near, far)                 # inside the ellipsoid: the far side
    ok = hit & (z > 0)
    out[ok] = z[ok]
    return out


def people_depth(camera: "Camera", people: Sequence[Walker], t: float) -> np.ndarray:
    """(H, W) float64 depth [m] of the nearest person at time ``t`` [s]; inf where none."""
    out = np.full((int(camera.height), int(camera.width)), np.inf)
    for person in people:
        out = np.minimum(out, ellipsoid_depth(camera, person.position(t), PERSON_RADII))
    return out


@dataclass(frozen=True)
class ClassChange:
    """Every Gaussian of class ``source`` takes class ``target`` from frame ``frame`` on (ids into the classes)."""

    source: int
    target: int
    frame: int

    @classmethod
    def parse(cls, text: str, class_names: Sequence[str], frame: int | None, frames: int) -> "ClassChange":
        """``FROM:TO`` (class names) at ``frame`` (None: ``frames // 2``).

        Raises:
            CssError: not two class names of the room, the same class twice, or a frame outside 1..frames-1.
        """
        parts = text.split(":")
        names = list(class_names)
        if len(parts) != 2 or parts[0] not in names or parts[1] not in names or parts[0] == parts[1]:
            raise CssError(f"--change-class {text!r}: expected FROM:TO, two different classes of the room "
                           f"({', '.join(names)})")
        at = frames // 2 if frame is None else int(frame)
        if not 1 <= at < frames:
            raise CssError(f"--change-frame must be in 1..{frames - 1} (a frame before and after the change), "
                           f"got {at}")
        return cls(names.index(parts[0]), names.index(parts[1]), at)


def overlay_people(person: np.ndarray, room_depth: np.ndarray, seg: np.ndarray, conf: np.ndarray,
                   rgb: np.ndarray, person_id: int) -> np.ndarray:
    """Draw the people into one frame in place where they are nearer than the room: ``person`` (H, W) their depth
    [m] (inf: none), ``room_depth`` (H, W) the room's (NaN: none); seg, conf, rgb: the frame's images. Returns the
    (H, W) bool mask of the person pixels."""
    with np.errstate(invalid="ignore"):
        mask = np.isfinite(person) & ~(person >= room_depth)   # NaN room depth: nothing behind, the person shows
    seg[mask] = person_id
    conf[mask] = PERSON_CONFIDENCE
    shade = np.clip(1.2 - 0.25 * person[mask], 0.4, 1.0)[:, None]      # nearer is brighter
    rgb[mask] = (np.array([150.0, 60.0, 170.0]) * shade).astype(np.uint8)
    return mask


def encode_depth(depth: np.ndarray, encoding: str) -> np.ndarray:
    """(H, W) metres (NaN / inf: none) as the image array of ``encoding``: float32 metres (NaN = none) or uint16
    millimetres (0 = none, clipped to 65.535 m)."""
    if encoding == "32FC1":
        return np.where(np.isfinite(depth), depth, np.nan).astype(np.float32)
    if encoding == "16UC1":
        with np.errstate(invalid="ignore"):
            mm = np.where(np.isfinite(depth) & (depth > 0), np.clip(np.rint(depth * 1000.0), 1, 65535), 0)
        return mm.astype(np.uint16)
    raise CssError(f"--depth-encoding must be one of {', '.join(DEPTH_ENCODINGS)}, got {encoding!r}")
