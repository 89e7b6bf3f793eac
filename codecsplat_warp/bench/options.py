"""The command-line options of every ``codecsplat bench NAME`` and the named sizes they offer.

Torch-free, so that ``codecsplat bench NAME --help`` (and a bad option) answers at once: the command line
builds its parser from here and imports the measuring module ``codecsplat_warp.bench.NAME`` (its
``run(args) -> dict``) only to run it. The modules take their size tables from here.
"""

from __future__ import annotations

import argparse
import os
from dataclasses import dataclass


@dataclass(frozen=True)
class Workload:
    """A rasterizer workload: pixel-aligned Gaussians of ``views`` context views of ``height`` x ``width``,
    rendered into one target of that size (see :mod:`.raster`)."""

    name: str
    views: int
    height: int
    width: int


WORKLOADS = {
    "re10k": Workload("re10k", 2, 256, 256),
    "dl3dv": Workload("dl3dv", 8, 256, 448),
}
"""``bench raster``'s workloads: RE10K (131,072 Gaussians -> 256x256) and DL3DV (917,504 -> 256x448)."""


@dataclass(frozen=True)
class CodecShape:
    """A ``bench codec`` scene shape: ``views`` images of ``height`` x ``width`` for the model preset ``preset``,
    and the paper's encode and decode seconds at that shape."""

    name: str
    preset: str
    views: int
    height: int
    width: int
    paper_encode_s: float
    paper_decode_s: float


CODEC_SHAPES = {
    "re10k": CodecShape("re10k", "re10k", 2, 256, 256, 0.062, 0.059),
    "dl3dv": CodecShape("dl3dv", "dl3dv", 8, 256, 448, 0.267, 0.273),
}


@dataclass(frozen=True)
class GeometryShape:
    """A ``bench geometry`` shape: ``views`` cameras of ``image_h`` x ``image_w`` and ``channels`` features on a
    ``grid_h`` x ``grid_w`` grid."""

    name: str
    views: int
    channels: int
    grid_h: int
    grid_w: int
    image_h: int
    image_w: int


GEOMETRY_SHAPES = {
    "re10k-64": GeometryShape("re10k-64", 2, 64, 64, 64, 256, 256),
    "re10k-256": GeometryShape("re10k-256", 2, 64, 256, 256, 256, 256),
    "dl3dv-64": GeometryShape("dl3dv-64", 8, 64, 64, 112, 256, 448),
    "dl3dv-256": GeometryShape("dl3dv-256", 8, 64, 256, 448, 256, 448),
}

REPORT_KERNELS = ("unproject", "reproject_average", "plane_sweep_cost_volume", "rasterize")
"""The kernels ``bench report`` can cover."""

LEAVEOUT_DEFAULT_SCENES = 3
"""Scenes ``bench leaveout`` measures by default: evenly spread over the sorted scene folders of ``--data``."""


def codec_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--shapes", default=",".join(CODEC_SHAPES), help=f"comma list of {', '.join(CODEC_SHAPES)} (default %(default)s)")
    parser.add_argument("--reps", type=int, default=None, help="timed repetitions (default: 20 on CUDA, 3 on CPU)")
    parser.add_argument("--checkpoint", default=None, help="pretrained model file (default: seeded random weights)")
    parser.add_argument("--posterior-gain", type=float, default=10.0,
                        help="scale of the random model's posterior (realistic symbols without training; default %(default)g)")
    parser.add_argument("--no-cpu-check", action="store_true",
                        help="on CUDA, skip decoding each bitstream with a CPU copy of the model in this process "
                             "(for machines whose Warp cannot compile CPU kernels; use --write-bitstream and "
                             "--decode-bitstream on another machine instead)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the random model and inputs (default %(default)s)")
    parser.add_argument("--write-bitstream", default=None, metavar="DIR",
                        help="write each shape's bitstream and symbol record to DIR")
    parser.add_argument("--decode-bitstream", default=None, metavar="FILE",
                        help="only decode FILE (from --write-bitstream) on --device and check its symbols")


def crossdevice_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--write", metavar="DIR", help="encode and decode here (normally --device cuda) and write the "
                        "fixture to DIR")
    parser.add_argument("--check", metavar="DIR", help="decode DIR's bitstream here (normally --device cpu) and "
                        "compare with DIR's Gaussians and renders")
    parser.add_argument("--reps", type=int, default=None,
                        help="with --write: timed decodes per precision (default: 20 on CUDA, 3 on CPU)")


def extreme_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--cases", default="", help="comma list of substrings; run only the cases whose name has one (default: every case)")


def geometry_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--shapes", default=",".join(GEOMETRY_SHAPES),
                        help=f"comma list of {', '.join(GEOMETRY_SHAPES)} (default %(default)s)")
    parser.add_argument("--reps", type=int, default=None, help="timed repetitions (default: 30 on CUDA, 3 on CPU)")
    parser.add_argument("--validate", choices=("on", "off"), default="on",
                        help="finite/positive input checks (one host sync per call; on by default, as for users)")


def leaveout_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", default=os.environ.get("CODECSPLAT_DATA"),
                        help="folder of real scenes (default $CODECSPLAT_DATA)")
    parser.add_argument("--scenes", default=None,
                        help=f"comma list of scene folder names (default: {LEAVEOUT_DEFAULT_SCENES} spread over --data)")
    parser.add_argument("--checkpoint", default=None, help="pretrained model file (default: the shipped model)")
    parser.add_argument("--lambda", dest="lam", type=float, default=128.0, help="rate trade-off of the encodes (default %(default)g)")
    parser.add_argument("--reps", type=int, default=None, help="timed repetitions (default: 20 on CUDA, 3 on CPU)")
    parser.add_argument("--scale", type=float, default=None,
                        help="fraction of the raster scene's Gaussians kept in b and c (default: 1 on CUDA, "
                             "0.25 on CPU)")
    parser.add_argument("--max-views", type=int, default=None,
                        help="largest context view count of the 2..N encodes in d (default: 8 on CUDA, 4 on CPU)")
    parser.add_argument("--offscreen-workload", choices=sorted(WORKLOADS), default="re10k",
                        help="bench raster workload of the off-screen measurement b (default: re10k)")
    parser.add_argument("--quick", action="store_true", help="tiny sizes and one repetition (CI, CPU smoke test)")


def raster_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--workloads", default="re10k,dl3dv", help=f"comma list of {', '.join(WORKLOADS)} (default %(default)s)")
    parser.add_argument("--reps", type=int, default=None, help="timed repetitions (default: 30 on CUDA, 3 on CPU)")
    parser.add_argument("--scale", type=float, default=1.0, help="fraction of the Gaussians kept, 0 < scale <= 1 (default %(default)g)")
    parser.add_argument("--no-gsplat", action="store_true", help="skip gsplat even when it is importable")
    parser.add_argument("--kernels", type=int, default=0, metavar="N",
                        help="CUDA: also list the N kernels with the most GPU time per call, ours and gsplat's (default 0: none)")


RDO_PROFILE_PARTS = ("codec", "depth_head", "refine_post", "reprojection", "gs_head", "map_to_world", "rasterize",
                     "convolutions", "decoder_graph", "loss", "perceptual", "optimiser", "other")
"""The parts of ``bench rdo --profile``'s step: forward ranges of the model (``convolutions``: their backward
alone; ``decoder_graph``: the decoder's CUDA graphs, forward and backward replays, whose kernels the ranges inside
them do not see), and the backward of each (``other``: the backward nodes of none of them)."""


def rdo_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", default=os.environ.get("CODECSPLAT_DATA"),
                        help="folder of scene folders (default $CODECSPLAT_DATA)")
    parser.add_argument("--index", default=None, help="evaluation index JSON fixing each scene's context and target "
                        "frames (as codecsplat eval --index; default: one nearest-view split per scene)")
    parser.add_argument("--protocol", choices=("re10k", "dl3dv", "scene"), default="re10k",
                        help="re10k: 2 views 256x256; dl3dv: 8 views 256x448; scene: the stored size and the model's "
                        "view count (default %(default)s)")
    parser.add_argument("--scenes", default="", help="comma list of scene folder names to keep (default: all)")
    parser.add_argument("--checkpoint", default=None, help="pretrained model file (default: the shipped model)")
    parser.add_argument("--lambdas", default="16,128,1024", help="comma list of lambdas in [16, 1024] (default %(default)s)")
    parser.add_argument("--steps", default="0,25,100,400",
                        help="comma list of optimisation step counts, each its own run; 0 is the amortised encoder "
                        "(default %(default)s)")
    parser.add_argument("--refiner", default=None, metavar="PATH", help="a learned latent refiner file trained for the "
                        "model (train.learned_refiner): adds rows of its iterations at --refiner-steps, and with "
                        "--profile times its iteration against the Adam step (default: none)")
    parser.add_argument("--refiner-steps", default="", help="comma list of the refiner's iteration counts, each its "
                        "own run (with --refiner; default: none, which --refiner without --profile refuses)")
    parser.add_argument("--set", default="", help="comma list of key=value overriding RDOConfig fields, e.g. "
                        "learning_rate=0.02,cross_view_weight=1 (default: none, the tuned settings)")
    parser.add_argument("--lpips-weights", default=None, help="folder with lpips_{vgg,alex}.safetensors (default "
                        "$CODECSPLAT_LPIPS_WEIGHTS)")
    parser.add_argument("--plot", default=None, metavar="PNG", help="write the error-against-time plot here "
                        "(default: none)")
    parser.add_argument("--compare", default="", metavar="JSON[,JSON...]", help="with --plot: earlier bench rdo "
                        "results (their --out files, e.g. another model's) drawn beside this run's curves, dotted, "
                        "each labelled by its file name (default: none)")
    parser.add_argument("--pictures", default=None, metavar="DIR", help="write each sample's targets by every step "
                        "count to DIR/<scene>-lambda<L>.png (default: none)")
    parser.add_argument("--trajectory", action="store_true", help="also score the targets at every check of each "
                        "run (stored per row; the checks' scoring then counts in the encode seconds)")
    parser.add_argument("--workers", type=int, default=None,
                        help="worker processes the (sample, lambda) pairs are dealt over, round-robin over the "
                        "visible GPUs (default: one per visible GPU with --device cuda/auto, else 1); workers sharing "
                        "a GPU slow each other's encode seconds")
    parser.add_argument("--profile", action="store_true", help="profile one step instead (first sample, first lambda)")
    parser.add_argument("--profile-steps", type=int, default=20,
                        help="unprofiled steps whose median wall time --profile reports (default %(default)s)")


def report_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out-dir", default="bench-report", help="folder for report.json, report.md, pareto.png (default %(default)s)")
    parser.add_argument("--quick", action="store_true", help="a small set on tiny sizes (under 2 min on a 2-core CPU)")
    parser.add_argument("--devices", default=None, help="comma list of devices to compare (default: --device)")
    parser.add_argument("--kernels", default=",".join(REPORT_KERNELS), help=f"comma list of {', '.join(REPORT_KERNELS)} (default: all)")
    parser.add_argument("--sizes", default=None, help="comma list of scene sizes to keep (default: all of the mode)")
    parser.add_argument("--dtypes", default="float32,float64", help="comma list of float32, float64 (default %(default)s)")
    parser.add_argument("--reps", type=int, default=None,
                        help="timed repetitions (default: 20 on CUDA, 5 on CPU, 3 with --quick)")
    parser.add_argument("--checkpoint", default=None, help="pretrained codec model (default: the shipped one)")
    parser.add_argument("--no-codec", action="store_true", help="leave the codec out")


ARGUMENTS = {
    "codec": codec_arguments,
    "crossdevice": crossdevice_arguments,
    "extreme": extreme_arguments,
    "geometry": geometry_arguments,
    "leaveout": leaveout_arguments,
    "raster": raster_arguments,
    "rdo": rdo_arguments,
    "report": report_arguments,
}
"""``codecsplat bench NAME`` -> the function that adds NAME's options to its parser."""
