"""Forged evidence packets: huge frame claims, forged returns and "resumed" floods (css_ros/io/evidence.py).

The ledger and the recovery without ROS; test_node_evidence_forged.py sends the same packets to a live css_node.
"""
from __future__ import annotations

import numpy as np
import pytest

from css_ros.engine.spec import MAX_FRAMES
from css_ros.errors import InputError
from css_ros.io import evidence as ev
from css_ros.io.evidence import SNAPSHOT, EvidenceLedger, decode_packet

FP = "0123456789abcdef" * 4
N, C, PRIOR = 50, 3, 1e-3
SECOND = 10**9   # ns: epochs are wall-clock ns


def _snapshot(origin: str, seq: int, total: np.ndarray, epoch: int, frames: int, flags: int = 0) -> bytes:
    rows = np.flatnonzero(np.any(total != 0.0, axis=1))
    return ev.encode_packet(SNAPSHOT, origin, FP, seq, rows, total[rows], PRIOR, N, snapshot_id=seq, epoch=epoch,
                            frames=frames, flags=flags)


@pytest.mark.parametrize("frames", [2**64 - 1, 2**63 + 5, MAX_FRAMES + 1])
def test_frame_claims_beyond_what_a_map_holds_are_refused_at_decode(frames):
    """A frame count above MAX_FRAMES (2^48) is refused by name, whatever the kind: it would overflow the int64
    frames_observed of a map file or the u64 of the next packet once adopted."""
    vals = np.ones((N, C))
    for data in (_snapshot("robot_a", 1, vals, 1, frames),
                 ev.encode_return("robot_a", "robot_b", FP, 1, frames, vals, PRIOR, 100)[0]):
        with pytest.raises(InputError, match="frame count above"):
            decode_packet(data, 100)
    assert decode_packet(_snapshot("robot_a", 1, vals, 1, MAX_FRAMES), 100).frames == MAX_FRAMES


def _recovery(checkpoint_epoch: int, checkpoint_frames: int, current_epoch: int, rate: float = 10.0):
    return ev.EvidenceRecovery("robot_b", FP, N, C, PRIOR, checkpoint_epoch=checkpoint_epoch,
                               checkpoint_frames=checkpoint_frames, current_epoch=current_epoch,
                               max_frame_evidence=1e12, max_sources=4, now=0.0, window=30.0, max_frame_rate=rate)


def _return(epoch: int, frames: int) -> ev.EvidencePacket:
    values = np.zeros((N, C))
    values[3, 1] = 2.0
    (p,) = ev.encode_return("robot_a", "robot_b", FP, epoch, frames, values, PRIOR, 100)
    return decode_packet(p, 100)


def test_a_return_claims_at_most_what_the_restarted_node_could_have_fused():
    """Checkpoint of epoch E with 7 frames, restarted 20 s later at 10 frames/s: a return may claim at most
    7 + 10 · (20 + FRAME_BURST_S) frames; 10^6 frames (the forged return of the probe) is refused and nothing is
    adopted, the largest plausible claim is adopted. Without a checkpoint the return's own epoch starts the clock."""
    e0 = 1_700_000_000 * SECOND
    limit = 7 + 10.0 * (20.0 + ev.FRAME_BURST_S)
    assert limit == 257.0
    rec = _recovery(e0, 7, e0 + 20 * SECOND)
    assert rec.offer(_return(e0, 10**6), 1.0) == (ev.RETURN_FRAMES_REASON, None)
    assert rec.offer(_return(e0 + 5 * SECOND, 258), 1.0) == (ev.RETURN_FRAMES_REASON, None)
    reason, got = rec.offer(_return(e0 + 5 * SECOND, 257), 1.0)
    assert reason is None and got is not None and got[:2] == (e0 + 5 * SECOND, 257)
    fresh = _recovery(0, 0, e0 + 20 * SECOND)          # no checkpoint: killed before its first save
    assert fresh.offer(_return(e0 + 18 * SECOND, 71), 1.0) == (ev.RETURN_FRAMES_REASON, None)   # 10 · (2 + 5) = 70
    assert fresh.offer(_return(e0 + 18 * SECOND, 70), 1.0)[0] is None


def test_resumed_floods_get_a_bounded_number_of_returns():
    """Source robot_a held evidence here (an unflagged snapshot); then 400 "resumed" snapshots of new epochs arrive
    within 20 s (what a forger sends under the 200 packets/s flood bound in 2 s, stretched). Returns due: at most
    RETURN_BURST + 20 s / RETURN_INTERVAL_S, not one per packet. An origin that stated evidence only in flagged
    snapshots (never held evidence here otherwise) gets none at all."""
    rng = np.random.default_rng(0)
    alpha = np.full((N, C), PRIOR)
    ledger = EvidenceLedger("me", FP, N, C, PRIOR, max_sources=4)
    held = rng.uniform(0, 1, (N, C))
    assert ledger.apply(decode_packet(_snapshot("robot_a", 1, held, 1, 5), N), alpha, now=0.0) is None
    tiny = np.zeros((N, C))
    tiny[0, 0] = 1e-3
    due = 0
    for k in range(400):
        now = 0.05 * k
        for origin in ("robot_a", "stranger"):
            pkt = decode_packet(_snapshot(origin, 2 + k, tiny, 10 + k, 1, flags=ev.FLAG_RESUMED), N)
            assert ledger.apply(pkt, alpha, now=now) is None
        due += ledger.returns_due.count("robot_a")
        assert "stranger" not in ledger.returns_due
        ledger.returns_due.clear()
    bound = ev.RETURN_BURST + int(0.05 * 399 / ev.RETURN_INTERVAL_S)
    assert 1 <= due <= bound == 6, due
    (ret,) = ledger.return_packets("robot_a", 100)    # the copy of the evidence it held, not the flood's
    np.testing.assert_array_equal(decode_packet(ret, 100).values, held[decode_packet(ret, 100).rows])



def _parts(origin: str, seq: int, total: np.ndarray, epoch: int, frames: int, max_rows: int,
           flags: int = 0) -> list[bytes]:
    """The snapshot parts (of at most ``max_rows`` rows, first sequence number ``seq``) stating ``total`` (n, C)."""
    n = total.shape[0]
    nz = np.flatnonzero(np.any(total != 0.0, axis=1))
    chunks = [nz[a:a + max_rows] for a in range(0, nz.size, max_rows)] or [nz]
    starts = [0] + [int(ch[0]) for ch in chunks[1:]]
    ends = starts[1:] + [n]
    return [ev.encode_packet(SNAPSHOT, origin, FP, seq + k, r, total[r], PRIOR, n, snapshot_id=seq, range_start=lo,
                             range_end=hi, part=k, parts=len(chunks), epoch=epoch, frames=frames, flags=flags)
            for k, (r, lo, hi) in enumerate(zip(chunks, starts, ends))]


def _stream(ledger: EvidenceLedger, alpha: np.ndarray, packets: list[tuple[float, bytes]],
            max_rows: int) -> tuple[int, int, list[tuple[str, str, int]]]:
    """Apply ``packets`` ((time, bytes)); returns (bytes received, bytes of the returns due, withheld entries)."""
    got = sent = 0
    withheld: list[tuple[str, str, int]] = []
    for now, data in packets:
        assert ledger.apply(decode_packet(data, max_rows), alpha, now=now) is None
        got += len(data)
        sent += sum(len(p) for o in ledger.returns_due for p in ledger.return_packets(o))
        ledger.returns_due.clear()
        withheld += ledger.returns_withheld
        ledger.returns_withheld.clear()
    return got, sent, withheld


def test_an_origin_cannot_make_the_node_send_more_than_ten_times_what_it_sends():
    """The hostile probe: an origin that holds 20,000 rows here sends 60 one-row snapshots flagged "resumed", each of a
    new epoch (16 kB in all). Before, 3 + 1 per 5 s returns of the whole 20,000 rows went out (x657). Now the returns
    to it stay within RETURN_AMPLIFICATION times the bytes it sent since its "resumed" run began: none here, and all
    60 are counted as withheld (byte budget) with the size each would have had."""
    n, c, max_rows = 20_000, 16, 5_000
    ledger = EvidenceLedger("me", FP, n, c, PRIOR, max_sources=4, max_rows=max_rows)
    alpha = np.full((n, c), PRIOR)
    held = np.random.default_rng(1).uniform(0.1, 1.0, (n, c))
    _stream(ledger, alpha, [(0.0, d) for d in _parts("robot_a", 1, held, SECOND, 5, max_rows)], max_rows)
    assert ledger.sources["robot_a"].held_rows == n
    one = np.zeros((n, c))
    one[7, 0] = 1e-3
    flood = [(0.04 * k, _parts("robot_a", 100 + k, one, 2 * SECOND + k, 1, max_rows, ev.FLAG_RESUMED)[0])
             for k in range(60)]
    got, sent, withheld = _stream(ledger, alpha, flood, max_rows)
    whole = ev.return_bytes(n, c, max_rows)
    assert whole == sum(len(p) for p in ev.encode_return("me", "robot_a", FP, SECOND, 5, held, PRIOR, max_rows))
    assert got == 60 * (ev.HEADER_SIZE + 4 + 8 * c) and whole > 10 * got   # 16 kB in; one return is 2.6 MB
    assert sent == 0
    assert withheld == [("robot_a", ev.WITHHELD_BUDGET, whole)] * 60


def test_the_byte_budget_holds_for_any_stream_and_a_real_restart_still_gets_its_return():
    """Property: whatever mix of "resumed" snapshots (each of a new epoch, holding 0-30 % or all of the origin's rows)
    and unflagged ones an origin sends, the returns due to it never exceed RETURN_AMPLIFICATION times the bytes it
    sent since its latest "resumed" run began. A real restart (its checkpoint holds most of its evidence, so its
    resumed snapshot is about as large as the return) gets its return on part 0 of its first resumed snapshot."""
    rng = np.random.default_rng(7)
    n, max_rows = 400, 64
    for trial in range(20):
        ledger = EvidenceLedger("me", FP, n, C, PRIOR, max_sources=4, max_rows=max_rows)
        alpha = np.full((n, C), PRIOR)
        held = np.where(rng.uniform(size=(n, 1)) < 0.8, rng.uniform(0.1, 1, (n, C)), 0.0)
        seq, t, run_in, run_out = 1, 0.0, 0, 0
        for k in range(60):
            resumed = k > 0 and rng.uniform() < 0.75
            total = held if not resumed or rng.uniform() < 0.2 else \
                np.where(rng.uniform(size=(n, 1)) < rng.uniform(0, 0.3), held, 0.0)
            parts = _parts("robot_a", seq, total, (k + 1) * SECOND, k + 2, max_rows, ev.FLAG_RESUMED * resumed)
            seq += len(parts)
            if not resumed:
                run_in = run_out = 0                     # an unflagged snapshot ends the run
            for data in parts:
                assert ledger.apply(decode_packet(data, max_rows), alpha, now=t) is None
                run_in += len(data) if resumed else 0
                run_out += sum(len(p) for o in ledger.returns_due for p in ledger.return_packets(o))
                ledger.returns_due.clear()
                ledger.returns_withheld.clear()
                assert run_out <= 10 * run_in, (trial, k, run_out, run_in)   # the bound asked for: x10
            t += float(rng.uniform(0.0, 4.0))

    ledger = EvidenceLedger("me", FP, n, C, PRIOR, max_sources=4, max_rows=max_rows)
    alpha = np.full((n, C), PRIOR)
    held = rng.uniform(0.1, 1, (n, C))
    _stream(ledger, alpha, [(0.0, d) for d in _parts("robot_a", 1, held, SECOND, 4, max_rows)], max_rows)
    ckpt = held.copy()
    ckpt[: n // 4] = 0.0                                 # its checkpoint holds 3 of its 4 frames
    first = _parts("robot_a", 1, ckpt, 2 * SECOND, 3, max_rows, ev.FLAG_RESUMED)[0]
    got, sent, withheld = _stream(ledger, alpha, [(1.0, first)], max_rows)
    assert sent == ev.return_bytes(n, C, max_rows) and withheld == []
