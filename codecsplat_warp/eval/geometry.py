"""Depth error against reference multi-view-stereo depth, for ``codecsplat eval`` and ``train.validate``.

The reference of a scene is ``DIR/<scene folder name>/depth.json`` (format ``codecsplat-depth-v1``, written by
``codecsplat depth SCENE -o DIR/<scene>``)::

    {"format": "codecsplat-depth-v1", "scale": s, "width": w, "height": h, "near": ..., "far": ...,
     "frames": [{"file": "images/x.jpg", "depth": "depth/x.png", "mask": "mask/x.png", "coverage": c,
                 "sources": [...]}, ...]}

``file`` is the image path as in the scene's ``cameras.json``; ``depth/x.png`` is a 16-bit PNG of w x h
pixels covering the same image extent as the stored photograph: depth = value * s (camera z, scene units),
0 where the stereo kept no depth (read by :func:`~codecsplat_warp.data.depth_maps.read_depth_maps`).

:class:`ReferenceDepth` brings a sample's context views to the sample's grid: the protocol's resize to cover
and centre crop (:func:`~codecsplat_warp.data.preprocess.crop_geometry`), sampled at each pixel centre with
the nearest reference pixel, so 0 (no depth) stays invalid. :func:`depth_errors` scores a depth map against
it on the pixels with a reference (> 0): AbsRel = mean(|d - d_ref| / d_ref) and delta<1.25 = the fraction with
max(d / d_ref, d_ref / d) < 1.25, pooled over the pixels of all context views of the sample.
"""

from __future__ import annotations

import pathlib

import numpy as np
import torch

from ..data.depth_maps import INDEX_FILE, DepthMaps, read_depth_maps
from ..data.preprocess import crop_geometry
from ..errors import DataError

DELTA_THRESHOLD = 1.25


def to_sample_grid(depth: np.ndarray, stored_size: tuple[int, int], size: tuple[int, int]) -> np.ndarray:
    """A depth map [h,w] covering a stored photograph of ``stored_size`` (width, height), brought to the grid of
    that photograph resized to cover ``size`` (width, height) and centre-cropped: nearest reference pixel at
    each pixel centre. Returns [size[1], size[0]], same dtype."""
    height, width = depth.shape
    scaled_w, scaled_h, left, top = crop_geometry(*stored_size, *size)
    cols = np.floor((np.arange(size[0]) + 0.5 + left) / scaled_w * width).astype(np.int64).clip(0, width - 1)
    rows = np.floor((np.arange(size[1]) + 0.5 + top) / scaled_h * height).astype(np.int64).clip(0, height - 1)
    return depth[rows[:, None], cols[None, :]]


class ReferenceDepth:
    """Reference depth of the samples' context views, from ``root/<scene>/depth.json``.

    A scene's depth maps are read when its first sample is due and kept until a sample of another scene comes.

    Raises:
        DataError: ``root`` is not a folder.
    """

    def __init__(self, root):
        self.root = pathlib.Path(root)
        if not self.root.is_dir():
            raise DataError(f"reference depth folder {self.root} does not exist (make it with codecsplat depth "
                            "SCENE -o DIR/<scene folder name>)")
        self._scene: tuple[str, DepthMaps | None] | None = None

    def context_depth(self, sample) -> torch.Tensor | None:
        """float64 [V,H,W] reference depth of ``sample``'s context views on its grid (0: none), or None when the
        scene has no ``depth.json`` or none of its context views has an entry there.

        Raises:
            DataError: a corrupt ``depth.json`` or depth PNG.
        """
        maps = self._maps(sample.scene)
        if maps is None or sample.stored_size is None or not set(sample.context_files) & set(maps.frames):
            return None
        size = (sample.context_cameras.width, sample.context_cameras.height)
        views = [to_sample_grid(maps.depth[maps.frames.index(f)].double().numpy(), sample.stored_size, size)
                 if f in maps.frames else np.zeros(size[::-1]) for f in sample.context_files]
        return torch.from_numpy(np.stack(views))

    def _maps(self, scene: str) -> DepthMaps | None:
        if self._scene is None or self._scene[0] != scene:
            folder = self.root / scene
            self._scene = scene, read_depth_maps(folder) if (folder / INDEX_FILE).is_file() else None
        return self._scene[1]


def depth_errors(depth: torch.Tensor, reference: torch.Tensor) -> dict[str, float]:
    """Errors of ``depth`` [V,H,W] against ``reference`` [V,H,W] (same units) on the pixels where the reference
    is > 0, pooled over the views.

    Returns:
        {"abs_rel": mean |d - d_ref| / d_ref, "delta_1_25": fraction with max(d/d_ref, d_ref/d) < 1.25 (d > 0),
        "pixels": pixels scored, "views": views with at least one}; empty when no pixel has a reference.
    """
    reference = reference.double().cpu()
    valid = reference > 0
    if not bool(valid.any()):
        return {}
    ratio = depth.detach().double().cpu()[valid] / reference[valid]
    within = (ratio > 0) & (torch.maximum(ratio, 1.0 / ratio) < DELTA_THRESHOLD)
    return {"abs_rel": float((ratio - 1.0).abs().mean()), "delta_1_25": float(within.double().mean()),
            "pixels": int(valid.sum()), "views": int(valid.flatten(1).any(dim=1).sum())}
