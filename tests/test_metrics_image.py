"""PSNR / SSIM / ImageMetrics against known values and against scikit-image on real photographs."""

from __future__ import annotations

import math

import pytest
import torch
from skimage.metrics import structural_similarity

from codecsplat_warp.errors import InputError
from codecsplat_warp.metrics import ImageMetrics, psnr, ssim
from conftest import LPIPS_WEIGHTS, needs_lpips


def _grey(value: float, size=(2, 3, 24, 32)) -> torch.Tensor:
    return torch.full(size, value, dtype=torch.float32)


def test_psnr_known_cases():
    target = _grey(0.5)
    assert torch.isinf(psnr(target, target)).all()
    assert psnr(target + 0.1, target).tolist() == pytest.approx([20.0, 20.0], abs=1e-5)
    noise = torch.randn(2, 3, 256, 256, generator=torch.Generator().manual_seed(1), dtype=torch.float64) * 0.05
    assert psnr(0.5 + noise, _grey(0.5, noise.shape)).tolist() == pytest.approx([-10 * math.log10(0.05**2)] * 2, abs=0.05)


def test_psnr_clips_the_prediction_to_the_unit_range():
    target = torch.cat([_grey(0.0, (1, 3, 16, 16)), _grey(0.9, (1, 3, 16, 16))])
    prediction = torch.cat([_grey(-0.5, (1, 3, 16, 16)), _grey(1.2, (1, 3, 16, 16))])
    values = psnr(prediction, target)
    assert math.isinf(values[0]) and values[1].item() == pytest.approx(20.0, abs=1e-5)
    raw = psnr(prediction, target, clip=False)  # the raw values: errors 0.5 and 0.3
    assert raw.tolist() == pytest.approx([-10 * math.log10(0.25), -10 * math.log10(0.09)], abs=1e-5)


def test_ssim_identical_and_flat_offset_match_the_closed_form():
    target = torch.rand(2, 3, 24, 32, generator=torch.Generator().manual_seed(2))
    assert ssim(target, target).tolist() == pytest.approx([1.0, 1.0], abs=1e-12)
    a, b, c1 = 0.3, 0.6, 0.01**2  # flat images: sigma terms cancel, SSIM = (2ab + C1) / (a^2 + b^2 + C1)
    assert ssim(_grey(a), _grey(b)).tolist() == pytest.approx([(2 * a * b + c1) / (a * a + b * b + c1)] * 2, rel=1e-9)


def test_ssim_rejects_images_smaller_than_the_window_and_mismatched_shapes():
    with pytest.raises(InputError, match="at least 11x11"):
        ssim(_grey(0.5, (1, 3, 10, 40)), _grey(0.5, (1, 3, 10, 40)))
    with pytest.raises(InputError):
        psnr(_grey(0.5, (1, 3, 16, 16)), _grey(0.5, (1, 3, 16, 17)))


def _skimage_ssim(prediction: torch.Tensor, target: torch.Tensor) -> list[float]:
    return [structural_similarity(p.clamp(0, 1).double().permute(1, 2, 0).numpy(), t.double().permute(1, 2, 0).numpy(),
                                  win_size=11, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                  data_range=1.0, channel_axis=2) for p, t in zip(prediction, target)]


def test_ssim_matches_skimage_on_smooth_random_images():
    g = torch.Generator().manual_seed(3)
    target = torch.nn.functional.avg_pool2d(torch.rand(3, 3, 70, 90, generator=g), 5, 1)
    prediction = target + 0.08 * torch.randn(target.shape, generator=g)
    assert ssim(prediction, target).tolist() == pytest.approx(_skimage_ssim(prediction, target), abs=1e-9)


def test_ssim_matches_skimage_on_real_photographs(data_root):
    from codecsplat_warp.data import load_scene, preprocess_scene
    from codecsplat_warp.data.preprocess import DatasetConfig

    scene = preprocess_scene(load_scene(data_root / "cap_beer"), DatasetConfig(width=160, height=128, near=0, far=0),
                             frames=[0, 1, 2, 3], use_config_depth_range=False)
    images = scene.images.double() / 255
    prediction, target = images[:2], images[2:]
    noisy = (target + 0.03 * torch.randn(target.shape, generator=torch.Generator().manual_seed(4),
                                         dtype=torch.float64)).clamp(0, 1)
    for a, b in ((prediction, target), (noisy, target)):
        ours = ssim(a, b).tolist()
        assert ours == pytest.approx(_skimage_ssim(a, b), abs=1e-9)
    assert 0.0 < min(ours) < 1.0


def test_image_metrics_without_lpips_weights_leaves_lpips_out(monkeypatch):
    monkeypatch.delenv("CODECSPLAT_LPIPS_WEIGHTS", raising=False)
    metrics = ImageMetrics()
    assert "CODECSPLAT_LPIPS_WEIGHTS" in metrics.lpips_missing
    values = metrics(_grey(0.4), _grey(0.5))
    assert set(values) == {"psnr", "ssim"} and values["psnr"] == pytest.approx([20.0, 20.0], abs=1e-5)


@needs_lpips
def test_image_metrics_with_lpips_weights_scores_identical_images_zero():
    metrics = ImageMetrics(LPIPS_WEIGHTS)
    target = torch.rand(1, 3, 64, 64, generator=torch.Generator().manual_seed(5))
    same = metrics(target, target)
    assert same["lpips_vgg"] == pytest.approx([0.0], abs=1e-6) and same["lpips_alex"] == pytest.approx([0.0], abs=1e-6)
    noisy = metrics((target + 0.2 * torch.randn(target.shape)).clamp(0, 1), target)
    assert noisy["lpips_vgg"][0] > 0.02 and noisy["lpips_alex"][0] > 0.02


@needs_lpips
def test_image_metrics_reuse_a_targets_lpips_features_only_while_it_is_unchanged():
    """Scoring several predictions against one target computes its LPIPS features once; an in-place change of the
    target (a new version) or another tensor computes them again."""
    from codecsplat_warp.metrics import LPIPS

    metrics = ImageMetrics(LPIPS_WEIGHTS)
    g = torch.Generator().manual_seed(3)
    target, first, second = (torch.rand(2, 3, 40, 48, generator=g) for _ in range(3))
    fresh = {net: LPIPS(net, LPIPS_WEIGHTS) for net in ("vgg", "alex")}

    def expected(prediction, reference):
        with torch.no_grad():
            return {f"lpips_{net}": [float(v) for v in model(prediction, reference)] for net, model in fresh.items()}

    for prediction in (first, second):
        values = metrics(prediction, target)
        assert {k: values[k] for k in expected(prediction, target)} == expected(prediction, target)
    target.mul_(0.5)
    values = metrics(first, target)
    assert {k: values[k] for k in expected(first, target)} == expected(first, target)
