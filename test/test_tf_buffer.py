"""The rclpy-free TF buffer against a numpy brute force: 4x4 matrices composed edge by edge, each edge interpolated
with scipy's Slerp (an implementation independent of the pose history's)."""
from __future__ import annotations

from types import SimpleNamespace as NS

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from css_ros.io.pose_history import LookupStatus, PosePolicy
from css_ros.io.tf_buffer import TfBuffer, TfSample, decode_tf_message
from tf_reference import brute_chain, mat, pose_errors

S = 1_000_000_000
T0 = 1_700_000_000 * S


def tf_msg(entries):
    """A duck-typed TFMessage from (parent, child, stamp_ns, xyz, xyzw) entries."""
    out = []
    for parent, child, stamp, xyz, q in entries:
        out.append(NS(header=NS(stamp=NS(sec=stamp // S, nanosec=stamp % S), frame_id=parent), child_frame_id=child,
                      transform=NS(translation=NS(x=xyz[0], y=xyz[1], z=xyz[2]),
                                   rotation=NS(x=q[0], y=q[1], z=q[2], w=q[3]))))
    return NS(transforms=out)


def assert_pose(look, T, tol=1e-9):
    assert look.status is LookupStatus.OK, (look.reason, look.detail)
    dp, da = pose_errors(look.position, look.quat, T)
    assert dp < tol and da < tol


def random_q(rng):
    return Rotation.random(random_state=rng).as_quat()


@pytest.fixture
def robot():
    """map->odom (20 Hz), odom->base_link (100 Hz, jittered), static base_link->camera_link->optical, plus a second
    camera on base_link; returns (buffer, dynamic samples per child, static T per child)."""
    rng = np.random.default_rng(7)
    buf = TfBuffer(PosePolicy(buffer=10.0, wait=0.5, max_extrapolation=0.02, max_gap=1.0))
    dyn: dict[str, list] = {"odom": [], "base_link": []}
    parents = {"odom": "map", "base_link": "odom", "camera_link": "base_link", "camera_optical_frame": "camera_link",
               "camera2_optical": "base_link"}
    for child, rate, jitter in (("odom", 20, 0.0), ("base_link", 100, 0.3)):
        t = T0
        q = random_q(rng)
        while t < T0 + 3 * S:
            q = (Rotation.from_quat(q) * Rotation.from_rotvec(rng.normal(0, 0.05, 3))).as_quat()
            xyz = rng.normal(0, 2.0, 3)
            dyn[child].append((t, xyz, q))
            t += int(S / rate * (1 + jitter * rng.uniform(-1, 1)))
    static = {c: (rng.normal(0, 0.3, 3), random_q(rng)) for c in ("camera_link", "camera_optical_frame",
                                                                    "camera2_optical")}
    buf.add_message(tf_msg([(parents[c], c, T0, *static[c]) for c in static]), static=True)
    # interleave the two dynamic streams in time order, one message per sample
    events = sorted([(s[0], c, s) for c in dyn for s in dyn[c]], key=lambda e: e[0])
    for _, c, (t, xyz, q) in events:
        assert buf.add_message(tf_msg([(parents[c], c, t, xyz, q)]), static=False) == []
    return buf, dyn, {c: mat(*v) for c, v in static.items()}, parents


def brute_in_map(frame, t, dyn, static, parents):
    return brute_chain(frame, "map", t, parents, dyn, static)


def test_chain_lookups_match_the_brute_force(robot):
    buf, dyn, static, parents = robot
    rng = np.random.default_rng(1)
    stamps = rng.integers(T0 + S // 10, T0 + 29 * S // 10, 40).tolist() + [dyn["base_link"][50][0]]
    for t in stamps:
        for source in ("camera_optical_frame", "camera2_optical", "base_link", "odom"):
            look = buf.lookup("map", source, t, waited=False)
            assert_pose(look, brute_in_map(source, t, dyn, static, parents))
        # across branches: neither frame is the root
        T_cam1 = brute_in_map("camera_optical_frame", t, dyn, static, parents)
        T_cam2 = brute_in_map("camera2_optical", t, dyn, static, parents)
        assert_pose(buf.lookup("camera_optical_frame", "camera2_optical", t, False), np.linalg.inv(T_cam1) @ T_cam2)
        assert_pose(buf.lookup("/camera_link", "/map", t, False),
                    np.linalg.inv(brute_in_map("camera_link", t, dyn, static, parents)))


def test_how_is_the_worst_edge_and_statics_hold_at_any_time(robot):
    buf, dyn, static, parents = robot
    t_odom = dyn["odom"][5][0]
    assert t_odom not in {s[0] for s in dyn["base_link"]}
    assert buf.lookup("map", "odom", t_odom, False).how == "exact"
    assert buf.lookup("map", "camera_optical_frame", t_odom, False).how == "interpolated"
    for t in (0, T0 - 100 * S, T0 + 10**6 * S):  # static-only chain: any stamp
        look = buf.lookup("base_link", "camera_optical_frame", t, waited=False)
        assert_pose(look, static["camera_link"] @ static["camera_optical_frame"])
        assert look.how == "exact"
    assert_pose(buf.lookup("map", "map", 5, False), np.eye(4))


def test_refusals_name_the_reason(robot):
    buf, dyn, static, parents = robot
    newest = min(dyn["odom"][-1][0], dyn["base_link"][-1][0])
    # unknown frame: wait first, then refused
    assert buf.lookup("map", "no_such_frame", T0 + S, waited=False).status is LookupStatus.WAIT
    r = buf.lookup("map", "no_such_frame", T0 + S, waited=True)
    assert (r.status, r.reason) == (LookupStatus.REFUSED, "tf unknown frame") and "no_such_frame" in r.detail
    # no path: a second tree
    buf.add_message(tf_msg([("world", "other", T0, [0, 0, 0], [0, 0, 0, 1])]), static=True)
    assert buf.lookup("map", "other", T0 + S, waited=False).status is LookupStatus.WAIT
    r = buf.lookup("map", "other", T0 + S, waited=True)
    assert (r.status, r.reason) == (LookupStatus.REFUSED, "tf no path") and "world" in r.detail
    # future: wait, then extrapolated within max_pose_extrapolation, refused beyond it
    far = dyn["odom"][-1][0] + S // 10
    assert buf.lookup("map", "camera_optical_frame", far, waited=False).status is LookupStatus.WAIT
    r = buf.lookup("map", "camera_optical_frame", far, waited=True)
    assert (r.status, r.reason) == (LookupStatus.REFUSED, "tf extrapolation into the future")
    assert r.detail.startswith("map -> odom:") or r.detail.startswith("odom -> base_link:")
    near = newest + S // 100
    assert buf.lookup("map", "camera_optical_frame", near, waited=True).how == "extrapolated"
    # past: refused at once (no later sample can help)
    r = buf.lookup("map", "camera_optical_frame", T0 - S, waited=False)
    assert (r.status, r.reason) == (LookupStatus.REFUSED, "tf extrapolation into the past")


def test_history_is_bounded_by_tf_buffer_s():
    buf = TfBuffer(PosePolicy(buffer=2.0))
    q = [0.0, 0.0, 0.0, 1.0]
    for k in range(1000):  # 10 s at 100 Hz
        buf.add(TfSample("map", "odom", T0 + k * S // 100, np.array([k * 0.01, 0, 0]), np.array(q)), static=False)
    hist = buf._edges["odom"].history
    assert hist is not None and len(hist) <= 2.0 * 100 * 1.2 + 64
    r = buf.lookup("map", "odom", T0 + 5 * S, waited=False)
    assert (r.status, r.reason) == (LookupStatus.REFUSED, "tf extrapolation into the past")
    assert "tf_buffer_s=2" in r.detail
    ok = buf.lookup("map", "odom", T0 + 9 * S + S // 200, waited=False)
    np.testing.assert_allclose(ok.position, [9.005, 0, 0], atol=1e-12)


def test_a_jump_of_map_odom_is_used_from_its_stamp_on():
    buf = TfBuffer(PosePolicy(buffer=10.0, max_gap=1.0))
    ident = [0.0, 0.0, 0.0, 1.0]
    jump_q = Rotation.from_rotvec([0, 0, 0.3]).as_quat()
    for k in range(40):  # 20 Hz map->odom: identity, then a correction at k = 20
        t = T0 + k * S // 20
        xyz, q = ([0.0, 0.0, 0.0], ident) if k < 20 else ([1.5, -0.5, 0.0], jump_q)
        buf.add_message(tf_msg([("map", "odom", t, xyz, q), ("odom", "base", t, [0.1 * k, 0, 0], ident)]), False)
    t = T0 + 25 * S // 20 + S // 40
    expected = mat([1.5, -0.5, 0.0], jump_q) @ mat([0.1 * 25.5, 0, 0], ident)
    assert_pose(buf.lookup("map", "base", t, False), expected)


def test_decode_drops_bad_transforms_and_accepts_slashes():
    msg = tf_msg([("/map", "/odom", T0, [1, 2, 3], [0, 0, 0, 1]),
                  ("map", "x", T0, [np.nan, 0, 0], [0, 0, 0, 1]),
                  ("map", "y", T0, [0, 0, 0], [0, 0, 0, 2.0]),
                  ("map", "map", T0, [0, 0, 0], [0, 0, 0, 1]),
                  ("", "z", T0, [0, 0, 0], [0, 0, 0, 1])])
    samples, problems = decode_tf_message(msg)
    assert [(s.parent, s.child) for s in samples] == [("map", "odom")]
    assert [p[0] for p in problems] == ["invalid transform"] * 4
    assert "norm" in problems[1][1] and "own parent" in problems[2][1] and "empty frame id" in problems[3][1]
    assert decode_tf_message(NS())[1][0][0] == "invalid tf message"


def test_parent_change_restarts_the_edge_and_repeats_are_reported():
    buf = TfBuffer()
    q = [0.0, 0.0, 0.0, 1.0]
    assert buf.add_message(tf_msg([("map", "a", T0, [1, 0, 0], q)]), False) == []
    assert buf.add_message(tf_msg([("map", "a", T0, [1, 0, 0], q)]), False)[0][0] == "tf repeated stamp"
    out = buf.add_message(tf_msg([("odom", "a", T0 + S, [2, 0, 0], q)]), False)
    assert out[0][:1] == ("tf parent changed",) and out[0][2] is False
    assert buf.lookup("map", "a", T0 + S, True).reason == "tf no path"
    assert_pose(buf.lookup("odom", "a", T0 + S, False), mat([2, 0, 0], q))
