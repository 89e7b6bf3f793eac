"""Small convolutional building blocks shared by the CodecSplat modules (NCHW float tensors)."""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F


def group_norm(channels: int) -> nn.GroupNorm:
    """GroupNorm with up to 8 groups (batch-size independent: training runs one scene per GPU)."""
    return nn.GroupNorm(math.gcd(8, channels), channels)


def conv3x3(in_channels: int, out_channels: int, stride: int = 1) -> nn.Conv2d:
    """3x3 convolution with 'same' padding (halves H, W when ``stride=2``)."""
    return nn.Conv2d(in_channels, out_channels, 3, stride=stride, padding=1)


def zero_conv(in_channels: int, out_channels: int, kernel_size: int = 3) -> nn.Conv2d:
    """Convolution initialised to output zeros: a residual branch ending in it starts as the identity."""
    conv = nn.Conv2d(in_channels, out_channels, kernel_size, padding=kernel_size // 2)
    nn.init.zeros_(conv.weight)
    nn.init.zeros_(conv.bias)
    return conv


class ResidualBlock(nn.Module):
    """Pre-activation residual block: x + conv(relu(norm(conv(relu(norm(x)))))). Shape-preserving."""

    def __init__(self, channels: int):
        super().__init__()
        self.body = nn.Sequential(
            group_norm(channels), nn.ReLU(inplace=False), conv3x3(channels, channels),
            group_norm(channels), nn.ReLU(inplace=False), conv3x3(channels, channels),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.body(x)


def conv_stack(in_channels: int, channels: int, out_channels: int, blocks: int, zero_init_out: bool = False) -> nn.Sequential:
    """conv3x3(in->channels), ``blocks`` residual blocks, ReLU, conv3x3(channels->out).

    With ``zero_init_out`` the last convolution starts at zero (residual heads).
    """
    out = zero_conv(channels, out_channels) if zero_init_out else conv3x3(channels, out_channels)
    return nn.Sequential(conv3x3(in_channels, channels), *[ResidualBlock(channels) for _ in range(blocks)],
                         nn.ReLU(inplace=False), out)


def resize(x: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Bilinear resize of [N,C,h,w] to [N,C,height,width] (identity when the size already matches)."""
    if x.shape[-2:] == (height, width):
        return x
    return F.interpolate(x, size=(height, width), mode="bilinear", align_corners=False)


def inverse_depth_to_grid(depth: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Depth [V,H,W] resampled to [V,height,width] by area-averaging inverse depth (exact for planes).

    Averaging 1/depth rather than depth keeps thin foreground structures from being pushed back.
    """
    if depth.shape[-2:] == (height, width):
        return depth
    inverse = F.interpolate((1.0 / depth)[:, None], size=(height, width), mode="area")
    return 1.0 / inverse[:, 0]
