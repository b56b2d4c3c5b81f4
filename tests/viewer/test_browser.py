"""The viewer in a real headless browser: Debian's chromium (software WebGL through SwiftShader) driven by Playwright
shows the splats, follows the frame slider, and saves edits made in the panel and by a click on the road."""
from __future__ import annotations

import io
import json
import shutil
import time

import numpy as np
import pytest

#: The system browser (make system-deps installs it); Playwright's own browser download is not reachable here.
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
#: WebGL without a GPU: ANGLE over SwiftShader.
CHROMIUM_ARGS = ["--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox"]
VIEWPORT = {"width": 1100, "height": 700}
#: The 3D view left of viser's panel (the panel is drawn over the canvas on the right).
SCENE_COLUMNS = slice(0, 700)

#: About 50 s on the shared 2-core machine (a third of it the fit): in `make test-slow`, which `.ci/run` runs too.
pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(shutil.which("chromium") is None, reason="Debian's chromium is not installed "
                                                                          "(make system-deps installs it)")]


def wait_for(condition, timeout_s: float, what: str):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


def scene_pixels(page) -> np.ndarray:  # -> int [H, W', 3] the 3D view, panel left out
    from PIL import Image

    png = page.locator("canvas").first.screenshot()
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int32)[:, SCENE_COLUMNS]


def settled(page, timeout_s: float = 20.0) -> np.ndarray:
    """The 3D view once two shots half a second apart agree (splats arrived, sorted and drawn)."""
    last = scene_pixels(page)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        page.wait_for_timeout(500)
        now = scene_pixels(page)
        if np.abs(now - last).max() <= 2:
            return now
        last = now
    return last


def changed_fraction(a: np.ndarray, b: np.ndarray) -> float:
    return float((np.abs(a - b).sum(axis=2) > 30).mean())


def test_the_viewer_draws_splats_follows_the_slider_and_saves_gui_edits(checkpoint, port, tmp_path):
    playwright = pytest.importorskip("playwright.sync_api")
    import viser

    from omniscs.viewer.app import ViewerApp
    from omniscs.viewer.targets import open_target

    spec = tmp_path / "gui-spec.json"
    target = open_target(checkpoint)
    server = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
    app = ViewerApp(server, target, frame=0, edits_out=spec)
    empty = viser.ViserServer(host="127.0.0.1", port=port + 1 if port < 65535 else port - 1, verbose=False)
    empty.initial_camera.position = server.initial_camera.position  # the same view of nothing
    empty.initial_camera.look_at = server.initial_camera.look_at
    try:
        with playwright.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport=VIEWPORT)
            page.goto(f"http://127.0.0.1:{empty.get_port()}")
            page.locator("canvas").first.wait_for(timeout=20_000)
            nothing = settled(page)

            page.goto(f"http://127.0.0.1:{server.get_port()}")
            page.get_by_role("button", name="Save edits").wait_for(timeout=20_000)
            first = settled(page)
            (tmp_path / "frame0.png").write_bytes(page.screenshot())
            assert first.std() > 20, "the 3D view is blank"
            assert changed_fraction(first, nothing) > 0.2, "the splats were not drawn"

            # a click at the right end of the slider's rail (not arrow keys: viser's 3D view also moves on them)
            rail = page.get_by_role("slider").first.locator("xpath=..").bounding_box()
            page.mouse.click(rail["x"] + rail["width"] - 2, rail["y"] + rail["height"] / 2)
            wait_for(lambda: app.frame_slider.value == 3, 20, "the server to see frame 3")
            later = settled(page)
            (tmp_path / "frame3.png").write_bytes(page.screenshot())
            # the ego drove 1.8 m and the cars moved (the viewpoint stays): their pixels change, the rest does not
            assert 0.004 < changed_fraction(later, first) < 0.2

            page.locator(f"[id='{app.agent_list._impl.uuid}']").click()
            page.get_by_role("option", name="1 car").click()
            wait_for(lambda: app.selected == 1, 20, "agent 1 to be selected")
            page.get_by_role("button", name="Remove agent").click()
            wait_for(lambda: app.target.session.edits(), 20, "the removal")
            page.get_by_text("Models", exact=True).click()  # the folder starts folded
            page.get_by_role("button", name="Insert: click the road").click()
            wait_for(lambda: "Click the road" in app.status.content, 20, "the insert to wait for a click")
            box = page.locator("canvas").first.bounding_box()
            for _ in range(10):  # until the browser has heard that the next click inserts (one click inserts once)
                page.mouse.click(box["x"] + 350, box["y"] + box["height"] * 0.75)  # the road left of the ego
                page.wait_for_timeout(1000)
                if len(app.target.session.edits()) == 2:
                    break
            wait_for(lambda: len(app.target.session.edits()) == 2, 5, "the insert")
            page.get_by_role("button", name="Save edits").click()
            wait_for(spec.exists, 20, "the spec file")
            page.get_by_text("Saved 2 edit(s)").wait_for(timeout=20_000)
            settled(page)
            (tmp_path / "inserted.png").write_bytes(page.screenshot())
            browser.close()
        saved = json.loads(spec.read_text())
        assert saved[-1] == {"op": "remove", "track_id": 1}
        inserted = saved[0]
        assert inserted["op"] == "insert" and inserted["track_id"] == 3 and inserted["roll_deg"] == 0.0
        assert app.target.session.graph.agent(3).present.all()
    finally:
        app.close()
        server.stop()
        empty.stop()
