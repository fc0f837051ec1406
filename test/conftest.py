"""Shared pytest setup: make the test helpers importable and register markers."""
from __future__ import annotations

import signal
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

# A suite started in the background by a non-interactive shell (`cmd &` without job control, as in scripts and
# some CI runners) inherits SIGINT ignored, and so would every css_node / css_import the tests start: the tests
# that stop them with SIGINT (Ctrl-C's signal) would then wait forever. A handler (unlike SIG_IGN) is reset to the
# default at exec, so the children get SIGINT as a terminal would give it to them.
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


def pytest_configure(config):
    config.addinivalue_line("markers", "slow: end-to-end tests that take tens of seconds (run in CI)")


@pytest.fixture(scope="session")
def tiny_demo(tmp_path_factory):
    """A small generated demo (1500 Gaussians, 2 frames of 32 x 24: ``bag/``, ``classes.yaml``, ...), made once per
    test process, for tests that only need some valid bag to run a tool on."""
    from css_ros.demo.make_demo import make_demo

    root = tmp_path_factory.mktemp("tiny_demo")
    make_demo(root, num_gaussians=1500, frames=2, width=32, height=24, seed=3, progress=False)
    return root

