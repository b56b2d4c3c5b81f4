"""Behaviour-level safety-critical scenarios: a STRIVE-like traffic model (graph network, per-agent latent,
kinematic bicycle decoding) and adversarial latent optimisation with L_adv = L_beh + L_app + L_restore.

The traffic model first reproduces the log (posterior latents, refined by fitting them to the logged future:
``problem``); then, per variant, every agent's latent is optimised so that the chosen adversary reaches the
planner's trajectory (L_beh, a log-sum-exp softmax over agents and steps: ``losses``), the rendered scene keeps its
look (L_app, the render-consistency term, only when a differentiable renderer is supplied: ``render_consistency``)
and the latents stay near where they started (L_restore). A documented plausibility penalty (comfort, collisions
with others, leaving the road: ``evaluation``) is added by default; set its weights to 0 for the paper's three terms
alone. An adversary that fails from the log's latents (and a standing one from the outset) restarts from a warm
start: a search over its control knots finds a comfortable path into the ego (``optimisation.intercept``) and its
latent is refitted to that path. ``generation`` schedules adversaries and time windows into N distinct variants.
"""
from omniscs.comfort import ComfortBounds
from omniscs.scs.behavior.adversarial_config import PRESETS, AdversarialConfig, adversarial_preset
from omniscs.scs.behavior.render_consistency import (AgentTrajectories, FeatureNet, FeatureNetConfig,
                                                    RenderConsistencyTerm, build_feature_net, masked_psnr)
from omniscs.devices import resolve_device
from omniscs.scs.behavior.checkpoint import DEFAULT_CHECKPOINT, load_traffic_model, save_checkpoint
from omniscs.scs.behavior.evaluation import Evaluation, VariantResult, evaluate
from omniscs.scs.behavior.generation import distinct_variants, generate_variants
from omniscs.scs.behavior.kinematics import KinematicLimits, rollout
from omniscs.scs.behavior.losses import behavior_loss
from omniscs.scs.behavior.model import ModelConfig, TrafficModel
from omniscs.scs.behavior.planner import PlannerConfig
from omniscs.scs.behavior.problem import BehaviorProblem, now_and_horizon
from omniscs.scs.behavior.tracks import EgoBox, TrafficScene, traffic_from_log, traffic_from_scene
from omniscs.scs.behavior.train import TrainConfig, train_model, train_preset
from omniscs.scs.behavior.variants import variant_spec, write_scene_variants

__all__ = [
    "PRESETS", "AdversarialConfig", "BehaviorProblem", "ComfortBounds", "Evaluation", "VariantResult",
    "adversarial_preset", "behavior_loss", "distinct_variants", "evaluate", "generate_variants", "now_and_horizon",
    "AgentTrajectories", "RenderConsistencyTerm", "FeatureNet", "FeatureNetConfig", "build_feature_net", "masked_psnr",
    "DEFAULT_CHECKPOINT", "load_traffic_model", "resolve_device", "save_checkpoint", "KinematicLimits", "rollout",
    "ModelConfig", "TrafficModel", "PlannerConfig", "EgoBox", "TrafficScene", "traffic_from_log",
    "traffic_from_scene", "TrainConfig", "train_model", "train_preset", "variant_spec", "write_scene_variants",
]
