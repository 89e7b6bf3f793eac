"""Baseline (b): gsplat-style PNG compression of Gaussians (gsplat ``PngCompression``, Morton-sorted).

As gsplat 1.5's ``png_compression``, with two deviations noted below:

* attributes in pre-activation form: centres through ``sign(x) log(1 + |x|)``, log scales, opacity
  logits, unit quaternions, the degree-0 SH colour;
* the Gaussians are sorted so neighbours in the image are neighbours in space: here by the **Morton
  (Z-order) code** of their transformed centres (gsplat uses PLAS when installed), then laid out row by row
  on a W x H grid with W = ceil(sqrt(N)); the last row is padded by repeating the last Gaussian (gsplat
  instead drops the lowest-opacity Gaussians to reach a square), and the decoder drops the padding;
* centres: 16-bit per channel, as two 8-bit RGB PNGs (low and high bytes); scales, quaternions (RGBA),
  opacities (grey) and SH DC: 8-bit PNGs, each channel with its own min/max;
* higher SH degrees: k-means with ``sh_clusters`` clusters (the paper's K_SH = 8192) over the flattened
  coefficients, **Euclidean** (gsplat's torchpq uses Manhattan), ``kmeans_iterations`` Lloyd steps;
  centroids quantised to 6 bits (one global range) and Deflated, labels stored as a 16-bit grey PNG.
"""

from __future__ import annotations

import io
import struct
import zlib
from dataclasses import dataclass

import numpy as np
import torch
from PIL import Image

from ..errors import BitstreamError, InputError
from ..gaussians import Gaussians
from .container import DEFLATE_LEVEL, pack, unpack
from .kmeans import kmeans
from .quantise import dequantise, quantise

MAGIC = b"GPNG"
MORTON_BITS = 10
"""Bits per axis of the Morton code that orders the Gaussians (a 2^30-cell grid)."""
CENTROID_BITS = 6
"""Quantisation of the SH k-means centroids (gsplat's default)."""
PNG_COMPRESS_LEVEL = 9
MAX_SH_CLUSTERS = 1 << 16
"""SH cluster labels are stored as a 16-bit image."""
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_CHUNK_HEAD = struct.Struct(">I4s")
"""A PNG chunk's big-endian data length and 4-byte type; its data and a CRC-32 of type and data follow."""


@dataclass(frozen=True)
class PngCompression:
    """gsplat-style PNG compressor (see the module docstring)."""

    sh_clusters: int = 8192
    kmeans_iterations: int = 10
    seed: int = 0

    def __post_init__(self) -> None:
        if not 1 <= self.sh_clusters <= MAX_SH_CLUSTERS or self.kmeans_iterations < 0:
            raise InputError(f"PNG compression needs 1 <= sh_clusters <= {MAX_SH_CLUSTERS} (16-bit labels) and "
                             f"kmeans_iterations >= 0, got {self.sh_clusters} and {self.kmeans_iterations}")

    @property
    def setting(self) -> str:
        """Codec setting as the tables print it."""
        return f"K_SH={self.sh_clusters}"

    def encode(self, gaussians: Gaussians) -> bytes:
        """Compressed bytes of ``gaussians``."""
        g = gaussians.detach()
        order = torch.argsort(morton_codes(_log_transform(g.means.float())), stable=True)
        n = len(g)
        width = max(1, int(np.ceil(np.sqrt(n))))
        height = -(-n // width)
        grid = lambda x: _grid(x.float()[order].reshape(n, -1), width, height)  # noqa: E731
        header = {"count": n, "width": width, "height": height, "sh_degree": g.sh_degree, "ranges": {}}
        parts: list[bytes] = []

        q, mins, maxs = quantise(grid(_log_transform(g.means.float())).reshape(-1, 3), 16)
        header["ranges"]["means"] = (mins, maxs)
        q = q.reshape(height, width, 3)
        parts += [_png((q & 0xFF).astype(np.uint8)), _png((q >> 8).astype(np.uint8))]
        attributes = {
            "scales": g.scales.float().clamp_min(1e-30).log(),
            "quats": torch.nn.functional.normalize(g.quats.float(), dim=-1),
            "opacities": torch.logit(g.opacities.float().clamp(2.0**-24, 1 - 2.0**-24)),
            "sh0": g.sh[:, 0, :],
        }
        for key, values in attributes.items():
            image = grid(values)
            q, mins, maxs = quantise(image.reshape(-1, image.shape[-1]), 8)
            header["ranges"][key] = (mins, maxs)
            parts.append(_png(q.reshape(image.shape).squeeze(-1) if image.shape[-1] == 1 else q.reshape(image.shape)))
        if g.sh_degree > 0:
            centroids, labels = kmeans(g.sh[:, 1:, :].reshape(n, -1).float(), self.sh_clusters, self.kmeans_iterations,
                                       self.seed)
            centroid_q, low, high = quantise(centroids.cpu().numpy().reshape(-1, 1), CENTROID_BITS)
            header["ranges"]["shN"] = (low, high)
            header["clusters"] = centroids.shape[0]
            parts.append(zlib.compress(centroid_q.tobytes(), DEFLATE_LEVEL))
            parts.append(_png(grid(labels[:, None]).astype(np.uint16)[..., 0]))
        return pack(MAGIC, header, parts)

    def decode(self, data: bytes, device: torch.device | str = "cpu") -> Gaussians:
        """Gaussians (float32, on ``device``; in sorted order, padding dropped) of bytes made by :meth:`encode`.

        Raises:
            BitstreamError: not such a stream, or corrupt.
        """
        header, parts = unpack(data, MAGIC)
        try:
            return _decode(header, parts, torch.device(device))
        # Pillow raises SyntaxError for a PNG chunk it cannot parse (a broken chunk header or checksum).
        except (KeyError, IndexError, TypeError, ValueError, OSError, SyntaxError, zlib.error) as exc:
            raise BitstreamError(f"corrupt PNG stream: {exc}") from None


def _decode(header: dict, parts: list[bytes], device: torch.device) -> Gaussians:
    n, width, height, degree = (int(header[k]) for k in ("count", "width", "height", "sh_degree"))
    if not 0 <= n <= width * height:
        raise BitstreamError(f"corrupt PNG stream: {n} Gaussians do not fit a {width}x{height} grid")
    ranges = header["ranges"]
    flat = lambda image: image.reshape(width * height, -1)[:n]  # noqa: E731
    low, high = (_read_png(p, (height, width, 3)).astype(np.uint16) for p in parts[:2])
    means = _inverse_log_transform(torch.from_numpy(dequantise(flat(low | (high << 8)), *ranges["means"], 16)))
    shapes = {"scales": 3, "quats": 4, "opacities": 1, "sh0": 3}
    values = {}
    for (key, channels), part in zip(shapes.items(), parts[2:6]):
        image = _read_png(part, (height, width, channels) if channels > 1 else (height, width))
        values[key] = torch.from_numpy(dequantise(flat(image), *ranges[key], 8))
    sh = values["sh0"][:, None, :]
    if degree > 0:
        clusters, rest = int(header["clusters"]), 3 * ((degree + 1) ** 2 - 1)
        centroid_q = np.frombuffer(zlib.decompress(parts[6]), dtype=np.uint8).reshape(-1, 1)
        centroids = dequantise(centroid_q, *ranges["shN"], CENTROID_BITS).reshape(clusters, rest)
        labels = flat(_read_png(parts[7], (height, width)).astype(np.int64))[:, 0]
        if labels.size and labels.max() >= clusters:
            raise BitstreamError("corrupt PNG stream: SH label out of range")
        sh = torch.cat([sh, torch.from_numpy(centroids[labels]).reshape(n, -1, 3)], dim=1)
    return Gaussians(
        means=means.to(device),
        quats=torch.nn.functional.normalize(values["quats"], dim=-1).to(device),
        scales=values["scales"].exp().to(device),
        opacities=torch.sigmoid(values["opacities"][:, 0]).to(device),
        sh=sh.contiguous().to(device),
    )


def morton_codes(points: torch.Tensor) -> torch.Tensor:
    """int64 [N] Z-order codes of points [N,3], each axis quantised to MORTON_BITS over its own range."""
    low, high = points.min(dim=0).values, points.max(dim=0).values
    cells = (1 << MORTON_BITS) - 1
    q = ((points - low) / (high - low).clamp_min(1e-30) * cells).round().long().clamp(0, cells)
    code = torch.zeros(points.shape[0], dtype=torch.long, device=points.device)
    for bit in range(MORTON_BITS):
        for axis in range(3):
            code |= ((q[:, axis] >> bit) & 1) << (3 * bit + axis)
    return code


def _log_transform(x: torch.Tensor) -> torch.Tensor:
    return torch.sign(x) * torch.log1p(x.abs())


def _inverse_log_transform(y: torch.Tensor) -> torch.Tensor:
    return torch.sign(y) * torch.expm1(y.abs())


def _grid(values: torch.Tensor, width: int, height: int) -> np.ndarray:
    """[height, width, C] numpy image of [N,C] values in row order, the last row padded with the last value."""
    pad = width * height - values.shape[0]
    padded = torch.cat([values, values[-1:].expand(pad, -1)]) if pad else values
    return padded.reshape(height, width, -1).cpu().numpy()


def _png(image: np.ndarray) -> bytes:
    """PNG bytes of a uint8 [H,W] / [H,W,3] / [H,W,4] or uint16 [H,W] image."""
    buffer = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image)).save(buffer, format="PNG", compress_level=PNG_COMPRESS_LEVEL)
    return buffer.getvalue()


def _read_png(data: bytes, shape: tuple[int, ...]) -> np.ndarray:
    """Pixels of PNG bytes, checked to have ``shape`` (and their chunks first, :func:`_check_png_chunks`)."""
    _check_png_chunks(data)
    with Image.open(io.BytesIO(data)) as image:
        pixels = np.asarray(image)
    if pixels.shape != shape:
        raise BitstreamError(f"corrupt PNG stream: image of shape {pixels.shape}, expected {shape}")
    return pixels


def _check_png_chunks(data: bytes) -> None:
    """Check the chunk layout of PNG bytes: the signature, every chunk inside the data with the CRC-32 the format
    gives it, ``IEND`` last and nothing after it.

    Pillow checks the CRCs of the chunks before the image data but not those of ``IDAT``, and stops inflating once
    it has the pixels, before zlib's checksum: without this check a flipped bit in the image data can decode to
    other pixels without an error.

    Raises:
        BitstreamError: a bad signature, a chunk running past the end, a CRC mismatch, no ``IEND``, or bytes after it.
    """
    if data[:len(PNG_SIGNATURE)] != PNG_SIGNATURE:
        raise BitstreamError("corrupt PNG stream: broken PNG signature")
    offset, kind = len(PNG_SIGNATURE), b""
    while kind != b"IEND":
        if offset + _CHUNK_HEAD.size + 4 > len(data):
            raise BitstreamError(f"corrupt PNG stream: broken PNG, no IEND chunk before the end ({len(data)} bytes)")
        length, kind = _CHUNK_HEAD.unpack_from(data, offset)
        end = offset + _CHUNK_HEAD.size + length
        if end + 4 > len(data):
            raise BitstreamError(f"corrupt PNG stream: broken PNG chunk {kind!r} at byte {offset} runs past the end")
        if zlib.crc32(data[offset + 4:end]) != int.from_bytes(data[end:end + 4], "big"):
            raise BitstreamError(f"corrupt PNG stream: broken PNG chunk {kind!r} at byte {offset} (CRC mismatch)")
        offset = end + 4
    if offset != len(data):
        raise BitstreamError(f"corrupt PNG stream: broken PNG, {len(data) - offset} bytes after its IEND chunk")
