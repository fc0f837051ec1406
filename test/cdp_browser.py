"""Headless Chromium driven over the DevTools protocol (websocket-client), for tests of pages people look at.

Software WebGL (SwiftShader through ANGLE), so it runs on machines without a GPU. Every wait is bounded.
"""
from __future__ import annotations

import base64
import io
import json
import shutil
import socket
import subprocess
import tempfile
import time
import urllib.parse
import urllib.request

import numpy as np

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "chrome")


def find_chromium() -> str | None:
    """Path of a Chromium/Chrome binary on PATH, or None."""
    for name in CHROMIUM_NAMES:
        path = shutil.which(name)
        if path:
            return path
    return None


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Browser:
    """One headless Chromium with one page, ``width`` × ``height`` CSS pixels (device scale 1)."""

    def __init__(self, width: int = 900, height: int = 600, timeout: float = 90.0) -> None:
        """``timeout`` [s] bounds the browser's start and each DevTools answer (a software-WebGL screenshot of a
        large scene on a loaded 2-core host took more than 20 s)."""
        import websocket

        exe = find_chromium()
        if exe is None:
            raise RuntimeError("no chromium on PATH")
        self.profile = tempfile.mkdtemp(prefix="css_chromium_")
        port = free_port()
        self.proc = subprocess.Popen(
            [exe, "--headless=new", "--no-sandbox", "--disable-gpu-sandbox", "--use-gl=angle",
             "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
             f"--window-size={width},{height}", "--force-device-scale-factor=1", "--hide-scrollbars",
             "--disable-background-timer-throttling", "--disable-renderer-backgrounding",
             "--disable-backgrounding-occluded-windows", "--no-first-run", "--no-default-browser-check",
             "--disable-extensions", "--mute-audio",
             f"--user-data-dir={self.profile}", f"--remote-debugging-port={port}", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + timeout
        ws_url = None
        while time.monotonic() < deadline and ws_url is None:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=1) as r:
                    pages = [t for t in json.load(r) if t.get("type") == "page"]
                if pages:
                    ws_url = pages[0]["webSocketDebuggerUrl"]
            except OSError:
                time.sleep(0.1)
        if ws_url is None:
            self.close()
            raise RuntimeError("chromium did not open its DevTools port")
        self.port = port
        self.ws = websocket.create_connection(ws_url, timeout=timeout, suppress_origin=True)
        self._id = 0
        self.call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1,
                  mobile=False)

    def call(self, method: str, **params):
        """Send one DevTools command and return its result (events in between are dropped)."""
        self._id += 1
        self.ws.send(json.dumps({"id": self._id, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv())
            if msg.get("id") == self._id:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})

    def goto(self, url: str) -> None:
        self.call("Page.navigate", url=url)

    def evaluate(self, expression: str):
        """Value of a JavaScript expression (JSON-serialisable)."""
        res = self.call("Runtime.evaluate", expression=expression, returnByValue=True)
        return res.get("result", {}).get("value")

    def screenshot(self) -> np.ndarray:
        """(H, W, 3) uint8 RGB of the page."""
        from PIL import Image

        data = self.call("Page.captureScreenshot", format="png")["data"]
        return np.asarray(Image.open(io.BytesIO(base64.b64decode(data))).convert("RGB"))

    def wait_for(self, predicate, timeout: float, what: str, poll: float = 0.2):
        """Poll ``predicate()`` until it returns a truthy value; raise TimeoutError naming ``what``."""
        deadline = time.monotonic() + timeout
        while True:
            value = predicate()
            if value is not None and value is not False and (not hasattr(value, "__len__") or len(value)):
                return value
            if time.monotonic() > deadline:
                raise TimeoutError(f"waited {timeout:.0f} s for {what}")
            time.sleep(poll)

    def stable_screenshot(self, timeout: float, accept=lambda img: True, repeats: int = 3) -> np.ndarray:
        """A screenshot equal to the ``repeats`` - 1 taken before it, 0.3 s apart (the page stopped changing), that
        ``accept`` takes. One repeat is not enough on a loaded host: software WebGL may skip a frame or two while
        it takes in new splats, and two equal screenshots then show the old scene."""
        last: list[np.ndarray] = []

        def probe():
            img = self.screenshot()
            if not last or img.shape != last[-1].shape or not np.array_equal(img, last[-1]):
                last.clear()
            last.append(img)
            return img if len(last) >= repeats and accept(img) else None

        return self.wait_for(probe, timeout, "the page to settle", poll=0.3)

    def new_tab(self, url: str) -> str:
        """Open ``url`` in another tab; returns its target id."""
        req = urllib.request.Request(f"http://127.0.0.1:{self.port}/json/new?{urllib.parse.quote(url, safe='')}",
                                     method="PUT")
        with urllib.request.urlopen(req, timeout=10) as r:
            return json.load(r)["id"]

    def activate_tab(self, target_id: str) -> None:
        """Bring a tab to the front (pages in background tabs may wait until they are shown)."""
        with urllib.request.urlopen(f"http://127.0.0.1:{self.port}/json/activate/{target_id}", timeout=10):
            pass

    def close_tab(self, target_id: str) -> None:
        with urllib.request.urlopen(f"http://127.0.0.1:{self.port}/json/close/{target_id}", timeout=10):
            pass

    def close(self) -> None:
        try:
            self.ws.close()
        except Exception:  # noqa: BLE001 - best effort
            pass
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
        shutil.rmtree(self.profile, ignore_errors=True)
