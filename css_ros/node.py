"""``python -m css_ros.node``: starts css_node (kept so existing launch lines and scripts keep working).

The node itself lives in :mod:`css_ros.ros`; this module only forwards to its entry point.
"""
from __future__ import annotations

if __name__ == "__main__":
    import sys

    from css_ros.ros.main import main

    sys.exit(main())
