"""The scene bitstream (paper Eq. 8): header, Deflate-compressed camera stream, one feature stream per view.

Layout (little-endian, no padding or alignment anywhere)::

    header      magic "CSPL" | format version u8 | flags u8 | model id 8 bytes | lambda float32     (18 bytes)
    cameras     length varint | CRC32 u32 of (header + payload) | payload = raw Deflate(camera record), or the
                record itself with FLAG_RAW_CAMERAS (written when Deflate would not make it smaller)
    view 0      length varint | CRC32 u32 of payload | payload = range-coded latents of view 0
    ...
    view V-1    (V is read from the camera record)

Camera record (before Deflate; ``f`` is float32, or float64 with :data:`FLAG_FLOAT64_CAMERAS`)::

    height u16 | width u16 | views u8
    intrinsics  fx fy cx cy (f), once with FLAG_SHARED_INTRINSICS, else per view
    extrinsics  per view: world-to-camera rotation as a unit quaternion w x y z (w >= 0) and translation (f x 7)
    near, far   (f x 2), once with FLAG_SHARED_DEPTH_RANGE, else per view

A rotation is stored as a quaternion rather than a matrix (4 numbers instead of 9); the scalar part is kept
rather than derived, since deriving it loses all precision for half-turns. The CRC of the camera stream
also covers the header, so every byte of a bitstream is checked. Parsing never allocates more than a few
kilobytes beyond the input: every field is bounded before use (:data:`MAX_VIEWS`, :data:`MAX_SIDE`,
:data:`MAX_PIXELS`, stream lengths against the bytes left, the camera record's exact size before and while
inflating it), so a decoder allocates at most what a scene of :data:`MAX_PIXELS` pixels needs.
"""

from __future__ import annotations

import math
import struct
import zlib
from dataclasses import dataclass

import numpy as np
import torch

from ..cameras import Cameras, intrinsics_matrix
from ..errors import BitstreamError, CameraError, InputError
from ..gaussians import quat_to_rotmat, rotmat_to_quat
from ..nn.config import MODEL_STRIDE
from .latent import LAMBDA_MAX, LAMBDA_MIN

MAGIC = b"CSPL"
FORMAT_VERSION = 2
"""The format version this code writes and the newest it reads (version 1 lacks :data:`FLAG_RAW_CAMERAS`)."""

FLAG_SHARED_INTRINSICS = 1
"""Every view has the same fx, fy, cx, cy: stored once."""

FLAG_SHARED_DEPTH_RANGE = 2
"""Every view has the same near and far: stored once."""

FLAG_FLOAT64_CAMERAS = 4
"""Camera numbers are float64 (written when the model computes in float64), else float32."""

FLAG_RAW_CAMERAS = 8
"""The camera record is stored as is: Deflate would have made it larger (small records of few views)."""

KNOWN_FLAGS = FLAG_SHARED_INTRINSICS | FLAG_SHARED_DEPTH_RANGE | FLAG_FLOAT64_CAMERAS | FLAG_RAW_CAMERAS

MODEL_ID_BYTES = 8
"""Bytes of the model identifier (the first 16 hex digits of its SHA-256 content hash)."""

MAX_VIEWS = 64
MIN_VIEWS = 2
MAX_SIDE = 8192
"""Largest image height or width in pixels."""
MAX_PIXELS = 2**26
"""Largest number of context pixels V*H*W (e.g. 16 views of 2048x2048; decoding makes one Gaussian each)."""

_HEADER = struct.Struct("<4sBB8sf")
HEADER_BYTES = _HEADER.size
_SHAPE = struct.Struct("<HHB")
CRC_BYTES = 4
"""Bytes of the CRC32 in every frame."""
_MAX_VARINT_BYTES = 5
"""Stream lengths are below 2**35; anything longer than the input is rejected anyway."""


@dataclass(frozen=True)
class Header:
    """The bitstream header.

    Attributes:
        version: format version (1).
        flags: bit set of the FLAG_* constants.
        model_id: 16 hex digits naming the model that wrote (and must decode) the bitstream.
        lam: the rate-distortion trade-off lambda the scene was coded at (float32 value).
    """

    version: int
    flags: int
    model_id: str
    lam: float


@dataclass
class Bitstream:
    """A parsed bitstream: header, context cameras (CPU) and the still range-coded feature streams.

    Attributes:
        header: :class:`Header`.
        cameras: the V context cameras (float32, or float64 with FLAG_FLOAT64_CAMERAS), on the CPU.
        feature_streams: V byte strings, one per view.
        part_bytes: bytes each part occupies in the input, framing included (``header``, ``cameras``,
            ``view{i}``).
    """

    header: Header
    cameras: Cameras
    feature_streams: list[bytes]
    part_bytes: dict[str, int]


# --------------------------------------------------------------------------------------------------
# Writing
def pack_bitstream(model_id: str, lam: float, cameras: Cameras, feature_streams: list[bytes]) -> bytes:
    """Eq. 8: the bytes of a scene.

    Args:
        model_id: 16 hex digits (see :func:`codecsplat_warp.model.pretrained.model_id`).
        lam: lambda in [LAMBDA_MIN, LAMBDA_MAX] (stored as float32).
        cameras: the V context cameras (V in [2, 64], sides <= 8192 and multiples of 4); float64 cameras
            are stored in float64, float32 ones in float32.
        feature_streams: V range-coded streams (whole 32-bit words).
    """
    if len(feature_streams) != cameras.num_views:
        raise InputError(f"{cameras.num_views} cameras need as many feature streams, got {len(feature_streams)}")
    _check_shape(cameras.height, cameras.width, cameras.num_views, InputError)
    record, flags = _camera_record(cameras)
    deflater = zlib.compressobj(9, zlib.DEFLATED, -15)
    payload = deflater.compress(record) + deflater.flush()
    if len(payload) >= len(record):
        payload, flags = record, flags | FLAG_RAW_CAMERAS
    header = _HEADER.pack(MAGIC, FORMAT_VERSION, flags, bytes.fromhex(model_id), float(lam))
    parts = [header, _frame(payload, zlib.crc32(payload, zlib.crc32(header)))]
    parts += [_frame(stream, zlib.crc32(stream)) for stream in feature_streams]
    return b"".join(parts)


def _frame(payload: bytes, crc: int) -> bytes:
    return _varint(len(payload)) + struct.pack("<I", crc) + payload


def framed_bytes(payload_bytes: int) -> int:
    """Bytes of a frame (varint length, CRC32, payload) around a payload of ``payload_bytes``."""
    return len(_varint(payload_bytes)) + CRC_BYTES + payload_bytes


def _varint(value: int) -> bytes:
    """LEB128 unsigned integer."""
    out = bytearray()
    while True:
        byte, value = value & 0x7F, value >> 7
        out.append(byte | (0x80 if value else 0))
        if not value:
            return bytes(out)


def _camera_record(cameras: Cameras) -> tuple[bytes, int]:
    """(record bytes, flags) of the cameras (see the module docstring)."""
    float64 = cameras.dtype == torch.float64
    dtype = torch.float64 if float64 else torch.float32
    cams = cameras.to("cpu", dtype)
    K = cams.K
    intrinsics = torch.stack([K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2]], dim=-1)
    depth_range = torch.stack([cams.near, cams.far], dim=-1)
    flags = FLAG_FLOAT64_CAMERAS if float64 else 0
    if bool((intrinsics == intrinsics[:1]).all()):
        flags |= FLAG_SHARED_INTRINSICS
        intrinsics = intrinsics[:1]
    if bool((depth_range == depth_range[:1]).all()):
        flags |= FLAG_SHARED_DEPTH_RANGE
        depth_range = depth_range[:1]
    quats = rotmat_to_quat(cams.w2c[:, :3, :3].double()).to(dtype)
    extrinsics = torch.cat([quats, cams.w2c[:, :3, 3]], dim=-1)
    numbers = torch.cat([intrinsics.reshape(-1), extrinsics.reshape(-1), depth_range.reshape(-1)])
    little_endian = "<f8" if float64 else "<f4"
    record = _SHAPE.pack(cams.height, cams.width, cams.num_views) + numbers.numpy().astype(little_endian).tobytes()
    return record, flags


# --------------------------------------------------------------------------------------------------
# Reading
def parse_bitstream(data: bytes) -> Bitstream:
    """Check and split a bitstream (no model needed).

    Raises:
        BitstreamError: not a bitstream, newer format version, truncated, corrupt (CRC mismatch), trailing
            bytes, or values out of their bounds; raised before anything larger than the input is allocated.
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise BitstreamError(f"a bitstream is bytes, got {type(data).__name__}")
    view = memoryview(data).cast("B")
    if len(view) < HEADER_BYTES:
        raise BitstreamError(f"truncated bitstream: {len(view)} bytes, the header alone has {HEADER_BYTES}")
    magic, version, flags, model_id, lam = _HEADER.unpack_from(view, 0)
    if magic != MAGIC:
        raise BitstreamError("not a CodecSplat bitstream (bad magic bytes)")
    if version > FORMAT_VERSION:
        raise BitstreamError(f"bitstream format version {version} is newer than this decoder's {FORMAT_VERSION}; "
                             "update codecsplat-warp")
    if version < 1:
        raise BitstreamError(f"corrupt bitstream: format version {version}")
    offset = HEADER_BYTES
    camera_payload, offset = _read_frame(view, offset, "camera stream", zlib.crc32(view[:HEADER_BYTES]))
    if flags & ~KNOWN_FLAGS:
        raise BitstreamError(f"bitstream sets unknown flags {flags:#04x}")
    if not (math.isfinite(lam) and LAMBDA_MIN <= lam <= LAMBDA_MAX):
        raise BitstreamError(f"bitstream lambda {lam!r} is outside [{LAMBDA_MIN:g}, {LAMBDA_MAX:g}]")
    cameras = _parse_cameras(camera_payload, flags)
    parts = {"header": HEADER_BYTES, "cameras": offset - HEADER_BYTES}
    streams = []
    for v in range(cameras.num_views):
        start = offset
        payload, offset = _read_frame(view, offset, f"feature stream of view {v}")
        if len(payload) % 4 or not payload:
            raise BitstreamError(f"feature stream of view {v} must hold whole 32-bit words, got {len(payload)} bytes")
        streams.append(bytes(payload))
        parts[f"view{v}"] = offset - start
    if offset != len(view):
        raise BitstreamError(f"{len(view) - offset} trailing bytes after the last feature stream")
    header = Header(version, flags, model_id.hex(), float(lam))
    return Bitstream(header, cameras, streams, parts)


def bytes_report(data: bytes) -> dict[str, int]:
    """Bytes per part of a bitstream: ``header``, ``cameras``, ``view0`` ... ``view{V-1}`` (framing included)
    and ``total`` (their sum, the length of ``data``). Raises BitstreamError like :func:`parse_bitstream`."""
    parts = parse_bitstream(data).part_bytes
    return {**parts, "total": sum(parts.values())}


def _read_frame(view: memoryview, offset: int, what: str, crc_seed: int = 0) -> tuple[memoryview, int]:
    """(payload, offset after it) of the length-CRC-payload frame at ``offset``; checks bounds and CRC."""
    length, offset = _read_varint(view, offset, what)
    if offset + CRC_BYTES + length > len(view):
        left = max(0, len(view) - offset - CRC_BYTES)
        raise BitstreamError(f"truncated bitstream: the {what} needs {length} bytes, {left} left")
    (crc,) = struct.unpack_from("<I", view, offset)
    payload = view[offset + CRC_BYTES:offset + CRC_BYTES + length]
    if zlib.crc32(payload, crc_seed) != crc:
        raise BitstreamError(f"corrupt bitstream: CRC mismatch in the {what}")
    return payload, offset + CRC_BYTES + length


def _read_varint(view: memoryview, offset: int, what: str) -> tuple[int, int]:
    value = 0
    for i in range(_MAX_VARINT_BYTES):
        if offset + i >= len(view):
            raise BitstreamError(f"truncated bitstream: the length of the {what} is cut off")
        byte = view[offset + i]
        value |= (byte & 0x7F) << (7 * i)
        if not byte & 0x80:
            return value, offset + i + 1
    raise BitstreamError(f"corrupt bitstream: the length of the {what} is too long")


def _check_shape(height: int, width: int, views: int, error: type[Exception] = BitstreamError) -> None:
    """``error`` unless the scene shape is within the format's bounds."""
    if not MIN_VIEWS <= views <= MAX_VIEWS:
        raise error(f"a scene has {MIN_VIEWS} to {MAX_VIEWS} context views, got {views}")
    for name, side in (("height", height), ("width", width)):
        if not 0 < side <= MAX_SIDE or side % MODEL_STRIDE:
            raise error(f"image {name} must be a multiple of {MODEL_STRIDE} in (0, {MAX_SIDE}], got {side}")
    if views * height * width > MAX_PIXELS:
        raise error(f"{views} views of {height}x{width} exceed the limit of {MAX_PIXELS} context pixels")


def record_bytes(views: int, flags: int) -> int:
    """Exact size in bytes of a camera record (before Deflate) with these views and flags."""
    intrinsics = 4 if flags & FLAG_SHARED_INTRINSICS else 4 * views
    depth_range = 2 if flags & FLAG_SHARED_DEPTH_RANGE else 2 * views
    number = 8 if flags & FLAG_FLOAT64_CAMERAS else 4
    return _SHAPE.size + number * (intrinsics + 7 * views + depth_range)


def _inflate(payload: memoryview, limit: int) -> bytes:
    """Deflate-decompress at most ``limit`` bytes; BitstreamError if the data is bad or does not end there."""
    inflater = zlib.decompressobj(-15)
    try:
        record = inflater.decompress(payload, limit)
    except zlib.error as exc:
        raise BitstreamError(f"corrupt camera stream: {exc}") from None
    if not inflater.eof or inflater.unconsumed_tail or inflater.unused_data:
        raise BitstreamError("corrupt camera stream: the Deflate data does not end with the camera record")
    return record


def _parse_cameras(payload: memoryview, flags: int) -> Cameras:
    if flags & FLAG_RAW_CAMERAS:
        record = bytes(payload[: record_bytes(MAX_VIEWS, flags) + 1])
    else:
        record = _inflate(payload, record_bytes(MAX_VIEWS, flags))
    if len(record) < _SHAPE.size:
        raise BitstreamError("corrupt camera stream: shorter than its image shape")
    height, width, views = _SHAPE.unpack_from(record, 0)
    _check_shape(height, width, views)
    if len(record) != record_bytes(views, flags):
        raise BitstreamError(f"corrupt camera stream: {len(record)} bytes for {views} views, expected "
                             f"{record_bytes(views, flags)}")
    float64 = bool(flags & FLAG_FLOAT64_CAMERAS)
    dtype = torch.float64 if float64 else torch.float32
    numbers = torch.from_numpy(np.frombuffer(record, dtype="<f8" if float64 else "<f4", offset=_SHAPE.size).astype(
        np.float64 if float64 else np.float32))
    n_k = 4 if flags & FLAG_SHARED_INTRINSICS else 4 * views
    intrinsics = numbers[:n_k].reshape(-1, 4).expand(views, 4)
    extrinsics = numbers[n_k:n_k + 7 * views].reshape(views, 7)
    depth_range = numbers[n_k + 7 * views:].reshape(-1, 2).expand(views, 2)
    if not bool(torch.isfinite(numbers).all()):
        raise BitstreamError("corrupt camera stream: non-finite camera values")
    quats = extrinsics[:, :4].double()
    norms = quats.norm(dim=-1, keepdim=True)
    if bool((norms < 0.5).any() or (norms > 2.0).any()):
        raise BitstreamError("corrupt camera stream: a rotation quaternion is far from unit length")
    w2c = torch.eye(4, dtype=torch.float64).repeat(views, 1, 1)
    w2c[:, :3, :3] = quat_to_rotmat(quats / norms)
    w2c[:, :3, 3] = extrinsics[:, 4:].double()
    K = intrinsics_matrix(*intrinsics.double().unbind(-1))
    try:
        cameras = Cameras(K=K.to(dtype), w2c=w2c.to(dtype), near=depth_range[:, 0].to(dtype).clone(),
                          far=depth_range[:, 1].to(dtype).clone(), width=width, height=height)
    except CameraError as exc:
        raise BitstreamError(f"corrupt camera stream: {exc}") from None
    return cameras
