"""The second hostile probe of sensor-model files (css_ros/engine/sensor_model.py): every OSError and every
non-regular file is a SensorModelError naming the file and the real reason (A, H); echoed values are cut (B);
numbers are bounded in length and sexagesimal ones refused before conversion (C); confidence coefficients are
bounded and the logistic score agrees, NaN-free and without warnings, on numpy and the compiled kernels (D);
all-zero weights (E), oversized vote tables (F), values of the wrong YAML type and duplicate keys (G) are refused.
css_replay --sensor-model gives the same refusals in one line, and reports pixels left out of an ECE (D)."""
from __future__ import annotations

import errno
import os
import resource
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml

sys.path.insert(0, str(Path(__file__).parent))
import ros_helpers as rh  # noqa: E402

from css_ros.engine.classes import ClassSet  # noqa: E402
from css_ros.engine.pixel_math import confidence_score  # noqa: E402
from css_ros.engine.sensor_model import (MAX_CONFIDENCE_COEF, MAX_DEPTH_BINS, MAX_SHOWN_CHARS,  # noqa: E402
                                         MAX_VOTE_TABLE_ENTRIES, MAX_YAML_NUMBER_CHARS, MIN_LARGEST_WEIGHT,
                                         ConfidenceMap, SensorModel, uniform_edges)
from css_ros.errors import SensorModelError  # noqa: E402
from css_ros.io.paths import resolve_data_path  # noqa: E402

NAMES = ("floor", "wall", "chair", "table")


def _good(names: tuple[str, ...] = NAMES) -> dict:
    """A valid model's dict without its fingerprint (so that edits of the tables still load)."""
    c = len(names)
    cmap = ConfidenceMap(np.array([1.2, 0.3, -0.2]), np.array([0.0, 0.5, 1.0]), np.array([0.05, 0.6, 0.97]))
    d = SensorModel(names, np.array([0.0, 4.0, 20.0]), np.full((c, 2), 0.5), None, cmap).to_dict()
    del d["fingerprint"]
    return d


class _NoAliases(yaml.SafeDumper):
    """Writes a list used twice twice (the reader refuses aliases)."""

    def ignore_aliases(self, data: object) -> bool:
        return True


def _write(path: Path, d: dict | str) -> Path:
    path.write_text(d if isinstance(d, str) else yaml.dump(d, Dumper=_NoAliases, sort_keys=False))
    return path


def _refusal(path: str | Path, class_names: tuple[str, ...] | None = None) -> str:
    with pytest.raises(SensorModelError) as info:
        SensorModel.load(path, class_names)
    return str(info.value)


# ----------------------------------------------------------------------------------------- A, H: the file itself
def test_every_os_error_is_a_sensor_model_error_with_its_reason(tmp_path, monkeypatch):
    """A: a name too long (absolute, and relative through resolve_data_path as css_node resolves it) and a
    permission error from stat or open are SensorModelError naming the file and the reason, never "does not exist"
    (the old reader let pathlib's OSError through)."""
    long_name = tmp_path / ("a" * 300 + ".yaml")
    msg = _refusal(long_name)
    assert msg == f"sensor model {long_name} cannot be read: file name too long", msg
    relative = resolve_data_path("b" * 300 + ".yaml")          # pathlib's exists() raised ENAMETOOLONG here
    assert "cannot be read: file name too long" in _refusal(relative)
    deep = "/tmp/" + "/".join(["c" * 200] * 25) + ".yaml"       # 5000 characters: the message quotes 1024 of them
    msg = _refusal(deep)
    assert msg.endswith("… cannot be read: file name too long") and len(msg) < 1100, msg[-200:]

    good = _write(tmp_path / "good.yaml", _good())
    import css_ros.engine.sensor_model as sm

    def denied(*args, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied", str(args[0]))

    monkeypatch.setattr(sm.os, "open", denied)                  # root reads mode-000 files: simulate EACCES
    assert _refusal(good) == f"sensor model {good} cannot be read: permission denied"
    monkeypatch.setattr(sm.os, "stat", denied)
    assert _refusal(good) == f"sensor model {good} cannot be read: permission denied"


def test_directories_fifos_devices_and_loops_say_what_they_are(tmp_path):
    """H: never "does not exist" unless ENOENT; a FIFO or a device is refused from its stat, never opened (a FIFO
    without a writer would block the reader for ever)."""
    (tmp_path / "adir.yaml").mkdir()
    os.mkfifo(tmp_path / "fifo.yaml")
    (tmp_path / "zero.yaml").symlink_to("/dev/zero")
    (tmp_path / "loop1.yaml").symlink_to(tmp_path / "loop2.yaml")
    (tmp_path / "loop2.yaml").symlink_to(tmp_path / "loop1.yaml")
    (tmp_path / "dangling.yaml").symlink_to(tmp_path / "nothing.yaml")
    (tmp_path / "file").write_text("x")
    for name, says in (("adir.yaml", "is a directory, not a regular file"),
                       ("fifo.yaml", "is a FIFO (named pipe), not a regular file"),
                       ("zero.yaml", "is a character device, not a regular file"),
                       ("loop1.yaml", "cannot be read: symlink loop (too many levels of symbolic links)"),
                       ("dangling.yaml", "does not exist"), ("missing.yaml", "does not exist"),
                       ("file/sm.yaml", "does not exist (a part of its path is not a directory)")):
        assert _refusal(tmp_path / name) == f"sensor model {tmp_path / name} {says}", name
    assert _refusal("") == "sensor model path is empty"


# ----------------------------------------------------------------------------------------- B: echoed values
def test_echoed_values_are_cut(tmp_path):
    """B: a class name or a version of 100 000 characters is quoted as its first MAX_SHOWN_CHARS and '…' (the old
    message held it whole: a 30 MB log line)."""
    d = _good(("B" * 100_000,) + NAMES[1:])
    msg = _refusal(_write(tmp_path / "long_class.yaml", d), NAMES)
    assert f"class 0 is '{'B' * MAX_SHOWN_CHARS}'…, the map's class file says 'floor'" in msg and len(msg) < 300
    d = dict(_good(), version=7)
    text = yaml.safe_dump(d).replace("version: 7", "version: 7" + "0" * 20 + "x" * 100_000)
    msg = _refusal(_write(tmp_path / "long_version.yaml", text))
    assert "version must be an integer, got '70000" in msg and "…" in msg and len(msg) < 300, msg[:400]


# ----------------------------------------------------------------------------------------- C: number tokens
def _capped() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (4 * 2**30, 4 * 2**30))


def test_long_and_sexagesimal_numbers_are_refused_before_conversion(tmp_path):
    """C: a float of more than MAX_YAML_NUMBER_CHARS characters and any YAML 1.1 sexagesimal number are refused
    (the old reader accepted ``0:0:0.5`` as 0.5 and turned 20 MB of ``1:1:...`` into millions of floats, 1.3 GB)."""
    text = yaml.safe_dump(_good())
    long_float = "0." + "5" * 100
    for name, value, says in (("sexagesimal", "0:0:0.5", "the sexagesimal number '0:0:0.5' (YAML 1.1 base 60)"),
                              ("sexagesimal_int", "1:30", "the sexagesimal number '1:30'"),
                              ("long_float", long_float, f"a number of 102 characters (at most "
                                                         f"{MAX_YAML_NUMBER_CHARS})"),
                              ("tagged_long", "!!float " + long_float, "a number of 102 characters")):
        path = _write(tmp_path / f"{name}.yaml", text.replace("- 0.5", f"- {value}", 1))
        assert says in _refusal(path), name
    # 10 MB of sexagesimal float in a child process: refused at < 400 MB peak (the old reader: ~700 MB, 2 s)
    path = _write(tmp_path / "huge.yaml", text.replace("- 0.5", "- 1" + ":59" * 3_300_000 + ".5", 1))
    script = ("from css_ros.engine.sensor_model import SensorModel\nimport sys\n"
              "try:\n    SensorModel.load(sys.argv[1])\nexcept Exception as exc:\n    print(type(exc).__name__, exc)\n"
              "print([ln for ln in open('/proc/self/status') if ln.startswith('VmHWM:')][0].split()[1])\n")
    proc = subprocess.run([sys.executable, "-c", script, str(path)], capture_output=True, text=True, timeout=60,
                          env=rh.node_env(0), preexec_fn=_capped)
    out = proc.stdout.splitlines()
    assert out[0].startswith("SensorModelError") and "a number of 9900003 characters" in out[0], proc.stdout[-500:]
    assert int(out[1]) / 1024 < 400, out


# ----------------------------------------------------------------------------------------- D: confidence map
def test_confidence_coefficients_are_bounded(tmp_path):
    """D: |coef| beyond MAX_CONFIDENCE_COEF is refused, naming confidence.coef (1e308 loaded and made ~/confidence
    NaN on the torch backend); the bound itself loads, and its score is finite without a RuntimeWarning even at
    the largest float evidence."""
    for coef in ([1e308, -1e308, 0.0], [1e308, 1e308, 1e308], [0.0, 0.0, 2 * MAX_CONFIDENCE_COEF]):
        d = _good()
        d["confidence"]["coef"] = coef
        msg = _refusal(_write(tmp_path / "coef.yaml", d))
        assert f"confidence.coef must be within +-{MAX_CONFIDENCE_COEF:g}" in msg, msg
    with pytest.raises(SensorModelError, match="coef must be within"):
        ConfidenceMap(np.array([1e7, 0.0, 0.0]), np.array([0.0, 1.0]), np.array([0.0, 1.0]))
    d = _good()
    d["confidence"]["coef"] = [MAX_CONFIDENCE_COEF, -MAX_CONFIDENCE_COEF, MAX_CONFIDENCE_COEF]
    m = SensorModel.load(_write(tmp_path / "edge.yaml", d))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        p = m.confidence(np.array([1e-9, 0.5, 1.0]), np.array([0.0, 1e6, np.finfo(np.float64).max]))
    assert np.all(np.isfinite(p))


def test_logistic_score_agrees_on_every_backend_for_nan_and_inf():
    """D: ConfidenceMap.score (numpy: the torch backend's final form), the pixel_math kernel in plain Python and
    compiled by numba (the CPU backend; CUDA compiles the same function) give one answer for NaN / inf / negative
    inputs and 0 x inf: a NaN argument scores 0.5, +-inf is clipped; no NaN, no RuntimeWarning."""
    from numba import njit

    compiled = njit(confidence_score)
    inputs = [(e, ev) for e in (np.nan, -np.inf, -1.0, 0.0, 1e-9, 0.3, 1.0, 2.0, np.inf)
              for ev in (np.nan, -np.inf, -5.0, 0.0, 3.0, 1e300, np.inf)]
    e = np.array([x[0] for x in inputs])
    ev = np.array([x[1] for x in inputs])
    for coef in ([1.2, 0.3, -0.2], [0.0, 0.0, 0.0], [MAX_CONFIDENCE_COEF, -MAX_CONFIDENCE_COEF, 1.0],
                 [-MAX_CONFIDENCE_COEF, MAX_CONFIDENCE_COEF, -MAX_CONFIDENCE_COEF]):
        cmap = ConfidenceMap(np.array(coef), np.array([0.0, 1.0]), np.array([0.0, 1.0]))
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            ref = cmap.score(e, ev)
        assert np.all(np.isfinite(ref)), coef
        py = np.array([confidence_score(a, b, *coef) for a, b in inputs])
        nb = np.array([compiled(a, b, *coef) for a, b in inputs])
        np.testing.assert_allclose(py, ref, rtol=0, atol=1e-12, err_msg=str(coef))
        np.testing.assert_allclose(nb, ref, rtol=0, atol=1e-12, err_msg=str(coef))
    zero_times_inf = ConfidenceMap(np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0]), np.array([0.0, 1.0]))
    assert zero_times_inf.score(np.array([0.9]), np.array([np.inf]))[0] == 0.5


def test_replay_headline_says_when_pixels_were_left_out_of_an_ece():
    """D: an ECE over pixels some of which were NaN is never printed bare: the summary says how many were left
    out (the old line read "calibrated confidence 0.750")."""
    from css_ros.evaluation.replay import headline

    def summary(ece, dropped):
        return {"ece": ece, "brier": 0.1, "mean_confidence": 0.5, "accuracy": 0.5, "n": 10, "dropped": dropped}

    metrics = {"segmentation": {}, "image_level": {}, "frames": {"processed": 5, "trained": 5, "skipped": {}},
               "timing": {"total_s": 1.0},
               "calibration": {"online": {"expectation": summary(0.1, 0), "confidence": summary(0.75, 28714)}}}
    text = headline(metrics)
    assert "E 0.100, calibrated confidence 0.750 (28714 pixels with a NaN / inf value left out)" in text, text
    metrics["calibration"]["online"]["confidence"] = summary(None, 49152)
    assert "calibrated confidence n/a (49152 pixels with a NaN / inf value left out)" in headline(metrics)


# ----------------------------------------------------------------------------------------- E, F, G: the values
def test_all_zero_weights_are_refused(tmp_path):
    """E: a model whose every weight is 0 (or below MIN_LARGEST_WEIGHT) would leave the map at its prior: refused."""
    for value in (0.0, 1e-9):
        d = dict(_good(), weight=[[value, value]] * len(NAMES))
        msg = _refusal(_write(tmp_path / "zero.yaml", d))
        assert f"every weight is below {MIN_LARGEST_WEIGHT:g}" in msg and "stay at its prior" in msg, msg
    with pytest.raises(SensorModelError, match="every weight is below"):
        SensorModel(NAMES, [0.0, 1.0], np.zeros((len(NAMES), 1)))


def test_vote_tables_beyond_the_bound_are_refused_at_load(tmp_path):
    """F: classes x bins x classes above MAX_VOTE_TABLE_ENTRIES is refused when the file is read (1500 classes x 256
    bins, a 1.9 MB file, asked 4.3 GiB per table copy when the map was built); the bound itself is accepted."""
    c, b = 300, 256                                            # 23 M entries
    names = tuple(f"c{i}" for i in range(c))
    d = {"format": "css_ros.sensor_model", "version": 1, "classes": list(names),
         "depth_edges": [i * 0.5 for i in range(b + 1)], "weight": [[0.5] * b] * c}
    msg = _refusal(_write(tmp_path / "many.yaml", yaml.dump(d, Dumper=_NoAliases, default_flow_style=True,
                                                            width=10**9)))
    assert (f"300 classes x 256 depth bins need a vote table of {c * b * c} entries (0.2 GB per copy), more than "
            f"{MAX_VOTE_TABLE_ENTRIES} (2^24)") in msg, msg
    ok = SensorModel(tuple(f"c{i}" for i in range(256)), np.arange(MAX_DEPTH_BINS + 1) * 0.5,
                     np.full((256, MAX_DEPTH_BINS), 0.5))
    assert ok.num_classes ** 2 * ok.num_bins == MAX_VOTE_TABLE_ENTRIES
    with pytest.raises(SensorModelError, match="more than 256 bins"):
        uniform_edges(8.0, 1e-320)


def test_values_of_the_wrong_yaml_type_and_duplicate_keys_are_refused(tmp_path):
    """G: version must be an integer (true == 1 and 1.0 were accepted), weights numbers (the strings "0.5", true,
    !!binary bytes were converted), and a key may appear once (the second silently won)."""
    text = yaml.safe_dump(_good(), sort_keys=False)
    cases = {
        "version true": (text.replace("version: 1", "version: true"), "version must be an integer, got True (a boolean)"),
        "version 1.0": (text.replace("version: 1", "version: 1.0"), "version must be an integer, got 1.0 (a float)"),
        "weight string": (text.replace("- 0.5", "- '0.5'", 1), "weight must hold numbers, found '0.5' (a string)"),
        "weight bool": (text.replace("- 0.5", "- true", 1), "weight must hold numbers, found True (a boolean)"),
        "weight null": (text.replace("- 0.5", "- null", 1), "weight must hold numbers, found None (null)"),
        "weight binary": (text.replace("- 0.5", "- !!binary MC41", 1), "YAML tag tag:yaml.org,2002:binary"),
        "knot string": (text.replace("- 0.05", "- '0.05'", 1), "knots_y must hold numbers, found '0.05'"),
        "duplicate weight": (text + "weight: [[1, 1], [1, 1], [1, 1], [1, 1]]\n", "key 'weight' given twice"),
        "duplicate format": ("format: not_a_model\n" + text, "key 'format' given twice"),
    }
    for case, (body, says) in cases.items():
        path = _write(tmp_path / f"{case.replace(' ', '_')}.yaml", body)
        msg = _refusal(path)
        assert msg.startswith(f"sensor model {path}") and says in msg, (case, msg)


# ----------------------------------------------------------------------------------------- css_replay
def test_css_replay_gives_the_same_refusals_in_one_line(tiny_demo, tmp_path):
    """css_replay BAG --sensor-model FILE (side by side; the reader is SensorModel.load, whose every refusal is
    tested above): exit 1, one line ``css_replay: error: sensor model FILE ...`` with the reader's reason (the old
    css_replay said "File name too long: /tmp/aaa..." without naming the file's role, printed a 100 kB line for B,
    replayed D with exit 0 and said "does not exist" of a FIFO)."""
    names = ClassSet.from_yaml(tiny_demo / "classes.yaml").names
    good = _good(names)
    os.mkfifo(tmp_path / "fifo.yaml")
    coef = dict(good, confidence=dict(good["confidence"], coef=[1e308, -1e308, 0.0]))
    cases = {
        "A name too long": (tmp_path / ("a" * 300 + ".yaml"), "cannot be read: file name too long"),
        "B long class name": (_write(tmp_path / "b.yaml", dict(good, classes=["B" * 100_000] + list(names[1:]))),
                              f"class 0 is '{'B' * MAX_SHOWN_CHARS}'…"),
        "D huge coef": (_write(tmp_path / "d.yaml", coef), "confidence.coef must be within"),
        "H FIFO": (tmp_path / "fifo.yaml", "is a FIFO (named pipe)"),
    }
    procs = {case: subprocess.Popen([sys.executable, "-m", "css_ros.evaluation.cli", str(tiny_demo / "bag"), "--out",
                                     str(tmp_path / f"out{i}"), "--quiet", "--sensor-model", str(path)],
                                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=rh.node_env(0))
             for i, (case, (path, _)) in enumerate(cases.items())}
    for i, (case, proc) in enumerate(procs.items()):
        out, err = proc.communicate(timeout=300)
        path, says = cases[case]
        lines = err.strip().splitlines()
        assert proc.returncode == 1 and len(lines) == 1, (case, out[-1000:], err[-1000:])
        assert lines[0].startswith(f"css_replay: error: sensor model {path}") and says in lines[0], (case, lines[0][:500])
        assert len(lines[0]) < 1000 and not (tmp_path / f"out{i}" / "report.md").exists(), case
