"""``css_export``: write the semantic map in 3D as viewer-ready PLY files (no ROS needed)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Sequence

from ..engine.classes import ClassSet
from ..engine.gaussians import GaussianModel
from ..engine.semantic_map import SemanticMap
from ..engine.spec import DEFAULT_MIN_EVIDENCE
from ..console import run_console
from ..errors import CssError
from .bundle import FORMATS, export_map

EXAMPLES = """\
examples:
  # everything, next to the map: map_semantic.ply, map_uncertainty_variance.ply (+ _colorbar.png), map_points.ply
  css_export out/map.npz --model bags/demo/model.ply --classes bags/demo/classes.yaml

  # only the semantic splat, observed Gaussians only, into another folder (no class file: class_0..C-1)
  css_export map.npz --model model.ply --formats semantic --drop-unobserved --out export/

  # the splat coloured by evidence (how much was seen), and the point cloud
  css_export map.npz --model model.ply --classes classes.yaml --formats uncertainty,points --uncertainty evidence

Open *_semantic.ply / *_uncertainty_*.ply in a 3DGS viewer (e.g. SuperSplat), *_points.ply in
CloudCompare or Open3D. Unobserved Gaussians are grey with label 255 unless --drop-unobserved.
"""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="css_export", description="Export a css_ros semantic map (.npz) as semantic / uncertainty splat "
        "PLYs and a point cloud PLY (SPEC §9; map frame, metres).",
        epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("map", type=Path, help="semantic map .npz written by css_node / css_replay")
    p.add_argument("--model", type=Path, required=True, metavar="PLY", help="the splat model the map was made on")
    group = p.add_mutually_exclusive_group()
    group.add_argument("--classes", type=Path, metavar="YAML", help="class file (names and colours); without it "
                       "the map's own number of classes, named class_0..C-1")
    group.add_argument("--num-classes", type=int, metavar="N", help="anonymous classes class_0..N-1 (checked "
                       "against the map)")
    p.add_argument("--out", type=Path, default=None, metavar="DIR", help="output folder (default: the map's folder)")
    p.add_argument("--formats", default=",".join(FORMATS),
                   help=f"comma-separated outputs among {', '.join(FORMATS)} (default: all)")
    p.add_argument("--uncertainty", choices=("variance", "evidence"), default="variance",
                   help="quantity of the uncertainty splat (default variance)")
    p.add_argument("--cmap", default=None, help="matplotlib colour map of the uncertainty splat "
                   "(default magma for variance, viridis for evidence)")
    p.add_argument("--min-evidence", type=float, default=DEFAULT_MIN_EVIDENCE,
                   help=f"a Gaussian is observed when S_n - C*alpha_0 >= this (default {DEFAULT_MIN_EVIDENCE})")
    p.add_argument("--drop-unobserved", action="store_true",
                   help="leave unobserved Gaussians out instead of writing them grey with label 255")
    return p


def _parse_formats(text: str) -> list[str]:
    formats = [f.strip() for f in text.split(",") if f.strip()]
    bad = [f for f in formats if f not in FORMATS]
    if bad or not formats:
        raise CssError(f"--formats: unknown {', '.join(bad) or 'empty list'} (choose from {', '.join(FORMATS)})")
    return list(dict.fromkeys(formats))


def export(args: argparse.Namespace) -> list[Path]:
    """Run the export described by parsed arguments; returns the files written."""
    formats = _parse_formats(args.formats)
    if not (args.min_evidence >= 0):
        raise CssError(f"--min-evidence must be >= 0, got {args.min_evidence}")
    if not args.map.is_file():
        raise CssError(f"map file not found: {args.map}")
    if not args.model.is_file():
        raise CssError(f"model file not found: {args.model}")
    if args.classes is not None:
        if not args.classes.is_file():
            raise CssError(f"class file not found: {args.classes}")
        classes = ClassSet.from_yaml(args.classes)
    elif args.num_classes is not None:
        if args.num_classes < 1:
            raise CssError("--num-classes must be >= 1")
        classes = ClassSet.default(args.num_classes)
    else:
        classes = None
    model = GaussianModel.from_ply(args.model)
    if classes is None:  # no class file: the map's classes, anonymous
        smap = SemanticMap.load(args.map, model)
        classes = ClassSet.default(smap.num_classes)
    else:  # the class count is known: a map of another count (or a bomb claiming one) is refused from its headers
        smap = SemanticMap.load(args.map, model, expected_classes=classes.num_classes)
    if classes.num_classes != smap.num_classes:
        raise CssError(f"the map has {smap.num_classes} classes but {classes.num_classes} were given "
                       f"({args.classes or '--num-classes'})")
    out = args.out if args.out is not None else args.map.parent
    return export_map(smap, classes, out, args.map.stem, formats, args.uncertainty, args.cmap, args.min_evidence,
                      bool(args.drop_unobserved))


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``css_export``: 0 on success, 1 with a one-line error, 2 for usage errors."""
    args = build_parser().parse_args(argv)

    def work() -> None:
        for path in export(args):
            print(path)

    return run_console("css_export", work)


if __name__ == "__main__":
    sys.exit(main())
