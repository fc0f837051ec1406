"""css_view's "Frame image" control in a real headless Chromium: the surprise image a person sees in the panel is the
node's surprise in the inferno colour map on [0, 1], grey where the segmentation had no label, with its colour bar;
choosing "None" takes it away. (The live page feeds it from the node's ~/surprise: test_view_live.py.)"""
from __future__ import annotations

import numpy as np
import pytest

from cdp_browser import Browser, find_chromium, free_port

pytest.importorskip("viser", reason="css_view needs the viser extra: pip install -e '.[view]'")
pytest.importorskip("websocket", reason="the browser test needs websocket-client (in '.[all]')")

pytestmark = pytest.mark.slow

H, W = 30, 40
#: the pixels of the panel's image of the given size, read back through a canvas (PNG: lossless)
READ_IMAGE = """(() => {
  const img = [...document.querySelectorAll('img')].find(i => i.naturalWidth === %d && i.naturalHeight === %d
                                                          && i.complete && i.offsetParent !== null);
  if (!img) return null;
  const c = document.createElement('canvas');
  c.width = img.naturalWidth; c.height = img.naturalHeight;
  const g = c.getContext('2d');
  g.drawImage(img, 0, 0);
  return Array.from(g.getImageData(0, 0, c.width, c.height).data);
})()""" % (W, H)


def surprise_image() -> np.ndarray:
    """A gradient 0..1 across the columns, the top rows without a label, a block exactly 0 and one exactly 1."""
    s = np.tile(np.linspace(0.0, 1.0, W, dtype=np.float32), (H, 1))
    s[:5] = np.nan
    s[20:25, 2:8] = 0.0
    s[20:25, 30:36] = 1.0
    return s


def test_the_page_shows_the_surprise_image_in_its_colour_map():
    if find_chromium() is None:
        pytest.skip("no chromium on PATH (CI installs Debian's chromium in .ci/run; apt-get install chromium)")
    import matplotlib

    from css_ros.engine.classes import ClassSet
    from css_ros.engine.gaussians import GaussianModel
    from css_ros.engine.semantic_map import SemanticMap
    from css_ros.export.colormap import UNKNOWN_RGB
    from css_ros.view.data import build_view_data
    from css_ros.view.server import MapView

    rng = np.random.default_rng(0)
    n = 300
    model = GaussianModel.from_activated(rng.uniform(-1, 1, (n, 3)), np.full((n, 3), 0.05),
                                         np.tile([1.0, 0, 0, 0], (n, 1)), np.full(n, 0.9), rng.uniform(0, 1, (n, 3)))
    view = MapView(build_view_data(SemanticMap(model, 3), ClassSet.default(3)), port=free_port(), frame_images=True)
    clients: list = []
    view.server.on_client_connect(lambda c: clients.append(c))
    browser = Browser(900, 700)
    try:
        browser.goto(view.url)
        browser.wait_for(lambda: clients, 30, "the page to connect")
        s = surprise_image()
        view.show_frame_image("surprise", s, "test frame")       # not chosen yet: not drawn
        assert view.frame_draws == 0 and view.frame_image("surprise") is s
        view.set_frame_image("surprise")
        assert view.frame_draws == 1
        browser.wait_for(lambda: browser.evaluate("document.body.innerText.includes('test frame · frame 1')"), 30,
                         "the caption of frame 1")
        px = browser.wait_for(lambda: browser.evaluate(READ_IMAGE), 30, "the surprise image in the panel")
        got = np.array(px, np.uint8).reshape(H, W, 4)
        assert np.all(got[..., 3] == 255)
        cm = matplotlib.colormaps["inferno"]
        expect = np.round(cm(np.nan_to_num(s))[..., :3] * 255).astype(np.uint8)
        expect[np.isnan(s)] = UNKNOWN_RGB
        np.testing.assert_array_equal(got[..., :3], expect)
        assert tuple(got[22, 4, :3]) == (0, 0, 4) and tuple(got[22, 32, :3]) == (252, 255, 164)   # inferno's ends
        bar = browser.wait_for(lambda: browser.evaluate(
            "(() => {const b = document.getElementById('css-frame-colorbar'); return b ? [b.dataset.vmin, "
            "b.dataset.vmax, b.innerText] : null;})()"), 10, "the frame image's colour bar")
        assert (float(bar[0]), float(bar[1])) == (0.0, 1.0) and "grey = no label" in bar[2]

        view.set_frame_image("none")
        browser.wait_for(lambda: browser.evaluate(READ_IMAGE) is None and browser.evaluate(
            "document.getElementById('css-frame-colorbar') === null"), 30, "the image to go")
        view.show_frame_image("surprise", s, "another frame")    # kept for later, not drawn
        assert view.frame_draws == 1
    finally:
        browser.close()
        view.stop()
