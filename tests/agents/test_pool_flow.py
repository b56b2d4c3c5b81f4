"""The build_pool flow: assets into a pool, catalogued (who added what); a rerun adds nothing new."""
from __future__ import annotations

import pytest

from omniscs import catalog


@pytest.mark.slow  # 11 s of pool building: make test's five minutes
def test_build_pool_catalogues_every_model_and_a_rerun_adds_nothing_new(prefect_harness, tmp_path):
    from flows.pool import build_pool

    ws, pool = tmp_path / "ws", tmp_path / "pool"
    first = build_pool(["sedan-0002", "barrier-0001"], str(pool), workspace=str(ws), run_id="pool1", gaussians=1500,
                       refine_steps=3)
    second = build_pool(["sedan-0002"], str(pool), workspace=str(ws), run_id="pool2", gaussians=1500, refine_steps=3)
    assert len(first["model_ids"]) == 2 and second["model_ids"][0] == first["model_ids"][0]
    rows = catalog.query(catalog.catalog_root(ws), "SELECT run_id, model_id, category, source, new FROM pool_by_run "
                                                   "ORDER BY run_id, source").to_pylist()
    assert [(r["run_id"], r["source"], r["new"]) for r in rows] == [("pool1", "barrier-0001", True),
                                                                  ("pool1", "sedan-0002", True),
                                                                  ("pool2", "sedan-0002", False)]
    assert {r["category"] for r in rows} == {"car", "barrier"}
    runs = catalog.query(catalog.catalog_root(ws), "SELECT flow, status FROM runs ORDER BY run_id").to_pylist()
    assert runs == [{"flow": "build_pool", "status": "completed"}] * 2
