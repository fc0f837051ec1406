"""``css_view``: serve the semantic splat of a map (or a css_replay output folder) as a web page."""
from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from pathlib import Path
from typing import Sequence

import numpy as np

from ..console import run_console
from ..engine.gaussians import GaussianModel
from ..engine.semantic_map import SemanticMap
from ..engine.similarity import Similarity
from ..errors import CssError
from .data import build_view_data, classes_for_map
from .opening import UP_CHOICES, axis_label, up_vector
from ..io.trajectory import load_trajectory

EXAMPLES = """\
examples:
  css_view out/replay_demo                                  # a css_replay output folder (map, model, classes, trajectory)
  css_view map.npz --model model.ply --classes classes.yaml # a map file
  css_view map.npz --model model.ply --up y                 # y is up (x, y, z; --up=-y for -y)
  css_view map.npz --model big.ply --max-gaussians 500000   # the 500k most informative Gaussians only
  css_view --live                                           # follow a running css_node over DDS

Open the printed URL in a browser. The page opens inside the map, on its observed surfaces: over the shoulder of
a fused frame (replay folders), else at the in-room viewpoint that shows the most classes, with ceilings cut
away along the up axis (the "Cut above" slider; its right end shows everything). Modes: RGB, semantic class,
E and Var of the argmax class, evidence; filters, class legend with toggles, camera trajectory coloured by
U_var, click for a point query.
"""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="css_view", description="Serve the semantic splat of a css_ros map as a web "
                                "page (viser; any WebGL browser).", epilog=EXAMPLES,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("map", type=Path, nargs="?", help="map .npz, or a css_replay output folder")
    p.add_argument("--model", type=Path, metavar="PLY", help="splat model of the map (default: from the "
                   "replay folder's metrics.json)")
    p.add_argument("--classes", type=Path, metavar="YAML", help="class file (default: the replay's, else "
                   "anonymous class_i)")
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (0.0.0.0: every interface; "
                   "default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8080, help="port (default 8080)")
    p.add_argument("--max-gaussians", type=int, default=None, metavar="N",
                   help="draw only the N most informative Gaussians (observed first, by evidence)")
    p.add_argument("--splat-to-map", type=float, nargs=8, metavar=("S", "X", "Y", "Z", "QX", "QY", "QZ", "QW"),
                   help="show the map in the map frame of this similarity (css_node's splat_to_map; default: the "
                   "replay folder's, else the splat's own frame)")
    p.add_argument("--up", choices=UP_CHOICES, default=None, metavar="AXIS",
                   help="the map's up axis: x, y, z, or -x, -y, -z written as --up=-y (default: from the trajectory, "
                   "else estimated from the map's surfaces); the page opens level with it and cuts ceilings along it")
    p.add_argument("--live", action="store_true", help="follow a running css_node over DDS (shows the node's "
                   "map frame)")
    p.add_argument("--node", default="/css_node", help="node name to follow with --live (default /css_node)")
    p.add_argument("--camera", default="", metavar="NS", help="with --live: the camera namespace of the node whose "
                   "frame images (surprise) the page shows (default: the un-namespaced camera)")
    p.add_argument("--exit-after", type=float, default=None, help=argparse.SUPPRESS)  # tests and benchmarks
    return p


def replay_config(folder: Path) -> dict:
    """The options a css_replay output folder was made with (``config`` of its metrics.json), or {} when the
    folder has no metrics.json."""
    metrics = folder / "metrics.json"
    if not metrics.is_file():
        return {}
    try:
        info = json.loads(metrics.read_text())
    except (OSError, ValueError) as exc:
        raise CssError(f"cannot read {metrics}: {exc}") from None
    cfg = info.get("config", {}) if isinstance(info, dict) else {}
    return cfg if isinstance(cfg, dict) else {}


def resolve_inputs(args: argparse.Namespace) -> tuple[Path, Path, Path | None, Path | None]:
    """(map file, model PLY, class file or None, trajectory file or None) from the arguments."""
    if args.map is None:
        raise CssError("give a map .npz or a css_replay output folder (or --live)")
    target: Path = args.map
    if not target.exists():
        raise CssError(f"map not found: {target}")
    model, classes, traj = args.model, args.classes, None
    if target.is_dir():
        map_file = target / "map.npz"
        if not map_file.is_file():
            raise CssError(f"{target} holds no map.npz (not a css_replay output folder)")
        cfg = replay_config(target)
        if model is None and cfg.get("model"):
            model = Path(cfg["model"])
        if classes is None and cfg.get("classes"):
            classes = Path(cfg["classes"])
        if (target / "trajectory.npz").is_file():
            traj = target / "trajectory.npz"
    else:
        map_file = target
    if model is None:
        raise CssError("--model is required with a map file (the splat PLY the map was made on)")
    if not model.is_file():
        raise CssError(f"model file not found: {model}")
    if classes is not None and not classes.is_file():
        raise CssError(f"class file not found: {classes}")
    return map_file, model, classes, traj


def display_frame(args: argparse.Namespace) -> Similarity:
    """The splat -> map similarity the page is drawn in: ``--splat-to-map``, else the one a css_replay output
    folder was made with (its metrics.json config), else the identity (the splat's own frame)."""
    if args.splat_to_map is not None:
        return Similarity.from_params(args.splat_to_map, "--splat-to-map")
    cfg = replay_config(args.map) if args.map is not None and args.map.is_dir() else {}
    if cfg.get("splat_to_map") is not None:
        return Similarity.from_params(cfg["splat_to_map"], f"{args.map / 'metrics.json'}: splat_to_map")
    return Similarity.identity()


def map_frame_query(smap: SemanticMap, to_map: Similarity):
    """The page's click query: points in the page's (map) frame, answered by the map in the splat's frame.
    Returns a function (M, 3) -> (labels (M,), E (M, C), Var (M, C))."""
    to_splat = to_map.inverse()

    def query(xyz: np.ndarray):
        q = smap.query_points(to_splat.apply(np.asarray(xyz, np.float64).reshape(-1, 3)))
        return q.labels, q.expectation, q.variance
    return query


def opening_line(view) -> str:
    """One line on where the page opens: the up axis and its source, the ceiling cut, the start pose."""
    o = view.opening
    cut = f"cut above {view.cut:.2f} m" if o.cut is not None else "no ceiling found, nothing cut"
    return (f"css_view: up {axis_label(o.up)} (from {o.up_source}), {cut}; opens at {o.source} "
            f"({o.classes_shown} classes in sight)")


def serve_offline(args: argparse.Namespace) -> int:
    """Load the map, serve it, block until interrupted (or ``--exit-after`` seconds)."""
    from .server import MapView, check_port_free

    map_file, model_file, class_file, traj_file = resolve_inputs(args)
    if args.max_gaussians is not None and args.max_gaussians < 1:
        raise CssError("--max-gaussians must be >= 1")
    check_port_free(args.host, args.port)  # before the (long) load
    t0 = time.perf_counter()
    model = GaussianModel.from_ply(model_file)
    smap = SemanticMap.load(map_file, model)
    classes = classes_for_map(smap, class_file)
    to_map = display_frame(args)
    data = build_view_data(smap, classes, args.max_gaussians, splat_to_map=to_map)
    if traj_file is not None:
        data.trajectory = load_trajectory(traj_file)   # css_replay writes it in the map frame
    view = MapView(data, args.host, args.port, query=map_frame_query(smap, to_map),
                   title=f"{map_file.name} on {model_file.name}", up=up_vector(args.up))
    print(f"css_view: {len(data.index):,} of {model.num_gaussians:,} Gaussians loaded in "
          f"{time.perf_counter() - t0:.1f} s", flush=True)
    print(opening_line(view), flush=True)
    print(f"css_view: open {view.url}  (Ctrl+C to stop)", flush=True)
    wait(args.exit_after)
    view.stop()
    return 0


def wait(seconds: float | None) -> None:
    """Block until Ctrl+C (or ``seconds``)."""
    done = threading.Event()
    try:
        done.wait(seconds) if seconds is not None else done.wait()
    except KeyboardInterrupt:
        pass


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``css_view``: 0 on success, 1 with a one-line error, 2 for usage errors."""
    args = build_parser().parse_args(argv)

    def work() -> int:
        try:
            import viser  # noqa: F401
        except ModuleNotFoundError:
            raise CssError("css_view needs the viser package: pip install 'css_ros[view]' (or '.[ros]' / '.[all]' "
                           "from a checkout)") from None
        if args.live:
            from .live import serve_live
            return serve_live(args)
        return serve_offline(args)

    return run_console("css_view", work)


if __name__ == "__main__":
    sys.exit(main())
