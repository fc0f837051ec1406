"""The node's evidence link (css_ros/ros/evidence.py) driven without DDS: a stand-in node and worker, messages handed
to its callback as the subscription would, and a fake clock. What the hostile probe found: sources listed for
junk origins (P2), per-origin diagnostics keys (P2), evidence_max_sources beyond a map file (P5), a flood of
other origins locking a peer out (P4), a refused packet starting the return window (P9), oversized messages (P6).
"""
from __future__ import annotations

import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("rclpy")
from rclpy.serialization import serialize_message  # noqa: E402
from std_msgs.msg import UInt8MultiArray  # noqa: E402

from css_ros.engine.map_file import MAX_RECEIVED_SOURCES, MAX_SOURCES  # noqa: E402
from css_ros.engine.semantic_map import SemanticMap  # noqa: E402
from css_ros.errors import ConfigError  # noqa: E402
from css_ros.io import evidence as ev  # noqa: E402
from css_ros.ros import evidence as link_mod  # noqa: E402
from css_ros.ros.diagnostics import Stats  # noqa: E402
from css_ros.ros.params import NodeParams, params_from_values  # noqa: E402
from css_ros.ros.work import WarnLimiter  # noqa: E402
from scenes import small_wall  # noqa: E402

C, PRIOR = 4, 1e-3
EPOCH = time.time_ns() - 100 * 10**9   # the checkpoint's: its node ran 100 s ago


class _Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


class _Node:
    """What EvidenceLink uses of an rclpy Node: publishers record, the subscription callback is kept."""

    def __init__(self) -> None:
        self.published: list[bytes] = []
        self.callbacks: list = []
        self.logs: list[str] = []
        log = SimpleNamespace(info=self.logs.append, warning=self.logs.append)
        self.get_logger = lambda: log

    def create_publisher(self, _type, _name, _qos):
        return SimpleNamespace(publish=lambda msg: self.published.append(bytes(msg.data)))

    def create_subscription(self, _type, _topic, callback, _qos, raw=False):
        assert raw, "the evidence subscription takes raw messages (the size is checked before deserializing)"
        self.callbacks.append(callback)

    def create_timer(self, _period, _callback):
        return None




class _Link:
    def __init__(self, tmp_path, monkeypatch, smap: SemanticMap | None = None, gaussians: int = 60,
                 **params) -> None:
        self.clock = _Clock()
        monkeypatch.setattr(link_mod.time, "monotonic", self.clock)
        self.model = small_wall(tmp_path, gaussians)
        self.n, self.fp = self.model.num_gaussians, self.model.fingerprint
        self.smap = smap if smap is not None else SemanticMap(self.model, C, prior=PRIOR)
        self.worker = SimpleNamespace(smap=self.smap, map_lock=threading.RLock(),
                                      policy=SimpleNamespace(changed=lambda: None), map_version=0,
                                      on_map_replaced=None)
        self.stats = Stats()
        self.node = _Node()
        self.warn = WarnLimiter(self.node.logs.append, 0.0)
        p = NodeParams(**{**dict(prior=PRIOR, publish_evidence=True, evidence_in="/crafted/evidence",
                                 evidence_origin="robot_b", log_period=0.5), **params})
        self.link = link_mod.EvidenceLink(self.node, p, self.worker, self.warn, self.stats.count)

    def send(self, data: bytes) -> None:
        msg = UInt8MultiArray()
        msg.data = data
        for cb in self.node.callbacks:
            cb(serialize_message(msg))

    def snapshot(self, origin, seq, vals, epoch=1, frames=1, fp=None, flags=0) -> bytes:
        rows = np.flatnonzero(np.any(vals != 0, axis=1))
        return ev.encode_packet(ev.SNAPSHOT, origin, fp or self.fp, seq, rows, vals[rows], PRIOR, self.n,
                                snapshot_id=seq, epoch=epoch, frames=frames, flags=flags)

    def diag(self) -> dict[str, int]:
        return self.stats.snapshot()[0]


def test_junk_origins_are_not_listed_and_leave_no_diagnostics_keys(tmp_path, monkeypatch):
    """P2: 300 origins each send one empty snapshot (applied: the ledger has room as empty sources hand on their
    slot). The map lists only this node and the peer holding evidence; the per-origin diagnostics keys are those of
    the ledger's current sources (at most evidence_max_sources), the rest are counted in one aggregate; the file
    loads. A peer whose evidence went to 0 (it reset) is no longer listed either."""
    lk = _Link(tmp_path, monkeypatch)
    held = np.zeros((lk.n, C))
    held[:5, 2] = 3.0
    lk.send(lk.snapshot("robot_a", 1, held))
    for k in range(300):
        lk.clock.t += 0.01
        lk.send(lk.snapshot(f"junk{k:05d}", 1, np.zeros((lk.n, C))))
    d = lk.diag()
    assert d["evidence_packets_applied"] == 301
    assert lk.smap.sources == ["robot_a", "robot_b"]
    per_origin = [k for k in d if k.startswith("evidence_packets_from[")]
    assert len(per_origin) <= 8 and "evidence_packets_from[robot_a]" in per_origin, per_origin
    assert d["evidence_sources_released"] >= 300 - 8
    lk.smap.save(tmp_path / "m.npz")
    assert SemanticMap.load(tmp_path / "m.npz", lk.model).sources == ["robot_a", "robot_b"]
    lk.send(lk.snapshot("robot_a", 2, np.zeros((lk.n, C)), frames=1))   # robot_a reset: holds nothing now
    assert lk.smap.sources == ["robot_b"]


def test_a_merged_maps_sources_stay_listed_and_the_list_stays_within_the_file_bound(tmp_path, monkeypatch):
    """Sources a loaded map holds as its own (a merged map's) stay listed; at most MAX_SOURCES in all."""
    model = small_wall(tmp_path, 60)
    smap = SemanticMap(model, C, prior=PRIOR)
    smap.sources = [f"old{k:04d}" for k in range(MAX_SOURCES)]
    lk = _Link(tmp_path, monkeypatch, smap=smap)
    vals = np.zeros((lk.n, C))
    vals[0, 0] = 1.0
    lk.send(lk.snapshot("robot_a", 1, vals))
    assert len(lk.smap.sources) == MAX_SOURCES and {"robot_a", "robot_b", "old0000"} <= set(lk.smap.sources)
    lk.smap.save(tmp_path / "m.npz")
    SemanticMap.load(tmp_path / "m.npz", lk.model)


def test_evidence_max_sources_beyond_what_a_map_file_keeps_is_refused_at_start():
    """P5: evidence_max_sources > MAX_RECEIVED_SOURCES (64) gave checkpoints that did not load."""
    with pytest.raises(ConfigError, match=r"parameter evidence_max_sources=65: at most 64 \(the received sources a "
                                          r"map file keeps"):
        params_from_values({"evidence_max_sources": MAX_RECEIVED_SOURCES + 1})
    assert params_from_values({"evidence_max_sources": MAX_RECEIVED_SOURCES}).evidence_max_sources == 64


def test_a_flood_of_refused_packets_under_many_origins_does_not_lock_a_peer_out(tmp_path, monkeypatch):
    """P4: robot_a holds a ledger slot and sends a snapshot every 3 s; 40 other origins send packets of another
    splat (refused, no slot) at 80 packets/s. Before, robot_a's bucket was pruned while idle and its snapshots were
    refused as "too many sources" until the flood stopped; now every one is applied."""
    lk = _Link(tmp_path, monkeypatch)
    vals = np.zeros((lk.n, C))
    vals[1, 1] = 1.0
    applied = 0
    for step in range(24 * 80):
        lk.clock.t += 1.0 / 80.0
        if step % 240 == 0:
            lk.send(lk.snapshot("robot_a", 1 + step // 240, vals * (1 + step // 240), frames=1 + step // 240))
            applied += 1
        lk.send(lk.snapshot(f"forger{step % 40:02d}", 1, vals, fp="ee" * 32))
    d = lk.diag()
    assert d["evidence_packets_from[robot_a]"] == applied == 8
    assert not any("too many sources" in k for k in d), d
    assert d["evidence_refused[evidence of another splat model]"] == 24 * 80
    np.testing.assert_allclose(lk.smap.concentrations_readonly[1, 1], PRIOR + 8.0)


def test_a_refused_packet_does_not_start_the_return_window(tmp_path, monkeypatch):
    """P9: a resumed node's return window runs from the first peer packet it applies. One packet of another splat
    right after the restart, then a valid return 65 s later: adopted (it was refused as "return while not
    recovering"). A window that did start (a valid snapshot) still ends after 60 s."""
    model = small_wall(tmp_path, 60)
    ckpt = SemanticMap(model, C, prior=PRIOR)
    ckpt.evidence_origin, ckpt.evidence_epoch, ckpt.frames_observed = "robot_b", EPOCH, 2
    lk = _Link(tmp_path, monkeypatch, smap=ckpt, resume=True)
    assert lk.link.recovery is not None
    lk.send(lk.snapshot("junk", 1, np.ones((lk.n, C)), fp="ee" * 32))   # refused at once
    lk.clock.t += 65.0
    back = np.zeros((lk.n, C))
    back[2, 1] = 4.0
    for data in ev.encode_return("peer_b", "robot_b", lk.fp, EPOCH, 3, back, PRIOR, 1000):
        lk.send(data)
    d = lk.diag()
    assert d.get("evidence_returns_adopted") == 1, d
    assert "evidence_refused[return while not recovering from a restart]" not in d
    np.testing.assert_allclose(lk.smap.concentrations_readonly[2, 1], PRIOR + 4.0)

    other = SemanticMap(model, C, prior=PRIOR)
    other.evidence_origin, other.evidence_epoch, other.frames_observed = "robot_b", EPOCH, 2
    lk2 = _Link(tmp_path, monkeypatch, smap=other, resume=True)
    lk2.send(lk2.snapshot("peer_c", 1, np.zeros((lk2.n, C))))          # applied: the window starts
    lk2.clock.t += 65.0
    lk2.link.publish()                                                   # the timer closes it
    for data in ev.encode_return("peer_b", "robot_b", lk2.fp, EPOCH, 3, back, PRIOR, 1000):
        lk2.send(data)
    assert "evidence_returns_adopted" not in lk2.diag()


def test_a_returned_evidence_next_to_small_received_evidence_leaves_a_map_that_loads(tmp_path, monkeypatch):
    """P3 on the return path: the checkpoint held 1e9 of own evidence, a peer 1e-3 on the same Gaussians; the
    return replaces the own part by less. α was α - own_base + returned: rounding lost the peer's 1e-3."""
    model = small_wall(tmp_path, 60)
    ckpt = SemanticMap(model, C, prior=PRIOR)
    ckpt.concentrations = np.full((model.num_gaussians, C), PRIOR + 1e9)
    ckpt.evidence_origin, ckpt.evidence_epoch, ckpt.frames_observed = "robot_b", EPOCH, 2
    lk = _Link(tmp_path, monkeypatch, smap=ckpt, resume=True, max_image_pixels=10**9)
    small = np.full((lk.n, C), 1e-3)
    lk.send(lk.snapshot("peer_c", 1, small))
    back = np.full((lk.n, C), 2.0)
    for data in ev.encode_return("peer_c", "robot_b", lk.fp, EPOCH, 3, back, PRIOR, 1000):
        lk.send(data)
    assert lk.diag().get("evidence_returns_adopted") == 1, lk.diag()
    lk.smap.save(tmp_path / "m.npz")
    loaded = SemanticMap.load(tmp_path / "m.npz", model)
    np.testing.assert_allclose(loaded.concentrations_readonly, PRIOR + 2.0 + 1e-3, rtol=1e-12)


def test_an_oversized_message_is_refused_before_it_is_deserialized(tmp_path, monkeypatch):
    """P6: a message larger than any valid packet (evidence_max_rows rows of the map's classes) is refused by size
    from its serialized bytes; a valid one still applies."""
    lk = _Link(tmp_path, monkeypatch, evidence_max_rows=100)
    head = lk.snapshot("big", 1, np.zeros((lk.n, C)))
    lk.send(head + bytes(lk.link.max_message_bytes()))
    assert lk.diag()["evidence_refused[message larger than any valid packet]"] == 1
    vals = np.zeros((lk.n, C))
    vals[0, 0] = 1.0
    lk.send(lk.snapshot("robot_a", 1, vals))
    assert lk.diag()["evidence_packets_applied"] == 1


def test_returns_to_one_origin_stay_within_ten_times_what_it_sent_and_the_rest_is_counted(tmp_path, monkeypatch):
    """The hostile probe through the node's link: origin 'crafted' holds 20,000 rows here, then sends 60 one-row
    snapshots flagged "resumed", each of a new epoch, at 25/s (the probe measured 4 returns of 10.6 MB for 16 kB:
    x657). What the node publishes on ~/evidence in response stays within 10 x the bytes that origin sent (none
    here: a return is 20,000 rows), every withheld return is counted with its reason and size, and a warning names
    the origin."""
    lk = _Link(tmp_path, monkeypatch, gaussians=20_000, evidence_max_rows=5_000)
    held = np.random.default_rng(3).uniform(0.5, 2.0, (lk.n, C))
    for data in _snapshot_parts(lk, "crafted", 1, held, epoch=1, frames=9, max_rows=5_000):
        lk.send(data)
    assert lk.diag().get("evidence_packets_applied") == 4
    before, received = len(lk.node.published), 0
    one = np.zeros((lk.n, C))
    one[11, 2] = 1e-3
    for k in range(60):
        data = lk.snapshot("crafted", 10 + k, one, epoch=2 + k, frames=1, flags=ev.FLAG_RESUMED)
        lk.send(data)
        received += len(data)
        lk.clock.t += 0.04
    published = sum(len(d) for d in lk.node.published[before:] if d[6] == ev.RETURN)
    d = lk.diag()
    print(f"\n60 resumed snapshots ({received} B): {published} B of returns published; withheld "
          f"{d.get(f'evidence_returns_withheld[{ev.WITHHELD_BUDGET}]')} ({d.get('evidence_return_bytes_withheld')} B)")
    assert d["evidence_packets_applied"] == 64
    assert published <= 10 * received
    whole = ev.return_bytes(lk.n, C, 5_000)
    assert d[f"evidence_returns_withheld[{ev.WITHHELD_BUDGET}]"] == 60
    assert d["evidence_return_bytes_withheld"] == 60 * whole
    assert any("return withheld" in line and "'crafted'" in line for line in lk.node.logs)


def _snapshot_parts(lk: _Link, origin: str, seq: int, total: np.ndarray, epoch: int, frames: int,
                    max_rows: int) -> list[bytes]:
    """Snapshot parts of at most ``max_rows`` rows stating ``total`` (N, C) for ``origin``."""
    nz = np.flatnonzero(np.any(total != 0.0, axis=1))
    chunks = [nz[a:a + max_rows] for a in range(0, nz.size, max_rows)] or [nz]
    starts = [0] + [int(ch[0]) for ch in chunks[1:]]
    ends = starts[1:] + [lk.n]
    return [ev.encode_packet(ev.SNAPSHOT, origin, lk.fp, seq + k, r, total[r], PRIOR, lk.n, snapshot_id=seq,
                             range_start=lo, range_end=hi, part=k, parts=len(chunks), epoch=epoch, frames=frames)
            for k, (r, lo, hi) in enumerate(zip(chunks, starts, ends))]
