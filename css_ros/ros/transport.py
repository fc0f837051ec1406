"""How css_node's DDS participants receive its inputs (Fast DDS, the Jazzy default rmw).

Synchronised cameras publish their images, confidences, camera_infos and segmentations with one stamp, back to
back. Between processes on one host Fast DDS sends them through the **publisher's** shared-memory segment (512 kB
by default); a burst larger than that (two 256x192 cameras with image and confidence: about 0.8 MB) recycles
buffers the node has not read yet whenever the node's receive thread is not scheduled within the burst (a busy
host): those samples are lost before any callback runs, at random, and no node parameter can bring them back.
A UDP socket instead holds a burst in the **receiver's** kernel buffer until the node reads it.

So css_node has two DDS participants (one rclpy context each): the **inputs participant** (camera streams,
poses) receives over UDPv4 only, with large socket buffers (:data:`NODE_TRANSPORT`, at most ``net.core.rmem_max``);
the **node's own participant** (candidate and point requests, outputs, services, evidence exchange, /rosout,
parameters) keeps Fast DDS's defaults, so large outputs still reach local subscribers through shared memory at
once, and a huge request does not hold up the camera streams. Publishers keep their own transports: they reach
the inputs participant over UDP. With a user's Fast DDS configuration (``FASTDDS_BUILTIN_TRANSPORTS``, an XML
profile), another rmw, localhost-only discovery (rmw_fastrtps's own transports) or ``CSS_NODE_TRANSPORT=shm``
there is one participant, left as configured.
See docs/reliability.md, "Synchronised cameras".
"""
from __future__ import annotations

import os
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Mapping, MutableMapping

#: Receive (and send) socket size [bytes] of the inputs participant: a burst of this many bytes waits in the kernel.
SOCKETS_SIZE = 8 * 1024 * 1024
#: FASTDDS_BUILTIN_TRANSPORTS of the inputs participant.
NODE_TRANSPORT = f"UDPv4?sockets_size={SOCKETS_SIZE}"
#: Below this ``net.core.rmem_max`` [bytes] the start-up line warns (the kernel caps the buffer there).
RMEM_MAX_WARN = 2 * 1024 * 1024
#: rmw implementations this applies to (unset RMW_IMPLEMENTATION: Fast DDS, Jazzy's default).
FASTDDS_RMWS = ("", "rmw_fastrtps_cpp", "rmw_fastrtps_dynamic_cpp")
#: Environment variables by which a user configures Fast DDS (then css_node changes nothing).
FASTDDS_CONFIG_VARS = ("FASTDDS_BUILTIN_TRANSPORTS", "FASTRTPS_DEFAULT_PROFILES_FILE",
                       "FASTDDS_DEFAULT_PROFILES_FILE")
#: Profile files Fast DDS loads from the working directory by itself.
FASTDDS_DEFAULT_FILES = ("DEFAULT_FASTRTPS_PROFILES.xml", "DEFAULT_FASTDDS_PROFILES.xml")
#: Environment variable choosing the inputs' transport: ``udp`` (the default) or ``shm`` (one participant with
#: Fast DDS's defaults, shared memory between processes on this host).
CHOICE_VAR = "CSS_NODE_TRANSPORT"
CHOICES = ("udp", "shm")
#: Suffix of the inputs participant's node name (``css_node_inputs``; no rosout, no parameter services).
INPUTS_SUFFIX = "_inputs"


@dataclass(frozen=True)
class InputTransport:
    """The inputs' transport decided at start.

    Attributes:
        line: the start-up log line (``DDS transport: ...``).
        warn: log it as a warning (a kernel cap below :data:`RMEM_MAX_WARN`, a configuration that leaves the
            inputs on shared memory, an unknown CSS_NODE_TRANSPORT value).
        builtin: FASTDDS_BUILTIN_TRANSPORTS for a separate inputs participant; None: the inputs share the node's
            own participant.
    """
    line: str
    warn: bool
    builtin: str | None


def rmem_max(path: str = "/proc/sys/net/core/rmem_max") -> int | None:
    """The kernel's cap on a socket's receive buffer [bytes] (None where unknown)."""
    try:
        return int(Path(path).read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return None


def choose_input_transport(env: Mapping[str, str] | None = None, cwd: Path | None = None,
                           cap: int | None = -1) -> InputTransport:
    """Decide how css_node receives its inputs from ``env`` (os.environ) and the working directory ``cwd``.

    ``cap``: net.core.rmem_max [bytes] (-1: read it; None: unknown)."""
    env = os.environ if env is None else env
    choice = env.get(CHOICE_VAR, "").strip().lower() or "udp"
    if choice not in CHOICES:
        return InputTransport(f"DDS transport: {CHOICE_VAR}={env.get(CHOICE_VAR)!r} is not one of "
                              f"{', '.join(CHOICES)}: Fast DDS defaults (shared memory) for the inputs", True, None)
    if choice == "shm":
        return InputTransport(f"DDS transport: Fast DDS defaults ({CHOICE_VAR}=shm): a same-stamp burst of several "
                              "cameras larger than the publisher's shared-memory segment can be lost "
                              "(docs/reliability.md)", False, None)
    rmw = env.get("RMW_IMPLEMENTATION", "")
    if rmw not in FASTDDS_RMWS:
        return InputTransport(f"DDS transport: {rmw}'s own (no Fast DDS settings)", False, None)
    here = Path.cwd() if cwd is None else cwd
    user = [v for v in FASTDDS_CONFIG_VARS if env.get(v)]
    user += [f for f in FASTDDS_DEFAULT_FILES if here.joinpath(f).is_file()]
    if user:
        return InputTransport(f"DDS transport: as configured by {', '.join(user)}", False, None)
    if _localhost_only(env):
        return InputTransport("DDS transport: rmw_fastrtps's own for localhost discovery (shared memory): a "
                              "same-stamp burst of several cameras larger than the publisher's segment can be lost "
                              "(docs/reliability.md)", True, None)
    cap = rmem_max() if cap == -1 else cap
    line = (f"DDS transport: inputs over UDPv4 (socket buffers {SOCKETS_SIZE >> 20} MiB"
            + (f", capped by net.core.rmem_max={cap}" if cap is not None and cap < SOCKETS_SIZE else "")
            + "), outputs and services with Fast DDS defaults (shared memory on this host)")
    if cap is not None and cap < RMEM_MAX_WARN:
        return InputTransport(line + f": a same-stamp burst of several cameras larger than {cap} bytes can be "
                              f"lost; raise it (sysctl -w net.core.rmem_max={SOCKETS_SIZE})", True, NODE_TRANSPORT)
    return InputTransport(line, False, NODE_TRANSPORT)


@contextmanager
def builtin_transports(value: str, env: MutableMapping[str, str] | None = None) -> Iterator[None]:
    """FASTDDS_BUILTIN_TRANSPORTS = ``value`` while a participant is created (Fast DDS reads it then, for that
    participant only), restored afterwards."""
    env = os.environ if env is None else env
    old = env.get("FASTDDS_BUILTIN_TRANSPORTS")
    env["FASTDDS_BUILTIN_TRANSPORTS"] = value
    try:
        yield
    finally:
        if old is None:
            env.pop("FASTDDS_BUILTIN_TRANSPORTS", None)
        else:
            env["FASTDDS_BUILTIN_TRANSPORTS"] = old


def open_inputs_node(name: str, namespace: str, builtin: str) -> tuple[Any, Any]:
    """A node ``name`` + :data:`INPUTS_SUFFIX` in ``namespace`` on a participant of its own (a new rclpy context)
    whose transports are ``builtin``. It takes no command-line arguments (the caller subscribes it to topic names
    it resolved with its own remappings), has no rosout and no parameter services. Returns (node, context)."""
    import rclpy
    from rclpy.context import Context
    from rclpy.node import Node
    from rclpy.signals import SignalHandlerOptions

    context = Context()
    rclpy.init(args=[], context=context, signal_handler_options=SignalHandlerOptions.NO)
    with builtin_transports(builtin):   # the participant is created with the context's first node
        node = Node(name + INPUTS_SUFFIX, namespace=namespace, context=context, use_global_arguments=False,
                    enable_rosout=False, start_parameter_services=False)
    return node, context


def _localhost_only(env: Mapping[str, str]) -> bool:
    """rmw_fastrtps sets its own transports (builtin ones off) for localhost-only discovery."""
    return env.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "").upper() == "LOCALHOST" or \
        env.get("ROS_LOCALHOST_ONLY", "") == "1"
