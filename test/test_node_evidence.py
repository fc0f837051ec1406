"""Several css_nodes, one map: evidence exchanged over real DDS (css_ros/ros/evidence.py, io/evidence.py).

Nodes run as subprocesses in their own namespaces on one ROS domain; each is fed a share of the frames and the
maps are compared with a node fed every frame (1e-9 relative). A test client also plays a source itself, with
packets built by the documented encoder, to check gaps, snapshots, replays and bad input.
"""
from __future__ import annotations

import sys
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
import ros_helpers as rh  # noqa: E402

from css_ros.engine.gaussians import GaussianModel  # noqa: E402
from css_ros.io import evidence as ev  # noqa: E402
from css_ros.io.evidence import DELTA, SNAPSHOT  # noqa: E402

pytestmark = pytest.mark.slow
PRIOR = 1e-3
FRAMES = 6
SNAPSHOT_PERIOD = 1.0


def _params(model: Path, ckpt: Path, **kw) -> dict:
    return dict(model_path=str(model), class_file="", num_classes=rh.NUM_CLASSES, prior=PRIOR,
                checkpoint_path=str(ckpt), resume=False, checkpoint_period=0.0, log_period=0.5, warmup=False,
                evidence_period=0.2, evidence_snapshot_period=SNAPSHOT_PERIOD, **kw)


def _start_peer(tmp_path, domain: int, model, paths: dict, name: str, peer: dict, origin: dict, log: str = "",
                **kw) -> tuple[rh.NodeProcess, rh.RosClient]:
    """Start node ``name`` (a, b: evidence peers with ``origin[name]``; ref: no exchange) under /<name> and a client
    of it; waits until it is up (a killed node's entities linger in DDS a while)."""
    ev = dict(publish_evidence=True, evidence_in=peer[name], evidence_origin=origin[name]) if name != "ref" else {}
    node = rh.NodeProcess({**_params(model, paths[name], **ev), **kw}, domain, tmp_path / f"{name}{log}.log",
                          remaps={"__ns": f"/{name}"})
    assert node.wait_log("services:", 60.0), node.log()
    client = _client(domain, f"/{name}")
    assert client.wait_connected(60.0), node.log()
    return node, client


def encode_packet(kind, origin, fp, seq, rows, values, prior, n, **kw):
    """The module's encoder, epoch 1, claiming one frame per sequence number (a snapshot: its id)."""
    kw.setdefault("frames", kw.get("snapshot_id") or seq)
    return ev.encode_packet(kind, origin, fp, seq, rows, values, prior, n, epoch=1, **kw)


def _frame(i: int) -> tuple[np.ndarray, tuple[float, float, float]]:
    rng = np.random.default_rng(100 + i)
    labels = rh.wall_labels().copy()
    labels[rng.integers(0, rh.HEIGHT, 40), rng.integers(0, rh.WIDTH, 40)] = 3
    return labels, (float(rng.uniform(-0.3, 0.3)), float(rng.uniform(-0.2, 0.2)), 0.0)


def _client(domain: int, ns: str) -> rh.RosClient:
    topics = {k: f"{ns}/{k}" for k in ("image", "segmentation", "segmentation_confidence", "camera_info", "pose",
                                       "candidates")}
    return rh.RosClient(domain, node_ns=f"{ns}/css_node", topics=topics)


def _feed(client: rh.RosClient, frames: list[int]) -> None:
    """Send each frame and wait for its output (sent again if lost to DDS discovery, never applied twice)."""
    for i in frames:
        labels, pos = _frame(i)
        stamp = (i + 1) * 10**9
        assert client.send_frame_until_processed(stamp, labels, position=pos) is not None, f"frame {i} not processed"


def _saved(client: rh.RosClient, path: Path) -> np.ndarray:
    assert client.call(client.save_client).success
    with np.load(path, allow_pickle=False) as data:
        return np.array(data["concentrations"]), [str(s) for s in data["sources"]]


def _evidence_log(nodes: dict) -> str:
    """The evidence exchange's log lines of each node (for a failure message: who sent, refused, took back what)."""
    keys = ("evidence", "return", "resumed", "refused", "took back", "epoch")
    return "\n".join(f"--- {name}\n" + "\n".join(line for line in node.log().splitlines()
                                                   if any(k in line for k in keys))[-3000:]
                     for name, node in nodes.items())


def _wait_holds(client: rh.RosClient, path: Path, origin: str | None, frames: int, timeout: float = 30.0) -> None:
    """Wait until the node of ``client`` holds ``frames`` frames of ``origin``'s evidence (None: of its one
    source), in step (its saved map's received_state: epoch, last sequence, frames, in step)."""
    end = time.monotonic() + timeout
    while True:
        assert client.call(client.save_client).success
        with np.load(path, allow_pickle=False) as data:
            names = [str(s) for s in data["received_sources"]] if "received_sources" in data else []
            state = np.array(data["received_state"]) if names else np.zeros((0, 4))
        held = {n: (int(st[2]), bool(st[3])) for n, st in zip(names, state)}
        if (held.get(origin) if origin is not None else next(iter(held.values()), None)) == (frames, True):
            return
        assert time.monotonic() < end, f"{path.stem} holds {held}, not {frames} frames of {origin!r}"
        time.sleep(0.2)


@contextmanager
def _peer_group(tmp_path, origin: dict):
    """Peers a and b (evidence exchange under ``origin``) and ref (no exchange) on a domain of their own, ref fed
    every frame (0..9). Yields (start, nodes, clients, paths, want): ``start(name, log, **kw)`` (re)starts one node
    (put it back in ``nodes`` / ``clients``), ``want`` is ref's map; every node in ``nodes`` is stopped at the end."""
    domain = rh.next_domain_id()
    model = rh.write_wall_model(tmp_path / "wall.ply")
    paths = {n: tmp_path / f"{n}.npz" for n in ("a", "b", "ref")}
    peer = {"a": "/b/css_node/evidence", "b": "/a/css_node/evidence"}

    def start(name: str, log: str = "", **kw) -> tuple[rh.NodeProcess, rh.RosClient]:
        return _start_peer(tmp_path, domain, model, paths, name, peer, origin, log, **kw)

    nodes: dict = {}
    clients: dict = {}
    try:
        for name in ("a", "b", "ref"):
            nodes[name], clients[name] = start(name)
        _feed(clients["ref"], list(range(10)))
        yield start, nodes, clients, paths, _saved(clients["ref"], paths["ref"])[0]
    finally:
        for c in clients.values():
            c.close()
        for n in nodes.values():
            n.stop()


def _converged(clients, paths, ref: np.ndarray, timeout: float = 20.0) -> list[np.ndarray]:
    end = time.monotonic() + timeout
    while True:
        maps = [_saved(c, p)[0] for c, p in zip(clients, paths)]
        if all(np.allclose(m, ref, rtol=1e-9, atol=0) for m in maps) or time.monotonic() > end:
            return maps
        time.sleep(0.3)


@pytest.mark.parametrize("n_nodes", [2, 3])
def test_nodes_sharing_evidence_equal_one_node_fed_every_frame(tmp_path, n_nodes):
    domain = rh.next_domain_id()
    model = rh.write_wall_model(tmp_path / "wall.ply")
    names = ["a", "b", "c"][:n_nodes]
    nodes, clients, paths = [], [], []
    try:
        for name in [*names, "ref"]:
            ckpt = tmp_path / f"{name}.npz"
            others = ",".join(f"/{o}/css_node/evidence" for o in names if o != name) if name != "ref" else ""
            nodes.append(rh.NodeProcess(_params(model, ckpt, publish_evidence=name != "ref", evidence_in=others,
                                                evidence_origin=f"robot_{name}"),
                                        domain, tmp_path / f"{name}.log", remaps={"__ns": f"/{name}"}))
            paths.append(ckpt)
        for name in [*names, "ref"]:
            clients.append(_client(domain, f"/{name}"))
        for c in clients:
            assert c.wait_connected(60.0), "node did not come up"
        for k, c in enumerate(clients[:-1]):
            _feed(c, [i for i in range(FRAMES) if i % n_nodes == k])
        _feed(clients[-1], list(range(FRAMES)))
        ref = _saved(clients[-1], paths[-1])[0]
        assert np.all(ref - PRIOR >= 0) and (ref - PRIOR).sum() > 100
        maps = _converged(clients[:-1], paths[:-1], ref)
        for name, m in zip(names, maps):
            np.testing.assert_allclose(m, ref, rtol=1e-9, atol=0, err_msg=f"node {name}")
        # no echo: after more snapshot periods the maps still equal the reference (echoed evidence would add up)
        time.sleep(2.5 * SNAPSHOT_PERIOD)
        for name, c, p in zip(names, clients, paths):
            m, sources = _saved(c, p)
            np.testing.assert_allclose(m, ref, rtol=1e-9, atol=0, err_msg=f"node {name} after settling")
            assert sources == sorted(f"robot_{o}" for o in names)
        if n_nodes == 2:  # a node started late catches up from the snapshots
            late_ckpt = tmp_path / "late.npz"
            nodes.append(rh.NodeProcess(_params(model, late_ckpt, evidence_in="/a/css_node/evidence,/b/css_node/evidence"),
                                        domain, tmp_path / "late.log", remaps={"__ns": "/late"}))
            late = _client(domain, "/late")
            clients.append(late)
            assert late.wait_connected(60.0)
            np.testing.assert_allclose(_converged([late], [late_ckpt], ref)[0], ref, rtol=1e-9, atol=0)
    finally:
        for c in clients:
            c.close()
        for n in nodes:
            n.stop()


def test_gaps_snapshots_replays_and_bad_packets_from_a_source(tmp_path):
    """The test client is source 'crafted': a lost packet is bridged by the next snapshot, bad packets refused."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_msgs.msg import UInt8MultiArray

    domain = rh.next_domain_id()
    model_path = rh.write_wall_model(tmp_path / "wall.ply")
    model = GaussianModel.from_ply(model_path)
    n, c, fp = model.num_gaussians, rh.NUM_CLASSES, model.fingerprint
    ckpt = tmp_path / "n.npz"
    node = rh.NodeProcess(_params(model_path, ckpt, evidence_in="/crafted/evidence", evidence_max_rate=40.0,
                                  evidence_allowed_origins="crafted,robot_z"), domain, tmp_path / "n.log")
    client = rh.RosClient(domain)
    try:
        pub = client.node.create_publisher(UInt8MultiArray, "/crafted/evidence",
                                           QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
        assert client.wait_connected(60.0)
        assert client.wait_until(lambda: pub.get_subscription_count() > 0, 30.0)

        def send(data: bytes) -> None:
            msg = UInt8MultiArray()
            msg.data = data
            pub.publish(msg)
            time.sleep(0.03)  # stay under the node's 40 packets/s

        rng = np.random.default_rng(0)
        d = [rng.uniform(0, 5, (n, c)) for _ in range(3)]
        rows = np.arange(n)
        pkt = lambda kind, seq, vals, **kw: encode_packet(kind, "crafted", fp, seq, rows, vals, PRIOR, n, **kw)  # noqa: E731
        send(pkt(SNAPSHOT, 1, np.zeros((n, c)), snapshot_id=1))
        send(pkt(DELTA, 2, d[0]))
        # seq 3 (d[1]) is lost; seq 4 arrives after the gap and must wait for a snapshot
        send(pkt(DELTA, 4, d[2]))
        send(pkt(DELTA, 2, d[0]))                                              # replayed
        bad = d[0].copy()
        bad[3, 1] = np.nan
        send(pkt(DELTA, 5, bad))                                               # NaN
        bad[3, 1] = -1.0
        send(pkt(DELTA, 6, bad))                                               # negative
        bad[3, 1] = 1e12
        send(pkt(DELTA, 7, bad))                                               # huge
        send(encode_packet(DELTA, "crafted", "ab" * 32, 8, rows, d[0], PRIOR, n))  # other model
        send(encode_packet(SNAPSHOT, "intruder", fp, 1, rows, d[0], PRIOR, n, snapshot_id=1))  # not allowed
        np.testing.assert_allclose(_saved(client, ckpt)[0], PRIOR + d[0], rtol=1e-12)
        total = d[0] + d[1] + d[2]
        send(encode_packet(SNAPSHOT, "crafted", fp, 9, rows[: n // 2], total[: n // 2], PRIOR, n, snapshot_id=9,
                           range_start=0, range_end=n // 2, part=0, parts=2))
        send(encode_packet(SNAPSHOT, "crafted", fp, 10, rows[n // 2:], total[n // 2:], PRIOR, n, snapshot_id=9,
                           range_start=n // 2, range_end=n, part=1, parts=2))
        send(pkt(DELTA, 11, d[0]))                                             # in step again: applied
        expected = PRIOR + total + d[0]
        got = client.wait_until(lambda: np.allclose(_saved(client, ckpt)[0], expected, rtol=1e-12), 10.0, 0.3)
        assert got, "snapshot did not bridge the gap"
        m, sources = _saved(client, ckpt)
        assert sources == ["crafted"]
        assert client.wait_until(lambda: int(client.diagnostics().get("evidence_packets_from[crafted]", 0)) >= 5, 10.0)
        for _ in range(120):                                                   # a flood: 120 packets at once
            msg = UInt8MultiArray()
            msg.data = pkt(DELTA, 1, d[0])
            pub.publish(msg)
        diag = client.wait_until(lambda: client.diagnostics() if any(
            k.startswith("evidence_refused[flood") for k in client.diagnostics()) else None, 20.0, 0.2)
        assert diag, "flood not reported"
        for reason in ("replayed or duplicate sequence number", "non-finite evidence", "negative evidence",
                       "evidence above the per-packet bound", "evidence of another splat model",
                       "origin not in evidence_allowed_origins",
                       "sequence gap or late start: waiting for a snapshot"):
            assert int(diag.get(f"evidence_refused[{reason}]", 0)) >= 1, reason
        np.testing.assert_allclose(_saved(client, ckpt)[0], expected, rtol=1e-12)  # nothing of it reached the map
        assert node.proc.poll() is None
    finally:
        client.close()
        node.stop()


def test_a_peer_killed_and_resumed_keeps_the_group_exactly_once(tmp_path):
    """A (even frames) and B (odd frames) exchange evidence; B is killed with SIGKILL right after a checkpoint while A
    keeps mapping, and restarted with resume:=true (same namespace, default origin id). At the end A and B both equal
    one node fed every frame (1e-9 relative): the resumed B knows which evidence is its own, A recognises B's restart
    at once (no "replayed" lock-out), and a ~/load_map of B's checkpoint counts nothing twice either."""
    from std_srvs.srv import Trigger

    origin = {"a": "robot_a", "b": ""}                      # B: the default origin (host name and pid)
    with _peer_group(tmp_path, origin) as (start, nodes, clients, paths, want):
        a = clients["a"]
        _feed(a, [0, 2])
        _feed(clients["b"], [1, 3])
        _wait_holds(a, paths["a"], None, 2)                 # A holds B's frames, B A's
        _wait_holds(clients["b"], paths["b"], "robot_a", 2)
        assert clients["b"].call(clients["b"].save_client).success
        clients["b"].close()
        nodes["b"].kill9()                                   # mid-run: A keeps mapping meanwhile
        _feed(a, [4, 6])
        nodes["b"], clients["b"] = start("b", log="_resumed", resume=True)
        b = clients["b"]
        assert "resumed from" in nodes["b"].log()
        _feed(b, [5, 7, 9])
        _feed(a, [8])
        maps = _converged([a, b], [paths["a"], paths["b"]], want, timeout=45.0)
        for name, m in zip("ab", maps):
            np.testing.assert_allclose(m, want, rtol=1e-9, atol=0,
                                       err_msg=f"node {name} after B's restart\n{_evidence_log(nodes)}")
        assert not any(k.startswith("evidence_refused[replayed") for k in a.diagnostics()), a.diagnostics()
        load = b.node.create_client(Trigger, "/b/css_node/load_map")
        assert b.call(load).success                          # B reloads its checkpoint: still exactly once
        time.sleep(2.5 * SNAPSHOT_PERIOD)
        maps = _converged([a, b], [paths["a"], paths["b"]], want, timeout=20.0)
        for name, m in zip("ab", maps):
            np.testing.assert_allclose(m, want, rtol=1e-9, atol=0, err_msg=f"node {name} after B's load_map")


@pytest.mark.parametrize("saved", ["early", "never"])
def test_a_peer_killed_without_saving_takes_back_its_evidence_from_the_group(tmp_path, saved):
    """Like the test above, but B is killed with SIGKILL long after its last checkpoint (saved after its first frame)
    or with none at all (a fresh map under its fixed origin id). Resumed, B flags its first snapshots "resumed"; A,
    holding more frames of B's previous epoch, sends them back (a return), B adopts them as its own and re-states
    them: A and B both end equal to one node fed every frame (1e-9 relative)."""
    with _peer_group(tmp_path, {"a": "robot_a", "b": "robot_b"}) as (start, nodes, clients, paths, want):
        a = clients["a"]
        _feed(a, [0, 2])
        _feed(clients["b"], [1])
        if saved == "early":
            assert clients["b"].call(clients["b"].save_client).success   # B's only checkpoint: one frame
        _feed(clients["b"], [3])
        _wait_holds(a, paths["a"], "robot_b", 2)            # A holds B's frames 1 and 3 (published)
        clients["b"].close()
        nodes["b"].kill9()
        _feed(a, [4, 6])
        nodes["b"], clients["b"] = start("b", log="_resumed", resume=True)
        b = clients["b"]
        _feed(b, [5, 7, 9])
        _feed(a, [8])
        maps = _converged([a, b], [paths["a"], paths["b"]], want, timeout=45.0)
        for name, m in zip("ab", maps):
            np.testing.assert_allclose(m, want, rtol=1e-9, atol=0,
                                       err_msg=f"node {name} after B's restart\n{_evidence_log(nodes)}")
        assert "took back the own evidence" in nodes["b"].log(), nodes["b"].log()   # (diagnostics: one topic)
        assert "return packet(s)" in nodes["a"].log(), nodes["a"].log()
        time.sleep(2.5 * SNAPSHOT_PERIOD)                   # settled: nothing counted twice later either
        maps = _converged([a, b], [paths["a"], paths["b"]], want, timeout=10.0)
        for name, m in zip("ab", maps):
            np.testing.assert_allclose(m, want, rtol=1e-9, atol=0, err_msg=f"node {name} after settling")


def test_peers_that_swap_to_a_retrained_splat_count_nothing_twice(tmp_path):
    """A and B exchange evidence (A frames 0 and 2, B frames 1 and 3), then both swap to a retrained splat dropped
    into their watch folders. Each moves its peer's evidence as received (not as its own); each peer's first
    snapshot on the new splat replaces the moved copy. Both end with equal maps holding the evidence once: its
    total is the pre-swap total times the transfer's ratio, not twice it (what re-publishing the peer's evidence
    as one's own gave)."""
    from retrain import retrained_variant

    from css_ros.ros.params import checkpoint_file

    domain = rh.next_domain_id()
    model_path = rh.write_wall_model(tmp_path / "wall.ply")
    old = GaussianModel.from_ply(model_path)
    new = retrained_variant(old, seed=3, jitter=0.005)
    peer = {"a": "/b/css_node/evidence", "b": "/a/css_node/evidence"}
    watch = {n: tmp_path / f"watch_{n}" for n in "ab"}
    template = {n: str(tmp_path / f"maps_{n}" / "{fingerprint}.npz") for n in "ab"}
    nodes, clients = {}, {}
    try:
        for n in "ab":
            watch[n].mkdir()
            nodes[n], clients[n] = _start_peer(tmp_path, domain, model_path, {n: Path(template[n])}, n, peer,
                                               {"a": "robot_a", "b": "robot_b"}, checkpoint_path=template[n],
                                               model_watch_dir=str(watch[n]), model_watch_period=0.3)
        a, b = clients["a"], clients["b"]
        _feed(a, [0, 2])
        _feed(b, [1, 3])
        old_path = {n: Path(checkpoint_file(template[n], old.fingerprint)) for n in "ab"}
        _wait_holds(a, old_path["a"], "robot_b", 2)
        _wait_holds(b, old_path["b"], "robot_a", 2)
        before = _saved(a, old_path["a"])[0]
        for n in "ab":
            new.to_ply(watch[n] / "retrained.ply")
        for n in "ab":
            assert nodes[n].wait_log("model swapped to", 30.0), nodes[n].log()
        fp = GaussianModel.from_ply(watch["a"] / "retrained.ply").fingerprint
        new_path = {n: Path(checkpoint_file(template[n], fp)) for n in "ab"}
        _wait_holds(a, new_path["a"], "robot_b", 2)         # B's snapshot on the new splat replaced the moved copy
        _wait_holds(b, new_path["b"], "robot_a", 2)
        maps = _converged([a, b], [new_path["a"], new_path["b"]], _saved(a, new_path["a"])[0], timeout=20.0)
        np.testing.assert_allclose(maps[1], maps[0], rtol=1e-9, atol=0, err_msg=_evidence_log(nodes))
        ratio = (maps[0] - PRIOR).sum() / (before - PRIOR).sum()
        assert 0.85 < ratio < 1.15, f"evidence after both swaps / before: {ratio:.3f}\n{_evidence_log(nodes)}"
    finally:
        for n in clients:
            clients[n].close()
        for n in nodes:
            nodes[n].stop()
