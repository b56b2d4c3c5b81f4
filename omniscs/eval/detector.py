"""The embedded proxy camera 3D detector: a small CenterNet-style network, trained here from scratch on 2 cores, that
finds the nuScenes detection classes in the cameras of a nuScenes dataroot and writes nuScenes detection results.
A stand-in for UniAD's detection head (a real learner, far weaker than UniAD), so that the paper's detection protocol
(base vs fine-tuned with appearance-SCS data; mAP, NDS) runs end to end on this machine; real stacks run as
external jobs.

Reads any nuScenes-format dataroot (the factory's exports or the real dataset): per keyframe sample and camera
(``sample_data`` of a ``CAM_*`` channel with ``is_key_frame``) the image, intrinsics and poses, and the sample's
annotations (global frame) projected into that camera.

Network (input: the image resized to ``DetectorConfig.input_width`` x ``input_height``, plus two coordinate channels
that let it read depth from the image row): four stride-2 blocks of two 3x3 convolutions (BN, ReLU; ``widths``), a
top-down path back to stride 4 (``STRIDE``) adding 1x1 lateral projections, then two 3x3 branches of ``head_width``:
  - heatmap: one logit per class of ``classes`` (all ten nuScenes detection classes by default) at each cell;
  - regression (``REGRESSION`` channels): sub-cell offset of the projected centre (2); log depth of the centre along
    the optical axis at ``reference_focal`` px (1: the depth is rescaled by the camera's focal length, so other
    intrinsics and input sizes read the same); log size (width, length, height: the nuScenes order) relative to the
    class's typical size (3); sin and cos of the *observation angle* alpha = global yaw - ground-plane azimuth of the
    ray from the camera to the centre (2: what an image shows of a box's heading; the same for every camera);
    velocity along and across that ray (m/s over ``VELOCITY_SCALE``: 2); the ground contact, where the box's bottom
    centre projects, relative to the cell (2).
Losses: CenterNet's penalty-reduced focal loss on the heatmaps (Gaussian peaks of the radius CenterNet derives from
the projected 2D box) and L1 on each regression at the object centres, each normalised by the number of centres.
Decoding: 3x3 max-pool peaks, the top ``DetectConfig.top_k`` per image above ``score_threshold``, each centre placed
twice: back-projected with the regressed depth, and read from the ground (the ray through the contact pixel meets the
ego's z = 0 plane, the centre is half the box height above it; a flat-ground assumption). The two are weighed by their
expected errors at that distance (inverse variances, from errors measured on the training images after training:
``calibrate_depth``): the ground reading is precise near the camera and loses a row's worth of precision
quadratically with distance, the regressed depth errs in proportion to it. Then camera -> ego -> global, and a
centre-distance NMS per class across the cameras of a sample.
"""
from __future__ import annotations

from pathlib import Path

from safetensors.torch import load_file, save_file

from omniscs.errors import ValidationError
from omniscs.eval.detection import DetectionConfig, filter_boxes
from omniscs.eval.detector_config import DetectConfig, DetectorConfig, DetectorTrainConfig, config_dict
from omniscs.eval.detector_decoding import detect, write_results
from omniscs.eval.detector_network import ProxyDetector
from omniscs.eval.detector_training import train_detector, training_set
from omniscs.eval.nuscenes_io import (
    NuScenesTables,
    evaluate_detection_results,
    evaluated_classes,
    evaluated_ground_truth,
)
from omniscs.pretrained.registry import folder as shipped_folder, network_with_weights, verified_folder
from omniscs.storage import atomic_directory, atomic_write_json, atomic_write_text
from omniscs.untrusted import read_json

WEIGHTS = "detector.safetensors"
CONFIG = "detector_config.json"
TRAINING = "training.json"
README = "README.md"
#: The detector shipped with the package (registry entry ``detector``; ``omniscs pretrained train detector``).
DEFAULT_DETECTOR = shipped_folder("detector")

#: The detector's public API: its checkpoints here, the rest re-exported from the modules it is split into
#: (detector_config, detector_views, detector_network, detector_training, detector_decoding), so omniscs/bench/ and
#: omniscs/pipeline/ import it from one place.
__all__ = ["CONFIG", "DEFAULT_DETECTOR", "README", "TRAINING", "WEIGHTS", "DetectConfig", "DetectorConfig",
           "DetectorTrainConfig", "ProxyDetector", "detect", "evaluate_detector", "load_detector", "save_detector",
           "score_detections", "train_detector", "training_set", "write_results"]


# ----------------------------------------------------------------------------- checkpoints
def save_detector(model: ProxyDetector, out_dir: str | Path, training: dict, overwrite: bool = False,
                  readme: str | None = None) -> Path:
    """Weights (safetensors), network config, training record (and a README when given), written atomically."""
    with atomic_directory(Path(out_dir), overwrite=overwrite) as tmp:
        save_file({k: v.detach().contiguous() for k, v in model.state_dict().items()}, str(tmp / WEIGHTS))
        atomic_write_json(tmp / CONFIG, config_dict(model.config))
        atomic_write_json(tmp / TRAINING, training)
        if readme is not None:
            atomic_write_text(tmp / README, readme)
    return Path(out_dir)


def load_detector(path: str | Path | None = None) -> ProxyDetector:
    """A saved detector (default: the shipped one); a clear error when the folder is not one."""
    path = verified_folder(path if path is not None else DEFAULT_DETECTOR)
    try:
        raw = read_json(path / CONFIG, f"{path} is not a proxy detector checkpoint; train one with `omniscs "
                        "pretrained train detector` or name its folder", expect=dict, error=ValidationError)
        config = DetectorConfig(**{**raw, "widths": tuple(raw["widths"]), "classes": tuple(raw["classes"])})
        state = load_file(str(path / WEIGHTS))
    except (OSError, ValueError, TypeError, KeyError) as e:
        raise ValidationError(f"{path} is not a proxy detector checkpoint ({e}); train one with "
                              "`omniscs pretrained train detector` or name its folder") from e
    return network_with_weights(ProxyDetector(config), state, path, CONFIG)


def evaluate_detector(model: ProxyDetector, dataroot: str | Path, version: str, results_path: str | Path,
                      config: DetectConfig = DetectConfig(), camera_view: bool = False) -> dict:
    """``model``'s detections of every keyframe of ``dataroot`` written to ``results_path`` and scored
    (``score_detections``)."""
    write_results(detect(model, dataroot, version, config=config), results_path)
    return score_detections(dataroot, version, results_path, camera_view)


def score_detections(dataroot: str | Path, version: str, results_path: str | Path, camera_view: bool = False) -> dict:
    """A results file scored by the nuScenes protocol over the classes the dataroot's evaluated ground truth holds (a
    class absent from a set would only add a zero): mAP, NDS, AP per class (the mean over the distance thresholds,
    and at each), evaluated boxes per class, samples. ``camera_view``: only the boxes a camera sees count
    (``nuscenes_io.in_camera_view``)."""
    tables = NuScenesTables.load(dataroot, version)
    gt, racks = evaluated_ground_truth(tables, tables.scene_samples(), camera_view)
    names = filter_boxes(gt, DetectionConfig(), racks).name
    present = evaluated_classes(gt, racks)
    if not present:
        raise ValidationError(f"{Path(dataroot) / version} has no evaluated ground-truth box"
                              f"{' in a camera view' if camera_view else ''} to score detections on")
    metrics, info = evaluate_detection_results(dataroot, version, results_path,
                                               config=DetectionConfig(class_names=present), camera_view=camera_view)
    return {"mAP": float(metrics.mean_ap), "NDS": float(metrics.nd_score), "classes": list(present),
            "AP": {c: float(v) for c, v in metrics.mean_dist_aps.items()},
            "AP_by_threshold": {c: {f"{t:g}": float(a) for t, a in metrics.label_aps[c].items()} for c in present},
            "gt_boxes": {c: int((names == c).sum()) for c in present}, "n_samples": int(info["n_samples"]),
            "camera_view": bool(camera_view)}
