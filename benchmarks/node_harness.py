"""css_node with per-stage timers, and optionally its engine stubbed: the node process of ``bench_node.py``.

    python benchmarks/node_harness.py --stats-out STATS.json [--engine-stub] --ros-args -p ...

Runs css_node's own entry point (:func:`css_ros.ros.main.main`) in this process after wrapping, by monkeypatching,
the functions a frame passes through, so that the node's own work per frame can be told apart from the engine's:

- ``take``: rclpy taking (deserialising) each input message (``Executor._take_subscription``);
- ``callback``: the node's subscription callback of each input message (input gate, message decode, queueing), of
  which ``decode`` is the label image's decode (``frame_gate.decode_labels``);
- ``worker``: ``MapWorker.process_frame`` as a whole, of which ``observe`` is ``SemanticMap.observe`` (the engine)
  and ``publish_frame`` the per-frame outputs (``OutputPublisher.publish_frame``), itself split into ``images``
  (``frame_output_images``: the colour-mapped labels), ``image_msgs`` (``conversions.image_bytes`` or ``image_msg``),
  ``view_msg`` (``conversions.view_points_msg``) and ``publish`` (``Publisher.publish``: rclpy's serialisation of
  a message object, and the DDS write).

Every timer records wall time (``time.perf_counter``) and the calling thread's CPU time (``time.thread_time``), per
frame (keyed by the input stamp [ns]). Work between frames (``ViewPublisher.tick``, ``OutputPublisher.publish_cloud``,
``StatusReporter.report``) is recorded per call. When the node stops (SIGINT / SIGTERM) the records are written as
JSON to ``--stats-out``.

``--engine-stub`` replaces ``SemanticMap.observe`` by :func:`stub_observe`, which returns a RenderedView of the
right sizes and dtypes at once (no rasterisation), so that the node's own work is measured on a CPU; the map, the
model and everything else are the node's real ones. The product has no such mode: the stub lives here only.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

#: U_var and U_exp of every stubbed view (any finite values: the node only forwards them).
STUB_U_VAR, STUB_U_EXP = 0.01, 0.5


class Probe:
    """Per-frame stage timings (stamp [ns] -> stage -> [wall s, cpu s]) and per-call timings of the work between
    frames (name -> list of [wall s, cpu s]); thread-safe."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.frames: dict[int, dict[str, list[float]]] = {}
        self.periodic: dict[str, list[list[float]]] = {}
        self.local = threading.local()   # .stamp: stamp of the input message in hand; .frame: worker's frame stamp

    def add(self, stamp: int, stage: str, wall: float, cpu: float) -> None:
        with self.lock:
            acc = self.frames.setdefault(stamp, {}).setdefault(stage, [0.0, 0.0])
            acc[0] += wall
            acc[1] += cpu

    def add_periodic(self, name: str, wall: float, cpu: float) -> None:
        with self.lock:
            self.periodic.setdefault(name, []).append([wall, cpu])

    def in_frame(self, stage: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        """``fn`` timed as ``stage`` of the worker's frame in hand (untimed outside ``process_frame``)."""
        probe = self

        def timed(*args: Any, **kwargs: Any) -> Any:
            stamp = getattr(probe.local, "frame", None)
            if stamp is None:
                return fn(*args, **kwargs)
            w, c = time.perf_counter(), time.thread_time()
            try:
                return fn(*args, **kwargs)
            finally:
                probe.add(stamp, stage, time.perf_counter() - w, time.thread_time() - c)
        return timed

    def between_frames(self, name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        probe = self

        def timed(*args: Any, **kwargs: Any) -> Any:
            w, c = time.perf_counter(), time.thread_time()
            try:
                return fn(*args, **kwargs)
            finally:
                probe.add_periodic(name, time.perf_counter() - w, time.thread_time() - c)
        return timed

    def dump(self, path: Path, extra: dict[str, Any]) -> None:
        with self.lock:
            data = {"frames": {str(k): v for k, v in self.frames.items()}, "periodic": self.periodic, **extra}
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(json.dumps(data))
        os.replace(tmp, path)


def stamp_of(msg: Any) -> int | None:
    """Header stamp [ns] of a message (None without a header)."""
    header = getattr(msg, "header", None)
    if header is None:
        return None
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def stub_observe(self: Any, camera: Any, labels: np.ndarray, confidence: np.ndarray | None = None,
                 probabilities: bool = False, outputs: Any = None, depth: Any = None) -> Any:
    """Stand-in for ``SemanticMap.observe``: a RenderedView of ``camera``'s size with the requested images in their
    final dtypes (labels: the input labels as int32; float planes and colour: constant noise made once per size),
    at once. Counts the frame (``frames_observed``) and sets ``last_update`` as the engine does; the concentrations
    are not changed."""
    from css_ros.engine.semantic_map import RenderedView, UpdateStats

    settings = self.render_settings(outputs, probabilities)
    wanted = settings.outputs
    h, w = camera.height, camera.width
    cache = self.__dict__.setdefault("_stub_planes", {})
    if (h, w) not in cache:
        rng = np.random.default_rng(0)
        cache[(h, w)] = {"plane": rng.random((h, w), dtype=np.float32),
                         "rgb": rng.integers(0, 256, (h, w, 3), dtype=np.uint8)}
    planes = cache[(h, w)]
    plane = planes["plane"]
    labels = np.asarray(labels, dtype=np.int32)
    used = int(np.count_nonzero(labels != self.ignore_label))
    self.last_update = UpdateStats(used, labels.size - used, 0, 0)
    self.frames_observed += 1

    def img(name: str, array: np.ndarray) -> np.ndarray | None:
        return array if name in wanted else None

    return RenderedView(labels=img("labels", labels), expectation=img("expectation", plane),  # type: ignore[arg-type]
                        variance=img("variance", plane), background=img("background", plane),  # type: ignore[arg-type]
                        evidence=img("evidence", plane), rgb=img("rgb", planes["rgb"]),  # type: ignore[arg-type]
                        u_var=STUB_U_VAR, u_exp=STUB_U_EXP,
                        probabilities=np.broadcast_to(plane[:, :, None], (h, w, self.num_classes))
                        if probabilities else None,
                        depth=img("depth", plane),
                        confidence=plane if "confidence" in wanted and settings.confidence is not None else None,
                        surprise=img("surprise", plane))


def install(probe: Probe, engine_stub: bool) -> None:
    """Wrap the node's frame path with ``probe``'s timers (and stub the engine); call before the node starts."""
    import rclpy.executors
    import rclpy.publisher

    from css_ros.engine.semantic_map import SemanticMap
    from css_ros.io import frame_gate
    from css_ros.ros import conversions, diagnostics, gate, outputs, view_publisher, worker

    local = probe.local

    # ---- inputs: take (deserialise) and callback of every subscription message, keyed by the message's stamp
    take = rclpy.executors.Executor._take_subscription

    def timed_take(self: Any, sub: Any) -> Any:
        w, c = time.perf_counter(), time.thread_time()
        run = take(self, sub)
        take_wall, take_cpu = time.perf_counter() - w, time.thread_time() - c
        if run is None:
            return None
        kind = str(sub.topic_name).rsplit("/", 1)[-1]

        async def timed_run() -> None:
            local.stamp = None
            w, c = time.perf_counter(), time.thread_time()
            try:
                await run()
            finally:
                stamp = local.stamp
                if stamp is not None:
                    probe.add(stamp, f"take:{kind}", take_wall, take_cpu)
                    probe.add(stamp, f"callback:{kind}", time.perf_counter() - w, time.thread_time() - c)
        return timed_run
    rclpy.executors.Executor._take_subscription = timed_take  # type: ignore[method-assign]

    def stamping(fn: Callable[..., Any]) -> Callable[..., Any]:
        def wrapped(self: Any, msg: Any, *args: Any, **kwargs: Any) -> Any:
            local.stamp = stamp_of(msg)
            return fn(self, msg, *args, **kwargs)
        return wrapped
    for name in ("on_segmentation", "on_pose", "on_camera_info", "on_confidence", "on_image"):
        setattr(gate.InputGate, name, stamping(getattr(gate.InputGate, name)))

    decode = frame_gate.decode_labels

    def timed_decode(msg: Any, *args: Any, **kwargs: Any) -> Any:
        w, c = time.perf_counter(), time.thread_time()
        try:
            return decode(msg, *args, **kwargs)
        finally:
            stamp = stamp_of(msg)
            if stamp is not None:
                probe.add(stamp, "decode", time.perf_counter() - w, time.thread_time() - c)
    frame_gate.decode_labels = timed_decode  # type: ignore[assignment]

    # ---- worker: the frame, the engine's observe inside it, and the output path
    process_frame = worker.MapWorker.process_frame

    def timed_process_frame(self: Any, job: Any) -> None:
        local.frame = job.stamp_ns
        w, c = time.perf_counter(), time.thread_time()
        try:
            process_frame(self, job)
        finally:
            probe.add(job.stamp_ns, "worker", time.perf_counter() - w, time.thread_time() - c)
            local.frame = None
    worker.MapWorker.process_frame = timed_process_frame  # type: ignore[method-assign]

    observe = stub_observe if engine_stub else SemanticMap.observe
    SemanticMap.observe = probe.in_frame("observe", observe)  # type: ignore[method-assign]
    outputs.OutputPublisher.publish_frame = probe.in_frame(  # type: ignore[method-assign]
        "publish_frame", outputs.OutputPublisher.publish_frame)
    outputs.frame_output_images = probe.in_frame("images", outputs.frame_output_images)
    for name in ("image_msg", "image_bytes"):   # image_bytes: serialised images (absent from older versions)
        if hasattr(conversions, name):
            setattr(conversions, name, probe.in_frame("image_msgs", getattr(conversions, name)))
    conversions.view_points_msg = probe.in_frame("view_msg", conversions.view_points_msg)
    rclpy.publisher.Publisher.publish = probe.in_frame(  # type: ignore[method-assign]
        "publish", rclpy.publisher.Publisher.publish)

    # ---- work between frames
    view_publisher.ViewPublisher.tick = probe.between_frames(  # type: ignore[method-assign]
        "view_stream_tick", view_publisher.ViewPublisher.tick)
    outputs.OutputPublisher.publish_cloud = probe.between_frames(  # type: ignore[method-assign]
        "semantic_cloud", outputs.OutputPublisher.publish_cloud)
    diagnostics.StatusReporter.report = probe.between_frames(  # type: ignore[method-assign]
        "status_report", diagnostics.StatusReporter.report)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    cut = argv.index("--ros-args") if "--ros-args" in argv else len(argv)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stats-out", type=Path, required=True, help="JSON file written when the node stops")
    ap.add_argument("--engine-stub", action="store_true", help="SemanticMap.observe returns a view at once")
    args = ap.parse_args(argv[:cut])
    probe = Probe()
    install(probe, args.engine_stub)
    from css_ros.ros.main import main as node_main

    cpu0 = os.times()
    rc = 1
    try:
        rc = node_main(argv[cut:])
    finally:
        t = os.times()
        probe.dump(args.stats_out, {"engine_stub": args.engine_stub, "exit_code": rc,
                                    "process_cpu_s": (t.user - cpu0.user) + (t.system - cpu0.system)})
    return rc


if __name__ == "__main__":
    sys.exit(main())
