"""Stage-1 training (paper §3.6): the codec-free CodecSplat generator, rendered at target views.

Loss: MSE + 0.05 * LPIPS-VGG between rendered and true target images (Eq. 14), plus the decoder depth
head's auxiliary ``depth_aux_weight * |S_aux - S_enc|_1`` on detached inputs (it trains only that head, so
that stage 2 starts with one; see :class:`codecsplat_warp.model.CodecSplat`), plus with ``--depth-weight W``
the depth supervision ``W * |log D_enc - log D_ref|_1`` on the context pixels whose reference depth is known
(:func:`reference_depth_loss`; the exact depth of procedural scenes, and for real scenes the multi-view stereo
depth that ``codecsplat depth`` wrote into their ``mvs/`` folder: see :data:`train.data.DEPTH_FOLDER`), plus
with ``--self-render-weight W`` the same render loss on the context views themselves (``W * D_render`` of the
Gaussians rendered into their own context cameras: pixel-aligned Gaussians should reproduce their input). AdamW (lr 1e-4, weight decay
0.01), linear warm-up then cosine decay to 10 %, gradient-norm clipping, bf16 autocast on CUDA (fp32 on
CPU). After every optimiser step an exponential moving average of the trainable weights is updated
(``--ema-decay``, default 0.999, warmed up as :func:`train.weight_average.warmed_up_decay`; 0 keeps none): it is
saved with each checkpoint, continues on resume, and is what validation, export and warm starts from the run
use (:func:`train.checkpoint.weights_for_use`). Resumable checkpoints (see :mod:`train.checkpoint`),
TensorBoard logs and a tqdm bar under ``--out``.

    python -m train.stage1 --preset re10k --data procedural --steps 100000 --out runs/stage1-re10k
    torchrun --nproc_per_node 4 -m train.stage1 ...        # DDP, one batch per GPU per step

Batches (:mod:`train.data`): ``--views 2,3,4,6,8 --sizes 256x256,256x448`` draws a context view count and an
image size per batch, and ``--batch-views 8`` fills a batch with as many scenes as have 8 context views
between them (4 scenes of 2 views, 1 of 8); the default is one scene at the preset's view count and size.
``--data chunks:DIR`` (or ``mix:chunks:DIR``) trains on a folder of RE10K / DL3DV ``.torch`` chunks with
pixelSplat's bounded view sampler: the context gap widens over DepthSplat's RE10K schedule (25-45 frames at
step 0 to 45-192 at step 150k), or stays in ``--context-gap MIN,MAX`` frames when that is given.
``--mono vgg16`` adds the frozen ImageNet VGG16 prior (weights from ``--mono-weights``, default
``lpips_vgg.safetensors`` in the LPIPS weights folder) and ``--init RUN_OR_MODEL_FILE`` warm-starts from the
weights of a run or a model file whose names and shapes match (the shipped default, say).

The global batch is ``world_size * accumulate`` batches per optimiser step: ``--accumulate 2`` on one GPU
sees the same batches per step as two DDP processes (batch ``(step * accumulate + micro) * world + rank``).

Rerunning the same command after an interruption continues from the last checkpoint. SIGTERM (or
``--time-limit-s``) ends a run cleanly after the current step, with a checkpoint of that step.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import os
import pathlib
import signal
import threading
import time
from dataclasses import asdict, dataclass, fields
from typing import Callable

import torch
import torch.distributed as dist
from torch.nn import functional as F
from tqdm import tqdm

from codecsplat_warp.device import resolve_device
from codecsplat_warp.errors import CodecSplatError, InputError
from codecsplat_warp.gaussians import Gaussians
from codecsplat_warp.metrics import LPIPS, WEIGHTS_ENV
from codecsplat_warp.metrics.image import psnr
from codecsplat_warp.model import CodecSplat
from codecsplat_warp.nn.config import ModelConfig, get_preset

from .checkpoint import (latest_checkpoint, load_checkpoint, load_matching_weights, read_weights,
                         save_checkpoint)
from .data import (BatchSource, DataSpec, StepDataset, TrainingBatch, fixed_context_gap, make_source, parse_sizes,
                   parse_views)
from .weight_average import WeightAverage

REPO_ROOT = pathlib.Path(__file__).resolve().parents[1]
DEFAULT_LPIPS_DIR = REPO_ROOT.parent / "shared" / "weights"
"""LPIPS weights used when neither ``--lpips-weights`` nor ``$CODECSPLAT_LPIPS_WEIGHTS`` is given."""


@dataclass
class TrainConfig:
    """Stage-1 options (each is a ``--flag`` of the command line, underscores as dashes)."""

    preset: str = "re10k"
    data: str = "procedural"
    holdout: str = ""
    out: str = "runs/stage1"
    steps: int = 100_000
    lr: float = 1e-4
    weight_decay: float = 0.01
    warmup_steps: int = 2000
    grad_clip: float = 1.0
    lpips_weight: float = 0.05
    lpips_weights: str | None = None
    checkpoint_every: int = 1000
    keep_checkpoints: int = 2
    log_every: int = 20
    seed: int = 0
    device: str = "auto"
    workers: int = 4
    time_limit_s: float = 0.0
    accumulate: int = 1
    views: str = ""
    sizes: str = ""
    batch_views: int = 0
    procedural_fraction: float = 0.5
    photo_textures: int = 0
    photometric: int = 0
    mirror: int = 0
    context_gap: str = ""
    mono: str = ""
    mono_weights: str = ""
    photometric_window: int = -1
    init: str = ""
    depth_aux_weight: float = 0.1
    depth_weight: float = 0.0
    self_render_weight: float = 0.0
    own_render_weight: float = 0.0
    ema_decay: float = 0.999


OPTION_HELP = {
    "preset": "network sizes: re10k (2 views, 256x256), dl3dv (8 views, 256x448) or tiny (for tests)",
    "data": "procedural; a folder of scene folders; chunks:DIR (RE10K/ACID/DL3DV .torch chunks with index.json); "
            "or mix: before either of the last two, to add procedural scenes",
    "holdout": "comma list of scene folders (or chunk keys) left out of training (default: none)",
    "out": "run folder: checkpoints, config.json, metrics.jsonl, TensorBoard logs; rerunning resumes from it",
    "steps": "optimiser steps in all (the cosine schedule ends here)",
    "lr": "peak AdamW learning rate, after the warm-up",
    "weight_decay": "AdamW weight decay",
    "warmup_steps": "steps of linear learning-rate warm-up, then cosine decay to 10 %% of --lr",
    "grad_clip": "clip the gradient's global L2 norm to this",
    "lpips_weight": "weight of LPIPS-VGG beside the MSE in the render loss (Eq. 14)",
    "lpips_weights": "folder with lpips_vgg.safetensors (default: $CODECSPLAT_LPIPS_WEIGHTS, else ../shared/weights)",
    "checkpoint_every": "write a checkpoint every this many steps (and at the end or on SIGTERM)",
    "keep_checkpoints": "how many of the newest checkpoints to keep",
    "log_every": "log metrics (metrics.jsonl, TensorBoard) every this many steps",
    "seed": "seed of the scene drawing and the initial weights; the same seed draws the same batches",
    "device": "cpu, cuda, cuda:N or auto (CUDA when torch sees a GPU; under torchrun, the local rank's GPU)",
    "workers": "data-loader processes per training process (CUDA only; 0 on the CPU): as many as its steps consume, "
               "since more take CPU from the host-bound steps (docs/training.md, Four GPUs)",
    "time_limit_s": "stop cleanly with a checkpoint after this many seconds of training (0: no limit)",
    "accumulate": "batches per optimiser step per process (global batch = processes x this)",
    "views": "comma list of context view counts, one drawn per batch; list one twice to draw it twice as often "
             "(default: the preset's view count)",
    "sizes": "comma list of HEIGHTxWIDTH image sizes in pixels, one drawn per batch (default: the preset's size)",
    "batch_views": "context views per batch: as many scenes as fill it at the drawn view count (default 0: one scene)",
    "procedural_fraction": "share of procedural scenes in a batch with mix: data, 0 to 1",
    "photo_textures": "1: procedural scenes also get crops of the training photographs as textures; 0: synthetic only",
    "photometric": "1: each scene gets one random brightness, contrast, saturation and gamma change for all its views",
    "mirror": "1: half of the scenes are mirrored left-right, images and cameras together",
    "context_gap": "MIN,MAX frames between a chunk scene's context views (default: DepthSplat's RE10K schedule, "
                   "25-45 frames at step 0 widening to 45-192 at step 150k)",
    "mono": "monocular prior in MVEnc: none or vgg16 (frozen ImageNet VGG16; default: the preset's, none)",
    "mono_weights": "VGG16 weights for --mono vgg16 (default: lpips_vgg.safetensors of the LPIPS weights folder)",
    "photometric_window": "odd window side of MVEnc's photometric (windowed NCC) cost volume, e.g. 5; 0: none "
                          "(default: the preset's, none)",
    "init": "warm start from a run folder or a model file: every weight whose name and shape match "
            "(default: none, random weights)",
    "depth_aux_weight": "weight of the decoder depth head's auxiliary L1 loss on detached features",
    "depth_weight": "weight of the log-depth L1 against the scenes' reference depth where it is known (exact for "
                    "procedural scenes, multi-view stereo from codecsplat depth for real ones); 0: off",
    "self_render_weight": "weight of the render loss on the context views themselves; 0: off",
    "own_render_weight": "weight of the render loss of each context view's own Gaussians alone, in its own camera "
                         "(pixel-aligned Gaussians that stand without the other views'); 0: off",
    "ema_decay": "decay of the weights' exponential moving average, which export, validation and warm starts use "
                 "(0: keep none)",
}
"""``--help`` text of every :class:`TrainConfig` field (its default is appended when it has one)."""


LOGGED = ("loss", "mse", "lpips", "psnr", "depth_aux", "depth_ref", "depth_ref_pixels", "self_psnr", "own_psnr",
          "grad_norm", "lr")
"""Training metrics written every ``log_every`` steps (TensorBoard and :data:`METRICS_FILE`), averaged over the
step's batches (micro-batches and DDP ranks); each record also has ``step``, ``elapsed_s`` (wall seconds since
this process started training, resumed chunks restart it), ``scenes`` (global scenes in the record's step)
and ``scenes_per_s`` (global scenes per second since the previous record)."""

METRICS_FILE = "metrics.jsonl"
"""One JSON object per logged step under the run folder (read by :mod:`train.validate` for curves)."""


def append_metrics(path: pathlib.Path, record: dict) -> None:
    """Append one JSON line (flushed, so an interrupted run keeps every logged step)."""
    with open(path, "a") as f:
        f.write(json.dumps(record) + "\n")


def truncate_metrics(path: pathlib.Path, last_step: int) -> None:
    """Drop logged steps after ``last_step`` (a resumed run repeats them)."""
    if path.is_file():
        kept = [line for line in path.read_text().splitlines() if line and json.loads(line)["step"] <= last_step]
        path.write_text("".join(line + "\n" for line in kept))


def lr_factor(step: int, warmup: int, total: int) -> float:
    """Learning-rate multiplier: linear warm-up over ``warmup`` steps, then cosine from 1 to 0.1."""
    if step < warmup:
        return (step + 1) / warmup
    progress = min(1.0, (step - warmup) / max(1, total - warmup))
    return 0.1 + 0.9 * 0.5 * (1.0 + math.cos(math.pi * progress))


def render_targets(model: CodecSplat, gaussians: Gaussians, batch: TrainingBatch, context: bool = False) -> torch.Tensor:
    """[S*T,3,H,W]: each scene's Gaussians (view-major, see ``CodecSplat.forward(scenes=...)``) rendered into
    that scene's target cameras; with ``context``, [S*V,3,H,W] rendered into its own context cameras."""
    per_scene = gaussians.split(batch.scenes)
    cameras = batch.scene_contexts() if context else batch.scene_targets()
    return torch.cat([model.render(g, c)["rgb"] for g, c in zip(per_scene, cameras)])


def render_distortion(rgb: torch.Tensor, target: torch.Tensor, lpips: LPIPS, lpips_weight: float) -> dict:
    """D_render = MSE + lpips_weight * LPIPS-VGG of renders [B,3,H,W] against targets, with its parts and the
    mean PSNR (detached) as 0-dim tensors: ``render``, ``mse``, ``lpips``, ``psnr``."""
    mse = F.mse_loss(rgb, target)
    perceptual = lpips(rgb, target).mean()
    return {"render": mse + lpips_weight * perceptual, "mse": mse, "lpips": perceptual,
            "psnr": psnr(rgb.detach(), target).mean()}


def context_render_terms(model: CodecSplat, gaussians: Gaussians, batch: TrainingBatch, lpips: LPIPS,
                         config: "TrainConfig") -> tuple[torch.Tensor | float, dict]:
    """The weighted sum of the context-view render losses that ``config`` turns on (0.0 when none is) and their
    PSNRs (detached): ``self_render_weight``, each scene's Gaussians rendered into its own context views
    (``self_psnr``); ``own_render_weight``, each context view's own Gaussians alone in its own camera
    (:meth:`CodecSplat.render_own_views`, ``own_psnr``); both :func:`render_distortion` against the context
    images."""
    renders = (
        (config.self_render_weight, "self_psnr", lambda: render_targets(model, gaussians, batch, context=True)),
        (config.own_render_weight, "own_psnr", lambda: model.render_own_views(gaussians, batch.context_cameras)),
    )
    total, metrics = 0.0, {}
    for weight, metric, render in renders:
        if weight > 0:
            parts = render_distortion(render(), batch.context_images, lpips, config.lpips_weight)
            total = total + weight * parts["render"]
            metrics[metric] = parts["psnr"]
    return total, metrics


def reference_depth_loss(depth: torch.Tensor, reference: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Masked log-depth L1: mean of |log depth - log reference| over the pixels whose reference is known.

    Args:
        depth: float [V,H,W] predicted depth (> 0, scene units).
        reference: float [V,H,W] reference depth, 0 where unknown.

    Returns:
        (loss, share of pixels with a reference) as 0-dim float32 tensors; the loss is 0 (with a zero gradient)
        when no pixel has a reference. The log makes it scale-free: 0.01 is a 1 % depth error in any scene's units.
    """
    known = reference > 0
    error = (depth.float().clamp_min(1e-6).log() - torch.where(known, reference.float(), 1.0).log()).abs()
    count = known.sum()
    return (error * known).sum() / count.clamp_min(1), count.float() / known.numel()


def stage1_loss(model: torch.nn.Module, lpips: LPIPS, batch: TrainingBatch, config: "TrainConfig") -> tuple[torch.Tensor, dict]:
    """Eq. 14 with D_render = MSE + lpips_weight * LPIPS-VGG, plus the depth head's auxiliary and, with
    ``depth_weight``, :func:`reference_depth_loss` of ``D_enc`` against the batch's reference depth (exact for
    procedural scenes, multi-view stereo for real ones); returns (loss, metrics as detached 0-dim tensors,
    read back only when logged).

    ``model`` may be the DDP wrapper; rendering uses the bare module.
    """
    bare = model.module if hasattr(model, "module") else model
    device = batch.context_images.device
    with torch.autocast(device.type, dtype=torch.bfloat16, enabled=device.type == "cuda"):
        out = model(batch.context_images, batch.context_cameras, scenes=batch.scenes)
    parts = render_distortion(render_targets(bare, out["gaussians"], batch), batch.target_images, lpips,
                              config.lpips_weight)
    depth_aux = (out["S_aux"].float() - out["S_enc"].detach().float()).abs().mean()
    depth_ref, known = reference_depth_loss(out["D_enc"], batch.context_depth)
    loss = parts["render"] + config.depth_aux_weight * depth_aux + config.depth_weight * depth_ref
    metrics = {"psnr": parts["psnr"], "depth_aux": depth_aux.detach(), "depth_ref": depth_ref.detach(),
               "depth_ref_pixels": known}
    context_loss, context_metrics = context_render_terms(bare, out["gaussians"], batch, lpips, config)
    loss = loss + context_loss
    metrics.update(context_metrics)
    return loss, {"loss": loss.detach(), "mse": parts["mse"].detach(), "lpips": parts["lpips"].detach(), **metrics}


def make_optimizer(model: torch.nn.Module, config: TrainConfig):
    """AdamW and its warm-up/cosine LambdaLR scheduler."""
    params = [p for p in model.parameters() if p.requires_grad]
    optimizer = torch.optim.AdamW(params, lr=config.lr, weight_decay=config.weight_decay)
    scheduler = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda step: lr_factor(step, config.warmup_steps, config.steps))
    return optimizer, scheduler


LossFn = Callable[[torch.nn.Module, LPIPS, TrainingBatch, TrainConfig, int], tuple[torch.Tensor, dict]]
"""``loss(model, lpips, batch, config, step) -> (loss, metrics)`` of one micro-batch; metrics are floats or
detached 0-dim tensors (read back only on logged steps)."""


@dataclass(frozen=True)
class Stage:
    """What a training stage brings to the shared loop of :func:`train` (stage 2: :mod:`train.stage2`).

    Attributes:
        name: progress-bar label.
        build_model: ``(model_config, config) -> CodecSplat`` on the CPU, initialised, with the parameters
            to train (and only those) requiring gradients; called before a checkpoint is resumed.
        loss: the step's :data:`LossFn`.
        logged: metrics written every ``log_every`` steps (those a step returns).
    """

    name: str
    build_model: Callable[[ModelConfig, TrainConfig], CodecSplat]
    loss: LossFn
    logged: tuple[str, ...]


def build_stage1_model(model_config: ModelConfig, config: TrainConfig) -> CodecSplat:
    """A codec-free CodecSplat: the mono prior's ImageNet weights loaded (``--mono-weights``), then the
    ``--init`` warm start (every tensor whose name and shape match) unless the run resumes."""
    model = CodecSplat(model_config)
    if model.mvenc.mono_backbone is not None:
        model.mvenc.mono_backbone.load_imagenet(config.mono_weights or pathlib.Path(_lpips_dir(config)) /
                                                "lpips_vgg.safetensors")
    if config.init and latest_checkpoint(config.out) is None:
        kept, _ = load_matching_weights(model, read_weights(config.init))
        print(f"stage1: warm start from {config.init}; not in it (kept as built): {', '.join(kept) or 'nothing'}")
    return model


STAGE1 = Stage(
    "stage1", build_stage1_model,
    lambda model, lpips, batch, config, step: stage1_loss(model, lpips, batch, config), LOGGED)


def train_step(model, lpips, optimizer, scheduler, batches: list[TrainingBatch], config: TrainConfig,
               step: int = 0, stage: Stage = STAGE1) -> dict:
    """One optimisation step over ``batches`` (micro-batches, gradients accumulated; DDP all-reduces only on
    the last one): forward, backward of the mean loss, clip, AdamW, scheduler; returns the metrics averaged
    over the micro-batches (``grad_norm`` and ``lr`` of the step; tensors are not read back here)."""
    optimizer.zero_grad(set_to_none=True)
    totals: dict = {}
    for index, batch in enumerate(batches):
        last = index == len(batches) - 1
        sync = contextlib.nullcontext() if last or not hasattr(model, "no_sync") else model.no_sync()
        with sync:
            loss, metrics = stage.loss(model, lpips, batch, config, step)
            (loss / len(batches)).backward()
        for name, value in metrics.items():
            totals[name] = totals.get(name, 0.0) + value / len(batches)
    totals["grad_norm"] = torch.nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip)
    optimizer.step()
    scheduler.step()
    totals["lr"] = scheduler.get_last_lr()[0]
    return totals


def read_metrics_back(metrics: dict) -> dict[str, float]:
    """``metrics`` with every tensor read back as a float (one device-to-host copy for all of them)."""
    names = [name for name, value in metrics.items() if isinstance(value, torch.Tensor)]
    values = torch.stack([metrics[name].detach().float().reshape(()) for name in names]).tolist() if names else []
    return {**{k: v for k, v in metrics.items() if k not in names}, **dict(zip(names, values))}


def mean_over_ranks(metrics: dict[str, float], world: int, device: torch.device) -> dict[str, float]:
    """``metrics`` averaged over the DDP ranks (every rank must call it at the same step); unchanged if world is 1."""
    if world <= 1:
        return metrics
    names = sorted(metrics)
    values = torch.tensor([float(metrics[n]) for n in names], dtype=torch.float64, device=device)
    dist.all_reduce(values, op=dist.ReduceOp.SUM)
    return dict(zip(names, (values / world).tolist()))


def _distributed() -> tuple[int, int, int]:
    """(rank, world_size, local_rank); initialises the process group when WORLD_SIZE > 1 (torchrun)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return 0, 1, 0
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    if torch.cuda.is_available():
        torch.cuda.set_device(local_rank)
    dist.init_process_group("nccl" if torch.cuda.is_available() else "gloo")
    return dist.get_rank(), world, local_rank


def _lpips_dir(config: TrainConfig) -> str:
    if config.lpips_weights:
        return config.lpips_weights
    return os.environ.get(WEIGHTS_ENV) or str(DEFAULT_LPIPS_DIR)


def data_spec(config: TrainConfig, model_config: ModelConfig, world: int = 1) -> DataSpec:
    """The batch drawing of ``config`` (``--views``, ``--sizes``, ``--batch-views``, ``--context-gap`` and the
    augmentation flags) for ``world`` processes; unset ones default to one scene at the model preset's view
    count and size and, for chunk scenes, DepthSplat's RE10K context gap schedule."""
    base = DataSpec.of_model(model_config)
    return DataSpec(views=parse_views(config.views) if config.views else base.views,
                    sizes=parse_sizes(config.sizes) if config.sizes else base.sizes, targets=base.targets,
                    batch_views=config.batch_views or base.batch_views,
                    procedural_fraction=config.procedural_fraction, photo_textures=bool(config.photo_textures),
                    photometric=bool(config.photometric), mirror=bool(config.mirror),
                    view_sampler=fixed_context_gap(config.context_gap) if config.context_gap else base.view_sampler,
                    batches_per_step=config.accumulate * world)


def stage1_model_config(config: TrainConfig) -> ModelConfig:
    """The ``--preset`` sizes with ``--mono`` (when given) in the mono slot and ``--photometric-window``
    (when >= 0)."""
    preset = get_preset(config.preset)
    if config.mono:
        preset = dataclasses.replace(preset, mono=config.mono)
    if config.photometric_window >= 0:
        preset = dataclasses.replace(preset, photometric_window=config.photometric_window)
    return preset


def train(config: TrainConfig, source: BatchSource | None = None, model_config: ModelConfig | None = None,
          progress: bool = True, stage: Stage = STAGE1) -> dict:
    """Run (or resume) stage 1 until ``config.steps``; returns the metrics of the last step run
    (with ``step`` and ``resumed_from``, the step of the checkpoint it started from; empty if none was run).

    Args:
        config: options; ``config.out`` holds checkpoints, TensorBoard logs and ``config.json``.
        source: batch source (default: :func:`train.data.make_source` of ``config.data``).
        model_config: network sizes (default: :func:`stage1_model_config`).
        progress: show a tqdm bar on rank 0.
        stage: model, loss and logged metrics of the stage (default: stage 1).
    """
    rank, world, local_rank = _distributed()
    device = resolve_device(config.device)
    if device.type == "cuda" and world > 1:
        device = torch.device("cuda", local_rank)
    model_config = model_config or stage1_model_config(config)
    source = source or make_source(config.data, data_spec(config, model_config, world), config.seed,
                                   [n for n in config.holdout.split(",") if n])
    out = pathlib.Path(config.out)
    torch.manual_seed(config.seed + rank)

    model = stage.build_model(model_config, config).to(device)
    optimizer, scheduler = make_optimizer(model, config)
    average = WeightAverage(model, config.ema_decay) if config.ema_decay > 0 else None
    start = 0
    checkpoint = latest_checkpoint(out)
    if checkpoint is not None:
        start = load_checkpoint(checkpoint, model, optimizer, scheduler, average)
    lpips = LPIPS("vgg", _lpips_dir(config)).to(device)
    trained = torch.nn.parallel.DistributedDataParallel(
        model, device_ids=[local_rank] if device.type == "cuda" else None) if world > 1 else model

    loader = _loader(source, start, config.steps, rank, world, config.accumulate,
                     config.workers if device.type == "cuda" else 0)
    writer = None
    if rank == 0:
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ModuleNotFoundError as exc:
            raise CodecSplatError("TensorBoard logging needs the train extra: pip install -e '.[train]'") from exc

        out.mkdir(parents=True, exist_ok=True)
        (out / "config.json").write_text(json.dumps({"train": asdict(config), "model": model_config.to_dict(),
                                                     "world_size": world}, indent=1))
        writer = SummaryWriter(str(out / "tensorboard"), purge_step=start)
        truncate_metrics(out / METRICS_FILE, start)
    bar = tqdm(total=config.steps, initial=start, disable=not progress or rank != 0, desc=stage.name, dynamic_ncols=True)
    metrics: dict = {}
    extra = {"train": asdict(config), "model": model_config.to_dict()}
    began = last_log = time.monotonic()
    scenes_since_log = 0
    stop_requested = threading.Event()
    previous_handler = signal.signal(signal.SIGTERM, lambda *_: stop_requested.set())
    try:
        for step, batches in zip(range(start, config.steps), _micro_batches(loader, config.accumulate)):
            batches = [to_device(batch, device) for batch in batches]
            metrics = train_step(trained, lpips, optimizer, scheduler, batches, config, step, stage)
            if average is not None:
                average.update(model)
            metrics.update(step=step + 1, resumed_from=start, scenes=sum(b.scenes for b in batches))
            scenes_since_log += metrics["scenes"]
            bar.update(1)
            if (step + 1) % config.log_every == 0:
                metrics = read_metrics_back(metrics)
                bar.set_postfix(loss=f"{metrics['loss']:.4f}", psnr=f"{metrics['psnr']:.2f}")
                now = time.monotonic()
                logged = mean_over_ranks({k: metrics[k] for k in stage.logged if k in metrics}
                                         | {"scenes": metrics["scenes"], "window_scenes": scenes_since_log}, world, device)
                window_scenes = logged.pop("window_scenes") * world
                logged["scenes"] *= world
                logged["scenes_per_s"] = round(window_scenes / max(now - last_log, 1e-9), 3)
                last_log, scenes_since_log = now, 0
                if writer is not None:
                    for name, value in logged.items():
                        writer.add_scalar(f"train/{name}", value, step + 1)
                    append_metrics(out / METRICS_FILE, {"step": step + 1, **logged,
                                                        "elapsed_s": round(now - began, 3)})
            stop = stop_requested.is_set() or (config.time_limit_s > 0 and time.monotonic() - began > config.time_limit_s)
            stop = _agree(stop, world, device)
            if (step + 1) % config.checkpoint_every == 0 or step + 1 == config.steps or stop:
                if rank == 0:
                    save_checkpoint(out, step + 1, model, optimizer, scheduler, extra, keep=config.keep_checkpoints,
                                    average=average)
                if world > 1:
                    dist.barrier()
            if stop:
                break
    finally:
        signal.signal(signal.SIGTERM, previous_handler)
        bar.close()
        if writer is not None:
            writer.close()
        if world > 1:
            dist.destroy_process_group()
    return read_metrics_back(metrics)


def _agree(stop: bool, world: int, device: torch.device) -> bool:
    """True on every rank when any rank wants to stop (so all ranks save and leave at the same step)."""
    if world <= 1:
        return stop
    flag = torch.tensor([float(stop)], device=device)
    dist.all_reduce(flag, op=dist.ReduceOp.MAX)
    return bool(flag.item())


def _loader(source: BatchSource, start: int, steps: int, rank: int, world: int, accumulate: int, workers: int):
    """Batches of this rank for steps start..steps-1, ``accumulate`` per step (global index
    ``(step * accumulate + micro) * world + rank``), prefetched by workers. Without the DataLoader's pin-memory
    thread: :func:`to_device` pins in the training thread (see there)."""
    indices = [(step * accumulate + micro) * world + rank for step in range(start, steps) for micro in range(accumulate)]
    dataset = StepDataset(source, steps * accumulate * world)
    return torch.utils.data.DataLoader(dataset, sampler=indices, batch_size=None, num_workers=workers,
                                       persistent_workers=False, prefetch_factor=4 if workers else None,
                                       pin_memory=False)


def to_device(batch: TrainingBatch, device: torch.device) -> TrainingBatch:
    """``batch`` on ``device``: on CUDA through page-locked memory, pinned here, in the training thread, and copied
    asynchronously. A DataLoader's pin-memory thread would pin while the training thread captures CUDA graphs (the
    semi-amortised inner loop captures one per scene): a CUDA call of another thread during a capture invalidates
    it and fails in that thread ("operation not permitted when stream is capturing"), which ended two runs."""
    if device.type != "cuda":
        return batch.to(device)
    return batch.pin_memory().to(device, non_blocking=True)


def _micro_batches(loader, accumulate: int):
    """Groups of ``accumulate`` consecutive batches of ``loader`` (one group per optimiser step)."""
    group = []
    for batch in loader:
        group.append(batch)
        if len(group) == accumulate:
            yield group
            group = []


def build_parser(config_class: type = TrainConfig, option_help: dict[str, str] | None = None,
                 prog: str = "python -m train.stage1", description: str = __doc__.split("\n\n")[0]
                 ) -> argparse.ArgumentParser:
    """The command line of ``config_class`` (:class:`TrainConfig` or a subclass): every field is a ``--flag``, with
    its text from ``option_help`` (default :data:`OPTION_HELP`) and its default."""
    option_help = OPTION_HELP if option_help is None else option_help
    parser = argparse.ArgumentParser(prog=prog, description=description)
    for field in fields(config_class):
        kind = {"int": int, "float": float}.get(str(field.type).removesuffix(" | None"), str)
        shown = "" if field.default in ("", None) else " (default %(default)s)"
        parser.add_argument("--" + field.name.replace("_", "-"), type=kind, default=field.default,
                            help=option_help[field.name] + shown)
    return parser


def parse_args(argv: list[str] | None = None, config_class: type = TrainConfig,
               parser: argparse.ArgumentParser | None = None) -> TrainConfig:
    """Command line -> ``config_class`` (:class:`TrainConfig` or a subclass, parsed by ``parser``, default
    :func:`build_parser`)."""
    args = (parser or build_parser()).parse_args(argv)
    config = config_class(**vars(args))
    if config.steps < 1 or config.checkpoint_every < 1 or config.log_every < 1 or config.accumulate < 1:
        raise InputError("--steps, --checkpoint-every, --log-every and --accumulate must be >= 1")
    if not 0.0 <= config.ema_decay < 1.0:
        raise InputError(f"--ema-decay must be in [0, 1) (0: keep none), got {config.ema_decay}")
    return config


def print_final_metrics(metrics: dict | None) -> None:
    """Print a run's final metrics as one JSON line, on rank 0 only (the other ranks log the same averages)."""
    if int(os.environ.get("RANK", "0")) == 0 and metrics:
        print(json.dumps(metrics))


def main(argv: list[str] | None = None) -> None:
    print_final_metrics(train(parse_args(argv)))


if __name__ == "__main__":
    main()
