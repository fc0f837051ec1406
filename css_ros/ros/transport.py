"""How css_node's DDS participant receives its inputs (Fast DDS, the Jazzy default rmw).

Synchronised cameras publish their images, confidences, camera_infos and segmentations with one stamp, back to
back. Between processes on one host Fast DDS sends them through the **publisher's** shared-memory segment (512 kB
by default); a burst larger than that (two 256x192 cameras with image and confidence: about 0.8 MB) recycles
buffers the node has not read yet whenever the node's receive thread is not scheduled within the burst (a busy
host): those samples are lost before any callback runs, at random, and no node parameter can bring them back.
A UDP socket instead holds a burst in the **receiver's** kernel buffer until the node reads it, so css_node
receives over UDPv4 with large socket buffers (:data:`NODE_TRANSPORT`, at most ``net.core.rmem_max``), unless
the user configured Fast DDS (``FASTDDS_BUILTIN_TRANSPORTS``, an XML profile) or another rmw. Publishers keep
their own transports: they reach the node over UDP. See docs/reliability.md, "Synchronised cameras".
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Mapping, MutableMapping

#: Receive (and send) socket size [bytes] css_node asks for: a burst of this many bytes waits in the kernel.
SOCKETS_SIZE = 8 * 1024 * 1024
#: FASTDDS_BUILTIN_TRANSPORTS for css_node when nobody configured Fast DDS.
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


def rmem_max(path: str = "/proc/sys/net/core/rmem_max") -> int | None:
    """The kernel's cap on a socket's receive buffer [bytes] (None where unknown)."""
    try:
        return int(Path(path).read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return None


#: Environment variable that opts css_node into receiving over UDP (value ``udp``). Not the default: with every
#: transport UDP, the node's own large outputs (a 20 000-candidate answer, ~/semantic_cloud) reach local subscribers
#: that kept Fast DDS's default socket buffers only through slow repairs (a 0.8 MB answer was not acknowledged
#: within 4.5 s at shutdown), which is worse for most robots than the synchronised-camera loss it cures.
OPT_IN_VAR = "CSS_NODE_TRANSPORT"


def configure_transport(env: MutableMapping[str, str] | None = None, cwd: Path | None = None,
                        cap: int | None = -1) -> tuple[str, bool]:
    """Set css_node's Fast DDS transport in ``env`` (os.environ) before ``rclpy.init`` when the user opted in
    (``CSS_NODE_TRANSPORT=udp``); otherwise leave Fast DDS's defaults (shared memory + UDP) and say so.

    Returns the start-up log line and whether it is a warning (a kernel cap below :data:`RMEM_MAX_WARN`, or a
    configuration that leaves the inputs on shared memory). ``cap``: net.core.rmem_max (-1: read it).
    """
    env = os.environ if env is None else env
    if env.get(OPT_IN_VAR, "").lower() != "udp":
        return ("DDS transport: Fast DDS defaults (shared memory between processes on this host; for several "
                f"cameras publishing same-stamp bursts set {OPT_IN_VAR}=udp, docs/reliability.md)"), False
    rmw = env.get("RMW_IMPLEMENTATION", "")
    if rmw not in FASTDDS_RMWS:
        return f"DDS transport: {rmw}'s own (no Fast DDS settings)", False
    user = [v for v in FASTDDS_CONFIG_VARS if env.get(v)]
    user += [f for f in FASTDDS_DEFAULT_FILES if (Path.cwd() if cwd is None else cwd).joinpath(f).is_file()]
    if user:
        return f"DDS transport: as configured by {', '.join(user)}", False
    if _localhost_only(env):
        return ("DDS transport: rmw_fastrtps's own for localhost discovery (shared memory): a same-stamp burst of "
                "several cameras larger than the publisher's segment can be lost (docs/reliability.md)"), True
    env["FASTDDS_BUILTIN_TRANSPORTS"] = NODE_TRANSPORT
    cap = rmem_max() if cap == -1 else cap
    line = f"DDS transport: inputs over UDPv4, socket buffers {SOCKETS_SIZE >> 20} MiB"
    if cap is not None and cap < SOCKETS_SIZE:
        line += f" (capped by net.core.rmem_max={cap})"
    if cap is not None and cap < RMEM_MAX_WARN:
        return (line + f": a same-stamp burst of several cameras larger than that can be lost; raise it "
                f"(sysctl -w net.core.rmem_max={SOCKETS_SIZE})"), True
    return line, False


def _localhost_only(env: Mapping[str, str]) -> bool:
    """rmw_fastrtps sets its own transports (builtin ones off) for localhost-only discovery."""
    return env.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "").upper() == "LOCALHOST" or \
        env.get("ROS_LOCALHOST_ONLY", "") == "1"
