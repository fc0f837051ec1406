"""Read a css_node parameter file (ROS 2 ``--params-file`` layout) outside ROS: css_replay and the tools share it.

Layout: ``css_node: {ros__parameters: {name: value, ...}}`` (also ``/css_node``, ``/**``); css_import, css_align
and ``css_make_demo --robot`` write one (:func:`write_params_file`), the node takes it with
``--ros-args --params-file FILE`` and css_replay with ``--params FILE`` (or finds ``css_node.yaml`` beside the bag).
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import yaml

from ..engine.atomic import atomic_file
from ..errors import ConfigError
from .topics import NODE_NAME

#: File name css_replay looks for next to a bag directory.
PARAMS_FILE_NAME = f"{NODE_NAME}.yaml"
#: Largest parameter file read [bytes] (a parameter file is a few kB; a larger one is not one).
MAX_PARAMS_FILE_BYTES = 1 << 20


def read_params_file(path: str | os.PathLike) -> dict[str, Any]:
    """The ``ros__parameters`` of css_node (merged over ``/**``) in ``path``; ConfigError naming the file."""
    path = Path(path)
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise ConfigError(f"parameter file {path}: {exc.strerror or exc}") from None
    if size > MAX_PARAMS_FILE_BYTES:
        raise ConfigError(f"parameter file {path}: {size} bytes, more than {MAX_PARAMS_FILE_BYTES} (not a parameter "
                          "file?)")
    try:
        doc = yaml.safe_load(path.read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise ConfigError(f"parameter file {path}: cannot read it as YAML: {exc}") from None
    if not isinstance(doc, dict):
        raise ConfigError(f"parameter file {path}: expected '{NODE_NAME}: {{ros__parameters: {{...}}}}'")
    out: dict[str, Any] = {}
    for key in ("/**", NODE_NAME, f"/{NODE_NAME}"):
        section = doc.get(key)
        if section is None:
            continue
        params = section.get("ros__parameters") if isinstance(section, dict) else None
        if not isinstance(params, dict):
            raise ConfigError(f"parameter file {path}: '{key}' has no ros__parameters mapping")
        out.update(params)
    if not out and doc:
        raise ConfigError(f"parameter file {path}: no '{NODE_NAME}' or '/**' section with ros__parameters")
    return out


def write_params_file(path: str | os.PathLike, params: dict[str, Any], comment: str = "") -> Path:
    """Write ``params`` as css_node's parameter file (atomically: temp file + rename); returns the path."""
    path = Path(path)
    text = "".join(f"# {line}\n" for line in comment.splitlines())
    text += yaml.safe_dump({NODE_NAME: {"ros__parameters": params}}, sort_keys=False, default_flow_style=None)
    with atomic_file(path, "w") as f:
        f.write(text)
    return path
