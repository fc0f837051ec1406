"""What the hostile evidence probe found (css_ros/io/evidence.py, without ROS): every map file the ledger leaves
behind loads, sources and rate-limit buckets stay bounded, and a snapshot part costs what it carries.

test_evidence_link.py checks the node's link (sources listed, diagnostics keys, the return window) the same way.
"""
from __future__ import annotations

import time

import numpy as np
import pytest

from css_ros.engine.map_file import MAX_RECEIVED_SOURCES, SourceEvidence
from css_ros.engine.semantic_map import SemanticMap
from css_ros.io import evidence as ev
from css_ros.io.evidence import DELTA, SNAPSHOT, EvidenceLedger, OriginBuckets, decode_packet
from scenes import small_wall

C, PRIOR = 4, 1e-3


def _packet(kind, origin, fp, n, seq, vals, epoch, frames, snapshot_id=0, c=C):
    rows = np.flatnonzero(np.any(vals != 0, axis=1))
    return decode_packet(ev.encode_packet(kind, origin, fp, seq, rows, vals[rows], PRIOR, n, snapshot_id=snapshot_id,
                                          epoch=epoch, frames=frames), 20_000)


def _bound_map(model, max_sources=8, max_frame_evidence=640.0 * 480.0):
    smap = SemanticMap(model, C, prior=PRIOR)
    ledger = EvidenceLedger("me", model.fingerprint, model.num_gaussians, C, PRIOR, max_sources=max_sources,
                            max_frame_evidence=max_frame_evidence)
    smap.evidence_origin, smap.received = "me", ledger.sources
    return smap, ledger


@pytest.mark.parametrize("seed", range(3))
def test_a_peer_withdrawing_large_evidence_leaves_a_map_that_loads(tmp_path, seed):
    """P3 at the magnitudes of a 640x480 camera on the 320-Gaussian wall: peer A sends 300 deltas of up to 960 per
    Gaussian, peer B 0.01-0.05 on the same Gaussians, then A resets (an empty snapshot of a new epoch). α was
    α_0 + B + A - A, which rounding left below α_0 + B (by ~1e-11): the file was refused at load. Now the rows are
    recomputed as α_0 + own + Σ sources: the file loads, and α equals α_0 + B to 1e-12 relative."""
    model = small_wall(tmp_path, 320)
    n, fp = model.num_gaussians, model.fingerprint
    rng = np.random.default_rng(seed)
    smap, ledger = _bound_map(model)
    conc = smap.concentrations
    z = np.zeros((n, C))
    b = rng.uniform(0.01, 0.05, (n, C))
    assert ledger.apply(_packet(SNAPSHOT, "A", fp, n, 1, z, 10, 0, 1), conc, now=0.0) is None
    assert ledger.apply(_packet(SNAPSHOT, "B", fp, n, 1, b, 20, 1, 1), conc, now=0.0) is None
    for k in range(300):
        d = np.zeros((n, C))
        d[:, 1] = rng.uniform(0, 960, n)
        assert ledger.apply(_packet(DELTA, "A", fp, n, 2 + k, d, 10, k + 1), conc, now=k * 0.1) is None
    assert ledger.apply(_packet(SNAPSHOT, "A", fp, n, 1, z, 11, 0, 1), conc, now=100.0) is None   # A resets
    smap.concentrations = conc
    smap.save(tmp_path / "m.npz")
    loaded = SemanticMap.load(tmp_path / "m.npz", model)
    np.testing.assert_allclose(loaded.concentrations_readonly, PRIOR + b, rtol=1e-12)
    np.testing.assert_array_equal(loaded.received["B"].evidence, b)
    assert not loaded.received["A"].evidence.any()
    np.testing.assert_allclose(ledger.received_total(), b, rtol=1e-15)   # the running total too (no drift)


def test_withdrawing_1e9_next_to_1e_3_leaves_a_map_that_loads(tmp_path):
    """P3 as the forger sent it: B states 1e-3 on every cell, A 1e9 (the per-packet bound), then A withdraws."""
    model = small_wall(tmp_path, 50)
    n, fp = model.num_gaussians, model.fingerprint
    smap, ledger = _bound_map(model)
    conc = smap.concentrations
    small = np.full((n, C), 1e-3)
    assert ledger.apply(_packet(SNAPSHOT, "bbb", fp, n, 1, small, 1, 1, 1), conc, now=0.0) is None
    assert ledger.apply(_packet(SNAPSHOT, "aaa", fp, n, 1, np.full((n, C), 1e9), 1, 2**48, 1), conc, now=0.0) is None
    assert ledger.apply(_packet(SNAPSHOT, "aaa", fp, n, 2, np.zeros((n, C)), 1, 2**48, 2), conc, now=0.0) is None
    smap.concentrations = conc
    smap.save(tmp_path / "m.npz")
    loaded = SemanticMap.load(tmp_path / "m.npz", model)
    np.testing.assert_allclose(loaded.concentrations_readonly, PRIOR + small, rtol=1e-12)


def test_own_evidence_survives_a_peer_withdrawal(tmp_path):
    """The node's own evidence (α - α_0 - received) is kept when a peer's snapshot changes the same rows."""
    model = small_wall(tmp_path, 50)
    n, fp = model.num_gaussians, model.fingerprint
    smap, ledger = _bound_map(model)
    conc = smap.concentrations
    own = np.random.default_rng(4).uniform(0, 3, (n, C))
    conc += own                                                   # frames this node fused
    peer = np.random.default_rng(5).uniform(0, 200, (n, C))
    assert ledger.apply(_packet(SNAPSHOT, "p", fp, n, 1, peer, 1, 1, 1), conc, now=0.0) is None
    np.testing.assert_allclose(conc, PRIOR + own + peer, rtol=1e-13)
    assert ledger.apply(_packet(SNAPSHOT, "p", fp, n, 2, peer / 2, 1, 1, 2), conc, now=0.0) is None
    np.testing.assert_allclose(conc, PRIOR + own + peer / 2, rtol=1e-13)
    np.testing.assert_allclose(ev.own_evidence(conc, PRIOR, ledger.received_total()), own, rtol=1e-10)


def test_empty_sources_are_not_holders_and_hand_their_slot_on(tmp_path):
    """P2 at the ledger: 500 junk origins each send an empty snapshot; the ledger never holds more than its slots,
    and none of them is a holder (a source whose evidence the map holds), so none is listed in the map file."""
    model = small_wall(tmp_path, 50)
    n, fp = model.num_gaussians, model.fingerprint
    smap, ledger = _bound_map(model)
    conc = smap.concentrations
    one = np.zeros((n, C))
    one[3, 1] = 2.0
    assert ledger.apply(_packet(SNAPSHOT, "robot_a", fp, n, 1, one, 1, 1, 1), conc, now=0.0) is None
    for k in range(500):
        assert ledger.apply(_packet(SNAPSHOT, f"junk{k:05d}", fp, n, 1, np.zeros((n, C)), 1, 1, 1), conc,
                            now=0.0) is None
        assert len(ledger.sources) <= 8
    assert ledger.holders() == ["robot_a"]
    # robot_a withdraws: it holds nothing now, and gives its slot to the next new source
    assert ledger.apply(_packet(SNAPSHOT, "robot_a", fp, n, 2, np.zeros((n, C)), 1, 1, 2), conc, now=0.0) is None
    assert ledger.holders() == []


def test_the_ledger_keeps_at_most_what_a_map_file_keeps(tmp_path):
    """P5 at the ledger: asked for 70 sources, it keeps MAX_RECEIVED_SOURCES (64); the 65th new source holding
    evidence is refused by name, and the map file loads."""
    model = small_wall(tmp_path, 80)
    n, fp = model.num_gaussians, model.fingerprint
    smap, ledger = _bound_map(model, max_sources=70)
    conc = smap.concentrations
    got = []
    for k in range(66):
        one = np.zeros((n, C))
        one[k, 0] = 1.0
        got.append(ledger.apply(_packet(SNAPSHOT, f"s{k}", fp, n, 1, one, 1, 1, 1), conc, now=0.0))
    assert got[:MAX_RECEIVED_SOURCES] == [None] * MAX_RECEIVED_SOURCES
    assert got[MAX_RECEIVED_SOURCES:] == ["too many sources"] * 2
    smap.concentrations = conc
    smap.save(tmp_path / "m.npz")
    assert len(SemanticMap.load(tmp_path / "m.npz", model).received) == MAX_RECEIVED_SOURCES


def test_a_file_of_64_sources_loaded_under_another_origin_keeps_at_most_64(tmp_path):
    """P5, the loaded-file path: a file saved by node X with 64 received sources, loaded by node Y, makes X's own
    evidence one more source. The smallest sources are kept as part of X's (nothing becomes Y's own), the ledger
    holds 64, the evidence is unchanged and Y's next file loads."""
    model = small_wall(tmp_path, 80)
    n = model.num_gaussians
    rng = np.random.default_rng(6)
    smap = SemanticMap(model, C, prior=PRIOR)
    received = {}
    for k in range(MAX_RECEIVED_SOURCES):
        evk = np.zeros((n, C))
        evk[k, 1] = 1.0 + k
        received[f"s{k:02d}"] = SourceEvidence(evk, epoch=1, last_seq=1, frames=1, in_step=True)
    own_x = rng.uniform(0, 1, (n, C))
    smap.concentrations = PRIOR + own_x + sum(s.evidence for s in received.values())
    smap.evidence_origin, smap.received = "X", received
    smap.save(tmp_path / "x.npz")
    loaded = SemanticMap.load(tmp_path / "x.npz", model)
    got = ev.received_sources(loaded, "Y")
    assert len(got) == MAX_RECEIVED_SOURCES and "X" in got and "s00" not in got and "s63" in got
    total = sum(s.evidence for s in got.values())
    np.testing.assert_allclose(total, smap.concentrations_readonly - PRIOR, rtol=1e-12)   # none of it is Y's own
    ledger = EvidenceLedger("Y", model.fingerprint, n, C, PRIOR, max_sources=8, received=got)
    loaded.evidence_origin, loaded.received = "Y", ledger.sources
    loaded.save(tmp_path / "y.npz")
    assert len(SemanticMap.load(tmp_path / "y.npz", model).received) == MAX_RECEIVED_SOURCES


# ---------------------------------------------------------------------------------------------------- P4 buckets
def test_a_flood_of_other_origins_never_evicts_a_protected_bucket():
    """P4: robot_a (a ledger source) sends a packet every 3 s; 40 other origins send 80 packets/s for 24 s. Its
    bucket is never evicted nor refused; the others are bounded by the capacity (LRU eviction), none refused for
    want of room."""
    ledger_sources = {"robot_a"}
    buckets = OriginBuckets(rate=200.0, capacity=32, protected=lambda o: o in ledger_sources)
    t, a_ok, other_refused = 0.0, 0, 0
    for step in range(24 * 80):
        t = step / 80.0
        if step % 240 == 0:
            assert buckets.allow("robot_a", t)
            a_ok += 1
        other_refused += not buckets.allow(f"junk{step % 40}", t)
        assert len(buckets) <= 32 + 1 and "robot_a" in buckets
    assert a_ok == 8 and other_refused == 0 and buckets.evicted > 0
    # an origin over its rate is refused by its own bucket, not by the others' flood
    assert sum(buckets.allow("robot_a", t) for _ in range(300)) == 200


def test_buckets_evict_the_least_recently_used_unprotected_origin():
    buckets = OriginBuckets(rate=10.0, capacity=3, protected=lambda o: o == "p")
    for k, o in enumerate(["p", "a", "b", "c"]):
        assert buckets.allow(o, float(k))
    assert "a" in buckets and "p" in buckets              # p is protected; a, b, c fill the three others
    assert buckets.allow("a", 4.0)                          # a used again: b is now the least recent
    assert buckets.allow("d", 5.0)
    assert "b" not in buckets and all(o in buckets for o in ("p", "a", "c", "d"))


# ---------------------------------------------------------------------------------------------------- P7 cost
def test_an_empty_snapshot_part_costs_what_it_carries_not_its_range():
    """P7: on a splat of 360,000 Gaussians and 19 classes, an empty snapshot part covering [0, N) of a source holding
    nothing (or one row) changes only those rows: well under a millisecond-scale budget (it passed over several
    (N, C) arrays, ~140 ms each on a 2-core KVM guest). The map holds what it should afterwards."""
    n, c, fp = 360_000, 19, "ab" * 32
    conc = np.full((n, c), PRIOR)
    ledger = EvidenceLedger("me", fp, n, c, PRIOR, max_sources=8, max_frame_evidence=640 * 480)
    vals = np.zeros((50, c))
    vals[:, 3] = 1.0
    legit = ev.encode_packet(SNAPSHOT, "robot_a", fp, 1, np.arange(50), vals, PRIOR, n, snapshot_id=1, epoch=1,
                             frames=1)
    assert ledger.apply(decode_packet(legit, 20_000), conc, now=0.0) is None
    times = []
    for k in range(40):
        rows = np.array([n - 1]) if k % 2 else np.zeros(0, np.int64)   # every other part holds one row
        pkt = decode_packet(ev.encode_packet(SNAPSHOT, "flooder", fp, k + 1, rows, np.ones((rows.size, c)), PRIOR,
                                             n, snapshot_id=k + 1, epoch=7, frames=1), 20_000)
        t0 = time.perf_counter()
        assert ledger.apply(pkt, conc, now=0.0) is None
        times.append(time.perf_counter() - t0)
    assert float(np.median(times)) < 0.01, times          # 10 ms: generous on a busy 2-core machine
    assert conc[n - 1].sum() == pytest.approx(c * (PRIOR + 1.0))   # the last part (odd k) held the row
    np.testing.assert_array_equal(conc[:50, 3], PRIOR + 1.0)
    assert ledger.sources["flooder"].held_rows == 1 and ledger.sources["robot_a"].held_rows == 50


def _first_of_two_parts(origin, fp, n, epoch):
    """Part 0 (empty, rows [0, n/2)) of a 2-part snapshot, never followed by part 1."""
    return decode_packet(ev.encode_packet(SNAPSHOT, origin, fp, 1, np.zeros(0, np.int64), np.zeros((0, C)), PRIOR, n,
                                          snapshot_id=1, range_start=0, range_end=n // 2, part=0, parts=2,
                                          epoch=epoch, frames=1), 20_000)


def test_unfinished_snapshots_never_lock_a_new_source_out(tmp_path):
    """Eight origins that each send only part 0 (empty) of a 2-part snapshot held all eight slots for ever: every
    new peer was refused as "too many sources". Sources holding no evidence now give way, the least recently active
    unfinished snapshot first; a source that holds evidence keeps its slot."""
    model = small_wall(tmp_path, 50)
    n, fp = model.num_gaussians, model.fingerprint
    smap, ledger = _bound_map(model)
    conc = smap.concentrations
    held = np.full((n, C), 0.5)
    assert ledger.apply(_packet(SNAPSHOT, "holder", fp, n, 1, held, 1, 1, 1), conc, now=0.0) is None
    for k in range(7):
        assert ledger.apply(_first_of_two_parts(f"junk{k}", fp, n, 5), conc, now=1.0 + k) is None
    assert len(ledger.sources) == 8
    real = np.full((n, C), 0.25)
    for t in range(3):   # every new peer gets a slot, each time from the stalest unfinished snapshot
        assert ledger.apply(_packet(SNAPSHOT, f"peer{t}", fp, n, 1, real, 7, 1, 1), conc, now=20.0 + t) is None
        assert f"junk{t}" not in ledger.sources and "holder" in ledger.sources
    np.testing.assert_allclose(conc, PRIOR + held + 3 * real)


def test_unfinished_returns_never_block_a_real_return():
    """Unfinished forged returns from max_sources senders blocked a real return until the window closed."""
    n, fp = 40, "ab" * 32
    rec = ev.EvidenceRecovery("me", fp, n, C, PRIOR, checkpoint_epoch=100, checkpoint_frames=1, current_epoch=200,
                              max_frame_evidence=10.0, max_sources=4, now=0.0, window=30.0)
    evidence = np.zeros((n, C))
    evidence[::2, 1] = 0.5
    for k in range(4):
        first, _ = ev.encode_return(f"forger{k}", "me", fp, 150, 2, evidence, PRIOR, 5)[:2]
        assert rec.offer(decode_packet(first, 100), now=1.0) == (None, None)
    parts = ev.encode_return("robot_a", "me", fp, 150, 2, evidence, PRIOR, 5)
    for p in parts[:-1]:
        assert rec.offer(decode_packet(p, 100), now=2.0) == (None, None)
    reason, adopted = rec.offer(decode_packet(parts[-1], 100), now=2.0)
    assert reason is None and adopted is not None
    np.testing.assert_array_equal(adopted[2], evidence)

