"""Holes (per-pixel ray-box test, crops, RoI) and DRNet (the paper's table, training, divergence, the least-squares
baseline), on hand-made cases with known answers and at the extremes."""
import numpy as np
import pytest
import torch
from torch import nn

from omniscs.background.drnet import (DRNet, DRNetConfig, DRNetDiverged, SpatialAttention, aligned_inverse,
                                      least_squares_depth, train_drnet)
from omniscs.background.holes import RemovedObject, box_entry_distance, crop_view, hole_bbox, hole_mask, roi_size
from omniscs.errors import OmniscsError
from omniscs.geometry import points_in_box
from omniscs.nsg.observations import View, project_points

K = np.array([[50.0, 0, 40.0], [0, 50.0, 30.0], [0, 0, 1.0]])
# an OpenCV camera at the origin looking along world +x (x right = world -y, y down = world -z)
CAM = np.array([[0.0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1]])


def _view(world_from_camera=CAM, w=80, h=60):
    return View(0, world_from_camera, K.copy(), w, h, "CAM_FRONT")


def _box(x, y=0.0, z=0.0, size=(2.0, 2.0, 2.0), frames=1):
    pose = np.eye(4)
    pose[:3, 3] = (x, y, z)
    return RemovedObject(7, np.array(size), np.repeat(pose[None], frames, 0), np.ones(frames, bool))


def test_the_hole_of_a_box_straight_ahead_is_its_projection_and_the_entry_depth_its_near_face():
    view = _view()
    obj = _box(10.0)  # near face at x = 9, 2 m square: +-1 m -> +-50/9 px about the centre
    mask = hole_mask(view, [obj], 0)
    assert mask[30, 40] and not mask[0, 0] and not mask[59, 79]
    ys, xs = np.nonzero(mask)
    assert 40 - 50 / 9 - 1 <= xs.min() <= 40 - 50 / 9 + 1 and 40 + 50 / 9 - 1 <= xs.max() <= 40 + 50 / 9 + 1
    entry = box_entry_distance(view, obj.pose(0), obj.size)
    assert entry[30, 40] == pytest.approx(9.0, abs=1e-6) and np.isinf(entry[0, 0])
    assert hole_mask(view, [obj], 3).sum() > mask.sum()  # dilation grows it


def test_boxes_behind_the_camera_around_it_and_cut_by_the_border():
    view = _view()
    assert not hole_mask(view, [_box(-10.0)], 0).any()  # behind
    inside = box_entry_distance(view, _box(0.0, size=(4, 4, 4)).pose(0), np.array([4.0, 4, 4]))
    assert np.all(inside == 0.0)  # the camera is in the box: every ray starts in it
    cut = hole_mask(view, [_box(6.0, y=-3.0, size=(4, 4, 4))], 0)  # off to the right, past the border
    assert cut.any() and cut[:, -1].any() and not cut[:, 0].any()
    far = hole_mask(view, [_box(10_000.0, size=(600, 600, 600))], 0)  # 10 km away, 3 px wide
    assert 0 < far.sum() < 30


def test_an_absent_object_and_bad_boxes():
    obj = _box(10.0, frames=2)
    absent = RemovedObject(7, obj.size, obj.world_from_box, np.array([False, True]))
    assert not hole_mask(_view(), [absent], 2).any()
    with pytest.raises(OmniscsError, match="positive"):
        RemovedObject(1, np.array([1.0, 0.0, 1.0]), obj.world_from_box, obj.present)
    with pytest.raises(OmniscsError, match="finite"):
        RemovedObject(1, obj.size, np.full((2, 4, 4), np.nan), obj.present)
    with pytest.raises(OmniscsError, match="no frame"):
        RemovedObject(1, obj.size, obj.world_from_box, np.zeros(2, bool)).roi()


def test_roi_box_is_larger_and_contains_the_box_and_a_margin():
    obj = _box(10.0, size=(8.0, 2.5, 3.5))
    pose, size = obj.roi()
    assert np.all(size > obj.size + 1.9) and np.array_equal(size, roi_size(obj.size))
    pts = np.array([[10.0, 0, 0], [14.5, 0, 0], [18.0, 0, 0], [10.0, 2.5, 0]])
    assert points_in_box(pts, pose, size).tolist() == [True, True, False, True]
    assert points_in_box(pts, pose, obj.size).tolist() == [True, False, False, False]


def test_a_crop_is_the_same_camera_with_its_principal_point_moved():
    view = _view()
    pts = np.array([[10.0, 1.0, 0.5], [20.0, -2.0, 1.0]])
    uv, _, _ = project_points(view, pts)
    crop = crop_view(view, (10, 5, 70, 50))
    uv2, _, _ = project_points(crop, pts)
    assert np.allclose(uv - uv2, [10, 5]) and (crop.width, crop.height) == (60, 45)
    assert hole_bbox(np.zeros((4, 4), bool), 2) is None
    m = np.zeros((10, 10), bool)
    m[4, 5] = True
    assert hole_bbox(m, 2) == (3, 2, 8, 7)
    with pytest.raises(OmniscsError):
        crop_view(view, (0, 0, 100, 10))


def test_drnet_is_the_papers_table():
    net = DRNet()
    convs = [m for m in net.body.modules() if isinstance(m, nn.Conv2d)]
    attention = [m for m in net.modules() if isinstance(m, SpatialAttention)]
    assert [(c.kernel_size[0], c.out_channels) for c in convs] == [(3, 32), (3, 64), (7, 1), (3, 32), (3, 1)]
    assert len(attention) == 1 and attention[0].conv.in_channels == 2  # channel mean and max
    assert sum(isinstance(m, nn.BatchNorm2d) for m in net.modules()) == 3
    assert sum(isinstance(m, nn.LeakyReLU) for m in net.modules()) == 3
    assert net(torch.zeros(2, 1, 9, 13)).shape == (2, 1, 9, 13)


def _smooth_scene(seed, n=6, h=40, w=60):
    rng = np.random.default_rng(seed)
    import cv2
    out = []
    for _ in range(n):
        d = cv2.resize(rng.uniform(2.0, 30.0, (4, 6)), (w, h), interpolation=cv2.INTER_CUBIC).clip(1.5, 35.0)
        out.append(d.astype(np.float32))
    return out


@pytest.mark.slow
def test_drnet_learns_a_scene_mapping_and_refines_a_biased_alignment():
    depths = _smooth_scene(0)
    # the relative depth is a monotone but not affine function of inverse depth (here a logarithm): the affine
    # alignment cannot undo it, a per-scene mapping can
    inputs = [(5.0 - np.log(d)).astype(np.float32) for d in depths]
    fitted = train_drnet(inputs, depths, DRNetConfig(steps=200, crop=32))
    err = np.mean([np.mean(np.abs(fitted.predict(x) - d) / d) for x, d in zip(inputs, depths)])
    lsq = np.mean([np.mean(np.abs(least_squares_depth(x, d) - d) / d) for x, d in zip(inputs, depths)])
    assert err < 0.6 * lsq and err < 0.1
    assert all(np.all(np.isfinite(fitted.predict(x))) for x in inputs)


def test_drnet_refuses_no_targets_bad_inputs_and_reports_divergence():
    depths = _smooth_scene(1, n=2)
    nothing = [np.full_like(d, np.nan) for d in depths]
    with pytest.raises(OmniscsError, match="no pixel outside the hole has a depth"):
        train_drnet([1.0 / d for d in depths], nothing)
    with pytest.raises(OmniscsError, match="finite"):
        train_drnet([np.full_like(d, np.nan) for d in depths], depths)
    with pytest.raises(DRNetDiverged):
        train_drnet([1.0 / d for d in depths], depths, DRNetConfig(steps=80, lr=1e6, crop=16))


def test_least_squares_alignment_recovers_an_affine_inverse_depth_and_stays_finite():
    depth = _smooth_scene(2, n=1)[0]
    rel = 3.0 / depth + 0.7  # relative = affine map of inverse depth
    target = depth.copy()
    target[::2] = np.nan  # sparse targets
    assert np.allclose(least_squares_depth(rel, target), depth, rtol=1e-4)
    flat = least_squares_depth(np.full_like(depth, 5.0), target)  # no information: finite, clamped
    assert np.all(np.isfinite(flat)) and np.all(flat > 0)
    wild = least_squares_depth(np.where(np.arange(depth.size).reshape(depth.shape) % 7 == 0, np.inf, rel), target)
    assert np.all(np.isfinite(wild))
    assert np.all(aligned_inverse(-rel, target) >= 0)
    with pytest.raises(OmniscsError, match="no pixel"):
        least_squares_depth(rel, np.full_like(depth, np.nan))
