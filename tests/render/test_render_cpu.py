"""The CPU backend agrees with the float64 reference (forward and gradients) and is deterministic."""
from __future__ import annotations

import numba
import numpy as np
import pytest
import torch

from omniscs.errors import OmniscsError
from omniscs.render import _cpu_kernels as kernels
from omniscs.render import rasterize
from omniscs.render.cpu import _depth_bits, project_cpu
from omniscs.render.projection import project_gaussians
from omniscs.render.scenes import StreetScene, random_scene, street_scene

PARAMS = ("means", "quats", "scales", "opacities", "colors")

#: Parity bounds from the issue: float32 CPU against float64 reference.
MEAN_ABS_TOLERANCE = 1e-4
MAX_ABS_TOLERANCE = 1e-2
#: Gradients: largest deviation relative to the largest reference gradient of the same tensor.
GRAD_RELATIVE_TOLERANCE = 1e-3


def as_dtype(scene: StreetScene, dtype: torch.dtype) -> StreetScene:
    return StreetScene(**{name: getattr(scene, name).to(dtype) for name in PARAMS + ("viewmats", "Ks")},
                       width=scene.width, height=scene.height)


def render_both(scene: StreetScene, **kwargs):
    """(cpu float32, reference float64) outputs for the same scene."""
    cpu = rasterize(**as_dtype(scene, torch.float32).as_kwargs(), backend="cpu", **kwargs)
    ref = rasterize(**as_dtype(scene, torch.float64).as_kwargs(), backend="reference", **kwargs)
    return cpu, ref


def assert_images_close(cpu: torch.Tensor, ref: torch.Tensor) -> None:
    error = (cpu.double() - ref).abs()
    assert error.mean().item() < MEAN_ABS_TOLERANCE, f"mean abs error {error.mean().item():.2e}"
    assert error.max().item() < MAX_ABS_TOLERANCE, f"max abs error {error.max().item():.2e}"


def gradients(scene: StreetScene, dtype: torch.dtype, backend: str, **kwargs) -> dict[str, torch.Tensor]:
    """Gradients of a fixed random weighting of colours and alphas, plus means2d's (and backgrounds' if given)."""
    s = as_dtype(scene, dtype)
    leaves = {name: getattr(s, name).clone().requires_grad_(True) for name in PARAMS}
    if kwargs.get("backgrounds") is not None:
        kwargs["backgrounds"] = leaves["backgrounds"] = kwargs["backgrounds"].to(dtype).clone().requires_grad_(True)
    colors, alphas, meta = rasterize(**{**s.as_kwargs(), **{k: leaves[k] for k in PARAMS}}, backend=backend, **kwargs)
    meta["means2d"].retain_grad()
    gen = torch.Generator().manual_seed(1)
    weights = torch.rand(colors.shape, generator=gen, dtype=torch.float64)
    loss = (colors.double() * weights).sum() + (alphas.double() * weights[..., :1]).sum()
    loss.backward()
    return {name: leaf.grad.double() for name, leaf in leaves.items()} | {"means2d": meta["means2d"].grad.double()}


SCENES = {
    "random 32x24 N=60": lambda: random_scene(60, 32, 24, seed=0),
    "random 64x48 N=400, 2 cameras": lambda: random_scene(400, 64, 48, n_cameras=2, seed=1),
    "random 97x61 N=1500": lambda: random_scene(1500, 97, 61, seed=2),
    "street 96x54 N=3000": lambda: street_scene(3000, 96, 54, seed=3),
    "street 80x45 N=1500": lambda: street_scene(1500, 80, 45, seed=4),
}


@pytest.mark.parametrize("name", [name for name in SCENES if name != "street 80x45 N=1500"])
@pytest.mark.parametrize("render_mode", ["RGB", "RGB+ED"])
def test_cpu_forward_matches_reference(name, render_mode):
    (cpu_colors, cpu_alphas, _), (ref_colors, ref_alphas, _) = render_both(SCENES[name](), render_mode=render_mode)
    assert_images_close(cpu_colors[..., :3], ref_colors[..., :3])
    assert_images_close(cpu_alphas, ref_alphas)
    if render_mode == "RGB+ED":  # depth in metres: compare relative to the scene's depth scale
        depth_scale = ref_colors[..., 3].max().item()
        assert_images_close(cpu_colors[..., 3] / depth_scale, ref_colors[..., 3] / depth_scale)


@pytest.mark.parametrize("name", ["random 64x48 N=400, 2 cameras", "street 80x45 N=1500"])
def test_cpu_gradients_match_reference_autograd(name):
    scene = SCENES[name]()
    backgrounds = torch.tensor([[0.2, 0.3, 0.4]]).expand(scene.viewmats.shape[0], 3)
    cpu = gradients(scene, torch.float32, "cpu", render_mode="RGB+D", backgrounds=backgrounds)
    ref = gradients(scene, torch.float64, "reference", render_mode="RGB+D", backgrounds=backgrounds)
    assert set(ref) == set(PARAMS) | {"means2d", "backgrounds"}
    for key in ref:
        scale = ref[key].abs().max().item()
        assert scale > 0, key
        assert (cpu[key] - ref[key]).abs().max().item() <= GRAD_RELATIVE_TOLERANCE * scale, key


def test_cpu_gradients_match_reference_with_sh_and_antialiasing():
    scene = random_scene(300, 48, 32, n_cameras=2, seed=4)
    coeffs = 0.3 * torch.randn(300, 16, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    scene = StreetScene(**{**{name: getattr(scene, name) for name in PARAMS + ("viewmats", "Ks")}, "colors": coeffs},
                        width=scene.width, height=scene.height)
    cpu = gradients(scene, torch.float32, "cpu", sh_degree=3, rasterize_mode="antialiased")
    ref = gradients(scene, torch.float64, "reference", sh_degree=3, rasterize_mode="antialiased")
    for key in ref:
        scale = ref[key].abs().max().item()
        assert (cpu[key] - ref[key]).abs().max().item() <= GRAD_RELATIVE_TOLERANCE * scale, key


def test_cpu_projection_matches_pytorch_definition():
    s = random_scene(2000, 80, 60, n_cameras=3, seed=5)
    args = (s.means, s.quats, s.scales, s.opacities, s.viewmats, s.Ks, s.width, s.height, 0.01, 1e10, 0.3, True)
    (ours, _), definition = project_cpu(*args), project_gaussians(*args)
    assert torch.equal(ours.visible, definition.visible)
    assert (ours.radii - definition.radii).abs().max().item() <= 1  # ceil() may round either way at integers
    visible = definition.visible
    for field in ("means2d", "conics", "depths", "opacities"):
        torch.testing.assert_close(getattr(ours, field)[visible], getattr(definition, field)[visible],
                                   rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("rotation_scale", [1.0, 1.7])
def test_cpu_projection_culls_off_screen_gaussians_as_the_definition_does(rotation_scale):
    # centres all around the screen's edges and behind the camera, sizes from specks to ones that reach far
    # into the screen: the bound that skips the covariance of off-screen Gaussians must never cull a visible
    # one (also for a camera matrix that is not a rotation)
    rng = np.random.default_rng(12)
    n = 6000
    depth = rng.uniform(-2.0, 30.0, n)
    means = np.stack([rng.uniform(-2.5, 2.5, n) * np.abs(depth), rng.uniform(-2.0, 2.0, n) * np.abs(depth), depth], -1)
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, :3] *= rotation_scale
    args = (torch.tensor(means), torch.tensor(rng.standard_normal((n, 4))),
            torch.tensor(np.exp(rng.uniform(np.log(0.01), np.log(4.0), (n, 3)))),
            torch.tensor(rng.uniform(0.005, 1.0, n)), viewmat[None],
            torch.tensor([[[60.0, 0.0, 40.0], [0.0, 60.0, 30.0], [0.0, 0.0, 1.0]]], dtype=torch.float64), 80, 60,
            0.01, 1e10, 0.3, True)
    (ours, _), definition = project_cpu(*args), project_gaussians(*args)
    assert 0.1 < definition.visible.double().mean().item() < 0.6  # many of both kinds
    assert torch.equal(ours.visible, definition.visible)
    assert (ours.radii - definition.radii).abs().max().item() <= 1


def test_cpu_backend_is_bitwise_deterministic():
    scene = as_dtype(street_scene(4000, 96, 54, seed=6), torch.float32)
    runs = [gradients(scene, torch.float32, "cpu", render_mode="RGB+ED") for _ in range(2)]
    images = [rasterize(**scene.as_kwargs(), backend="cpu")[0] for _ in range(2)]
    assert torch.equal(images[0], images[1])
    for key in runs[0]:
        assert torch.equal(runs[0][key], runs[1][key]), key


def test_cpu_results_do_not_depend_on_the_number_of_threads():
    scene = as_dtype(street_scene(3000, 80, 45, seed=12), torch.float32)
    threads = numba.get_num_threads()
    try:
        runs = []
        for n_threads in (1, threads):
            numba.set_num_threads(n_threads)
            runs.append(gradients(scene, torch.float32, "cpu") | {"image": rasterize(**scene.as_kwargs(), backend="cpu")[0]})
    finally:
        numba.set_num_threads(threads)
    for key in runs[0]:
        assert torch.equal(runs[0][key], runs[1][key]), key


def test_tile_lists_and_reduction_do_not_depend_on_how_the_work_is_split():
    # the parallel counting sort of the tile lists and the gradient reduction cut their work into `parts` runs
    # (the thread count); any count, thread or not, must give the serial result, for several cameras
    scene = random_scene(2000, 70, 45, n_cameras=3, seed=21)
    screen, depths = project_cpu(scene.means.float(), scene.quats.float(), scene.scales.float(),
                                 scene.opacities.float(), scene.viewmats, scene.Ks, scene.width, scene.height,
                                 0.01, 1e10, 0.3)
    n_cams, n = screen.radii.shape[:2]
    radii = screen.radii.numpy()
    order, n_visible = kernels.depth_order(_depth_bits(depths), radii)
    colors = np.random.default_rng(3).uniform(size=(n_cams * n, 3)).astype(np.float32)
    flat = [screen.means2d.reshape(-1, 2).numpy(), screen.conics.reshape(-1, 3).numpy(),
            screen.opacities.reshape(-1).numpy(), colors, radii.reshape(-1, 2), order, n_visible,
            scene.width, scene.height]
    serial = kernels.bin_gaussians(*flat, 1)
    assert serial[1].size > 1000  # the scene crosses many tiles of every camera
    slots = np.random.default_rng(4).standard_normal((serial[1].size, kernels.N_GEOMETRY_SLOTS + 3)).astype(np.float32)

    def reduced(bins, parts):
        outs = tuple(np.zeros((n_cams * n,) + shape, np.float64) for shape in ((2,), (3,), (), (2,), (3,)))
        kernels.reduce_slots(bins[2], bins[5], bins[6], slots, *outs, parts)
        return outs

    for parts in (2, 3, 7):
        split = kernels.bin_gaussians(*flat, parts)
        for a, b in zip(serial, split):
            assert np.array_equal(a, b)
        for a, b in zip(reduced(serial, 1), reduced(split, parts)):
            assert np.array_equal(a, b)
        tiles = kernels.spread_order(1000, parts)
        assert np.array_equal(np.sort(tiles), np.arange(1000))
        assert np.array_equal(tiles[:(1000 + parts - 1) // parts], np.arange(0, 1000, parts))


@pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="Numba runs one thread here: nothing to leak")
def test_the_kernels_leave_torch_thread_count_as_they_found_it():
    # Numba's OpenMP layer sets the calling thread's OpenMP thread count, which torch reads too
    from omniscs.quality import ssim_loss

    scene = as_dtype(street_scene(2000, 64, 36, seed=2), torch.float32)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        gradients(scene, torch.float32, "cpu")
        assert torch.get_num_threads() == 1
        rendered = torch.rand(1, 3, 36, 64, requires_grad=True)
        ssim_loss(rendered, torch.rand(1, 3, 36, 64), 11).backward()
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(threads)


def test_means2d_gradient_and_absgrad_are_available_for_densification():
    s = as_dtype(random_scene(200, 40, 30, seed=7), torch.float32)
    means = s.means.clone().requires_grad_(True)
    colors, _, meta = rasterize(**{**s.as_kwargs(), "means": means}, backend="cpu", absgrad=True)
    meta["means2d"].retain_grad()
    colors.sum().backward()
    grad, absgrad = meta["means2d"].grad, meta["means2d"].absgrad
    assert grad.shape == absgrad.shape == (1, 200, 2)
    visible = meta["radii"][..., 0] > 0
    assert (grad[~visible] == 0).all() and grad[visible].abs().sum() > 0
    assert (absgrad >= grad.abs() - 1e-6).all()  # sum of |per-pixel terms| bounds |sum|


def test_cpu_backend_refuses_to_differentiate_cameras():
    s = as_dtype(random_scene(10, 16, 12), torch.float32)
    with pytest.raises(OmniscsError, match="viewmats"):
        rasterize(**{**s.as_kwargs(), "viewmats": s.viewmats.clone().requires_grad_(True)}, backend="cpu")


def test_auto_backend_picks_cpu_for_cpu_tensors():
    s = as_dtype(random_scene(10, 16, 12), torch.float32)
    assert rasterize(**s.as_kwargs())[2]["backend"] == "cpu"


def test_float64_inputs_give_float64_outputs_close_to_reference():
    s = random_scene(300, 40, 30, seed=8)
    cpu_colors, cpu_alphas, _ = rasterize(**s.as_kwargs(), backend="cpu")
    ref_colors, ref_alphas, _ = rasterize(**s.as_kwargs(), backend="reference")
    assert cpu_colors.dtype == torch.float64
    assert_images_close(cpu_colors, ref_colors)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_depth_sort_matches_a_stable_argsort_of_visible_gaussians(dtype):
    rng = np.random.default_rng(9)
    depths = np.round(rng.uniform(0.01, 1e4, (2, 5000)), 1).astype(dtype)  # rounding makes many ties
    depths[0, :10] = depths[0, 10]
    radii = np.where(rng.uniform(size=(2, 5000, 1)) < 0.8, 3, 0).astype(np.int32).repeat(2, -1)
    order, n_visible = kernels.depth_order(_depth_bits(torch.from_numpy(depths)), radii)
    for cam in range(2):
        visible = np.nonzero(radii[cam, :, 0] > 0)[0]
        expected = visible[np.argsort(depths[cam, visible], kind="stable")]
        assert n_visible[cam] == visible.size
        assert np.array_equal(order[cam, :visible.size], expected)
        assert set(order[cam, visible.size:]) == set(np.nonzero(radii[cam, :, 0] == 0)[0])


def test_float32_inputs_composite_in_the_order_of_their_float64_depths():
    # depths 4 + 1e-9 (index 0) and 4 (index 1): equal in float32, so only float64 depths put index 1 in front
    angle = 1e-9
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[0, 0] = viewmat[2, 2] = np.cos(angle)
    viewmat[2, 0], viewmat[0, 2] = np.sin(angle), -np.sin(angle)
    K = torch.tensor([[20.0, 0.0, 12.0], [0.0, 20.0, 8.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    args = dict(means=torch.tensor([[1.0, 0.0, 4.0], [0.0, 0.0, 4.0]]), quats=torch.tensor([[1.0, 0, 0, 0]] * 2),
                scales=torch.full((2, 3), 1.0), opacities=torch.tensor([0.9, 0.9]),
                colors=torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), viewmats=viewmat[None], Ks=K[None],
                width=24, height=16)
    cpu = rasterize(**args, backend="cpu")[0]
    ref = rasterize(**{k: v.double() if isinstance(v, torch.Tensor) else v for k, v in args.items()},
                    backend="reference")[0]
    assert ref[0, 8, 12, 2] > ref[0, 8, 12, 0]  # the blue one (index 1) is in front
    assert_images_close(cpu, ref)


def test_sparse_one_hot_channels_match_reference_and_their_dense_sum():
    # label channels: each Gaussian is 1 in one channel beyond the fused four and 0 in the others (the kernel skips
    # the zeros); the result must equal the reference and, summed over the label channels, a dense channel of ones
    scene = random_scene(300, 40, 30, n_cameras=2, seed=12)
    gen = torch.Generator().manual_seed(5)
    owner = torch.randint(0, 6, (300,), generator=gen)
    labels = torch.nn.functional.one_hot(owner, 6).to(torch.float64)
    features = torch.cat([torch.rand(300, 4, generator=gen, dtype=torch.float64), labels, torch.ones(300, 1,
                                                                                                  dtype=torch.float64)], 1)
    scene = StreetScene(**{**{name: getattr(scene, name) for name in PARAMS + ("viewmats", "Ks")}, "colors": features},
                        width=scene.width, height=scene.height)
    (cpu_colors, _, _), (ref_colors, _, _) = render_both(scene)
    assert_images_close(cpu_colors, ref_colors)
    torch.testing.assert_close(cpu_colors[..., 4:10].sum(-1), cpu_colors[..., 10], rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("n_channels", [1, 2, 6])
def test_feature_channels_of_any_count_match_reference(n_channels):
    scene = random_scene(300, 40, 30, n_cameras=2, seed=10)
    features = torch.rand(300, n_channels, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    scene = StreetScene(**{**{name: getattr(scene, name) for name in PARAMS + ("viewmats", "Ks")}, "colors": features},
                        width=scene.width, height=scene.height)
    backgrounds = torch.linspace(0.1, 0.9, n_channels)[None].expand(2, n_channels)
    (cpu_colors, _, _), (ref_colors, _, _) = render_both(scene, backgrounds=backgrounds)
    assert cpu_colors.shape == (2, 30, 40, n_channels)
    assert_images_close(cpu_colors, ref_colors)
    cpu = gradients(scene, torch.float32, "cpu", backgrounds=backgrounds)
    ref = gradients(scene, torch.float64, "reference", backgrounds=backgrounds)
    for key in ref:
        assert (cpu[key] - ref[key]).abs().max().item() <= GRAD_RELATIVE_TOLERANCE * ref[key].abs().max().item(), key


def test_row_tests_never_skip_a_pixel_inside_the_cut_off_ellipse():
    # thin, tilted, off-centre Gaussians (one per camera, so nothing occludes): the row and chord tests
    # skip tile rows by geometry; every pixel whose float64 alpha is clearly above the threshold (and
    # inside the pixel box) must still be composited, with the alpha the float64 formula gives
    from omniscs.render.constants import ALPHA_THRESHOLD
    from omniscs.render.cpu import rasterize_cpu
    from omniscs.render.projection import ScreenGaussians
    rng = np.random.default_rng(31)
    n_cams, width, height = 64, 72, 56
    angle = rng.uniform(0.0, np.pi, n_cams)
    long_sigma, short_sigma = rng.uniform(3.0, 25.0, n_cams), rng.uniform(0.6, 1.5, n_cams)
    rot = np.stack([np.cos(angle), np.sin(angle), -np.sin(angle), np.cos(angle)], -1).reshape(n_cams, 2, 2)
    cov = rot @ (np.eye(2) * np.stack([long_sigma ** 2, short_sigma ** 2], -1)[:, None, :]) @ rot.transpose(0, 2, 1)
    inv = np.linalg.inv(cov)
    conics = np.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], -1)
    means2d = np.stack([rng.uniform(8.0, width - 8.0, n_cams), rng.uniform(8.0, height - 8.0, n_cams)], -1)
    opacities = rng.uniform(0.05, 0.3, n_cams)  # cut-off ellipse inside the 3-sigma pixel box
    radius = np.ceil(3.0 * np.sqrt(np.linalg.eigvalsh(cov)[:, -1]))
    screen = ScreenGaussians(
        means2d=torch.tensor(means2d[:, None], dtype=torch.float32),
        conics=torch.tensor(conics[:, None], dtype=torch.float32),
        depths=torch.ones(n_cams, 1), opacities=torch.tensor(opacities[:, None], dtype=torch.float32),
        radii=torch.tensor(np.stack([radius, radius], -1)[:, None], dtype=torch.int32))
    _, alphas = rasterize_cpu(screen, torch.ones(n_cams, 1, 3), torch.zeros(n_cams, 3), width, height)
    ys, xs = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    f32 = lambda a: a.astype(np.float32).astype(np.float64)  # noqa: E731  the kernels' inputs
    dx, dy = f32(means2d[:, 0])[:, None, None] - xs, f32(means2d[:, 1])[:, None, None] - ys
    a, b, c = (f32(conics[:, k])[:, None, None] for k in range(3))
    alpha = f32(opacities)[:, None, None] * np.exp(-(0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy))
    in_box = (np.abs(dx) <= radius[:, None, None]) & (np.abs(dy) <= radius[:, None, None])
    clearly_in = in_box & (alpha >= 1.02 * ALPHA_THRESHOLD)
    clearly_out = alpha <= 0.98 * ALPHA_THRESHOLD
    rendered = alphas[..., 0].double().numpy()
    assert clearly_in.sum() > 10_000  # many pixels on rows of every kind (tile edges, chord ends)
    assert np.abs(rendered - alpha)[clearly_in].max() < 1e-5
    assert (rendered[clearly_out] == 0.0).all()


_FAULTS_PROBE = """
import resource, torch
from omniscs.render import rasterize
from omniscs.render.scenes import street_scene
small = street_scene(1_000, 64, 36)
colors, alphas, _ = rasterize(**{**small.as_kwargs(), "means": small.means.requires_grad_(True)}, backend="cpu")
(colors.sum() + alphas.sum()).backward()
scene = street_scene(20_000, 320, 180)
def forward():
    with torch.no_grad():
        rasterize(**scene.as_kwargs(), backend="cpu")
forward(), forward()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(5):
    forward()
print((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) // 5)
"""


def test_repeated_renders_reuse_freed_memory_instead_of_fresh_pages():
    # importing omniscs tunes glibc to keep freed arrays; with its adaptive defaults (and this sequence: a small
    # forward+backward, then forwards) the heap was trimmed after every render: about 490 page faults a call
    import subprocess
    import sys

    env = {k: v for k, v in __import__("os").environ.items() if not k.startswith("MALLOC_")}
    out = subprocess.run([sys.executable, "-c", _FAULTS_PROBE], env=env, capture_output=True, text=True, check=True)
    assert int(out.stdout.split()[-1]) < 50
