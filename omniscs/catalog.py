"""The Parquet catalog: table schemas (declared here once), validated writes, read-only DuckDB queries.

Layout: ``<root>/<table>/run_id=<run_id>/<writer>-<time_us>-<uuid>.parquet``: hive-partitioned by run, one new
file per task, never edited in place; ``time_us`` (16 digits, microseconds since 1970) says when the file was
written. ``run_id`` lives in the path only, and the views add it back.

Every table has three views (see ``catalogs/README.md``): ``<table>`` shows each logical row once (rows of runs
that ended; a completed run wins over a failed or cancelled one, then the run that finished last),
``<table>_by_run`` one row per logical key and ended run (what a run produced), ``<table>_raw`` every row of every
file, with the file it came from (runs still going or killed included).
"""
from __future__ import annotations

import io
import os
import re
import time
import uuid
from pathlib import Path

import duckdb
import pyarrow as pa
import pyarrow.parquet as pq

from omniscs.errors import OmniscsError
from omniscs.ids import check_id
from omniscs.storage import atomic_write_bytes, inside
from omniscs.untrusted import check_parquet_files

SCHEMAS: dict[str, pa.Schema] = {
    "runs": pa.schema([
        pa.field("flow", pa.string(), nullable=False),
        pa.field("status", pa.string(), nullable=False),          # completed | failed | cancelled
        pa.field("started_at_us", pa.int64(), nullable=False),
        pa.field("finished_at_us", pa.int64(), nullable=False),
        pa.field("n_scenes", pa.int32(), nullable=False),
        pa.field("config_json", pa.string(), nullable=False),
        pa.field("omniscs_version", pa.string(), nullable=False),
        pa.field("error", pa.string()),
        pa.field("flow_run_id", pa.string()),                     # Prefect's flow run (what its events name)
    ]),
    "scenes": pa.schema([
        pa.field("scene_id", pa.string(), nullable=False),
        pa.field("source_kind", pa.string(), nullable=False),     # synthetic | store | nuscenes | ...
        pa.field("source_json", pa.string(), nullable=False),
        pa.field("template", pa.string()),
        pa.field("lighting", pa.string()),
        pa.field("seed", pa.int64()),
        pa.field("source_scene_id", pa.string()),                 # the dataset's own scene / sequence / segment id
        pa.field("dataroot", pa.string()),                        # the dataset root a recorded scene came from
        pa.field("location", pa.string()),                        # the dataset's location name, when it has one
        pa.field("path", pa.string(), nullable=False),
        pa.field("content_hash", pa.string(), nullable=False),
        pa.field("n_frames", pa.int32(), nullable=False),
        pa.field("duration_s", pa.float64(), nullable=False),
        pa.field("cameras", pa.list_(pa.string()), nullable=False),
        pa.field("n_tracks", pa.int32(), nullable=False),
        pa.field("n_moving", pa.int32(), nullable=False),
        pa.field("has_lidar", pa.bool_(), nullable=False),
        pa.field("has_gt", pa.bool_(), nullable=False),
        pa.field("reused", pa.bool_(), nullable=False),
        pa.field("ingest_seconds", pa.float64(), nullable=False),
        pa.field("preview_path", pa.string()),
    ]),
    "agents": pa.schema([
        pa.field("scene_id", pa.string(), nullable=False),
        pa.field("track_id", pa.int64(), nullable=False),
        pa.field("category", pa.string(), nullable=False),
        pa.field("source_category", pa.string()),
        pa.field("length", pa.float64(), nullable=False),
        pa.field("width", pa.float64(), nullable=False),
        pa.field("height", pa.float64(), nullable=False),
        pa.field("first_frame", pa.int32(), nullable=False),
        pa.field("last_frame", pa.int32(), nullable=False),
        pa.field("n_frames", pa.int32(), nullable=False),
        pa.field("path_length_m", pa.float64(), nullable=False),
        pa.field("max_speed_mps", pa.float64(), nullable=False),
        pa.field("moving", pa.bool_(), nullable=False),
        pa.field("frames_visible", pa.int32()),                   # frames with any visible pixel; null if unknown
        pa.field("mean_visible_pixels", pa.float64()),
        pa.field("max_visible_pixels", pa.int64()),
        pa.field("mean_lidar_points", pa.float64()),
        pa.field("min_distance_to_ego_m", pa.float64(), nullable=False),
    ]),
    "frames": pa.schema([
        pa.field("scene_id", pa.string(), nullable=False),
        pa.field("frame_idx", pa.int32(), nullable=False),
        pa.field("timestamp_us", pa.int64(), nullable=False),
        pa.field("ego_x", pa.float64(), nullable=False),
        pa.field("ego_y", pa.float64(), nullable=False),
        pa.field("ego_z", pa.float64(), nullable=False),
        pa.field("ego_yaw", pa.float64(), nullable=False),
        pa.field("ego_speed_mps", pa.float64(), nullable=False),
        pa.field("n_boxes", pa.int32(), nullable=False),
        pa.field("n_visible_agents", pa.int32()),
    ]),
    "variants": pa.schema([                                       # SCS variants: behaviour-level, and appearance-level (kind appearance)
        pa.field("scene_id", pa.string(), nullable=False),
        pa.field("variant_id", pa.string(), nullable=False),
        pa.field("kind", pa.string(), nullable=False),            # cut_in | head_on | rear_end | t_bone | none | appearance | designed
        pa.field("adversary", pa.int64(), nullable=False),        # track id (appearance: the composited object's track)
        pa.field("collision_step", pa.int32()),                   # step of first contact in the variant; null = none
        pa.field("collision_time_s", pa.float64()),
        pa.field("success", pa.bool_()),          # ego and adversary boxes overlap (IoU > 0.02)
        pa.field("plausible", pa.bool_()),        # comfort, no other collision, stays on the road
        pa.field("reachable", pa.bool_()),        # the adversary could reach the ego path at all
        pa.field("n_violations", pa.int32(), nullable=False),
        pa.field("violations", pa.list_(pa.string()), nullable=False),
        pa.field("loss_adv", pa.float64()),
        pa.field("loss_beh", pa.float64()),
        pa.field("loss_app", pa.float64()),                       # null: no renderer (scene graph) was supplied
        pa.field("loss_restore", pa.float64()),
        pa.field("loss_plaus", pa.float64()),
        pa.field("adversary_min_accel_mps2", pa.float64()),
        pa.field("adversary_max_accel_mps2", pa.float64()),
        pa.field("adversary_max_lateral_accel_mps2", pa.float64()),
        pa.field("min_distance_m", pa.float64()),
        pa.field("planner", pa.string()),         # replay | rule
        pa.field("iterations", pa.int32()),       # Adam steps of the kept attempt
        pa.field("attempts", pa.int32()),         # adversaries tried for this variant
        pa.field("source", pa.string()),                          # latent | knots (the interception path itself)
        pa.field("optimisation_seconds", pa.float64()),  # over every attempt
        pa.field("checkpoint", pa.string()),      # content hash (12 hex) of the traffic model
        pa.field("variants_path", pa.string(), nullable=False),   # the variants.json holding the trajectories
        pa.field("bev_path", pa.string()),
        pa.field("placement", pa.string()),                       # appearance: replace | insert; designed: designed (null: behaviour)
        pa.field("object_id", pa.string()),                       # appearance: the composited model (pm-... / nsg:...)
        pa.field("object_category", pa.string()),
        pa.field("pose", pa.string()),                            # appearance: upright | on_side | overturned | replace
        pa.field("edits_json", pa.string()),                      # appearance: the variant's edit specs (JSON)
        pa.field("passed_gates", pa.bool_()),     # the quality gates' verdict (omniscs.gates); null: not judged
        pa.field("gate_reasons", pa.list_(pa.string())),          # why it failed (empty when it passed)
    ]),
    "plans": pa.schema([                                          # what each scene needs modelled (plan stage)
        pa.field("scene_id", pa.string(), nullable=False),
        pa.field("plan_id", pa.string(), nullable=False),         # 12 hex of the plan stage's key
        pa.field("content_hash", pa.string(), nullable=False),    # the scene store it was made for
        pa.field("agent_nodes", pa.list_(pa.int64()), nullable=False),
        pa.field("n_agent_nodes", pa.int32(), nullable=False),
        pa.field("node_reasons_json", pa.string(), nullable=False),  # track id -> moving | edited | behavior (+)
        pa.field("n_background_tracks", pa.int32(), nullable=False),
        pa.field("needs_360", pa.list_(pa.int64()), nullable=False),
        pa.field("background_repair", pa.list_(pa.int64()), nullable=False),
        pa.field("inserted", pa.list_(pa.int64()), nullable=False),
        pa.field("cameras", pa.list_(pa.string()), nullable=False),
        pa.field("n_train_frames", pa.int32(), nullable=False),
        pa.field("n_heldout_frames", pa.int32(), nullable=False),
        pa.field("modelled_area_m2", pa.float64(), nullable=False),
        pa.field("gaussian_budget", pa.int64(), nullable=False),
        pa.field("stages", pa.list_(pa.string()), nullable=False),  # the stages this scene runs
        pa.field("plan_path", pa.string(), nullable=False),
        pa.field("reused", pa.bool_(), nullable=False),
    ]),
    "models": pa.schema([                                         # fitted scene graphs (fit stage)
        pa.field("scene_id", pa.string(), nullable=False),
        pa.field("model_id", pa.string(), nullable=False),        # nsg-<preset>-<hash of scene content + config>
        pa.field("kind", pa.string(), nullable=False),            # nsg
        pa.field("preset", pa.string(), nullable=False),          # fast | balanced | accurate
        pa.field("status", pa.string(), nullable=False),          # fitted | diverged
        pa.field("checkpoint_path", pa.string()),                 # null when the fit diverged (nothing saved)
        pa.field("reused", pa.bool_(), nullable=False),           # an identical fit was already on disk
        pa.field("n_gaussians", pa.int64()),
        pa.field("n_agent_nodes", pa.int32(), nullable=False),
        pa.field("agent_nodes", pa.list_(pa.int64()), nullable=False),
        pa.field("iterations", pa.int32(), nullable=False),
        pa.field("fit_seconds", pa.float64()),
        pa.field("train_psnr", pa.float64()),
        pa.field("heldout_psnr", pa.float64()),                   # every 4th frame, full resolution
        pa.field("heldout_ssim", pa.float64()),
        pa.field("error", pa.string()),                           # why the fit diverged
    ]),
    "datasets": pa.schema([                                       # annotated datasets (dataset stage)
        pa.field("dataset_id", pa.string(), nullable=False),
        pa.field("path", pa.string(), nullable=False),
        pa.field("content_hash", pa.string(), nullable=False),    # the dataset stage's key: same inputs, same data
        pa.field("reused", pa.bool_(), nullable=False),
        pa.field("scene_ids", pa.list_(pa.string()), nullable=False),
        pa.field("n_scenes", pa.int32(), nullable=False),
        pa.field("n_variants", pa.int32(), nullable=False),
        pa.field("n_frames", pa.int64(), nullable=False),
        pa.field("n_samples", pa.int64(), nullable=False),        # frame x camera images
        pa.field("n_annotations", pa.int64(), nullable=False),    # box x camera
        pa.field("n_ego_solved", pa.int32(), nullable=False),
        pa.field("fidelity_psnr", pa.float64()),                  # mean over variants; null: no exact reference
        pa.field("fidelity_ssim", pa.float64()),
        pa.field("fidelity_masked_psnr", pa.float64()),
        pa.field("feature_drift", pa.float64()),                  # mean over variants (recorded logs' proxy too)
        pa.field("card_path", pa.string(), nullable=False),
        pa.field("preview_path", pa.string(), nullable=False),
        pa.field("config_json", pa.string(), nullable=False),
        pa.field("n_requested", pa.int32()),      # variants the request asked for (every scene, both levels)
        pa.field("n_rejected", pa.int32()),       # variants that failed the quality gates (in the dataset or not)
        pa.field("n_failed_kept", pa.int32()),    # of those, put into the dataset (keep_failed), marked
        pa.field("warnings", pa.list_(pa.string())),              # the card's warnings, in plain words
    ]),
    "samples": pa.schema([                                        # one rendered image: frame x camera of a variant
        pa.field("dataset_id", pa.string(), nullable=False),
        pa.field("scene_id", pa.string(), nullable=False),        # the source scene
        pa.field("variant_id", pa.string(), nullable=False),
        pa.field("store_id", pa.string(), nullable=False),        # the variant's scene store in the dataset
        pa.field("frame_idx", pa.int32(), nullable=False),        # frame of the variant's store
        pa.field("scene_frame", pa.int32(), nullable=False),      # the source scene's frame
        pa.field("camera", pa.string(), nullable=False),
        pa.field("timestamp_us", pa.int64(), nullable=False),
        pa.field("image_path", pa.string(), nullable=False),
        pa.field("gt_path", pa.string(), nullable=False),         # depth, instance and semantic masks (npz)
        pa.field("ego_x", pa.float64(), nullable=False),
        pa.field("ego_y", pa.float64(), nullable=False),
        pa.field("ego_yaw", pa.float64(), nullable=False),
        pa.field("command", pa.string(), nullable=False),         # right | left | forward (UniAD's rule)
        pa.field("n_boxes", pa.int32(), nullable=False),          # boxes whose rectangle meets the image
        pa.field("n_visible", pa.int32(), nullable=False),        # ... with instance-mask pixels
        pa.field("viewpoint_offset_m", pa.float64(), nullable=False),  # ego to the nearest logged ego position
        pa.field("fidelity_psnr", pa.float64()),                  # against the exact render; null: none measured
        pa.field("fidelity_ssim", pa.float64()),
        pa.field("fidelity_masked_psnr", pa.float64()),           # over the reference's agent pixels
        pa.field("fidelity_masked_ssim", pa.float64()),
        pa.field("feature_drift", pa.float64()),                  # vs the unedited render, edits left out (0..1)
        pa.field("logged_psnr", pa.float64()),                    # the unedited render vs the logged image
        pa.field("variant_fidelity_psnr", pa.float64()),          # mean over the variant's measured frames
        pa.field("variant_feature_drift", pa.float64()),
        pa.field("ego_solved", pa.bool_()),                       # the ego drives a collision-free solution
    ]),
    "annotations": pa.schema([                                    # one box seen by one camera in one sample
        pa.field("dataset_id", pa.string(), nullable=False),
        pa.field("scene_id", pa.string(), nullable=False),
        pa.field("variant_id", pa.string(), nullable=False),
        pa.field("store_id", pa.string(), nullable=False),
        pa.field("frame_idx", pa.int32(), nullable=False),
        pa.field("camera", pa.string(), nullable=False),
        pa.field("track_id", pa.int64(), nullable=False),
        pa.field("category", pa.string(), nullable=False),
        pa.field("is_adversary", pa.bool_(), nullable=False),
        pa.field("moved", pa.bool_(), nullable=False),            # an agent node the variant places
        *[pa.field(c, pa.float64(), nullable=False) for c in ("cx", "cy", "cz", "length", "width", "height", "yaw")],
        *[pa.field(c, pa.float64(), nullable=False) for c in ("ego_x", "ego_y", "ego_z", "ego_yaw")],  # ego frame
        *[pa.field(c, pa.float64(), nullable=False) for c in ("cam_x", "cam_y", "cam_z")],  # camera frame centre
        *[pa.field(c, pa.float64(), nullable=False) for c in ("x1", "y1", "x2", "y2")],  # projected box, clipped
        *[pa.field(c, pa.float64()) for c in ("tight_x1", "tight_y1", "tight_x2", "tight_y2")],  # from the mask
        pa.field("mask_pixels", pa.int64(), nullable=False),
        pa.field("visible_fraction", pa.float64(), nullable=False),  # unoccluded, in-image share of the object
        pa.field("visibility_level", pa.int32(), nullable=False),  # nuScenes 1..4 (v0-40 .. v80-100)
        pa.field("in_image_fraction", pa.float64(), nullable=False),
        pa.field("num_lidar_points", pa.int64(), nullable=False),  # simulated from the rendered depth, whole frame
        *[pa.field(c, pa.float64(), nullable=False) for c in ("vx", "vy", "vz")],  # world frame, m/s
    ]),
    "pool": pa.schema([                                           # models added to a pool (build_pool)
        pa.field("pool_path", pa.string(), nullable=False),
        pa.field("model_id", pa.string(), nullable=False),        # pm-<content hash>
        pa.field("category", pa.string(), nullable=False),
        pa.field("length", pa.float64(), nullable=False),
        pa.field("width", pa.float64(), nullable=False),
        pa.field("height", pa.float64(), nullable=False),
        pa.field("n_gaussians", pa.int64(), nullable=False),
        pa.field("provenance", pa.string(), nullable=False),      # mesh | imported | scene_track
        pa.field("source", pa.string(), nullable=False),          # asset id, file name or scene/track
        pa.field("quality", pa.float64()),                        # PSNR (dB) on held-out views; null: not scored
        pa.field("new", pa.bool_(), nullable=False),              # false: the same model was already there
        pa.field("seconds", pa.float64(), nullable=False),        # to build it
    ]),
    "agent_models": pa.schema([                                   # the dual strategy's choice per agent node (agents stage)
        pa.field("scene_id", pa.string(), nullable=False),
        pa.field("model_id", pa.string(), nullable=False),        # the completed graph (agents-<key>)
        pa.field("fit_model_id", pa.string(), nullable=False),    # the fitted graph it completed
        pa.field("track_id", pa.int64(), nullable=False),
        pa.field("strategy", pa.string(), nullable=False),        # fitted | online | pool
        pa.field("reason", pa.string(), nullable=False),
        pa.field("needs_360", pa.bool_(), nullable=False),        # an edit turns it off its observed views
        pa.field("pool_path", pa.string()),                       # null: no pool given
        pa.field("pool_model_id", pa.string()),                   # the matched pool model ('pool')
        pa.field("distance", pa.float64()),                       # its matching distance
        pa.field("clarity", pa.float64()),                        # 0..1; null where not scored ('fitted')
        pa.field("coverage", pa.float64()),                       # azimuth share seen, mirror images included
        pa.field("mirrored", pa.bool_(), nullable=False),         # unseen side filled by mirror symmetry
        pa.field("added_to_pool", pa.string()),                   # pool model id when the track grew the pool
        pa.field("n_gaussians", pa.int64(), nullable=False),
    ]),
    "background_repairs": pa.schema([                             # large static objects repaired behind (background stage)
        pa.field("scene_id", pa.string(), nullable=False),
        pa.field("model_id", pa.string(), nullable=False),        # the repaired graph (background-<key>)
        pa.field("fit_model_id", pa.string(), nullable=False),    # the graph it repaired (fit or agents stage)
        pa.field("track_id", pa.int64(), nullable=False),         # the object moved or removed
        pa.field("hole_views", pa.int64(), nullable=False),       # training views it shows in
        pa.field("hole_pixels", pa.int64(), nullable=False),      # at the repair's working resolution
        pa.field("observed_pixels", pa.int64(), nullable=False),  # filled by what other views observed
        pa.field("plane_pixels", pa.int64()),                     # filled from a plane's texture (null: before planes)
        pa.field("carried_pixels", pa.int64(), nullable=False),   # filled from earlier views' inpainting
        pa.field("inpainted_pixels", pa.int64(), nullable=False),  # filled by the 2D inpainter
        pa.field("unfilled_pixels", pa.int64(), nullable=False),  # left unsupervised (no context)
        pa.field("seeds", pa.int64(), nullable=False),            # Gaussians seeded in the hole
        pa.field("dropped_gaussians", pa.int64(), nullable=False),  # hidden behind the object in every view
        pa.field("depth_method", pa.string(), nullable=False),    # drnet | lsq
        pa.field("refit", pa.string(), nullable=False),           # roi | full | none
        pa.field("seconds", pa.float64(), nullable=False),
        pa.field("repair_path", pa.string(), nullable=False),     # masks, filled views, depth maps (in the checkpoint)
    ]),
    "downstream_models": pa.schema([                              # driving models trained on generated datasets
        pa.field("model_id", pa.string(), nullable=False),        # proxy-planner-<hash> | external-<hash>
        pa.field("kind", pa.string(), nullable=False),            # proxy_planner | external
        pa.field("base_model_id", pa.string()),                   # what it was fine-tuned from
        pa.field("dataset_ids", pa.list_(pa.string()), nullable=False),  # trained on
        pa.field("status", pa.string(), nullable=False),          # trained | failed
        pa.field("path", pa.string()),                            # checkpoint folder (proxy) or work dir (external)
        pa.field("n_examples", pa.int64()),
        pa.field("train_seconds", pa.float64()),
        pa.field("command", pa.string()),                         # the external job's command line
        pa.field("log_path", pa.string()),
        pa.field("error", pa.string()),                           # why it failed (exit code, timeout, bad input)
        pa.field("config_json", pa.string(), nullable=False),
    ]),
    "evaluations": pa.schema([                                    # one number of one evaluation
        pa.field("eval_id", pa.string(), nullable=False),
        pa.field("model_id", pa.string(), nullable=False),
        pa.field("dataset_id", pa.string()),                      # null: a dataroot or the external job's own set
        pa.field("task", pa.string(), nullable=False),            # planning | detection
        pa.field("split", pa.string(), nullable=False),           # behaviour-SCS | original | ... (what was tested)
        pa.field("metric", pa.string(), nullable=False),          # L2 | collision | mAP | NDS | AP | trans_err ...
        pa.field("class_name", pa.string(), nullable=False),      # detection metrics per class; '' = all classes
        pa.field("horizon", pa.string(), nullable=False),         # 1s | 2s | 3s (planning); '' = none
        pa.field("convention", pa.string(), nullable=False),      # uniad | stp3 (planning); camera_view
                                                                  # (detection, boxes in view); '' = none
        pa.field("value", pa.float64()),                          # null when undefined or failed
        pa.field("n", pa.int64()),                                # examples or samples evaluated
        pa.field("status", pa.string(), nullable=False),          # ok | failed
        pa.field("error", pa.string()),
    ]),
    "closed_loop_runs": pa.schema([                               # one closed-loop test run (closed_loop_eval)
        pa.field("eval_id", pa.string(), nullable=False),         # the evaluation (policy x scenarios) it belongs to
        pa.field("scenario_id", pa.string(), nullable=False),     # <scene id>/log or <scene id>/<variant id>
        pa.field("scene_id", pa.string(), nullable=False),
        pa.field("kind", pa.string(), nullable=False),            # log | behavior
        pa.field("model_id", pa.string(), nullable=False),        # the scene graph driven in
        pa.field("policy", pa.string(), nullable=False),          # replay | rule | proxy | drivearena
        pa.field("reactive", pa.bool_(), nullable=False),         # agents brake for the ego (IDM)
        pa.field("status", pa.string(), nullable=False),          # ok | failed
        pa.field("reason", pa.string()),                          # why the episode ended
        pa.field("steps", pa.int64()),
        pa.field("simulated_s", pa.float64()),
        pa.field("pdms", pa.float64()),                           # NAVSIM's PDM score (mean over steps)
        pa.field("hd_score", pa.float64()),                       # HUGSIM's HD-Score
        pa.field("epdms", pa.float64()),                          # NAVSIM v2's EPDMS (mean over steps); null in
                                                                  # partitions written before it was scored
        pa.field("route_completion", pa.float64()),
        pa.field("no_collision", pa.float64()),                   # mean NC (NAVSIM rule)
        pa.field("drivable_compliance", pa.float64()),            # mean DAC
        pa.field("time_to_collision", pa.float64()),              # mean TTC score
        pa.field("comfort", pa.float64()),                        # mean comfort score
        pa.field("ego_progress", pa.float64()),                   # mean EP
        pa.field("collision", pa.bool_()),                        # any contact during the run
        pa.field("steps_per_s", pa.float64()),                    # simulation speed (render + policy + control)
        pa.field("run_path", pa.string()),                        # run.json, steps.json, replay.json, pictures
        pa.field("error", pa.string()),
    ]),
}

#: The columns that identify one logical row of each table. The default view ``<table>`` shows each value once,
#: ``<table>_by_run`` once per run. Scene ids name a scene's content (source and its options), so the same key
#: from two runs is the same thing made twice; plan, model and variant ids are only unique within their scene.
KEYS: dict[str, tuple[str, ...]] = {
    "runs": ("run_id",),
    "scenes": ("scene_id",),
    "agents": ("scene_id", "track_id"),
    "frames": ("scene_id", "frame_idx"),
    "variants": ("scene_id", "variant_id"),
    "plans": ("scene_id", "plan_id"),
    "models": ("scene_id", "model_id"),
    "datasets": ("dataset_id",),
    "samples": ("dataset_id", "store_id", "frame_idx", "camera"),
    "annotations": ("dataset_id", "store_id", "frame_idx", "camera", "track_id"),
    "pool": ("pool_path", "model_id"),
    "agent_models": ("scene_id", "model_id", "track_id"),
    "background_repairs": ("scene_id", "model_id", "track_id"),
    "downstream_models": ("model_id",),
    "evaluations": ("eval_id", "split", "metric", "class_name", "horizon", "convention"),
    "closed_loop_runs": ("eval_id", "scenario_id"),
}

#: The run status whose rows win over those of other ended runs (failed, cancelled) in the default views.
COMPLETED = "completed"


def catalog_root(workspace: Path) -> Path:
    return Path(workspace) / "catalog"


def validated_table(table: str, rows: list[dict]) -> pa.Table:
    """Rows as an Arrow table of the declared schema; unknown or missing required fields are errors."""
    if table not in SCHEMAS:
        raise OmniscsError(f"unknown catalog table {table!r}; tables: {sorted(SCHEMAS)}")
    schema = SCHEMAS[table]
    for i, row in enumerate(rows):
        extra = set(row) - set(schema.names)
        if extra:
            raise OmniscsError(f"catalog table {table}: row {i} has undeclared field(s) {sorted(extra)}")
        missing = [f.name for f in schema if not f.nullable and row.get(f.name) is None]
        if missing:
            raise OmniscsError(f"catalog table {table}: row {i} lacks required field(s) {missing}")
    try:
        return pa.Table.from_pylist(rows, schema=schema)
    except (pa.ArrowInvalid, pa.ArrowTypeError, TypeError, ValueError) as exc:
        raise OmniscsError(f"catalog table {table}: a row does not fit the schema ({exc})") from None


def write_rows(root: Path, table: str, run_id: str, rows: list[dict], writer: str = "task") -> Path | None:
    """Write ``rows`` as one new Parquet file in ``table``'s partition for ``run_id``; returns its path."""
    check_id("run id", run_id)
    check_id("writer", writer)
    arrow = validated_table(table, rows)
    if arrow.num_rows == 0:
        return None
    buf = io.BytesIO()
    pq.write_table(arrow, buf)
    name = f"{writer}-{time.time_ns() // 1000:016d}-{uuid.uuid4().hex[:12]}.parquet"
    path = Path(root) / table / f"run_id={run_id}" / name
    return atomic_write_bytes(path, buf.getvalue())


# ----------------------------------------------------------------------------- views
#: DuckDB variable holding the catalog root (as a glob prefix) that every view reads from.
ROOT_VARIABLE = "omniscs_catalog"

_DUCK_TYPES = {pa.string(): "VARCHAR", pa.int64(): "BIGINT", pa.int32(): "INTEGER", pa.float64(): "DOUBLE",
               pa.bool_(): "BOOLEAN"}

# The run id from a file's path (``.../run_id=<id>/<file>``), and the write time (16 digits) from its name; files
# written before names carried a time give '' and count as the oldest.
_RUN_OF_FILE = r"regexp_extract(filename, '[/\\]run_id=([^/\\]+)[/\\][^/\\]+$', 1)"
_WRITTEN = r"regexp_extract(file, '-([0-9]{16})-[0-9a-f]{12}\.parquet$', 1)"


def _duck_type(t: pa.DataType) -> str:
    if pa.types.is_list(t):
        return _duck_type(t.value_type) + "[]"
    return _DUCK_TYPES[t]


def _cols(table: str, prefix: str = "") -> str:
    return ", ".join(f'{prefix}"{name}"' for name in SCHEMAS[table].names)


def _raw_view(table: str) -> str:
    """Every row of every file of ``table``, typed as declared (a file older than a column reads it as null);
    with no file yet, no row but the same columns."""
    schema = SCHEMAS[table]
    typed = ", ".join(f'CAST("{f.name}" AS {_duck_type(f.type)}) AS "{f.name}"' for f in schema)
    empty = ", ".join(["NULL::VARCHAR AS filename"] + [f'NULL::{_duck_type(f.type)} AS "{f.name}"' for f in schema])
    return (f"CREATE OR REPLACE VIEW {table}_raw AS\n"
            f"  SELECT {_RUN_OF_FILE} AS run_id,\n    {typed},\n    filename AS file\n"
            f"  FROM (SELECT * FROM read_parquet(getvariable('{ROOT_VARIABLE}') || '/{table}/run_id=*/*.parquet',\n"
            "          filename = true, hive_partitioning = false, union_by_name = true, allow_empty = true)\n"
            f"        UNION ALL BY NAME SELECT {empty} WHERE false);")


def _placeholder_view(table: str) -> str:
    """``<table>_raw`` with the right columns and no row, without reading any file (cheap to bind)."""
    cols = ", ".join(f'NULL::{_duck_type(f.type)} AS "{f.name}"' for f in SCHEMAS[table])
    return f"CREATE OR REPLACE VIEW {table}_raw AS SELECT NULL::VARCHAR AS run_id, {cols}, NULL::VARCHAR AS file " \
           "WHERE false;"


def _views(table: str) -> list[str]:
    """``<table>_raw``, ``<table>_by_run`` and ``<table>`` (see the module docstring and catalogs/README.md)."""
    cols = _cols(table)
    if table == "runs":
        return [
            _raw_view("runs"),
            f"CREATE OR REPLACE VIEW runs AS\n  SELECT run_id, {cols}\n  FROM runs_raw\n"
            f"  QUALIFY row_number() OVER (PARTITION BY run_id\n"
            f"    ORDER BY finished_at_us DESC, {_WRITTEN} DESC, file DESC) = 1;",
            "CREATE OR REPLACE VIEW runs_by_run AS SELECT * FROM runs;",
        ]
    key = ", ".join(f'"{k}"' for k in KEYS[table])
    b_key = ", ".join(f'b."{k}"' for k in KEYS[table])
    return [
        _raw_view(table),
        f"CREATE OR REPLACE VIEW {table}_by_run AS\n  SELECT run_id, {cols}\n  FROM {table}_raw\n"
        f"  WHERE run_id IN (SELECT run_id FROM runs_raw)\n"
        f"  QUALIFY row_number() OVER (PARTITION BY run_id, {key}\n"
        f"    ORDER BY {_WRITTEN} DESC, file DESC) = 1;",
        f"CREATE OR REPLACE VIEW {table} AS\n  SELECT b.run_id, {_cols(table, 'b.')}\n"
        f"  FROM {table}_by_run AS b JOIN runs AS r ON r.run_id = b.run_id\n"
        f"  QUALIFY row_number() OVER (PARTITION BY {b_key}\n"
        f"    ORDER BY (r.status = '{COMPLETED}') DESC, r.finished_at_us DESC, b.run_id DESC) = 1;",
    ]


def view_statements() -> list[str]:
    """The statements that create every view, reading from the root held in the DuckDB variable
    ``ROOT_VARIABLE`` (set it first)."""
    return [statement for table in SCHEMAS for statement in _views(table)]


def view_names() -> list[str]:
    """Every view a catalog query can read."""
    return [f"{table}{suffix}" for table in SCHEMAS for suffix in ("", "_by_run", "_raw")]


def _glob_prefix(root: str | os.PathLike) -> str:
    """``root`` as the literal start of a DuckDB glob: '*', '?' and '[' match only themselves."""
    text = str(root)
    if os.sep == "\\":
        text = text.replace("\\", "/")
    elif "\\" in text:
        raise OmniscsError(f"catalog root {text} holds a backslash, which DuckDB reads as a path separator; "
                           "move the workspace to a path without one")
    return re.sub(r"([*?\[])", r"[\1]", text)


def _sql_string(text: str) -> str:
    return "'" + text.replace("'", "''") + "'"


def views_sql(root: str = "omniscs-data/catalog") -> str:
    """DuckDB statements that create the catalog views over ``root``, for use in the duckdb shell (the same
    views as ``connect``)."""
    lines = ["-- Catalog views for the duckdb shell; generated by omniscs.catalog.views_sql().",
             "-- <table>: each logical row once; <table>_by_run: per run; <table>_raw: every row of every file.",
             f"SET VARIABLE {ROOT_VARIABLE} = {_sql_string(_glob_prefix(root))};"]
    return "\n".join(lines + view_statements()) + "\n"


def check_contained(root: Path) -> None:
    """Refuse a catalog whose table folders or files are symbolic links out of ``root``: DuckDB allows the files
    under ``root`` as written, so such a link would let a query read elsewhere."""
    if not root.is_dir():
        return
    for table in root.iterdir():
        inside(table, root, "catalog entry")
        if table.is_dir() and not table.is_symlink():
            for entry in table.iterdir():
                if entry.is_symlink():
                    inside(entry, root, "catalog file")


def catalog_files(root: Path, table: str) -> list[Path]:
    """Every file the views of ``table`` read: ``<root>/<table>/run_id=*/*.parquet`` (hidden names too, as DuckDB's
    glob matches them)."""
    folder = Path(root) / table
    if not folder.is_dir():
        return []
    return sorted(f for d in folder.iterdir() if d.name.startswith("run_id=") and d.is_dir()
                  for f in d.iterdir() if f.name.endswith(".parquet"))


#: Columns a file of each table must have to be one of ours (the first logical key, which every version wrote; a
#: run's status for ``runs``, whose key lives in the path).
_REQUIRED = {table: ("status",) if table == "runs" else KEYS[table][:1] for table in SCHEMAS}


def check_catalog_files(root: Path) -> None:
    """Refuse, as one OmniscsError naming the file, a file in the catalog that is not one of its tables' Parquet
    files (junk, truncated, or a foreign schema), before DuckDB reads it: DuckDB would fail with its own trace on
    junk and show a foreign file's rows as the table's (``union_by_name``)."""
    for table, schema in SCHEMAS.items():
        check_parquet_files(catalog_files(root, table), schema, f"catalog file of table {table}",
                            "catalog files are written by omniscs only: move that file out of the catalog folder",
                            required=_REQUIRED[table])


def connect(root: Path) -> duckdb.DuckDBPyConnection:
    """An in-memory DuckDB connection with the catalog views over ``root`` (empty views when no files yet) that
    can read nothing but files under ``root``: no other file, no extension, no network, no setting changed
    (the configuration is locked), no spilling to disk."""
    root = Path(root).expanduser().resolve()
    check_contained(root)
    prefix = _glob_prefix(root)
    check_catalog_files(root)
    con = duckdb.connect()
    try:
        for name, value in [("temp_directory", ""), ("python_enable_replacements", False),
                            ("parquet_metadata_cache", True),
                            ("autoinstall_known_extensions", False), ("autoload_known_extensions", False),
                            ("allow_community_extensions", False),
                            # DuckDB checks the glob pattern as written, so the escaped prefix is allowed too
                            ("allowed_directories", sorted({str(root) + "/", prefix + "/"})),
                            ("enable_external_access", False), ("lock_configuration", True)]:
            con.execute(f"SET {name} = ?", [value])
        con.execute(f"SET VARIABLE {ROOT_VARIABLE} = ?", [prefix])
        # DuckDB binds a view (reading every file's footer) when it is created, and again for each view built on
        # it; so the views on top are created over placeholders first, then each _raw view once for real. The
        # definitions end up exactly those of view_statements().
        placeholders = [_placeholder_view(table) for table in SCHEMAS]
        on_top = [statement for table in SCHEMAS for statement in _views(table)[1:]]
        real = [_raw_view(table) for table in SCHEMAS]
        for statement in placeholders + on_top + real:
            con.execute(statement)
    except BaseException:
        con.close()
        raise
    return con


_EXPLAIN = re.compile(r"\s*EXPLAIN\s+(?:ANALYZE\s+)?(?P<rest>.*)", re.IGNORECASE | re.DOTALL)


def _first_line(exc: Exception) -> str:
    lines = str(exc).strip().splitlines()
    return lines[0] if lines else type(exc).__name__


def check_read_only(sql: str) -> str:
    """``sql`` when it is one SELECT statement (or EXPLAIN of one), else one OmniscsError saying why."""
    views = ", ".join(SCHEMAS)
    if not isinstance(sql, str) or not sql.strip():
        raise OmniscsError(f"the catalog query is empty; give one SELECT statement over the views {views} "
                           "(or their _by_run and _raw forms)")
    try:
        statements = duckdb.extract_statements(sql)
    except duckdb.Error as exc:
        raise OmniscsError(f"catalog query failed: {_first_line(exc)}") from None
    if not statements:
        raise OmniscsError("the catalog query holds no statement, only comments or ';'; give one SELECT statement")
    if len(statements) > 1:
        raise OmniscsError(f"catalog queries are read-only: only SELECT, one statement at a time (got "
                           f"{len(statements)} statements); run them one by one")
    statement = statements[0]
    kind = statement.type
    if kind == duckdb.StatementType.EXPLAIN:
        m = _EXPLAIN.fullmatch(statement.query.strip().rstrip(";"))
        inner = None
        if m:
            try:
                inner = duckdb.extract_statements(m.group("rest"))
            except duckdb.Error:
                inner = None
        if inner is None or len(inner) != 1 or inner[0].type != duckdb.StatementType.SELECT:
            raise OmniscsError("catalog queries are read-only: only SELECT, or EXPLAIN [ANALYZE] of a SELECT, "
                               "is allowed")
    elif kind != duckdb.StatementType.SELECT:
        raise OmniscsError(f"catalog queries are read-only: only SELECT is allowed, not {kind.name} "
                           f"(views: {views}, and their _by_run and _raw forms)")
    return sql


def query(root: Path, sql: str) -> pa.Table:
    """Run one read-only SQL statement (SELECT, or EXPLAIN of one) over the catalog views; anything else, a SQL
    mistake or an attempt to read outside the catalog is one OmniscsError line."""
    check_read_only(sql)
    con = connect(root)
    try:
        return con.sql(sql).to_arrow_table()
    except duckdb.PermissionException as exc:
        raise OmniscsError(f"catalog queries are read-only: only SELECT over the catalog's views, which read "
                           f"nothing outside {root} ({_first_line(exc)})") from None
    except duckdb.CatalogException as exc:
        line = _first_line(exc)
        hint = (f" (the views: {', '.join(SCHEMAS)}, each also as <table>_by_run and <table>_raw)"
                if "Table with name" in line else "")
        raise OmniscsError(f"catalog query failed: {line}{hint}") from None
    except duckdb.Error as exc:
        raise OmniscsError(f"catalog query failed: {_first_line(exc)}") from None
    finally:
        con.close()
