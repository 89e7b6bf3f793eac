"""Full-reference image metrics of the paper's tables: PSNR, SSIM and LPIPS (VGG and AlexNet).

* **PSNR** (dB) of the prediction clipped to [0, 1] against the target: ``-10 log10(MSE)`` per image
  (identical images give +inf); the one PSNR of the package, also of the training logs and the benchmarks
  (``clip=False`` for raw values).
* **SSIM** (Wang et al. 2004) with an 11x11 Gaussian window (sigma 1.5), data range 1, C1 = (0.01)^2,
  C2 = (0.03)^2, population (not sample) statistics, averaged over the valid (unpadded) region and the
  three channels: the setting of scikit-image's ``structural_similarity(win_size=11, gaussian_weights=True,
  use_sample_covariance=False, data_range=1, channel_axis=...)`` that pixelSplat / DepthSplat evaluate
  with. Computed by ``kornia.metrics.ssim`` in float64 (tests/test_metrics_image.py checks it against
  scikit-image on real photographs).
* **LPIPS** v0.1 with VGG16 and AlexNet trunks (:class:`~codecsplat_warp.metrics.lpips.LPIPS`).

All functions take batches [B,3,H,W] of floats in [0,1] and return one value per image, [B] float64.
"""

from __future__ import annotations

import os
import weakref

import kornia
import torch

from ..checks import check_tensor, common_device
from ..errors import InputError
from .lpips import LPIPS, resolve_weights_dir

SSIM_WINDOW = 11
"""Side of the Gaussian SSIM window in pixels (sigma 1.5, kornia's fixed value)."""

_FLOATS = (torch.float32, torch.float64, torch.float16, torch.bfloat16)


def _check_pair(prediction: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Both images as float64 [B,3,H,W] on one device; InputError on shape, dtype or device mismatch."""
    dims: dict[str, int] = {}
    prediction = check_tensor("prediction", prediction, ("B", 3, "H", "W"), _FLOATS, dims)
    target = check_tensor("target", target, ("B", 3, "H", "W"), _FLOATS, dims)
    common_device(prediction=prediction, target=target)
    return prediction.double(), target.double()


def psnr(prediction: torch.Tensor, target: torch.Tensor, clip: bool = True) -> torch.Tensor:
    """PSNR in dB [B] float64 of ``prediction`` against ``target`` (both [B,3,H,W], peak value 1).

    ``clip`` (the paper's metric, training logs included) clips the prediction to [0, 1] first, as an image
    written to disk would be; ``clip=False`` compares the raw values (two renderers' outputs, which may
    leave [0, 1]). Identical images give +inf.
    """
    prediction, target = _check_pair(prediction, target)
    if clip:
        prediction = prediction.clamp(0.0, 1.0)
    mse = ((prediction - target) ** 2).mean(dim=(1, 2, 3))
    return -10.0 * torch.log10(mse)


def ssim(prediction: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean SSIM [B] (11x11 Gaussian window, see the module docstring) of ``prediction`` clipped to [0, 1].

    Raises:
        InputError: images smaller than the window (11 pixels) on either side, or mismatched inputs.
    """
    prediction, target = _check_pair(prediction, target)
    if min(prediction.shape[-2:]) < SSIM_WINDOW:
        raise InputError(f"SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels, "
                         f"got {prediction.shape[-1]}x{prediction.shape[-2]}")
    index_map = kornia.metrics.ssim(prediction.clamp(0.0, 1.0), target, SSIM_WINDOW, max_val=1.0, eps=0.0,
                                    padding="valid")
    return index_map.mean(dim=(1, 2, 3))


class ImageMetrics:
    """PSNR, SSIM and, when LPIPS weights are available, LPIPS-VGG and LPIPS-Alex of image batches.

    Args:
        lpips_weights: folder with ``lpips_vgg.safetensors`` / ``lpips_alex.safetensors``; None reads
            ``$CODECSPLAT_LPIPS_WEIGHTS``. When neither names a folder, LPIPS is left out
            (:attr:`lpips_missing` says why) rather than failing a whole evaluation.
        device: where the LPIPS networks run (the images are moved there).

    Raises:
        InputError: an explicitly given folder lacks the weight files or holds mismatching ones.
    """

    NAMES = ("psnr", "ssim", "lpips_vgg", "lpips_alex")
    """Keys of :meth:`__call__`'s result, in table order."""

    def __init__(self, lpips_weights: str | os.PathLike | None = None, device: torch.device | str = "cpu"):
        self.device = torch.device(device)
        self.lpips: dict[str, LPIPS] = {}
        self.lpips_missing: str | None = None
        self._target_cache: dict[str, tuple] = {}
        try:
            folder = resolve_weights_dir(lpips_weights)
        except InputError as exc:
            self.lpips_missing = str(exc)
            return
        for net in ("vgg", "alex"):
            self.lpips[net] = LPIPS(net, folder).to(self.device)

    def __call__(self, prediction: torch.Tensor, target: torch.Tensor) -> dict[str, list[float]]:
        """Per-image values {name: [B floats]} of prediction vs target [B,3,H,W] in [0,1] (LPIPS keys only
        when weights are loaded). The LPIPS features of the last target are kept while that tensor lives
        unchanged: a demo or an evaluation scores several methods against one target in a row."""
        values = {"psnr": psnr(prediction, target), "ssim": ssim(prediction, target)}
        with torch.no_grad():
            for net, model in self.lpips.items():
                x, _ = model.check_images(prediction.clamp(0.0, 1.0).to(self.device), target.to(self.device))
                values[f"lpips_{net}"] = model.distance(model.unit_features(x), self._target_units(net, target))
        return {name: [float(v) for v in value] for name, value in values.items()}

    def _target_units(self, net: str, target: torch.Tensor) -> list[torch.Tensor]:
        """LPIPS ``net``'s unit features of ``target``, reused while it is the same tensor at the same version."""
        cached = self._target_cache.get(net)
        if cached is not None and cached[0]() is target and cached[1] == target._version:
            return cached[2]
        units = self.lpips[net].unit_features(target.to(self.device))
        self._target_cache[net] = (weakref.ref(target), target._version, units)
        return units
