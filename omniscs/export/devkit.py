"""A compatibility shim for nuscenes-devkit 1.2.0 under numpy 2, so that its own renderers work on any dataroot
(ours or nuScenes'), applied without editing the devkit.

The devkit pins numpy<2 (the project installs it with ``--no-deps`` beside numpy 2). Under numpy 2,
``NuScenesExplorer.render_ego_centric_map`` (the map underlay of ``render_sample_data`` for LIDAR_TOP with
``underlay_map=True``, which ``render_sample`` always asks for) fails with ``TypeError: only 0-dimensional arrays can
be converted to Python scalars``: it takes ``MapMask.to_pixel_coords`` of the ego's position, which answers one-element
arrays, and calls ``int()`` on them (numpy 1.25 deprecated that, numpy 2 refuses it). The tables and map masks the
export writes are as the devkit expects; the shim lets that one call see the ego's map pixel as Python ints, only
while the underlay is drawn, so every other caller of ``to_pixel_coords`` keeps its arrays.

Use it once before rendering::

    from omniscs.export.devkit import patch_nuscenes_devkit
    patch_nuscenes_devkit()
    nusc = NuScenes(version="v1.0-trainval", dataroot=..., verbose=False)
    nusc.render_sample(nusc.sample[0]["token"], out_path="sample.png")
"""
from __future__ import annotations

import functools

#: Marks the devkit's method once it is wrapped (the shim is idempotent).
_PATCHED = "_omniscs_numpy2_shim"


def patch_nuscenes_devkit() -> None:
    """Wrap ``NuScenesExplorer.render_ego_centric_map`` so that its map mask gives the ego's pixel as Python ints
    while the underlay is drawn (see the module docstring); a second call changes nothing. Raises ImportError
    when nuscenes-devkit is not installed."""
    from nuscenes.nuscenes import NuScenesExplorer

    original = NuScenesExplorer.render_ego_centric_map
    if getattr(original, _PATCHED, False):
        return

    @functools.wraps(original)
    def render_ego_centric_map(self, sample_data_token: str, axes_limit: float = 40, ax=None) -> None:
        nusc = self.nusc
        sample = nusc.get("sample", nusc.get("sample_data", sample_data_token)["sample_token"])
        log = nusc.get("log", nusc.get("scene", sample["scene_token"])["log_token"])
        mask = nusc.get("map", log["map_token"])["mask"]  # the object the devkit's method reads
        to_pixel_coords = mask.to_pixel_coords

        def one_pixel(x, y):  # the ego's one position: its pixel as two ints, as numpy 1 let int() take them
            px, py = to_pixel_coords(x, y)
            return (int(px[0]), int(py[0])) if px.size == 1 else (px, py)

        mask.to_pixel_coords = one_pixel  # shadows the method on this object only, for this call
        try:
            return original(self, sample_data_token, axes_limit=axes_limit, ax=ax)
        finally:
            del mask.to_pixel_coords

    setattr(render_ego_centric_map, _PATCHED, True)
    NuScenesExplorer.render_ego_centric_map = render_ego_centric_map
