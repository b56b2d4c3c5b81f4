"""Viewer benchmark (``omniscs bench view``): how fast ``omniscs view`` shows a fitted world in a browser and how
fast the camera view follows an edit.

1. Splat view: time to first frame (page load to the first screenshot whose 3D view shows the splats) and frames per
   second while the camera orbits, for 50k / 200k / 500k Gaussians, in Debian's headless chromium. Its WebGL is
   software (ANGLE over SwiftShader, on the CPU): the frame rates are a floor for a machine with a GPU.
2. Edit to camera image: an agent moved through the viewer's own gizmo-release handler (``ViewerApp.move_selected``:
   the edit session, the 3D scene, the camera image rendered by our rasteriser at 640x360 with its boxes) until the
   image is set; median and p90 over edits of different agents, against the issue's 1 s target.

The world is a held-out procedural log (no other benchmark or test uses its seed) fitted with the fast preset
through the pipeline's own stages, reused from the workspace when present (the fit is not what this measures).
Where the fit has fewer Gaussians than a count asks for, the scene is densified by one deterministic rule
(``densified``) so that the viewer draws exactly that many splats."""
from __future__ import annotations

import io
import math
import shutil
import statistics
import threading
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch

from omniscs.bench.harness import drop_partial, finish, load_line, machine_info, save_partial, write_report
from omniscs.errors import OmniscsError
from omniscs.gaussians import GaussianParams, concat_params
from omniscs.nsg.graph import SceneGraph
from omniscs.progress import Progress, no_progress
from omniscs.quaternions import normalize_quats, rotmats_from_unit_quats
from omniscs.scene.store import CameraRecord

BENCH = "view"


@dataclass(frozen=True)
class ViewBenchConfig:
    """The world, the splat counts, the browser and the edits of the viewer benchmark."""

    scene: tuple[str, int] = ("straight", 8401)
    """(template, seed) of the held-out procedural log that is fitted and viewed."""
    n_frames: int = 40
    """Frames of the log (4 s at 10 Hz)."""
    fit_size: tuple[int, int] = (320, 180)
    """(width, height) of the one logged front camera the graph is fitted to."""
    fit_preset: str = "fast"
    """Scene-graph preset of the fit (the issue's target is for a fast-preset graph)."""
    fit_iterations: int | None = None
    """Fit iterations (None: the preset's); the quick set-up fits briefly."""
    counts: tuple[int, ...] = (50_000, 200_000, 500_000)
    """Gaussians drawn as splats, one browser measurement each."""
    densify_seed: int = 0
    """Seed of the jitter of the densifying copies (``densified``)."""
    densify_opacity: float = 0.5
    """A densifying copy's opacity as a share of its source's (fainter copies keep the picture close to the fit's)."""
    viewport: tuple[int, int] = (1100, 700)
    """Browser window (width, height) in CSS pixels; viser's panel covers the right of it."""
    scene_columns: int = 700
    """Columns of the 3D view left of the panel that the screenshots compare."""
    first_frame_timeout_s: float = 300.0
    """Longest wait for the splats to show after the page load."""
    splats_shown_share: float = 0.5
    """A screenshot shows the splats when its pixels that differ from the empty scene are at least this share of
    those of the settled view (the splats, sorted and drawn)."""
    orbit_seconds: float = 6.0
    """How long the frame rate is counted while the camera orbits (at least)."""
    orbit_min_frames: int = 4
    """The count goes on past ``orbit_seconds`` until the page has drawn this many frames (a slow page) ..."""
    orbit_max_seconds: float = 90.0
    """... or this long has passed."""
    orbit_period_s: float = 12.0
    """Seconds per full orbit of the camera about its look-at point."""
    orbit_updates_hz: float = 30.0
    """Camera poses sent per second from the server while orbiting (viser's client camera API)."""
    image_size: tuple[int, int] = (640, 360)
    """(width, height) of the camera view in the edit latency (the issue's target size)."""
    edits: int = 20
    """Timed edits (moves of the agents present at the middle frame, in turn)."""
    edit_step_m: float = 0.8
    """Each move: this far sideways (alternating left and right) and a 5 degree turn."""
    edit_target_s: float = 1.0
    """The issue's target: the camera view updates within this after an edit."""


def quick_config() -> ViewBenchConfig:
    """A tiny set-up for tests of the benchmark's code path (not for numbers)."""
    return replace(ViewBenchConfig(), n_frames=12, fit_size=(96, 54), fit_iterations=60, counts=(3_000, 12_000),
                   first_frame_timeout_s=90.0, orbit_seconds=1.5, orbit_min_frames=2, orbit_max_seconds=10.0,
                   image_size=(160, 90), edits=3)


# ----------------------------------------------------------------------------- the world
def prepare(config: ViewBenchConfig, workspace: Path, progress: Progress = no_progress) -> dict:
    """Ingest, plan and fit the benchmark's log (reused when already in the workspace). The plan is the one for
    behaviour variants, so that the moving agents are nodes that the viewer can edit."""
    from omniscs.pipeline.request import SceneRequest
    from omniscs.pipeline.stages import fit_stage, ingest_stage, load_plan, plan_stage
    from omniscs.scene import SyntheticSource

    template, seed = config.scene
    progress(0, None, f"{template}:{seed}: ingest, plan, {config.fit_preset} fit")
    source = SyntheticSource(template=template, seed=seed, n_frames=config.n_frames, n_cameras=1,
                             width=config.fit_size[0], height=config.fit_size[1])
    scene_rec = ingest_stage(source, workspace)
    request = SceneRequest(fit_preset=config.fit_preset, behavior_variants=1, annotate=False, previews=False)
    plan = load_plan(plan_stage(scene_rec.path, request, workspace))
    overrides = {} if config.fit_iterations is None else {"iterations": config.fit_iterations}
    fitted = fit_stage(scene_rec.path, plan, config.fit_preset, workspace, **overrides)
    if fitted.path is None:
        raise OmniscsError(f"the {config.fit_preset} fit of {template}:{seed} diverged; run the benchmark again with "
                           "another --workspace")
    metrics = fitted.info.get("metrics", {})
    return {"scene": f"{template}:{seed}", "scene_id": scene_rec.scene_id, "checkpoint": str(fitted.path),
            "fit_seconds": metrics.get("fit_seconds"), "heldout_psnr": metrics.get("heldout_psnr"),
            "fit_reused": fitted.reused}


#: How a count above the fit's Gaussians is made (``densified``), as the report states it.
DENSIFY_RULE = ("the fit's Gaussians, plus (count - fitted) copies of its background Gaussians in turn (copy k of "
                "Gaussian k mod n_background), each moved by a normal offset in that Gaussian's own axes with its own "
                "scales as standard deviations (seeded), at {opacity:g} of its opacity; scales, rotation and colour "
                "kept")


def densified(graph: SceneGraph, count: int, seed: int = 0, opacity_share: float = 0.5) -> SceneGraph:
    """``graph`` with ``count - graph.n_gaussians`` Gaussians added to its background (``graph`` itself when it has
    ``count`` or more). The rule: copy k (k = 0, 1, ...) is of background Gaussian ``k mod n_background``, moved by
    a normal offset drawn in that Gaussian's own axes with its own scales as standard deviations (seeded: the same
    scene every run), with ``opacity_share`` of its opacity; scales, rotation and colour are the source's."""
    extra = int(count) - graph.n_gaussians
    if extra <= 0:
        return graph
    bg = graph.background.detached().to("cpu")
    source = torch.arange(extra) % len(bg)
    generator = torch.Generator().manual_seed(int(seed))
    rotation = rotmats_from_unit_quats(normalize_quats(bg.quats[source]))        # [E, 3, 3] node from Gaussian
    local = torch.randn(extra, 3, generator=generator, dtype=bg.means.dtype) * bg.log_scales[source].exp()
    alpha = torch.sigmoid(bg.opacity_logits[source]) * float(opacity_share)
    copies = GaussianParams(means=bg.means[source] + (rotation @ local[:, :, None])[:, :, 0],
                            quats=bg.quats[source].clone(), log_scales=bg.log_scales[source].clone(),
                            opacity_logits=torch.logit(alpha, eps=1e-6), sh_dc=bg.sh_dc[source].clone(),
                            sh_rest=bg.sh_rest[source].clone())
    return replace(graph, background=concat_params([bg, copies]),
                   content_hash=f"{graph.content_hash}+densified-{int(count)}")


def seen_agents(graph: SceneGraph, frame: int, camera: str | None = None) -> list[int]:
    """Track ids of the agent nodes whose box centre the camera (default: the first) sees at ``frame``, nearest first:
    an edit of an agent out of view leaves the camera image as it was."""
    from omniscs.geometry import invert_transform

    cam = graph.cameras[0] if camera is None else graph.camera(camera)
    cam_from_world = invert_transform(graph.world_from_ego[frame] @ cam.ego_from_camera)
    seen = []
    for a in graph.agents:
        if not a.present[frame]:
            continue
        x, y, z = (cam_from_world @ a.world_from_agent[frame][:, 3])[:3]
        u, v = cam.K[0, 0] * x / max(z, 1e-9) + cam.K[0, 2], cam.K[1, 1] * y / max(z, 1e-9) + cam.K[1, 2]
        if z > 1.0 and 0 <= u < cam.width and 0 <= v < cam.height:
            seen.append((float(z), a.track_id))
    return [tid for _, tid in sorted(seen)]


def busiest_frame(graph: SceneGraph) -> int:
    """The frame whose front camera sees the most agent nodes (ties: the one nearest the middle of the log)."""
    middle = graph.n_frames // 2
    return max(range(graph.n_frames), key=lambda f: (len(seen_agents(graph, f)), -abs(f - middle)))


def resized_cameras(graph: SceneGraph, width: int, height: int) -> SceneGraph:
    """``graph`` whose logged cameras render at ``width`` x ``height`` (intrinsics scaled; the same viewpoints)."""
    cameras = []
    for c in graph.cameras:
        K = np.array(c.K, dtype=np.float64)
        K[0] *= width / c.width
        K[1] *= height / c.height
        cameras.append(CameraRecord(c.name, int(width), int(height), K, c.ego_from_camera))
    return replace(graph, cameras=tuple(cameras))


# ----------------------------------------------------------------------------- the browser
#: WebGL without a GPU: ANGLE over SwiftShader, on the CPU.
CHROMIUM_ARGS = ("--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox")

#: Counts the frames the page draws: a requestAnimationFrame tick in which any WebGL draw call ran. viser renders on
#: demand (a camera move, an update, a 1 Hz heartbeat), so plain animation-frame callbacks would count ticks that
#: draw nothing; counting ticks with draws counts what the user sees redrawn.
FRAME_COUNTER = """
(() => {
  let drew = false;
  window.__omniscsFrames = 0;
  window.__omniscsFirstDraw = null;  // performance.now() of the first tick that drew: ms after navigation start
  for (const proto of [WebGLRenderingContext.prototype, WebGL2RenderingContext.prototype]) {
    for (const name of ["drawArrays", "drawElements", "drawArraysInstanced", "drawElementsInstanced",
                        "drawRangeElements"]) {
      const draw = proto[name];
      if (typeof draw !== "function") continue;
      proto[name] = function (...args) { drew = true; return draw.apply(this, args); };
    }
  }
  const tick = () => {
    if (drew) {
      window.__omniscsFrames += 1;
      if (window.__omniscsFirstDraw === null) window.__omniscsFirstDraw = performance.now();
      drew = false;
    }
    requestAnimationFrame(tick);
  };
  requestAnimationFrame(tick);
})();
"""


def chromium_path() -> str:
    """Debian's chromium (Playwright's own browser download is not reachable here)."""
    found = shutil.which("chromium") or ("/usr/bin/chromium" if Path("/usr/bin/chromium").is_file() else None)
    if found is None:
        raise OmniscsError("Debian's chromium is not installed; run `make system-deps` (it installs chromium) and "
                           "run the benchmark again")
    return found


def free_port() -> int:
    """A port free on the loopback now."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def scene_pixels(page, columns: int, timeout_s: float = 300.0) -> np.ndarray:  # -> uint8 [H, columns, 3]
    """The 3D view left of the panel, as the page shows it. A page screenshot of that region, not the canvas
    element's: an element shot first waits for the element to hold still, which a page busy taking in hundreds of
    thousands of splats does not do for tens of seconds."""
    from PIL import Image

    height = page.viewport_size["height"]
    png = page.screenshot(clip={"x": 0, "y": 0, "width": columns, "height": height}, timeout=timeout_s * 1000)
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.uint8)


def changed_share(a: np.ndarray, b: np.ndarray) -> float:
    """Share of pixels whose colour differs by more than 30 (summed over RGB) between two shots."""
    return float((np.abs(a.astype(np.int16) - b.astype(np.int16)).sum(axis=2) > 30).mean())


def settled_shot(page, columns: int, timeout_s: float = 30.0) -> np.ndarray:
    """The 3D view once two shots half a second apart agree."""
    last = scene_pixels(page, columns)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        page.wait_for_timeout(500)
        now = scene_pixels(page, columns)
        if np.abs(now.astype(np.int16) - last).max() <= 2:
            return now
        last = now
    return last


def first_frame(page, url: str, empty: np.ndarray, config: ViewBenchConfig) -> dict:
    """Load ``url`` and screenshot the 3D view back to back until it settles on a picture that is not the empty
    scene. The first frame is the first shot that shows at least ``splats_shown_share`` of the settled view's change
    from the empty scene: ``first_frame_s`` is the end of that shot, ``first_frame_after_s`` the end of the shot
    before it (which did not show them; 0 for the first shot), so the splats appeared between the two. A shot waits
    for the page to produce a frame, and the first one for the page to show its canvas at all. Times are seconds
    from the start of the page load; ``first_draw_s`` is the page's first WebGL draw of anything (its own clock,
    from navigation start)."""
    shots: list[tuple[float, np.ndarray]] = []
    start = time.perf_counter()
    page.goto(url)
    loaded_s = time.perf_counter() - start
    deadline = start + config.first_frame_timeout_s
    settled_at = None
    while time.perf_counter() < deadline:
        shot = scene_pixels(page, config.scene_columns)
        shots.append((time.perf_counter() - start, shot))
        if len(shots) >= 3 and shots[-1][0] - shots[-3][0] >= 0.4 and changed_share(shot, empty) > 0.02 \
                and all(np.abs(s.astype(np.int16) - shot).max() <= 2 for _, s in shots[-3:-1]):
            settled_at = shots[-3][0]
            break
        page.wait_for_timeout(50)
    full = changed_share(shots[-1][1], empty)
    shown = next((k for k, (_, s) in enumerate(shots) if changed_share(s, empty) >= config.splats_shown_share * full),
                 None)
    first_draw = page.evaluate("window.__omniscsFirstDraw")
    ok = settled_at is not None and shown is not None
    return {"page_load_s": loaded_s, "first_draw_s": None if first_draw is None else first_draw / 1000.0,
            "first_frame_s": shots[shown][0] if ok else None,
            "first_frame_after_s": (shots[shown - 1][0] if shown > 0 else 0.0) if ok else None,
            "settled_s": settled_at, "shots": len(shots), "changed_vs_empty": full,
            "blank": bool(shots[-1][1].std() < 5.0)}


def orbit_fps(page, server, config: ViewBenchConfig) -> dict:
    """Frames per second the page draws while the server orbits the browser's camera about its look-at point
    (viser's client camera API), counted by ``FRAME_COUNTER``; and how much the view changed (the orbit moved it)."""
    before = scene_pixels(page, config.scene_columns)
    clients = list(server.get_clients().values())
    if not clients:
        raise OmniscsError("the browser did not connect to the viewer; nothing to orbit")
    client = clients[0]
    centre = np.asarray(client.camera.look_at, dtype=np.float64)
    offset = np.asarray(client.camera.position, dtype=np.float64) - centre
    stop = threading.Event()

    def orbit() -> None:
        t0 = time.perf_counter()
        while not stop.wait(1.0 / config.orbit_updates_hz):
            angle = 2.0 * math.pi * (time.perf_counter() - t0) / config.orbit_period_s
            c, s = math.cos(angle), math.sin(angle)
            rotated = np.array([c * offset[0] - s * offset[1], s * offset[0] + c * offset[1], offset[2]])
            with client.atomic():
                client.camera.position = tuple(centre + rotated)
                client.camera.look_at = tuple(centre)

    mover = threading.Thread(target=orbit, name="omniscs-bench-orbit", daemon=True)
    mover.start()
    try:
        page.wait_for_timeout(500)  # the orbit under way
        n0, t0 = page.evaluate("[window.__omniscsFrames, performance.now()]")
        page.wait_for_timeout(int(1000 * config.orbit_seconds))
        n1, t1 = page.evaluate("[window.__omniscsFrames, performance.now()]")
        while n1 - n0 < config.orbit_min_frames and (t1 - t0) / 1000.0 < config.orbit_max_seconds:
            page.wait_for_timeout(500)
            n1, t1 = page.evaluate("[window.__omniscsFrames, performance.now()]")
    finally:
        stop.set()
        mover.join(timeout=5.0)
    after = scene_pixels(page, config.scene_columns)
    seconds = (t1 - t0) / 1000.0
    return {"orbit_fps": (n1 - n0) / seconds, "orbit_frames": int(n1 - n0), "orbit_seconds": seconds,
            "orbit_changed_view": changed_share(before, after)}


# ----------------------------------------------------------------------------- the measurements
def measure_splat_view(graph: SceneGraph, checkpoint: Path, frame: int, config: ViewBenchConfig,
                       progress: Progress = no_progress, measured=None) -> list[dict]:
    """Per count: the server's set-up, the browser's time to first frame and its frame rate while orbiting.
    ``measured(rows)`` gets the rows so far after each count."""
    import viser
    from playwright.sync_api import sync_playwright

    from omniscs.viewer.app import ViewerApp
    from omniscs.viewer.state import ViewerConfig
    from omniscs.viewer.targets import GraphTarget

    rows = []
    width, height = config.viewport
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium_path(), headless=True, args=list(CHROMIUM_ARGS))
        empty_shot = None
        try:
            for count in config.counts:
                progress(0, None, f"splat view: {count:,} Gaussians")
                dense = densified(graph, count, config.densify_seed, config.densify_opacity)
                started = time.perf_counter()
                target = GraphTarget(checkpoint, dense, ViewerConfig(splat_budget=count))
                server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
                app = ViewerApp(server, target, frame=frame)
                setup_s = time.perf_counter() - started
                try:
                    if empty_shot is None:  # the same view of nothing: every count has the same initial camera
                        empty = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
                        empty.initial_camera.position = server.initial_camera.position
                        empty.initial_camera.look_at = server.initial_camera.look_at
                        try:
                            page = browser.new_page(viewport={"width": width, "height": height})
                            page.goto(f"http://127.0.0.1:{empty.get_port()}")
                            page.locator("canvas").first.wait_for(timeout=60_000)
                            empty_shot = settled_shot(page, config.scene_columns)
                            page.close()
                        finally:
                            empty.stop()
                    context = browser.new_context(viewport={"width": width, "height": height})
                    context.add_init_script(FRAME_COUNTER)
                    page = context.new_page()
                    shown = first_frame(page, f"http://127.0.0.1:{server.get_port()}", empty_shot, config)
                    fps = orbit_fps(page, server, config)
                    context.close()
                finally:
                    app.close()
                    server.stop()
                drawn = sum(len(s) for s in target.layers.values())
                rows.append({"gaussians": count, "drawn_splats": drawn, "fitted_gaussians": graph.n_gaussians,
                             "densified_copies": max(0, dense.n_gaussians - graph.n_gaussians),
                             "server_setup_s": setup_s, **shown, **fps})
                if measured is not None:
                    measured(rows)
        finally:
            browser.close()
    return rows


def _moved(world_from_box: np.ndarray, sideways_m: float, yaw_deg: float) -> np.ndarray:  # [4, 4] -> [4, 4]
    """A box pose moved ``sideways_m`` along its own y and turned ``yaw_deg`` about its own z."""
    yaw = math.radians(yaw_deg)
    step = np.eye(4)
    step[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    step[1, 3] = sideways_m
    return np.asarray(world_from_box, dtype=np.float64) @ step


#: The sources of the page's images, joined: viser gives each new camera image a new blob URL.
IMAGE_SOURCES = "() => Array.from(document.images).map(i => i.src).join('|')"
#: True once the page's images are others than ``old`` and all of them decoded.
IMAGES_CHANGED = ("old => { const imgs = Array.from(document.images); "
                  "return imgs.map(i => i.src).join('|') !== old && imgs.every(i => i.complete); }")


def quiet_images(page, quiet_s: float = 0.6, timeout_s: float = 60.0) -> str:
    """The page's image sources once they have not changed for ``quiet_s`` (every update sent has arrived)."""
    last, since = page.evaluate(IMAGE_SOURCES), time.monotonic()
    deadline = since + timeout_s
    while time.monotonic() < deadline:
        page.wait_for_timeout(50)
        now = page.evaluate(IMAGE_SOURCES)
        if now != last:
            last, since = now, time.monotonic()
        elif time.monotonic() - since >= quiet_s:
            return now
    raise OmniscsError(f"the viewer's camera image kept changing for {timeout_s:.0f} s; is the machine overloaded?")


def measure_edits(app, page, frame: int, config: ViewBenchConfig, progress: Progress = no_progress) -> dict:
    """Edits of the agents the camera sees at ``frame``, in turn, each through ``ViewerApp.move_selected`` (what a
    gizmo release runs), with the viewer open in ``page`` (None: no browser connected): ``handler_s`` until the handler
    returns with the new camera image set, ``shown_s`` until the page holds the new image (decoded; None without a
    page); and the camera image alone (render + boxes) after each. The first image (kernels compiled or loaded) is
    made before timing."""
    target = app.target
    camera = app.camera.value
    app.refresh_image()  # warm-up
    tracks = seen_agents(target.session.graph, frame, camera)
    if not tracks:
        raise OmniscsError(f"camera {camera} sees no agent node at frame {frame}; nothing to edit in its view")
    rows = []
    for k in range(config.edits):
        tid = tracks[k % len(tracks)]
        progress(k, config.edits, f"edit {k + 1}: agent {tid}")
        app.select(tid)
        old = None if page is None else quiet_images(page)  # the selection's own images have arrived
        box = next(b for b in target.frame_state(frame).boxes if b.track_id == tid)
        pose = _moved(box.world_from_box, config.edit_step_m * (1 if k % 2 == 0 else -1), 5.0)
        handled: dict[str, float] = {}

        def edit() -> None:
            began = time.perf_counter()
            app.move_selected(pose)
            handled["s"] = time.perf_counter() - began

        drawn = None if page is None else page.evaluate("window.__omniscsFrames")
        started = time.perf_counter()
        worker = threading.Thread(target=edit, name="omniscs-bench-edit")  # as viser runs a handler: off the page
        worker.start()
        shown_s = None
        if page is not None:
            try:
                page.wait_for_function(IMAGES_CHANGED, arg=old, polling=10, timeout=60_000)
                shown_s = time.perf_counter() - started
                drawn = page.evaluate("window.__omniscsFrames") - drawn
            except Exception:  # noqa: BLE001 - playwright's timeout: counted as not shown, the run goes on
                pass
        worker.join()
        if page is not None:
            quiet_images(page)
        began = time.perf_counter()
        image = target.camera_image(camera, frame, True, tid)
        image_s = time.perf_counter() - began
        rows.append({"edit": k, "track_id": tid, "browser": page is not None, "shown_s": shown_s,
                     "frames_drawn_until_shown": drawn if shown_s is not None else None, "handler_s": handled["s"],
                     "camera_image_s": image_s, "accepted": not app.status.content.startswith("Move refused"),
                     "image_size": f"{image.shape[1]}x{image.shape[0]}"})
    return {"rows": rows, "tracks": tracks, "camera": camera}


def close_notifications(page, wait_s: float = 10.0) -> None:
    """Close the browser's toasts (chromium's software WebGL is announced by one, a few seconds after the page
    loads) so they do not hide the view; waits up to ``wait_s`` for one to appear (a GPU browser shows none)."""
    close = page.locator(".mantine-Notification-closeButton")
    try:
        close.first.wait_for(timeout=wait_s * 1000)
    except Exception:  # noqa: BLE001 - playwright's timeout: no toast to close
        return
    for button in close.all():
        try:
            button.click(timeout=2_000)
        except Exception:  # noqa: BLE001 - a toast that closed by itself meanwhile
            continue
    page.wait_for_timeout(1_500)  # its closing animation


def _quantised_png(png: bytes, f) -> None:
    """A screenshot as a 256-colour PNG (reports keep pictures small)."""
    from PIL import Image

    Image.open(io.BytesIO(png)).convert("RGB").quantize(256).save(f, format="PNG", optimize=True)


def _percentile(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values, dtype=np.float64), q))


def run_view_benchmark(out_dir: str | Path, workspace: str | Path | None = None,
                       config: ViewBenchConfig | None = None, progress: Progress = no_progress) -> dict:
    """Fit (or reuse) the benchmark's world, measure the splat view per count and the edit latency, and write
    ``<out_dir>/view/report.json``, ``report.md``, ``report.png`` (frame rate per count) and ``viewer.png``."""
    import viser

    from omniscs.nsg.checkpoint import load_graph
    from omniscs.storage import workspace_root
    from omniscs.viewer.app import ViewerApp
    from omniscs.viewer.state import ViewerConfig
    from omniscs.viewer.targets import GraphTarget

    config = config or ViewBenchConfig()
    chromium_path()  # before the fit: a missing browser is one line, not a failure after minutes
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        raise OmniscsError("the Python package playwright is not installed; `pip install -e .[test]` installs it") \
            from None
    machine = machine_info()
    ws = workspace_root(workspace)
    world = prepare(config, ws, progress)
    checkpoint = Path(world["checkpoint"])
    graph = load_graph(checkpoint)
    frame = busiest_frame(graph)
    world.update({"fitted_gaussians": graph.n_gaussians, "agent_nodes": len(graph.agents), "frame": frame})

    # edits first, with the viewer of the fitted graph open in the browser; then its screenshot
    from playwright.sync_api import sync_playwright

    edit_graph = resized_cameras(graph, *config.image_size)
    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    app = ViewerApp(server, GraphTarget(checkpoint, edit_graph, ViewerConfig()), frame=frame)
    width, height = config.viewport
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium_path(), headless=True, args=list(CHROMIUM_ARGS))
            try:
                browser_version = browser.version
                context = browser.new_context(viewport={"width": width, "height": height})
                context.add_init_script(FRAME_COUNTER)
                page = context.new_page()
                page.goto(f"http://127.0.0.1:{server.get_port()}")
                page.get_by_role("button", name="Save edits").wait_for(timeout=120_000)
                settled_shot(page, config.scene_columns)
                edits = measure_edits(app, page, frame, config, progress)
                context.close()  # the same edits again with no browser connected: the server's own share
                alone = measure_edits(app, None, frame, config, progress)
                progress(0, None, "screenshot of the viewer")
                app.select(edits["tracks"][0])
                page = browser.new_page(viewport={"width": width, "height": height})
                page.goto(f"http://127.0.0.1:{server.get_port()}")
                page.get_by_role("button", name="Save edits").wait_for(timeout=120_000)
                quiet_images(page)
                close_notifications(page)
                settled_shot(page, config.scene_columns)
                picture = page.screenshot()
            finally:
                browser.close()
    finally:
        app.close()
        server.stop()
    edits["rows"] += alone["rows"]
    save_partial(out_dir, BENCH, edits["rows"])  # a run cut short in the browser part still has its edits
    splat_rows = measure_splat_view(graph, checkpoint, frame, config, progress,
                                    lambda rows: save_partial(out_dir, BENCH, edits["rows"] + rows))

    accepted = [r for r in edits["rows"] if r["accepted"] and r["browser"] and r["shown_s"] is not None]
    alone_rows = [r for r in edits["rows"] if r["accepted"] and not r["browser"]]

    def spread(key: str, rows: list[dict] = accepted) -> dict:
        values = [r[key] for r in rows]
        return {"median_s": statistics.median(values), "p90_s": _percentile(values, 90), "max_s": max(values)} \
            if values else {"median_s": None, "p90_s": None, "max_s": None}

    shown = spread("shown_s")
    summary = {"edits": config.edits, "accepted": sum(r["accepted"] for r in edits["rows"] if r["browser"]),
               "timed": len(accepted), "agents": len({r["track_id"] for r in accepted}),
               "image_size": f"{config.image_size[0]}x{config.image_size[1]}", "shown": shown,
               "handler": spread("handler_s"), "camera_image": spread("camera_image_s"),
               "handler_no_browser": spread("handler_s", alone_rows),
               "camera_image_no_browser": spread("camera_image_s", alone_rows),
               "target_s": config.edit_target_s,
               "meets_target": shown["median_s"] is not None and shown["median_s"] < config.edit_target_s
               and shown["p90_s"] < config.edit_target_s}
    report = {"benchmark": BENCH, "config": asdict(config), "world": world, "splat_view": splat_rows,
              "edit_latency": summary, "edits": edits["rows"],
              "renderer": "chromium (Debian) headless, WebGL through ANGLE over SwiftShader: software, on the CPU",
              "browser": browser_version, "densify_rule": DENSIFY_RULE.format(opacity=config.densify_opacity),
              "machine": finish(machine)}
    write_report(out_dir, BENCH, report, markdown(report),
                 {"": lambda f: _plot(splat_rows, f), "viewer": lambda f: _quantised_png(picture, f)})
    drop_partial(out_dir, BENCH)
    return report


# ----------------------------------------------------------------------------- the report
def _num(value, fmt: str = "{:.2f}") -> str:
    return "-" if value is None else fmt.format(value)


def markdown(report: dict) -> str:
    cfg, world, e = report["config"], report["world"], report["edit_latency"]
    lines = [
        "# Viewer benchmark (`omniscs bench view`)", "",
        f"World: the procedural log `{world['scene']}` ({cfg['n_frames']} frames, one {cfg['fit_size'][0]}x"
        f"{cfg['fit_size'][1]} front camera; a held-out seed), fitted with the `{cfg['fit_preset']}` preset "
        f"({world['fitted_gaussians']:,} Gaussians, {world['agent_nodes']} agent nodes"
        + (f", {world['fit_seconds']:.0f} s fit" if world.get("fit_seconds") else "")
        + (f", held-out PSNR {world['heldout_psnr']:.1f} dB" if world.get("heldout_psnr") else "")
        + f"), viewed at frame {world['frame']}.", "",
        f"Browser: {report['renderer']} ({report.get('browser') or 'version unknown'}), window "
        f"{cfg['viewport'][0]}x{cfg['viewport'][1]}. **Its WebGL is software (SwiftShader on this machine's CPUs), "
        "so the frame rates below are a floor for a machine with a GPU.**", "",
        "## Splat view", "",
        "Time to first frame: from the start of the page load to the end of the first screenshot of the 3D view "
        f"(the canvas left of the panel) that shows at least {cfg['splats_shown_share']:.0%} of the settled view's "
        "change from the empty scene (a viser server with the same camera and nothing in it). Screenshots are taken "
        "back to back; each waits for the page to produce a frame, so the splats appeared between the end of the shot "
        "before (the 'after' column) and the end of that shot. First draw: the page's first WebGL draw call of "
        "anything (its own clock, from navigation start). Settled: three shots over 0.4 s or more agree. "
        "Frame rate: frames the page drew (animation-frame ticks with a WebGL draw call; viser draws on demand) over "
        f"{cfg['orbit_seconds']:g} s (longer until it drew {cfg['orbit_min_frames']} frames, at most "
        f"{cfg['orbit_max_seconds']:g} s) while the server orbits the browser's camera about its look-at point (one "
        f"turn per {cfg['orbit_period_s']:g} s, {cfg['orbit_updates_hz']:g} poses per second through viser's client "
        "camera API). Server set-up: the target (activation, splat layers) and the viewer's scene and panel, before "
        "the page load.", "",
        f"How each count was made: {report['densify_rule']}. A count below the fit's Gaussians keeps the most "
        "opaque (the viewer's own budget).", "",
        "| Gaussians | drawn splats | densified copies | server set-up (s) | page load (s) | first draw (s) | "
        "first frame (s) | after (s) | settled (s) | orbit fps | orbit frames | view changed by orbit |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in report["splat_view"]:
        lines.append(f"| {r['gaussians']:,} | {r['drawn_splats']:,} | {r['densified_copies']:,} | "
                     f"{_num(r['server_setup_s'])} | {_num(r['page_load_s'])} | {_num(r['first_draw_s'])} | "
                     f"{_num(r['first_frame_s'])} | {_num(r['first_frame_after_s'])} | {_num(r['settled_s'])} | "
                     f"{_num(r['orbit_fps'], '{:.1f}')} | {r['orbit_frames']} | {r['orbit_changed_view']:.0%} |")
    verdict = "meets" if e["meets_target"] else "misses"
    lines += [
        "", "## Edit to camera image", "",
        f"{e['edits']} moves ({e['accepted']} accepted, {e['timed']} seen arriving in the browser) of {e['agents']} "
        f"agents that the camera sees at frame {world['frame']} (the frame where it sees the most agent nodes), in "
        f"turn, each {cfg['edit_step_m']:g} m sideways and turned 5 degrees, through the viewer's gizmo-release "
        "handler (`ViewerApp.move_selected`: the edit session, the 3D scene, and the camera image rendered by our "
        f"rasteriser at {e['image_size']} with its boxes), run on a thread as viser runs handlers, with the viewer "
        "open in the browser. Shown: from the call until the page holds the new camera image, decoded. Handler: until "
        "the handler returns with the image set. Camera image: the same render and boxes timed again after each edit. "
        "The first image (kernel compilation) is made before timing. Then the same edits again with the page closed: "
        "what the server itself takes when no software-WebGL browser shares the machine's CPUs.", "",
        "| step | median (s) | p90 (s) | max (s) |", "|---|---|---|---|"]
    for key, name in (("shown", "edit to image shown in the browser"), ("handler", "edit handler (server)"),
                      ("camera_image", "camera image alone (render + boxes)"),
                      ("handler_no_browser", "edit handler, no browser connected"),
                      ("camera_image_no_browser", "camera image alone, no browser connected")):
        lines.append(f"| {name} | {_num(e[key]['median_s'], '{:.3f}')} | {_num(e[key]['p90_s'], '{:.3f}')} | "
                     f"{_num(e[key]['max_s'], '{:.3f}')} |")
    drawn = [r["frames_drawn_until_shown"] for r in report["edits"] if r.get("frames_drawn_until_shown") is not None]
    if e["handler_no_browser"]["median_s"] is not None and drawn:
        lines += ["", f"With no browser connected the handler takes {e['handler_no_browser']['median_s']:.3f} s "
                  f"(median; the camera image {e['camera_image_no_browser']['median_s']:.3f} s of it); with the page "
                  f"open, {e['handler']['median_s']:.3f} s, and the page drew a median of {statistics.median(drawn):g} "
                  "frame(s) of its 3D view between an edit and its new camera image: chromium's software WebGL "
                  "redraws on the same CPUs as the server."]
    lines += [
        "", f"The camera view {verdict} the issue's target (shown in the browser under {e['target_s']:g} s at "
        f"{e['image_size']} after each edit, median and p90, on this machine).", "",
        "![the viewer](viewer.png)", "",
        "The viewer after the timed edits, the first edited agent selected: splats, agent boxes with their track ids, "
        "the gizmo, and the panel with the camera view.", "",
        load_line(report["machine"]), ""]
    return "\n".join(lines)


def _plot(rows: list[dict], f) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    counts = [r["gaussians"] for r in rows]
    fig, (left, right) = plt.subplots(1, 2, figsize=(9, 3.4))
    left.plot(counts, [r["first_frame_s"] or float("nan") for r in rows], "o-", label="first frame")
    left.plot(counts, [r["settled_s"] or float("nan") for r in rows], "s--", label="settled")
    left.set_xlabel("Gaussians drawn")
    left.set_ylabel("seconds after page load")
    left.legend()
    right.plot(counts, [r["orbit_fps"] for r in rows], "o-", color="#dd8452")
    right.set_xlabel("Gaussians drawn")
    right.set_ylabel("frames per second (orbiting)")
    right.set_title("software WebGL (SwiftShader): a floor", fontsize=9)
    for ax in (left, right):
        ax.set_xscale("log")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(f, format="png", dpi=90)
    plt.close(fig)
