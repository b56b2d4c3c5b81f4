"""``DriveArenaDriver`` against a small agent written to DriveArena's driver spec on loopback: one well-formed,
polled frame per step drives the log; an agent that is not there is a clear domain error."""
from __future__ import annotations

import base64
import io
import socket

import numpy as np
import pytest
from fastapi import FastAPI, HTTPException, Request, Response
from PIL import Image

from omniscs.closedloop.policies import DRIVEARENA_CAMERAS, DRIVEARENA_SIZE, DriveArenaDriver
from omniscs.closedloop.run import run_episode
from omniscs.closedloop.simulator import ClosedLoopConfig, Simulator
from omniscs.errors import OmniscsError
from omniscs.server.transport import start_in_thread

CAMERA = "CAM_FRONT"


class StraightAgent:
    """What the agent saw, and the plan it will hand out: straight ahead at the speed it was told."""

    def __init__(self) -> None:
        self.frames: list[dict] = []  # one per POST /driver-api/
        self.plan = None
        self.answered_not_ready = False
        self.not_ready = 0             # 204 replies given
        self.cleans = 0

    def app(self) -> FastAPI:
        app = FastAPI()
        W, H = DRIVEARENA_SIZE

        @app.post("/driver-api/")
        async def driver_api(request: Request):
            body = await request.json()
            image = np.asarray(Image.open(io.BytesIO(base64.b64decode(body["img_byte_array"]))).convert("RGB"))
            if image.shape != (len(DRIVEARENA_CAMERAS) * H, W, 3):
                raise HTTPException(422, f"expected six {W} x {H} tiles stacked, got {image.shape}")
            tiles = image.reshape(len(DRIVEARENA_CAMERAS), H, W, 3)
            self.frames.append({key: body[key] for key in ("timestamp", "command", "ego_pose", "vel", "accel",
                                                           "rotation_rate")}
                               | {"tile_means": tiles.reshape(len(tiles), -1).mean(1)})
            v = float(body["vel"][0])
            self.plan = [[[0.0, v * 0.5 * k] for k in range(1, 7)]]
            self.answered_not_ready = False
            return {"ok": True}

        @app.get("/driver-get/")
        async def driver_get():
            if self.plan is None or not self.answered_not_ready:  # the first poll after a frame: "not yet"
                self.answered_not_ready = self.plan is not None
                self.not_ready += 1
                return Response(status_code=204)
            plan, self.plan = self.plan, None
            return {"bbox_results": [{"planning_traj": plan}]}

        @app.get("/driver-clean/")
        async def driver_clean():
            self.frames, self.plan, self.not_ready = [], None, 0
            self.cleans += 1
            return {"ok": True}

        return app


def simulator(world) -> Simulator:  # world: (scene, graph, log scenario), the shared fit of ``conftest.world``
    scene, graph, _ = world
    return Simulator(graph, scene, ClosedLoopConfig(cameras=(CAMERA,), width=64, outputs=("rgb",)))


def test_a_drivearena_agent_drives_the_log_with_one_polled_frame_per_step(world):
    agent = StraightAgent()
    with start_in_thread(agent.app()) as server:
        result = run_episode(simulator(world), DriveArenaDriver(server.url, timeout_s=10), world[2])
    steps = result.summary["steps"]
    assert result.scores.route_completion > 0.5
    assert agent.cleans == 1
    assert steps >= 5 and len(agent.frames) == steps and agent.not_ready == steps
    assert [f["timestamp"] for f in agent.frames] == pytest.approx([0.1 * k for k in range(steps)])
    assert all(f["command"] in (0, 1, 2) for f in agent.frames)
    assert all(np.asarray(f["ego_pose"]).shape == (4, 4) for f in agent.frames)
    assert agent.frames[0]["vel"][0] > 1.0, "the agent was not told the ego's speed"
    means = np.stack([f["tile_means"] for f in agent.frames])
    front = DRIVEARENA_CAMERAS.index(CAMERA)
    assert (means[:, front] > 5).all(), "the front camera's tile is black"
    assert (np.delete(means, front, axis=1) == 0).all(), "cameras the graph lacks must be sent black"


def test_an_unreachable_agent_is_a_clear_domain_error(world):
    with socket.socket() as probe:  # a port nobody listens on
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    with pytest.raises(OmniscsError, match=f"127.0.0.1:{port} unreachable"):
        run_episode(simulator(world), DriveArenaDriver(f"http://127.0.0.1:{port}", timeout_s=5), world[2])
