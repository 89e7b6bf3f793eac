"""Network building blocks shared by the model (:mod:`codecsplat_warp.model`), the latent codec
(:mod:`codecsplat_warp.codec`) and the metrics (LPIPS):

* :mod:`.config`: :class:`ModelConfig` (the sizes of the network and its codec), the presets and the
  strides (:data:`MODEL_STRIDE`, :data:`FEATURE_STRIDE`);
* :mod:`.layers`: convolutions, residual blocks, resizing, the VGG16 trunk and :func:`copy_weights`;
* :mod:`.mono`: the frozen pretrained monocular backbones of MVEnc's mono slot.

Nothing here imports the model or the codec.
"""

from .config import FEATURE_STRIDE, MODEL_STRIDE, PRESETS, ModelConfig, get_preset

__all__ = ["FEATURE_STRIDE", "MODEL_STRIDE", "PRESETS", "ModelConfig", "get_preset"]
