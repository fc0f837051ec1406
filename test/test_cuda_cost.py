"""The paper estimate of the CUDA backend (css_ros/engine/cuda/cost_model.py): its counts against brute force
and the simulated GPU's own frame (test_cuda_sim.py), its arithmetic against its stated roofline rule."""
from __future__ import annotations

import numpy as np
import pytest

from css_ros import SemanticMap
from css_ros.engine.cuda import cost_model as cm
from css_reference import kappa_reference
from scenes import camera, random_scene


def test_labels_per_tile_against_brute_force():
    rng = np.random.default_rng(0)
    labels = rng.integers(-1, 4, (19, 21))
    labels[:8, :8] = 2                      # one label in the first tile
    labels[:8, 8:16] = -1                   # none in the second
    got = cm._labels_per_tile(labels, 3, 3, 8)
    want = [len({int(x) for x in labels[ty * 8:ty * 8 + 8, tx * 8:tx * 8 + 8].ravel() if x >= 0})
            for ty in range(3) for tx in range(3)]
    assert got.tolist() == want and want[0] == 1 and want[1] == 0


def test_frame_counts_against_the_brute_force_compositing():
    model = random_scene(1, n=150)
    cam = camera(width=20, height=14, f=14.0)
    smap = SemanticMap(model, 3)
    labels = np.zeros((14, 20), dtype=int)
    labels[:, 10:] = 1
    counts = cm.frame_counts(smap._backend.geometry, [cam], 3, [labels])
    kap, _ = kappa_reference(model.means, model.scales, model.quats_wxyz, model.opacities, cam.K,
                             cam.T_map_cam, cam.width, cam.height)
    assert counts.contributions == np.count_nonzero(kap) > 100
    assert counts.kept >= np.count_nonzero(kap.sum(axis=0))   # kept boxes include every contributor
    assert counts.walked == 64 * counts.keys and counts.keys >= counts.kept
    # every tile holds labels 0 or 1 or both: between one and two atomics per list entry
    assert counts.keys <= counts.label_sums <= 2 * counts.keys
    two = cm.frame_counts(smap._backend.geometry, [cam, cam], 3, [labels, labels])
    assert two == counts + counts and two.views == 2
    big = cm.frame_counts(smap._backend.geometry, [cam], 3, [labels], tile=16)
    assert big.walked == 256 * big.keys and big.keys < counts.keys and big.contributions == counts.contributions


def _counts(**kw):
    base = dict(gaussians=100_000, views=1, width=320, height=240, classes=20, sh_coeffs=16, kept=30_000,
                keys=180_000, walked=11_520_000, contributions=2_700_000, label_sums=220_000)
    return cm.FrameCounts(**{**base, **kw})


def test_roofline_rule_and_linearity():
    gpu = cm.H100_SXM
    k = cm._kernel("x", 7e9, 0.0, gpu, launches=2)    # 7 GB at 3.35 TB/s x 0.7 = 2.985 ms
    assert k.ms == pytest.approx(7e9 / (3350e9 * cm.MEM_EFFICIENCY) * 1e3 + 2 * cm.LAUNCH_MS + cm.NUMBA_LAUNCH_MS)
    k = cm._kernel("x", 0.0, 1e12, gpu, kernels=0)
    assert k.ms == pytest.approx(1e12 / (gpu.thread_instr_t * 1e12 * cm.ISSUE_EFFICIENCY) * 1e3)
    one, two = cm.observe_costs(_counts()), cm.observe_costs(_counts() + _counts())
    for a, b in zip(one, two):
        assert b.instructions == pytest.approx(2 * a.instructions) and b.ms >= a.ms, a.stage
        # the projection reads the model once however many views (their lanes share it); the rest scales
        model_bytes = _counts().gaussians * 88 if a.stage == "project" else 0
        assert b.bytes - model_bytes == pytest.approx(2 * (a.bytes - model_bytes)), a.stage
    # more classes cost the render more; past 40 classes it walks the lists once more per 40
    r20, r41 = (next(c for c in cm.observe_costs(_counts(classes=n)) if c.stage == "render") for n in (20, 41))
    assert r41.instructions > r20.instructions + _counts().walked * cm.INSTR_WALK * 0.99
    assert [c.stage for c in cm.score_costs(_counts(views=4))][-2] == "score"


def test_bench_stages_split_the_observe_cost():
    costs = cm.observe_costs(_counts())
    stages = cm.bench_stages(costs)
    assert set(stages) == {"prepare", "update", "render"}
    assert sum(stages.values()) == pytest.approx(sum(c.ms for c in costs))
    ms = {c.stage: c.ms for c in costs}
    assert stages["prepare"] == pytest.approx(ms["project"] + ms["order"])


def test_sensor_model_update_costs_one_more_walk():
    """The sensor-model update walks every labelled pixel twice (depth, then votes); a dense confusion adds an
    atomic per class and list entry; the rest of the observe does not change."""
    c = _counts()
    plain, weights, confusion = (cm.observe_costs(c, sensor_model=k) for k in cm.SENSOR_MODELS)
    upd = [next(s for s in costs if s.stage == "update") for costs in (plain, weights, confusion)]
    assert upd[1].instructions >= upd[0].instructions + c.walked * cm.INSTR_WALK
    assert upd[2].instructions == upd[1].instructions and upd[2].bytes > upd[1].bytes > upd[0].bytes
    assert upd[0].ms < upd[1].ms <= upd[2].ms
    for a, b in zip(plain, confusion):
        if a.stage not in ("update", "transfers + sync"):
            assert a == b, a.stage
    with pytest.raises(ValueError):
        cm.observe_costs(c, sensor_model="nope")
