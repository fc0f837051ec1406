"""One rclpy node in a private context, spun by a daemon thread: what css_ctl and css_view --live use to
talk to a running css_node from a plain Python process (no ``rclpy.init`` of the global context, so several
links, and the caller's own ROS use, never interfere)."""
from __future__ import annotations

import argparse
import re
import threading
import time
from typing import Callable, Sequence

#: Smallest --timeout of the clients [s]: below 10 ms nothing can answer (1e-320 was accepted).
MIN_TIMEOUT_S = 0.01
#: One component of a ROS name: a letter or underscore, then letters, digits, underscores.
_NAME_COMPONENT = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def node_name_arg(suffixes: Sequence[str]) -> Callable[[str], str]:
    """An argparse ``type`` for --node: css_node's fully qualified name (/namespace/name, a trailing '/' dropped)
    whose topics and services ``<name>/<suffix>`` are valid ROS names (rclpy's own check: characters, length).

    Refused with a usage error naming the option (exit 2), before any DDS participant starts: an empty name, a
    relative one (no leading '/'), '~' (the calling tool's own private namespace, not css_node's), components
    that are not ROS names (``/css-node``, ``/1x``), and names whose longest topic would be too long.
    """
    def parse(text: str) -> str:
        shown = text if len(text) <= 60 else f"{text[:40]}...({len(text)} characters)"
        hint = "give css_node's full name like /css_node or /robot1/css_node"
        name = text.rstrip("/")
        if not text.strip():
            raise argparse.ArgumentTypeError(f"an empty name: {hint}")
        if text.startswith("~"):
            raise argparse.ArgumentTypeError(f"{shown!r} starts with '~', which names this tool's own private "
                                             f"namespace, not css_node's: {hint}")
        if not text.startswith("/"):
            raise argparse.ArgumentTypeError(f"{shown!r} is relative (no leading '/'): {hint}")
        bad = [c for c in name.split("/")[1:] if not _NAME_COMPONENT.fullmatch(c)]
        if not name or bad:
            raise argparse.ArgumentTypeError(
                f"{shown!r} is not a node name: {bad[0]!r} is not a ROS name (a letter or '_', then letters, "
                f"digits, '_')" if bad else f"{shown!r} is not a node name: {hint}")
        from rclpy.validate_full_topic_name import validate_full_topic_name

        for suffix in sorted(suffixes, key=len, reverse=True):
            topic = f"{name}/{suffix}"
            try:
                validate_full_topic_name(topic)
            except Exception as exc:  # noqa: BLE001 - rclpy's Invalid*NameException family
                why = str(exc).splitlines()[0].split(": ", 1)[-1].rstrip(":")
                limit = re.search(r"'(\d+)U - (\d+)U'", why)   # rcl says "length should not exceed '255U - 8U'"
                if limit:
                    why = f"longer than the {int(limit[1]) - int(limit[2])} characters ROS allows"
                where = f"{name[:40]}.../{suffix} ({len(topic)} characters)" if len(topic) > 60 else topic
                raise argparse.ArgumentTypeError(f"{shown!r} gives the topic {where}, which ROS refuses: "
                                                 f"{why}") from None
        return name
    parse.__name__ = "node name"
    return parse


class NodeLink:
    """An rclpy node (``<prefix>_<n>``) with its own context and single-threaded executor.

    Args:
        prefix: node name prefix (a number keeps names unique when several run at once).
        start: spin right away; False lets the caller create its subscriptions first, then :meth:`start`.
        domain_id: ROS domain (None: ROS_DOMAIN_ID, as every ROS process).
    """

    def __init__(self, prefix: str = "css_ctl", start: bool = True, domain_id: int | None = None) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        self.context = Context()
        rclpy.init(context=self.context, **({} if domain_id is None else {"domain_id": domain_id}))
        self.node = rclpy.create_node(f"{prefix}_{time.monotonic_ns() % 10**9}", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, daemon=True)
        if start:
            self.start()

    def start(self) -> None:
        """Start the spin thread (once)."""
        if not self._thread.is_alive():
            self._thread.start()

    def _spin(self) -> None:
        try:
            while self.context.ok():
                self.executor.spin_once(timeout_sec=0.05)
        except Exception:  # noqa: BLE001 - shutting down
            pass

    @staticmethod
    def wait(cond: Callable[[], bool], timeout: float) -> bool:
        """Poll ``cond`` every 20 ms for up to ``timeout`` s; its last value."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if cond():
                return True
            time.sleep(0.02)
        return bool(cond())

    def close(self) -> None:
        """Shut the context down and let the spin thread end (2 s at most)."""
        self.context.try_shutdown()
        if self._thread.is_alive():
            self._thread.join(2.0)
