"""The evidence packets and the exactly-once ledger (css_ros/io/evidence.py), without ROS."""
from __future__ import annotations

import numpy as np
import pytest

from css_ros.engine.gaussians import GaussianModel
from css_ros.engine.semantic_map import SemanticMap, SourceEvidence
from css_ros.errors import InputError, MapError
from css_ros.io import evidence as ev
from css_ros.io.evidence import DELTA, HEADER_SIZE, SNAPSHOT, EvidenceLedger, EvidenceOutbox, decode_packet


def encode_packet(kind, origin, fp, seq, rows, values, prior, n, epoch=1, frames=None, **kw):
    """The module's encoder; by default epoch 1 and frames = the sequence number (deltas: one frame per packet)
    or the snapshot id (all parts of a snapshot claim the same frames)."""
    if frames is None:
        frames = kw.get("snapshot_id") or seq
    return ev.encode_packet(kind, origin, fp, seq, rows, values, prior, n, epoch=epoch, frames=frames, **kw)

FP = "0123456789abcdef" * 4
N, C, PRIOR = 50, 3, 1e-3


def test_packet_round_trip_and_layout():
    rows = np.array([1, 7, 49])
    vals = np.arange(9, dtype=float).reshape(3, 3) / 7
    data = encode_packet(DELTA, "robot_a", FP, 5, rows, vals, PRIOR, N)
    assert len(data) == HEADER_SIZE + 3 * (4 + 8 * C) and HEADER_SIZE == 136 and data[:4] == b"CSSE"
    pkt = decode_packet(data, max_rows=10)
    assert (pkt.kind, pkt.origin, pkt.seq, pkt.range_end, pkt.num_classes, pkt.prior) == (DELTA, "robot_a", 5, N, C, PRIOR)
    assert pkt.fingerprint_digest == bytes.fromhex(FP)
    np.testing.assert_array_equal(pkt.rows, rows)
    np.testing.assert_array_equal(pkt.values, vals)  # float64: bit exact


@pytest.mark.parametrize("mutate, reason", [
    (lambda d: d[:-1], "size does not match"),
    (lambda d: b"XXXX" + d[4:], "magic"),
    (lambda d: d[:HEADER_SIZE] + np.array([7, 1, 49], "<u4").tobytes() + d[HEADER_SIZE + 12:], "strictly increasing"),
])
def test_malformed_packets_are_refused(mutate, reason):
    data = encode_packet(DELTA, "a", FP, 1, np.array([1, 7, 49]), np.ones((3, C)), PRIOR, N)
    with pytest.raises(InputError, match=reason):
        decode_packet(mutate(data), max_rows=10)
    with pytest.raises(InputError, match="too many rows"):
        decode_packet(data, max_rows=2)


def test_ledger_exactly_once_gap_and_snapshot():
    alpha = np.full((N, C), PRIOR)
    ledger = EvidenceLedger("me", FP, N, C, PRIOR, max_sources=2)
    rng = np.random.default_rng(0)
    d = [rng.uniform(0, 1, (N, C)) for _ in range(3)]
    rows = np.arange(N)
    dec = lambda data: decode_packet(data, N)  # noqa: E731
    assert ledger.apply(dec(encode_packet(DELTA, "a", FP, 1, rows, d[0], PRIOR, N)), alpha).startswith("sequence gap")
    np.testing.assert_array_equal(alpha, PRIOR)                     # a late start waits for a snapshot
    assert ledger.apply(dec(encode_packet(SNAPSHOT, "a", FP, 2, rows, d[0], PRIOR, N, snapshot_id=2)), alpha) is None
    np.testing.assert_allclose(alpha, PRIOR + d[0], rtol=1e-15)
    assert ledger.apply(dec(encode_packet(DELTA, "a", FP, 3, rows, d[1], PRIOR, N)), alpha) is None
    assert ledger.apply(dec(encode_packet(DELTA, "a", FP, 3, rows, d[1], PRIOR, N)), alpha).startswith("replayed")
    assert ledger.apply(dec(encode_packet(DELTA, "me", FP, 1, rows, d[1], PRIOR, N)), alpha).startswith("own")
    np.testing.assert_allclose(alpha, PRIOR + d[0] + d[1], rtol=1e-14)
    # seq 4 lost: 5 refused, the snapshot 6..7 (two parts) states the total d0 + d1 + d2 + d2
    total = d[0] + d[1] + 2 * d[2]
    assert ledger.apply(dec(encode_packet(DELTA, "a", FP, 5, rows, d[2], PRIOR, N)), alpha) is not None
    for part, (lo, hi) in enumerate(((0, 20), (20, N))):
        assert ledger.apply(dec(encode_packet(SNAPSHOT, "a", FP, 6 + part, rows[lo:hi], total[lo:hi], PRIOR, N,
                                              snapshot_id=6, range_start=lo, range_end=hi, part=part, parts=2)),
                            alpha) is None
    np.testing.assert_allclose(alpha, PRIOR + total, rtol=1e-14)
    assert ledger.apply(dec(encode_packet(DELTA, "b", "ff" * 32, 1, rows, d[0], PRIOR, N)), alpha) == \
        "evidence of another splat model"


def test_outbox_publishes_only_its_own_evidence():
    rng = np.random.default_rng(1)
    own_true, received = rng.uniform(0, 2, (N, C)), rng.uniform(0, 3, (N, C))
    own_true[:10] = 0.0                                              # Gaussians seen only by others
    alpha = PRIOR + received + own_true
    box = EvidenceOutbox("me", FP, N, C, PRIOR, max_rows=16)
    packets = [decode_packet(p, 16) for p in box.snapshot(box.own(alpha, received), 1)]
    assert len(packets) == 3 and all(p.kind == SNAPSHOT for p in packets)
    got = np.zeros((N, C))
    for p in packets:
        got[p.rows] = p.values
    np.testing.assert_allclose(got, own_true, rtol=1e-12, atol=1e-14)
    assert not np.any(np.isin(np.arange(10), np.concatenate([p.rows for p in packets])))  # no echo
    assert box.deltas(alpha, received, 2) == []                         # nothing new: nothing sent
    alpha[12] += 0.5
    (delta,) = [decode_packet(p, 16) for p in box.deltas(alpha, received, 2)]
    assert delta.seq == 4 and delta.rows.tolist() == [12]
    np.testing.assert_allclose(delta.values[0], 0.5, rtol=1e-12)


def test_deltas_equal_the_plain_formula_and_the_received_total_is_kept_in_step():
    """The publisher's one-pass delta test (numba) sends exactly the rows and values of the plain numpy rule
    (own = alpha - prior - received, rounding-level own is 0, rows where some class grew beyond rounding);
    the ledger's maintained total equals the sum of its sources after deltas, snapshots and a reset."""
    rng = np.random.default_rng(5)
    n, c = 400, 5
    box = EvidenceOutbox("me", FP, n, c, PRIOR, max_rows=64)
    received = rng.uniform(0, 3, (n, c))
    alpha = PRIOR + received + rng.uniform(0, 1, (n, c)) * (rng.random((n, c)) < 0.3)
    box.snapshot(box.own(alpha, received), 1)
    grow = rng.choice(n, 50, replace=False)
    alpha[grow, rng.integers(0, c, 50)] += rng.uniform(0.01, 2.0, 50)
    alpha[::37, 1] += 1e-15                                            # rounding-level alone: not sent
    own = alpha - PRIOR - received
    own[own <= 1e-12 * alpha.sum(axis=1, keepdims=True)] = 0.0
    delta = own - box.published
    want_rows = np.flatnonzero(np.any(delta > 1e-12 * alpha.sum(axis=1, keepdims=True), axis=1))
    want_vals = np.maximum(delta[want_rows], 0.0)
    packets = [decode_packet(p, n) for p in box.deltas(alpha, received, 2)]
    assert np.array_equal(np.concatenate([p.rows for p in packets]), want_rows) and set(want_rows) == set(grow)
    np.testing.assert_array_equal(np.concatenate([p.values for p in packets]), want_vals)
    assert box.deltas(alpha, received, 2) == []

    ledger = EvidenceLedger("me", FP, n, c, PRIOR, max_sources=4)
    conc = np.full((n, c), PRIOR)
    for origin, seq0 in (("a", 1), ("b", 1)):
        rows = np.sort(rng.choice(n, 30, replace=False))
        vals = rng.uniform(0, 2, (30, c))
        assert ledger.apply(decode_packet(encode_packet(SNAPSHOT, origin, FP, seq0, rows, vals, PRIOR, n,
                                                        snapshot_id=seq0, range_start=0, range_end=n, part=0,
                                                        parts=1), n), conc) is None
        rows2 = np.sort(rng.choice(n, 20, replace=False))
        assert ledger.apply(decode_packet(encode_packet(DELTA, origin, FP, seq0 + 1, rows2, vals[:20], PRIOR, n),
                                          n), conc) is None
    np.testing.assert_allclose(ledger.received_total(), sum(s.evidence for s in ledger.sources.values()), rtol=1e-15)
    np.testing.assert_allclose(conc, PRIOR + ledger.received_total(), rtol=1e-14)
    ledger.forget()
    assert not ledger.received_total().any() and not any(s.in_step for s in ledger.sources.values())


# ---------------------------------------------------------------------------------------------------- restarts
def _snap(origin, seq, total, epoch=1, frames=None, parts=1, fp=FP, n=N):
    """The packets of one snapshot of ``total`` (N, C) in ``parts`` parts, sequence numbers seq, seq + 1, ..."""
    bounds = np.linspace(0, n, parts + 1).astype(int)
    rows = np.arange(n)
    return [decode_packet(encode_packet(SNAPSHOT, origin, fp, seq + k, rows[lo:hi], total[lo:hi], PRIOR, n,
                                        epoch=epoch, frames=frames or seq, snapshot_id=seq, range_start=lo,
                                        range_end=hi, part=k, parts=parts), n)
            for k, (lo, hi) in enumerate(zip(bounds[:-1], bounds[1:]))]


def _delta(origin, seq, vals, epoch=1, frames=None, rows=None, fp=FP, n=N):
    rows = np.arange(n) if rows is None else rows
    return decode_packet(encode_packet(DELTA, origin, fp, seq, rows, vals, PRIOR, n, epoch=epoch,
                                       frames=frames or seq), n)


def _apply_all(ledger, alpha, packets, now=None):
    return [ledger.apply(p, alpha, now) for p in packets]


def test_a_restarted_source_is_recognised_at_once():
    """A peer restarted with the same origin id (a new epoch, sequence numbers from 1 again) is applied from its first
    snapshot on: no lock-out until its new sequence passes the old one."""
    rng = np.random.default_rng(2)
    alpha = np.full((N, C), PRIOR)
    ledger = EvidenceLedger("me", FP, N, C, PRIOR, max_sources=4)
    total = np.zeros((N, C))
    assert _apply_all(ledger, alpha, _snap("a", 1, total)) == [None]
    for seq in range(2, 16):                                          # 14 deltas: the old life reaches seq 15
        d = rng.uniform(0, 1, (N, C))
        assert ledger.apply(_delta("a", seq, d), alpha) is None
        total += d
    restarted = total * 0.75                                          # its checkpoint held less
    assert _apply_all(ledger, alpha, _snap("a", 1, restarted, epoch=2, parts=2)) == [None, None]
    np.testing.assert_allclose(alpha, PRIOR + restarted, rtol=1e-13)
    d = rng.uniform(0, 1, (N, C))
    assert ledger.apply(_delta("a", 3, d, epoch=2), alpha) is None     # in step with the new life at once
    assert ledger.apply(_delta("a", 16, d, epoch=1), alpha) is not None  # a late packet of the old life: refused
    np.testing.assert_allclose(alpha, PRIOR + restarted + d, rtol=1e-13)


def test_a_forged_huge_sequence_number_locks_no_source_out():
    """A forged delta with sequence 2^64 - 1 under a peer's origin changes nothing; a forged snapshot with it holds
    only until the peer's next snapshot, also after the receiver's map was reset."""
    rng = np.random.default_rng(3)
    alpha = np.full((N, C), PRIOR)
    ledger = EvidenceLedger("me", FP, N, C, PRIOR, max_sources=4)
    d = [rng.uniform(0, 1, (N, C)) for _ in range(4)]
    assert _apply_all(ledger, alpha, _snap("a", 1, d[0])) == [None]
    top = 2**64 - 1
    assert ledger.apply(_delta("a", top, d[3], frames=2), alpha) is not None
    assert ledger.apply(_delta("a", 2, d[1]), alpha) is None          # the peer goes on
    np.testing.assert_allclose(alpha, PRIOR + d[0] + d[1], rtol=1e-13)
    assert _apply_all(ledger, alpha, _snap("a", top, 5 * d[3], frames=3)) == [None]   # forged, applied ...
    assert ledger.apply(_delta("a", 3, d[2]), alpha) is not None
    assert _apply_all(ledger, alpha, _snap("a", 4, d[0] + d[1] + d[2], frames=4)) == [None]  # ... until this
    assert ledger.apply(_delta("a", 5, d[3]), alpha) is None
    np.testing.assert_allclose(alpha, PRIOR + sum(d), rtol=1e-13)
    assert _apply_all(ledger, alpha, _snap("a", top, d[3], frames=6)) == [None]   # forged again, then a reset
    alpha[...] = PRIOR
    ledger.forget()
    assert _apply_all(ledger, alpha, _snap("a", 6, sum(d), frames=6)) == [None]
    assert ledger.apply(_delta("a", 7, d[0], frames=7), alpha) is None
    np.testing.assert_allclose(alpha, PRIOR + sum(d) + d[0], rtol=1e-13)


def test_refused_packets_take_no_source_slot():
    """Eight junk origins, each with a refused packet, take no slot: an honest new peer is still applied; sources
    holding no evidence give their slot to a new one."""
    alpha = np.full((N, C), PRIOR)
    ledger = EvidenceLedger("me", FP, N, C, PRIOR, max_sources=6)
    ones = np.ones((N, C))
    for k in range(8):
        assert ledger.apply(_delta(f"junk{k}", 5, ones), alpha) is not None       # late start: refused
        assert _apply_all(ledger, alpha, _snap(f"junk{k}", 1, ones, fp="ee" * 32)) != [None]  # other splat
    assert ledger.sources == {}
    assert _apply_all(ledger, alpha, _snap("honest", 1, ones)) == [None]
    for k in range(5):                                                         # empty sources fill the slots ...
        assert _apply_all(ledger, alpha, _snap(f"empty{k}", 1, np.zeros((N, C)))) == [None]
    assert _apply_all(ledger, alpha, _snap("late", 1, ones)) == [None]         # ... and give one up
    assert len(ledger.sources) == 6 and {"honest", "late"} <= set(ledger.sources)
    np.testing.assert_allclose(alpha, PRIOR + 2 * ones, rtol=1e-15)


def test_a_source_cannot_claim_more_than_its_frames_can_add():
    """One frame adds at most P (pixels of the largest image) per Gaussian and in total: a snapshot or delta beyond
    P times the frames it claims is refused, and so are frames claimed faster than max_frame_rate."""
    n, c, p = 20_000, 4, 640.0 * 480.0
    alpha = np.full((n, c), PRIOR)
    ledger = EvidenceLedger("me", FP, n, c, PRIOR, max_sources=4, max_frame_evidence=p, max_frame_rate=30.0)
    huge = np.full((n, c), 1e9)
    assert _apply_all(ledger, alpha, _snap("x", 1, huge, frames=60, n=n), now=0.0) == [ev.BOUND_REASON]
    assert not ledger.sources
    fine = np.zeros((n, c))
    fine[:10, 1] = 0.5 * p                                           # 10 Gaussians, each half an image
    assert _apply_all(ledger, alpha, _snap("x", 1, fine, frames=10, n=n), now=0.0) == [None]
    refused = [ledger.apply(_delta("x", 2, huge[:100], frames=11 + k, rows=np.arange(100), n=n), alpha, now=0.1)
               for k in range(50)]                                   # 50 deltas of 1e9: none moves the sequence
    assert set(refused) == {ev.BOUND_REASON}
    one = np.zeros((100, c))
    one[:, 2] = p                                                    # each of 100 Gaussians fully seen in 1 frame
    assert ledger.apply(_delta("x", 2, one, frames=11, rows=np.arange(100), n=n), alpha, now=0.1) is not None, \
        "100 full images in one frame"
    assert ledger.apply(_delta("x", 2, one[:1], frames=11, rows=np.arange(1), n=n), alpha, now=0.1) is None
    assert ledger.apply(_delta("x", 3, one[:1], frames=10**6, rows=np.arange(1), n=n), alpha, now=0.2) == \
        "frames claimed faster than evidence_max_frame_rate"
    assert ledger.apply(_delta("x", 3, one[:1], frames=10 + 300, rows=np.arange(1), n=n), alpha, now=10.0) is None
    assert alpha.max() <= PRIOR + 2 * p


def test_packets_of_format_1_are_refused_by_name():
    data = bytearray(encode_packet(DELTA, "a", FP, 1, np.array([1]), np.ones((1, C)), PRIOR, N))
    data[4:6] = (1).to_bytes(2, "little")
    with pytest.raises(InputError, match="format 1"):
        decode_packet(bytes(data), 10)


# ---------------------------------------------------------------------------------------------------- checkpoints
class _Node:
    """A css_node's evidence exchange without ROS: its map, ledger and outbox, wired as css_ros/ros/evidence.py does
    (a snapshot first after every start, reset and load, then deltas); frames add evidence directly."""

    def __init__(self, model, origin, smap=None, resume=False, window=30.0):
        self.model, self.origin = model, origin
        self.smap = smap if smap is not None else SemanticMap(model, C, prior=PRIOR)
        self.box = EvidenceOutbox(origin, model.fingerprint, model.num_gaussians, C, PRIOR, max_rows=100)
        checkpoint_epoch = self.smap.evidence_epoch
        self.bind()
        self.outgoing, self.recovery, self.adopted = [], None, False
        if resume:                                    # EvidenceLink._start_recovery
            self.own_base = self.box.own(self.smap.concentrations, self.ledger.received_total()).copy()
            self.frames_base = self.smap.frames_observed
            self.recovery = ev.EvidenceRecovery(origin, model.fingerprint, model.num_gaussians, C, PRIOR,
                                                checkpoint_epoch, self.frames_base, self.box.epoch,
                                                max_frame_evidence=4096.0 ** 2, max_sources=4, now=0.0,
                                                window=window)

    def bind(self):
        m = self.model
        self.ledger = EvidenceLedger(self.origin, m.fingerprint, m.num_gaussians, C, PRIOR, max_sources=4,
                                     received=ev.received_sources(self.smap, self.origin))
        self.smap.evidence_origin, self.smap.received = self.origin, self.ledger.sources
        self.smap.evidence_epoch = self.box.epoch
        self.snapshot_due = True

    def publish(self):
        conc, frames = self.smap.concentrations, self.smap.frames_observed
        received = self.ledger.received_total()
        out, self.outgoing = self.outgoing, []        # returns due to restarted peers
        flags = ev.FLAG_RESUMED if self.recovery is not None and not self.adopted else 0
        if self.snapshot_due:
            self.snapshot_due = False
            return out + self.box.snapshot(self.box.own(conc, received), frames, flags)
        return out + self.box.deltas(conc, received, frames)

    def receive(self, packets, now=1.0):
        n = self.model.num_gaussians
        reasons = []
        for p in packets:
            pkt = decode_packet(p, n)
            if pkt.kind == ev.RETURN:                 # EvidenceLink._on_return
                if pkt.subject != self.origin:
                    continue
                if self.recovery is None:
                    reasons.append("not recovering")
                    continue
                reason, got = self.recovery.offer(pkt, now)
                self.adopted |= reason == ev.NOT_NEEDED_REASON   # answered: stop flagging
                if got is not None:                   # EvidenceLink._adopt_return_locked
                    _, frames, evidence = got
                    conc = self.smap.concentrations
                    received = self.ledger.received_total()
                    own = np.maximum(ev.own_evidence(conc, PRIOR, received) - self.own_base, 0.0) + evidence
                    conc[...] = PRIOR + own + received
                    self.smap.frames_observed += frames - self.frames_base
                    self.own_base, self.frames_base = evidence, frames
                    self.snapshot_due = self.adopted = True
                reasons.append(reason)
                continue
            reasons.append(self.ledger.apply(pkt, self.smap.concentrations))
            for subject in self.ledger.returns_due:
                self.outgoing += self.ledger.return_packets(subject, 100)
            self.ledger.returns_due.clear()
        return reasons

    def reset(self):                                  # ~/reset_map: MapWorker.reset_map + on_map_replaced
        self.smap.reset()
        self.ledger.forget()
        self.box.reset()
        self.smap.evidence_epoch = self.box.epoch
        self.snapshot_due, self.recovery = True, None

    def load(self, path):                             # ~/load_map: MapWorker.load_map + on_map_replaced
        loaded = SemanticMap.load(path, self.model)
        self.smap.concentrations[...] = loaded.concentrations
        self.smap.frames_observed = loaded.frames_observed
        self.smap.evidence_origin, self.smap.received = loaded.evidence_origin, loaded.received
        self.bind()
        self.box.reset()
        self.smap.evidence_epoch = self.box.epoch
        self.recovery = None


def _observe(node, rng):
    """One frame: evidence on a few Gaussians (what a rendered segmentation would add)."""
    n = node.model.num_gaussians
    add = np.zeros((n, C))
    rows = rng.choice(n, 40, replace=False)
    add[rows, rng.integers(0, C, 40)] = rng.uniform(0.1, 3.0, 40)
    node.smap.concentrations[...] += add
    node.smap.frames_observed += 1
    return add


def _four_exchanged_frames(model, rng, ckpt, save_after):
    """Nodes robot_a and robot_b each observe four frames, exchanging evidence after each; B saves its map to
    ``ckpt`` after frame ``save_after`` (0..3; None: never). Returns (a, b, A's own evidences, B's own evidences)."""
    a, b = _Node(model, "robot_a"), _Node(model, "robot_b")
    own_a, own_b = [], []
    for k in range(4):
        own_a.append(_observe(a, rng))
        own_b.append(_observe(b, rng))
        _exchange(a, b)
        if k == save_after:
            b.smap.save(ckpt)
    return a, b, own_a, own_b


def _exchange(a, b, rounds=2):
    for _ in range(rounds):
        a.receive(b.publish())
        b.receive(a.publish())


def test_a_crashed_and_resumed_node_keeps_the_group_exactly_once(tmp_path):
    """A and B exchange evidence; B's checkpoint keeps each source's evidence apart from its own, so B resumed from it
    (after a kill: the frame it fused after its checkpoint is lost, in every map alike) re-states only its own
    evidence; ~/reset_map withdraws it, ~/load_map re-states the file's. Every map equals the sum of the frames the
    group still holds, to rounding."""
    import ros_helpers as rh

    model = GaussianModel.from_ply(rh.write_wall_model(tmp_path / "wall.ply"))
    rng = np.random.default_rng(7)
    ckpt = tmp_path / "b.npz"
    a, b, own_a, own_b = _four_exchanged_frames(model, rng, ckpt, save_after=3)
    saved_b = sum(own_b)
    _observe(b, rng)                                   # fused after the checkpoint, sent, then B is killed
    a.receive(b.publish())
    own_a.append(_observe(a, rng))
    a.publish()                                        # B is down: this delta is lost to it
    b = _Node(model, "robot_b", SemanticMap.load(ckpt, model))   # resumed (same origin; a new epoch)
    assert set(b.smap.received) == {"robot_a"}
    for _ in range(3):
        own_a.append(_observe(a, rng))
        own_b.append(_observe(b, rng))
        _exchange(a, b)
    a.snapshot_due = True                              # A's periodic snapshot re-syncs B (its deltas were a gap)
    _exchange(a, b)
    want = PRIOR + sum(own_a) + saved_b + sum(own_b[4:])
    for node in (a, b):
        np.testing.assert_allclose(node.smap.concentrations, want, rtol=1e-12, err_msg=node.origin)
    b.smap.save(ckpt)
    b.reset()                                          # B's own evidence is withdrawn everywhere
    _exchange(a, b)
    a.snapshot_due = True
    _exchange(a, b)
    for node in (a, b):
        np.testing.assert_allclose(node.smap.concentrations, PRIOR + sum(own_a), rtol=1e-12, err_msg=node.origin)
    b.load(ckpt)                                       # ... and re-stated from the file, A's part replaced by A
    own_a.append(_observe(a, rng))
    _exchange(a, b)
    a.snapshot_due = True
    _exchange(a, b)
    want = PRIOR + sum(own_a) + saved_b + sum(own_b[4:])
    for node in (a, b):
        np.testing.assert_allclose(node.smap.concentrations, want, rtol=1e-12, err_msg=node.origin)


def test_map_files_keep_received_sources_and_old_files_still_load(tmp_path):
    import ros_helpers as rh

    model = GaussianModel.from_ply(rh.write_wall_model(tmp_path / "wall.ply"))
    n = model.num_gaussians
    smap = SemanticMap(model, C, prior=PRIOR)
    ev_a = np.zeros((n, C))
    ev_a[[3, 9], 1] = [2.0, 5.0]
    smap.concentrations[...] += ev_a + 0.25
    smap.evidence_origin = "robot_b"
    smap.received = {"robot_a": SourceEvidence(ev_a, epoch=2**64 - 1, last_seq=7, frames=3, in_step=True)}
    path = smap.save(tmp_path / "m.npz")
    back = SemanticMap.load(path, model)
    assert back.evidence_origin == "robot_b" and set(back.received) == {"robot_a"}
    got = back.received["robot_a"]
    np.testing.assert_array_equal(got.evidence, ev_a)
    assert (got.epoch, got.last_seq, got.frames, got.in_step) == (2**64 - 1, 7, 3, True)
    # another node resuming it: robot_b's own part becomes a received source, robot_a's stays
    rec = ev.received_sources(back, "robot_c")
    np.testing.assert_allclose(rec["robot_b"].evidence, np.full((n, C), 0.25), rtol=1e-12)
    assert set(ev.received_sources(back, "robot_a")) == {"robot_b"}   # its own evidence, as robot_b held it

    with np.load(path) as data:
        members = {k: data[k] for k in data.files}
    old = {k: v for k, v in members.items() if k != "evidence_origin" and not k.startswith("received_")}
    np.savez(tmp_path / "old.npz", **old)
    legacy = SemanticMap.load(tmp_path / "old.npz", model)
    assert legacy.evidence_origin == "" and legacy.received == {}
    assert set(ev.received_sources(legacy, "robot_b")) == set()          # all of it is own
    for name, bad, why in [
        ("state", {**members, "received_state": members["received_state"][:, :3]}, "inconsistent shapes"),
        ("partial", {k: v for k, v in members.items() if k != "received_rows"}, "not all of"),
        ("exceeds", {**members, "received_evidence": members["received_evidence"] * 10}, "exceeds"),
        ("rows", {**members, "received_rows": members["received_rows"][::-1].copy()}, "not increasing"),
    ]:
        np.savez(tmp_path / f"{name}.npz", **bad)
        with pytest.raises(MapError, match=why):
            SemanticMap.load(tmp_path / f"{name}.npz", model)


@pytest.mark.parametrize("checkpoint", ["older", "none", "latest"])
def test_a_killed_node_takes_back_its_unsaved_evidence_from_a_peer(tmp_path, checkpoint):
    """B is killed with an older checkpoint (or none: a fresh map under the same origin) after it published more
    frames; resumed, its first snapshot is flagged "resumed", A (which holds B's previous epoch with more frames)
    sends it back a return, B adopts it as its own evidence and re-states it: both maps equal one node fed every
    frame the group published (the frame B fused but never published before the kill is lost everywhere). B fuses
    a frame before its first snapshot (its frames may exceed the copy's: B, not A, decides). "latest": B saved
    after its last published frame, the return is not needed."""
    import ros_helpers as rh

    model = GaussianModel.from_ply(rh.write_wall_model(tmp_path / "wall.ply"))
    rng = np.random.default_rng(11)
    ckpt = tmp_path / "b.npz"
    save_after = {"older": 1, "latest": 3}.get(checkpoint)   # "older": two of B's four frames
    a, b, own_a, own_b = _four_exchanged_frames(model, rng, ckpt, save_after)
    published_frames = b.smap.frames_observed
    _observe(b, rng)                                  # fused, never published: lost with the kill
    own_a.append(_observe(a, rng))
    a.publish()                                       # B is down: lost to it
    smap = SemanticMap.load(ckpt, model) if checkpoint != "none" else None
    b = _Node(model, "robot_b", smap, resume=True)
    own_b.append(_observe(b, rng))                    # mapping at once, before its first snapshot
    first = b.publish()
    assert decode_packet(first[0], model.num_gaussians).flags == ev.FLAG_RESUMED
    assert a.receive(first) == [None] * len(first)
    returned = a.publish()
    kinds = [decode_packet(p, model.num_gaussians).kind for p in returned]
    assert ev.RETURN in kinds
    reasons = b.receive(returned)
    if checkpoint == "latest":
        assert set(reasons) == {ev.NOT_NEEDED_REASON} and b.adopted
    else:
        assert all(r is None for r in reasons)
    assert b.adopted and b.smap.frames_observed == published_frames + 1
    for _ in range(3):
        own_a.append(_observe(a, rng))
        own_b.append(_observe(b, rng))
        _exchange(a, b)
    a.snapshot_due = b.snapshot_due = True            # the periodic snapshots (B's: no longer flagged)
    _exchange(a, b)
    want = PRIOR + sum(own_a) + sum(own_b)
    for node in (a, b):
        np.testing.assert_allclose(node.smap.concentrations, want, rtol=1e-12, err_msg=node.origin)
    assert all(s.returnable is None for s in a.ledger.sources.values())   # B's unflagged snapshot ended it
    assert b.smap.frames_observed == published_frames + 4


def test_forged_or_late_returns_are_refused(tmp_path):
    """Returns for another node, of an epoch before the checkpoint's or of the current one, holding no more frames,
    above what their frames can add, or after the window (30 s from the first peer packet) change nothing."""
    ev_ = np.zeros((N, C))
    ev_[[2, 7], 1] = [3.0, 4.0]

    def rec():
        return ev.EvidenceRecovery("robot_b", FP, N, C, PRIOR, checkpoint_epoch=100, checkpoint_frames=5,
                                   current_epoch=200, max_frame_evidence=10.0, max_sources=4, now=0.0, window=30.0)

    def ret(epoch=150, frames=9, values=ev_, subject="robot_b", sender="robot_a"):
        (p,) = ev.encode_return(sender, subject, FP, epoch, frames, values, PRIOR, 100)
        return decode_packet(p, 100)

    assert rec().offer(ret(subject="robot_c"), 1.0)[0] == "return for another node"
    assert "did not run last" in rec().offer(ret(epoch=99), 1.0)[0]
    assert "did not run last" in rec().offer(ret(epoch=200), 1.0)[0]
    assert "no more" in rec().offer(ret(epoch=100, frames=5), 1.0)[0]
    huge = ev_.copy()
    huge[2, 1] = 1000.0                                # above 10 per frame × 9 frames
    assert rec().offer(ret(values=huge), 1.0)[0] == ev.BOUND_REASON
    late = rec()                                       # the window runs from the first packet heard from a peer
    assert late.open(1e6)                              # nobody heard yet (a peer discovered late): still open
    late.heard(1000.0)
    late.heard(1020.0)                                 # later packets do not move it
    assert late.open(1029.9) and not late.open(1030.0)
    assert late.offer(ret(), 1030.5)[0] == "return after the recovery window"
    late = rec()
    late.heard(1000.0)
    assert late.offer(ret(), 1029.0)[0] is None
    r = rec()
    reason, got = r.offer(ret(), 1.0)
    assert reason is None and got is not None and got[:2] == (150, 9)
    np.testing.assert_array_equal(got[2], ev_)
    assert "no more" in r.offer(ret(), 2.0)[0]        # a second, equal one: the first was adopted
    with pytest.raises(InputError, match="unknown packet flags"):
        p = bytearray(ev.encode_return("robot_a", "robot_b", FP, 150, 9, ev_, PRIOR, 100)[0])
        p[7] = 4
        decode_packet(bytes(p), 100)
    # a ledger never applies a return (it is for its subject only)
    led = EvidenceLedger("robot_c", FP, N, C, PRIOR, max_sources=4)
    assert led.apply(ret(), np.full((N, C), PRIOR)) == "return packet (for its subject only)"


def test_a_node_killed_again_before_it_took_its_evidence_back_still_gets_it(tmp_path):
    """B is killed, resumed, and killed again before a return reached it: A keeps the copy of B's first epoch (not
    the second start's smaller one) while B stays resumed, and the third start takes it back."""
    import ros_helpers as rh

    model = GaussianModel.from_ply(rh.write_wall_model(tmp_path / "wall.ply"))
    rng = np.random.default_rng(5)
    ckpt = tmp_path / "b.npz"
    a, b, own_a, own_b = _four_exchanged_frames(model, rng, ckpt, save_after=0)
    published_frames = b.smap.frames_observed
    b = _Node(model, "robot_b", SemanticMap.load(ckpt, model), resume=True)   # killed; resumed
    assert a.receive(b.publish()) == [None]
    a.publish()                                        # its return is lost: B is killed again at once
    b = _Node(model, "robot_b", SemanticMap.load(ckpt, model), resume=True)
    a.receive(b.publish())
    b.receive(a.publish())
    assert b.adopted and b.smap.frames_observed == published_frames
    _exchange(a, b)
    a.snapshot_due = b.snapshot_due = True
    _exchange(a, b)
    want = PRIOR + sum(own_a) + sum(own_b)
    for node in (a, b):
        np.testing.assert_allclose(node.smap.concentrations, want, rtol=1e-12, err_msg=node.origin)
