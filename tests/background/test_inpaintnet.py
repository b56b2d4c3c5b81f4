"""The embedded inpainting network: an Inpainter that keeps known pixels exact at any image size, a training loop
that learns to fill holes (and refuses bad pairs), packs that carry pairs to another machine, and shipped weights
that fill held-out repair holes better than OpenCV's FSR."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from omniscs.background.inpaint import Inpainter, OpenCVInpainter, load_inpainter
from omniscs.background.inpaint_pack import read_pack, write_pack
from omniscs.background.inpaintnet import (SHIPPED, InpaintNet, InpaintNetConfig, InpaintTrainConfig, NetInpainter,
                                           check_pairs, load_inpaint_net, save_inpaint_net, train_inpaint_net)
from omniscs.errors import OmniscsError, ValidationError

TINY = InpaintNetConfig(widths=(8, 12, 16), dilations=(2,), long_side=32)


def striped_pairs(n: int = 24, size: int = 32, seed: int = 0):
    """Images of vertical colour stripes (period and colours vary) with a box of a foreign colour, the box's
    hole, and the stripes without it: learnable from the context on both sides of the hole."""
    rng = np.random.default_rng(seed)
    images, holes, targets = [], [], []
    xx = np.arange(size)
    for _ in range(n):
        period = int(rng.integers(4, 9))
        a, b = rng.integers(0, 256, 3), rng.integers(0, 256, 3)
        row = np.where((xx // (period // 2)) % 2 == 0, 0, 1)
        target = np.where(row[None, :, None] == 0, a, b).repeat(size, 0).astype(np.uint8)
        hole = np.zeros((size, size), bool)
        y0, x0 = rng.integers(4, size // 2, 2)
        hole[y0:y0 + 10, x0:x0 + 10] = True
        image = target.copy()
        image[hole] = (255, 0, 255)
        images.append(image)
        holes.append(hole)
        targets.append(target)
    return np.stack(images), np.stack(holes), np.stack(targets)


def hole_mae(filled, truth, hole) -> float:
    return float(np.abs(filled[hole].astype(np.float64) - truth[hole]).mean())


@pytest.mark.parametrize("shape", [(32, 48), (37, 51), (5, 3), (135, 240), (900, 1600)])
def test_the_network_inpainter_keeps_known_pixels_and_fills_finite_pixels_at_any_size(shape):
    torch.manual_seed(0)
    filler = NetInpainter(InpaintNet(TINY))
    assert isinstance(filler, Inpainter)
    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 256, shape + (3,), dtype=np.uint8)
    hole = np.zeros(shape, bool)
    hole[shape[0] // 3:2 * shape[0] // 3 + 1, shape[1] // 3:2 * shape[1] // 3 + 1] = True
    out = filler.inpaint(rgb, hole)
    assert out.shape == rgb.shape and out.dtype == np.uint8
    assert np.array_equal(out[~hole], rgb[~hole])


def test_the_fill_does_not_depend_on_what_the_hole_showed():
    torch.manual_seed(0)
    filler = NetInpainter(InpaintNet(TINY))
    images, holes, _ = striped_pairs(1)
    other = images[0].copy()
    other[holes[0]] = (0, 255, 0)
    assert np.array_equal(filler.inpaint(images[0], holes[0]), filler.inpaint(other, holes[0]))


@pytest.mark.slow
def test_training_learns_to_fill_held_out_stripes_better_than_it_started():
    images, holes, targets = striped_pairs(48)
    cfg = InpaintTrainConfig(steps=300, batch=8, lr=3e-3, architecture=TINY)
    state, history = train_inpaint_net(images[:40], holes[:40], targets[:40], cfg)
    assert history["loss_last"] < 0.6 * history["loss_first"]
    net = InpaintNet(TINY)
    net.load_state_dict(state)
    trained = NetInpainter(net)
    torch.manual_seed(1)
    untrained = NetInpainter(InpaintNet(TINY))
    held = range(40, 48)
    mae = {name: np.mean([hole_mae(f.inpaint(images[i], holes[i]), targets[i], holes[i]) for i in held])
           for name, f in (("trained", trained), ("untrained", untrained))}
    # measured 30 against 68 grey levels (FSR, Fourier-based, continues such periodic stripes almost exactly: the
    # comparison with it is the shipped network's test on procedural repair holes)
    assert mae["trained"] < 0.6 * mae["untrained"], mae


def test_training_is_deterministic_for_a_seed():
    images, holes, targets = striped_pairs(8)
    cfg = InpaintTrainConfig(steps=5, batch=4, architecture=TINY)
    a, _ = train_inpaint_net(images, holes, targets, cfg)
    b, _ = train_inpaint_net(images, holes, targets, cfg)
    assert all(torch.equal(a[k], b[k]) for k in a)


@pytest.mark.parametrize("change, message", [
    (lambda i, h, t: (i.astype(np.float32), h, t), "uint8"),
    (lambda i, h, t: (i, h, t[:, :16]), "targets"),
    (lambda i, h, t: (i, h.astype(np.uint8), t), "bool"),
    (lambda i, h, t: (i, np.zeros_like(h), t), "cover some pixels"),
    (lambda i, h, t: (i, np.ones_like(h), t), "cover some pixels"),
    (lambda i, h, t: (i[:, :30, :30], h[:, :30, :30], t[:, :30, :30]), "multiples"),
    (lambda i, h, t: (i[:1], h[:1], t[:1]), "at least two"),
])
def test_bad_training_pairs_are_refused_with_what_is_expected(change, message):
    images, holes, targets = change(*striped_pairs(4))
    with pytest.raises(OmniscsError, match=message):
        check_pairs(images, holes, targets, TINY.multiple)


def test_weights_round_trip_through_safetensors_in_half_precision(tmp_path):
    torch.manual_seed(0)
    net = InpaintNet(TINY)
    save_inpaint_net(net.state_dict(), TINY, tmp_path / "w", {"note": "test"})
    back = load_inpaint_net(tmp_path / "w")
    assert back.config == TINY
    images, holes, _ = striped_pairs(2)
    a, b = NetInpainter(net.eval()).inpaint(images[0], holes[0]), NetInpainter(back).inpaint(images[0], holes[0])
    assert np.abs(a.astype(int) - b).max() <= 2  # float16 storage moves a fill by at most a grey level or two


def test_missing_weights_say_how_to_make_them(tmp_path):
    with pytest.raises(ValidationError, match="pretrained train inpaint --install"):
        load_inpaint_net(tmp_path)
    with pytest.raises(OmniscsError, match="pretrained train inpaint --install"):
        load_inpainter(f"net:{tmp_path}")


def test_a_pack_round_trips_holes_exactly_and_images_within_webp_error(tmp_path):
    # smooth colour gradients with pixel noise, like a render (WebP subsamples colour: random hard-edged stripes
    # would measure that, not the pack)
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:48, 0:64] / 64.0
    base = np.stack([40 + 160 * xx, 30 + 180 * yy, 60 + 60 * (xx + yy)], -1)
    images = np.clip(base[None] + rng.integers(-6, 7, (6, 48, 64, 3)), 0, 255).astype(np.uint8)
    targets = np.clip(images.astype(int)[:, :, ::-1] + 10, 0, 255).astype(np.uint8)  # differs everywhere
    holes = np.zeros((6, 48, 64), bool)
    for i in range(6):
        holes[i, 5 + i:20 + 2 * i, 10 + 3 * i:40] = True
    write_pack(tmp_path / "p.zip", images, holes, targets)
    back = read_pack(tmp_path / "p.zip")
    assert np.array_equal(back["holes"], holes)
    assert back["images"].shape == images.shape and np.abs(back["images"].astype(int) - images).mean() < 5.0
    # inside the hole the target comes back; outside the hole's bounding box the image stands in for it
    assert np.abs(back["targets"][holes].astype(int) - targets[holes]).mean() < 5.0
    assert np.array_equal(back["targets"][:, :, 45:], back["images"][:, :, 45:])


def test_a_pack_refuses_empty_holes_and_a_foreign_file(tmp_path):
    images, holes, targets = striped_pairs(2)
    holes[1] = False
    with pytest.raises(OmniscsError, match="non-empty hole"):
        write_pack(tmp_path / "p.zip", images, holes, targets)
    assert not (tmp_path / "p.zip").exists()
    (tmp_path / "x.zip").write_bytes(b"not a zip")
    with pytest.raises(ValidationError, match="not a readable inpainting pack"):
        read_pack(tmp_path / "x.zip")


# ---------------------------------------------------------------------------------------------- shipped weights
@pytest.fixture(scope="module")
def held_out_pairs():
    """Repair pairs of two worlds that neither trained nor evaluated the shipped network (seeds 3950-3951)."""
    from omniscs.training.inpaint import InpaintDataConfig, repair_pairs

    cfg = dataclasses.replace(InpaintDataConfig(), frames=(10, 30))
    parts = [repair_pairs(s, cfg) for s in (3950, 3951)]
    return {k: np.concatenate([p[k] for p in parts]) for k in ("images", "holes", "targets")}


@pytest.mark.skipif(not (SHIPPED / "inpaint.safetensors").is_file(), reason="no shipped inpainting weights")
@pytest.mark.slow
def test_the_shipped_network_fills_held_out_repair_holes_better_than_fsr(held_out_pairs):
    from omniscs.training.inpaint import evaluate_inpainters

    assert len(held_out_pairs["images"]) >= 8
    report = evaluate_inpainters({"embedded": load_inpainter("embedded"), "fsr": OpenCVInpainter("fsr_fast")},
                                 held_out_pairs)
    # measured 28.0 against 18.9 dB (15 pairs); a network no better than FSR fails
    assert report["embedded"]["hole_psnr_pooled"] > report["fsr"]["hole_psnr_pooled"] + 1.0, report


def test_repair_pairs_hide_the_agent_and_their_targets_differ_inside_the_hole(held_out_pairs):
    images, holes, targets = held_out_pairs["images"], held_out_pairs["holes"], held_out_pairs["targets"]
    assert images.shape[1:3] == (144, 256) and holes.dtype == np.bool_
    shares = holes.reshape(len(holes), -1).mean(1)
    assert (shares > 0).all() and (shares <= 0.7).all()
    inside = [np.abs(i[h].astype(int) - t[h]).mean() for i, h, t in zip(images, holes, targets)]
    outside = [np.abs(i[~h].astype(int) - t[~h]).mean() for i, h, t in zip(images, holes, targets)]
    assert np.median(inside) > 5 * np.median(outside)  # the agent stood in the hole (outside: shadows only)


def test_inpainting_data_refuse_benchmark_seeds_and_a_folder_without_weights(tmp_path):
    from omniscs.training.inpaint import InpaintDataConfig, cached_pairs, install_trained_inpaint

    with pytest.raises(OmniscsError, match=">= 3000"):
        cached_pairs([101], InpaintDataConfig(), tmp_path)
    with pytest.raises(OmniscsError, match="no weights"):
        install_trained_inpaint(tmp_path, out=tmp_path / "out")
    assert not (tmp_path / "out").exists()
