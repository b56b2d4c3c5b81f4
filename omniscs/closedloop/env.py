"""The simulator as a gymnasium environment, registered as ``omniscs/ClosedLoop-v0``.

``reset(options={"scenario": ClosedLoopScenario})`` starts an episode (default: the environment's own scenario);
``step(action)`` takes a plan ([6, 2] float waypoints in the planning frame, x right, y forward, at 0.5 s) or a dict
``{"accel": a, "steer_rate": r}`` of direct controls. Observations are a dict per output (rgb, depth, instance,
semantic) of per-camera arrays; ``info`` is the simulator's (HUGSIM's keys and ours). The reward is the step's
progress along the route in metres, minus 100 at a collision: scores that matter are the run's PDMS and HD-Score,
which ``info["scores"]`` carries when the episode ends."""
from __future__ import annotations

import gymnasium
import numpy as np
from gymnasium import spaces

from omniscs.closedloop import metrics
from omniscs.closedloop.epdms import score_with_epdms
from omniscs.closedloop.run import scored_trace
from omniscs.closedloop.scenario import ClosedLoopScenario
from omniscs.closedloop.simulator import ClosedLoopConfig, Simulator, StepResult
from omniscs.closedloop.vehicle import Controls
from omniscs.errors import ValidationError
from omniscs.eval.planning import STEPS

ENV_ID = "omniscs/ClosedLoop-v0"
COLLISION_PENALTY = 100.0


class ClosedLoopEnv(gymnasium.Env):
    metadata = {"render_modes": ["rgb_array"]}

    def __init__(self, graph, scene, scenario: ClosedLoopScenario, config: ClosedLoopConfig = ClosedLoopConfig(),
                 render_mode: str | None = None) -> None:
        super().__init__()
        self.sim = Simulator(graph, scene, config)
        self.scenario = scenario
        self.render_mode = render_mode
        images = {}
        for cam in self.sim.rig:
            shape = (cam.height, cam.width)
            images.setdefault("rgb", {})[cam.name] = spaces.Box(0, 255, shape + (3,), np.uint8)
            images.setdefault("depth", {})[cam.name] = spaces.Box(0.0, np.inf, shape, np.float32)
            images.setdefault("instance", {})[cam.name] = spaces.Box(-1, np.iinfo(np.int32).max, shape, np.int32)
            images.setdefault("semantic", {})[cam.name] = spaces.Box(0, 255, shape, np.uint8)
        self.observation_space = spaces.Dict({k: spaces.Dict(images[k]) for k in config.outputs})
        self.action_space = spaces.Box(-config.max_plan_m, config.max_plan_m, (STEPS, 2), np.float64)
        self._last: StepResult | None = None
        self._progress = 0.0

    def _obs(self, res: StepResult) -> dict:
        return {k: getattr(res.observation, k) for k in self.sim.config.outputs}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        scenario = (options or {}).get("scenario", self.scenario)
        if not isinstance(scenario, ClosedLoopScenario):
            raise ValidationError("options['scenario'] must be a ClosedLoopScenario (omniscs.closedloop.scenario)")
        self.scenario = scenario
        self._last = self.sim.reset(scenario)
        self._progress = self._route_progress()
        return self._obs(self._last), self._last.info

    def _route_progress(self) -> float:
        ep = self.sim.episode
        return float(metrics.progress_along(self.sim.ego_centre()[None, :2], ep.scenario.route)[0])

    def step(self, action):
        if isinstance(action, dict):
            action = Controls(float(action["accel"]), float(action["steer_rate"]))
        res = self.sim.step(action)
        self._last = res
        progress = self._route_progress()
        reward = progress - self._progress - (COLLISION_PENALTY if res.info["collision"] else 0.0)
        self._progress = progress
        info = dict(res.info)
        terminated = res.done and res.reason in ("collision", "offroad", "route_completed", "left_fitted_area")
        truncated = res.done and not terminated
        if res.done:
            info["scores"] = score_with_epdms(scored_trace(self.sim)).to_dict()
        return self._obs(res), float(reward), bool(terminated), bool(truncated), info

    def render(self):
        if self.render_mode == "rgb_array" and self._last is not None:
            return next(iter(self._last.observation.rgb.values()), None)
        return None


def register() -> None:
    """Register ``omniscs/ClosedLoop-v0`` with gymnasium (idempotent):
    ``gymnasium.make(ENV_ID, graph=..., scene=..., scenario=..., config=...)``."""
    if ENV_ID not in gymnasium.registry:
        gymnasium.register(id=ENV_ID, entry_point="omniscs.closedloop.env:ClosedLoopEnv",
                           disable_env_checker=True, order_enforce=False)


register()
