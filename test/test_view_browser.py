"""css_view in a real headless Chromium (software WebGL): what a person sees on the page.

The expectation comes from the engine: the same camera (read back from the browser) rendered by
``SemanticMap.render`` gives the label image whose class shares the canvas must show.
Set CSS_WRITE_SCREENSHOTS=1 to refresh the README screenshots in docs/img/.
"""
from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pytest

from cdp_browser import Browser, find_chromium, free_port

pytest.importorskip("viser", reason="css_view needs the viser extra: pip install -e '.[view]'")
pytest.importorskip("websocket", reason="the browser test needs websocket-client (in '.[all]')")

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "bags" / "demo"
IMG = ROOT / "docs" / "img"
WIDTH, HEIGHT = 760, 440
#: Gaussians drawn (the most informative ones, as --max-gaussians does): software WebGL draws every frame on
#: the CPU, and a smaller page settles in seconds
MAX_GAUSSIANS = 12_000
#: the "software WebGL" notice viser shows in the top-left corner (CSS px), left out of every comparison
#: (the test closes it; the box covers it while it fades)
NOTICE_BOX = (0, 0, 330, 160)
MATCH_RGB = 40.0      # a pixel shows a class when its colour is this close (RGB distance) to the palette colour
SHARE_TOL = 0.06      # absolute tolerance on each class's share of the class-coloured pixels

pytestmark = pytest.mark.slow


def demo_map():
    """The demo model with a map where every Gaussian holds its true class (the model's class_id field)
    with a seeded share of a second class, so E and Var vary over the map."""
    from plyfile import PlyData

    from css_ros.engine.classes import ClassSet
    from css_ros.engine.gaussians import GaussianModel
    from css_ros.engine.semantic_map import SemanticMap

    model = GaussianModel.from_ply(DEMO / "model.ply")
    truth = np.asarray(PlyData.read(str(DEMO / "model.ply"))["vertex"]["class_id"], dtype=np.int64)
    classes = ClassSet.from_yaml(DEMO / "classes.yaml")
    c = classes.num_classes
    rng = np.random.default_rng(7)
    n = model.num_gaussians
    strength = rng.uniform(2.0, 40.0, n)
    conc = np.full((n, c), 1e-3)
    conc[np.arange(n), truth] += strength
    conc[np.arange(n), (truth + 1) % c] += strength * rng.uniform(0.0, 0.6, n)
    smap = SemanticMap(model, c)
    smap.concentrations = conc
    return smap, classes


def match_colors(img: np.ndarray, region: np.ndarray, colors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel of ``region``: the index of the nearest of ``colors`` (K, 3) and whether the pixel is drawn
    mostly in it.

    A splat pixel is a colour c composited over the white background with coverage a:
    p = white + a (c - white). Per pixel and colour the least-squares a and the residual are computed; the
    pixel matches the colour with the smallest residual when that residual is <= MATCH_RGB and a >= 0.5
    (the engine labels the pixels whose background weight is below 0.5, unknown_threshold).
    """
    px = img[region].astype(np.float64) - 255.0                    # (P, 3) offset from white
    dirs = np.asarray(colors, np.float64) - 255.0                  # (K, 3)
    a = np.clip(px @ dirs.T / np.maximum((dirs ** 2).sum(axis=1), 1.0), 0.0, 1.0)   # (P, K)
    resid = np.linalg.norm(px[:, None, :] - a[:, :, None] * dirs[None], axis=2)     # (P, K)
    best = np.argmin(resid, axis=1)
    rows = np.arange(len(px))
    return best, (resid[rows, best] <= MATCH_RGB) & (a[rows, best] >= 0.5)


def class_shares(img: np.ndarray, palette: np.ndarray, region: np.ndarray) -> np.ndarray:
    """(C,) share of each class among the pixels of ``region`` drawn mostly in a class colour."""
    best, counted = match_colors(img, region, palette)
    counts = np.bincount(best[counted], minlength=len(palette)).astype(np.float64)
    return counts / max(counts.sum(), 1.0)


@pytest.fixture(scope="module")
def page():
    if find_chromium() is None:
        pytest.skip("no chromium on PATH (CI installs Debian's chromium in .ci/run; apt-get install chromium)")
    from css_ros.view.data import build_view_data
    from css_ros.view.server import MapView

    from css_ros.engine.semantic_map import SemanticMap

    full, classes = demo_map()
    data = build_view_data(full, classes, MAX_GAUSSIANS)

    def query(xyz):
        q = full.query_points(xyz)
        return q.labels, q.expectation, q.variance

    view = MapView(data, port=free_port(), query=query, title="demo map")
    # the engine's map of exactly the drawn Gaussians (below the page's default ceiling cut, brute force along its
    # up axis): the expectation of what the canvas shows
    assert np.array_equal(view.opening.up, [0.0, 0.0, 1.0]) and view.cut < view.cut_max()
    drawn = data.index[data.centers[:, 2].astype(np.float64) <= view.cut]
    smap = SemanticMap(full.model.select(drawn), classes.num_classes)
    smap.concentrations = full.concentrations[drawn]
    clients = []
    view.server.on_client_connect(lambda client: clients.append(client))
    browser = Browser(WIDTH, HEIGHT)
    try:
        browser.goto(view.url)
        browser.wait_for(lambda: clients, 20, "the page to connect")
        cam = clients[0].camera
        aim(cam)
        # close the "software WebGL" notice (it would cover part of the canvas)
        browser.evaluate("document.querySelectorAll('.mantine-Notification-closeButton, "
                         "button[class*=CloseButton]').forEach(b => b.click())")
        yield view, browser, smap, classes, cam
    finally:
        browser.close()
        view.stop()


POSITION, LOOK_AT = (3.6, 2.6, 2.3), (-0.5, -0.5, 0.3)


def aim(cam, timeout: float = 20.0) -> None:
    """Point the page's camera at the test view and wait until the page reports that pose back, unchanged for
    0.6 s (on a loaded host the page's report of its start view can arrive after our setting and override it)."""
    end = time.monotonic() + timeout
    while True:
        cam.up_direction = (0.0, 0.0, 1.0)
        cam.position = POSITION
        cam.look_at = LOOK_AT
        steady = 0
        while steady < 3 and np.allclose(cam.position, POSITION, atol=1e-3):
            time.sleep(0.2)
            steady += 1
        if steady == 3:
            return
        assert time.monotonic() < end, f"the page keeps its camera at {cam.position}, not {POSITION}"


def canvas_box(browser: Browser) -> tuple[int, int]:
    """(width, height) in CSS px of the largest canvas (the 3D view; it starts at the page's top-left)."""
    sizes = browser.evaluate("[...document.querySelectorAll('canvas')].map(c => "
                             "{const r = c.getBoundingClientRect(); return [r.left, r.top, r.width, r.height];})")
    left, top, w, h = max(sizes, key=lambda s: s[2] * s[3])
    assert (left, top) == (0, 0)
    return int(w), int(h)


def engine_labels(smap, cam, width: int, height: int) -> np.ndarray:
    """The engine's label image for the browser's camera (viser reports an OpenCV-convention pose)."""
    from css_ros.engine.camera import Camera
    from css_ros.engine.camera import quaternion_xyzw_to_matrix

    w, x, y, z = (float(v) for v in cam.wxyz)
    T = np.eye(4)
    T[:3, :3] = quaternion_xyzw_to_matrix([x, y, z, w])
    T[:3, 3] = cam.position
    f = (height / 2.0) / np.tan(cam.fov / 2.0)
    K = np.array([[f, 0, (width - 1) / 2.0], [0, f, (height - 1) / 2.0], [0, 0, 1.0]])
    return smap.render(Camera(K=K, width=width, height=height, T_map_cam=T)).labels


def region_mask(width: int, height: int) -> np.ndarray:
    m = np.ones((height, width), dtype=bool)
    x0, y0, x1, y1 = NOTICE_BOX
    m[y0:y1, x0:x1] = False
    return m


def settle(browser: Browser, width: int, view, timeout: float = 60.0) -> np.ndarray:
    """A settled screenshot of the page once it has taken in the server's latest redraw: its status line shows
    that redraw's number (sent after the splats, on the same ordered websocket), and the canvas stopped changing."""
    status = view.redraws
    browser.wait_for(lambda: browser.evaluate(f"document.body.innerText.includes('update {status} ·')"), timeout,
                     f"the page to show update {status}")
    return browser.stable_screenshot(timeout, accept=lambda img: view.redraws == status)


def save_shot(img: np.ndarray, name: str) -> None:
    from PIL import Image

    if os.environ.get("CSS_WRITE_SCREENSHOTS"):
        IMG.mkdir(parents=True, exist_ok=True)
        Image.fromarray(img).save(IMG / name)


def test_semantic_mode_shows_the_class_shares_of_the_view(page):
    view, browser, smap, classes, cam = page
    view.set_mode("semantic")
    img = settle(browser, WIDTH, view)
    w, h = canvas_box(browser)
    region = region_mask(w, h)
    labels = engine_labels(smap, cam, w, h)
    expected = np.bincount(labels[region][labels[region] < classes.num_classes],
                           minlength=classes.num_classes).astype(np.float64)
    expected /= expected.sum()
    seen = class_shares(img[:h, :w], classes.palette, region)
    save_shot(img, "css_view_semantic.png")
    top = [classes.names[i] for i in np.argsort(-expected)[:4]]
    assert expected.max() < 0.9, "the test view must show several classes"
    for ci in range(classes.num_classes):
        assert abs(seen[ci] - expected[ci]) <= SHARE_TOL, (
            f"{classes.names[ci]}: {seen[ci]:.3f} of the class pixels on the canvas, engine render "
            f"{expected[ci]:.3f} (largest expected: {top})")


def test_toggling_a_class_off_removes_its_colour(page):
    view, browser, smap, classes, cam = page
    view.set_mode("semantic")
    w, h = canvas_box(browser)
    region = region_mask(w, h)
    wall = classes.names.index("wall")
    before = class_shares(settle(browser, WIDTH, view)[:h, :w], classes.palette, region)
    assert before[wall] > 0.05
    view.set_class_visible(wall, False)
    try:
        img = settle(browser, WIDTH, view)
        px = img[:h, :w][region].astype(np.float64)
        near_wall = np.linalg.norm(px - classes.palette[wall].astype(np.float64), axis=1) <= 8.0
        assert near_wall.mean() < 0.002, f"{near_wall.mean():.4f} of the canvas still shows the wall colour"
        after = class_shares(img[:h, :w], classes.palette, region)
        assert after[classes.names.index("floor")] > 0.05  # the rest is still drawn
        save_shot(img, "css_view_wall_hidden.png")
    finally:
        view.set_class_visible(wall, True)


def test_expectation_mode_shows_its_colour_bar_range(page):
    view, browser, smap, classes, cam = page
    view.set_mode("expectation")
    try:
        img = settle(browser, WIDTH, view)
        text = browser.wait_for(lambda: browser.evaluate(
            "(() => {const b = document.getElementById('css-colorbar'); return b ? "
            "[b.querySelector('.vmin').innerText, b.querySelector('.vmax').innerText, b.dataset.vmin, "
            "b.dataset.vmax] : null;})()"), 10, "the colour bar")
        c = classes.num_classes
        assert float(text[0]) == pytest.approx(1.0 / c, rel=1e-2) and float(text[1]) == 1.0
        assert float(text[2]) == pytest.approx(1.0 / c, rel=1e-5) and float(text[3]) == 1.0
        # the canvas now shows viridis colours, not the class palette
        import matplotlib

        w, h = canvas_box(browser)
        region = region_mask(w, h)
        viridis = matplotlib.colormaps["viridis"](np.linspace(0, 1, 64))[:, :3] * 255.0
        drawn = np.linalg.norm(img[:h, :w][region].astype(np.float64) - 255.0, axis=1) > 60.0
        _, on_scale = match_colors(img[:h, :w], region, viridis)
        _, on_palette = match_colors(img[:h, :w], region, classes.palette)
        assert drawn.mean() > 0.3
        assert on_scale[drawn].mean() > 0.6 > 0.3 > on_palette[drawn].mean(), (on_scale[drawn].mean(), on_palette[drawn].mean())
        save_shot(img, "css_view_expectation.png")
    finally:
        view.set_mode("semantic")


def test_ten_tabs_and_tabs_closing_mid_update(tmp_path):
    """Ten pages at once, five closed while the splat is being resent: the server keeps serving the rest
    and a new page still gets the current state."""
    if find_chromium() is None:
        pytest.skip("no chromium on PATH (CI installs Debian's chromium in .ci/run; apt-get install chromium)")
    from css_ros.engine.classes import ClassSet
    from css_ros.engine.gaussians import GaussianModel
    from css_ros.engine.semantic_map import SemanticMap
    from css_ros.view.data import build_view_data
    from css_ros.view.server import MapView

    rng = np.random.default_rng(0)
    n = 400
    model = GaussianModel.from_activated(rng.uniform(-1, 1, (n, 3)), np.full((n, 3), 0.05),
                                         np.tile([1.0, 0, 0, 0], (n, 1)), np.full(n, 0.9), rng.uniform(0, 1, (n, 3)))
    smap = SemanticMap(model, 3)
    conc = np.full((n, 3), 1e-3)
    conc[np.arange(n), rng.integers(0, 3, n)] += 10.0
    smap.concentrations = conc
    view = MapView(build_view_data(smap, ClassSet.default(3)), port=free_port())
    connected, gone = [], []
    view.server.on_client_connect(lambda c: connected.append(c))
    view.server.on_client_disconnect(lambda c: gone.append(c))
    browser = Browser(320, 240)
    try:
        tabs = []
        for k in range(10):   # headless pages connect once shown: bring each new tab to the front
            tabs.append(browser.new_tab(view.url))
            browser.activate_tab(tabs[-1])
            browser.wait_for(lambda k=k: len(connected) > k, 30, f"page {k + 1} to connect")
        for i, tab in enumerate(tabs[:5]):
            view.set_mode(("variance", "evidence", "rgb", "expectation", "semantic")[i])  # resend while closing
            browser.close_tab(tab)
        browser.wait_for(lambda: len(gone) >= 5, 20, "five pages to disconnect")
        before = view.redraws
        view.set_class_visible(0, False)
        assert view.redraws == before + 1
        assert len(view.server.get_clients()) == 5
        browser.activate_tab(browser.new_tab(view.url))
        browser.wait_for(lambda: len(view.server.get_clients()) == 6, 20, "a new page to connect")
    finally:
        browser.close()
        view.stop()
