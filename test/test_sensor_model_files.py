"""Hostile sensor-model files and every reader of them: SensorModel.load, css_replay --sensor-model, css_node's
sensor_model parameter (css_ros/engine/sensor_model.py). Each is refused in one line naming the file and the
fault, in bounded memory and time: non-finite confidence coefficients or knots, YAML aliases (a few kB expanding
to GBs), integers of hundreds or thousands of digits, nesting 2000 deep."""
from __future__ import annotations

import resource
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

sys.path.insert(0, str(Path(__file__).parent))
import ros_helpers as rh  # noqa: E402

from css_ros.engine.classes import ClassSet  # noqa: E402
from css_ros.engine.sensor_model import (MAX_YAML_DEPTH, MAX_YAML_SCALARS, ConfidenceMap, SensorModel,  # noqa: E402
                                         read_plain_yaml)
from css_ros.errors import SensorModelError  # noqa: E402

#: Address-space cap of every reader run here [bytes]: an alias bomb read by the old loader needs 7+ GiB.
MEMORY_CAP = 4 * 2**30


def _good(names: tuple[str, ...]) -> dict:
    c = len(names)
    cmap = ConfidenceMap(np.array([1.2, 0.3, -0.2]), np.array([0.0, 0.5, 1.0]), np.array([0.05, 0.6, 0.97]))
    return SensorModel(names, [0.0, 4.0, 20.0], np.full((c, 2), 0.5), None, cmap).to_dict()


def hostile_files(folder: Path, names: tuple[str, ...]) -> dict[str, tuple[Path, str]]:
    """case -> (file, what the one-line refusal must say)."""
    folder.mkdir(parents=True, exist_ok=True)
    out = {}

    def write(case: str, text: str, expect: str) -> None:
        path = folder / f"{case.replace(' ', '_')}.yaml"
        path.write_text(text)
        out[case] = (path, expect)

    for case, key, index, value in (("nan coef", "coef", 0, float("nan")), ("inf coef", "coef", 2, float("inf")),
                                    ("nan knot", "knots_x", 1, float("nan")),
                                    ("inf knot", "knots_y", 2, float("-inf"))):
        d = _good(names)
        d["confidence"][key][index] = value                  # the fingerprint leaves the confidence map out
        write(case, yaml.safe_dump(d), f"{key} must be finite")
    good = yaml.safe_dump(_good(names), default_flow_style=None, width=10**6)
    # 10 anchors of 10 aliases each: 10^9 numbers (8 GB as float64) out of 1 kB of text
    bomb = "bomb0: &b0 [0.5, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5]\n" + "".join(
        f"bomb{k}: &b{k} [{', '.join([f'*b{k - 1}'] * 10)}]\n" for k in range(1, 9))
    write("alias bomb", bomb + good.replace("weight:", "weight: *b8\nunused:"), "YAML aliases")
    write("400 digits", good.replace("version: 1", "version: 1" + "0" * 399), "an integer of 400 characters")
    write("5000 digits", good + "calibration: {pixels: " + "9" * 5000 + "}\n", "an integer of 5000 characters")
    write("20 deep", good + "calibration: {x: " + "[" * 20 + "]" * 20 + "}\n",
          f"nested deeper than {MAX_YAML_DEPTH} levels")
    # libyaml's parser stops at 1000 flow levels itself ("while increasing flow level"); the pure-Python one does not
    write("2000 deep", good + "calibration: {x: " + "[" * 2000 + "]" * 2000 + "}\n",
          f"nested deeper than {MAX_YAML_DEPTH} levels|flow level")
    return out


def _says(line: str, expect: str) -> bool:
    """``line`` holds one of the |-separated phrases of ``expect``."""
    return any(phrase in line for phrase in expect.split("|"))


def _capped() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_CAP, MEMORY_CAP))


def test_read_plain_yaml_equals_safe_load_on_plain_documents_and_refuses_the_rest():
    text = "a: [1, 2.5, -3e2, .inf, null, true, 'x', 2001-12-14]\nb: {c: [[1], []], d: ~}\ne: 0x1F\n"
    assert read_plain_yaml(text, "f") == yaml.safe_load(text)
    for bad, expect in (("a: &x [1]\nb: *x\n", "aliases"), ("a: !!python/name:os.system x\n", "tag"),
                        ("? [1, 2]\n: 3\n", "as a mapping key"), ("a: 1\n---\nb: 2\n", "more than one"),
                        ("a: !!set {x}\n", "tag"), ("[" * 17 + "]" * 17, "deeper than 16")):
        with pytest.raises(SensorModelError, match=expect):
            read_plain_yaml(bad, "f")
    with pytest.raises(SensorModelError, match=f"more than {MAX_YAML_SCALARS} values"):
        read_plain_yaml("[" + "0," * MAX_YAML_SCALARS + "0]", "f")


def test_sensor_model_load_refuses_hostile_files_in_bounded_memory(tmp_path):
    """Each file is read by SensorModel.load in a child process under a 4 GiB address-space cap: one
    SensorModelError naming the file and the fault, peak memory below 400 MB (an alias bomb is refused at its first
    alias, before any expansion)."""
    names = ClassSet.default(4).names
    cases = hostile_files(tmp_path, names)
    script = ("import resource, sys\nfrom css_ros.engine.sensor_model import SensorModel\n"
              "from css_ros.errors import SensorModelError\n"
              "try:\n    SensorModel.load(sys.argv[1])\n    print('loaded')\n"
              "except SensorModelError as exc:\n    print('refused:', exc)\n"
              # VmHWM: this process's own peak (ru_maxrss would keep the forking pytest worker's size across exec)
              "hwm = [ln for ln in open('/proc/self/status') if ln.startswith('VmHWM:')][0].split()[1]\n"
              "print('rss_mb', int(hwm) / 1024)\n")
    for case, (path, expect) in cases.items():
        proc = subprocess.run([sys.executable, "-c", script, str(path)], capture_output=True, text=True, timeout=120,
                              env=rh.node_env(0), preexec_fn=_capped)
        lines = proc.stdout.splitlines()
        assert proc.returncode == 0 and len(lines) == 2, (case, proc.stdout, proc.stderr[-2000:])
        assert lines[0].startswith(f"refused: sensor model {path}") and _says(lines[0], expect), (case, lines[0])
        assert float(lines[1].split()[1]) < 400, (case, lines[1])


def test_css_replay_refuses_hostile_sensor_models_in_one_line(tiny_demo, tmp_path):
    """css_replay BAG --sensor-model FILE: exit 1, one ``css_replay: error: sensor model FILE: ...`` line naming the
    fault (never "unexpected"), and no output written (the file is read before the replay starts)."""
    names = ClassSet.from_yaml(tiny_demo / "classes.yaml").names
    for case, (path, expect) in hostile_files(tmp_path / "files", names).items():
        out = tmp_path / f"out_{path.stem}"
        proc = subprocess.run([sys.executable, "-m", "css_ros.evaluation.cli", str(tiny_demo / "bag"), "--out",
                               str(out), "--quiet", "--sensor-model", str(path)], capture_output=True, text=True,
                              timeout=300, env=rh.node_env(0), preexec_fn=_capped)
        err = proc.stderr.strip().splitlines()
        assert proc.returncode == 1 and len(err) == 1, (case, proc.stdout[-2000:], proc.stderr[-2000:])
        assert err[0].startswith(f"css_replay: error: sensor model {path}") and _says(err[0], expect), (case, err[0])
        assert "unexpected" not in err[0]
        assert not (out / "report.md").exists() and not (out / "metrics.json").exists(), case


@pytest.mark.slow
def test_css_node_refuses_hostile_sensor_models_with_cannot_start(tmp_path):
    """css_node with sensor_model:=FILE: exit 2 and one FATAL ``cannot start: sensor model FILE: ...`` line naming the
    fault and the parameter, no traceback (side by side, each under the 4 GiB cap)."""
    model = rh.write_wall_model(tmp_path / "wall.ply")
    names = ClassSet.default(rh.NUM_CLASSES).names
    cases = hostile_files(tmp_path / "files", names)
    procs = {}
    for case, (path, _) in cases.items():
        args = [sys.executable, "-m", "css_ros.node", "--ros-args", "-p", f"model_path:={model}", "-p",
                "class_file:=''", "-p", f"num_classes:={rh.NUM_CLASSES}", "-p", "warmup:=false", "-p",
                f"sensor_model:={path}", "-p", f"checkpoint_path:={tmp_path / 'map.npz'}"]
        procs[case] = subprocess.Popen(args, env=rh.node_env(rh.next_domain_id()), stdout=subprocess.PIPE,
                                       stderr=subprocess.STDOUT, text=True, preexec_fn=_capped)
    for case, proc in procs.items():
        out, _ = proc.communicate(timeout=180)
        path, expect = cases[case]
        fatal = [line for line in out.splitlines() if "cannot start:" in line]
        assert proc.returncode == 2 and "Traceback" not in out, (case, out[-3000:])
        assert len(fatal) == 1 and "FATAL" in fatal[0], (case, out[-3000:])
        assert f"sensor model {path}" in fatal[0] and _says(fatal[0], expect), (case, fatal[0])
        assert f"(parameter sensor_model='{path}')" in fatal[0], (case, fatal[0])
