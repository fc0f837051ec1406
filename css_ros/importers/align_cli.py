"""``css_align``: estimate ``splat_to_map`` (the splat's frame and scale -> the robot's map) from matched camera poses.

The trainer's cameras (INRIA cameras.json, nerfstudio transforms.json, COLMAP sparse model: the importers' readers)
against the robot's poses of the same images: a CSV of ``name,x,y,z,qx,qy,qz,qw``, or a bag's pose topic
interpolated at the images' stamps (a CSV of ``name,stamp``) exactly as css_node would (pose types, extrinsics).
Prints scale, rotation, translation, residuals and inliers, and writes the node parameters as YAML.
"""
from __future__ import annotations

import argparse
import csv
import math
import sys
from pathlib import Path, PurePath
from typing import Sequence

import numpy as np

from ..console import cli_main
from ..engine.similarity import Similarity
from ..errors import ConfigError, InputError
from ..io.bag import InputBag
from ..io.frame_gate import pose_message_pose
from ..io.frames import FrameRejected, decode_pose
from ..io.messages import stamp_to_ns
from ..io.params_file import write_params_file
from ..io.pose_history import LookupStatus, PoseHistory, PosePolicy
from ..io.topics import POSE_TYPES
from .align import (DEFAULT_MAX_RESIDUAL_M, DEFAULT_MAX_ROTATION_DEG, Alignment, fit_splat_to_map, rotations_of)
from .cli import load_views

#: Largest CSV read [bytes].
MAX_CSV_BYTES = 64 << 20
#: An integer stamp with more digits than this is in nanoseconds; otherwise seconds.
NS_DIGITS = 12

EPILOG = """\
robot poses, one of:
  --poses-csv FILE            rows: name,x,y,z,qx,qy,qz,qw (pose of the optical frame, or of the frame the
                              --camera-extrinsics are given in), map frame, metres
  --bag BAG --stamps-csv FILE rows: name,stamp (seconds, or integer nanoseconds); the pose topic of the bag is
                              interpolated at each stamp as css_node does (--pose-topic, --pose-type)
images are matched by file stem (images/00012.jpg <-> 00012). A header row is skipped.

examples:
  css_align output/train/cameras.json --poses-csv robot_poses.csv --out css_node.yaml
  css_align data/sparse/0 --bag run1/bag --stamps-csv image_stamps.csv --pose-type odometry \\
      --camera-extrinsics 0.2 0 1.0 -0.5 0.5 -0.5 0.5
"""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="css_align", formatter_class=argparse.RawDescriptionHelpFormatter, epilog=EPILOG,
        description="Estimate splat_to_map, the similarity (scale, rotation, translation) that takes a trained "
                    "splat's coordinates into the robot's map frame, from the trainer's cameras and the robot's "
                    "poses of the same images; writes the css_node parameters as YAML.")
    p.add_argument("poses", type=Path, help="trainer cameras: cameras.json, transforms.json or a COLMAP model folder")
    p.add_argument("--format", choices=("inria", "nerfstudio", "colmap"), default=None,
                   help="trainer pose format (default: from the path)")
    p.add_argument("--poses-csv", type=Path, default=None, metavar="CSV", help="robot poses per image")
    p.add_argument("--bag", type=Path, default=None, metavar="BAG", help="bag with the robot's pose topic")
    p.add_argument("--stamps-csv", type=Path, default=None, metavar="CSV", help="image stamps (with --bag)")
    p.add_argument("--pose-topic", default="/pose", metavar="TOPIC", help="pose topic in --bag (default /pose)")
    p.add_argument("--pose-type", choices=("auto", *POSE_TYPES), default="auto",
                   help="pose message type (default: from the bag)")
    p.add_argument("--camera-extrinsics", nargs=7, type=float, default=None, metavar="V",
                   help="x y z qx qy qz qw of the camera's optical frame in the frame the robot poses describe")
    p.add_argument("--max-residual", type=float, default=DEFAULT_MAX_RESIDUAL_M, metavar="M",
                   help=f"refuse when the RMS position residual exceeds this [m] (default {DEFAULT_MAX_RESIDUAL_M:g})")
    p.add_argument("--max-rotation-residual", type=float, default=DEFAULT_MAX_ROTATION_DEG, metavar="DEG",
                   help="refuse when the median orientation residual exceeds this [deg] (default "
                        f"{DEFAULT_MAX_ROTATION_DEG:g})")
    p.add_argument("--out", type=Path, default=Path("css_align.yaml"), metavar="YAML",
                   help="parameter file to write (default css_align.yaml)")
    return p


#: Largest coordinate accepted in pose files [m or splat units]: beyond, the fit's arithmetic overflows.
MAX_COORDINATE_M = 1e7


def _rows(path: Path, width: int, what: str) -> list[list[str]]:
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise InputError(f"{what} {path}: {exc.strerror or exc}") from None
    if size > MAX_CSV_BYTES:
        raise InputError(f"{what} {path}: {size} bytes, more than {MAX_CSV_BYTES}")
    rows = []
    first_line: dict[str, int] = {}
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            for k, row in enumerate(csv.reader(fh)):
                row = [c.strip() for c in row]
                if not row or not any(row) or row[0].startswith("#"):
                    continue
                if len(row) != width:
                    raise InputError(f"{what} {path}, line {k + 1}: {len(row)} columns, expected {width}")
                try:
                    float(row[1])
                except ValueError:
                    if k == 0:
                        continue  # header
                    raise InputError(f"{what} {path}, line {k + 1}: not a number: {row[1]!r}") from None
                name = _stem(row[0])
                if name in first_line:  # two poses for one image: which one is right cannot be known
                    raise InputError(f"{what} {path}, line {k + 1}: image {row[0]!r} already on line "
                                     f"{first_line[name]}; give each image once")
                first_line[name] = k + 1
                rows.append(row)
    except (UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"{what} {path} is not a text CSV file ({type(exc).__name__}: {exc})") from None
    return rows


def _stem(name: str) -> str:
    return PurePath(name.replace("\\", "/")).stem


def robot_poses_from_csv(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    out = {}
    for row in _rows(path, 8, "--poses-csv"):
        try:
            v = np.array([float(x) for x in row[1:]])
        except ValueError:
            raise InputError(f"--poses-csv {path}: a value for {row[0]} is not a number") from None
        if not np.all(np.isfinite(v)) or np.any(np.abs(v[:3]) > MAX_COORDINATE_M):
            raise InputError(f"--poses-csv {path}: the position of {row[0]} is not finite or beyond "
                             f"{MAX_COORDINATE_M:g} m")
        if not 0.5 < np.linalg.norm(v[3:]) < 2.0:
            raise InputError(f"--poses-csv {path}: the quaternion of {row[0]} has norm {np.linalg.norm(v[3:]):.3g}")
        q = v[3:] / np.linalg.norm(v[3:])
        out[_stem(row[0])] = (v[:3], q)
    return out


def _stamp_ns(text: str) -> int:
    if text.lstrip("-").isdigit() and len(text.lstrip("-")) > NS_DIGITS:
        return int(text)
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(text)
    return int(round(value * 1e9))


def robot_poses_from_bag(bag: Path, stamps_csv: Path, topic: str, pose_type: str
                         ) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], list[str]]:
    """name stem -> pose interpolated at the image's stamp; and the names whose stamp had no pose (with why)."""
    stamps = {}
    for row in _rows(stamps_csv, 2, "--stamps-csv"):
        try:
            stamps[_stem(row[0])] = _stamp_ns(row[1])
        except ValueError:
            raise InputError(f"--stamps-csv {stamps_csv}: bad stamp {row[1]!r} for {row[0]}") from None
    history = PoseHistory(PosePolicy(buffer=1e7, max_samples=10**8))   # the whole bag at once
    with InputBag(bag) as b:
        topics = b.topics()
        if topic not in topics:
            raise InputError(f"bag {bag} has no topic {topic}; topics: {', '.join(sorted(topics))}")
        if pose_type == "auto":
            by_type = {v: k for k, v in POSE_TYPES.items()}
            if topics[topic][0] not in by_type:
                raise InputError(f"{topic} has type {topics[topic][0]}, not a pose type ({', '.join(POSE_TYPES)})")
            pose_type = by_type[topics[topic][0]]
        for m in b.messages([topic]):
            try:
                p, q = decode_pose(pose_message_pose(m.msg, pose_type))
            except (FrameRejected, AttributeError):
                continue
            history.add(stamp_to_ns(m.msg.header.stamp), p, q)
    out, missing = {}, []
    for name, s in stamps.items():
        look = history.lookup(s, waited=True)
        if look.status is LookupStatus.OK:
            out[name] = (look.position, look.quat)
        else:
            missing.append(f"{name} ({look.reason})")
    return out, missing


def run(args: argparse.Namespace) -> str:
    if (args.poses_csv is None) == (args.bag is None):
        raise ConfigError("give the robot poses: --poses-csv FILE, or --bag BAG with --stamps-csv FILE")
    if args.bag is not None and args.stamps_csv is None:
        raise ConfigError("--bag needs --stamps-csv FILE (image name, stamp)")
    for opt, value in (("--max-residual", args.max_residual), ("--max-rotation-residual", args.max_rotation_residual)):
        if not (math.isfinite(value) and value > 0):
            raise ConfigError(f"{opt} must be a finite number > 0, got {value}")
    views = load_views(args.poses, args.format, ignore_distortion=True)
    stems = [v.stem for v in views]
    twice = sorted({n for n in stems if stems.count(n) > 1})
    if twice:
        raise InputError(f"{args.poses}: image names given more than once ({', '.join(twice[:5])}); give each once")
    far = [v.stem for v in views if not np.all(np.isfinite(v.position)) or np.any(np.abs(v.position) > MAX_COORDINATE_M)]
    if far:
        raise InputError(f"{args.poses}: camera positions not finite or beyond {MAX_COORDINATE_M:g} units "
                         f"({', '.join(far[:5])})")
    missing: list[str] = []
    if args.poses_csv is not None:
        robot = robot_poses_from_csv(args.poses_csv)
    else:
        robot, missing = robot_poses_from_bag(args.bag, args.stamps_csv, args.pose_topic, args.pose_type)
    ext = Similarity.rigid_from_params(args.camera_extrinsics, "--camera-extrinsics") \
        if args.camera_extrinsics else None
    names, src, dst, R_src, q_dst = [], [], [], [], []
    for v in views:
        if v.stem not in robot:
            continue
        p, q = robot[v.stem]
        if ext is not None:
            p, q = ext.compose_pose(p, q)
        names.append(v.stem)
        src.append(v.position)
        R_src.append(v.T_map_cam[:3, :3])
        dst.append(p)
        q_dst.append(q)
    fit: Alignment = fit_splat_to_map(np.array(src).reshape(-1, 3), np.array(dst).reshape(-1, 3),
                                      np.array(R_src).reshape(-1, 3, 3),
                                      rotations_of(np.array(q_dst).reshape(-1, 4)) if q_dst else None,
                                      args.max_residual, args.max_rotation_residual)
    sim = fit.similarity
    params = sim.to_params()
    outliers = [n for n, ok in zip(names, fit.inliers) if not ok]
    lines = [
        f"matched {len(names)} of {len(views)} trainer cameras with robot poses"
        + (f" ({len(missing)} stamps without a pose, e.g. {missing[0]})" if missing else ""),
        f"scale {sim.scale:.6g} (map metres per splat unit)",
        f"rotation (qx qy qz qw) {' '.join(f'{x:.6f}' for x in params[4:])}",
        f"translation [m] {' '.join(f'{x:.4f}' for x in params[1:4])}",
        f"inliers {fit.num_inliers} of {len(names)}" + (f" (outliers: {', '.join(outliers[:8])})" if outliers else ""),
        f"residuals: position RMS {fit.rms_m * 1e3:.1f} mm, max {fit.max_m * 1e3:.1f} mm; orientation median "
        f"{fit.rot_median_deg:.2f} deg, max {fit.rot_max_deg:.2f} deg",
    ]
    write_params_file(args.out, {"splat_to_map": [float(x) for x in params]},
                      comment=f"css_align {args.poses}: {fit.num_inliers} inliers, position RMS "
                              f"{fit.rms_m * 1e3:.1f} mm, orientation median {fit.rot_median_deg:.2f} deg")
    lines.append(f"wrote {args.out} (splat_to_map); use it with css_node --ros-args --params-file {args.out} "
                 f"or css_replay --params {args.out}")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point; returns the exit code (0 ok, 1 error, 2 usage error)."""
    return cli_main("css_align", build_parser(), run, argv)


if __name__ == "__main__":
    sys.exit(main())
