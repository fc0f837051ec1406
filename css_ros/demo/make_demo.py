"""css_make_demo: render the procedural demo room along a robot trajectory and write a rosbag2 bag + PLY model.

Output layout (``--out``, default ``bags/demo``)::

    model.ply      INRIA 3DGS PLY of the room (SH degree 0) with an extra per-Gaussian ``class_id`` field
    classes.yaml   class names and palette (ClassSet format)
    bag/           rosbag2 bag (metadata.yaml + bag.mcap, zstd chunk compression; or sqlite3 .db3)
    README.md      what is inside and how it was made

Topics (all stamps of one frame identical; header frame ids "camera_optical" and "map"):
``/image`` rgb8, ``/segmentation`` mono8 (noisy), ``/segmentation_confidence`` 32FC1, ``/segmentation_gt``
mono8 (255 = no label), ``/camera_info`` sensor_msgs/CameraInfo, ``/pose`` geometry_msgs/PoseStamped
(T_map_cam of the optical frame). The output is byte-for-byte deterministic for given arguments.

``--scene`` picks the layout (``room``: the shipped 8 x 6 m room; ``studio``: a 9 x 4.5 m studio flat with the same
16 classes and its own path, see :mod:`css_ros.demo.scene`) and ``--errors`` the error model of
``/segmentation`` (``frame``: :mod:`css_ros.demo.segmentation_noise`, per-frame drifting errors plus a few
view-consistent rules; ``range``: :mod:`css_ros.demo.range_noise`, errors growing with depth and consistent
across views of a surface). The defaults (room, frame) write exactly what they wrote before these options
existed; other choices add a depth-band accuracy table to README.md.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal, Sequence

import numpy as np

from ..errors import CssError
from ..io.topics import BAG_CAMERA_FRAME, BAG_MAP_FRAME, BAG_START_NS, BAG_TOPICS
from .renderer import FOV_X_DEG, DemoRenderer, bag_in_place, camera_k, systematic_rule_masks
from .changes import DEFAULT_CHANGE, DEPTH_ENCODINGS
from .robot_demo import ROBOT_DEFAULTS, make_robot_demo

__all__ = ["DemoStats", "main", "make_demo"]
#: Defaults of the shipped demo (sized so bags/demo stays well under 15 MB and replays in well under 2 min).
DEFAULTS = {"num_gaussians": 50_000, "frames": 120, "width": 256, "height": 192}
ERROR_MODELS: tuple[str, ...] = ("frame", "range")  #: ``--errors`` choices (first = default)
SCENES: tuple[str, ...] = ("room", "studio")        #: ``--scene`` choices (first = default)


@dataclass
class DemoStats:
    """Summary of a generated demo (also written to README.md)."""

    frames: int
    width: int
    height: int
    num_gaussians: int
    num_classes: int
    duration_s: float
    noisy_pixel_error: float        # fraction of labelled pixels where /segmentation != /segmentation_gt
    noisy_error_p10_p90: tuple[float, float]
    unlabelled_fraction: float      # fraction of GT pixels = 255
    late_first_frame: int           # first frame of the trajectory's late phase (unseen south-west corner)
    bytes_total: int = 0
    seconds: float = 0.0
    errors: str = "frame"           # error model of /segmentation (ERROR_MODELS)
    scene: str = "room"             # scene layout (SCENES)
    #: (B, 2) (correct, labelled) pixel counts per depth band of range_noise.DEPTH_BANDS_M (None: not measured)
    band_counts: np.ndarray | None = None
    world: "WorldOptions | None" = None  # people, class change, depth topic (None: none)
    change_frame: int | None = None      # first frame of the class change
    person_frames: int = 0               # frames that show a person
    person_share: float = 0.0            # share of all pixels that show a person


def _dir_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


@dataclass
class _DemoFrame:
    """One frame's images before they are written (all (H, W); ``rgb`` (H, W, 3)).

    ``band_depth``: surface depth [m] for the depth-band table (None: not wanted); ``depth``: the splat's rendered
    depth [m] (NaN: none); ``changed``: the changed-class ground truth (None without a class change)."""

    rgb: np.ndarray
    gt: np.ndarray
    seg: np.ndarray
    conf: np.ndarray
    band_depth: np.ndarray | None
    depth: np.ndarray
    changed: np.ndarray | None


class _FrameErrors:
    """The per-frame corruption of one error model: ``labels(camera, frame) -> _DemoFrame``, with the class change
    (:class:`~css_ros.demo.changes.ClassChange`) as one more rule of the renderer, on in the biased labels and in
    the ground truth from its frame on."""

    def __init__(self, errors: str, model: Any, scene: Any, num_classes: int, seed: int, backend: str,
                 want_depth: bool, change: Any = None) -> None:
        from .range_noise import RangeNoise, SurfaceDepth
        from .scene import CLASS_NAMES
        from .segmentation_noise import DEFAULT_SYSTEMATIC, SegmentationNoise

        self.errors = errors
        self.rules = DEFAULT_SYSTEMATIC if errors == "frame" else ()
        masks, targets = systematic_rule_masks(scene, CLASS_NAMES, self.rules)
        self.change = change
        if change is not None:
            selected = scene.class_ids == change.source
            if any(np.any(m & selected) for m in masks):
                raise CssError(f"--change-class: the class {CLASS_NAMES[change.source]} is relabelled by a systematic "
                               "rule of the frame error model; choose another class or --errors range")
            masks, targets = [*masks, selected], [*targets, change.target]
        self.renderer = DemoRenderer(model, scene.class_ids, num_classes, masks, targets, backend=backend)
        self.noise = SegmentationNoise(CLASS_NAMES, seed=seed) if errors == "frame" else None
        self.range = RangeNoise(model, scene.class_ids, CLASS_NAMES, seed=seed) if errors == "range" else None
        self.surface = SurfaceDepth(model) if want_depth and self.range is None else None

    def labels(self, camera: Any, frame: int) -> _DemoFrame:
        off = [False] * len(self.rules)
        extra = [] if self.change is None else [frame >= self.change.frame]
        final = () if self.change is None else (*off, True)
        if self.range is not None:
            view = self.renderer.render_view(camera, truth=(*off, *extra), final=final)
            fr = self.range.apply(view.gt, camera, frame)
            return _DemoFrame(view.rgb, view.gt, fr.labels, fr.confidence, fr.depth, view.depth, view.changed)
        assert self.noise is not None
        active = [self.noise.systematic_active(frame, r, rule.probability) for r, rule in enumerate(self.rules)]
        view = self.renderer.render_view(camera, (*active, *extra), (*off, *extra), final)
        seg, conf = self.noise.apply(view.biased, frame)
        band = self.surface.depth(camera) if self.surface is not None else None
        return _DemoFrame(view.rgb, view.gt, seg, conf, band, view.depth, view.changed)


@dataclass(frozen=True)
class WorldOptions:
    """The changing world of a demo (:mod:`css_ros.demo.changes`): ``people`` walkers, a class change ``change``
    ("FROM:TO" or None) from ``change_frame`` (None: half way), and a ``/depth`` topic in ``depth`` encoding (None:
    none)."""

    people: int = 0
    change: str | None = None
    change_frame: int | None = None
    depth: str | None = None

    @property
    def any(self) -> bool:
        return bool(self.people or self.change or self.depth)


def make_demo(out: str | Path, num_gaussians: int = DEFAULTS["num_gaussians"], frames: int = DEFAULTS["frames"],
              width: int = DEFAULTS["width"], height: int = DEFAULTS["height"], seed: int = 0,
              storage: Literal["mcap", "sqlite3"] = "mcap", overwrite: bool = False, progress: bool = True,
              backend: str = "numba", errors: str = "frame", scene: str = "room",
              world: WorldOptions = WorldOptions()) -> DemoStats:
    """Generate the demo data set into ``out`` (see module docstring). Returns its :class:`DemoStats`.

    ``errors`` (:data:`ERROR_MODELS`) picks the error model of ``/segmentation``, ``scene`` (:data:`SCENES`) the
    layout, ``world`` the people, class change and depth topic; the defaults write the shipped demo.

    Raises:
        CssError: ``out/bag`` exists and ``overwrite`` is False, or invalid arguments.
    """
    from .changes import ClassChange, demo_class_set_with_people, walkers
    from .scene import build_scene_arrays, demo_class_set
    from ..engine.gaussians import GaussianModel
    from .trajectory import late_phase_start, robot_trajectory

    _check_args(errors, scene, frames, width, height, storage, world)
    t_start = time.perf_counter()
    out = Path(out)
    bag_dir = out / "bag"
    if bag_dir.exists() and not overwrite:
        raise CssError(f"{bag_dir} exists; pass --overwrite to regenerate it")
    room = demo_class_set()
    change = None if world.change is None else ClassChange.parse(world.change, room.names, world.change_frame, frames)
    out.mkdir(parents=True, exist_ok=True)

    arrays = build_scene_arrays(num_gaussians, seed, layout=scene)
    model = GaussianModel.from_activated(arrays.means, arrays.scales, arrays.quats_wxyz, arrays.opacities,
                                         arrays.colors)
    model = replace(model, normals=arrays.normals)  # the PLY's nx ny nz: true surface normals
    classes = demo_class_set_with_people(room) if world.people else room
    traj = robot_trajectory(frames, seed=seed, layout=scene)
    default_run = errors == ERROR_MODELS[0] and scene == SCENES[0] and not world.any
    corrupt = _FrameErrors(errors, model, arrays, room.num_classes, seed, backend, want_depth=not default_run,
                           change=change)
    info: dict[str, Any] = {"generator": "css_make_demo", "num_gaussians": num_gaussians, "frames": frames,
                            "width": width, "height": height, "seed": seed}
    if not default_run:  # the shipped demo's metadata stays byte-identical
        info.update(errors=errors, scene=scene)
    if world.any:
        info.update(people=world.people, change=None if change is None else world.change,
                    change_frame=None if change is None else change.frame, depth=world.depth)
    tally = _write_frames(out, storage, info, traj, corrupt, walkers(scene, world.people), classes, world,
                          (width, height), progress)
    model.to_ply(out / "model.ply", extra_fields={"class_id": arrays.class_ids.astype(np.uint8)})
    classes.to_yaml(out / "classes.yaml")
    late = int(np.argmax(traj.phase == 3)) if np.any(traj.phase == 3) else frames
    err = np.asarray(tally.error_rates)
    stats = DemoStats(
        frames=frames, width=width, height=height, num_gaussians=num_gaussians, num_classes=classes.num_classes,
        duration_s=float(traj.times[-1]), noisy_pixel_error=float(err.mean()),
        noisy_error_p10_p90=(float(np.percentile(err, 10)), float(np.percentile(err, 90))),
        unlabelled_fraction=tally.unlabelled / (frames * width * height), late_first_frame=late,
        errors=errors, scene=scene, band_counts=None if default_run else tally.bands,
        world=world, change_frame=None if change is None else change.frame,
        person_frames=tally.person_frames, person_share=tally.person_pixels / (frames * width * height),
    )
    (out / "README.md").write_text(_readme(stats, out, storage, seed, late_phase_start(scene)))
    stats.bytes_total = _dir_bytes(out)
    stats.seconds = time.perf_counter() - t_start
    return stats


def _check_args(errors: str, scene: str, frames: int, width: int, height: int, storage: str,
                world: WorldOptions) -> None:
    """Refuse invalid arguments (CssError naming the option)."""
    from .changes import DEPTH_ENCODINGS

    if errors not in ERROR_MODELS:
        raise CssError(f"--errors must be one of {', '.join(ERROR_MODELS)}, got {errors!r}")
    if scene not in SCENES:
        raise CssError(f"--scene must be one of {', '.join(SCENES)}, got {scene!r}")
    if frames < 2:
        raise CssError(f"--frames must be >= 2, got {frames}")
    if width < 16 or height < 16:
        raise CssError(f"image size must be at least 16x16, got {width}x{height}")
    if storage not in ("mcap", "sqlite3"):
        raise CssError(f"--storage must be mcap or sqlite3, got {storage!r}")
    if world.people < 0:
        raise CssError(f"--people must be >= 0, got {world.people}")
    if world.depth is not None and world.depth not in DEPTH_ENCODINGS:
        raise CssError(f"--depth-encoding must be one of {', '.join(DEPTH_ENCODINGS)}, got {world.depth!r}")
    if world.change_frame is not None and world.change is None:
        raise CssError("--change-frame needs --change-class")


@dataclass
class _Tally:
    """What the frame loop counts for DemoStats."""

    bands: np.ndarray
    error_rates: list = field(default_factory=list)
    unlabelled: int = 0
    person_frames: int = 0
    person_pixels: int = 0


def _write_frames(out: Path, storage: str, info: dict[str, Any], traj: Any, corrupt: _FrameErrors,
                  people: list, classes: Any, world: WorldOptions, size: tuple[int, int], progress: bool) -> _Tally:
    """Render, corrupt and write every frame of the bag (OUT/bag, written in place at the end)."""
    from ..engine.camera import Camera
    from .changes import encode_depth, overlay_people, people_depth
    from .range_noise import DEPTH_BANDS_M, depth_band_counts

    width, height = size
    stamps = BAG_START_NS + np.rint(traj.times * 1e3).astype(np.int64) * 1_000_000  # millisecond-aligned
    K = camera_k(width, height)
    tally = _Tally(np.zeros((len(DEPTH_BANDS_M) - 1, 2), dtype=np.int64))
    with bag_in_place(out, storage) as writer:
        writer.set_custom_data("css_ros.demo", json.dumps(info, sort_keys=True))
        with writer:
            frame_iter: Any = range(len(stamps))
            if progress:
                from tqdm import tqdm

                frame_iter = tqdm(frame_iter, desc="css_make_demo", unit="frame", file=sys.stderr)
            for i in frame_iter:
                cam = Camera(K, width, height, traj.T_map_cam[i])
                fr = corrupt.labels(cam, i)
                depth = fr.depth.astype(np.float64)
                if people:
                    person = people_depth(cam, people, float(traj.times[i]))
                    mask = overlay_people(person, depth, fr.seg, fr.conf, fr.rgb, classes.num_classes - 1)
                    depth = np.where(mask, person, depth)
                    tally.person_frames += bool(mask.any())
                    tally.person_pixels += int(mask.sum())
                stamp = int(stamps[i])
                writer.write_camera_info(BAG_TOPICS["camera_info"], K, width, height, stamp, BAG_CAMERA_FRAME)
                writer.write_pose(BAG_TOPICS["pose"], traj.positions[i], traj.quaternions_xyzw[i], stamp, BAG_MAP_FRAME)
                writer.write_image(BAG_TOPICS["image"], fr.rgb, "rgb8", stamp, BAG_CAMERA_FRAME)
                writer.write_image(BAG_TOPICS["segmentation"], fr.seg, "mono8", stamp, BAG_CAMERA_FRAME)
                writer.write_image(BAG_TOPICS["confidence"], fr.conf, "32FC1", stamp, BAG_CAMERA_FRAME)
                writer.write_image(BAG_TOPICS["gt"], fr.gt, "mono8", stamp, BAG_CAMERA_FRAME)
                if world.depth is not None:
                    writer.write_image(BAG_TOPICS["depth"], encode_depth(depth, world.depth), world.depth, stamp,
                                       BAG_CAMERA_FRAME)
                if fr.changed is not None:
                    writer.write_image(BAG_TOPICS["gt_changed"], fr.changed, "mono8", stamp, BAG_CAMERA_FRAME)
                valid = fr.gt != 255
                tally.unlabelled += int(np.count_nonzero(~valid))
                tally.error_rates.append(float(np.count_nonzero((fr.seg != fr.gt) & valid))
                                         / max(1, int(np.count_nonzero(valid))))
                if fr.band_depth is not None:
                    tally.bands += depth_band_counts(fr.seg, fr.gt, fr.band_depth)
    return tally


def _regen_command(s: DemoStats, out: Path, storage: str, seed: int) -> str:
    """The css_make_demo command line that regenerates this data set (only non-default options)."""
    cmd = "css_make_demo"
    defaults = {"num_gaussians": DEFAULTS["num_gaussians"], "frames": DEFAULTS["frames"], "width": DEFAULTS["width"],
                "height": DEFAULTS["height"], "seed": 0}
    args = {"num_gaussians": s.num_gaussians, "frames": s.frames, "width": s.width, "height": s.height, "seed": seed}
    cmd += f" --out {out.as_posix()}"
    for k, v in args.items():
        if v != defaults[k]:
            cmd += f" --{k.replace('_', '-')} {v}"
    if s.scene != SCENES[0]:
        cmd += f" --scene {s.scene}"
    if s.errors != ERROR_MODELS[0]:
        cmd += f" --errors {s.errors}"
    w = s.world
    if w is not None and w.people:
        cmd += f" --people {w.people}"
    if w is not None and w.change is not None:
        cmd += f" --change-class {w.change}"
        if w.change_frame is not None:
            cmd += f" --change-frame {w.change_frame}"
    if w is not None and w.depth is not None:
        cmd += " --depth" + (f" --depth-encoding {w.depth}" if w.depth != "32FC1" else "")
    if storage != "mcap":
        cmd += f" --storage {storage}"
    return cmd + " --overwrite"


def _world_topics_md(s: DemoStats) -> str:
    """The topic rows of the changing world (after the table's last row) and the frame-id line."""
    from .changes import PERSON_CLASS

    w = s.world
    rows = ""
    if w is not None and w.depth is not None:
        unit = "metres (NaN = none)" if w.depth == "32FC1" else "millimetres (0 = none)"
        rows += (f"| `/depth` | sensor_msgs/Image {w.depth} | depth along the optical axis in {unit}: the splat's "
                 "rendered depth" + (", the people in front" if w.people else "") + " |\n")
    if w is not None and w.change is not None:
        rows += ("| `/segmentation_gt_changed` | sensor_msgs/Image mono8 | the changing object's pixels with its class "
                 "at the end of the bag (255 elsewhere), in every frame |\n")
    note = ""
    if w is not None and w.people:
        note = (f"\nThe people are in `/segmentation` (class `{PERSON_CLASS}`), `/image` and `/depth`, never in "
                "`model.ply` nor in `/segmentation_gt` (the static ground truth: the room behind them).\n")
    return rows + "\nImage headers use frame id `camera_optical`.\n" + note + "\n"


def _world_md(s: DemoStats) -> str:
    """README section on the people and the class change (empty without them)."""
    from .changes import PERSON_RADII, WALKING_SPEED

    w = s.world
    if w is None or not (w.people or w.change):
        return ""
    lines = ["", "## A changing world", ""]
    if w.people:
        lines.append(f"- {w.people} people (upright ellipsoids {2 * PERSON_RADII[2]:.2f} m tall, "
                     f"{2 * PERSON_RADII[0]:.2f} m wide) walk to and fro along straight paths at {WALKING_SPEED:g} "
                     f"m/s; they show in {s.person_frames} of {s.frames} frames and on "
                     f"{100 * s.person_share:.2f} % of all pixels (counted as wrong in the accuracy above: the "
                     "ground truth is the room behind them).")
    if w.change is not None:
        src, dst = w.change.split(":")
        lines.append(f"- from frame {s.change_frame} on, every Gaussian of class `{src}` has class `{dst}` (same "
                     "geometry and colour) in `/segmentation` and `/segmentation_gt`; "
                     "`/segmentation_gt_changed` marks its pixels with the new class in every frame.")
    lines += ["", "Replay with `css_replay` (`--transient-classes person`, `--evidence-half-life H`): its report's "
              "section \"A changing world\" measures both."]
    return "\n".join(lines) + "\n"


def _choices_line(s: DemoStats) -> str:
    """One README line naming the scene and error model ("" for the shipped defaults, whose README predates it)."""
    if s.scene == SCENES[0] and s.errors == ERROR_MODELS[0]:
        return ""
    return (f"\nScene layout `{s.scene}` (`--scene`), error model of `/segmentation`: `{s.errors}` (`--errors`; "
            f"`frame` = per-frame drifting errors, `range` = errors growing with depth, consistent across views).\n")


def _readme(s: DemoStats, out: Path, storage: str, seed: int, late_wp: int) -> str:
    cmd = _regen_command(s, out, storage, seed)
    rate = (s.frames - 1) / s.duration_s
    scene = _ROOM_SCENE_MD if s.scene == "room" else _STUDIO_SCENE_MD
    traj = _traj_room_md(s, late_wp) if s.scene == "room" else _traj_studio_md(s, late_wp)
    noise = _NOISE_FRAME_MD if s.errors == "frame" else _NOISE_RANGE_MD
    return f"""# css_ros demo data

Generated by `css_make_demo` (module `css_ros.demo.make_demo`); regenerate with

    {cmd}

The output is deterministic: with the same software versions the same command writes the same bytes.
{_choices_line(s)}
## Content

| file | what |
|---|---|
| `model.ply` | INRIA 3DGS PLY, {s.num_gaussians} Gaussians, SH degree 0, extra field `class_id` \
(ground truth per Gaussian), surface normals in `nx ny nz` |
| `classes.yaml` | {s.num_classes} classes (id, name, colour) |
| `bag/` | rosbag2 ({storage}), {s.frames} frames of {s.width}x{s.height}, {s.duration_s:.1f} s ({rate:.2f} frames/s) |

Topics (one message per frame each, all with the frame's stamp):

| topic | type | content |
|---|---|---|
| `/image` | sensor_msgs/Image rgb8 | colour rendered from `model.ply` |
| `/segmentation` | sensor_msgs/Image mono8 | noisy segmentation (class ids), imitating a network |
| `/segmentation_confidence` | sensor_msgs/Image 32FC1 | per-pixel confidence in [0, 1] of the noisy segmentation |
| `/segmentation_gt` | sensor_msgs/Image mono8 | ground-truth labels (255 = no surface) |
| `/camera_info` | sensor_msgs/CameraInfo | pinhole K, {FOV_X_DEG:.0f} deg horizontal FoV, no distortion |
| `/pose` | geometry_msgs/PoseStamped | T_map_cam of the optical frame (z forward, x right, y down), frame `map` |
""" + _world_topics_md(s) + scene + traj + noise + _stats_md(s) + _bands_md(s) + _world_md(s)


_ROOM_SCENE_MD = """## Scene

A furnished 8 m x 6 m x 2.7 m room (map frame: x east, y north, z up): wooden floor with a rug, painted walls
and ceiling, door, window, dining table with four chairs, sofa and coffee table, bookshelf with boxes,
cabinet, two floor lamps (thin poles), two potted plants, three pictures and five wall outlets. Gaussians
lie on the surfaces: flattened (normal-axis standard deviation 4-12 % of the in-plane ones), oriented with the
surface, spread by a low-discrepancy sequence with density set by area and a minimum for thin parts, opacities
Beta-distributed (mostly 0.8-0.99, 7 % faint), colours from textured materials (planks, grain, fabric, rug
pattern, paintings, sky) with baked shading.

"""


def _traj_room_md(s: DemoStats, late_wp: int) -> str:
    return f"""## Trajectory

A mobile robot's camera at ~1 m height, looking slightly down, moving at ~0.5 m/s and turning at ~35 deg/s:
first the east half and the north side, then revisits of the sofa and the dining table from new viewpoints,
and from frame {s.late_first_frame} on (waypoint {late_wp}) the south-west corner with the bookshelf and a
plant, which is not seen before.

"""


_NOISE_FRAME_MD = """## Noise model of `/segmentation`

Documented in `css_ros/demo/segmentation_noise.py`; seeded and deterministic. Errors come in six kinds:

- view-consistent (systematic) confusions attached to surfaces during stretches of frames, rendered from the
  splat: the cabinet labelled shelf, the top band of the walls labelled ceiling, the books labelled shelf,
  the door labelled wall, the window sill labelled wall (fusion cannot average these away);
- a per-frame severity (smooth drift plus occasional bad frames) scaling the 2D errors below;
- missing small objects: outlets, pictures, boxes, lamps replaced by their surroundings;
- look-alike confusions from a fixed confusion table (wall/ceiling, table/shelf/cabinet, chair/sofa,
  rug/floor, picture/window, ...), concentrated next to the look-alike class, sometimes over a whole object;
- blobs of wrong labels;
- wobbling and jittered class boundaries.

All random fields are smooth in space and evolve smoothly over frames. The confidence is high in clean
interiors and lower at boundaries and over most 2D-corrupted regions, but some errors are confident and the
systematic ones are not flagged at all.

"""


def _stats_md(s: DemoStats) -> str:
    return f"""On this data set the noisy segmentation disagrees with the ground truth on {100 * s.noisy_pixel_error:.1f} % \
of the labelled pixels (10th-90th percentile over frames: {100 * s.noisy_error_p10_p90[0]:.1f}-\
{100 * s.noisy_error_p10_p90[1]:.1f} %); {100 * s.unlabelled_fraction:.2f} % of the pixels have no ground truth.
"""


_STUDIO_SCENE_MD = """## Scene

A studio flat of 9 m x 4.5 m x 2.6 m (map frame: x east, y north, z up), furnished with the same 16 classes as
the demo room but laid out differently: a sofa against the east wall facing west with a rug and a coffee table
turned by 90 degrees in front of it, a dining table turned by 15 degrees with two chairs under two north windows,
a desk with a chair against the south wall, a kitchen row (base cabinets with a counter, wall cabinets) in the
north-west corner, a bookshelf with books and boxes on the west wall, the door in the south wall, moving boxes
on the floor, two floor lamps, three plants, three pictures and six outlets. Gaussians are made as in the
room (flattened, oriented with the surface, low-discrepancy spread, Beta opacities, textured materials with
baked shading; the window light comes from the north).

"""


def _traj_studio_md(s: DemoStats, late_wp: int) -> str:
    return f"""## Trajectory

A mobile robot's camera at ~1 m height along the free corridor in the middle of the flat (~0.5 m/s, ~28 deg/s
turns), alternating close looks (< 1.5 m) with views along the long axis (far walls 5-8 m away): the living
corner at the east end, a long view west across the flat, the dining table and the desk from close by, and
from frame {s.late_first_frame} on (waypoint {late_wp}) the west end seen close for the first time (moving boxes,
door, bookshelf, kitchen), then a long view back east.

"""


_NOISE_RANGE_MD = """## Noise model of `/segmentation`

Documented in `css_ros/demo/range_noise.py`; seeded and deterministic. It imitates a network whose errors grow
with the distance of the surface and repeat in every view of it:

- each Gaussian is wrong in a view when a smooth 3D random field u(x) (uniform in [0, 1], correlation length
  0.3 m, fixed for the whole bag) is below the error probability
  p_err(d) = min(0.95, s_t * 0.8 * sigmoid(2 ln(d / 2.4 m) + bias_class)) of its camera depth d: the same far
  surface is wrong in every far view and right in the near ones (no fusion of far views can undo it);
- class offsets: floor, wall, ceiling better; small objects (outlet, picture, lamp, box, plant) worse; s_t is a
  mild per-frame severity (log-normal, std 0.15);
- the wrong label is fixed per surface patch (second field, 1 m): small objects mostly become the class they
  sit on (outlet, picture -> wall; box -> shelf / table), other classes a look-alike class
  (wall -> ceiling / cabinet / door, floor -> rug, cabinet -> shelf, chair -> sofa / table, ...);
- per frame on top: small blobs of look-alike labels (~2 % of the image) and 1-2 px boundary jitter.

The confidence is an overconfident network's: lower at label boundaries, slightly lower with depth and near a
surface's wrong/right transition, low on half of the per-frame blobs; far wrong patches stay confident.

"""


def _bands_md(s: DemoStats) -> str:
    """Accuracy of /segmentation per depth band (empty when not measured)."""
    if s.band_counts is None:
        return ""
    from .range_noise import DEPTH_BANDS_M, band_label

    counts = np.asarray(s.band_counts)
    total = max(1, int(counts[:, 1].sum()))
    lines = ["", "## Accuracy by depth", "",
             f"Input pixel accuracy (`/segmentation` == `/segmentation_gt` over labelled pixels): "
             f"{100 * counts[:, 0].sum() / total:.1f} %. Per band of surface depth (camera z, metres):", "",
             "| depth | share of labelled pixels | accuracy |", "|---|---|---|"]
    for k in range(len(counts)):
        acc = f"{100 * counts[k, 0] / counts[k, 1]:.1f} %" if counts[k, 1] else "-"
        lines.append(f"| {band_label(DEPTH_BANDS_M[k], DEPTH_BANDS_M[k + 1])} | "
                     f"{100 * counts[k, 1] / total:.1f} % | {acc} |")
    return "\n".join(lines) + "\n"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="css_make_demo",
        description="Generate the procedural demo room (3DGS PLY), a robot trajectory and a rosbag2 bag with "
                    "RGB, noisy segmentation, confidence, ground truth, camera info and poses.")
    p.add_argument("--out", type=Path, default=None,
                   help="output directory (default: bags/demo; with --robot: bags/robot_demo)")
    p.add_argument("--robot", action="store_true",
                   help="the robot-like demo: nav_msgs/Odometry of base_link at 100 Hz, two cameras (front, left) "
                        "with extrinsics and their own stamps, segmentation 0.25 s late, the splat in its own "
                        "scaled and rotated frame, and a css_node.yaml with the matching parameters")
    p.add_argument("--tf", action="store_true",
                   help="with --robot: poses on /tf and /tf_static (map -> odom -> base_link -> <camera>_link -> "
                        "<camera>_optical) instead of the Odometry topic, and pose_source: tf in css_node.yaml")
    p.add_argument("--num-gaussians", type=int, default=None, metavar="N",
                   help=f"Gaussians in the room ({DEFAULTS['num_gaussians']})")
    p.add_argument("--frames", type=int, default=None, metavar="F",
                   help=f"frames along the trajectory ({DEFAULTS['frames']}; with --robot "
                        f"{ROBOT_DEFAULTS['frames']} per camera)")
    p.add_argument("--width", type=int, default=None, metavar="W",
                   help=f"image width in pixels ({DEFAULTS['width']}; with --robot {ROBOT_DEFAULTS['width']})")
    p.add_argument("--height", type=int, default=None, metavar="H",
                   help=f"image height in pixels ({DEFAULTS['height']}; with --robot {ROBOT_DEFAULTS['height']})")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="seed of scene sampling, noise and path (0)")
    p.add_argument("--scene", choices=SCENES, default=SCENES[0],
                   help="scene layout: room (the shipped 8 x 6 m room) or studio (a 9 x 4.5 m studio flat with the "
                        "same 16 classes, its own path) (room)")
    p.add_argument("--errors", choices=ERROR_MODELS, default=ERROR_MODELS[0],
                   help="error model of /segmentation: frame (per-frame drifting errors plus a few view-consistent "
                        "rules) or range (errors growing with depth, consistent across views of a surface) (frame)")
    g = p.add_argument_group("a changing world (not with --robot)")
    g.add_argument("--people", type=int, default=0, metavar="N",
                   help="N people walking through the room (class 'person', appended to the class file): in the "
                        "segmentation, colour and depth images, never in the splat nor in /segmentation_gt (0)")
    g.add_argument("--change-class", nargs="?", const=DEFAULT_CHANGE, default=None, metavar="FROM:TO",
                   help=f"every Gaussian of class FROM has class TO from --change-frame on (same geometry), in "
                        f"/segmentation and /segmentation_gt; /segmentation_gt_changed marks its pixels "
                        f"(without a value: {DEFAULT_CHANGE})")
    g.add_argument("--change-frame", type=int, default=None, metavar="K",
                   help="first frame of the class change (default: half way, frames // 2)")
    g.add_argument("--depth", action="store_true",
                   help="write /depth: the splat's rendered depth along the optical axis, people in front")
    g.add_argument("--depth-encoding", choices=DEPTH_ENCODINGS, default=DEPTH_ENCODINGS[0],
                   help="32FC1 metres or 16UC1 millimetres (32FC1)")
    p.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap", help="rosbag2 storage (mcap)")
    p.add_argument("--backend", choices=("numba", "torch"), default="numba", help="rasteriser backend (numba)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing OUT/bag")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


#: Bytes per pixel of one frame's images before compression: rgb8 image, mono8 segmentation and GT, 32FC1 confidence.
RAW_BYTES_PER_PIXEL = 3 + 1 + 1 + 4
#: Compressed bag size / raw image bytes, measured on the shipped demo (an 8.2 MB bag for 120 frames of 256 x 192).
TYPICAL_COMPRESSION = 0.16


def size_estimate(num_gaussians: int, frames: int, width: int, height: int) -> str:
    """One line announcing the size of the data set about to be generated (the progress bar then shows the ETA)."""
    raw = frames * width * height * RAW_BYTES_PER_PIXEL
    line = (f"css_make_demo: {frames} frames of {width}x{height} from {num_gaussians} Gaussians: "
            f"{raw / 1e6:.0f} MB of images, a bag of about {raw * TYPICAL_COMPRESSION / 1e6:.0f} MB")
    if raw * TYPICAL_COMPRESSION > 1e9:
        line += " (large: check the free disk space; the progress bar shows the time left)"
    return line


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point; returns the process exit code (0 ok, 2 usage/CssError)."""
    args = build_parser().parse_args(argv)
    defaults = ROBOT_DEFAULTS if args.robot else DEFAULTS
    for name in ("num_gaussians", "frames", "width", "height"):
        if getattr(args, name) is None:
            setattr(args, name, defaults[name])
    if args.out is None:
        args.out = Path("bags") / ("robot_demo" if args.robot else "demo")
    if args.tf and not args.robot:
        print("css_make_demo: error: --tf needs --robot", file=sys.stderr)
        return 2
    world = WorldOptions(args.people, args.change_class, args.change_frame,
                         args.depth_encoding if args.depth else None)
    if args.robot and (args.scene != SCENES[0] or args.errors != ERROR_MODELS[0] or world.any
                       or args.change_frame is not None):
        print("css_make_demo: error: --robot supports only --scene room --errors frame (no people, class change "
              "or depth)", file=sys.stderr)
        return 2
    if args.robot:
        try:
            info = make_robot_demo(args.out, num_gaussians=args.num_gaussians, frames=args.frames,
                                   width=args.width, height=args.height, seed=args.seed, overwrite=args.overwrite,
                                   progress=not args.quiet, tf=args.tf)
        except (CssError, ValueError) as exc:
            print(f"css_make_demo: error: {exc}", file=sys.stderr)
            return 2
        print(f"wrote {args.out}: {info['frames_per_camera']} frames per camera ({', '.join(info['cameras'])}), "
              f"{info['odometry_messages']} {'/tf' if args.tf else 'odometry'} messages "
              f"over {info['duration_s']:.0f} s; replay it with "
              f"css_replay {args.out / 'bag'}")
        return 0
    if not args.quiet:
        print(size_estimate(args.num_gaussians, args.frames, args.width, args.height), file=sys.stderr)
    try:
        stats = make_demo(args.out, num_gaussians=args.num_gaussians, frames=args.frames, width=args.width,
                          height=args.height, seed=args.seed, storage=args.storage, overwrite=args.overwrite,
                          progress=not args.quiet, backend=args.backend, errors=args.errors, scene=args.scene,
                          world=world)
    except (CssError, ValueError) as exc:
        print(f"css_make_demo: error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {args.out} ({stats.bytes_total / 1e6:.1f} MB, {stats.frames} frames {stats.width}x{stats.height}, "
          f"{stats.num_gaussians} Gaussians, noisy pixel error {100 * stats.noisy_pixel_error:.1f} %) "
          f"in {stats.seconds:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
