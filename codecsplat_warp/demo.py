"""``codecsplat demo``: the shipped model on a real captured scene, end to end, offline.

The scene is, by name, ``nerd_mary_rose`` (four photographs of a wooden tankard raised with the Mary Rose, shipped
with the package at 256x256: CC BY 4.0, see its ``cameras.json``; a held-out scene that no training run has seen)
or ``procedural`` (a procedural room, :func:`codecsplat_warp.data.procedural_scene`); any other value is a scene
folder (any format :func:`~codecsplat_warp.data.load_scene` reads). A folder's context views are the model's view
count around its middle view, with the targets between them (:func:`~codecsplat_warp.data.split_context_targets`),
resized and centre-cropped to the model's image size. The context views are encoded at a few lambdas, each
bitstream is decoded and its target views rendered and scored against the photographs. One more bitstream at the
largest lambda comes from the encoder with rate-distortion optimisation (``rdo_steps`` steps of
:mod:`codecsplat_warp.model.rdo`; the same decoder reads it). Written to the output folder:

* ``scene-lambda<L>.csplat`` and ``scene-lambda<L>-rdo.csplat``: the scene bitstreams;
* ``scene.ply``: the Gaussians decoded from the largest lambda, pruned of those that no demo view (context or
  target) can show (:func:`~codecsplat_warp.model.prune.prune_gaussians`; 3DGS PLY);
* ``renders/target<i>-lambda<L>[-rdo].png`` and ``comparison.png`` (the context photographs | per target: the
  photograph | copy the nearest context view | the codec-free path | one column per lambda, the RDO one last);
* ``rate_distortion.png`` and ``summary.json`` (bytes per part, metrics, seconds; the two references under
  ``references``: what copying the nearest context view scores at zero bytes, and the model without its codec;
  ``package_digest``, :func:`package_digest` of the code and model that wrote it).
"""

from __future__ import annotations

import hashlib
import importlib.util
import pathlib
import statistics
import time
from dataclasses import asdict, dataclass
from typing import Sequence

import numpy as np
import torch
from tqdm.auto import tqdm

from .cameras import Cameras
from .choices import DEMO_LAMBDAS, DEMO_RDO_STEPS, DEMO_SCENE, DEMO_SEED, DEMO_TARGET_VIEWS, PROCEDURAL
from .codec import bytes_report, check_lambda
from .data import load_scene, split_context_targets
from .data.procedural import ProceduralConfig, procedural_scene
from .errors import InputError
from .eval.protocols import Protocol, Sample, nearest_context_images, protocol_sample
from .eval.report import BACKBONE, COPY_NEAREST, format_bytes, plot_comparison, plot_rate_distortion
from .export.files import atomic_output, write_bytes, write_json
from .export.ply import write_ply
from .export.video import to_uint8_frames
from .measure import timed
from .metrics.image import ImageMetrics
from .model.codecsplat import model_id
from .model.prune import prune_gaussians

SHIPPED_SCENES = pathlib.Path(__file__).resolve().parent / "assets" / "scenes"
"""Scene folders shipped with the package, each usable by its folder name (``--scene NAME``)."""


def package_folders() -> list[pathlib.Path]:
    """The folders the package runs from: ``codecsplat_warp`` (its modules, the shipped model and scenes) and the
    folder ``codecsplat_warp.kernels`` comes from (the repository's ``kernels/`` in a source checkout) where that
    lies outside it."""
    package = pathlib.Path(__file__).resolve().parent
    spec = importlib.util.find_spec("codecsplat_warp.kernels")
    kernels = [pathlib.Path(p).resolve() for p in (spec.submodule_search_locations or [])] if spec else []
    return [package] + [k for k in kernels if not k.is_relative_to(package)]


def package_digest(folders: Sequence[pathlib.Path] | None = None) -> str:
    """SHA-256 hex of every file under ``folders`` (default :func:`package_folders`: the package's code, the
    shipped model and the demo scenes), by name and contents; compiled ``__pycache__`` files are left out. The
    demo records it in ``summary.json``, so that a summary can be told from one that other code or another model
    wrote."""
    sha = hashlib.sha256()
    for index, folder in enumerate(folders if folders is not None else package_folders()):
        files = sorted(p for p in folder.rglob("*") if p.is_file() and "__pycache__" not in p.parts)
        for path in files:
            data = path.read_bytes()
            sha.update(f"{index}/{path.relative_to(folder).as_posix()}:{len(data)}:".encode())
            sha.update(data)
    return sha.hexdigest()


@dataclass
class DemoConfig:
    """Options of ``codecsplat demo``."""

    out: str = "codecsplat-demo"
    scene: str = DEMO_SCENE
    lambdas: tuple[float, ...] = DEMO_LAMBDAS
    seed: int = DEMO_SEED
    target_views: int = DEMO_TARGET_VIEWS
    rdo_steps: int = DEMO_RDO_STEPS
    lpips_weights: str | None = None
    progress: bool = True


def builtin_scenes() -> list[str]:
    """Names ``--scene`` takes besides a path: the shipped scene folders and :data:`PROCEDURAL`."""
    return sorted(p.name for p in SHIPPED_SCENES.iterdir() if p.is_dir()) + [PROCEDURAL]


def demo_sample(model_config, scene: str, seed: int, target_views: int) -> Sample:
    """The demo's context and target views of ``scene`` (a built-in name or a scene folder, see the module
    docstring) at the model's image size and view count; ``seed`` draws the procedural room.

    Raises:
        InputError: ``scene`` is neither a built-in name nor an existing path.
        DataError: the folder holds no readable scene, or fewer views than the demo needs.
    """
    if scene == PROCEDURAL:
        return procedural_sample(model_config, seed, target_views)
    folder = SHIPPED_SCENES / scene if scene in builtin_scenes() else pathlib.Path(scene)
    if not folder.exists():
        raise InputError(f"demo scene {scene!r} is neither a built-in scene ({', '.join(builtin_scenes())}) "
                         "nor an existing scene folder")
    return folder_sample(folder, model_config, target_views)


def folder_sample(folder: pathlib.Path, model_config, target_views: int) -> Sample:
    """The model's view count around the middle view of the scene in ``folder`` as context, ``target_views``
    targets between them, resized and centre-cropped to the model's size (the scene keeps its near/far)."""
    scene = load_scene(folder)
    context, target = split_context_targets(scene.cameras, scene.num_views // 2, model_config.num_views, target_views)
    protocol = Protocol("demo", model_config.width, model_config.height, model_config.num_views, target_views)
    return protocol_sample(folder.name, scene, protocol, context, target)


def procedural_sample(model_config, seed: int, target_views: int) -> Sample:
    """A procedural room at the model's size, captured forward-facing (cameras on a small circle, looking the same
    way, as in an LLFF capture): ``num_views`` context views, targets between them."""
    views = model_config.num_views
    scene = procedural_scene(seed, ProceduralConfig(width=model_config.width, height=model_config.height,
                                                    num_views=views + target_views, layout="room", trajectory="forward"))
    context, target = split_context_targets(scene.cameras, 0, views, target_views)
    images = scene.images.float() / 255.0
    cameras = scene.cameras.to(dtype=torch.float32)
    return Sample(scene.key, context, target, images[context], cameras.select(context), images[target],
                  cameras.select(target))


def run_demo(model, config: DemoConfig, device: torch.device) -> dict:
    """Run the demo (see the module docstring) with ``model`` on ``device``; returns the summary dict."""
    lambdas = sorted(check_lambda(lam) for lam in config.lambdas)
    if not lambdas:
        raise InputError("give at least one lambda")
    if config.target_views < 1:
        raise InputError(f"the demo needs at least 1 target view, got {config.target_views}")
    if config.rdo_steps < 0:
        raise InputError(f"the demo's RDO steps must be >= 0, got {config.rdo_steps}")
    encodes = [(lam, 0) for lam in lambdas] + ([(lambdas[-1], config.rdo_steps)] if config.rdo_steps else [])
    out = pathlib.Path(config.out)
    metrics = ImageMetrics(config.lpips_weights, device)
    start = time.perf_counter()
    quiet = None if config.progress else True  # None: a bar only when stderr is a terminal
    with tqdm(total=3 + 2 * len(encodes), desc="demo", unit="step", disable=quiet) as progress:
        sample = demo_sample(model.config, config.scene, config.seed, config.target_views).to(device)
        progress.update(1)
        references, reference_renders = reference_views(model, sample, metrics)
        progress.update(1)
        rows, renders, decoded, kept_scene = [], [], None, None
        for lam, steps in encodes:
            name = f"λ={lam:g}" + (f" RDO {steps} steps" if steps else "")
            progress.set_postfix_str(f"encode {name}")
            data, encode_s = timed(lambda: model.encode(sample.context_images, sample.context_cameras, lam,
                                                        steps=steps), device)
            write_bytes(out / _bitstream_name(lam, steps), data)
            progress.update(1)
            progress.set_postfix_str(f"decode {name}")
            decoded, decode_s = timed(lambda: model.decode_scene(data), device)
            if not steps:
                kept_scene = decoded
            (visible, target_report), prune_s = timed(
                lambda: prune_gaussians(decoded.gaussians, sample.target_cameras), device)
            with torch.no_grad():
                rgb = model.render(visible, sample.target_cameras)["rgb"]
            scores = {k: statistics.fmean(v) for k, v in metrics(rgb, sample.target_images).items()}
            rows.append({"method": "CodecSplat RDO" if steps else "CodecSplat", "setting": name, "lam": lam,
                         "rdo_steps": steps, "bytes": len(data),
                         "parts": bytes_report(data), **scores, "encode_s": encode_s, "decode_s": decode_s,
                         "prune_s": prune_s, "pruned_for_targets": target_report.to_dict()})
            renders.append(to_uint8_frames(rgb))
            progress.update(1)
        progress.set_postfix_str("PLY and plots")
        kept, ply_report = prune_gaussians(kept_scene.gaussians, _demo_views(sample))  # the largest amortised λ
        ply_bytes = write_ply(out / "scene.ply", kept)
        files = _write_images(out, sample, rows, renders, references, reference_renders)
        plot_rate_distortion(rows, out / "rate_distortion.png")
        progress.update(1)
    summary = {
        "config": asdict(config), "device": str(device), "model_id": model_id(model), "package_digest": package_digest(),
        "scene": sample.scene, "context_views": sample.context,
        "target_views": sample.target, "image_size": [sample.context_cameras.height, sample.context_cameras.width],
        "lpips": metrics.lpips_missing or "LPIPS-VGG and LPIPS-Alex v0.1", "rows": rows, "references": references,
        "ply": {"path": str(out / "scene.ply"), "gaussians": len(kept), "pruned": ply_report.pruned,
                "prune": ply_report.to_dict(), "bytes": ply_bytes, "lambda": lambdas[-1]},
        "files": [str(out / _bitstream_name(lam, steps)) for lam, steps in encodes] + files
        + [str(out / "scene.ply"), str(out / "rate_distortion.png"), str(out / "summary.json")],
        "seconds": time.perf_counter() - start,
    }
    write_json(out / "summary.json", summary)
    return summary


def reference_views(model, sample: Sample, metrics: ImageMetrics) -> tuple[list[dict], list[np.ndarray]]:
    """The two references every lambda is judged against, on the sample's targets: copying the nearest context
    view (zero bytes) and the model's codec-free path. Returns their rows (``method`` and the metrics) and
    their uint8 renders [T,H,W,3]."""
    with torch.no_grad(), torch.autocast(sample.context_images.device.type, dtype=torch.bfloat16,
                                         enabled=sample.context_images.device.type == "cuda"):
        free = model(sample.context_images, sample.context_cameras)["gaussians"]
    with torch.no_grad():
        predictions = {COPY_NEAREST: nearest_context_images(sample.context_images, sample.context_cameras,
                                                            sample.target_cameras),
                       BACKBONE: model.render(free, sample.target_cameras)["rgb"]}
    rows = [{"method": name, **{k: statistics.fmean(v) for k, v in metrics(rgb, sample.target_images).items()}}
            for name, rgb in predictions.items()]
    return rows, [to_uint8_frames(rgb) for rgb in predictions.values()]


QUALITY_COLUMNS = (("psnr", "PSNR dB", ".2f"), ("ssim", "SSIM", ".3f"), ("lpips_vgg", "LPIPS-VGG", ".3f"),
                   ("lpips_alex", "LPIPS-Alex", ".3f"))


def quality_table(summary: dict) -> str:
    """Markdown table of the device-independent results of a demo summary: per lambda the bitstream bytes and
    the target-view quality (LPIPS columns only when the run had the weights). docs/getting-started.md quotes it."""
    columns = [c for c in QUALITY_COLUMNS if all(c[0] in row for row in summary["rows"])]
    lines = ["| λ | bytes | " + " | ".join(header for _, header, _ in columns) + " |",
             "|---|---|" + "---|" * len(columns)]
    for row in summary["rows"]:
        cells = [row["setting"][2:], f"{row['bytes']:,d}"] + [format(row[key], spec) for key, _, spec in columns]
        lines.append("| " + " | ".join(cells) + " |")
    for row in summary.get("references", []):
        cells = [row["method"], "0" if row["method"] == COPY_NEAREST else "-"]
        lines.append("| " + " | ".join(cells + [format(row[key], spec) for key, _, spec in columns]) + " |")
    return "\n".join(lines)


def _demo_views(sample: Sample) -> Cameras:
    """The context and target cameras of ``sample`` as one batch."""
    context, target = sample.context_cameras, sample.target_cameras.to(dtype=sample.context_cameras.dtype)
    return Cameras(K=torch.cat([context.K, target.K]), w2c=torch.cat([context.w2c, target.w2c]),
                   near=torch.cat([context.near, target.near]), far=torch.cat([context.far, target.far]),
                   width=context.width, height=context.height)


def _write_images(out: pathlib.Path, sample: Sample, rows: list[dict], renders: list[np.ndarray],
                  references: list[dict], reference_renders: list[np.ndarray]) -> list[str]:
    """Per-target PNG renders and ``comparison.png`` (first column: the context photographs; then one row per
    target: its photograph, the references, each lambda)."""
    import imageio.v3 as iio

    paths = []
    for row, frames in zip(rows, renders):
        for i, frame in enumerate(frames):
            path = out / "renders" / f"target{i}-lambda{row['lam']:g}{'-rdo' if row['rdo_steps'] else ''}.png"
            with atomic_output(path) as tmp:
                iio.imwrite(tmp, frame, extension=".png")
            paths.append(str(path))
    truth = to_uint8_frames(sample.target_images)
    titles = (["target photograph"] + [f"{_short(r['method'])}\n{r['psnr']:.2f} dB" for r in references]
              + [f"{r['setting']}: {format_bytes(r['bytes'])}\n{r['psnr']:.2f} dB" for r in rows])
    plot_comparison([truth] + reference_renders + renders, titles, out / "comparison.png",
                    inputs=to_uint8_frames(sample.context_images), input_title="context photograph")
    return paths + [str(out / "comparison.png")]


def _bitstream_name(lam: float, rdo_steps: int) -> str:
    """The file name of the demo's bitstream at ``lam`` (``-rdo`` when the encoder optimised it)."""
    return f"scene-lambda{lam:g}{'-rdo' if rdo_steps else ''}.csplat"


def _short(method: str) -> str:
    """A reference's name short enough for a panel title."""
    return {COPY_NEAREST: "copy nearest context", BACKBONE: "codec-free"}.get(method, method)
