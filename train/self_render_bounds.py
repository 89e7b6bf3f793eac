"""What limits the self-render PSNR of a CodecSplat model: its codec-free Gaussians rendered back into their own
context views, against the context images, on held-out samples.

For each sample of an evaluation index (as ``train.validate``), the mean PSNR (dB, on [0,1]-clipped images) over
the context views of five renders:

* ``as_predicted``: the model's Gaussians of all views rendered into each context view (the self-render PSNR of
  ``codecsplat eval`` and ``train.validate``);
* ``own_view``: only a view's own H*W Gaussians rendered into its own camera;
* ``pixel_colours_own``: ideal pixel-aligned Gaussians (:func:`ideal_pixel_gaussians`: at the pixel centres
  unprojected at the model's ``D_enc``, opacity 0.99, isotropic 0.5-pixel scale, the pixel's colour) of a view
  rendered into its own camera;
* ``pixel_colours_all``: those ideal Gaussians of all views rendered into each context view (what the other views'
  Gaussians at the model's depth cost);
* ``optimised_colours_own``: ``pixel_colours_own`` with the colours fitted by Adam to the own-view render
  (:func:`optimise_colours`): the bound of pixel-aligned Gaussians under the rasterizer's blur.

    python -m train.self_render_bounds --data ../shared/data/scenes --index train/heldout_index/index-re10k.json \\
        --protocol re10k --samples 3 --steps 60 --out self-render-bounds.json
"""

from __future__ import annotations

import argparse
import itertools
import json
import pathlib
from dataclasses import replace

import torch
from tqdm import tqdm

from codecsplat_warp.cameras import Cameras
from codecsplat_warp.device import resolve_device
from codecsplat_warp.errors import InputError
from codecsplat_warp.eval.protocols import PROTOCOLS, Sample, find_scenes, folder_index_plan
from codecsplat_warp.gaussians import SH_C0, Gaussians
from codecsplat_warp.metrics.image import psnr
from codecsplat_warp.model import CodecSplat, model_id
from codecsplat_warp.model.heads import pixel_footprint
from codecsplat_warp.model.pretrained import load_pretrained
from codecsplat_warp.ops.geometry import unproject

VARIANTS = ("as_predicted", "own_view", "pixel_colours_own", "pixel_colours_all", "optimised_colours_own")
"""The reported renders, in table order (see the module docstring)."""

SIZED_PROTOCOLS = tuple(name for name, protocol in PROTOCOLS.items() if protocol.width)
"""The protocols with a fixed image size and view count (re10k, dl3dv)."""


def ideal_pixel_gaussians(images: torch.Tensor, depth: torch.Tensor, cameras: Cameras, scale_px: float = 0.5,
                          opacity: float = 0.99) -> Gaussians:
    """One Gaussian per pixel centre, the best pixel-aligned Gaussians can do without offsets.

    Args:
        images: [V,3,H,W] colours in [0,1].
        depth: [V,H,W] camera-z depth (world units, > 0) at which each pixel centre is unprojected.
        cameras: the V cameras of the images.
        scale_px: isotropic standard deviation in pixels at the Gaussian's depth (world: depth / focal * scale_px,
            focal the mean of fx and fy).
        opacity: opacity of every Gaussian, in (0, 1).

    Returns:
        V*H*W Gaussians, view-major, float32, SH degree 0 with DC ``(rgb - 0.5) / SH_C0`` (renders the pixel's
        colour), identity rotations.
    """
    means = unproject(depth.float(), cameras).reshape(-1, 3)
    scales = (pixel_footprint(depth.float(), cameras) * scale_px).reshape(-1, 1).expand(-1, 3).contiguous()
    quats = torch.zeros(len(means), 4, device=means.device)
    quats[:, 0] = 1.0
    colours = images.float().permute(0, 2, 3, 1).reshape(-1, 1, 3)
    return Gaussians(means, quats, scales, torch.full((len(means),), opacity, device=means.device),
                     (colours - 0.5) / SH_C0)


def self_render_psnr(model: CodecSplat, gaussians: Gaussians, cameras: Cameras, images: torch.Tensor,
                     own_only: bool) -> float:
    """Mean PSNR (dB, clipped) over the V context views of ``gaussians`` rendered into ``cameras``.

    Args:
        gaussians: V*H*W Gaussians, view-major (H*W per context view).
        images: [V,3,H,W] context images in [0,1].
        own_only: render only view v's H*W Gaussians into camera v; else all Gaussians into every camera.
    """
    rgb = model.render_own_views(gaussians, cameras) if own_only else model.render(gaussians, cameras)["rgb"]
    return float(psnr(rgb, images).mean())


def optimise_colours(model: CodecSplat, gaussians: Gaussians, cameras: Cameras, images: torch.Tensor, steps: int,
                     lr: float = 0.05) -> Gaussians:
    """``gaussians`` with each view's SH DC colours fitted to its own image: ``steps`` Adam steps (learning rate
    ``lr``) on the MSE of the view's own Gaussians rendered into its own camera; everything else is kept.

    Args:
        gaussians: V*H*W Gaussians, view-major.
        images: [V,3,H,W] context images in [0,1].

    Returns:
        the Gaussians with the fitted DC colours (detached).
    """
    fitted = []
    for v, piece in enumerate(gaussians.split(cameras.num_views)):
        dc = piece.sh[:, :1].detach().clone().requires_grad_(True)
        optimiser = torch.optim.Adam([dc], lr=lr)
        camera, image = cameras.select([v]), images[v:v + 1]
        with torch.enable_grad():
            for _ in range(steps):
                rgb = model.render(replace(piece, sh=torch.cat([dc, piece.sh[:, 1:]], 1)), camera)["rgb"]
                loss = (rgb - image).square().mean()
                optimiser.zero_grad()
                loss.backward()
                optimiser.step()
        fitted.append(torch.cat([dc.detach(), piece.sh[:, 1:]], 1))
    return replace(gaussians, sh=torch.cat(fitted))


@torch.no_grad()
def sample_bounds(model: CodecSplat, sample: Sample, steps: int) -> dict[str, float]:
    """PSNR (dB) of each of :data:`VARIANTS` for one sample (codec-free forward of the model, float32)."""
    images, cameras = sample.context_images, sample.context_cameras
    out = model(images, cameras)
    ideal = ideal_pixel_gaussians(images, out["D_enc"], cameras)
    return {
        "as_predicted": self_render_psnr(model, out["gaussians"], cameras, images, own_only=False),
        "own_view": self_render_psnr(model, out["gaussians"], cameras, images, own_only=True),
        "pixel_colours_own": self_render_psnr(model, ideal, cameras, images, own_only=True),
        "pixel_colours_all": self_render_psnr(model, ideal, cameras, images, own_only=False),
        "optimised_colours_own": self_render_psnr(model, optimise_colours(model, ideal, cameras, images, steps),
                                                  cameras, images, own_only=True),
    }


def bounds_table(rows: list[dict], means: dict[str, float]) -> str:
    """The printed table: one line per sample and the means, a column per variant (dB)."""
    width = max(len(name) for name in VARIANTS) + 2
    lines = [f"{'scene':<28}" + "".join(f"{name:>{width}}" for name in VARIANTS)]
    lines += [f"{row['scene']:<28}" + "".join(f"{row[name]:>{width}.2f}" for name in VARIANTS) for row in rows]
    lines.append(f"{'mean':<28}" + "".join(f"{means[name]:>{width}.2f}" for name in VARIANTS))
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m train.self_render_bounds``."""
    parser = argparse.ArgumentParser(prog="python -m train.self_render_bounds", description=__doc__.split("\n\n")[0])
    parser.add_argument("--checkpoint", type=pathlib.Path,
                        help="model file written by save_pretrained (default: the shipped model)")
    parser.add_argument("--data", type=pathlib.Path, required=True, help="folder of held-out scene folders")
    parser.add_argument("--index", type=pathlib.Path, required=True,
                        help="evaluation index JSON of held-out samples, e.g. train/heldout_index/index-re10k.json")
    parser.add_argument("--protocol", default="re10k",
                        help=f"one of {', '.join(SIZED_PROTOCOLS)}: re10k: 256x256; dl3dv: 256x448 (HxW); the view "
                        "counts come from the index (default %(default)s)")
    parser.add_argument("--samples", type=int, default=0,
                        help="only the first N samples of the index (default %(default)s: all)")
    parser.add_argument("--steps", type=int, default=60,
                        help="Adam steps of the colour fit of optimised_colours_own (default %(default)s)")
    parser.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or auto (default %(default)s)")
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("self-render-bounds.json"),
                        help="JSON of the per-sample rows and the means (default %(default)s)")
    return parser


def check_options(args: argparse.Namespace) -> None:
    """InputError naming the option when ``--protocol``, ``--samples`` or ``--steps`` is out of range."""
    if args.protocol not in SIZED_PROTOCOLS:
        raise InputError(f"--protocol must be one of {', '.join(SIZED_PROTOCOLS)}, got {args.protocol!r}")
    if args.samples < 0:
        raise InputError(f"--samples must be >= 0 (0: all), got {args.samples}")
    if args.steps < 0:
        raise InputError(f"--steps must be >= 0, got {args.steps}")


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    check_options(args)
    device = resolve_device(args.device)
    model = load_pretrained(args.checkpoint, device=device)
    plan = folder_index_plan(find_scenes(args.data), args.index, PROTOCOLS[args.protocol])
    count = min(args.samples, len(plan.keys)) if args.samples else len(plan.keys)
    summary = {"model_id": model_id(model), "checkpoint": str(args.checkpoint or "shipped"), "device": str(device),
               "protocol": args.protocol, "index": str(args.index), "steps": args.steps, "samples": []}
    for sample in tqdm(itertools.islice(plan.load(0), count), total=count, desc="self-render bounds"):
        summary["samples"].append({"scene": sample.scene, **sample_bounds(model, sample.to(device), args.steps)})
        rows = summary["samples"]
        summary["means"] = {name: sum(row[name] for row in rows) / len(rows) for name in VARIANTS}
        args.out.write_text(json.dumps(summary, indent=1))  # after every sample: nothing lost on interruption
    print(bounds_table(summary["samples"], summary["means"]))


if __name__ == "__main__":
    main()
