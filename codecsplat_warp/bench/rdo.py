"""``codecsplat bench rdo``: encoder-side rate-distortion optimisation, error against encode time, and its step profile.

**Curve** (default): for every sample of ``--data`` (scene folders; ``--index`` fixes the samples, as for
``codecsplat eval``), every lambda of ``--lambdas`` and every step count of ``--steps`` (each an independent run
with its own learning-rate schedule; 0 is the amortised encoder), the scene is encoded with
``model.encode_scene(..., steps=N)``, decoded with the unchanged ``decode_scene`` and rendered into the target
views. Per point: encode seconds (the whole encode: backbone, optimisation, coding; CUDA synchronised), bitstream
bytes, target PSNR, SSIM and LPIPS-VGG/Alex (when weights are found), and the context views' PSNR of the decoded
scene. Copy-the-nearest-view and the codec-free model are scored once per sample as references. The table gives
the means over samples per (lambda, steps); ``rdo_curve.png`` plots target PSNR, LPIPS-VGG and KiB against mean
encode seconds, a line per lambda. With ``--workers`` the (sample, lambda) pairs are dealt over processes (one per
visible GPU by default), and each worker's seconds of start, loading and work are printed (``worker_seconds``).
``--set key=value,...`` overrides fields of :class:`~codecsplat_warp.model.rdo.RDOConfig` (learning rate, loss
weights, precision) for experiments, and ``--pictures DIR`` writes one picture per sample and lambda: the targets'
truth, copy-nearest, codec-free and every step count. ``--refiner PATH`` (a learned refiner trained for the model,
:mod:`codecsplat_warp.model.rdo.refiner`) adds rows of method ``refiner`` at each iteration count of
``--refiner-steps``: the same encode with the refiner's iterations in place of Adam's steps, to compare at equal
encode seconds.

**Profile** (``--profile``): one step of the optimisation broken into the codec, the depth head, R_post (the
reprojection apart), the GS head, the 2D->3D map (unprojection), the rasterizer, the loss and the optimiser, each
forward and backward, from ``torch.profiler`` on the first sample at the first lambda: CPU time per part on the
CPU, GPU kernel time per part on CUDA (beside the step's wall time, whose excess over the kernels is launch,
synchronisation and Python time). On CUDA the decoder runs as CUDA graphs (the default): its parts then read 0
and its kernels, forward and backward, are the part ``decoder_graph``. The median wall time of ``--profile-steps``
unprofiled steps comes first; a second table lists the step's costliest GPU kernels (CUDA) or operators (CPU).
With ``--refiner`` the median wall time of as many refiner iterations follows, and its ratio to the Adam step's.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import statistics
import sys
import time

import torch

from ..device import cudnn_autotuned
from ..errors import DataError, InputError
from ..eval.protocols import (PROTOCOLS, Sample, eager_plan, find_scenes, folder_index_plan, nearest_context_images,
                              scene_samples, select_scenes)
from ..eval.report import plot_comparison, pyplot, save_figure
from ..eval.shards import (format_worker_seconds, report_progress, run_sharded, shard_devices, split_round_robin,
                           worker_seconds)
from ..export.video import to_uint8_frames
from ..measure import format_table, machine_name, synchronize
from ..metrics import LPIPS
from ..metrics.image import ImageMetrics
from ..model import pretrained
from ..model.codecsplat import model_id
from ..model.rdo import (LatentRefiner, RDOConfig, decoder_fixed, latent_optimiser, load_refiner, psnr_of_mse,
                         rdo_config, rdo_step, rdo_target, refiner_step, start_variables, step_decoder)
from .options import RDO_PROFILE_PARTS

METRICS = ("psnr", "ssim", "lpips_vgg", "lpips_alex")
CODED_METHODS = ("codecsplat", "refiner")
"""The rows' methods that code the scene (the others are references): Adam's steps and a refiner's iterations."""


def run(args: argparse.Namespace) -> dict:
    device = torch.device(args.device)
    settings = parse_settings(args.set)
    rdo_config("fast", None, None, 0, **settings)  # bad settings fail before any work
    steps = _int_list(args.steps, "--steps")
    lambdas = [float(x) for x in args.lambdas.split(",") if x.strip()]
    refiner_steps = _int_list(args.refiner_steps, "--refiner-steps") if args.refiner else []
    if not lambdas or not steps or any(n < 0 for n in steps + refiner_steps):
        raise InputError("--lambdas and --steps need at least one value each, steps >= 0")
    compared = _compared_results(args.compare, args.plot)  # unreadable files fail before any work
    if args.refiner and not refiner_steps and not args.profile:
        raise InputError("--refiner needs --refiner-steps (its iteration counts, each its own run)")
    workers = [device] if args.profile else shard_devices(args.device, args.workers)
    model = pretrained.load_pretrained(args.checkpoint, device)
    refiner = load_refiner(args.refiner, model_id(model), device)[0] if args.refiner else None  # fails before work
    samples = _samples(args, model)
    result = {"device": str(device), "machine": machine_name(device), "protocol": args.protocol,
              "settings": settings, "lambdas": lambdas, "steps": steps, "workers": len(workers)}
    if args.refiner:
        result.update(refiner=args.refiner, refiner_steps=refiner_steps)
    if args.profile:
        perceptual = _perceptual(settings, args.lpips_weights, device)
        result["profile"] = profile_step(model, samples[0], lambdas[0], settings, args.profile_steps, device,
                                         perceptual, refiner)
        if not args.json:
            print(format_profile(result["profile"]))
        return result
    del model  # each worker loads its own
    units = [(s, k) for s in range(len(samples)) for k in range(len(lambdas))]
    parts = [_worker_part(samples, part) for part in split_round_robin(units, min(len(workers), len(units)))]
    started = time.time()
    job = {"checkpoint": args.checkpoint, "lambdas": lambdas, "steps": steps, "settings": settings,
           "refiner": args.refiner, "refiner_steps": refiner_steps,
           "lpips_weights": args.lpips_weights, "pictures": args.pictures, "trajectory": args.trajectory,
           "started": started}
    results = run_sharded(bench_samples, [(job, part) for part in parts], workers[:len(parts)],
                          progress=not args.json, desc="bench rdo", unit="sample-lambda")
    rows = sorted((row for rows, _, _ in results for row in rows), key=_row_order(samples, lambdas))
    result.update(rows=rows, summary=summarize(rows), lpips=results[0][1], wall_s=time.time() - started,
                  worker_seconds=[timing for _, _, timing in results])
    if not args.json:
        print(format_summary(result["summary"], result["machine"]))
        print(format_worker_seconds(result["wall_s"], result["worker_seconds"], "sample-lambda pairs"))
    if args.plot:
        plot_curve(result["summary"], pathlib.Path(args.plot), compared)
    return result


def _compared_results(text: str, plot: str | None) -> list[tuple[str, list[dict]]]:
    """``--compare``'s files as (label: the file name without ``.json``, summary) pairs. Raises InputError without
    ``--plot``, and DataError for a file that is missing or not a bench rdo result."""
    paths = [pathlib.Path(part.strip()) for part in text.split(",") if part.strip()]
    if paths and not plot:
        raise InputError("--compare draws earlier results beside this run's on --plot: give --plot PNG too")
    compared = []
    for path in paths:
        try:
            summary = json.loads(path.read_text()).get("summary")
        except (OSError, ValueError, AttributeError) as error:
            raise DataError(f"--compare {path}: cannot read it as a bench rdo result (its --out JSON): {error}") \
                from None
        if not isinstance(summary, list) or not all(isinstance(e, dict) and "method" in e for e in summary):
            raise DataError(f"--compare {path}: not a bench rdo result (its --out JSON has no summary of rows)")
        compared.append((path.name.removesuffix(".json"), summary))
    return compared


def _worker_part(samples: list[Sample], units: list[tuple[int, int]]) -> list[tuple[Sample, list[int]]]:
    """A worker's (sample index, lambda index) units as (sample, its lambda indices), each sample once."""
    lambdas: dict[int, list[int]] = {}
    for s, k in units:
        lambdas.setdefault(s, []).append(k)
    return [(samples[s], ks) for s, ks in lambdas.items()]


def _row_order(samples: list[Sample], lambdas: list[float]):
    """Sort key putting the workers' rows in one process's order: by sample, then the references, then by lambda
    (the sort is stable, so the step counts of a run stay in order)."""
    position = {_key(sample): i for i, sample in enumerate(samples)}
    return lambda row: (position[_key(row)], lambdas.index(row["lambda"]) if "lambda" in row else -1)


def bench_samples(shard: tuple[dict, list[tuple[Sample, list[int]]]],
                  device: torch.device) -> tuple[list[dict], str, dict[str, float]]:
    """One worker's part (:func:`~codecsplat_warp.eval.shards.run_sharded`): the rows of each of its samples at the
    lambdas (indices into the job's) dealt to it (:func:`bench_sample`; the references come with a sample's first
    lambda), what its LPIPS scores are, and where its time went (:func:`~codecsplat_warp.eval.shards.worker_seconds`).
    The units are (sample, lambda) pairs, not samples, so that a held-out set of a few scenes still spreads evenly
    over the GPUs."""
    job, part = shard
    entered = time.time()
    model = pretrained.load_pretrained(job["checkpoint"], device)
    metrics = ImageMetrics(job["lpips_weights"], device)
    perceptual = _perceptual(job["settings"], job["lpips_weights"], device)
    refiner = load_refiner(job["refiner"], model_id(model), device)[0] if job["refiner"] else None
    rows, warmed, done, total = [], set(), 0, sum(len(ks) for _, ks in part)
    loaded = time.time()
    for sample, ks in part:
        shape = tuple(sample.context_images.shape)
        rows += bench_sample(model, sample.to(device), [job["lambdas"][k] for k in ks], job["steps"], job["settings"],
                             metrics, device, job["pictures"], perceptual, job["trajectory"], references=0 in ks,
                             warm_up=shape not in warmed, refiner=refiner, refiner_steps=job["refiner_steps"])
        warmed.add(shape)
        done += len(ks)
        report_progress(done, total)
    seconds = worker_seconds(total, job["started"], entered, loaded)  # the model and metrics its load
    return rows, metrics.lpips_missing or "LPIPS-VGG and LPIPS-Alex v0.1", seconds


def _key(item) -> tuple:
    """(scene, context, target) of a sample or of one of its rows."""
    get = item.get if isinstance(item, dict) else lambda name: getattr(item, name)
    return get("scene"), tuple(get("context")), tuple(get("target"))


def _perceptual(settings: dict, lpips_weights: str | None, device: torch.device) -> torch.nn.Module | None:
    """The LPIPS-VGG network of a perceptual term, or None without one."""
    return LPIPS("vgg", lpips_weights).to(device) if settings.get("perceptual_weight", 0) > 0 else None


def parse_settings(text: str) -> dict:
    """``key=value,...`` -> {RDOConfig field: value}, each value typed like the field's default."""
    defaults = RDOConfig()
    settings = {}
    for item in (part.strip() for part in text.split(",")):
        if not item:
            continue
        key, sep, value = item.partition("=")
        if not sep or not hasattr(defaults, key) or key in ("steps", "time_budget", "seed"):
            raise InputError(f"--set takes key=value pairs of RDOConfig fields (not steps, time_budget or seed), "
                             f"got {item!r}")
        kind = type(getattr(defaults, key))
        try:
            settings[key] = _parse_bool(value) if kind is bool else kind(value)
        except ValueError:
            raise InputError(f"--set {key}: {value!r} is not a {kind.__name__}") from None
    return settings


def _parse_bool(text: str) -> bool:
    """true/false, yes/no, on/off, 1/0 (any case) -> bool; ValueError otherwise."""
    words = {"true": True, "yes": True, "on": True, "1": True, "false": False, "no": False, "off": False, "0": False}
    if text.strip().lower() not in words:
        raise ValueError(text)
    return words[text.strip().lower()]


def _int_list(text: str, what: str) -> list[int]:
    try:
        return [int(part) for part in text.split(",") if part.strip()]
    except ValueError:
        raise InputError(f"{what} must be a comma list of integers, got {text!r}") from None


def _samples(args: argparse.Namespace, model) -> list[Sample]:
    """The samples of ``--data`` (``--index`` entries, or one nearest-view split per scene), on the CPU."""
    if not args.data:
        raise InputError("bench rdo needs --data (a folder of scene folders; default $CODECSPLAT_DATA)")
    protocol = PROTOCOLS[args.protocol]
    names = tuple(name.strip() for name in args.scenes.split(",") if name.strip())
    if args.index:
        plan = folder_index_plan(find_scenes(args.data), args.index, protocol, names)
    else:
        samples = []
        for path in select_scenes(find_scenes(args.data), tuple(sorted(names))):
            samples += scene_samples(path, protocol, protocol.context_views or model.config.num_views, 1)
        plan = eager_plan(samples, [])
    samples = list(plan.load(0))
    if not samples:
        raise InputError(f"no sample under {args.data} for the {args.protocol} protocol")
    return samples


def bench_sample(model, sample: Sample, lambdas: list[float], steps: list[int], settings: dict,
                 metrics: ImageMetrics, device: torch.device, pictures: str | None,
                 perceptual: torch.nn.Module | None = None, trajectory: bool = False, references: bool = True,
                 warm_up: bool = True, refiner: LatentRefiner | None = None,
                 refiner_steps: list[int] = ()) -> list[dict]:  # fmt: skip
    """Rows of one sample: the references (copy-nearest, codec-free; with ``references``) and one per (lambda,
    steps) of method ``codecsplat`` (Adam's steps), then one per (lambda, refiner iterations) of method
    ``refiner`` (``refiner_steps`` iterations of ``refiner``); with ``trajectory``, each RDO row also scores the
    targets at every check of the run (``row["trajectory"]``). ``warm_up`` first runs a short untimed encode
    (Warp kernels, the allocator), and one of the refiner when there is one."""
    def score(rgb: torch.Tensor) -> dict:
        return _target_scores(metrics, rgb, sample)

    base = {"scene": sample.scene, "context": sample.context, "target": sample.target}
    copy = nearest_context_images(sample.context_images, sample.context_cameras, sample.target_cameras)
    with torch.no_grad():
        free = model.render(model(sample.context_images, sample.context_cameras)["gaussians"],
                            sample.target_cameras)["rgb"]
    rows = [{**base, "method": "copy nearest", **score(copy)},
            {**base, "method": "codec-free", **score(free)}] if references else []
    if warm_up:
        model.encode_scene(sample.context_images, sample.context_cameras, lambdas[0], steps=min(steps[-1], 2),
                           rdo_settings=settings, perceptual=perceptual)
        if refiner is not None and refiner_steps:
            model.encode_scene(sample.context_images, sample.context_cameras, lambdas[0],
                               steps=min(refiner_steps[-1], 2), rdo_settings=settings, perceptual=perceptual,
                               refiner=refiner)
    runs = [("codecsplat", count, None) for count in steps]
    runs += [("refiner", count, refiner) for count in refiner_steps] if refiner is not None else []
    for lam in lambdas:
        renders, titles = [to_uint8_frames(sample.target_images), to_uint8_frames(copy), to_uint8_frames(free)], \
            ["truth", "copy nearest", "codec-free"]
        for method, count, run_refiner in runs:
            checks: list[dict] = []
            hook = _trajectory_hook(model, sample, metrics, checks) if trajectory else None
            synchronize(device)
            start = time.perf_counter()
            encoded = model.encode_scene(sample.context_images, sample.context_cameras, lam, steps=count,
                                         rdo_settings=settings, perceptual=perceptual, on_check=hook,
                                         refiner=run_refiner)
            synchronize(device)
            seconds = time.perf_counter() - start
            with torch.no_grad():
                scene = model.decode_scene(encoded.data)
                rgb = model.render(scene.gaussians, sample.target_cameras)["rgb"]
                own = model.render(scene.gaussians, sample.context_cameras)["rgb"]
            context_psnr = psnr_of_mse(float((own.clamp(0, 1) - sample.context_images).square().mean()))
            row = {**base, "method": method, "lambda": lam, "steps": count, "seconds": seconds,
                   "bytes": len(encoded.data), "context_psnr": context_psnr, **score(rgb)}
            if encoded.rdo is not None:
                row["rdo"] = encoded.rdo.to_dict()
            if checks:
                row["trajectory"] = checks
            rows.append(row)
            print(f"{sample.scene} λ={lam:g} {method} steps={count}: {seconds:.2f} s, {len(encoded.data)} B, "
                  f"target {row['psnr']:.2f} dB, context {context_psnr:.2f} dB", file=sys.stderr, flush=True)
            renders.append(to_uint8_frames(rgb))
            titles.append(f"{'refiner ' if run_refiner is not None else ''}{count} steps, {len(encoded.data) / 1024:.1f} KiB\n{row['psnr']:.2f} dB, {seconds:.1f} s")
        if pictures:
            path = pathlib.Path(pictures) / f"{sample.scene}-lambda{lam:g}.png"
            plot_comparison(renders, titles, path)
    return rows


def _trajectory_hook(model, sample: Sample, metrics: ImageMetrics, checks: list[dict]):
    """An ``on_check`` hook that scores the targets decoded from every check's coding, and the cross-view PSNR
    (each context view rendered from the other views' Gaussians alone, black behind them): appends to ``checks``."""
    cameras, images = sample.context_cameras, sample.context_images

    @torch.no_grad()
    def hook(check, compressed) -> None:
        gaussians = model.decode_feature(compressed.feature, cameras)[2]
        rgb = model.render(gaussians, sample.target_cameras)["rgb"]
        scores = _target_scores(metrics, rgb, sample)
        others = model.render(gaussians, cameras, leave_out=gaussians.view_ranges(cameras.num_views))["rgb"]
        cross = (others.clamp(0, 1) - images).square().mean(dim=(1, 2, 3))
        checks.append({**vars(check), **{f"target_{k}": v for k, v in scores.items()},
                       "cross_psnr": psnr_of_mse(float(cross.mean()))})

    return hook


def _target_scores(metrics: ImageMetrics, rgb: torch.Tensor, sample: Sample) -> dict[str, float]:
    """Each metric of ``rgb`` [T,3,H,W] against the sample's target images, averaged over the targets."""
    return {k: statistics.fmean(v) for k, v in metrics(rgb, sample.target_images).items()}


def summarize(rows: list[dict]) -> list[dict]:
    """Means over samples per (method, lambda, steps), the references' included."""
    groups: dict[tuple, list[dict]] = {}
    for row in rows:
        groups.setdefault((row["method"], row.get("lambda"), row.get("steps")), []).append(row)
    summary = []
    for (method, lam, steps), group in groups.items():
        entry = {"method": method, "lambda": lam, "steps": steps, "samples": len(group)}
        for key in (*METRICS, "seconds", "bytes", "context_psnr"):
            values = [r[key] for r in group if key in r]
            if values:
                entry[key] = statistics.fmean(values)
        summary.append(entry)
    return summary


def format_summary(summary: list[dict], machine: str) -> str:
    columns = [("method", "method", "s"), ("lambda", "λ", "g"), ("steps", "steps", "d"), ("samples", "samples", "d"),
               ("seconds", "encode s", ".2f"), ("KiB", "KiB", ".2f"), ("psnr", "PSNR", ".2f"), ("ssim", "SSIM", ".3f"),
               ("lpips_vgg", "LPIPS-VGG", ".3f"), ("context_psnr", "context PSNR", ".2f")]
    rows = [{**entry, "KiB": entry["bytes"] / 1024 if "bytes" in entry else None} for entry in summary]
    return f"bench rdo on {machine}: means over samples\n" + format_table(rows, columns)


def plot_curve(summary: list[dict], path: pathlib.Path, compared: list[tuple[str, list[dict]]] = ()) -> None:
    """Target PSNR, LPIPS-VGG and KiB against mean encode seconds, one line per method of coding (Adam's steps,
    a refiner's iterations) and lambda (points: step counts), with the references as horizontal lines; each of
    ``compared`` (label, an earlier result's summary) adds its coded lines, dotted and labelled with it."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    for prefix, entries, style in [("", summary, None), *((f"{label}: ", entries, ":") for label, entries in compared)]:
        _plot_coded_lines(axes, [e for e in entries if e["method"] in CODED_METHODS], prefix, style)
    for entry, style in zip((e for e in summary if e["method"] not in CODED_METHODS), ("k:", "k--")):
        for ax, key in zip(axes[:2], ("psnr", "lpips_vgg")):
            if key in entry:
                ax.axhline(entry[key], linestyle=style[1:], color="k", linewidth=1, label=entry["method"])
    for ax, label in zip(axes, ("target PSNR (dB)", "target LPIPS-VGG", "bitstream KiB")):
        ax.set_xlabel("encode seconds (mean per scene)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    save_figure(fig, path)


def _plot_coded_lines(axes, coded: list[dict], prefix: str, style: str | None) -> None:
    """:func:`plot_curve`'s lines of the ``coded`` entries of one result on its three ``axes``: one per method
    and lambda, labelled with ``prefix``, in the line ``style`` (None: solid for Adam's steps, dashed for a
    refiner), each point annotated with its step count."""
    for method, lam in sorted({(e["method"], e["lambda"]) for e in coded}):
        line = sorted((e for e in coded if (e["method"], e["lambda"]) == (method, lam)), key=lambda e: e["seconds"])
        seconds = [e["seconds"] for e in line]
        label = prefix + (f"λ={lam:g}" if method == "codecsplat" else f"{method} λ={lam:g}")
        marker = "o" if method == "codecsplat" else "s"
        for ax, key, scale in zip(axes, ("psnr", "lpips_vgg", "bytes"), (1, 1, 1 / 1024)):
            if all(key in e for e in line):
                ax.plot(seconds, [e[key] * scale for e in line],
                        marker + (style or ("-" if method == "codecsplat" else "--")), label=label)
                for e, x in zip(line, seconds):
                    ax.annotate(str(e["steps"]), (x, e[key] * scale), fontsize=7, xytext=(2, 2),
                                textcoords="offset points")


# --------------------------------------------------------------------------------------------------
# Profile of one step
def profile_step(model, sample: Sample, lam: float, settings: dict, steps: int, device: torch.device,
                 perceptual: torch.nn.Module | None = None, refiner: LatentRefiner | None = None) -> dict:
    """Median wall ms of ``steps`` optimisation steps, then one profiled step broken into
    :data:`RDO_PROFILE_PARTS` (ms of CPU time on the CPU, of GPU kernels on CUDA); with a ``refiner``, the median
    wall ms of ``steps`` of its iterations (``refiner_step_ms``, after 3 untimed ones, with the same decoder)."""
    from torch.profiler import ProfilerActivity, profile

    sample = sample.to(device)
    # the run below: 3 warm-up, timed, 1 profiled
    config = rdo_config("fast", steps + 4, None, 0, sample.context_cameras.num_views, **settings)
    # the model's forward runs the decoder heads, which an encode first runs inside the optimisation: the same
    # cuDNN algorithm search (torch keeps the first algorithm a convolution of a shape got, searched or not)
    with torch.no_grad(), cudnn_autotuned(device):
        feature = model(sample.context_images, sample.context_cameras)["F_c"]
        start = model.codec.compress(feature, lam, reconstruct=True)
    target = rdo_target(model, sample.context_images, sample.context_cameras, lam, start, config, perceptual)
    latents = start_variables(start, config, feature)
    optimiser = latent_optimiser(latents, config)
    with decoder_fixed(model, device):
        model.train()
        decoder = step_decoder(model, target, latents, config)

        def step() -> None:
            rdo_step(model, latents, optimiser, target, config, None, decoder)

        for _ in range(3):
            step()
        times = []
        for _ in range(steps):
            synchronize(device)
            began = time.perf_counter()
            step()
            synchronize(device)
            times.append(1e3 * (time.perf_counter() - began))
        activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
        with profile(activities=activities) as prof:
            step()
            synchronize(device)
        iteration_times = _refiner_times(model, refiner, latents, target, config, decoder, steps, device) \
            if refiner is not None else None
    parts = _step_parts(prof.events(), device)
    extra = {} if iteration_times is None else {"refiner_step_ms": statistics.median(iteration_times),
                                                "refiner_step_ms_all": iteration_times}
    return {"scene": sample.scene, "views": sample.context_cameras.num_views,
            "size": [sample.context_cameras.width, sample.context_cameras.height], "lambda": lam,
            "step_ms": statistics.median(times), "step_ms_all": times, **extra,
            "clock": "GPU kernel time" if device.type == "cuda" else "CPU time", "parts_ms": parts,
            "top": _top_work(prof.key_averages(), device)}


def _refiner_times(model, refiner: LatentRefiner, latents: list[torch.Tensor], target, config: RDOConfig, decoder,
                   steps: int, device: torch.device) -> list[float]:
    """Wall ms of ``steps`` iterations of ``refiner`` from ``latents`` (after 3 untimed ones), as the encoder runs
    them (:func:`~codecsplat_warp.model.rdo.refiner_step` under no_grad)."""
    state = refiner.start(latents)
    moved = [z.detach() for z in latents]
    times = []
    with torch.no_grad():
        for index in range(steps + 3):
            synchronize(device)
            began = time.perf_counter()
            moved, _ = refiner_step(model, refiner, moved, state, target, config, None, config.learning_rate,
                                    0.0, decoder)
            synchronize(device)
            if index >= 3:
                times.append(1e3 * (time.perf_counter() - began))
    return times


TOP_ROWS = 15
"""Rows of the profile's table of the costliest kernels (CUDA) or operators (CPU)."""


def _top_work(averages, device: torch.device) -> list[dict]:
    """The :data:`TOP_ROWS` costliest entries of a profiled step: on CUDA the GPU kernels by their own device time
    (kernels replayed from the decoder's CUDA graphs included, where the parts cannot see them), on the CPU the
    operators by their own CPU time; each ``{"name", "ms", "calls"}``."""
    if device.type == "cuda":
        # the model's record_function ranges (the parts' names) also show on the GPU timeline: not kernels
        rows = [(e.key, e.self_device_time_total, e.count) for e in averages
                if e.device_type == torch.autograd.DeviceType.CUDA and e.self_device_time_total > 0
                and e.key not in RDO_PROFILE_PARTS]
    else:
        rows = [(e.key, e.self_cpu_time_total, e.count) for e in averages if e.self_cpu_time_total > 0]
    rows.sort(key=lambda row: -row[1])
    return [{"name": name, "ms": round(total / 1e3, 3), "calls": calls} for name, total, calls in rows[:TOP_ROWS]]


_BACKWARD_PARTS = (("_RasterizeBackward", "rasterize"), ("_ReprojectAverage", "reprojection"),
                   ("_Unproject", "map_to_world"), ("Convolution", "convolutions"),
                   ("_ReplayDecoderBackward", "decoder_graph"))
"""Backward autograd nodes by name fragment -> part (the rest is "other")."""

_FORWARD_PARTS = {"codec": "codec", "depth_head": "depth_head", "refine_post": "refine_post", "gs_head": "gs_head",
                  "map_to_world": "map_to_world", "rasterize": "rasterize", "loss": "loss", "perceptual": "perceptual",
                  "optimiser": "optimiser", "_ReplayDecoder": "decoder_graph"}
"""Forward ranges and operators by name -> part (``_ReplayDecoder``: the replay of the decoder's forward graph)."""


def _step_parts(events, device: torch.device) -> dict[str, dict[str, float]]:
    """{part: {"forward": ms, "backward": ms}} from a profiled step's events: forward by the record_function
    ranges of the model (nested ranges are subtracted from their parents) and the decoder graph's replay, backward
    by autograd node. Only host-side events count: on CUDA a range also shows as an annotation on the GPU's
    timeline, whose device time is its span, the same kernels again with the gaps between them."""
    def ms(event) -> float:
        if device.type != "cuda":
            return event.cpu_time_total / 1e3
        # the kernels of the ops below the event (a range's own device span would count the gaps between them)
        stack, total = list(event.cpu_children), event.self_device_time_total
        while stack:
            child = stack.pop()
            total += child.self_device_time_total
            stack.extend(child.cpu_children)
        return total / 1e3

    parts = {name: {"forward": 0.0, "backward": 0.0} for name in RDO_PROFILE_PARTS}
    for event in events:
        name = event.name
        if event.device_type != torch.autograd.DeviceType.CPU:
            continue
        if name in _FORWARD_PARTS:
            parts[_FORWARD_PARTS[name]]["forward"] += ms(event)
        elif name in ("_ReprojectAverage",):
            parts["reprojection"]["forward"] += ms(event)
            parts["refine_post"]["forward"] -= ms(event)
        elif name.startswith("autograd::engine::evaluate_function:"):
            node = name.split(":")[-1].strip()
            part = next((p for fragment, p in _BACKWARD_PARTS if fragment in node), "other")
            parts[part]["backward"] += ms(event)
    parts["optimiser"]["backward"] = 0.0
    return {name: {k: round(v, 3) for k, v in value.items()} for name, value in parts.items()}


def format_profile(profile: dict) -> str:
    parts = profile["parts_ms"]
    rows = [{"part": name, "forward": v["forward"], "backward": v["backward"], "total": v["forward"] + v["backward"]}
            for name, v in parts.items()]
    rows.append({"part": "sum of parts", "total": sum(r["total"] for r in rows)})
    head = (f"RDO step on {profile['scene']} ({profile['views']} views, {profile['size'][0]}x{profile['size'][1]}, "
            f"λ={profile['lambda']:g}): median wall {profile['step_ms']:.2f} ms; parts in {profile['clock']} (ms)")
    if "refiner_step_ms" in profile:
        head += (f"\nrefiner iteration: median wall {profile['refiner_step_ms']:.2f} ms "
                 f"({profile['refiner_step_ms'] / profile['step_ms']:.2f}x the Adam step)")
    columns = [("part", "part", "s"), ("forward", "forward", ".2f"), ("backward", "backward", ".2f"),
               ("total", "total", ".2f")]
    what = "GPU kernels" if profile["clock"] == "GPU kernel time" else "operators"
    top = [{**row, "name": row["name"][:90]} for row in profile["top"]]
    costliest = format_table(top, [("name", what, "s"), ("ms", "ms", ".3f"), ("calls", "calls", "d")])
    return (f"{head}\n{format_table(rows, columns)}\n\n"
            f"The {len(top)} costliest {what} of the step (own time):\n{costliest}")
