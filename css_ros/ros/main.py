"""``css_node`` entry point: argument handling, signals, executor loop and clean shutdown."""
from __future__ import annotations

import signal
import sys
import threading
from typing import Any, Sequence

from ..errors import CssError
from ..io.topics import NODE_NAME
from .params import format_default, param_table

#: Seconds css_node waits at shutdown for the inputs thread to return from its executor (it polls every 0.1 s).
INPUTS_JOIN_TIMEOUT_S = 2.0

USAGE = f"""usage: css_node [-h] [--ros-args -p NAME:=VALUE ... -r FROM:=TO ... --params-file FILE]

{NODE_NAME}: Continuous Semantic Splatting. Maps segmentations onto a 3D Gaussian Splatting model and
scores candidate views (SPEC §7-8). Stop it with SIGINT or SIGTERM: it finishes the current frame (or
candidate slice) and writes a final checkpoint.

examples:
  css_node --ros-args --params-file config/css_node.yaml      # the shipped demo model and classes
  css_node --ros-args -p model_path:=/data/room.ply -p class_file:=/data/classes.yaml \\
           -r segmentation:=/camera/seg -r pose:=/camera/pose_optical
  (then, e.g., css_demo plays the demo bag into it; css_ctl talks to it)
"""

#: What each input kind carries (css_node --help); names and types come from io.topics.
_INPUT_HELP = {
    "segmentation": "label image (mono8/8UC1/mono16/16UC1), one per frame: the frame's anchor",
    "confidence": "optional per-pixel confidence in [0, 1] (32FC1), matched by stamp",
    "image": "optional colour image, matched by stamp (only for the PSNR on /diagnostics)",
    "camera_info": "pinhole intrinsics; the latest valid one is used",
    "pose": "pose of the camera (pose_type: PoseStamped, PoseWithCovarianceStamped or Odometry)",
    "candidates": "poses to score as candidate views (answered on ~/candidate_scores)",
    "point_queries": "points to query (answered on ~/point_query_results)",
}
#: What each output carries (css_node --help).
_OUTPUT_HELP = {
    "semantic": "argmax class per pixel (mono8/mono16), per observed frame",
    "semantic_color": "the labels in class colours (rgb8)",
    "expectation": "E of the argmax class (32FC1)",
    "variance": "Var of the argmax class (32FC1)",
    "rendered_image": "colour render of the splat (rgb8)",
    "confidence": "calibrated probability that the label is right (32FC1; with a sensor model)",
    "surprise": "1 - E of each pixel's observed label before the frame's update (32FC1; NaN: no label)",
    "view_uncertainty": "U_var, U_exp of the frame's view (one point at the camera)",
    "candidate_scores": "U_var, U_exp, info_gain per candidate pose, request order",
    "semantic_cloud": "observed Gaussians with class and uncertainty (every cloud_period s)",
    "point_query_results": "SPEC §9 field at each queried point",
}


def topics_text() -> str:
    """The topics in and out and the services, with their message types (``css_node --help``)."""
    from ..io.topics import INPUT_TOPICS, INPUT_TYPES, OUTPUT_TOPICS

    lines = ["topics in (relative: remap with -r NAME:=/your/topic; with cameras:=[ns...] each camera reads "
             "/ns/NAME):"]
    lines += [f"  {INPUT_TOPICS[k]} [{INPUT_TYPES[k]}]\n      {d}" for k, d in _INPUT_HELP.items()]
    lines += ["  <depth_topic> [sensor_msgs/msg/Image]\n      optional measured depth registered to the "
              "segmentation (16UC1 mm, 32FC1 m), matched by stamp (parameter depth_topic)",
              "  <evidence_in topics> [std_msgs/msg/UInt8MultiArray]\n      evidence of other nodes (parameter "
              "evidence_in)", "", "topics out (private: /css_node/NAME; per camera namespace with several "
              "cameras):"]
    lines += [f"  ~/{k} [{OUTPUT_TOPICS[k]}]\n      {d}" for k, d in _OUTPUT_HELP.items()]
    lines += ["  ~/evidence [std_msgs/msg/UInt8MultiArray]\n      this node's evidence (publish_evidence)",
              "  ~/view/info, ~/view/semantics, ~/view/model\n      for css_view --live (view_period)",
              "  /diagnostics [diagnostic_msgs/msg/DiagnosticArray]\n      counters (publish_diagnostics)",
              "", "services (std_srvs/srv/Trigger; css_ctl save|reset|load): ~/save_map, ~/reset_map, ~/load_map, "
              "~/view/resync", ""]
    return "\n".join(lines)


def help_text() -> str:
    """Usage, examples, the topics in and out and the parameter table (``css_node --help``)."""
    rows = []
    for name, default, unit, desc in param_table():
        rows.append(f"  {name} = {format_default(default)}{' [' + unit + ']' if unit else ''}\n      {desc}")
    return (USAGE + "\n" + topics_text() + "\nparameters (name, default, unit, description):\n"
            + "\n".join(rows) + "\n")


def wants_help(argv: Sequence[str]) -> bool:
    """-h / --help before any --ros-args."""
    user = list(argv)
    if "--ros-args" in user:
        user = user[:user.index("--ros-args")]
    return "-h" in user or "--help" in user


def main(args: Sequence[str] | None = None) -> int:
    """Console entry point ``css_node``; returns the process exit code (0 clean stop, 2 start-up error).

    SIGINT / SIGTERM stop the node: the worker finishes its frame or candidate slice and a final checkpoint
    is written before the ROS context shuts down.
    """
    argv = list(sys.argv[1:] if args is None else args)
    if wants_help(argv):
        print(help_text())
        return 0

    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    from .transport import choose_input_transport

    transport = choose_input_transport()
    try:
        rclpy.init(args=[sys.argv[0], *argv], signal_handler_options=SignalHandlerOptions.NO)
    except Exception as exc:  # noqa: BLE001 - rcl reports bad --ros-args as a generic RCLError
        print(f"{NODE_NAME}: cannot initialise ROS (check the --ros-args): {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    node = None
    inputs_thread: threading.Thread | None = None
    failed: list[BaseException] = []   # an exception of the inputs thread, raised here after the clean stop
    try:
        from .node import CssNode

        log = rclpy.logging.get_logger(NODE_NAME)
        (log.warning if transport.warn else log.info)(transport.line)
        try:
            node = CssNode(inputs_transport=transport.builtin)
        except CssError as exc:  # ModelError, MapError, ConfigError, class file
            rclpy.logging.get_logger(NODE_NAME).fatal(f"cannot start: {exc}")
            return 2
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        if node.inputs is not node:   # the inputs participant: its own context, executor and thread
            inputs_thread = threading.Thread(target=_spin_inputs, args=(node, stop, failed), name="css_inputs",
                                             daemon=True)
            inputs_thread.start()
        while not stop.is_set() and rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        stop.set()
        if inputs_thread is not None:
            inputs_thread.join(INPUTS_JOIN_TIMEOUT_S)
        if node is not None:
            node.get_logger().info("shutting down")
            node.shutdown()
            node.close_inputs()
            node.destroy_node()
        rclpy.try_shutdown()
    if failed:
        raise failed[0]
    return 0


def _spin_inputs(node: Any, stop: threading.Event, failed: list[BaseException]) -> None:
    """Thread: run the callbacks of the inputs participant (every call of the input gate) until ``stop``; an
    exception in a callback is kept in ``failed`` and stops the node as it would on the one executor thread."""
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

    executor = SingleThreadedExecutor(context=node.inputs.context)
    executor.add_node(node.inputs)
    try:
        while not stop.is_set() and node.inputs.context.ok():
            executor.spin_once(timeout_sec=0.1)
    except ExternalShutdownException:
        pass
    except Exception as exc:  # noqa: BLE001 - re-raised by main after the clean stop
        failed.append(exc)
        stop.set()
    finally:
        executor.shutdown(timeout_sec=0.0)


if __name__ == "__main__":
    sys.exit(main())
