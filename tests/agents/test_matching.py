"""Matching framework: degradations do what they say, embedders give unit vectors, ranking and the category-gated
Hungarian assignment give the known answers; on pool keyframes the baselines find clean views of their model."""
from __future__ import annotations

import numpy as np
import pytest

from omniscs.agents.degradation import Degradation, degrade
from omniscs.agents.matching import (ColourHistogram, HOG, RawPixels, assign, crop_square, model_scores,
                                     top_k_accuracy)
from omniscs.errors import ValidationError


def _image(seed=0):
    rng = np.random.default_rng(seed)
    img = (rng.uniform(0, 1, (8, 8, 3)) * 255).astype(np.uint8)
    return np.kron(img, np.ones((8, 8, 1), np.uint8))  # 64 x 64 blocks: sharp edges


def test_degradations_blur_hide_darken_and_keep_the_size():
    img, rng = _image(), np.random.default_rng(0)
    same = degrade(img, Degradation(), rng)
    assert np.array_equal(same, img)
    far = degrade(img, Degradation(downsample=8), rng)
    assert far.shape == img.shape and np.abs(np.diff(far.astype(int), axis=1)).mean() < \
        np.abs(np.diff(img.astype(int), axis=1)).mean()
    dark = degrade(img, Degradation(gain=0.5), rng)
    assert dark.mean() < 0.55 * img.mean()
    hidden = degrade(img, Degradation(occlusion=0.5), rng)
    changed = (hidden != img).any(-1).mean()
    assert 0.4 < changed <= 0.55
    assert degrade(img, Degradation(jpeg=10, noise=10), rng).shape == img.shape
    with pytest.raises(ValidationError):
        Degradation(downsample=0.5)
    with pytest.raises(ValidationError):
        Degradation(occlusion=1.0)


@pytest.mark.parametrize("embedder", [ColourHistogram(), HOG(), RawPixels()])
def test_embedders_give_unit_rows_and_the_same_image_the_same_vector(embedder):
    crops = np.stack([_image(i) for i in range(3)])
    e = embedder.embed(crops)
    assert e.shape[0] == 3 and np.allclose(np.linalg.norm(e, axis=1), 1.0, atol=1e-5)
    assert np.allclose(embedder.embed(crops[:1]), e[:1])


def test_crop_square_takes_the_object_box():
    img = np.zeros((96, 96, 3), np.uint8)
    alpha = np.zeros((96, 96))
    img[40:60, 10:80] = 200
    alpha[40:60, 10:80] = 1.0
    c = crop_square(img, alpha)
    assert c.shape == (64, 64, 3) and c[32, 32].mean() == 200


def test_ranking_and_the_gated_hungarian_assignment():
    scores = np.array([[0.9, 0.8, 0.1], [0.95, 0.2, 0.3], [0.1, 0.2, 0.9]], np.float32)
    models = np.array([10, 11, 12])
    acc = top_k_accuracy(scores, models, np.array([10, 10, 12]), ks=(1, 2))
    assert acc == {1: 1.0, 2: 1.0}
    # greedy would give query 0 model 10 and query 1 model 11 (sum 1.1); Hungarian: 0 -> 11, 1 -> 10 (sum 1.75)
    assert assign(scores, ["car", "car", "bus"], ["car", "car", "bus"]) == [1, 0, 2]
    assert assign(scores, ["car", "car", "truck"], ["car", "car", "bus"])[2] is None  # no truck in the pool
    with pytest.raises(ValidationError):
        assign(scores, ["car"], ["car", "car", "bus"])
    g_scores, g_models = model_scores(np.eye(2, dtype=np.float32), np.eye(2, dtype=np.float32)[[0, 1, 1]],
                                      np.array([5, 6, 6]))
    assert g_models.tolist() == [5, 6] and g_scores.tolist() == [[1.0, 0.0], [0.0, 1.0]]


def test_the_colour_histogram_finds_clean_views_of_pool_models():
    from omniscs.agents.mesh import keyframes, model_from_mesh
    from omniscs.world.assets import build_asset

    gallery, gallery_model, queries, truth = [], [], [], []
    for i, aid in enumerate(["sedan-0001", "sedan-0002", "suv-0001", "van-0001", "box_truck-0001", "bus-0001"]):
        a = build_asset(aid)
        s = a.surface
        params, _ = model_from_mesh(s.vertices, s.faces, s.face_colour, 2000, 0)
        k = keyframes(params, a.size)
        for j in range(30):
            crop = crop_square(k[j, ..., :3], k[j, ..., 3] / 255.0)
            (gallery if j % 2 == 0 else queries).append(crop)
            (gallery_model if j % 2 == 0 else truth).append(i)
    e = ColourHistogram()
    scores, models = model_scores(e.embed(np.stack(queries)), e.embed(np.stack(gallery)), np.array(gallery_model))
    assert top_k_accuracy(scores, models, np.array(truth))[1] >= 0.8


def test_crop_scale_says_how_small_the_crop_sees_the_object():
    from omniscs.agents.matching import crop_scale

    img = np.zeros((200, 200, 3), np.uint8)
    alpha = np.zeros((200, 200))
    alpha[50:62, 20:48] = 1.0  # 28 x 12 pixels: the square is 27 + 4 = 31 pixels
    assert crop_scale(img, alpha) == pytest.approx(64 / 31)
    alpha[:] = 0.0
    alpha[10:190, 10:150] = 1.0  # larger than the crop: seen sharp
    assert crop_scale(img, alpha) == 1.0
    assert crop_scale(img[:16, :32]) == pytest.approx(2.0)  # no mask: the whole image
    assert crop_scale(img, np.zeros((200, 200))) == 1.0  # an empty mask: the whole image (200 px)


def test_gallery_scale_takes_the_nearest_octave_and_stays_finite():
    from omniscs.agents.matching import GALLERY_SCALES, gallery_scale

    assert [gallery_scale(s) for s in (1.0, 1.3, 1.5, 2.9, 3.0, 5.0, 6.0, 100.0)] == \
        [1.0, 1.0, 2.0, 4.0, 4.0, 4.0, 8.0, 8.0]
    assert all(gallery_scale(s) == 1.0 for s in (0.0, 0.5, -3.0, float("nan"), float("-inf")))
    assert gallery_scale(float("inf")) == 1.0 and max(GALLERY_SCALES) == 8.0


def test_a_query_seen_small_is_compared_with_keyframes_as_small(tmp_path):
    """The gallery at x4 holds each keyframe downsampled 4 times: a keyframe degraded so is its own best match
    there (similarity 1), and match_scores with that scale gives it the same score it gets against that gallery."""
    from omniscs.agents.matching import best_per_model, match_scores, pool_gallery
    from omniscs.agents.mesh import model_from_mesh
    from omniscs.agents.pool import Pool
    from omniscs.world.assets import build_asset

    pool = Pool(tmp_path / "pool")
    for aid in ("sedan-0050", "sedan-0051"):
        a = build_asset(aid)
        params, _ = model_from_mesh(a.surface.vertices, a.surface.faces, a.surface.face_colour, 1000, 0)
        pool.add(params, a.category, "mesh", aid)
    table = pool.table().sort_values("model_id")
    e = ColourHistogram()
    full, owner, _ = pool_gallery(pool, e)
    small, owner4, _ = pool_gallery(pool, e, 4.0)
    assert small.shape == full.shape and list(owner4) == list(owner) and not np.allclose(small, full)
    names = sorted(p.name for p in (pool.root / "embeddings").iterdir())  # cached apart
    assert len(names) == 2 and names[0] == names[1].replace(".npz", "-x4.npz")
    assert np.array_equal(pool_gallery(pool, e, 4.0)[0], small)  # read back from the cache
    with pytest.raises(ValidationError):
        pool_gallery(pool, e, 3.0)
    mid = table.model_id.iloc[0]
    k = pool.keyframes(mid)[5]
    query = degrade(crop_square(np.ascontiguousarray(k[..., :3]), k[..., 3] / 255.0), Degradation(downsample=4),
                    np.random.default_rng(0))[None]
    cols = np.searchsorted(np.array(sorted(table.model_id)), owner.astype(str))
    at_small = best_per_model(e.embed(query), small, cols, 2)[0]
    assert at_small[0] == pytest.approx(1.0, abs=1e-5)
    size = table[["length", "width", "height"]].to_numpy()[0]
    _, models, scores, _ = match_scores({1: query}, {1: size}, pool, e, size_weight=0.0, scales={1: np.array([4.2])})
    assert models[0] == mid and scores[0] == pytest.approx(at_small, abs=1e-6)
    _, _, unscaled, _ = match_scores({1: query}, {1: size}, pool, e, size_weight=0.0)
    assert unscaled[0] == pytest.approx(best_per_model(e.embed(query), full, cols, 2)[0], abs=1e-6)
    with pytest.raises(ValidationError):
        match_scores({1: query}, {1: size}, pool, e, scales={1: np.array([1.0, 2.0])})
