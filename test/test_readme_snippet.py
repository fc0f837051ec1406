"""The README's examples on the shipped demo: the Python API snippet runs as written, from an empty working folder, and
its results are real (images of the bag's camera size, labels that match the ground truth, finite scores, a map that
saves and loads with every frame it fused); the css_ctl query example's points lie on surfaces of the demo room."""
from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from css_ros.io.bag import InputBag
from css_ros.io.messages import camera_info_to_intrinsics, image_to_array

ROOT = Path(__file__).resolve().parents[1]
DEMO_BAG = ROOT / "bags" / "demo" / "bag"

#: Run in the child after the snippet (its names in ``ns``): what the test checks, as JSON on the last line.
REPORT = r"""
import json, sys
import numpy as np
ns = {"__name__": "__main__"}
exec(compile(open(sys.argv[1]).read(), "README.md (Python API)", "exec"), ns)
view, scores, picks, smap = ns["view"], ns["scores"], ns["picks"], ns["smap"]
np.save("labels.npy", view.labels)
print(json.dumps({"u_var": view.u_var, "u_exp": view.u_exp, "scores": np.asarray(scores).tolist(),
                  "picks": [int(i) for i in picks.indices], "frames": smap.frames_observed,
                  "num_classes": smap.num_classes, "num_gaussians": smap.model.num_gaussians}))
"""


def readme_snippet() -> str:
    """The first ``python`` block of the README's "Python API" section."""
    text = (ROOT / "README.md").read_text()
    section = text.split("\n## Python API\n", 1)[1].split("\n## ", 1)[0]
    match = re.search(r"```python\n(.*?)```", section, re.S)
    assert match, "no python block in the README's Python API section"
    return match.group(1)


def demo_frame(index: int) -> tuple[tuple[int, int], np.ndarray]:
    """((height, width) of camera_info, ground-truth labels) of the demo bag's frame ``index`` (read independently of
    the snippet)."""
    with InputBag(DEMO_BAG) as bag:
        info = next(m.msg for m in bag.messages(["/camera_info"]))
        gt = [m.msg for m in bag.messages(["/segmentation_gt"])][index]
    _, width, height = camera_info_to_intrinsics(info)
    return (height, width), image_to_array(gt)


@pytest.mark.slow
@pytest.mark.skipif(not DEMO_BAG.is_dir(), reason="the demo bag is not in this checkout")
def test_the_python_api_snippet_runs_as_written_on_the_demo(tmp_path):
    snippet = readme_snippet()
    assert "K, width, height" in snippet and "scene.ply" not in snippet   # no placeholders left
    frame = int(re.search(r"cam, labels = cams\[(\d+)\], segs\[\1\]", snippet).group(1))
    (tmp_path / "snippet.py").write_text(snippet)
    # an empty working folder, away from the clone: the demo is found by resolve_data_path, out/ is made here
    r = subprocess.run([sys.executable, "-c", REPORT, "snippet.py"], cwd=tmp_path, capture_output=True, text=True,
                       timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    got = json.loads(r.stdout.strip().splitlines()[-1])

    (h, w), gt = demo_frame(frame)
    labels = np.load(tmp_path / "labels.npy")
    assert labels.shape == (h, w) == (192, 256) and labels.dtype == np.int32
    seen = (gt != 255) & (labels != 255)
    assert seen.mean() > 0.9   # the room fills the view: few unknown pixels
    assert np.mean(labels[seen] == gt[seen]) > 0.8   # the fused map's labels match the ground truth
    assert np.isfinite(got["u_var"]) and 0.0 < got["u_var"] <= 0.25   # a Beta's variance is at most 1/4
    assert np.isfinite(got["u_exp"]) and 0.0 <= got["u_exp"] <= 1.0
    scores = np.array(got["scores"])
    assert scores.shape == (120 - frame - 1, 3) and np.all(np.isfinite(scores)) and np.all(scores[:, 2] >= 0)
    assert len(set(got["picks"])) == 8 and all(0 <= i < len(scores) for i in got["picks"])
    # the loaded map: every frame observed or updated, the demo's classes and Gaussians
    assert (got["frames"], got["num_classes"], got["num_gaussians"]) == (frame + 1, 16, 50_000)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["labels.npy", "out", "snippet.py"]
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["map.npz"]


def readme_query_points() -> np.ndarray:
    """(M, 3) points of the README's ``css_ctl query`` example (the same line as css_ctl --help's)."""
    from css_ros.clients.ctl import EXAMPLES

    line = re.search(r"^css_ctl query ([-0-9. ]+?)\s+#", (ROOT / "README.md").read_text(), re.M)
    assert line, "no css_ctl query example with numbers in the README"
    assert f"css_ctl query {line.group(1).strip()}\n" in EXAMPLES   # css_ctl --help shows the same points
    return np.array(line.group(1).split(), dtype=float).reshape(-1, 3)


def test_the_css_ctl_query_example_points_lie_on_the_demo_rooms_surfaces():
    """With the demo model's ground truth (its per-Gaussian ``class_id``) as the map, the README's query points answer
    the classes the README names, not unknown; a mid-air point answers unknown."""
    from plyfile import PlyData

    from css_ros import ClassSet, GaussianModel, SemanticMap

    model = GaussianModel.from_ply(ROOT / "bags" / "demo" / "model.ply")
    class_id = np.asarray(PlyData.read(str(ROOT / "bags" / "demo" / "model.ply"))["vertex"]["class_id"], np.int64)
    names = ClassSet.from_yaml(ROOT / "bags" / "demo" / "classes.yaml").names
    smap = SemanticMap(model, len(names))
    smap.concentrations[np.arange(model.num_gaussians), class_id] += 100.0   # every Gaussian well observed
    q = smap.query_points(readme_query_points())
    assert [names[c] for c in q.labels] == ["table", "floor", "wall"]
    assert np.all(q.background < smap.unknown_threshold)
    assert smap.query_points(np.array([[0.5, 0.2, 1.0]])).labels[0] == smap.ignore_label   # free space: unknown
