"""Learned refiner training: a small recurrent network that moves the latents at encode time, trained with the
target views in the loss; the model (encoder and decoder) stays frozen, so bitstreams and decoders do not change.

The refiner (:mod:`codecsplat_warp.model.rdo.refiner`) reads, per latent level and iteration, the latents and the
gradient of the presets' own context loss (normalised by Adam's moments), the run's progress and its lambda, with its
GRU state, and proposes the update; at initialisation its iterations are the presets' Adam steps. Per training step
and scene:

1. the frozen model's amortised encoder and codec give the latents ``z_0`` (:meth:`CodecSplat.forward` with a
   lambda drawn as stage 2 draws it, log-uniform in [LAMBDA_MIN, LAMBDA_MAX]; the refiner reads the same lambda),
   without gradient;
2. ``R`` iterations of the refiner run on the context views from ``z_0``
   (:func:`codecsplat_warp.model.rdo.learned_refine`, the code the encoder runs with a refiner: the loss,
   learning-rate schedule and quantiser of ``--inner-preset`` with ``R`` steps). ``R`` is drawn per training step
   from the list ``--iterations`` (:func:`train.semi_amortised.draw_count`, a function of the seed and the step
   alone: every scene of the step and every DDP rank runs the same count), so that one refiner learns every count
   the encoder will run it at (one trained at 25 iterations alone beat Adam's steps at 25 and 50 but fell behind
   them at 160, at a higher rate). The gradient input of each iteration is detached (first order); the path
   through the refiner keeps its graph;
3. the frozen decoder decodes ``z_R`` and stage 2's loss is taken on the *target* views
   (:func:`train.stage2.codec_loss`: render distortion, depth and rate terms), whose gradient reaches the refiner's
   weights alone, through every iteration.

Besides stage 2's metrics the log holds the refiner's (:data:`REFINER_LOGGED`, ``iterations`` the step's ``R``).
The run folder's newest weights (the weight average's, :func:`train.checkpoint.weights_for_use`) are written as
``refiner.safetensors`` in ``--out`` when the run ends (at ``--steps``, at ``--time-limit-s`` or on SIGTERM), with
the refiner's id and the model's (:func:`codecsplat_warp.model.rdo.save_refiner`); ``codecsplat bench rdo
--refiner`` screens it.

Everything else (data, checkpoints every ``--checkpoint-every`` steps and on SIGTERM or ``--time-limit-s``,
resumption from ``--out``, DDP under torchrun, TensorBoard, metrics.jsonl) is stage 1's loop
(:func:`train.stage1.train`)::

    torchrun --nproc_per_node 4 -m train.learned_refiner --data runs/scenes-256 --holdout ... \\
        --iterations 8,25,50,160 --steps 2000 --out runs/refiner
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import time
from dataclasses import dataclass

import torch
import torch.distributed as dist

from codecsplat_warp.errors import DataError, InputError
from codecsplat_warp.metrics import LPIPS
from codecsplat_warp.metrics.image import psnr
from codecsplat_warp.model import CodecSplat
from codecsplat_warp.model.codecsplat import model_id
from codecsplat_warp.model.pretrained import DEFAULT_CHECKPOINT
from codecsplat_warp.model.rdo import (LatentRefiner, RefinerConfig, learned_refine, load_refiner,
                                       rdo_config, save_refiner)
from codecsplat_warp.nn.config import ModelConfig

from . import stage1, stage2
from .checkpoint import latest_checkpoint, model_file_config, read_weights, weights_for_use
from .data import BatchSource, TrainingBatch
from .semi_amortised import check_inner_preset, decode_latents, draw_count, parse_counts, psnr_of, synchronize

REFINER_LOGGED = ("iterations", "context_gain", "target_gain", "target_psnr_amortised", "iterations_per_s")
"""The refiner's metrics, logged beside stage 2's: its iterations per scene (the count ``R`` drawn for the step);
the context views' PSNR gain over them (dB, of the loss's noisy-quantiser renders, first iteration against last);
the targets' PSNR of the refined decode minus the amortised decode's (dB); the amortised decode's target PSNR (dB);
iterations per second."""

LOGGED = stage2.LOGGED + REFINER_LOGGED

REFINER_FILE = "refiner.safetensors"
"""The refiner file a run writes in its folder when it ends."""


@dataclass
class LearnedRefinerConfig(stage2.Stage2Config):
    """Options: stage 2's (:class:`train.stage2.Stage2Config`) plus the refiner's; ``model`` names the frozen
    model, ``init`` a refiner file to start from, and ``codec_init``, ``codec_latent_channels``,
    ``codec_finest_stride`` and ``trainable`` are not used."""

    out: str = "runs/refiner"
    steps: int = 2000
    model: str = str(DEFAULT_CHECKPOINT)
    init: str = ""
    lr: float = 1e-4
    warmup_steps: int = 50
    rate_warmup_steps: int = 0
    beta: float | None = 1.3e-3
    views: str = "2"
    coded_every: int = 1000
    iterations: str = "8"
    inner_preset: str = "medium"
    hidden: int = 16


OPTION_HELP = {
    **stage2.OPTION_HELP,
    "model": "the frozen model the refiner is trained for: a model file (default: the shipped model)",
    "init": "a refiner file to start from (default: none, a fresh refiner whose iterations are Adam's steps)",
    "iterations": "comma list of the refiner's iteration counts R, one drawn per training step for all its scenes "
                  "(the target loss is taken at the last iteration); list the counts the encoder will run it at, "
                  "one twice to draw it twice as often",
    "inner_preset": "the encoder preset whose loss, learning rate and cross-view term the iterations use (medium or "
                    "slow; its schedule spread over the R iterations)",
    "hidden": "the refiner's GRU state channels per latent level",
    "codec_init": "not used by this stage",
    "codec_latent_channels": "not used by this stage",
    "codec_finest_stride": "not used by this stage",
    "trainable": "not used by this stage (only the refiner trains)",
}
"""``--help`` text of every :class:`LearnedRefinerConfig` field."""


class RefinerTraining(torch.nn.Module):
    """The frozen ``model`` and the trained ``refiner`` as one module, so that stage 1's loop checkpoints both and
    DDP all-reduces the refiner's gradients: its forward is the refinement of a batch (:meth:`forward`)."""

    def __init__(self, model: CodecSplat, refiner: LatentRefiner):
        super().__init__()
        self.model = model
        self.refiner = refiner

    def forward(self, batch: TrainingBatch, lam: float, latents: list[torch.Tensor], config: LearnedRefinerConfig,
                step: int) -> tuple[list[torch.Tensor], dict]:
        """Each scene of ``batch`` refined by ``R`` iterations from its slice of ``latents`` (per level,
        [S*V,C_l,h_l,w_l], scene-major), ``R`` drawn from ``config.iterations`` for the training ``step`` (the
        same on every rank): the refined latents (the same shapes, with the graph to the refiner's parameters)
        and the refiner's metrics (:data:`REFINER_LOGGED`, means over the scenes; the target ones 0 here)."""
        rank = dist.get_rank() if dist.is_initialized() else 0
        views = batch.context_images.shape[0] // batch.scenes
        device = batch.context_images.device
        iterations = draw_count(parse_counts(config.iterations, "--iterations", 1), config.seed, step, 0, 0)
        rdo = rdo_config(config.inner_preset, steps=iterations, views=views, cuda_graphs=False, check_every=0)
        refined, gains = [], []
        synchronize(device)
        began = time.perf_counter()
        for scene, cameras in enumerate(batch.scene_contexts()):
            rows = slice(scene * views, (scene + 1) * views)
            generator = torch.Generator(device=device).manual_seed(
                ((config.seed * 1_000_003 + step) * 1009 + rank) * 101 + scene)
            result = learned_refine(self.model, batch.context_images[rows].float(), cameras.to(dtype=torch.float32),
                                    lam, [z[rows] for z in latents], self.refiner, rdo, generator)
            refined.append(result.latents)
            if result.first is not None:
                gains.append(psnr_of(result.last["mse"]) - psnr_of(result.first["mse"]))
        synchronize(device)
        total = iterations * batch.scenes
        metrics = {"iterations": float(iterations),
                   "context_gain": torch.stack(gains).mean() if gains else 0.0,
                   "target_gain": 0.0, "target_psnr_amortised": 0.0,
                   "iterations_per_s": total / max(time.perf_counter() - began, 1e-9) if total else 0.0}
        return [torch.cat(level) for level in zip(*refined)], metrics


def refiner_loss(trained: torch.nn.Module, lpips: LPIPS, batch: TrainingBatch, config: LearnedRefinerConfig,
                 step: int) -> tuple[torch.Tensor, dict]:
    """Stage 2's loss on the target views of the latents the refiner reaches (see the module docstring); returns
    (loss, metrics as floats or detached 0-dim tensors). ``trained`` is the :class:`RefinerTraining` or its DDP
    wrapper."""
    model = (trained.module if hasattr(trained, "module") else trained).model
    lam = stage2.step_lambda(config, step)
    images, cameras = batch.context_images, batch.context_cameras
    with torch.no_grad(), torch.autocast(images.device.type, dtype=torch.bfloat16,
                                         enabled=images.device.type == "cuda"):
        out = model(images, cameras, lam=lam, scenes=batch.scenes)
        amortised = psnr(stage1.render_targets(model, out["gaussians"], batch), batch.target_images).mean()
    refined, inner = trained(batch, lam, out["latents"], config, step)
    out = {**out, **decode_latents(model, cameras, lam, out["neighbours"], refined)}
    loss, metrics = stage2.codec_loss(model, lpips, batch, config, step, lam, out)
    inner.update(target_psnr_amortised=amortised, target_gain=metrics["psnr"] - amortised)
    return loss, {**metrics, **inner}


def build_model(model_config: ModelConfig, config: LearnedRefinerConfig) -> RefinerTraining:
    """The frozen model from ``config.model`` and a refiner for its latents, fresh or from ``config.init``
    (neither is read when ``config.out`` has a checkpoint to resume); only the refiner's parameters require
    gradients. Raises DataError when ``config.model`` does not hold this model's weights and RefinerError when
    ``config.init`` is not a refiner trained for it."""
    model = CodecSplat(model_config, codec=True)
    refiner = LatentRefiner(RefinerConfig(tuple(model_config.codec_latent_channels), config.hidden))
    if latest_checkpoint(config.out) is None:
        try:
            model.load_state_dict(read_weights(config.model))
        except RuntimeError as exc:
            raise DataError(f"--model {config.model} does not hold a CodecSplat of the sizes in its config: {exc}") \
                from None
        if config.init:
            start, _ = load_refiner(config.init, model_id(model))
            if start.config != refiner.config:
                raise InputError(f"--init {config.init} is a refiner of sizes {start.config}, not {refiner.config}")
            refiner.load_state_dict(start.state_dict())
    model.requires_grad_(False)
    refiner.requires_grad_(True)
    return RefinerTraining(model, refiner)


def run_model_config(config: LearnedRefinerConfig) -> ModelConfig:
    """The model's sizes: from ``config.out`` when resuming, else from the metadata of the model file
    ``config.model``."""
    file = pathlib.Path(config.out) / "config.json"
    if file.is_file():
        return ModelConfig.from_dict(json.loads(file.read_text())["model"])
    return model_file_config(config.model, "--model")


def export_refiner(run_dir) -> tuple[pathlib.Path, str]:
    """Write the newest checkpoint's refiner (the weight average's values when kept) to ``run_dir/``
    :data:`REFINER_FILE`, tied to the id of the frozen model in the checkpoint; returns the file and the refiner's
    id. DataError when ``run_dir`` has no checkpoint."""
    run_dir = pathlib.Path(run_dir)
    folder = latest_checkpoint(run_dir)
    if folder is None:
        raise DataError(f"{run_dir}: no checkpoint to export a refiner from")
    settings = json.loads((run_dir / "config.json").read_text())
    weights = weights_for_use(folder)
    model = CodecSplat(ModelConfig.from_dict(settings["model"]), codec=True)
    model.load_state_dict({k.removeprefix("model."): v for k, v in weights.items() if k.startswith("model.")})
    refiner = LatentRefiner(RefinerConfig(tuple(model.config.codec_latent_channels), settings["train"]["hidden"]))
    refiner.load_state_dict({k.removeprefix("refiner."): v for k, v in weights.items() if k.startswith("refiner.")})
    path = run_dir / REFINER_FILE
    return path, save_refiner(refiner, path, model_id(model))


STAGE = stage1.Stage("refiner", build_model, refiner_loss, LOGGED)


def train(config: LearnedRefinerConfig, source: BatchSource | None = None, progress: bool = True) -> dict:
    """Run (or resume) the refiner's training until ``config.steps`` (:func:`train.stage1.train`), then write
    its file (:func:`export_refiner`, rank 0); the metrics of the last step carry ``refiner`` (the file) and
    ``refiner_id``."""
    metrics = stage1.train(config, source, run_model_config(config), progress, stage=STAGE)
    if int(os.environ.get("RANK", "0")) == 0 and latest_checkpoint(config.out) is not None:
        path, identity = export_refiner(config.out)
        metrics.update(refiner=str(path), refiner_id=identity)
    return metrics


def build_parser() -> argparse.ArgumentParser:
    """The command line: :class:`LearnedRefinerConfig`'s fields as flags."""
    return stage1.build_parser(LearnedRefinerConfig, OPTION_HELP, "python -m train.learned_refiner",
                               __doc__.split("\n\n")[0])


def parse_args(argv: list[str] | None = None) -> LearnedRefinerConfig:
    """Command line -> :class:`LearnedRefinerConfig`; InputError for a bad refiner option."""
    config = stage1.parse_args(argv, LearnedRefinerConfig, build_parser())
    check_inner_preset(config.inner_preset)
    parse_counts(config.iterations, "--iterations", 1)
    if config.hidden < 1:
        raise InputError("--hidden must be >= 1")
    if config.coded_every < 1:
        raise InputError("--coded-every must be >= 1")
    return config


def main(argv: list[str] | None = None) -> None:
    stage1.print_final_metrics(train(parse_args(argv)))


if __name__ == "__main__":
    main()
