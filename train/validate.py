"""Held-out validation of a stage-1 run and its training curve.

For each held-out real scene, a fixed set of samples (anchor view, nearest context views, targets in
between; see :func:`codecsplat_warp.data.split_context_targets`) is rendered by the run's latest checkpoint and
compared with the "copy the nearest context view" baseline (the context image whose camera centre is
closest to the target's, returned unchanged). PSNR on [0,1]-clipped images.

    python -m train.validate --run runs/stage1 --data DIR --scenes a,b,c,d --out runs/stage1/validation.json

Writes the JSON summary and ``curve.png`` (training loss and PSNR against step, with the held-out PSNR of
the model and of the baseline) next to it.
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
from codecsplat_warp.metrics.image import psnr
from codecsplat_warp.model import CodecSplat, ModelConfig

from .checkpoint import latest_checkpoint, load_model_weights
from .data import TrainingSample, real_scene_source
from .stage1 import METRICS_FILE


@dataclass
class SceneScore:
    """Mean target-view PSNR (dB) of one held-out scene over its samples."""

    scene: str
    samples: int
    model_psnr: float
    nearest_view_psnr: float


def nearest_context_images(sample: TrainingSample) -> torch.Tensor:
    """[T,3,H,W] for each target, the context image whose camera centre is nearest to the target's."""
    distance = torch.cdist(sample.target_cameras.centers.double(), sample.context_cameras.centers.double())
    return sample.context_images[distance.argmin(dim=1)]


@torch.no_grad()
def score_scene(model: CodecSplat, root, scene: str, samples: int, device: torch.device) -> SceneScore:
    """Model and nearest-view PSNR on ``samples`` deterministic samples of one scene."""
    source = real_scene_source(model.config, root, seed=12345, scene_names=[scene])
    model_scores, baseline_scores = [], []
    for index in range(samples):
        sample = source(index).to(device)
        gaussians = model(sample.context_images, sample.context_cameras)["gaussians"]
        rgb = model.render(gaussians, sample.target_cameras)["rgb"]
        model_scores.append(float(psnr(rgb, sample.target_images).mean()))
        baseline_scores.append(float(psnr(nearest_context_images(sample), sample.target_images).mean()))
    return SceneScore(scene, samples, sum(model_scores) / samples, sum(baseline_scores) / samples)


def load_run(run: pathlib.Path, device: torch.device) -> tuple[CodecSplat, int]:
    """The model of a run's latest checkpoint (sizes from its ``config.json``) and the checkpoint's step."""
    checkpoint = latest_checkpoint(run)
    if checkpoint is None:
        raise InputError(f"no checkpoint under {run}/checkpoints")
    config = json.loads((run / "config.json").read_text())
    model = CodecSplat(ModelConfig.from_dict(config["model"]))
    index = load_model_weights(checkpoint, model)
    return model.to(device).eval(), int(index["step"])


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


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m train.validate", description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", type=pathlib.Path, required=True, help="stage-1 run folder")
    parser.add_argument("--data", type=pathlib.Path, required=True, help="folder of real scene folders")
    parser.add_argument("--scenes", required=True, help="comma-separated held-out scene names")
    parser.add_argument("--samples", type=int, default=8, help="samples per scene")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--out", type=pathlib.Path, help="JSON summary (default RUN/validation.json)")
    args = parser.parse_args(argv)
    device = resolve_device(args.device)
    model, step = load_run(args.run, device)
    names = [n for n in args.scenes.split(",") if n]
    scores = [score_scene(model, args.data, name, args.samples, device) for name in tqdm(names, desc="validate")]
    out = args.out or args.run / "validation.json"
    summary = {
        "step": step, "scenes": [vars(s) for s in scores],
        "model_psnr": sum(s.model_psnr for s in scores) / len(scores),
        "nearest_view_psnr": sum(s.nearest_view_psnr for s in scores) / len(scores),
    }
    out.write_text(json.dumps(summary, indent=1))
    plot_curve(read_metrics(args.run), scores, step, out.with_name("curve.png"))
    print(f"{'scene':<28}{'model dB':>10}{'nearest dB':>12}")
    for s in scores:
        print(f"{s.scene:<28}{s.model_psnr:>10.2f}{s.nearest_view_psnr:>12.2f}")
    print(f"{'mean':<28}{summary['model_psnr']:>10.2f}{summary['nearest_view_psnr']:>12.2f}  (step {step})")


if __name__ == "__main__":
    main()
