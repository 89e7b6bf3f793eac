"""Sizes of the CodecSplat network (backbone and latent codec), as frozen dataclasses with named presets.

Presets:

* ``re10k``: 2 context views at 256x256 (RealEstate10K protocol of the paper).
* ``dl3dv``: 8 context views at 256x448 (DL3DV protocol); each view attends to / matches against its
  2 nearest neighbours by camera distance.
* ``tiny``: a few thousand parameters at 32x48, for CPU tests (a forward pass takes well under a second).

The image size of a preset is the training size; the network itself accepts any V >= 2 and any H, W
divisible by 4 (:data:`MODEL_STRIDE`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

from ..errors import InputError
from .mono import MONO_BACKBONES

MODEL_STRIDE = 4
"""Image height and width must be multiples of this (the matching grid is 1/4 resolution)."""

FEATURE_STRIDE = 2
"""The Gaussian-generation feature F_g lives on the 1/2-resolution grid (see :mod:`codecsplat_warp.model.feathead`)."""


LATER_FIELDS = {"codec_finest_stride": 4, "photometric_window": 0}
"""ModelConfig fields that earlier model files lack, with the value those files imply."""


@dataclass(frozen=True)
class ModelConfig:
    """Hyper-parameters of :class:`~codecsplat_warp.model.codecsplat.CodecSplat`.

    Attributes:
        name: preset name (informational).
        num_views: number of context views the preset is trained with.
        height, width: training image size in pixels (multiples of 4).
        num_target_views: target views rendered per training sample.
        cnn_channels: channels of the 1/4-resolution image features (MVEnc CNN and attention width).
        attention_layers: self + cross-view attention blocks on the 1/4 grid.
        attention_heads: heads of every attention (must divide ``cnn_channels``).
        neighbours: k nearest views (by camera-centre distance) each view attends to and matches
            against when V - 1 > k; with fewer views every other view is used.
        depth_candidates: D, plane-sweep depths uniform in inverse depth between near and far.
        depth_channels: width of the cost-volume regressor and of the full-resolution depth refiner.
        feature_channels: C_F, channels of the Gaussian-generation feature F_g (1/2 resolution, see
            :mod:`codecsplat_warp.model.feathead`).
        refine_channels: width of the depth-guided refiner R.
        head_channels: width of the Gaussian and depth heads.
        sh_degree: spherical-harmonics degree of the Gaussian colours (DepthSplat uses 2).
        scale_min_px, scale_max_px: Gaussian scale range in pixel footprints (scale = s * depth / focal).
        max_offset_px: largest sub-pixel offset of a Gaussian centre, in pixels.
        codec_channels: width of the latent codec (analysis, top-down and synthesis), see
            :mod:`codecsplat_warp.codec.latent`.
        codec_latent_channels: channels of each latent level, coarsest first; level l of L sits at stride
            ``codec_finest_stride * 2**(L-1-l)`` of the feature grid.
        codec_finest_stride: stride of the finest latent level on the feature grid, a power of two >= 2
            (4: 1/8 of the image, as in the shipped model; 2: 1/4 of the image, as in model dce2a7bfd3a0b5f0).
        lambda_channels: size of the rate embedding e_lambda.
        mono: pretrained monocular backbone in MVEnc's mono slot: ``"none"`` or a name of
            :data:`codecsplat_warp.nn.mono.MONO_BACKBONES` (``"vgg16"``: frozen ImageNet VGG16 to relu3_3).
        photometric_window: side (odd, pixels) of the grey-level windows of MVEnc's photometric cost volume, a
            plane sweep of windowed NCC at full resolution next to the learned one (see
            :mod:`codecsplat_warp.model.mvenc`); 0: none (every model shipped before 2026-11-25).
    """

    name: str = "custom"
    num_views: int = 2
    height: int = 256
    width: int = 256
    num_target_views: int = 4
    cnn_channels: int = 128
    attention_layers: int = 2
    attention_heads: int = 4
    neighbours: int = 2
    depth_candidates: int = 64
    depth_channels: int = 64
    feature_channels: int = 32
    refine_channels: int = 64
    head_channels: int = 64
    sh_degree: int = 2
    scale_min_px: float = 0.5
    scale_max_px: float = 15.0
    max_offset_px: float = 0.5
    codec_channels: int = 48
    codec_latent_channels: tuple[int, ...] = (16, 24, 32)
    codec_finest_stride: int = 4
    lambda_channels: int = 64
    mono: str = "none"
    photometric_window: int = 0

    def __post_init__(self) -> None:
        latent = self.codec_latent_channels
        if not isinstance(latent, (list, tuple)) or not latent or any(not isinstance(c, int) or c < 1 for c in latent):
            raise InputError(f"ModelConfig.codec_latent_channels must be a non-empty list of positive ints, "
                             f"got {latent!r}")
        object.__setattr__(self, "codec_latent_channels", tuple(latent))  # JSON gives a list
        positive = ("num_views", "height", "width", "num_target_views", "cnn_channels", "attention_heads",
                    "neighbours", "depth_candidates", "depth_channels", "feature_channels", "refine_channels",
                    "head_channels", "codec_channels", "lambda_channels")
        for name in positive:
            if int(getattr(self, name)) < 1:
                raise InputError(f"ModelConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.attention_layers < 0:
            raise InputError(f"ModelConfig.attention_layers must be >= 0, got {self.attention_layers}")
        if self.height % MODEL_STRIDE or self.width % MODEL_STRIDE:
            raise InputError(f"ModelConfig height/width must be multiples of {MODEL_STRIDE}, "
                             f"got {self.height}x{self.width}")
        if self.cnn_channels % 4:
            raise InputError(f"ModelConfig.cnn_channels must be a multiple of 4 (2D sine positions), "
                             f"got {self.cnn_channels}")
        if self.cnn_channels % self.attention_heads:
            raise InputError(f"ModelConfig.attention_heads={self.attention_heads} must divide "
                             f"cnn_channels={self.cnn_channels}")
        if self.depth_candidates < 2:
            raise InputError(f"ModelConfig.depth_candidates must be >= 2, got {self.depth_candidates}")
        if not 0 <= self.sh_degree <= 3:
            raise InputError(f"ModelConfig.sh_degree must be 0..3, got {self.sh_degree}")
        if not 0 < self.scale_min_px < self.scale_max_px:
            raise InputError(f"ModelConfig needs 0 < scale_min_px < scale_max_px, got "
                             f"{self.scale_min_px}, {self.scale_max_px}")
        stride = self.codec_finest_stride
        if not isinstance(stride, int) or stride < 2 or stride & (stride - 1):
            raise InputError(f"ModelConfig.codec_finest_stride must be a power of two >= 2, got {stride!r}")
        if self.mono != "none" and self.mono not in MONO_BACKBONES:
            raise InputError(f"ModelConfig.mono must be none or one of {', '.join(MONO_BACKBONES)}, got {self.mono!r}")
        if self.photometric_window and (self.photometric_window < 3 or self.photometric_window % 2 == 0):
            raise InputError(f"ModelConfig.photometric_window must be 0 or an odd number >= 3, "
                             f"got {self.photometric_window}")
        if self.num_views < 2:
            raise InputError(f"ModelConfig.num_views must be >= 2 (matching needs a second view), got {self.num_views}")

    def to_dict(self) -> dict:
        """Plain dict (JSON-serialisable), the inverse of :meth:`from_dict`. Fields added after model files
        were shipped (:data:`LATER_FIELDS`) are left out at the value those files imply, so that their
        config, and with it their weights digest and model id, stay what they were."""
        values = asdict(self)
        for name, implied in LATER_FIELDS.items():
            if values[name] == implied:
                del values[name]
        return values

    @classmethod
    def from_dict(cls, values: dict) -> "ModelConfig":
        """Config from a dict; unknown keys raise InputError naming them."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise InputError(f"unknown ModelConfig field(s): {', '.join(unknown)}")
        return cls(**values)


PRESETS: dict[str, ModelConfig] = {
    "re10k": ModelConfig(name="re10k", num_views=2, height=256, width=256),
    "dl3dv": ModelConfig(name="dl3dv", num_views=8, height=256, width=448, neighbours=2),
    "tiny": ModelConfig(name="tiny", num_views=2, height=32, width=48, num_target_views=2, cnn_channels=16,
                        attention_layers=1, attention_heads=2, depth_candidates=8, depth_channels=16,
                        feature_channels=8, refine_channels=16, head_channels=16, sh_degree=1, codec_channels=16,
                        codec_latent_channels=(4, 8), lambda_channels=16),
}
"""Named presets; see the module docstring."""


def get_preset(name: str) -> ModelConfig:
    """The preset called ``name`` (``re10k``, ``dl3dv``, ``tiny``); InputError listing them otherwise."""
    try:
        return PRESETS[name]
    except KeyError:
        raise InputError(f"unknown model preset {name!r}; choose one of {', '.join(PRESETS)}") from None
