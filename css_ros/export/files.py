"""Atomic file writes of the export layer: :func:`css_ros.engine.atomic.atomic_file` in binary mode."""
from __future__ import annotations

import os
from contextlib import contextmanager
from typing import BinaryIO, Iterator, cast

from ..engine.atomic import atomic_file


@contextmanager
def atomic_binary(path: str | os.PathLike[str]) -> Iterator[BinaryIO]:
    """Open a temporary file for writing that replaces ``path`` when the block ends without error.

    A crash or an exception leaves any previous ``path`` intact and no temporary file behind; the new file has
    the mode a plain ``open()`` would give it (0o666 less the umask).
    """
    with atomic_file(path, "wb") as fh:
        yield cast(BinaryIO, fh)
