"""Synthetic camera rigs and depth maps for tests, ``selfcheck`` and benchmarks.

Rigs use OpenCV axes and look roughly along +z at a scene 2-4 units away (see :mod:`codecsplat_warp.cameras`).
"""

from __future__ import annotations

import math

import torch

from .cameras import Cameras, intrinsics_matrix


def rotation(yaw: float, pitch: float, roll: float) -> torch.Tensor:
    """[3,3] float64 rotation from yaw (about y), pitch (about x) and roll (about z), radians."""
    cy, sy, cp, sp, cr, sr = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch), math.cos(roll), math.sin(roll)
    Ry = torch.tensor([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]], dtype=torch.float64)
    Rx = torch.tensor([[1, 0, 0], [0, cp, -sp], [0, sp, cp]], dtype=torch.float64)
    Rz = torch.tensor([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1]], dtype=torch.float64)
    return Ry @ Rx @ Rz


def make_rig(num_views: int, width: int, height: int, dtype=torch.float64, device="cpu", seed: int = 0,
             baseline: float = 0.25, offset=(0.0, 0.0, 0.0)) -> Cameras:
    """V cameras on a short horizontal arc, slightly rotated towards the scene centre, random principal points."""
    g = torch.Generator().manual_seed(seed)
    c2w = torch.eye(4, dtype=torch.float64).repeat(num_views, 1, 1)
    for v in range(num_views):
        x = (v - (num_views - 1) / 2) * baseline
        jitter = (torch.rand(3, generator=g, dtype=torch.float64) - 0.5) * 0.1
        c2w[v, :3, :3] = rotation(-0.15 * x + float(jitter[0]), float(jitter[1]), float(jitter[2]))
        c2w[v, :3, 3] = torch.tensor([x, 0.05 * v, 0.0], dtype=torch.float64) + torch.tensor(offset, dtype=torch.float64)
    f = 0.9 * max(width, height)
    fx = torch.full((num_views,), f, dtype=torch.float64) * (1 + 0.05 * torch.rand(num_views, generator=g, dtype=torch.float64))
    fy = fx * (1 + 0.01 * torch.rand(num_views, generator=g, dtype=torch.float64))
    cx = width / 2 + (torch.rand(num_views, generator=g, dtype=torch.float64) - 0.5)
    cy = height / 2 + (torch.rand(num_views, generator=g, dtype=torch.float64) - 0.5)
    near = torch.full((num_views,), 0.5, dtype=torch.float64)
    far = torch.full((num_views,), 20.0, dtype=torch.float64)
    cams = Cameras.from_c2w(intrinsics_matrix(fx, fy, cx, cy), c2w, near, far, width, height)
    return cams.to(device=device, dtype=dtype)


def smooth_depth(num_views: int, height: int, width: int, dtype=torch.float64, device="cpu", seed: int = 1,
                 lo: float = 2.0, hi: float = 4.0) -> torch.Tensor:
    """[V,H,W] smooth random depth in [lo, hi] (bilinearly upsampled noise)."""
    g = torch.Generator().manual_seed(seed)
    coarse = torch.rand(num_views, 1, 3, 3, generator=g, dtype=torch.float64)
    fine = torch.nn.functional.interpolate(coarse, size=(height, width), mode="bilinear", align_corners=True)[:, 0]
    return (lo + (hi - lo) * fine).to(device=device, dtype=dtype)


def random_gaussians(n, width=16, height=16, cameras=1, sh_degree=None, dtype=torch.float64, device="cpu", seed=0):
    """Random Gaussians 2-4 units in front of ``cameras`` pinhole cameras slightly apart along x.

    Returns [means [N,3], quats [N,4], scales [N,3], opacities [N], colors [N,3] or SH [N,(d+1)^2,3],
    viewmats [B,4,4] world-to-camera, Ks [B,3,3] pixels], in the argument order of ``rasterize``.
    """
    g = torch.Generator().manual_seed(seed)

    def rand(*shape):
        return torch.rand(*shape, generator=g, dtype=dtype)

    means = (rand(n, 3) - 0.5) * torch.tensor([1.6, 1.2, 2.0], dtype=dtype) + torch.tensor([0, 0, 3.0], dtype=dtype)
    quats = rand(n, 4) - 0.5
    scales = rand(n, 3) * 0.15 + 0.03
    opacities = rand(n) * 0.9 + 0.05
    if sh_degree is None:
        colors = rand(n, 3)
    else:
        colors = (rand(n, (sh_degree + 1) ** 2, 3) - 0.5) * 0.6
    viewmats = torch.eye(4, dtype=dtype).repeat(cameras, 1, 1)
    viewmats[:, 0, 3] = torch.linspace(0.0, 0.3, cameras, dtype=dtype)
    f = 1.1 * max(width, height)
    Ks = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=dtype).repeat(cameras, 1, 1)
    tensors = [means, quats, scales, opacities, colors, viewmats, Ks]
    return [t.to(device) for t in tensors]
