"""nuScenes detection metrics: mAP, the five true-positive errors and NDS, on results in the nuScenes detection
results format, by the published protocol (Caesar et al., nuScenes, CVPR 2020; the devkit's ``detection_cvpr_2019``
configuration):

- Boxes are matched per class and per distance threshold (0.5 / 1 / 2 / 4 m between centres in the ground plane):
  predictions in order of falling score (equal scores: the later one first), each to the nearest unmatched ground
  truth box of its sample (the first of equals), a match when nearer than the threshold.
- Precision is interpolated at 101 recall points (0 beyond the largest recall reached); AP is the mean precision
  above recall 0.1 after subtracting the minimum precision 0.1, rescaled to [0, 1].
- True-positive errors at the 2 m threshold, each a cumulative mean over matches, read at the same operating points
  and averaged from recall 0.1 to the largest recall reached (1 when that is below 0.1): translation (m, ground
  plane), scale (1 - IoU of the boxes aligned), orientation (yaw, rad; period pi for barriers), velocity (m/s,
  ground plane), attribute (1 - accuracy; undefined where the ground truth has no attribute). Not defined: cones'
  attribute, velocity and orientation, barriers' attribute and velocity.
- NDS = (5 mAP + sum over the five errors of max(0, 1 - mean error over classes)) / 10.
- Ground truth and predictions farther from the ego (LIDAR_TOP ego pose, ground plane) than the class range are
  left out, ground truth with no LiDAR or radar point in it too, and bicycles and motorcycles inside a bicycle rack.

``accumulate``, ``calc_ap`` and ``calc_tp`` agree with the nuScenes devkit's functions of the same names to 1e-6
(``tests/eval/test_detection.py`` runs both on the same boxes); the matching is vectorised per sample instead of a
loop over every ground truth box.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from omniscs.errors import ValidationError
from omniscs.quaternions import yaw_from_quaternion

#: The ten nuScenes detection classes, in the devkit's order.
DETECTION_NAMES: tuple[str, ...] = ("car", "truck", "bus", "trailer", "construction_vehicle", "pedestrian",
                                    "motorcycle", "bicycle", "traffic_cone", "barrier")
#: Attributes a box of each class may carry (the devkit's ``ATTRIBUTE_NAMES`` by class).
CLASS_ATTRIBUTES: dict[str, tuple[str, ...]] = {
    **{c: ("vehicle.moving", "vehicle.parked", "vehicle.stopped")
       for c in ("car", "truck", "bus", "trailer", "construction_vehicle")},
    "pedestrian": ("pedestrian.moving", "pedestrian.sitting_lying_down", "pedestrian.standing"),
    "motorcycle": ("cycle.with_rider", "cycle.without_rider"), "bicycle": ("cycle.with_rider", "cycle.without_rider"),
    "traffic_cone": (), "barrier": (),
}
TP_METRICS: tuple[str, ...] = ("trans_err", "scale_err", "orient_err", "vel_err", "attr_err")
#: Errors the protocol leaves undefined for a class.
UNDEFINED_TP: dict[str, tuple[str, ...]] = {"traffic_cone": ("attr_err", "vel_err", "orient_err"),
                                            "barrier": ("attr_err", "vel_err")}
#: Recall points of the interpolated precision.
N_POINTS = 101


@dataclass(frozen=True)
class DetectionConfig:
    """The protocol's settings (defaults: the devkit's ``detection_cvpr_2019``)."""

    class_range: dict[str, float] = field(default_factory=lambda: {
        "car": 50.0, "truck": 50.0, "bus": 50.0, "trailer": 50.0, "construction_vehicle": 50.0, "pedestrian": 40.0,
        "motorcycle": 40.0, "bicycle": 40.0, "traffic_cone": 30.0, "barrier": 30.0})
    """Largest ego distance (m, ground plane) of an evaluated box, per class."""
    dist_ths: tuple[float, ...] = (0.5, 1.0, 2.0, 4.0)
    """Centre-distance thresholds of a match (m)."""
    dist_th_tp: float = 2.0
    """The threshold at which the true-positive errors are measured."""
    min_recall: float = 0.1
    min_precision: float = 0.1
    max_boxes_per_sample: int = 500
    mean_ap_weight: float = 5.0
    class_names: tuple[str, ...] = DETECTION_NAMES
    """Classes averaged into mAP and NDS (the protocol: all ten, absent ones count as AP 0)."""

    def __post_init__(self):
        unknown = [c for c in self.class_names if c not in DETECTION_NAMES]
        if unknown or not self.class_names:
            raise ValidationError(f"class_names must be detection classes among {list(DETECTION_NAMES)}; "
                                  f"got {list(self.class_names)}")
        if not all(0.0 < d for d in self.dist_ths) or not 0.0 <= self.min_precision < 1.0 \
                or not 0.0 <= self.min_recall <= 1.0:
            raise ValidationError("dist_ths must be positive, min_precision in [0, 1), min_recall in [0, 1]")
        object.__setattr__(self, "class_names", tuple(self.class_names))
        object.__setattr__(self, "dist_ths", tuple(float(d) for d in self.dist_ths))


@dataclass(frozen=True)
class Boxes:
    """Boxes of many samples as arrays (one row per box), ground truth or predictions, in the global frame."""

    sample_token: np.ndarray  # [N] str
    translation: np.ndarray   # [N, 3]
    size: np.ndarray          # [N, 3] width, length, height
    rotation: np.ndarray      # [N, 4] quaternion w, x, y, z
    velocity: np.ndarray      # [N, 2] m/s, global x, y (NaN = unknown)
    name: np.ndarray          # [N] str, a detection class
    score: np.ndarray         # [N] float (ground truth: -1)
    attribute: np.ndarray     # [N] str ('' = none)
    ego_dist: np.ndarray      # [N] m, ground plane distance to the ego
    num_pts: np.ndarray       # [N] int LiDAR + radar points (predictions: -1)

    def __len__(self) -> int:
        return len(self.sample_token)

    def take(self, index) -> "Boxes":
        return Boxes(*(getattr(self, f)[index] for f in self.__dataclass_fields__))

    @classmethod
    def from_records(cls, records: list[dict], ego_dist=None, num_pts=None) -> "Boxes":
        """From dicts with the results format's keys (``sample_token``, ``translation``, ``size``, ``rotation``,
        ``velocity``, ``detection_name``, ``detection_score``, ``attribute_name``)."""
        n = len(records)
        return cls(np.array([r["sample_token"] for r in records], dtype=object),
                   np.array([r["translation"] for r in records], np.float64).reshape(n, 3),
                   np.array([r["size"] for r in records], np.float64).reshape(n, 3),
                   np.array([r["rotation"] for r in records], np.float64).reshape(n, 4),
                   np.array([r.get("velocity", (np.nan, np.nan))[:2] for r in records], np.float64).reshape(n, 2),
                   np.array([r["detection_name"] for r in records], dtype=object),
                   np.array([r.get("detection_score", -1.0) for r in records], np.float64),
                   np.array([r.get("attribute_name", "") for r in records], dtype=object),
                   np.zeros(n) if ego_dist is None else np.asarray(ego_dist, np.float64),
                   np.full(n, -1, np.int64) if num_pts is None else np.asarray(num_pts, np.int64))


@dataclass(frozen=True)
class MetricData:
    """One class at one threshold: precision, confidence and the true-positive errors at 101 recall points."""

    recall: np.ndarray
    precision: np.ndarray
    confidence: np.ndarray
    trans_err: np.ndarray
    vel_err: np.ndarray
    scale_err: np.ndarray
    orient_err: np.ndarray
    attr_err: np.ndarray

    @classmethod
    def no_predictions(cls) -> "MetricData":
        ones = np.ones(N_POINTS)
        return cls(np.linspace(0, 1, N_POINTS), np.zeros(N_POINTS), np.zeros(N_POINTS), ones, ones.copy(),
                   ones.copy(), ones.copy(), ones.copy())

    @property
    def max_recall_ind(self) -> int:
        """Index of the largest recall reached: the last point with a non-zero confidence (0 when none)."""
        nz = np.nonzero(self.confidence)[0]
        return int(nz[-1]) if len(nz) else 0


def angle_diff(a: np.ndarray, b: np.ndarray, period: float) -> np.ndarray:
    """Smallest signed difference a - b for angles of the given period, in (-pi, pi]."""
    d = (a - b + period / 2) % period - period / 2
    return np.where(d > np.pi, d - 2 * np.pi, d)


def scale_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:  # [N, 3] sizes each -> [N]
    """IoU of two boxes with the same centre and heading (only their sizes differ)."""
    inter = np.prod(np.minimum(a, b), axis=-1)
    return inter / (np.prod(a, axis=-1) + np.prod(b, axis=-1) - inter)


def cummean(x: np.ndarray) -> np.ndarray:
    """Running mean ignoring NaN; all NaN -> ones (an error that is never defined counts as the worst)."""
    if np.isnan(x).all():
        return np.ones(len(x))
    sums = np.nancumsum(x.astype(np.float64))
    counts = np.cumsum(~np.isnan(x))
    return np.divide(sums, counts, out=np.zeros_like(sums), where=counts != 0)


def _by_sample(boxes: Boxes) -> dict[str, np.ndarray]:
    """Row indices of each sample's boxes, in their order."""
    order = np.argsort(boxes.sample_token.astype(str), kind="stable")
    tokens = boxes.sample_token[order]
    out: dict[str, np.ndarray] = {}
    if len(order):
        cuts = np.flatnonzero(tokens[1:] != tokens[:-1]) + 1
        for part in np.split(order, cuts):
            out[str(boxes.sample_token[part[0]])] = part
    return out


def accumulate(gt: Boxes, pred: Boxes, class_name: str, dist_th: float) -> MetricData:
    """Match ``pred`` to ``gt`` for one class at one centre-distance threshold (the protocol above)."""
    gt_c = gt.take(gt.name == class_name)
    npos = len(gt_c)
    if npos == 0:
        return MetricData.no_predictions()
    pr = pred.take(pred.name == class_name)
    order = np.lexsort((np.arange(len(pr)), pr.score))[::-1]  # falling score; equal scores: the later box first
    gt_rows = _by_sample(gt_c)
    taken = {tok: np.zeros(len(rows), bool) for tok, rows in gt_rows.items()}
    tp = np.zeros(len(order))
    matched_gt = np.full(len(order), -1)
    for k, i in enumerate(order):
        rows = gt_rows.get(str(pr.sample_token[i]))
        if rows is None:
            continue
        d = np.hypot(gt_c.translation[rows, 0] - pr.translation[i, 0], gt_c.translation[rows, 1] - pr.translation[i, 1])
        free = taken[str(pr.sample_token[i])]
        d = np.where(free, np.inf, d)
        j = int(np.argmin(d))
        if d[j] < dist_th:
            free[j] = True
            tp[k] = 1.0
            matched_gt[k] = rows[j]
    if not tp.any():
        return MetricData.no_predictions()
    conf = pr.score[order]
    tps = np.cumsum(tp)
    fps = np.cumsum(1.0 - tp)
    precision = tps / (tps + fps)
    recall = tps / float(npos)
    points = np.linspace(0, 1, N_POINTS)
    precision_i = np.interp(points, recall, precision, right=0)
    conf_i = np.interp(points, recall, conf, right=0)
    hit = tp > 0
    p_rows, g_rows = order[hit], matched_gt[hit]
    period = np.pi if class_name == "barrier" else 2 * np.pi
    g_attr = gt_c.attribute[g_rows].astype(str)
    errors = {
        "trans_err": np.hypot(*(gt_c.translation[g_rows, :2] - pr.translation[p_rows, :2]).T),
        "vel_err": np.linalg.norm(pr.velocity[p_rows] - gt_c.velocity[g_rows], axis=1),
        "scale_err": 1.0 - scale_iou(gt_c.size[g_rows], pr.size[p_rows]),
        "orient_err": np.abs(angle_diff(yaw_from_quaternion(gt_c.rotation[g_rows]),
                                        yaw_from_quaternion(pr.rotation[p_rows]), period)),
        "attr_err": np.where(g_attr == "", np.nan, 1.0 - (g_attr == pr.attribute[p_rows].astype(str))),
    }
    match_conf = conf[hit]
    resampled = {k: np.interp(conf_i[::-1], match_conf[::-1], cummean(v)[::-1])[::-1] for k, v in errors.items()}
    return MetricData(points, precision_i, conf_i, **resampled)


def calc_ap(md: MetricData, min_recall: float, min_precision: float) -> float:
    """Mean interpolated precision above ``min_recall``, less ``min_precision``, rescaled to [0, 1]."""
    precision = md.precision[round(100 * min_recall) + 1:] - min_precision
    return float(np.mean(np.clip(precision, 0.0, None))) / (1.0 - min_precision)


def calc_tp(md: MetricData, min_recall: float, metric: str) -> float:
    """Mean of a true-positive error from ``min_recall`` to the largest recall reached (1 when below)."""
    first, last = round(100 * min_recall) + 1, md.max_recall_ind
    if last < first:
        return 1.0
    return float(np.mean(getattr(md, metric)[first:last + 1]))


@dataclass(frozen=True)
class DetectionMetrics:
    """The protocol's numbers for one evaluation."""

    label_aps: dict[str, dict[float, float]]   # class -> threshold -> AP
    label_tp_errors: dict[str, dict[str, float]]  # class -> error name -> value (NaN: undefined)
    config: DetectionConfig
    n_gt: dict[str, int]
    n_pred: dict[str, int]

    @property
    def mean_dist_aps(self) -> dict[str, float]:
        return {c: float(np.mean(list(self.label_aps[c].values()))) for c in self.config.class_names}

    @property
    def mean_ap(self) -> float:
        return float(np.mean(list(self.mean_dist_aps.values())))

    @property
    def tp_errors(self) -> dict[str, float]:
        out = {}
        for m in TP_METRICS:
            values = np.array([self.label_tp_errors[c][m] for c in self.config.class_names], np.float64)
            out[m] = float(np.nanmean(values)) if np.isfinite(values).any() else 1.0
        return out

    @property
    def tp_scores(self) -> dict[str, float]:
        return {m: max(0.0, 1.0 - e) for m, e in self.tp_errors.items()}

    @property
    def nd_score(self) -> float:
        w = self.config.mean_ap_weight
        return float((w * self.mean_ap + sum(self.tp_scores.values())) / (w + len(TP_METRICS)))

    def to_dict(self) -> dict:
        """mAP, NDS, the mean errors and, per class, the AP at each threshold, their mean, the errors and the box
        counts (NaN errors as None)."""
        def num(x: float) -> float | None:
            return float(x) if np.isfinite(x) else None

        return {"mAP": self.mean_ap, "NDS": self.nd_score, "tp_errors": self.tp_errors,
                "classes": {c: {"AP": {f"{t:g}": self.label_aps[c][t] for t in self.config.dist_ths},
                                "mean_AP": self.mean_dist_aps[c],
                                "tp_errors": {m: num(v) for m, v in self.label_tp_errors[c].items()},
                                "n_gt": self.n_gt.get(c, 0), "n_pred": self.n_pred.get(c, 0)}
                            for c in self.config.class_names}}


def evaluate(gt: Boxes, pred: Boxes, config: DetectionConfig = DetectionConfig()) -> DetectionMetrics:
    """AP per class and threshold, the true-positive errors and NDS of ``pred`` against ``gt``, both already
    filtered (``filter_boxes``)."""
    aps: dict[str, dict[float, float]] = {}
    errors: dict[str, dict[str, float]] = {}
    for c in config.class_names:
        aps[c] = {}
        for t in config.dist_ths:
            aps[c][t] = calc_ap(accumulate(gt, pred, c, t), config.min_recall, config.min_precision)
        md = accumulate(gt, pred, c, config.dist_th_tp)
        errors[c] = {m: (np.nan if m in UNDEFINED_TP.get(c, ()) else calc_tp(md, config.min_recall, m))
                     for m in TP_METRICS}
    counts = lambda b: {c: int(np.sum(b.name == c)) for c in config.class_names}  # noqa: E731
    return DetectionMetrics(aps, errors, config, counts(gt), counts(pred))


def _resampled(boxes: Boxes, index: dict[str, np.ndarray], picks: list[str]) -> Boxes:
    """The boxes of the picked groups (a group picked twice comes twice, under renamed sample tokens)."""
    rows, tokens = [], []
    for k, g in enumerate(picks):
        rows.append(index[g])
        tokens.append(np.array([f"{t}#{k}" for t in boxes.sample_token[index[g]]], dtype=object))
    at = np.concatenate(rows) if rows else np.zeros(0, np.int64)
    out = boxes.take(at)
    return Boxes(np.concatenate(tokens) if tokens else out.sample_token,
                 *(getattr(out, f) for f in list(Boxes.__dataclass_fields__)[1:]))


def bootstrap_map_difference(gt: Boxes, pred_a: Boxes, pred_b: Boxes, groups: dict[str, str],
                             config: DetectionConfig = DetectionConfig(), n: int = 200, seed: int = 0) -> dict:
    """How far the mAP difference b - a (all three already filtered) can be trusted: ``groups`` (sample token ->
    group, e.g. its scene) are drawn with replacement ``n`` times, whole groups at a time since frames of one scene
    are nearly the same picture, and the difference recomputed. Returns the observed difference, the 2.5 / 97.5 %
    percentiles, the share of draws where b beats a, and the number of groups."""
    names = sorted(set(groups.values()))
    if len(names) < 2 or n < 1:
        raise ValidationError("a bootstrap needs at least two groups (scenes) and one draw")

    def by_group(boxes: Boxes) -> dict[str, np.ndarray]:
        g = np.array([groups.get(str(t), "") for t in boxes.sample_token], dtype=object)
        return {name: np.flatnonzero(g == name) for name in names}

    index = {"gt": by_group(gt), "a": by_group(pred_a), "b": by_group(pred_b)}
    rng = np.random.default_rng(seed)
    diffs = []
    for _ in range(n):
        picks = [names[i] for i in rng.integers(0, len(names), len(names))]
        g = _resampled(gt, index["gt"], picks)
        diffs.append(evaluate(g, _resampled(pred_b, index["b"], picks), config).mean_ap
                     - evaluate(g, _resampled(pred_a, index["a"], picks), config).mean_ap)
    d = np.asarray(diffs)
    return {"difference": evaluate(gt, pred_b, config).mean_ap - evaluate(gt, pred_a, config).mean_ap,
            "low": float(np.percentile(d, 2.5)), "high": float(np.percentile(d, 97.5)),
            "share_b_better": float(np.mean(d > 0)), "n_groups": len(names), "n_draws": int(n)}


def filter_boxes(boxes: Boxes, config: DetectionConfig, racks: dict[str, np.ndarray] | None = None) -> Boxes:
    """Leave out boxes beyond their class range, ground truth with no point in it (``num_pts == 0``), and bicycles
    and motorcycles whose centre lies in one of their sample's bicycle racks (``racks``: sample -> [R, 4, 4]
    world_from_rack with the rack's size folded in: the rack is the unit cube [-0.5, 0.5]^3 in that frame)."""
    limit = np.array([config.class_range.get(str(n), -np.inf) for n in boxes.name], np.float64)
    keep = (boxes.ego_dist < limit) & (boxes.num_pts != 0)
    if racks:
        for i in np.flatnonzero(keep & np.isin(boxes.name.astype(str), ("bicycle", "motorcycle"))):
            frames = racks.get(str(boxes.sample_token[i]))
            if frames is None or not len(frames):
                continue
            local = np.einsum("rij,j->ri", np.linalg.inv(frames), np.append(boxes.translation[i], 1.0))[:, :3]
            if np.any(np.all(np.abs(local) <= 0.5, axis=1)):
                keep[i] = False
    return boxes.take(keep)
