"""Stage-2 training (paper §3.5, Eqs. 11-13): the codec, decoder depth head and post-codec refiner.

Initialised from a stage-1 run (``--init``); everything else is frozen. Per step, lambda is drawn
log-uniformly from [16, 1024] and the loss is

    (lambda / 1024) * [D_render + gamma * |S - S_enc|_1] + beta * R

with D_render = MSE + 0.05 LPIPS-VGG (as in stage 1), S the decoder's normalised inverse depth (Eq. 7),
S_enc the encoder's (Eq. 13), gamma = 0.1 and R the estimated rate in bits per context pixel (Eq. 6
divided by V*H*W: D_render is a per-pixel mean, and the paper's beta only balances it in these units).
beta defaults to 1e-4 for the dl3dv preset and 4e-4 otherwise (RE10K). Over the first
``--rate-warmup-steps`` steps beta ramps up linearly from 0 (rate annealing): a fresh codec's decoder cannot
use its latents yet, and a full rate penalty from the start drives every latent to the prior (posterior
collapse) before it learns to.

Every ``--coded-every`` steps the current scene is also really encoded (eval mode): the log then holds the
coded feature bits, the discrete model's estimate of them (``rate_gap`` = coded / estimate - 1, the
coder's overhead, a few percent at most) and ``train_rate_gap`` (coded / the step's noisy training estimate - 1).
The training loop, checkpoints, resumption, TensorBoard, metrics.jsonl, bf16 and DDP are stage 1's
(:func:`train.stage1.train`).

    python -m train.stage2 --init runs/stage1-re10k --data procedural --steps 200000 --out runs/stage2-re10k
"""

from __future__ import annotations

import json
import math
import pathlib
from dataclasses import dataclass

import torch
import torch.distributed as dist
from torch.nn import functional as F

from codecsplat_warp.codec import LAMBDA_MAX, LAMBDA_MIN
from codecsplat_warp.errors import DataError, InputError
from codecsplat_warp.metrics import LPIPS
from codecsplat_warp.model import CodecSplat, ModelConfig

from . import stage1
from .checkpoint import latest_checkpoint, load_model_weights
from .data import Source, TrainingSample

RATE_WEIGHTS = {"dl3dv": 1e-4}
"""beta of a preset (by ModelConfig.name); others use :data:`DEFAULT_RATE_WEIGHT` (the paper's RE10K value)."""

DEFAULT_RATE_WEIGHT = 4e-4

LOGGED = ("loss", "mse", "lpips", "psnr", "depth_l1", "lambda", "bits", "bpp", "grad_norm", "lr",
          "coded_bits", "coded_estimate_bits", "rate_gap", "train_rate_gap")
"""Metrics written every ``log_every`` steps (the coded_* ones only on steps that encode)."""


@dataclass
class Stage2Config(stage1.TrainConfig):
    """Stage-2 options: stage 1's (see :class:`train.stage1.TrainConfig`) plus the ones below.

    ``preset`` is ignored: the network sizes are those of the ``init`` run.
    """

    out: str = "runs/stage2"
    steps: int = 200_000
    init: str = ""
    gamma: float = 0.1
    beta: float | None = None
    rate_warmup_steps: int = 5000
    coded_every: int = 200


def rate_weight(config: Stage2Config, model_config: ModelConfig) -> float:
    """beta: ``config.beta`` or the preset's default (:data:`RATE_WEIGHTS`)."""
    return config.beta if config.beta is not None else RATE_WEIGHTS.get(model_config.name, DEFAULT_RATE_WEIGHT)


def rate_ramp(step: int, warmup: int) -> float:
    """Factor of beta at ``step``: linear from 1/warmup to 1 over the first ``warmup`` steps, then 1."""
    return min(1.0, (step + 1) / warmup) if warmup > 0 else 1.0


def sample_lambda(seed: int, step: int, rank: int) -> float:
    """Lambda of a step, log-uniform in [LAMBDA_MIN, LAMBDA_MAX], a function of (seed, step, rank) only."""
    generator = torch.Generator().manual_seed((seed * 1_000_003 + step) * 1009 + rank)
    u = float(torch.rand((), generator=generator, dtype=torch.float64))
    return math.exp(math.log(LAMBDA_MIN) + u * (math.log(LAMBDA_MAX) - math.log(LAMBDA_MIN)))


def stage2_loss(model: torch.nn.Module, lpips: LPIPS, sample: TrainingSample, config: Stage2Config,
                step: int) -> tuple[torch.Tensor, dict]:
    """Eq. 12 for one scene at a lambda drawn for ``step``; returns (loss, float metrics).

    ``model`` may be the DDP wrapper; rendering and the coded-rate check use the bare module.
    """
    bare = model.module if hasattr(model, "module") else model
    rank = dist.get_rank() if dist.is_initialized() else 0
    lam = sample_lambda(config.seed, step, rank)
    images, cameras = sample.context_images, sample.context_cameras
    device = images.device
    with torch.autocast(device.type, dtype=torch.bfloat16, enabled=device.type == "cuda"):
        out = model(images, cameras, lam=lam)
    rgb = bare.render(out["gaussians"], sample.target_cameras)["rgb"]
    mse = F.mse_loss(rgb, sample.target_images)
    perceptual = lpips(rgb, sample.target_images).mean()
    depth_l1 = (out["S"].float() - out["S_enc"].detach().float()).abs().mean()
    bpp = out["rate_bits"] / images[:, 0].numel()
    distortion = mse + config.lpips_weight * perceptual + config.gamma * depth_l1
    beta = rate_weight(config, bare.config) * rate_ramp(step, config.rate_warmup_steps)
    loss = lam / LAMBDA_MAX * distortion + beta * bpp
    metrics = {"loss": loss.item(), "mse": mse.item(), "lpips": perceptual.item(), "depth_l1": depth_l1.item(),
               "psnr": float(stage1.psnr(rgb.detach(), sample.target_images)), "lambda": lam,
               "bits": out["rate_bits"].item(), "bpp": bpp.item()}
    if (step + 1) % config.coded_every == 0:
        metrics.update(coded_rate(bare, sample, lam, metrics["bits"]))
    return loss, metrics


@torch.no_grad()
def coded_rate(model: CodecSplat, sample: TrainingSample, lam: float, training_bits: float) -> dict:
    """Really encode the sample's context views at ``lam`` (eval mode) and compare with the rate estimates."""
    was_training = model.training
    model.eval()
    try:
        encoded = model.encode_scene(sample.context_images, sample.context_cameras, lam)
    finally:
        model.train(was_training)
    coded = 8.0 * sum(encoded.feature_bytes)
    estimate = float(encoded.estimated_bits.sum())
    return {"coded_bits": coded, "coded_estimate_bits": estimate, "rate_gap": coded / estimate - 1.0,
            "train_rate_gap": coded / training_bits - 1.0}


def build_stage2_model(model_config: ModelConfig, config: Stage2Config) -> CodecSplat:
    """A CodecSplat with its codec: backbone from the stage-1 run ``config.init`` (unless ``config.out``
    already has a checkpoint to resume), only the stage-2 modules trainable."""
    model = CodecSplat(model_config, codec=True)
    if latest_checkpoint(config.out) is None:
        load_stage1_weights(model, config.init)
    model.requires_grad_(False)
    for module in model.codec_modules():
        module.requires_grad_(True)
    return model


def load_stage1_weights(model: CodecSplat, run) -> None:
    """Copy the newest checkpoint of the stage-1 run ``run`` into ``model``'s backbone (its stage-2 modules keep
    their initialisation). Raises DataError when ``run`` has no stage-1 checkpoint."""
    folder = latest_checkpoint(run)
    if folder is None:
        raise DataError(f"--init {run}: no checkpoint there (expected a stage-1 run folder with checkpoints/)")
    backbone = CodecSplat(model.config)
    try:
        load_model_weights(folder, backbone)
    except RuntimeError as exc:
        raise DataError(f"--init {folder} is not a stage-1 checkpoint of this model: {exc}") from None
    model.load_state_dict(backbone.state_dict(), strict=False)  # the backbone's keys are a subset of the model's


def run_model_config(config: Stage2Config) -> ModelConfig:
    """The network sizes: from ``config.out`` when resuming, else from the stage-1 run ``config.init``."""
    for run in (config.out, config.init):
        file = pathlib.Path(run) / "config.json"
        if run and file.is_file():
            return ModelConfig.from_dict(json.loads(file.read_text())["model"])
    raise InputError(f"--init must name a stage-1 run folder (with config.json), got {config.init!r}")


STAGE2 = stage1.Stage("stage2", build_stage2_model, stage2_loss, LOGGED)


def train(config: Stage2Config, source: Source | None = None, progress: bool = True) -> dict:
    """Run (or resume) stage 2 until ``config.steps``; see :func:`train.stage1.train` for the rest."""
    return stage1.train(config, source, run_model_config(config), progress, stage=STAGE2)


def parse_args(argv: list[str] | None = None) -> Stage2Config:
    """Command line -> :class:`Stage2Config` (every field is a flag)."""
    config = stage1.parse_args(argv, Stage2Config, "python -m train.stage2", __doc__.split("\n\n")[0])
    if config.coded_every < 1 or config.rate_warmup_steps < 0:
        raise InputError("--coded-every must be >= 1 and --rate-warmup-steps >= 0")
    return config


def main(argv: list[str] | None = None) -> None:
    stage1.print_final_metrics(train(parse_args(argv)))


if __name__ == "__main__":
    main()
