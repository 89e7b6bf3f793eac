"""Where the codec path loses quality: oracle swaps of the decoded feature and depth on held-out samples.

For each sample of an evaluation index (as ``codecsplat eval --index``), the target views are rendered from
Gaussians built five ways, and the mean PSNR (dB, on [0,1]-clipped images) of each is reported:

* ``codec-free``: GS head on (F_c, D_enc), the ceiling;
* ``decoder on F_c``: the decoder side (depth head, R_post, GS head) fed the encoder's F_c instead of F^_c;
* ``codec``: the real codec path at each lambda (F^_c, then depth head, R_post, GS head);
* ``codec, D_enc``: F^_c through R_post and the GS head with the encoder's depth instead of D^;
* ``F_c with D^``: the GS head on F_c (no R_post) with the decoder's depth D^ of that lambda;

plus the relative feature error |F^_c - F_c|^2 / |F_c|^2 at each lambda (eval-mode rounding, as coded).

    python -m train.codec_limits --data ../shared/data/scenes --index train/heldout_index/index-re10k.json \\
        --protocol re10k --samples 3 --out codec-limits.json
"""

from __future__ import annotations

import argparse
import json
import pathlib

import torch

from codecsplat_warp.device import resolve_device
from codecsplat_warp.eval.protocols import PROTOCOLS, Sample, find_scenes, index_samples
from codecsplat_warp.metrics.image import psnr
from codecsplat_warp.model import CodecSplat
from codecsplat_warp.model.pretrained import load_pretrained


@torch.no_grad()
def sample_scores(model: CodecSplat, sample: Sample, lambdas: list[float]) -> dict[str, float]:
    """PSNR (dB) of each oracle swap of the module docstring, and the feature errors, for one sample."""
    cameras, targets = sample.context_cameras, sample.target_cameras
    out = model(sample.context_images, cameras)
    f_c, d_enc, neighbours = out["F_c"], out["D_enc"], out["neighbours"]

    def score(gaussians) -> float:
        return float(psnr(model.render(gaussians, targets)["rgb"], sample.target_images).mean())

    def refined(feature, depth):
        return model.decode_gaussians(model.refine_post(feature, depth, cameras, neighbours), depth, cameras)

    scores = {"codec-free": score(out["gaussians"]),
              "decoder on F_c": score(model.decode_feature(f_c, cameras, neighbours)[2])}
    for lam in lambdas:
        f_hat = model.codec(f_c, lam).feature
        _, d_hat, gaussians = model.decode_feature(f_hat, cameras, neighbours)
        scores[f"codec λ={lam:g}"] = score(gaussians)
        scores[f"codec λ={lam:g}, D_enc"] = score(refined(f_hat, d_enc))
        scores[f"F_c with D^ of λ={lam:g}"] = score(model.decode_gaussians(f_c, d_hat, cameras))
        scores[f"feature error λ={lam:g}"] = float((f_hat - f_c).square().mean() / f_c.square().mean())
    return scores


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m train.codec_limits``."""
    parser = argparse.ArgumentParser(prog="python -m train.codec_limits", description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", help="model file (default: the shipped model)")
    parser.add_argument("--data", type=pathlib.Path, required=True, help="folder of scene folders")
    parser.add_argument("--index", type=pathlib.Path, required=True, help="evaluation index JSON")
    parser.add_argument("--protocol", choices=[p for p in PROTOCOLS if PROTOCOLS[p].width], default="re10k",
                        help="re10k: 256x256; dl3dv: 256x448 (HxW) (default %(default)s)")
    parser.add_argument("--samples", type=int, default=0,
                        help="only the first N samples of the index (default %(default)s: all)")
    parser.add_argument("--lambdas", default="16,1024", help="comma list of lambdas in [16, 1024] (default %(default)s)")
    parser.add_argument("--device", default="auto", help="cpu, cuda, cuda:N or auto (default %(default)s)")
    parser.add_argument("--out", type=pathlib.Path, required=True, help="JSON to write")
    return parser


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    device = resolve_device(args.device)
    model = load_pretrained(args.model, device=device)
    samples = index_samples(find_scenes(args.data), args.index, PROTOCOLS[args.protocol])
    samples = samples[:args.samples] if args.samples > 0 else samples
    lambdas = [float(v) for v in args.lambdas.split(",")]
    rows = [{"scene": s.scene, **sample_scores(model, s.to(device), lambdas)} for s in samples]
    means = {key: sum(r[key] for r in rows) / len(rows) for key in rows[0] if key != "scene"}
    args.out.write_text(json.dumps({"model": args.model or "shipped", "protocol": args.protocol,
                                    "index": str(args.index), "means": means, "samples": rows}, indent=1))
    for key, value in means.items():
        print(f"{key:<28}{value:9.3f}")


if __name__ == "__main__":
    main()
