"""The byte layout shared by the baseline compressors: a tag, a small JSON header and length-prefixed parts.

    magic (4 bytes) | u32 header length | header (UTF-8 JSON) | u32 part count | (u32 length | bytes) * count

All integers little-endian. The header holds what a decoder needs besides the parts (counts, shapes,
quantisation ranges); the parts hold the compressed payloads. The framing costs 12 + 4 * parts bytes
plus the JSON, which is counted in every reported size.
"""

from __future__ import annotations

import json
import struct

from ..errors import BitstreamError

DEFLATE_LEVEL = 9
"""zlib (Deflate) compression level of every baseline: the smallest output zlib can make."""

_U32 = struct.Struct("<I")


def pack(magic: bytes, header: dict, parts: list[bytes]) -> bytes:
    """One byte string holding ``header`` (JSON-serialisable) and ``parts``, tagged by the 4-byte ``magic``."""
    if len(magic) != 4:
        raise ValueError(f"magic must be 4 bytes, got {magic!r}")
    text = json.dumps(header, separators=(",", ":")).encode("utf-8")
    chunks = [magic, _U32.pack(len(text)), text, _U32.pack(len(parts))]
    for part in parts:
        chunks += [_U32.pack(len(part)), bytes(part)]
    return b"".join(chunks)


def unpack(data: bytes, magic: bytes) -> tuple[dict, list[bytes]]:
    """Inverse of :func:`pack`.

    Raises:
        BitstreamError: another tag, a length running past the end, trailing bytes, or a header that is
            not a JSON object.
    """
    data = bytes(data)
    if data[:4] != magic:
        raise BitstreamError(f"not a {magic.decode('ascii', 'replace')} stream (starts with {data[:4]!r})")
    offset = 4
    header_length, offset = _read_u32(data, offset)
    header_text, offset = _read_bytes(data, offset, header_length)
    try:
        header = json.loads(header_text.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise BitstreamError(f"corrupt {magic!r} header: {exc}") from None
    if not isinstance(header, dict):
        raise BitstreamError(f"corrupt {magic!r} header: not a JSON object")
    count, offset = _read_u32(data, offset)
    parts = []
    for _ in range(count):
        length, offset = _read_u32(data, offset)
        part, offset = _read_bytes(data, offset, length)
        parts.append(part)
    if offset != len(data):
        raise BitstreamError(f"{len(data) - offset} unexpected bytes after the last part")
    return header, parts


def _read_u32(data: bytes, offset: int) -> tuple[int, int]:
    value, end = _read_bytes(data, offset, 4)
    return _U32.unpack(value)[0], end


def _read_bytes(data: bytes, offset: int, length: int) -> tuple[bytes, int]:
    if offset + length > len(data):
        raise BitstreamError(f"truncated stream: needs {offset + length} bytes, has {len(data)}")
    return data[offset:offset + length], offset + length
