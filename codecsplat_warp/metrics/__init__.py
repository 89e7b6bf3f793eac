"""Image metrics: LPIPS (VGG16 / AlexNet trunks, weights from safetensors files)."""

from .lpips import LPIPS, WEIGHTS_ENV, resolve_weights_dir

__all__ = ["LPIPS", "WEIGHTS_ENV", "resolve_weights_dir"]
