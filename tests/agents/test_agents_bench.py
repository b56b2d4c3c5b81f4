"""``bench agents``' report: Table 4's summary, the targets and the Markdown, from hand-made rows; matching ranks
queries against a pool."""
import numpy as np

from omniscs.bench.agents import ARMS, MATCH_LEVELS, TABLE4_EDITS, _targets, agents_markdown, run_matching, table4_summary


def _rows():
    rows = []
    for name, _ in TABLE4_EDITS:
        for arm, psnr in zip(ARMS, (15.0, 18.5, 17.0, 18.5, 19.0)):
            for track, shift in ((1, -0.5), (2, 0.5)):
                rows.append({"scene_id": "s", "track_id": track, "edit": name, "arm": arm, "n_views": 3,
                             "masked_psnr": psnr + shift, "masked_ssim": 0.5})
    rows.append({"scene_id": "s", "track_id": 3, "edit": "rotate 90°", "arm": "naive", "n_views": 0,
                 "masked_psnr": None, "masked_ssim": None})  # no view shows it: left out, not a zero
    return rows


def test_the_summary_and_targets_follow_the_rows():
    summary = table4_summary(_rows())
    cell = next(s for s in summary if s["edit"] == "rotate 90°" and s["arm"] == "dual")
    assert cell["agents"] == 2 and cell["masked_psnr"] == 18.5
    naive = next(s for s in summary if s["edit"] == "rotate 90°" and s["arm"] == "naive")
    assert naive["agents"] == 2 and naive["masked_psnr"] == 15.0
    matching = [{"embedder": "e", "cue": "appearance", "level": lv, "top1": 0.5, "top5": 0.9, "queries": 4}
                for lv, _ in MATCH_LEVELS]
    targets = _targets(matching, summary, [{"seconds": 2.0}, {"seconds": 4.0}])
    assert targets["dual_gain_db"]["gains"] == {"rotate 90°": 3.5, "rotate 180°": 3.5, "rotate 270°": 3.5}
    assert targets["dual_gain_db"]["met"] and not targets["matching_top1_at_target_level"]["met"]
    assert targets["build_seconds"]["median"] == 3.0 and targets["build_seconds"]["met"]
    report = {"machine": {"cpus": 2, "platform": "x", "load_average_start": [1.0, 1, 1],
                          "load_average_end": [2.0, 2, 2]},
              "config": {"preset": "fast", "scenes": ["straight:1"]}, "targets": targets, "table4": summary,
              "matching": matching, "decisions": [],
              "pool": {"size": 3, "by_category": {"car": 3}, "quality_db_median": 18.0,
                       "build_seconds_per_model": [2.0, 4.0], "growth": []}}
    text = agents_markdown(report)
    assert "| rotate 90° | 15.00 / 0.500 | 18.50 / 0.500 | 17.00 / 0.500 | 18.50 / 0.500 | 19.00 / 0.500 |" in text
    assert "goal 3 dB each: met" in text and "goal 95 %: NOT met" in text


def test_matching_ranks_keyframe_queries_first_within_their_category(tmp_path):
    from omniscs.agents.matching import ColourHistogram, crop_square
    from omniscs.agents.mesh import model_from_mesh
    from omniscs.agents.pool import Pool
    from omniscs.world.assets import build_asset

    pool = Pool(tmp_path / "pool")
    for aid in ("sedan-0050", "suv-0040", "bus-0013"):
        a = build_asset(aid)
        params, _ = model_from_mesh(a.surface.vertices, a.surface.faces, a.surface.face_colour, 1000, 0)
        pool.add(params, a.category, "mesh", aid)
    table = pool.table()
    queries = []
    for m in table.itertuples():
        k = pool.keyframes(m.model_id)[7]
        queries.append((crop_square(np.ascontiguousarray(k[..., :3]), k[..., 3] / 255.0), m.category, m.model_id,
                        np.array([m.length, m.width, m.height])))
    rows = run_matching(queries, pool, [ColourHistogram()])
    assert len(rows) == 2 * len(MATCH_LEVELS)
    clean = [r for r in rows if r["level"] == "clean"]
    assert all(r["top1"] == 1.0 and r["top5"] == 1.0 for r in clean)
    assert all(0.0 <= r["top1"] <= r["top5"] <= 1.0 for r in rows)
