"""``codecsplat depth``: multi-view stereo depth of every view of a posed scene, written as a depth map folder.

:func:`write_scene_depth` loads a scene (any format :func:`~codecsplat_warp.data.load_scene` reads), resizes it to
a largest side if asked, runs :func:`~codecsplat_warp.ops.mvs.mvs_depth` and writes the folder described in
:mod:`codecsplat_warp.data.depth_maps` (read it back with :func:`~codecsplat_warp.data.depth_maps.read_depth_maps`).
Every file is written atomically and ``depth.json`` last, so an interrupted run leaves no index behind.
"""

from __future__ import annotations

import pathlib
import time
from dataclasses import dataclass

import matplotlib
import numpy as np
import torch
from PIL import Image
from tqdm.auto import tqdm

from .data import load_scene
from .data.depth_maps import DEPTH_FORMAT, INDEX_FILE, depth_scale, quantize_depth
from .data.preprocess import resize_to_max_side
from .errors import DataError
from .export.files import atomic_output, write_json
from .ops.mvs import MVSConfig, MVSDepth, mvs_depth


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
    plus ``"output"`` (the folder).

    Raises:
        DataError: unreadable scene, or frames whose image stems collide.
        MVSError: fewer than 3 views, or a view without a usable source view.
    """
    start = time.perf_counter()
    scene = load_scene(run.scene)
    stems = _unique_stems(scene.frame_names)
    images, cameras = scene.decoded_images(), scene.cameras
    if run.max_size is not None:
        images, cameras = resize_to_max_side(images, cameras, run.max_size)
    V, _, height, width = images.shape
    with tqdm(total=V, desc="depth", unit="view", disable=None if run.progress else True, leave=False) as bar:
        result = mvs_depth((images.float() / 255).to(device), cameras.to(device, torch.float32), run.config,
                           progress=lambda done: bar.update(done - bar.n))  # fmt: skip
    near, far = float(cameras.near.min()), float(cameras.far.max())
    scale = depth_scale(far)
    out = pathlib.Path(run.out)
    shown = preview_range(result.depth, near, far)
    frames = []
    for v, (frame, stem) in enumerate(zip(scene.frame_names, stems)):
        frames.append(_write_view(out, stem, frame, images[v], result, v, scale, shown))
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    payload = {"format": DEPTH_FORMAT, "scale": scale, "width": width, "height": height, "near": near, "far": far,
               "frames": frames, "preview_depth_range": list(shown), "config": run.config.to_dict(), "max_size": run.max_size, "scene": str(run.scene),
               "device": str(device), "seconds": time.perf_counter() - start}
    write_json(out / INDEX_FILE, payload)
    return {**payload, "output": str(out)}


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


def _write_view(out: pathlib.Path, stem: str, frame: str, image: torch.Tensor, result: MVSDepth, v: int,
                scale: float, shown: tuple[float, float]) -> dict:  # fmt: skip
    """Write view v's depth, mask and preview PNGs (colours spanning the depths ``shown``); returns its
    ``frames`` entry of ``depth.json``."""
    depth = result.depth[v].cpu()
    files = {"depth": f"depth/{stem}.png", "mask": f"mask/{stem}.png", "preview": f"preview/{stem}.png"}
    _write_png(out / files["depth"], quantize_depth(depth, scale))
    _write_png(out / files["mask"], np.where(result.mask[v].cpu().numpy(), 255, 0).astype(np.uint8))
    _write_png(out / files["preview"], preview_image(image, depth, *shown))
    sources = [int(s) for s in result.sources.index[v].tolist() if s >= 0]
    return {"file": frame, "depth": files["depth"], "mask": files["mask"], "preview": files["preview"],
            "coverage": float(result.coverage[v]), "sources": sources}


def _write_png(path: pathlib.Path, array: np.ndarray) -> None:
    """Write a uint8 (grey or RGB) or uint16 (grey) array as a PNG, atomically."""
    with atomic_output(path) as tmp:
        Image.fromarray(array).save(tmp, format="PNG")


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
