"""``css_import``: a trained splat + posed images + label PNGs -> the bag layout css_replay / css_demo read."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Sequence

import numpy as np
from tqdm import tqdm

from ..engine.classes import ClassSet
from ..console import cli_main
from ..engine.similarity import Similarity
from ..io.params_file import PARAMS_FILE_NAME
from .colmap import load_colmap
from .inria import load_inria
from .labels import LabelDecoder, load_remap
from .nerfstudio import load_nerfstudio
from .pairing import pair_frames
from .align import UP_AXES, up_alignment
from .views import ImportFormatError, PosedView
from .writer import write_dataset

EPILOG = """\
pose formats (--format, default: guessed from the path):
  inria       cameras.json of the INRIA 3DGS trainer (camera centre + camera-to-world rotation, OpenCV axes)
  nerfstudio  transforms.json (camera-to-world, OpenGL axes: y and z are flipped here)
  colmap      sparse model folder with cameras/images .txt or .bin (world-to-camera: inverted here)
The model and the poses must be in the same world frame and scale (the trainer's output is).

label files (matched to the images by file stem, e.g. 00001.jpg <-> labels/00001.png):
  8/16-bit grey or palette PNGs hold class ids; RGB PNGs hold class colours of --classes.
  --gt: same format; --confidence: <stem>.npy (float array in [0, 1]) or grey PNG (scaled to [0, 1]).

examples:
  css_import output/train/cameras.json --model output/train/point_cloud/iteration_30000/point_cloud.ply \\
      --labels seg/ --gt gt/ --images images/ --classes classes.yaml --out data/train
  css_import data/sparse/0 --model splat.ply --labels seg/ --num-classes 20 --rate 5 --out data/room
  css_import transforms.json --model splat.ply --labels seg_color/ --classes classes.yaml \\
      --remap remap.yaml --out data/scene
  css_replay data/train/bag          # then evaluate (reads data/train/model.ply, classes.yaml, css_node.yaml)

up direction: the trainer's frame is rarely z-up (COLMAP: arbitrary; INRIA: as COLMAP). css_import finds the up
direction from the cameras (--up-axis auto), writes the poses in a z-up map frame and OUT/css_node.yaml with the
splat_to_map that puts the splat there (css_replay and css_node read it). To align with a robot's map, use
css_align instead.
"""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="css_import", formatter_class=argparse.RawDescriptionHelpFormatter, epilog=EPILOG,
        description="Import posed images and label PNGs for a trained 3D Gaussian Splatting model: write "
                    "OUT/model.ply, OUT/classes.yaml and the rosbag2 bag OUT/bag that css_replay and css_demo read.")
    p.add_argument("poses", type=Path, help="cameras.json, transforms.json or a COLMAP sparse model folder")
    p.add_argument("--format", choices=("inria", "nerfstudio", "colmap"), default=None,
                   help="pose format (default: from the path)")
    p.add_argument("--model", type=Path, required=True, metavar="PLY", help="trained INRIA 3DGS PLY model")
    p.add_argument("--labels", type=Path, required=True, metavar="DIR", help="folder of label PNGs (input segmentation)")
    p.add_argument("--gt", type=Path, default=None, metavar="DIR", help="folder of ground-truth label PNGs")
    p.add_argument("--confidence", type=Path, default=None, metavar="DIR",
                   help="folder of confidence maps (<stem>.npy float in [0, 1], or grey PNG)")
    p.add_argument("--images", type=Path, default=None, metavar="DIR", help="folder of the colour images")
    p.add_argument("--classes", type=Path, default=None, metavar="YAML", help="class file (names, colours)")
    p.add_argument("--num-classes", type=int, default=None, metavar="N",
                   help="number of classes when there is no class file (anonymous names)")
    p.add_argument("--remap", type=Path, default=None, metavar="YAML",
                   help="class-id remapping 'remap: {source: target}' applied to labels and GT")
    p.add_argument("--ignore-label", type=int, default=255, help="'no label' id (default 255)")
    p.add_argument("--unknown-colors", choices=("error", "ignore"), default="error",
                   help="colour-PNG pixels whose colour is no class colour: fail (default) or map to the ignore label")
    p.add_argument("--ignore-distortion", action="store_true",
                   help="accept cameras with lens distortion and use their pinhole part (only for nearly "
                        "undistorted images)")
    p.add_argument("--up-axis", choices=("auto", *UP_AXES, "none"), default="auto",
                   help="the splat's up direction: auto (default) = the mean of the cameras' -y axes; the bag's "
                        "poses are written in a z-up map frame and OUT/css_node.yaml holds the splat_to_map that "
                        "takes the splat there; none = keep the trainer's frame")
    p.add_argument("--rate", type=float, default=10.0, metavar="HZ", help="frame rate of the bag stamps (default 10)")
    p.add_argument("--poses-on", choices=("topic", "tf"), default="topic",
                   help="how the bag carries the camera poses: topic (default) = geometry_msgs/PoseStamped on /pose; "
                        "tf = the transform map -> camera_optical on /tf at each frame's stamp, as a TF robot "
                        "records it (css_replay and css_calibrate read either)")
    p.add_argument("--max-frames", type=int, default=None, metavar="N", help="import the first N labelled frames")
    p.add_argument("--link-model", action="store_true", help="symlink the model into OUT instead of copying it")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def guess_format(path: Path) -> str:
    """'colmap' for a folder with cameras.txt/.bin, 'nerfstudio' for transforms.json (or a folder holding it),
    'inria' for any other .json."""
    if path.is_dir():
        if any((path / f"cameras.{e}").is_file() for e in ("txt", "bin")):
            return "colmap"
        if (path / "transforms.json").is_file():
            return "nerfstudio"
        if (path / "cameras.json").is_file():
            return "inria"
        raise ImportFormatError(f"{path}: no cameras.json, transforms.json or COLMAP model in this folder")
    if path.name == "transforms.json":
        return "nerfstudio"
    if path.suffix == ".json":
        return "inria"
    raise ImportFormatError(f"{path}: cannot tell the pose format (pass --format)")


def load_views(path: Path, fmt: str | None, ignore_distortion: bool) -> list[PosedView]:
    """Posed views of ``path`` in format ``fmt`` (guessed when None)."""
    if not path.exists():
        raise ImportFormatError(f"pose file not found: {path}")
    fmt = fmt or guess_format(path)
    if fmt == "inria":
        return load_inria(path / "cameras.json" if path.is_dir() else path)
    if fmt == "nerfstudio":
        return load_nerfstudio(path, ignore_distortion)
    return load_colmap(path, ignore_distortion)


def to_map_frame(view: PosedView, splat_to_map: Similarity) -> PosedView:
    """The view with its pose moved from the splat's frame into the map frame."""
    if splat_to_map.is_identity:
        return view
    T = splat_to_map.matrix() @ view.T_map_cam
    T[:3, :3] /= splat_to_map.scale
    return PosedView(view.name, view.K, view.width, view.height, T)


def run(args: argparse.Namespace) -> str:
    """Import; returns the summary printed at the end."""
    if args.classes is not None and str(args.classes) != "":
        classes = ClassSet.from_yaml(args.classes)
        if args.num_classes is not None and args.num_classes != classes.num_classes:
            raise ImportFormatError(f"--num-classes {args.num_classes} contradicts {args.classes} "
                                    f"({classes.num_classes} classes)")
        classes_file: Path | None = args.classes
    elif args.num_classes is not None:
        if args.num_classes < 1:
            raise ImportFormatError("--num-classes must be >= 1")
        classes, classes_file = ClassSet.default(args.num_classes), None
    else:
        raise ImportFormatError("pass --classes FILE or --num-classes N")
    if args.max_frames is not None and args.max_frames < 1:
        raise ImportFormatError("--max-frames must be >= 1")
    views = load_views(args.poses, args.format, args.ignore_distortion)
    up = up_alignment(np.array([v.T_map_cam[:3, :3] for v in views]), args.up_axis)
    views = [to_map_frame(v, up) for v in views]
    pairing = pair_frames(views, args.labels, args.gt, args.confidence, args.images)
    frames = pairing.frames[: args.max_frames] if args.max_frames else pairing.frames
    decoder = LabelDecoder(palette=classes.palette, remap=load_remap(args.remap) if args.remap else {},
                           ignore_label=args.ignore_label, unknown_colors=args.unknown_colors)
    with tqdm(total=len(frames), desc="css_import", unit="frame", disable=args.quiet, file=sys.stderr) as bar:
        s = write_dataset(args.out, frames, args.model, classes, classes_file, decoder, rate_hz=args.rate,
                          ignore_label=args.ignore_label, link_model=args.link_model, progress=bar.update,
                          node_params={"splat_to_map": [float(x) for x in up.to_params()]}, poses_on=args.poses_on)
    lines = [f"imported {s.frames} frames of {len(views)} cameras ({s.segmentation_encoding} labels) -> {s.bag}"]
    if pairing.without_labels:
        lines.append(f"note: {len(pairing.without_labels)} cameras have no label file and were left out "
                     f"(e.g. {pairing.without_labels[0]})")
    if s.unknown_color_pixels:
        lines.append(f"warning: {s.unknown_color_pixels} pixels of unknown colour set to the ignore label")
    if s.out_of_range_pixels:
        share = s.out_of_range_pixels / max(s.labelled_pixels, 1)
        lines.append(f"warning: {s.out_of_range_pixels} labelled pixels ({100 * share:.2f} %) hold ids >= "
                     f"{classes.num_classes} (not a class of {s.classes.name}); use --remap")
    if not up.is_identity:
        lines.append(f"the map frame is z-up: poses rotated by splat_to_map {up.to_params()[4:]} (qx qy qz qw), "
                     f"in {args.out / PARAMS_FILE_NAME} (--up-axis to choose the up direction)")
    lines.append(f"next: css_replay {s.bag}")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point; returns the exit code (0 ok, 1 error, 2 usage error)."""
    return cli_main("css_import", build_parser(), run, argv)


if __name__ == "__main__":
    sys.exit(main())
