"""The optimisation's loss: the decoder from the optimised tensors, the context renders and the terms of
:func:`rdo_loss` (the package docstring gives the formula)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch
from torch.nn import functional as F
from torch.profiler import record_function

from ...cameras import Cameras
from ...codec.latent import LAMBDA_MAX, CompressedLatents
from ...errors import InputError
from ...gaussians import Gaussians
from ...nn.config import FEATURE_STRIDE
from .presets import RDOConfig


CROSS_VIEW_ALPHA_FLOOR = 0.05
"""The least alpha :func:`cross_view_error` divides a colour by (where the other views barely cover a pixel, its
weight is as small)."""


@dataclass
class RDOTarget:
    """The fixed inputs of a run: context ``images`` [V,3,H,W], ``cameras``, ``lam``, the decoder's
    ``neighbours`` [V,M], the renderer's ``depth_range`` (near, far), the amortised ``latents`` and decoder's normalised
    inverse depth ``s_start`` [V,H,W] (None when no term needs it), and the perceptual term's
    ``perceptual_distance`` (renders [V,3,H,W] -> their mean distance to the context images, 0-dim;
    :func:`perceptual_distance`; None without a perceptual term) and the ``context_loss`` of the run's settings
    (:func:`context_loss`)."""

    images: torch.Tensor
    cameras: Cameras
    lam: float
    neighbours: torch.Tensor
    depth_range: tuple[float, float]
    latents: list[torch.Tensor]
    s_start: torch.Tensor | None
    perceptual_distance: Callable[[torch.Tensor], torch.Tensor] | None = None
    context_loss: Callable[..., tuple[torch.Tensor, torch.Tensor]] | None = None


class PerceptualDistance(torch.nn.Module):
    """The perceptual term's distance: the mean over views of the ``network``'s distance (LPIPS'
    ``unit_features`` and ``distance``) between renders [V,3,H,W] (clamped to [0, 1]) and the context images whose
    unit features are ``target_units``; 0-dim float32."""

    def __init__(self, network: torch.nn.Module, target_units: list[torch.Tensor]):
        super().__init__()
        self.network = network
        self.target_units = target_units

    def forward(self, rgb: torch.Tensor) -> torch.Tensor:
        return self.network.distance(self.network.unit_features(rgb.clamp(0.0, 1.0)), self.target_units).mean()


class ContextLoss(torch.nn.Module):
    """The loss's terms that every run has, from the context renders and the bits:
    ``lam / LAMBDA_MAX * (MSE + cross_view_weight * cross) + rate_weight * bpp`` (:func:`cross_view_error` only with
    a cross-view weight). Called with the rasterizer's ``rgb`` [V,3,H,W] (or [2V,3,H,W] with the cross-view renders
    after the context views', :func:`render_context_views`), the estimated ``bits`` (0-dim float32) and, with the
    cross-view term, its ``alpha`` [2V,H,W]; returns ``(loss, [mse, cross, bpp])``, float32 (cross 0 without the
    term)."""

    def __init__(self, images: torch.Tensor, lam: float, cross_view_weight: float, rate_weight: float):
        super().__init__()
        self.images = images
        self.distortion_weight = lam / LAMBDA_MAX
        self.cross_view_weight = cross_view_weight
        self.rate_weight = rate_weight

    def forward(self, rgb: torch.Tensor, bits: torch.Tensor, *alpha: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
        V = self.images.shape[0]
        mse = F.mse_loss(rgb[:V], self.images)
        bpp = bits / self.images[:, 0].numel()
        cross = torch.zeros_like(mse)
        distortion = mse
        if self.cross_view_weight > 0:
            cross = cross_view_error(rgb[V:], alpha[0][V:], self.images)
            distortion = distortion + self.cross_view_weight * cross
        loss = self.distortion_weight * distortion + self.rate_weight * bpp
        return loss, torch.stack([mse, cross, bpp])


Decoded = tuple[torch.Tensor, torch.Tensor, Gaussians]
"""What the decoder makes of the latents: (estimated bits of all views, 0-dim; S [V,H,W]; the Gaussians)."""


def decode_variables(model, variables: list[torch.Tensor], target: RDOTarget, variable: str,
                     generator: torch.Generator | None = None, noise: list[torch.Tensor] | None = None,
                     lambda_embedding: torch.Tensor | None = None, temperature: torch.Tensor | None = None,
                     held_offsets: list[torch.Tensor] | None = None) -> Decoded:
    """The decoder from the optimised tensors -> :data:`Decoded`: the codec's pass in the model's mode from the
    latents (``variable="latents"``: ``variables`` are the latents, :meth:`LatentCodec.forward_latents`) or from
    F_c (``"feature"``: ``variables`` is [F_c], through the analysis and the posterior), then the depth head,
    R_post, the GS head and the 2D->3D map. ``generator``/``noise``/``lambda_embedding``/``temperature``/
    ``held_offsets``: see :meth:`LatentCodec.forward_latents` (``held_offsets`` with the latents only)."""
    cameras = target.cameras
    if held_offsets is not None and variable != "latents":
        raise InputError("held rounding offsets apply when the latents are optimised (variable='latents')")
    with record_function("codec"):
        if variable == "latents":
            coded = model.codec.forward_latents(variables, target.lam, cameras.height // FEATURE_STRIDE,
                                                cameras.width // FEATURE_STRIDE, generator, noise, lambda_embedding,
                                                temperature, held_offsets)
        else:
            coded = model.codec(variables[0], target.lam, generator, noise, lambda_embedding, temperature)
    s, _, gaussians = model.decode_feature(coded.feature, cameras, target.neighbours)
    return coded.bits.sum(), s, gaussians


def rdo_loss(model, variables: list[torch.Tensor], target: RDOTarget, config: RDOConfig,
             generator: torch.Generator | None = None, compressed: CompressedLatents | None = None,
             decoder: Callable[..., Decoded] | None = None, temperature: float | None = None
             ) -> tuple[torch.Tensor, dict]:  # fmt: skip
    """The loss of the module docstring and its parts (``mse``, ``cross``, ``depth``, ``bpp`` as 0-dim tensors).

    ``variables``: the optimised tensors (:attr:`RDOConfig.variable`). With ``compressed`` (a real coding of
    them), its decoder feature and discrete-model bits replace the
    training quantiser's: the loss the encoder measures at a check. ``decoder`` replaces :func:`decode_variables`
    (:func:`step_decoder`). ``temperature``: of annealed rounding (:attr:`RDOConfig.rounding`; None: noisy).
    """
    cameras, images = target.cameras, target.images
    autocast = torch.autocast(images.device.type, dtype=torch.bfloat16,
                              enabled=config.precision == "bfloat16")
    with autocast:
        if compressed is not None:
            bits = compressed.bits.sum().to(images.device, torch.float32)
            s, _, gaussians = model.decode_feature(compressed.feature, cameras, target.neighbours)
        elif decoder is not None:
            bits, s, gaussians = decoder(variables, generator, temperature)
        else:
            annealing = None if temperature is None else torch.full((), temperature, device=images.device)
            bits, s, gaussians = decode_variables(model, variables, target, config.variable, generator,
                                                  temperature=annealing)
    rendered = render_context_views(model, gaussians, target, config.cross_view_weight > 0)
    head = target.context_loss
    if (head.cross_view_weight, head.rate_weight) != (config.cross_view_weight, config.rate_weight):
        raise InputError("rdo_loss needs the RDOTarget that rdo_target made for the same cross-view and rate weights")
    with record_function("loss"):
        loss, values = head(rendered[0], bits.float(), *rendered[1:])
        loss, values = loss.clone(), values.clone()  # a graph's outputs are overwritten by its next replay
    parts = {"mse": values[0], "bpp": values[2]}
    if config.cross_view_weight > 0:
        parts["cross"] = values[1]
    extra = []
    if config.perceptual_weight > 0:
        with record_function("perceptual"):
            parts["perceptual"] = target.perceptual_distance(rendered[0][:cameras.num_views]).clone()
        extra.append(config.perceptual_weight * parts["perceptual"])
    if config.depth_weight > 0 and target.s_start is not None:
        parts["depth"] = (s.float() - target.s_start).abs().mean()
        extra.append(config.depth_weight * parts["depth"])
    if extra:
        loss = loss + target.lam / LAMBDA_MAX * sum(extra)
    if config.anchor_weight > 0:
        moved = variables if compressed is None else compressed.latents
        parts["anchor"] = torch.stack([(z - z0).square().mean() for z, z0 in zip(moved, target.latents)]).mean()
        loss = loss + config.anchor_weight * parts["anchor"]
    return loss, parts


def render_context_views(model, gaussians: Gaussians, target: RDOTarget, cross_views: bool
                         ) -> tuple[torch.Tensor] | tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """The decoded Gaussians rendered into the context cameras: ``(rgb [V,3,H,W],)``; with ``cross_views``
    ``(rgb [2V,3,H,W], alpha [2V,H,W])``, the second V each context view rendered from the other views' Gaussians
    alone (premultiplied), in the same rasterizer call (its ``leave_out``). ``gaussians`` are the decoder's V*H*W
    pixel-aligned Gaussians, view-major."""
    cameras = target.cameras
    if not cross_views:
        return (model.render(gaussians, cameras, depth_range=target.depth_range)["rgb"],)
    twice, leave_out = cameras.memoized("rdo_cross_views", lambda: _cross_view_cameras(gaussians, cameras))
    out = model.render(gaussians, twice, depth_range=target.depth_range, leave_out=leave_out)
    return out["rgb"], out["alpha"]


def _cross_view_cameras(gaussians: Gaussians, cameras: Cameras) -> tuple[Cameras, torch.Tensor]:
    """The context cameras twice and the ``leave_out`` ranges [2V,2] that make the second V render each view
    without its own Gaussians (the first V render all)."""
    own = gaussians.view_ranges(cameras.num_views).to(torch.int32)
    return Cameras.concat([cameras, cameras]), torch.cat([torch.zeros_like(own), own])


def cross_view_error(rgb: torch.Tensor, alpha: torch.Tensor, images: torch.Tensor) -> torch.Tensor:
    """How badly the other views' Gaussians predict each context view: 0-dim, the mean over views.

    ``rgb`` [V,3,H,W] (premultiplied) and ``alpha`` [V,H,W] render view v from the Gaussians of every other view
    alone (:func:`render_context_views`); where they cover it, their colour divided by their alpha (at least
    :data:`CROSS_VIEW_ALPHA_FLOOR`) is compared with the photograph ``images`` [V,3,H,W], each pixel's squared
    error weighted by that alpha (detached) and the weights normalised per view. What the other views leave
    uncovered costs nothing, and making their Gaussians transparent does not lower the error (rendering them over
    the photograph instead rewarded transparency: 2 views, 17.05 dB against 17.33 without the term)."""
    alpha = alpha[:, None]
    weight = alpha.detach()
    squared = (rgb / alpha.clamp_min(CROSS_VIEW_ALPHA_FLOOR) - images).square()
    per_view = (weight * squared).sum(dim=(1, 2, 3)) / (squared.shape[1] * weight.sum(dim=(1, 2, 3))).clamp_min(1e-6)
    return per_view.mean()


def psnr_of_mse(mse: float) -> float:
    """PSNR in dB (peak 1) of a mean squared error, at most 120 dB."""
    return -10.0 * math.log10(max(mse, 1e-12))
