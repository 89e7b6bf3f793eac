"""codecsplat-warp: CodecSplat (feed-forward 3DGS with a learned scene bitstream) on NVIDIA Warp kernels.

The front door::

    from codecsplat_warp import CodecSplat, Cameras, load_pretrained, load_scene, rasterize, unproject, reproject_average

Everything else lives in the subpackages, in layers that only import downwards (the contracts are in
pyproject.toml): :mod:`codecsplat_warp.kernels` (pure Warp), :mod:`~codecsplat_warp.errors` and
:mod:`~codecsplat_warp.measure` (timing, usable from every layer) -> :mod:`~codecsplat_warp.device` ->
:mod:`~codecsplat_warp.cameras` (conventions), :mod:`~codecsplat_warp.gaussians`, :mod:`~codecsplat_warp.nn` ->
:mod:`~codecsplat_warp.ops` (differentiable Warp ops) -> :mod:`~codecsplat_warp.codec` (latents, entropy
coding, bitstream) -> :mod:`~codecsplat_warp.model` (the network) -> data, metrics, export, baselines ->
:mod:`~codecsplat_warp.eval` -> bench, demo, depth, selfcheck -> :mod:`~codecsplat_warp.cli`.
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

_FRONT_DOOR = {
    "CodecSplat": ".model.codecsplat",
    "Cameras": ".cameras",
    "load_pretrained": ".model.pretrained",
    "load_scene": ".data",
    "rasterize": ".ops.raster",
    "unproject": ".ops.geometry",
    "reproject_average": ".ops.geometry",
}
"""Each front-door name and the module that defines it, imported on first use (PEP 562), so that importing a light
module such as :mod:`codecsplat_warp.errors` (the command line does, to answer ``--help`` at once) does not
import torch and Warp."""

__all__ = list(_FRONT_DOOR)


def __getattr__(name: str):
    module = _FRONT_DOOR.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(module, __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_FRONT_DOOR])
