#!/usr/bin/env python3
"""A changing world on the demo room: people walking through it and an object whose class changes half way.

Makes two demos with ``css_make_demo`` (same seed, size and trajectory): ``people`` (``--people N --change-class
--depth``: N walkers of class person in the segmentation, colour and depth images; the sofa becomes a box from the
middle frame on) and ``person_free`` (the same without the people). Then replays both bags through css_replay's
frame reader (:class:`css_ros.evaluation.source.FrameSource`: the same decoding, stamp pairing and poses) into one
map per variant, all fed the same frames:

=============================  ==========================================================================
variant                        map
=============================  ==========================================================================
paper                          the paper's update (no depth, no transient class, no forgetting)
depth                          the bag's ``/depth`` (``observe(..., depth=...)``)
transient                      ``transient_classes=[person]``
depth+transient                both
half-life H                    ``evidence_half_life=H``
depth+transient+half-life H    all three (H = --half-life, then each of --more-half-lives)
=============================  ==========================================================================

(``paper`` and ``depth`` also on the person-free bag, for the accuracy loss the people cause.) Each map is measured
with css_replay's own code (:class:`css_ros.evaluation.change_metrics.ChangeTally`) on its final renders at every
frame's pose: the share of rendered pixels labelled person, the accuracy against the static ground truth, the share
of the changed object's pixels in its new class, and the AUROC of ``RenderedView.surprise`` at the first fused frame
that shows the new class (changed pixels against every other labelled pixel). "Others kept right" (forgetting
variants) is the share of the pixels of unchanged objects that are right in the map with the same rules but no
forgetting and still right with it.

    python benchmarks/changing_world.py                   # the shipped demo's size: 50k Gaussians, 120 frames 256x192
    python benchmarks/changing_world.py --quick           # 8k Gaussians, 40 frames of 128x96 (a smoke run)
    python benchmarks/changing_world.py --check-replay    # also run css_replay on the people bag (last variant) and
                                                          # check that its report gives the same figures

Outputs in ``--out`` (default ``out/changing_world``): the two demos (``people/``, ``person_free/``),
``results.json`` and ``results.md`` (the table printed at the end, with the targets of README "A changing world").
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from css_ros.demo.changes import PERSON_CLASS  # noqa: E402
from css_ros.demo.make_demo import WorldOptions, make_demo  # noqa: E402
from css_ros.engine.classes import ClassSet  # noqa: E402
from css_ros.engine.gaussians import GaussianModel  # noqa: E402
from css_ros.engine.semantic_map import SemanticMap  # noqa: E402
from css_ros.evaluation.change_metrics import ChangeTally  # noqa: E402
from css_ros.evaluation.config import ReplayConfig  # noqa: E402
from css_ros.evaluation.source import FrameSource  # noqa: E402

#: sizes of a full run (the shipped demo's) and of --quick
FULL = {"gaussians": 50_000, "frames": 120, "width": 256, "height": 192}
QUICK = {"gaussians": 8_000, "frames": 40, "width": 128, "height": 96}
#: the targets the table is checked against (README "A changing world")
TARGETS = {"depth_person_share": 0.0005, "depth_accuracy_loss": 0.002, "transient_person_share": 0.0,
           "half_life_changed": 0.90, "half_life_others_kept": 0.98, "surprise_auroc": 0.95}


@dataclass(frozen=True)
class Variant:
    """One map: which bag, and its changing-world rules."""

    name: str
    bag: str  # "people" or "person_free"
    depth: bool = False
    transient: bool = False
    half_life: float | None = None


def variants(half_life: float, more: list[float]) -> list[Variant]:
    """The maps of a run: the paper's update first on each bag (the reference of "others kept right")."""
    h = f"{half_life:g}"
    return [Variant("paper", "people"), Variant("depth", "people", depth=True),
            Variant("transient", "people", transient=True),
            Variant("depth+transient", "people", depth=True, transient=True),
            Variant(f"half-life {h}", "people", half_life=half_life),
            *[Variant(f"depth+transient+half-life {x:g}", "people", True, True, x) for x in (half_life, *more)],
            Variant("person-free paper", "person_free"), Variant("person-free depth", "person_free", depth=True)]


def reference(v: Variant, chosen: list[Variant]) -> str | None:
    """The map "others kept right" compares a forgetting variant with: the same rules without forgetting."""
    if v.half_life is None:
        return None
    return next(r.name for r in chosen if (r.depth, r.transient, r.half_life) == (v.depth, v.transient, None))


def make_bags(out: Path, args: argparse.Namespace) -> dict[str, Path]:
    """The two demos (made unless --reuse-bags finds them)."""
    dirs = {"people": out / "people", "person_free": out / "person_free"}
    for name, people in (("people", args.people), ("person_free", 0)):
        if args.reuse_bags and (dirs[name] / "bag" / "metadata.yaml").is_file():
            continue
        t = time.perf_counter()
        make_demo(dirs[name], num_gaussians=args.gaussians, frames=args.frames, width=args.width,
                  height=args.height, seed=args.seed, overwrite=True, progress=not args.quiet, backend=args.backend,
                  world=WorldOptions(people=people, change="sofa:box", depth="32FC1"))
        print(f"made {dirs[name]} in {time.perf_counter() - t:.0f} s", file=sys.stderr)
    return dirs


def _config(bag_dir: Path, num_classes: int) -> ReplayConfig:
    return ReplayConfig(bag=bag_dir / "bag", model=bag_dir / "model.ply", classes=bag_dir / "classes.yaml",
                        out=bag_dir / "unused", num_classes=num_classes, quiet=True, output_bag=False)


def replay(bag_dir: Path, chosen: list[Variant], backend: str) -> dict[str, dict[str, Any]]:
    """Fuse the bag into one map per variant (the same frames), then render every frame's pose with each final
    map; returns each variant's figures."""
    classes = ClassSet.from_yaml(bag_dir / "classes.yaml")
    C = classes.num_classes
    person = classes.names.index(PERSON_CLASS) if PERSON_CLASS in classes.names else None
    model = GaussianModel.from_ply(bag_dir / "model.ply")
    maps, tallies, held = {}, {}, {}
    for v in chosen:
        transient = [person] if v.transient and person is not None else []
        maps[v.name] = SemanticMap(model, C, backend=backend, transient_classes=transient,
                                   evidence_half_life=v.half_life)
        tallies[v.name] = ChangeTally(C, 255, transient, classes.names)
        held[v.name] = np.zeros(2, dtype=np.int64)
    source = FrameSource(_config(bag_dir, C))
    source.check()
    for frame in source.frames():
        for v in chosen:
            view = maps[v.name].observe(frame.camera, frame.labels, frame.confidence, outputs=("labels", "surprise"),
                                        depth=frame.depth if v.depth else None)
            stats = maps[v.name].last_update
            assert stats is not None
            held[v.name] += (stats.transient, stats.occluded)
            tallies[v.name].add_input(frame.labels)
            tallies[v.name].add_observation(frame.index, frame.gt, frame.gt_changed, view.surprise)
    kept = {v.name: np.zeros(2, dtype=np.int64) for v in chosen}
    final = FrameSource(_config(bag_dir, C))
    final.present, final.anchor_count, final.pose_type = source.present, source.anchor_count, source.pose_type
    for frame in final.frames():
        labels = {v.name: maps[v.name].render(frame.camera, outputs=("labels",)).labels for v in chosen}
        assert frame.gt is not None
        others = (frame.gt != 255) & (frame.gt < C)
        if frame.gt_changed is not None:
            others &= frame.gt_changed == 255
        for v in chosen:
            tallies[v.name].add_render(labels[v.name], frame.gt, frame.gt_changed)
            ref = reference(v, chosen)
            if ref is not None:
                right_ref = others & (labels[ref] == frame.gt)
                kept[v.name] += (int((right_ref & (labels[v.name] == frame.gt)).sum()), int(right_ref.sum()))
    return {v.name: _figures(tallies[v.name].summary(), person, classes.names, held[v.name], kept[v.name],
                             reference(v, chosen)) for v in chosen}


def _figures(summary: dict[str, Any], person: int | None, names: tuple[str, ...], held: np.ndarray,
             kept: np.ndarray, kept_reference: str | None) -> dict[str, Any]:
    per_class = summary["rendered_pixels_per_class"]
    total = sum(per_class.values())
    return {
        "person_share": (per_class[names[person]] / total if person is not None and total else 0.0),
        "static_accuracy": summary["static_accuracy"]["value"],
        "changed_accuracy": summary["changed_accuracy"]["value"],
        "changed_accuracy_after": summary["changed_accuracy_after"]["value"],
        "others_accuracy": summary["others_accuracy"]["value"],
        "others_kept": float(kept[0] / kept[1]) if kept[1] else None,
        "others_kept_reference": kept_reference,
        "surprise_auroc": summary["surprise_auroc"]["value"],
        "surprise_frame": summary["surprise_auroc"].get("frame"),
        "transient_pixels": int(held[0]), "occluded_pixels": int(held[1]),
        "summary": summary,
    }


def _pct(x: float | None, digits: int = 2) -> str:
    return "n/a" if x is None else f"{100 * x:.{digits}f} %"


def table(results: dict[str, dict[str, Any]]) -> list[str]:
    """The markdown table of every variant."""
    rows = ["| variant | person share of the map | accuracy vs static truth | loss vs person-free | changed object "
            "in new class: all poses / after the change | others kept right (vs no forgetting) | surprise AUROC "
            "(frame) | held back: transient / occluded px |", "|---|---|---|---|---|---|---|---|"]
    for name, r in results.items():
        ref = results.get(f"person-free {name}") if not name.startswith("person-free") else None
        loss = "—" if ref is None or r["static_accuracy"] is None or ref["static_accuracy"] is None else \
            f"{100 * (ref['static_accuracy'] - r['static_accuracy']) + 0.0:+.2f} pt".replace("-0.00", "0.00")
        auroc = "n/a" if r["surprise_auroc"] is None else f"{r['surprise_auroc']:.3f} ({r['surprise_frame']})"
        rows.append(f"| {name} | {_pct(r['person_share'], 3)} | {_pct(r['static_accuracy'])} | {loss} | "
                    f"{_pct(r['changed_accuracy'], 1)} / {_pct(r['changed_accuracy_after'], 1)} | "
                    f"{_pct(r['others_kept']) if r['others_kept_reference'] else '—'} | {auroc} | "
                    f"{r['transient_pixels']} / {r['occluded_pixels']} |")
    return rows


def targets(results: dict[str, dict[str, Any]], half_life: float) -> list[tuple[str, str, bool | None]]:
    """(target, measured, met) of each target (met None: not measured)."""
    h = f"{half_life:g}"
    d, free, t = results["depth"], results["person-free depth"], results["transient"]
    hl = results[f"half-life {h}"]
    out: list[tuple[str, str, bool | None]] = []

    def check(what: str, value: float | None, ok: bool | None, text: str) -> None:
        out.append((what, text if value is not None else "n/a", None if value is None else ok))

    loss = None if d["static_accuracy"] is None or free["static_accuracy"] is None else \
        free["static_accuracy"] - d["static_accuracy"]
    check("depth: person share <= 0.05 %", d["person_share"], d["person_share"] <= TARGETS["depth_person_share"],
          _pct(d["person_share"], 3))
    check("depth: accuracy loss vs person-free <= 0.2 pt", loss,
          loss is not None and loss <= TARGETS["depth_accuracy_loss"],
          "n/a" if loss is None else f"{100 * loss:.2f} pt".replace("-0.00", "0.00"))
    check("transient classes without depth: person share 0 %", t["person_share"],
          t["person_share"] <= TARGETS["transient_person_share"], _pct(t["person_share"], 3))
    for key, where in (("changed_accuracy", "all poses"), ("changed_accuracy_after", "poses after the change")):
        check(f"half-life {h}: changed object in new class >= 90 % ({where})", hl[key],
              (hl[key] or 0) >= TARGETS["half_life_changed"], _pct(hl[key], 1))
    check(f"half-life {h}: others kept right >= 98 % (vs the paper's update)", hl["others_kept"],
          (hl["others_kept"] or 0) >= TARGETS["half_life_others_kept"], _pct(hl["others_kept"]))
    for name in ("paper", f"half-life {h}"):
        a = results[name]["surprise_auroc"]
        check(f"{name}: surprise AUROC at the first changed frame >= 0.95", a,
              (a or 0) >= TARGETS["surprise_auroc"], "n/a" if a is None else f"{a:.3f}")
    return out


def check_replay(bag_dir: Path, out: Path, half_life: float, mine: dict[str, Any]) -> list[str]:
    """Run css_replay on the people bag with the last variant's rules; the differences between its report's
    figures and the benchmark's (none expected)."""
    from css_ros.evaluation.cli import main as css_replay

    rc = css_replay([str(bag_dir / "bag"), "--out", str(out), "--quiet", "--no-output-bag", "--transient-classes",
                     PERSON_CLASS, "--evidence-half-life", f"{half_life:g}"])
    if rc != 0:
        return [f"css_replay exited with {rc}"]
    cw = json.loads((out / "metrics.json").read_text())["changing_world"]
    diffs = []
    for key in ("static_accuracy", "changed_accuracy", "changed_accuracy_after", "others_accuracy", "surprise_auroc"):
        a, b = cw[key]["value"], mine[key]
        if (a is None) != (b is None) or (a is not None and abs(a - b) > 1e-9):
            diffs.append(f"{key}: css_replay {a}, benchmark {b}")
    held = cw["fused_pixels_without_evidence"]
    if (held["transient"], held["occluded"]) != (mine["transient_pixels"], mine["occluded_pixels"]):
        diffs.append(f"held back pixels: css_replay {held}, benchmark {mine['transient_pixels']} / "
                     f"{mine['occluded_pixels']}")
    return diffs


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("out") / "changing_world")
    p.add_argument("--quick", action="store_true", help=f"smaller demos ({QUICK})")
    for k, v in FULL.items():
        p.add_argument(f"--{k}", type=int, default=None, help=f"demo size (default {v}; --quick {QUICK[k]})")
    p.add_argument("--people", type=int, default=2, help="walkers in the people bag (2)")
    p.add_argument("--half-life", type=float, default=5.0,
                   help="evidence half-life of the forgetting variants the targets are checked on (5)")
    p.add_argument("--more-half-lives", type=float, nargs="*", default=[10.0, 20.0], metavar="H",
                   help="further half-lives, with depth and transient classes (10 20)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--backend", default="numba", help="rasteriser backend of the demo and the maps (numba)")
    p.add_argument("--reuse-bags", action="store_true", help="keep demos already in --out")
    p.add_argument("--check-replay", action="store_true",
                   help="also run css_replay on the people bag and check its report gives the same figures")
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)
    for k in FULL:
        if getattr(args, k) is None:
            setattr(args, k, (QUICK if args.quick else FULL)[k])
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    t0 = time.perf_counter()
    args.out.mkdir(parents=True, exist_ok=True)
    dirs = make_bags(args.out, args)
    chosen = variants(args.half_life, args.more_half_lives)
    results: dict[str, dict[str, Any]] = {}
    for bag in ("people", "person_free"):
        t = time.perf_counter()
        results.update(replay(dirs[bag], [v for v in chosen if v.bag == bag], args.backend))
        print(f"replayed {dirs[bag]} in {time.perf_counter() - t:.0f} s", file=sys.stderr)
    checks = targets(results, args.half_life)
    machine = f"{platform.machine()}, {os.cpu_count()} CPUs, {platform.python_version()}, backend {args.backend}"
    lines = [f"# A changing world ({args.gaussians} Gaussians, {args.frames} frames of {args.width}x{args.height}, "
             f"{args.people} people, sofa -> box from frame {args.frames // 2}, seed {args.seed})", "",
             *table(results), "", "| target | measured | met |", "|---|---|---|",
             *[f"| {w} | {m} | {'n/a' if ok is None else ('yes' if ok else 'NO')} |" for w, m, ok in checks], "",
             f"{machine}; {time.perf_counter() - t0:.0f} s in all."]
    diffs: list[str] = []
    if args.check_replay:
        last = f"depth+transient+half-life {args.half_life:g}"
        diffs = check_replay(dirs["people"], args.out / "replay_check", args.half_life, results[last])
        lines += ["", f"css_replay cross-check ({last}): " + ("the same figures" if not diffs else "; ".join(diffs))]
    text = "\n".join(lines) + "\n"
    (args.out / "results.md").write_text(text)
    (args.out / "results.json").write_text(json.dumps(
        {"config": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}, "machine": machine,
         "results": results, "targets": [{"target": w, "measured": m, "met": ok} for w, m, ok in checks]},
        indent=2, default=lambda x: x.item() if isinstance(x, np.generic) else str(x)))
    print(text)
    return 1 if diffs else 0


if __name__ == "__main__":
    sys.exit(main())
