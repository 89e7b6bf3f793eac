"""The scene bitstream container: round trip, byte accounting, CRC, bounds, and a fuzzed parser."""

from __future__ import annotations

import struct
import tracemalloc
import zlib

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from codecsplat_warp.codec import bitstream as bs
from codecsplat_warp.codec import bytes_report, pack_bitstream, parse_bitstream
from codecsplat_warp.errors import BitstreamError, InputError
from codecsplat_warp.synthetic import make_rig

MODEL_ID = "0123456789abcdef"
STREAMS = [b"\x01\x02\x03\x04" * 3, b"\xff\xee\xdd\xcc"]


def _packed(cameras=None, streams=STREAMS, lam=64.0) -> bytes:
    cameras = cameras if cameras is not None else make_rig(2, 48, 32, dtype=torch.float32)
    return pack_bitstream(MODEL_ID, lam, cameras, streams)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_round_trip_keeps_cameras_header_and_streams(dtype):
    cameras = make_rig(3, 48, 32, dtype=dtype)
    data = pack_bitstream(MODEL_ID, 100.5, cameras, STREAMS + [b"\x00" * 8])
    parsed = parse_bitstream(data)
    assert parsed.header == bs.Header(bs.FORMAT_VERSION, parsed.header.flags, MODEL_ID, 100.5)
    assert bool(parsed.header.flags & bs.FLAG_FLOAT64_CAMERAS) == (dtype == torch.float64)
    assert parsed.feature_streams == STREAMS + [b"\x00" * 8]
    cams = parsed.cameras
    assert (cams.width, cams.height, cams.num_views, cams.dtype) == (48, 32, 3, dtype)
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    for a, b in ((cams.K, cameras.K), (cams.w2c, cameras.w2c), (cams.near, cameras.near), (cams.far, cameras.far)):
        torch.testing.assert_close(a, b, atol=tol * 100, rtol=tol)


def test_shared_intrinsics_and_depth_range_are_stored_once():
    shared = make_rig(4, 48, 32, dtype=torch.float32)
    shared = shared.__class__(K=shared.K[:1].expand(4, 3, 3).clone(), w2c=shared.w2c, near=shared.near, far=shared.far,
                              width=48, height=32)
    header = parse_bitstream(_packed(shared, STREAMS * 2)).header
    assert header.flags & bs.FLAG_SHARED_INTRINSICS and header.flags & bs.FLAG_SHARED_DEPTH_RANGE
    varied = shared.with_depth_range(torch.tensor([0.5, 0.6, 0.7, 0.8]), 20.0)
    header = parse_bitstream(_packed(varied, STREAMS * 2)).header
    assert header.flags & bs.FLAG_SHARED_INTRINSICS and not header.flags & bs.FLAG_SHARED_DEPTH_RANGE
    assert bs.record_bytes(4, header.flags) == 5 + 4 * (4 + 28 + 8)


def test_camera_record_is_stored_raw_when_deflate_would_grow_it():
    few = make_rig(2, 48, 32, dtype=torch.float32)  # 2 views of distinct numbers: Deflate cannot shrink 85 bytes
    parsed = parse_bitstream(_packed(few))
    assert parsed.header.flags & bs.FLAG_RAW_CAMERAS
    assert parsed.part_bytes["cameras"] == bs.framed_bytes(bs.record_bytes(2, parsed.header.flags))
    torch.testing.assert_close(parsed.cameras.w2c, few.w2c, atol=1e-5, rtol=1e-5)
    rig = make_rig(2, 48, 32, dtype=torch.float32)
    repeated = rig.__class__(K=rig.K[:1].expand(16, 3, 3).clone(), w2c=rig.w2c[:1].expand(16, 4, 4).clone(),
                             near=rig.near[:1].expand(16).clone(), far=rig.far[:1].expand(16).clone(), width=48,
                             height=32)  # fmt: skip
    parsed = parse_bitstream(_packed(repeated, STREAMS * 8))
    assert not parsed.header.flags & bs.FLAG_RAW_CAMERAS
    assert parsed.part_bytes["cameras"] < bs.framed_bytes(bs.record_bytes(16, parsed.header.flags))
    raw = _frames(_header(bs.FLAG_RAW_CAMERAS), bs._camera_record(few)[0] + b"\x00", STREAMS)
    with pytest.raises(BitstreamError, match="corrupt camera stream"):
        parse_bitstream(raw)


def test_packing_checks_its_inputs():
    cameras = make_rig(2, 48, 32, dtype=torch.float32)
    with pytest.raises(InputError, match="feature streams"):
        pack_bitstream(MODEL_ID, 64.0, cameras, STREAMS[:1])
    with pytest.raises(InputError, match="multiple of 4"):
        pack_bitstream(MODEL_ID, 64.0, make_rig(2, 50, 32, dtype=torch.float32), STREAMS)


def test_bytes_report_accounts_for_every_byte():
    data = _packed()
    report = bytes_report(data)
    assert set(report) == {"header", "cameras", "view0", "view1", "total"}
    assert report["header"] == bs.HEADER_BYTES == 18
    assert report["view0"] == 1 + 4 + len(STREAMS[0]) and report["view1"] == 1 + 4 + len(STREAMS[1])
    assert report["total"] == len(data) == sum(v for k, v in report.items() if k != "total")


def test_every_single_byte_corruption_and_truncation_is_detected():
    data = _packed()
    for i in range(len(data)):
        for flip in (0x01, 0x80):
            corrupted = bytearray(data)
            corrupted[i] ^= flip
            with pytest.raises(BitstreamError):
                parse_bitstream(bytes(corrupted))
        with pytest.raises(BitstreamError):
            parse_bitstream(data[:i])
    with pytest.raises(BitstreamError, match="trailing"):
        parse_bitstream(data + b"\x00")


def test_version_magic_flags_lambda_and_shape_errors_name_the_problem():
    data = bytearray(_packed())
    newer = bytearray(data)
    newer[4] = bs.FORMAT_VERSION + 1
    with pytest.raises(BitstreamError, match="newer"):
        parse_bitstream(bytes(newer))
    with pytest.raises(BitstreamError, match="magic"):
        parse_bitstream(b"PNG\x00" + bytes(data[4:]))
    with pytest.raises(BitstreamError, match="unknown flags"):
        parse_bitstream(_rewrite_header(data, flags=0x40))
    with pytest.raises(BitstreamError, match="lambda"):
        parse_bitstream(_rewrite_header(data, lam=4096.0))
    record = struct.pack("<HHB", 32, 48, 65) + b"\x00" * 100
    with pytest.raises(BitstreamError, match="65"):
        parse_bitstream(_with_camera_record(record, flags=0))
    record = struct.pack("<HHB", 30, 48, 2)
    with pytest.raises(BitstreamError, match="multiple of 4"):
        parse_bitstream(_with_camera_record(record, flags=0))
    with pytest.raises(BitstreamError, match="limit"):
        parse_bitstream(_with_camera_record(struct.pack("<HHB", 8192, 8192, 2), flags=0))
    with pytest.raises(BitstreamError, match="bytes for 2 views"):
        parse_bitstream(_with_camera_record(struct.pack("<HHB", 32, 48, 2) + b"\x00" * 12, flags=0))


def test_invalid_camera_values_are_bitstream_errors():
    cams = make_rig(2, 48, 32, dtype=torch.float32)
    record, flags = bs._camera_record(cams)
    numbers = np.frombuffer(record, dtype="<f4", offset=5).copy()
    numbers[0] = -1.0  # fx of a focal length
    with pytest.raises(BitstreamError, match="focal"):
        parse_bitstream(_with_camera_record(record[:5] + numbers.tobytes(), flags))
    numbers[0] = np.nan
    with pytest.raises(BitstreamError, match="non-finite"):
        parse_bitstream(_with_camera_record(record[:5] + numbers.tobytes(), flags))


def test_deflate_bombs_are_cut_off():
    bomb = zlib.compressobj(9, zlib.DEFLATED, -15)
    payload = bomb.compress(struct.pack("<HHB", 32, 48, 2) + b"\x00" * 10_000_000) + bomb.flush()
    tracemalloc.start()
    try:
        with pytest.raises(BitstreamError, match="Deflate"):
            parse_bitstream(_frames(_header(), payload, []))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 1_000_000


# --------------------------------------------------------------------------------------------------
# Fuzzing: arbitrary, mutated, truncated, and well-framed random inputs raise only BitstreamError.
def _parse_within_bounds(data: bytes) -> None:
    """Parse ``data``; anything but success or BitstreamError fails, and so does a large allocation."""
    tracemalloc.start()
    try:
        try:
            parse_bitstream(data)
        except BitstreamError:
            pass
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 200_000 + 4 * len(data), peak


FUZZ = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
"""No deadline (Hypothesis's default is 200 ms an example): an example's time says nothing about the parser on a
loaded machine. What each example may allocate is bounded by :func:`_parse_within_bounds` instead."""


@FUZZ
@given(st.binary(max_size=400))
def test_fuzz_random_bytes(data):
    """Catches: any exception but BitstreamError, or an allocation beyond the bound, on arbitrary bytes with or
    without the magic and format version in front."""
    _parse_within_bounds(data)
    _parse_within_bounds(bs.MAGIC + bytes([1]) + data)


@FUZZ
@given(st.lists(st.tuples(st.integers(0, 10_000), st.integers(0, 255), st.sampled_from(["set", "insert", "delete"])),
                min_size=1, max_size=6), st.integers(0, 400))
def test_fuzz_mutated_and_truncated_bitstreams(edits, cut):
    """Catches: any exception but BitstreamError, or an allocation beyond the bound, on a valid bitstream with
    bytes set, inserted or deleted, and cut short."""
    data = bytearray(_packed())
    for position, value, kind in edits:
        i = position % (len(data) + 1)
        if kind == "insert":
            data.insert(i, value)
        elif i < len(data) and kind == "set":
            data[i] = value
        elif i < len(data):
            del data[i]
    _parse_within_bounds(bytes(data))
    _parse_within_bounds(bytes(data[:cut]))


@FUZZ
@given(flags=st.integers(0, 15), views=st.integers(0, 70), height=st.integers(0, 9000), width=st.integers(0, 9000),
       exact=st.booleans(), data=st.data(), streams=st.lists(st.binary(max_size=24), max_size=4),
       lam=st.floats(allow_nan=True, allow_infinity=True, width=32))
def test_fuzz_well_framed_inputs_with_valid_crcs(flags, views, height, width, exact, data, streams, lam):
    """Valid framing and CRCs, so the fuzzing reaches the camera record and stream checks; with ``exact`` the
    camera numbers have the size the views and flags call for (random, or plausible cameras). Catches: a field
    used before its bound is checked (views, image size, flags, lambda, camera values, stream lengths), as any
    exception but BitstreamError or an allocation beyond the bound."""
    size = bs.record_bytes(views, flags) - 5
    numbers = data.draw(st.binary(min_size=size, max_size=size) if exact else st.binary(max_size=600))
    if exact and views and data.draw(st.booleans()):
        numbers = _plausible_numbers(views, flags, data.draw(st.integers(0, 2**16)))
    record = struct.pack("<HHB", height, width, views % 256) + numbers
    deflater = zlib.compressobj(9, zlib.DEFLATED, -15)
    payload = record if flags & bs.FLAG_RAW_CAMERAS else deflater.compress(record) + deflater.flush()
    _parse_within_bounds(_frames(_header(flags=flags, lam=lam), payload, streams))


def _plausible_numbers(views: int, flags: int, seed: int) -> bytes:
    """Camera numbers of ``views`` views that form valid cameras: unit quaternions, positive focals."""
    rng = np.random.default_rng(seed)
    k = 1 if flags & bs.FLAG_SHARED_INTRINSICS else views
    r = 1 if flags & bs.FLAG_SHARED_DEPTH_RANGE else views
    quats = rng.normal(size=(views, 4))
    extrinsics = np.concatenate([quats / np.linalg.norm(quats, axis=1, keepdims=True), rng.normal(size=(views, 3))], 1)
    numbers = np.concatenate([np.tile([40.0, 40.0, 24.0, 16.0], k), extrinsics.ravel(), np.tile([0.5, 20.0], r)])
    return numbers.astype("<f8" if flags & bs.FLAG_FLOAT64_CAMERAS else "<f4").tobytes()


# --------------------------------------------------------------------------------------------------
def _header(flags: int = 0, lam: float = 64.0) -> bytes:
    return struct.pack("<4sBB8sf", bs.MAGIC, bs.FORMAT_VERSION, flags, bytes.fromhex(MODEL_ID), lam)


def _frames(header: bytes, camera_payload: bytes, streams: list[bytes]) -> bytes:
    out = header + bs._frame(camera_payload, zlib.crc32(camera_payload, zlib.crc32(header)))
    return out + b"".join(bs._frame(s, zlib.crc32(s)) for s in streams)


def _rewrite_header(data: bytes, flags: int | None = None, lam: float | None = None) -> bytes:
    """``data`` with new header fields and a camera CRC that matches them."""
    _, _, old_flags, _, old_lam = struct.unpack_from("<4sBB8sf", data)
    header = _header(old_flags if flags is None else flags, old_lam if lam is None else lam)
    length, offset = bs._read_varint(memoryview(data), bs.HEADER_BYTES, "cameras")
    payload = bytes(data[offset + 4:offset + 4 + length])
    return _frames(header, payload, []) + bytes(data[offset + 4 + length:])


def _with_camera_record(record: bytes, flags: int) -> bytes:
    deflater = zlib.compressobj(9, zlib.DEFLATED, -15)
    return _frames(_header(flags), deflater.compress(record) + deflater.flush(), STREAMS)
