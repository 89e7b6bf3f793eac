"""Protocol preprocessing as DepthSplat / pixelSplat do it: resize (keeping the aspect ratio) so the image
covers the target size, then centre-crop; intrinsics follow through :meth:`Cameras.rescaled` and
:meth:`Cameras.cropped`. Dataset configurations give the protocol resolution and the depth range.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch
from PIL import Image

from ..cameras import Cameras
from ..errors import DataError
from .scene import Scene


@dataclass(frozen=True)
class DatasetConfig:
    """Protocol of one dataset: image size in pixels and the depth range given to every camera."""

    width: int
    height: int
    near: float
    far: float


DATASET_CONFIGS = {
    "re10k": DatasetConfig(width=256, height=256, near=0.5, far=100.0),
    "acid": DatasetConfig(width=256, height=256, near=1.0, far=100.0),
    "dl3dv": DatasetConfig(width=448, height=256, near=0.5, far=200.0),
}
"""DepthSplat's settings: RE10K 256x256 with near/far 0.5/100, ACID 1/100, DL3DV 256x448 (HxW) with 0.5/200."""


def dataset_config(name: str) -> DatasetConfig:
    """The configuration named ``name`` (``re10k``, ``acid``, ``dl3dv``); DataError for unknown names."""
    try:
        return DATASET_CONFIGS[name.lower()]
    except KeyError:
        raise DataError(f"unknown dataset config {name!r}; known: {', '.join(DATASET_CONFIGS)}") from None


def crop_geometry(in_width: int, in_height: int, width: int, height: int) -> tuple[int, int, int, int]:
    """(scaled_width, scaled_height, left, top): the resize that covers width x height, and the centred crop."""
    scale = max(height / in_height, width / in_width)
    scaled_w, scaled_h = max(width, round(in_width * scale)), max(height, round(in_height * scale))
    return scaled_w, scaled_h, (scaled_w - width) // 2, (scaled_h - height) // 2


def resize_and_crop(images: torch.Tensor, cameras: Cameras, width: int, height: int) -> tuple[torch.Tensor, Cameras]:
    """Resize uint8 [V,3,H,W] images (Lanczos, aspect kept) to cover ``width`` x ``height``, then centre-crop.

    Returns:
        uint8 [V,3,height,width] images and the cameras adjusted to them.
    """
    if images.dim() != 4 or images.shape[0] == 0 or images.shape[1] != 3 or images.dtype != torch.uint8:
        raise DataError(f"images must be uint8 [V,3,H,W] with V >= 1, got {images.dtype} {tuple(images.shape)}")
    in_h, in_w = images.shape[-2:]
    if (in_w, in_h) != (cameras.width, cameras.height):
        raise DataError(f"images are {in_w}x{in_h} but the cameras are {cameras.width}x{cameras.height}")
    scaled_w, scaled_h, left, top = crop_geometry(in_w, in_h, width, height)
    resized = torch.stack([resize_image(image, scaled_w, scaled_h) for image in images])
    cropped = resized[:, :, top:top + height, left:left + width].contiguous()
    return cropped, protocol_cameras(cameras, width, height)


def max_side_size(width: int, height: int, max_side: int) -> tuple[int, int]:
    """(width, height) of an image resized so that its long side is at most ``max_side`` pixels, aspect kept
    (sides rounded); the size itself when it already is."""
    if max_side < 1:
        raise DataError(f"max_side must be >= 1, got {max_side}")
    if max(width, height) <= max_side:
        return width, height
    scale = max_side / max(width, height)
    return max(1, round(width * scale)), max(1, round(height * scale))


def resize_to_max_side(images: torch.Tensor, cameras: Cameras, max_side: int) -> tuple[torch.Tensor, Cameras]:
    """uint8 [V,3,H,W] images resized (:func:`max_side_size`, :func:`resize_image`) so that the long side is at most
    ``max_side`` pixels, covering the whole image, and the cameras rescaled to them."""
    width, height = max_side_size(images.shape[-1], images.shape[-2], max_side)
    if (width, height) == tuple(images.shape[-1:-3:-1]):
        return images, cameras
    return torch.stack([resize_image(image, width, height) for image in images]), cameras.rescaled(width, height)


def protocol_cameras(cameras: Cameras, width: int, height: int) -> Cameras:
    """The cameras of images resized to cover ``width`` x ``height`` and centre-cropped (see :func:`resize_and_crop`)."""
    scaled_w, scaled_h, left, top = crop_geometry(cameras.width, cameras.height, width, height)
    return cameras.rescaled(scaled_w, scaled_h).cropped(left, top, width, height)


def preprocess_scene(scene: Scene, config: DatasetConfig | str, frames=None, use_config_depth_range: bool = True) -> Scene:
    """The frames of ``scene`` decoded, resized and centre-cropped to the protocol size of ``config``.

    Args:
        scene: any loaded scene.
        config: a :class:`DatasetConfig` or its name (``re10k``, ``dl3dv``, ``acid``).
        frames: view indices to keep (all when None).
        use_config_depth_range: give every camera the config's near/far (True, as DepthSplat does for
            RE10K/DL3DV) or keep the scene's own bounds (False, for formats that carry them).
    """
    config = dataset_config(config) if isinstance(config, str) else config
    if scene.depth is not None and (scene.cameras.width, scene.cameras.height) != (config.width, config.height):
        raise DataError(f"{scene.source}: resampling ground-truth depth is not supported; render at the protocol size")
    frames = list(range(scene.num_views)) if frames is None else [int(f) for f in frames]
    images, cameras = resize_and_crop(scene.decoded_images(frames), scene.cameras.select(frames),
                                      config.width, config.height)
    if use_config_depth_range:
        cameras = cameras.with_depth_range(config.near, config.far)
    return replace(scene.select(frames), images=images, cameras=cameras)

def resize_image(image: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """uint8 [3,H,W] image resized to ``width`` x ``height`` (Lanczos; the whole image, no crop)."""
    if tuple(image.shape[1:]) == (height, width):
        return image
    pil = Image.fromarray(image.permute(1, 2, 0).numpy())
    resized = np.asarray(pil.resize((width, height), Image.Resampling.LANCZOS))
    return torch.from_numpy(resized.copy()).permute(2, 0, 1)
