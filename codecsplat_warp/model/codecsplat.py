"""CodecSplat network, codec-free path (paper §3.2-3.4, stage 1 of §3.5).

    images, cameras --MVEnc--> F_mv, P_depth, D_enc --FeatHead--> F_g --R_pre--> F_c
    (F_c, D_enc) --GSHead--> per-pixel Gaussians --Map 2D->3D--> world Gaussians --rasterize--> images

The stage-2 codec sits between ``F_c`` and the Gaussian head; :meth:`CodecSplat.decode_gaussians` is the
part it reuses (with its own depth head and post-codec refiner, see :mod:`.heads` and :mod:`.refine`).
"""

from __future__ import annotations

import torch
from torch import nn

from ..cameras import Cameras
from ..device import check_finite, check_tensor, common_device
from ..errors import DeviceMismatchError, InputError
from ..ops.raster import rasterize
from .config import MODEL_STRIDE, ModelConfig
from .feathead import FeatHead
from .gaussians import Gaussians, map_to_world
from .heads import GaussianHead
from .mvenc import MonoBackbone, MVEnc
from .refine import Refiner

RENDER_NEAR_FRACTION = 0.5
"""Gaussians closer to a target camera than this fraction of its near bound are culled by the renderer."""

RENDER_FAR_FACTOR = 2.0
"""... and those farther than this multiple of its far bound."""


class CodecSplat(nn.Module):
    """Feed-forward Gaussian generator: context views -> F_g, F_c, D_enc, S_enc and world-space Gaussians.

    Args:
        config: sizes (see :mod:`.config` presets).
        mono_backbone: optional pretrained monocular feature extractor (see :class:`.mvenc.MonoBackbone`).
    """

    def __init__(self, config: ModelConfig, mono_backbone: MonoBackbone | None = None):
        super().__init__()
        self.config = config
        self.mvenc = MVEnc(config, mono_backbone)
        self.feat_head = FeatHead(config)
        self.refine_pre = Refiner(config)
        self.gs_head = GaussianHead(config)

    def forward(self, images: torch.Tensor, cameras: Cameras) -> dict:
        """Run the codec-free path.

        Args:
            images: [V,3,H,W] float in [0,1], V >= 2, H and W multiples of 4 equal to the cameras' size.
            cameras: the V context cameras, on the model's device.

        Returns:
            dict with ``F_mv`` [V,C,H/4,W/4], ``P_depth`` [V,D,H/4,W/4], ``F_g`` and ``F_c`` [V,C_F,H/2,W/2],
            ``D_enc`` [V,H,W] (metric, in [near, far]), ``S_enc`` [V,H,W] (Eq. 13, in [0,1]), ``neighbours``
            [V,M] and ``gaussians`` (:class:`Gaussians`, N = V*H*W, float32).

        Raises:
            InputError: bad shape, dtype, size or values; DeviceMismatchError: inputs not on the model's device.
        """
        images = self._check_inputs(images, cameras)
        enc = self.mvenc(images, cameras)
        f_g = self.feat_head(images, enc.features, enc.prob)
        f_c = self.refine_pre(f_g, enc.depth, cameras, enc.neighbours)
        return {
            "F_mv": enc.features, "P_depth": enc.prob, "F_g": f_g, "F_c": f_c, "D_enc": enc.depth,
            "S_enc": enc.normalized_depth, "neighbours": enc.neighbours,
            "gaussians": self.decode_gaussians(f_c, enc.depth, cameras),
        }

    def decode_gaussians(self, feature: torch.Tensor, depth: torch.Tensor, cameras: Cameras) -> Gaussians:
        """Eqs. 9-10: GSHead(feature [V,C_F,H/2,W/2], depth [V,H,W]) then Map 2D->3D -> world Gaussians."""
        pixels = self.gs_head(feature, depth, cameras)
        with torch.autocast(feature.device.type, enabled=False):  # world positions and SH rotations in float32
            return map_to_world(pixels, depth.float(), cameras)

    def render(self, gaussians: Gaussians, cameras: Cameras, background: torch.Tensor | None = None,
               render_depth: bool = False) -> dict:
        """Rasterize ``gaussians`` into B target ``cameras`` (float32, autocast off).

        Returns:
            dict with ``rgb`` [B,3,H,W], ``alpha`` [B,H,W], ``depth`` [B,H,W] (None unless ``render_depth``)
            and the rasterizer's ``meta``.
        """
        common_device(means=gaussians.means, K=cameras.K)
        cams = cameras.to(dtype=torch.float32)
        with torch.autocast(gaussians.means.device.type, enabled=False):
            rgb, depth, alpha, meta = rasterize(
                gaussians.means.float(), gaussians.quats.float(), gaussians.scales.float(),
                gaussians.opacities.float(), gaussians.sh.float(), cams.w2c, cams.K, cams.width, cams.height,
                near=float(cams.near.min()) * RENDER_NEAR_FRACTION, far=float(cams.far.max()) * RENDER_FAR_FACTOR,
                background=background, mode="classic", sh_degree=gaussians.sh_degree, render_depth=render_depth,
            )
        return {"rgb": rgb.permute(0, 3, 1, 2), "alpha": alpha[..., 0],
                "depth": depth[..., 0] if depth is not None else None, "meta": meta}

    def _check_inputs(self, images: torch.Tensor, cameras: Cameras) -> torch.Tensor:
        if not isinstance(cameras, Cameras):
            raise InputError(f"cameras must be a codecsplat_warp.cameras.Cameras, got {type(cameras).__name__}")
        V = cameras.num_views
        images = check_tensor("images", images, (V, 3, cameras.height, cameras.width),
                              (torch.float32, torch.float64, torch.bfloat16, torch.float16))
        if V < 2:
            raise InputError(f"images must hold at least 2 context views (multi-view matching), got {V}")
        H, W = images.shape[-2:]
        if H % MODEL_STRIDE or W % MODEL_STRIDE:
            raise InputError(f"images height and width must be multiples of {MODEL_STRIDE}, got {H}x{W}")
        param = next(self.parameters())
        if images.device != param.device or cameras.device != param.device:
            raise DeviceMismatchError(f"images on {images.device} and cameras on {cameras.device} must be on the "
                                      f"model's device {param.device}")
        check_finite("images", images)
        if bool(images.min() < 0) or bool(images.max() > 1):
            raise InputError("images must hold values in [0, 1]")
        return images.to(param.dtype)
