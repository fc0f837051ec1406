"""One rclpy node in a private context, spun by a daemon thread: what css_ctl and css_view --live use to
talk to a running css_node from a plain Python process (no ``rclpy.init`` of the global context, so several
links, and the caller's own ROS use, never interfere)."""
from __future__ import annotations

import threading
import time
from typing import Callable


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
