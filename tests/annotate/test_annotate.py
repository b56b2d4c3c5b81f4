"""Render + annotate: the ground truth of a rendered variant agrees with what was drawn, stays finite at the
edges (boxes behind the camera, cut by the border, none visible, the ego off the fitted area), and the variant's
store reads and exports like any other."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pandas as pd
import pytest
import torch

from annotate_fixtures import fitted_scene, logged_variant
from omniscs.annotate import AnnotateConfig
from omniscs.annotate.config import visibility_level
from omniscs.annotate.frames import COMMANDS, driving_commands
from omniscs.annotate.fidelity import feature_drift, image_fidelity
from omniscs.annotate.variant import write_annotated_variant
from omniscs.annotate.views import projected_box
from omniscs.errors import OmniscsError
from omniscs.geometry import make_transform, pose_from_xyz_yaw, rotmat_from_euler
from omniscs.nsg.graph import BACKGROUND, render_view
from omniscs.pipeline.procedural import variant_world, world_description, world_lidar, world_reference
from omniscs.scene import load_scene

K = np.array([[50.0, 0, 48], [0, 50.0, 27], [0, 0, 1]])


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    return fitted_scene(tmp_path_factory.mktemp("annotate"))


@pytest.fixture(scope="module")
def annotated(fitted, tmp_path_factory):
    scene, graph = fitted
    variant = logged_variant(scene, shift={2: 0.15})
    out = tmp_path_factory.mktemp("variant") / "store"
    return write_annotated_variant(graph, scene, variant, out, "nsg-test-v000", reference=world_reference(scene),
                                   describe=world_description(scene))


def _iou(a, b) -> float:
    w = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    h = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = w * h
    return inter / ((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter)


def test_every_visible_box_projects_onto_its_rendered_instance_mask(annotated):
    checked = 0
    for a in annotated.annotations:
        if a["visibility_level"] >= 3 and a["tight_x1"] is not None:
            iou = _iou((a["x1"], a["y1"], a["x2"], a["y2"]), (a["tight_x1"], a["tight_y1"], a["tight_x2"], a["tight_y2"]))
            assert iou >= 0.7, (a["frame_idx"], a["camera"], a["track_id"], iou)
            checked += 1
    assert checked >= 10


def test_instance_masks_in_the_store_match_the_mask_pixels_of_the_annotations(annotated):
    store = load_scene(annotated.store)
    for a in annotated.annotations[:12]:
        mask = store.instance_mask(a["camera"], a["frame_idx"]) == a["track_id"]
        assert int(mask.sum()) == a["mask_pixels"]
    boxes = store.boxes.set_index(["frame_idx", "track_id"])
    pixels = pd.DataFrame(annotated.annotations).groupby(["frame_idx", "track_id"]).mask_pixels.sum()
    for key, n in pixels.items():
        assert boxes.loc[key, "visible_pixels"] == n


def test_label_channels_leave_the_colours_unchanged(fitted):
    scene, graph = fitted
    view = graph.view(scene.camera_names[0], 3)
    plain = render_view(graph, view)
    labelled = render_view(graph, view, labels={BACKGROUND: torch.ones(len(graph.background), 2)})
    assert torch.equal(plain.rgb, labelled.rgb) and torch.equal(plain.depth, labelled.depth)
    # one all-ones channel on every background Gaussian sums to the background's unoccluded share, at most alpha
    share = labelled.labels[..., 0]
    assert float((share - labelled.alpha).max()) <= 1e-4 and float(share.sum()) > 0


def test_culling_agents_out_of_view_leaves_every_pixel_as_the_full_render(fitted):
    from omniscs.annotate.views import ViewAnnotator

    scene, graph = fitted
    annotator = ViewAnnotator(graph)
    for cam in scene.camera_names:
        for f in (0, scene.n_frames - 1):
            full = (graph.render(graph.view(cam, f)).rgb.clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8)
            np.testing.assert_array_equal(annotator.unedited(cam, f)[1], full)


def test_own_alphas_rendered_together_equal_each_instance_rendered_alone(fitted):
    import torch

    from omniscs.annotate.views import Instance, ViewAnnotator
    from omniscs.annotate.variant import _world_from_box

    scene, graph = fitted
    annotator = ViewAnnotator(graph)
    view = graph.view(scene.camera_names[0], 0)
    nodes = [Instance(int(r.track_id), str(r.category), _world_from_box(r), np.array([r.length, r.width, r.height]))
             for r in scene.boxes_at(0).itertuples() if int(r.track_id) in graph.agent_ids]
    depth = graph.render(view).depth
    assert nodes and float(depth.max()) > 0
    some = torch.arange(0, len(graph.background), 7)  # background Gaussians all over the view
    twins = [Instance(9001, "barrier", np.eye(4), np.ones(3), some), Instance(9002, "barrier", np.eye(4), np.ones(3),
                                                                                 some)]  # cover the same pixels
    renders = []
    count = annotator._alpha_channels

    def counted(*args):
        renders.append(len(args[1]))
        return count(*args)

    annotator._alpha_channels = counted
    means = graph.background.means.detach().numpy()
    world_from_camera = view.world_from_camera
    apart = []  # two clumps of background Gaussians well apart in the view, each inside its own 2 m box
    for k, x in enumerate((-4.0, 4.0)):
        centre = world_from_camera[:3, :3] @ np.array([x, 1.5, 12.0]) + world_from_camera[:3, 3]  # on the road
        box = np.eye(4)
        box[:3, 3] = centre
        near = np.nonzero(np.abs(means - centre).max(1) < 0.8)[0]
        apart.append(Instance(9101 + k, "barrier", box, np.full(3, 2.0), torch.from_numpy(near)))
    assert all(len(a.members) for a in apart)
    for group in (apart, nodes, nodes + twins):
        renders.clear()
        together = annotator._own_alphas(view, group, {})
        if group is apart:
            assert renders == [2]  # one rendering gave both: they share no pixel
        for inst in group:
            alone = count(view, [annotator._alone(view, inst, {})])
            assert together[inst.track_id] == pytest.approx(float(alone.sum()), rel=1e-5, abs=1e-3)
    assert together[9001] == together[9002] > 0.0 and len(renders) >= 3  # the twins overlap: rendered alone


def test_a_car_behind_another_is_less_visible_than_the_car_in_front(tmp_path):
    agents = ({"x": 11.0, "y": 0.0, "speed": 6.0, "asset": "sedan-0003"},
              {"x": 17.0, "y": 0.0, "speed": 6.0, "asset": "sedan-0011"})
    scene, graph = fitted_scene(tmp_path, agents=agents, n_frames=4, n_cameras=1, iterations=120)
    result = write_annotated_variant(graph, scene, logged_variant(scene), tmp_path / "v", "occluded-v000")
    front = [a for a in result.annotations if a["track_id"] == 1]
    behind = [a for a in result.annotations if a["track_id"] == 2]
    assert front and behind
    assert min(a["visible_fraction"] for a in front) > max(a["visible_fraction"] for a in behind)
    assert all(a["visibility_level"] >= 3 for a in front) and all(a["visibility_level"] <= 2 for a in behind)


def test_every_number_written_is_finite(annotated):
    for table in (annotated.samples, annotated.annotations):
        for row in table:
            for key, value in row.items():
                if isinstance(value, float):
                    assert np.isfinite(value), (key, value)
    store = load_scene(annotated.store)
    for cam in store.camera_names:
        for f in range(store.n_frames):
            assert np.all(np.isfinite(store.depth(cam, f))) and store.depth(cam, f).min() >= 0
    assert np.all(np.isfinite(store.lidar(0))) and len(store.lidar(0)) > 100
    assert (store.boxes.num_lidar_points >= 0).all()


def test_fidelity_against_the_exact_render_is_measured_on_every_frame(annotated):
    s = annotated.summary
    assert s["fidelity_frames"] == s["n_images"]
    assert 15.0 < s["fidelity_psnr"] < 60.0 and 0.0 < s["fidelity_ssim"] <= 1.0
    assert all(r["fidelity_psnr"] is not None for r in annotated.samples)


def test_identical_images_give_the_capped_psnr_and_an_empty_mask_gives_none():
    img = np.full((20, 30, 3), 128, np.uint8)
    fid = image_fidelity(img, img, np.zeros((20, 30), bool))
    assert fid["psnr"] == 100.0 and fid["ssim"] == pytest.approx(1.0) and fid["masked_psnr"] is None


def _texture(seed: int = 0) -> np.ndarray:  # uint8 [90, 160, 3]: blobs and edges at several scales
    import cv2

    rng = np.random.default_rng(seed)
    img = np.zeros((90, 160, 3), np.float32)
    for sigma, weight in ((1.0, 0.05), (3.0, 0.1), (8.0, 0.1)):
        layer = cv2.GaussianBlur(rng.random((90, 160, 3)).astype(np.float32), (0, 0), sigma)
        img += weight * (layer - layer.mean()) / layer.std()
    return (np.clip(img + 0.5, 0, 1) * 255).astype(np.uint8)


def test_feature_drift_is_zero_for_the_same_image_and_grows_with_blur_more_than_with_a_small_shift():
    import cv2

    img = _texture()
    shifted = np.roll(img, 2, axis=1)
    blurred = cv2.GaussianBlur(img, (0, 0), 4.0)
    assert feature_drift(img, img) < 1e-12
    stripes = np.zeros_like(img)
    stripes[(np.arange(90) // 6) % 2 == 1] = 200  # another structure: horizontal edges only
    small, blur, other = feature_drift(img, shifted), feature_drift(img, blurred), feature_drift(img, stripes)
    assert 0.0 < small < blur and 4 * small < other <= 1.0


def _descriptor_by_numpy(rgb, keep, cells):
    """The descriptor written with whole-array numpy (the reference for the one-pass kernel)."""
    from omniscs.annotate.fidelity import DRIFT_BINS, DRIFT_COLOUR_WEIGHT

    img = rgb.astype(np.float64) / 255.0
    gy, gx = np.gradient(rgb.astype(np.float64).sum(-1) / 765.0)  # grey rounded as the kernel does: ties stay ties
    h, w = keep.shape
    rows, cols = cells
    cell = ((np.arange(h) * rows // h)[:, None] * cols + (np.arange(w) * cols // w)[None, :]).ravel()
    k = keep.ravel().astype(np.float64)
    n = rows * cols
    pixels, kept_n = np.bincount(cell, minlength=n), np.bincount(cell, weights=k, minlength=n)
    bins = np.minimum((np.mod(np.arctan2(gy, gx), np.pi) / np.pi * DRIFT_BINS).astype(int), DRIFT_BINS - 1).ravel()
    hist = np.bincount(cell * DRIFT_BINS + bins, weights=np.hypot(gx, gy).ravel() * k,
                       minlength=n * DRIFT_BINS).reshape(n, DRIFT_BINS)
    hist /= np.linalg.norm(hist, axis=1, keepdims=True) + 1e-9
    colour = np.stack([np.bincount(cell, weights=img[..., c].ravel() * k, minlength=n) for c in range(3)], 1)
    colour /= np.maximum(kept_n, 1.0)[:, None]
    out = np.concatenate([hist, DRIFT_COLOUR_WEIGHT * colour], 1).reshape(rows, cols, -1)
    return out, np.where(pixels > 0, kept_n / np.maximum(pixels, 1), 0.0).reshape(rows, cols)


@pytest.mark.parametrize("shape,cells", [((90, 160), (6, 8)), ((7, 5), (6, 8)), ((33, 47), (3, 4))])
def test_structure_descriptor_matches_its_numpy_formulation(shape, cells):
    from omniscs.annotate.fidelity import structure_descriptor

    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 256, (*shape, 3), dtype=np.uint8)
    keep = rng.random(shape) > 0.3
    got, got_kept = structure_descriptor(rgb, keep, cells)
    want, want_kept = _descriptor_by_numpy(rgb, keep, cells)
    np.testing.assert_allclose(got, want, atol=1e-9)
    np.testing.assert_allclose(got_kept, want_kept, atol=1e-12)


def test_feature_drift_leaves_out_the_pixels_not_kept_and_stays_finite_on_flat_or_empty_input():
    img = _texture()
    edited = img.copy()
    edited[20:60, 40:100] = 60  # a hole: flat, dark
    keep = np.ones(img.shape[:2], bool)
    keep[15:65, 30:110] = False
    assert feature_drift(img, edited) > 4 * feature_drift(img, np.roll(img, 2, axis=1))
    assert feature_drift(img, edited, keep) < 1e-9
    flat = np.full_like(img, 90)
    assert np.isfinite(feature_drift(flat, flat)) and 0.0 <= feature_drift(flat, img) <= 1.0
    assert feature_drift(img, edited, np.zeros(img.shape[:2], bool)) is None
    with pytest.raises(ValueError, match="differ in size"):
        feature_drift(img, img[:, :100])


def test_every_sample_gets_a_finite_feature_drift_against_the_unedited_render(annotated):
    drifts = [r["feature_drift"] for r in annotated.samples]
    assert all(d is not None and 0.0 <= d <= 1.0 for d in drifts)
    assert all(10.0 < r["logged_psnr"] <= 100.0 for r in annotated.samples)
    assert annotated.summary["feature_drift"] == pytest.approx(np.mean(drifts))


def test_the_variant_store_reads_back_with_its_visibility_and_commands(annotated):
    store = load_scene(annotated.store)
    assert store.n_frames == annotated.summary["n_frames"] and store.has_gt and store.has_lidar
    from omniscs.scene.sources.common import load_attributes

    vis = load_attributes(store)
    assert set(vis["value"]) <= {"v0-40", "v40-60", "v60-80", "v80-100"} and len(vis) == len(store.boxes)
    meta = json.loads((annotated.store / "variant.json").read_text())
    assert meta["commands"] and set(meta["commands"]) <= set(COMMANDS)
    assert meta["scene_frames"] == list(range(store.n_frames))


def test_moved_agents_are_annotated_where_the_variant_put_them(annotated, fitted):
    scene, _ = fitted
    store = load_scene(annotated.store)
    last = store.n_frames - 1
    moved = store.boxes[(store.boxes.frame_idx == last) & (store.boxes.track_id == 2)].iloc[0]
    logged = scene.boxes[(scene.boxes.frame_idx == last) & (scene.boxes.track_id == 2)].iloc[0]
    assert moved.cy == pytest.approx(logged.cy - 0.15 * last)


def test_only_the_agents_the_variant_puts_off_their_logged_pose_count_as_moved(annotated):
    flags = {}
    for row in annotated.annotations:
        flags.setdefault(row["track_id"], set()).add(row["moved"])
    assert flags[2] == {True}  # drifted to the right
    assert all(f == {False} for tid, f in flags.items() if tid != 2) and len(flags) > 1


def test_frames_where_the_ego_leaves_the_fitted_area_are_dropped_and_recorded(fitted, tmp_path):
    scene, graph = fitted
    variant = logged_variant(scene, ego_lateral=lambda f: 0.0 if f < 6 else 9.0)
    result = write_annotated_variant(graph, scene, variant, tmp_path / "v", "off-v000",
                                     config=AnnotateConfig(max_viewpoint_offset_m=4.0))
    assert result.summary["dropped_frames"] == 4 and result.summary["n_frames"] == 6
    everywhere = logged_variant(scene, ego_lateral=lambda f: 9.0)
    with pytest.raises(OmniscsError, match="outside the fitted area in every frame"):
        write_annotated_variant(graph, scene, everywhere, tmp_path / "w", "off-v001")
    assert not (tmp_path / "w").exists()


def test_a_scene_without_agents_gives_samples_and_no_annotations(tmp_path):
    scene, graph = fitted_scene(tmp_path, agents=(), n_frames=3, n_cameras=1, iterations=40)
    result = write_annotated_variant(graph, scene, logged_variant(scene), tmp_path / "v", "empty-v000")
    assert len(result.samples) == 3 and result.annotations == []
    assert all(r["n_boxes"] == 0 for r in result.samples)
    assert load_scene(result.store).boxes.empty


def test_a_variant_without_scene_frames_or_of_another_scene_is_refused(fitted, tmp_path):
    scene, graph = fitted
    resampled = dict(logged_variant(scene), source_frames=None)
    with pytest.raises(OmniscsError, match="resampled"):
        write_annotated_variant(graph, scene, resampled, tmp_path / "v", "x-v000")
    short = dict(logged_variant(scene))
    short["ego"] = short["ego"][:3]
    with pytest.raises(OmniscsError, match="does not cover"):
        write_annotated_variant(graph, scene, short, tmp_path / "v", "x-v000")
    assert not (tmp_path / "v").exists()


# ----------------------------------------------------------------------------- boxes at the edges of the view
def test_a_box_straddling_the_camera_plane_gets_a_finite_rectangle_inside_the_image():
    camera_from_box = make_transform(rotmat_from_euler(yaw=0.3), np.array([1.0, 0.2, 0.1]))
    rect = projected_box(camera_from_box, np.array([4.5, 1.9, 1.6]), K, 96, 54, near=0.5)
    assert rect is not None
    (x1, y1, x2, y2), inside = rect
    assert 0 <= x1 < x2 <= 96 and 0 <= y1 < y2 <= 54 and 0.0 < inside <= 1.0


def test_a_box_wholly_behind_the_camera_or_beside_the_image_has_no_rectangle():
    size = np.array([4.5, 1.9, 1.6])
    assert projected_box(make_transform(np.eye(3), np.array([0.0, 0.0, -10.0])), size, K, 96, 54, 0.5) is None
    assert projected_box(make_transform(np.eye(3), np.array([400.0, 0.0, 10.0])), size, K, 96, 54, 0.5) is None


def test_a_box_ten_kilometres_away_is_finite_and_tiny():
    rect = projected_box(make_transform(np.eye(3), np.array([0.0, 0.0, 10_000.0])), np.array([4.5, 1.9, 1.6]),
                         K, 96, 54, 0.5)
    (x1, y1, x2, y2), inside = rect
    assert np.isfinite([x1, y1, x2, y2]).all() and x2 - x1 < 0.1 and inside == pytest.approx(1.0)


def test_a_box_cut_by_the_image_border_reports_its_in_image_fraction():
    rect = projected_box(make_transform(np.eye(3), np.array([5.0, 0.0, 8.0])), np.array([4.5, 1.9, 1.6]),
                         K, 96, 54, 0.5)
    (x1, _, x2, _), inside = rect
    assert x2 == 96 and 0.0 < inside < 1.0


# ----------------------------------------------------------------------------- commands and visibility levels
def _path(lateral_per_s: float, n: int = 40, speed: float = 8.0) -> np.ndarray:
    t = np.arange(n) * 0.1
    return np.stack([pose_from_xyz_yaw(speed * ti, lateral_per_s * ti ** 2, 0.0, 0.0) for ti in t])


def test_driving_commands_follow_uniads_rule():
    ts = (np.arange(40) * 100_000).astype(np.int64)
    assert set(driving_commands(_path(0.0), ts)) == {COMMANDS.index("forward")}
    assert driving_commands(_path(0.5), ts)[0] == COMMANDS.index("left")   # 4.5 m to the left after 3 s
    assert driving_commands(_path(-0.5), ts)[0] == COMMANDS.index("right")
    assert driving_commands(_path(0.5)[:1], ts[:1])[0] == COMMANDS.index("forward")  # one step: nothing ahead


@pytest.mark.parametrize("fraction, level", [(0.0, 1), (0.39, 1), (0.4, 2), (0.6, 3), (0.8, 4), (1.0, 4)])
def test_visibility_levels_are_nuscenes_bins(fraction, level):
    assert visibility_level(fraction) == level


@pytest.mark.parametrize("field, value", [("frame_every", 0), ("mask_weight", 0.0), ("mask_weight", 1.5),
                                          ("lidar_max_range_m", -1.0), ("fidelity_every", -1),
                                          ("exact_fidelity", "yes")])
def test_bad_annotate_settings_are_one_clear_error(field, value):
    with pytest.raises(OmniscsError, match=field):
        AnnotateConfig(**{field: value})


# ----------------------------------------------------------------------------- the store as a dataset: exports
@pytest.fixture(scope="module")
def exported(annotated, tmp_path_factory):
    from omniscs.export import export_scenes

    root = tmp_path_factory.mktemp("export") / "nuscenes"
    export_scenes([annotated.store], "nuscenes", root, version="v1.0-mini")
    from nuscenes import NuScenes

    return root, NuScenes(version="v1.0-mini", dataroot=str(root), verbose=False)


def test_the_variant_store_describes_its_own_world(annotated):
    store = load_scene(annotated.store)
    world = store.world
    assert world is not None and world.n_frames == store.n_frames
    np.testing.assert_allclose(world.ego_poses, store.world_from_ego_all)
    moved = world.agent(2).poses[-1, :3, 3]
    box = store.boxes[(store.boxes.frame_idx == store.n_frames - 1) & (store.boxes.track_id == 2)].iloc[0]
    np.testing.assert_allclose(moved, [box.cx, box.cy, box.cz], atol=1e-9)


def test_the_nuscenes_export_of_a_variant_loads_with_its_rendered_visibility_and_map(annotated, exported):
    from nuscenes.map_expansion.map_api import NuScenesMap

    from omniscs.export.common import token
    from omniscs.scene.sources.common import load_attributes

    root, nusc = exported
    store = load_scene(annotated.store)
    levels = {(int(f), int(t)): v for f, t, v in load_attributes(store)[["frame_idx", "track_id", "value"]]
              .itertuples(index=False)}
    names = {"1": "v0-40", "2": "v40-60", "3": "v60-80", "4": "v80-100"}
    checked = 0
    for (f, tid), level in levels.items():
        key = token("sample_annotation", store.scene_id, tid, f)
        if key in nusc._token2ind["sample_annotation"]:
            assert names[nusc.get("sample_annotation", key)["visibility_token"]] == level
            checked += 1
    assert checked == len(nusc.sample_annotation) > 0
    nusc_map = NuScenesMap(dataroot=str(root), map_name=nusc.log[0]["location"])
    for pose in nusc.ego_pose:
        x, y = pose["translation"][:2]
        assert nusc_map.record_on_point(x, y, "drivable_area"), (x, y)


def test_the_uniad_export_of_a_variant_has_finite_boxes_and_commands(annotated, tmp_path):
    import pickle

    from omniscs.export import export_scenes

    out = export_scenes([annotated.store], "uniad", tmp_path / "uniad")
    infos = []
    for path in sorted((out / "infos").glob("*.pkl")):
        with open(path, "rb") as f:
            infos += pickle.load(f)["infos"]
    assert infos and all(np.isfinite(i["gt_boxes"]).all() and np.isfinite(i["can_bus"]).all() for i in infos)
    assert sum(len(i["gt_boxes"]) for i in infos) > 0


def test_the_exported_variant_reads_back_into_a_scene_store(annotated, exported, tmp_path):
    from omniscs.scene.sources import DatasetSource, read_dataset_scene
    from tests.dataset_fixtures import box_errors, match_tracks, pose_error

    root, nusc = exported
    original = load_scene(annotated.store)
    read = load_scene(read_dataset_scene(DatasetSource("nuscenes", str(root)), tmp_path / "back"))
    keyframes = [0, 5]
    frame_map = {j: f for j, f in enumerate(keyframes)}
    assert read.n_frames == len(keyframes) and pose_error(original, read, frame_map) < 1e-9
    expected = original.boxes[original.boxes.frame_idx.isin(keyframes)]
    assert len(read.boxes) == len(expected) > 0
    err = box_errors(original.boxes, read.boxes, frame_map, match_tracks(original.boxes, read.boxes, frame_map))
    assert max(err.values()) < 1e-9, err


def test_a_car_moved_behind_the_ego_gets_lidar_points_from_the_ring_and_none_from_the_front_cameras(fitted, tmp_path):
    """The default 360° LiDAR (a ring of depth renders at the mount) returns from a box behind the ego that no
    dataset camera sees; sampling the cameras' depth alone (``lidar_source`` cameras) leaves it without points."""
    scene, graph = fitted
    variant = logged_variant(scene)
    ego = scene.world_from_ego_all
    variant["agents"]["1"] = [[float(ego[f, 0, 3] - 9.0), 0.0, 0.0] for f in range(scene.n_frames)]
    counts = {}
    for source in ("ring", "cameras"):
        out = write_annotated_variant(graph, scene, variant, tmp_path / source, "nsg-test-v000",
                                      config=AnnotateConfig(lidar_source=source, fidelity_every=0))
        store = load_scene(out.store)
        counts[source] = store.boxes[store.boxes.track_id == 1].num_lidar_points.to_numpy()
        points = np.concatenate([store.lidar(t) for t in range(store.n_frames)])
        assert np.isfinite(points).all() and out.summary["lidar_seconds"] > 0
        np.testing.assert_allclose(np.asarray(store.manifest["ego_from_lidar"]).reshape(4, 4),
                                   scene.world.lidar.ego_from_lidar)
    assert (counts["ring"] >= 20).all() and (counts["cameras"] == 0).all()


def test_a_procedural_variant_gets_the_exact_sweep_of_its_own_world(fitted, tmp_path):
    """With ``lidar`` (procedural scenes, lidar_source world) a variant's LiDAR is its world ray-cast with the
    variant's edits: a car moved behind the ego returns points where its new box is, none where it stood."""
    from omniscs.annotate.frames import variant_frames
    from omniscs.world import WorldRenderer

    scene, graph = fitted
    variant = logged_variant(scene)
    ego = scene.world_from_ego_all
    variant["agents"]["1"] = [[float(ego[f, 0, 3] - 9.0), 0.0, 0.0] for f in range(scene.n_frames)]
    out = write_annotated_variant(graph, scene, variant, tmp_path / "w", "nsg-test-v000", lidar=world_lidar(scene),
                                  config=AnnotateConfig(fidelity_every=0))
    assert out.summary["lidar_source"] == "world"
    store = load_scene(out.store)
    vf = variant_frames(scene, variant, frozenset(graph.agent_ids), None, AnnotateConfig())
    exact = WorldRenderer(variant_world(scene.world, vf))
    for t in (0, store.n_frames - 1):
        np.testing.assert_array_equal(store.lidar(t), exact.lidar_scan(int(vf.scene_frames[t])))
    moved = store.boxes[store.boxes.track_id == 1].num_lidar_points.to_numpy()
    assert (moved >= 20).all()
    logged = WorldRenderer(scene.world).lidar_scan(int(vf.scene_frames[0]))  # the unedited world: car ahead
    assert not np.array_equal(logged, store.lidar(0))


def test_stray_background_gaussians_at_the_lidar_are_cleared_for_it_and_agents_never_are(fitted):
    """A blob of background Gaussians around the sensor would fill every ring view at a few decimetres: the ring
    leaves out background Gaussians within the clearance; agent nodes beside the sensor stay."""
    from omniscs.annotate.lidar import ring_views
    from omniscs.annotate.views import ViewAnnotator
    from omniscs.gaussians import concat_params, params_from_values
    from omniscs.nsg.observations import View

    scene, graph = fitted
    f = 3
    world_from_lidar = scene.world_from_ego_all[f] @ np.asarray(scene.world.lidar.ego_from_lidar)
    rng = np.random.default_rng(0)
    blob = params_from_values(torch.from_numpy(world_from_lidar[:3, 3] + rng.normal(0, 0.3, (200, 3))).float(),
                              torch.full((200, 3), 0.2), torch.full((200,), 0.9), torch.full((200, 3), 0.5),
                              graph.sh_degree)
    cluttered = dataclasses.replace(graph, background=concat_params([graph.background,
                                                                     blob.to(graph.background.device)]))
    annotator = ViewAnnotator(cluttered, AnnotateConfig())
    ahead = ring_views(AnnotateConfig())[0]
    view = View(f, world_from_lidar @ ahead.lidar_from_view, ahead.K, ahead.width, ahead.height)
    blocked = annotator.depth(view, {})
    cleared = annotator.depth(view, {}, background_clearance_m=3.0)
    assert np.median(blocked[blocked > 0]) < 1.0 < np.median(cleared[cleared > 0])
    # the car ahead (an agent node 11 m on) is in the cleared view at its range
    box = scene.boxes[(scene.boxes.frame_idx == f) & (scene.boxes.track_id == 1)].iloc[0]
    ahead_m = float(np.linalg.norm(np.array([box.cx, box.cy]) - world_from_lidar[:2, 3]))
    centre = cleared[:, ahead.width // 2]
    assert np.any(np.abs(centre - (ahead_m - 0.5 * box.length)) < 1.0)


def test_lidar_points_per_box_match_a_count_over_every_point():
    from omniscs.annotate.lidar import points_in_boxes
    from omniscs.geometry import invert_transform, make_transform, transform_points

    rng = np.random.default_rng(4)
    points = np.zeros((5000, 4), np.float32)
    points[:, :3] = rng.uniform([-30, -30, -2], [30, 30, 4], (5000, 3))
    boxes, sizes = [], []
    for _ in range(12):
        yaw = rng.uniform(-np.pi, np.pi)
        R = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
        boxes.append(make_transform(R, rng.uniform([-25, -25, 0], [25, 25, 1])))
        sizes.append(rng.uniform([2, 1, 1], [12, 3, 4]))
    boxes, sizes = np.stack(boxes), np.stack(sizes)
    brute = [int(np.all(np.abs(transform_points(invert_transform(T), points[:, :3].astype(np.float64)))
                        <= 0.5 * s, axis=1).sum()) for T, s in zip(boxes, sizes)]
    assert points_in_boxes(points, boxes, sizes).tolist() == brute and sum(brute) > 0
    grown = [int(np.all(np.abs(transform_points(invert_transform(T), points[:, :3].astype(np.float64)))
                        <= 0.5 * s + 0.3, axis=1).sum()) for T, s in zip(boxes, sizes)]
    assert points_in_boxes(points, boxes, sizes, margin=0.3).tolist() == grown and sum(grown) > sum(brute)
    assert points_in_boxes(np.zeros((0, 4), np.float32), boxes, sizes).tolist() == [0] * 12


def test_a_replay_holds_the_unedited_render_of_every_logged_view_and_annotations_are_the_same_with_it(
        fitted, annotated, tmp_path):
    from omniscs.annotate.replay import Replay
    from omniscs.annotate.scene import replay_scene
    from omniscs.annotate.views import ViewAnnotator

    scene, graph = fitted
    info = replay_scene(graph, scene, tmp_path / "replay")
    replay = Replay.open(tmp_path / "replay")
    assert info["n_views"] == len(replay) == scene.n_frames * len(scene.camera_names)
    annotator = ViewAnnotator(graph)
    for cam in scene.camera_names:
        for f in (0, scene.n_frames - 1):
            rgb, logged_psnr = replay.view(cam, f)
            _, rendered, want = annotator.unedited(cam, f, lambda c=cam, t=f: scene.image(c, t))
            np.testing.assert_array_equal(rgb, rendered)
            assert logged_psnr == pytest.approx(want, abs=1e-9) and 10.0 < logged_psnr < 100.0
    variant = logged_variant(scene, shift={2: 0.15})
    again = write_annotated_variant(graph, scene, variant, tmp_path / "store", "nsg-test-v000",
                                    reference=world_reference(scene), describe=world_description(scene),
                                    annotator=ViewAnnotator(graph, replay=replay))
    for key in ("feature_drift", "logged_psnr", "fidelity_psnr", "mask_pixels"):
        assert [r.get(key) for r in again.samples] == pytest.approx([r.get(key) for r in annotated.samples])


def test_a_damaged_replay_is_a_clear_error(fitted, tmp_path):
    from omniscs.annotate.replay import Replay
    from omniscs.annotate.scene import replay_scene
    from omniscs.annotate.views import ViewAnnotator
    from omniscs.errors import ValidationError

    scene, graph = fitted
    with pytest.raises(ValidationError, match="not a readable replay"):
        Replay.open(tmp_path / "nothing")
    replay_scene(graph, scene, tmp_path / "replay")
    cam = scene.camera_names[0]
    (tmp_path / "replay" / "images" / cam / "000001.png").unlink()
    replay = Replay.open(tmp_path / "replay")
    with pytest.raises(ValidationError, match="missing or unreadable"):
        ViewAnnotator(graph, replay=replay).unedited(cam, 1)
    with pytest.raises(OmniscsError, match="no view"):
        replay.view(cam, 10_000)
