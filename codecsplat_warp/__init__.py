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

from .cameras import Cameras
from .data import load_scene
from .model.codecsplat import CodecSplat
from .model.pretrained import load_pretrained
from .ops.geometry import reproject_average, unproject
from .ops.raster import rasterize

__version__ = "0.1.0"

__all__ = ["CodecSplat", "Cameras", "load_pretrained", "load_scene", "rasterize", "unproject", "reproject_average"]
