"""Where data files are found: the shipped demo bag and relative model/class paths (ROS-free)."""
from __future__ import annotations

import os
import sys
from pathlib import Path

PACKAGE = "css_ros"
DEFAULT_DEMO_BAG = Path("bags") / "demo" / "bag"
#: The source tree (repository root) when running from a checkout or an editable install.
SOURCE_ROOT = Path(__file__).resolve().parents[2]


def share_directories() -> list[Path]:
    """Installed share directories of the package: ament's (colcon) when available, then ``<prefix>/share``."""
    dirs = []
    try:
        from ament_index_python.packages import get_package_share_directory

        dirs.append(Path(get_package_share_directory(PACKAGE)))
    except Exception:  # noqa: BLE001 - not installed with ament (pip / source tree), or no ament at all
        pass
    dirs.append(Path(sys.prefix) / "share" / PACKAGE)
    return dirs


def resolve_data_path(path: str) -> Path:
    """Find a data file: absolute/'~' paths as given; relative ones against the working directory, the
    installed package share directory (share/css_ros) and the source tree, first existing wins (else
    the working-directory path, so the caller's error names what was asked for)."""
    p = Path(os.path.expanduser(path))
    if p.is_absolute():
        return p
    for base in [Path.cwd(), *share_directories(), SOURCE_ROOT]:
        try:
            if (base / p).exists():
                return base / p
        except OSError:  # name too long, permission denied: the caller's reader names the fault
            continue
    return Path.cwd() / p


def find_demo_bag() -> Path | None:
    """Locate the shipped demo bag ``bags/demo/bag``: in the current directory, the source tree, then
    the installed share directories. None when it is nowhere."""
    for base in [Path.cwd(), SOURCE_ROOT, *share_directories()]:
        if (base / DEFAULT_DEMO_BAG).is_dir():
            return base / DEFAULT_DEMO_BAG
    return None
