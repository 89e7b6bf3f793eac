"""Image metrics: PSNR, SSIM (11x11 Gaussian window) and LPIPS (VGG16 / AlexNet trunks, weights from safetensors files)."""

from .image import SSIM_WINDOW, ImageMetrics, psnr, ssim
from .lpips import LPIPS, WEIGHTS_ENV, resolve_weights_dir

__all__ = ["ImageMetrics", "LPIPS", "SSIM_WINDOW", "WEIGHTS_ENV", "psnr", "resolve_weights_dir", "ssim"]
