"""The CodecSplat network (codec-free path): MVEnc, FeatHead, refiner, heads, 2D->3D map, presets.

Entry point: ``CodecSplat(get_preset("re10k"))``; see :mod:`.codecsplat`.
"""

from .codecsplat import CodecSplat
from .config import FEATURE_STRIDE, MODEL_STRIDE, PRESETS, ModelConfig, get_preset
from .feathead import FeatHead
from .gaussians import Gaussians, map_to_world, quat_multiply, quat_to_rotmat, rotate_sh, rotmat_to_quat, sh_basis
from .heads import DepthHead, GaussianHead, PixelGaussians, depth_from_normalized, normalized_from_depth
from .mvenc import MonoBackbone, MVEnc, MVEncOutput
from .refine import Refiner

__all__ = [
    "CodecSplat",
    "FEATURE_STRIDE", "MODEL_STRIDE", "PRESETS", "ModelConfig", "get_preset", "FeatHead", "Gaussians",
    "map_to_world", "quat_multiply", "quat_to_rotmat", "rotate_sh", "rotmat_to_quat", "sh_basis", "DepthHead",
    "GaussianHead", "PixelGaussians", "depth_from_normalized", "normalized_from_depth", "MonoBackbone", "MVEnc",
    "MVEncOutput", "Refiner",
]
