"""``css_map``: one CLI for saved maps: ``info``, ``merge`` (same splat) and ``transfer`` (another splat).

A thin layer over :mod:`css_ros.engine.map_file`, :mod:`css_ros.engine.merge` and
:mod:`css_ros.engine.transfer`; exit codes as :mod:`css_ros.console` documents.
"""
from __future__ import annotations

import argparse
import hashlib
import sys
from pathlib import Path
from typing import Sequence

import numpy as np

from ..console import run_console
from ..engine.gaussians import GaussianModel
from ..engine.map_file import MapInfo, read_map_info
from ..engine.merge import merge_maps
from ..engine.semantic_map import SemanticMap
from ..engine.spec import DEFAULT_TRANSFER_TOLERANCE, MAX_TRANSFER_TOLERANCE
from ..engine.transfer import transfer_map
from ..errors import CssError, MapError

EXAMPLES = """\
examples:
  css_map info out/map.npz
  css_map merge robot_a.npz robot_b.npz --model scene.ply --out both.npz
  css_map transfer map.npz --from scene.ply --to scene_retrained.ply --out map_retrained.npz
"""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="css_map", description="Inspect, merge and transfer css_ros semantic maps "
                                "(.npz written by css_node / css_replay).", epilog=EXAMPLES,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True, metavar="{info,merge,transfer}")
    info = sub.add_parser("info", help="model fingerprint, N, C, prior, frames, sources, evidence statistics")
    info.add_argument("maps", type=Path, nargs="+", metavar="MAP")
    merge = sub.add_parser("merge", help="sum the evidence above the prior of maps of the same splat")
    merge.add_argument("maps", type=Path, nargs="+", metavar="MAP")
    merge.add_argument("--model", type=Path, required=True, metavar="PLY", help="the splat every map was made on")
    merge.add_argument("--out", type=Path, required=True, metavar="NPZ", help="merged map file")
    tr = sub.add_parser("transfer", help="move a map's evidence to another splat of the same scene")
    tr.add_argument("map", type=Path, metavar="MAP")
    tr.add_argument("--from", dest="source", type=Path, required=True, metavar="PLY", help="the map's splat")
    tr.add_argument("--to", dest="target", type=Path, required=True, metavar="PLY", help="the new splat")
    tr.add_argument("--out", type=Path, required=True, metavar="NPZ", help="transferred map file")
    tr.add_argument("--tolerance", type=float, default=DEFAULT_TRANSFER_TOLERANCE, metavar="M",
                    help=f"how far a retrained Gaussian may have moved, metres (default {DEFAULT_TRANSFER_TOLERANCE})")
    return p


def format_info(info: MapInfo) -> str:
    """Human-readable summary of one map file."""
    per_class = ", ".join(f"{v:.4g}" for v in info.evidence_per_class)
    return "\n".join([
        f"map:          {info.path}",
        f"model:        {info.fingerprint}",
        f"gaussians:    {info.num_gaussians}",
        f"classes:      {info.num_classes}",
        f"prior:        {info.prior:g}",
        f"background:   {info.background:g}",
        f"frames:       {info.frames_observed}",
        f"sources:      {', '.join(info.sources) if info.sources else '(none listed)'}",
        f"sensor model: {info.sensor_model or '(none: the paper update)'}",
        f"evidence:     {info.evidence_total:.6g} total, {info.observed_gaussians} Gaussians observed "
        f"({100.0 * info.observed_gaussians / info.num_gaussians:.1f} %), max {info.evidence_max:.6g} per Gaussian",
        f"per class:    {per_class}",
    ])


def _model(path: Path) -> GaussianModel:
    if not path.is_file():
        raise CssError(f"model file not found: {path}")
    return GaussianModel.from_ply(path)


def _file_hash(path: Path) -> str:
    """SHA-256 of a file's bytes (symlinks followed)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _refuse_same_maps(paths: Sequence[Path], maps: Sequence[SemanticMap]) -> None:
    """A map merged with itself (the same file, a link to it, a byte-identical copy) or two maps without sources
    holding identical evidence would count that evidence twice: refuse them."""
    seen: dict[str, Path] = {}
    for p in paths:
        digest = _file_hash(p)
        if digest in seen:
            raise MapError(f"{p} and {seen[digest]} are the same map (identical content): merging a map with itself "
                           "would count its evidence twice")
        seen[digest] = p
    for i, (pa, a) in enumerate(zip(paths, maps)):
        for pb, b in zip(paths[i + 1:], maps[i + 1:]):
            if not a.sources and not b.sources and np.array_equal(a.concentrations_readonly,
                                                                    b.concentrations_readonly):
                raise MapError(f"{pa} and {pb} hold identical evidence and list no sources: they are copies of one "
                               "map, and merging them would count it twice")


def _merge(args: argparse.Namespace) -> None:
    infos = [read_map_info(p) for p in args.maps]
    first = infos[0]
    for info in infos[1:]:  # the clear refusals, before the model is read
        if info.fingerprint != first.fingerprint:
            raise MapError(f"{info.path} and {first.path} were made on different splat models "
                           f"({info.fingerprint[:12]}… vs {first.fingerprint[:12]}…); css_map transfer one first")
        if info.num_classes != first.num_classes:
            raise MapError(f"{info.path} has {info.num_classes} classes, {first.path} {first.num_classes}")
        if info.prior != first.prior or info.background != first.background:
            raise MapError(f"{info.path} has prior/background {info.prior:g}/{info.background:g}, {first.path} "
                           f"{first.prior:g}/{first.background:g}: their evidence is not comparable")
        if info.sensor_model != first.sensor_model:
            raise MapError(f"{info.path} and {first.path} were fused with different sensor models "
                           f"({info.sensor_model[:12] or 'none'} vs {first.sensor_model[:12] or 'none'}): their "
                           "evidence is weighted differently and does not add up")
    model = _model(args.model)
    maps = [SemanticMap.load(p, model) for p in args.maps]
    _refuse_same_maps(args.maps, maps)
    merged = merge_maps(maps, [str(p) for p in args.maps])
    merged.save(args.out)
    print(f"merged {len(maps)} maps into {args.out}: {merged.frames_observed} frames, sources "
          f"{', '.join(merged.sources) or '(none listed)'}")


def _transfer(args: argparse.Namespace) -> None:
    info = read_map_info(args.map)
    old = _model(args.source)
    if info.fingerprint != old.fingerprint:
        raise MapError(f"{args.map} was made on another splat than {args.source} (fingerprints "
                       f"{info.fingerprint[:12]}… and {old.fingerprint[:12]}…)")
    smap = SemanticMap.load(args.map, old)
    new = _model(args.target)
    out, report = transfer_map(smap, new, args.tolerance)
    out.save(args.out)
    print(f"transferred {args.map} ({old.num_gaussians} Gaussians) to {args.target} ({new.num_gaussians}) "
          f"-> {args.out}")
    print(f"evidence ratio {report.ratio:.4f} (old {report.evidence_old:.6g}, new {report.evidence_new:.6g}, "
          f"lost {report.evidence_lost:.6g} from {report.old_dropped} of {report.old_observed} observed old "
          f"Gaussians); {report.new_observed} new Gaussians got evidence, {report.new_at_prior} keep the prior")


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)

    def work() -> None:
        if args.command == "info":
            print("\n\n".join(format_info(read_map_info(p)) for p in args.maps))
        elif args.command == "merge":
            _merge(args)
        else:
            if not 0 <= args.tolerance <= MAX_TRANSFER_TOLERANCE:
                raise CssError(f"--tolerance must be within 0..{MAX_TRANSFER_TOLERANCE:g} metres (how far a retrained "
                               f"Gaussian may have moved), got {args.tolerance}")
            _transfer(args)

    return run_console("css_map", work)


if __name__ == "__main__":
    sys.exit(main())
