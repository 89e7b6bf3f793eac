"""CUDA graphs of a run: the decoder (:class:`GraphedDecoder`) and the loss's fixed and perceptual terms,
captured once per run and replayed every step; a capture that fails falls back to eager, with a warning. Every
capture runs inside :func:`~codecsplat_warp.device.capture_guard`.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import torch

from ...checks import validation
from ...device import capture_guard
from ...gaussians import Gaussians
from .loss import ContextLoss, Decoded, PerceptualDistance, RDOTarget, decode_variables
from .presets import RDOConfig

GRAPH_MIN_STEPS = 16
"""Runs of fewer steps stay eager: the capture costs about as much as a dozen steps save (2 views on an H200:
0.25 s for 5 graphed steps against 0.19 s eager)."""


def uses_cuda_graphs(config: RDOConfig, device: torch.device) -> bool:
    """Whether a run of ``config`` on ``device`` replays the decoder as CUDA graphs: on CUDA, with
    ``config.cuda_graphs``, and with at least :data:`GRAPH_MIN_STEPS` steps (or a time budget alone)."""
    long_enough = config.steps is None or config.steps >= GRAPH_MIN_STEPS
    return config.cuda_graphs and device.type == "cuda" and long_enough


def perceptual_distance(network: torch.nn.Module, target_units: list[torch.Tensor], images: torch.Tensor,
                        graphed: bool) -> Callable[[torch.Tensor], torch.Tensor]:
    """:class:`PerceptualDistance` for renders shaped like ``images``; with ``graphed`` (CUDA) its forward and
    backward captured as CUDA graphs (``torch.cuda.make_graphed_callables``): with LPIPS-VGG launched eagerly a
    2-view step took 16.0 ms on an H200, replayed 12.9-13.2 ms. A capture that fails falls back to eager, with a
    warning."""
    distance = PerceptualDistance(network, target_units)
    if not graphed:
        return distance
    sample = (torch.rand_like(images, dtype=torch.float32).requires_grad_(True),)
    return _graphed_callable(distance, sample, "the RDO perceptual term")


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
    sample = (torch.rand(views, 3, H, W, device=images.device).requires_grad_(True),
              torch.rand((), device=images.device).requires_grad_(True))
    if config.cross_view_weight > 0:
        sample += (torch.rand(views, H, W, device=images.device).requires_grad_(True),)
    return _graphed_callable(loss, sample, "the RDO loss")


ACCUMULATE_GRAD_STREAM_WARNING = "The AccumulateGrad node's stream does not match"
"""The start of torch's warning (since torch 2.10) that a gradient arrives on another stream than the one its leaf's
accumulator was made on: ``torch.cuda.make_graphed_callables`` itself gives it once, warming the sample up on a side
stream and capturing on another. Harmless there: the graphs hand the sample's gradients back, no accumulator runs."""


def _graphed_callable(function: torch.nn.Module, sample: tuple[torch.Tensor, ...], what: str) -> Callable:
    """``torch.cuda.make_graphed_callables(function, sample)`` (``sample``: CUDA tensors shaped as the calls'
    arguments, requiring gradients), captured inside :func:`~codecsplat_warp.device.capture_guard` and without
    :data:`ACCUMULATE_GRAD_STREAM_WARNING`; ``function`` itself when the capture fails, with a warning that says
    ``what`` runs without CUDA graphs."""
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=ACCUMULATE_GRAD_STREAM_WARNING, category=UserWarning)
            with torch.enable_grad(), validation(False), capture_guard(sample[0].device):
                return torch.cuda.make_graphed_callables(function, sample)
    except RuntimeError as error:
        warnings.warn(f"{what} runs without CUDA graphs: capturing it failed ({error})", RuntimeWarning, stacklevel=3)
        return function


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
        with capture_guard(variables[0].device):
            self._capture(model, target, variables, variable, annealed, precision)

    def _capture(self, model, target: RDOTarget, variables: list[torch.Tensor], variable: str, annealed: bool,
                 precision: str) -> None:
        """Warm the decoder up and capture its two graphs (arguments as the constructor's)."""
        with torch.no_grad():
            embedding = model.codec.embedding(target.lam)
        device = variables[0].device
        self.temperature = temperature = torch.full((), 0.5, device=device) if annealed else None
        self.noise = noise = [torch.rand_like(z, dtype=torch.float32) for z in target.latents]
        self.variables = static = [v.detach().clone().requires_grad_(True) for v in variables]

        # the closures hold the static tensors, not self: a graphed decoder is freed as soon as its run drops it,
        # not later by the cyclic garbage collector (see the module docstring)
        def decode() -> list[torch.Tensor]:
            # a graph replays kernels, not autocast's cast cache: captured without it
            with torch.autocast("cuda", dtype=torch.bfloat16, enabled=precision == "bfloat16", cache_enabled=False):
                bits, s, g = decode_variables(model, static, target, variable, noise=noise,
                                              lambda_embedding=embedding, temperature=temperature)
            return [bits, s, g.means, g.quats, g.scales, g.opacities, g.sh]

        def backward(outputs: list[torch.Tensor], grads: list[torch.Tensor]) -> tuple[torch.Tensor, ...]:
            return torch.autograd.grad(outputs, static, grads, allow_unused=True)

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
