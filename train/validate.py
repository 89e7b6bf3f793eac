"""Held-out validation of a training run: codec-free target-view PSNR, self-render PSNR and depth error on fixed
held-out samples.

The samples are the entries of an evaluation index file (scene folder -> context and target frames, e.g.
``train/heldout_index/index-re10k.json``) under ``--data``, preprocessed to the ``--protocol`` size as
``codecsplat eval`` does (:func:`codecsplat_warp.eval.protocols.index_samples`). Each is rendered by the run's
latest checkpoint (its weight average where it keeps one: :func:`train.checkpoint.weights_for_use`; a stage-1
checkpoint without codec too) and compared with the "copy the nearest context view" baseline. PSNR on
[0,1]-clipped images. Also per sample: the codec-free Gaussians rendered into their own context views (self-render
PSNR against the context images) and, with ``--mvs-depth DIR`` (``DIR/<scene>/depth.json`` of ``codecsplat
depth``), the encoder depth ``D_enc`` against the context views' reference depth (AbsRel and delta<1.25 over the
pixels with reference depth, :mod:`codecsplat_warp.eval.geometry`); the depth means are over the samples that
have reference depth (``depth_samples``).

    python -m train.validate --run runs/stage1 --data DIR --index train/heldout_index/index-re10k.json \
        --protocol re10k --mvs-depth MVS

Writes the JSON summary and ``curve.png`` (training loss and PSNR against step, with the held-out PSNR of
the model and of the baseline) next to it (default ``RUN/validation-PROTOCOL.json``).
"""

from __future__ import annotations

import argparse
import json
import pathlib
from dataclasses import dataclass

import torch
from tqdm import tqdm

from codecsplat_warp.device import resolve_device
from codecsplat_warp.errors import InputError
from codecsplat_warp.eval.geometry import ReferenceDepth, depth_errors
from codecsplat_warp.eval.protocols import PROTOCOLS, Sample, find_scenes, index_samples, nearest_context_images
from codecsplat_warp.metrics.image import psnr
from codecsplat_warp.model import CodecSplat
from codecsplat_warp.nn.config import ModelConfig

from .checkpoint import latest_checkpoint, read_weights
from .stage1 import METRICS_FILE


@dataclass
class SceneScore:
    """Scores of one held-out sample: mean target-view PSNR (dB) of the codec-free model and of the nearest
    view, mean self-render PSNR (dB) over the context views, and the errors of ``D_enc`` against the reference
    depth (None without it)."""

    scene: str
    samples: int
    model_psnr: float
    nearest_view_psnr: float
    self_render_psnr: float | None = None
    depth_abs_rel: float | None = None
    depth_delta_1_25: float | None = None


@torch.no_grad()
def score_sample(model: CodecSplat, sample: Sample, device: torch.device,
                 reference: ReferenceDepth | None = None) -> SceneScore:
    """Codec-free model, nearest-view and self-render PSNR of one sample, and ``D_enc``'s errors against the
    reference depth of its context views (when ``reference`` has any)."""
    depth_reference = reference.context_depth(sample) if reference is not None else None
    sample = sample.to(device)
    with torch.autocast(device.type, dtype=torch.bfloat16, enabled=device.type == "cuda"):
        out = model(sample.context_images, sample.context_cameras)
    rgb = model.render(out["gaussians"], sample.target_cameras)["rgb"]
    own = model.render(out["gaussians"], sample.context_cameras)["rgb"]
    nearest = nearest_context_images(sample.context_images, sample.context_cameras, sample.target_cameras)
    errors = depth_errors(out["D_enc"], depth_reference) if depth_reference is not None else {}
    return SceneScore(sample.scene, 1, float(psnr(rgb, sample.target_images).mean()),
                      float(psnr(nearest, sample.target_images).mean()), float(psnr(own, sample.context_images).mean()),
                      errors.get("abs_rel"), errors.get("delta_1_25"))


def summarize(scores: list[SceneScore]) -> dict:
    """Means over the samples: PSNRs over all, depth errors over those with reference depth (``depth_samples``)."""
    def mean(key: str) -> float | None:
        values = [getattr(s, key) for s in scores if getattr(s, key) is not None]
        return sum(values) / len(values) if values else None

    keys = ("model_psnr", "nearest_view_psnr", "self_render_psnr", "depth_abs_rel", "depth_delta_1_25")
    return {**{key: mean(key) for key in keys}, "depth_samples": sum(s.depth_abs_rel is not None for s in scores)}


def load_run(run: pathlib.Path, device, step: int | None = None) -> tuple[CodecSplat, int]:
    """The model of a run's newest checkpoint, or of its checkpoint after ``step`` (sizes from the run's
    ``config.json``; with its codec when the checkpoint has one; the weight average's values where it keeps
    one), and the checkpoint's step."""
    checkpoint = latest_checkpoint(run) if step is None else run / "checkpoints" / f"step-{step:08d}"
    if checkpoint is None or not (checkpoint / "checkpoint.json").is_file():
        raise InputError(f"no checkpoint {'' if step is None else f'of step {step} '}under {run}/checkpoints")
    config = ModelConfig.from_dict(json.loads((run / "config.json").read_text())["model"])
    weights = read_weights(checkpoint)
    model = CodecSplat(config, codec=any(name.startswith("codec.") for name in weights))
    model.load_state_dict(weights)
    return model.to(device).eval(), int(json.loads((checkpoint / "checkpoint.json").read_text())["step"])


def read_metrics(run: pathlib.Path) -> list[dict]:
    """Logged training steps of a run (empty when it logged none)."""
    path = run / METRICS_FILE
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line]


def plot_curve(records: list[dict], scores: list[SceneScore], step: int, path: pathlib.Path) -> None:
    """Training loss and PSNR against step (raw and smoothed) with the held-out PSNRs at ``step``."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    steps = [r["step"] for r in records]
    fig, (ax_loss, ax_psnr) = plt.subplots(1, 2, figsize=(11, 4))
    for ax, key in ((ax_loss, "loss"), (ax_psnr, "psnr")):
        values = torch.tensor([r[key] for r in records], dtype=torch.float64)
        ax.plot(steps, values.tolist(), alpha=0.3, lw=0.8, label=f"train {key}")
        if len(values) >= 10:
            window = max(5, len(values) // 20)
            smooth = torch.nn.functional.avg_pool1d(values[None, None], window, 1).flatten()
            ax.plot(steps[window - 1:], smooth.tolist(), lw=1.5, label=f"train {key} (mean of {window})")
        ax.set_xlabel("step")
        ax.set_ylabel(key + (" (dB)" if key == "psnr" else ""))
        ax.grid(alpha=0.3)
    if scores:
        model_mean = sum(s.model_psnr for s in scores) / len(scores)
        baseline_mean = sum(s.nearest_view_psnr for s in scores) / len(scores)
        ax_psnr.scatter([step], [model_mean], color="C3", zorder=3, label=f"held-out model {model_mean:.2f} dB")
        ax_psnr.axhline(baseline_mean, color="C2", ls="--", label=f"held-out nearest view {baseline_mean:.2f} dB")
    ax_loss.set_yscale("log")
    ax_loss.legend(loc="upper right")
    ax_psnr.legend(loc="upper left", fontsize=8)
    fig.suptitle(f"stage 1 training ({len(scores)} held-out scenes)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m train.validate``."""
    parser = argparse.ArgumentParser(prog="python -m train.validate", description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", type=pathlib.Path, required=True, help="training run folder (stage 1 or 2)")
    parser.add_argument("--data", type=pathlib.Path, required=True, help="folder of real scene folders")
    parser.add_argument("--index", type=pathlib.Path, required=True,
                        help="evaluation index JSON of held-out samples, e.g. train/heldout_index/index-re10k.json")
    parser.add_argument("--protocol", choices=[p for p in PROTOCOLS if PROTOCOLS[p].width], default="re10k",
                        help="re10k: 256x256; dl3dv: 256x448 (HxW); the view counts come from the index "
                        "(default %(default)s)")
    parser.add_argument("--step", type=int, help="validate the checkpoint of this step (default: the newest)")
    parser.add_argument("--device", default="auto", help="cpu, cuda, cuda:N or auto (default %(default)s)")
    parser.add_argument("--out", type=pathlib.Path,
                        help="JSON summary; a PNG curve is written beside it (default RUN/validation-PROTOCOL.json)")
    parser.add_argument("--mvs-depth", type=pathlib.Path,
                        help="folder of reference depth, DIR/<scene>/depth.json (codecsplat depth): scores D_enc's "
                        "AbsRel and delta<1.25 (default: no depth scores)")
    return parser


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    device = resolve_device(args.device)
    reference = ReferenceDepth(args.mvs_depth) if args.mvs_depth else None
    model, step = load_run(args.run, device, args.step)
    samples = index_samples(find_scenes(args.data), args.index, PROTOCOLS[args.protocol])
    scores = [score_sample(model, sample, device, reference) for sample in tqdm(samples, desc="validate")]
    out = args.out or args.run / f"validation-{args.protocol}.json"
    summary = {"step": step, "protocol": args.protocol, "index": str(args.index),
               "mvs_depth": str(args.mvs_depth) if args.mvs_depth else None, "scenes": [vars(s) for s in scores],
               **summarize(scores)}
    out.write_text(json.dumps(summary, indent=1))
    plot_curve(read_metrics(args.run), scores, step, out.with_suffix(".png"))
    print(score_table(scores, summary, step))


def score_table(scores: list[SceneScore], summary: dict, step: int) -> str:
    """The printed table: one line per sample and the means (depth columns "-" without reference depth)."""
    def cells(model_psnr, nearest, own, abs_rel, delta) -> str:
        depth = "".join(f"{'-' if v is None else format(v, '.3f'):>9}" for v in (abs_rel, delta))
        return f"{model_psnr:>10.2f}{nearest:>12.2f}{'-' if own is None else format(own, '.2f'):>9}{depth}"

    lines = [f"{'scene':<28}{'model dB':>10}{'nearest dB':>12}{'self dB':>9}{'AbsRel':>9}{'δ<1.25':>9}"]
    lines += [f"{s.scene:<28}" + cells(s.model_psnr, s.nearest_view_psnr, s.self_render_psnr, s.depth_abs_rel,
                                        s.depth_delta_1_25) for s in scores]
    lines.append(f"{'mean':<28}" + cells(*(summary[k] for k in ("model_psnr", "nearest_view_psnr", "self_render_psnr",
                                                                 "depth_abs_rel", "depth_delta_1_25")))
                 + f"  (step {step}; depth over {summary['depth_samples']} of {len(scores)} samples)")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
