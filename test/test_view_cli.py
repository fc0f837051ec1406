"""css_view's command line: bad input gives one clear line and an exit code, a good map serves a page."""
from __future__ import annotations

import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("viser", reason="css_view needs the viser extra: pip install -e '.[view]'")

from cdp_browser import free_port  # noqa: E402

from css_ros.engine.gaussians import GaussianModel  # noqa: E402
from css_ros.engine.semantic_map import SemanticMap  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def css_view(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "css_ros.view.cli", *args], capture_output=True, text=True,
                          timeout=timeout)


def tiny_model(path: Path, n: int = 200, seed: int = 0) -> GaussianModel:
    rng = np.random.default_rng(seed)
    model = GaussianModel.from_activated(rng.uniform(-1, 1, (n, 3)), np.full((n, 3), 0.05),
                                         np.tile([1.0, 0, 0, 0], (n, 1)), np.full(n, 0.8), rng.uniform(0, 1, (n, 3)))
    model.to_ply(path)
    return model


@pytest.fixture()
def tiny_map(tmp_path):
    model = tiny_model(tmp_path / "model.ply")
    smap = SemanticMap(model, 3)
    smap.save(tmp_path / "map.npz")
    return tmp_path


def test_missing_files_are_one_line_errors(tmp_path, tiny_map):
    r = css_view(str(tmp_path / "nope.npz"), "--model", str(tiny_map / "model.ply"))
    assert r.returncode == 1 and r.stderr.strip() == f"css_view: error: map not found: {tmp_path / 'nope.npz'}"
    r = css_view(str(tiny_map / "map.npz"), "--model", str(tmp_path / "no.ply"))
    assert r.returncode == 1 and "model file not found" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    r = css_view(str(tiny_map / "map.npz"))
    assert r.returncode == 1 and "--model is required" in r.stderr
    (tmp_path / "empty").mkdir()
    r = css_view(str(tmp_path / "empty"))  # a folder without map.npz
    assert r.returncode == 1 and "no map.npz" in r.stderr


def test_map_of_another_model_is_refused(tmp_path, tiny_map):
    tiny_model(tmp_path / "other.ply", seed=1)
    r = css_view(str(tiny_map / "map.npz"), "--model", str(tmp_path / "other.ply"), "--port", str(free_port()))
    assert r.returncode == 1 and "this map belongs to model" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_port_in_use_is_named(tiny_map):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        r = css_view(str(tiny_map / "map.npz"), "--model", str(tiny_map / "model.ply"), "--port", str(port))
    assert r.returncode == 1
    assert f"cannot serve on 127.0.0.1:{port}" in r.stderr and "--port" in r.stderr


def printed_url(proc: subprocess.Popen, timeout: float = 60.0) -> str | None:
    """The URL css_view prints on its "css_view: open URL" line (None if it exits or takes too long)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            return None
        if line.startswith("css_view: open "):
            return line.split()[2]
    return None


def test_port_out_of_range_is_refused_and_port_0_prints_the_port_taken(tiny_map):
    r = css_view(str(tiny_map / "map.npz"), "--model", str(tiny_map / "model.ply"), "--port", "70000")
    assert r.returncode == 1 and "--port 70000 is not a TCP port" in r.stderr and "Traceback" not in r.stderr
    proc = subprocess.Popen([sys.executable, "-m", "css_ros.view.cli", str(tiny_map / "map.npz"), "--model",
                             str(tiny_map / "model.ply"), "--port", "0", "--exit-after", "60"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        url = printed_url(proc)
        assert url is not None and not url.endswith(":0")
        with urllib.request.urlopen(url, timeout=10) as resp:
            assert resp.status == 200
    finally:
        proc.terminate()
        proc.wait(10)


def test_serves_the_page_and_prints_the_url(tiny_map):
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "css_ros.view.cli", str(tiny_map / "map.npz"), "--model",
                             str(tiny_map / "model.ply"), "--port", str(port), "--exit-after", "60"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        url = printed_url(proc)
        assert url == f"http://127.0.0.1:{port}"
        with urllib.request.urlopen(url, timeout=10) as resp:
            assert resp.status == 200 and b"<html" in resp.read(2000).lower()
    finally:
        proc.terminate()
        proc.wait(10)


def test_click_picks_the_first_gaussian_on_the_ray_and_queries_there(tmp_path):
    from css_ros.engine.classes import ClassSet
    from css_ros.io.trajectory import load_trajectory, write_replay_trajectory
    from css_ros.engine.camera import Camera, intrinsics_from_fov
    from css_ros.view.data import build_view_data
    from css_ros.view.server import MapView, pick_gaussian

    # three Gaussians on the z axis at z = 1, 2, 3 and one off the ray
    means = np.array([[0, 0, 3.0], [0, 0, 1.0], [0, 0, 2.0], [1.0, 0, 1.0]])
    model = GaussianModel.from_activated(means, np.full((4, 3), 0.05), np.tile([1.0, 0, 0, 0], (4, 1)),
                                         np.full(4, 0.9), np.full((4, 3), 0.5))
    smap = SemanticMap(model, 2)
    conc = np.full((4, 2), 1e-3)
    conc[:, 1] += 10.0
    conc[1] = [30.0, 1e-3]       # the nearest one on the ray holds class 0
    smap.concentrations = conc
    data = build_view_data(smap, ClassSet(("road", "tree"), np.array([[255, 0, 0], [0, 255, 0]], np.uint8)))
    keep = np.ones(4, bool)
    assert pick_gaussian(data, keep, np.zeros(3), np.array([0, 0, 1.0])) == 1
    keep[1] = False
    assert pick_gaussian(data, keep, np.zeros(3), np.array([0, 0, 1.0])) == 2
    assert pick_gaussian(data, keep, np.zeros(3), np.array([0, 1.0, 0])) is None
    # a replay trajectory round trip, drawn as frustums
    cam = Camera.from_pose(intrinsics_from_fov(64, 48, 60.0), 64, 48, [0, 0, -1.0], [0, 0, 0, 1.0])
    write_replay_trajectory(tmp_path / "trajectory.npz", [(cam, 0.01), (cam, None)])
    traj = load_trajectory(tmp_path / "trajectory.npz")
    assert np.allclose(traj[0][0], cam.T_map_cam) and traj[0][3] == 0.01 and np.isnan(traj[1][3])
    assert traj[0][1] == pytest.approx(2 * np.arctan(24 / cam.fy)) and traj[0][2] == pytest.approx(64 / 48)
    data.trajectory = traj

    def query(xyz):
        q = smap.query_points(xyz)
        return q.labels, q.expectation, q.variance

    view = MapView(data, port=free_port(), query=query)
    try:
        text = view.show_query(means[1])
        q = smap.query_points(means[1:2])
        assert "**road**" in text and f"| road | {q.expectation[0, 0]:.3f} | {q.variance[0, 0]:.2e} |" in text
    finally:
        view.stop()


def test_replay_prints_the_view_command():
    from css_ros.evaluation.cli import view_command
    from css_ros.evaluation.config import ReplayConfig

    cfg = ReplayConfig.__new__(ReplayConfig)
    object.__setattr__(cfg, "out", Path("out/replay demo"))
    assert view_command(cfg) == "css_view 'out/replay demo'"


def test_view_stream_sends_exactly_the_visibly_changed_gaussians():
    from css_ros.engine.field3d import gaussian_semantics
    from css_ros.io.clouds import unpack_cloud
    from css_ros.io.view_stream import changed_gaussians, semantic_keys, semantics_columns
    from css_ros.view.live import semantics_from

    rng = np.random.default_rng(3)
    n, c = 5000, 6
    conc = np.full((n, c), 1e-3)
    seen = rng.random(n) < 0.6
    conc[seen, rng.integers(0, c, seen.sum())] += rng.uniform(0.1, 40, seen.sum())
    keys = np.full(n, -1, np.int64)
    first = changed_gaussians(conc, 1e-3, 0.5, 255, keys)
    assert np.array_equal(first, np.arange(n))                      # everything is new
    ref = gaussian_semantics(conc, 1e-3, 0.5, 255)
    assert np.array_equal(keys, semantic_keys(ref.label, ref.expectation, ref.evidence))
    bump = rng.choice(n, 300, replace=False)
    conc[bump, 1] += 25.0                                           # a visible change
    conc[seen, 3] += 1e-9                                           # an invisible one on the observed
    assert np.array_equal(changed_gaussians(conc, 1e-3, 0.5, 255, keys), np.sort(bump))
    # the message's columns give back label, E (to 1/510), Var and evidence
    sem = gaussian_semantics(conc[bump], 1e-3, 0.5, 255)
    from types import SimpleNamespace

    f = semantics_columns(bump, sem.label, sem.expectation, sem.evidence)
    msg = SimpleNamespace(**{**f, "fields": [SimpleNamespace(name=n, offset=o, datatype=d, count=k)
                                             for n, o, d, k in f["fields"]], "data": f["data"].tobytes()})
    rows = unpack_cloud(msg)
    lab, e, var, total, obs = semantics_from(rows["label"], rows["expectation"], rows["evidence"], c, 1e-3, 0.5)
    assert np.array_equal(rows["index"], bump) and np.array_equal(lab, sem.label) and np.array_equal(obs, sem.observed)
    np.testing.assert_allclose(e, sem.expectation, atol=0.5 / 255 + 1e-7)
    np.testing.assert_allclose(var, e * (1 - e) / (1 + sem.total), rtol=1e-5)


def test_a_replay_folder_names_its_model_classes_and_trajectory(tmp_path, tiny_map):
    import argparse
    import json

    from css_ros.view.cli import resolve_inputs

    out = tmp_path / "replay"
    out.mkdir()
    (out / "map.npz").write_bytes((tiny_map / "map.npz").read_bytes())
    classes = ROOT / "bags" / "demo" / "classes.yaml"
    (out / "metrics.json").write_text(json.dumps({"config": {"model": str(tiny_map / "model.ply"),
                                                             "classes": str(classes)}}))
    (out / "trajectory.npz").write_bytes(b"")
    args = argparse.Namespace(map=out, model=None, classes=None)
    assert resolve_inputs(args) == (out / "map.npz", tiny_map / "model.ply", classes, out / "trajectory.npz")
    args = argparse.Namespace(map=out, model=tmp_path / "other.ply", classes=None)
    with pytest.raises(Exception, match="model file not found"):
        resolve_inputs(args)


def test_a_replay_made_with_splat_to_map_is_shown_and_queried_in_the_map_frame(tmp_path):
    """A robot's replay (splat_to_map: scale 2, 90 deg about z, shifted) is drawn in the map frame: centres
    s R mu + t and covariances s^2 R Sigma R^T (R written out by hand), frustums carried along, and a click at a
    Gaussian's map-frame centre answers what the map holds at its splat-frame centre."""
    import argparse
    import json

    from css_ros.engine.camera import Camera, intrinsics_from_fov
    from css_ros.engine.classes import ClassSet
    from css_ros.io.trajectory import load_trajectory, write_replay_trajectory
    from css_ros.view.cli import display_frame, map_frame_query
    from css_ros.view.data import build_view_data

    model = tiny_model(tmp_path / "model.ply")
    smap = SemanticMap(model, 3)
    conc = np.full((model.num_gaussians, 3), 1e-3)
    conc[np.arange(model.num_gaussians), np.arange(model.num_gaussians) % 3] = 20.0
    smap.concentrations = conc
    out = tmp_path / "replay"
    out.mkdir()
    h = np.sqrt(0.5)
    params = [2.0, 1.0, -2.0, 0.5, 0.0, 0.0, h, h]          # qz = qw = sqrt(1/2): +90 deg about z
    (out / "metrics.json").write_text(json.dumps({"config": {"splat_to_map": params}}))
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    t = np.array([1.0, -2.0, 0.5])
    to_map = display_frame(argparse.Namespace(map=out, splat_to_map=None))
    data = build_view_data(smap, ClassSet.default(3), splat_to_map=to_map)
    mu = model.means.astype(np.float64)
    np.testing.assert_allclose(data.centers, 2.0 * mu @ R.T + t, atol=1e-5)
    np.testing.assert_allclose(data.covariances, 4.0 * R @ model.covariances() @ R.T, rtol=1e-4, atol=1e-9)
    # --splat-to-map wins over the folder's; no folder and no option: the splat frame
    assert display_frame(argparse.Namespace(map=out, splat_to_map=[1.0, 0, 0, 0, 0, 0, 0, 1])).is_identity
    assert display_frame(argparse.Namespace(map=tmp_path / "map.npz", splat_to_map=None)).is_identity
    # the click query: at the map-frame centre of Gaussian k, the field of the splat-frame centre
    labels, e, _ = map_frame_query(smap, to_map)(data.centers[:4].astype(np.float64))
    ref = smap.query_points(mu[:4])
    assert np.array_equal(labels, ref.labels) and np.allclose(e, ref.expectation, atol=1e-6)
    # the trajectory is written in the map frame: centre moved, axes turned by R (not scaled)
    cam = Camera.from_pose(intrinsics_from_fov(64, 48, 60.0), 64, 48, [0.3, 0.1, -1.0], [0, 0, 0, 1.0])
    write_replay_trajectory(out / "trajectory.npz", [(cam, 0.01)], to_map)
    pose = load_trajectory(out / "trajectory.npz")[0][0]
    np.testing.assert_allclose(pose[:3, 3], 2.0 * R @ cam.T_map_cam[:3, 3] + t, atol=1e-12)
    np.testing.assert_allclose(pose[:3, :3], R @ cam.T_map_cam[:3, :3], atol=1e-12)

