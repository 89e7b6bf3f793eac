"""Semi-amortised training: the encoder's optimisation inside every training step, the target views in the loss.

At test time the encoder presets ``medium`` and ``slow`` move the amortised latents by Adam steps on the context
views alone (:mod:`codecsplat_warp.model.rdo`). The oracle of docs/benchmarks.md shows that latents which render
the target views far better exist, but that fitting the photographs does not find them. This stage trains the model
for the encoder that optimises (as semi-amortised VAEs, Kim et al. 2018, train through the inference that runs at
test time): per step and scene,

1. the amortised encoder and codec give the latents ``z`` (:meth:`CodecSplat.forward` with a lambda, as stage 2);
2. ``K`` steps of the encoder's own optimisation run on the context views from ``z``
   (:func:`codecsplat_warp.model.rdo.refine_latents`: the presets' loss, learning-rate schedule and quantiser, the
   preset ``--inner-preset`` with its step count set to ``K``), ``K`` drawn from ``--inner-steps`` (per scene, or per
   step with ``--inner-draw step``) so that one model serves every preset, ``fast`` (``K = 0``) included;
3. the decoder decodes the refined latents ``z_K`` and the stage-2 loss is taken on the *target* views
   (:func:`train.stage2.codec_loss`: render distortion, depth, feature and rate terms).

The gradient is first-order through the inner loop: the refined latents enter the decoder as
``z + stop_gradient(z_K - z)``, so the decoder (codec top-down pass and synthesis, depth head, R_post; the modules of
``--train-modules``) learns to render the targets from the latents the optimisation reaches, and the amortised
encoder's analysis and posterior receive the decoder's gradient at ``z_K`` as if it were at ``z``. With
``--encoder-gradient amortised`` the refined latents enter as constants instead: the encoder then learns from the
draws with ``K = 0`` alone (stage 2's objective, so that ``fast``'s latents are not pushed towards the refined ones,
which cost more bytes), and the decoder from every draw.

First-order, the decoder learns to decode what the optimisation reaches, not to steer where it goes: the
derivative of the context loss's gradient by the weights (which direction a latent move takes) needs the
rasterizer's second derivatives, which it does not have. ``--lookahead-weight w`` adds that term for one more
*virtual* step ``z' = z_K - w P grad_z L_c(z_K)``, with ``P`` Adam's per-element step scale at ``z_K`` held
(:func:`~codecsplat_warp.model.rdo.loop.adam_step_scale`): the target loss ``L_t(z')`` falls to first order by
``w <P grad_z L_t, grad_z L_c>``, whose gradient by the weights is a Hessian-vector product of ``L_c`` along
``u = P grad_z L_t``, taken by central differences of two context-loss evaluations at ``z_K +- eps u / rms(u)``
(:func:`lookahead_term`, as DARTS approximates its second-order term). The optimisation
pays for its bytes: the rate term is the refined latents' estimated bits. A model trained so decodes with the
same decoder code and bitstream format, but its weights change: it gets a new model id.

Besides stage 2's metrics the log holds the inner loop's figures (:data:`INNER_LOGGED`): the step count ``K``, the
context views' PSNR gain over the ``K`` steps (of the loss's noisy-quantiser renders, first step against last), the
target views' PSNR gain of the refined decode over the amortised one, and inner steps per second.

Everything else (data, batches, checkpoints every ``--checkpoint-every`` steps and on SIGTERM or
``--time-limit-s``, resumption from ``--out``, DDP under torchrun, TensorBoard, metrics.jsonl) is stage 1's loop
(:func:`train.stage1.train`)::

    torchrun --nproc_per_node 4 -m train.semi_amortised --data runs/scenes-256 --holdout ... \\
        --inner-steps 0,8,16,25 --steps 4000 --lr 2e-5 --out runs/semi
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib
import time
from dataclasses import dataclass

import torch
import torch.distributed as dist

from codecsplat_warp.errors import DataError, InputError
from codecsplat_warp.metrics import LPIPS
from codecsplat_warp.metrics.image import psnr
from codecsplat_warp.model import CodecSplat
from codecsplat_warp.model.pretrained import DEFAULT_CHECKPOINT
from codecsplat_warp.model.rdo import PRESETS, decode_variables, latent_target, rdo_config, rdo_loss, refine_latents
from codecsplat_warp.nn.config import FEATURE_STRIDE, ModelConfig

from . import stage1, stage2
from .checkpoint import latest_checkpoint, model_file_config, read_weights
from .data import BatchSource, TrainingBatch

INNER_LOGGED = ("inner_steps", "context_gain", "target_gain", "target_psnr_amortised", "inner_steps_per_s",
                "lookahead_alignment")
"""The inner loop's metrics, logged beside stage 2's: ``K``; the context views' PSNR gain over the ``K`` steps
(dB; 0 when ``K`` is 0); the targets' PSNR of the refined decode minus the amortised decode's (dB); the amortised
decode's target PSNR (dB); inner steps per second (0 when ``K`` is 0); the look-ahead's alignment
(:func:`lookahead_term`; 0 without the term)."""

LOGGED = stage2.LOGGED + INNER_LOGGED

DEFAULT_TRAIN_MODULES = "codec,depth_head,refine_post"
"""The modules trained by default: stage 2's (the codec, the decoder depth head and R_post)."""


@dataclass
class SemiAmortisedConfig(stage2.Stage2Config):
    """Options: stage 2's (:class:`train.stage2.Stage2Config`) plus the inner loop's; ``init`` names the whole
    model to start from (a model file or a run folder), not a stage-1 run, and ``codec_init``,
    ``codec_latent_channels``, ``codec_finest_stride`` and ``trainable`` are not used."""

    out: str = "runs/semi"
    steps: int = 4000
    init: str = str(DEFAULT_CHECKPOINT)
    lr: float = 2e-5
    warmup_steps: int = 100
    rate_warmup_steps: int = 0
    beta: float | None = 1.3e-3
    inner_steps: str = "0,8,16,25"
    inner_preset: str = "medium"
    inner_precision: str = "float32"
    inner_cuda_graphs: int = 1
    inner_draw: str = "scene"
    train_modules: str = DEFAULT_TRAIN_MODULES
    encoder_gradient: str = "refined"
    lookahead_weight: float = 0.0
    lookahead_epsilon: float = 0.05


ENCODER_GRADIENTS = ("refined", "amortised")
"""``--encoder-gradient``'s choices (see the module docstring)."""

INNER_DRAWS = ("scene", "step")
"""``--inner-draw``'s choices: one K per rank and scene, or one K per step shared by every rank and scene."""

OPTION_HELP = {
    **stage2.OPTION_HELP,
    "init": "the model to start from: a model file (default: the shipped model) or a run folder of this stage",
    "inner_steps": "comma list of inner optimisation step counts K, one drawn per step and scene (see --inner-draw; "
                   "0: the amortised latents, the fast preset); list one twice to draw it twice as often",
    "inner_preset": "the encoder preset whose optimisation runs inside each step (medium or slow; its loss, "
                    "learning rate and cross-view term, with K steps)",
    "inner_precision": "precision of the inner optimisation's networks: float32 (as the presets) or bfloat16",
    "inner_cuda_graphs": "1: the inner optimisation replays its decoder and loss as CUDA graphs, as the presets do "
                         "(on CUDA, for K >= 16; each loop pays a capture, so it gains on long loops only); 0: eager",
    "inner_draw": "how K is drawn: scene (per rank and scene) or step (one K per step for every rank and scene, so "
                  "that under DDP no rank waits on another's longer inner loop)",
    "train_modules": "comma list of the model's modules that train (codec, depth_head, refine_post, gs_head, "
                     "refine_pre, feat_head, mvenc), or a dotted path to a part of one: codec.synthesis is the "
                     "codec's decoder side, so that with the rest of the codec frozen the bytes stay the model's",
    "encoder_gradient": "where the amortised encoder (the codec's analysis and posterior) learns from: refined (the "
                        "target loss at the refined latents, passed straight through to the amortised ones) or "
                        "amortised (the draws with K = 0 alone; the refined latents enter the decoder as constants)",
    "lookahead_weight": "weight of the look-ahead term (0: off): the gradient of the target loss after one more "
                        "virtual Adam step on the context loss (the inner loop's step scales held), taken through "
                        "that step's dependence on the weights by central differences; it teaches the decoder "
                        "latent moves that carry from the context views to the targets (module docstring)",
    "lookahead_epsilon": "half the central difference's span along the look-ahead direction (normalised to an RMS "
                         "of 1), in quantisation steps",
    "codec_init": "not used by this stage",
    "codec_latent_channels": "not used by this stage",
    "codec_finest_stride": "not used by this stage",
    "trainable": "not used by this stage (see --train-modules)",
}
"""``--help`` text of every :class:`SemiAmortisedConfig` field."""


def parse_counts(text: str, option: str, minimum: int) -> list[int]:
    """A comma list of counts, ``"0,8,16,25"`` -> [0, 8, 16, 25] (repeats kept: they weigh the draw of
    :func:`draw_count`); InputError naming the command-line ``option`` unless every entry is an integer >=
    ``minimum``. The lists of ``--inner-steps`` here and ``--iterations`` of :mod:`train.learned_refiner`."""
    message = f"{option} must be a comma list of integers >= {minimum}, got {text!r}"
    try:
        counts = [int(k) for k in text.split(",") if k.strip()]
    except ValueError:
        raise InputError(message) from None
    if not counts or any(k < minimum for k in counts):
        raise InputError(message)
    return counts


def draw_count(counts: list[int], seed: int, step: int, rank: int, scene: int) -> int:
    """One of ``counts``, uniformly, a function of (seed, step, rank, scene) alone: the inner step count of one
    scene of a step here; with ``rank`` and ``scene`` 0, one count per step that every rank draws alike."""
    generator = torch.Generator().manual_seed(((seed * 1_000_003 + step) * 1009 + rank) * 101 + scene + 7)
    return counts[int(torch.randint(len(counts), (), generator=generator))]


def inner_count(counts: list[int], config: SemiAmortisedConfig, step: int, rank: int, scene: int) -> int:
    """``K`` of one scene of a step (:func:`draw_count` from ``counts``): per rank and scene with ``--inner-draw
    scene``, or one per step for every rank and scene with ``--inner-draw step``."""
    per_scene = config.inner_draw == "scene"
    return draw_count(counts, config.seed, step, rank if per_scene else 0, scene if per_scene else 0)


def semi_amortised_loss(model: torch.nn.Module, lpips: LPIPS, batch: TrainingBatch, config: SemiAmortisedConfig,
                        step: int) -> tuple[torch.Tensor, dict]:
    """The stage-2 loss on the target views of the latents refined by ``K`` inner steps (see the module
    docstring); returns (loss, metrics as floats or detached 0-dim tensors). ``model`` may be the DDP wrapper."""
    bare = model.module if hasattr(model, "module") else model
    lam = stage2.step_lambda(config, step)
    images, cameras = batch.context_images, batch.context_cameras
    with torch.autocast(images.device.type, dtype=torch.bfloat16, enabled=images.device.type == "cuda"):
        out = model(images, cameras, lam=lam, scenes=batch.scenes)
    refined, scales, inner = refine_scenes(bare, batch, lam, out["latents"], config, step)
    entering = None
    if inner["inner_steps"] > 0:
        amortised_gaussians = out["gaussians"]
        entering = entering_latents(out["latents"], refined, through_encoder=config.encoder_gradient == "refined")
        out = {**out, **decode_latents(bare, cameras, lam, out["neighbours"], entering)}
        with torch.no_grad():
            inner["target_psnr_amortised"] = psnr(stage1.render_targets(bare, amortised_gaussians, batch),
                                                  batch.target_images).mean()
    loss, metrics = stage2.codec_loss(model, lpips, batch, config, step, lam, out)
    if inner["inner_steps"] > 0:
        inner["target_gain"] = metrics["psnr"] - inner["target_psnr_amortised"]
    else:
        inner["target_psnr_amortised"] = metrics["psnr"]
    if config.lookahead_weight > 0 and entering is not None:
        target_gradients = torch.autograd.grad(loss, entering, retain_graph=True)
        lookahead, inner["lookahead_alignment"] = lookahead_term(bare, batch, lam, refined, target_gradients, scales,
                                                                 config, step)
        loss = loss + lookahead
    return loss, {**metrics, **inner}


def refine_scenes(model: CodecSplat, batch: TrainingBatch, lam: float, latents: list[torch.Tensor],
                  config: SemiAmortisedConfig, step: int
                  ) -> tuple[list[torch.Tensor], list[list[torch.Tensor] | None], dict]:  # fmt: skip
    """Each scene of ``batch`` refined by its drawn ``K`` inner steps from its slice of ``latents`` (per level,
    [S*V,C_l,h_l,w_l], scene-major); returns the refined latents (detached, the same shapes), each scene's Adam
    step scale after its last step (:attr:`~codecsplat_warp.model.rdo.loop.Refinement.step_scale`, per level
    [V,C_l,h_l,w_l]; None where ``K`` is 0 and without the look-ahead) and the inner loop's metrics
    (:data:`INNER_LOGGED`, the mean over the scenes; ``inner_steps`` a float)."""
    rank = dist.get_rank() if dist.is_initialized() else 0
    counts = parse_counts(config.inner_steps, "--inner-steps", 0)
    views = batch.context_images.shape[0] // batch.scenes
    device = batch.context_images.device
    refined, scales, drawn, gains, seconds = [], [], [], [], 0.0
    for scene, cameras in enumerate(batch.scene_contexts()):
        rows = slice(scene * views, (scene + 1) * views)
        steps = inner_count(counts, config, step, rank, scene)
        rdo = rdo_config(config.inner_preset, steps=steps, views=views, precision=config.inner_precision,
                         cuda_graphs=bool(config.inner_cuda_graphs), check_every=0)
        generator = torch.Generator(device=device).manual_seed(config.seed * 1_000_003 + step * 101 + scene)
        synchronize(device)
        began = time.perf_counter()
        result = refine_latents(model, batch.context_images[rows].float(), cameras.to(dtype=torch.float32), lam,
                                [z[rows] for z in latents], rdo, generator, step_scale=config.lookahead_weight > 0)
        synchronize(device)
        seconds += time.perf_counter() - began
        refined.append(result.latents)
        scales.append(result.step_scale)
        drawn.append(steps)
        if result.first is not None:
            gains.append(psnr_of(result.last["mse"]) - psnr_of(result.first["mse"]))
    total = sum(drawn)
    metrics = {"inner_steps": total / len(drawn),
               "context_gain": torch.stack(gains).mean() if gains else 0.0,
               "target_gain": 0.0, "target_psnr_amortised": 0.0,
               "inner_steps_per_s": total / seconds if total else 0.0, "lookahead_alignment": 0.0}
    return [torch.cat(level) for level in zip(*refined)], scales, metrics


def entering_latents(latents: list[torch.Tensor], refined: list[torch.Tensor], through_encoder: bool
                     ) -> list[torch.Tensor]:  # fmt: skip
    """The refined latents as the decoder takes them, first-order: ``z + stop_gradient(refined - z)`` with ``z``
    the amortised ``latents``, or, with ``through_encoder`` False, ``refined + 0 * z`` (no gradient reaches the
    encoder, which stays in the graph so that DDP finds its parameters used); per level, ``z``'s shapes and
    dtypes."""
    if through_encoder:
        return [z + (r.to(z.dtype) - z).detach() for z, r in zip(latents, refined)]
    return [r.to(z.dtype) + 0.0 * z for z, r in zip(latents, refined)]


def lookahead_term(model: CodecSplat, batch: TrainingBatch, lam: float, refined: list[torch.Tensor],
                   target_gradients: tuple[torch.Tensor, ...], scales: list[list[torch.Tensor] | None],
                   config: SemiAmortisedConfig, step: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The look-ahead term of the module docstring, summed over the scenes that took inner steps, and the mean
    alignment ``<u, grad_z L_c> / rms(u)`` of those scenes (detached; > 0 where a context step lowers the target
    loss). Its value is ``-w rms(u) (L_c(z_K + eps u^) - L_c(z_K - eps u^)) / (2 eps)`` with ``u^ = u / rms(u)``,
    ``u = P grad_z L_t``, the latents constant, so that its gradient is the look-ahead's by the weights alone.

    Args:
        refined: the refined latents ``z_K`` (per level, [S*V,C_l,h_l,w_l], scene-major; detached).
        target_gradients: ``grad_z L_t`` at the latents that entered the decoder (the same shapes).
        scales: each scene's Adam step scale ``P`` (:func:`refine_scenes`; None for a scene without inner steps).
    """
    views = batch.context_images.shape[0] // batch.scenes
    epsilon, terms, alignments = config.lookahead_epsilon, [], []
    rdo = rdo_config(config.inner_preset, steps=1, views=views, cuda_graphs=False, check_every=0)
    for scene, cameras in enumerate(batch.scene_contexts()):
        if scales[scene] is None:
            continue
        rows = slice(scene * views, (scene + 1) * views)
        direction = [g[rows].detach().float() * p for g, p in zip(target_gradients, scales[scene])]
        size = torch.cat([d.flatten() for d in direction]).square().mean().sqrt()
        if not bool(torch.isfinite(size)) or float(size) == 0.0:
            continue
        direction = [d / size for d in direction]
        latents = [z[rows].float() for z in refined]
        images = batch.context_images[rows].float()
        target = latent_target(model, images, cameras.to(dtype=torch.float32), lam, latents, rdo)
        seed = (config.seed * 1_000_003 + step) * 101 + scene + 1
        offsets = rounding_offsets(model, latents, lam, cameras)
        ahead = context_loss_at(model, [z + epsilon * d for z, d in zip(latents, direction)], target, rdo, seed,
                                offsets)
        behind = context_loss_at(model, [z - epsilon * d for z, d in zip(latents, direction)], target, rdo, seed,
                                 offsets)
        slope = (ahead - behind) / (2.0 * epsilon)
        terms.append(-config.lookahead_weight * size * slope)
        alignments.append(slope.detach())
    if not terms:
        zero = refined[0].new_zeros(())
        return zero, zero
    return torch.stack(terms).sum(), torch.stack(alignments).mean()


@torch.no_grad()
def rounding_offsets(model: CodecSplat, latents: list[torch.Tensor], lam: float, cameras) -> list[torch.Tensor]:
    """The training quantiser's rounding offsets ``round(r) - r`` at ``latents`` (per level, their shapes), which
    :func:`context_loss_at` holds so that its decoder input is linear in the latents."""
    coded = model.codec.forward_latents(latents, lam, cameras.height // FEATURE_STRIDE, cameras.width // FEATURE_STRIDE)
    return coded.rounding_offsets


def context_loss_at(model: CodecSplat, latents: list[torch.Tensor], target, rdo, seed: int,
                    offsets: list[torch.Tensor]) -> torch.Tensor:
    """The presets' context loss (:func:`~codecsplat_warp.model.rdo.rdo_loss`, eager, float32) at ``latents``
    (constants), with the graph to the model's parameters. The training quantiser's noise is drawn from ``seed`` and
    its rounding offsets are the held ``offsets`` (:func:`rounding_offsets`), so that two calls differ by the
    latents alone, and smoothly: the straight-through rounding's linearisation, which the inner loop's gradient
    follows (with this pass's own rounding a small move of the latents changes the decoder input by 0 or 1)."""
    generator = torch.Generator(device=latents[0].device).manual_seed(seed)

    def decoder(variables, noise_generator, _temperature):
        return decode_variables(model, variables, target, "latents", noise_generator, held_offsets=offsets)

    loss, _ = rdo_loss(model, [z.detach() for z in latents], target, rdo, generator, decoder=decoder)
    return loss


def decode_latents(model: CodecSplat, cameras, lam: float, neighbours: torch.Tensor,
                   latents: list[torch.Tensor]) -> dict:
    """The codec path's outputs from ``latents`` (per level, on the gained grid; the model's training quantiser),
    with their graph: ``F_hat``, ``S``, ``D_hat``, ``rate_bits`` and ``gaussians`` (bf16 autocast on CUDA, as
    stage 2)."""
    device = latents[0].device
    with torch.autocast(device.type, dtype=torch.bfloat16, enabled=device.type == "cuda"):
        coded = model.codec.forward_latents(latents, lam, cameras.height // FEATURE_STRIDE,
                                            cameras.width // FEATURE_STRIDE)
        s, depth, gaussians = model.decode_feature(coded.feature, cameras, neighbours)
    return {"F_hat": coded.feature, "S": s, "D_hat": depth, "rate_bits": coded.bits.sum(), "gaussians": gaussians}


def psnr_of(mse: torch.Tensor) -> torch.Tensor:
    """PSNR in dB (peak 1) of a mean squared error tensor."""
    return -10.0 * torch.log10(mse.float().clamp_min(1e-12))


def synchronize(device: torch.device) -> None:
    """Wait for ``device``'s queued work (CUDA; nothing on the CPU), e.g. before reading a wall clock."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def build_model(model_config: ModelConfig, config: SemiAmortisedConfig) -> CodecSplat:
    """The whole model from ``config.init`` (unless ``config.out`` has a checkpoint to resume), with only the
    modules of ``config.train_modules`` trainable. Raises InputError for an unknown module name and DataError
    when ``config.init`` does not hold this model's weights."""
    model = CodecSplat(model_config, codec=True)
    if latest_checkpoint(config.out) is None:
        try:
            model.load_state_dict(read_weights(config.init))
        except RuntimeError as exc:
            raise DataError(f"--init {config.init} does not hold a CodecSplat of the sizes in its config: {exc}") \
                from None
    model.requires_grad_(False)
    for name in config.train_modules.split(","):
        module = trained_module(model, name.strip())
        if module is None:
            raise InputError(f"--train-modules {name!r} is not a module of the model")
        module.requires_grad_(True)
    if model.mvenc.mono_backbone is not None:
        model.mvenc.mono_backbone.requires_grad_(False)
    return model


def trained_module(model: CodecSplat, name: str) -> torch.nn.Module | None:
    """The module of ``model`` named ``name``: a top-level one (``gs_head``) or a dotted path to one inside it
    (``codec.synthesis``, the codec's decoder side, which the bytes do not depend on); None when there is none."""
    if not name:
        return None
    try:
        return model.get_submodule(name)  # AttributeError for a missing name or one that is not a module
    except AttributeError:
        return None


def run_model_config(config: SemiAmortisedConfig) -> ModelConfig:
    """The network sizes: from ``config.out`` when resuming, else from ``config.init`` (a run folder's
    config.json, or a model file's metadata)."""
    for run in (config.out, config.init):
        file = pathlib.Path(run) / "config.json"
        if run and file.is_file():
            return ModelConfig.from_dict(json.loads(file.read_text())["model"])
    path = pathlib.Path(config.init)
    if not path.is_file():
        raise InputError(f"--init must name a model file or a run folder, got {config.init!r}")
    return model_file_config(path, "--init")


STAGE = stage1.Stage("semi", build_model, semi_amortised_loss, LOGGED)


def train(config: SemiAmortisedConfig, source: BatchSource | None = None, progress: bool = True) -> dict:
    """Run (or resume) semi-amortised training until ``config.steps``; see :func:`train.stage1.train`."""
    return stage1.train(config, source, run_model_config(config), progress, stage=STAGE)


def build_parser() -> argparse.ArgumentParser:
    """The command line: :class:`SemiAmortisedConfig`'s fields as flags."""
    return stage1.build_parser(SemiAmortisedConfig, OPTION_HELP, "python -m train.semi_amortised",
                               __doc__.split("\n\n")[0])


def parse_args(argv: list[str] | None = None) -> SemiAmortisedConfig:
    """Command line -> :class:`SemiAmortisedConfig`; InputError for a bad inner-loop option."""
    config = stage1.parse_args(argv, SemiAmortisedConfig, build_parser())
    parse_counts(config.inner_steps, "--inner-steps", 0)
    check_inner_preset(config.inner_preset)
    if config.inner_precision not in ("float32", "bfloat16"):
        raise InputError(f"--inner-precision must be float32 or bfloat16, got {config.inner_precision!r}")
    if config.inner_draw not in INNER_DRAWS:
        raise InputError(f"--inner-draw must be one of {', '.join(INNER_DRAWS)}, got {config.inner_draw!r}")
    if config.inner_cuda_graphs not in (0, 1):
        raise InputError(f"--inner-cuda-graphs must be 0 or 1, got {config.inner_cuda_graphs}")
    if config.coded_every < 1:
        raise InputError("--coded-every must be >= 1")
    if not (math.isfinite(config.lookahead_weight) and config.lookahead_weight >= 0):
        raise InputError(f"--lookahead-weight must be >= 0, got {config.lookahead_weight}")
    if not (math.isfinite(config.lookahead_epsilon) and config.lookahead_epsilon > 0):
        raise InputError(f"--lookahead-epsilon must be > 0, got {config.lookahead_epsilon}")
    if config.encoder_gradient not in ENCODER_GRADIENTS:
        raise InputError(f"--encoder-gradient must be one of {', '.join(ENCODER_GRADIENTS)}, got "
                         f"{config.encoder_gradient!r}")
    return config


def check_inner_preset(name: str) -> None:
    """InputError unless ``name`` is a preset that optimises (``--inner-preset``)."""
    if name not in PRESETS or name == "fast":
        raise InputError(f"--inner-preset must be an optimising preset ({', '.join(p for p in PRESETS if p != 'fast')}), "
                         f"got {name!r}")


def main(argv: list[str] | None = None) -> None:
    stage1.print_final_metrics(train(parse_args(argv)))


if __name__ == "__main__":
    main()
