"""Training of the shipped proxy planner (``omniscs.eval.planner``, registry entry ``planner``): procedural logs
without any SCS, one planning example every 0.5 s, laid out as the planning protocol lays out its train scenes
(``omniscs.pipeline.procedural.procedural_scenes``: templates in turn from ``train_seed``), so that the protocol can
name the base's logs from its training record and rehearse them.

Reproduce the shipped weights (seconds on 2 cores)::

    omniscs pretrained train planner
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from omniscs.errors import OmniscsError
from omniscs.eval.planner import DEFAULT_PLANNER, ProxyPlanner, TrainConfig, save_planner, train_planner
from omniscs.eval.scenarios import planning_examples, scenario_from_traffic
from omniscs.pipeline.procedural import procedural_scene_id, procedural_scenes, procedural_traffic
from omniscs.progress import Progress, no_progress
from omniscs.world.layouts import TEMPLATES

#: The command that reproduces the shipped planner (recorded in training.json).
TRAIN_COMMAND = "omniscs pretrained train planner"


@dataclass(frozen=True)
class ShippedPlannerConfig:
    """The shipped planner's data and training (its training.json: seeds 300000-300039, 100 frames, 40 epochs)."""

    train_scenes: int = 40
    """Procedural train logs (templates in turn)."""
    train_seed: int = 300_000
    """Seed of the first train log; the planning protocol's train scenes start here too."""
    n_frames: int = 100
    """Frames per log (10 Hz)."""
    train: TrainConfig = field(default_factory=lambda: TrainConfig(epochs=40, seed=0))
    """Optimiser settings of the run."""


def planner_logs(config: ShippedPlannerConfig, progress: Progress = no_progress) -> list:
    """The planning examples of the train logs, scene after scene (a log whose world cannot be built is skipped, as
    the planning protocol skips it)."""
    scenes = procedural_scenes(TEMPLATES, config.train_seed, config.train_scenes)
    examples = []
    for i, (template, seed) in enumerate(scenes):
        progress(i, len(scenes), f"train log {template}:{seed}")
        try:
            traffic = procedural_traffic(template, seed, config.n_frames,
                                         scene_id=procedural_scene_id(template, seed))
        except OmniscsError:
            continue
        examples += planning_examples(scenario_from_traffic(traffic))
    progress(len(scenes), len(scenes), "train logs")
    return examples


def train_shipped_planner(config: ShippedPlannerConfig = ShippedPlannerConfig(), out: Path | None = DEFAULT_PLANNER,
                          progress: Progress = no_progress) -> tuple[ProxyPlanner, dict]:
    """Train the base planner on the train logs and write it with its record to ``out`` (replacing what is there;
    None: write nothing). Returns the model and the record."""
    progress(0, None, "training the base planner on the train logs")
    model, record = train_planner(planner_logs(config, progress), config.train, progress=progress)
    record.update(command=TRAIN_COMMAND, data={
        "templates": list(TEMPLATES), "train_seeds": [config.train_seed, config.train_seed + config.train_scenes - 1],
        "n_frames": config.n_frames, "source": "procedural logs (procedural_traffic), no SCS"})
    if out is not None:
        save_planner(model, out, record, overwrite=True)
    return model, record


__all__ = ["ShippedPlannerConfig", "TRAIN_COMMAND", "planner_logs", "train_shipped_planner"]
