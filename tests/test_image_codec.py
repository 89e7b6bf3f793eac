"""The image-codec baseline (``codecsplat_warp.baselines.image_codec``): WebP and JPEG files of the context
photographs decode to the photographs within their coding error, spend more bytes at higher qualities, and bad
qualities, bad images and corrupt files are typed errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from codecsplat_warp.baselines import ImageCodec
from codecsplat_warp.baselines.image_codec import FORMATS
from codecsplat_warp.choices import BASELINE_NAMES, IMAGE_CODEC_QUALITIES
from codecsplat_warp.data import ProceduralConfig, procedural_scene
from codecsplat_warp.errors import BitstreamError, InputError


@pytest.fixture(scope="module")
def photographs() -> np.ndarray:
    """Two textured procedural views, uint8 [2,32,48,3]."""
    scene = procedural_scene(4, ProceduralConfig(width=48, height=32, num_views=2, texture_size=16))
    return scene.images.permute(0, 2, 3, 1).numpy()


def _psnr(decoded: torch.Tensor, photographs: np.ndarray) -> float:
    truth = torch.from_numpy(photographs).permute(0, 3, 1, 2).double() / 255
    return float(-10 * torch.log10(((decoded.double() - truth) ** 2).mean()))


@pytest.mark.parametrize("name", sorted(FORMATS))
def test_round_trip_gives_the_photographs_within_the_coding_error(photographs, name):
    fine, coarse = ImageCodec(name, 95), ImageCodec(name, 5)
    files = fine.encode(photographs)
    decoded = fine.decode(files)
    assert len(files) == 2 and decoded.shape == (2, 3, 32, 48) and decoded.dtype == torch.float32
    assert float(decoded.min()) >= 0 and float(decoded.max()) <= 1
    assert torch.equal(decoded * 255, (decoded * 255).round())  # whole pixel values
    # on this texture: 31.9 / 31.6 dB at q=95, 25.2 / 21.5 dB at q=5 (WebP / JPEG)
    assert _psnr(decoded, photographs) > 30 and _psnr(coarse.decode(coarse.encode(photographs)), photographs) < 27
    assert fine.encode(photographs) == files  # deterministic
    assert (fine.label, fine.setting) == (FORMATS[name].label, "q=95")


@pytest.mark.parametrize("name", sorted(FORMATS))
def test_bytes_grow_with_quality(photographs, name):
    sizes = [sum(map(len, ImageCodec(name, q).encode(photographs))) for q in (5, 35, 70, 95)]
    assert sizes == sorted(sizes) and len(set(sizes)) == 4, sizes


@pytest.mark.parametrize("name", sorted(FORMATS))
def test_corrupt_files_raise_bitstream_errors(photographs, name):
    codec = ImageCodec(name, 50)
    first, second = codec.encode(photographs)
    other = ImageCodec("jpeg" if name == "webp" else "webp", 50).encode(photographs)
    small = codec.encode(photographs[:, :16, :24].copy())
    for files, match in [([], "no"), ([first[:len(first) // 2], second], "view 0"), ([first, b""], "view 1"),
                         ([first, bytes(200)], "not a"), (other, f"not an RGB {codec.label}"),
                         ([first, small[1]], "differ in size")]:
        with pytest.raises(BitstreamError, match=match):
            codec.decode(files)
    rng = np.random.default_rng(0)
    for _ in range(50):  # no checksum: a flipped bit is detected or decodes, and nothing else
        mutated = bytearray(first)
        mutated[int(rng.integers(len(first)))] ^= 1 << int(rng.integers(8))
        try:
            codec.decode([bytes(mutated)])
        except BitstreamError:
            pass


@pytest.mark.parametrize("name,quality", [("webp", -1), ("webp", 101), ("jpeg", 0), ("jpeg", 5.5), ("webp", True),
                                          ("png", 50)])
def test_bad_qualities_and_formats_are_input_errors(name, quality):
    with pytest.raises(InputError, match="quality|format"):
        ImageCodec(name, quality)


def test_bad_images_are_input_errors(photographs):
    codec = ImageCodec("webp", 50)
    for images in (photographs.astype(np.float32), photographs[0], photographs[..., :2], photographs[:0]):
        with pytest.raises(InputError, match="uint8"):
            codec.encode(images)


def test_every_image_baseline_has_a_format_and_default_qualities_it_accepts():
    assert set(IMAGE_CODEC_QUALITIES) == set(FORMATS) <= set(BASELINE_NAMES)
    for name, qualities in IMAGE_CODEC_QUALITIES.items():
        assert list(qualities) == sorted(set(qualities)) and [ImageCodec(name, q).quality for q in qualities]
