"""The CUDA backend's kernels, run through the numba-cuda simulator, against the float64 brute-force
reference (test/css_reference.py) and the numba CPU path, on tiny scenes.

The simulator must be switched on before numba is imported, so these tests run in a subprocess
started by test/test_cuda_backend.py with NUMBA_ENABLE_CUDASIM=1 (on a machine with a GPU: on the device, with
CSS_CUDA_CHECKS=device); collected in a process without either (the ordinary pytest run) this module skips itself.
"""
from __future__ import annotations

import os

import numpy as np
import pytest

if os.environ.get("NUMBA_ENABLE_CUDASIM", "0") in ("", "0") and os.environ.get("CSS_CUDA_CHECKS") != "device":
    pytest.skip("CUDA checks run in a subprocess (test_cuda_backend.py::test_simulated_kernels: simulated, or on the "
                "GPU where there is one)", allow_module_level=True)
pytest.importorskip("numba.cuda", reason="numba-cuda is not installed (pip install -e '.[cuda]')")

import sys  # noqa: E402

from numba import cuda  # noqa: E402

# Each simulated GPU thread is a Python thread, and a barrier or warp exchange waits for 32-256 of them to be
# scheduled in turn: at the default 5 ms GIL switch interval that waiting, not the kernels' work, set the pace
# (a score_views of one 16 x 12 view took 89 s; 6 s at 0.5 ms).
sys.setswitchinterval(5e-4)

from css_ros import GaussianModel, SemanticMap  # noqa: E402
from css_ros.engine.cuda import kernels  # noqa: E402
from css_ros.engine.cuda.layout import HEADER_WORDS  # noqa: E402
from css_ros.engine.sh import eval_sh  # noqa: E402
from css_ros.engine.sensor_model import SensorModel  # noqa: E402
from css_reference import kappa_reference, project_reference, render_reference, update_reference  # noqa: E402
from scenes import camera, edge_case_scene, random_scene  # noqa: E402

C = 4
W, H = 16, 12
# The GPU pixel walk is float32 (alpha, transmittance, kappa * weight, the per-tile sums) and the map's
# running sums float64: kappa carries ~1e-6 relative error (float32 rounding over a few dozen
# compositing steps), so concentrations are compared with KAPPA_RTOL and a tiny absolute floor.
KAPPA_RTOL, KAPPA_ATOL = 2e-5, 1e-7
CAMS = [dict(width=W, height=H, f=12.0),
        dict(width=13, height=11, f=10.0, position=(0.3, -0.2, -0.5), quat=(0.05, -0.08, 0.02, 0.995)),
        dict(width=W, height=H, f=12.5, cx=3.0, cy=9.0)]


def reference(model, cam):
    return kappa_reference(model.means, model.scales, model.quats_wxyz, model.opacities,
                           cam.K, cam.T_map_cam, cam.width, cam.height)


def depth_reference(model, cam, kap):
    """Brute-force expected depth sum kappa z / sum kappa per pixel (H * W,), NaN without any contribution."""
    proj = project_reference(model.means, model.scales, model.quats_wxyz, model.opacities, cam.K, cam.T_map_cam,
                             cam.width, cam.height)
    z = np.array([0.0 if p is None else p[0] for p in proj])
    ks = kap.sum(axis=1)
    depth = np.full(ks.shape, np.nan)
    seen = ks > 0
    depth[seen] = (kap[seen] @ z) / ks[seen]
    return depth


def assert_depth(got, want, err_msg=""):
    """Same NaN pixels (no contribution), else equal within 1e-5 relative."""
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want), err_msg=err_msg)
    seen = ~np.isnan(want)
    np.testing.assert_allclose(got[seen], want[seen], rtol=1e-5, atol=0, err_msg=err_msg)


def labels_and_confidence(cam, seed):
    rng = np.random.default_rng(seed)
    lab = rng.integers(0, C, (cam.height, cam.width))
    lab[rng.random(lab.shape) < 0.15] = 255          # no label
    lab[rng.random(lab.shape) < 0.05] = C + 3        # out of range: ignored
    conf = rng.uniform(0.2, 1.0, lab.shape).astype(np.float32)
    return lab, conf


@pytest.mark.parametrize("case", range(len(CAMS)))
def test_update_matches_brute_force_and_numba(case):
    model = random_scene(case, n=120) if case != 2 else edge_case_scene()
    cam = camera(**CAMS[case])
    lab, conf = labels_and_confidence(cam, case)
    gpu = SemanticMap(model, C, backend="cuda")
    cpu = SemanticMap(model, C)
    stats = gpu.update(cam, lab, conf)
    assert stats == cpu.update(cam, lab, conf)
    kap, _ = reference(model, cam)
    ref = update_reference(kap, np.full((model.num_gaussians, C), 1e-3), lab, C, confidence=conf)
    assert kap.max() > 0.1 and np.abs(ref - 1e-3).max() > 0.5   # the scene is really seen
    np.testing.assert_allclose(gpu.concentrations, ref, rtol=KAPPA_RTOL, atol=KAPPA_ATOL)
    np.testing.assert_allclose(gpu.concentrations, cpu.concentrations, rtol=KAPPA_RTOL, atol=KAPPA_ATOL)
    # the paper estimate's counts (cost_model, from the CPU engine) are the GPU frame's own sizes
    from css_ros.engine.cuda.cost_model import frame_counts

    frame = gpu._backend.prepare(cam)
    counts = frame_counts(cpu._backend.geometry, [cam], C)
    assert (counts.kept, counts.keys) == (frame.num_pairs, int(frame.offsets[-1])) and counts.keys > 0


@pytest.mark.parametrize("case", range(len(CAMS)))
def test_render_matches_brute_force_and_numba(case):
    model = random_scene(10 + case, n=120) if case != 2 else edge_case_scene(1)
    cam = camera(**CAMS[case])
    rng = np.random.default_rng(case)
    alpha = rng.gamma(0.5, 2.0, (model.num_gaussians, C)) + 1e-3
    gpu = SemanticMap(model, C, backend="cuda", unknown_threshold=0.7, background_rgb=(0.2, 0.4, 0.6))
    cpu = SemanticMap(model, C, unknown_threshold=0.7, background_rgb=(0.2, 0.4, 0.6))
    gpu.concentrations[...] = alpha      # a host write must reach the device copy
    cpu.concentrations[...] = alpha
    a = gpu.render(cam, probabilities=True)
    b = cpu.render(cam, probabilities=True)
    kap, bg = reference(model, cam)
    E, V, lab, e_hat, v_hat, u_var, u_exp = render_reference(kap, bg, alpha, 1e-3)
    if case == 2:
        assert bg.min() < 1e-2   # the opaque sheets: early termination is exercised
    shape = (cam.height, cam.width)
    np.testing.assert_allclose(a.background, bg.reshape(shape), atol=1e-6)
    np.testing.assert_allclose(a.probabilities, E.reshape(*shape, C), atol=2e-6)
    np.testing.assert_allclose(a.expectation, e_hat.reshape(shape), atol=2e-6)
    np.testing.assert_allclose(a.variance, v_hat.reshape(shape), rtol=1e-5, atol=1e-9)
    want = np.where(bg.reshape(shape) > 0.7, 255, lab.reshape(shape))
    np.testing.assert_array_equal(a.labels, want)
    s_n = alpha.sum(axis=1)
    np.testing.assert_allclose(a.evidence, (kap @ s_n + bg * C * 1e-3).reshape(shape), rtol=1e-5, atol=1e-5)
    assert abs(a.u_var - u_var) <= 1e-5 * u_var and abs(a.u_exp - u_exp) < 1e-6
    for f in ("expectation", "variance", "background", "evidence", "probabilities"):
        np.testing.assert_allclose(getattr(a, f), getattr(b, f), rtol=1e-5, atol=1e-6, err_msg=f)
    assert_depth(a.depth, b.depth, "depth against numba")
    assert_depth(a.depth, depth_reference(model, cam, kap).reshape(shape), "depth against the reference")
    np.testing.assert_array_equal(a.labels, b.labels)
    assert np.abs(a.rgb.astype(int) - b.rgb).max() <= 1


def test_observe_sequence_and_host_coherence():
    """observe = update then render at the same pose; the host array follows the device state."""
    model = random_scene(3, n=120)
    cams = [camera(width=W, height=H, f=12.0, position=(0.1 * i, 0.0, 0.0)) for i in range(2)]
    gpu = SemanticMap(model, C, backend="cuda")
    cpu = SemanticMap(model, C)
    for i, cam in enumerate(cams):
        lab, conf = labels_and_confidence(cam, 20 + i)
        a = gpu.observe(cam, lab, conf)
        b = cpu.observe(cam, lab, conf)
        np.testing.assert_allclose(a.expectation, b.expectation, atol=1e-6)
        np.testing.assert_allclose(a.variance, b.variance, rtol=1e-5, atol=1e-9)
        np.testing.assert_array_equal(a.labels, b.labels)
    np.testing.assert_allclose(gpu.concentrations, cpu.concentrations, rtol=KAPPA_RTOL, atol=KAPPA_ATOL)
    gpu.reset()
    assert np.all(gpu.concentrations == 1e-3)
    fresh = SemanticMap(model, C, backend="cuda")
    np.testing.assert_allclose(gpu.render(cams[0]).expectation, fresh.render(cams[0]).expectation, atol=0)


def test_score_views_batched_matches_numba_and_render():
    model = random_scene(4, n=120)
    rng = np.random.default_rng(4)
    alpha = rng.gamma(0.5, 2.0, (model.num_gaussians, C)) + 1e-3
    views = [camera(width=W, height=H, f=12.0, position=(0.2 * i, -0.1 * i, 0.0)) for i in range(3)]
    views.insert(1, camera(width=8, height=8, f=7.0, quat=(0.0, 0.1, 0.0, 0.995)))   # another size
    views.append(camera(width=W, height=H, f=12.0, quat=(0.0, 1.0, 0.0, 0.0)))       # looks away: empty
    gpu = SemanticMap(model, C, backend="cuda")
    cpu = SemanticMap(model, C)
    gpu.concentrations[...] = alpha
    cpu.concentrations[...] = alpha
    got = gpu.score_views(views)
    want = cpu.score_views(views)
    assert got.shape == (len(views), 3) and np.all(np.isfinite(got))
    np.testing.assert_allclose(got[:, 2], want[:, 2], rtol=1e-4, atol=1e-9)     # the info gain, on the device
    assert got[4, 2] == 0.0 and np.all(got[:4, 2] > 0)
    got = got[:, :2]
    np.testing.assert_allclose(got, want[:, :2], rtol=1e-5, atol=1e-7)
    for i in (0, 1):
        r = gpu.render(views[i])
        np.testing.assert_allclose(got[i], [r.u_var, r.u_exp], rtol=1e-5, atol=1e-7)
    kap, bg = reference(model, views[2])
    _, _, _, _, _, u_var, u_exp = render_reference(kap, bg, alpha, 1e-3)
    np.testing.assert_allclose(got[2], [u_var, u_exp], rtol=1e-5, atol=1e-7)
    e_b = 1.0 / C
    assert got[4, 1] == pytest.approx(1.0 - e_b) and got[4, 0] == pytest.approx(e_b * (1 - e_b) / (1 + C * 1e-3))
    # score_images (the protocol method) gives the same images as render
    e, v, _ = list(gpu._backend.score_images(views[:2], gpu._concentrations, e_b, e_b * (1 - e_b) / (1 + C * 1e-3),
                                          C * 1e-3))[1]
    np.testing.assert_allclose(e, gpu.render(views[1]).expectation, atol=1e-7)


def test_view_dependent_colour_matches_reference():
    rng = np.random.default_rng(7)
    base = random_scene(7, n=100)
    sh = rng.normal(scale=0.4, size=(base.num_gaussians, 16, 3)).astype(np.float32)
    model = GaussianModel(means=base.means, sh=sh, opacity_logits=base.opacity_logits,
                          log_scales=base.log_scales, rotations=base.rotations)
    cam = camera(width=W, height=H, f=12.0, position=(0.2, 0.1, -0.3))
    buf = SemanticMap(model, 2, backend="cuda", background_rgb=(0.2, 0.4, 0.6))
    backend = buf._backend
    out = backend.render(backend.prepare(cam), np.ones((model.num_gaussians, 2)), 0.5, 0.0, 1.0,
                         np.array([0.2, 0.4, 0.6]), False)
    kap, bg = reference(model, cam)
    dirs = model.means.astype(np.float64) - cam.position
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    colours = np.maximum(eval_sh(sh.astype(np.float64), dirs) + 0.5, 0.0)
    ref = kap @ colours + bg[:, None] * np.array([0.2, 0.4, 0.6])
    # the device delivers uint8 colour (raw form: byte / 255): each byte is the rounding of a value within 1e-5 of
    # the float64 reference, i.e. within half a step (plus that tolerance) of ref * 255
    assert np.all(np.abs(out.rgb.reshape(-1, 3) * 255.0 - np.clip(ref, 0.0, 1.0) * 255.0) <= 0.5 + 255e-5)
    assert ref.max() > 0.05


def test_projection_capacity_grows_for_large_batches():
    """Kept (view, Gaussian) pairs are appended through an atomic counter into buffers sized from a
    guess; a batch that keeps more pairs than the guess must be projected again, not truncated."""
    model = random_scene(5, n=60, log_scale=(-2.0, -0.5))
    views = [camera(width=8, height=6, f=6.0, position=(0.01 * i, 0, 0)) for i in range(6)]
    gpu = SemanticMap(model, 2, backend="cuda")
    gpu._backend._capacity[6] = 5           # far too small
    frame = gpu._backend.prepare_views(views, want_color=False)
    assert frame.num_pairs > 5 * 6
    np.testing.assert_allclose(gpu.score_views(views)[:, :2], SemanticMap(model, 2).score_views(views)[:, :2],
                               rtol=1e-5)


def test_broken_kernel_stack_is_one_line_css_error(monkeypatch):
    """A CUDA stack that fails at the first launch (as numba-cuda 0.30 with numpy 2.5 did:
    AttributeError row_stack) is reported when the map is created, as one CssError naming the fix."""
    from css_ros.engine.cuda import kernels
    from css_ros.errors import CssError

    class Broken:
        def __getitem__(self, launch):
            def run(*args):
                raise AttributeError("module 'numpy' has no attribute 'row_stack'")
            return run

    monkeypatch.setattr(kernels, "moments_kernel", Broken())
    with pytest.raises(CssError) as err:
        SemanticMap(random_scene(0, n=10), 2, backend="cuda")
    msg = str(err.value)
    assert "\n" not in msg and "row_stack" in msg and "numpy<2.4" in msg and "backend 'numba'" in msg


@pytest.mark.parametrize("chunk", [3])
def test_render_in_class_passes_matches_brute_force(monkeypatch, chunk):
    """More classes than one pass holds (RENDER_CLASS_CHUNK, 40 on a GPU) walk the tile lists once per
    pass; labels (first maximum across passes), E, Var, probabilities and the view scores equal the
    reference whether the 7 classes take 3 passes (3 + 3 + 1) or one."""
    from css_ros.engine.cuda import kernels

    monkeypatch.setattr(kernels, "RENDER_CLASS_CHUNK", chunk)
    n_cls = 7
    model = edge_case_scene(1)
    cam = camera(**CAMS[2])
    rng = np.random.default_rng(3)
    alpha = rng.gamma(0.5, 2.0, (model.num_gaussians, n_cls)) + 1e-3
    gpu = SemanticMap(model, n_cls, backend="cuda", unknown_threshold=1.0)
    gpu.concentrations[...] = alpha
    a = gpu.render(cam, probabilities=True)
    kap, bg = reference(model, cam)
    E, V, lab, e_hat, v_hat, u_var, u_exp = render_reference(kap, bg, alpha, 1e-3)
    shape = (cam.height, cam.width)
    np.testing.assert_allclose(a.probabilities, E.reshape(*shape, n_cls), atol=2e-6)
    np.testing.assert_allclose(a.expectation, e_hat.reshape(shape), atol=2e-6)
    assert_depth(a.depth, depth_reference(model, cam, kap).reshape(shape))   # summed in the first pass only
    top2 = np.sort(E, axis=1)[:, -2:]
    decided = (top2[:, 1] - top2[:, 0] > 1e-5) | (top2[:, 1] == top2[:, 0])   # float32 sums: no near-ties
    assert decided.mean() > 0.9
    np.testing.assert_array_equal(a.labels.reshape(-1)[decided], lab[decided])
    np.testing.assert_allclose(a.variance.reshape(-1)[decided], v_hat[decided], rtol=1e-5, atol=1e-9)
    assert np.any(lab[decided] < 3) and np.any(lab[decided] >= 3)   # winners from more than one pass
    np.testing.assert_allclose(gpu.score_views([cam])[0, :2], [u_var, u_exp], rtol=1e-5, atol=1e-7)


def test_read_access_does_not_reupload_the_map():
    """concentrations_readonly downloads once after an update and leaves the device copy valid (no
    re-upload of the whole map); it cannot be written; writes go through ``concentrations``."""
    model = random_scene(0, n=60)
    cam = camera(**CAMS[0])
    lab, conf = labels_and_confidence(cam, 0)
    gpu = SemanticMap(model, C, backend="cuda")
    cpu = SemanticMap(model, C)
    gpu.update(cam, lab, conf)
    cpu.update(cam, lab, conf)
    backend = gpu._backend
    uploads = []
    original = backend.ops.copy_into
    backend.ops.copy_into = lambda dst, host: (uploads.append(host.shape), original(dst, host))[1]
    view = gpu.concentrations_readonly
    np.testing.assert_allclose(view, cpu.concentrations, rtol=KAPPA_RTOL, atol=KAPPA_ATOL)
    with pytest.raises(ValueError):
        view[0, 0] = 1.0
    gpu.update(cam, lab, conf)                 # the device copy is still the valid one
    cpu.update(cam, lab, conf)
    assert uploads == []
    np.testing.assert_allclose(gpu.concentrations_readonly, cpu.concentrations, rtol=KAPPA_RTOL, atol=KAPPA_ATOL)
    gpu.concentrations[0, :] = 7.0             # write access: uploaded before the next kernel
    gpu.update(cam, lab, conf)
    assert uploads == [(model.num_gaussians, C)]
    assert gpu.concentrations_readonly[0, 0] >= 7.0


def random_sensor_model(num_classes, num_bins, lo, hi, seed):
    """Random weights in [0.2, 1], a random row-stochastic confusion, bin edges inside (lo, hi) metres (depths
    below the first edge use bin 0, beyond the last bin B - 1)."""
    rng = np.random.default_rng(seed)
    edges = np.sort(rng.uniform(lo, hi, num_bins + 1))
    return SensorModel(tuple(f"c{i}" for i in range(num_classes)), edges,
                       rng.uniform(0.2, 1.0, (num_classes, num_bins)),
                       rng.dirichlet(np.full(num_classes, 0.7), (num_classes, num_bins)))


SENSOR_CASES = [
    # sparse scene: pixels without any Gaussian (NaN depth, no-depth count), 3 bins
    dict(scene=lambda: random_scene(0, n=60, log_scale=(-3.0, -1.5)), cam=0, classes=4, bins=3, edges=(1.5, 4.5),
         clipped="beyond"),
    # opaque sheets (early termination), borders, behind the camera; 4 bins
    dict(scene=lambda: edge_case_scene(), cam=2, classes=4, bins=4, edges=(1.6, 4.0), clipped="below"),
    # C B = 80 > 64 (at most 64 row slots per tile, fewer Gaussians staged per batch), an odd image size
    dict(scene=lambda: random_scene(1, n=120), cam=1, classes=20, bins=4, edges=(1.0, 5.0), clipped="beyond"),
]


@pytest.mark.parametrize("case", range(len(SENSOR_CASES)))
def test_sensor_model_update_matches_numba_and_reference(case):
    """The sensor-model update variant (expected depth from a first walk, then the voting walk by (label, depth
    bin) rows, the table applied per tile) against the numba path and the float64 brute force; the render's depth
    of the same observe; the no-depth counts."""
    spec = SENSOR_CASES[case]
    model, cam, n_cls = spec["scene"](), camera(**CAMS[spec["cam"]]), spec["classes"]
    sensor = random_sensor_model(n_cls, spec["bins"], *spec["edges"], seed=case)
    rng = np.random.default_rng(30 + case)
    lab = rng.integers(0, n_cls, (cam.height, cam.width))
    lab[rng.random(lab.shape) < 0.15] = 255
    conf = rng.uniform(0.2, 1.0, lab.shape).astype(np.float32)
    conf[rng.random(lab.shape) < 0.05] = 0.0
    gpu = SemanticMap(model, n_cls, backend="cuda", sensor_model=sensor)
    cpu = SemanticMap(model, n_cls, sensor_model=sensor)
    stats = gpu.update(cam, lab, conf)
    assert stats == cpu.update(cam, lab, conf)           # used, ignored, out of range, no depth
    np.testing.assert_allclose(gpu.concentrations, cpu.concentrations, rtol=KAPPA_RTOL, atol=KAPPA_ATOL)
    assert_depth(gpu.render(cam).depth, cpu.render(cam).depth)
    # float64 brute force: bin of each labelled pixel's expected depth, its row of the table
    kap, _ = reference(model, cam)
    depth = depth_reference(model, cam, kap)
    soft = sensor.soft_labels()
    used = (lab.ravel() < n_cls) & (conf.ravel() > 0)
    seen = used & ~np.isnan(depth)
    bins = np.clip(np.searchsorted(soft.edges, np.nan_to_num(depth), side="right") - 1, 0, spec["bins"] - 1)
    y = np.zeros((lab.size, n_cls))
    y[seen] = conf.ravel()[seen, None] * soft.table[lab.ravel()[seen] * spec["bins"] + bins[seen]]
    ref = 1e-3 + kap.T @ y
    np.testing.assert_allclose(gpu.concentrations, ref, rtol=KAPPA_RTOL, atol=KAPPA_ATOL)
    assert stats.no_depth == np.count_nonzero(used & np.isnan(depth))
    assert len(np.unique(bins[seen])) >= 2 and np.abs(ref - 1e-3).max() > 0.3   # bins and votes really differ
    if spec["clipped"] == "below":   # depths before the first edge use bin 0, beyond the last bin B - 1
        assert np.any(depth[seen] < soft.edges[0])
    else:
        assert np.any(depth[seen] >= soft.edges[-1])
    if case == 0:
        assert stats.no_depth > 0
        # nothing in view: every used pixel is without depth, nothing is added
        away = camera(**dict(CAMS[0], quat=(0.0, 1.0, 0.0, 0.0)))
        before = gpu.concentrations.copy()
        stats = gpu.update(away, lab, conf)
        assert stats.no_depth == stats.used == cpu.update(away, lab, conf).no_depth > 0
        np.testing.assert_array_equal(gpu.concentrations, before)


def test_final_outputs_with_a_confidence_map_match_numba():
    """The device's final form (thresholded labels, float32 planes, uint8 colour, depth in metres, the calibrated
    confidence, U reduced on the device) against the numba path on the same map, with a sensor model and a
    confidence map; a subset of outputs; views that stay valid after later frames."""
    from css_ros.engine.sensor_model import ConfidenceMap

    model = random_scene(5, n=120)
    cam = camera(**CAMS[1])
    sensor = random_sensor_model(C, 2, 1.0, 4.0, seed=9)
    sensor = SensorModel(sensor.class_names, sensor.depth_edges, sensor.weight, sensor.confusion,
                         ConfidenceMap(np.array([1.4, 0.5, -0.8]), np.array([0.0, 0.35, 0.7, 1.0]),
                                       np.array([0.02, 0.3, 0.8, 0.98])))
    kw = dict(sensor_model=sensor, unknown_threshold=0.6, depth_scale=2.5, background_rgb=(0.1, 0.2, 0.3))
    gpu, cpu = SemanticMap(model, C, backend="cuda", **kw), SemanticMap(model, C, **kw)
    lab, conf = labels_and_confidence(cam, 5)
    a, b = gpu.observe(cam, lab, conf), cpu.observe(cam, lab, conf)
    assert 0 < np.count_nonzero(b.labels == 255) < b.labels.size             # the threshold is exercised
    np.testing.assert_array_equal(a.labels, b.labels)
    assert a.labels.dtype == np.int32 and a.rgb.dtype == np.uint8 and a.confidence.dtype == np.float32
    for f in ("expectation", "variance", "background", "evidence"):
        assert getattr(a, f).dtype == np.float32
        np.testing.assert_allclose(getattr(a, f), getattr(b, f), rtol=1e-5, atol=1e-6, err_msg=f)
    assert_depth(a.depth, b.depth)
    assert np.nanmax(a.depth) > 1.0                                           # metres: depth_scale applied
    np.testing.assert_allclose(a.confidence, b.confidence, atol=2e-5)
    assert np.all(a.confidence[a.labels == 255] == 0) and a.confidence.max() > 0.1
    assert np.abs(a.rgb.astype(int) - b.rgb).max() <= 1
    assert a.u_var == pytest.approx(b.u_var, rel=1e-5) and a.u_exp == pytest.approx(b.u_exp, rel=1e-6)
    part = gpu.render(cam, outputs=("confidence",), probabilities=True)
    assert part.labels is None and part.rgb is None and part.expectation is None
    np.testing.assert_array_equal(part.confidence, a.confidence)
    np.testing.assert_allclose(part.probabilities, cpu.render(cam, probabilities=True).probabilities, atol=2e-6)
    kept = a.expectation.copy()
    gpu.observe(cam, np.zeros_like(lab))                                      # reuses the device buffer
    np.testing.assert_array_equal(a.expectation, kept)
    assert not np.array_equal(gpu.render(cam).expectation, kept)


def test_one_copy_of_only_the_requested_bytes():
    """A frame copies its outputs to the host once, and only the requested planes (plus the header: U sums, the
    update's counts, the frame's sizes)."""
    model = random_scene(6, n=80)
    cam = camera(**CAMS[0])
    gpu = SemanticMap(model, C, backend="cuda")
    ops = gpu._backend.ops
    copies = []
    original = ops.download_words
    ops.download_words = lambda dev, n: (copies.append(4 * n), original(dev, n))[1]
    gpu.render(cam, outputs=("labels", "rgb"))
    hw = cam.width * cam.height
    header = 4 * HEADER_WORDS
    assert header == 64
    assert copies == [header + 4 * hw + -(-3 * hw // 4) * 4]
    copies.clear()
    gpu.observe(cam, np.zeros((cam.height, cam.width), dtype=np.int64), outputs=())
    assert copies == [header]


def _reference_votes(labels, conf, ignore_label):
    """The label rule written out pixel by pixel in float64 (independent of label_input): (classes, weights, counts)."""
    cls = np.full(labels.shape, -1, dtype=np.int64)
    wts = np.zeros(labels.shape)
    counts = [0, 0, 0]
    for idx, raw in np.ndenumerate(labels):
        value = int(raw)
        if value == ignore_label:
            counts[1] += 1
        elif not 0 <= value < C:
            counts[2] += 1
        else:
            c = 1.0 if conf is None else float(conf[idx])
            w = 0.0 if np.isnan(c) else min(max(c, 0.0), 1.0)
            w = float(np.float32(w))
            if w > 0:
                cls[idx], wts[idx] = value, w
                counts[0] += 1
            else:
                counts[1] += 1
    return cls, wts, counts


@pytest.mark.parametrize("dtype,conf_dtype,ignore", [(np.uint8, None, 255), (np.uint16, np.float32, 65535),
                                                     (np.int32, np.float64, -1), (np.int64, np.float32, 255)])
def test_labels_and_confidence_as_they_come(dtype, conf_dtype, ignore):
    """The update kernel reads the labels in their own dtype and the confidence in its own (no int64 copy, no plane
    of ones): ignore value, ids >= C, negative ids, NaN / negative / > 1 / inf confidences follow the label rule,
    and the counts (made on the device) and the concentrations equal a pixel-by-pixel reference and the numba path."""
    model = random_scene(8, n=120)
    cam = camera(**CAMS[0])
    rng = np.random.default_rng(5)
    values = [0, 1, 2, 3, C, C + 7, ignore] + ([-3] if np.issubdtype(dtype, np.signedinteger) else [])
    lab = rng.choice(values, (cam.height, cam.width)).astype(dtype)
    conf = None
    if conf_dtype is not None:
        conf = rng.choice([0.5, 1.0, 2.0, 0.0, -1.0, np.nan, np.inf, 0.25], lab.shape).astype(conf_dtype)
    uploads = []
    gpu = SemanticMap(model, C, backend="cuda", ignore_label=ignore)
    ops = gpu._backend.ops
    original = ops.host_to_device
    ops.host_to_device = lambda dev, host, name: (uploads.append((name, host.dtype)), original(dev, host, name))[1]
    cpu = SemanticMap(model, C, ignore_label=ignore)
    view = gpu.observe(cam, lab, conf)
    stats = gpu.last_update
    cpu.observe(cam, lab, conf)
    cls, wts, counts = _reference_votes(lab, conf, ignore)
    assert (stats.used, stats.ignored, stats.out_of_range) == tuple(counts) and counts[0] > 0 and counts[2] > 0
    assert stats == cpu.last_update
    assert ("labels", np.dtype(dtype)) in uploads
    assert [n for n, _ in uploads if n == "confidence"] == ([] if conf is None else ["confidence"])
    if conf is not None:
        assert ("confidence", np.dtype(conf_dtype)) in uploads
    kap, _ = reference(model, cam)
    ref = update_reference(kap, np.full((model.num_gaussians, C), 1e-3), np.where(cls < 0, 255, cls), C,
                           confidence=wts)
    np.testing.assert_allclose(gpu.concentrations, ref, rtol=KAPPA_RTOL, atol=KAPPA_ATOL)
    np.testing.assert_allclose(gpu.concentrations, cpu.concentrations, rtol=KAPPA_RTOL, atol=KAPPA_ATOL)
    assert view.labels.shape == lab.shape


def test_observe_and_query_make_one_synchronisation_and_bind_launches_once():
    """After the first frame of a size, an observe and a query render each make exactly one device -> host copy (the
    view's, which also brings the update's counts and the frame's sizes) and no other download, and launch only
    launches bound at the first frame: project, emit keys, update, moments, render for an observe of every image but
    the surprise (which adds the moments before the update: test_cuda_change_rules.py)."""
    from css_ros.engine.final_form import IMAGE_OUTPUTS

    outputs = tuple(n for n in IMAGE_OUTPUTS if n != "surprise")
    model = random_scene(9, n=120)
    gpu = SemanticMap(model, C, backend="cuda")
    backend, ops = gpu._backend, gpu._backend.ops
    cams = [camera(width=W, height=H, f=12.0, position=(0.05 * i, 0.0, 0.0)) for i in range(3)]
    lab, conf = labels_and_confidence(cams[0], 30)
    gpu.observe(cams[0], lab, conf, outputs=outputs)          # binds the launches of this size
    gpu.render(cams[0])
    calls: list[str] = []
    depth = [0]   # the numpy ops' download_words calls download itself: count the outermost transfers only

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
    bindings, launches = backend.launches.bindings, backend.launches.count
    for cam in cams[1:]:
        calls.clear()
        gpu.observe(cam, lab, conf, outputs=outputs)
        assert calls == ["download_words"]
        assert backend.launches.count - launches == 5
        launches = backend.launches.count
        calls.clear()
        gpu.render(cam)
        assert calls == ["download_words"]
        assert backend.launches.count - launches == 4
        launches = backend.launches.count
    assert backend.launches.bindings == bindings


def test_a_frame_beyond_the_plan_is_done_again_once():
    """A single-view plan whose buffers are too small for the frame: the update adds nothing on the device, the
    view's copy says so, the plan grows and the frame is done again: the map receives the frame exactly once and the
    result equals the numba path's (also when the keys, not the pairs, overflow)."""
    from css_ros.engine.cuda.view_plan import ViewPlan

    model = random_scene(12, n=120)
    cam = camera(**CAMS[0])
    lab, conf = labels_and_confidence(cam, 40)
    for pairs, keys in ((3, 400), (400, 5)):
        gpu = SemanticMap(model, C, backend="cuda")
        backend = gpu._backend
        plan = ViewPlan(backend.ops, cam.width, cam.height, *_tiles(cam), pairs, keys)
        backend._plans[(cam.width, cam.height)] = plan
        cpu = SemanticMap(model, C)
        a = gpu.observe(cam, lab, conf)
        b = cpu.observe(cam, lab, conf)
        assert plan.buffers.pairs > pairs or plan.buffers.keys > keys
        assert gpu.last_update == cpu.last_update and gpu.frames_observed == 1
        np.testing.assert_allclose(gpu.concentrations, cpu.concentrations, rtol=KAPPA_RTOL, atol=KAPPA_ATOL)
        np.testing.assert_array_equal(a.labels, b.labels)
        np.testing.assert_allclose(a.expectation, b.expectation, atol=2e-6)


def _tiles(cam):
    from css_ros.engine.spec import TILE_SIZE

    tx = -(-cam.width // TILE_SIZE)
    return tx, tx * -(-cam.height // TILE_SIZE)


def test_info_gain_and_greedy_batch_match_numba_with_a_sensor_model():
    """score_views' info gain (evidence mass by a second walk, the closed form per pair) and select_views on the
    device against the numba path, with a sensor model (per-bin net vote weights), importance and pixel_scale;
    view_masses against numba's per-view masses."""
    model = random_scene(8, n=150)
    sensor = random_sensor_model(C, 3, 1.0, 4.0, seed=4)
    gpu = SemanticMap(model, C, backend="cuda", sensor_model=sensor)
    cpu = SemanticMap(model, C, sensor_model=sensor)
    rng = np.random.default_rng(8)
    alpha = rng.gamma(0.5, 2.0, (model.num_gaussians, C)) + 1e-3
    gpu.concentrations[...] = alpha
    cpu.concentrations[...] = alpha
    views = [camera(width=W, height=H, f=12.0, position=(0.15 * i, 0.05 * i, 0.0)) for i in range(4)]
    views.insert(2, camera(width=10, height=8, f=8.0, quat=(0.0, 0.1, 0.0, 0.995)))
    imp = rng.uniform(0.0, 2.0, model.num_gaussians)
    got, want = gpu.score_views(views, imp, pixel_scale=4.0), cpu.score_views(views, imp, pixel_scale=4.0)
    assert np.all(want[:, 2] > 0)
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-9)
    a, b = gpu.select_views(views, 4, imp, 4.0), cpu.select_views(views, 4, imp, 4.0)
    np.testing.assert_array_equal(a.indices, b.indices)
    np.testing.assert_allclose(a.gains, b.gains, rtol=1e-4)
    args = (views, gpu._concentrations, *gpu._background_moments(), gpu._mass_weights())
    for (ids_g, m_g), (ids_c, m_c) in zip(gpu._backend.view_masses(*args),
                                          cpu._backend.view_masses(views, cpu._concentrations,
                                                                   *cpu._background_moments(), cpu._mass_weights())):
        order = np.argsort(ids_c, kind="stable")
        np.testing.assert_array_equal(ids_g, ids_c[order])
        np.testing.assert_allclose(m_g, m_c[order], rtol=1e-4, atol=1e-7)
    np.testing.assert_allclose(gpu.task_importance(views[:2]), cpu.task_importance(views[:2]), rtol=1e-4, atol=1e-7)


@cuda.jit
def _precull_flags(cam_row, means, max_std, width, height, out):  # pragma: no cover
    """out[i] = the projection's float32 pre-test for Gaussian i."""
    i = cuda.grid(1)
    if i < out.shape[0]:
        out[i] = kernels._surely_culled(cam_row, means, i, max_std[i], width, height)


def test_float32_precull_keeps_exactly_the_cpu_pairs():
    """The projection's float32 pre-test culls only pairs the float64 EWA path culls: on a scene spread in front,
    behind, at the near plane, around the image borders and far from the origin, the kept pairs equal the numba
    projection's, and the pre-test does cull most of the pairs that are out of view."""
    from css_ros.engine.cpu.projection import GaussianGeometry, project
    from css_ros.engine.splat_math import camera_row

    rng = np.random.default_rng(11)
    n = 400
    z = rng.uniform(1.0, 4.0, 50)
    side = rng.choice([-1.0, 1.0], 50)
    means = np.concatenate([rng.uniform([-3, -3, -1], [3, 3, 6], (n - 200, 3)),          # all around the view
                            rng.uniform([-0.02, -0.02, 0.0], [0.02, 0.02, 0.03], (50, 3)),  # at the near plane
                            rng.uniform([-40, -40, 5], [40, 40, 60], (50, 3)),             # far, large coordinates
                            rng.uniform([-3, -3, -5], [3, 3, -1], (50, 3)),                # surely behind
                            np.stack([side * z * rng.uniform(5, 8, 50), rng.uniform(-1, 1, 50), z], axis=1)])
    base = random_scene(11, n=n)
    model = GaussianModel(means=means.astype(np.float32), sh=base.sh, opacity_logits=base.opacity_logits,
                          log_scales=base.log_scales, rotations=base.rotations)
    for cam in (camera(width=W, height=H, f=12.0), camera(width=W, height=H, f=12.0, position=(500.0, -300.0, 2.0))):
        if cam.position[0] > 100:   # the same scene seen from far from the origin
            model = GaussianModel(means=(means + cam.position).astype(np.float32), sh=base.sh,
                                  opacity_logits=base.opacity_logits, log_scales=base.log_scales,
                                  rotations=base.rotations)
        gpu = SemanticMap(model, C, backend="cuda")
        frame = gpu._backend.prepare(cam)
        kept = np.sort(gpu._backend.ops.download(frame.ids)[:frame.num_pairs])  # a device array on a GPU
        cpu_ids = np.sort(project(GaussianGeometry.from_model(model), cam).ids)
        np.testing.assert_array_equal(kept, cpu_ids)

        culled = np.zeros(model.num_gaussians, dtype=np.bool_)
        ms = np.asarray(model.scales, dtype=np.float64).max(axis=1)
        _precull_flags[(model.num_gaussians + 31) // 32, 32](camera_row(cam), np.asarray(model.means, dtype=np.float64), ms,
                                                   float(cam.width), float(cam.height), culled)
        assert not np.any(culled[cpu_ids])                         # never a pair the float64 path keeps
        assert np.all(culled[n - 100:n - 50])     # behind the camera
        if cam.position[0] < 100:                 # 5-8 x the image's half width beside it (near the origin: far
            assert np.all(culled[n - 50:])        # from it float32 cannot place z to 0.1 %, the float64 path decides)


@cuda.jit
def _both_warp_sums(x, fast, shuffles):  # pragma: no cover
    i = cuda.grid(1)
    fast[i] = kernels.warp_sum(x[i])
    shuffles[i] = kernels.warp_sum_shuffles(x[i])


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_one_exchange_warp_sum_equals_the_five_shuffles(dtype):
    """The simulator's one-exchange warp_sum gives every lane the bit-identical sum of the five-shuffle butterfly
    the GPU runs, which itself is the float sum of the warp's 32 values (to rounding)."""
    x = (np.random.default_rng(3).standard_normal(64) * 100.0).astype(dtype)
    fast, shuffles = np.zeros_like(x), np.zeros_like(x)
    _both_warp_sums[1, 64](x, fast, shuffles)
    np.testing.assert_array_equal(fast, shuffles)
    for w in range(2):
        assert np.all(fast[32 * w:32 * w + 32] == fast[32 * w])
        np.testing.assert_allclose(fast[32 * w], x[32 * w:32 * w + 32].astype(np.float64).sum(),
                                   rtol=1e-6 if dtype == np.float32 else 1e-14)


def test_stub_device_counts_the_host_work_of_a_frame():
    """benchmarks/cuda_host.py's stub device runs the backend's Python as on a GPU with no kernel: an observe of the
    default images (no surprise) is 5 launches (project, emit keys, update, moments, render), a query render 4, one
    synchronisation each, no launch bound again after the warm-up, and the host time is measured (> 0)."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "cuda_host.py"
    spec = importlib.util.spec_from_file_location("cuda_host", path)
    cuda_host = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(cuda_host)
    model = random_scene(13, n=200)
    cams = [camera(width=W, height=H, f=12.0, position=(0.05 * i, 0.0, 0.0)) for i in range(3)]
    labels = [np.random.default_rng(i).integers(0, C, (H, W)).astype(np.uint8) for i in range(3)]
    r = cuda_host.measure(model, cams, labels, C, frames=5)
    assert r["launches_per_observe"] == 5 and r["launches_per_query"] == 4
    assert r["syncs_per_observe"] == 1 and r["syncs_per_query"] == 1
    assert r["new_bindings"] == 0 and r["uploads_per_observe"] == 2   # the camera row and the labels
    assert 0 < r["observe_ms"] < 1e3 and 0 < r["query_ms"] < 1e3


def test_scoring_in_batches_of_bounded_pairs_equals_one_batch(monkeypatch):
    """score_views and select_views cut many candidates into batches of at most SCORE_BATCH_PAIRS pairs (bounded GPU
    memory): with a bound of two views' pairs the columns and the picks equal those of one batch."""
    from css_ros.engine.cuda import backend as cuda_backend
    from css_ros.engine.cuda.view_plan import HEADROOM

    model = random_scene(14, n=100)
    rng = np.random.default_rng(14)
    alpha = rng.gamma(0.5, 2.0, (model.num_gaussians, C)) + 1e-3
    views = [camera(width=8, height=6, f=6.0, position=(0.15 * i, -0.05 * i, 0.0)) for i in range(4)]
    gpu = SemanticMap(model, C, backend="cuda")
    gpu.concentrations[...] = alpha
    whole = gpu.score_views(views)                              # one batch (the bound is far away)
    picks = gpu.select_views(views, 3)
    per_view = gpu._backend._pairs_per_view[(8, 6)]
    monkeypatch.setattr(cuda_backend, "SCORE_BATCH_PAIRS", int(2.5 * HEADROOM * per_view))
    chunks = gpu._backend._score_chunks(list(range(4)), 8, 6)
    assert len(chunks) == 2 and sorted(sum(chunks, [])) == list(range(4))
    np.testing.assert_allclose(gpu.score_views(views), whole, rtol=1e-12)
    again = gpu.select_views(views, 3)
    np.testing.assert_array_equal(again.indices, picks.indices)
    np.testing.assert_allclose(again.gains, picks.gains, rtol=1e-12)


def test_scoring_holds_one_batch_at_a_time(monkeypatch):
    """A scoring batch's frame (its projection rows, sorts and tile keys: most of a scoring's GPU memory) is gone
    before the next batch's is made, in score_views, select_views and view_masses (task_importance): the peak
    holds one batch, not two."""
    import gc
    import weakref

    from css_ros.engine.cuda import backend as cuda_backend
    from css_ros.engine.cuda.view_plan import HEADROOM

    model = random_scene(15, n=100)
    views = [camera(width=8, height=6, f=6.0, position=(0.1 * i, -0.05 * i, 0.0)) for i in range(6)]
    gpu = SemanticMap(model, C, backend="cuda")
    gpu.score_views(views)                                      # measures the pairs per view of this size
    backend = gpu._backend
    monkeypatch.setattr(cuda_backend, "SCORE_BATCH_PAIRS", int(2.5 * HEADROOM * backend._pairs_per_view[(8, 6)]))
    assert len(backend._score_chunks(list(range(6)), 8, 6)) == 3
    made: list[weakref.ref] = []
    alive_at_new: list[int] = []
    prepare = backend.prepare_views

    def recording(cameras, *args, **kwargs):
        if len(cameras) > 1 or made:
            gc.collect()
            alive_at_new.append(sum(ref() is not None for ref in made))
        frame = prepare(cameras, *args, **kwargs)
        made.append(weakref.ref(frame))
        return frame

    monkeypatch.setattr(backend, "prepare_views", recording)
    for call in (lambda: gpu.score_views(views), lambda: gpu.select_views(views, 2),
                 lambda: gpu.task_importance(views)):
        made.clear()
        alive_at_new.clear()
        call()
        assert len(made) == 3 and alive_at_new == [0, 0, 0], alive_at_new
