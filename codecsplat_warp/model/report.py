"""Parameter count, forward time and peak memory of each model preset (``python -m codecsplat_warp.model.report``).

Runs the codec-free forward pass (MVEnc -> F_g -> F_c -> Gaussians, no rendering) on random images and a
row of cameras, in float32 on the CPU and in bf16 autocast on CUDA (the training setting). Peak memory is
``torch.cuda.max_memory_allocated`` on CUDA and the process's peak resident set size (``ru_maxrss``, which
never decreases, so CPU rows after the first are upper bounds) on the CPU.
"""

from __future__ import annotations

import argparse
import resource

import torch

from ..cameras import Cameras, intrinsics_matrix
from ..device import resolve_device
from ..measure import timed
from .codecsplat import CodecSplat
from ..nn.config import PRESETS, ModelConfig


def parameter_count(model: torch.nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


def example_inputs(config: ModelConfig, device: torch.device) -> tuple[torch.Tensor, Cameras]:
    """Random images [V,3,H,W] and V cameras on a line, 0.3 apart, looking down +z (near 0.5, far 100)."""
    V, H, W = config.num_views, config.height, config.width
    g = torch.Generator().manual_seed(0)
    images = torch.rand(V, 3, H, W, generator=g)
    f = torch.full((V,), 0.9 * W)
    K = intrinsics_matrix(f, f, torch.full((V,), W / 2), torch.full((V,), H / 2))
    c2w = torch.eye(4).repeat(V, 1, 1)
    c2w[:, 0, 3] = 0.3 * torch.arange(V)
    cameras = Cameras.from_c2w(K, c2w, torch.full((V,), 0.5), torch.full((V,), 100.0), W, H)
    return images.to(device), cameras.to(device)


def measure(config: ModelConfig, device: torch.device, repeats: int = 3) -> dict:
    """{params, forward_s (best of ``repeats`` after a warm-up), peak_mb} of one preset on ``device``."""
    model = CodecSplat(config).to(device).eval()
    images, cameras = example_inputs(config, device)
    autocast = torch.autocast(device.type, dtype=torch.bfloat16, enabled=device.type == "cuda")

    def run() -> float:
        with torch.no_grad(), autocast:
            return timed(lambda: model(images, cameras), device)[1]

    run()  # warm-up: Warp kernel compilation / loading, allocator
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    best = min(run() for _ in range(repeats))
    if device.type == "cuda":
        peak = torch.cuda.max_memory_allocated(device) / 2**20
    else:
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return {"params": parameter_count(model), "forward_s": best, "peak_mb": peak}


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m codecsplat_warp.model.report``."""
    parser = argparse.ArgumentParser(prog="python -m codecsplat_warp.model.report", description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="auto", help="cpu, cuda, cuda:N or auto (default %(default)s)")
    parser.add_argument("--presets", nargs="*", default=["tiny", "re10k", "dl3dv"], choices=list(PRESETS),
                        help="presets to measure, smallest first so that CPU peak-RSS rows stay meaningful "
                        "(default: %(default)s)")
    parser.add_argument("--repeats", type=int, default=3,
                        help="timed forward passes per preset, after one warm-up; the fastest is shown "
                        "(default %(default)s)")
    return parser


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    device = resolve_device(args.device)
    print(f"device: {device}{' (' + torch.cuda.get_device_name(device) + ')' if device.type == 'cuda' else ''}")
    print(f"{'preset':8s} {'views':>5s} {'size':>9s} {'params':>10s} {'forward_s':>10s} {'peak_MB':>9s}")
    for name in args.presets:
        config = PRESETS[name]
        row = measure(config, device, args.repeats)
        print(f"{name:8s} {config.num_views:5d} {config.height:4d}x{config.width:<4d} {row['params']:10,d} "
              f"{row['forward_s']:10.4f} {row['peak_mb']:9.1f}")


if __name__ == "__main__":
    main()
