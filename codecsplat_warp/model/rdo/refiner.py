"""A learned refiner of the latents: a small recurrent network that proposes the encoder's latent updates from the
gradient of the presets' own context loss, trained with the target views in the loss (``train/learned_refiner.py``).

Per iteration ``i`` (:func:`refiner_step`) and latent level ``l`` (latents ``z`` [V,C_l,h_l,w_l] on the gained
grid, float32, one quantisation step = 1):

1. ``g``: the gradient of :func:`~.loss.rdo_loss` (the presets' loss and training quantiser) with respect to ``z``,
   taken at a detached copy of ``z`` (first order: no gradient flows through ``g``); non-finite entries zeroed.
2. Adam's moments of ``g`` (``m``, ``v``; torch's defaults beta1 0.9, beta2 0.999, eps 1e-8, bias-corrected) give
   the Adam direction ``d = m^ / (sqrt(v^) + eps)`` and the normalised gradient ``g / (sqrt(v^) + eps)``.
3. A convolutional GRU per level (:class:`LevelCell`) reads ``z`` over the per-channel RMS of the amortised
   latents, ``z - z_0``, ``d``, the normalised gradient, the run's progress in [0, 1] and its lambda's position
   in [0, 1] (:func:`~codecsplat_warp.codec.latent.lambda_position`, log-linear from LAMBDA_MIN to LAMBDA_MAX),
   the last two as constant channels, with its hidden state, and proposes ``delta`` [V,C_l,h_l,w_l]. The lambda
   channel is there because the other inputs are invariant to the loss's scale: without it the refiner cannot
   tell a run at a small lambda, where bytes are dear, from one at a large lambda (trained without it, it
   proposed about the same moves at every lambda and, at lambda 128, spent far more bytes than Adam's steps).
4. ``z <- clamp(z + lr_i * (delta - exp(s_l) * d), +-LATENT_LIMIT)``, with ``lr_i`` the presets' learning-rate
   schedule at iteration ``i`` and ``s_l`` [C_l] a learned log step size per channel.

At initialisation ``delta`` is 0 (each level's output convolution starts at zero) and ``s_l`` is 0, so ``R``
iterations are exactly ``R`` Adam steps of the presets (:func:`~.loop.rdo_step`; torch's unfused Adam's
arithmetic): training starts from the optimiser it is meant to beat. The path ``z_i -> network -> z_{i+1}`` keeps
its graph, so the target views' loss at ``z_R`` reaches the network's weights through every iteration (truncated
where the gradient input is detached, as learned optimisers and RAFT-style refiners are trained).

A refiner is stored as safetensors (:func:`save_refiner`, format :data:`REFINER_FORMAT`) with its own id
(:func:`refiner_id`) and the id of the model it was trained for; :func:`load_refiner` refuses it for another model
or in another format (:class:`~codecsplat_warp.errors.RefinerError`, naming both ids or both formats).
"""

from __future__ import annotations

import hashlib
import json
import os
import pathlib
from dataclasses import dataclass

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save_file
from torch import nn

from ...codec.latent import lambda_position
from ...errors import InputError, RefinerError
from .loss import RDOTarget, rdo_loss
from .presets import LATENT_LIMIT, RDOConfig

REFINER_FORMAT = "codecsplat-latent-refiner/2"
"""The ``format`` entry of a refiner file's metadata. Format 1 had no lambda channel (its cells read one input
channel fewer); its files are refused."""

ADAM_BETAS = (0.9, 0.999)
ADAM_EPS = 1e-8
"""Adam's moment decays and epsilon (torch's defaults, those of the presets' optimiser)."""

INPUTS_PER_CHANNEL = 4
"""Inputs of a level's cell per latent channel: the scaled latents, their change, the Adam direction and the
normalised gradient (:data:`RUN_INPUTS` come on top)."""

RUN_INPUTS = 2
"""Constant input channels of a level's cell, one value per run and iteration: the run's progress and its
lambda's position, both in [0, 1]."""


@dataclass(frozen=True)
class RefinerConfig:
    """The refiner's sizes: ``channels`` per latent level (the codec's order, coarsest first) and ``hidden``, the
    GRU's state channels per level."""

    channels: tuple[int, ...]
    hidden: int = 16

    def __post_init__(self) -> None:
        if not self.channels or any(c < 1 for c in self.channels) or self.hidden < 1:
            raise InputError(f"a refiner needs channels >= 1 per level and hidden >= 1, got {self}")

    def to_dict(self) -> dict:
        return {"channels": list(self.channels), "hidden": self.hidden}

    @classmethod
    def from_dict(cls, data: dict) -> RefinerConfig:
        return cls(tuple(int(c) for c in data["channels"]), int(data["hidden"]))


class LevelCell(nn.Module):
    """One latent level's convolutional GRU: inputs [V, INPUTS_PER_CHANNEL*C+RUN_INPUTS, h, w] projected to
    ``hidden`` channels (1x1), the gates and candidate (3x3) over inputs and state, and the proposal ``delta``
    [V,C,h,w] (3x3, zero at initialisation, so that the inputs' weights, the lambda channel's included, may start
    anywhere). All float32."""

    def __init__(self, channels: int, hidden: int):
        super().__init__()
        self.project = nn.Conv2d(INPUTS_PER_CHANNEL * channels + RUN_INPUTS, hidden, 1)
        self.gates = nn.Conv2d(2 * hidden, 2 * hidden, 3, padding=1)
        self.candidate = nn.Conv2d(2 * hidden, hidden, 3, padding=1)
        self.head = nn.Conv2d(hidden, channels, 3, padding=1)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def forward(self, inputs: torch.Tensor, state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = torch.relu(self.project(inputs))
        update, reset = torch.sigmoid(self.gates(torch.cat([x, state], 1))).chunk(2, 1)
        candidate = torch.tanh(self.candidate(torch.cat([x, reset * state], 1)))
        state = (1 - update) * state + update * candidate
        return self.head(state), state


@dataclass
class RefinerState:
    """A run's state: the amortised latents ``start`` and their per-channel RMS ``scale`` [1,C_l,1,1] (both
    detached), Adam's moments ``first`` and ``second`` (detached), the GRUs' ``hidden`` states [V,hidden,h_l,w_l]
    (with their graph) and the iterations taken, ``count``."""

    start: list[torch.Tensor]
    scale: list[torch.Tensor]
    first: list[torch.Tensor]
    second: list[torch.Tensor]
    hidden: list[torch.Tensor]
    count: int = 0


class LatentRefiner(nn.Module):
    """The refiner of the module docstring: one :class:`LevelCell` and one log step size [C_l] per level."""

    def __init__(self, config: RefinerConfig):
        super().__init__()
        self.config = config
        self.cells = nn.ModuleList(LevelCell(c, config.hidden) for c in config.channels)
        self.log_step = nn.ParameterList(nn.Parameter(torch.zeros(c)) for c in config.channels)

    def start(self, latents: list[torch.Tensor]) -> RefinerState:
        """The state of a run from the amortised ``latents`` (per level [V,C_l,h_l,w_l]); InputError when their
        channels are not the refiner's."""
        channels = tuple(z.shape[1] for z in latents)
        if channels != self.config.channels:
            raise InputError(f"the refiner was built for latent channels {self.config.channels}, the model's latents "
                             f"have {channels}")
        start = [z.detach().float() for z in latents]
        scale = [z.square().mean(dim=(0, 2, 3), keepdim=True).sqrt().clamp_min(1e-3) for z in start]
        zeros = [torch.zeros_like(z) for z in start]
        hidden = [z.new_zeros(z.shape[0], self.config.hidden, *z.shape[2:]) for z in start]
        return RefinerState(start, scale, zeros, [z.clone() for z in zeros], hidden)

    def forward(self, latents: list[torch.Tensor], grads: list[torch.Tensor], state: RefinerState, lr: float,
                progress: float, lam: float) -> list[torch.Tensor]:
        """The moved latents (not yet clamped) from ``latents`` and their loss's ``grads`` (per level
        [V,C_l,h_l,w_l] float32; the gradients detached and finite), the learning rate ``lr`` of this iteration,
        the run's ``progress`` in [0, 1] and its rate-distortion ``lam`` (in [LAMBDA_MIN, LAMBDA_MAX]); updates
        ``state``."""
        beta1, beta2 = ADAM_BETAS
        state.count += 1
        correction1, correction2 = 1 - beta1 ** state.count, 1 - beta2 ** state.count
        run = (progress, lambda_position(lam))
        moved = []
        for level, (z, g) in enumerate(zip(latents, grads)):
            first = state.first[level] = beta1 * state.first[level] + (1 - beta1) * g
            second = state.second[level] = beta2 * state.second[level] + (1 - beta2) * g * g
            denominator = (second / correction2).sqrt() + ADAM_EPS
            direction = (first / correction1) / denominator
            constants = [z.new_full((z.shape[0], 1, *z.shape[2:]), value) for value in run]
            inputs = torch.cat([z / state.scale[level], z - state.start[level], direction, g / denominator,
                                *constants], 1)
            delta, state.hidden[level] = self.cells[level](inputs, state.hidden[level])
            step = self.log_step[level].exp()[None, :, None, None]
            moved.append(z + lr * (delta - step * direction))
        return moved


def refiner_step(model, refiner: LatentRefiner, latents: list[torch.Tensor], state: RefinerState,
                 target: RDOTarget, config: RDOConfig, generator: torch.Generator | None, lr: float, progress: float,
                 decoder=None, temperature: float | None = None) -> tuple[list[torch.Tensor], dict]:
    """One iteration of the refiner (the module docstring): the context loss's gradient at a detached copy of
    ``latents`` (:func:`~.loss.rdo_loss` with ``config``, ``generator``, ``decoder`` and ``temperature`` as
    :func:`~.loop.rdo_step` uses them; the model put in training mode), then the refiner's move at the run's
    lambda ``target.lam``, clamped to +-:data:`~.presets.LATENT_LIMIT`. Returns the new latents (with the graph to
    the refiner's parameters and to ``latents`` where grad mode is on) and the loss's parts before the move
    (detached 0-dim tensors)."""
    if not model.training:
        model.train()
    leaves = [z.detach().requires_grad_(True) for z in latents]
    with torch.enable_grad():
        loss, parts = rdo_loss(model, leaves, target, config, generator, decoder=decoder, temperature=temperature)
        grads = torch.autograd.grad(loss, leaves)
    grads = [torch.nan_to_num(g, nan=0.0, posinf=0.0, neginf=0.0) for g in grads]
    moved = refiner(latents, grads, state, lr, progress, target.lam)
    return [z.clamp(-LATENT_LIMIT, LATENT_LIMIT) for z in moved], {k: v.detach() for k, v in parts.items()}


def refiner_id(refiner: LatentRefiner) -> str:
    """16 hex digits naming a refiner: SHA-256 of its config and weights (names, shapes, float32 values)."""
    sha = hashlib.sha256(json.dumps(refiner.config.to_dict(), sort_keys=True).encode())
    state = refiner.state_dict()
    for name in sorted(state):
        tensor = state[name].detach().to("cpu", torch.float32).contiguous()
        sha.update(f"{name}:{tuple(tensor.shape)}".encode())
        sha.update(tensor.numpy().astype("<f4").tobytes())
    return sha.hexdigest()[:16]


def save_refiner(refiner: LatentRefiner, path, model_id: str) -> str:
    """Write ``refiner`` to the safetensors file ``path`` (atomically) with its config, its id and the id of the
    model it was trained for (``model_id``, :func:`~codecsplat_warp.model.codecsplat.model_id`); returns its id."""
    path = pathlib.Path(path)
    identity = refiner_id(refiner)
    tensors = {name: t.detach().to("cpu", torch.float32).contiguous() for name, t in refiner.state_dict().items()}
    metadata = {"format": REFINER_FORMAT, "config": json.dumps(refiner.config.to_dict()), "refiner_id": identity,
                "model_id": model_id}
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    save_file(tensors, str(tmp), metadata=metadata)
    os.replace(tmp, path)
    return identity


def load_refiner(path, model_id: str | None = None, device=None) -> tuple[LatentRefiner, dict]:
    """A refiner from a file of :func:`save_refiner`, in eval mode with its parameters frozen, on ``device``;
    returns it and the file's metadata (``refiner_id``, ``model_id``).

    Raises:
        RefinerError: the file is missing, unreadable, of another format or corrupt (its weights do not match its
            id), or ``model_id`` is given and is not the id of the model the refiner was trained for.
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise RefinerError(f"refiner file {path} not found")
    try:
        with safe_open(str(path), framework="pt") as f:
            metadata = f.metadata() or {}
            tensors = {name: f.get_tensor(name) for name in f.keys()}  # noqa: SIM118 (safe_open is not iterable)
    except (SafetensorError, OSError) as exc:
        raise RefinerError(f"{path} is not a readable safetensors file: {exc}") from None
    found = metadata.get("format")
    if found != REFINER_FORMAT:
        if str(found).startswith(REFINER_FORMAT.rsplit("/", 1)[0] + "/"):
            raise RefinerError(f"{path}: a latent refiner of format {found}, this version reads "
                               f"{REFINER_FORMAT} only: train one again with python -m "
                               f"train.learned_refiner")
        raise RefinerError(f"{path}: not a latent refiner file (format {found!r}, expected {REFINER_FORMAT})")
    try:
        refiner = LatentRefiner(RefinerConfig.from_dict(json.loads(metadata["config"])))
        refiner.load_state_dict(tensors)
    except (KeyError, ValueError, RuntimeError) as exc:
        raise RefinerError(f"{path}: config and weights do not fit together: {exc}") from None
    if refiner_id(refiner) != metadata.get("refiner_id"):
        raise RefinerError(f"{path}: the weights do not match the refiner id {metadata.get('refiner_id')} (corrupt "
                           f"file)")
    if model_id is not None and metadata.get("model_id") != model_id:
        raise RefinerError(f"refiner {metadata['refiner_id']} ({path}) was trained for model "
                           f"{metadata.get('model_id')}, not for this model {model_id}: train one for it with "
                           f"python -m train.learned_refiner --model <its file>")
    refiner.requires_grad_(False)
    if device is not None:
        refiner = refiner.to(device)
    return refiner.eval(), {"refiner_id": metadata["refiner_id"], "model_id": metadata["model_id"]}
