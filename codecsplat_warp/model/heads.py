"""Depth head (paper Eqs. 9-10, 18), Gaussian head (Eq. 11) and the 2D->3D map (Eq. 12).

Normalised inverse depth ``S`` in [0, 1] maps to metric depth inside the per-view bounds:
``D = 1 / (1/f + S (1/n - 1/f))`` (S = 0 is the far bound f, S = 1 the near bound n), and back by
``S = (1/D - 1/f) / (1/n - 1/f)`` (Eq. 18).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn
from torch.nn import functional as F

from ..cameras import Cameras
from ..errors import InputError
from ..gaussians import Gaussians, quat_multiply, rotate_sh, rotmat_to_quat
from ..nn.config import FEATURE_STRIDE, ModelConfig
from ..nn.layers import conv3x3, conv_stack, pixel_shuffle_conv
from ..ops.geometry import unproject

SH_HIGHER_ORDER_SCALE = 0.1
"""Raw SH outputs of degree l >= 1 are multiplied by ``0.1 * 0.25**l`` (DepthSplat's sh_mask): starts view-independent."""


def _bounds(near: torch.Tensor, far: torch.Tensor, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(1/far, 1/near - 1/far) [V] reshaped to broadcast against a [V,...] tensor ``like``; the difference is
    taken in the bounds' own dtype (float64 cameras) before the cast, so near ~ far keeps its precision."""
    if near.shape != (like.shape[0],) or far.shape != (like.shape[0],):
        raise InputError(f"near/far must have shape [{like.shape[0]}] (one bound per view), "
                         f"got {tuple(near.shape)} and {tuple(far.shape)}")
    view = (-1,) + (1,) * (like.dim() - 1)
    inv_far = 1.0 / far
    return inv_far.reshape(view).to(like.dtype), (1.0 / near - inv_far).reshape(view).to(like.dtype)


def depth_from_normalized(s: torch.Tensor, near: torch.Tensor, far: torch.Tensor) -> torch.Tensor:
    """Eq. 10: metric depth [V,...] from normalised inverse depth ``s`` [V,...] in [0,1] and bounds near/far [V]."""
    inv_far, span = _bounds(near, far, s)
    return 1.0 / (inv_far + s * span)


def normalized_from_depth(depth: torch.Tensor, near: torch.Tensor, far: torch.Tensor) -> torch.Tensor:
    """Eq. 18: normalised inverse depth S_enc [V,...] of metric depth [V,...] (0 at far, 1 at near)."""
    inv_far, span = _bounds(near, far, depth)
    return (1.0 / depth - inv_far) / span


def append_channel(x: torch.Tensor, extra: torch.Tensor) -> torch.Tensor:
    """``x`` [V,C,H,W] with ``extra`` [V,H,W] appended as channel C, in ``x``'s memory layout. A channels-last ``x``
    (the RDO's decoder heads on the CPU) gives a channels-last result; a plain ``torch.cat`` would give an NCHW one
    (the one-channel map is laid out as NCHW), which the next convolution copies back (26 ms of a 2-view RDO step on
    the 2-core EPYC)."""
    extra = extra[:, None].to(x.dtype)
    if not x.is_contiguous() and x.is_contiguous(memory_format=torch.channels_last):
        H, W = extra.shape[-2:]
        extra = torch.empty_strided(extra.shape, (H * W, 1, W, 1), dtype=x.dtype, device=x.device).copy_(extra)
    return torch.cat([x, extra], dim=1)


def _check_feature_grid(feature: torch.Tensor, height: int, width: int) -> None:
    """InputError unless ``feature`` [V,C,h,w] is on the 1/FEATURE_STRIDE grid of a height x width image."""
    if feature.dim() != 4 or feature.shape[-2:] != (height // FEATURE_STRIDE, width // FEATURE_STRIDE):
        raise InputError(f"feature must be [V,C,{height // FEATURE_STRIDE},{width // FEATURE_STRIDE}] for a "
                         f"{height}x{width} image, got {tuple(feature.shape)}")


class SubPixelUpsample(nn.Module):
    """Learned x FEATURE_STRIDE upsampling: conv3x3 to ``out * stride**2`` channels, then pixel shuffle."""

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__()
        self.conv = conv3x3(in_channels, out_channels * FEATURE_STRIDE**2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return pixel_shuffle_conv(x, self.conv, FEATURE_STRIDE)


class DepthHead(nn.Module):
    """Eqs. 9-10: normalised inverse depth S = sigmoid(DepthHead(F)) and metric depth D from a feature.

    Used by the decoder on the reconstructed feature (stage 2); the codec-free path uses D_enc.
    """

    def __init__(self, config: ModelConfig):
        super().__init__()
        c = config.head_channels
        self.body = nn.Sequential(conv_stack(config.feature_channels, c, c, blocks=1), SubPixelUpsample(c, c),
                                  nn.ReLU(inplace=False), conv3x3(c, 1))

    def forward(self, feature: torch.Tensor, cameras: Cameras) -> tuple[torch.Tensor, torch.Tensor]:
        """feature [V,C_F,h,w] -> (S [V,H,W] in (0,1), depth [V,H,W] in (near, far)) at the cameras' size."""
        _check_feature_grid(feature, cameras.height, cameras.width)
        s = torch.sigmoid(self.body(feature)[:, 0].float())
        return s, depth_from_normalized(s, cameras.near, cameras.far)


@dataclass
class PixelGaussians:
    """Per-pixel Gaussian attributes in CAMERA space, before the 2D->3D map (Eq. 11 output).

    Attributes:
        opacities: [V,H,W] in (0,1).
        offsets: [V,H,W,2] sub-pixel centre offsets (du, dv) in pixels.
        scales: [V,H,W,3] standard deviations in world units (pixel footprint times depth / focal).
        quats: [V,H,W,4] unit quaternions (w,x,y,z) rotating the Gaussian frame into the camera frame.
        sh: [V,H,W,K,3] SH colour coefficients w.r.t. camera-frame view directions, K = (degree+1)^2.
    """

    opacities: torch.Tensor
    offsets: torch.Tensor
    scales: torch.Tensor
    quats: torch.Tensor
    sh: torch.Tensor


def pixel_footprint(depth: torch.Tensor, cameras: Cameras) -> torch.Tensor:
    """[V,H,W] world size of one pixel at each ``depth`` [V,H,W] (camera z, world units) of the V ``cameras``:
    depth / focal, focal the mean of fx and fy (pixels); in ``depth``'s dtype."""
    focal = 0.5 * (cameras.K[:, 0, 0] + cameras.K[:, 1, 1])
    return depth / focal.reshape(-1, 1, 1).to(depth.dtype)


class GaussianHead(nn.Module):
    """Eq. 11: per-pixel Gaussian attributes from a feature [V,C_F,h,w] and depth [V,H,W].

    The 1/2-resolution feature is upsampled to the image grid by a learned sub-pixel convolution, the
    normalised inverse depth is appended, and a conv stack predicts 1 + 2 + 3 + 4 + 3K raw channels.
    """

    def __init__(self, config: ModelConfig):
        super().__init__()
        self.config = config
        self.num_sh = (config.sh_degree + 1) ** 2
        self.raw_channels = 1 + 2 + 3 + 4 + 3 * self.num_sh
        c = config.head_channels
        self.upsample = SubPixelUpsample(config.feature_channels, c)
        self.body = conv_stack(c + 1, c, self.raw_channels, blocks=1)
        degrees = torch.cat([torch.full((2 * l + 1,), float(l)) for l in range(config.sh_degree + 1)])
        sh_scale = torch.where(degrees > 0, SH_HIGHER_ORDER_SCALE * 0.25 ** degrees, torch.ones_like(degrees))
        self.register_buffer("sh_scale", sh_scale, persistent=False)
        # on the module's device, so that a forward pass copies nothing from the host (CUDA graph capture)
        self.register_buffer("identity_quat", torch.tensor([1.0, 0.0, 0.0, 0.0]), persistent=False)

    def forward(self, feature: torch.Tensor, depth: torch.Tensor, cameras: Cameras) -> PixelGaussians:
        """feature [V,C_F,h,w], depth [V,H,W] (metric, in the cameras' bounds) -> :class:`PixelGaussians`."""
        _check_feature_grid(feature, depth.shape[1], depth.shape[2])
        x = self.upsample(feature)
        s = normalized_from_depth(depth, cameras.near, cameras.far).clamp(0.0, 1.0)
        raw = self.body(append_channel(x, s)).permute(0, 2, 3, 1).float()
        return self._activate(raw, depth, cameras)

    def _activate(self, raw: torch.Tensor, depth: torch.Tensor, cameras: Cameras) -> PixelGaussians:
        cfg = self.config
        opacity_raw, offset_raw, scale_raw, quat_raw, sh_raw = raw.split([1, 2, 3, 4, 3 * self.num_sh], dim=-1)
        footprint = pixel_footprint(depth, cameras)[..., None]
        scale_px = cfg.scale_min_px + (cfg.scale_max_px - cfg.scale_min_px) * torch.sigmoid(scale_raw)
        identity = self.identity_quat.to(raw.dtype)
        sh = sh_raw.reshape(*sh_raw.shape[:-1], 3, self.num_sh).transpose(-1, -2) * self.sh_scale[:, None]
        return PixelGaussians(
            opacities=torch.sigmoid(opacity_raw[..., 0]),
            offsets=cfg.max_offset_px * torch.tanh(offset_raw),
            scales=scale_px * footprint,
            quats=F.normalize(quat_raw + identity, dim=-1, eps=1e-6),
            sh=sh,
        )


# --------------------------------------------------------------------------------------------------
# Eq. 12: pixel-aligned camera-space predictions to world space
#
# * centres: the pixel centre shifted by the predicted sub-pixel offset, unprojected at its depth
#   (:func:`codecsplat_warp.ops.geometry.unproject` plus the exact in-plane shift ``R_c2w (du d/fx, dv d/fy, 0)``);
# * rotations: ``q_world = q(R_c2w) * q_cam``;
# * SH colours: rotated by ``R_c2w`` per degree, so that evaluating them with world-space view directions
#   gives the colour the head predicted for the corresponding camera-space directions;
# * scales and opacities are frame-independent.
def map_to_world(pixels: PixelGaussians, depth: torch.Tensor, cameras: Cameras) -> Gaussians:
    """Eq. 12: pixel-aligned camera-space Gaussians [V,H,W,...] and depth [V,H,W] -> world :class:`Gaussians`.

    N = V*H*W Gaussians ordered view-major, then row, then column.
    """
    V, H, W = depth.shape
    if (H, W) != (cameras.height, cameras.width) or V != cameras.num_views:
        raise InputError(f"depth must be [V={cameras.num_views},{cameras.height},{cameras.width}] to match the "
                         f"cameras, got {tuple(depth.shape)}")
    c2w = cameras.c2w.to(depth.dtype)
    rot = c2w[:, :3, :3]
    focal = torch.stack([cameras.K[:, 0, 0], cameras.K[:, 1, 1]], dim=-1).to(depth.dtype)  # [V,2]
    shift = pixels.offsets.to(depth.dtype) * depth[..., None] / focal[:, None, None, :]  # [V,H,W,2] camera xy
    shift3 = torch.cat([shift, torch.zeros_like(shift[..., :1])], dim=-1)
    means = unproject(depth, cameras) + torch.einsum("vij,vhwj->vhwi", rot, shift3)
    cam_quats = rotmat_to_quat(rot)[:, None, None, :].to(pixels.quats.dtype)
    quats = quat_multiply(cam_quats.expand_as(pixels.quats), pixels.quats)
    sh = rotate_sh(pixels.sh, rot.to(pixels.sh.dtype))
    return Gaussians(
        means=means.reshape(-1, 3),
        quats=quats.reshape(-1, 4),
        scales=pixels.scales.reshape(-1, 3),
        opacities=pixels.opacities.reshape(-1),
        sh=sh.reshape(-1, sh.shape[-2], 3),
    )
