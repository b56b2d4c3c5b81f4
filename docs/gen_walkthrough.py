"""Regenerate the viewer guide's walk-through and its screenshots: design a scenario in `omniscs view` (one car cuts
into the ego's lane, an overturned box truck lies on the road ahead), save it, and have `omniscs generate` render and
annotate it as a designed variant.

    .venv/bin/python docs/gen_walkthrough.py [--workspace WS] [--out docs/guide/images]

What it runs, in order (about 5 minutes on a 2-core machine, most of it the two fast fits):
1. `omniscs generate syn:straight:33 --frames 20 --cameras 1 --fit-preset fast --no-previews`: the fitted log.
2. A model pool with the library's first box truck (what `make demo` builds).
3. The viewer of the fitted graph with `--scene` and `--pool`, in headless chromium (Playwright; software WebGL).
   Clicks in the panel pick the car, show its path's control points, pick the model and how it lies, and save.
   Two steps a user does with the mouse in 3D are made through the handlers the mouse calls, with the same
   arguments a drag or click gives: the release of the path's dragged control points (``ViewerApp.draw_path``;
   the handles are moved first so the screenshot shows them where they were dropped) and the click on the road
   (``ViewerApp.insert_at``, at the first road point ahead that the placement checks pass).
4. `omniscs generate ... --edit @walkthrough-edits.json --pool POOL --annotate`: the dataset with variant d000.
5. Screenshots of the viewer after each step and the dataset's annotated front image, into --out.
"""
from __future__ import annotations

import argparse
import io
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

SOURCE = "syn:straight:33"
FRAMES = 20
#: The car that cuts in: in the lane right of the ego's, 14 m ahead and a little faster. It moves into the ego's lane
#: over the middle of the log and brakes there, ending BRAKE_M closer to the ego than it would have been.
CUT_IN_TRACK = 1
BRAKE_M = 6.0
#: Where the truck may lie: ahead of the ego's start, in its lane or the next, first placement that passes.
TRUCK_AHEAD_M = (40.0, 45.0, 50.0, 55.0, 60.0)
TRUCK_LATERAL_M = (0.0, -3.7, 3.7)
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMIUM_ARGS = ["--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox"]
VIEWPORT = {"width": 1400, "height": 800}


def omniscs(*args: str, log: Path) -> None:
    cmd = [sys.executable, "-c", "import sys; from omniscs.cli import main; sys.argv[0] = 'omniscs'; main()", *args]
    with log.open("a") as fh:
        fh.write("$ omniscs " + " ".join(args) + "\n")
        fh.flush()
        subprocess.run(cmd, check=True, stdout=fh, stderr=subprocess.STDOUT)


def fitted(ws: Path) -> tuple[Path, Path]:
    """(scene store, fitted checkpoint) of SOURCE in workspace ``ws`` (the newest fit there)."""
    scenes = sorted((ws / "scenes").iterdir())
    models = sorted((ws / "models").glob("*/*/graph.json"), key=lambda p: p.stat().st_mtime)
    return scenes[-1], models[-1].parent


def wait_for(condition, timeout_s: float, what: str):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return
        time.sleep(0.1)
    raise RuntimeError(f"timed out waiting for {what}")


def settle(page, seconds: float = 3.0) -> None:
    """Give the browser time to receive and draw (software WebGL is slow)."""
    page.wait_for_timeout(int(seconds * 1000))


def ego_frame_point(world_from_ego: np.ndarray, ahead: float, lateral: float) -> np.ndarray:  # [4, 4] -> [2]
    return (world_from_ego @ np.array([ahead, lateral, 0.0, 1.0]))[:2]


def invert(T: np.ndarray) -> np.ndarray:
    return np.linalg.inv(T)


def look(app, world_from_ego: np.ndarray) -> None:  # [4, 4]
    """Every browser's 3D view from 14 m behind and 8 m above the ego, looking 25 m ahead of it."""
    eye = (world_from_ego @ np.array([-14.0, 0.0, 8.0, 1.0]))[:3]
    at = (world_from_ego @ np.array([25.0, 0.0, 0.0, 1.0]))[:3]
    for client in app.server.get_clients().values():
        client.camera.position = tuple(float(v) for v in eye)
        client.camera.look_at = tuple(float(v) for v in at)


def camera_view(app, frame: int, png: Path) -> None:
    """The panel's camera view at ``frame`` (logged left, rendered with the edits right) at full size."""
    from PIL import Image

    name = app.target.camera_names[0]
    Image.fromarray(app.target.camera_image(name, frame, True, app.selected)).save(png)


def close_notice(page) -> None:
    """Close the browser's 'software WebGL' notice, when it shows (it would cover the view)."""
    try:
        page.locator("[class*='Notification'] button").first.click(timeout=3000)
    except Exception:  # no notice: nothing to close
        pass


def design(app, page, out: Path) -> None:
    """The cut-in and the overturned truck, through the panel (and the two 3D handlers), with screenshots."""
    from omniscs.viewer.paths import control_frames

    target = app.target
    ego = target.session.base.world_from_ego
    page.locator(f"[id='{app.agent_list._impl.uuid}']").click()
    page.get_by_role("option", name=f"{CUT_IN_TRACK} car").click()
    wait_for(lambda: app.selected == CUT_IN_TRACK, 20, "the car to be selected")
    page.get_by_text("Draw its path", exact=True).click()
    wait_for(lambda: len(app._path_handles) > 0, 20, "the path's control points")
    node = target.session.graph.agent(CUT_IN_TRACK)
    frames = control_frames(node.present)
    points = np.array([h.position[:2] for h in app._path_handles], dtype=np.float64)
    for k, f in enumerate(frames):
        s = k / max(len(frames) - 1, 1)
        ahead, lateral = (invert(ego[f]) @ np.array([*points[k], ego[f][2, 3], 1.0]))[:2]
        into_lane = float(np.clip((s - 0.25) / 0.35, 0.0, 1.0))  # the lane change over the middle of the log
        braking = float(np.clip((s - 0.5) / 0.5, 0.0, 1.0))      # then it brakes in the ego's lane
        points[k] = ego_frame_point(ego[f], ahead - BRAKE_M * braking, lateral * (1.0 - into_lane))
        app._path_handles[k].position = (float(points[k, 0]), float(points[k, 1]),
                                         float(app._path_handles[k].position[2]))
    app.draw_path(points)
    print(target.placement_verdict(CUT_IN_TRACK))
    look(app, ego[FRAMES - 6])
    app.frame_slider.value = FRAMES - 6
    settle(page, 5)
    page.screenshot(path=str(out / "walkthrough-cut-in.jpg"), type="jpeg", quality=85)
    camera_view(app, FRAMES - 6, out / "walkthrough-cut-in-camera.png")

    page.get_by_text("Models", exact=True).click()
    truck = next(label for label in app._models if label.endswith(" truck"))
    page.locator(f"[id='{app.model_list._impl.uuid}']").click()
    page.get_by_role("option", name=truck).click()
    page.locator(f"[id='{app.lie._impl.uuid}']").click()
    page.get_by_role("option", name="overturned").click()
    wait_for(lambda: app.lie.value == "overturned" and app.model_list.value == truck, 20, "the model and its lie")
    ground = float(np.median(ego[:, 2, 3]))
    for ahead in TRUCK_AHEAD_M:
        for lateral in TRUCK_LATERAL_M:
            x, y = ego_frame_point(ego[0], ahead, lateral)
            tid = app.insert_at(float(x), float(y), ground)
            verdict = None if tid is None else target.placement_verdict(tid)
            print(f"truck at {ahead:g} m ahead, {lateral:g} m left: {verdict or app.status.content}")
            if verdict is not None and verdict.endswith("seen by a camera."):
                break
            if tid is not None:  # refused by the checks: take it out again and try the next point
                app.remove_selected()
        else:
            continue
        break
    else:
        raise RuntimeError("no road point ahead passes the placement checks for the truck")
    app.frame_slider.value = FRAMES - 1
    look(app, ego[FRAMES - 1])
    settle(page, 5)
    page.screenshot(path=str(out / "walkthrough-truck.jpg"), type="jpeg", quality=85)
    camera_view(app, FRAMES - 1, out / "walkthrough-truck-camera.png")
    page.get_by_role("button", name="Save edits").click()
    page.get_by_text("Saved", exact=False).first.wait_for(timeout=20_000)
    settle(page, 2)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--workspace", type=Path, default=Path("/tmp/omniscs-walkthrough"))
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "guide" / "images")
    args = parser.parse_args()
    ws, out = args.workspace, args.out
    ws.mkdir(parents=True, exist_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    log = ws / "walkthrough.log"
    common = ["--workspace", str(ws), "--frames", str(FRAMES), "--cameras", "1", "--fit-preset", "fast",
              "--no-previews"]
    omniscs("generate", SOURCE, *common, log=log)
    scene, graph = fitted(ws)

    from omniscs.cli.generate import demo_pool

    pool = demo_pool(ws)
    spec = ws / "walkthrough-edits.json"
    spec.unlink(missing_ok=True)

    import viser
    from playwright.sync_api import sync_playwright

    from omniscs.viewer.app import ViewerApp
    from omniscs.viewer.targets import open_target

    target = open_target(graph, scene=scene, pool=pool)
    server = viser.ViserServer(host="127.0.0.1", port=8097, verbose=False)
    app = ViewerApp(server, target, frame=0, edits_out=spec)
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport=VIEWPORT)
            page.goto(f"http://127.0.0.1:{server.get_port()}")
            page.get_by_role("button", name="Save edits").wait_for(timeout=30_000)
            close_notice(page)
            look(app, target.session.base.world_from_ego[0])
            settle(page, 6)
            page.screenshot(path=str(out / "walkthrough-log.jpg"), type="jpeg", quality=85)
            design(app, page, out)
            browser.close()
    finally:
        app.close()
        server.stop()
    print(json.dumps(json.loads(spec.read_text()), indent=None)[:400])

    omniscs("generate", SOURCE, *common, "--edit", f"@{spec}", "--pool", str(pool), "--annotate", log=log)
    dataset = sorted((ws / "datasets").iterdir(), key=lambda p: p.stat().st_mtime)[-1]
    card = json.loads((dataset / "dataset.json").read_text())
    print(f"dataset {dataset}: {card['counts']['variants_by_level']}, gates {card['gates']['produced']}")
    annotated_front(dataset, out / "walkthrough-dataset.png")


def annotated_front(dataset: Path, png: Path, frames=(4, 10, 16)) -> None:
    """The designed variant's front camera at ``frames`` as the viewer shows the dataset (3D boxes, 2D boxes with
    their visibility levels), side by side."""
    import cv2

    from omniscs.viewer.targets import open_target

    target = open_target(dataset)
    target.pick(next(i for i, r in enumerate(target.samples) if r["variant_id"] == "d000"))
    tiles = [target.camera_image(target.camera_names[0], f, boxes=True) for f in frames]
    for f, tile in zip(frames, tiles):
        cv2.putText(tile, f"frame {f}", (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 2)
    from PIL import Image

    Image.fromarray(np.concatenate(tiles, axis=1)).save(png)
    print(f"wrote {png}")


if __name__ == "__main__":
    main()
