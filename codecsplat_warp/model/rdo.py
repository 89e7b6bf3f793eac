"""Encoder-side rate-distortion optimisation (RDO): the coded latents fitted per scene through the fixed decoder.

The amortised encoder (MVEnc, FeatHead, R_pre, the codec's analysis and posterior) predicts the latents in one pass.
The encoder also has the context photographs, and the decoder (the codec's top-down pass and synthesis, the depth
head, R_post with the Warp reprojection, the GS head, the Warp unprojection and rasterizer) is differentiable end
to end, so the latents can be optimised against what the decoder will make of them. Nothing in the model, the
decoder or the bitstream format changes: the optimised latents are coded by the same range coder, under the same
priors, and any decoder of the model decodes them.

What is optimised: the posterior means of every latent level on the gained grid (one quantisation step = 1), starting
from the amortised ones, with Adam; or (``RDOConfig.variable="feature"``) the encoder's F_c, which the codec's
analysis and posterior turn into the latents. Per step (:func:`rdo_loss`), with the codec's training quantiser (straight-through
rounding towards the decoder, noisy rate), the loss is

    (lambda / 1024) * [MSE(decoded Gaussians rendered into the context cameras, context images)
                       + perceptual_weight * LPIPS(the same renders, context images)
                       + cross_view_weight * (each context view predicted by the OTHER views' Gaussians alone:
                                              their colour over their alpha against the photograph, weighted by
                                              that alpha)
                       + depth_weight * |S - S_amortised|_1]
    + rate_weight * (estimated bits / context pixels) + anchor_weight * mean((z - z_amortised)^2)

The tuned settings (:func:`rdo_config`) use the first term, the rate and, for scenes of at most
:data:`~codecsplat_warp.choices.RDO_CROSS_VIEW_MAX_VIEWS` views, the cross-view term: without it the 2-view targets'
gain peaked after some 20 steps while the context views kept improving (the photographs got fitted with geometry
that no other view confirms); with it they still gain at 160 steps. With eight views the term gained nothing and the
targets still gain after 300 steps without it: the presets' step counts grow with the square of the view count
(:func:`preset_steps`). On the held-out scenes the depth term and the anchor lowered the targets' PSNR, and the
LPIPS term trades PSNR and bytes for LPIPS and needs the LPIPS weights (docs/benchmarks.md, "Encoder RDO"); they
stay for experiments (``codecsplat bench rdo --set``).

Every ``check_every`` steps and at the end, the current latents are coded for real (the coder's rounding, the
float64 prior path; :meth:`LatentCodec.compress_latents`) and scored by the same loss, with the discrete model's
bits: the encoder keeps the best latents it has measured (the amortised ones are step 0), not just the last. It
has no target views: this is the loss it can measure.

Robustness: gradients that are not finite are zeroed, latents are clamped to +-:data:`LATENT_LIMIT` (far inside the
coder's escape range), a check whose loss is not finite ends the run, and Ctrl-C (KeyboardInterrupt) during the
steps ends it too: in every case the best latents measured so far are returned (:attr:`RDOResult.stopped` says
why). With the same ``seed`` two runs on the CPU give the same latents.
"""

from __future__ import annotations

import contextlib
import math
import time
import warnings
from dataclasses import dataclass, field, replace
from typing import Callable, Iterator

import torch
from torch.nn import functional as F
from torch.profiler import record_function

from ..cameras import Cameras
from ..checks import validation
from ..choices import (RDO_CROSS_VIEW_MAX_VIEWS, RDO_CROSS_VIEW_MIN_STEPS, RDO_CROSS_VIEW_WEIGHT, RDO_MIN_PRESET_STEPS,
                       RDO_PRESETS)
from ..codec.latent import LAMBDA_MAX, CompressedLatents, check_lambda
from ..errors import InputError
from ..gaussians import Gaussians
from ..nn.config import FEATURE_STRIDE
from .culling import render_depth_range
from .mvenc import context_neighbours

LATENT_LIMIT = 4096.0
"""Latents are clamped to [-LATENT_LIMIT, LATENT_LIMIT] quantisation steps after every step."""

CROSS_VIEW_ALPHA_FLOOR = 0.05
"""The least alpha :func:`cross_view_error` divides a colour by (where the other views barely cover a pixel, its
weight is as small)."""

VARIABLES = ("latents", "feature")
"""What the optimisation can move (:attr:`RDOConfig.variable`)."""

PRESETS = tuple(RDO_PRESETS)
"""The presets' names: ``fast`` is the amortised encoder alone (the API's default), ``medium`` and ``slow`` optimise
(:func:`preset_steps`)."""


def preset_steps(preset: str, views: int) -> int:
    """Optimisation steps of ``preset`` for ``views`` context views: :data:`~codecsplat_warp.choices.RDO_PRESETS`'s
    factor times views squared, at least :data:`~codecsplat_warp.choices.RDO_MIN_PRESET_STEPS`, and at least the
    preset's :data:`~codecsplat_warp.choices.RDO_CROSS_VIEW_MIN_STEPS` where the cross-view term is on
    (:func:`cross_view_default`): 25 / 160 for 2 views, 80 / 320 for 8 (0 for ``fast``). InputError for an unknown
    preset."""
    if preset not in RDO_PRESETS:
        raise InputError(f"unknown RDO preset {preset!r}; choose one of {', '.join(PRESETS)}")
    factor = RDO_PRESETS[preset]
    if factor == 0:
        return 0
    least = RDO_CROSS_VIEW_MIN_STEPS[preset] if cross_view_default(views) > 0 else RDO_MIN_PRESET_STEPS
    return max(least, round(factor * views * views))


def cross_view_default(views: int) -> float:
    """The tuned cross-view weight for ``views`` context views: :data:`~codecsplat_warp.choices.
    RDO_CROSS_VIEW_WEIGHT` for 2 to :data:`~codecsplat_warp.choices.RDO_CROSS_VIEW_MAX_VIEWS` views, else 0."""
    return RDO_CROSS_VIEW_WEIGHT if 2 <= views <= RDO_CROSS_VIEW_MAX_VIEWS else 0.0


@dataclass(frozen=True)
class RDOConfig:
    """Settings of one optimisation.

    Attributes:
        steps: Adam steps (0: none, the amortised latents); None runs until ``time_budget`` is spent.
        time_budget: wall seconds the steps may take (None: no limit); the run stops at whichever of ``steps``
            and ``time_budget`` comes first.
        learning_rate: Adam's step at the start, in quantisation steps of the gained grid; it falls on a cosine to
            ``final_lr_fraction`` of that over the run (by steps, or by the budget's seconds when that ends sooner).
        final_lr_fraction: see ``learning_rate``.
        rate_weight: beta, the weight of the rate in bits per context pixel (the shipped model's stage-2 value).
        cross_view_weight: weight of the cross-view term (:func:`cross_view_error`; 0: off; needs at least 2
            views). :func:`rdo_config` sets the tuned one for the view count (:func:`cross_view_default`).
        depth_weight: weight of |S - S_amortised|_1 (0: off).
        perceptual_weight: weight of a perceptual distance (LPIPS) of the context renders (0: off; needs the
            ``perceptual`` network, see :func:`rdo_target`).
        anchor_weight: weight of the mean squared change of the latents from the amortised ones, in quantisation
            steps squared (0: off).
        check_every: steps between two real codings of the latents (the best measured is kept); 0 codes only the
            amortised latents and the last ones.
        seed: seed of the training quantiser's noise.
        precision: ``"float32"`` or ``"bfloat16"`` (bf16 autocast for the networks, on CUDA and on the CPU; the
            geometry, the rasterizer and the real codings at the checks stay float32).
        cuda_graphs: on CUDA, run the decoder up to the Gaussians (:class:`GraphedDecoder`, in either precision)
            and the loss's fixed terms (:func:`context_loss`) as CUDA graphs captured once per run; ignored on the
            CPU.
        variable: what Adam moves: ``"latents"`` (the posterior means on the gained grid) or ``"feature"`` (the
            encoder's F_c, through the codec's analysis and posterior; :func:`optimise_latents` then needs it).
        feature_step: with ``variable="feature"``, Adam's start step as a fraction of the amortised F_c's standard
            deviation (``learning_rate`` is the step for the latents).
        rounding: the training quantiser's: ``"noise"`` (straight-through rounding to the decoder, the rate at
            uniform noise) or ``"annealed"`` (stochastic Gumbel annealing for both, its temperature falling
            geometrically from ``anneal_start`` to ``anneal_end`` over the run; :class:`~codecsplat_warp.codec.
            latent.NoisyQuantizer`).
        anneal_start, anneal_end: see ``rounding``.
    """

    steps: int | None = 0
    time_budget: float | None = None
    learning_rate: float = 0.1
    final_lr_fraction: float = 0.1
    rate_weight: float = 1.3e-3
    cross_view_weight: float = 0.0
    depth_weight: float = 0.0
    perceptual_weight: float = 0.0
    anchor_weight: float = 0.0
    check_every: int = 100
    seed: int = 0
    precision: str = "float32"
    cuda_graphs: bool = True
    variable: str = "latents"
    feature_step: float = 0.01
    rounding: str = "noise"
    anneal_start: float = 0.5
    anneal_end: float = 0.05

    def __post_init__(self) -> None:
        if self.steps is None and self.time_budget is None:
            raise InputError("RDO needs a step count or a time budget (both are None)")
        if self.steps is not None and (isinstance(self.steps, bool) or not isinstance(self.steps, int)
                                       or self.steps < 0):
            raise InputError(f"RDO steps must be an integer >= 0, got {self.steps!r}")
        if self.time_budget is not None and not (math.isfinite(self.time_budget) and self.time_budget > 0):
            raise InputError(f"the RDO time budget must be a number of seconds > 0, got {self.time_budget!r}")
        positive = {"learning_rate": self.learning_rate, "final_lr_fraction": self.final_lr_fraction,
                    "feature_step": self.feature_step, "anneal_start": self.anneal_start,
                    "anneal_end": self.anneal_end}
        for name, value in positive.items():
            if not (math.isfinite(value) and value > 0):
                raise InputError(f"RDOConfig.{name} must be > 0, got {value!r}")
        weights = {"rate_weight": self.rate_weight, "cross_view_weight": self.cross_view_weight,
                   "depth_weight": self.depth_weight, "perceptual_weight": self.perceptual_weight,
                   "anchor_weight": self.anchor_weight}
        for name, value in weights.items():
            if not (math.isfinite(value) and value >= 0):
                raise InputError(f"RDOConfig.{name} must be >= 0, got {value!r}")
        if self.check_every < 0:
            raise InputError(f"RDOConfig.check_every must be >= 0, got {self.check_every}")
        if self.rounding not in ("noise", "annealed"):
            raise InputError(f"RDOConfig.rounding must be noise or annealed, got {self.rounding!r}")
        if self.variable not in VARIABLES:
            raise InputError(f"RDOConfig.variable must be one of {', '.join(VARIABLES)}, got {self.variable!r}")
        if self.variable == "feature" and self.anchor_weight > 0:
            raise InputError("RDOConfig.anchor_weight needs variable='latents' (it measures the latents' change)")
        if self.precision not in ("float32", "bfloat16"):
            raise InputError(f"RDOConfig.precision must be float32 or bfloat16, got {self.precision!r}")

    @property
    def optimises(self) -> bool:
        """Whether this config takes any step (False: the amortised encoder alone)."""
        return self.steps != 0


def rdo_config(preset: str = "fast", steps: int | None = None, time_budget: float | None = None,
               seed: int = 0, views: int = 2, **settings) -> RDOConfig:
    """The :class:`RDOConfig` of a preset for ``views`` context views (:func:`preset_steps`), with ``steps``
    (overrides the preset's count), ``time_budget`` and any other field given. Unless given, ``cross_view_weight``
    is the tuned one for the view count (:func:`cross_view_default`), with a preset or an explicit step count alike.

    With a ``time_budget`` and neither ``steps`` nor a preset that optimises, the steps are unlimited: the budget
    alone ends the run.

    Raises:
        InputError: an unknown preset, steps < 0, a budget <= 0, or another bad setting.
    """
    preset_count = preset_steps(preset, views)
    settings.setdefault("cross_view_weight", cross_view_default(views))
    if steps is None:
        steps = preset_count
        if time_budget is not None and steps == 0:
            steps = None
    return RDOConfig(steps=steps, time_budget=time_budget, seed=seed, **settings)


@dataclass
class RDOCheck:
    """One real coding of the latents during a run: ``step`` (0: the amortised latents), wall ``seconds`` since
    the run started, the measured ``loss``, the context views' ``psnr`` (dB) and the coded ``bits`` (ideal code
    length of all views under the discrete model)."""

    step: int
    seconds: float
    loss: float
    psnr: float
    bits: float


@dataclass
class RDOResult:
    """What :func:`optimise_latents` returns.

    Attributes:
        compressed: the coding of the best latents measured (what the bitstream carries).
        best_step: the step whose latents those are (0: the amortised ones).
        steps: steps taken.
        seconds: wall seconds of the whole optimisation, checks and the final coding included.
        stopped: why the steps ended: ``"steps"``, ``"time"``, ``"interrupted"`` (Ctrl-C) or ``"non-finite"``.
        checks: every real coding, in order.
    """

    compressed: CompressedLatents
    best_step: int
    steps: int
    seconds: float
    stopped: str
    checks: list[RDOCheck] = field(default_factory=list)

    def to_dict(self) -> dict:
        """JSON-ready summary (without the latents)."""
        return {"best_step": self.best_step, "steps": self.steps, "seconds": self.seconds, "stopped": self.stopped,
                "checks": [vars(c) for c in self.checks]}


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


def perceptual_distance(network: torch.nn.Module, target_units: list[torch.Tensor], images: torch.Tensor,
                        graphed: bool) -> Callable[[torch.Tensor], torch.Tensor]:
    """:class:`PerceptualDistance` for renders shaped like ``images``; with ``graphed`` (CUDA) its forward and
    backward captured as CUDA graphs (``torch.cuda.make_graphed_callables``): with LPIPS-VGG launched eagerly a
    2-view step took 16.0 ms on an H200, replayed 12.9-13.2 ms. A capture that fails falls back to eager, with a
    warning."""
    distance = PerceptualDistance(network, target_units)
    if not graphed:
        return distance
    try:
        with torch.enable_grad(), validation(False):
            sample = torch.rand_like(images, dtype=torch.float32).requires_grad_(True)
            return torch.cuda.make_graphed_callables(distance, (sample,))
    except RuntimeError as error:
        warnings.warn(f"the RDO perceptual term runs without CUDA graphs: capturing it failed ({error})",
                      RuntimeWarning, stacklevel=2)
        return distance


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


def context_loss(images: torch.Tensor, lam: float, config: RDOConfig, graphed: bool
                 ) -> Callable[..., tuple[torch.Tensor, torch.Tensor]]:  # fmt: skip
    """:class:`ContextLoss` of ``config``'s weights for the context ``images`` [V,3,H,W]; with ``graphed`` (CUDA)
    its forward and backward captured as CUDA graphs (``torch.cuda.make_graphed_callables``; their outputs are
    overwritten by the next call). Launched eagerly, its two dozen small kernels and their gradients left the GPU
    idle for about 2.5 ms of a 2-view step on an H100 (the host launching them one by one). A capture that fails
    falls back to eager, with a warning."""
    loss = ContextLoss(images, lam, config.cross_view_weight, config.rate_weight)
    if not graphed:
        return loss
    V, _, H, W = images.shape
    views = 2 * V if config.cross_view_weight > 0 else V
    try:
        with torch.enable_grad(), validation(False):
            sample = (torch.rand(views, 3, H, W, device=images.device).requires_grad_(True),
                      torch.rand((), device=images.device).requires_grad_(True))
            if config.cross_view_weight > 0:
                sample += (torch.rand(views, H, W, device=images.device).requires_grad_(True),)
            return torch.cuda.make_graphed_callables(loss, sample)
    except RuntimeError as error:
        warnings.warn(f"the RDO loss runs without CUDA graphs: capturing it failed ({error})", RuntimeWarning,
                      stacklevel=2)
        return loss


def rdo_target(model, images: torch.Tensor, cameras: Cameras, lam: float, start: CompressedLatents,
               config: RDOConfig, perceptual: torch.nn.Module | None = None) -> RDOTarget:
    """The fixed inputs of a run from the context views and the amortised coding ``start`` (with its feature):
    :func:`latent_target` of its latents and feature.

    ``perceptual``: a network with LPIPS' ``unit_features(images)`` and ``distance(x_units, y_units)`` (e.g.
    :class:`codecsplat_warp.metrics.LPIPS`), needed when ``config.perceptual_weight`` > 0 (InputError otherwise).
    """
    return latent_target(model, images, cameras, lam, start.latents, config, perceptual, start.feature)


@torch.no_grad()
def latent_target(model, images: torch.Tensor, cameras: Cameras, lam: float, latents: list[torch.Tensor],
                  config: RDOConfig, perceptual: torch.nn.Module | None = None,
                  feature: torch.Tensor | None = None) -> RDOTarget:
    """The fixed inputs of a run from the context ``images`` [V,3,H,W] and ``cameras`` and the amortised
    ``latents`` (per level, on the gained grid; detached here), with the decoder's feature F^_c of them
    (``feature``, [V,C_F,H/2,W/2]) where the depth term needs it (InputError when it is missing then).
    ``perceptual``: see :func:`rdo_target`."""
    if config.perceptual_weight > 0 and perceptual is None:
        raise InputError("RDO with a perceptual weight needs the perceptual network (e.g. codecsplat_warp.metrics."
                         "LPIPS('vgg')): pass perceptual=")
    if config.depth_weight > 0 and feature is None:
        raise InputError("RDO with a depth weight needs the amortised coding's decoder feature: pass feature=")
    s_start = model.depth_head(feature.float(), cameras)[0] if config.depth_weight > 0 else None
    graphed = uses_cuda_graphs(config, images.device)
    distance = (perceptual_distance(perceptual, perceptual.unit_features(images), images, graphed)
                if config.perceptual_weight > 0 else None)
    return RDOTarget(images, cameras, lam, context_neighbours(cameras, model.config.neighbours),
                     render_depth_range(cameras), [z.detach() for z in latents], s_start, distance,
                     context_loss(images, lam, config, graphed))


Decoded = tuple[torch.Tensor, torch.Tensor, Gaussians]
"""What the decoder makes of the latents: (estimated bits of all views, 0-dim; S [V,H,W]; the Gaussians)."""


def decode_variables(model, variables: list[torch.Tensor], target: RDOTarget, variable: str,
                     generator: torch.Generator | None = None, noise: list[torch.Tensor] | None = None,
                     lambda_embedding: torch.Tensor | None = None, temperature: torch.Tensor | None = None
                     ) -> Decoded:
    """The decoder from the optimised tensors -> :data:`Decoded`: the codec's pass in the model's mode from the
    latents (``variable="latents"``: ``variables`` are the latents, :meth:`LatentCodec.forward_latents`) or from
    F_c (``"feature"``: ``variables`` is [F_c], through the analysis and the posterior), then the depth head,
    R_post, the GS head and the 2D->3D map. ``generator``/``noise``/``lambda_embedding``/``temperature``: see
    :meth:`LatentCodec.forward_latents`."""
    cameras = target.cameras
    with record_function("codec"):
        if variable == "latents":
            coded = model.codec.forward_latents(variables, target.lam, cameras.height // FEATURE_STRIDE,
                                                cameras.width // FEATURE_STRIDE, generator, noise, lambda_embedding,
                                                temperature)
        else:
            coded = model.codec(variables[0], target.lam, generator, noise, lambda_embedding, temperature)
    s, _, gaussians = model.decode_feature(coded.feature, cameras, target.neighbours)
    return coded.bits.sum(), s, gaussians


class GraphedDecoder:
    """:func:`decode_variables` in training mode, captured as two CUDA graphs (forward, and backward to the
    optimised tensors) for one run's shapes, and replayed through an autograd function.

    One step of the eager decoder launches some 1,500 small kernels from Python (the codec's levels, the heads'
    convolutions and norms, the Warp reprojection and unprojection, their backward): the GPU waits on the host.
    Replayed, they cost two launches. The rasterizer, whose buffers depend on the Gaussians, the loss and the
    optimiser stay eager. Inputs are copied into the graphs' static tensors and outputs and gradients are copied
    out of them, so nothing outside aliases the graphs' memory; what the graphs read outside their own memory (the
    lambda embedding, the cameras, their memoized kernel arrays, the neighbours) lives as long as they do. The
    quantiser's noise is drawn outside the graphs by the run's generator, in the eager decoder's order.

    Args:
        model: the frozen model (training mode, parameters without gradients), on CUDA.
        target: the run's :class:`RDOTarget` (its amortised latents give the noise's shapes).
        variables: the run's optimised tensors (float32): their shapes fix the graphs'.
        variable: what they are (:attr:`RDOConfig.variable`).
        annealed: annealed rounding (:attr:`RDOConfig.rounding`), its temperature set at every call.
        precision: :attr:`RDOConfig.precision`; ``"bfloat16"`` captures the networks under bf16 autocast.
    Calling it with the optimised tensors, the generator and the temperature gives :data:`Decoded`.
    """

    WARMUP = 3
    """Eager forward+backward passes on a side stream before the capture (cuDNN and Warp pick and load kernels)."""

    def __init__(self, model, target: RDOTarget, variables: list[torch.Tensor], variable: str = "latents",
                 annealed: bool = False, precision: str = "float32"):
        with torch.no_grad():
            embedding = model.codec.embedding(target.lam)
        device = variables[0].device
        self.temperature = torch.full((), 0.5, device=device) if annealed else None
        self.noise = [torch.rand_like(z, dtype=torch.float32) for z in target.latents]
        self.variables = [v.detach().clone().requires_grad_(True) for v in variables]

        def decode() -> list[torch.Tensor]:
            # a graph replays kernels, not autocast's cast cache: captured without it
            with torch.autocast("cuda", dtype=torch.bfloat16, enabled=precision == "bfloat16", cache_enabled=False):
                bits, s, g = decode_variables(model, self.variables, target, variable, noise=self.noise,
                                              lambda_embedding=embedding, temperature=self.temperature)
            return [bits, s, g.means, g.quats, g.scales, g.opacities, g.sh]

        def backward(outputs: list[torch.Tensor], grads: list[torch.Tensor]) -> tuple[torch.Tensor, ...]:
            return torch.autograd.grad(outputs, self.variables, grads, allow_unused=True)

        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            for _ in range(self.WARMUP):
                outputs = decode()
                backward(outputs, [torch.zeros_like(o) for o in outputs])
        torch.cuda.current_stream().wait_stream(side)
        del outputs
        self.forward_graph, self.backward_graph = torch.cuda.CUDAGraph(), torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.forward_graph):
            self.outputs = decode()
        self.output_grads = [torch.zeros_like(o) for o in self.outputs]
        with torch.cuda.graph(self.backward_graph, pool=self.forward_graph.pool()):
            grads = backward(self.outputs, self.output_grads)
        self.grads = [torch.zeros_like(z) if g is None else g for z, g in zip(self.variables, grads)]
        # the graphs read these by address: they must live as long as the graphs
        self.held = (target, embedding, target.cameras.memo_values(), decode)

    def __call__(self, variables: list[torch.Tensor], generator: torch.Generator | None,
                 temperature: float | None = None) -> Decoded:
        if self.temperature is not None and temperature is not None:
            self.temperature.fill_(temperature)
        for noise in self.noise:
            torch.rand(noise.shape, generator=generator, device=noise.device, dtype=noise.dtype, out=noise)
        bits, s, *fields_ = _ReplayDecoder.apply(self, *variables)
        return bits, s, Gaussians(*fields_)


class _ReplayDecoder(torch.autograd.Function):
    """The autograd face of :class:`GraphedDecoder`: forward replays its forward graph on copies of the optimised
    tensors, backward its backward graph on copies of the outputs' gradients."""

    @staticmethod
    def forward(ctx, graphs: GraphedDecoder, *variables: torch.Tensor) -> tuple[torch.Tensor, ...]:
        for static, v in zip(graphs.variables, variables):
            static.detach().copy_(v)
        graphs.forward_graph.replay()
        ctx.graphs = graphs
        return tuple(o.detach().clone() for o in graphs.outputs)

    @staticmethod
    def backward(ctx, *grads: torch.Tensor):
        graphs = ctx.graphs
        for static, g in zip(graphs.output_grads, grads):  # autograd gives zeros for an unused output
            static.copy_(g)
        graphs.backward_graph.replay()
        return (None, *(g.clone() for g in graphs.grads))


GRAPH_MIN_STEPS = 16
"""Runs of fewer steps stay eager: the capture costs about as much as a dozen steps save (2 views on an H200:
0.25 s for 5 graphed steps against 0.19 s eager)."""


def uses_cuda_graphs(config: RDOConfig, device: torch.device) -> bool:
    """Whether a run of ``config`` on ``device`` replays the decoder as CUDA graphs: on CUDA, with
    ``config.cuda_graphs``, and with at least :data:`GRAPH_MIN_STEPS` steps (or a time budget alone)."""
    long_enough = config.steps is None or config.steps >= GRAPH_MIN_STEPS
    return config.cuda_graphs and device.type == "cuda" and long_enough


def step_decoder(model, target: RDOTarget, variables: list[torch.Tensor], config: RDOConfig
                 ) -> GraphedDecoder | None:
    """The decoder that :func:`rdo_step` should use: a :class:`GraphedDecoder` when :func:`uses_cuda_graphs`,
    else None (the eager :func:`decode_variables`). The model must be in training mode with its parameters
    frozen. A capture that fails falls back to eager, with a warning."""
    if not uses_cuda_graphs(config, target.images.device):
        return None
    try:
        with validation(False):
            return GraphedDecoder(model, target, variables, config.variable, config.rounding == "annealed",
                                  config.precision)
    except RuntimeError as error:
        warnings.warn(f"RDO runs without CUDA graphs: capturing the decoder failed ({error})", RuntimeWarning,
                      stacklevel=2)
        return None


def rdo_loss(model, variables: list[torch.Tensor], target: RDOTarget, config: RDOConfig,
             generator: torch.Generator | None = None, compressed: CompressedLatents | None = None,
             decoder: GraphedDecoder | None = None, temperature: float | None = None) -> tuple[torch.Tensor, dict]:
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


def _progress(config: RDOConfig, step: int, elapsed: float) -> float:
    """How far along the run is, in [0, 1]: by ``step`` or by ``elapsed`` seconds, whichever is further."""
    done = 0.0
    if config.steps:
        done = step / config.steps
    if config.time_budget:
        done = max(done, elapsed / config.time_budget)
    return min(done, 1.0)


def _learning_rate(config: RDOConfig, start: float, step: int, elapsed: float) -> float:
    """The cosine schedule from ``start`` at ``step`` / ``elapsed`` seconds."""
    done = _progress(config, step, elapsed)
    floor = config.final_lr_fraction
    return start * (floor + (1.0 - floor) * 0.5 * (1.0 + math.cos(math.pi * done)))


def annealing_temperature(config: RDOConfig, step: int, elapsed: float) -> float | None:
    """The temperature of annealed rounding at ``step`` / ``elapsed`` seconds (geometric from ``anneal_start``
    to ``anneal_end``), or None with ``rounding="noise"``."""
    if config.rounding != "annealed":
        return None
    return config.anneal_start * (config.anneal_end / config.anneal_start) ** _progress(config, step, elapsed)


def optimise_latents(model, images: torch.Tensor, cameras: Cameras, lam: float, start: CompressedLatents,
                     config: RDOConfig, progress: bool = False, perceptual: torch.nn.Module | None = None,
                     on_check: Callable[[RDOCheck, CompressedLatents], None] | None = None,
                     feature: torch.Tensor | None = None) -> RDOResult:
    """Optimise the latents of a scene from the amortised coding ``start`` (see the module docstring), or with
    ``config.variable="feature"`` the encoder's F_c that the latents are analysed from.

    Args:
        model: a :class:`~codecsplat_warp.model.CodecSplat` with its codec (its weights are not changed).
        images: [V,3,H,W] context images in [0,1]; cameras: the V context cameras (float32), on the model's device.
        lam: the rate-distortion lambda in [16, 1024].
        start: the amortised encoder's coding, with ``feature`` (``compress(..., reconstruct=True)``).
        config: the settings; ``config.steps`` of 0 returns ``start`` as it is.
        progress: show a progress bar (tqdm, on a terminal's stderr).
        perceptual: the perceptual network of ``config.perceptual_weight`` (see :func:`rdo_target`).
        on_check: called with every check and its coding (step 0 included), e.g. to score target views.
        feature: the amortised F_c [V,C_F,H/2,W/2] that ``start`` codes, for ``config.variable="feature"``.
    Returns:
        :class:`RDOResult`.
    """
    lam = check_lambda(lam)
    began = time.perf_counter()
    if not config.optimises:
        return RDOResult(start, 0, 0, 0.0, "steps")
    if start.feature is None:
        raise InputError("optimise_latents needs the amortised coding's feature: compress with reconstruct=True")
    variables = start_variables(start, config, feature)
    checks: list[RDOCheck] = []
    kept: dict = {}

    def record(check: RDOCheck, compressed: CompressedLatents) -> None:
        checks.append(check)
        if not kept or check.loss < kept["check"].loss:
            kept.update(check=check, compressed=compressed)
        if on_check is not None:
            on_check(check, compressed)

    with decoder_fixed(model, images.device):
        target = rdo_target(model, images, cameras, lam, start, config, perceptual)
        record(_measure(model, start, target, config, 0, time.perf_counter() - began), start)
        optimiser = latent_optimiser(variables, config)
        first_lr = optimiser.param_groups[0]["lr"]
        generator = torch.Generator(device=images.device).manual_seed(config.seed)
        model.train()
        decoder = step_decoder(model, target, variables, config)
        step, stopped = 0, "steps"
        bar = _progress_bar(config, progress)
        try:
            with validation(False):  # the model's outputs, not user input: one check per step would sync
                while True:
                    elapsed = time.perf_counter() - began
                    if config.steps is not None and step >= config.steps:
                        break
                    if config.time_budget is not None and elapsed >= config.time_budget:
                        stopped = "time"
                        break
                    for group in optimiser.param_groups:
                        group["lr"] = _learning_rate(config, first_lr, step, elapsed)
                    rdo_step(model, variables, optimiser, target, config, generator, decoder,
                             annealing_temperature(config, step, elapsed))
                    step += 1
                    _advance(bar, config, step, began)
                    if config.check_every and step % config.check_every == 0 and step != config.steps:
                        measured = _check(model, variables, target, config, step, began)
                        if measured is None:
                            stopped = "non-finite"
                            break
                        record(*measured)
                        _describe(bar, checks[-1], kept["check"])
        except KeyboardInterrupt:
            stopped = "interrupted"
        finally:
            if bar is not None:
                bar.close()
        if stopped != "non-finite" and step > checks[-1].step:
            measured = _check(model, variables, target, config, step, began)
            if measured is None:
                stopped = "non-finite"
            else:
                record(*measured)
        return RDOResult(kept["compressed"], kept["check"].step, step, time.perf_counter() - began, stopped, checks)


@contextlib.contextmanager
def decoder_fixed(model, device: torch.device) -> Iterator[None]:
    """The model set up for an optimisation through it on ``device``: every parameter frozen (no weight gradients)
    and, on the CPU, the decoder heads channels-last (:func:`heads_channels_last`); its parameters' gradient flags,
    weights and training mode given back when the block ends, however it ends."""
    was_training = model.training
    frozen = [p.requires_grad for p in model.parameters()]
    model.requires_grad_(False)
    originals = heads_channels_last(model, device)
    try:
        yield
    finally:
        restore_weights(originals)
        for p, flag in zip(model.parameters(), frozen):
            p.requires_grad_(flag)
        model.train(was_training)


CPU_CHANNELS_LAST = ("depth_head", "refine_post", "gs_head")
"""The decoder modules whose convolutions an RDO run on the CPU runs in channels-last layout (oneDNN's faster path:
a 2-view step of llff_horns on the 2-core EPYC 4.16 -> 3.90 s, medians of 12 interleaved steps). Not the codec: its
float64 prior path must compute what every decoder computes, bit for bit. Not on CUDA, where channels-last was
slower."""


def heads_channels_last(model, device: torch.device) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """On the CPU, the 4-dim weights of the modules of :data:`CPU_CHANNELS_LAST` in channels-last layout (the same
    values, the same parameters); returns each changed tensor with its former data for :func:`restore_weights`.
    Elsewhere nothing changes and the list is empty."""
    if device.type != "cpu":
        return []
    tensors = [t for name in CPU_CHANNELS_LAST for module in getattr(model, name).modules()
               for t in (*module.parameters(recurse=False), *module.buffers(recurse=False)) if t.dim() == 4]
    originals = [(t, t.data) for t in tensors]
    for t in tensors:
        t.data = t.data.contiguous(memory_format=torch.channels_last)
    return originals


def restore_weights(originals: list[tuple[torch.Tensor, torch.Tensor]]) -> None:
    """Give each tensor of :func:`heads_channels_last` its former data back."""
    for tensor, data in originals:
        tensor.data = data


def start_variables(start: CompressedLatents, config: RDOConfig, feature: torch.Tensor | None = None
                    ) -> list[torch.Tensor]:
    """The tensors the optimisation moves, as fresh leaves (float32): the amortised latents of ``start``, or for
    ``config.variable="feature"`` the amortised F_c ``feature`` (InputError when it is missing)."""
    if config.variable == "latents":
        return [z.detach().float().clone().requires_grad_(True) for z in start.latents]
    if feature is None:
        raise InputError("RDO with variable='feature' needs the amortised F_c: pass feature=")
    return [feature.detach().float().clone().requires_grad_(True)]


def latent_optimiser(variables: list[torch.Tensor], config: RDOConfig) -> torch.optim.Adam:
    """Adam over the optimised tensors (fused into one kernel on CUDA), starting at ``config.learning_rate`` for
    the latents and at ``config.feature_step`` times F_c's standard deviation for the feature."""
    lr = config.learning_rate
    if config.variable == "feature":
        lr = config.feature_step * float(variables[0].detach().std())
    return torch.optim.Adam(variables, lr=lr, fused=variables[0].device.type == "cuda")


def rdo_step(model, variables: list[torch.Tensor], optimiser: torch.optim.Optimizer, target: RDOTarget,
             config: RDOConfig, generator: torch.Generator | None, decoder: GraphedDecoder | None = None,
             temperature: float | None = None) -> dict:
    """One optimisation step of the optimised tensors ``variables`` in place (training quantiser; no host
    synchronisation of its own): loss, its gradient to ``variables`` alone, non-finite gradients zeroed, Adam,
    clamp to +-:data:`LATENT_LIMIT`. Returns the loss's parts before the step (:func:`rdo_loss`, detached 0-dim
    tensors). ``decoder``: see :func:`step_decoder`; ``temperature``: see :func:`rdo_loss`. The model is put in
    training mode unless it is in it already (the optimisation sets modes on the whole model only; a call of
    ``train()`` walks all its 295 modules). No gradient reaches the model's parameters, frozen or not: training
    runs these steps inside its own step (:func:`refine_latents`)."""
    if not model.training:
        model.train()
    loss, parts = rdo_loss(model, variables, target, config, generator, decoder=decoder, temperature=temperature)
    grads = torch.autograd.grad(loss, variables)
    with record_function("optimiser"), torch.no_grad():
        for v, g in zip(variables, grads):
            v.grad = torch.nan_to_num_(g, nan=0.0, posinf=0.0, neginf=0.0)
        optimiser.step()
        for v in variables:
            v.clamp_(-LATENT_LIMIT, LATENT_LIMIT)
    return {name: value.detach() for name, value in parts.items()}


@dataclass
class Refinement:
    """What :func:`refine_latents` returns: the refined ``latents`` (per level, detached, float32) and the
    loss's parts (:func:`rdo_loss`, detached 0-dim tensors) at the ``first`` and the ``last`` step (before each
    step's update; both None after 0 steps)."""

    latents: list[torch.Tensor]
    first: dict | None
    last: dict | None


def refine_latents(model, images: torch.Tensor, cameras: Cameras, lam: float, latents: list[torch.Tensor],
                   config: RDOConfig, generator: torch.Generator | None = None) -> Refinement:
    """``config.steps`` steps of the encoder's optimisation (:func:`rdo_step`, the presets' loss, learning-rate
    schedule and quantiser) from ``latents`` (per level, on the gained grid), without real codings or checks:
    what semi-amortised training runs inside each of its steps (:mod:`train.semi_amortised`), on the model as it
    is (its parameters may require gradients; none reaches them). ``config`` must have a step count and
    ``variable="latents"``; ``images`` [V,3,H,W] float32 in [0,1], ``cameras`` the V context cameras."""
    if config.steps is None or config.variable != "latents":
        raise InputError("refine_latents needs a step count and variable='latents'")
    variables = [z.detach().float().clone().requires_grad_(True) for z in latents]
    if config.steps == 0:
        return Refinement([v.detach() for v in variables], None, None)
    target = latent_target(model, images, cameras, lam, latents, config)
    optimiser = latent_optimiser(variables, config)
    first_lr = optimiser.param_groups[0]["lr"]
    first = last = None
    with validation(False):
        for step in range(config.steps):
            for group in optimiser.param_groups:
                group["lr"] = _learning_rate(config, first_lr, step, 0.0)
            last = rdo_step(model, variables, optimiser, target, config, generator,
                            temperature=annealing_temperature(config, step, 0.0))
            first = first or last
    return Refinement([v.detach() for v in variables], first, last)


def _check(model, variables: list[torch.Tensor], target: RDOTarget, config: RDOConfig, step: int,
           began: float) -> tuple[RDOCheck, CompressedLatents] | None:
    """Code the optimised tensors for real and measure them; None when they, or their loss, are not finite."""
    if not all(bool(torch.isfinite(v).all()) for v in variables):
        return None
    model.eval()
    if config.variable == "feature":
        compressed = model.codec.compress(variables[0].detach(), target.lam, reconstruct=True)
    else:
        compressed = model.codec.compress_latents(variables, target.lam, target.cameras.height // FEATURE_STRIDE,
                                                  target.cameras.width // FEATURE_STRIDE, reconstruct=True)
    check = _measure(model, compressed, target, config, step, time.perf_counter() - began)
    return (check, compressed) if math.isfinite(check.loss) else None


@torch.no_grad()
def _measure(model, compressed: CompressedLatents, target: RDOTarget, config: RDOConfig, step: int,
             seconds: float) -> RDOCheck:
    """The loss of a real coding (its decoder feature, its discrete-model bits), in eval mode."""
    model.eval()
    measured = replace(config, precision="float32")
    loss, parts = rdo_loss(model, compressed.latents, target, measured, compressed=compressed)
    return RDOCheck(step, seconds, float(loss), psnr_of_mse(float(parts["mse"])), float(compressed.bits.sum()))


def _progress_bar(config: RDOConfig, progress: bool):
    """A tqdm bar over the steps (or the budget's seconds when the steps are unlimited), or None."""
    if not progress:
        return None
    from tqdm.auto import tqdm

    if config.steps is not None:
        return tqdm(total=config.steps, desc="RDO", unit="step", leave=False, disable=None)
    return tqdm(total=round(config.time_budget, 1), desc="RDO", unit="s", leave=False, disable=None,
                bar_format="{l_bar}{bar}| {n:.1f}/{total:.1f} s [{elapsed}<{remaining}{postfix}]")


def _advance(bar, config: RDOConfig, step: int, began: float) -> None:
    if bar is None:
        return
    if config.steps is not None:
        bar.update(1)
    else:
        bar.n = min(round(time.perf_counter() - began, 1), bar.total)
        bar.refresh()


def _describe(bar, check: RDOCheck, best: RDOCheck) -> None:
    if bar is not None:
        bar.set_postfix_str(f"context {check.psnr:.2f} dB, {check.bits / 8192:.2f} KiB, best step {best.step}")
