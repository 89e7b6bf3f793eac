"""The optimisation itself: the run of the presets (:func:`optimise_latents`, with its real codings, checks, time
budget and progress bar; Adam's steps or a learned refiner's iterations) and its steps without them
(:func:`refine_latents`, what semi-amortised training runs inside each training step, and :func:`learned_refine`,
what the refiner's training runs)."""

from __future__ import annotations

import contextlib
import math
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Iterator

import torch
from torch.profiler import record_function

from ...cameras import Cameras
from ...checks import validation
from ...codec.latent import CompressedLatents, check_lambda
from ...device import cudnn_autotuned
from ...errors import InputError
from ...nn.config import FEATURE_STRIDE
from ..culling import render_depth_range
from ..mvenc import context_neighbours
from .graphs import GraphedDecoder, context_loss, perceptual_distance, step_decoder, uses_cuda_graphs
from .loss import RDOTarget, psnr_of_mse, rdo_loss
from .presets import LATENT_LIMIT, RDOConfig
from .refiner import LatentRefiner, refiner_step


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
                     feature: torch.Tensor | None = None, refiner: LatentRefiner | None = None) -> RDOResult:
    """Optimise the latents of a scene from the amortised coding ``start`` (see the module docstring), or with
    ``config.variable="feature"`` the encoder's F_c that the latents are analysed from.

    With a ``refiner`` (:mod:`.refiner`, trained for this model) each step is one of its iterations
    (:func:`~.refiner.refiner_step`) instead of an Adam step, with the same loss, learning-rate schedule, time
    budget, checks and progress bar; the coding kept is then the last one measured (the refiner is trained for
    the target views at its last iteration, which the context loss of the checks cannot judge).

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
        refiner: a learned refiner, or None for the presets' Adam (InputError with ``config.variable="feature"``).
    Returns:
        :class:`RDOResult`.
    """
    lam = check_lambda(lam)
    began = time.perf_counter()
    if not config.optimises:
        return RDOResult(start, 0, 0, 0.0, "steps")
    if start.feature is None:
        raise InputError("optimise_latents needs the amortised coding's feature: compress with reconstruct=True")
    if refiner is not None and config.variable != "latents":
        raise InputError("a learned refiner moves the latents: it needs variable='latents'")
    variables = start_variables(start, config, feature)
    checks: list[RDOCheck] = []
    kept: dict = {}

    def record(check: RDOCheck, compressed: CompressedLatents) -> None:
        checks.append(check)
        if not kept or check.loss < kept["check"].loss or refiner is not None:
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
        state = refiner.start(variables) if refiner is not None else None
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
                    temperature = annealing_temperature(config, step, elapsed)
                    if refiner is None:
                        for group in optimiser.param_groups:
                            group["lr"] = _learning_rate(config, first_lr, step, elapsed)
                        rdo_step(model, variables, optimiser, target, config, generator, decoder, temperature)
                    else:
                        with torch.no_grad():
                            moved, _ = refiner_step(model, refiner, variables, state, target, config, generator,
                                                    _learning_rate(config, first_lr, step, elapsed),
                                                    _progress(config, step, elapsed), decoder, temperature)
                            for v, z in zip(variables, moved):
                                v.copy_(z)
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
    """The model set up for an optimisation through it on ``device``: every parameter frozen (no weight gradients,
    :func:`parameters_frozen`), on CUDA cuDNN's algorithm search on (:func:`~codecsplat_warp.device.cudnn_autotuned`:
    an 8-view step on an H200 47.2-47.5 -> 45.0-45.2 ms) and on the CPU the decoder heads channels-last
    (:func:`heads_channels_last`); its weights, training mode and cuDNN's flag given back when the block ends,
    however it ends."""
    was_training = model.training
    with parameters_frozen(model), cudnn_autotuned(device):
        originals = heads_channels_last(model, device)
        try:
            yield
        finally:
            restore_weights(originals)
            model.train(was_training)


@contextlib.contextmanager
def parameters_frozen(model) -> Iterator[None]:
    """Every parameter of ``model`` without gradient inside the block (an optimisation of its inputs records no
    weight-gradient paths, and its decoder can be captured as CUDA graphs, :func:`step_decoder`); each parameter's
    flag given back when the block ends, however it ends."""
    flags = [p.requires_grad for p in model.parameters()]
    model.requires_grad_(False)
    try:
        yield
    finally:
        for p, flag in zip(model.parameters(), flags):
            p.requires_grad_(flag)


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
    """What :func:`refine_latents` and :func:`learned_refine` return: the refined ``latents`` (per level, float32;
    detached from :func:`refine_latents`, with the graph to the refiner's parameters from :func:`learned_refine`
    under grad mode) and the loss's parts (:func:`rdo_loss`, detached 0-dim tensors) at the ``first`` and the
    ``last`` step (before each step's update; both None after 0 steps); from :func:`refine_latents` asked for it,
    also Adam's per-element ``step_scale`` after the last step (:func:`adam_step_scale`; else None, and None after 0
    steps)."""

    latents: list[torch.Tensor]
    first: dict | None
    last: dict | None
    step_scale: list[torch.Tensor] | None = None


STEP_SCALE_FLOOR = 0.1
""":func:`adam_step_scale` divides by at least this fraction of the mean root second moment of a level."""


@torch.no_grad()
def adam_step_scale(optimiser: torch.optim.Adam, variables: list[torch.Tensor]) -> list[torch.Tensor]:
    """How Adam's next step scales a change of the gradient, per element of each of ``variables`` (per level, the
    shapes of the latents; float32): ``(1 - beta1) / max(r, STEP_SCALE_FLOOR * mean(r))`` with ``r = sqrt(v / (1 -
    beta2^t))`` from its second moments ``v`` after ``t`` steps, i.e. the step's derivative by the gradient with the
    moments held (multiply by the learning rate for quantisation steps per unit of gradient). The floor (the mean
    over the level) bounds it where ``v`` is tiny: there the gradient that the step divides would raise ``v`` too,
    and the held moments would overstate the step's change by orders of magnitude."""
    group = optimiser.param_groups[0]
    beta1, beta2 = group["betas"]
    scales = []
    for v in variables:
        state = optimiser.state[v]
        root = (state["exp_avg_sq"] / (1.0 - beta2 ** float(state["step"]))).sqrt()
        floor = (STEP_SCALE_FLOOR * root.mean()).clamp_min(group["eps"])
        scales.append((1.0 - beta1) / torch.maximum(root, floor))
    return scales


def refine_latents(model, images: torch.Tensor, cameras: Cameras, lam: float, latents: list[torch.Tensor],
                   config: RDOConfig, generator: torch.Generator | None = None, step_scale: bool = False
                   ) -> Refinement:  # fmt: skip
    """``config.steps`` steps of the encoder's optimisation (:func:`rdo_step`, the presets' loss, learning-rate
    schedule and quantiser) from ``latents`` (per level, on the gained grid), without real codings or checks:
    what semi-amortised training runs inside each of its steps (:mod:`train.semi_amortised`), on the model as it
    is (its parameters may require gradients; none reaches them: they are frozen while it runs). With
    ``config.cuda_graphs`` on CUDA and at least :data:`~.graphs.GRAPH_MIN_STEPS` steps the decoder and the loss are
    replayed as CUDA graphs, as in the presets. ``config`` must have a step count and ``variable="latents"``;
    ``images`` [V,3,H,W] float32 in [0,1], ``cameras`` the V context cameras. ``step_scale``: also return Adam's
    step scale after the last step (:func:`adam_step_scale`; what a look-ahead needs, a few kernels per call)."""
    if config.steps is None or config.variable != "latents":
        raise InputError("refine_latents needs a step count and variable='latents'")
    variables = [z.detach().float().clone().requires_grad_(True) for z in latents]
    if config.steps == 0:
        return Refinement([v.detach() for v in variables], None, None)
    target = latent_target(model, images, cameras, lam, latents, config)
    optimiser = latent_optimiser(variables, config)
    first_lr = optimiser.param_groups[0]["lr"]
    first = last = None
    with validation(False), parameters_frozen(model):
        decoder = step_decoder(model.train(), target, variables, config)
        for step in range(config.steps):
            for group in optimiser.param_groups:
                group["lr"] = _learning_rate(config, first_lr, step, 0.0)
            last = rdo_step(model, variables, optimiser, target, config, generator, decoder,
                            temperature=annealing_temperature(config, step, 0.0))
            first = first or last
    scale = adam_step_scale(optimiser, variables) if step_scale else None
    return Refinement([v.detach() for v in variables], first, last, scale)


def learned_refine(model, images: torch.Tensor, cameras: Cameras, lam: float, latents: list[torch.Tensor],
                   refiner: LatentRefiner, config: RDOConfig, generator: torch.Generator | None = None
                   ) -> Refinement:  # fmt: skip
    """``config.steps`` iterations of a learned ``refiner`` (:func:`~.refiner.refiner_step`, the presets' loss,
    learning-rate schedule and quantiser, as :func:`optimise_latents` runs them) from ``latents`` (per level, on
    the gained grid), without real codings or checks: what the refiner's training runs (:mod:`train.
    learned_refiner`). Under grad mode the returned latents keep the graph through every iteration to the
    refiner's parameters (not to the model's: the loss's gradient is taken at detached copies). ``config`` must
    have a step count and ``variable="latents"``; ``images`` [V,3,H,W] float32 in [0,1], ``cameras`` the V context
    cameras."""
    if config.steps is None or config.variable != "latents":
        raise InputError("learned_refine needs a step count and variable='latents'")
    moved = [z.detach().float() for z in latents]
    if config.steps == 0:
        return Refinement(moved, None, None)
    target = latent_target(model, images, cameras, lam, latents, config)
    state = refiner.start(moved)
    first = last = None
    with validation(False):
        for step in range(config.steps):
            moved, last = refiner_step(model, refiner, moved, state, target, config, generator,
                                       _learning_rate(config, config.learning_rate, step, 0.0),
                                       _progress(config, step, 0.0), temperature=annealing_temperature(config, step, 0.0))
            first = first or last
    return Refinement(moved, first, last)


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
