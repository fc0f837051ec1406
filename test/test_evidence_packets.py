"""The evidence packets and the exactly-once ledger (css_ros/io/evidence.py), without ROS."""
from __future__ import annotations

import numpy as np
import pytest

from css_ros.errors import InputError
from css_ros.io.evidence import (DELTA, HEADER_SIZE, SNAPSHOT, EvidenceLedger, EvidenceOutbox, decode_packet,
                                 encode_packet)

FP = "0123456789abcdef" * 4
N, C, PRIOR = 50, 3, 1e-3


def test_packet_round_trip_and_layout():
    rows = np.array([1, 7, 49])
    vals = np.arange(9, dtype=float).reshape(3, 3) / 7
    data = encode_packet(DELTA, "robot_a", FP, 5, rows, vals, PRIOR, N)
    assert len(data) == HEADER_SIZE + 3 * (4 + 8 * C) and HEADER_SIZE == 120 and data[:4] == b"CSSE"
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
    packets = [decode_packet(p, 16) for p in box.snapshot(box.own(alpha, received))]
    assert len(packets) == 3 and all(p.kind == SNAPSHOT for p in packets)
    got = np.zeros((N, C))
    for p in packets:
        got[p.rows] = p.values
    np.testing.assert_allclose(got, own_true, rtol=1e-12, atol=1e-14)
    assert not np.any(np.isin(np.arange(10), np.concatenate([p.rows for p in packets])))  # no echo
    assert box.deltas(alpha, received) == []                         # nothing new: nothing sent
    alpha[12] += 0.5
    (delta,) = [decode_packet(p, 16) for p in box.deltas(alpha, received)]
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
    box.snapshot(box.own(alpha, received))
    grow = rng.choice(n, 50, replace=False)
    alpha[grow, rng.integers(0, c, 50)] += rng.uniform(0.01, 2.0, 50)
    alpha[::37, 1] += 1e-15                                            # rounding-level alone: not sent
    own = alpha - PRIOR - received
    own[own <= 1e-12 * alpha.sum(axis=1, keepdims=True)] = 0.0
    delta = own - box.published
    want_rows = np.flatnonzero(np.any(delta > 1e-12 * alpha.sum(axis=1, keepdims=True), axis=1))
    want_vals = np.maximum(delta[want_rows], 0.0)
    packets = [decode_packet(p, n) for p in box.deltas(alpha, received)]
    assert np.array_equal(np.concatenate([p.rows for p in packets]), want_rows) and set(want_rows) == set(grow)
    np.testing.assert_array_equal(np.concatenate([p.values for p in packets]), want_vals)
    assert box.deltas(alpha, received) == []

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
