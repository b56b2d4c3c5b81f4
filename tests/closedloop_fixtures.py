"""A fitted scene graph of a 2 s procedural log for the closed-loop tests (ego at 6 m/s, a car 11 m ahead keeping
pace, one overtaking in the next lane), and a behaviour variant of it in which the car ahead stops."""
from __future__ import annotations

from annotate_fixtures import logged_variant

N_FRAMES = 20


def stopping_variant(scene, stop_x: float = 15.3) -> dict:
    """The log, but the car ahead (track 1) brakes to a stop at ``stop_x`` within 0.5 s."""
    v = logged_variant(scene)
    start = float(scene.boxes_at(0).set_index("track_id").loc[1].cx)
    v["agents"]["1"] = [[min(start + 6.0 * 0.1 * k, stop_x), 0.0, 0.0] for k in range(len(v["source_frames"]))]
    v["variant_id"], v["adversary"] = "stop", 1
    return v
