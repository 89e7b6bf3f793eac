"""Stage-2 training (paper §3.6, Eqs. 15-18): the codec, decoder depth head and post-codec refiner.

Initialised from a stage-1 run (``--init``): the backbone, the GS head and the decoder depth head (which
stage 1 trained as an auxiliary on F_c) are copied, and the post-codec refiner R_post starts as a copy of
the pre-codec refiner R_pre (same shapes, same job on a feature that should look like F_c). ``--codec-init
MODEL_FILE_OR_RUN`` instead warm-starts all three stage-2 modules (latent codec, decoder depth head and R_post)
from another model's (the shipped default, say: continuing its stage 2 on a backbone that stage 1 trained
further). ``--codec-latent-channels 16,24,32,16 --codec-finest-stride 2`` gives the new run's codec other
latent levels than the init run's; a ``--codec-init`` codec with the same levels minus the finer ones is then
grown into it (:meth:`LatentCodec.grow_from`). Only the codec, the depth head and R_post train (``--trainable
PREFIX,...`` narrows that to the parameters named so, e.g. a grown codec's new levels); everything else is
frozen. Per step, lambda is drawn log-uniformly from [16, 1024] and the loss is

    (lambda / 1024) * [D_render + gamma * |S - S_enc|_1 + W * |log D^ - log D_ref|_1
                       + alpha(step) * |F^_c - F_c|^2 / |F_c|^2] + beta * R

with D_render = MSE + 0.05 LPIPS-VGG (as in stage 1), S the decoder's normalised inverse depth (Eq. 9),
S_enc the encoder's (Eq. 18), gamma = 0.1 and R the estimated rate in bits per context pixel (Eq. 7
divided by the batch's V*H*W: D_render is a per-pixel mean, and the paper's beta only balances it in these
units). The W term (``--depth-weight``, default 0: off) supervises the decoder depth D^ (Eq. 10) with the
batch's reference depth where it is known, as stage 1 does D_enc (:func:`train.stage1.reference_depth_loss`).
beta defaults to 1e-4 for the dl3dv preset and 4e-4 otherwise (RE10K). Over the first
``--rate-warmup-steps`` steps beta ramps up linearly from 0 (rate annealing): a fresh codec's decoder cannot
use its latents yet, and a full rate penalty from the start drives every latent to the prior (posterior
collapse) before it learns to.

The alpha term is a documented deviation from the paper (Eq. 16 has no feature term): the relative squared
error of the decoded feature against the frozen encoder's F_c, weighted ``--feature-weight`` at the first
step and falling linearly to ``--feature-weight-final`` over ``--feature-decay-steps``. It gives the codec a
dense target from the first step, where the render loss alone reaches it only through the frozen GS head.

Every ``--coded-every`` steps the current scene is also really encoded (eval mode): the log then holds the
coded feature bits, the discrete model's estimate of them (``rate_gap`` = coded / estimate - 1, the
coder's overhead, a few percent at most) and ``train_rate_gap`` (coded / the step's noisy training estimate - 1).
The training loop, checkpoints, resumption, TensorBoard, metrics.jsonl, bf16 and DDP are stage 1's
(:func:`train.stage1.train`).

    python -m train.stage2 --init runs/stage1-re10k --data procedural --steps 200000 --out runs/stage2-re10k
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import pathlib
from dataclasses import dataclass

import torch
import torch.distributed as dist

from codecsplat_warp.codec import LAMBDA_MAX, LAMBDA_MIN
from codecsplat_warp.errors import DataError, InputError
from codecsplat_warp.metrics import LPIPS
from codecsplat_warp.model import CodecSplat
from codecsplat_warp.nn.config import ModelConfig

from . import stage1
from .checkpoint import latest_checkpoint, read_weights
from .data import BatchSource, TrainingBatch

RATE_WEIGHTS = {"dl3dv": 1e-4}
"""beta of a preset (by ModelConfig.name); others use :data:`DEFAULT_RATE_WEIGHT` (the paper's RE10K value)."""

DEFAULT_RATE_WEIGHT = 4e-4

LOGGED = ("loss", "mse", "lpips", "psnr", "depth_l1", "depth_ref", "depth_ref_pixels", "feature_error", "feature_weight",
          "self_psnr", "own_psnr", "lambda", "bits", "bpp", "grad_norm", "lr", "coded_bits", "coded_estimate_bits",
          "rate_gap", "train_rate_gap")
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
    codec_init: str = ""
    feature_weight: float = 0.0
    feature_weight_final: float = 0.0
    feature_decay_steps: int = 1
    codec_latent_channels: str = ""
    codec_finest_stride: int = 0
    trainable: str = ""


OPTION_HELP = {
    **stage1.OPTION_HELP,
    "preset": "ignored: the network sizes are those of the --init run",
    "init": "the stage-1 run folder to start from: backbone, GS head, decoder depth head; R_post copies R_pre "
            "(default: none, which only a run being resumed may leave out)",
    "gamma": "weight of the depth term |S - S_enc|_1 inside the lambda bracket (Eq. 16)",
    "self_render_weight": "weight of the decoded Gaussians' render loss on the context views themselves, inside "
                          "the lambda bracket; 0: off",
    "own_render_weight": "weight of the render loss of each context view's own decoded Gaussians alone, in its own "
                         "camera, inside the lambda bracket; 0: off",
    "beta": "weight of the rate in bits per context pixel (default: 1e-4 for the dl3dv preset, else 4e-4)",
    "rate_warmup_steps": "steps over which beta ramps up linearly from 0 (0: full rate from the first step)",
    "coded_every": "really encode the step's scene every this many steps and log the coded bits",
    "codec_init": "warm-start the latent codec, decoder depth head and R_post from this model file or run "
                  "(default: none, R_post from R_pre and the codec from scratch)",
    "feature_weight": "alpha at the first step: weight of the relative feature error |F^_c - F_c|^2 / |F_c|^2",
    "feature_weight_final": "alpha after --feature-decay-steps (linear in between)",
    "feature_decay_steps": "steps over which alpha falls from --feature-weight to --feature-weight-final",
    "codec_latent_channels": "comma list of latent channels per level, coarsest first, e.g. 16,24,32,16 "
                             "(default: the --init run's codec; a --codec-init codec with fewer levels is grown)",
    "codec_finest_stride": "stride of the finest latent level on the feature grid: 4 (1/8 of the image) or 2 (1/4) "
                           "(default 0: the --init run's)",
    "trainable": "comma list of parameter-name prefixes; only those train, e.g. codec.synthesis "
                 "(default: every stage-2 module)",
}
"""``--help`` text of every :class:`Stage2Config` field."""


def rate_weight(config: Stage2Config, model_config: ModelConfig) -> float:
    """beta: ``config.beta`` or the preset's default (:data:`RATE_WEIGHTS`)."""
    return config.beta if config.beta is not None else RATE_WEIGHTS.get(model_config.name, DEFAULT_RATE_WEIGHT)


def rate_ramp(step: int, warmup: int) -> float:
    """Factor of beta at ``step``: linear from 1/warmup to 1 over the first ``warmup`` steps, then 1."""
    return min(1.0, (step + 1) / warmup) if warmup > 0 else 1.0


def feature_weight(config: Stage2Config, step: int) -> float:
    """alpha at ``step``: linear from ``feature_weight`` to ``feature_weight_final`` over ``feature_decay_steps``."""
    t = min(1.0, step / max(1, config.feature_decay_steps))
    return config.feature_weight + t * (config.feature_weight_final - config.feature_weight)


def sample_lambda(seed: int, step: int, rank: int) -> float:
    """Lambda of a step, log-uniform in [LAMBDA_MIN, LAMBDA_MAX], a function of (seed, step, rank) only."""
    generator = torch.Generator().manual_seed((seed * 1_000_003 + step) * 1009 + rank)
    u = float(torch.rand((), generator=generator, dtype=torch.float64))
    return math.exp(math.log(LAMBDA_MIN) + u * (math.log(LAMBDA_MAX) - math.log(LAMBDA_MIN)))


def stage2_loss(model: torch.nn.Module, lpips: LPIPS, batch: TrainingBatch, config: Stage2Config,
                step: int) -> tuple[torch.Tensor, dict]:
    """Eq. 16 (plus the feature term, see the module docstring) for one batch at a lambda drawn for ``step``;
    returns (loss, metrics as floats or detached 0-dim tensors).

    ``model`` may be the DDP wrapper; rendering and the coded-rate check use the bare module.
    """
    lam = step_lambda(config, step)
    images = batch.context_images
    with torch.autocast(images.device.type, dtype=torch.bfloat16, enabled=images.device.type == "cuda"):
        out = model(images, batch.context_cameras, lam=lam, scenes=batch.scenes)
    return codec_loss(model, lpips, batch, config, step, lam, out)


def step_lambda(config: Stage2Config, step: int) -> float:
    """The step's lambda (:func:`sample_lambda` of the seed, the step and this process's DDP rank)."""
    return sample_lambda(config.seed, step, dist.get_rank() if dist.is_initialized() else 0)


def codec_loss(model: torch.nn.Module, lpips: LPIPS, batch: TrainingBatch, config: Stage2Config, step: int,
               lam: float, out: dict) -> tuple[torch.Tensor, dict]:
    """The loss of :func:`stage2_loss` from the codec path's outputs ``out`` (:meth:`CodecSplat.forward` with
    ``lam``: ``gaussians``, ``S``, ``S_enc``, ``D_hat``, ``F_c``, ``F_hat``, ``rate_bits``), whichever latents
    they were decoded from (semi-amortised training decodes refined ones, :mod:`train.semi_amortised`)."""
    bare = model.module if hasattr(model, "module") else model
    images = batch.context_images
    parts = stage1.render_distortion(stage1.render_targets(bare, out["gaussians"], batch), batch.target_images,
                                     lpips, config.lpips_weight)
    depth_l1 = (out["S"].float() - out["S_enc"].detach().float()).abs().mean()
    depth_ref, known = stage1.reference_depth_loss(out["D_hat"], batch.context_depth)
    target = out["F_c"].detach().float()
    feature_error = (out["F_hat"].float() - target).square().mean() / target.square().mean().clamp_min(1e-12)
    alpha = feature_weight(config, step)
    bpp = out["rate_bits"] / images[:, 0].numel()
    distortion = parts["render"] + config.gamma * depth_l1 + config.depth_weight * depth_ref + alpha * feature_error
    beta = rate_weight(config, bare.config) * rate_ramp(step, config.rate_warmup_steps)
    loss = lam / LAMBDA_MAX * distortion + beta * bpp
    metrics = {"loss": loss.detach(), "mse": parts["mse"].detach(), "lpips": parts["lpips"].detach(),
               "depth_l1": depth_l1.detach(), "depth_ref": depth_ref.detach(), "depth_ref_pixels": known,
               "psnr": parts["psnr"], "feature_error": feature_error.detach(),
               "feature_weight": alpha, "lambda": lam, "bits": out["rate_bits"].detach() / batch.scenes,
               "bpp": bpp.detach()}
    context_loss, context_metrics = stage1.context_render_terms(bare, out["gaussians"], batch, lpips, config)
    loss = loss + lam / LAMBDA_MAX * context_loss
    metrics.update(context_metrics)
    if (step + 1) % config.coded_every == 0:
        metrics.update(coded_rate(bare, batch, lam, float(out["rate_bits"].detach())))
    return loss, metrics


@torch.no_grad()
def coded_rate(model: CodecSplat, batch: TrainingBatch, lam: float, training_bits: float) -> dict:
    """Really encode the batch's first scene at ``lam`` (eval mode) and compare with the rate estimates
    (``training_bits``: the step's noisy estimate for the whole batch)."""
    was_training = model.training
    model.eval()
    views = batch.context_images.shape[0] // batch.scenes
    try:
        encoded = model.encode_scene(batch.context_images[:views], batch.context_cameras.select(slice(0, views)), lam)
    finally:
        model.train(was_training)
    coded = 8.0 * sum(encoded.feature_bytes)
    estimate = float(encoded.estimated_bits.sum())
    return {"coded_bits": coded, "coded_estimate_bits": estimate, "rate_gap": coded / estimate - 1.0,
            "train_rate_gap": coded * batch.scenes / training_bits - 1.0}


def build_stage2_model(model_config: ModelConfig, config: Stage2Config) -> CodecSplat:
    """A CodecSplat with its codec: backbone, heads and R_post from the stage-1 run ``config.init``, then the
    stage-2 modules from ``config.codec_init`` when given (unless ``config.out`` already has a checkpoint to
    resume); only the stage-2 modules trainable."""
    model = CodecSplat(model_config, codec=True)
    if latest_checkpoint(config.out) is None:
        load_stage1_weights(model, config.init)
        if config.codec_init:
            load_codec_weights(model, config.codec_init)
    model.requires_grad_(False)
    for module in model.codec_modules():
        module.requires_grad_(True)
    if config.trainable:
        train_only(model, config.trainable.split(","))
    return model


def train_only(model: CodecSplat, prefixes: list[str]) -> None:
    """Freeze every stage-2 parameter whose name starts with none of ``prefixes`` (``codec.top_down.blocks.3``,
    ``depth_head``, ...). Raises InputError for a prefix that names no stage-2 parameter."""
    def named(name: str, prefix: str) -> bool:
        return name == prefix or name.startswith(prefix + ".")

    names = [n for n, p in model.named_parameters() if p.requires_grad]
    for prefix in prefixes:
        if not any(named(n, prefix) for n in names):
            raise InputError(f"--trainable {prefix!r} names no stage-2 parameter (they start with "
                             f"{', '.join(model.CODEC_MODULE_NAMES)})")
    for name, parameter in model.named_parameters():
        if not any(named(name, p) for p in prefixes):
            parameter.requires_grad_(False)


def load_stage1_weights(model: CodecSplat, run) -> None:
    """Copy the newest checkpoint of the stage-1 run ``run`` (its weight average where it has one, see
    :func:`train.checkpoint.weights_for_use`) into ``model``'s backbone and heads, and its pre-codec refiner
    into the post-codec refiner too (the latent codec keeps its initialisation).
    Raises DataError when ``run`` has no stage-1 checkpoint of this model."""
    folder = latest_checkpoint(run)
    if folder is None:
        raise DataError(f"--init {run}: no checkpoint there (expected a stage-1 run folder with checkpoints/)")
    backbone = CodecSplat(model.config)
    try:
        backbone.load_state_dict(read_weights(folder))
    except RuntimeError as exc:
        raise DataError(f"--init {folder} is not a stage-1 checkpoint of this model: {exc}") from None
    model.load_state_dict(backbone.state_dict(), strict=False)  # the backbone's keys are a subset of the model's
    model.refine_post.load_state_dict(backbone.refine_pre.state_dict())


def load_codec_weights(model: CodecSplat, source) -> None:
    """Copy the stage-2 modules (:attr:`CodecSplat.CODEC_MODULE_NAMES`: the ``codec.*``, ``depth_head.*`` and
    ``refine_post.*`` tensors) of a model file or run into ``model``.
    Raises DataError when the source lacks one of them or holds other shapes."""
    weights = read_weights(source)
    for name in model.CODEC_MODULE_NAMES:
        prefix = name + "."
        tensors = {k[len(prefix):]: v for k, v in weights.items() if k.startswith(prefix)}
        try:
            getattr(model, name).load_state_dict(tensors)
        except RuntimeError as exc:
            failed = f"--codec-init {source} holds no {name} of this model's shapes: {exc}"
            if name != "codec":
                raise DataError(failed) from None
            reason = _grow_codec(model, tensors)
            if reason:
                raise DataError(f"{failed}; nor one that grows into it: {reason}") from None


def _grow_codec(model: CodecSplat, state: dict[str, torch.Tensor]) -> str:
    """Grow the codec ``state`` (of a codec with fewer, coarser levels) into ``model.codec``; returns why it
    does not fit, or "" when it did. The source's levels are read off its tensors: the channels from each
    level's gain, the finest stride from its number of synthesis upsamplings."""
    levels = sorted({int(k.split(".")[2]) for k in state if k.startswith("top_down.blocks.")})
    ups = {int(k.split(".")[2]) for k in state if k.startswith("synthesis.ups.")}
    if not levels or not ups:
        return "it holds no latent levels or synthesis"
    source = dataclasses.replace(
        model.config, codec_latent_channels=tuple(state[f"top_down.blocks.{l}.gain.bias"].numel() for l in levels),
        codec_finest_stride=2 ** len(ups))
    try:
        fresh = model.codec.grow_from(state, source)
    except (InputError, RuntimeError) as exc:
        return str(exc)
    print(f"stage2: grew the --codec-init codec (levels {source.codec_latent_channels}, finest stride "
          f"{source.codec_finest_stride}) into {model.config.codec_latent_channels} at stride "
          f"{model.config.codec_finest_stride}; {len(fresh)} tensors start fresh")
    return ""


def run_model_config(config: Stage2Config) -> ModelConfig:
    """The network sizes: from ``config.out`` when resuming, else from the stage-1 run ``config.init`` with
    the codec layout options (``--codec-latent-channels``, ``--codec-finest-stride``) applied."""
    for run in (config.out, config.init):
        file = pathlib.Path(run) / "config.json"
        if run and file.is_file():
            model_config = ModelConfig.from_dict(json.loads(file.read_text())["model"])
            return model_config if run == config.out else codec_layout(model_config, config)
    raise InputError(f"--init must name a stage-1 run folder (with config.json), got {config.init!r}")


def codec_layout(model_config: ModelConfig, config: Stage2Config) -> ModelConfig:
    """``model_config`` with the latent levels and finest stride of ``config`` where given."""
    changes = {}
    if config.codec_latent_channels:
        try:
            changes["codec_latent_channels"] = tuple(int(c) for c in config.codec_latent_channels.split(","))
        except ValueError:
            raise InputError(f"--codec-latent-channels must be a comma-separated list of ints, got "
                             f"{config.codec_latent_channels!r}") from None
    if config.codec_finest_stride:
        changes["codec_finest_stride"] = config.codec_finest_stride
    return dataclasses.replace(model_config, **changes)


STAGE2 = stage1.Stage("stage2", build_stage2_model, stage2_loss, LOGGED)


def train(config: Stage2Config, source: BatchSource | None = None, progress: bool = True) -> dict:
    """Run (or resume) stage 2 until ``config.steps``; see :func:`train.stage1.train` for the rest."""
    return stage1.train(config, source, run_model_config(config), progress, stage=STAGE2)


def build_parser() -> argparse.ArgumentParser:
    """The stage-2 command line: :class:`Stage2Config`'s fields as flags."""
    return stage1.build_parser(Stage2Config, OPTION_HELP, "python -m train.stage2", __doc__.split("\n\n")[0])


def parse_args(argv: list[str] | None = None) -> Stage2Config:
    """Command line -> :class:`Stage2Config` (every field is a flag)."""
    config = stage1.parse_args(argv, Stage2Config, build_parser())
    if config.coded_every < 1 or config.rate_warmup_steps < 0 or config.feature_decay_steps < 1:
        raise InputError("--coded-every and --feature-decay-steps must be >= 1 and --rate-warmup-steps >= 0")
    return config


def main(argv: list[str] | None = None) -> None:
    stage1.print_final_metrics(train(parse_args(argv)))


if __name__ == "__main__":
    main()
