"""Baseline (a): the Gaussians' 3DGS PLY attributes, quantised per column, then Deflate.

The columns are those of :func:`codecsplat_warp.export.ply.ply_attributes` without the (zero) normals:
positions quantised to ``position_bits`` and every other column (SH, opacity logit, log scales,
quaternion) to ``attribute_bits``. Columns are stored one after the other (column-major); 16-bit columns
as a high-byte plane followed by a low-byte plane, which Deflate compresses better than interleaved bytes.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np
import torch

from ..errors import BitstreamError, DataError
from ..export.ply import gaussians_from_attributes, ply_attributes
from ..gaussians import Gaussians
from .container import DEFLATE_LEVEL, pack, unpack
from .quantise import dequantise, quantise

MAGIC = b"GPQD"
_POSITIONS = ("x", "y", "z")
_NORMALS = ("nx", "ny", "nz")


@dataclass(frozen=True)
class PlyDeflate:
    """PLY attributes, uniformly quantised, Deflate-compressed (see the module docstring)."""

    position_bits: int = 16
    attribute_bits: int = 8

    @property
    def setting(self) -> str:
        """Codec setting as the tables print it."""
        return f"{self.position_bits}/{self.attribute_bits}-bit"

    def encode(self, gaussians: Gaussians) -> bytes:
        """Compressed bytes of ``gaussians``."""
        columns = {k: v for k, v in ply_attributes(gaussians).items() if k not in _NORMALS}
        names = list(columns)
        groups = [(list(_POSITIONS), self.position_bits), ([n for n in names if n not in _POSITIONS], self.attribute_bits)]
        header = {"count": len(gaussians), "groups": []}
        planes = []
        for group, bits in groups:
            q, mins, maxs = quantise(np.stack([columns[n] for n in group], axis=1), bits)
            header["groups"].append({"names": group, "bits": bits, "mins": mins, "maxs": maxs})
            planes.append(_byte_planes(q))
        return pack(MAGIC, header, [zlib.compress(b"".join(planes), DEFLATE_LEVEL)])

    def decode(self, data: bytes, device: torch.device | str = "cpu") -> Gaussians:
        """Gaussians (float32, on ``device``) of bytes made by :meth:`encode`.

        Raises:
            BitstreamError: not such a stream, or corrupt.
        """
        header, parts = unpack(data, MAGIC)
        try:
            count, groups = int(header["count"]), header["groups"]
            payload = zlib.decompress(parts[0])
            columns, offset = {}, 0
            for group in groups:
                bits, names = int(group["bits"]), list(group["names"])
                size = count * len(names) * (1 if bits <= 8 else 2)
                q = _from_byte_planes(payload[offset:offset + size], count, len(names), bits)
                offset += size
                values = dequantise(q, group["mins"], group["maxs"], bits)
                columns.update({n: values[:, i] for i, n in enumerate(names)})
        except (KeyError, IndexError, TypeError, ValueError, zlib.error) as exc:
            raise BitstreamError(f"corrupt PLY->Deflate stream: {exc}") from None
        if offset != len(payload):
            raise BitstreamError("corrupt PLY->Deflate stream: payload size does not match the header")
        try:
            return gaussians_from_attributes(columns, device)
        except DataError as exc:
            raise BitstreamError(f"corrupt PLY->Deflate stream: {exc}") from None


def _byte_planes(q: np.ndarray) -> bytes:
    """Column-major bytes of uint8/uint16 [N,C]; uint16 as the high-byte plane then the low-byte plane."""
    columns = np.ascontiguousarray(q.T)
    if columns.dtype == np.uint8:
        return columns.tobytes()
    return (columns >> 8).astype(np.uint8).tobytes() + (columns & 0xFF).astype(np.uint8).tobytes()


def _from_byte_planes(raw: bytes, count: int, channels: int, bits: int) -> np.ndarray:
    """Inverse of :func:`_byte_planes`: [count, channels] uint8 or uint16."""
    planes = np.frombuffer(raw, dtype=np.uint8)
    if bits <= 8:
        return planes.reshape(channels, count).T
    high, low = planes.reshape(2, channels, count).astype(np.uint16)
    return ((high << 8) | low).T
