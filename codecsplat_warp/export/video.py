"""Novel-view paths and frame output: orbit cameras around a decoded scene, PNG frames, GIF and MP4 files.

GIF is written by Pillow; MP4 (H.264) by an imageio video plugin: ``imageio-ffmpeg`` (a dependency of the
package, which bundles an ffmpeg binary) or, where only it is installed, PyAV (``av``). Both Pillow and
imageio-ffmpeg come with ``pip install codecsplat-warp``.
"""

from __future__ import annotations

import importlib.util
import math
import os
import pathlib

import numpy as np
import torch

from ..cameras import Cameras
from ..choices import FRAME_FORMATS
from ..data.procedural import look_at
from ..errors import InputError
from .files import atomic_output

FORMATS = FRAME_FORMATS
"""Output formats of :func:`write_frames`."""

MP4_PLUGINS = (("imageio_ffmpeg", "FFMPEG"), ("av", "pyav"))
"""(module, imageio plugin) pairs that can write MP4, in order of preference."""

MP4_FFMPEG_MACRO_BLOCK = 2
"""imageio-ffmpeg rounds frame sides up to a multiple of this (its default, 16, resized 30x20 frames to 32x32);
2 is what H.264 in yuv420p needs, so even-sided frames keep their size and odd sides grow by one pixel."""

MP4_MISSING = "--format mp4 needs an imageio video plugin: pip install imageio-ffmpeg (or pip install av)"

ORBIT_MIN_RADIUS_FRACTION = 0.05
"""The orbit radius is at least this fraction of the focus distance (for context cameras at one spot)."""


def mp4_plugin() -> str | None:
    """The imageio plugin that will write MP4 here, or None when none is installed."""
    for module, plugin in MP4_PLUGINS:
        if importlib.util.find_spec(module) is not None:
            return plugin
    return None


def orbit_cameras(context: Cameras, depth: torch.Tensor, count: int) -> Cameras:
    """``count`` cameras on a circle around the context viewpoint, all looking at the scene's focus point.

    The circle lies in the plane of the mean context image (its right and down axes), centred on the
    mean context camera centre, with a radius equal to the largest distance of a context camera from that
    centre (at least :data:`ORBIT_MIN_RADIUS_FRACTION` of the focus distance). The focus point lies along
    the mean viewing direction at the median of ``depth`` [V,H,W] (metric camera z). The cameras keep the
    first context camera's intrinsics and image size and the context's overall near/far range: they stay
    where the context views saw the scene, so the renders show parallax without leaving it.
    """
    if count < 1:
        raise InputError(f"an orbit needs at least 1 camera, got {count}")
    c2w = context.c2w.detach().to("cpu", torch.float64)
    centres = c2w[:, :3, 3]
    centre = centres.mean(0)
    forward = torch.nn.functional.normalize(c2w[:, :3, 2].mean(0), dim=0)
    down = torch.nn.functional.normalize(c2w[:, :3, 1].mean(0) - forward * (c2w[:, :3, 1].mean(0) @ forward), dim=0)
    right = torch.linalg.cross(down, forward)
    focus_distance = float(depth.detach().double().median())
    radius = max(float((centres - centre).norm(dim=-1).max()), ORBIT_MIN_RADIUS_FRACTION * focus_distance)
    angles = 2 * math.pi * torch.arange(count, dtype=torch.float64) / count
    eyes = centre + radius * (angles.cos()[:, None] * right + angles.sin()[:, None] * down)
    focus = (centre + focus_distance * forward).expand(count, 3)
    poses = look_at(eyes, focus, up=tuple((-down).tolist()))
    near, far = float(context.near.min()), float(context.far.max())
    K = context.K[:1].detach().to("cpu", torch.float64).expand(count, 3, 3)
    cameras = Cameras.from_c2w(K, poses, torch.full((count,), near, dtype=torch.float64),
                               torch.full((count,), far, dtype=torch.float64), context.width, context.height)
    return cameras.to(context.device, context.dtype)


def to_uint8_frames(rgb: torch.Tensor) -> np.ndarray:
    """uint8 [B,H,W,3] frames of float images [B,3,H,W] (clipped to [0,1], rounded)."""
    return (rgb.detach().clamp(0, 1) * 255).round().to(torch.uint8).permute(0, 2, 3, 1).cpu().numpy()


def write_frames(folder: str | os.PathLike, frames: np.ndarray, format: str, fps: float = 30.0) -> list[pathlib.Path]:
    """Write uint8 frames [F,H,W,3] into ``folder``: ``frame_0000.png`` ... (png), ``render.gif`` or
    ``render.mp4`` (H.264 at the frames' size when H and W are even, see :data:`MP4_FFMPEG_MACRO_BLOCK`);
    each file atomically. Returns the written paths.

    Raises:
        InputError: unknown format, fps <= 0, or mp4 without a video plugin (:data:`MP4_MISSING`).
    """
    import imageio.v3 as iio

    if format not in FORMATS:
        raise InputError(f"unknown frame format {format!r}; choose one of {', '.join(FORMATS)}")
    if not fps > 0:
        raise InputError(f"fps must be > 0, got {fps}")
    folder = pathlib.Path(folder)
    if format == "png":
        paths = [folder / f"frame_{i:04d}.png" for i in range(len(frames))]
        for path, frame in zip(paths, frames):
            with atomic_output(path) as tmp:
                iio.imwrite(tmp, frame, extension=".png")
        return paths
    path = folder / f"render.{format}"
    with atomic_output(path) as tmp:
        if format == "gif":
            iio.imwrite(tmp, frames, extension=".gif", duration=1000.0 / fps, loop=0)
        else:
            plugin = mp4_plugin()
            if plugin is None:
                raise InputError(MP4_MISSING)
            options = {"macro_block_size": MP4_FFMPEG_MACRO_BLOCK} if plugin == "FFMPEG" else {}
            iio.imwrite(tmp, frames, extension=".mp4", plugin=plugin, fps=fps, codec="libx264", **options)
    return [path]
