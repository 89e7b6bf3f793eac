"""Plain-torch references for the geometry ops (``torch.nn.functional.grid_sample`` based, dense, slow).

They materialise every warped source copy ([V,M,C,h,w]), which is exactly what the Warp kernels avoid;
they exist to check values and gradients and as the benchmark baseline.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ..cameras import Cameras


def pixel_grid(height: int, width: int, dtype: torch.dtype, device) -> torch.Tensor:
    """[H,W,3] homogeneous pixel centres (u, v, 1) with the +0.5 convention."""
    v, u = torch.meshgrid(torch.arange(height, dtype=dtype, device=device) + 0.5,
                          torch.arange(width, dtype=dtype, device=device) + 0.5, indexing="ij")
    return torch.stack([u, v, torch.ones_like(u)], dim=-1)


def unproject_reference(depth: torch.Tensor, cameras: Cameras) -> torch.Tensor:
    """[V,H,W,3] world points: c2w @ (depth * K⁻¹ (u, v, 1))."""
    V, H, W = depth.shape
    cams = cameras.to(dtype=depth.dtype).rescaled(W, H)
    rays = pixel_grid(H, W, depth.dtype, depth.device) @ torch.linalg.inv(cams.K).transpose(-1, -2)[:, None]
    cam_points = rays * depth[..., None]
    c2w = cams.c2w
    return cam_points @ c2w[:, None, :3, :3].transpose(-1, -2) + c2w[:, None, None, :3, 3]


def warp_source_reference(feat, depth_r, cameras, r, neighbours):
    """Warped source features [M,C,h,w] and validity [M,h,w] for reference view r at depths depth_r [h,w]."""
    V, C, H, W = feat.shape
    cams = cameras.to(dtype=feat.dtype).rescaled(W, H)
    rays = pixel_grid(H, W, feat.dtype, feat.device) @ torch.linalg.inv(cams.K[r]).T
    p_r = rays * depth_r[..., None]
    warped, valid = [], []
    for s in neighbours.tolist():
        rel = cams.w2c[s] @ cams.c2w[r]
        p_s = p_r @ rel[:3, :3].T + rel[:3, 3]
        z = p_s[..., 2]
        uv = (p_s @ cams.K[s].T)[..., :2] / z[..., None]
        inside = (z > 0) & (uv[..., 0] >= 0) & (uv[..., 0] <= W) & (uv[..., 1] >= 0) & (uv[..., 1] <= H)
        grid = torch.stack([2 * uv[..., 0] / W - 1, 2 * uv[..., 1] / H - 1], dim=-1)
        grid = torch.where(inside[..., None], grid, torch.zeros_like(grid))
        sample = F.grid_sample(feat[s:s + 1], grid[None], mode="bilinear", padding_mode="border", align_corners=False)
        warped.append(sample[0] * inside[None])
        valid.append(inside)
    if not warped:
        return feat.new_zeros(0, C, H, W), torch.zeros(0, H, W, dtype=torch.bool, device=feat.device)
    return torch.stack(warped), torch.stack(valid)


def reproject_average_reference(feat, depth, cameras: Cameras, neighbours: torch.Tensor):
    """(avg [V,C,h,w], count [V,h,w] int32) by grid_sample over materialised warped copies."""
    outs, counts = [], []
    for r in range(feat.shape[0]):
        warped, valid = warp_source_reference(feat, depth[r], cameras, r, neighbours[r])
        n = valid.sum(0)
        outs.append(warped.sum(0) / n.clamp(min=1).to(feat.dtype))
        counts.append(n.to(torch.int32))
    return torch.stack(outs), torch.stack(counts)


def cost_volume_reference(feat, candidates, cameras: Cameras, neighbours: torch.Tensor):
    """cost [V,D,h,w]: mean over valid sources of <f_r, warped f_s>/sqrt(C) per sweep depth."""
    V, C, H, W = feat.shape
    out = []
    for r in range(V):
        planes = []
        for d in candidates[r]:
            warped, valid = warp_source_reference(feat, d.expand(H, W), cameras, r, neighbours[r])
            corr = (warped * feat[r][None]).sum(1) / C ** 0.5
            n = valid.sum(0)
            planes.append(corr.sum(0) / n.clamp(min=1).to(feat.dtype))
        out.append(torch.stack(planes))
    return torch.stack(out)
