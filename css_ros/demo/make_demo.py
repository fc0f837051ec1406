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
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Literal, Sequence

import numpy as np

from ..errors import CssError
from ..io.topics import BAG_CAMERA_FRAME, BAG_MAP_FRAME, BAG_START_NS, BAG_TOPICS
from .renderer import FOV_X_DEG, DemoRenderer, bag_in_place, camera_k, systematic_rule_masks
from .robot_demo import ROBOT_DEFAULTS, make_robot_demo

__all__ = ["DemoStats", "main", "make_demo"]
#: Defaults of the shipped demo (sized so bags/demo stays well under 15 MB and replays in well under 2 min).
DEFAULTS = {"num_gaussians": 50_000, "frames": 120, "width": 256, "height": 192}


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


def _dir_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def make_demo(out: str | Path, num_gaussians: int = DEFAULTS["num_gaussians"], frames: int = DEFAULTS["frames"],
              width: int = DEFAULTS["width"], height: int = DEFAULTS["height"], seed: int = 0,
              storage: Literal["mcap", "sqlite3"] = "mcap", overwrite: bool = False, progress: bool = True,
              backend: str = "numba") -> DemoStats:
    """Generate the demo data set into ``out`` (see module docstring). Returns its :class:`DemoStats`.

    Raises:
        CssError: ``out/bag`` exists and ``overwrite`` is False, or invalid arguments.
    """
    from ..engine.camera import Camera
    from .scene import CLASS_NAMES, build_scene_arrays, demo_class_set
    from ..engine.gaussians import GaussianModel
    from .segmentation_noise import DEFAULT_SYSTEMATIC, SegmentationNoise
    from .trajectory import LATE_PHASE_START, robot_trajectory

    if frames < 2:
        raise CssError(f"--frames must be >= 2, got {frames}")
    if width < 16 or height < 16:
        raise CssError(f"image size must be at least 16x16, got {width}x{height}")
    if storage not in ("mcap", "sqlite3"):
        raise CssError(f"--storage must be mcap or sqlite3, got {storage!r}")
    t_start = time.perf_counter()
    out = Path(out)
    bag_dir = out / "bag"
    if bag_dir.exists() and not overwrite:
        raise CssError(f"{bag_dir} exists; pass --overwrite to regenerate it")
    out.mkdir(parents=True, exist_ok=True)

    scene = build_scene_arrays(num_gaussians, seed)
    model = GaussianModel.from_activated(scene.means, scene.scales, scene.quats_wxyz, scene.opacities, scene.colors)
    model = replace(model, normals=scene.normals)  # the PLY's nx ny nz: true surface normals
    classes = demo_class_set()
    traj = robot_trajectory(frames, seed=seed)
    noise = SegmentationNoise(CLASS_NAMES, seed=seed)
    stamps = BAG_START_NS + np.rint(traj.times * 1e3).astype(np.int64) * 1_000_000  # millisecond-aligned
    K = camera_k(width, height)
    masks, targets = systematic_rule_masks(scene, CLASS_NAMES, DEFAULT_SYSTEMATIC)
    renderer = DemoRenderer(model, scene.class_ids, classes.num_classes, masks, targets, backend=backend)
    errors: list[float] = []
    unlabelled = 0
    with bag_in_place(out, storage) as writer:
        writer.set_custom_data("css_ros.demo", json.dumps(
            {"generator": "css_make_demo", "num_gaussians": num_gaussians, "frames": frames, "width": width,
             "height": height, "seed": seed}, sort_keys=True))
        with writer:
            frame_iter: Any = range(frames)
            if progress:
                from tqdm import tqdm

                frame_iter = tqdm(frame_iter, desc="css_make_demo", unit="frame", file=sys.stderr)
            for i in frame_iter:
                cam = Camera(K, width, height, traj.T_map_cam[i])
                active = [noise.systematic_active(i, r, rule.probability)
                          for r, rule in enumerate(DEFAULT_SYSTEMATIC)]
                rgb, gt, biased = renderer.render(cam, active)
                seg, conf = noise.apply(biased, i)
                stamp = int(stamps[i])
                writer.write_camera_info(BAG_TOPICS["camera_info"], K, width, height, stamp, BAG_CAMERA_FRAME)
                writer.write_pose(BAG_TOPICS["pose"], traj.positions[i], traj.quaternions_xyzw[i], stamp, BAG_MAP_FRAME)
                writer.write_image(BAG_TOPICS["image"], rgb, "rgb8", stamp, BAG_CAMERA_FRAME)
                writer.write_image(BAG_TOPICS["segmentation"], seg, "mono8", stamp, BAG_CAMERA_FRAME)
                writer.write_image(BAG_TOPICS["confidence"], conf, "32FC1", stamp, BAG_CAMERA_FRAME)
                writer.write_image(BAG_TOPICS["gt"], gt, "mono8", stamp, BAG_CAMERA_FRAME)
                valid = gt != 255
                unlabelled += int(np.count_nonzero(~valid))
                errors.append(float(np.count_nonzero((seg != gt) & valid)) / max(1, int(np.count_nonzero(valid))))

    model.to_ply(out / "model.ply", extra_fields={"class_id": scene.class_ids.astype(np.uint8)})
    classes.to_yaml(out / "classes.yaml")
    late = int(np.argmax(traj.phase == 3)) if np.any(traj.phase == 3) else frames
    err = np.asarray(errors)
    stats = DemoStats(
        frames=frames, width=width, height=height, num_gaussians=num_gaussians, num_classes=classes.num_classes,
        duration_s=float(traj.times[-1]), noisy_pixel_error=float(err.mean()),
        noisy_error_p10_p90=(float(np.percentile(err, 10)), float(np.percentile(err, 90))),
        unlabelled_fraction=unlabelled / (frames * width * height), late_first_frame=late,
    )
    (out / "README.md").write_text(_readme(stats, out, storage, seed, LATE_PHASE_START))
    stats.bytes_total = _dir_bytes(out)
    stats.seconds = time.perf_counter() - t_start
    return stats


def _readme(s: DemoStats, out: Path, storage: str, seed: int, late_wp: int) -> str:
    cmd = "css_make_demo"
    defaults = {"num_gaussians": DEFAULTS["num_gaussians"], "frames": DEFAULTS["frames"], "width": DEFAULTS["width"],
                "height": DEFAULTS["height"], "seed": 0}
    args = {"num_gaussians": s.num_gaussians, "frames": s.frames, "width": s.width, "height": s.height, "seed": seed}
    cmd += f" --out {out.as_posix()}"
    for k, v in args.items():
        if v != defaults[k]:
            cmd += f" --{k.replace('_', '-')} {v}"
    if storage != "mcap":
        cmd += f" --storage {storage}"
    cmd += " --overwrite"
    rate = (s.frames - 1) / s.duration_s
    return f"""# css_ros demo data

Generated by `css_make_demo` (module `css_ros.demo.make_demo`); regenerate with

    {cmd}

The output is deterministic: with the same software versions the same command writes the same bytes.

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

Image headers use frame id `camera_optical`.

## Scene

A furnished 8 m x 6 m x 2.7 m room (map frame: x east, y north, z up): wooden floor with a rug, painted walls
and ceiling, door, window, dining table with four chairs, sofa and coffee table, bookshelf with boxes,
cabinet, two floor lamps (thin poles), two potted plants, three pictures and five wall outlets. Gaussians
lie on the surfaces: flattened (normal-axis standard deviation 4-12 % of the in-plane ones), oriented with the
surface, spread by a low-discrepancy sequence with density set by area and a minimum for thin parts, opacities
Beta-distributed (mostly 0.8-0.99, 7 % faint), colours from textured materials (planks, grain, fabric, rug
pattern, paintings, sky) with baked shading.

## Trajectory

A mobile robot's camera at ~1 m height, looking slightly down, moving at ~0.5 m/s and turning at ~35 deg/s:
first the east half and the north side, then revisits of the sofa and the dining table from new viewpoints,
and from frame {s.late_first_frame} on (waypoint {late_wp}) the south-west corner with the bookshelf and a
plant, which is not seen before.

## Noise model of `/segmentation`

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

On this data set the noisy segmentation disagrees with the ground truth on {100 * s.noisy_pixel_error:.1f} % \
of the labelled pixels (10th-90th percentile over frames: {100 * s.noisy_error_p10_p90[0]:.1f}-\
{100 * s.noisy_error_p10_p90[1]:.1f} %); {100 * s.unlabelled_fraction:.2f} % of the pixels have no ground truth.
"""


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
    if args.robot:
        try:
            info = make_robot_demo(args.out, num_gaussians=args.num_gaussians, frames=args.frames,
                                   width=args.width, height=args.height, seed=args.seed, overwrite=args.overwrite,
                                   progress=not args.quiet)
        except (CssError, ValueError) as exc:
            print(f"css_make_demo: error: {exc}", file=sys.stderr)
            return 2
        print(f"wrote {args.out}: {info['frames_per_camera']} frames per camera ({', '.join(info['cameras'])}), "
              f"{info['odometry_messages']} odometry messages over {info['duration_s']:.0f} s; replay it with "
              f"css_replay {args.out / 'bag'}")
        return 0
    if not args.quiet:
        print(size_estimate(args.num_gaussians, args.frames, args.width, args.height), file=sys.stderr)
    try:
        stats = make_demo(args.out, num_gaussians=args.num_gaussians, frames=args.frames, width=args.width,
                          height=args.height, seed=args.seed, storage=args.storage, overwrite=args.overwrite,
                          progress=not args.quiet, backend=args.backend)
    except (CssError, ValueError) as exc:
        print(f"css_make_demo: error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {args.out} ({stats.bytes_total / 1e6:.1f} MB, {stats.frames} frames {stats.width}x{stats.height}, "
          f"{stats.num_gaussians} Gaussians, noisy pixel error {100 * stats.noisy_pixel_error:.1f} %) "
          f"in {stats.seconds:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
