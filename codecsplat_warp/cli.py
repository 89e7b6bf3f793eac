"""The ``codecsplat`` command line.

Commands: ``demo`` (the shipped model on a real captured scene), ``encode`` (scene -> bitstream), ``decode``
(bitstream -> 3DGS PLY), ``render`` (bitstream -> frames, GIF or MP4), ``view`` (bitstream, PLY or scene folder ->
an interactive viewer in the browser), ``eval`` (the paper's tables with baselines), ``depth`` (multi-view stereo
depth maps of a posed scene), ``bench`` (benchmarks) and ``selfcheck`` (kernels against float64 references).

Exit codes: 0 success, 1 user error (bad arguments or input, reported as one line without a traceback),
2 internal error (a bug: the traceback is printed). Every command takes ``--device cpu|cuda|auto`` and
``--json`` (machine-readable result on stdout instead of the human summary). Progress bars go to stderr
when it is a terminal and never with ``--json``. Commands that run the model take ``--checkpoint PATH``
(default: the model shipped with the package).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import json
import math
import pathlib
import sys
import time
import traceback
from typing import Callable, Iterator

from .errors import CodecSplatError

EXIT_OK, EXIT_USER, EXIT_INTERNAL = 0, 1, 2

BENCHMARKS = {
    "codec": "codecsplat_warp.bench.codec",
    "crossdevice": "codecsplat_warp.bench.crossdevice",
    "extreme": "codecsplat_warp.bench.extreme",
    "geometry": "codecsplat_warp.bench.geometry",
    "leaveout": "codecsplat_warp.bench.leaveout",
    "raster": "codecsplat_warp.bench.raster",
    "rdo": "codecsplat_warp.bench.rdo",
    "report": "codecsplat_warp.bench.report",
}
"""``codecsplat bench NAME`` -> module with ``run(args) -> dict`` (its options: :mod:`.bench.options`)."""

USER_OS_ERRORS = (FileNotFoundError, PermissionError, IsADirectoryError, NotADirectoryError, FileExistsError)
"""File-system errors caused by the paths a user gave: reported as user errors."""


class UsageError(CodecSplatError):
    """The command line itself is wrong (unknown option, missing argument, bad value)."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # argparse would exit with 2, which we reserve for internal errors
        raise UsageError(f"{self.prog.split()[-1]}: {message}" if " " in self.prog else message)


def _common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--device", default="auto", help="cpu, cuda, cuda:N or auto: CUDA when torch sees a GPU "
                        "(default auto)")
    parser.add_argument("--json", action="store_true", help="print the result as JSON on stdout instead of the "
                        "summary (default off)")
    parser.add_argument("--threads", type=int, help="CPU threads for Warp and torch work (default: "
                        "$CODECSPLAT_THREADS, else every available core)")


def _model_options(parser: argparse.ArgumentParser) -> None:
    _common(parser)
    parser.add_argument("--checkpoint", help="pretrained model file (default: the model shipped with the package)")


def _number_list(kind, text: str, what: str) -> list:
    try:
        return [kind(part) for part in text.split(",") if part.strip()]
    except ValueError:
        raise UsageError(f"{what} must be a comma-separated list of numbers, got {text!r}") from None


def build_parser() -> argparse.ArgumentParser:
    from .bench.options import ARGUMENTS as BENCHMARK_ARGUMENTS
    from .choices import BASELINE_NAMES, DEMO_LAMBDAS, DEMO_SCENE, DEMO_SEED, DEMO_TARGET_VIEWS, IMAGE_CODEC_QUALITIES
    from .choices import DEMO_RDO_STEPS, PROCEDURAL, RDO_PERCEPTUAL_WEIGHT
    from .choices import FRAME_FORMATS as FORMATS
    from .choices import PAPER_LAMBDAS, PROTOCOL_NAMES as PROTOCOLS, RDO_PRESETS
    from .view.options import add_arguments as add_view_arguments

    parser = _Parser(prog="codecsplat", description="CodecSplat on NVIDIA Warp: KB-level feed-forward 3D Gaussian "
                                                    "splatting bitstreams, kernels, benchmarks and tools.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    demo = sub.add_parser("demo", help="shipped model + real captured scene -> bitstreams, renders, PLY, metrics")
    _model_options(demo)
    demo.add_argument("-o", "--out", default="codecsplat-demo", help="output folder (default ./codecsplat-demo)")
    demo.add_argument("--scene", default=DEMO_SCENE, help=f"{DEMO_SCENE} (photographs shipped with the package), "
                      f"{PROCEDURAL} (a procedural room) or a scene folder of your own (default {DEMO_SCENE})")
    demo.add_argument("--lambdas", default=",".join(f"{x:g}" for x in DEMO_LAMBDAS),
                      help="comma list of rate trade-offs in [16, 1024] (default %(default)s)")
    demo.add_argument("--seed", type=int, default=DEMO_SEED, help=f"seed of the {PROCEDURAL} room (default %(default)s)")
    demo.add_argument("--targets", type=int, default=DEMO_TARGET_VIEWS,
                      help="target views rendered and scored (default %(default)s)")
    demo.add_argument("--rdo-steps", type=int, default=DEMO_RDO_STEPS,
                      help="encoder rate-distortion optimisation steps of one more bitstream at the largest lambda, "
                      "shown beside the amortised ones; 0 leaves it out (default %(default)s)")
    demo.add_argument("--lpips-weights", help="folder with lpips_{vgg,alex}.safetensors (default $CODECSPLAT_LPIPS_WEIGHTS)")

    encode = sub.add_parser("encode", help="scene (any supported format) -> scene bitstream")
    _model_options(encode)
    encode.add_argument("scene", help="scene folder or pose file (cameras.json, transforms.json, LLFF, COLMAP, ...)")
    encode.add_argument("-o", "--out", required=True, help="bitstream file to write (e.g. scene.csplat)")
    encode.add_argument("--views", help="context view indices, e.g. 0,5 (default: the model's view count, evenly spread)")
    encode.add_argument("--lambda", dest="lam", type=float, default=128.0, help="rate trade-off in [16, 1024] (default 128)")
    encode.add_argument("--size", help="WIDTHxHEIGHT to resize and centre-crop to (default: the model's training size)")
    encode.add_argument("--preset", choices=list(RDO_PRESETS), default=None,
                        help="encoder rate-distortion optimisation: fast (the amortised encoder alone), medium or slow "
                        "(optimisation steps: medium 1.25, slow 5 x views squared; 25/160 steps for 2 views, with a "
                        "cross-view term, 80/320 for 8) (default: medium on a CUDA GPU, fast on the CPU; see docs/cli.md)")
    encode.add_argument("--steps", type=int, default=None,
                        help="optimisation steps, overriding the preset's count (default: the preset's)")
    encode.add_argument("--time-budget", type=float, default=None, metavar="SECONDS",
                        help="stop the optimisation after this many seconds, keeping the best bitstream so far; alone, "
                        "it optimises until the budget is spent (default: no limit)")
    encode.add_argument("--seed", type=int, default=0, help="seed of the optimisation's quantisation noise (default 0)")
    encode.add_argument("--perceptual", type=float, nargs="?", const=RDO_PERCEPTUAL_WEIGHT, default=0.0,
                        metavar="WEIGHT", help="add an LPIPS-VGG term of this weight to the optimisation's loss "
                        f"(alone: {RDO_PERCEPTUAL_WEIGHT:g}): sharper, perceptually closer renders for more bytes and a "
                        "little PSNR (needs optimisation steps and the LPIPS weights; see docs/cli.md) (default: off)")
    encode.add_argument("--lpips-weights", help="folder with lpips_vgg.safetensors, for --perceptual (default "
                        "$CODECSPLAT_LPIPS_WEIGHTS)")

    decode = sub.add_parser("decode", help="scene bitstream -> 3DGS PLY file")
    _model_options(decode)
    decode.add_argument("bitstream", help="bitstream file written by codecsplat encode")
    decode.add_argument("-o", "--out", required=True, help="PLY file to write")
    decode.add_argument("--prune", action="store_true", help="leave out Gaussians with opacity < 1/255 (and, with "
                                                              "--cameras, those outside every view of that file)")
    decode.add_argument("--cameras", help="with --prune: pose file of the views the PLY is meant for (cameras.json or "
                                          "any supported format, in the encoded scene's world frame)")

    render = sub.add_parser("render", help="scene bitstream -> rendered frames (PNG), GIF or MP4")
    _model_options(render)
    render.add_argument("bitstream", help="bitstream file written by codecsplat encode")
    cameras = render.add_mutually_exclusive_group(required=True)
    cameras.add_argument("--cameras", help="pose file of the views to render (cameras.json or any supported format), "
                                           "in the encoded scene's world frame; rendered at its image size")
    cameras.add_argument("--orbit", type=int, metavar="N", help="N views on a circle around the context viewpoint")
    render.add_argument("-o", "--out", required=True, help="output folder")
    render.add_argument("--format", choices=FORMATS, default="png", help="png frames, gif or mp4 (H.264, through imageio-ffmpeg) (default %(default)s)")
    render.add_argument("--fps", type=float, default=30.0, help="frames per second of gif/mp4 (default %(default)g)")

    view = sub.add_parser("view", help="bitstream, 3DGS PLY or scene folder -> an interactive viewer in the browser "
                          "(until Ctrl-C)")
    _model_options(view)
    add_view_arguments(view, tuple(RDO_PRESETS))

    evaluate = sub.add_parser("eval", help="the paper's Tables 1 and 2 (with baselines) on scene folders or chunks")
    _model_options(evaluate)
    evaluate.add_argument("--data", required=True, help="a scene folder, a folder of scene folders, or a folder of "
                          "RE10K/ACID/DL3DV .torch chunks with their index.json (needs --index)")
    evaluate.add_argument("--protocol", choices=list(PROTOCOLS), default="re10k",
                          help="re10k: 2 views 256x256, depth 0.5-100 on chunks; dl3dv: 8 views 256x448, depth 0.5-200 "
                          "on chunks; scene: stored size, model's views (scene folders keep their depth range) "
                          "(default %(default)s)")
    evaluate.add_argument("--lambdas", default=",".join(f"{x:g}" for x in PAPER_LAMBDAS), help="comma list of CodecSplat lambdas in [16, 1024] (default %(default)s)")
    evaluate.add_argument("--baselines", default=",".join(BASELINE_NAMES),
                          help=f"comma list of {', '.join(BASELINE_NAMES)}, or none (default %(default)s)")
    evaluate.add_argument("--scenes", default="", help="comma list of scene folder names (or chunk scene keys) to keep "
                          "(default: all)")
    evaluate.add_argument("--samples-per-scene", type=int, default=1, help="samples per scene without --index, their "
                          "anchor views spread over the scene (default %(default)s)")
    evaluate.add_argument("--index", help="evaluation index JSON (pixelSplat form: scene folder or chunk key -> context "
                          "and target frames, null to skip); fixes the samples, --samples-per-scene is then unused")
    evaluate.add_argument("--targets", type=int, help="target views per sample (default: the protocol's, 3)")
    evaluate.add_argument("--lpips-weights", help="folder with lpips_{vgg,alex}.safetensors (default $CODECSPLAT_LPIPS_WEIGHTS)")
    evaluate.add_argument("--webp-qualities", default=",".join(map(str, IMAGE_CODEC_QUALITIES["webp"])),
                          help="comma list of WebP qualities (0-100) of the WebP + codec-free baseline: the context "
                          "photographs as WebP files, the codec-free model on the decoded ones (default %(default)s)")
    evaluate.add_argument("--jpeg-qualities", default=",".join(map(str, IMAGE_CODEC_QUALITIES["jpeg"])),
                          help="comma list of JPEG qualities (1-100) of the JPEG + codec-free baseline (default "
                          "%(default)s)")
    evaluate.add_argument("--rdo-presets", help="comma list of encoder RDO presets that take steps (medium, slow): each "
                          "adds CodecSplat rows at every lambda, encoded with that rate-distortion optimisation "
                          "(default: none)")
    evaluate.add_argument("--rdo-steps", help="comma list of RDO step counts: each adds CodecSplat rows at every "
                          "lambda, optimised for that many steps (default: none)")
    evaluate.add_argument("--rdo-seed", type=int, default=0, help="seed of the RDO rows' quantisation noise "
                          "(default %(default)s)")
    evaluate.add_argument("--rdo-perceptual", help="comma list of LPIPS-VGG weights (> 0): each adds the rows of every "
                          "RDO preset and step count once more, optimised with that perceptual term in the loss "
                          "(needs the LPIPS weights) (default: none)")
    evaluate.add_argument("--png-sh-clusters", type=int, default=8192, help="K_SH, colour clusters of the PNG baseline (default %(default)s)")
    evaluate.add_argument("--kmeans-iterations", type=int, default=10, help="Lloyd steps of the PNG baseline's k-means (default %(default)s)")
    evaluate.add_argument("--size", help="WIDTHxHEIGHT instead of the protocol's image size (its depth range stays)")
    evaluate.add_argument("--restart", action="store_true",
                          help="start over instead of resuming the finished samples in OUT/results.json")
    evaluate.add_argument("--renders", action="store_true",
                          help="also write OUT/renders/SCENE-N.png per sample: its targets by every method beside the "
                          "ground truth")
    evaluate.add_argument("--mvs-depth", help="folder of reference depth, DIR/<scene>/depth.json (codecsplat depth): "
                          "scores the encoder and decoder depth of the context views")
    evaluate.add_argument("--workers", type=int, metavar="N",
                          help="worker processes to deal the scenes over (with RDO rows, each scene's base rows and "
                          "RDO rows apart, by their cost), on the GPUs in turn (--device cuda or "
                          "auto; several per GPU are allowed) or on the CPU (--device cpu); each writes OUT/shards/K/, "
                          "merged into OUT (default: one per visible GPU with --device cuda or auto, else 1: this "
                          "process alone)")
    evaluate.add_argument("-o", "--out", default="codecsplat-eval", help="output folder (default ./codecsplat-eval)")

    _depth_parser(sub)

    selfcheck = sub.add_parser("selfcheck", help="every kernel vs its float64 reference (--device auto: every device)")
    _common(selfcheck)

    bench = sub.add_parser("bench", help="benchmarks (tables on stdout, JSON with --out)")
    bench_sub = bench.add_subparsers(dest="benchmark", required=True, parser_class=_Parser)
    for name in BENCHMARKS:
        p = bench_sub.add_parser(name, help=f"{name} benchmark")
        _common(p)
        p.add_argument("--out", help="write the JSON result to this file")
        BENCHMARK_ARGUMENTS[name](p)
    return parser


def _depth_parser(sub) -> None:
    from .mvs_config import MVSConfig

    d = MVSConfig()
    depth = sub.add_parser("depth", help="multi-view stereo depth of every view of posed scenes -> 16-bit PNG depth "
                           "maps, masks, previews and depth.json")
    _common(depth)
    depth.add_argument("scenes", nargs="+", metavar="SCENE",
                       help="scene folder or pose file (cameras.json, transforms.json, LLFF, COLMAP, ...) with at least "
                       "3 posed views; several: one run over all of them")
    depth.add_argument("-o", "--out", required=True,
                       help="output folder (depth/, mask/, preview/, depth.json); with several scenes, OUT/<scene "
                       "folder name>/ each")
    depth.add_argument("--restart", action="store_true",
                       help="compute again a scene whose output already holds this run's depth.json (default: keep it)")
    depth.add_argument("--max-size", type=int, metavar="PX",
                       help="compute at the images resized so their long side is at most PX pixels (default: the "
                       "stored size)")
    depth.add_argument("--planes", type=int, default=d.num_planes,
                       help=f"sweep planes, uniform in inverse depth between near and far (default {d.num_planes})")
    depth.add_argument("--sources", type=int, default=d.num_sources,
                       help=f"source views per view, at most 8 (default {d.num_sources})")
    depth.add_argument("--window-radius", type=int, default=d.window_radius,
                       help=f"NCC window half-size in samples (default {d.window_radius}: 5x5 samples)")
    depth.add_argument("--window-step", type=int, default=d.window_step,
                       help=f"pixels between NCC window samples (default {d.window_step})")
    depth.add_argument("--min-ncc", type=float, default=d.min_ncc,
                       help=f"smallest aggregated NCC of a confident depth, in [-1, 1] (default {d.min_ncc:g})")
    depth.add_argument("--min-texture", type=float, default=d.min_texture,
                       help=f"smallest grey-level standard deviation (0-1 scale) of a confident window (default "
                       f"{d.min_texture:g})")
    depth.add_argument("--consistent-views", type=int, default=d.min_consistent_views,
                       help=f"source views that must agree with a depth to keep it (default {d.min_consistent_views})")
    depth.add_argument("--max-reprojection", type=float, default=d.max_reprojection_px,
                       help=f"largest reprojection error of an agreeing view, in pixels (default "
                       f"{d.max_reprojection_px:g})")
    depth.add_argument("--max-relative-depth", type=float, default=d.max_relative_depth,
                       help=f"largest relative depth difference of an agreeing view (default {d.max_relative_depth:g} "
                       "= 1 %%)")
    depth.add_argument("--allow-unmatched", action="store_true",
                       help="write an empty depth map for a view without a usable source view instead of failing")


# --------------------------------------------------------------------------------------------------
# Shared steps
def _use_threads(count: int | None) -> None:
    """Apply ``--threads`` (or its default) before a command runs (imports torch and Warp), and keep the memory the
    process frees unless ``$CODECSPLAT_KEEP_FREED_MEMORY`` is 0 (:func:`~codecsplat_warp.device.keep_freed_memory`)."""
    from .device import freed_memory_wanted, keep_freed_memory, set_cpu_threads

    if count is not None and count < 1:
        raise UsageError(f"--threads must be a positive integer, got {count}")
    set_cpu_threads(count)
    if freed_memory_wanted():
        keep_freed_memory()


def _device(args):
    from .device import resolve_device

    return resolve_device(args.device)


def _checkpoint(args) -> str | None:
    """``--checkpoint``, None for the model shipped with the package (UsageError when this installation has none)."""
    from .model import pretrained

    if args.checkpoint is None and not pretrained.DEFAULT_CHECKPOINT.is_file():
        raise UsageError(f"no model is shipped with this installation ({pretrained.DEFAULT_CHECKPOINT} is missing): "
                         "pass --checkpoint PATH (a file written by save_pretrained)")
    return args.checkpoint


def _load_model(args, device):
    from .model import pretrained

    return pretrained.load_pretrained(_checkpoint(args), device)


def _read_bitstream(path: str) -> bytes:
    file = pathlib.Path(path)
    if not file.is_file():
        raise UsageError(f"bitstream file {path} does not exist")
    return file.read_bytes()


def _emit(args, result: dict, lines: list[str]) -> None:
    print(json.dumps(result, indent=2) if args.json else "\n".join(lines))


@contextlib.contextmanager
def _progress(args, phases: list[str]) -> Iterator[Callable[[], None]]:
    """A progress bar over the named phases of a command (on a terminal's stderr, never with --json); yields
    ``advance()``, which marks the current phase done and names the next."""
    from tqdm.auto import tqdm

    quiet = True if args.json else None  # None: tqdm shows the bar only when stderr is a terminal
    with tqdm(total=len(phases), desc=args.command, unit="step", disable=quiet, leave=False) as bar:
        bar.set_postfix_str(phases[0])

        def advance() -> None:
            bar.update(1)
            if bar.n < len(phases):
                bar.set_postfix_str(phases[bar.n])

        yield advance


def _parts_table(parts: dict[str, int]) -> list[str]:
    return [f"  {name:<10s}{count:>10,d} B" for name, count in parts.items()]


# --------------------------------------------------------------------------------------------------
# Commands
def _cmd_demo(args) -> int:
    from .demo import DemoConfig, run_demo
    from .eval.report import format_bytes

    device = _device(args)
    model = _load_model(args, device)
    config = DemoConfig(out=args.out, scene=args.scene, lambdas=tuple(_number_list(float, args.lambdas, "--lambdas")),
                        seed=args.seed, target_views=args.targets, rdo_steps=args.rdo_steps,
                        lpips_weights=args.lpips_weights,
                        progress=not args.json)
    summary = run_demo(model, config, device)
    lines = [f"demo scene {summary['scene']} ({summary['image_size'][0]}x{summary['image_size'][1]}, "
             f"{len(summary['context_views'])} context + {len(summary['target_views'])} target views) on {device}:"]
    for row in summary["rows"]:
        quality = "  ".join(f"{k} {row[k]:.3f}" for k in ("psnr", "ssim", "lpips_vgg", "lpips_alex") if k in row)
        lines.append(f"  {row['setting']:<22s}{format_bytes(row['bytes']):>12s}  {quality}  "
                     f"encode {row['encode_s']:.2f} s, decode {row['decode_s']:.2f} s")
    ply = summary["ply"]
    lines += [f"PLY (λ={ply['lambda']:g}): {ply['gaussians']:,d} Gaussians, {ply['pruned']:,d} pruned "
              "(opacity < 1/255 or seen by no demo view)",
              f"LPIPS: {summary['lpips']}",
              f"wrote {len(summary['files'])} files to {args.out}/ in {summary['seconds']:.1f} s "
              "(comparison.png, rate_distortion.png, scene.ply, summary.json, ...)"]
    _emit(args, summary, lines)
    return EXIT_OK


def _cmd_encode(args) -> int:
    import torch

    from .codec import bytes_report, check_lambda
    from .data import load_scene
    from .data.preprocess import DatasetConfig, preprocess_scene
    from .export.files import write_bytes
    from .measure import timed

    _check_rdo_arguments(args.steps, args.time_budget)
    device = _device(args)
    lam = check_lambda(args.lam)
    size = _size(args.size) if args.size else None
    preset = args.preset or default_preset(device)
    perceptual = _perceptual_network(args.perceptual, args.lpips_weights, preset, args.steps, args.time_budget, device)
    start = time.perf_counter()
    with _progress(args, ["scene", "model", "encode", "write"]) as advance:
        scene = load_scene(args.scene)
        advance()
        model = _load_model(args, device)
        views = _context_views(args.views, scene.num_views, model.config.num_views)
        width, height = size or (model.config.width, model.config.height)
        scene = preprocess_scene(scene, DatasetConfig(width=width, height=height, near=0.0, far=0.0), frames=views,
                                 use_config_depth_range=False)
        images = (scene.images.float() / 255.0).to(device)
        cameras = scene.cameras.to(device, torch.float32)
        load_s = time.perf_counter() - start
        advance()
        rdo_settings = {"perceptual_weight": args.perceptual} if perceptual is not None else None
        encoded, encode_s = timed(lambda: model.encode_scene(images, cameras, lam, preset=preset, steps=args.steps,
                                                             time_budget=args.time_budget, seed=args.seed,
                                                             progress=not args.json, rdo_settings=rdo_settings,
                                                             perceptual=perceptual), device)
        advance()
        write_bytes(args.out, encoded.data)
        advance()
    parts = bytes_report(encoded.data)
    rdo = encoded.rdo.to_dict() if encoded.rdo is not None else None
    result = {"output": args.out, "scene": str(args.scene), "views": views, "width": width, "height": height,
              "lambda": lam, "preset": preset, "perceptual": args.perceptual, "rdo": rdo, "bytes": parts,
              "bits_per_pixel": 8 * parts["total"] / (len(views) * width * height),
              "seconds": {"load": load_s, "encode": encode_s}}
    lines = [f"encoded {len(views)} views {views} of {args.scene} at {width}x{height}, λ={lam:g} -> {args.out}",
             *_parts_table(parts), f"  {result['bits_per_pixel']:.4f} bits per pixel"]
    if rdo is not None:
        first, kept = rdo["checks"][0], next(c for c in rdo["checks"] if c["step"] == rdo["best_step"])
        stopped = {"steps": "", "time": " (time budget spent)", "interrupted": " (stopped by Ctrl-C)",
                   "non-finite": " (stopped: the loss was no longer finite)"}[rdo["stopped"]]
        label = preset if args.steps is None else f"--steps {args.steps}"
        label += f", LPIPS-VGG {args.perceptual:g}" if perceptual is not None else ""
        lines.append(f"RDO ({label}): {rdo['steps']} steps in {rdo['seconds']:.2f} s"
                     f"{stopped}; kept step {rdo['best_step']}: context views {first['psnr']:.2f} -> "
                     f"{kept['psnr']:.2f} dB")
    lines.append(f"load + preprocess {load_s:.2f} s, encode {encode_s:.2f} s on {device}")
    _emit(args, result, lines)
    return EXIT_OK


def _perceptual_network(weight: float, lpips_weights: str | None, preset: str, steps: int | None,
                        time_budget: float | None, device):
    """The LPIPS-VGG network of ``codecsplat encode --perceptual`` on ``device`` (None for weight 0), before any
    other work. UsageError for a weight < 0 or one without optimisation steps (``fast`` and no ``--steps`` or
    budget); InputError without the LPIPS weights."""
    from .metrics.lpips import LPIPS
    from .model.rdo import rdo_config

    if not (math.isfinite(weight) and weight >= 0):
        raise UsageError(f"--perceptual must be a weight >= 0, got {weight:g}")
    if weight == 0:
        return None
    if not rdo_config(preset, steps, time_budget).optimises:
        raise UsageError("--perceptual weighs a term of the encoder's optimisation: give --preset medium or slow, "
                         "--steps N or --time-budget SECONDS")
    return LPIPS("vgg", lpips_weights).to(device)


def _check_rdo_arguments(steps: int | None, time_budget: float | None) -> None:
    """UsageError for ``--steps`` < 0 or a ``--time-budget`` that is not a number of seconds > 0 (before any work)."""
    if steps is not None and steps < 0:
        raise UsageError(f"--steps must be >= 0, got {steps}")
    if time_budget is not None and not (math.isfinite(time_budget) and time_budget > 0):
        raise UsageError(f"--time-budget must be a number of seconds > 0, got {time_budget:g}")


def default_preset(device) -> str:
    """The encode command's RDO preset without ``--preset``: ``medium`` on a CUDA GPU (most of ``slow``'s gain in a
    quarter of its time), ``fast`` on the CPU (each optimisation step takes seconds there)."""
    return "medium" if device.type == "cuda" else "fast"


def _context_views(text: str | None, available: int, default_count: int) -> list[int]:
    """Context view indices from ``--views`` or ``default_count`` evenly spread over the scene."""
    if text is None:
        if available < default_count:
            raise UsageError(f"the scene has {available} views, the model needs {default_count}: pass --views")
        return sorted({round(i * (available - 1) / (default_count - 1)) for i in range(default_count)})
    views = _number_list(int, text, "--views")
    bad = [v for v in views if not 0 <= v < available]
    if bad:
        raise UsageError(f"--views {bad} out of range: the scene has views 0..{available - 1}")
    if len(set(views)) != len(views) or len(views) < 2:
        raise UsageError(f"--views needs at least 2 distinct views, got {views}")
    return views


def _size(text: str) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise UsageError(f"--size must be WIDTHxHEIGHT, e.g. 256x256, got {text!r}") from None
    if width < 4 or height < 4 or width % 4 or height % 4:
        raise UsageError(f"--size sides must be positive multiples of 4, got {width}x{height}")
    return width, height


def _cmd_decode(args) -> int:
    import torch

    from .data import load_scene
    from .export.ply import write_ply
    from .measure import timed
    from .model.prune import prune_gaussians

    if args.cameras and not args.prune:
        raise UsageError("--cameras only chooses what --prune leaves out: pass --prune too")
    device = _device(args)
    data = _read_bitstream(args.bitstream)
    targets = load_scene(args.cameras).cameras.to(device, torch.float32) if args.cameras else None
    with _progress(args, ["model", "decode", "prune", "write"]) as advance:
        model = _load_model(args, device)
        advance()
        scene, decode_s = timed(lambda: model.decode_scene(data), device)
        advance()
        gaussians, report, prune_s = scene.gaussians, None, 0.0
        if args.prune:
            (gaussians, report), prune_s = timed(lambda: prune_gaussians(scene.gaussians, targets), device)
        advance()
        start = time.perf_counter()
        size = write_ply(args.out, gaussians)
        write_s = time.perf_counter() - start
        advance()
    result = {"output": args.out, "gaussians": len(gaussians), "pruned": report.pruned if report else 0,
              "prune": report.to_dict() if report else None, "ply_bytes": size, "bitstream_bytes": len(data),
              "lambda": scene.lam, "views": scene.cameras.num_views,
              "seconds": {"decode": decode_s, "prune": prune_s, "write": write_s}}
    lines = [f"decoded {args.bitstream} ({len(data):,d} B, λ={scene.lam:g}, {scene.cameras.num_views} views) on {device}",
             f"wrote {len(gaussians):,d} Gaussians to {args.out} ({size:,d} B)"]
    if report:
        lines.append(_prune_line(report, f"every view of {args.cameras}" if args.cameras else None))
    lines.append(f"decode {decode_s:.2f} s, prune {prune_s:.2f} s, write {write_s:.2f} s")
    _emit(args, result, lines)
    return EXIT_OK


def _prune_line(report, views: str | None) -> str:
    """One line saying what pruning left out (``views``: what the frustum test used, None for opacity only)."""
    line = f"left out {report.pruned:,d} of {report.total:,d} Gaussians: {report.transparent:,d} with opacity < 1/255"
    return line + (f", {report.outside_frusta:,d} outside {views}" if views else "")


def _cmd_render(args) -> int:
    import numpy as np
    import torch

    from .data import load_scene
    from .export.video import MP4_MISSING, mp4_plugin, orbit_cameras, to_uint8_frames, write_frames
    from .measure import timed
    from .model.prune import prune_gaussians

    if args.format == "mp4" and mp4_plugin() is None:
        raise UsageError(MP4_MISSING)
    if args.orbit is not None and args.orbit < 1:
        raise UsageError(f"--orbit needs at least 1 view, got {args.orbit}")
    if not args.fps > 0:
        raise UsageError(f"--fps must be > 0, got {args.fps}")
    device = _device(args)
    data = _read_bitstream(args.bitstream)
    posed = load_scene(args.cameras).cameras if args.cameras else None
    count = posed.num_views if posed is not None else args.orbit
    with _progress(args, ["model", "decode", "prune", *(f"frame {i}" for i in range(count)), "write"]) as advance:
        model = _load_model(args, device)
        advance()
        scene = model.decode_scene(data)
        cameras = posed if posed is not None else orbit_cameras(scene.cameras, scene.depth, count)
        cameras = cameras.to(device, torch.float32)
        advance()
        (gaussians, report), prune_s = timed(lambda: prune_gaussians(scene.gaussians, cameras), device)
        advance()
        frames = []
        start = time.perf_counter()
        with torch.no_grad():
            for view in range(count):
                frames.append(to_uint8_frames(model.render(gaussians, cameras.select([view]))["rgb"])[0])
                advance()
        render_s = time.perf_counter() - start
        paths = write_frames(args.out, np.stack(frames), args.format, args.fps)
        advance()
    result = {"output": [str(p) for p in paths], "frames": count, "width": cameras.width,
              "height": cameras.height, "format": args.format, "prune": report.to_dict(),
              "seconds": {"prune": prune_s, "render": render_s}}
    lines = [f"rendered {count} frames at {cameras.width}x{cameras.height} in {render_s:.2f} s on {device}",
             _prune_line(report, "every frame") + f" (in {prune_s:.2f} s)",
             f"wrote {paths[0]}" if len(paths) == 1 else f"wrote {len(paths)} PNG frames to {args.out}/"]
    _emit(args, result, lines)
    return EXIT_OK


def _cmd_view(args) -> int:
    from .view.serve import ViewConfig, serve

    device = _device(args)
    config = ViewConfig(input=args.input, host=args.host, port=args.port, lam=args.lam, preset=args.preset,
                        views=args.views, size=_size(args.size) if args.size else None, cameras=args.cameras,
                        max_side=args.max_frame_side, progress=not args.json)

    def announce(result: dict, lines: list[str]) -> None:
        _emit(args, result, lines)
        sys.stdout.flush()

    serve(config, device, _checkpoint(args), _context_views, default_preset(device), announce)
    return EXIT_OK


def _cmd_eval(args) -> int:
    from .eval.evaluate import BASELINE_NAMES, EvalConfig
    from .eval.shards import evaluate_sharded, format_worker_seconds, shard_devices

    baselines = () if args.baselines.strip().lower() == "none" else tuple(
        b.strip() for b in args.baselines.split(",") if b.strip())
    unknown = sorted(set(baselines) - set(BASELINE_NAMES))
    if unknown:
        raise UsageError(f"--baselines: unknown {', '.join(unknown)}; choose from {', '.join(BASELINE_NAMES)} or none")
    device = _device(args)
    workers = shard_devices(args.device, args.workers)
    checkpoint = _checkpoint(args)
    config = EvalConfig(data=args.data, out=args.out, protocol=args.protocol,
                        lambdas=tuple(_number_list(float, args.lambdas, "--lambdas")), baselines=baselines,
                        samples_per_scene=args.samples_per_scene, target_views=args.targets,
                        lpips_weights=args.lpips_weights, png_sh_clusters=args.png_sh_clusters,
                        kmeans_iterations=args.kmeans_iterations, progress=not args.json,
                        scenes=tuple(name.strip() for name in args.scenes.split(",") if name.strip()),
                        index=args.index, size=_size(args.size) if args.size else None, resume=not args.restart,
                        renders=args.renders, mvs_depth=args.mvs_depth,
                        webp_qualities=tuple(_number_list(int, args.webp_qualities, "--webp-qualities")),
                        jpeg_qualities=tuple(_number_list(int, args.jpeg_qualities, "--jpeg-qualities")),
                        rdo_presets=tuple(name.strip() for name in (args.rdo_presets or "").split(",") if name.strip()),
                        rdo_steps=tuple(_number_list(int, args.rdo_steps or "", "--rdo-steps")), rdo_seed=args.rdo_seed,
                        rdo_perceptual=tuple(_number_list(float, args.rdo_perceptual or "", "--rdo-perceptual")))
    result = evaluate_sharded(config, checkpoint, device, workers, threads=args.threads)
    lines = [f"{len(result['scenes'])} scene(s), {args.protocol} protocol, {result['machine']}",
             "", "Table 1", result["tables"]["table1"], "", "Table 2 (seconds)", result["tables"]["table2"], "",
             f"LPIPS: {result['lpips']}"]
    if result["skipped"]:
        lines.append("skipped: " + ", ".join(s["scene"] for s in result["skipped"]))
    if "worker_seconds" in result:  # dealt over worker processes
        lines.append(format_worker_seconds(result["wall_s"], result["worker_seconds"], "samples"))
    lines.append("wrote " + ", ".join(result["files"].values()))
    _emit(args, result, lines)
    return EXIT_OK


def _cmd_depth(args) -> int:
    from .depth import DepthRun, finished_run, write_scene_depth
    from .mvs_config import MVSConfig

    if args.max_size is not None and args.max_size < 16:
        raise UsageError(f"--max-size must be at least 16 pixels, got {args.max_size}")
    config = MVSConfig(num_planes=args.planes, num_sources=args.sources, window_radius=args.window_radius,
                       window_step=args.window_step, min_ncc=args.min_ncc, min_texture=args.min_texture,
                       min_consistent_views=args.consistent_views, max_reprojection_px=args.max_reprojection,
                       max_relative_depth=args.max_relative_depth, allow_unmatched=args.allow_unmatched)
    device = _device(args)
    start = time.perf_counter()
    runs = [DepthRun(scene=scene, out=out, config=config, max_size=args.max_size, progress=not args.json)
            for scene, out in _depth_outputs(args.scenes, args.out)]  # fmt: skip
    results = []
    for run in runs:
        done = None if args.restart else finished_run(run)
        results.append(done or write_scene_depth(run, device))
    seconds = time.perf_counter() - start
    views = sum(len(r["frames"]) for r in results)
    coverage = sum(f["coverage"] for r in results for f in r["frames"]) / views
    summary = {"scenes": results, "views": views, "mean_coverage": coverage, "seconds": seconds,
               "seconds_per_view": seconds / views, "device": str(device)}
    lines = [f"{'scene':<28s}{'views':>6s}{'size':>10s}{'coverage':>10s}{'seconds':>9s}"]
    for r in results:
        scene_coverage = sum(f["coverage"] for f in r["frames"]) / len(r["frames"])
        timing = "kept" if r["resumed"] else f"{r['seconds']:.2f}"
        lines.append(f"{pathlib.Path(r['output']).name:<28s}{len(r['frames']):>6d}{r['width']:>5d}x{r['height']:<4d}"
                     f"{scene_coverage:>10.1%}{timing:>9s}")
        unmatched = [f["file"] for f in r["frames"] if not f["sources"]]
        if unmatched:
            lines.append(f"  no usable source view, empty depth map: {', '.join(unmatched)}")
    lines += [f"{'all':<28s}{views:>6d}{'':>10s}{coverage:>10.1%}{seconds:>9.2f}",
              f"{seconds / views:.3f} s per view on {device}; wrote {args.out}/"]
    _emit(args, summary, lines)
    return EXIT_OK


def _depth_outputs(scenes: list[str], out: str) -> list[tuple[str, str]]:
    """(scene, output folder) of each scene: ``out`` itself for one scene, ``out/<scene folder name>`` for several."""
    if len(scenes) == 1:
        return [(scenes[0], out)]
    names = [_scene_folder_name(scene) for scene in scenes]
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise UsageError(f"several scenes share the folder name {', '.join(repeated)}: their outputs would collide")
    return [(scene, str(pathlib.Path(out) / name)) for scene, name in zip(scenes, names)]


def _scene_folder_name(scene: str) -> str:
    """The name of a scene's folder (of the pose file's folder when given a file)."""
    path = pathlib.Path(scene).resolve()
    return path.parent.name if path.is_file() else path.name


def _cmd_selfcheck(args) -> int:
    from .device import available_devices, resolve_device
    from .selfcheck import run_selfcheck

    devices = available_devices() if args.device == "auto" else [resolve_device(args.device)]
    result = run_selfcheck(devices, progress=not args.json)
    if args.json:
        print(json.dumps({k: v for k, v in result.items() if k != "table"}, indent=2))
    else:
        print(result["table"])
        if args.device == "auto" and len(devices) == 1:
            print("\nno CUDA GPU found: the CPU was checked alone")
        print("\nselfcheck: " + ("all kernels agree with their float64 references" if result["ok"] else "FAILED"))
    return EXIT_OK if result["ok"] else EXIT_INTERNAL


def _cmd_bench(args) -> int:
    from .export.files import write_json
    from .device import resolve_device

    args.device = str(resolve_device(args.device))
    result = importlib.import_module(BENCHMARKS[args.benchmark]).run(args)
    if args.out:
        write_json(args.out, result)
    if args.json:
        print(json.dumps(result, indent=2))
    return EXIT_OK if result.get("passed", True) else EXIT_USER  # a benchmark with checks (extreme) failed them


COMMANDS = {"demo": _cmd_demo, "encode": _cmd_encode, "decode": _cmd_decode, "render": _cmd_render,
            "view": _cmd_view, "eval": _cmd_eval, "depth": _cmd_depth, "selfcheck": _cmd_selfcheck, "bench": _cmd_bench}


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``codecsplat`` console script; returns the exit code."""
    try:
        args = build_parser().parse_args(argv)
        _use_threads(args.threads)
        return COMMANDS[args.command](args)
    except CodecSplatError as exc:
        print(f"codecsplat: error: {exc}", file=sys.stderr)
        return EXIT_USER
    except USER_OS_ERRORS as exc:
        print(f"codecsplat: error: {exc}", file=sys.stderr)
        return EXIT_USER
    except KeyboardInterrupt:
        print("codecsplat: interrupted", file=sys.stderr)
        return 130
    except Exception:  # noqa: BLE001 - anything else is a bug: show it
        traceback.print_exc()
        return EXIT_INTERNAL


if __name__ == "__main__":
    sys.exit(main())
