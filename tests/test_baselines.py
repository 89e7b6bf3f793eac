"""Baseline compressors: decodable, within their quantisation error, and corrupt input raises BitstreamError."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from codecsplat_warp.baselines import FeatureDeflate, PlyDeflate, PngCompression, kmeans, morton_codes
from codecsplat_warp.baselines.container import pack, unpack
from codecsplat_warp.baselines.png import MAGIC as PNG_MAGIC
from codecsplat_warp.cameras import Cameras, intrinsics_matrix
from codecsplat_warp.errors import BitstreamError
from test_ply import random_gaussians


def _nearest_distance(points: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    return torch.cdist(points.double(), reference.double()).min(dim=1).values


def test_ply_deflate_round_trip_is_within_half_a_quantisation_step():
    gaussians = random_gaussians(300, degree=2)
    codec = PlyDeflate(position_bits=16, attribute_bits=8)
    data = codec.encode(gaussians)
    back = codec.decode(data)
    assert len(back) == 300 and back.sh_degree == 2
    raw_ply_bytes = 300 * (3 + 3 + 27 + 1 + 3 + 4) * 4
    assert len(data) < raw_ply_bytes / 2
    span = gaussians.means.max(0).values - gaussians.means.min(0).values
    assert bool(((back.means - gaussians.means).abs() <= span / 65535 / 2 + 1e-5).all())
    sh_span = gaussians.sh.max() - gaussians.sh.min()
    assert float((back.sh - gaussians.sh).abs().max()) <= float(sh_span) / 255 / 2 + 1e-6
    log_scale_span = float(gaussians.scales.log().max() - gaussians.scales.log().min())
    assert float((back.scales.log() - gaussians.scales.log()).abs().max()) <= log_scale_span / 255 / 2 + 1e-5


@pytest.mark.parametrize("n,degree", [(50, 1), (64, 0), (7, 2)])
def test_png_round_trip_keeps_every_gaussian_and_drops_the_padding(n, degree):
    gaussians = random_gaussians(n, degree, seed=n)
    codec = PngCompression(sh_clusters=4096, kmeans_iterations=3)
    back = codec.decode(codec.encode(gaussians))
    assert len(back) == n and back.sh_degree == degree
    # sorted order: every decoded centre lies within one 16-bit step (in log space) of an original one
    assert float(_nearest_distance(back.means, gaussians.means).max()) < 1e-3
    assert float(_nearest_distance(gaussians.means, back.means).max()) < 1e-3
    match = torch.cdist(back.means.double(), gaussians.means.double()).argmin(dim=1)
    assert float((back.opacities - gaussians.opacities[match]).abs().max()) < 0.02
    if degree:  # as many clusters as Gaussians: only the 6-bit centroid quantisation remains
        rest = gaussians.sh[match, 1:]
        step = float(rest.max() - rest.min()) / 63
        assert float((back.sh[:, 1:] - rest).abs().max()) <= step / 2 + 1e-5


def test_png_with_few_sh_clusters_shares_the_higher_sh():
    gaussians = random_gaussians(200, degree=1)
    codec = PngCompression(sh_clusters=8, kmeans_iterations=5)
    back = codec.decode(codec.encode(gaussians))
    assert len(torch.unique(back.sh[:, 1:].reshape(200, -1), dim=0)) <= 8


def test_feature_deflate_round_trip_is_float16_exact():
    g = torch.Generator().manual_seed(0)
    feature, depth = torch.randn(2, 8, 6, 10, generator=g), torch.rand(2, 12, 20, generator=g) * 10 + 1
    f = torch.full((2,), 15.0, dtype=torch.float64)
    c2w = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    c2w[1, 0, 3] = 0.25
    cameras = Cameras.from_c2w(intrinsics_matrix(f, f, f * 0 + 10, f * 0 + 6), c2w, torch.full((2,), 0.5),
                               torch.full((2,), 50.0), 20, 12)
    scene = FeatureDeflate().decode(FeatureDeflate().encode(feature, depth, cameras))
    assert torch.equal(scene.feature, feature.half().float()) and torch.equal(scene.depth, depth.half().float())
    torch.testing.assert_close(scene.cameras.w2c, cameras.w2c.float())
    torch.testing.assert_close(scene.cameras.K, cameras.K.float())
    assert (scene.cameras.width, scene.cameras.height) == (20, 12)


def _streams():
    gaussians = random_gaussians(30, degree=1)
    g = torch.Generator().manual_seed(1)
    f = torch.full((2,), 15.0)
    cameras = Cameras.from_c2w(intrinsics_matrix(f, f, f * 0 + 8, f * 0 + 8), torch.eye(4).repeat(2, 1, 1),
                               torch.full((2,), 0.5), torch.full((2,), 50.0), 16, 16)
    return [(PlyDeflate(), PlyDeflate().encode(gaussians)), (PngCompression(), PngCompression().encode(gaussians)),
            (FeatureDeflate(), FeatureDeflate().encode(torch.randn(2, 4, 8, 8, generator=g),
                                                       torch.rand(2, 16, 16, generator=g) + 1, cameras))]


def test_broken_framing_is_detected():
    rng = np.random.default_rng(0)
    for codec, data in _streams():
        for candidate in (b"", data[:3], data[:len(data) // 2], data[:-1], data + b"x", b"XXXX" + data[4:],
                          bytes(rng.integers(0, 256, 64, dtype=np.uint8))):
            with pytest.raises(BitstreamError):
                codec.decode(candidate)


def _repacked(data: bytes, magic: bytes, header_update: dict | None = None,
              flip: tuple[int, int] | None = None) -> bytes:
    """``data`` re-framed with ``header_update`` merged into its header and ``flip`` = (byte, bit) of part 0 flipped."""
    header, parts = unpack(data, magic)
    if flip is not None:
        part = bytearray(parts[0])
        part[flip[0]] ^= 1 << flip[1]
        parts[0] = bytes(part)
    return pack(magic, {**header, **(header_update or {})}, parts)


def test_png_stream_with_a_bad_count_or_a_broken_png_chunk_is_detected():
    codec, data = _streams()[1]
    header, _ = unpack(data, PNG_MAGIC)
    too_many = header["width"] * header["height"] + 1
    with pytest.raises(BitstreamError, match="do not fit"):
        codec.decode(_repacked(data, PNG_MAGIC, {"count": too_many}))
    # Byte 36 of a PNG is the low byte of its second chunk's length (8-byte signature + 25-byte IHDR chunk + 3):
    # the chunk no longer ends where its CRC is, which the decoder must report as a BitstreamError.
    with pytest.raises(BitstreamError, match="broken PNG"):
        codec.decode(_repacked(data, PNG_MAGIC, flip=(36, 3)))


def test_ply_stream_quantised_to_zero_bits_is_detected():
    """Catches: a header whose ``bits`` a flipped bit turned from 8 into 0, decoded to NaN Gaussians (0 levels)
    without an error."""
    codec, data = _streams()[0]
    header, _ = unpack(data, b"GPQD")
    groups = [header["groups"][0], {**header["groups"][1], "bits": 0}]
    with pytest.raises(BitstreamError, match="quantisation to"):
        codec.decode(_repacked(data, b"GPQD", {"groups": groups}))


def _png_chunks(png: bytes) -> dict[bytes, tuple[int, int]]:
    """``{chunk type: (first, end)}`` byte ranges of the data of each chunk of a PNG (one chunk of each type)."""
    chunks, offset = {}, 8
    while offset < len(png):
        length, kind = int.from_bytes(png[offset:offset + 4], "big"), png[offset + 4:offset + 8]
        chunks[kind] = (offset + 8, offset + 8 + length)
        offset += 12 + length
    return chunks


def test_every_flipped_bit_of_a_png_image_data_is_detected():
    """Pillow checks no CRC of the image data (IDAT) and stops inflating before zlib's checksum, so flips there
    decoded to other opacities or SH labels without an error. Catches: a decoder that does not check each PNG
    chunk's CRC-32 (the opacity and SH-label images, the two that decoded silently, every bit of their IDAT)."""
    codec, data = _streams()[1]
    header, parts = unpack(data, PNG_MAGIC)
    assert len(parts) == 8  # means (low bytes, high bytes), scales, quats, opacities, sh0, SH centroids, SH labels
    for index in (4, 7):
        first, end = _png_chunks(parts[index])[b"IDAT"]
        for byte in range(first, end):
            for bit in range(8):
                flipped = bytearray(parts[index])
                flipped[byte] ^= 1 << bit
                with pytest.raises(BitstreamError, match="broken PNG"):
                    codec.decode(pack(PNG_MAGIC, header, parts[:index] + [bytes(flipped)] + parts[index + 1:]))


def _layout(data: bytes) -> tuple[list[int], range, list[range]]:
    """Where the container (see :mod:`codecsplat_warp.baselines.container`) puts things in ``data``: the bytes of
    its framing (magic, header length, part count, part lengths), of its JSON header, and of each part."""
    header_end = 8 + int.from_bytes(data[4:8], "little")
    framing, parts, offset = [*range(8), *range(header_end, header_end + 4)], [], header_end + 4
    for _ in range(int.from_bytes(data[header_end:header_end + 4], "little")):
        length = int.from_bytes(data[offset:offset + 4], "little")
        framing += range(offset, offset + 4)
        parts.append(range(offset + 4, offset + 4 + length))
        offset += 4 + length
    return framing, range(8, header_end), parts


def _tensors(decoded) -> list[torch.Tensor]:
    """Every tensor of a decoded baseline stream (Gaussians, or a feature scene with its cameras)."""
    if hasattr(decoded, "means"):
        return [decoded.means, decoded.quats, decoded.scales, decoded.opacities, decoded.sh]
    cameras = decoded.cameras
    return [decoded.feature, decoded.depth, cameras.K, cameras.w2c, cameras.near, cameras.far,
            torch.tensor([cameras.width, cameras.height])]


def _same(a, b) -> bool:
    return all(x.shape == y.shape and torch.equal(x, y) for x, y in zip(_tensors(a), _tensors(b), strict=True))


def _json_object(text: bytes) -> dict | None:
    """The JSON object ``text`` (UTF-8) holds, or None when it holds none."""
    try:
        header = json.loads(text.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError):
        return None
    return header if isinstance(header, dict) else None


def _expected_flip_outcome(codec, magic: bytes, data: bytes, flipped: bytes, byte: int):
    """What decoding ``flipped`` (``data`` with one bit of ``byte`` flipped) must give, by where the byte lies:

    * the framing (magic, lengths, part count): ``None``, a BitstreamError;
    * a part: ``"error or original"``: every part carries a checksum of what it decodes to (zlib's Adler-32 over
      the inflated bytes, PNG's CRC-32 per chunk), so a flip decodes only where the payload format leaves the bit
      unused (a stored Deflate block's padding bits, the padding after the last block) or codes the same bytes
      (a back-reference to equal bytes): to the original;
    * the JSON header (no checksum): not a JSON object any more, a BitstreamError; the same object (``1e-05`` and
      ``1E-05``), the original; another object, either a BitstreamError or what that header says of the unchanged
      parts, i.e. the decode of the container packed again with it.
    """
    framing, header_bytes, _ = _layout(data)
    if byte in framing:
        return None
    if byte not in header_bytes:
        return "error or original"
    header = _json_object(flipped[header_bytes.start:header_bytes.stop])
    if header is None:
        return None
    original_header, parts = unpack(data, magic)
    if header == original_header:
        return "original"
    try:
        return codec.decode(pack(magic, header, parts))
    except BitstreamError:
        return "error"


def test_bit_flips_are_detected_or_decode_to_what_the_format_says():
    """Each flipped bit, by where it lies (:func:`_expected_flip_outcome`): every bit of the framing, and 200 random
    bits a codec. Catches: a decoder that returns something (garbage, NaN, a partial decode) for a stream its
    format marks as corrupt, that ignores a part's checksum, that hides an error behind a default value, or that
    raises anything but BitstreamError."""
    rng = np.random.default_rng(0)
    for codec, data in _streams():
        magic, original = data[:4], codec.decode(data)
        flips = [(byte, bit) for byte in _layout(data)[0] for bit in range(8)]
        flips += [(int(rng.integers(len(data))), int(rng.integers(8))) for _ in range(200)]
        for byte, bit in flips:
            flipped = bytearray(data)
            flipped[byte] ^= 1 << bit
            expected = _expected_flip_outcome(codec, magic, data, bytes(flipped), byte)
            where = f"{type(codec).__name__}: bit {bit} of byte {byte}"
            if expected is None:
                with pytest.raises(BitstreamError):
                    codec.decode(bytes(flipped))
                continue
            try:
                decoded = codec.decode(bytes(flipped))
            except BitstreamError:
                assert expected != "original", f"{where}: the same header, yet an error"
                continue
            assert expected != "error", f"{where}: decoded a header that does not decode when packed again"
            assert all(bool(t.isfinite().all()) for t in _tensors(decoded)), f"{where}: decoded to NaN or infinity"
            reference, said = (original, "the original's") if isinstance(expected, str) else (expected, "the new header's")
            assert _same(decoded, reference), f"{where}: decoded to other values than {said} decode"


def test_container_round_trip_and_framing_errors():
    data = pack(b"TEST", {"a": [1, 2]}, [b"xyz", b""])
    assert unpack(data, b"TEST") == ({"a": [1, 2]}, [b"xyz", b""])
    with pytest.raises(BitstreamError, match="not a ELSE stream"):
        unpack(data, b"ELSE")
    with pytest.raises(BitstreamError, match="truncated"):
        unpack(data[:-1], b"TEST")
    with pytest.raises(BitstreamError, match="unexpected bytes"):
        unpack(data + b"\0", b"TEST")


def test_kmeans_converges_to_a_fixed_point_of_lloyds_step_and_caps_k_at_n():
    g = torch.Generator().manual_seed(2)
    centres = torch.tensor([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])
    points = centres.repeat_interleave(50, 0) + 0.1 * torch.randn(150, 2, generator=g)
    found, labels = kmeans(points, 3, iterations=20, seed=3)
    assert torch.equal(labels, torch.cdist(points, found).argmin(dim=1))
    for k in labels.unique():
        torch.testing.assert_close(found[k], points[labels == k].mean(0))
    distinct = points[:4]
    found, labels = kmeans(distinct, 100, iterations=2)
    assert found.shape == (4, 2) and torch.equal(found[labels], distinct)


def test_morton_order_follows_space():
    line = torch.stack([torch.linspace(0, 1, 9), torch.zeros(9), torch.zeros(9)], -1)
    assert torch.equal(torch.argsort(morton_codes(line)), torch.arange(9))
    assert int(morton_codes(torch.tensor([[0.0, 0, 0], [0, 0, 1], [1, 1, 1]]))[2]) == (1 << 30) - 1
