"""The world benchmark (``omniscs bench world``): its report folder holds the JSON, the Markdown and both
pictures, and nothing else lands beside it."""
W, H = 96, 54


def test_benchmark_writes_json_markdown_and_plots(tmp_path):
    import json

    from omniscs.bench.world import run_world_benchmark

    calls = []
    result = run_world_benchmark(tmp_path, seeds=(0,), n_frames=2, n_cameras=1, width=W, height=H,
                                 progress=lambda done, total: calls.append((done, total)))
    assert calls[-1] == (2, 2)
    assert result["asset_count"] >= 200 and result["runs"][0]["total_s"] > 0
    folder = tmp_path / "world"
    assert json.loads((folder / "report.json").read_text())["median_total_s"] == result["median_total_s"]
    assert "| straight | 0 |" in (folder / "report.md").read_text()
    assert (folder / "report.png").stat().st_size > 0
    assert (folder / "preview.png").stat().st_size > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["world"]  # one folder per benchmark, nothing beside it
