"""The image-codec baseline (``codecsplat_warp.baselines.image_codec``): WebP and JPEG files of the context
photographs decode to the photographs within their coding error, spend more bytes at higher qualities, bad
qualities, bad images and corrupt files are typed errors, and a flipped bit decodes to what the file says."""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch
from PIL import Image

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


def _pillow_pixels(data: bytes) -> torch.Tensor | None:
    """float32 [1,3,H,W] pixels / 255 that Pillow itself decodes from an image file, or None where it cannot."""
    try:
        with Image.open(io.BytesIO(data)) as image:
            image.load()
            pixels = np.array(image)
    except Exception:  # noqa: BLE001 - any failure to read is "no pixels" here
        return None
    return torch.from_numpy(pixels).permute(2, 0, 1)[None].float() / 255 if pixels.ndim == 3 else None


def _flip_regions(name: str, data: bytes) -> tuple[range, range]:
    """Bytes of a file a flipped bit must make undecodable, and bytes whose flip must leave the pixels alone.

    JPEG: the start-of-image marker; the contents of the JFIF APP0 segment (an application segment: identifier,
    version, density, thumbnail size, which no decoder reads pixels from). WebP: the RIFF container's tags and
    sizes and the VP8 chunk's tag and size (the first 20 bytes); nothing there leaves the pixels alone."""
    if name == "jpeg":
        assert data[2:4] == b"\xff\xe0" and data[6:11] == b"JFIF\0"
        return range(0, 2), range(6, 4 + int.from_bytes(data[4:6], "big"))
    assert data[:4] == b"RIFF" and data[8:16] == b"WEBPVP8 "
    return range(0, 20), range(0)


@pytest.mark.parametrize("name", sorted(FORMATS))
def test_a_flipped_bit_is_detected_or_decodes_to_the_pixels_the_file_holds(photographs, name):
    """JPEG and lossy WebP carry no checksum, so most flips decode to other pixels; what must hold for each flip
    (every bit of the first 20 bytes, then 50 random bits): a BitstreamError where the file's framing breaks, the
    original pixels where the bit is metadata (:func:`_flip_regions`), and elsewhere either a BitstreamError or
    exactly the pixels Pillow reads from the flipped file. Catches: a decoder that returns made-up, stale or
    default pixels for a file it cannot read, that hides a broken header, or that changes the pixels it read."""
    codec = ImageCodec(name, 50)
    first = codec.encode(photographs)[0]
    original = codec.decode([first])
    must_fail, unused = _flip_regions(name, first)
    rng = np.random.default_rng(0)
    flips = [(byte, bit) for byte in range(20) for bit in range(8)]
    flips += [(int(rng.integers(20, len(first))), int(rng.integers(8))) for _ in range(50)]
    for byte, bit in flips:
        flipped = bytearray(first)
        flipped[byte] ^= 1 << bit
        where = f"bit {bit} of byte {byte}"
        if byte in must_fail:
            with pytest.raises(BitstreamError):
                codec.decode([bytes(flipped)])
            continue
        try:
            decoded = codec.decode([bytes(flipped)])
        except BitstreamError:
            assert byte not in unused, f"{where} is metadata, yet the file no longer decodes"
            continue
        expected = original if byte in unused else _pillow_pixels(bytes(flipped))
        assert expected is not None, f"{where}: decoded a file that Pillow cannot read"
        assert decoded.shape == expected.shape and torch.equal(decoded, expected), where


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
