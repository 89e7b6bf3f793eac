"""Depth map folders (``codecsplat depth`` writes them): format, quantisation and :func:`read_depth_maps`.

A folder ``OUT`` in the ``codecsplat-depth-v1`` format holds:

* ``OUT/depth/<image stem>.png``: uint16 PNG, camera-z depth in scene units = value * ``scale``, 0 = no depth;
* ``OUT/mask/<image stem>.png``: uint8 PNG, 255 where a depth is kept, 0 elsewhere;
* ``OUT/preview/<image stem>.png``: the image beside its turbo-coloured inverse depth (black: no depth);
* ``OUT/depth.json``: ``{"format": "codecsplat-depth-v1", "scale", "width", "height", "near", "far", "frames":
  [{"file": image path as in the scene, "depth": "depth/<stem>.png", "mask": "mask/<stem>.png", "coverage",
  "sources": [frame indices]}], "config": {MVS parameters}, "device", "seconds", ...}``. It is written last, so
  a folder whose writer was interrupted has none.

Depth maps cover the same image extent as the photographs (at ``width`` x ``height``, any size of the same
aspect can be had by resampling). ``scale`` = far / 65535, so a kept depth d in [near, far] is stored as
round(d / scale): reading loses at most scale / 2 = far / 131070 (:func:`quantization_error`).
"""

from __future__ import annotations

import json
import pathlib
from dataclasses import dataclass

import numpy as np
import torch
from PIL import Image

from ..errors import DataError

DEPTH_FORMAT = "codecsplat-depth-v1"
"""The ``format`` field of ``depth.json``."""

INDEX_FILE = "depth.json"
"""The index file of a depth map folder."""

DEPTH_LEVELS = 65535
"""Largest stored depth value (uint16); ``scale`` maps it to the far bound."""


@dataclass(frozen=True)
class DepthMaps:
    """Depth maps of a folder read by :func:`read_depth_maps`.

    Attributes:
        depth: float32 [N,h,w] camera-z depth in scene units, 0 where there is none.
        frames: N image paths as in the scene (e.g. ``images/x.jpg``), to match the scene's ``frame_names``.
        sources: N lists of the source frame indices each depth map was computed from.
        coverage: N fractions of pixels with a depth (as written).
        scale: scene units per stored depth level.
        near, far: depth range of the sweep (scene units).
        index: the whole ``depth.json`` (config, device, seconds, ...).
    """

    depth: torch.Tensor
    frames: list[str]
    sources: list[list[int]]
    coverage: list[float]
    scale: float
    near: float
    far: float
    index: dict

    @property
    def mask(self) -> torch.Tensor:
        """bool [N,h,w], True where a depth is stored."""
        return self.depth > 0

    def frame_index(self, name: str) -> int:
        """Position of the frame named ``name`` (an image path as in the scene); DataError if absent."""
        try:
            return self.frames.index(name)
        except ValueError:
            raise DataError(f"no depth map for frame {name!r} (the folder has {len(self.frames)} frames)") from None


def depth_scale(far: float) -> float:
    """Scene units per stored level for depths up to ``far``: far / :data:`DEPTH_LEVELS`."""
    return float(far) / DEPTH_LEVELS


def quantization_error(scale: float) -> float:
    """Largest absolute depth error (scene units) of writing and reading a depth in range: half a level."""
    return 0.5 * scale


def quantize_depth(depth: torch.Tensor, scale: float) -> np.ndarray:
    """uint16 [h,w] stored levels of a float [h,w] depth map (0 stays 0; a kept depth is at least level 1).

    Raises:
        DataError: a depth beyond the last level (depth > 65535.5 * scale).
    """
    values = depth.detach().to("cpu", torch.float64).numpy()
    levels = np.rint(values / scale)
    if levels.max(initial=0) > DEPTH_LEVELS:
        raise DataError(f"depth {values.max():g} exceeds the storable range {DEPTH_LEVELS * scale:g} (scale {scale:g})")
    levels = np.where(values > 0, np.maximum(levels, 1), 0)
    return levels.astype(np.uint16)


def dequantize_depth(levels: np.ndarray, scale: float) -> torch.Tensor:
    """float32 [h,w] depth of stored uint16 levels (0 stays 0)."""
    return torch.from_numpy((levels.astype(np.float64) * scale).astype(np.float32))


def read_depth_maps(folder) -> DepthMaps:
    """Read a depth map folder in the :data:`DEPTH_FORMAT` (see the module docstring).

    Raises:
        DataError: missing folder or ``depth.json``, another format, missing or undecodable PNG, or a PNG that
            is not 16-bit or not of the size ``depth.json`` states (naming the file).
    """
    folder = pathlib.Path(folder)
    index_file = folder / INDEX_FILE
    if not folder.is_dir():
        raise DataError(f"depth map folder {folder} does not exist")
    if not index_file.is_file():
        raise DataError(f"{index_file} does not exist (not a depth map folder, or its writer was interrupted)")
    try:
        index = json.loads(index_file.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DataError(f"{index_file}: cannot read JSON: {exc}") from None
    if not isinstance(index, dict) or index.get("format") != DEPTH_FORMAT:
        got = index.get("format") if isinstance(index, dict) else type(index).__name__
        raise DataError(f"{index_file}: format must be {DEPTH_FORMAT!r}, got {got!r}")
    try:
        scale, width, height = float(index["scale"]), int(index["width"]), int(index["height"])
        frames = list(index["frames"])
        files = [str(frame["depth"]) for frame in frames]
        names = [str(frame["file"]) for frame in frames]
        sources = [[int(s) for s in frame["sources"]] for frame in frames]
        coverage = [float(frame["coverage"]) for frame in frames]
        near, far = float(index["near"]), float(index["far"])
    except (KeyError, TypeError, ValueError) as exc:
        raise DataError(f"{index_file}: missing or malformed field: {exc!r}") from None
    if not frames:
        raise DataError(f"{index_file}: holds no frame")
    depth = torch.stack([dequantize_depth(_read_levels(folder / f, width, height), scale) for f in files])
    return DepthMaps(depth=depth, frames=names, sources=sources, coverage=coverage, scale=scale, near=near, far=far,
                     index=index)


def _read_levels(path: pathlib.Path, width: int, height: int) -> np.ndarray:
    """uint16 [height,width] levels of one depth PNG; DataError naming the file otherwise."""
    try:
        with Image.open(path) as image:
            mode = image.mode
            levels = np.asarray(image)
    except FileNotFoundError:
        raise DataError(f"depth map {path} does not exist") from None
    except (OSError, ValueError) as exc:
        raise DataError(f"cannot decode depth map {path}: {exc}") from None
    if mode not in ("I;16", "I;16B", "I;16L", "I") or levels.ndim != 2:
        raise DataError(f"depth map {path} must be a 16-bit grey PNG, got mode {mode}")
    if levels.shape != (height, width):
        raise DataError(f"depth map {path} is {levels.shape[1]}x{levels.shape[0]}, depth.json says {width}x{height}")
    if levels.min(initial=0) < 0 or levels.max(initial=0) > DEPTH_LEVELS:
        raise DataError(f"depth map {path} holds values outside 0..{DEPTH_LEVELS}")
    return levels.astype(np.uint16)
