"""css_calibrate's --out is checked when parsed, before any work (a usage error naming --out, exit 2): never an
input of the run or a file inside an input bag (J), never a directory nor in a folder where nothing can be
written (K), and no missing folder is created (L); a late write failure names --out and leaves no figure behind;
a class file whose vote table would exceed the bound is refused before pass 1 (F). css_ros/calibration/cli.py."""
from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from css_ros.calibration.cli import figure_paths, main, write_outputs
from css_ros.calibration.learn import LabelDepthCounts
from css_ros.engine.classes import ClassSet
from css_ros.engine.sensor_model import MAX_VOTE_TABLE_ENTRIES, SensorModel, uniform_edges
from css_ros.errors import CssError


def _scene(root: Path) -> Path:
    """A folder as css_calibrate expects one (bag/metadata.yaml, model.ply, classes.yaml beside it); the files are
    stand-ins: every refusal here comes before any of them is read."""
    (root / "bag").mkdir(parents=True)
    for name in ("bag/metadata.yaml", "bag/data_0.mcap", "model.ply", "classes.yaml", "css_node.yaml"):
        (root / name).write_text(f"original {name}\n")
    return root / "bag"


def _snapshot(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): p.read_text() for p in sorted(root.rglob("*")) if p.is_file()}


def _usage_error(capsys, argv: list[str]) -> str:
    start = time.monotonic()
    assert main(argv) == 2
    assert time.monotonic() - start < 5.0
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("css_calibrate: error: --out "), err[-1]
    return err[-1]


@pytest.mark.parametrize("out, says", [
    ("classes.yaml", "is an input of this run (the class file {root}/classes.yaml): it would be overwritten"),
    ("css_node.yaml", "is an input of this run (the parameter file {root}/css_node.yaml)"),
    ("bag/metadata.yaml", "would be written inside the input bag {root}/bag; write it outside the bag"),
    ("bag/sm.yaml", "would be written inside the input bag {root}/bag"),
    ("bag/../bag/./x.yaml", "would be written inside the input bag {root}/bag"),
    ("link/sm.yaml", "would be written inside the input bag {root}/bag"),     # a symlink to the bag folder
])
def test_out_that_is_an_input_is_refused_before_any_work(tmp_path, capsys, out, says):
    """J: the old css_calibrate overwrote the bag's class file or metadata.yaml and exited 0."""
    bag = _scene(tmp_path)
    (tmp_path / "link").symlink_to(bag)
    before = _snapshot(tmp_path)
    line = _usage_error(capsys, [str(bag), "--out", str(tmp_path / out), "--no-confidence", "--quiet"])
    assert f"--out {tmp_path / out}" in line and says.format(root=tmp_path) in line, line
    assert _snapshot(tmp_path) == before


def test_out_equal_to_model_or_classes_given_explicitly_is_refused(tmp_path, capsys):
    """J: --model / --classes elsewhere, --out the same file (through a hard link too)."""
    bag = _scene(tmp_path / "scene")
    classes = tmp_path / "my_classes.yaml"
    classes.write_text("x\n")
    line = _usage_error(capsys, [str(bag), "--classes", str(classes), "--out", str(classes)])
    assert f"is an input of this run (--classes {classes})" in line, line
    (tmp_path / "alias.yaml").hardlink_to(classes)
    line = _usage_error(capsys, [str(bag), "--classes", str(classes), "--out", str(tmp_path / "alias.yaml")])
    assert f"is an input of this run (--classes {classes})" in line, line
    assert classes.read_text() == "x\n"


def test_out_directory_or_unwritable_folder_is_refused_before_any_work(tmp_path, capsys):
    """K: the old css_calibrate found these after the whole pass (an hour on real data), named a temporary file and
    left the figures behind."""
    bag = _scene(tmp_path / "scene")
    (tmp_path / "isdir.yaml").mkdir()
    line = _usage_error(capsys, [str(bag), "--out", str(tmp_path / "isdir.yaml")])
    assert line.endswith(f"--out {tmp_path / 'isdir.yaml'} is a directory: name the .yaml file to write"), line
    (tmp_path / "fig_confusion.png").mkdir()
    line = _usage_error(capsys, [str(bag), "--out", str(tmp_path / "fig.yaml")])
    assert f"its figure {tmp_path / 'fig_confusion.png'} would replace a directory" in line, line
    (tmp_path / "afile").write_text("")
    line = _usage_error(capsys, [str(bag), "--out", str(tmp_path / "afile" / "sm.yaml")])
    assert f"{tmp_path / 'afile'} is not a directory" in line, line
    if Path("/proc/self").is_dir():                 # a folder where no file can be created, even by root
        line = _usage_error(capsys, [str(bag), "--out", "/proc/css_calibrate_test.yaml"])
        assert "--out /proc/css_calibrate_test.yaml: cannot write in /proc (" in line, line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "fig_confusion.png", "isdir.yaml", "scene"]


def test_missing_out_folder_is_refused_not_created(tmp_path, capsys):
    """L: the old css_calibrate created every missing folder of --out (a typo made directories anywhere)."""
    bag = _scene(tmp_path / "scene")
    out = tmp_path / "typo" / "deeper" / "sm.yaml"
    line = _usage_error(capsys, [str(bag), "--out", str(out)])
    assert line.endswith(f"--out {out}: its folder {out.parent} does not exist (css_calibrate creates no folder: "
                         "make it first)"), line
    assert not (tmp_path / "typo").exists()


def test_the_default_out_folder_is_made_only_once_the_options_are_right(tmp_path, capsys, monkeypatch):
    """The default --out (out/calibration/sensor_model.yaml under the working folder, beside css_replay's
    out/replay_<bag>) is the one folder css_calibrate makes; not on a usage error, and never inside an input bag."""
    from css_ros.calibration.cli import DEFAULT_OUT, build_parser, option_error

    assert DEFAULT_OUT == Path("out") / "calibration" / "sensor_model.yaml"
    bag = _scene(tmp_path / "scene")
    monkeypatch.chdir(tmp_path)
    assert main([str(bag), "--heldout-every", "1"]) == 2     # another option wrong: no folder made
    assert not (tmp_path / "out").exists()
    args = build_parser().parse_args([str(bag)])
    assert args.out == DEFAULT_OUT and option_error(args) is None
    assert (tmp_path / "out" / "calibration").is_dir() and not any((tmp_path / "out" / "calibration").iterdir())
    monkeypatch.chdir(tmp_path / "scene" / "bag")   # run from inside the bag: the default would land in it
    line = _usage_error(capsys, [str(bag)])
    assert "would be written inside the input bag" in line and not (bag / "out").exists(), line


def test_help_states_the_out_rules():
    """L: the decision is in --help (the console script, as a user runs it)."""
    proc = subprocess.run([sys.executable, "-m", "css_ros.calibration.cli", "--help"], capture_output=True,
                          text=True, timeout=60)
    text = " ".join(proc.stdout.split())
    assert proc.returncode == 0
    assert "default out/calibration/sensor_model.yaml, whose folder is made when missing" in text, text
    assert "The folder of any other --out must exist and be writable: css_calibrate creates no other folder" in text
    assert "must not be inside an input bag nor be an input of the run" in text, text


def test_a_late_write_failure_names_out_and_removes_the_figures(tmp_path, monkeypatch):
    """K: when the YAML cannot be written after the figures were, the error names --out and no figure is left."""
    names = ("a", "b", "c")
    classes = ClassSet(names, np.array([[200, 0, 0], [0, 200, 0], [0, 0, 200]], np.uint8))
    edges = uniform_edges(8.0, 4.0)
    counts = LabelDepthCounts(3, edges)
    sensor = SensorModel(names, edges, np.full((3, 2), 0.5))
    out = tmp_path / "sm.yaml"

    def fail(self, path):
        raise OSError(28, "No space left on device", str(path) + ".tmp")

    monkeypatch.setattr(SensorModel, "save", fail)
    with pytest.raises(CssError) as info:
        write_outputs(out, sensor, counts, classes, [])
    assert str(info.value) == f"cannot write --out {out} (No space left on device); nothing was written"
    assert not any(p.exists() for p in figure_paths(out).values()) and list(tmp_path.iterdir()) == []


def test_a_class_file_beyond_the_vote_table_bound_is_refused_before_pass_1(tmp_path, capsys):
    """F: 1100 classes x 16 bins x 1100 classes (19 M) is above MAX_VOTE_TABLE_ENTRIES: one line naming the class file and the
    bound, exit 1, before any frame is read."""
    from test_calibrate_options import _bag

    bag = _bag(tmp_path / "scene", "plain")
    classes = tmp_path / "many_classes.yaml"
    ClassSet(tuple(f"c{i}" for i in range(1100)), np.zeros((1100, 3), np.uint8)).to_yaml(classes)
    assert main([str(bag), "--classes", str(classes), "--out", str(tmp_path / "sm.yaml"), "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"css_calibrate: error: {classes}: 1100 classes x 16 "
                                               "depth bins need a vote table"), err
    assert f"more than {MAX_VOTE_TABLE_ENTRIES} (2^24)" in err[0]
    assert not (tmp_path / "sm.yaml").exists()
