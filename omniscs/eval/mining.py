"""What a detector misses: every evaluated ground-truth box of a nuScenes dataroot matched against a detection results
file by nuScenes' centre-distance rule, described by category, ego distance, visibility, orientation to the ego and
pose; the miss rate along each; and the (category, orientation, pose) cells an appearance-SCS generator should
composite (``pick_scs_objects``). Pure numpy/pandas (matplotlib for the plot); the readers are the evaluation's own
(``omniscs.eval.nuscenes_io``), so what counts as a ground-truth box here is what the detection protocol evaluates.
"""
from __future__ import annotations

import dataclasses
import io
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable

import numpy as np
import pandas as pd

from omniscs.errors import OmniscsError, ValidationError
from omniscs.eval.detection import Boxes, DetectionConfig, filter_boxes
from omniscs.eval.nuscenes_io import CATEGORY_TO_DETECTION, NuScenesTables, load_ground_truth, load_results
from omniscs.storage import atomic_directory, atomic_write_bytes, atomic_write_json, atomic_write_text

#: Orientation bins, in summary order (see ``orientation_bins``).
ORIENTATIONS: tuple[str, ...] = ("toward", "away", "left side", "right side")
#: Pose bins, in summary order (see ``pose_bins``).
POSES: tuple[str, ...] = ("upright", "on its side", "overturned")
#: The exporter writes each scene's description as this prefix followed by the store's scene id.
EXPORT_DESCRIPTION_PREFIX = "omniscs "
#: Files ``mine`` writes into its output folder.
MISSED_JSON, MISSED_MD, MISSED_PNG = "missed.json", "missed.md", "missed.png"
#: Tracks listed per pick in missed.md (missed.json lists them all).
MARKDOWN_TRACKS = 6
#: Columns of ``MissedReport.boxes``, one row per evaluated ground-truth box.
BOX_COLUMNS: tuple[str, ...] = (
    "sample_token", "scene_name", "annotation_token", "instance_token", "detection_name", "category",
    "x", "y", "z", "width", "length", "height", "qw", "qx", "qy", "qz", "yaw_deg", "pitch_deg", "roll_deg", "tilt_deg",
    "ego_distance_m", "distance_bin", "visibility", "relative_heading_deg", "orientation", "pose", "missed",
    "match_distance_m", "match_score", "scene_id", "track_id")


@dataclass(frozen=True)
class MiningConfig:
    """Which ground-truth boxes a detector misses, and how the misses are binned. Matching is nuScenes' centre-distance
    rule (the devkit's ``accumulate``) at one threshold; the ground truth and the predictions are filtered as the
    protocol filters them (``detection``: class ranges, boxes without points, bicycles in racks)."""

    match_distance_m: float = 2.0
    """A prediction matches a ground-truth box of its class and sample whose centre is closer than this in the ground
    plane (m; nuScenes matches at 0.5, 1, 2 and 4 m: 2 is its middle threshold and the one of its TP errors)."""
    min_score: float = 0.0
    """Predictions scoring below this are ignored (0: every prediction, as the protocol's AP sweeps every score)."""
    distance_edges_m: tuple[float, ...] = (10.0, 20.0, 30.0, 40.0)
    """Inner edges of the ego-distance bins (m, increasing): the default makes 0-10, 10-20, 20-30, 30-40 and 40+."""
    facing_deg: float = 45.0
    """Half-width of the 'away' and 'toward' orientation bins (degrees, 0..90); the two side bins take the rest."""
    on_side_deg: float = 45.0
    """A box whose up axis is tilted more than this from the vertical lies on its side (degrees)."""
    overturned_deg: float = 135.0
    """... and more than this, it is overturned (degrees; above ``on_side_deg``)."""
    scenes: tuple[str, ...] = ()
    """Scenes mined (names or tokens of the scene table); empty: every scene of the dataroot."""
    detection: DetectionConfig = field(default_factory=DetectionConfig)
    """The protocol's settings used here: class ranges (which boxes are evaluated) and the results' box limit."""
    max_track_id: int = 100_000
    """Largest track id tried when recovering an OmniSCS export's (scene id, track id) from its instance tokens."""
    pick_top: int = 10
    """How many (category, orientation, pose) cells ``mine`` picks as SCS objects."""
    pick_min_count: int = 3
    """Fewest evaluated ground-truth boxes a picked cell must hold (a miss rate of one or two boxes means little)."""

    def __post_init__(self):
        edges = tuple(float(e) for e in self.distance_edges_m)
        if not edges or not all(math.isfinite(e) and e > 0 for e in edges) or any(b <= a for a, b in
                                                                                 zip(edges, edges[1:])):
            raise OmniscsError(f"distance_edges_m must be positive, finite and increasing; got {list(edges)}")
        if not (math.isfinite(self.match_distance_m) and self.match_distance_m > 0):
            raise OmniscsError(f"match_distance_m must be a positive number of metres; got {self.match_distance_m}")
        if not math.isfinite(self.min_score):
            raise OmniscsError(f"min_score must be finite; got {self.min_score}")
        if not 0.0 < self.facing_deg <= 90.0:
            raise OmniscsError(f"facing_deg must lie in (0, 90]; got {self.facing_deg}")
        if not 0.0 < self.on_side_deg < self.overturned_deg < 180.0:
            raise OmniscsError("need 0 < on_side_deg < overturned_deg < 180; got "
                               f"{self.on_side_deg} and {self.overturned_deg}")
        if self.max_track_id < 0 or self.pick_top < 0 or self.pick_min_count < 1:
            raise OmniscsError("max_track_id and pick_top must be >= 0 and pick_min_count >= 1")
        object.__setattr__(self, "distance_edges_m", edges)
        object.__setattr__(self, "scenes", tuple(self.scenes))

    def to_dict(self) -> dict:
        return _plain(dataclasses.asdict(self))


# ----------------------------------------------------------------------------- geometry of a box seen from the ego
def box_angles(rotation: np.ndarray) -> dict[str, np.ndarray]:  # [N, 4] w, x, y, z -> each [N] degrees
    """Yaw, pitch and roll (z-y-x Euler angles: R = Rz(yaw) Ry(pitch) Rx(roll); pitch in [-90, 90]) and the tilt
    (angle between the box's up axis and the world's, [0, 180]) of non-zero quaternions; q and -q agree."""
    q = np.asarray(rotation, np.float64).reshape(-1, 4)
    norm = np.linalg.norm(q, axis=1)
    if not np.all(np.isfinite(q)) or np.any(norm <= 0):
        raise ValidationError("a box rotation is zero or not finite; give a non-zero (w, x, y, z) quaternion")
    w, x, y, z = (q / norm[:, None]).T
    r00, r10 = 1 - 2 * (y * y + z * z), 2 * (x * y + w * z)
    r20, r21, r22 = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
    angles = {"yaw_deg": np.arctan2(r10, r00), "pitch_deg": np.arcsin(np.clip(-r20, -1, 1)),
              "roll_deg": np.arctan2(r21, r22), "tilt_deg": np.arccos(np.clip(r22, -1, 1))}
    return {k: np.degrees(v) + 0.0 for k, v in angles.items()}  # + 0.0: no -0.0 in the tables


def relative_heading_deg(yaw_deg: np.ndarray, box_xy: np.ndarray, ego_xy: np.ndarray) -> np.ndarray:
    """[N] degrees in [-180, 180): the box heading (its +x axis in the ground plane, ``yaw_deg`` [N]) less the
    direction of the ego's line of sight to it (from ``ego_xy`` [N, 2] to ``box_xy`` [N, 2], global frame)."""
    d = np.asarray(box_xy, np.float64) - np.asarray(ego_xy, np.float64)
    sight = np.degrees(np.arctan2(d[:, 1], d[:, 0]))
    return (np.asarray(yaw_deg, np.float64) - sight + 180.0) % 360.0 - 180.0


def orientation_bins(relative_deg: np.ndarray, facing_deg: float = 45.0) -> np.ndarray:  # [N] -> [N] str
    """How a box is turned to the ego, from ``relative_heading_deg`` (a: heading less line of sight):

    - 'away':       |a| <= facing_deg: it heads along the line of sight, the ego sees its back;
    - 'toward':     |a| >= 180 - facing_deg: it heads at the ego (faces it), the ego sees its front;
    - 'left side':  facing_deg < a < 180 - facing_deg: it heads to the ego's left across the line of sight, and its
      left flank faces the ego;
    - 'right side': -180 + facing_deg < a < -facing_deg: the mirror image, its right flank faces the ego.
    """
    a = np.asarray(relative_deg, np.float64)
    return np.where(np.abs(a) <= facing_deg, "away",
                    np.where(np.abs(a) >= 180.0 - facing_deg, "toward",
                             np.where(a > 0, "left side", "right side"))).astype(object)


def pose_bins(tilt_deg: np.ndarray, on_side_deg: float = 45.0, overturned_deg: float = 135.0) -> np.ndarray:
    """'upright' (tilt <= on_side_deg), 'on its side' (up to ``overturned_deg``) or 'overturned' (beyond), from the
    tilt of the box's up axis (``box_angles``). For a box turned about one axis the tilt is |roll| or |pitch|, so
    this is the rule '|roll| or |pitch| in 45..135: on its side, beyond 135: overturned' made independent of the
    Euler convention (z-y-x angles put a box flipped end over end at roll 180, pitch 0)."""
    t = np.asarray(tilt_deg, np.float64)
    return np.where(t > overturned_deg, "overturned",
                    np.where(t > on_side_deg, "on its side", "upright")).astype(object)


def distance_bins(ego_distance_m: np.ndarray, edges_m: tuple[float, ...]) -> tuple[np.ndarray, list[str]]:
    """Each distance's bin label ([N] str; a distance on an edge goes to the farther bin) and all labels in order."""
    labels = [f"{lo:g}-{hi:g} m" for lo, hi in zip((0.0, *edges_m), edges_m)] + [f"{edges_m[-1]:g}+ m"]
    index = np.searchsorted(np.asarray(edges_m, np.float64), np.asarray(ego_distance_m, np.float64), side="right")
    return np.asarray(labels, dtype=object)[index], labels


# ----------------------------------------------------------------------------- matching
def match_ground_truth(gt: Boxes, pred: Boxes, match_distance_m: float, min_score: float = 0.0) -> np.ndarray:
    """[N_gt] int: the row of ``pred`` matched to each ground-truth box (-1: missed). nuScenes' rule, per class:
    predictions scoring at least ``min_score`` in falling score (equal scores: the later box first, as the
    protocol's ``accumulate``) each take the nearest still-unmatched box of their class and sample whose centre is
    closer than ``match_distance_m`` in the ground plane."""
    matched = np.full(len(gt), -1, np.int64)
    for name in np.unique(gt.name.astype(str)):
        gt_rows = np.flatnonzero(gt.name == name)
        rows_of_sample: dict[str, np.ndarray] = {}
        for tok in np.unique(gt.sample_token[gt_rows].astype(str)):
            rows_of_sample[tok] = gt_rows[gt.sample_token[gt_rows] == tok]
        candidates = np.flatnonzero((pred.name == name) & (pred.score >= min_score))
        order = candidates[np.lexsort((candidates, pred.score[candidates]))[::-1]]
        for i in order:
            rows = rows_of_sample.get(str(pred.sample_token[i]))
            if rows is None:
                continue
            d = np.hypot(*(gt.translation[rows, :2] - pred.translation[i, :2]).T)
            d = np.where(matched[rows] >= 0, np.inf, d)
            j = int(np.argmin(d))
            if d[j] < match_distance_m:
                matched[rows[j]] = i
    return matched


# ----------------------------------------------------------------------------- reading the dataroot
def ground_truth_annotations(tables: NuScenesTables, samples: list[str]) -> list[tuple[dict, str]]:
    """The sample_annotation records behind ``load_ground_truth(tables, samples)``'s boxes, one per box and in the
    same order, with each one's nuScenes category name (that loader keeps neither tokens nor categories)."""
    anns_by_sample: dict[str, list[dict]] = {}
    for ann in tables["sample_annotation"].values():  # the same walk as load_ground_truth: keep them in step
        anns_by_sample.setdefault(ann["sample_token"], []).append(ann)
    out = []
    for token in samples:
        for ann in anns_by_sample.get(token, []):
            category = tables["category"][tables["instance"][ann["instance_token"]]["category_token"]]["name"]
            if CATEGORY_TO_DETECTION.get(category) is not None:
                out.append((ann, category))
    return out


def recover_tracks(tables: NuScenesTables, instance_tokens: Iterable[str], max_track_id: int = 100_000
                   ) -> dict[str, tuple[str, int]]:
    """{instance token: (scene id, track id)} for the instances an OmniSCS export wrote. The nuScenes exporter makes
    tokens as md5 digests of what identifies a record (``omniscs.export.common.token``): a scene's is
    ``token("scene", scene_id)`` and an instance's ``token("instance", scene_id, track_id)``, where ``scene_id`` is the
    scene store's id (also written into the scene's description after 'omniscs '; the scene *name* is 'scene-0001'
    or the source log's name). So a scene whose description or name hashes to its own token is an export of that
    store, and its instances are found by hashing track ids 0..``max_track_id``. Instances of other scenes (a real
    nuScenes log, a track id beyond the range) are left out."""
    from omniscs.export.common import token  # the exporter's own rule (imported here: it pulls in the scene layer)

    wanted: dict[str, set[str]] = {}
    for inst in instance_tokens:
        rec = tables["instance"].get(inst)
        first = tables["sample_annotation"].get(rec["first_annotation_token"]) if rec else None
        if first is not None:
            wanted.setdefault(tables["sample"][first["sample_token"]]["scene_token"], set()).add(inst)
    found: dict[str, tuple[str, int]] = {}
    for scene_token, pending in wanted.items():
        scene = tables["scene"][scene_token]
        description = str(scene.get("description", ""))
        candidates = [description[len(EXPORT_DESCRIPTION_PREFIX):]] if description.startswith(
            EXPORT_DESCRIPTION_PREFIX) else []
        scene_id = next((c for c in [*candidates, str(scene["name"])] if token("scene", c) == scene_token), None)
        if scene_id is None:
            continue
        for track_id in range(max_track_id + 1):
            inst = token("instance", scene_id, track_id)
            if inst in pending:
                found[inst] = (scene_id, track_id)
                pending.discard(inst)
                if not pending:
                    break
    return found


# ----------------------------------------------------------------------------- the report
@dataclass(frozen=True, eq=False)
class MissedReport:
    """Every evaluated ground-truth box of the mined samples, matched or missed (``boxes``: one row each, columns
    ``BOX_COLUMNS``: global centre x, y, z and quaternion qw..qz, size as nuScenes stores it (width, length, height),
    angles in degrees, visibility the nuScenes token '1'..'4', ``match_*`` <NA> when missed, ``scene_id`` and
    ``track_id`` <NA> unless recovered), and the miss rate by category, ego distance, visibility, orientation and pose
    (each: key column, ``n_gt``, ``n_missed``, ``miss_rate`` <NA> for an empty bin)."""

    boxes: pd.DataFrame
    by_category: pd.DataFrame
    by_distance: pd.DataFrame
    by_visibility: pd.DataFrame
    by_orientation: pd.DataFrame
    by_pose: pd.DataFrame
    config: MiningConfig
    n_samples: int
    source: dict
    """Where it came from: dataroot, version, results path and the results' meta."""

    @property
    def n_gt(self) -> int:
        return len(self.boxes)

    @property
    def n_missed(self) -> int:
        return int(self.boxes["missed"].sum())

    @property
    def miss_rate(self) -> float | None:
        return self.n_missed / self.n_gt if self.n_gt else None

    @property
    def summaries(self) -> dict[str, pd.DataFrame]:
        return {"category": self.by_category, "distance": self.by_distance, "visibility": self.by_visibility,
                "orientation": self.by_orientation, "pose": self.by_pose}

    @property
    def missed_boxes(self) -> pd.DataFrame:
        return self.boxes[self.boxes["missed"]]

    def to_dict(self) -> dict:
        """Totals, the settings, where it came from and each summary as a list of rows; JSON-safe (None, never NaN)."""
        return _plain({"dataroot": self.source.get("dataroot"), "version": self.source.get("version"),
                       "results": self.source.get("results"), "results_meta": self.source.get("meta", {}),
                       "n_samples": self.n_samples, "n_gt": self.n_gt, "n_missed": self.n_missed,
                       "miss_rate": self.miss_rate, "n_tracks_recovered": int(self.boxes["track_id"].notna().sum()),
                       "config": self.config.to_dict(),
                       "summaries": {k: df.to_dict("records") for k, df in self.summaries.items()}})

    def markdown(self) -> str:
        """Totals and one table per summary."""
        c = self.config
        lines = ["# What the detector misses", "",
                 f"Results `{self.source.get('results')}` against `{self.source.get('dataroot')}` "
                 f"({self.source.get('version')}): {self.n_samples} samples, {self.n_gt} evaluated ground-truth boxes, "
                 f"{self.n_missed} missed (miss rate {_fmt(self.miss_rate)}). A box is missed when no prediction of "
                 f"its class scoring at least {c.min_score:g} is matched to it within {c.match_distance_m:g} m "
                 "(nuScenes' centre-distance rule).", ""]
        for name, df in self.summaries.items():
            lines += [f"## By {name}", "", _markdown_table(df), ""]
        return "\n".join(lines)

    def png_bytes(self) -> bytes:
        """One figure: a bar chart of the miss rate per summary, each bar marked 'missed/evaluated', and the totals."""
        from matplotlib.figure import Figure

        fig = Figure(figsize=(16, 9), dpi=100, layout="constrained")
        axes = fig.subplots(2, 3).ravel()
        titles = {"category": "by nuScenes category", "distance": "by ego distance",
                  "visibility": "by visibility (nuScenes level)", "orientation": "by orientation to the ego",
                  "pose": "by pose"}
        for ax, (name, df) in zip(axes, self.summaries.items()):
            labels = [str(v) for v in df[name]]
            if name == "visibility":
                labels = [f"{v}: {lvl}" for v, lvl in zip(df["visibility"], df["level"])]
            rates = df["miss_rate"].to_numpy(np.float64, na_value=np.nan)
            x = np.arange(len(df))
            ax.bar(x, np.nan_to_num(rates), color=[_rate_colour(r) for r in rates], edgecolor="0.3")
            for xi, r, m, n in zip(x, rates, df["n_missed"], df["n_gt"]):
                text = f"{m}/{n}" if n else "no boxes"
                ax.text(xi, (0.0 if np.isnan(r) else r) + 0.02, text, ha="center", va="bottom", fontsize=10)
            ax.set_xticks(x, labels, rotation=25 if len(df) > 3 else 0, ha="right" if len(df) > 3 else "center",
                          fontsize=10)
            ax.set_ylim(0, 1.15)
            ax.set_ylabel("miss rate")
            ax.set_title(titles[name], fontsize=12)
            ax.grid(axis="y", alpha=0.3)
        info = axes[-1]
        info.axis("off")
        c = self.config
        info.text(0.0, 0.95, "\n".join([
            f"{self.n_missed} of {self.n_gt} evaluated boxes missed",
            f"miss rate {_fmt(self.miss_rate)} over {self.n_samples} samples", "",
            f"match: centre closer than {c.match_distance_m:g} m,", f"predictions scoring >= {c.min_score:g}", "",
            "bars: miss rate; labels: missed / evaluated",
            f"tracks recovered: {int(self.boxes['track_id'].notna().sum())} of {self.n_gt} boxes"]),
            va="top", ha="left", fontsize=12, family="monospace", transform=info.transAxes)
        fig.suptitle("What the detector misses", fontsize=15)
        buf = io.BytesIO()
        fig.savefig(buf, format="png")
        return buf.getvalue()

    def plot(self, path: str | Path) -> Path:
        """Write ``png_bytes`` to ``path`` atomically."""
        return atomic_write_bytes(path, self.png_bytes())


def build_report(dataroot: str | Path, version: str | None, results_path: str | Path,
                 config: MiningConfig = MiningConfig()) -> MissedReport:
    """Match a results file against the evaluated ground truth of ``config.scenes`` of a dataroot and describe each
    ground-truth box (see ``MissedReport``). ``version`` None: the dataroot's only one. Refuses (``ValidationError``,
    one line) a missing dataroot, results the protocol refuses (unknown or missing sample tokens, non-finite scores,
    ...) and a dataroot with nothing to evaluate."""
    root = Path(dataroot)
    if not root.is_dir():
        raise ValidationError(f"dataroot {root} does not exist; pass the folder that holds {version or 'v1.0-*'}/ "
                              "(e.g. what 'omniscs dataset export --format nuscenes' wrote)")
    tables = NuScenesTables.load(root, version)
    version = tables.version
    samples = tables.scene_samples(list(config.scenes) or None)
    if not samples:
        raise ValidationError(f"{root / version} has no samples; mine a dataroot with annotated keyframes")
    gt, racks = load_ground_truth(tables, samples)
    pred, meta = load_results(results_path, tables, samples, config.detection)
    annotations = ground_truth_annotations(tables, samples)
    # filter_boxes keeps rows in order and never reads the score: carry each row's index through it in the score.
    kept = filter_boxes(dataclasses.replace(gt, score=np.arange(len(gt), dtype=np.float64)), config.detection,
                        racks).score.astype(np.int64)
    if len(kept) == 0:
        raise ValidationError(f"{root / version} has no evaluated ground-truth box (none of a detection class within "
                              "its class range and with a LiDAR or radar point); mine a dataroot whose annotations "
                              "count their points")
    gt = gt.take(kept)
    annotations = [annotations[i] for i in kept]
    pred = filter_boxes(pred, config.detection, racks)
    matched = match_ground_truth(gt, pred, config.match_distance_m, config.min_score)
    boxes = _box_table(tables, gt, annotations, pred, matched, config)
    return MissedReport(boxes=boxes, **_summaries(boxes, config), config=config, n_samples=len(samples),
                        source={"dataroot": str(root), "version": version, "results": str(results_path), "meta": meta})


def _box_table(tables: NuScenesTables, gt: Boxes, annotations: list[tuple[dict, str]], pred: Boxes,
               matched: np.ndarray, config: MiningConfig) -> pd.DataFrame:
    try:
        angles = box_angles(gt.rotation)
    except ValidationError:
        bad = next(a["token"] for (a, _), q in zip(annotations, gt.rotation)
                   if not (np.all(np.isfinite(q)) and np.linalg.norm(q) > 0))
        raise ValidationError(f"annotation {bad} has a zero or non-finite rotation; fix the dataroot") from None
    ego_xy = np.array([tables.reference_pose(str(t))["translation"][:2] for t in gt.sample_token], np.float64)
    ego_xy = ego_xy.reshape(len(gt), 2)
    relative = relative_heading_deg(angles["yaw_deg"], gt.translation[:, :2], ego_xy)
    bins, _ = distance_bins(gt.ego_dist, config.distance_edges_m)
    hit = matched >= 0
    match_distance = np.full(len(gt), np.nan)
    match_distance[hit] = np.hypot(*(gt.translation[hit, :2] - pred.translation[matched[hit], :2]).T)
    match_score = np.where(hit, pred.score[np.where(hit, matched, 0)] if len(pred) else np.nan, np.nan)
    tracks = recover_tracks(tables, {a["instance_token"] for a, _ in annotations}, config.max_track_id)
    scene_names = {t: s["name"] for t, s in tables["scene"].items()}
    track = [tracks.get(a["instance_token"]) for a, _ in annotations]
    table = pd.DataFrame({
        "sample_token": gt.sample_token.astype(str).astype(object),
        "scene_name": [scene_names[tables["sample"][str(t)]["scene_token"]] for t in gt.sample_token],
        "annotation_token": [a["token"] for a, _ in annotations],
        "instance_token": [a["instance_token"] for a, _ in annotations],
        "detection_name": gt.name.astype(str).astype(object),
        "category": [c for _, c in annotations],
        "x": gt.translation[:, 0], "y": gt.translation[:, 1], "z": gt.translation[:, 2],
        "width": gt.size[:, 0], "length": gt.size[:, 1], "height": gt.size[:, 2],
        "qw": gt.rotation[:, 0], "qx": gt.rotation[:, 1], "qy": gt.rotation[:, 2], "qz": gt.rotation[:, 3],
        **angles,
        "ego_distance_m": gt.ego_dist, "distance_bin": bins,
        "visibility": [str(a.get("visibility_token", "")) for a, _ in annotations],
        "relative_heading_deg": relative,
        "orientation": orientation_bins(relative, config.facing_deg),
        "pose": pose_bins(angles["tilt_deg"], config.on_side_deg, config.overturned_deg),
        "missed": ~hit,
        "match_distance_m": pd.array(np.where(hit, match_distance, np.nan), dtype="Float64"),
        "match_score": pd.array(match_score, dtype="Float64"),
        "scene_id": pd.array([t[0] if t else None for t in track], dtype=object),
        "track_id": pd.array([t[1] if t else None for t in track], dtype="Int64"),
    })  # Float64 turns the NaN of a miss into <NA>
    return table[list(BOX_COLUMNS)]


def _summaries(boxes: pd.DataFrame, config: MiningConfig) -> dict[str, pd.DataFrame]:
    from omniscs.scene.sources.nuscenes import VISIBILITY  # nuScenes' levels: token, name, description

    _, distance_labels = distance_bins(np.zeros(0), config.distance_edges_m)
    level_of = {tok: level for tok, level, _ in VISIBILITY}
    visibility = [*level_of, *sorted(set(boxes["visibility"]) - set(level_of))]
    by_visibility = _summary(boxes, "visibility", "visibility", visibility)
    by_visibility.insert(1, "level", [level_of.get(v, "unknown") for v in visibility])
    return {"by_category": _summary(boxes, "category", "category", sorted(set(boxes["category"]))),
            "by_distance": _summary(boxes, "distance_bin", "distance", distance_labels),
            "by_visibility": by_visibility,
            "by_orientation": _summary(boxes, "orientation", "orientation", list(ORIENTATIONS)),
            "by_pose": _summary(boxes, "pose", "pose", list(POSES))}


def _summary(boxes: pd.DataFrame, column: str, key: str, levels: list[str]) -> pd.DataFrame:
    """One row per level (in order, empty ones too): n_gt, n_missed and miss_rate (<NA> when empty)."""
    n_gt = boxes.groupby(column)["missed"].size().reindex(levels, fill_value=0).astype(int)
    n_missed = boxes.groupby(column)["missed"].sum().reindex(levels, fill_value=0).astype(int)
    rate = [m / n if n else None for m, n in zip(n_missed, n_gt)]
    return pd.DataFrame({key: levels, "n_gt": n_gt.to_numpy(), "n_missed": n_missed.to_numpy(),
                         "miss_rate": pd.array(rate, dtype="Float64")})


# ----------------------------------------------------------------------------- picking SCS objects
@dataclass(frozen=True, eq=False)
class ScsPick:
    """One (category, orientation, pose) cell of the report and the missed ground-truth boxes in it."""

    category: str
    orientation: str
    pose: str
    n_gt: int
    n_missed: int
    miss_rate: float
    missed: pd.DataFrame
    """Rows of ``MissedReport.boxes``: the cell's missed boxes (with ``scene_id``/``track_id`` where recovered)."""

    def to_dict(self) -> dict:
        return _plain({"category": self.category, "orientation": self.orientation, "pose": self.pose,
                       "n_gt": self.n_gt, "n_missed": self.n_missed, "miss_rate": self.miss_rate,
                       "missed": missed_box_records(self.missed)})


def pick_scs_objects(report: MissedReport, top: int = 10, min_count: int = 3) -> list[ScsPick]:
    """The objects an appearance-SCS generator should composite: the (nuScenes category, orientation, pose) cells of
    ``report.boxes`` holding at least ``min_count`` evaluated boxes and at least one miss, ranked by miss rate (ties:
    more missed first, then by name), the first ``top``; each with its missed boxes. A cell is what a generator can
    reproduce (which object, turned how to the ego, in which pose); its missed boxes name the samples and, for an
    OmniSCS export, the (scene id, track id) whose agent model or motion the composite can reuse."""
    if top < 0 or min_count < 1:
        raise OmniscsError(f"top must be >= 0 and min_count >= 1; got top={top}, min_count={min_count}")
    keys = ["category", "orientation", "pose"]
    cells = report.boxes.groupby(keys)["missed"].agg(n_gt="size", n_missed="sum").reset_index()
    cells = cells[(cells["n_gt"] >= min_count) & (cells["n_missed"] > 0)].copy()
    cells["miss_rate"] = cells["n_missed"] / cells["n_gt"]
    cells = cells.sort_values(["miss_rate", "n_missed", *keys], ascending=[False, False, True, True, True]).head(top)
    picks = []
    for cell in cells.itertuples(index=False):
        inside = (report.boxes["category"] == cell.category) & (report.boxes["orientation"] == cell.orientation) & \
                 (report.boxes["pose"] == cell.pose) & report.boxes["missed"]
        picks.append(ScsPick(cell.category, cell.orientation, cell.pose, int(cell.n_gt), int(cell.n_missed),
                             float(cell.miss_rate), report.boxes[inside].reset_index(drop=True)))
    return picks


def missed_box_records(boxes: pd.DataFrame) -> list[dict]:
    """Boxes (rows of ``MissedReport.boxes``) as JSON-safe dicts with nuScenes-style translation/size/rotation."""
    out = []
    for row in boxes.itertuples(index=False):
        out.append(_plain({
            "sample_token": row.sample_token, "scene_name": row.scene_name, "annotation_token": row.annotation_token,
            "instance_token": row.instance_token, "scene_id": row.scene_id, "track_id": row.track_id,
            "category": row.category, "detection_name": row.detection_name,
            "translation": [row.x, row.y, row.z], "size": [row.width, row.length, row.height],
            "rotation": [row.qw, row.qx, row.qy, row.qz], "yaw_deg": row.yaw_deg, "pitch_deg": row.pitch_deg,
            "roll_deg": row.roll_deg, "ego_distance_m": row.ego_distance_m, "visibility": row.visibility,
            "orientation": row.orientation, "pose": row.pose}))
    return out


def picks_markdown(picks: list[ScsPick]) -> str:
    lines = ["## SCS objects to composite", ""]
    if not picks:
        return "\n".join(lines + ["No (category, orientation, pose) cell has enough boxes and a miss.", ""])
    table = pd.DataFrame([{"category": p.category, "orientation": p.orientation, "pose": p.pose, "n_gt": p.n_gt,
                           "n_missed": p.n_missed, "miss_rate": p.miss_rate,
                           "tracks": _track_list(p.missed)} for p in picks])
    return "\n".join(lines + [_markdown_table(table), ""])


def _track_list(boxes: pd.DataFrame, most: int = MARKDOWN_TRACKS) -> str:
    """'scene_id#track_id' of the boxes' distinct recovered tracks (the first ``most``), or '–'."""
    known = boxes[boxes["track_id"].notna()]
    tracks = list(dict.fromkeys(f"{s}#{t}" for s, t in zip(known["scene_id"], known["track_id"])))
    more = f" (+{len(tracks) - most} more)" if len(tracks) > most else ""
    return ", ".join(tracks[:most]) + more if tracks else "–"


# ----------------------------------------------------------------------------- the stage
def mine(dataroot: str | Path, version: str | None, results_path: str | Path, out_dir: str | Path,
         config: MiningConfig = MiningConfig(), overwrite: bool = False) -> MissedReport:
    """``build_report``, ``pick_scs_objects`` (``config.pick_top``, ``config.pick_min_count``), then the folder
    ``out_dir`` with ``missed.json`` (the report's dict, the picks and every missed box), ``missed.md`` and
    ``missed.png``, all or nothing: everything is made in memory, written into a temporary sibling folder and renamed.
    An existing ``out_dir`` is replaced only with ``overwrite`` (and only one omniscs wrote)."""
    report = build_report(dataroot, version, results_path, config)
    picks = pick_scs_objects(report, config.pick_top, config.pick_min_count)
    payload = {"report": report.to_dict(), "picks": [p.to_dict() for p in picks],
               "missed": missed_box_records(report.missed_boxes)}
    text = report.markdown() + "\n" + picks_markdown(picks)
    png = report.png_bytes()
    with atomic_directory(out_dir, overwrite=overwrite) as tmp:
        atomic_write_json(tmp / MISSED_JSON, payload)
        atomic_write_text(tmp / MISSED_MD, text)
        atomic_write_bytes(tmp / MISSED_PNG, png)
    return report


# ----------------------------------------------------------------------------- helpers
def _plain(value):
    """JSON-safe copy: numpy scalars as Python numbers, NaN/Inf and <NA> as None, tuples and arrays as lists."""
    if value is None or value is pd.NA:
        return None
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_plain(v) for v in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, Path):
        return str(value)
    return value


def _fmt(x) -> str:
    return "–" if x is None or x is pd.NA or (isinstance(x, float) and not math.isfinite(x)) else f"{x:.3f}"


def _markdown_table(df: pd.DataFrame) -> str:
    def cell(v) -> str:
        return _fmt(v) if v is None or v is pd.NA or isinstance(v, (float, np.floating)) else str(v)

    rows = ["| " + " | ".join(df.columns) + " |", "|" + "---|" * len(df.columns)]
    rows += ["| " + " | ".join(cell(v) for v in r) + " |" for r in df.itertuples(index=False)]
    return "\n".join(rows)


def _rate_colour(rate: float):
    """Green (nothing missed) through yellow to red (all missed); grey for an empty bin."""
    from matplotlib import colormaps

    return (0.8, 0.8, 0.8, 1.0) if not np.isfinite(rate) else colormaps["RdYlGn_r"](0.1 + 0.8 * float(rate))
