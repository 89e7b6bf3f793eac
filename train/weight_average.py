"""Exponential moving average (EMA) of a model's trainable weights, the weights a run is evaluated and exported
with (:func:`train.checkpoint.weights_for_use`). Adjacent raw checkpoints of small-batch Adam runs can differ by
most of a dB on held-out scenes (a stage-1 run: 15.91 dB at step 13,250, 16.78 dB at step 13,333); an average
over the last ~1 / (1 - decay) steps is meant to smooth that out."""

from __future__ import annotations

import torch

from codecsplat_warp.errors import DataError, InputError


def warmed_up_decay(decay: float, updates: int) -> float:
    """Decay of the update after ``updates`` earlier ones: ``min(decay, (1 + updates) / (10 + updates))``
    (TF's ExponentialMovingAverage with num_updates), so that the first weights of a short run weigh little."""
    return min(decay, (1.0 + updates) / (10.0 + updates))


class WeightAverage:
    """EMA of the parameters of a module that require gradients, updated after each optimiser step.

    Attributes:
        decay: the decay in (0, 1) once warmed up (see :func:`warmed_up_decay`).
        updates: number of updates so far (0 right after :meth:`restart`).
        averages: {parameter name: float32 tensor of the parameter's shape, on the parameter's device}.
    """

    def __init__(self, model: torch.nn.Module, decay: float):
        if not 0.0 < decay < 1.0:
            raise InputError(f"the weight average's decay must be in (0, 1), got {decay}")
        self.decay = decay
        self.restart(model)

    def restart(self, model: torch.nn.Module) -> None:
        """Start over from ``model``'s current trainable weights (``updates`` 0)."""
        self.averages = {name: p.detach().to(torch.float32, copy=True)
                         for name, p in model.named_parameters() if p.requires_grad}
        self.updates = 0

    @torch.no_grad()
    def update(self, model: torch.nn.Module) -> None:
        """``average = d * average + (1 - d) * weight`` for every averaged parameter of ``model`` (the bare
        module, not a DDP wrapper), with ``d`` the warmed-up decay."""
        parameters = dict(model.named_parameters())
        weights = [parameters[name].detach().float() for name in self.averages]
        torch._foreach_lerp_(list(self.averages.values()), weights, 1.0 - warmed_up_decay(self.decay, self.updates))
        self.updates += 1

    def load(self, averages: dict[str, torch.Tensor], updates: int) -> None:
        """Continue from saved ``averages`` (the names and shapes of :attr:`averages`) after ``updates`` updates.
        Raises DataError when the names differ (a checkpoint of other trainable parameters)."""
        if set(averages) != set(self.averages):
            raise DataError(f"the saved weight average holds other parameters than the trainable ones: "
                            f"{sorted(set(averages) ^ set(self.averages))[:5]}")
        for name, average in self.averages.items():
            average.copy_(averages[name])
        self.updates = updates
