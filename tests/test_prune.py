"""Pruning of Gaussians that contribute nothing (codecsplat_warp.model.prune): the counts are right, and the
pruned Gaussians render exactly what all of them render, batched or one camera at a time."""

from __future__ import annotations

import pytest
import torch

from codecsplat_warp.cameras import Cameras
from codecsplat_warp.errors import DeviceMismatchError
from codecsplat_warp.model import CodecSplat
from codecsplat_warp.nn.config import get_preset
from codecsplat_warp.model.culling import render_depth_range
from codecsplat_warp.gaussians import Gaussians
from codecsplat_warp.model.prune import (OPACITY_THRESHOLD, PruneReport, depth_rounding_bound, prune_gaussians,
                                         prune_transparent)
from codecsplat_warp.ops.raster import rasterize
from codecsplat_warp.synthetic import make_rig

WIDTH, HEIGHT = 48, 32
NEAR, FAR = 1.0, 8.0
COUNTS = {"visible": 300, "transparent": 200, "behind": 150, "beyond_far": 100, "beside": 250, "too_close": 50}


def _cameras(views: int = 3) -> Cameras:
    rig = make_rig(views, WIDTH, HEIGHT, seed=4)
    near, far = torch.full((views,), 2 * NEAR, dtype=torch.float64), torch.full((views,), FAR / 2, dtype=torch.float64)
    return Cameras(K=rig.K, w2c=rig.w2c, near=near, far=far, width=WIDTH, height=HEIGHT)


def _gaussians(centres: torch.Tensor, opacities: torch.Tensor, seed: int) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    n = centres.shape[0]
    return Gaussians(means=centres.float(),
                     quats=torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1),
                     scales=0.02 + 0.08 * torch.rand(n, 3, generator=g), opacities=opacities.float(),
                     sh=0.3 * torch.randn(n, 4, 3, generator=g))


def _box(n: int, lo, hi, g: torch.Generator) -> torch.Tensor:
    lo, hi = torch.tensor(lo, dtype=torch.float64), torch.tensor(hi, dtype=torch.float64)
    return lo + (hi - lo) * torch.rand(n, 3, generator=g, dtype=torch.float64)


def categorised_scene(seed: int = 0) -> tuple[Gaussians, dict[str, int]]:
    """Gaussians in known categories for cameras at about the origin looking along +z (depth range
    (NEAR, FAR)): visible ones in the middle of the view, transparent ones there too, and opaque ones behind
    the cameras, beyond FAR, far beside the image and in front of NEAR. Shuffled."""
    g = torch.Generator().manual_seed(seed)
    c = COUNTS
    centres = torch.cat([
        _box(c["visible"] + c["transparent"], (-0.4, -0.3, 2.5), (0.4, 0.3, 4.0), g),
        _box(c["behind"], (-1.0, -1.0, -4.0), (1.0, 1.0, -0.5), g),
        _box(c["beyond_far"], (-0.5, -0.5, 2 * FAR), (0.5, 0.5, 3 * FAR), g),
        _box(c["beside"], (40.0, -1.0, 2.0), (60.0, 1.0, 5.0), g),
        _box(c["too_close"], (-0.01, -0.01, 0.2 * NEAR), (0.01, 0.01, 0.5 * NEAR), g),
    ])  # fmt: skip
    opacities = 0.2 + 0.8 * torch.rand(centres.shape[0], generator=g, dtype=torch.float64)
    opacities[c["visible"]:c["visible"] + c["transparent"]] *= 0.99 / 255 / opacities.max()
    order = torch.randperm(centres.shape[0], generator=g)
    return _gaussians(centres[order], opacities[order], seed), c


def boundary_scene(n: int = 3000, seed: int = 1) -> Gaussians:
    """Gaussians around every culling boundary: the image edges (well beyond them too), the near and the far
    plane; opacities from 0 to 1, many just above and below 1/255."""
    g = torch.Generator().manual_seed(seed)
    z = torch.cat([NEAR + 0.02 * torch.randn(n // 4, generator=g, dtype=torch.float64),
                   FAR + 0.2 * torch.randn(n // 4, generator=g, dtype=torch.float64),
                   0.5 + 12 * torch.rand(n - 2 * (n // 4), generator=g, dtype=torch.float64)])
    half_width, half_height = 0.5 * WIDTH / (0.9 * WIDTH), 0.5 * HEIGHT / (0.9 * WIDTH)
    xy = (torch.rand(n, 2, generator=g, dtype=torch.float64) - 0.5) * 3 * torch.tensor([half_width, half_height],
                                                                                      dtype=torch.float64)
    centres = torch.cat([xy * z[:, None], z[:, None]], dim=1)
    opacities = torch.where(torch.rand(n, generator=g) < 0.3, (0.5 + torch.rand(n, generator=g)) / 255,
                            torch.rand(n, generator=g)).double()
    return _gaussians(centres, opacities, seed)


def render(gaussians: Gaussians, cameras: Cameras) -> list[torch.Tensor]:
    rgb, depth, alpha, _ = rasterize(gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities,
                                     gaussians.sh, cameras.w2c.float(), cameras.K.float(), WIDTH, HEIGHT, near=NEAR,
                                     far=FAR)
    return [rgb, depth, alpha]


def assert_same_renders(pruned: Gaussians, full: Gaussians, cameras: Cameras) -> None:
    """Batched and one camera at a time, the pruned Gaussians render what all of them render."""
    for views in ([list(range(cameras.num_views))] + [[v] for v in range(cameras.num_views)]):
        for got, expected in zip(render(pruned, cameras.select(views)), render(full, cameras.select(views))):
            torch.testing.assert_close(got, expected, rtol=1e-6, atol=1e-6)


def test_counts_of_each_reason_and_identical_renders():
    gaussians, counts = categorised_scene()
    cameras = _cameras()
    kept, report = prune_gaussians(gaussians, cameras, depth_range=(NEAR, FAR))
    outside = counts["behind"] + counts["beyond_far"] + counts["beside"] + counts["too_close"]
    assert report == PruneReport(total=len(gaussians), transparent=counts["transparent"], outside_frusta=outside,
                                 kept=counts["visible"])
    assert report.pruned == len(gaussians) - len(kept) and report.to_dict()["pruned"] == report.pruned
    assert len(kept) == counts["visible"] and bool((kept.opacities >= OPACITY_THRESHOLD).all())
    assert kept.sh.shape[1:] == gaussians.sh.shape[1:] and kept.means.dtype == gaussians.means.dtype
    assert_same_renders(kept, gaussians, cameras)


def test_gaussians_at_every_culling_boundary_render_the_same_when_pruned():
    gaussians = boundary_scene()
    cameras = _cameras()
    kept, report = prune_gaussians(gaussians, cameras, depth_range=(NEAR, FAR))
    assert report.transparent > 0 and report.outside_frusta > 0 and report.kept > 0
    assert_same_renders(kept, gaussians, cameras)


def test_default_depth_range_is_the_one_codecsplat_render_uses():
    model = CodecSplat(get_preset("tiny"))
    base = _cameras(3)
    near, far = torch.tensor([2.0, 2.4, 3.0], dtype=torch.float64), torch.tensor([3.0, 3.5, 4.0], dtype=torch.float64)
    cameras = Cameras(K=base.K, w2c=base.w2c, near=near, far=far, width=WIDTH, height=HEIGHT)
    assert render_depth_range(cameras) == (1.0, 8.0)
    gaussians = boundary_scene(seed=2)
    kept, report = prune_gaussians(gaussians, cameras)
    assert report.outside_frusta > 0
    for views in ([0, 1, 2], [0], [2]):
        with torch.no_grad():
            got, expected = model.render(kept, cameras.select(views)), model.render(gaussians, cameras.select(views))
        torch.testing.assert_close(got["rgb"], expected["rgb"], rtol=1e-6, atol=1e-6)
        torch.testing.assert_close(got["alpha"], expected["alpha"], rtol=1e-6, atol=1e-6)


def test_opacity_only_without_cameras_and_the_export_names():
    gaussians, counts = categorised_scene()
    kept, report = prune_gaussians(gaussians)
    assert report == PruneReport(len(gaussians), counts["transparent"], 0, len(gaussians) - counts["transparent"])
    opaque, removed = prune_transparent(gaussians)
    assert removed == counts["transparent"] and torch.equal(opaque.means, kept.means)
    assert OPACITY_THRESHOLD == 1 / 255


def test_nothing_left_and_nothing_given():
    gaussians, _ = categorised_scene()
    invisible = Gaussians(gaussians.means + torch.tensor([0.0, 0.0, -100.0]), gaussians.quats, gaussians.scales,
                          gaussians.opacities, gaussians.sh)
    cameras = _cameras()
    kept, report = prune_gaussians(invisible, cameras, depth_range=(NEAR, FAR))
    assert len(kept) == 0 and report.kept == 0 and report.outside_frusta == len(invisible) - report.transparent
    assert_same_renders(kept, invisible, cameras)
    again, empty = prune_gaussians(kept, cameras, depth_range=(NEAR, FAR))
    assert len(again) == 0 and empty == PruneReport(0, 0, 0, 0)


def test_a_scene_too_large_for_its_near_plane_keeps_every_opaque_gaussian():
    gaussians, counts = categorised_scene()
    far_away = Gaussians(gaussians.means * 1e5, gaussians.quats, gaussians.scales, gaussians.opacities, gaussians.sh)
    cameras = _cameras()
    assert depth_rounding_bound(far_away.means, cameras) >= 0.5 * NEAR
    _, report = prune_gaussians(far_away, cameras, depth_range=(NEAR, FAR))
    assert report.outside_frusta == 0 and report.transparent == counts["transparent"]


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU visible to torch")
def test_cameras_on_another_device_are_refused():
    gaussians, _ = categorised_scene()
    with pytest.raises(DeviceMismatchError):
        prune_gaussians(gaussians, _cameras().to("cuda"))
