"""Procedural furnished room built the way a pretrained 3DGS model looks: flat Gaussians lying on surfaces.

Two layouts share the 16 semantic classes (:data:`CLASS_NAMES`); ``build_scene_arrays(..., layout=...)`` picks one
(map frame: x east, y north, z up, metres):

* ``"room"`` (:func:`indoor_layout`, the default and the shipped demo) spans x in [-4, 4], y in [-3, 3],
  z in [0, 2.7]. It holds a wooden floor with a rug, painted walls and ceiling, a door, a window, a dining table
  with four chairs, a sofa with a coffee table, a bookshelf with boxes, a cabinet, two floor lamps (thin poles),
  two potted plants, three pictures and five wall outlets.
* ``"studio"`` (:func:`studio_layout`) is a long studio flat, x in [-4.5, 4.5], y in [-2.25, 2.25], z in [0, 2.6]
  (far walls up to ~9 m away): living corner at the east end (sofa against the east wall facing west, rug,
  coffee table turned by 90 degrees), a dining table turned by 15 degrees with two chairs under two north
  windows, a desk with a chair against the south wall, a kitchen row of cabinets (base and wall units) in the
  north-west corner, a bookshelf on the west wall, the door in the south wall, two floor lamps, three plants,
  three pictures, six outlets and moving boxes on the floor.

Every object is a set of surface *primitives* (rectangles, cylinders, discs, ellipsoids). Gaussians are
spread over them with a low-discrepancy (R2) sequence so the surfaces are covered without holes; each is
flattened (two in-plane standard deviations ~0.6-0.8 x the local sample spacing, one along the normal ~5-10 x
smaller) and oriented so its smallest axis is the surface normal. Opacities follow a Beta distribution
(mostly 0.8-0.99, a tail of faint Gaussians), colours are per-material base colours with procedural texture
(planks, wood grain, fabric, rug pattern, paintings, sky) and baked shading. Everything is vectorised numpy
and deterministic for a seed; 1M Gaussians take a few seconds.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from ..engine.classes import ClassSet

if TYPE_CHECKING:
    from ..engine.gaussians import GaussianModel

__all__ = [
    "CLASS_NAMES",
    "CLASS_PALETTE",
    "LAYOUTS",
    "ROOM_MAX",
    "ROOM_MIN",
    "STUDIO_MAX",
    "STUDIO_MIN",
    "Primitive",
    "SceneArrays",
    "build_indoor_scene",
    "build_scene_arrays",
    "demo_class_set",
    "indoor_layout",
    "layout_primitives",
    "obstacle_footprints",
    "room_bounds",
    "studio_layout",
]

#: Semantic classes of the demo room, id = index.
CLASS_NAMES: tuple[str, ...] = (
    "floor", "wall", "ceiling", "door", "window", "rug", "table", "chair",
    "shelf", "sofa", "cabinet", "lamp", "picture", "outlet", "plant", "box",
)
#: Display palette (RGB uint8), one row per class (ADE20K/Cityscapes-like, well separated).
CLASS_PALETTE: np.ndarray = np.array([
    [128, 64, 128],   # floor
    [70, 70, 70],     # wall
    [120, 120, 180],  # ceiling
    [255, 160, 0],    # door
    [0, 200, 255],    # window
    [220, 20, 60],    # rug
    [255, 230, 0],    # table
    [0, 130, 0],      # chair
    [160, 80, 200],   # shelf
    [0, 0, 230],      # sofa
    [255, 120, 180],  # cabinet
    [0, 90, 90],  # lamp (dark teal: visible on white backgrounds)
    [0, 255, 140],    # picture
    [255, 0, 0],      # outlet
    [107, 142, 35],   # plant
    [150, 100, 50],   # box
], dtype=np.uint8)

ROOM_MIN = np.array([-4.0, -3.0, 0.0])  #: room interior lower corner (map, metres)
ROOM_MAX = np.array([4.0, 3.0, 2.7])    #: room interior upper corner (map, metres)
STUDIO_MIN = np.array([-4.5, -2.25, 0.0])  #: studio interior lower corner (map, metres)
STUDIO_MAX = np.array([4.5, 2.25, 2.6])    #: studio interior upper corner (map, metres)
#: Names of the scene layouts (``build_scene_arrays(layout=...)``); "room" is the shipped demo.
LAYOUTS: tuple[str, ...] = ("room", "studio")
_H = float(ROOM_MAX[2])
_CID = {name: i for i, name in enumerate(CLASS_NAMES)}
_THIN_FACE = 0.025  # box faces narrower than this (m) are not sampled: the neighbouring faces cover them
_PLASTIC = 1.32471795724474602596  # plastic number, R2 low-discrepancy sequence


def demo_class_set() -> ClassSet:
    """The demo room's :class:`ClassSet` (names + palette); ``config/demo_classes.yaml`` holds the same."""
    return ClassSet(CLASS_NAMES, CLASS_PALETTE.copy())


# ----------------------------------------------------------------------------------------------- primitives
@dataclass(frozen=True)
class Primitive:
    """One surface patch of the scene.

    Attributes:
        kind: "rect" | "cylinder" | "disc" | "ellipsoid".
        class_id: ground-truth class of every Gaussian on it.
        center: (3,) map frame, metres (cylinder: middle of the axis).
        frame: (3, 3) columns e1, e2, e3 (orthonormal, right-handed). rect: e1, e2 span the plane and
            e3 = e1 x e2 is the normal of the visible side; cylinder/disc: e3 is the axis (disc normal).
        size: rect (a, b) half extents along e1, e2; cylinder (r, h) radius and half height;
            disc (r,); ellipsoid (rx, ry, rz) semi-axes along e1, e2, e3.
        material: texture name (see ``_texture``).
        color: (3,) base RGB in [0, 1].
        holes: world axis-aligned boxes (lo (3,), hi (3,)); samples inside are dropped (e.g. the floor under a
            rug, the wall behind the door).
        name: object name, for debugging.
        foliage: if True, Gaussians are scattered in a shell of the ellipsoid with random orientation (leaves).
    """

    kind: str
    class_id: int
    center: np.ndarray
    frame: np.ndarray
    size: tuple[float, ...]
    material: str
    color: tuple[float, float, float]
    holes: tuple[tuple[tuple[float, float, float], tuple[float, float, float]], ...] = ()
    name: str = ""
    foliage: bool = False

    @property
    def area(self) -> float:
        """Surface area in m^2 (holes included)."""
        if self.kind == "rect":
            return 4.0 * self.size[0] * self.size[1]
        if self.kind == "cylinder":
            return 2.0 * math.pi * self.size[0] * 2.0 * self.size[1]
        if self.kind == "disc":
            return math.pi * self.size[0] ** 2
        a, b, c = self.size  # Knud Thomsen's approximation of the ellipsoid surface
        p = 1.6075
        return 4.0 * math.pi * (((a * b) ** p + (a * c) ** p + (b * c) ** p) / 3.0) ** (1.0 / p)

    @property
    def feature_size(self) -> float:
        """Smallest dimension of the patch (m): the sample spacing is kept below ~2/5 of it."""
        if self.kind == "rect":
            return 2.0 * min(self.size)
        if self.kind == "cylinder":
            return 2.0 * min(self.size[0] * 1.5, self.size[1])
        if self.kind == "disc":
            return 2.0 * self.size[0]
        return 2.0 * min(self.size)

    def hole_fraction(self) -> float:
        """Approximate fraction of the area removed by ``holes`` (rect only; 0 otherwise)."""
        if not self.holes or self.kind != "rect":
            return 0.0
        rng = np.random.default_rng(0)
        st = rng.random((4000, 2))
        pts = _rect_points(self, st)
        return float(np.mean(_in_holes(self, pts)))


def _frame(e1: np.ndarray, e2: np.ndarray) -> np.ndarray:
    e1 = np.asarray(e1, float) / np.linalg.norm(e1)
    e2 = np.asarray(e2, float) / np.linalg.norm(e2)
    return np.stack([e1, e2, np.cross(e1, e2)], axis=1)


_X, _Y, _Z = np.eye(3)


def _rect(center, e1, e2, a, b, cls, material, color, holes=(), name="") -> Primitive:
    return Primitive("rect", _CID[cls], np.asarray(center, float), _frame(e1, e2), (float(a), float(b)),
                     material, tuple(color), tuple(holes), name)


def _box(center, half, cls, material, color, yaw_deg=0.0, skip=("-z",), name="") -> list[Primitive]:
    """Rect faces of a box with outward normals (yaw about +z). ``skip`` lists faces not sampled
    ("+x", "-x", "+y", "-y", "+z", "-z" in the box frame): faces touching the floor or a wall."""
    c = np.asarray(center, float)
    hx, hy, hz = half
    cy, sy = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    X = np.array([cy, sy, 0.0])
    Y = np.array([-sy, cy, 0.0])
    Z = _Z
    faces = {
        "+x": (c + hx * X, Y, Z, hy, hz),
        "-x": (c - hx * X, Z, Y, hz, hy),
        "+y": (c + hy * Y, Z, X, hz, hx),
        "-y": (c - hy * Y, X, Z, hx, hz),
        "+z": (c + hz * Z, X, Y, hx, hy),
        "-z": (c - hz * Z, Y, X, hy, hx),
    }
    out = []
    for key, (fc, e1, e2, a, b) in faces.items():
        if key in skip or 2.0 * min(a, b) < _THIN_FACE:
            continue
        out.append(_rect(fc, e1, e2, a, b, cls, material, color, name=f"{name}{key}"))
    return out


def _cylinder(center, radius, half_height, cls, material, color, name="") -> Primitive:
    return Primitive("cylinder", _CID[cls], np.asarray(center, float), np.eye(3),
                     (float(radius), float(half_height)), material, tuple(color), (), name)


def _disc(center, radius, cls, material, color, up=True, name="") -> Primitive:
    fr = np.eye(3) if up else _frame(_Y, _X)
    return Primitive("disc", _CID[cls], np.asarray(center, float), fr, (float(radius),), material,
                     tuple(color), (), name)


def _ellipsoid(center, radii, cls, material, color, foliage=False, name="") -> Primitive:
    return Primitive("ellipsoid", _CID[cls], np.asarray(center, float), np.eye(3), tuple(map(float, radii)),
                     material, tuple(color), (), name, foliage)


def _aabb(lo, hi):
    return (tuple(map(float, lo)), tuple(map(float, hi)))


# ----------------------------------------------------------------------------------------------- layout
_WOOD_FLOOR = (0.56, 0.40, 0.26)
_PAINT = (0.86, 0.84, 0.79)
_CEILING = (0.94, 0.94, 0.93)
_DOOR = (0.47, 0.31, 0.19)
_GLASS = (0.70, 0.82, 0.93)
_RUG = (0.62, 0.16, 0.15)
_TABLE = (0.52, 0.34, 0.20)
_CHAIR = (0.33, 0.25, 0.18)
_SHELF = (0.74, 0.62, 0.46)
_SOFA = (0.24, 0.34, 0.55)
_CABINET = (0.90, 0.89, 0.86)
_METAL = (0.22, 0.22, 0.23)
_SHADE = (0.96, 0.90, 0.74)
_POT = (0.62, 0.32, 0.20)
_LEAF = (0.20, 0.45, 0.16)
_OUTLET = (0.95, 0.95, 0.93)


def _table(cx, cy, hx, hy, top_z, thick, leg, cls="table", color=_TABLE, name="table") -> list[Primitive]:
    prims = _box((cx, cy, top_z - thick / 2), (hx, hy, thick / 2), cls, "wood", color, skip=(), name=name)
    lh = (top_z - thick) / 2
    for sx in (-1, 1):
        for sy in (-1, 1):
            lx, ly = cx + sx * (hx - leg), cy + sy * (hy - leg)
            prims += _box((lx, ly, lh), (leg / 2, leg / 2, lh), cls, "wood", color, skip=("-z", "+z"),
                          name=f"{name}_leg")
    return prims


def _chair(cx, cy, yaw_deg, name="chair") -> list[Primitive]:
    """Dining chair at (cx, cy) facing direction yaw (the sitter looks along +x of the chair frame)."""
    cyw, syw = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    fwd = np.array([cyw, syw, 0.0])
    left = np.array([-syw, cyw, 0.0])
    c = np.array([cx, cy, 0.0])
    seat_h, half = 0.46, 0.22
    prims = _box(c + [0, 0, seat_h - 0.02], (half, half, 0.02), "chair", "wood", _CHAIR, yaw_deg, skip=(),
                 name=f"{name}_seat")
    back_c = c - (half - 0.02) * fwd + [0, 0, seat_h + 0.24]
    prims += _box(back_c, (0.02, half, 0.22), "chair", "wood", _CHAIR, yaw_deg, skip=("-z",), name=f"{name}_back")
    lh = (seat_h - 0.04) / 2
    for a in (-1, 1):
        for b in (-1, 1):
            p = c + a * (half - 0.025) * fwd + b * (half - 0.025) * left + [0, 0, lh]
            prims += _box(p, (0.018, 0.018, lh), "chair", "wood", _CHAIR, yaw_deg, skip=("-z", "+z"),
                          name=f"{name}_leg")
    return prims


def _floor_lamp(x, y, height, name="lamp") -> list[Primitive]:
    pole_h = height - 0.28
    return [
        _cylinder((x, y, 0.015), 0.16, 0.015, "lamp", "metal", _METAL, name=f"{name}_base"),
        _disc((x, y, 0.03), 0.16, "lamp", "metal", _METAL, name=f"{name}_base_top"),
        _cylinder((x, y, 0.03 + pole_h / 2), 0.018, pole_h / 2, "lamp", "metal", _METAL, name=f"{name}_pole"),
        _cylinder((x, y, height - 0.14), 0.21, 0.14, "lamp", "shade", _SHADE, name=f"{name}_shade"),
        _disc((x, y, height), 0.21, "lamp", "shade", _SHADE, name=f"{name}_shade_top"),
    ]


def _plant(x, y, pot_r, pot_h, foliage_r, name="plant") -> list[Primitive]:
    return [
        _cylinder((x, y, pot_h / 2), pot_r, pot_h / 2, "plant", "pot", _POT, name=f"{name}_pot"),
        _disc((x, y, pot_h), pot_r, "plant", "soil", (0.25, 0.17, 0.11), name=f"{name}_soil"),
        _ellipsoid((x, y, pot_h + foliage_r * 0.9), (foliage_r, foliage_r, foliage_r * 1.15), "plant", "leaf",
                   _LEAF, foliage=True, name=f"{name}_leaves"),
    ]


def _wall_item(wall: str, along: float, z: float, half_w: float, half_h: float, depth: float, cls: str,
               material: str, color, name: str, lo: np.ndarray = ROOM_MIN, hi: np.ndarray = ROOM_MAX
               ) -> list[Primitive]:
    """Thin box mounted on a wall of the room ``lo``..``hi`` (interior corners, metres): ``along`` is the
    coordinate along the wall, ``z`` the centre height."""
    x0, y0 = lo[:2]
    x1, y1 = hi[:2]
    d = depth / 2
    if wall == "south":
        return _box((along, y0 + d, z), (half_w, d, half_h), cls, material, color, skip=("-y",), name=name)
    if wall == "north":
        return _box((along, y1 - d, z), (half_w, d, half_h), cls, material, color, skip=("+y",), name=name)
    if wall == "west":
        return _box((x0 + d, along, z), (d, half_w, half_h), cls, material, color, skip=("-x",), name=name)
    return _box((x1 - d, along, z), (d, half_w, half_h), cls, material, color, skip=("+x",), name=name)


#: Object footprints (x0, y0, x1, y1) on the floor, map frame metres: used for floor holes and by the trajectory.
_FOOTPRINTS: dict[str, tuple[float, float, float, float]] = {
    "sofa": (0.5, -3.0, 2.5, -2.08),
    "coffee_table": (1.0, -1.62, 2.0, -1.12),
    "rug": (0.3, -2.05, 2.7, -0.45),
    "dining_table": (-2.3, 0.05, -0.7, 0.95),
    "chairs": (-2.2, -0.5, -0.8, 1.5),
    "shelf": (-4.0, -2.2, -3.64, -1.2),
    "cabinet": (1.0, 2.54, 1.8, 3.0),
    "lamp_se": (2.94, -2.86, 3.36, -2.44),
    "lamp_nw": (-3.71, 2.34, -3.29, 2.76),
    "plant_ne": (3.1, 1.1, 3.9, 1.9),
    "plant_sw": (-3.85, -3.0, -3.05, -2.2),
}


def obstacle_footprints(layout: str = "room") -> dict[str, tuple[float, float, float, float]]:
    """Axis-aligned floor footprints (x0, y0, x1, y1) in metres of a layout's furniture (a robot must stay out;
    it may drive over the "rug")."""
    return dict(_STUDIO_FOOTPRINTS if _check_layout(layout) == "studio" else _FOOTPRINTS)


def indoor_layout() -> list[Primitive]:
    """All surface primitives of the demo room (fixed layout; the seed only affects sampling and texture)."""
    x0, y0, _ = ROOM_MIN
    x1, y1, _ = ROOM_MAX
    prims: list[Primitive] = []

    # --- shell: floor (holes under the rug and the closed furniture), ceiling, four walls (normals inward)
    fp = _FOOTPRINTS
    floor_holes = tuple(_aabb((fp[k][0] + 0.03, fp[k][1] + 0.03, -0.1), (fp[k][2] - 0.03, fp[k][3] - 0.03, 0.1))
                        for k in ("rug", "sofa", "shelf", "cabinet"))
    prims.append(_rect((0, 0, 0), _X, _Y, 4.0, 3.0, "floor", "planks", _WOOD_FLOOR, floor_holes, "floor"))
    prims.append(_rect((0, 0, _H), _Y, _X, 3.0, 4.0, "ceiling", "ceiling", _CEILING, (), "ceiling"))
    door_hole = _aabb((-3.15, y1 - 0.1, -0.1), (-2.35, y1 + 0.1, 2.0))
    window_hole = _aabb((x1 - 0.1, -0.97, 0.93), (x1 + 0.1, 0.57, 2.07))
    prims.append(_rect((x0, 0, _H / 2), _Y, _Z, 3.0, _H / 2, "wall", "paint", _PAINT, (), "wall_west"))
    prims.append(_rect((x1, 0, _H / 2), _Z, _Y, _H / 2, 3.0, "wall", "paint", _PAINT, (window_hole,), "wall_east"))
    prims.append(_rect((0, y0, _H / 2), _Z, _X, _H / 2, 4.0, "wall", "paint", _PAINT, (), "wall_south"))
    prims.append(_rect((0, y1, _H / 2), _X, _Z, 4.0, _H / 2, "wall", "paint", _PAINT, (door_hole,), "wall_north"))

    # --- door (north wall, west end) and window (east wall)
    prims += _wall_item("north", -2.75, 1.025, 0.45, 1.025, 0.04, "door", "door", _DOOR, "door")
    prims.append(_rect((x1 - 0.01, -0.2, 1.5), _Z, _Y, 0.6, 0.8, "window", "glass", _GLASS, (), "window"))
    prims += _wall_item("east", -0.2, 0.86, 0.86, 0.03, 0.16, "window", "sill", _CABINET, "window_sill")

    # --- rug, sofa corner, coffee table
    r = fp["rug"]
    prims.append(_rect(((r[0] + r[2]) / 2, (r[1] + r[3]) / 2, 0.008), _X, _Y, (r[2] - r[0]) / 2,
                       (r[3] - r[1]) / 2, "rug", "rug", _RUG, (), "rug"))
    s = fp["sofa"]
    sx = (s[0] + s[2]) / 2
    prims += _box((sx, -2.55, 0.21), (1.0, 0.45, 0.21), "sofa", "fabric", _SOFA, skip=("-z", "-y"), name="sofa_base")
    prims += _box((sx, -2.89, 0.62), (1.0, 0.11, 0.20), "sofa", "fabric", _SOFA, skip=("-z", "-y"), name="sofa_back")
    for side in (-1, 1):
        prims += _box((sx + side * 0.9, -2.5, 0.53), (0.1, 0.42, 0.11), "sofa", "fabric", _SOFA, skip=("-z",),
                      name="sofa_arm")
    prims += _box((sx - 0.45, -2.3, 0.47), (0.42, 0.2, 0.05), "sofa", "fabric", (0.30, 0.40, 0.62), skip=("-z",),
                  name="cushion")
    prims += _box((sx + 0.45, -2.3, 0.47), (0.42, 0.2, 0.05), "sofa", "fabric", (0.30, 0.40, 0.62), skip=("-z",),
                  name="cushion")
    c = fp["coffee_table"]
    prims += _table((c[0] + c[2]) / 2, (c[1] + c[3]) / 2, 0.5, 0.25, 0.42, 0.04, 0.05, name="coffee_table")

    # --- dining table and four chairs
    prims += _table(-1.5, 0.5, 0.8, 0.45, 0.75, 0.04, 0.06, name="dining_table")
    prims += _chair(-1.9, -0.22, 90.0, "chair_s1")
    prims += _chair(-1.1, -0.22, 90.0, "chair_s2")
    prims += _chair(-1.9, 1.22, -90.0, "chair_n1")
    prims += _chair(-1.1, 1.22, -90.0, "chair_n2")

    # --- bookshelf (west wall, south part): open, with boards and boxes on them
    sh_x0, sh_x1, sh_y0, sh_y1, sh_h = -4.0, -3.64, -2.2, -1.2, 1.9
    cxs, cys = (sh_x0 + sh_x1) / 2, (sh_y0 + sh_y1) / 2
    for y_side, skip in ((sh_y0 + 0.01, ("-z",)), (sh_y1 - 0.01, ("-z",))):
        prims += _box((cxs, y_side, sh_h / 2), (0.18, 0.01, sh_h / 2), "shelf", "wood", _SHELF, skip=skip,
                      name="shelf_side")
    prims.append(_rect((sh_x0 + 0.008, cys, sh_h / 2), _Y, _Z, 0.49, sh_h / 2, "shelf", "wood", _SHELF, (),
                       "shelf_back"))
    boards = (0.06, 0.5, 0.94, 1.38, 1.88)
    for bz in boards:
        prims += _box((cxs + 0.005, cys, bz), (0.175, 0.48, 0.015), "shelf", "wood", _SHELF, skip=("-x",),
                      name="shelf_board")
    # boxes / books on the boards (deterministic pseudo-random layout)
    lay = np.random.default_rng(7)
    book_colors = [(0.70, 0.15, 0.12), (0.15, 0.30, 0.60), (0.85, 0.75, 0.30), (0.20, 0.50, 0.30),
                   (0.90, 0.90, 0.85), (0.45, 0.25, 0.45)]
    for bz in boards[:-1]:
        y = sh_y0 + 0.06
        while True:
            w = float(lay.uniform(0.08, 0.2))
            h = float(lay.uniform(0.16, 0.3))
            if y + w > sh_y1 - 0.05:
                break
            if lay.random() < 0.8:
                col = book_colors[int(lay.integers(len(book_colors)))]
                prims += _box((sh_x0 + 0.17, y + w / 2, bz + 0.015 + h / 2), (0.11, w / 2 - 0.005, h / 2), "box",
                              "book", col, skip=("-z", "-x"), name="shelf_box")
            y += w + float(lay.uniform(0.0, 0.08))

    # --- cabinet (north wall) with a box on top, picture above it
    cb = fp["cabinet"]
    prims += _box(((cb[0] + cb[2]) / 2, (cb[1] + cb[3]) / 2, 0.45), (0.4, 0.23, 0.45), "cabinet", "lacquer",
                  _CABINET, skip=("-z", "+y"), name="cabinet")
    prims += _box((1.25, 2.75, 0.99), (0.15, 0.1, 0.09), "box", "book", (0.80, 0.55, 0.25), skip=("-z",),
                  name="cab_box")
    prims += _box((1.55, 2.8, 0.96), (0.08, 0.08, 0.06), "box", "book", (0.25, 0.45, 0.70), skip=("-z",),
                  name="cab_box2")
    # small objects on the tables
    prims += _box((-1.8, 0.45, 0.81), (0.12, 0.09, 0.06), "box", "book", (0.75, 0.20, 0.15), skip=("-z",),
                  name="table_box")
    prims += _box((-1.1, 0.6, 0.79), (0.1, 0.14, 0.04), "box", "book", (0.20, 0.35, 0.65), skip=("-z",),
                  name="table_box2")
    prims += _box((1.7, -1.37, 0.46), (0.13, 0.1, 0.04), "box", "book", (0.85, 0.80, 0.30), skip=("-z",),
                  name="coffee_box")

    # --- lamps, plants
    prims += _floor_lamp(3.15, -2.65, 1.65, "lamp_se")
    prims += _floor_lamp(-3.5, 2.55, 1.6, "lamp_nw")
    prims += _plant(3.5, 1.5, 0.2, 0.38, 0.42, "plant_ne")
    prims += _plant(-3.45, -2.6, 0.18, 0.34, 0.36, "plant_sw")

    # --- pictures (thin, on walls) and outlets (tiny, near the floor)
    prims += _wall_item("south", 1.5, 1.55, 0.45, 0.3, 0.02, "picture", "painting", (0.5, 0.5, 0.5), "picture_s")
    prims += _wall_item("north", 1.4, 1.6, 0.25, 0.2, 0.02, "picture", "painting", (0.5, 0.5, 0.5), "picture_n")
    prims += _wall_item("west", 0.5, 1.5, 0.35, 0.25, 0.02, "picture", "painting", (0.5, 0.5, 0.5), "picture_w")
    for wall, along, z in (("south", -1.0, 0.3), ("north", 0.2, 0.3), ("west", 1.8, 0.3), ("east", -2.0, 0.3),
                           ("east", 2.2, 1.1)):
        prims += _wall_item(wall, along, z, 0.04, 0.06, 0.012, "outlet", "outlet", _OUTLET, f"outlet_{wall}")
    return prims


# ----------------------------------------------------------------------------------------------- studio layout
_S_LO, _S_HI = STUDIO_MIN, STUDIO_MAX
_SH = float(STUDIO_MAX[2])
_CARDBOARD = (0.68, 0.52, 0.34)
_COUNTER = (0.30, 0.28, 0.26)

#: Studio footprints (x0, y0, x1, y1), map frame metres (rotated objects: their axis-aligned bounds).
_STUDIO_FOOTPRINTS: dict[str, tuple[float, float, float, float]] = {
    "sofa": (3.5, -1.05, 4.5, 1.05),
    "coffee_table": (2.27, -0.5, 2.83, 0.5),
    "rug": (1.7, -1.3, 3.45, 1.3),
    "dining_table": (-0.68, 0.95, 0.68, 1.75),
    "chairs": (-1.12, 0.86, 1.12, 1.84),
    "desk": (-2.2, -2.25, -0.8, -1.6),
    "desk_chair": (-1.75, -1.55, -1.25, -1.05),
    "shelf": (-4.5, -1.3, -4.14, 0.1),
    "cabinet": (-4.5, 1.65, -2.3, 2.25),
    "lamp_ne": (3.89, 1.64, 4.31, 2.06),
    "lamp_sw": (-4.31, -1.96, -3.89, -1.54),
    "plant_se": (3.65, -2.2, 4.45, -1.4),
    "plant_n": (1.35, 1.45, 2.15, 2.25),
    "plant_w": (-4.45, 0.3, -3.75, 1.0),
    "floor_boxes": (-2.9, -2.15, -2.3, -1.6),
}


def _table_yaw(cx: float, cy: float, hx: float, hy: float, top_z: float, thick: float, leg: float,
               yaw_deg: float, name: str) -> list[Primitive]:
    """A table (top and four legs) turned by ``yaw_deg`` about +z around its centre (cx, cy)."""
    prims = _box((cx, cy, top_z - thick / 2), (hx, hy, thick / 2), "table", "wood", _TABLE, yaw_deg, skip=(),
                 name=name)
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    lh = (top_z - thick) / 2
    for sx in (-1, 1):
        for sy in (-1, 1):
            ax, ay = sx * (hx - leg), sy * (hy - leg)
            prims += _box((cx + c * ax - s * ay, cy + s * ax + c * ay, lh), (leg / 2, leg / 2, lh), "table", "wood",
                          _TABLE, yaw_deg, skip=("-z", "+z"), name=f"{name}_leg")
    return prims


def _sofa(cx: float, cy: float, facing_deg: float, name: str = "sofa") -> list[Primitive]:
    """Three-seat sofa whose seat centre is (cx, cy), the sitter looking along ``facing_deg`` (back and base
    faces against the wall behind it are not sampled)."""
    yaw = facing_deg - 90.0  # the box frame's +y is the facing direction
    c, s = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))

    def at(lx: float, ly: float, z: float) -> tuple[float, float, float]:
        return (cx + c * lx - s * ly, cy + s * lx + c * ly, z)

    prims = _box(at(0, 0, 0.21), (1.0, 0.45, 0.21), "sofa", "fabric", _SOFA, yaw, skip=("-z", "-y"),
                 name=f"{name}_base")
    prims += _box(at(0, -0.34, 0.62), (1.0, 0.11, 0.20), "sofa", "fabric", _SOFA, yaw, skip=("-z", "-y"),
                  name=f"{name}_back")
    for side in (-1, 1):
        prims += _box(at(side * 0.9, 0.05, 0.53), (0.1, 0.42, 0.11), "sofa", "fabric", _SOFA, yaw, skip=("-z",),
                      name=f"{name}_arm")
        prims += _box(at(side * 0.45, 0.25, 0.47), (0.42, 0.2, 0.05), "sofa", "fabric", (0.30, 0.40, 0.62), yaw,
                      skip=("-z",), name="cushion")
    return prims


def _studio_shelf() -> list[Primitive]:
    """Open bookshelf on the studio's west wall (y in [-1.3, 0.1], 2 m high) with books / boxes on 4 boards."""
    x0, x1, y0, y1, h = float(_S_LO[0]), float(_S_LO[0]) + 0.36, -1.3, 0.1, 2.0
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    prims: list[Primitive] = []
    for y_side in (y0 + 0.01, y1 - 0.01):
        prims += _box((cx, y_side, h / 2), (0.18, 0.01, h / 2), "shelf", "wood", _SHELF, skip=("-z",),
                      name="shelf_side")
    prims.append(_rect((x0 + 0.008, cy, h / 2), _Y, _Z, (y1 - y0) / 2 - 0.01, h / 2, "shelf", "wood", _SHELF, (),
                       "shelf_back"))
    boards = (0.06, 0.52, 0.98, 1.44, 1.98)
    for bz in boards:
        prims += _box((cx + 0.005, cy, bz), (0.175, (y1 - y0) / 2 - 0.02, 0.015), "shelf", "wood", _SHELF,
                      skip=("-x",), name="shelf_board")
    lay = np.random.default_rng(11)
    book_colors = [(0.60, 0.20, 0.15), (0.12, 0.25, 0.50), (0.80, 0.70, 0.35), (0.25, 0.45, 0.35),
                   (0.92, 0.90, 0.86), (0.50, 0.30, 0.40), _CARDBOARD]
    for bz in boards[:-1]:
        y = y0 + 0.05
        while True:
            w = float(lay.uniform(0.07, 0.26))
            hb = float(lay.uniform(0.14, 0.34))
            if y + w > y1 - 0.05:
                break
            if lay.random() < 0.75:
                col = book_colors[int(lay.integers(len(book_colors)))]
                prims += _box((x0 + 0.17, y + w / 2, bz + 0.015 + hb / 2), (0.11, w / 2 - 0.005, hb / 2), "box",
                              "book", col, skip=("-z", "-x"), name="shelf_box")
            y += w + float(lay.uniform(0.0, 0.1))
    return prims


def _studio_shell() -> list[Primitive]:
    """Floor, ceiling, four walls (door hole in the south wall, two window holes in the north wall), door,
    two windows with sills."""
    x0, y0, _ = _S_LO
    x1, y1, _ = _S_HI
    hx, hy = float(x1 - x0) / 2, float(y1 - y0) / 2
    fp = _STUDIO_FOOTPRINTS
    floor_holes = tuple(_aabb((fp[k][0] + 0.03, fp[k][1] + 0.03, -0.1), (fp[k][2] - 0.03, fp[k][3] - 0.03, 0.1))
                        for k in ("rug", "sofa", "shelf", "cabinet"))
    prims = [
        _rect((0, 0, 0), _X, _Y, hx, hy, "floor", "planks", _WOOD_FLOOR, floor_holes, "floor"),
        _rect((0, 0, _SH), _Y, _X, hy, hx, "ceiling", "ceiling", _CEILING, (), "ceiling"),
    ]
    door_x = -3.6
    door_hole = _aabb((door_x - 0.45, y0 - 0.1, -0.1), (door_x + 0.45, y0 + 0.1, 2.0))
    window_xs = (0.2, 2.8)
    window_holes = tuple(_aabb((wx - 0.52, y1 - 0.1, 0.93), (wx + 0.52, y1 + 0.1, 2.07)) for wx in window_xs)
    prims.append(_rect((x0, 0, _SH / 2), _Y, _Z, hy, _SH / 2, "wall", "paint", _PAINT, (), "wall_west"))
    prims.append(_rect((x1, 0, _SH / 2), _Z, _Y, _SH / 2, hy, "wall", "paint", _PAINT, (), "wall_east"))
    prims.append(_rect((0, y0, _SH / 2), _Z, _X, _SH / 2, hx, "wall", "paint", _PAINT, (door_hole,), "wall_south"))
    prims.append(_rect((0, y1, _SH / 2), _X, _Z, hx, _SH / 2, "wall", "paint", _PAINT, window_holes, "wall_north"))
    prims += _wall_item("south", door_x, 1.025, 0.45, 1.025, 0.04, "door", "door", _DOOR, "door", _S_LO, _S_HI)
    for wx in window_xs:
        prims.append(_rect((wx, y1 - 0.01, 1.5), _X, _Z, 0.55, 0.6, "window", "glass", _GLASS, (), "window"))
        prims += _wall_item("north", wx, 0.86, 0.62, 0.03, 0.16, "window", "sill", _CABINET, "window_sill",
                            _S_LO, _S_HI)
    return prims


def _studio_kitchen() -> list[Primitive]:
    """Base cabinets with a counter top and wall cabinets in the north-west corner, boxes on the counter."""
    y1 = float(_S_HI[1])
    prims = _box((-3.4, y1 - 0.3, 0.45), (1.1, 0.3, 0.45), "cabinet", "lacquer", _CABINET, skip=("-z", "+y", "-x"),
                 name="cabinet")
    prims += _box((-3.4, y1 - 0.31, 0.915), (1.1, 0.31, 0.015), "cabinet", "wood", _COUNTER, skip=("+y", "-x"),
                  name="cabinet_top")
    prims += _box((-3.5, y1 - 0.18, 1.85), (1.0, 0.18, 0.35), "cabinet", "lacquer", _CABINET, skip=("+y", "-x"),
                  name="cabinet_upper")
    prims += _box((-3.95, y1 - 0.3, 0.99), (0.12, 0.1, 0.06), "box", "book", (0.80, 0.55, 0.25), skip=("-z",),
                  name="cab_box")
    prims += _box((-2.75, y1 - 0.25, 0.97), (0.09, 0.07, 0.04), "box", "book", (0.25, 0.45, 0.70), skip=("-z",),
                  name="cab_box2")
    return prims


def studio_layout() -> list[Primitive]:
    """All surface primitives of the studio flat (fixed layout; see the module docstring)."""
    lo, hi = _S_LO, _S_HI
    prims = _studio_shell()
    fp = _STUDIO_FOOTPRINTS
    r = fp["rug"]
    prims.append(_rect(((r[0] + r[2]) / 2, (r[1] + r[3]) / 2, 0.008), _X, _Y, (r[2] - r[0]) / 2, (r[3] - r[1]) / 2,
                       "rug", "rug", _RUG, (), "rug"))
    prims += _sofa(4.0, 0.0, 180.0)
    prims += _table_yaw(2.55, 0.0, 0.28, 0.5, 0.42, 0.04, 0.05, 0.0, "coffee_table")
    prims += _box((2.6, 0.25, 0.46), (0.1, 0.13, 0.04), "box", "book", (0.85, 0.80, 0.30), 30.0, skip=("-z",),
                  name="coffee_box")
    # dining table turned by 15 degrees with a chair at each end, facing it
    prims += _table_yaw(0.0, 1.35, 0.55, 0.35, 0.75, 0.04, 0.06, 15.0, "dining_table")
    prims += _chair(0.82, 1.57, 195.0, "chair_e")
    prims += _chair(-0.82, 1.13, 15.0, "chair_w")
    # desk against the south wall with a chair and a box
    prims += _table_yaw(-1.5, -1.925, 0.7, 0.325, 0.74, 0.03, 0.04, 0.0, "desk")
    prims += _chair(-1.5, -1.3, -90.0, "chair_desk")
    prims += _box((-1.0, -2.0, 0.80), (0.12, 0.09, 0.06), "box", "book", (0.75, 0.20, 0.15), -10.0, skip=("-z",),
                  name="desk_box")
    prims += _studio_kitchen()
    prims += _studio_shelf()
    # moving boxes on the floor by the door
    prims += _box((-2.6, -1.88, 0.2), (0.25, 0.22, 0.2), "box", "book", _CARDBOARD, 10.0, skip=("-z",),
                  name="floor_box")
    prims += _box((-2.62, -1.86, 0.52), (0.18, 0.15, 0.12), "box", "book", _CARDBOARD, -15.0, skip=("-z",),
                  name="floor_box")
    prims += _floor_lamp(4.1, 1.85, 1.7, "lamp_ne")
    prims += _floor_lamp(-4.1, -1.75, 1.55, "lamp_sw")
    prims += _plant(4.05, -1.8, 0.2, 0.4, 0.4, "plant_se")
    prims += _plant(1.75, 1.85, 0.17, 0.32, 0.34, "plant_n")
    prims += _plant(-4.1, 0.65, 0.15, 0.3, 0.3, "plant_w")
    prims += _wall_item("east", 0.0, 1.55, 0.6, 0.3, 0.02, "picture", "painting", (0.5, 0.5, 0.5), "picture_e",
                        lo, hi)
    prims += _wall_item("south", -1.5, 1.6, 0.35, 0.25, 0.02, "picture", "painting", (0.5, 0.5, 0.5), "picture_s",
                        lo, hi)
    prims += _wall_item("north", -1.6, 1.6, 0.3, 0.22, 0.02, "picture", "painting", (0.5, 0.5, 0.5), "picture_n",
                        lo, hi)
    for wall, along, z in (("south", 0.8, 0.3), ("south", -0.9, 1.0), ("north", 1.3, 0.3), ("north", -2.15, 1.1),
                           ("east", -1.4, 0.3), ("west", 1.3, 0.3)):
        prims += _wall_item(wall, along, z, 0.04, 0.06, 0.012, "outlet", "outlet", _OUTLET, f"outlet_{wall}", lo, hi)
    return prims


# ----------------------------------------------------------------------------------------------- layouts
def _check_layout(layout: str) -> str:
    if layout not in LAYOUTS:
        raise ValueError(f"unknown scene layout {layout!r}; expected one of {', '.join(LAYOUTS)}")
    return layout


def room_bounds(layout: str = "room") -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) interior corners (3,) of a layout's room, map frame metres (copies)."""
    if _check_layout(layout) == "studio":
        return STUDIO_MIN.copy(), STUDIO_MAX.copy()
    return ROOM_MIN.copy(), ROOM_MAX.copy()


def layout_primitives(layout: str = "room") -> list[Primitive]:
    """The surface primitives of a layout (``"room"``: :func:`indoor_layout`, ``"studio"``: :func:`studio_layout`)."""
    return studio_layout() if _check_layout(layout) == "studio" else indoor_layout()


def _window_wall(layout: str) -> tuple[int, float]:
    """(axis, interior coordinate) of the wall with the windows (for the baked window light)."""
    return (1, float(STUDIO_MAX[1])) if layout == "studio" else (0, float(ROOM_MAX[0]))


# ----------------------------------------------------------------------------------------------- sampling
def _r2(n: int, offset: np.ndarray) -> np.ndarray:
    """First n points (n, 2) in [0, 1)^2 of the R2 low-discrepancy sequence shifted by ``offset``."""
    a = np.array([1.0 / _PLASTIC, 1.0 / _PLASTIC ** 2])
    i = np.arange(1, n + 1, dtype=np.float64)[:, None]
    return np.mod(offset[None, :] + i * a[None, :], 1.0)


def _rect_points(p: Primitive, st: np.ndarray) -> np.ndarray:
    u = (2.0 * st[:, 0] - 1.0) * p.size[0]
    v = (2.0 * st[:, 1] - 1.0) * p.size[1]
    return p.center + u[:, None] * p.frame[:, 0] + v[:, None] * p.frame[:, 1]


def _in_holes(p: Primitive, pts: np.ndarray) -> np.ndarray:
    inside = np.zeros(len(pts), dtype=bool)
    for lo, hi in p.holes:
        inside |= np.all((pts >= np.asarray(lo)) & (pts <= np.asarray(hi)), axis=1)
    return inside


def _sample_primitive(p: Primitive, n: int, rng: np.random.Generator) -> dict[str, Any]:
    """Sample n surface points of primitive p.

    Returns dict: pos (n,3), normal (n,3), t1 (n,3) (unit tangent), uv (n,2) local texture coords in metres,
    spacing (scalar, m).
    """
    keep_frac = 1.0 - p.hole_fraction()
    m = int(math.ceil(n / max(keep_frac, 0.05) * 1.15)) + 16
    while True:
        st = _r2(m, rng.random(2))
        # small jitter (a tenth of a cell) so the pattern is not perfectly regular
        st = np.mod(st + rng.normal(0.0, 0.1 / math.sqrt(m), st.shape), 1.0)
        pos, normal, t1, uv = _map_primitive(p, st)
        if p.holes:
            ok = ~_in_holes(p, pos)
            pos, normal, t1, uv = pos[ok], normal[ok], t1[ok], uv[ok]
        if len(pos) >= n:
            break
        m *= 2
    spacing = math.sqrt(p.area * keep_frac / max(n, 1))
    return {"pos": pos[:n], "normal": normal[:n], "t1": t1[:n], "uv": uv[:n], "spacing": spacing}


def _map_primitive(p: Primitive, st: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Area-preserving map of unit-square samples onto the primitive: positions, normals, tangents, uv (m)."""
    e1, e2, e3 = p.frame[:, 0], p.frame[:, 1], p.frame[:, 2]
    n = len(st)
    if p.kind == "rect":
        u = (2.0 * st[:, 0] - 1.0) * p.size[0]
        v = (2.0 * st[:, 1] - 1.0) * p.size[1]
        pos = p.center + u[:, None] * e1 + v[:, None] * e2
        return pos, np.broadcast_to(e3, (n, 3)).copy(), np.broadcast_to(e1, (n, 3)).copy(), np.stack([u, v], 1)
    if p.kind == "cylinder":
        r, h = p.size
        th = 2.0 * math.pi * st[:, 0]
        z = (2.0 * st[:, 1] - 1.0) * h
        radial = np.cos(th)[:, None] * e1 + np.sin(th)[:, None] * e2
        pos = p.center + r * radial + z[:, None] * e3
        tang = -np.sin(th)[:, None] * e1 + np.cos(th)[:, None] * e2
        return pos, radial, tang, np.stack([r * th, z], 1)
    if p.kind == "disc":
        r = p.size[0]
        th = 2.0 * math.pi * st[:, 0]
        rho = r * np.sqrt(st[:, 1])
        x, y = rho * np.cos(th), rho * np.sin(th)
        pos = p.center + x[:, None] * e1 + y[:, None] * e2
        return pos, np.broadcast_to(e3, (n, 3)).copy(), np.broadcast_to(e1, (n, 3)).copy(), np.stack([x, y], 1)
    # ellipsoid: uniform on the unit sphere, then scaled
    a, b, c = p.size
    zc = 1.0 - 2.0 * st[:, 1]
    ph = 2.0 * math.pi * st[:, 0]
    rr = np.sqrt(np.maximum(0.0, 1.0 - zc * zc))
    unit = np.stack([rr * np.cos(ph), rr * np.sin(ph), zc], 1)
    local = unit * np.array([a, b, c])
    nrm_local = local / np.array([a, b, c]) ** 2
    nrm_local /= np.linalg.norm(nrm_local, axis=1, keepdims=True)
    pos = p.center + local @ p.frame.T
    normal = nrm_local @ p.frame.T
    ref = np.where(np.abs(normal[:, 2:3]) < 0.9, _Z[None, :], _X[None, :])
    tang = np.cross(ref, normal)
    tang /= np.linalg.norm(tang, axis=1, keepdims=True)
    return pos, normal, tang, np.stack([ph * a, zc * c], 1)


def _allocate(prims: list[Primitive], total: int) -> np.ndarray:
    """Gaussians per primitive: proportional to visible area, with a floor that keeps the sample spacing below
    ~2/5 of each primitive's smallest dimension (thin poles, small boxes); sums exactly to ``total``."""
    area = np.array([p.area * (1.0 - p.hole_fraction()) for p in prims])
    feat = np.array([p.feature_size for p in prims])
    n_min = np.maximum(4.0, area / (feat / 2.5) ** 2)
    if n_min.sum() >= total:
        want = n_min * (total / n_min.sum())
    else:
        lo, hi = 0.0, total / area.sum() * 2.0 + 1.0
        for _ in range(100):
            lam = 0.5 * (lo + hi)
            if np.maximum(n_min, lam * area).sum() > total:
                hi = lam
            else:
                lo = lam
        want = np.maximum(n_min, lo * area)
        want *= total / want.sum()
    counts = np.floor(want).astype(np.int64)
    rest = total - int(counts.sum())
    if rest > 0:
        order = np.argsort(-(want - counts), kind="stable")
        counts[order[:rest]] += 1
    return counts


# ----------------------------------------------------------------------------------------------- appearance
def _noise3(pos: np.ndarray, rng: np.random.Generator, freqs: tuple[float, ...], k: int = 6) -> np.ndarray:
    """Smooth procedural noise (sum of random plane waves) at positions (n, 3); roughly unit std."""
    out = np.zeros(len(pos))
    for f in freqs:
        d = rng.normal(size=(3, k))
        d /= np.linalg.norm(d, axis=0, keepdims=True)
        ph = rng.uniform(0, 2 * math.pi, k)
        out += np.sin(2 * math.pi * f * (pos @ d) + ph).sum(axis=1) / math.sqrt(k / 2) / math.sqrt(len(freqs))
    return out


def _hash01(k: np.ndarray, salt: int) -> np.ndarray:
    """Deterministic pseudo-random value in [0, 1) per integer (vectorised integer hash)."""
    x = (k.astype(np.int64) * 73856093 + salt * 19349663) & 0xFFFFFFFF
    x = (x ^ (x >> 13)) * 1274126177 & 0xFFFFFFFF
    x = x ^ (x >> 16)
    return (x & 0xFFFFFF) / float(0x1000000)


def _texture(p: Primitive, pos: np.ndarray, uv: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Per-Gaussian RGB in [0, 1] of primitive p (base colour x procedural pattern)."""
    n = len(pos)
    base = np.broadcast_to(np.asarray(p.color, float), (n, 3)).copy()
    u, v = uv[:, 0], uv[:, 1]
    mat = p.material
    if mat == "planks":
        plank_w = 0.18
        k = np.floor(v / plank_w)
        offset = np.floor(u / 1.2 + _hash01(k, 3) * 3.0)
        tone = 0.82 + 0.3 * _hash01(k * 31 + offset, 5)
        grain = 0.06 * np.sin(2 * math.pi * (v * 30.0 + 0.8 * _noise3(pos, rng, (1.5,))))
        seam = np.where(np.mod(v, plank_w) < 0.012, 0.6, 1.0)
        base *= (tone + grain)[:, None] * seam[:, None]
    elif mat in ("paint", "ceiling", "lacquer", "sill"):
        amp = {"paint": 0.05, "ceiling": 0.03, "lacquer": 0.02, "sill": 0.02}[mat]
        base *= (1.0 + amp * _noise3(pos, rng, (0.6, 2.5)))[:, None]
        if mat == "lacquer":  # door seams / handles of the cabinet front
            seam = (np.abs(np.mod(u + 0.2, 0.4) - 0.2) < 0.01) | (np.abs(v) < 0.008)
            base[seam] *= 0.55
    elif mat == "wood" or mat == "door":
        grain = np.sin(2 * math.pi * (v * 18.0 + 1.5 * _noise3(pos, rng, (2.0,))))
        base *= (0.92 + 0.09 * grain + 0.04 * _noise3(pos, rng, (6.0,)))[:, None]
        if mat == "door":  # panels and a handle
            panel = (np.abs(np.abs(u) - 0.3) < 0.02) | (np.abs(np.abs(v) - 0.5) < 0.02)
            base[panel] *= 0.7
            handle = (np.abs(u - 0.33) < 0.05) & (np.abs(v + 0.02) < 0.03)
            base[handle] = (0.75, 0.72, 0.6)
    elif mat == "fabric":
        weave = 0.03 * np.sin(2 * math.pi * u * 40.0) * np.sin(2 * math.pi * v * 40.0)
        base *= (0.95 + 0.06 * _noise3(pos, rng, (3.0, 9.0)) + weave)[:, None]
    elif mat == "rug":
        border = (np.abs(u) > p.size[0] - 0.15) | (np.abs(v) > p.size[1] - 0.15)
        diamond = np.sin(2 * math.pi * (u + v) / 0.35) * np.sin(2 * math.pi * (u - v) / 0.35) > 0
        alt = np.array([0.85, 0.70, 0.45])
        base = np.where(diamond[:, None], base, alt * 0.8)
        base[border] = (0.18, 0.16, 0.30)
        base *= (0.95 + 0.05 * _noise3(pos, rng, (8.0,)))[:, None]
    elif mat == "glass":
        sky = np.stack([0.62 + 0.1 * v, 0.76 + 0.08 * v, 0.95 + 0.02 * v], 1)
        cloud = np.clip(_noise3(pos, rng, (1.2, 3.0)), 0, None)[:, None]
        base = sky * (1 - 0.35 * np.minimum(cloud, 1)) + 0.35 * np.minimum(cloud, 1) * 0.98
        frame = (np.abs(u) < 0.025) | (np.abs(v) < 0.025) | (np.abs(u) > p.size[0] - 0.04) | \
            (np.abs(v) > p.size[1] - 0.04)
        base[frame] = (0.95, 0.95, 0.94)
    elif mat == "painting":
        pal = rng.uniform(0.1, 0.95, (3, 3))
        w = np.stack([_noise3(pos, rng, (2.0, 5.0)) for _ in range(3)], 1)
        w = np.exp(1.5 * w)
        w /= w.sum(1, keepdims=True)
        base = w @ pal
        frame = (np.abs(u) > p.size[0] - 0.04) | (np.abs(v) > p.size[1] - 0.04)  # wooden frame band
        base[frame] = (0.30, 0.20, 0.12)
    elif mat == "outlet":
        slot = ((np.abs(np.abs(u) - 0.02) < 0.006) & (np.abs(v) < 0.012))
        base[slot] = (0.15, 0.15, 0.15)
    elif mat == "metal":
        base *= (0.9 + 0.15 * _noise3(pos, rng, (5.0,)))[:, None]
    elif mat == "shade":
        base *= (1.0 + 0.03 * _noise3(pos, rng, (10.0,)))[:, None]
    elif mat == "pot":
        base *= (0.92 + 0.08 * np.sin(2 * math.pi * v * 12.0))[:, None]
    elif mat == "soil":
        base *= (0.85 + 0.25 * rng.random(n))[:, None]
    elif mat == "leaf":
        g = rng.random(n)
        base = np.stack([0.10 + 0.20 * g, 0.30 + 0.30 * g, 0.08 + 0.12 * rng.random(n)], 1)
    elif mat == "book":
        base *= (0.9 + 0.1 * np.sin(2 * math.pi * v * 8.0) + 0.04 * _noise3(pos, rng, (10.0,)))[:, None]
    base *= (1.0 + rng.normal(0.0, 0.025, (n, 1)))
    return base


def _shade(colors: np.ndarray, pos: np.ndarray, normal: np.ndarray,
           window_wall: tuple[int, float] = (0, float(ROOM_MAX[0]))) -> np.ndarray:
    """Bake soft lighting: a ceiling/window key light, ambient term and darkening near the floor corners.

    ``window_wall`` = (axis, coordinate) of the interior side of the wall with the windows (a max wall: the
    light falls off with ``coordinate - pos[:, axis]``); the room's is the east wall x = 4."""
    light = np.array([0.45, 0.2, 0.87])
    light /= np.linalg.norm(light)
    lam = np.abs(normal @ light)  # two-sided (Gaussians have no facing)
    axis, coord = window_wall
    window = 0.12 * np.exp(-(coord - pos[:, axis]) / 2.5)
    corner = 1.0 - 0.12 * np.exp(-pos[:, 2] / 0.25) * (np.abs(normal[:, 2]) < 0.5)
    f = (0.70 + 0.30 * lam + window) * corner
    return np.clip(colors * f[:, None], 0.0, 1.0)


# ----------------------------------------------------------------------------------------------- assembly
def _frames_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """Quaternions (n, 4) (w, x, y, z) of rotation matrices (n, 3, 3) (Shepperd, vectorised)."""
    from ..engine.camera import matrix_to_quaternion_xyzw

    q = matrix_to_quaternion_xyzw(R)
    return np.concatenate([q[:, 3:4], q[:, :3]], axis=1)


@dataclass
class SceneArrays:
    """Activated per-Gaussian arrays of the demo scene (N Gaussians, map frame, metres).

    Attributes:
        means (N, 3), scales (N, 3) standard deviations (scale[:, 2] is the one along the surface normal),
        quats_wxyz (N, 4), opacities (N,), colors (N, 3) RGB in [0, 1], class_ids (N,) int64,
        primitive_ids (N,) int64 index into ``primitives``, normals (N, 3) unit surface normals.
    """

    means: np.ndarray
    scales: np.ndarray
    quats_wxyz: np.ndarray
    opacities: np.ndarray
    colors: np.ndarray
    class_ids: np.ndarray
    primitive_ids: np.ndarray
    normals: np.ndarray
    primitives: list[Primitive] = field(default_factory=list)


def build_scene_arrays(num_gaussians: int, seed: int = 0, layout: str = "room") -> SceneArrays:
    """Sample a demo layout (:data:`LAYOUTS`; default the shipped room) with exactly ``num_gaussians`` Gaussians
    (deterministic for ``seed``; the room's arrays do not depend on the studio's existence)."""
    num_gaussians = int(num_gaussians)
    prims = layout_primitives(layout)
    window_wall = _window_wall(layout)
    if num_gaussians < 4 * len(prims):
        raise ValueError(f"num_gaussians must be >= {4 * len(prims)} for the demo {layout}, got {num_gaussians}")
    counts = _allocate(prims, num_gaussians)
    root = np.random.default_rng(seed)
    child_seeds = root.integers(0, 2**63 - 1, size=len(prims))
    parts: dict[str, list[np.ndarray]] = {k: [] for k in ("pos", "normal", "t1", "sig", "col", "cls", "pid")}
    for i, (p, n) in enumerate(zip(prims, counts)):
        if n == 0:
            continue
        rng = np.random.default_rng(int(child_seeds[i]))
        smp = _sample_primitive(p, int(n), rng)
        pos, normal, t1 = smp["pos"], smp["normal"], smp["t1"]
        spacing = smp["spacing"]
        if p.foliage:
            # leaves: scattered in a shell, randomly oriented, less flat, more translucent
            pos = p.center + (pos - p.center) * rng.uniform(0.65, 1.0, (n, 1))
            rand = rng.normal(size=(n, 3))
            normal = rand / np.linalg.norm(rand, axis=1, keepdims=True)
            ref = np.where(np.abs(normal[:, 2:3]) < 0.9, _Z[None, :], _X[None, :])
            t1 = np.cross(ref, normal)
            t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
            sig_in = spacing * rng.uniform(0.7, 1.1, n)
        else:
            sig_in = spacing * rng.uniform(0.6, 0.8, n)
            # reconstruction noise: a millimetre-scale offset along the normal
            pos = pos + normal * rng.normal(0.0, 0.0015, (n, 1))
        # random in-plane rotation and anisotropy
        psi = rng.uniform(0, math.pi, n)
        t2 = np.cross(normal, t1)
        a1 = np.cos(psi)[:, None] * t1 + np.sin(psi)[:, None] * t2
        aniso = np.exp(rng.uniform(0.0, math.log(2.2), n))
        sig1 = sig_in * np.sqrt(aniso)
        sig2 = sig_in / np.sqrt(aniso)
        thin = rng.uniform(0.04, 0.12, n) if not p.foliage else rng.uniform(0.15, 0.3, n)
        sig_n = np.maximum(np.minimum(sig1, sig2) * thin, 5e-4)
        col = _shade(_texture(p, pos, smp["uv"], rng), pos, normal, window_wall)
        parts["pos"].append(pos)
        parts["normal"].append(normal)
        parts["t1"].append(a1)
        parts["sig"].append(np.stack([sig1, sig2, sig_n], 1))
        parts["col"].append(col)
        parts["cls"].append(np.full(n, p.class_id, dtype=np.int64))
        parts["pid"].append(np.full(n, i, dtype=np.int64))
    pos = np.concatenate(parts["pos"])
    normal = np.concatenate(parts["normal"])
    a1 = np.concatenate(parts["t1"])
    a2 = np.cross(normal, a1)
    R = np.stack([a1, a2, normal], axis=2)  # columns: axis 0, 1 in plane, axis 2 = normal
    quats = _frames_to_quat_wxyz(R)
    # opacities: mostly high (Beta(5, 1.2) in [0.05, 0.99]), 7% faint Gaussians (Beta(1.5, 4))
    orng = np.random.default_rng([seed, 1])
    op = 0.05 + 0.94 * orng.beta(5.0, 1.2, num_gaussians)
    faint = orng.random(num_gaussians) < 0.07
    op[faint] = 0.05 + 0.9 * orng.beta(1.5, 4.0, int(faint.sum()))
    return SceneArrays(
        means=pos, scales=np.concatenate(parts["sig"]), quats_wxyz=quats, opacities=op,
        colors=np.clip(np.concatenate(parts["col"]), 0.0, 1.0), class_ids=np.concatenate(parts["cls"]),
        primitive_ids=np.concatenate(parts["pid"]), normals=normal, primitives=prims,
    )


def build_indoor_scene(num_gaussians: int, seed: int = 0, layout: str = "room"
                       ) -> tuple["GaussianModel", np.ndarray]:
    """The demo room (or another layout) as a splat model.

    Args:
        num_gaussians: exact number N of Gaussians (>= ~1000; the demo uses ~50k, benchmarks up to 1M+).
        seed: sampling/texture seed; the furniture layout is fixed.
        layout: one of :data:`LAYOUTS`.
    Returns:
        (model, class_ids): an SH-degree-0 :class:`GaussianModel` in the map frame (metres) and the ground-truth
        class id (N,) int64 of every Gaussian (ids index :data:`CLASS_NAMES`).
    """
    from ..engine.gaussians import GaussianModel

    s = build_scene_arrays(num_gaussians, seed, layout)
    model = GaussianModel.from_activated(s.means, s.scales, s.quats_wxyz, s.opacities, s.colors)
    return model, s.class_ids
