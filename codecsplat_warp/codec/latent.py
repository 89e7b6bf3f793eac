"""The learned feature codec (paper Eqs. 6-7): a lambda-conditioned hierarchical VAE on F_c.

Structure (QARV / lossy-vae style, all views of a scene as one batch, each view coded independently):

* **Analysis** (bottom-up): F_c [V,C_F,h,w] (zero-padded to multiples of the coarsest stride) -> one
  feature per latent level, at strides ``f, 2f, ..., f * 2**(L-1)`` of the feature grid, ``f`` =
  ``ModelConfig.codec_finest_stride`` (4: image strides 8, 16, 32 with L = 3; 2: image strides 4 to 32 with L = 4).
* **Top-down** (the entropy model and the first half of the synthesis): from a learned constant at the
  coarsest stride, each :class:`LatentBlock` predicts the prior (mean, log-scale) of its latent from what
  the decoder already has, the posterior mean ``z`` from that and the bottom-up feature, quantises ``z``
  (see below) and merges the result back; a x2 sub-pixel upsampling leads to the next finer level.
* **Synthesis**: ``log2(f)`` x2 upsamplings from the finest latent stride back to the feature grid -> F^_c.
* **Rate control**: lambda in [:data:`LAMBDA_MIN`, :data:`LAMBDA_MAX`] is embedded (sinusoids of the
  normalised log lambda -> MLP) and every residual block applies a FiLM scale/shift of that embedding.
  Each latent level is also quantised on a lambda-dependent per-channel grid (gain units, as in Cui et al.
  2021): the latent, its prior mean and scale are multiplied by ``g = sqrt(lam / LAMBDA_MIN) *
  exp(Linear(e_lambda))`` before quantisation and divided after. The square root is the MSE-optimal step
  of high-rate theory, so bytes grow and distortion falls with lambda from the first step; the learned
  factor (zero at initialisation) refines it.

Quantisation has three forms, all driven through the same top-down pass:

All of the following happens on the gained grid (``z``, ``mu`` there mean ``g z``, ``g mu``):

* training (:class:`NoisyQuantizer`): the rate (Eq. 7) is evaluated at ``z + U(-0.5, 0.5)``, while the
  decoder path receives ``round(z - mu) + mu`` with a straight-through gradient (the "mixed" scheme of
  Minnen & Singh 2020, which keeps the decoder's training input equal to its test input);
* coding (:class:`RoundingQuantizer`): residual symbols ``s = round(z - m)`` with the prior quantised as
  in :mod:`.entropy` (mean ``m`` on a grid, scale to a table index), ``z^ = s + m``, rate from that
  discrete model (so the estimate is the ideal code length of what is coded);
* decoding (:class:`DecodingQuantizer`): the same discrete model, symbols read from the range decoders.

Bit-exact coding across devices: when coding, the lambda embedding and the top-down pass run in float64
(a float64 copy of those weights, autocast off; they work on the small latent grids, so this is cheap),
and the prior parameters are quantised as described in :mod:`.entropy`. The encoder runs exactly the
decoder's computation on the symbols it chose, so both sides derive the same prior from the same
integers. A CPU and a GPU (or two thread counts) still differ in the last bits of a float64 result
(summation order; ~1e-14 relative after the few layers of the prior path). Residual risk: a symbol's
model differs only if such a difference moves a log-scale across a table boundary (spacing 0.12) or a
mean across a grid midpoint (spacing 1/64), i.e. if the exact value lies within ~1e-13 of one: about
1e-11 per symbol, 1e-6 to 1e-5 per scene of 1e5 to 5e5 symbols. It would garble the rest of that view's
stream (the CRCs check bytes, not symbols). In float32 the same risk would be ~1e-5 per symbol, i.e.
almost every scene, hence the float64 path. The analysis and the synthesis have no influence on the
symbols' models and run in the model's dtype (bf16 autocast on CUDA is fine).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from ..errors import InputError
from ..measure import Timer, no_timer
from ..nn.config import ModelConfig
from ..nn.layers import conv3x3, pixel_shuffle_conv
from . import entropy

LAMBDA_MIN = 16.0
"""Smallest rate-distortion trade-off lambda the codec is trained for (lowest rate)."""

LAMBDA_MAX = 1024.0
"""Largest lambda (highest rate); the stage-2 loss weighs distortion by lambda / LAMBDA_MAX."""


def lambda_position(lam: float) -> float:
    """Where ``lam`` lies on the coded range, log-linearly: ``log(lam / LAMBDA_MIN) / log(LAMBDA_MAX / LAMBDA_MIN)``,
    0 at :data:`LAMBDA_MIN` and 1 at :data:`LAMBDA_MAX` (a float; outside [0, 1] for a lambda outside the range)."""
    return math.log(lam / LAMBDA_MIN) / math.log(LAMBDA_MAX / LAMBDA_MIN)


def check_lambda(lam: float) -> float:
    """``lam`` as a float; InputError unless it is finite and in [LAMBDA_MIN, LAMBDA_MAX]."""
    value = float(lam)
    if not math.isfinite(value) or not LAMBDA_MIN <= value <= LAMBDA_MAX:
        raise InputError(f"lambda must be in [{LAMBDA_MIN:g}, {LAMBDA_MAX:g}], got {lam!r}")
    return value


def num_levels(config: ModelConfig) -> int:
    """Number of latent levels L."""
    return len(config.codec_latent_channels)


def level_stride(config: ModelConfig, level: int) -> int:
    """Stride on the feature grid of latent level ``level`` (0 = coarsest): ``finest * 2**(L-1-level)``."""
    return config.codec_finest_stride * 2 ** (num_levels(config) - 1 - level)


def padding_multiple(config: ModelConfig) -> int:
    """The feature grid is zero-padded to multiples of this (the coarsest latent stride)."""
    return level_stride(config, 0)


def latent_shapes(config: ModelConfig, height: int, width: int) -> list[tuple[int, int, int]]:
    """(channels, rows, columns) of every latent level, coarsest first, for a feature grid of height x width."""
    m = padding_multiple(config)
    rows, cols = -(-height // m) * m, -(-width // m) * m
    strides = [level_stride(config, l) for l in range(num_levels(config))]
    return [(c, rows // s, cols // s) for c, s in zip(config.codec_latent_channels, strides)]


LAMBDA_FREQUENCIES = 4
"""Sinusoids of the normalised log lambda t in [0, 1]: frequencies pi * 2**k, k < 4 (smooth in lambda)."""


class LambdaEmbedding(nn.Module):
    """e_lambda [E]: ``t`` = :func:`lambda_position` of lambda, its sines and cosines
    (:data:`LAMBDA_FREQUENCIES`) and ``t`` itself -> 2-layer MLP."""

    def __init__(self, dim: int):
        super().__init__()
        frequencies = math.pi * 2.0 ** torch.arange(LAMBDA_FREQUENCIES, dtype=torch.float32)
        self.register_buffer("frequencies", frequencies, persistent=False)
        self.mlp = nn.Sequential(nn.Linear(2 * LAMBDA_FREQUENCIES + 1, dim), nn.GELU(), nn.Linear(dim, dim))

    def forward(self, lam: float) -> torch.Tensor:
        weight = self.mlp[0].weight
        t = torch.tensor([lambda_position(lam)], dtype=weight.dtype, device=weight.device)
        angles = t * self.frequencies.to(weight.dtype)
        return self.mlp(torch.cat([t, angles.sin(), angles.cos()]))


class FiLMBlock(nn.Module):
    """Residual block ``x + conv(gelu(FiLM_e(conv(gelu(x)))))``, FiLM_e a lambda-dependent scale and shift.
    Shape-preserving."""

    def __init__(self, channels: int, embedding: int):
        super().__init__()
        self.conv1 = conv3x3(channels, channels)
        self.conv2 = conv3x3(channels, channels)
        self.film = nn.Linear(embedding, 2 * channels)

    def forward(self, x: torch.Tensor, emb: torch.Tensor) -> torch.Tensor:
        scale, shift = self.film(emb).to(x.dtype).chunk(2)
        h = self.conv1(F.gelu(x))
        h = h * (1.0 + scale[:, None, None]) + shift[:, None, None]
        return x + self.conv2(F.gelu(h))


class Upsample2x(nn.Module):
    """x2 sub-pixel upsampling: conv3x3 to 4c channels, then pixel shuffle."""

    def __init__(self, channels: int):
        super().__init__()
        self.conv = conv3x3(channels, 4 * channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return pixel_shuffle_conv(x, self.conv, 2)


class Analysis(nn.Module):
    """Bottom-up: padded F_c [V,C_F,h,w] -> features [V,c,h/s,w/s] at every latent level's stride s (coarsest
    first): a stride-2 stem, then stride-2 stages up to the coarsest stride; the levels take the last L outputs."""

    def __init__(self, config: ModelConfig):
        super().__init__()
        c, e = config.codec_channels, config.lambda_channels
        self.levels = num_levels(config)
        stages = int(math.log2(padding_multiple(config))) - 1
        self.stem = nn.Conv2d(config.feature_channels, c, 3, stride=2, padding=1)
        self.stem_block = FiLMBlock(c, e)
        self.downs = nn.ModuleList(conv3x3(c, c, stride=2) for _ in range(stages))
        self.blocks = nn.ModuleList(FiLMBlock(c, e) for _ in range(stages))

    def forward(self, feature: torch.Tensor, emb: torch.Tensor) -> list[torch.Tensor]:
        x = self.stem_block(self.stem(feature), emb)
        features = [x]
        for down, block in zip(self.downs, self.blocks):
            x = block(down(x), emb)
            features.append(x)
        return features[::-1][:self.levels]


Quantizer = Callable[[int, "torch.Tensor | None", torch.Tensor, torch.Tensor], torch.Tensor]
"""``quantize(level, z, mean, log_scale) -> z_hat`` on the quantisation grid; ``z`` (posterior mean) is None
on the decoder."""


def base_log_gain(lam: float) -> float:
    """log of the fixed part of the quantisation gain, ``0.5 * log(lam / LAMBDA_MIN)`` (1 at LAMBDA_MIN)."""
    return 0.5 * math.log(lam / LAMBDA_MIN)


class LatentBlock(nn.Module):
    """One latent level: prior from the top-down feature, posterior from it and the bottom-up feature,
    quantisation on the lambda-dependent grid, merge back into the top-down feature."""

    def __init__(self, channels: int, latent_channels: int, embedding: int):
        super().__init__()
        self.prior = nn.Sequential(nn.GELU(), conv3x3(channels, 2 * latent_channels))
        self.posterior = nn.Sequential(conv3x3(2 * channels, channels), nn.GELU(), conv3x3(channels, latent_channels))
        self.gain = nn.Linear(embedding, latent_channels)
        nn.init.zeros_(self.gain.weight)
        nn.init.zeros_(self.gain.bias)
        self.merge = conv3x3(channels + latent_channels, channels)
        self.post = FiLMBlock(channels, embedding)

    def forward(self, x: torch.Tensor, emb: torch.Tensor, lam: float, encoded: torch.Tensor | None, level: int,
                quantize: Quantizer, latent: torch.Tensor | None = None) -> torch.Tensor:
        """One level: ``encoded`` is the bottom-up feature (None on the decoder); ``latent``, when given, is the
        posterior mean on the gained grid to code instead of the one the posterior computes (encoder-side
        rate-distortion optimisation, :mod:`codecsplat_warp.model.rdo`)."""
        mean, log_scale = self.prior(x).chunk(2, dim=1)
        log_gain = (base_log_gain(lam) + _at_least_float32(self.gain(emb)))[:, None, None]
        gain = log_gain.exp()
        if latent is not None:
            z = latent.to(gain.dtype)
        elif encoded is not None:
            z = self.posterior(torch.cat([x, encoded.to(x.dtype)], dim=1)) * gain
        else:
            z = None
        z_hat = quantize(level, z, mean * gain, bounded_log_scale(log_scale + log_gain)) / gain
        x = x + self.merge(torch.cat([x, z_hat.to(x.dtype)], dim=1))
        return self.post(x, emb)


UNUSED_POSTERIOR_GAIN = 1e-3
"""Factor on a new level's random posterior (:func:`_start_unused`): its latents stay far below half a
quantisation step at every lambda (the gain is at most 8), so they round to zero."""


@torch.no_grad()
def _start_unused(block: "LatentBlock") -> None:
    """Make a fresh latent level start unused, in place: its prior is mean 0 at the smallest scale (whatever
    the lambda gain), its posterior is random but tiny (zero symbols, at ~1e-5 bits each), and it adds nothing
    to the top-down feature (the merge reads only the latent, the residual block starts as the identity).
    The merge's latent weights and the posterior stay random, so gradients reach the level from the first step."""
    prior = block.prior[-1]
    latent = prior.out_channels // 2
    nn.init.zeros_(prior.weight)
    nn.init.zeros_(prior.bias)
    prior.bias[latent:] = entropy.log_scale_bounds()[0] - base_log_gain(LAMBDA_MAX)
    block.posterior[-1].weight.mul_(UNUSED_POSTERIOR_GAIN)
    block.posterior[-1].bias.mul_(UNUSED_POSTERIOR_GAIN)
    channels = block.merge.out_channels
    block.merge.weight[:, :channels] = 0.0
    nn.init.zeros_(block.merge.bias)
    nn.init.zeros_(block.post.conv2.weight)
    nn.init.zeros_(block.post.conv2.bias)


class _ClampTowardsRange(torch.autograd.Function):
    """``x.clamp(lo, hi)`` whose gradient passes inside the range, and outside it only where a descent step
    moves ``x`` back towards the range (CompressAI's LowerBound, on both sides)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, lo: float, hi: float) -> torch.Tensor:
        ctx.save_for_backward(x)
        ctx.bounds = (lo, hi)
        return x.clamp(lo, hi)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        (x,) = ctx.saved_tensors
        lo, hi = ctx.bounds
        passes = ((x >= lo) | (grad < 0)) & ((x <= hi) | (grad > 0))
        return grad * passes, None, None


def bounded_log_scale(log_scale: torch.Tensor) -> torch.Tensor:
    """Clamp to the scale table's range. Past a bound the gradient only passes where it leads back into
    the range: a plain straight-through clamp let the rate push the log-scales of zero residuals ever further
    below the smallest scale (by up to 1e5 in a diverged stage-2 run), where no gradient could bring them back
    when their residuals grew."""
    lo, hi = entropy.log_scale_bounds()
    return _ClampTowardsRange.apply(log_scale, lo, hi)


class TopDown(nn.Module):
    """Top-down pass: learned constant at the coarsest stride -> latent blocks (x2 upsampling between)
    -> top-down feature [V,c,h/f,w/f] at the finest latent stride f."""

    def __init__(self, config: ModelConfig):
        super().__init__()
        c, e = config.codec_channels, config.lambda_channels
        self.start = nn.Parameter(torch.zeros(1, c, 1, 1))
        self.blocks = nn.ModuleList(LatentBlock(c, cz, e) for cz in config.codec_latent_channels)
        self.ups = nn.ModuleList(Upsample2x(c) for _ in range(num_levels(config) - 1))

    def forward(self, emb: torch.Tensor, lam: float, views: int, shapes: list[tuple[int, int, int]],
                encoded: list[torch.Tensor] | None, quantize: Quantizer,
                latents: list[torch.Tensor] | None = None) -> torch.Tensor:
        """``encoded``: the analysis features per level (None on the decoder); ``latents``: per level, posterior
        means on the gained grid that replace the posterior's (see :meth:`LatentBlock.forward`)."""
        x = self.start.expand(views, -1, shapes[0][1], shapes[0][2])
        for level, block in enumerate(self.blocks):
            if level:
                x = self.ups[level - 1](x)
            x = block(x, emb, lam, encoded[level] if encoded is not None else None, level, quantize,
                      latents[level] if latents is not None else None)
        return x


class Synthesis(nn.Module):
    """Top-down feature [V,c,h/f,w/f] -> F^_c [V,C_F,h,w] (padded grid): log2(f) x2 upsamplings, each after a
    residual block (f: the finest latent stride)."""

    def __init__(self, config: ModelConfig):
        super().__init__()
        c, e = config.codec_channels, config.lambda_channels
        stages = int(math.log2(config.codec_finest_stride))
        self.blocks = nn.ModuleList(FiLMBlock(c, e) for _ in range(stages))
        self.ups = nn.ModuleList(Upsample2x(c) for _ in range(stages))
        self.out = conv3x3(c, config.feature_channels)

    def forward(self, x: torch.Tensor, emb: torch.Tensor) -> torch.Tensor:
        for block, up in zip(self.blocks, self.ups):
            x = up(block(x, emb))
        return self.out(F.gelu(x))


# --------------------------------------------------------------------------------------------------
# Quantizers
def _at_least_float32(t: torch.Tensor) -> torch.Tensor:
    """``t`` in float32, or float64 if it already is (half-precision autocast outputs are widened)."""
    return t.to(torch.promote_types(t.dtype, torch.float32))


class NoisyQuantizer:
    """Training: rate at ``z + U(-0.5, 0.5)``, decoder input ``round(z - mu) + mu`` (straight-through).

    With a ``temperature``, annealed rounding instead (stochastic Gumbel annealing, Yang et al. 2020, "Improving
    Inference for Neural Image Compression"): each residual ``r`` becomes ``floor(r) + y``, ``y`` a relaxed Bernoulli
    sample (binary Concrete) of rounding up, whose log-odds are ``(atanh(a) - atanh(1 - a)) / T`` for ``a = r -
    floor(r)``, at temperature ``T``; the decoder and the rate both see it. As ``T`` falls to 0 it becomes the
    coder's rounding (a coin flip only at exactly half-way).

    Args:
        generator: the noise's random generator, on the latents' device (None: torch's global one).
        noise: per level, U(0, 1) samples drawn beforehand (float32, each of its latent's shape) to use instead of
            drawing them (a CUDA graph replays the pass with new samples in the same tensors).
        temperature: None, or the annealing temperature T > 0 (a 0-dim float32 tensor on the latents' device, so
            that a CUDA graph reads its current value).
        held_offsets: per level, ``round(r) - r`` recorded by another pass (:attr:`rounding_offsets`) to add
            instead of this pass's: the decoder input becomes ``z + offset``, linear in the latents, which is the
            straight-through rounding's own linearisation (finite differences along the latents then measure
            what its gradient says; :func:`train.semi_amortised.lookahead_term`). Not with a temperature.

    Attributes:
        bits: per level, the estimated bits of each view [V] (float32, differentiable).
        latents: per level, the posterior means it was given, on the gained grid (differentiable; what
            semi-amortised training refines, :mod:`train.semi_amortised`).
        rounding_offsets: per level, the ``round(r) - r`` this pass added (detached; without a temperature).
    """

    def __init__(self, generator: torch.Generator | None = None, noise: list[torch.Tensor] | None = None,
                 temperature: torch.Tensor | None = None, held_offsets: list[torch.Tensor] | None = None):
        if temperature is not None and held_offsets is not None:
            raise InputError("held rounding offsets apply to the noisy quantiser, not to annealed rounding")
        self.bits: list[torch.Tensor] = []
        self.latents: list[torch.Tensor] = []
        self.rounding_offsets: list[torch.Tensor] = []
        self.generator = generator
        self.noise = noise
        self.temperature = temperature
        self.held_offsets = held_offsets

    def __call__(self, level: int, z, mean, log_scale):
        self.latents.append(z)
        residual = z.float() - mean.float()
        if self.noise is not None:
            noise = self.noise[level]
        else:
            noise = torch.rand(residual.shape, generator=self.generator, device=residual.device,
                               dtype=residual.dtype)
        if self.temperature is not None:
            quantized = annealed_rounding(residual, noise, self.temperature)
            self.bits.append(entropy.gaussian_bits(quantized, log_scale.float().exp()).sum(dim=(1, 2, 3)))
            return mean.float() + quantized
        offset = (torch.round(residual) - residual).detach()
        self.rounding_offsets.append(offset)
        rounded = residual + (offset if self.held_offsets is None else self.held_offsets[level])
        noisy = residual + noise - 0.5
        self.bits.append(entropy.gaussian_bits(noisy, log_scale.float().exp()).sum(dim=(1, 2, 3)))
        return mean.float() + rounded


ANNEAL_EDGE = 1e-4
"""How close to an integer the fractional part is clamped in :func:`annealed_rounding` (atanh stays finite)."""


def annealed_rounding(residual: torch.Tensor, uniform: torch.Tensor, temperature: torch.Tensor) -> torch.Tensor:
    """The relaxed rounding of :class:`NoisyQuantizer` with a temperature: ``floor(r) + sigmoid((logit + L) / T)``
    with ``logit = (atanh(a) - atanh(1 - a)) / T``, ``a`` the fractional part of ``r`` and ``L = log(u) -
    log(1 - u)`` logistic noise from the U(0, 1) samples ``uniform``; differentiable in ``residual``."""
    low = torch.floor(residual).detach()
    fraction = (residual - low).clamp(ANNEAL_EDGE, 1.0 - ANNEAL_EDGE)
    u = uniform.clamp(ANNEAL_EDGE, 1.0 - ANNEAL_EDGE)
    logistic = torch.log(u) - torch.log1p(-u)
    logit = (torch.atanh(fraction) - torch.atanh(1.0 - fraction)) / temperature
    return low + torch.sigmoid((logit + logistic) / temperature)


class RoundingQuantizer:
    """Coding: residual symbols under the quantised prior (see :mod:`.entropy`); records what is coded.

    Attributes:
        bits: per level, ideal code length of each view [V] under the discrete model.
        symbols, indices: per level, residual symbols and scale indices (int64, shape of the latent).
        latents: per level, the posterior means it was given, on the gained grid (at least float32).
    """

    def __init__(self):
        self.bits: list[torch.Tensor] = []
        self.symbols: list[torch.Tensor] = []
        self.indices: list[torch.Tensor] = []
        self.latents: list[torch.Tensor] = []

    def __call__(self, level: int, z, mean, log_scale):
        z, mean, log_scale = (_at_least_float32(t) for t in (z, mean, log_scale))
        self.latents.append(z)
        mean = entropy.quantize_mean(mean)
        index = entropy.scale_index(log_scale)
        residual = torch.round(z - mean).detach()
        if not bool(torch.isfinite(residual).all()) or float(residual.abs().max()) > 2.0**entropy.ESCAPE_MAX_BITS:
            raise InputError(f"latent level {level} holds non-finite or huge values (|residual| > "
                             f"2**{entropy.ESCAPE_MAX_BITS}): the feature to code is not sane")
        scales = entropy.scale_table().to(device=index.device, dtype=residual.dtype)[index]
        self.bits.append(entropy.gaussian_bits(residual, scales).sum(dim=(1, 2, 3)))
        self.symbols.append(residual.to(torch.int64))
        self.indices.append(index)
        return residual + mean


class DecodingQuantizer:
    """Decoding: the discrete model of :class:`RoundingQuantizer`, symbols read from one range decoder per view.

    Attributes:
        symbols: per level, the decoded residual symbols (int64, shape of the latent).
    """

    def __init__(self, decoders: list, timer: Timer):
        self.decoders = decoders
        self.timer = timer
        self.symbols: list[torch.Tensor] = []

    def __call__(self, level: int, z, mean, log_scale):
        mean = entropy.quantize_mean(mean)
        with self.timer("entropy"):
            index = entropy.scale_index(log_scale).cpu().numpy()
            decoded = [entropy.decode_symbols(d, i.reshape(-1)).reshape(i.shape) for d, i in zip(self.decoders, index)]
            symbols = torch.from_numpy(np.stack(decoded)).to(mean.device)
        self.symbols.append(symbols)
        return symbols.to(mean.dtype) + mean


# --------------------------------------------------------------------------------------------------
@dataclass
class CodecOutput:
    """Result of :meth:`LatentCodec.forward`.

    Attributes:
        feature: F^_c [V,C_F,h,w], the reconstructed feature.
        bits: [V] estimated bits of each view (Eq. 7; noisy in training, the discrete model's otherwise).
        latents: per level (coarsest first), the posterior means that were quantised, on the gained grid
            [V,C_l,h_l,w_l], differentiable in training mode.
        rounding_offsets: per level, the noisy quantiser's ``round(r) - r`` of the residuals ``r`` (detached; the
            latents' shapes); None from the coder's rounding (eval mode) and from annealed rounding.
    """

    feature: torch.Tensor
    bits: torch.Tensor
    latents: list[torch.Tensor]
    rounding_offsets: list[torch.Tensor] | None = None


@dataclass
class CompressedLatents:
    """Result of :meth:`LatentCodec.compress`.

    Attributes:
        streams: one range-coded byte stream per view.
        symbols: per level (coarsest first), the coded residual symbols int64 [V,C_l,h_l,w_l] (CPU).
        bits: [V] ideal code length of each view under the discrete model (float64, CPU).
        latents: per level, the posterior means that were coded, on the gained grid, float32 [V,C_l,h_l,w_l] on
            the codec's device (the start of encoder-side optimisation, :meth:`LatentCodec.forward_latents`).
        feature: F^_c [V,C_F,h,w], what the decoder will reconstruct from the streams (the codec's dtype), or
            None unless asked for.
    """

    streams: list[bytes]
    symbols: list[torch.Tensor]
    bits: torch.Tensor
    latents: list[torch.Tensor]
    feature: torch.Tensor | None


class LatentCodec(nn.Module):
    """Analysis -> hierarchical latents -> synthesis on the feature grid, conditioned on lambda.

    See the module docstring. Works on any feature grid (zero-padded internally to
    :func:`padding_multiple`, cropped back afterwards).
    """

    def __init__(self, config: ModelConfig):
        super().__init__()
        self.config = config
        self.embedding = LambdaEmbedding(config.lambda_channels)
        self.analysis = Analysis(config)
        self.top_down = TopDown(config)
        self.synthesis = Synthesis(config)
        self._exact: tuple | None = None  # (weights key, float64 copy), see _float64_prior_path

    @torch.no_grad()
    def scale_posterior(self, gain: float) -> None:
        """Multiply every level's posterior mean (its last layer's weight and bias) by ``gain``, in place.

        An untrained codec's posterior means are small, so they round to zero symbols; benchmarks and tests
        of random-weight models scale them (by ~30) so that the coder codes real symbols.
        """
        for block in self.top_down.blocks:
            block.posterior[-1].weight.mul_(gain)
            block.posterior[-1].bias.mul_(gain)

    @torch.no_grad()
    def grow_from(self, state: dict[str, torch.Tensor], source: ModelConfig) -> list[str]:
        """Load the codec ``state`` (a state dict of ``LatentCodec(source)``) into this codec, which has the
        same levels plus finer ones (a smaller ``codec_finest_stride``); returns the names of the tensors
        that keep their initialisation.

        The shared analysis, levels, embedding and output convolution copy over. Of the source synthesis's
        upsampling stages, the finest ones stay in the synthesis, the others become the top-down upsamplings
        into the new levels (the residual blocks before them are dropped). Each new level starts unused
        (:func:`_start_unused`): all its symbols are zero and nearly free, and it passes the top-down feature
        on unchanged, so the grown codec first codes and reconstructs nearly what the source did, and
        training then learns what the new latents add. (Zero symbols at a random prior instead cost kilobytes,
        and their rate gradient through the shared top-down path wrecked a trained codec in training run G,
        2026-11-24.)

        Raises:
            InputError: the configs differ in anything but the finer levels.
        """
        extra = num_levels(self.config) - num_levels(source)
        same = ("feature_channels", "codec_channels", "lambda_channels")
        if (extra < 1 or any(getattr(source, n) != getattr(self.config, n) for n in same)
                or self.config.codec_latent_channels[:num_levels(source)] != source.codec_latent_channels
                or self.config.codec_finest_stride * 2 ** extra != source.codec_finest_stride):
            raise InputError(f"cannot grow a codec with levels {source.codec_latent_channels} at finest stride "
                             f"{source.codec_finest_stride} into one with {self.config.codec_latent_channels} at "
                             f"{self.config.codec_finest_stride}: it needs the same levels plus finer ones")
        mapped = {}
        for name, tensor in state.items():
            part, _, rest = name.partition(".")
            if part == "synthesis" and rest.split(".")[0] in ("blocks", "ups"):
                kind, index, tail = rest.split(".", 2)
                stage = int(index) - extra
                if stage >= 0:
                    mapped[f"synthesis.{kind}.{stage}.{tail}"] = tensor
                elif kind == "ups":
                    mapped[f"top_down.ups.{num_levels(source) - 1 + int(index)}.{tail}"] = tensor
            else:
                mapped[name] = tensor
        for block in self.top_down.blocks[num_levels(source):]:
            _start_unused(block)
        missing, unexpected = self.load_state_dict(mapped, strict=False)
        if unexpected:
            raise InputError(f"codec state holds tensors this codec lacks: {', '.join(unexpected)}")
        return missing

    def forward(self, feature: torch.Tensor, lam: float, generator: torch.Generator | None = None,
                noise: list[torch.Tensor] | None = None, lambda_embedding: torch.Tensor | None = None,
                temperature: torch.Tensor | None = None) -> CodecOutput:
        """Differentiable pass: F_c [V,C_F,h,w] -> :class:`CodecOutput`. In training mode the quantisation
        is noisy (:class:`NoisyQuantizer`), in eval mode it is the coder's (:class:`RoundingQuantizer`).
        ``generator``, ``noise``, ``lambda_embedding``, ``temperature``: as in :meth:`forward_latents`."""
        h, w = feature.shape[-2:]
        lam = check_lambda(lam)
        emb = self.embedding(lam) if lambda_embedding is None else lambda_embedding
        encoded = self.analysis(self._pad(feature), emb)
        quantizer = NoisyQuantizer(generator, noise, temperature) if self.training else RoundingQuantizer()
        x = self.top_down(emb, lam, feature.shape[0], latent_shapes(self.config, h, w), encoded, quantizer)
        return CodecOutput(self.synthesis(x, emb)[..., :h, :w], torch.stack(quantizer.bits).sum(0),
                           quantizer.latents)

    def forward_latents(self, latents: list[torch.Tensor], lam: float, height: int, width: int,
                        generator: torch.Generator | None = None, noise: list[torch.Tensor] | None = None,
                        lambda_embedding: torch.Tensor | None = None,
                        temperature: torch.Tensor | None = None,
                        held_offsets: list[torch.Tensor] | None = None) -> CodecOutput:
        """Differentiable pass from given latents instead of the analysis and the posterior: per level, the
        posterior means on the gained grid [V,C_l,h_l,w_l] (what :meth:`compress` records in
        :attr:`CompressedLatents.latents`) -> :class:`CodecOutput` on a ``height`` x ``width`` feature grid.
        Noisy quantisation in training mode (``generator`` draws the noise, or ``noise`` gives it: see
        :class:`NoisyQuantizer`), the coder's in eval mode. ``lambda_embedding``: ``self.embedding(lam)`` computed
        beforehand (it copies lambda to the device, which a CUDA graph capture must not do). ``temperature``: annealed
        rounding instead of the noisy one in training mode; ``held_offsets``: rounding offsets of another pass
        (both :class:`NoisyQuantizer`, training mode only)."""
        lam = check_lambda(lam)
        emb = self.embedding(lam) if lambda_embedding is None else lambda_embedding
        if held_offsets is not None and not self.training:
            raise InputError("held rounding offsets need the codec in training mode (the noisy quantiser)")
        quantizer = (NoisyQuantizer(generator, noise, temperature, held_offsets) if self.training
                     else RoundingQuantizer())
        shapes = latent_shapes(self.config, height, width)
        x = self.top_down(emb, lam, latents[0].shape[0], shapes, None, quantizer, latents)
        offsets = quantizer.rounding_offsets if self.training and temperature is None else None
        return CodecOutput(self.synthesis(x, emb)[..., :height, :width], torch.stack(quantizer.bits).sum(0),
                           quantizer.latents, offsets)

    @torch.no_grad()
    def compress(self, feature: torch.Tensor, lam: float, timer: Timer = no_timer,
                 reconstruct: bool = False) -> CompressedLatents:
        """Encoder: F_c [V,C_F,h,w] -> one range-coded stream per view (:class:`CompressedLatents`; its
        ``feature`` only with ``reconstruct``).

        The analysis runs in the feature's dtype, the prior path in float64 (see the module docstring).
        """
        lam = check_lambda(lam)
        h, w = feature.shape[-2:]
        encoded = self.analysis(self._pad(feature), self.embedding(lam))
        with torch.autocast(feature.device.type, enabled=False):
            encoded = [e.double() for e in encoded]
        return self._code(lam, feature.shape[0], h, w, encoded, None, timer, reconstruct)

    @torch.no_grad()
    def compress_latents(self, latents: list[torch.Tensor], lam: float, height: int, width: int,
                         timer: Timer = no_timer, reconstruct: bool = False) -> CompressedLatents:
        """Encoder from given latents (per level, posterior means on the gained grid, as in
        :meth:`forward_latents`) on a ``height`` x ``width`` feature grid -> :class:`CompressedLatents`: the
        same streams that :meth:`decompress` reads, coded under the float64 prior path."""
        lam = check_lambda(lam)
        with torch.autocast(latents[0].device.type, enabled=False):
            latents = [z.detach().double() for z in latents]
        return self._code(lam, latents[0].shape[0], height, width, None, latents, timer, reconstruct)

    def _code(self, lam: float, views: int, height: int, width: int, encoded: list[torch.Tensor] | None,
              latents: list[torch.Tensor] | None, timer: Timer, reconstruct: bool) -> CompressedLatents:
        """The float64 top-down pass with the coder's quantiser on the analysis features ``encoded`` or on
        ``latents``, then one range-coded stream per view; with ``reconstruct`` also the decoder's F^_c."""
        shapes = latent_shapes(self.config, height, width)
        exact = self._float64_prior_path()
        quantizer = RoundingQuantizer()
        device = self.top_down.start.device
        with torch.autocast(device.type, enabled=False):
            x = exact.top_down(exact.embedding(lam), lam, views, shapes, encoded, quantizer, latents)
        feature = None
        if reconstruct:  # as the decoder does it: the model's dtype, autocast off
            with torch.autocast(device.type, enabled=False):
                x = x.to(self.top_down.start.dtype)
                feature = self.synthesis(x, self.embedding(lam))[..., :height, :width]
        with timer("entropy"):
            symbols = [s.cpu() for s in quantizer.symbols]
            indices = [i.cpu() for i in quantizer.indices]
            streams = []
            for view in range(views):
                encoder = entropy.new_encoder()
                for s, i in zip(symbols, indices):
                    entropy.encode_symbols(encoder, s[view].reshape(-1).numpy(), i[view].reshape(-1).numpy())
                streams.append(entropy.encoder_bytes(encoder))
        return CompressedLatents(streams, symbols, torch.stack(quantizer.bits).sum(0).cpu(),
                                 [z.float() for z in quantizer.latents], feature)

    @torch.no_grad()
    def decompress(self, streams: list[bytes], height: int, width: int, lam: float,
                   timer: Timer = no_timer) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Decoder: one stream per view -> (F^_c [V,C_F,height,width] in the model's dtype, on its device;
        the decoded symbols per level, int64 [V,C_l,h_l,w_l]). ``height`` x ``width`` is the feature grid."""
        lam = check_lambda(lam)
        shapes = latent_shapes(self.config, height, width)
        exact = self._float64_prior_path()
        with timer("entropy"):
            decoders = [entropy.new_decoder(s) for s in streams]
        quantizer = DecodingQuantizer(decoders, timer)
        device = self.top_down.start.device
        with torch.autocast(device.type, enabled=False):
            x = exact.top_down(exact.embedding(lam), lam, len(streams), shapes, None, quantizer)
        x = x.to(self.top_down.start.dtype)
        feature = self.synthesis(x, self.embedding(lam))[..., :height, :width]
        return feature, quantizer.symbols

    def _pad(self, feature: torch.Tensor) -> torch.Tensor:
        m = padding_multiple(self.config)
        h, w = feature.shape[-2:]
        return F.pad(feature, (0, -w % m, 0, -h % m))

    def _float64_prior_path(self) -> nn.ModuleDict:
        """A float64 copy of the lambda embedding and the top-down pass (the modules that define the priors),
        made again only when a weight changed (new storage or an in-place update)."""
        sources = [*self.embedding.parameters(), *self.top_down.parameters()]
        key = tuple((p.data_ptr(), p._version, p.device) for p in sources)
        if self._exact is None or self._exact[0] != key:
            modules = nn.ModuleDict({"embedding": self.embedding, "top_down": self.top_down})
            self._exact = (key, copy.deepcopy(modules).double().requires_grad_(False))
        return self._exact[1]
