"""How every ROS-free console script ends: one-line errors and documented exit codes.

0 success; 1 a user-facing error (``CssError``: bad file, bad option value, refused data; or an OS
error naming the file); 2 a usage error (argparse); 130 interrupted (SIGINT); 143 terminated
(SIGTERM). SIGTERM unwinds exactly like SIGINT (an exception through the work), so the same clean-up
runs: no half-written output is left. An unexpected exception is also one line (exit 1) unless
``CSS_DEBUG=1`` is set, which shows the traceback.
"""
from __future__ import annotations

import argparse
import math
import os
import signal
import sys
import threading
from typing import Any, Callable, Sequence

from .errors import CssError

DEBUG_ENV = "CSS_DEBUG"


def bounded_number(lo: float, hi: float, lo_open: bool = False, integer: bool = False) -> Callable[[str], float | int]:
    """An argparse ``type``: a finite number in [lo, hi] ((lo, hi] with ``lo_open``), an integer with ``integer``;
    argparse names the option in its refusal (exit 2)."""
    def parse(text: str) -> float | int:
        try:
            value: float | int = int(text) if integer else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {'an integer' if integer else 'a number'}") from None
        if not (math.isfinite(value) and (lo < value if lo_open else lo <= value) and value <= hi):
            raise argparse.ArgumentTypeError(f"{text} is outside {'(' if lo_open else '['}{lo:g}, {hi:g}]")
        return value
    parse.__name__ = "integer" if integer else "number"
    return parse


class Terminated(KeyboardInterrupt):
    """SIGTERM arrived: raised in the main thread, unwinds (and cleans up) as KeyboardInterrupt does."""


def _on_sigterm(signum: int, frame: Any) -> None:
    raise Terminated()


def run_console(prog: str, work: Callable[[], int | None]) -> int:
    """Run ``work`` (which prints its own results) and turn failures into ``prog: error: ...`` lines."""
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        return _run(prog, work)
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _run(prog: str, work: Callable[[], int | None]) -> int:
    try:
        code = work()
    except CssError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:
        print(f"{prog}: error: {exc.strerror or exc}: {exc.filename or ''}".rstrip(": "), file=sys.stderr)
        return 1
    except Terminated:
        print(f"{prog}: terminated", file=sys.stderr)
        return 143
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - last resort: one line for the user, traceback on request
        if os.environ.get(DEBUG_ENV):
            raise
        print(f"{prog}: error: unexpected {type(exc).__name__}: {exc} (set {DEBUG_ENV}=1 for the traceback)",
              file=sys.stderr)
        return 1
    return int(code or 0)


def cli_main(prog: str, parser: "argparse.ArgumentParser", run: "Callable[[argparse.Namespace], str]",
             argv: "Sequence[str] | None" = None) -> int:
    """The whole ``main`` of a CLI whose ``run(args)`` returns the text to print: argparse's exit code on a usage
    error (2, or 0 for ``--help``), else :func:`run_console`'s."""
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:
        return int(exc.code or 0)
    return run_console(prog, lambda: print(run(args)))
