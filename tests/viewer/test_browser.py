"""The viewer in a real headless browser: Debian's chromium (software WebGL through SwiftShader) driven by Playwright
shows the splats, follows the frame slider, and saves an edit made in the panel."""
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

pytestmark = pytest.mark.skipif(shutil.which("chromium") is None, reason="Debian's chromium is not installed "
                                                                          "(make system-deps installs it)")


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


def test_the_viewer_draws_splats_follows_the_slider_and_saves_a_gui_edit(checkpoint, port, tmp_path):
    playwright = pytest.importorskip("playwright.sync_api")
    import viser

    from omniscs.viewer.app import ViewerApp, open_target

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

            slider = page.get_by_role("slider").first
            slider.focus()
            for _ in range(3):
                slider.press("ArrowRight")
            wait_for(lambda: app.frame_slider.value == 3, 20, "the server to see frame 3")
            later = settled(page)
            (tmp_path / "frame3.png").write_bytes(page.screenshot())
            # the ego drove 1.8 m and the cars moved: the whole view shifts
            assert changed_fraction(later, first) > 0.02

            page.locator(f"[id='{app.agent_list._impl.uuid}']").click()
            page.get_by_role("option", name="1 car").click()
            wait_for(lambda: app.selected == 1, 20, "agent 1 to be selected")
            page.get_by_role("button", name="Remove agent").click()
            wait_for(lambda: app.target.session.edits(), 20, "the removal")
            page.get_by_role("button", name="Save edits").click()
            wait_for(spec.exists, 20, "the spec file")
            browser.close()
        assert json.loads(spec.read_text()) == [{"op": "remove", "track_id": 1}]
    finally:
        app.close()
        server.stop()
        empty.stop()
