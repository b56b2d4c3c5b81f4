"""Behaviour-level safety-critical scenarios: a STRIVE-like traffic model (graph network, per-agent latent,
kinematic bicycle decoding) and adversarial latent optimisation with L_adv = L_beh + L_app + L_restore."""
from omniscs.scs.behavior.adversarial import (PRESETS, AdversarialConfig, BehaviorProblem, ComfortBounds,
                                              VariantResult, adversarial_preset, behaviour_loss, generate_variants)
from omniscs.scs.behavior.appearance import (AgentTrajectories, AppearanceTerm, FeatureNet,
                                             FeatureNetConfig, build_feature_net, masked_psnr, variant_ground_truth)
from omniscs.scs.behavior.checkpoint import DEFAULT_CHECKPOINT, load_checkpoint, save_checkpoint
from omniscs.scs.behavior.kinematics import KinematicLimits, rollout
from omniscs.scs.behavior.model import ModelConfig, TrafficModel
from omniscs.scs.behavior.planner import PlannerConfig
from omniscs.scs.behavior.tracks import EgoBox, TrafficScene, traffic_from_scene, traffic_from_world
from omniscs.scs.behavior.train import TrainConfig, train_model, train_preset
from omniscs.scs.behavior.variants import load_traffic, variant_spec, write_scene_variants

__all__ = [
    "PRESETS", "AdversarialConfig", "BehaviorProblem", "ComfortBounds", "VariantResult", "adversarial_preset",
    "behaviour_loss", "generate_variants", "AgentTrajectories", "AppearanceTerm", "FeatureNet",
    "FeatureNetConfig", "build_feature_net", "masked_psnr", "variant_ground_truth", "DEFAULT_CHECKPOINT",
    "load_checkpoint", "save_checkpoint", "KinematicLimits", "rollout", "ModelConfig", "TrafficModel",
    "PlannerConfig", "EgoBox", "TrafficScene", "traffic_from_scene", "traffic_from_world", "TrainConfig",
    "train_model", "train_preset", "load_traffic", "variant_spec", "write_scene_variants",
]
