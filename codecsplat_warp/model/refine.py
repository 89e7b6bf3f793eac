"""Depth-guided multi-view refiner R (paper Eqs. 3-5), used before the codec (R_pre) and after it (R_post).

``F_out = F + R(F, A(F, D), S)`` where ``A`` is the Warp reprojection average
(:func:`codecsplat_warp.ops.geometry.reproject_average`: each view's pixels are back-projected with its own
depth, projected into the neighbour views and the neighbours' features sampled and averaged) and ``S`` the
normalised inverse depth (Eq. 18). The paper feeds ``D^-1``; ``S`` is the same quantity affinely rescaled
per view by its near/far bounds, which makes the input independent of the scene's arbitrary world scale.
A validity channel (1 where at least one neighbour saw the point) tells R where ``A`` is meaningful.
The last convolution starts at zero, so an untrained refiner is the identity.
"""

from __future__ import annotations

import torch
from torch import nn

from ..cameras import Cameras
from ..nn.config import ModelConfig
from ..nn.layers import conv_stack, inverse_depth_to_grid
from ..ops.geometry import reproject_average
from .heads import normalized_from_depth


class Refiner(nn.Module):
    """Residual depth-guided refinement of a view-aligned feature [V,C_F,h,w]."""

    def __init__(self, config: ModelConfig):
        super().__init__()
        c = config.feature_channels
        self.net = conv_stack(2 * c + 2, config.refine_channels, c, blocks=2, zero_init_out=True)

    def forward(self, feature: torch.Tensor, depth: torch.Tensor, cameras: Cameras,
                neighbours: torch.Tensor | None = None) -> torch.Tensor:
        """feature [V,C_F,h,w], depth [V,H,W] (any grid; resampled to h x w), cameras at image size,
        optional neighbours [V,M] -> refined feature [V,C_F,h,w] (same dtype as ``feature``)."""
        h, w = feature.shape[-2:]
        grid_depth = inverse_depth_to_grid(depth.float(), h, w)
        aligned, count = reproject_average(feature.float(), grid_depth, cameras, neighbours=neighbours)
        s = normalized_from_depth(grid_depth, cameras.near, cameras.far)
        valid = (count > 0).to(feature.dtype)
        inputs = torch.cat([feature, aligned.to(feature.dtype), valid[:, None], s[:, None].to(feature.dtype)], dim=1)
        return feature + self.net(inputs)
