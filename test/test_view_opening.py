"""css_view's first picture, as a new user gets it: ``css_view`` started from the command line (every Gaussian of
the demo's 50k drawn), opened in headless Chromium (software WebGL), the first settled screenshot, no interaction.

Two maps: (a) the replay folder of the shipped demo bag (css_replay, as the README's command 1 runs it), and (b) a
bare map file + splat of the same room turned so that its vertical axis is y, with no trajectory and no frame.
The first screenshot must show the observed surfaces: at least MIN_CLASSES of the map's classes and class colours
on at least MIN_CLASS_SHARE of the canvas. Pixels are classified against the class file's palette here (colour
of a class over the white background, and not the grey of unobserved Gaussians), not by the viewer's code.
Set CSS_WRITE_SCREENSHOTS=1 to refresh the README's opening screenshots in docs/img/.
"""
from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from cdp_browser import Browser, find_chromium, free_port

pytest.importorskip("viser", reason="css_view needs the viser extra: pip install -e '.[view]'")
pytest.importorskip("websocket", reason="the browser test needs websocket-client (in '.[all]')")

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "bags" / "demo"
IMG = ROOT / "docs" / "img"
WIDTH, HEIGHT = 760, 440
MIN_CLASSES = 5             # classes the first picture must show ...
MIN_CLASS_SHARE = 0.10      # ... and the share of the canvas in class colours
CLASS_MIN_PIXELS = 0.003    # a class counts as shown on at least this share of the canvas (not a few edge pixels)
MATCH_RGB = 40.0            # a pixel is drawn in a colour when within this RGB distance of a blend of it over white
GREY = (128, 128, 128)      # unobserved Gaussians (README: "grey")

pytestmark = pytest.mark.slow


def palette_of(class_file: Path) -> tuple[list[str], np.ndarray]:
    """(names, (C, 3) palette) read straight from the class YAML."""
    rows = sorted(yaml.safe_load(class_file.read_text())["classes"], key=lambda r: r["id"])
    return [r["name"] for r in rows], np.array([r["color"] for r in rows], np.float64)


def fit(px: np.ndarray, color) -> tuple[np.ndarray, np.ndarray]:
    """(coverage a in [0, 1], RGB residual) per pixel (P, 3) of the least-squares blend white + a (color - white):
    the page composites splats over its white background, and even dense surfaces let some of it through."""
    off, d = px - 255.0, np.asarray(color, np.float64) - 255.0
    a = np.clip(off @ d / max(float(d @ d), 1.0), 0.0, 1.0)
    return a, np.linalg.norm(off - a[:, None] * d, axis=1)


def classify(img: np.ndarray, palette: np.ndarray) -> np.ndarray:
    """(H, W) class index of every pixel drawn mostly (coverage >= 0.5) in a class colour, -1 elsewhere: white,
    page UI, blends of several colours, and every pixel that the grey of unobserved Gaussians over white explains
    as well (a dark grey class colour such as the demo's wall counts only where it is darker than that grey)."""
    px = img.reshape(-1, 3).astype(np.float64)
    fits = [fit(px, c) for c in palette]
    resid = np.stack([r for _, r in fits], axis=1)
    cover = np.stack([a for a, _ in fits], axis=1)
    best = np.argmin(resid, axis=1)
    rows = np.arange(len(px))
    ok = (resid[rows, best] <= MATCH_RGB) & (cover[rows, best] >= 0.5) & (fit(px, GREY)[1] > MATCH_RGB)
    return np.where(ok, best, -1).reshape(img.shape[:2])


def canvas_box(browser: Browser) -> tuple[int, int]:
    """(width, height) in CSS px of the 3D view (the largest canvas; it starts at the page's top-left)."""
    sizes = browser.evaluate("[...document.querySelectorAll('canvas')].map(c => "
                             "{const r = c.getBoundingClientRect(); return [r.left, r.top, r.width, r.height];})")
    left, top, w, h = max(sizes, key=lambda s: s[2] * s[3])
    assert (left, top) == (0, 0)
    return int(w), int(h)


def wait_until(predicate, timeout: float, what: str, poll: float = 0.2):
    """Poll ``predicate()`` until it returns something truthy; raise TimeoutError naming ``what``."""
    deadline = time.monotonic() + timeout
    while not (value := predicate()):
        if time.monotonic() > deadline:
            raise TimeoutError(f"waited {timeout:.0f} s for {what}")
        time.sleep(poll)
    return value


def first_picture(args: list[str], timeout: float = 300.0) -> tuple[np.ndarray, np.ndarray, str]:
    """Start ``css_view args`` (its own port), open its URL in headless Chromium and return (the first settled
    screenshot of the page, its 3D canvas, css_view's output). Settled: the splat is drawn (non-white pixels) and two screenshots
    in a row are equal."""
    if find_chromium() is None:
        pytest.skip("no chromium on PATH (CI installs Debian's chromium in .ci/run; apt-get install chromium)")
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.Popen([sys.executable, "-m", "css_ros.view.cli", *args, "--port", str(free_port())],
                            stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env=env)
    lines: list[str] = []

    def read() -> None:
        for line in proc.stdout:
            lines.append(line)
    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    browser = None
    try:
        end = time.monotonic() + timeout

        def url():
            found = [ln.split("open ", 1)[1].split()[0] for ln in list(lines) if "css_view: open http" in ln]
            assert found or proc.poll() is None, f"css_view exited {proc.poll()}: {''.join(lines)}"
            return found[0] if found else None
        address = wait_until(url, timeout, "css_view to print its URL")
        browser = Browser(WIDTH, HEIGHT)
        browser.goto(address)
        wait_until(lambda: browser.evaluate("document.querySelectorAll('canvas').length"), 60, "the page's canvas")

        def drawn(img: np.ndarray) -> bool:   # the splat is on the canvas (its size is final once the panel docks)
            w, h = canvas_box(browser)
            return bool(np.mean(np.abs(img[:h, :w].astype(np.int16) - 255).sum(axis=2) > 60) > 0.05)
        img = browser.stable_screenshot(max(end - time.monotonic(), 30.0), accept=drawn)
        w, h = canvas_box(browser)
        return img, img[:h, :w], "".join(lines)
    finally:
        if browser is not None:
            browser.close()
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
        reader.join(10)


def assert_shows_the_room(canvas: np.ndarray, class_file: Path, what: str) -> tuple[int, float]:
    names, palette = palette_of(class_file)
    labels = classify(canvas, palette)
    counts = np.bincount(labels[labels >= 0], minlength=len(names))
    shown = [names[c] for c in np.flatnonzero(counts >= CLASS_MIN_PIXELS * labels.size)]
    share = float(np.count_nonzero(labels >= 0)) / labels.size
    assert len(shown) >= MIN_CLASSES and share >= MIN_CLASS_SHARE, (
        f"{what}: the first picture shows {len(shown)} classes ({', '.join(shown)}) and class colours on "
        f"{share:.1%} of the canvas (want >= {MIN_CLASSES} and >= {MIN_CLASS_SHARE:.0%})")
    return len(shown), share


def save_shot(img: np.ndarray, name: str) -> None:
    from PIL import Image

    if os.environ.get("CSS_WRITE_SCREENSHOTS"):
        IMG.mkdir(parents=True, exist_ok=True)
        Image.fromarray(img).save(IMG / name)


@pytest.fixture(scope="module")
def replay(tmp_path_factory) -> Path:
    """The README's command 1 into a temporary folder: css_replay on the shipped demo bag."""
    out = tmp_path_factory.mktemp("replay") / "replay_demo"
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    res = subprocess.run([sys.executable, "-m", "css_ros.evaluation.cli", "--out", str(out), "--quiet"],
                         cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    assert res.returncode == 0, res.stdout + res.stderr
    assert (out / "map.npz").is_file() and (out / "trajectory.npz").is_file()
    return out


def test_the_demo_replay_opens_on_its_observed_room(replay):
    page, canvas, log = first_picture([str(replay)])
    assert "opens at trajectory frame" in log and "up +z (from trajectory)" in log, log
    save_shot(page, "css_view_opening.png")
    print("classes shown, class share:", assert_shows_the_room(canvas, DEMO / "classes.yaml", "css_view out/replay_demo"))


def test_a_bare_y_up_map_opens_inside_its_room(replay, tmp_path):
    """The replay's map and the demo splat turned by -90 degrees about x (z up becomes y up), saved as a plain
    map file and PLY: no trajectory, no splat_to_map, nothing says which way is up."""
    from css_ros.engine.gaussians import GaussianModel
    from css_ros.engine.semantic_map import SemanticMap
    from css_ros.engine.similarity import Similarity

    model = GaussianModel.from_ply(DEMO / "model.ply")
    fused = SemanticMap.load(replay / "map.npz", model)
    turn = Similarity.from_params([1.0, 0.0, 0.0, 0.0, -np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5)])
    np.testing.assert_allclose(turn.apply(np.array([[0.0, 0.0, 1.0]])), [[0.0, 1.0, 0.0]], atol=1e-12)
    turned = turn.transform_model(model)
    turned.to_ply(tmp_path / "room_y_up.ply")
    bare = SemanticMap(turned, fused.num_classes, prior=fused.prior, background=fused.background)
    bare.concentrations = fused.concentrations.copy()
    bare.save(tmp_path / "map.npz")
    page, canvas, log = first_picture([str(tmp_path / "map.npz"), "--model", str(tmp_path / "room_y_up.ply"),
                                 "--classes", str(DEMO / "classes.yaml")])
    assert "up +y (from surfaces)" in log, log
    save_shot(page, "css_view_opening_y_up.png")
    print("classes shown, class share:", assert_shows_the_room(canvas, DEMO / "classes.yaml", "a bare y-up map"))
