"""The CUDA backend's rules for a changing world (css_ros/engine/change_rules.py: transient classes, measured depth,
forgetting, surprise), run through the numba-cuda simulator against a float64 brute force written here pixel by pixel
(test/css_reference.py gives every pixel's kappa) and against the numba backend, on tiny scenes.

Like test_cuda_sim.py, the simulator must be switched on before numba is imported: these tests run in a subprocess
started by test/test_cuda_backend.py (NUMBA_ENABLE_CUDASIM=1; on a machine with a GPU, CSS_CUDA_CHECKS=device runs
them on the device); collected in a process without either this module skips itself.
"""
from __future__ import annotations

import os

import numpy as np
import pytest

if os.environ.get("NUMBA_ENABLE_CUDASIM", "0") in ("", "0") and os.environ.get("CSS_CUDA_CHECKS") != "device":
    pytest.skip("CUDA checks run in a subprocess (test_cuda_backend.py::test_simulated_change_rules: simulated, or on "
                "the GPU where there is one)", allow_module_level=True)
pytest.importorskip("numba.cuda", reason="numba-cuda is not installed (pip install -e '.[cuda]')")

import sys  # noqa: E402

# the simulator's barriers wait for Python threads: a short GIL switch interval (see test_cuda_sim.py)
sys.setswitchinterval(5e-4)

from css_ros.engine.final_form import IMAGE_OUTPUTS  # noqa: E402
from css_ros import SemanticMap  # noqa: E402
from css_ros.engine.sensor_model import SensorModel  # noqa: E402
from css_reference import kappa_reference, project_reference  # noqa: E402
from scenes import camera, edge_case_scene, random_scene  # noqa: E402

C = 4
W, H = 16, 12
PRIOR = 1e-3
# the GPU walk is float32 (kappa ~1e-6 relative), the map float64: the tolerances of test_cuda_sim.py
KAPPA_RTOL, KAPPA_ATOL = 2e-5, 1e-7
SURPRISE_ATOL = 1e-4
TOL_ABS, TOL_REL = 0.05, 0.03


def scene_pixels(model, cam):
    """(kappa (P, N), final transmittance (P,), camera depth z (N,) in splat units) by brute force."""
    kap, bg = kappa_reference(model.means, model.scales, model.quats_wxyz, model.opacities, cam.K, cam.T_map_cam,
                              cam.width, cam.height)
    proj = project_reference(model.means, model.scales, model.quats_wxyz, model.opacities, cam.K, cam.T_map_cam,
                             cam.width, cam.height)
    z = np.array([np.inf if p is None else p[0] for p in proj])
    return kap, bg, z


def pixel_vote(raw, conf, ignore):
    """(class, float32 weight, status 0 used / 1 ignored / 2 out of range) of one pixel: the label rule in float64."""
    if raw == ignore:
        return -1, 0.0, 1
    if not 0 <= raw < C:
        return -1, 0.0, 2
    w = 0.0 if np.isnan(conf) else min(max(conf, 0.0), 1.0)
    w = float(np.float32(w))
    return (raw, w, 0) if w > 0 else (-1, 0.0, 1)


def world_reference(pixels, alpha, labels, conf, *, ignore=255, transient=(), depth=None, scale=1.0, decay=1.0,
                    soft=None, front=True):
    """The changing world's update of one frame in float64, pixel by pixel (the module docstring of change_rules):
    (alpha after, counts (used, ignored, out of range, no depth, transient, occluded), surprise (P,) NaN without a
    vote). ``soft``: a sensor model's (edges in splat units, table) with the bin of the rendered depth; ``front``
    False: keep the contributions in front of the measured surface (to show that the rule matters)."""
    kap, bg, z = pixels
    z = np.where(np.isfinite(z), z, 0.0)     # Gaussians not in view: kappa 0 everywhere
    e_n = alpha / alpha.sum(axis=1, keepdims=True)
    lab = np.asarray(labels).ravel()
    cf = np.ones(lab.size) if conf is None else np.asarray(conf, dtype=np.float64).ravel()
    dep = None if depth is None else np.asarray(depth, dtype=np.float64).ravel()
    counts = [0] * 6
    surprise = np.full(lab.size, np.nan)
    inc = np.zeros_like(alpha)
    for i in range(lab.size):
        y, w, status = pixel_vote(int(lab[i]), cf[i], ignore)
        if status:
            counts[status] += 1
            continue
        k = kap[i]
        surprise[i] = 1.0 - (k @ e_n[:, y] + bg[i] / C)
        if y in transient:
            counts[4] += 1
            continue
        keep = k > 0
        seen = k.sum() > 0
        d = np.nan if dep is None else dep[i]
        if np.isfinite(d) and d > 0 and seen:
            tau = max(TOL_ABS, TOL_REL * d)
            if d < (k @ z) / k.sum() * scale - tau:
                counts[5] += 1
                continue
            if front and (k @ z) / k.sum() * scale < d - tau:
                keep &= z * scale >= d - tau
        counts[0] += 1
        vote = np.zeros(C)
        vote[y] = w
        if soft is not None:
            if not seen:
                counts[3] += 1
                continue
            edges, table = soft
            b = int(np.clip(np.searchsorted(edges, (k @ z) / k.sum(), side="right") - 1, 0, len(edges) - 2))
            vote = w * table[y * (len(edges) - 1) + b]
        inc += np.outer(np.where(keep, k, 0.0), vote)
    out = alpha.copy()
    touched = (inc != 0).any(axis=1)
    out[touched] = PRIOR + (alpha[touched] - PRIOR) * decay + inc[touched]
    return out, tuple(counts), surprise


def rendered_depth(pixels, scale):
    """Each pixel's rendered depth sum kappa z / sum kappa in metres (NaN without a contribution)."""
    kap, _, z = pixels
    ks = kap.sum(axis=1)
    zz = np.where(np.isfinite(z), z, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(ks > 0, (kap @ zz) / ks * scale, np.nan)


def measured_depth(pixels, scale, seed):
    """A depth image of every kind, pixel by pixel: none (NaN, 0, negative, inf), clearly nearer than the rendered
    depth (occluded), at it (the Gaussians well in front dropped) and far behind it (most dropped); each value is
    nudged until no rule's comparison lies within 1e-4 relative of its threshold (float32 on the device)."""
    kap, _, z = pixels
    r = rendered_depth(pixels, scale)
    rng = np.random.default_rng(seed)
    kinds = rng.integers(0, 7, r.size)
    d = np.full(r.size, np.nan)
    for i in range(r.size):
        base = r[i] if np.isfinite(r[i]) else rng.uniform(1.0, 5.0)
        d[i] = (np.nan, 0.0, -1.0, np.inf, 0.5 * base, base, 1.6 * base)[kinds[i]]
        for step in range(50):
            if not (np.isfinite(d[i]) and d[i] > 0 and np.isfinite(r[i])):
                break
            tau = max(TOL_ABS, TOL_REL * d[i])
            zs = z[kap[i] > 0] * scale
            close = np.abs(d[i] - (r[i] - tau)) < 1e-4 * d[i] or np.any(np.abs(zs - (d[i] - tau)) < 1e-4 * d[i])
            if not close:
                break
            d[i] *= 1.0 + 1e-3 * (step + 1)
    return d.astype(np.float32)


def frame_inputs(cam, seed, classes=C):
    rng = np.random.default_rng(seed)
    lab = rng.integers(0, classes, (cam.height, cam.width)).astype(np.int32)
    lab[rng.random(lab.shape) < 0.12] = 255
    lab[rng.random(lab.shape) < 0.05] = classes + 2
    conf = rng.uniform(0.2, 1.0, lab.shape).astype(np.float32)
    conf[rng.random(lab.shape) < 0.04] = np.nan
    return lab, conf


def counts_of(stats):
    return (stats.used, stats.ignored, stats.out_of_range, stats.no_depth, stats.transient, stats.occluded)


def both(model, **kwargs):
    """(cuda map, numba map) with the same arguments."""
    return SemanticMap(model, C, backend="cuda", **kwargs), SemanticMap(model, C, **kwargs)


def assert_same(gpu, cpu, view=None, cpu_view=None):
    """The CUDA map agrees with the numba map: the last update's counts exactly, the concentrations within the float32
    walk's tolerance, the surprise images within SURPRISE_ATOL (NaN at the same pixels)."""
    assert gpu.last_update == cpu.last_update
    np.testing.assert_allclose(gpu.concentrations, cpu.concentrations, rtol=KAPPA_RTOL, atol=KAPPA_ATOL)
    if view is not None:
        np.testing.assert_array_equal(np.isnan(view.surprise), np.isnan(cpu_view.surprise))
        np.testing.assert_allclose(view.surprise, cpu_view.surprise, atol=SURPRISE_ATOL, equal_nan=True)


CASES = [
    # a random cloud, metres = 2 splat units
    dict(scene=lambda: random_scene(21, n=120), cam=dict(width=W, height=H, f=12.0), scale=2.0),
    # opaque sheets (early termination), borders, behind the camera; an odd image size
    dict(scene=lambda: edge_case_scene(2), cam=dict(width=13, height=11, f=10.0, cx=3.0, cy=8.0), scale=1.0),
]


@pytest.mark.parametrize("case", range(len(CASES)))
def test_transient_occluded_and_front_drop_match_the_brute_force(case):
    """One update with transient classes and a measured depth of every kind: the counts exactly, the concentrations
    within float32 rounding of the walk; occluded pixels, dropped contributions and transient pixels really occur."""
    spec = CASES[case]
    model, cam, scale = spec["scene"](), camera(**spec["cam"]), spec["scale"]
    pixels = scene_pixels(model, cam)
    lab, conf = frame_inputs(cam, case)
    depth = measured_depth(pixels, scale, case).reshape(cam.height, cam.width)
    gpu, cpu = both(model, depth_scale=scale, transient_classes=[1], depth_tolerance=TOL_ABS,
                    depth_tolerance_relative=TOL_REL)
    stats = gpu.update(cam, lab, conf, depth=depth)
    cpu.update(cam, lab, conf, depth=depth)
    assert_same(gpu, cpu)
    alpha0 = np.full((model.num_gaussians, C), PRIOR)
    want, counts, _ = world_reference(pixels, alpha0, lab, conf, transient=(1,), depth=depth, scale=scale)
    assert counts_of(stats) == counts
    assert sum(counts) - counts[3] == cam.width * cam.height
    assert counts[4] > 0 and counts[5] > 0 and counts[0] > 0
    np.testing.assert_allclose(gpu.concentrations, want, rtol=KAPPA_RTOL, atol=KAPPA_ATOL)
    # each rule changed the result: without the depth rules, or without the front drop alone, the frame adds more
    plain, _, _ = world_reference(pixels, alpha0, lab, conf, transient=(1,), scale=scale)
    assert np.abs(plain - want).max() > 0.05
    kept, _, _ = world_reference(pixels, alpha0, lab, conf, transient=(1,), depth=depth, scale=scale, front=False)
    assert np.abs(kept - want).max() > 0.05
    assert np.all(gpu.concentrations[:, 1] == PRIOR)       # the transient class never gets evidence


def test_depth_without_a_measurement_is_the_plain_update():
    """A depth image of NaN, zeros, negative values and inf measures nothing: the update equals the one without a
    depth image (counts and concentrations), though it takes the depth kernel variant."""
    model, cam = random_scene(22, n=120), camera(width=W, height=H, f=12.0)
    lab, conf = frame_inputs(cam, 7)
    rng = np.random.default_rng(7)
    depth = rng.choice(np.array([np.nan, 0.0, -2.0, np.inf], dtype=np.float32), lab.shape)
    a = SemanticMap(model, C, backend="cuda")
    b = SemanticMap(model, C, backend="cuda")
    sa = a.update(cam, lab, conf, depth=depth)
    sb = b.update(cam, lab, conf)
    assert sa == sb and sa.occluded == 0 and sa.used > 0
    cpu = SemanticMap(model, C)
    cpu.update(cam, lab, conf, depth=depth)
    assert_same(a, cpu)
    np.testing.assert_allclose(a.concentrations, b.concentrations, rtol=1e-6, atol=0)
    want, counts, _ = world_reference(scene_pixels(model, cam), np.full((model.num_gaussians, C), PRIOR), lab, conf)
    assert counts_of(sa) == counts
    np.testing.assert_allclose(a.concentrations, want, rtol=KAPPA_RTOL, atol=KAPPA_ATOL)


def test_surprise_and_half_life_over_several_frames():
    """Four frames of moving cameras with an evidence half-life of 1.5 observations, transient classes and measured
    depth every other frame: after each frame the concentrations follow the float64 brute force applied frame after
    frame (only Gaussians that received evidence decay) and the numba map; each observed frame's surprise is
    1 - E^y under the map before it (NaN without a vote), brought by the view's one copy. The last frame is an
    update alone (the batched path's frame: its own increments buffer)."""
    model = random_scene(23, n=120)
    cams = [camera(width=W, height=H, f=12.0, position=(0.08 * i, -0.03 * i, 0.05 * i)) for i in range(4)]
    half_life = 1.5
    gpu, cpu = both(model, transient_classes=[2], evidence_half_life=half_life, depth_tolerance=TOL_ABS,
                    depth_tolerance_relative=TOL_REL)
    decay = 2.0 ** (-1.0 / half_life)
    want = np.full((model.num_gaussians, C), PRIOR)
    ops = gpu._backend.ops
    copies = []
    original = ops.download_words
    ops.download_words = lambda dev, n: (copies.append(n), original(dev, n))[1]
    untouched_seen = False
    for i, cam in enumerate(cams):
        pixels = scene_pixels(model, cam)
        lab, conf = frame_inputs(cam, 40 + i)
        depth = measured_depth(pixels, 1.0, 40 + i).reshape(cam.height, cam.width) if i % 2 else None
        before = want
        want, counts, surprise = world_reference(pixels, before, lab, conf, transient=(2,), depth=depth, decay=decay)
        if i == len(cams) - 1:
            assert counts_of(gpu.update(cam, lab, conf, depth=depth)) == counts
            cpu.update(cam, lab, conf, depth=depth)
            assert_same(gpu, cpu)
            np.testing.assert_allclose(gpu.concentrations, want, rtol=KAPPA_RTOL, atol=KAPPA_ATOL)
            break
        copies.clear()
        view = gpu.observe(cam, lab, conf, depth=depth, outputs=IMAGE_OUTPUTS)
        assert len(copies) == 1                          # counts and surprise came with the view
        assert_same(gpu, cpu, view, cpu.observe(cam, lab, conf, depth=depth, outputs=IMAGE_OUTPUTS))
        assert counts_of(gpu.last_update) == counts
        np.testing.assert_allclose(gpu.concentrations, want, rtol=KAPPA_RTOL, atol=KAPPA_ATOL, err_msg=f"frame {i}")
        got = view.surprise
        assert got.dtype == np.float32 and got.shape == lab.shape
        np.testing.assert_array_equal(np.isnan(got).ravel(), np.isnan(surprise))
        np.testing.assert_allclose(got.ravel(), surprise, atol=SURPRISE_ATOL, equal_nan=True)
        untouched_seen |= bool(np.any((want == before).all(axis=1) & (before != PRIOR).any(axis=1)))
    assert untouched_seen                                # a Gaussian without evidence kept its concentrations
    assert np.nanmax(surprise) - np.nanmin(surprise) > 0.3   # the map was sure of some labels by then


SENSOR = dict(bins=3, edges=(1.5, 4.5))


def test_sensor_model_with_depth_transient_surprise_and_half_life():
    """The sensor-model variant with every rule: the rendered depth of walk 1 gates the pixel (occluded) and picks
    the bin; front contributions are dropped in walk 2; the no-depth count holds only voted pixels."""
    rng = np.random.default_rng(5)
    edges = np.sort(rng.uniform(*SENSOR["edges"], SENSOR["bins"] + 1))
    sensor = SensorModel(tuple(f"c{i}" for i in range(C)), edges, rng.uniform(0.2, 1.0, (C, SENSOR["bins"])),
                         rng.dirichlet(np.full(C, 0.7), (C, SENSOR["bins"])))
    model, cam = random_scene(0, n=60, log_scale=(-3.0, -1.5)), camera(width=W, height=H, f=12.0)
    scale = 1.25
    gpu, cpu = both(model, sensor_model=sensor, depth_scale=scale, transient_classes=[3], evidence_half_life=2.0,
                    depth_tolerance=TOL_ABS, depth_tolerance_relative=TOL_REL)
    soft = sensor.soft_labels(scale)
    pixels = scene_pixels(model, cam)
    want = np.full((model.num_gaussians, C), PRIOR)
    for i in range(2):
        lab, conf = frame_inputs(cam, 60 + i)
        depth = measured_depth(pixels, scale, 60 + i).reshape(cam.height, cam.width)
        view = gpu.observe(cam, lab, conf, depth=depth, outputs=IMAGE_OUTPUTS)
        assert_same(gpu, cpu, view, cpu.observe(cam, lab, conf, depth=depth, outputs=IMAGE_OUTPUTS))
        want, counts, surprise = world_reference(pixels, want, lab, conf, transient=(3,), depth=depth, scale=scale,
                                                 decay=2.0 ** -0.5, soft=(soft.edges, soft.table))
        assert counts_of(gpu.last_update) == counts
        assert counts[3] > 0 and counts[4] > 0 and counts[5] > 0
        np.testing.assert_allclose(gpu.concentrations, want, rtol=KAPPA_RTOL, atol=KAPPA_ATOL)
        np.testing.assert_allclose(view.surprise.ravel(), surprise, atol=SURPRISE_ATOL, equal_nan=True)


def test_rules_keep_one_synchronisation_and_the_default_its_launches():
    """After the first frame of a size: an observe without the rules (and without the surprise) is the plain
    update's five launches; the surprise adds one (the moments before the update); with measured depth, transient
    classes, the surprise and a half-life it is seven (the increments applied too); always one copy to the host, and
    the uploads are the camera, the labels (and the depth)."""
    model, cam = random_scene(24, n=120), camera(width=W, height=H, f=12.0)
    pixels = scene_pixels(model, cam)
    lab, conf = frame_inputs(cam, 3)
    depth = measured_depth(pixels, 1.0, 3).reshape(cam.height, cam.width)
    plain = SemanticMap(model, C, backend="cuda")
    world = SemanticMap(model, C, backend="cuda", transient_classes=[0], evidence_half_life=3.0)
    for smap, frame, launches, uploads in ((plain, dict(outputs=("labels",)), 5, ["plan_camera", "labels"]),
                                           (plain, dict(outputs=("labels", "surprise")), 6, ["plan_camera", "labels"]),
                                           (world, dict(depth=depth, outputs=IMAGE_OUTPUTS), 7,
                                            ["plan_camera", "labels", "depth"])):
        backend, ops = smap._backend, smap._backend.ops
        smap.observe(cam, lab, None, **frame)             # binds the launches of this size
        syncs: list[str] = []
        sent: list[str] = []
        _count_outermost(ops, syncs)
        original = ops.host_to_device
        ops.host_to_device = lambda dev, host, name, _o=original, _s=sent: (_s.append(name), _o(dev, host, name))[1]
        count, bindings = backend.launches.count, backend.launches.bindings
        smap.observe(cam, lab, None, **frame)
        assert backend.launches.count - count == launches and backend.launches.bindings == bindings
        assert syncs == ["download_words"]
        assert sorted(sent) == sorted(uploads)


def _count_outermost(ops, calls):
    """Record the device -> host transfers and synchronisations of ``ops`` in ``calls`` (the outermost call only:
    the numpy ops' download_words calls download itself)."""
    depth = [0]

    def counted(name, original):
        def call(*args):
            if depth[0] == 0:
                calls.append(name)
            depth[0] += 1
            try:
                return original(*args)
            finally:
                depth[0] -= 1
        return call

    for name in ("download", "download_words", "scalars", "synchronize", "download_frame"):
        setattr(ops, name, counted(name, getattr(ops, name)))


def test_a_frame_beyond_the_plan_forgets_once():
    """A frame that overflows the single-view plan adds nothing and is done again: with a half-life the increments
    are applied once (the decay too), and the surprise is the retried frame's."""
    from css_ros.engine.cuda.view_plan import ViewPlan
    from css_ros.engine.spec import TILE_SIZE

    model, cam = random_scene(25, n=120), camera(width=W, height=H, f=12.0)
    pixels = scene_pixels(model, cam)
    lab, conf = frame_inputs(cam, 9)
    gpu, cpu = both(model, evidence_half_life=1.0)
    gpu.concentrations[...] = 0.5                        # evidence to forget
    cpu.concentrations[...] = 0.5
    backend = gpu._backend
    tx = -(-cam.width // TILE_SIZE)
    plan = ViewPlan(backend.ops, cam.width, cam.height, tx, tx * -(-cam.height // TILE_SIZE), 3, 400)
    backend._plans[(cam.width, cam.height)] = plan
    view = gpu.observe(cam, lab, conf, outputs=IMAGE_OUTPUTS)
    assert_same(gpu, cpu, view, cpu.observe(cam, lab, conf, outputs=IMAGE_OUTPUTS))
    assert plan.buffers.pairs > 3
    want, counts, surprise = world_reference(pixels, np.full((model.num_gaussians, C), 0.5), lab, conf, decay=0.5)
    assert counts_of(gpu.last_update) == counts
    np.testing.assert_allclose(gpu.concentrations, want, rtol=KAPPA_RTOL, atol=KAPPA_ATOL)
    np.testing.assert_allclose(view.surprise.ravel(), surprise, atol=SURPRISE_ATOL, equal_nan=True)
