"""The simulated 360° LiDAR of rendered variants: its beams cover every azimuth, a box behind the ego gets points,
each return lies at the depth it was looked up in, and empty, far or broken depth gives no point and no NaN."""
from __future__ import annotations

import numpy as np
import pytest

from omniscs.annotate import AnnotateConfig
from omniscs.annotate.lidar import (beam_directions, lidar_from_views, points_in_boxes, ring_views)
from omniscs.errors import OmniscsError
from omniscs.geometry import make_transform, pose_from_xyz_yaw, rotmat_from_euler

#: A nuScenes-like mount: 0.94 m ahead of the ego origin, 1.84 m up.
MOUNT = make_transform(np.eye(3), [0.94, 0.0, 1.84])


def _pixel_rays(view) -> np.ndarray:  # -> [H, W, 3] rays through the pixel centres, z = 1, view frame
    u, v = np.meshgrid(np.arange(view.width) + 0.5, np.arange(view.height) + 0.5)
    return np.stack([(u - view.K[0, 2]) / view.K[0, 0], (v - view.K[1, 2]) / view.K[1, 1], np.ones_like(u)], -1)


def _ring_depth(config: AnnotateConfig, surfaces) -> list:
    """Depth of every ring view ray-traced against ``surfaces`` (callables: rays [M, 3] + origin [3], LiDAR frame ->
    distance t along the ray, inf where missed), as (depth, K, lidar_from_view) the way the renderer would give it."""
    views = []
    for r in ring_views(config):
        rays = _pixel_rays(r).reshape(-1, 3)
        d_lidar = rays @ r.lidar_from_view[:3, :3].T  # z = 1 in the view: t along it is the depth
        t = np.full(len(rays), np.inf)
        for surface in surfaces:
            t = np.minimum(t, surface(d_lidar))
        depth = np.where(np.isfinite(t), t, 0.0).reshape(r.height, r.width).astype(np.float32)
        views.append((depth, r.K, r.lidar_from_view))
    return views


def _plane(normal, offset):
    """The plane n . x = offset (LiDAR frame), hit from the origin where the ray meets it ahead."""
    n = np.asarray(normal, dtype=np.float64)

    def hit(d):
        dn = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = offset / dn
        return np.where((dn != 0) & (t > 0), t, np.inf)
    return hit


def _box(centre, size):
    """An axis-aligned box (LiDAR frame), hit by the slab test from the origin."""
    lo = np.asarray(centre) - 0.5 * np.asarray(size)
    hi = np.asarray(centre) + 0.5 * np.asarray(size)

    def hit(d):
        with np.errstate(divide="ignore", invalid="ignore"):
            a, b = lo / d, hi / d
        near = np.nanmax(np.minimum(a, b), 1)
        far = np.nanmin(np.maximum(a, b), 1)
        return np.where((far >= near) & (near > 0), near, np.inf)
    return hit


def test_the_beams_are_nuscenes_like_and_cover_every_azimuth():
    config = AnnotateConfig()
    d = beam_directions(config)
    elevation = np.degrees(np.arcsin(d[:, 2]))
    assert np.isclose(elevation.max(), 10.67) and np.isclose(elevation.min(), -30.67)
    assert len(np.unique(np.round(elevation, 6))) == 32
    azimuth = np.degrees(np.arctan2(d[:, 1], d[:, 0]))
    gaps = np.diff(np.sort(np.unique(np.round(azimuth, 6))))
    assert gaps.max() < 0.34 and np.isclose(np.linalg.norm(d, axis=1), 1.0).all()


def test_every_beam_lands_in_a_ring_view():
    """With a sphere all round, every beam returns (no gap between the views, none above or below them)."""
    for config in (AnnotateConfig(), AnnotateConfig(lidar_ring_views=3, lidar_ring_pixel_deg=1.0),
                   AnnotateConfig(lidar_ring_views=8, lidar_min_elevation_deg=-60.0, lidar_max_elevation_deg=-5.0)):
        views = []
        for r in ring_views(config):
            depth = 15.0 / np.linalg.norm(_pixel_rays(r), axis=-1)  # a sphere of 15 m
            views.append((depth.astype(np.float32), r.K, r.lidar_from_view))
        points = lidar_from_views(views, beam_directions(config), np.eye(4), 70.0)
        assert len(points) == len(beam_directions(config))
        # A beam takes the depth of the pixel it crosses, whose centre ray is off the beam by at most half the
        # pixel's diagonal (under its size at the view's centre): range = 15 cos(pixel ray) / cos(beam), off by at
        # most tan(angle off the axis) times that angle.
        off_axis = max(float(np.linalg.norm(_pixel_rays(r)[[0, 0, -1, -1], [0, -1, 0, -1], :2], axis=-1).max())
                       for r in ring_views(config))
        tolerance = 15.0 * off_axis * np.radians(config.lidar_ring_pixel_deg) * np.sqrt(0.5) + 1e-4
        np.testing.assert_allclose(np.linalg.norm(points[:, :3], axis=1), 15.0, atol=tolerance)


def test_a_wall_gives_points_at_its_known_range_in_every_direction():
    """Four walls 20 m around the LiDAR (a square room): every return lies on a wall, the ones behind the ego
    included, at the range the depth gave (exact: depth on a wall facing a view is the same in all its pixels)."""
    config = AnnotateConfig(lidar_ring_views=4)
    walls = [_plane([1, 0, 0], 20.0), _plane([-1, 0, 0], 20.0), _plane([0, 1, 0], 20.0), _plane([0, -1, 0], 20.0)]
    points = lidar_from_views(_ring_depth(config, walls), beam_directions(config), MOUNT, 70.0)
    lidar = points[:, :3].astype(np.float64) - MOUNT[:3, 3]
    assert np.isfinite(points).all() and points.dtype == np.float32 and points.shape[1] == 4
    assert np.allclose(np.abs(lidar[:, :2]).max(1), 20.0, atol=1e-3)
    assert (lidar[:, 0] < -19.9).sum() > 1_000  # behind the ego
    assert (points[:, 3] == 0).all()


def test_a_rotated_mount_puts_the_points_in_the_ego_frame():
    """nuScenes' LIDAR_TOP has its x axis to the ego's right: the same wall ahead of the ego lands ahead of it."""
    mount = make_transform(rotmat_from_euler(yaw=-np.pi / 2), [0.94, 0.0, 1.84])
    config = AnnotateConfig(lidar_ring_views=4)  # a view faces the wall: its depth is exact in every pixel
    # a room in the LiDAR frame, its wall on the LiDAR's +y (the ego's +x) nearer than the others
    room = [_plane([0, 1, 0], 12.0), _plane([0, -1, 0], 30.0), _plane([1, 0, 0], 30.0), _plane([-1, 0, 0], 30.0)]
    points = lidar_from_views(_ring_depth(config, room), beam_directions(config), mount, 70.0)
    azimuth = np.degrees(np.arctan2(points[:, 1], points[:, 0] - 0.94))  # about the mount, ego frame
    ahead, behind = np.abs(azimuth) < 30.0, np.abs(azimuth) > 150.0  # beams the views facing those walls answer
    assert ahead.sum() > 1_000 and np.allclose(points[ahead, 0], 0.94 + 12.0, atol=1e-3)
    assert behind.sum() > 1_000 and np.allclose(points[behind, 0], 0.94 - 30.0, atol=1e-3)


def test_a_box_behind_the_ego_gets_points():
    config = AnnotateConfig()
    ground = _plane([0, 0, -1], 1.84)  # the road, 1.84 m below the LiDAR
    car_behind = _box([-12.0, 0.0, -1.84 + 0.75], [4.5, 1.9, 1.5])  # LiDAR frame, on the road behind
    points = lidar_from_views(_ring_depth(config, [ground, car_behind]), beam_directions(config), MOUNT,
                              70.0)
    ego_from_box = pose_from_xyz_yaw(0.94 - 12.0, 0.0, 0.75, 0.0)
    count = int(points_in_boxes(points, ego_from_box[None], np.array([[4.5, 1.9, 1.5]]))[0])
    assert count >= 50
    # the road all round; a beam takes the depth of the pixel it crosses, so on a surface seen at a slant the
    # return is off by up to what the depth changes within a ring pixel (centimetres; a finer ring, less)
    road = points[np.linalg.norm(points[:, :2] - [-11.06, 0.0], axis=1) > 4.0]
    assert len(road) > 20_000 and np.median(np.abs(road[:, 2])) < 0.02 and np.abs(road[:, 2]).max() < 0.15


def test_returns_beyond_the_range_or_without_a_surface_are_dropped_and_never_nan():
    config = AnnotateConfig()
    beams = beam_directions(config)
    views = ring_views(config)
    empty = [(np.zeros((r.height, r.width), np.float32), r.K, r.lidar_from_view) for r in views]
    far = [(np.full((r.height, r.width), 5_000.0, np.float32), r.K, r.lidar_from_view) for r in views]
    broken = [(np.full((r.height, r.width), v, np.float32), r.K, r.lidar_from_view)
              for r, v in zip(views, [np.nan, np.inf, -np.inf, -3.0, 0.0, np.nan])]
    for depth_views in (empty, far, broken, []):
        points = lidar_from_views(depth_views, beams, MOUNT, config.lidar_max_range_m)
        assert points.shape == (0, 4) and points.dtype == np.float32
    # just inside and just outside the range
    near_edge = [(np.full((r.height, r.width), 69.0, np.float32), r.K, r.lidar_from_view) for r in views]
    points = lidar_from_views(near_edge, beams, np.eye(4), 70.0)
    ranges = np.linalg.norm(points[:, :3], axis=1)
    assert np.isfinite(points).all() and 0 < len(points) < len(beams) and ranges.max() <= 70.0
    assert len(lidar_from_views(near_edge, beams[:0], np.eye(4), 70.0)) == 0
    # the blind range: a surface all round within 0.7 m returns nothing to a sensor blind within 1 m
    close = [(np.full((r.height, r.width), 0.5, np.float32), r.K, r.lidar_from_view) for r in views]
    assert len(lidar_from_views(close, beams, np.eye(4), 70.0, min_range_m=1.0)) == 0
    assert len(lidar_from_views(close, beams, np.eye(4), 70.0)) == len(beams)


def test_a_view_away_from_the_lidar_origin_is_refused():
    r = ring_views(AnnotateConfig())[0]
    moved = r.lidar_from_view.copy()
    moved[0, 3] = 0.5
    with pytest.raises(OmniscsError, match="origin"):
        lidar_from_views([(np.ones((r.height, r.width), np.float32), r.K, moved)],
                         beam_directions(AnnotateConfig()), np.eye(4), 70.0)


def test_a_coarser_ring_renders_fewer_pixels():
    fine = sum(r.width * r.height for r in ring_views(AnnotateConfig()))
    coarse = sum(r.width * r.height for r in ring_views(AnnotateConfig(lidar_ring_pixel_deg=0.66)))
    assert coarse < 0.3 * fine


@pytest.mark.parametrize("field, value", [("lidar_source", "radar"), ("lidar_ring_views", 2),
                                          ("lidar_ring_pixel_deg", 0.0), ("lidar_ring_pixel_deg", 90.0),
                                          ("lidar_min_elevation_deg", 20.0), ("lidar_max_elevation_deg", 95.0),
                                          ("lidar_beams", 0), ("lidar_horizontal_step_deg", 1e-9),
                                          ("lidar_ring_pixel_deg", float("nan")), ("lidar_min_range_m", -1.0),
                                          ("lidar_min_range_m", 70.0), ("lidar_background_clearance_m", 80.0),
                                          ("lidar_depth_alpha", 0.0)])
def test_bad_lidar_settings_are_one_clear_error(field, value):
    with pytest.raises(OmniscsError, match=field):
        AnnotateConfig(**{field: value})
