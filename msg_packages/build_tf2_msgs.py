"""Build the tf2_msgs message package into this Python environment when no tf2_msgs exists (PyPI-only ROS 2 install).

Usage: ``<venv>/bin/python msg_packages/build_tf2_msgs.py [--force] [--check]``

No tf2_msgs wheel exists on PyPI, but ROS 2 Jazzy's build tools do (the ``tf`` extra of setup.py). This script:

1. does nothing when ``tf2_msgs`` is importable and was not built here (a real ROS install: never shadowed), or when
   the copy built here is up to date (same message definitions);
2. rewrites the include paths of the wheel machine in ``<prefix>/share/**/*__rosidl_generator_pyExport.cmake`` to
   this interpreter's Python and numpy headers (redone on every run, since pip may reinstall those wheels);
3. builds ``msg_packages/tf2_msgs`` with colcon in a temporary workspace (``-DBUILD_TESTING=OFF``: the linters are not
   installed), with ``PATH``, ``AMENT_PREFIX_PATH``, ``CMAKE_PREFIX_PATH`` and ``LD_LIBRARY_PATH`` on the prefix;
4. copies the libraries into ``<prefix>/lib`` (which the ROS wheels already put on ``LD_LIBRARY_PATH``), the Python
   package into site-packages and ``share/tf2_msgs`` plus its ament index entries into ``<prefix>/share``, and
   records what it copied in ``<prefix>/share/tf2_msgs/css_ros_build.json``;
5. checks that a fresh interpreter imports ``tf2_msgs.msg.TFMessage`` and serialises one.

Exit codes: 0 built or nothing to do, 1 the build or the check failed (the output says where), 2 build tools missing.
``--check``: only say whether tf2_msgs is importable here (exit 0) or not (exit 1).
"""
from __future__ import annotations

import argparse
import hashlib
import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import time
from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parent / "tf2_msgs"
# The package's source folder beside this script is not an importable tf2_msgs: keep it off the import path.
sys.path = [p for p in sys.path if Path(p or os.getcwd()).resolve() != PACKAGE_DIR.parent]
PREFIX = Path(sys.prefix)
SITE = Path(sysconfig.get_paths()["purelib"])
MARKER = PREFIX / "share" / "tf2_msgs" / "css_ros_build.json"
#: What the build needs from the ``tf`` extra (a share/ folder of the prefix each, plus colcon itself).
NEEDED_SHARE = ("ament_cmake", "rosidl_default_generators", "rosidl_core_generators", "python_cmake_module",
                "geometry_msgs")
#: Seconds the colcon build may take at most.
BUILD_TIMEOUT_S = 900


def definitions_hash() -> str:
    """SHA-256 over the package's files (what a rebuild depends on)."""
    h = hashlib.sha256()
    for path in sorted(p for p in PACKAGE_DIR.rglob("*") if p.is_file()):
        h.update(str(path.relative_to(PACKAGE_DIR)).encode() + b"\0" + path.read_bytes())
    return h.hexdigest()


def system_tf2_msgs() -> str | None:
    """Where an importable tf2_msgs not built by this script lives (None: none, or ours)."""
    spec = importlib.util.find_spec("tf2_msgs")
    if spec is None:
        return None
    origin = spec.origin or (list(spec.submodule_search_locations or [""])[0])
    ours = SITE / "tf2_msgs"
    return None if MARKER.is_file() and Path(origin).resolve().is_relative_to(ours.resolve()) else origin


def fix_export_paths() -> int:
    """Point the ``*__rosidl_generator_pyExport.cmake`` files at this interpreter's headers; returns files changed."""
    import numpy

    py_include = sysconfig.get_paths()["include"]
    np_include = numpy.get_include()

    def fix(match: re.Match) -> str:
        parts = []
        for entry in match.group(1).split(";"):
            if entry and not Path(entry).exists():
                if re.search(r"/include/python3\.\d+$", entry):
                    entry = py_include
                elif re.search(r"/numpy/(_core|core)/include$", entry):
                    entry = np_include
            parts.append(entry)
        return f'INTERFACE_INCLUDE_DIRECTORIES "{";".join(parts)}"'

    changed = 0
    for path in (PREFIX / "share").glob("**/*__rosidl_generator_pyExport.cmake"):
        text = path.read_text()
        new = re.sub(r'INTERFACE_INCLUDE_DIRECTORIES "([^"]*)"', fix, text)
        if new != text:
            path.write_text(new)
            changed += 1
    return changed


def build_env() -> dict[str, str]:
    env = dict(os.environ)
    env.pop("PYTHONPATH", None)
    lib = str(PREFIX / "lib")
    env["PATH"] = os.pathsep.join([str(PREFIX / "bin"), env.get("PATH", "")])
    env["AMENT_PREFIX_PATH"] = str(PREFIX)
    env["CMAKE_PREFIX_PATH"] = str(PREFIX)
    env["LD_LIBRARY_PATH"] = os.pathsep.join([lib, env.get("LD_LIBRARY_PATH", "")]).rstrip(os.pathsep)
    return env


def colcon_build(ws: Path) -> Path:
    """Build the package in workspace ``ws``; returns its merged install folder (raises CalledProcessError)."""
    src = ws / "src" / "tf2_msgs"
    shutil.copytree(PACKAGE_DIR, src)
    colcon = shutil.which("colcon", path=str(PREFIX / "bin")) or "colcon"
    cmd = [colcon, "build", "--merge-install", "--base-paths", "src", "--build-base", "build", "--install-base",
           "install", "--event-handlers", "console_direct-", "--cmake-args", "-DBUILD_TESTING=OFF",
           f"-DPython3_EXECUTABLE={sys.executable}"]
    res = subprocess.run(cmd, cwd=ws, env=build_env(), capture_output=True, text=True, timeout=BUILD_TIMEOUT_S)
    if res.returncode != 0:
        sys.stderr.write(res.stdout[-6000:] + res.stderr[-6000:])
        raise subprocess.CalledProcessError(res.returncode, cmd)
    return ws / "install"


def copy_into_prefix(install: Path) -> list[str]:
    """Copy the built package into the prefix; returns the paths written (relative to the prefix)."""
    written: list[str] = []

    def put(src: Path, dst: Path) -> None:
        if src.is_dir():
            if dst.exists():
                shutil.rmtree(dst)
            shutil.copytree(src, dst, symlinks=True)
        else:
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dst, follow_symlinks=False)
        written.append(str(dst.relative_to(PREFIX)))

    for lib in sorted((install / "lib").glob("libtf2_msgs__*.so*")):
        put(lib, PREFIX / "lib" / lib.name)
    site = next((install / "lib").glob("python3*/site-packages"))
    put(site / "tf2_msgs", SITE / "tf2_msgs")
    put(install / "share" / "tf2_msgs", PREFIX / "share" / "tf2_msgs")
    for entry in sorted((install / "share" / "ament_index" / "resource_index").glob("*/tf2_msgs")):
        put(entry, PREFIX / "share" / "ament_index" / "resource_index" / entry.parent.name / "tf2_msgs")
    return written


def check_import() -> str | None:
    """None when a fresh interpreter imports and serialises a TFMessage, else its error output."""
    code = ("from tf2_msgs.msg import TFMessage\nfrom geometry_msgs.msg import TransformStamped\n"
            "from rclpy.serialization import serialize_message, deserialize_message\n"
            "m = TFMessage(transforms=[TransformStamped(child_frame_id='a')])\n"
            "assert deserialize_message(serialize_message(m), TFMessage).transforms[0].child_frame_id == 'a'\n")
    env = dict(os.environ)
    env.pop("PYTHONPATH", None)
    res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    return None if res.returncode == 0 else (res.stdout + res.stderr)[-3000:]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="build_tf2_msgs.py", description=__doc__.splitlines()[0])
    parser.add_argument("--force", action="store_true", help="rebuild even when the copy built here is up to date")
    parser.add_argument("--check", action="store_true", help="only report whether tf2_msgs is importable")
    opts = parser.parse_args(argv)
    if opts.check:
        found = importlib.util.find_spec("tf2_msgs")
        print(f"tf2_msgs: {found.origin if found else 'not importable'}")
        return 0 if found else 1
    system = system_tf2_msgs()
    if system is not None:
        print(f"build_tf2_msgs: tf2_msgs is provided by this ROS install ({system}): nothing to build")
        return 0
    digest = definitions_hash()
    if not opts.force and MARKER.is_file():
        try:
            if json.loads(MARKER.read_text()).get("definitions") == digest and check_import() is None:
                print(f"build_tf2_msgs: tf2_msgs in {PREFIX} is up to date")
                return 0
        except (OSError, ValueError):
            pass
    missing = [name for name in NEEDED_SHARE if not (PREFIX / "share" / name).is_dir()]
    if shutil.which("colcon", path=str(PREFIX / "bin")) is None or importlib.util.find_spec("colcon_ros") is None:
        missing.append("colcon (colcon-core, colcon-ros, colcon-cmake)")
    if missing:
        print(f"build_tf2_msgs: error: build tools missing in {PREFIX}: {', '.join(missing)}; install them with "
              "pip install -e '.[tf]'", file=sys.stderr)
        return 2
    t0 = time.monotonic()
    fixed = fix_export_paths()
    try:
        with tempfile.TemporaryDirectory(prefix="tf2_msgs_ws_") as ws:
            written = copy_into_prefix(colcon_build(Path(ws)))
    except (subprocess.CalledProcessError, subprocess.TimeoutExpired, OSError, StopIteration) as exc:
        print(f"build_tf2_msgs: error: colcon build of {PACKAGE_DIR} failed: {exc}", file=sys.stderr)
        return 1
    MARKER.write_text(json.dumps({"definitions": digest, "written": written}, indent=1) + "\n")
    problem = check_import()
    if problem is not None:
        print(f"build_tf2_msgs: error: tf2_msgs was built but does not import:\n{problem}", file=sys.stderr)
        return 1
    print(f"build_tf2_msgs: built tf2_msgs into {PREFIX} in {time.monotonic() - t0:.0f} s ({fixed} export files "
          "fixed)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
