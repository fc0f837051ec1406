"""The CUDA backend in an ordinary test run (no GPU needed).

- test_simulated_kernels runs test/test_cuda_sim.py in a subprocess with NUMBA_ENABLE_CUDASIM=1
  (the simulator must be chosen before numba is imported; this process has numba CPU kernels loaded); on a machine
  with a GPU it runs the same checks on the device. test_simulated_change_rules does the same for
  test/test_cuda_change_rules.py.
- Without a GPU and without the simulator, asking for backend "cuda" is a clear CssError.
- On a machine with a GPU, the same comparison with the numba path runs on the device.
"""
from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from css_ros import SemanticMap
from css_ros.errors import CssError

ROOT = Path(__file__).resolve().parents[1]
HAS_NUMBA_CUDA = importlib.util.find_spec("numba_cuda") is not None
#: The GPU walk is float32 (docs/cuda.md "What is tested"): concentrations agree with the float64 CPU walk to ~1e-5
#: relative (9e-6 measured on an H200), a few Gaussians at the alpha = 1/255 cut-off by more.
KAPPA_RTOL = 5e-5
BIKER_PLY = Path(os.environ.get("CSS_BIKER_PLY", "/work/shared/data/real-ply/biker.ply"))
needs_numba_cuda = pytest.mark.skipif(not HAS_NUMBA_CUDA, reason="numba-cuda is not installed (pip install -e '.[cuda]')")


def _env(sim: bool) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(ROOT / "test"), env.get("PYTHONPATH", "")])
    env["NUMBA_ENABLE_CUDASIM"] = "1" if sim else "0"
    return env


@needs_numba_cuda
def test_simulated_kernels():
    """Every check of test_cuda_sim.py (brute-force reference and numba path) under the simulator; on a machine with
    a GPU the same checks on the device (the simulator's pace is the CPU's, not the hardware's: minutes)."""
    env = _env(not GPU)
    if GPU:
        env["CSS_CUDA_CHECKS"] = "device"
    out = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                          str(ROOT / "test" / "test_cuda_sim.py")],
                         env=env, cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stdout[-6000:] + out.stderr[-3000:]
    assert " passed" in out.stdout and "skipped" not in out.stdout.splitlines()[-1], out.stdout[-2000:]


@needs_numba_cuda
def test_simulated_change_rules():
    """The changing world's rules of test_cuda_change_rules.py (float64 brute force) under the simulator, or on the
    GPU where there is one."""
    env = _env(not GPU)
    if GPU:
        env["CSS_CUDA_CHECKS"] = "device"
    out = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                          str(ROOT / "test" / "test_cuda_change_rules.py")],
                         env=env, cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stdout[-6000:] + out.stderr[-3000:]
    assert " passed" in out.stdout and "skipped" not in out.stdout.splitlines()[-1], out.stdout[-2000:]


def test_cuda_backend_is_lazy():
    """Choosing another backend never imports numba.cuda (the CPU install stays light)."""
    code = ("import sys; from css_ros import SemanticMap; from scenes import random_scene; "
            "SemanticMap(random_scene(0, n=10), 2); "
            "assert 'numba.cuda' not in sys.modules and 'css_ros.engine.cuda.backend' not in sys.modules")
    out = subprocess.run([sys.executable, "-c", code], env=_env(False), cwd=ROOT, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr[-3000:]


def _gpu_available() -> bool:
    if not HAS_NUMBA_CUDA or os.environ.get("NUMBA_ENABLE_CUDASIM", "0") not in ("", "0"):
        return False
    code = "from numba import cuda; import sys; sys.exit(0 if cuda.is_available() else 1)"
    return subprocess.run([sys.executable, "-c", code], env=_env(False), capture_output=True, timeout=120).returncode == 0


GPU = _gpu_available()


@pytest.mark.skipif(GPU, reason="this machine has a GPU")
def test_no_gpu_no_simulator_is_a_clear_error():
    code = ("from css_ros import SemanticMap; from css_ros.errors import CssError; from scenes import random_scene\n"
            "try:\n    SemanticMap(random_scene(0, n=10), 2, backend='cuda')\n"
            "except CssError as e:\n    print('CSSERROR', e)\n")
    out = subprocess.run([sys.executable, "-c", code], env=_env(False), cwd=ROOT, capture_output=True, text=True,
                         timeout=120)
    assert "CSSERROR" in out.stdout, out.stdout + out.stderr[-3000:]
    assert ("numba-cuda" in out.stdout) or ("NUMBA_ENABLE_CUDASIM" in out.stdout)


def test_unknown_option_is_a_clear_error():
    from scenes import random_scene

    with pytest.raises((CssError, TypeError)):
        SemanticMap(random_scene(0, n=10), 2, backend="nope")


@pytest.mark.skipif(not GPU, reason="needs a CUDA GPU (the simulated form is test_simulated_kernels)")
def test_gpu_matches_numba():  # pragma: no cover - GPU only
    """On a real GPU: a few observed frames, a render and score_views agree with the numba path."""
    from scenes import camera, random_scene

    model = random_scene(0, n=3000, log_scale=(-4.0, -1.5))
    cams = [camera(width=96, height=72, f=70.0, position=(0.05 * i, 0, 0)) for i in range(4)]
    gpu, cpu = SemanticMap(model, 6, backend="cuda"), SemanticMap(model, 6)
    rng = np.random.default_rng(0)
    for cam in cams[:3]:
        lab = rng.integers(0, 6, (cam.height, cam.width))
        a, b = gpu.observe(cam, lab), cpu.observe(cam, lab)
        np.testing.assert_allclose(a.expectation, b.expectation, atol=1e-5)
        np.testing.assert_allclose(a.variance, b.variance, rtol=1e-4, atol=1e-8)
    # the GPU walk is float32 (docs/cuda.md "What is tested"): ~1e-5 relative on the concentrations
    np.testing.assert_allclose(gpu.concentrations, cpu.concentrations, rtol=KAPPA_RTOL, atol=1e-7)
    np.testing.assert_allclose(gpu.score_views(cams), cpu.score_views(cams), rtol=1e-4)


@pytest.mark.skipif(not GPU, reason="needs a CUDA GPU")
@pytest.mark.skipif(not BIKER_PLY.exists(), reason="needs the real biker splat (CSS_BIKER_PLY)")
@pytest.mark.parametrize("with_sensor_model", [False, True])
def test_gpu_agrees_with_numba_at_real_density(with_sensor_model):  # pragma: no cover - GPU only
    """A trained splat at its real density (biker, 152k Gaussians, 640 x 480, C = 20), six observes of noisy labels:
    rendered labels agree on >= 99.99 % of pixels, U_var and U_exp within 1e-4 relative, the total evidence within
    1e-5 relative, info gain within 1e-4 (docs/cuda.md gives the measured agreement)."""
    from css_ros import Camera, GaussianModel
    from css_ros.engine.sensor_model import ConfidenceMap, SensorModel

    c, w, h = 20, 640, 480
    model = GaussianModel.from_ply(BIKER_PLY)
    centre = np.median(np.asarray(model.means, dtype=np.float64), axis=0)
    f = w / (2.0 * np.tan(np.radians(37.5)))
    k = np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
    cams = [Camera.look_at(centre + np.array([2.2 * np.cos(a), -0.4, 2.2 * np.sin(a)]), centre, k, w, h,
                           up=(0.0, -1.0, 0.0)) for a in np.linspace(0.0, 2.0 * np.pi, 8, endpoint=False)]
    kw = {}
    if with_sensor_model:
        rng = np.random.default_rng(1)
        kw["sensor_model"] = SensorModel(tuple(f"c{i}" for i in range(c)), np.array([0.0, 1.5, 3.0, 6.0]),
                                         rng.uniform(0.3, 1.0, (c, 3)), rng.dirichlet(np.full(c, 0.5), (c, 3)),
                                         ConfidenceMap(np.array([1.2, 0.3, -0.4]), np.array([0.0, 0.5, 1.0]),
                                                       np.array([0.05, 0.6, 0.97])))
    gpu, cpu = SemanticMap(model, c, backend="cuda", **kw), SemanticMap(model, c, **kw)
    rng = np.random.default_rng(0)
    for cam in cams[:6]:
        blocks = rng.integers(0, c, (h // 16, w // 16))                      # surfaces of one label, 30 % noise
        lab = np.kron(blocks, np.ones((16, 16), dtype=np.int64))
        lab = np.where(rng.random(lab.shape) < 0.3, rng.integers(0, c, lab.shape), lab)
        gpu.observe(cam, lab)
        cpu.observe(cam, lab)
    prior = c * 1e-3 * model.num_gaussians
    ev_g, ev_c = gpu.concentrations_readonly.sum() - prior, cpu.concentrations.sum() - prior
    assert abs(ev_g - ev_c) <= 1e-5 * ev_c
    for cam in cams:
        a, b = gpu.render(cam), cpu.render(cam)
        assert np.mean(a.labels == b.labels) >= 0.9999
        assert a.u_var == pytest.approx(b.u_var, rel=1e-4) and a.u_exp == pytest.approx(b.u_exp, rel=1e-4)
        if with_sensor_model:
            assert np.mean(np.abs(a.confidence - b.confidence) < 1e-3) >= 0.9999
    small = [cam.scaled(0.25) for cam in cams]
    np.testing.assert_allclose(gpu.score_views(small, pixel_scale=16.0), cpu.score_views(small, pixel_scale=16.0),
                               rtol=1e-4)
    assert list(gpu.select_views(small, 3).indices) == list(cpu.select_views(small, 3).indices)


@pytest.mark.skipif(not GPU, reason="needs a CUDA GPU")
def test_no_allocations_once_warm_and_views_stay_valid():  # pragma: no cover - GPU only
    """Once warm (the single-view plan settles its capacities over its first 8 frames), observes allocate no device
    memory from the driver (every per-frame buffer is the plan's) and no page-locked host memory while the caller
    drops its views; a kept view stays valid."""
    import torch

    from scenes import camera, random_scene

    model = random_scene(1, n=20000, log_scale=(-4.0, -1.5))
    cams = [camera(width=320, height=240, f=250.0, position=(0.02 * i, 0, 0)) for i in range(20)]
    gpu = SemanticMap(model, 8, backend="cuda")
    rng = np.random.default_rng(1)
    labels = [rng.integers(0, 8, (240, 320)) for _ in cams]
    for cam, lab in zip(cams[:10], labels[:10]):
        gpu.observe(cam, lab)
    torch.cuda.synchronize()
    segments = torch.cuda.memory_stats()["segment.all.allocated"]
    pinned = gpu._backend.ops.pinned_allocations
    for cam, lab in zip(cams[10:], labels[10:]):
        gpu.observe(cam, lab)
    assert torch.cuda.memory_stats()["segment.all.allocated"] == segments
    assert gpu._backend.ops.pinned_allocations == pinned
    kept = gpu.render(cams[0])
    snapshot = kept.expectation.copy()
    for cam, lab in zip(cams[1:4], labels[1:4]):
        gpu.observe(cam, lab)
    np.testing.assert_array_equal(kept.expectation, snapshot)
