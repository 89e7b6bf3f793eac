"""The CodecSplat network (codec-free path): MVEnc, FeatHead, refiner, heads, 2D->3D map.

Entry point: ``CodecSplat(get_preset("re10k"))`` (presets in :mod:`codecsplat_warp.nn.config`); see
:mod:`.codecsplat`. The world-space :class:`~codecsplat_warp.gaussians.Gaussians` live in
:mod:`codecsplat_warp.gaussians`.
"""

from .codecsplat import CodecSplat, model_id
from .feathead import FeatHead
from .heads import DepthHead, GaussianHead, PixelGaussians, depth_from_normalized, map_to_world, normalized_from_depth
from .mvenc import MonoBackbone, MVEnc, MVEncOutput
from .refine import Refiner

__all__ = [
    "CodecSplat", "model_id", "FeatHead", "DepthHead", "GaussianHead", "PixelGaussians", "depth_from_normalized", "map_to_world",
    "normalized_from_depth", "MonoBackbone", "MVEnc", "MVEncOutput", "Refiner",
]
