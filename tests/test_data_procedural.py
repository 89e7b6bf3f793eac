"""Procedural scenes: an RE10K-shaped sample, exact geometry, multi-view depth consistency."""

from __future__ import annotations

import pytest
import torch

from codecsplat_warp.data import ProceduralConfig, ProceduralDataset, make_dataloader, procedural_scene, render
from codecsplat_warp.data.procedural import first_hit
from codecsplat_warp.ops.geometry import reproject_average, unproject

SMALL = ProceduralConfig(width=64, height=48, num_views=2, trajectory="orbit")


def test_re10k_shaped_sample_shapes_depth_range_and_texture():
    scene = procedural_scene(1, ProceduralConfig(width=256, height=256, num_views=2))
    assert scene.images.shape == (2, 3, 256, 256) and scene.images.dtype == torch.uint8
    assert scene.depth.shape == (2, 256, 256) and bool(torch.isfinite(scene.depth).all())
    # near/far bracket the rendered depth by 10% on either side (procedural_scene's contract)
    depth_min, depth_max = float(scene.depth.min()), float(scene.depth.max())
    assert scene.cameras.near.tolist() == pytest.approx([0.9 * depth_min] * 2, rel=1e-6)
    assert scene.cameras.far.tolist() == pytest.approx([1.1 * depth_max] * 2, rel=1e-6)
    assert scene.images.float().std() > 10  # textured, not flat


def test_same_seed_same_scene_and_layouts_differ():
    a, b = procedural_scene(3, SMALL), procedural_scene(3, SMALL)
    assert torch.equal(a.images, b.images) and torch.equal(a.depth, b.depth)
    c = procedural_scene(4, SMALL)
    assert not torch.equal(a.images, c.images)
    for layout in ("room", "tabletop"):
        for trajectory in ("orbit", "forward"):
            scene = procedural_scene(5, ProceduralConfig(width=32, height=24, num_views=3, layout=layout,
                                                         trajectory=trajectory))
            assert scene.metadata["layout"] == layout and scene.metadata["trajectory"] == trajectory
            assert bool(torch.isfinite(scene.depth).all()) and bool((scene.depth > 0).all())


def _surface_distance(world, points: torch.Tensor) -> torch.Tensor:
    """[N] unsigned distance of points to the nearest primitive surface (closed-form, no ray casting)."""
    rel = points[:, None] - world.rect_centre[None]
    normal = torch.nn.functional.normalize(torch.cross(world.rect_u, world.rect_v, dim=-1), dim=-1)
    a = (rel * world.rect_u).sum(-1) / (world.rect_u ** 2).sum(-1)
    b = (rel * world.rect_v).sum(-1) / (world.rect_v ** 2).sum(-1)
    plane = torch.where((a.abs() <= 1 + 1e-6) & (b.abs() <= 1 + 1e-6), (rel * normal).sum(-1).abs(), torch.inf)
    local = torch.einsum("bji,nbj->nbi", world.box_rotation, points[:, None] - world.box_centre[None])
    q = local.abs() - world.box_half[None]
    box = (q.clamp(min=0).norm(dim=-1) + q.amax(-1).clamp(max=0)).abs()
    sphere = ((points[:, None] - world.sphere_centre[None]).norm(dim=-1) - world.sphere_radius[None]).abs()
    return torch.cat([plane, box, sphere], dim=1).amin(1)


def test_unprojected_depth_lies_on_the_surfaces():
    scene = procedural_scene(11, SMALL)
    points = unproject(scene.depth.double(), scene.cameras.to(dtype=torch.float64)).reshape(-1, 3)
    distance = _surface_distance(scene.metadata["world"], points)
    assert float((distance / scene.depth.double().reshape(-1)).max()) < 1e-5


def _project(points: torch.Tensor, cameras, view: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pixel columns, rows and depth of world points [N,3] in one view (pure torch pinhole, +0.5 centres)."""
    cam = points @ cameras.w2c[view, :3, :3].T + cameras.w2c[view, :3, 3]
    K = cameras.K[view]
    return K[0, 0] * cam[:, 0] / cam[:, 2] + K[0, 2], K[1, 1] * cam[:, 1] / cam[:, 2] + K[1, 2], cam[:, 2]


def _bilinear(image: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """[N] bilinear samples of an [H,W] image at pixel coordinates (u, v), pixel centres at +0.5."""
    H, W = image.shape
    grid = torch.stack([2 * u / W - 1, 2 * v / H - 1], dim=-1)[None, None]
    return torch.nn.functional.grid_sample(image[None, None], grid, align_corners=False, padding_mode="border")[0, 0, 0]


def test_depth_consistent_across_views_and_with_reproject_average():
    """Unproject view 0's depth, reproject into view 1 and compare with view 1's depth where visible.

    Visibility is decided exactly, by casting a ray from view 1's centre to each point; comparisons skip
    points whose 2x2 bilinear footprint in view 1 straddles a depth edge.
    """
    for seed in (21, 22, 24):
        scene = procedural_scene(seed, SMALL)
        cameras = scene.cameras.to(dtype=torch.float64)
        depth = scene.depth.double()
        H, W = depth.shape[1:]
        points = unproject(depth, cameras)[0].reshape(-1, 3)
        u, v, z = _project(points, cameras, 1)
        inside = (z > 0) & (u >= 0.5) & (u <= W - 0.5) & (v >= 0.5) & (v <= H - 0.5)
        centre = cameras.centers[1]
        t_hit, _ = first_hit(scene.metadata["world"], centre, points - centre)
        visible = inside & ((t_hit - 1).abs() < 1e-6)
        spread = (torch.nn.functional.max_pool2d(depth[1][None], 2, 1) + torch.nn.functional.max_pool2d(-depth[1][None], 2, 1))[0]
        footprint = spread[(v - 0.5).floor().long().clamp(0, H - 2), (u - 0.5).floor().long().clamp(0, W - 2)]
        checked = visible & (footprint < 0.05 * z)
        assert int(checked.sum()) > 0.2 * H * W, f"seed {seed}: too few mutually visible pixels"
        sampled = _bilinear(depth[1], u, v)
        relative = ((sampled - z) / z)[checked].abs()
        assert float(relative.quantile(0.95)) < 1e-2, f"seed {seed}: view 1 depth disagrees with view 0 unprojection"

        avg, count = reproject_average(depth[:, None].contiguous(), depth, cameras)
        reprojected = avg[0, 0].reshape(-1)
        valid = checked & (count[0].reshape(-1) == 1)
        assert int(valid.sum()) > 0.9 * int(checked.sum())
        torch.testing.assert_close(reprojected[valid], sampled[valid], rtol=1e-6, atol=1e-9)
        assert float(((reprojected - z) / z)[valid].abs().quantile(0.95)) < 1e-2


def test_render_more_views_of_the_same_world():
    scene = procedural_scene(9, SMALL)
    rgb, depth = render(scene.metadata["world"], scene.cameras.select([1]))
    assert torch.allclose(depth.float(), scene.depth[1:], rtol=1e-6)
    assert torch.equal((rgb * 255).round().clamp(0, 255).to(torch.uint8), scene.images[1:])


def test_procedural_dataset_batches():
    dataset = ProceduralDataset(4, ProceduralConfig(width=32, height=32), num_context_views=2, num_target_views=1)
    batch = next(iter(make_dataloader(dataset, batch_size=2, shuffle=False)))
    assert batch["context"]["image"].shape == (2, 2, 3, 32, 32) and batch["target"]["depth"].shape == (2, 1, 32, 32)
    assert batch["context"]["index"][0].tolist() == [0, 2] and batch["target"]["index"][0].tolist() == [1]
    assert torch.equal(dataset[1]["context"]["image"], batch["context"]["image"][1])
