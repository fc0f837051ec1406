"""css_view's opening view without a browser: the up axis of a map in any orientation, the ceiling cut, and a start
pose inside the room from which the engine's own render shows the observed classes.

The maps are the demo room with each Gaussian's true class (the model's class_id field) as its observation, the
ceiling left unobserved as in a replay, turned so that its vertical axis is each of the six frame axes.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from css_ros.engine.camera import Camera, intrinsics_from_fov, matrix_to_quaternion_xyzw
from css_ros.engine.classes import ClassSet
from css_ros.engine.gaussians import GaussianModel
from css_ros.engine.semantic_map import SemanticMap
from css_ros.engine.similarity import Similarity

pytest.importorskip("viser", reason="css_view needs the viser extra: pip install -e '.[view]'")

from css_ros.view.data import build_view_data  # noqa: E402
from css_ros.view.opening import (OPENING_FOV_Y, STEP_BACK, STEP_UP, camera_axes, opening_view)  # noqa: E402
from css_ros.view.server import MapView, frustum_scale  # noqa: E402

DEMO = Path(__file__).resolve().parents[1] / "bags" / "demo"

S = np.sqrt(0.5)
#: quaternion (x, y, z, w) turning the demo's z-up map frame so that its up axis becomes the key
TURNS = {"+z": (0, 0, 0, 1), "-z": (1, 0, 0, 0), "+y": (-S, 0, 0, S), "-y": (S, 0, 0, S), "+x": (0, S, 0, S),
         "-x": (0, -S, 0, S)}
AXES = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0), "+z": (0, 0, 1), "-z": (0, 0, -1)}
FURNITURE = ("rug", "table", "chair", "shelf", "sofa", "cabinet", "lamp", "plant", "box")


@pytest.fixture(scope="module")
def room():
    """(model, true class per Gaussian, classes) of the demo room."""
    from plyfile import PlyData

    model = GaussianModel.from_ply(DEMO / "model.ply")
    truth = np.asarray(PlyData.read(str(DEMO / "model.ply"))["vertex"]["class_id"], dtype=np.int64)
    return model, truth, ClassSet.from_yaml(DEMO / "classes.yaml")


def observed_map(model, truth, classes, ceiling_seen: bool = False) -> SemanticMap:
    smap = SemanticMap(model, classes.num_classes)
    seen = np.ones(len(truth), bool) if ceiling_seen else truth != classes.names.index("ceiling")
    conc = smap.concentrations.copy()
    conc[np.flatnonzero(seen), truth[seen]] += 5.0
    smap.concentrations = conc
    return smap


def turned(smap, classes, up: str):
    """View data of ``smap`` in a frame where the room's up is ``up``."""
    turn = Similarity.from_params([1.0, 0.0, 0.0, 0.0, *TURNS[up]])
    np.testing.assert_allclose(turn.apply(np.array([[0.0, 0.0, 1.0]]))[0], AXES[up], atol=1e-12)
    return build_view_data(smap, classes, splat_to_map=turn)


@pytest.mark.parametrize("up", sorted(TURNS))
def test_a_bare_map_finds_its_up_axis_from_its_surfaces(room, up):
    model, truth, classes = room
    o = opening_view(turned(observed_map(model, truth, classes), classes, up))
    assert o.up_source == "surfaces"
    np.testing.assert_array_equal(o.up, AXES[up])


@pytest.mark.parametrize("up", ["-z", "+x"])
def test_the_up_axis_holds_when_the_ceiling_was_observed_too(room, up):
    model, truth, classes = room
    o = opening_view(turned(observed_map(model, truth, classes, ceiling_seen=True), classes, up))
    np.testing.assert_array_equal(o.up, AXES[up])


@pytest.mark.parametrize("up", ["+z", "-x"])
def test_a_corridor_narrower_than_high_still_finds_its_floor(room, up):
    """The room squeezed along y to 2.1 m wide (2.7 m high; the Gaussians keep their shapes, so the room's
    surfaces keep their normals): the thinnest axis is now a wall's normal; the floor was observed and the
    ceiling not, which picks the vertical."""
    model, truth, classes = room
    narrow = GaussianModel.from_activated(model.means * [1.0, 2.1 / 6.0, 1.0], model.scales, model.rotations,
                                          model.opacities, model.base_colors)
    data = turned(observed_map(narrow, truth, classes), classes, up)
    extent = np.ptp(data.centers, axis=0)
    assert np.argmin(extent) != int(np.flatnonzero(AXES[up])[0])   # thinnest is not the vertical
    np.testing.assert_array_equal(opening_view(data).up, AXES[up])


def test_the_default_cut_removes_the_ceiling_and_keeps_the_furniture(room):
    model, truth, classes = room
    data = turned(observed_map(model, truth, classes), classes, "-y")
    view = MapView(data, "127.0.0.1", 0, title="t")
    try:
        heights = -data.centers[:, 1].astype(np.float64)      # brute force: the room's up is -y here
        ceiling = truth == classes.names.index("ceiling")
        furniture = np.isin(truth, [classes.names.index(n) for n in FURNITURE])
        assert view.opening.cut is not None
        assert heights[ceiling].min() > view.cut >= heights[furniture].max()
        assert np.array_equal(view.keep, heights <= view.cut)
        view.set_cut(1.0)
        assert np.array_equal(view.keep, heights <= 1.0)
        view.set_cut(view.cut_max())
        assert view.keep.all()
    finally:
        view.stop()


def test_a_map_without_a_ceiling_is_not_cut(room):
    model, truth, classes = room
    keep = np.flatnonzero(truth != classes.names.index("ceiling"))
    smap = observed_map(model.select(keep), truth[keep], classes)
    view = MapView(build_view_data(smap, classes), "127.0.0.1", 0, title="t")
    try:
        assert view.opening.cut is None and view.keep.all()
    finally:
        view.stop()


def engine_render(smap, up: str, data, o, size: int = 96):
    """The engine's labels from the opening camera, of the observed Gaussians below the cut (what the page shows
    in class colours; the cut ones are not drawn, the unobserved ones are grey), the map turned as ``data``."""
    heights = data.centers.astype(np.float64) @ o.up
    shown = np.flatnonzero(data.semantics.observed & (heights <= (o.cut if o.cut is not None else np.inf)))
    turn = Similarity.from_params([1.0, 0.0, 0.0, 0.0, *TURNS[up]])
    sub = SemanticMap(turn.transform_model(smap.model).select(shown), smap.num_classes)
    sub.concentrations = smap.concentrations[shown]
    right, down, fwd = camera_axes(o.look_at - o.position, o.up)
    K = intrinsics_from_fov(size, size, np.degrees(OPENING_FOV_Y))
    cam = Camera.from_pose(K, size, size, o.position, matrix_to_quaternion_xyzw(np.stack([right, down, fwd], 1)))
    return sub.render(cam).labels


@pytest.mark.parametrize("up", ["+z", "+y"])
def test_the_opening_camera_is_in_the_room_and_the_engine_sees_the_classes_from_it(room, up):
    model, truth, classes = room
    smap = observed_map(model, truth, classes)
    data = turned(smap, classes, up)
    o = opening_view(data)
    assert o.source == "a viewpoint inside the observed box"
    lo, hi = np.percentile(data.centers, 1, axis=0), np.percentile(data.centers, 99, axis=0)
    assert np.all(o.position > lo) and np.all(o.position < hi), (o.position, lo, hi)
    assert o.position @ o.up < o.cut
    labels = engine_render(smap, up, data, o)
    counts = np.bincount(labels[labels < classes.num_classes], minlength=classes.num_classes) / labels.size
    assert np.count_nonzero(counts >= 0.01) >= 5 and counts.sum() >= 0.6, counts


def level_trajectory(up: np.ndarray, pitch_deg: float):
    """Eight cameras on a 2 m circle around the room's centre at 1.2 m, looking inwards and ``pitch_deg`` down,
    in the z-up demo frame turned to y up: (T_map_cam (4, 4), fov_y, aspect, u_var) rows."""
    turn = Similarity.from_params([1.0, 0.0, 0.0, 0.0, *TURNS["+y"]])
    rows = []
    for k in range(8):
        yaw = np.radians(45.0 * k)
        fwd_z_up = -np.array([np.cos(yaw), np.sin(yaw), 0.0]) * np.cos(np.radians(pitch_deg)) + \
            np.array([0.0, 0.0, -np.sin(np.radians(pitch_deg))])
        pos_z_up = np.array([2.0 * np.cos(yaw), 2.0 * np.sin(yaw), 1.2])
        fwd, pos = turn.apply(fwd_z_up[None])[0] - turn.apply(np.zeros((1, 3)))[0], turn.apply(pos_z_up[None])[0]
        right, down, f = camera_axes(fwd, up)
        T = np.eye(4)
        T[:3, :3] = np.stack([right, down, f], 1)
        T[:3, 3] = pos
        rows.append((T, np.radians(50.0), 4 / 3, 0.01))
    return rows


@pytest.mark.parametrize("pitch", [0.0, 30.0])
def test_a_trajectory_gives_the_up_axis_and_the_start_over_a_frames_shoulder(room, pitch):
    model, truth, classes = room
    data = turned(observed_map(model, truth, classes), classes, "+y")
    up = np.array([0.0, 1.0, 0.0])
    data.trajectory = level_trajectory(up, pitch)
    o = opening_view(data)
    assert o.up_source == "trajectory"
    np.testing.assert_array_equal(o.up, up)
    assert o.source.startswith("trajectory frame ")
    T = data.trajectory[int(o.source.split()[-1])][0]
    level = T[:3, 2] - (T[:3, 2] @ up) * up
    expected = T[:3, 3] - STEP_BACK * level / np.linalg.norm(level) + STEP_UP * up
    np.testing.assert_allclose(o.position, expected, atol=1e-9)
    ahead = (o.look_at - o.position) / np.linalg.norm(o.look_at - o.position)
    target = T[:3, 3] + 1.5 * T[:3, 2] - o.position
    np.testing.assert_allclose(ahead, target / np.linalg.norm(target), atol=1e-9)


def test_up_given_on_the_command_line_wins(room):
    model, truth, classes = room
    data = turned(observed_map(model, truth, classes), classes, "+y")
    o = opening_view(data, up=np.array([1.0, 0.0, 0.0]))
    assert o.up_source == "--up" and np.array_equal(o.up, [1.0, 0.0, 0.0])
    from css_ros.view.cli import build_parser, up_vector

    assert np.array_equal(up_vector(build_parser().parse_args(["m.npz", "--up=-y"]).up), [0.0, -1.0, 0.0])
    assert np.array_equal(up_vector(build_parser().parse_args(["m.npz", "--up", "y"]).up), [0.0, 1.0, 0.0])
    assert np.array_equal(up_vector(build_parser().parse_args(["m.npz", "--up", "+x"]).up), [1.0, 0.0, 0.0])
    with pytest.raises(SystemExit):
        build_parser().parse_args(["m.npz", "--up", "w"])


def test_frustums_shrink_where_frames_crowd():
    line = np.outer(np.arange(20) * 0.1, [1.0, 0.0, 0.0])
    assert frustum_scale(line) == pytest.approx(0.05)
    assert frustum_scale(line * 10.0) == pytest.approx(0.15)
    assert frustum_scale(line[:1]) == pytest.approx(0.15)


@pytest.mark.parametrize("shape", ["one point", "five in one place", "a vertical line", "a flat patch"])
def test_degenerate_maps_open_at_a_finite_pose(shape):
    means = {"one point": np.zeros((1, 3)), "five in one place": np.zeros((5, 3)),
             "a vertical line": np.c_[np.zeros(50), np.zeros(50), np.linspace(0.0, 2.0, 50)],
             "a flat patch": np.random.default_rng(0).uniform(-1, 1, (30, 3)) * [1.0, 1.0, 0.0]}[shape]
    n = len(means)
    model = GaussianModel.from_activated(means, np.full((n, 3), 0.05), np.tile([1.0, 0, 0, 0], (n, 1)),
                                         np.full(n, 0.9), np.full((n, 3), 0.5))
    smap = SemanticMap(model, 3)
    smap.concentrations = smap.concentrations + np.array([0.0, 5.0, 0.0])
    view = MapView(build_view_data(smap, ClassSet.default(3)), "127.0.0.1", 0, title="t")
    try:
        o = view.opening
        assert np.isfinite(o.position).all() and np.isfinite(o.look_at).all()
        assert np.linalg.norm(o.look_at - o.position) > 0.1 and abs(np.linalg.norm(o.up) - 1.0) < 1e-12
        assert view.keep.all()
    finally:
        view.stop()
