"""css_node's live-view stream reads the map without handing it out for writing (a device backend would download and
then re-upload the whole (N, C) concentrations on every tick)."""
from __future__ import annotations

import threading

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from css_ros.engine.classes import ClassSet  # noqa: E402
from css_ros.engine.gaussians import GaussianModel  # noqa: E402
from css_ros.engine.semantic_map import SemanticMap  # noqa: E402
from css_ros.ros.view_publisher import ViewPublisher  # noqa: E402

N, C = 50, 3


@pytest.fixture()
def node():
    context = rclpy.context.Context()
    rclpy.init(context=context, domain_id=0)
    n = rclpy.create_node("view_publisher_reads", context=context, start_parameter_services=False,
                          enable_rosout=False)
    yield n
    n.destroy_node()
    rclpy.try_shutdown(context=context)


@pytest.mark.parametrize("device_like", [False, True])
def test_tick_reads_the_concentrations_read_only(node, monkeypatch, device_like):
    rng = np.random.default_rng(0)
    model = GaussianModel.from_activated(rng.normal(size=(N, 3)), np.full((N, 3), 0.1), np.tile([1.0, 0, 0, 0], (N, 1)),
                                         np.full(N, 0.9), rng.random((N, 3)))
    smap = SemanticMap(model, C)
    backend = smap._backend
    if device_like:   # a backend holding the map on a device hands readers a read-only view (as backend cuda does)
        def read_only(host: np.ndarray) -> np.ndarray:
            view = host.view()
            view.flags.writeable = False
            return view
        monkeypatch.setattr(backend, "host_read", read_only)
    pub = ViewPublisher(node, smap, ClassSet.default(C), period=0.0, max_changes=1000, min_evidence=0.5)

    def no_write(host: np.ndarray) -> np.ndarray:
        raise AssertionError("the live view asked for the concentrations for writing")
    monkeypatch.setattr(backend, "host_write", no_write)
    lock = threading.Lock()
    pub.tick(0.0, 1, lock)
    assert pub.last_sent == N   # the first message carries every Gaussian
    smap._concentrations[:20, 1] += 10.0   # 20 Gaussians observed as class 1 (as a frame would change them)
    pub.tick(1.0, 2, lock)
    assert pub.last_sent == 20
