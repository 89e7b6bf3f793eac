"""Warp Gaussian rasterizer vs. the dense torch reference, gradcheck, gsplat's pure-torch functions, edge cases."""

from __future__ import annotations

import inspect
import math
import os
import pathlib
import struct
import subprocess
import sys

import pytest
import torch
from conftest import DEVICES

from codecsplat_warp.device import THREADS_VARIABLE
from codecsplat_warp.errors import InputError, RasterMemoryError
from codecsplat_warp.kernels import raster_tiles
from codecsplat_warp.kernels.raster_tiles import NO_DEPTH_BITS
from codecsplat_warp.ops.raster import SortKey, default_tile_size, project_gaussians, rasterize
from codecsplat_warp.reference.raster import rasterize_dense
from codecsplat_warp.synthetic import random_gaussians as make_scene


def relative_error(a, b):
    return ((a - b).abs().max() / b.abs().max().clamp_min(1e-12)).item()


def render_both(scene, width, height, tile_size=16, **kwargs):
    """Render with Warp (tiles of ``tile_size``) and the dense reference, and differentiate a random weighting of
    all outputs."""
    leaves = [t.detach().clone().requires_grad_() for t in scene[:5]]
    background = kwargs.pop("background", None)
    if background is not None:
        background = background.detach().clone().requires_grad_()
    inputs = [*leaves, *scene[5:]]
    ours = rasterize(*inputs, width, height, background=background, tile_size=tile_size, **kwargs)
    ref = rasterize_dense(*inputs, width, height, background=background, **kwargs)
    g = torch.Generator().manual_seed(1)
    weights = [torch.rand(o.shape, generator=g, dtype=o.dtype).to(o.device) for o in ref[:3]]
    wrt = leaves + ([background] if background is not None else [])
    grads_ours = torch.autograd.grad(sum((o * w).sum() for o, w in zip(ours[:3], weights)), wrt, allow_unused=True)
    grads_ref = torch.autograd.grad(sum((o * w).sum() for o, w in zip(ref[:3], weights)), wrt, allow_unused=True)
    return ours, ref, grads_ours, grads_ref


def assert_matches_reference(ours, ref, grads_ours, grads_ref, image_atol, grad_rtol):
    rgb, depth, alpha, meta = ours
    assert torch.equal(meta.radii, ref[3])
    assert (rgb - ref[0]).abs().max() <= image_atol
    assert (alpha - ref[2]).abs().max() <= image_atol
    if depth is not None:
        assert relative_error(depth, ref[1]) <= image_atol * 10
    for name, a, b in zip(("means", "quats", "scales", "opacities", "colors", "background"), grads_ours, grads_ref):
        assert torch.isfinite(a).all(), name
        assert relative_error(a, b) <= grad_rtol, name


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize(
    "mode, sh_degree, width, height, cameras",
    [("classic", None, 19, 13, 2), ("antialiased", 3, 16, 16, 1), ("classic", 1, 33, 20, 1)],
)
def test_matches_dense_reference_float64(device, mode, sh_degree, width, height, cameras):
    scene = make_scene(30, width, height, cameras, sh_degree, device=device)
    background = torch.rand(cameras, 3, dtype=torch.float64, device=device)
    result = render_both(scene, width, height, background=background, mode=mode)
    assert result[0][3].intersection_count > 0
    assert_matches_reference(*result, image_atol=1e-9, grad_rtol=1e-7)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("mode", ["classic", "antialiased"])
def test_matches_dense_reference_float32(device, mode):
    scene = make_scene(40, 24, 18, 2, sh_degree=2, dtype=torch.float32, device=device)
    background = torch.rand(2, 3, device=device)
    result = render_both(scene, 24, 18, background=background, mode=mode)
    assert_matches_reference(*result, image_atol=1e-5, grad_rtol=1e-4)


@pytest.mark.parametrize("device", DEVICES)
def test_tile_size_and_render_depth_do_not_change_the_image(device):
    scene = make_scene(30, 21, 21, device=device)
    rgb16, depth16, alpha16, _ = rasterize(*scene, 21, 21, tile_size=16)
    rgb8, depth8, alpha8, meta8 = rasterize(*scene, 21, 21, tile_size=8, render_depth=False)
    assert depth8 is None and meta8.tile_size == 8
    assert (rgb16 - rgb8).abs().max() < 1e-12 and (alpha16 - alpha8).abs().max() < 1e-12


@pytest.mark.parametrize("device", DEVICES)
def test_a_call_without_a_tile_size_uses_its_devices_default(device):
    """Catches: the CUDA default (8) or the CPU's (16) lost, e.g. one fixed default for both."""
    scene = make_scene(30, 21, 21, device=device)
    want = {"cuda": 8, "cpu": 16}[torch.device(device).type]
    assert default_tile_size(torch.device(device)) == want
    assert rasterize(*scene, 21, 21)[3].tile_size == want


@pytest.mark.parametrize("device", DEVICES)
def test_rectangles_of_more_tiles_than_a_mask_holds_match_the_reference(device):
    """The projection hands the tiles a row reaches to the emission as a 64-bit mask of its rectangle; rows whose
    rectangle spans more tiles (here the large Gaussians, over 64 tiles of 4 pixels) are tested again there."""
    scene = make_scene(30, 48, 40, 1, device=device)
    scene[2][:10] *= 6.0
    ours, ref, grads_ours, grads_ref = render_both(scene, 48, 40, tile_size=4)
    tiles_spanned = ((2 * ours[3].radii[0] + 4) // 4).prod(dim=-1)
    assert (tiles_spanned > 64).sum() >= 3 and ((tiles_spanned > 0) & (tiles_spanned <= 64)).sum() >= 10
    assert_matches_reference(ours, ref, grads_ours, grads_ref, image_atol=1e-9, grad_rtol=1e-7)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("tile_size", [20, 32])
def test_tiles_larger_than_16_match_16_with_gradients(device, tile_size):
    """On CUDA a tile of more than 256 pixels spans several blocks, the last one partly idle."""
    scene = make_scene(30, 45, 37, 2, device=device)
    outputs, grads = [], []
    for size in (16, tile_size):
        leaves = [t.detach().clone().requires_grad_() for t in scene[:5]]
        rgb, depth, alpha, _ = rasterize(*leaves, *scene[5:], 45, 37, tile_size=size)
        (rgb.sum() + 0.1 * depth.sum() + alpha.sum()).backward()
        outputs.append((rgb, depth, alpha))
        grads.append([leaf.grad for leaf in leaves])
    for a, b in zip(*outputs):
        assert (a - b).abs().max() < 1e-12
    for a, b in zip(*grads):
        assert relative_error(b, a) < 1e-10


@pytest.mark.parametrize(
    "argument, sh_degree, mode",
    [("means", None, "classic"), ("quats", None, "antialiased"), ("scales", None, "antialiased"),
     ("opacities", None, "classic"), ("colors", None, "classic"), ("colors", 1, "classic"),
     ("colors", 3, "antialiased"), ("means", 2, "classic"), ("means", 3, "antialiased")],
)  # fmt: skip
def test_gradcheck_float64(argument, sh_degree, mode):
    scene = make_scene(20, 16, 16, sh_degree=sh_degree, seed=3)
    index = ("means", "quats", "scales", "opacities", "colors").index(argument)
    background = torch.tensor([[0.2, 0.3, 0.4]], dtype=torch.float64)

    def render(x):
        inputs = list(scene)
        inputs[index] = x
        rgb, depth, alpha, _ = rasterize(*inputs, 16, 16, background=background, mode=mode)
        return torch.cat([rgb, depth, alpha], dim=-1)

    x = scene[index].clone().requires_grad_()
    assert torch.autograd.gradcheck(render, (x,), eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


def test_gradcheck_background():
    scene = make_scene(20, 16, 16, seed=4)

    def render(background):
        return rasterize(*scene, 16, 16, background=background)[0]

    background = torch.tensor([[0.2, 0.3, 0.4]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(render, (background,), fast_mode=True)


def opaque_scene(n=20, dtype=torch.float64, device="cpu", seed=3):
    """Nearly opaque, enlarged Gaussians: many pixels reach a transmittance of 1e-2 (the early stop matters)."""
    scene = make_scene(n, 16, 16, seed=seed, dtype=dtype, device=device)
    scene[3][:] = 0.97
    scene[2][:] *= 2
    return scene


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype, image_atol, grad_rtol", [(torch.float64, 1e-9, 1e-7), (torch.float32, 1e-5, 1e-4)])
def test_early_stop_threshold_matches_reference(device, dtype, image_atol, grad_rtol):
    scene = opaque_scene(dtype=dtype, device=device)
    stopped = rasterize(*scene, 16, 16, min_transmittance=1e-2)[0]
    assert (stopped - rasterize(*scene, 16, 16)[0]).abs().max() > 1e-2  # the threshold changes the image
    background = torch.rand(1, 3, dtype=dtype, device=device)
    result = render_both(scene, 16, 16, background=background, mode="antialiased", min_transmittance=1e-2)
    assert_matches_reference(*result, image_atol=image_atol, grad_rtol=grad_rtol)


def test_no_early_stop_matches_reference():
    result = render_both(opaque_scene(), 16, 16, min_transmittance=0.0)
    assert_matches_reference(*result, image_atol=1e-9, grad_rtol=1e-7)


@pytest.mark.parametrize("argument", ["means", "opacities", "colors"])
def test_gradcheck_float64_at_early_stop_threshold(argument):
    scene = opaque_scene()
    index = ("means", "quats", "scales", "opacities", "colors").index(argument)

    def render(x):
        inputs = list(scene)
        inputs[index] = x
        rgb, depth, alpha, _ = rasterize(*inputs, 16, 16, min_transmittance=1e-2)
        return torch.cat([rgb, depth, alpha], dim=-1)

    x = scene[index].clone().requires_grad_()
    assert torch.autograd.gradcheck(render, (x,), eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


@pytest.mark.parametrize("value", [-1e-3, 1.0, math.nan, "0.1", True])
def test_bad_early_stop_threshold_raises_input_error(value):
    with pytest.raises(InputError, match="min_transmittance"):
        rasterize(*make_scene(4, 8, 8), 8, 8, min_transmittance=value)


@pytest.mark.parametrize("outputs", [("rgb",), ("depth",), ("alpha",), ("rgb", "alpha")])
def test_gradients_of_some_outputs_match_reference(outputs):
    """Outputs without a gradient reach the backward as None (no zero-filled gradients are made)."""
    scene = make_scene(30, 19, 13, seed=2)
    leaves = [t.clone().requires_grad_() for t in scene[:5]]
    picked = [("rgb", "depth", "alpha").index(name) for name in outputs]
    ours = rasterize(*leaves, *scene[5:], 19, 13)
    ref = rasterize_dense(*leaves, *scene[5:], 19, 13)
    grads_ours = torch.autograd.grad(sum(ours[i].sum() for i in picked), leaves)
    grads_ref = torch.autograd.grad(sum(ref[i].sum() for i in picked), leaves, allow_unused=True)
    for a, b, leaf in zip(grads_ours, grads_ref, leaves):
        assert relative_error(a, torch.zeros_like(leaf) if b is None else b) <= 1e-7


@pytest.fixture
def gsplat_impl():
    """gsplat 1.5.3's pure-torch functions (installed by the dev extra; skipped only where it is absent)."""
    return pytest.importorskip("gsplat.cuda._torch_impl", reason="gsplat 1.5.3 (dev extra) is not installed")


@pytest.mark.parametrize("mode", ["classic", "antialiased"])
def test_projection_matches_gsplat(mode, gsplat_impl):
    means, quats, scales, _, colors, viewmats, Ks = make_scene(60, 40, 30, cameras=2, sh_degree=3, seed=5)
    means[:5, 2] = -1.0  # behind the camera
    opacities = torch.ones(60, dtype=torch.float64)
    ours = project_gaussians(means, quats, scales, opacities, colors, viewmats, Ks, 40, 30, mode=mode)
    covars, _ = gsplat_impl._quat_scale_to_covar_preci(quats, scales, compute_preci=False)
    radii, means2d, depths, conics, comp = gsplat_impl._fully_fused_projection(
        means, covars, viewmats, Ks, 40, 30, eps2d=0.3, calc_compensations=(mode == "antialiased")
    )
    visible = (ours.radii > 0).all(-1)
    assert visible.sum() > 50 and not visible[:, :5].any()
    assert torch.equal(visible, (radii > 0).all(-1))
    torch.testing.assert_close(ours.means2d[visible], means2d[visible], rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(ours.depths[visible], depths[visible], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(ours.conics[visible], conics[visible], rtol=1e-9, atol=1e-12)
    expected_opacity = comp if mode == "antialiased" else torch.ones_like(depths)
    torch.testing.assert_close(ours.opacities[visible], expected_opacity[visible], rtol=1e-8, atol=1e-12)
    # Radii: gsplat's CUDA rule, min(3.33, sqrt(2 ln(255 o))) sigma of the blurred covariance, from gsplat's conics.
    blurred = torch.linalg.inv(
        torch.stack([conics[..., 0], conics[..., 1], conics[..., 1], conics[..., 2]], -1).reshape(2, 60, 2, 2)
    )
    extent = torch.clamp(torch.sqrt(2 * torch.log(255 * expected_opacity)), max=3.33)
    expected_radii = torch.ceil(extent[..., None] * torch.sqrt(torch.diagonal(blurred, dim1=-2, dim2=-1)))
    assert torch.equal(ours.radii[visible].double(), expected_radii[visible])
    # SH colours: gsplat's evaluation towards the mean from the camera centre, + 0.5, clamped at 0.
    centers = torch.linalg.inv(viewmats)[:, :3, 3]
    for degree in range(4):
        ours = project_gaussians(means, quats, scales, opacities, colors, viewmats, Ks, 40, 30, sh_degree=degree)
        sh = gsplat_impl._spherical_harmonics(degree, means[None] - centers[:, None], colors[None].expand(2, -1, -1, -1))
        expected = torch.clamp_min(sh + 0.5, 0.0)
        torch.testing.assert_close(ours.colors[visible], expected[visible], rtol=1e-10, atol=1e-12)


def test_gradcheck_projection_stage_float64():
    scene = make_scene(10, 16, 16, cameras=2, sh_degree=1, seed=6)
    leaves = tuple(t.clone().requires_grad_() for t in scene[:5])

    def project(*params):
        proj = project_gaussians(*params, *scene[5:], 16, 16, mode="antialiased")
        parts = [proj.means2d, proj.conics, proj.opacities[..., None], proj.colors, proj.depths[..., None]]
        return torch.cat(parts, dim=-1)

    assert (project_gaussians(*scene, 16, 16).radii > 0).all(-1).sum() > 10
    assert torch.autograd.gradcheck(project, leaves, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


def test_zero_gaussians_render_the_background():
    scene = make_scene(0, 8, 8)
    background = torch.tensor([[0.1, 0.5, 0.9]], dtype=torch.float64, requires_grad=True)
    rgb, depth, alpha, meta = rasterize(*scene, 8, 8, background=background)
    assert torch.equal(rgb[0, 3, 4], background[0].detach()) and alpha.abs().max() == 0 and depth.abs().max() == 0
    assert meta.intersection_count == 0 and meta.radii.shape == (1, 0, 2)
    rgb.sum().backward()
    assert torch.equal(background.grad, torch.full((1, 3), 64.0, dtype=torch.float64))


def tilted_thin_scene(dtype=torch.float64, device="cpu"):
    """Two long, thin Gaussians at 45 and -60 degrees in a 64x64 image: their bounding boxes cover every tile, their
    ellipses about half of them."""
    scene = make_scene(2, 64, 64, dtype=dtype)
    scene[0][:] = torch.tensor([[0.05, 0.02, 3.0], [-0.1, 0.15, 3.5]], dtype=dtype)
    angles = torch.tensor([math.pi / 4, -math.pi / 3], dtype=dtype)
    scene[1][:] = torch.stack([torch.cos(angles / 2), 0 * angles, 0 * angles, torch.sin(angles / 2)], dim=1)
    scene[2][:] = torch.tensor([[0.8, 0.01, 0.01], [0.9, 0.02, 0.01]], dtype=dtype)
    scene[3][:] = torch.tensor([0.9, 0.6], dtype=dtype)
    return [t.to(device) for t in scene]


def tiles_of_rectangles(projected, width: int, height: int, tile_size: int) -> int:
    """Tile intersections of the bounding rectangles (gsplat's binning rule) of the visible projected Gaussians."""
    means, radii = projected.means2d.double(), projected.radii.double()
    low = torch.floor((means - radii) / tile_size).clamp(min=0)
    high = torch.ceil((means + radii) / tile_size)
    high = torch.minimum(high, torch.tensor([math.ceil(width / tile_size), math.ceil(height / tile_size)]).to(high))
    visible = (projected.radii > 0).any(-1)
    return int(((high - low).clamp(min=0).prod(-1) * visible).sum())


def tiles_with_alpha_above_threshold(projected, width: int, height: int, tile_size: int) -> int:
    """Tiles holding a pixel centre where a visible Gaussian's alpha reaches 1/255, summed over the Gaussians."""
    ys, xs = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    total = 0
    for mean, conic, opacity in zip(projected.means2d[0].double().cpu(), projected.conics[0].double().cpu(),
                                    projected.opacities[0].double().cpu()):  # fmt: skip
        dx, dy = mean[0] - xs.double(), mean[1] - ys.double()
        power = 0.5 * (conic[0] * dx * dx + conic[2] * dy * dy) + conic[1] * dx * dy
        reached = (opacity * torch.exp(-power) >= 1 / 255).double()
        per_tile = torch.nn.functional.max_pool2d(reached[None, None], tile_size, ceil_mode=True)
        total += int(per_tile.sum())
    return total


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_a_gaussian_is_binned_only_into_the_tiles_its_ellipse_reaches(device, dtype):
    scene = tilted_thin_scene(dtype, device)
    projected = project_gaussians(*scene, 64, 64)
    meta = rasterize(*scene, 64, 64)[3]  # the device's default tiles: 16 px on the CPU, 8 on CUDA
    rectangles = tiles_of_rectangles(projected, 64, 64, 16)
    needed = tiles_with_alpha_above_threshold(projected, 64, 64, meta.tile_size)
    assert rectangles == 32  # with 16 px tiles the bounding boxes cover every tile
    assert needed <= meta.intersection_count <= needed + 2  # needed: 18 with 16 px tiles
    # float32: the thin axis (conic ~10 px^-2) amplifies rounding; the bounding-box binning gave the same errors
    atol, rtol = (1e-9, 1e-7) if dtype == torch.float64 else (5e-5, 1e-3)
    assert_matches_reference(*render_both(scene, 64, 64), image_atol=atol, grad_rtol=rtol)


def test_all_culled_gives_background_and_zero_gradients():
    scene = make_scene(10, 8, 8)
    scene[0] = scene[0] * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)  # everything behind the camera
    leaves = [t.clone().requires_grad_() for t in scene[:5]]
    background = torch.tensor([[0.1, 0.5, 0.9]], dtype=torch.float64)
    rgb, depth, alpha, meta = rasterize(*leaves, *scene[5:], 8, 8, background=background)
    assert torch.equal(rgb, background[:, None, None].expand(1, 8, 8, 3)) and alpha.abs().max() == 0
    assert meta.intersection_count == 0 and meta.visible_counts.tolist() == [0]
    (rgb.sum() + depth.sum() + alpha.sum()).backward()
    for leaf in leaves:
        assert leaf.grad is not None and leaf.grad.abs().max() == 0


def test_near_plane_is_exclusive_and_far_culls():
    means, quats, scales, opacities, colors, viewmats, Ks = make_scene(3, 16, 16)
    means[:, :2] = 0.0
    means[:, 2] = torch.tensor([0.5, 0.5 + 1e-9, 20.0], dtype=torch.float64)
    proj = project_gaussians(means, quats, scales, opacities, colors, viewmats, Ks, 16, 16, near=0.5, far=10.0)
    assert (proj.radii[0] > 0).all(-1).tolist() == [False, True, False]


@pytest.mark.parametrize(
    "case",
    ["huge_scales", "tiny_scales", "flat", "opacity_0_and_1", "one_by_one", "odd_size", "close_to_camera"],
)
def test_hard_inputs_match_reference_and_stay_finite(case):
    width, height = {"one_by_one": (1, 1), "odd_size": (17, 5)}.get(case, (16, 16))
    scene = make_scene(25, width, height, seed=7)
    if case == "huge_scales":
        scene[2][:3] = 1e3
    elif case == "tiny_scales":
        scene[2][:] = 1e-8
    elif case == "flat":
        scene[2][:, 0] = 0.0
    elif case == "opacity_0_and_1":
        scene[3][::2] = 0.0
        scene[3][1::2] = 1.0
    elif case == "close_to_camera":
        scene[0][:, 2] = torch.linspace(0.02, 0.5, 25, dtype=torch.float64)
    background = torch.rand(1, 3, dtype=torch.float64)
    result = render_both(scene, width, height, background=background, mode="antialiased")
    assert all(torch.isfinite(t).all() for t in result[0][:3])
    # Near-flat footprints make det(cov2d) ill-conditioned: two float64 evaluation orders differ by ~1e-9.
    assert_matches_reference(*result, image_atol=1e-7, grad_rtol=1e-5)


@pytest.mark.parametrize("argument", ["means", "quats", "scales", "opacities", "colors", "viewmats", "Ks", "background"])
@pytest.mark.parametrize("value", [math.nan, math.inf])
def test_non_finite_inputs_raise_input_error(argument, value):
    scene = dict(zip(("means", "quats", "scales", "opacities", "colors", "viewmats", "Ks"), make_scene(6, 8, 8)))
    scene["background"] = torch.zeros(1, 3, dtype=torch.float64)
    scene[argument].view(-1)[-1] = value
    background = scene.pop("background")
    with pytest.raises(InputError, match=argument):
        rasterize(**scene, width=8, height=8, background=background)


def test_zero_quaternion_and_bad_arguments_raise_input_error():
    scene = make_scene(4, 8, 8)
    quats = scene[1].clone()
    quats[2] = 0.0
    with pytest.raises(InputError, match="quats"):
        rasterize(scene[0], quats, *scene[2:], 8, 8)
    with pytest.raises(InputError, match="scales"):
        rasterize(scene[0], scene[1], scene[2][:3], *scene[3:], 8, 8)
    with pytest.raises(InputError, match="mode"):
        rasterize(*scene, 8, 8, mode="fancy")
    with pytest.raises(InputError, match="sh_degree"):
        rasterize(*scene[:4], torch.zeros(4, 4, 3, dtype=torch.float64), *scene[5:], 8, 8, sh_degree=2)
    with pytest.raises(InputError, match="width"):
        rasterize(*scene, 0, 8)
    with pytest.raises(InputError, match="near"):
        rasterize(*scene, 8, 8, near=0.0)


def test_cached_settings_still_raise_for_every_bad_call():
    """A call's settings are cached per distinct arguments: a bad argument raises on every call, ``True`` is not
    taken for a width of 1 cached before, and an unhashable argument is checked without the cache."""
    scene = make_scene(4, 8, 8)
    rasterize(*scene, 1, 8)
    for _ in range(2):
        with pytest.raises(InputError, match="width"):
            rasterize(*scene, True, 8)
        with pytest.raises(InputError, match="mode"):
            rasterize(*scene, 8, 8, mode=["classic"])


@pytest.mark.parametrize("device", DEVICES)
def test_leave_out_renders_each_camera_as_if_its_range_were_absent(device):
    """Camera b with ``leave_out[b] = (s, e)`` renders (and differentiates) like a call without Gaussians s..e-1:
    ranges inside, reversed (empty) and past the end (clamped)."""
    scene = make_scene(30, 19, 13, 3, sh_degree=1, device=device)
    ranges = [(5, 20), (12, 9), (25, 99)]
    leaves = [t.clone().requires_grad_() for t in scene[:5]]
    g = torch.Generator().manual_seed(2)
    weights = torch.rand(3, 13, 19, 4, generator=g, dtype=torch.float64).to(device)

    def loss(rgb, alpha, b=slice(None)):
        return (torch.cat([rgb, alpha], -1) * weights[b]).sum()

    rgb, _, alpha, meta = rasterize(*leaves, *scene[5:], 19, 13, leave_out=torch.tensor(ranges, device=device))
    grads = torch.autograd.grad(loss(rgb, alpha), leaves)
    per_camera = []
    total = 0.0
    for b, (first, end) in enumerate(ranges):
        keep = torch.ones(30, dtype=torch.bool, device=device)
        keep[first:end] = False
        one, _, one_alpha, one_meta = rasterize(*[t[keep] for t in leaves], scene[5][b:b + 1], scene[6][b:b + 1],
                                                19, 13)  # fmt: skip
        assert torch.equal(meta.radii[b][keep], one_meta.radii[0]) and not meta.radii[b][~keep].any()
        per_camera.append(torch.cat([one, one_alpha], -1))
        total = total + loss(one, one_alpha, slice(b, b + 1))
    assert (torch.cat([rgb, alpha], -1) - torch.cat(per_camera)).abs().max() <= 1e-12
    for name, ours, want in zip(("means", "quats", "scales", "opacities", "colors"), grads,
                                torch.autograd.grad(total, leaves)):  # fmt: skip
        assert relative_error(ours, want) <= 1e-10, name


def test_leave_out_of_the_wrong_shape_or_dtype_is_an_input_error():
    scene = make_scene(4, 8, 8, 2)
    with pytest.raises(InputError, match="leave_out"):
        rasterize(*scene, 8, 8, leave_out=torch.zeros(1, 2, dtype=torch.int64))
    with pytest.raises(InputError, match="leave_out"):
        rasterize(*scene, 8, 8, leave_out=torch.zeros(2, 2))


def test_memory_budget_raises_before_allocating():
    """16 bytes per intersection with this scene's 32-bit sort keys: a budget of exactly that renders."""
    scene = make_scene(30, 32, 32)
    count = rasterize(*scene, 32, 32)[3].intersection_count
    rasterize(*scene, 32, 32, max_intersection_bytes=16 * count)
    with pytest.raises(RasterMemoryError, match=f"{count:,} tile intersections need {16 * count:,} bytes"):
        rasterize(*scene, 32, 32, max_intersection_bytes=16 * count - 1)


def test_culled_rows_are_never_read_and_zeroed_only_for_projection(monkeypatch):
    """rasterize leaves the projected rows of culled Gaussians unwritten (the kernel's ``zero_culled`` = 0): poisoned
    with NaN, they must not reach the images or gradients; project_gaussians writes them as zeros."""
    import codecsplat_warp.ops.raster as raster_ops

    make_rows = raster_ops._rows_and_cameras

    def poisoned_rows(means, num_cameras, leave_out):
        rows, cameras = make_rows(means, num_cameras, leave_out)
        rows.fill_(float("nan"))
        return rows, cameras

    monkeypatch.setattr(raster_ops, "_rows_and_cameras", poisoned_rows)
    scene = make_scene(40, 16, 16, seed=11)
    scene[0][::2, 2] *= -1.0  # every other Gaussian behind the camera: culled
    ours, ref, grads_ours, grads_ref = render_both(scene, 16, 16)
    assert_matches_reference(ours, ref, grads_ours, grads_ref, image_atol=1e-10, grad_rtol=1e-8)
    assert 0 < int(ours[3].visible_counts.sum()) <= 20
    proj = project_gaussians(*scene, 16, 16)
    culled = (proj.radii[0] == 0).all(-1)
    assert culled[::2].all()
    for field in (proj.means2d, proj.conics, proj.opacities, proj.colors, proj.depths):
        assert torch.equal(field[0][culled], torch.zeros_like(field[0][culled]))


@pytest.mark.parametrize("device", DEVICES)
def test_projection_lists_each_visible_row_once(device):
    """The projection appends every visible row (non-zero radii) exactly once to the list that the projection
    backward walks (a warp-aggregated append on CUDA, in no particular order), for two cameras that see different
    Gaussians; culled rows are not listed."""
    import codecsplat_warp.ops.raster as raster_ops

    means, quats, scales, opacities, colors, viewmats, Ks = make_scene(300, 24, 20, seed=5)
    means[::3, 2] *= -1.0
    viewmats = viewmats.expand(2, 4, 4).clone()
    viewmats[1, 0, 3] += 0.5
    inputs = [t.to(device) for t in (means, quats, scales, opacities, colors, viewmats, Ks.expand(2, 3, 3))]
    checked = raster_ops._prepare(*inputs, 24, 20, 0.01, 1e10, None, "classic", None, True, 16, 1e-4)
    means, quats, scales, opacities, colors, viewmats, Ks, background, settings = checked
    none_left_out = raster_ops._leave_out_ranges(None, viewmats, means)
    outputs, saved = raster_ops._render(means, quats, scales, opacities, colors, background, viewmats, Ks,
                                        none_left_out, settings, raster_ops.DEFAULT_MAX_INTERSECTION_BYTES)
    visible = outputs[3].reshape(-1, 2).any(dim=-1).nonzero().flatten().cpu()
    listed = saved.visible.rows[: int(saved.visible.count)].cpu().to(torch.int64)
    assert 100 < len(visible) < 600 and (visible < 300).any() and (visible >= 300).any()
    assert torch.equal(listed.sort().values, visible)
    # what the backward keeps is its own memory, not a view of the forward's [2*B*N + flags] int64 buffer
    assert saved.visible.count.untyped_storage().nbytes() == 8


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("sh_degree", [None, 2])
def test_projection_backward_sums_each_gaussians_cameras(device, sh_degree):
    """The projection backward (one thread per visible row; with SH colours the coefficients in a kernel of their
    own, one thread per Gaussian summing its cameras) gives the sum over the cameras of each camera's gradient, with
    Gaussians culled in some of the three cameras (behind one of them) and others in all."""
    means, quats, scales, opacities, colors, viewmats, Ks = make_scene(60, 19, 13, 1, sh_degree, seed=8)
    viewmats = viewmats.expand(3, 4, 4).clone()
    viewmats[1, 0, 3] += 0.4
    viewmats[2, 2, 3] -= 3.0  # amid the Gaussians: about half of them behind it
    Ks = Ks.expand(3, 3, 3)
    leaves = [t.to(device).requires_grad_() for t in (means, quats, scales, opacities, colors)]
    weights = torch.rand(3, 13, 19, 5, dtype=torch.float64, device=device)

    def gradients(cameras):
        rgb, depth, alpha, meta = rasterize(*leaves, viewmats[cameras].to(device), Ks[cameras].to(device), 19, 13,
                                            mode="antialiased", sh_degree=sh_degree)  # fmt: skip
        loss = (torch.cat([rgb, depth, alpha], dim=-1) * weights[cameras]).sum()
        return torch.autograd.grad(loss, leaves), meta.radii

    together, radii = gradients([0, 1, 2])
    alone = [gradients([camera])[0] for camera in range(3)]
    seen = (radii > 0).any(-1).cpu()
    assert seen.all(dim=0).any() and not seen.all(dim=0).all() and (~seen[2]).any()
    for name, total, parts in zip(("means", "quats", "scales", "opacities", "colors"), together, zip(*alone)):
        assert total.abs().max() > 0, name
        torch.testing.assert_close(total, sum(parts), rtol=1e-10, atol=1e-12, msg=name)


def test_radii_changed_in_place_before_the_backward_raise_autograds_error():
    """The projection backward reads the radii, which the call also returns: changed in place before the backward,
    they raise autograd's error instead of changing the gradient, for the render and the projection alone."""
    scene = make_scene(20, 16, 16, cameras=2, sh_degree=2, seed=3)
    leaves = [t.clone().requires_grad_() for t in scene[:5]]
    rgb, _, _, meta = rasterize(*leaves, *scene[5:], 16, 16)
    meta.radii.zero_()
    with pytest.raises(RuntimeError, match="modified by an inplace operation"):
        rgb.sum().backward()
    projected = project_gaussians(*leaves, *scene[5:], 16, 16, sh_degree=2)
    projected.radii.zero_()
    with pytest.raises(RuntimeError, match="modified by an inplace operation"):
        projected.colors.sum().backward()


@pytest.mark.parametrize("device", DEVICES)
def test_projection_folds_the_visible_depth_range(device, monkeypatch):
    """The smallest and largest float32 bit pattern of a visible row's depth, as the projection folds them over the
    lines of the flag buffer (on CUDA from 94 warps spread over the lines; culled rows, here the ones behind the
    camera, left out); the published key layout starts at the smallest."""
    import codecsplat_warp.ops.raster as raster_ops

    project = raster_ops._project
    flags = []

    def spy(*args, **kwargs):
        flags.append(inspect.signature(project).bind(*args, **kwargs).arguments["flags"])
        return project(*args, **kwargs)

    monkeypatch.setattr(raster_ops, "_project", spy)
    monkeypatch.setattr(raster_ops, "_graphs_enabled", lambda: False)  # the eager launches, spied on
    means, quats, scales, opacities, colors, viewmats, Ks = make_scene(3000, 40, 30, dtype=torch.float32, seed=6)
    means[::4, 2] *= -1.0
    inputs = [t.to(device) for t in (means, quats, scales, opacities, colors, viewmats, Ks)]
    checked = raster_ops._prepare(*inputs, 40, 30, 0.01, 1e10, None, "classic", None, True, 16, 1e-4)
    means, quats, scales, opacities, colors, viewmats, Ks, background, settings = checked
    none_left_out = raster_ops._leave_out_ranges(None, viewmats, means)
    outputs, saved = raster_ops._render(means, quats, scales, opacities, colors, background, viewmats, Ks,
                                        none_left_out, settings, raster_ops.DEFAULT_MAX_INTERSECTION_BYTES)
    visible = outputs[3].reshape(-1, 2).any(dim=-1)
    depths = saved.splats[visible, 9].float().cpu()
    assert 1000 < len(depths) < 3000
    want = (float32_bits(depths.min().item()), float32_bits(depths.max().item()))
    flag_values = [f.tolist() for f in flags]
    assert [folded_depth_range(values) for values in flag_values] == [want]
    assert raster_tiles.key_layout(flag_values[0])[0] == want[0]  # the published layout's depth base


def folded_depth_range(flag_values: list[int]) -> tuple[int, int]:
    """``(smallest, largest)`` float32 bit pattern of a visible depth over the depth-range lines of a whole flag
    buffer's values."""
    from codecsplat_warp.kernels.lanes import CACHE_LINE_INT64

    first = raster_tiles.DEPTH_RANGE
    lines = range(first, first + raster_tiles.DEPTH_RANGE_LINES * CACHE_LINE_INT64, CACHE_LINE_INT64)
    return min(flag_values[k] for k in lines), max(flag_values[k + 1] for k in lines)


def test_too_many_tiles_for_the_sort_key_is_a_typed_error():
    means, quats, scales, opacities, colors, viewmats, Ks = make_scene(2, 16, 16)
    two_cameras = viewmats.expand(2, 4, 4), Ks.expand(2, 3, 3)
    with pytest.raises(InputError, match="tile part of the sort key"):
        rasterize(means, quats, scales, opacities, colors, *two_cameras, 65536, 65536, tile_size=1)


def float32_bits(value: float) -> int:
    return struct.unpack("<i", struct.pack("<f", value))[0]


def published_key_layout(num_tiles: int, nearest_bits: int, farthest_bits: int, device: str) -> SortKey:
    """The sort key that the emit kernel's one-thread launch publishes for a depth range folded into two different
    lines of a flag buffer (the other lines empty), as the projection leaves it."""
    import codecsplat_warp.ops.raster as raster_ops
    from codecsplat_warp.device import warp_scope
    from codecsplat_warp.kernels.lanes import CACHE_LINE_INT64

    flags = torch.zeros(raster_tiles.NUM_FLAGS, dtype=torch.int64)
    lines = raster_tiles.DEPTH_RANGE + CACHE_LINE_INT64 * torch.arange(raster_tiles.DEPTH_RANGE_LINES)
    flags[lines] = NO_DEPTH_BITS
    flags[lines[3]], flags[lines[7] + 1] = nearest_bits, farthest_bits
    ints = torch.cat([torch.zeros(2, dtype=torch.int64), flags]).to(device)
    # one camera, one row of num_tiles 16-pixel tiles
    settings = raster_ops._make_settings(2, 3, 16 * num_tiles, 16, 0.01, 100.0, "classic", None, True,
                                         16, 1e-4)  # fmt: skip
    radii = torch.zeros(1, 2, dtype=torch.int32, device=device)
    binning = raster_ops._Binning(torch.zeros(1, 10, device=device), radii, ints, ints[:1], torch.zeros_like(ints[:1]),
                                  ints[1:2], ints[2:], 1, settings)  # fmt: skip
    assert binning.num_tiles == num_tiles
    with warp_scope(torch.device(device)) as wdev:
        raster_ops._emit(binning, 0, *raster_ops._sort_buffers(ints, 0, torch.uint32), wdev)
    return SortKey(*raster_tiles.key_layout(ints[2:].tolist()))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize(
    "num_tiles, nearest, farthest, want",
    [
        (1, 2.0, 4.0, (torch.uint32, 0, 24)),  # one octave: 2^23 + 1 bit patterns
        (256, 1.5, 9.0, (torch.uint32, 1, 24)),  # the RE10K bench: 25 depth bits + 8 tile bits, one dropped
        (448, 1.5, 9.0, (torch.uint32, 2, 23)),  # the DL3DV bench with 16x16 tiles: 9 tile bits, two dropped
        (1792, 1.5, 9.0, (torch.uint32, 4, 21)),  # the DL3DV bench with 8x8 tiles: 11 tile bits, four dropped
        (4096, 1.0, 8.0, (torch.uint32, 5, 20)),  # 12 tile bits: five dropped
        (2**16, 1.0, 8.0, (torch.int64, 0, 25)),  # 32 bits would drop nine: a lossless 64-bit key
        (2**31 - 1, 1.0, 8.0, (torch.int64, 0, 25)),  # the most flat tiles a call may have (31 bits)
    ],
)
def test_published_sort_key_layout_packs_the_depth_span(device, num_tiles, nearest, farthest, want):
    key = published_key_layout(num_tiles, float32_bits(nearest), float32_bits(farthest), device)
    assert (key.dtype, key.depth_shift, key.depth_bits) == want
    assert key.depth_base == float32_bits(nearest)
    assert key.bits == (num_tiles - 1).bit_length() + key.depth_bits
    assert key.bytes_per_intersection == (16 if key.dtype == torch.uint32 else 24)


def test_published_sort_key_layout_of_an_empty_depth_range():
    key = published_key_layout(4, NO_DEPTH_BITS, 0, "cpu")
    assert (key.dtype, key.depth_shift, key.depth_bits, key.bits) == (torch.uint32, 0, 0, 2)


def test_key_layout_slots_follow_the_validation_flags():
    from codecsplat_warp.kernels import raster_project

    assert raster_project.VALIDATION_FLAGS <= raster_tiles.KEY_LAYOUT < raster_tiles.HOST_FLAGS <= raster_tiles.DEPTH_RANGE


def scene_at_depths(nearest, farthest, n=40, size=32, seed=4):
    """make_scene's Gaussians moved to depths in [nearest, farthest] (the nearest and farthest included), each
    kept at its pixel position."""
    means, *rest = make_scene(n, size, size, seed=seed)
    z = torch.linspace(nearest, farthest, n, dtype=means.dtype)[torch.randperm(n, generator=torch.Generator().manual_seed(seed))]
    means = torch.cat([means[:, :2] * (z / means[:, 2])[:, None], z[:, None]], dim=1)
    return [means, *rest]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize(
    "nearest, farthest, size, want",
    [(2.0, 2.9, 32, (torch.uint32, 0)), (2.0, 7.0, 32, (torch.uint32, 2)), (1.0, 9.0, 32, (torch.uint32, 3)),
     (1.0, 1000.0, 32, (torch.uint32, 5)), (0.02, 5e9, 64, (torch.int64, 0))],
)  # fmt: skip
def test_every_sort_key_layout_matches_dense_reference(device, nearest, farthest, size, want, monkeypatch):
    """1024 one-pixel tiles (10 key bits) and depth spans of 22, 24, 25 and 27 bits: a lossless 32-bit key, ones
    that drop two, three and five depth bits; 4096 tiles (12 bits) and a 29-bit span: a 64-bit key. Each renders
    like the dense reference."""
    import codecsplat_warp.ops.raster as raster_ops

    read = raster_tiles.key_layout
    layouts = []

    def spy(values):
        layouts.append(SortKey(*read(values)))
        return read(values)

    monkeypatch.setattr(raster_tiles, "key_layout", spy)
    scene = [t.to(device) for t in scene_at_depths(nearest, farthest, size=size)]
    ours, ref, grads_ours, grads_ref = render_both(scene, size, size, tile_size=1)
    assert [(key.dtype, key.depth_shift) for key in layouts] == [want]
    assert_matches_reference(ours, ref, grads_ours, grads_ref, image_atol=1e-10, grad_rtol=1e-8)


def test_depths_within_the_dropped_bits_keep_row_order():
    """With two depth bits dropped (1024 tiles, a 24-bit depth span), two Gaussians 2 float32 ulps apart tie: the
    first row composites first although it is the farther one."""
    means, quats, scales, opacities, colors, viewmats, Ks = make_scene(3, 32, 32, dtype=torch.float32)
    near = 2.0
    behind = torch.nextafter(torch.nextafter(torch.tensor(near), torch.tensor(3.0)), torch.tensor(3.0)).item()
    means = torch.tensor([[0.0, 0.0, behind], [0.0, 0.0, near], [0.0, 0.0, 7.0]])
    opacities = torch.tensor([0.9, 0.9, 0.9])
    colors = torch.eye(3)
    rgb = rasterize(means, quats, scales, opacities, colors, viewmats, Ks, 32, 32, tile_size=1)[0]
    centre = rgb[0, 16, 16]
    assert centre[0] > 5 * centre[1]  # row 0 (red, behind by 2 ulps) is in front


@pytest.mark.parametrize("device", DEVICES)
def test_projection_zeroes_every_tile_range(device, monkeypatch):
    """The projection zeroes the tile ranges in a loop over its B*N threads: with 6 Gaussians and 480 one-pixel
    tiles, ranges poisoned before it runs come out of the binning as from a clean buffer, and the images match."""
    import codecsplat_warp.ops.raster as raster_ops

    monkeypatch.setattr(raster_ops, "_graphs_enabled", lambda: False)  # the eager launches, poisoned
    inputs = [t.to(device) for t in make_scene(6, 24, 20, seed=2)]
    means, quats, scales, opacities, colors, viewmats, Ks, background, settings = raster_ops._prepare(
        *inputs, 24, 20, 0.01, 1e10, None, "classic", None, True, 1, 1e-4
    )
    checked = (means, quats, scales, opacities, colors, background, viewmats, Ks,
               raster_ops._leave_out_ranges(None, viewmats, means), settings,
               raster_ops.DEFAULT_MAX_INTERSECTION_BYTES)  # fmt: skip
    clean_outputs, clean = raster_ops._render(*checked)
    project = raster_ops._project

    def poisoned(*args, **kwargs):
        inspect.signature(project).bind(*args, **kwargs).arguments["ranges"].fill_(7)
        return project(*args, **kwargs)

    monkeypatch.setattr(raster_ops, "_project", poisoned)
    outputs, saved = raster_ops._render(*checked)
    assert 0 < outputs[4] < 480 and (clean.ranges == 0).all(dim=1).sum() > 100
    assert torch.equal(saved.ranges, clean.ranges)
    assert torch.equal(outputs[0], clean_outputs[0])


@pytest.fixture
def speculating(monkeypatch):
    """Speculative binning on every device (the CPU included), with no guess from earlier calls; yields the list
    of the capacities of every emit launch (0: the one-thread launch that only publishes the key layout)."""
    import codecsplat_warp.ops.raster as raster_ops

    monkeypatch.setattr(raster_ops, "SPECULATIVE_DEVICE_TYPES", ("cpu", "cuda"))
    monkeypatch.setattr(raster_ops, "_speculations", {})
    emit = raster_ops._emit
    capacities = []

    def spy(binning, capacity, *args):
        capacities.append(capacity)
        return emit(binning, capacity, *args)

    monkeypatch.setattr(raster_ops, "_emit", spy)
    with raster_ops.forward_graphs(False):  # the eager launches' speculation (graphs: tests/test_raster_graphs.py)
        yield capacities


def render_with_gradients(scene, size, tile_size):
    """Images and the gradients of a random weighting of them (as :func:`render_both`, without the reference)."""
    leaves = [t.detach().clone().requires_grad_() for t in scene[:5]]
    rgb, depth, alpha, meta = rasterize(*leaves, *scene[5:], size, size, tile_size=tile_size)
    g = torch.Generator().manual_seed(2)
    loss = sum((o * torch.rand(o.shape, generator=g, dtype=o.dtype).to(o.device)).sum() for o in (rgb, depth, alpha))
    return [rgb, depth, alpha, meta.radii, *torch.autograd.grad(loss, leaves)], meta.intersection_count


def assert_same_render(a, b):
    """Images and radii bit for bit; gradients to float32 rounding (CUDA's atomic sums run in no fixed order)."""
    for x, y in zip(a[:4], b[:4]):
        assert torch.equal(x, y)
    for x, y in zip(a[4:], b[4:]):
        assert torch.equal(x, y) if x.device.type == "cpu" else relative_error(x, y) < 1e-5


def exact_render(scene, size, tile_size):
    """:func:`render_with_gradients` without speculation."""
    import codecsplat_warp.ops.raster as raster_ops

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(raster_ops, "SPECULATIVE_DEVICE_TYPES", ())
        return render_with_gradients(scene, size, tile_size)


@pytest.mark.parametrize("device", DEVICES)
def test_speculative_binning_renders_like_the_exact_one(device, speculating):
    """The first call of a shape bins after the host read, exactly; the next ones emit, sort and composite into the
    guessed capacity (count + 1/8 + 1024, padded) before it, once each, and render the same images, bit for bit,
    and gradients (see :func:`assert_same_render`)."""
    scene = [t.to(device) for t in make_scene(40, 24, 24, 2, dtype=torch.float32, seed=8)]
    exact, count = exact_render(scene, 24, 16)
    assert speculating == [0, count]  # the one-thread launch that publishes the key layout, then the exact emit
    speculating.clear()
    for _ in range(3):
        assert_same_render(render_with_gradients(scene, 24, 16)[0], exact)
    assert speculating == [0, count] + [count + count // 8 + 1024] * 2


def scene_with_more_intersections(scene, factor):
    return [scene[0], scene[1], scene[2] * factor, *scene[3:]]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize(
    "first, second, size, tile_size, wrong",
    [
        ("few", "many", 32, 1, "capacity"),  # the guessed capacity is too small (3,981 + 1/8 + 1024 < 10,843)
        ((2.0, 2.9), (0.02, 5e9), 64, 1, "key dtype"),  # a 32-bit key guessed, a 64-bit key needed (4096 tiles)
        ((2.0, 2.01), (2.0, 7.0), 32, 16, "sort bits"),  # a 24-bit sort guessed (2 tile + 17 depth bits), 26 needed
    ],
)
def test_a_wrong_guess_bins_again_exactly(device, first, second, size, tile_size, wrong, speculating):
    """A call whose guess from the call before does not hold its intersections emits, sorts and composites them
    again into exact buffers (over the first compositing's outputs), and renders as without speculation."""
    import codecsplat_warp.ops.raster as raster_ops

    def scene_for(kind):
        if kind in ("few", "many"):
            scene = make_scene(40, size, size, seed=9)
            return scene_with_more_intersections(scene, 1.0 if kind == "few" else 4.0)
        return scene_at_depths(*kind, size=size)

    scenes = [[t.to(device) for t in scene_for(kind)] for kind in (first, second)]
    exact, count = exact_render(scenes[1], size, tile_size)
    render_with_gradients(scenes[0], size, tile_size)
    guess = next(iter(raster_ops._speculations.values()))
    speculating.clear()
    assert_same_render(render_with_gradients(scenes[1], size, tile_size)[0], exact)
    assert speculating == [guess.capacity, count]
    after = next(iter(raster_ops._speculations.values()))
    if wrong == "capacity":
        assert count > guess.capacity
    elif wrong == "key dtype":
        assert (guess.key_dtype, after.key_dtype) == (torch.uint32, torch.int64)
    else:
        assert (guess.end_bit, after.end_bit) == (24, 32)


def test_speculative_capacity_is_cut_to_the_sort_budget(speculating):
    """A guess larger than ``max_intersection_bytes`` allows is cut to it: a budget of exactly the count renders,
    one byte less raises the typed error."""
    scene = make_scene(30, 32, 32)
    count = rasterize(*scene, 32, 32)[3].intersection_count
    speculating.clear()
    rasterize(*scene, 32, 32, max_intersection_bytes=16 * count)
    assert speculating == [count]
    with pytest.raises(RasterMemoryError, match=f"{count:,} tile intersections need {16 * count:,} bytes"):
        rasterize(*scene, 32, 32, max_intersection_bytes=16 * count - 1)


def test_speculations_round_the_sort_bits_and_forget_the_oldest_shape(speculating):
    """The guessed sort covers whole 8-bit radix digits of the key (at most its width); the guesses of 64 shapes
    are kept, the least recent one dropped first."""
    import codecsplat_warp.ops.raster as raster_ops

    for bits, key_dtype, end_bit in [(0, torch.uint32, 0), (19, torch.uint32, 24), (32, torch.uint32, 32),
                                     (33, torch.int64, 40), (62, torch.int64, 64)]:  # fmt: skip
        raster_ops._remember("shape", 800, SortKey(0, 0, 0, bits))
        assert raster_ops._speculations["shape"] == raster_ops._Speculation(800 + 100 + 1024, key_dtype, end_bit)
    for k in range(64):
        raster_ops._remember(k, 1, SortKey(0, 0, 0, 8))
    assert len(raster_ops._speculations) == 64 and "shape" not in raster_ops._speculations
    raster_ops._remember(0, 1, SortKey(0, 0, 0, 8))  # 0 becomes the most recent: 1 goes next
    raster_ops._remember("new", 1, SortKey(0, 0, 0, 8))
    assert 0 in raster_ops._speculations and 1 not in raster_ops._speculations


_DEBUG_SPECULATION_SCRIPT = """
import sys
import warp as wp
wp.config.mode = "debug"  # every array access bounds-checked: an out-of-bounds one aborts the process
import codecsplat_warp.ops.raster as raster_ops
from codecsplat_warp.ops.raster import rasterize
sys.path.insert(0, sys.argv[1])
from test_raster import make_scene, scene_at_depths, scene_with_more_intersections
raster_ops.SPECULATIVE_DEVICE_TYPES = ("cpu",)
for first, second, tile_size in [((2.0, 2.9), (1.0, 9.0), 1), ((2.0, 2.01), (2.0, 7.0), 16)]:
    for scene in (scene_at_depths(*first), scene_at_depths(*second), scene_at_depths(*second)):
        rasterize(*scene, 32, 32, tile_size=tile_size)
base = make_scene(40, 32, 32, seed=9)
for factor in (1.0, 2.0, 2.0):
    rasterize(*scene_with_more_intersections(base, factor), 32, 32, tile_size=1)
print("in bounds")
"""


def test_speculative_binning_stays_in_bounds_in_warp_debug_mode():
    """Hits and every kind of wrong guess (a too short buffer, a 32-bit key where a 64-bit one is needed, too few
    sorted bits) run with Warp's bounds checks on (in a subprocess: a failed check aborts the process). The emit
    writes no further than the guessed capacity, tile_ranges and the compositing read only inside it.

    On one thread: Warp's debug-mode CPU kernels check their tile arena through one process-wide pointer on x86-64
    (native/tile.h: the JIT has no thread-local storage), which launches running at once on several threads race on;
    release builds never read it."""
    tests = pathlib.Path(__file__).resolve().parent
    env = {**os.environ, THREADS_VARIABLE: "1"}
    result = subprocess.run([sys.executable, "-c", _DEBUG_SPECULATION_SCRIPT, str(tests)], capture_output=True,
                            text=True, timeout=600, cwd=tests.parent, env=env)  # fmt: skip
    assert result.returncode == 0 and "in bounds" in result.stdout, result.stderr[-2000:]
