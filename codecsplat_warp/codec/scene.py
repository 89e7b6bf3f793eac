"""What the decoder returns for a scene bitstream."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..cameras import Cameras
from ..gaussians import Gaussians
from .bitstream import Header


@dataclass
class DecodedScene:
    """A decoded scene (paper §3.4), built from the bitstream alone.

    Attributes:
        gaussians: the N = V*H*W world-space Gaussians (float32 unless the model is float64).
        cameras: the V context cameras stored in the bitstream.
        depth: [V,H,W] decoder-side depth D^ (metric, inside each view's near/far).
        lam: the lambda the scene was coded at.
        header: the parsed :class:`~codecsplat_warp.codec.bitstream.Header`.
        latents: per latent level (coarsest first), the decoded residual symbols int64 [V,C_l,h_l,w_l]
            (what must agree bit-exactly between encoder and decoder, across devices).
    """

    gaussians: Gaussians
    cameras: Cameras
    depth: torch.Tensor
    lam: float
    header: Header
    latents: list[torch.Tensor]


@dataclass
class EncodedScene:
    """What the encoder produces for a scene, with the numbers behind the bytes.

    Attributes:
        data: the self-contained scene bitstream.
        feature_bytes: range-coded payload bytes of each view's feature stream (framing excluded).
        latents: per latent level (coarsest first), the coded residual symbols int64 [V,C_l,h_l,w_l] (CPU).
        estimated_bits: [V] ideal code length of each view's latents under the discrete model (Eq. 7).
        rdo: the encoder-side optimisation's result (``codecsplat_warp.model.rdo.RDOResult``: steps, seconds,
            why it stopped, its checks), None for the amortised encoder alone.
    """

    data: bytes
    feature_bytes: list[int]
    latents: list[torch.Tensor]
    estimated_bits: torch.Tensor
    rdo: object | None = None
