"""MVEnc (paper Eq. 1): multi-view matching features, depth probabilities and encoder depth.

DepthSplat-style, sized to train on one GPU:

1. a CNN maps each image to features at 1/4 resolution;
2. optional features of a pretrained monocular backbone (the *mono slot*, see :class:`MonoBackbone`;
   ``ModelConfig.mono = "vgg16"`` puts a frozen ImageNet VGG16 there) are resized to the same grid and
   added by a residual 1x1 convolution over [CNN features, mono features] that starts at zero (so a model
   trained without the branch is unchanged when it is added);
3. transformer blocks of per-view self-attention and cross-view attention: each view attends to all
   tokens of its neighbour views (all other views, or its ``k`` nearest by camera-centre distance when
   there are more than ``k + 1`` views);
4. a plane-sweep cost volume over D depths uniform in inverse depth between each view's near and far
   (the Warp op :func:`codecsplat_warp.ops.geometry.plane_sweep_cost_volume`);
5. a conv regressor turns cost volume + features into logits, a softmax over D gives ``P_depth``; with
   ``ModelConfig.photometric_window`` a second, hand-made cost volume joins it: windowed NCC of the grey-level
   images at full resolution over the same planes (:func:`codecsplat_warp.ops.mvs.photometric_cost_volume`),
   averaged to the 1/4 grid, adds its own logits through a conv stack that starts at zero (a matcher that needs
   no training data where the views are textured; a model trained without it is unchanged when it is added);
   the expected normalised inverse depth is bilinearly upsampled to full resolution and refined by a
   residual conv stack that sees the image (in logit space, so the depth stays inside [near, far]).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import torch
from torch import nn
from torch.nn import functional as F

from ..cameras import Cameras
from ..errors import InputError
from ..nn.config import MODEL_STRIDE, ModelConfig
from ..nn.layers import ResidualBlock, conv3x3, conv_stack, group_norm, resize, zero_conv
from ..ops.geometry import inverse_depth_candidates, nearest_views, plane_sweep_cost_volume
from ..ops.mvs import photometric_cost_volume
from .heads import depth_from_normalized

LOGIT_EPS = 1e-4
"""Clamp of the coarse normalised inverse depth before taking its logit (keeps the refinement finite)."""


@runtime_checkable
class MonoBackbone(Protocol):
    """The slot for a pretrained monocular backbone (e.g. a Depth Anything ViT, as in DepthSplat).

    Any ``nn.Module`` with an integer attribute ``out_channels`` whose forward maps images
    [V,3,H,W] in [0,1] to features [V,out_channels,h,w] at any resolution qualifies; MVEnc resizes them
    to the 1/4 grid and fuses them with its CNN features. Pass it as ``CodecSplat(config, mono_backbone=...)``.
    Freeze it yourself (``requires_grad_(False)``) if it should not be fine-tuned.
    """

    out_channels: int

    def __call__(self, images: torch.Tensor) -> torch.Tensor: ...


@dataclass
class MVEncOutput:
    """What MVEnc returns (V views, h x w = H/4 x W/4 grid, D depth candidates).

    Attributes:
        features: F_mv [V,C,h,w] image + cross-view matching features.
        prob: P_depth [V,D,h,w] softmax matching probabilities over the candidates.
        candidates: [V,D] candidate depths, from far (index 0) to near (index D-1).
        depth: D_enc [V,H,W] refined encoder depth at full resolution, inside [near, far].
        normalized_depth: S_enc [V,H,W] in [0,1], the normalised inverse depth of ``depth`` (Eq. 18).
        neighbours: [V,M] int64 source views used for attention and matching (the k nearest by camera distance).
    """

    features: torch.Tensor
    prob: torch.Tensor
    candidates: torch.Tensor
    depth: torch.Tensor
    normalized_depth: torch.Tensor
    neighbours: torch.Tensor


def context_neighbours(cameras: Cameras, k: int, scenes: int = 1) -> torch.Tensor:
    """int64 [V,M]: each context view's ``min(k, V / scenes - 1)`` nearest views of its own scene (``scenes``
    scenes of equally many consecutive views, see :func:`~codecsplat_warp.ops.geometry.nearest_views`)."""
    return nearest_views(cameras, min(k, cameras.num_views // scenes - 1), scenes).long()


def sine_positions(channels: int, height: int, width: int, device, dtype) -> torch.Tensor:
    """[height*width, channels] 2D sine/cosine position code (x in the first half, y in the second)."""
    quarter = channels // 4
    freqs = 1.0 / (10000.0 ** (torch.arange(quarter, device=device, dtype=torch.float32) / quarter))
    ys = torch.arange(height, device=device, dtype=torch.float32)[:, None] * freqs
    xs = torch.arange(width, device=device, dtype=torch.float32)[:, None] * freqs
    code_x = torch.cat([xs.sin(), xs.cos()], dim=-1)[None].expand(height, width, 2 * quarter)
    code_y = torch.cat([ys.sin(), ys.cos()], dim=-1)[:, None].expand(height, width, 2 * quarter)
    return torch.cat([code_x, code_y], dim=-1).reshape(height * width, channels).to(dtype)


class ImageEncoder(nn.Module):
    """CNN from images [V,3,H,W] in [0,1] to features [V,C,H/4,W/4] (two stride-2 stages of residual blocks)."""

    def __init__(self, channels: int):
        super().__init__()
        half = channels // 2
        self.net = nn.Sequential(
            nn.Conv2d(3, half, 7, stride=2, padding=3), ResidualBlock(half), ResidualBlock(half),
            conv3x3(half, channels, stride=2), ResidualBlock(channels), ResidualBlock(channels),
            group_norm(channels),
        )

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.net(images * 2.0 - 1.0)


class Attention(nn.Module):
    """Multi-head attention of queries [V,Nq,C] over keys/values [V,Nk,C] (scaled dot product)."""

    def __init__(self, channels: int, heads: int):
        super().__init__()
        self.heads = heads
        self.q = nn.Linear(channels, channels)
        self.kv = nn.Linear(channels, 2 * channels)
        self.out = nn.Linear(channels, channels)

    def forward(self, queries: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
        V, Nq, C = queries.shape
        split = lambda t: t.reshape(V, t.shape[1], self.heads, C // self.heads).transpose(1, 2)  # noqa: E731
        q = split(self.q(queries))
        k, v = (split(t) for t in self.kv(context).chunk(2, dim=-1))
        out = F.scaled_dot_product_attention(q, k, v)
        return self.out(out.transpose(1, 2).reshape(V, Nq, C))


class CrossViewBlock(nn.Module):
    """Pre-norm transformer block: self-attention in each view, cross-attention to neighbours, MLP."""

    def __init__(self, channels: int, heads: int):
        super().__init__()
        self.norm_self, self.self_attn = nn.LayerNorm(channels), Attention(channels, heads)
        self.norm_cross, self.cross_attn = nn.LayerNorm(channels), Attention(channels, heads)
        self.norm_mlp = nn.LayerNorm(channels)
        self.mlp = nn.Sequential(nn.Linear(channels, 4 * channels), nn.GELU(), nn.Linear(4 * channels, channels))

    def forward(self, tokens: torch.Tensor, neighbours: torch.Tensor) -> torch.Tensor:
        """tokens [V,N,C], neighbours [V,M] -> [V,N,C]; view v attends to the tokens of neighbours[v]."""
        x = self.norm_self(tokens)
        tokens = tokens + self.self_attn(x, x)
        x = self.norm_cross(tokens)
        context = x[neighbours].reshape(x.shape[0], -1, x.shape[2])
        tokens = tokens + self.cross_attn(x, context)
        return tokens + self.mlp(self.norm_mlp(tokens))


class MVEnc(nn.Module):
    """Eq. 1: (F_mv, D_enc, P_depth) = MVEnc(images, cameras). See the module docstring for the stages."""

    def __init__(self, config: ModelConfig, mono_backbone: MonoBackbone | None = None):
        super().__init__()
        if mono_backbone is not None and not isinstance(getattr(mono_backbone, "out_channels", None), int):
            raise InputError("mono_backbone must be an nn.Module with an integer attribute out_channels")
        self.config = config
        c = config.cnn_channels
        self.image_encoder = ImageEncoder(c)
        self.mono_backbone = mono_backbone
        self.mono_fuse = zero_conv(c + mono_backbone.out_channels, c, 1) if mono_backbone is not None else None
        self.blocks = nn.ModuleList(CrossViewBlock(c, config.attention_heads) for _ in range(config.attention_layers))
        self.regressor = conv_stack(config.depth_candidates + c, config.depth_channels, config.depth_candidates,
                                    blocks=2)
        self.photometric_regressor = (conv_stack(config.depth_candidates, config.depth_channels,
                                                 config.depth_candidates, blocks=1, zero_init_out=True)
                                      if config.photometric_window else None)
        refine = config.depth_channels
        self.refine_context = nn.Conv2d(c, refine, 1)
        self.refiner = conv_stack(3 + 1 + refine, refine, 1, blocks=1, zero_init_out=True)

    def forward(self, images: torch.Tensor, cameras: Cameras, neighbours: torch.Tensor | None = None) -> MVEncOutput:
        """images [V,3,H,W] in [0,1] (H, W multiples of 4), cameras of the same V and size, and the source views
        each view attends to and matches against, int64 [V,M] (default: its nearest, :func:`context_neighbours`)
        -> :class:`MVEncOutput`."""
        V, _, H, W = images.shape
        h, w = H // MODEL_STRIDE, W // MODEL_STRIDE
        if neighbours is None:
            neighbours = context_neighbours(cameras, self.config.neighbours)
        features = self.image_encoder(images)
        if self.mono_backbone is not None:
            mono = resize(self.mono_backbone(images), h, w).to(features.dtype)
            features = features + self.mono_fuse(torch.cat([features, mono], dim=1))
        features = self._attend(features, neighbours)
        candidates = inverse_depth_candidates(cameras, self.config.depth_candidates).float()
        cost = self._cost_volume(features, candidates, cameras, neighbours)
        logits = self.regressor(torch.cat([cost.to(features.dtype), features], dim=1))
        if self.photometric_regressor is not None:
            logits = logits + self._photometric_logits(images, candidates, cameras, neighbours).to(logits.dtype)
        prob = torch.softmax(logits.float(), dim=1)
        s_levels = torch.linspace(0.0, 1.0, prob.shape[1], dtype=prob.dtype, device=prob.device)
        coarse = (prob * s_levels[None, :, None, None]).sum(dim=1, keepdim=True)
        s = self._refine(coarse, features, images)
        depth = depth_from_normalized(s, cameras.near.to(s.dtype), cameras.far.to(s.dtype))
        return MVEncOutput(features=features, prob=prob, candidates=candidates, depth=depth, normalized_depth=s,
                           neighbours=neighbours)

    def _attend(self, features: torch.Tensor, neighbours: torch.Tensor) -> torch.Tensor:
        if not self.blocks:
            return features
        V, C, h, w = features.shape
        tokens = features.flatten(2).transpose(1, 2) + sine_positions(C, h, w, features.device, features.dtype)
        for block in self.blocks:
            tokens = block(tokens, neighbours)
        return tokens.transpose(1, 2).reshape(V, C, h, w)

    @staticmethod
    def _cost_volume(features, candidates, cameras, neighbours) -> torch.Tensor:
        """Warp plane sweep [V,D,h,w] in float32 (the kernels take float32/float64, not bfloat16)."""
        return plane_sweep_cost_volume(features.float(), candidates, cameras, neighbours=neighbours)

    def _photometric_logits(self, images, candidates, cameras, neighbours) -> torch.Tensor:
        """Logits [V,D,h,w] from the full-resolution windowed-NCC plane sweep, averaged over each 4x4 cell."""
        ncc = photometric_cost_volume(images.float(), candidates, cameras, self.config.photometric_window, neighbours)
        return self.photometric_regressor(F.avg_pool2d(ncc, MODEL_STRIDE).to(self.photometric_regressor[0].weight.dtype))

    def _refine(self, coarse: torch.Tensor, features: torch.Tensor, images: torch.Tensor) -> torch.Tensor:
        """Coarse S [V,1,h,w] -> refined S [V,H,W] in (0,1): bilinear upsampling plus a residual logit."""
        H, W = images.shape[-2:]
        up = resize(coarse, H, W).clamp(LOGIT_EPS, 1.0 - LOGIT_EPS)
        context = resize(self.refine_context(features), H, W)
        residual = self.refiner(torch.cat([images.to(context.dtype), up.to(context.dtype), context], dim=1))
        return torch.sigmoid(torch.logit(up) + residual.float())[:, 0]
