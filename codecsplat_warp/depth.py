"""``codecsplat depth``: multi-view stereo depth of every view of a posed scene, written as a depth map folder.

:func:`write_scene_depth` loads a scene (any format :func:`~codecsplat_warp.data.load_scene` reads), resizes it to
a largest side if asked, runs :func:`~codecsplat_warp.ops.mvs.mvs_depth` and writes the folder described in
:mod:`codecsplat_warp.data.depth_maps` (read it back with :func:`~codecsplat_warp.data.depth_maps.read_depth_maps`).
Every file is written atomically and ``depth.json`` last, so an interrupted run leaves no index behind, and a
finished one is recognised (:func:`finished_run`) and not computed again.
"""

from __future__ import annotations

import json
import os
import pathlib
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import matplotlib
import numpy as np
import torch
from PIL import Image
from tqdm.auto import tqdm

from .data import load_scene
from .data.depth_maps import DEPTH_FORMAT, INDEX_FILE, depth_scale, quantize_depth
from .data.preprocess import max_side_size, resize_image
from .errors import DataError
from .export.files import atomic_output, write_json
from .ops.mvs import MVSConfig, mvs_depth


@dataclass(frozen=True)
class DepthRun:
    """What :func:`write_scene_depth` does.

    Attributes:
        scene: scene folder or pose file.
        out: output folder.
        config: the MVS parameters.
        max_size: largest image side [pixels] the depth maps are computed at (None: the stored size).
        progress: show a progress bar over the views (on a terminal's stderr).
    """

    scene: str
    out: str
    config: MVSConfig = MVSConfig()
    max_size: int | None = None
    progress: bool = True


def write_scene_depth(run: DepthRun, device: torch.device) -> dict:
    """Compute and write the depth maps of every view of ``run.scene``; returns the ``depth.json`` payload
    plus ``"output"`` (the folder) and ``"resumed": False``. Images are decoded and resized, and the files
    written, on a thread pool (:func:`io_pool`).

    Raises:
        DataError: unreadable scene, or frames whose image stems collide.
        MVSError: fewer than 3 views, or a view without a usable source view.
    """
    start = time.perf_counter()
    scene = load_scene(run.scene)
    stems = _unique_stems(scene.frame_names)
    width, height = scene.cameras.width, scene.cameras.height
    if run.max_size is not None:
        width, height = max_side_size(width, height, run.max_size)
    pool = io_pool()
    images = torch.stack(list(pool.map(lambda v: resize_image(scene.decoded_images([v])[0], width, height),
                                       range(scene.num_views))))  # fmt: skip
    cameras = scene.cameras.rescaled(width, height)
    with tqdm(total=scene.num_views, desc=f"depth {scene.key}", unit="view", disable=None if run.progress else True,
              leave=False) as bar:  # fmt: skip
        result = mvs_depth((images.float() / 255).to(device), cameras.to(device, torch.float32), run.config,
                           progress=lambda done: bar.update(done - bar.n))  # fmt: skip
    depth, mask, coverage = result.depth.cpu(), result.mask.cpu(), result.coverage.tolist()
    near, far = float(cameras.near.min()), float(cameras.far.max())
    scale, shown = depth_scale(far), preview_range(depth, near, far)
    out = pathlib.Path(run.out)
    views = [pool.submit(_write_view, out, stem, images[v], depth[v], mask[v], scale, shown)
             for v, stem in enumerate(stems)]  # fmt: skip
    frames = [{"file": frame, **view.result(), "coverage": coverage[v],
               "sources": [int(s) for s in result.sources.index[v].tolist() if s >= 0]}
              for v, (frame, view) in enumerate(zip(scene.frame_names, views))]  # fmt: skip
    payload = {"format": DEPTH_FORMAT, "scale": scale, "width": width, "height": height, "near": near, "far": far,
               "frames": frames, "preview_depth_range": list(shown), "config": run.config.to_dict(),
               "max_size": run.max_size, "scene": str(run.scene), "device": str(device),
               "seconds": time.perf_counter() - start}
    write_json(out / INDEX_FILE, payload)
    return {**payload, "output": str(out), "resumed": False}


def finished_run(run: DepthRun) -> dict | None:
    """The ``depth.json`` payload (plus ``"output"`` and ``"resumed": True``) of ``run.out`` when it holds this
    run's result (same scene, config and max_size), else None."""
    index = pathlib.Path(run.out) / INDEX_FILE
    try:
        payload = json.loads(index.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    same = (isinstance(payload, dict) and payload.get("format") == DEPTH_FORMAT and payload.get("scene") == str(run.scene)
            and payload.get("config") == run.config.to_dict() and payload.get("max_size") == run.max_size)
    return {**payload, "output": str(run.out), "resumed": True} if same else None


_pool: ThreadPoolExecutor | None = None


def io_pool() -> ThreadPoolExecutor:
    """The thread pool that decodes, resizes and writes images (Pillow releases the GIL while it works)."""
    global _pool
    if _pool is None:
        _pool = ThreadPoolExecutor(max_workers=os.cpu_count() or 1, thread_name_prefix="codecsplat-depth-io")
    return _pool


PREVIEW_QUANTILES = (0.02, 0.98)
"""Quantiles of a scene's kept inverse depths that the preview colours span (blue to red)."""


def preview_range(depth: torch.Tensor, near: float, far: float) -> tuple[float, float]:
    """(nearest, farthest) depth the previews of a scene colour: the :data:`PREVIEW_QUANTILES` of the inverse
    of its kept depths [V,H,W] (0 = none), or (near, far) where fewer than two distinct depths are kept."""
    kept = depth[depth > 0].detach().to("cpu", torch.float64)
    if kept.numel() > 100_000:  # torch.quantile's input limit is far above; a strided subsample is plenty
        kept = kept[:: kept.numel() // 100_000]
    if kept.numel() < 2:
        return near, far
    low, high = torch.quantile(1.0 / kept, torch.tensor(PREVIEW_QUANTILES, dtype=torch.float64)).tolist()
    return (1.0 / high, 1.0 / low) if high > low else (near, far)


def preview_image(image: torch.Tensor, depth: torch.Tensor, near: float, far: float) -> np.ndarray:
    """uint8 [h,2w,3]: the uint8 [3,h,w] image beside the turbo-coloured inverse depth of [h,w] ``depth``
    (``near`` and nearer: red, ``far`` and farther: blue; black where the depth is 0)."""
    depth = depth.detach().to("cpu", torch.float64)
    kept = depth > 0
    inverse = torch.where(kept, 1.0 / depth.clamp(min=1e-12), torch.zeros_like(depth))
    level = ((inverse - 1.0 / far) / (1.0 / near - 1.0 / far)).clamp(0.0, 1.0).numpy()
    colours = (matplotlib.colormaps["turbo"](level)[..., :3] * 255).round().astype(np.uint8)
    colours[~kept.numpy()] = 0
    return np.concatenate([image.permute(1, 2, 0).cpu().numpy(), colours], axis=1)


def _write_view(out: pathlib.Path, stem: str, image: torch.Tensor, depth: torch.Tensor, mask: torch.Tensor,
                scale: float, shown: tuple[float, float]) -> dict:  # fmt: skip
    """Write one view's depth, mask and preview PNGs (preview colours spanning the depths ``shown``); returns
    their paths relative to ``out`` (``depth``, ``mask``, ``preview``)."""
    files = {"depth": f"depth/{stem}.png", "mask": f"mask/{stem}.png", "preview": f"preview/{stem}.png"}
    _write_png(out / files["depth"], quantize_depth(depth, scale))
    _write_png(out / files["mask"], np.where(mask.numpy(), 255, 0).astype(np.uint8))
    _write_png(out / files["preview"], preview_image(image, depth, *shown))
    return files


PNG_COMPRESSION = 1
"""zlib level of the PNGs: 1 encodes a depth map about 3x faster than Pillow's default 6, for 0-20 % more bytes."""


def _write_png(path: pathlib.Path, array: np.ndarray) -> None:
    """Write a uint8 (grey or RGB) or uint16 (grey) array as a PNG, atomically."""
    with atomic_output(path) as tmp:
        Image.fromarray(array).save(tmp, format="PNG", compress_level=PNG_COMPRESSION)


def _unique_stems(frame_names: list[str]) -> list[str]:
    """The file stem of every frame name; DataError naming two frames whose stems collide."""
    stems = [pathlib.PurePosixPath(name).stem for name in frame_names]
    seen: dict[str, str] = {}
    for name, stem in zip(frame_names, stems):
        if stem in seen:
            raise DataError(f"frames {seen[stem]!r} and {name!r} share the file stem {stem!r}: their depth maps "
                            "would overwrite each other")
        seen[stem] = name
    return stems
