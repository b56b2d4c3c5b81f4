"""Relit agent nodes on CUDA (run by infra/gpu_check/run.sh on a GPU machine): the checks of the CUDA case of
tests/nsg/test_relight.py (relit colours through gsplat at each frame's pose and after a turn, against the colours
baked by hand and against the CPU render; the light fitted back through gsplat; the dual strategy's colour
correction and refinement on CUDA) on the carried tiny scene, since
that machine lacks the world's packages that the test's own fixture needs."""
from __future__ import annotations

import json
import os
from pathlib import Path

from omniscs.scene import load_scene
from tests.nsg.test_relight import relit_graph, relit_node_checks

SCENES = Path(os.environ.get("GPU_CHECK_SCENES", ".gpu_check"))

if __name__ == "__main__":
    print("relit node on CUDA:", json.dumps(relit_node_checks(relit_graph(load_scene(SCENES / "scene_small")), "cuda")),
          flush=True)
