"""The dataset benchmark (``omniscs bench dataset``) end to end at thumbnail size."""
import numpy as np
import pytest


@pytest.mark.slow
def test_the_dataset_benchmark_runs_end_to_end_at_thumbnail_size(tmp_path):
    from omniscs.bench.dataset import quick_config, run_dataset_benchmark

    result = run_dataset_benchmark(tmp_path / "r", tmp_path / "ws", quick_config())
    for name in ("report.json", "report.md", "report.png"):
        assert (tmp_path / "r" / "dataset" / name).is_file()
    s, scene = result["summary"], result["scenes"][0]
    assert s["variants_per_hour"] > 0 and s["images_per_s_nuscenes_size"] > 0
    assert scene["with fidelity"]["psnr_drift_pairs"] and not scene["without fidelity"]["psnr_drift_pairs"]
    assert all(np.isfinite(v) for pair in scene["with fidelity"]["psnr_drift_pairs"] for v in pair)
    proxies = scene["proxies only"]
    assert all(p is None for p in proxies["fidelity_psnr"]) and all(d is not None for d in proxies["feature_drift"])
    xosc = result["openscenario"]  # the OpenSCENARIO step: every annotated variant exported and checked
    assert (tmp_path / "r" / "dataset" / "openscenario.md").is_file()
    assert xosc["variants"] >= 1 and xosc["files"] >= 2, xosc
    assert xosc["files_passed"] == xosc["files"] and xosc["errors"] == 0, xosc
    assert xosc["round_trip_max_position_m"] is not None and xosc["round_trip_max_position_m"] < 0.01, xosc
