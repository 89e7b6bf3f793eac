"""FeatHead (paper Eq. 2): the Gaussian-generation feature F_g = FeatHead(I, F_mv, P_depth).

Design choice: **F_g is [V, C_F, H/2, W/2] with C_F = 32** for the ``re10k`` / ``dl3dv`` presets (8 for ``tiny``).

* The codec (stage 2) entropy-codes this tensor, so it must be compact: at 1/2 resolution and 32 channels
  it holds 8 values per pixel, against 3 for the image itself before the codec's own analysis transform
  downsamples it further; a full-resolution F_g would quadruple the codec's input for no new information.
* It must still carry everything the decoder needs with no access to the images: per-pixel colour (the
  Gaussian head upsamples F_g x2 by a learned sub-pixel convolution, so a 2x2 block of pixels, i.e. 12
  colour values, sits in each 32-channel cell), depth cues for the decoder's depth head, and opacity/scale
  cues. At 1/4 resolution the same budget would need 48 colour values per cell, too many for a compact C_F.
* The 1/2 grid also gives the depth-guided refiner and the Warp reprojection 4x more samples than the
  matching grid at a modest cost.

The image enters losslessly as a 2x2 space-to-depth block (12 channels); F_mv and P_depth are upsampled
bilinearly from the 1/4 matching grid.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from ..nn.config import FEATURE_STRIDE, ModelConfig
from ..nn.layers import conv_stack, resize


class FeatHead(nn.Module):
    """Eq. 2: images [V,3,H,W] in [0,1], F_mv [V,C,h,w], P_depth [V,D,h,w] -> F_g [V,C_F,H/2,W/2]."""

    def __init__(self, config: ModelConfig):
        super().__init__()
        in_channels = 3 * FEATURE_STRIDE**2 + config.cnn_channels + config.depth_candidates
        self.net = conv_stack(in_channels, config.head_channels, config.feature_channels, blocks=2)

    def forward(self, images: torch.Tensor, features: torch.Tensor, prob: torch.Tensor) -> torch.Tensor:
        pixels = F.pixel_unshuffle(images * 2.0 - 1.0, FEATURE_STRIDE)
        h, w = pixels.shape[-2:]
        matching = resize(torch.cat([features, prob.to(features.dtype)], dim=1), h, w)
        return self.net(torch.cat([pixels.to(matching.dtype), matching], dim=1))
