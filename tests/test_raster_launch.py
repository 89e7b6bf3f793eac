"""codecsplat_warp.device.launch, which the rasterizer relies on for a low host overhead: a launch is checked and
recorded once per argument types (or caller-given layout) and thread, then replayed with new tensors, shapes and
scalars; and ops.primitives.radix_sort_pairs, the sort the rasterizer calls on tensors directly."""

from __future__ import annotations

import contextlib
import gc
import threading
import weakref
from typing import Any

import pytest
import torch
import warp as wp
from conftest import DEVICES

from codecsplat_warp.device import launch, stage_host_values, vectors, warp_scope
from codecsplat_warp.errors import InputError
from codecsplat_warp.ops.primitives import inclusive_scan, radix_sort_pairs


@wp.kernel
def _scaled_sum(points: wp.array(dtype=Any), weights: wp.array(dtype=Any), factor: Any, offset: int,
                out: wp.array(dtype=Any)):  # fmt: skip
    i = wp.tid()
    p = points[i]
    out[i] = factor * weights[i] * (p[0] + p[1] + p[2]) + type(factor)(float(offset * points.shape[0]))


def _run(points: torch.Tensor, weights: torch.Tensor, factor: float, offset: int, layout=None) -> torch.Tensor:
    out = torch.empty_like(weights)
    scalar = wp.float64 if points.dtype == torch.float64 else wp.float32
    with warp_scope(points.device) as wdev:
        launch(_scaled_sum, points.shape[0], [vectors(points), weights, scalar(factor), offset, out], wdev,
               layout=layout)  # fmt: skip
    return out


def _expected(points, weights, factor, offset):
    return factor * weights * points.sum(dim=-1) + offset * points.shape[0]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("explicit_layout", [False, True])
def test_replays_follow_new_tensors_shapes_and_scalars(device, dtype, explicit_layout):
    g = torch.Generator().manual_seed(0)
    layout = ("scaled_sum", dtype) if explicit_layout else None
    for n, factor, offset in [(5, 2.0, 1), (5, -0.5, 3), (17, 3.0, -2), (1, 1.5, 0), (17, 0.25, 7)]:
        points = torch.rand(n, 3, generator=g, dtype=dtype).to(device)
        weights = torch.rand(n, generator=g, dtype=dtype).to(device)
        got = _run(points, weights, factor, offset, layout)
        torch.testing.assert_close(got, _expected(points, weights, factor, offset))


@pytest.mark.parametrize("device", DEVICES)
def test_vectors_of_a_tensor_without_array_dimension_raise(device):
    with pytest.raises(InputError, match="no array dimension left"):
        _run(torch.rand(3, device=device), torch.rand(1, device=device), 1.0, 0)


@pytest.mark.parametrize("device", DEVICES)
def test_non_contiguous_tensor_raises_on_a_replay_too(device):
    points, weights = torch.rand(6, 3, device=device), torch.rand(6, device=device)
    _run(points, weights, 1.0, 0)
    with pytest.raises(InputError, match="'weights'.*contiguous"):
        _run(points, torch.rand(12, device=device)[::2], 1.0, 0)


@pytest.mark.parametrize("device", DEVICES)
def test_recorded_launch_keeps_no_tensor_alive(device):
    _run(torch.rand(4, 3, device=device), torch.rand(4, device=device), 1.0, 0)
    points = torch.rand(8, 3, device=device)
    alive = weakref.ref(points)
    _run(points, torch.rand(8, device=device), 1.0, 0)
    del points
    gc.collect()
    assert alive() is None


@pytest.mark.parametrize("device", DEVICES)
def test_threads_replay_their_own_launches(device):
    results, errors = {}, []

    def work(seed: int) -> None:
        try:
            g = torch.Generator().manual_seed(seed)
            for _ in range(50):
                n = int(torch.randint(1, 64, (1,), generator=g))
                points = torch.rand(n, 3, generator=g).to(device)
                weights = torch.rand(n, generator=g).to(device)
                factor = float(torch.rand(1, generator=g))
                got = _run(points, weights, factor, seed)
                torch.testing.assert_close(got, _expected(points, weights, factor, seed))
            results[seed] = True
        except Exception as exc:  # noqa: BLE001 - reported by the main thread
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(seed,)) for seed in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert not errors and len(results) == 4


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize(
    "key_dtype, count, end_bit",
    [(torch.int64, 1, 5), (torch.int64, 37, 12), (torch.int64, 1000, 40), (torch.int64, 513, 63),
     (torch.uint32, 1, 5), (torch.uint32, 1000, 25), (torch.uint32, 513, 32)],
)  # fmt: skip
def test_radix_sort_pairs_sorts_like_a_stable_sort(device, key_dtype, count, end_bit):
    g = torch.Generator().manual_seed(count)
    keys = torch.randint(0, 2 ** min(end_bit, 62), (2 * count,), generator=g, dtype=torch.int64)
    keys[: count // 3] = keys[count // 3 : 2 * (count // 3)]  # ties: the sort must keep their order
    values = torch.arange(2 * count, dtype=torch.int32)
    want_keys, order = torch.sort(keys[:count], stable=True)
    keys, values = keys.to(key_dtype).to(device), values.to(device)
    with warp_scope(keys.device):
        radix_sort_pairs(keys, values, count, end_bit)
    assert torch.equal(keys[:count].cpu().to(torch.int64), want_keys)
    assert torch.equal(values[:count].cpu(), order.to(torch.int32))


def test_radix_sort_pairs_rejects_short_or_mistyped_buffers():
    with pytest.raises(InputError, match="keys"):
        radix_sort_pairs(torch.zeros(3, dtype=torch.int64), torch.zeros(4, dtype=torch.int32), 2, 8)
    with pytest.raises(InputError, match="values"):
        radix_sort_pairs(torch.zeros(4, dtype=torch.int64), torch.zeros(4, dtype=torch.int64), 2, 8)
    with pytest.raises(InputError, match="keys"):
        radix_sort_pairs(torch.zeros(4, dtype=torch.int32), torch.zeros(4, dtype=torch.int32), 2, 8)


@pytest.mark.parametrize("device", DEVICES)
def test_warp_scope_runs_on_torchs_current_stream_and_restores_warps(device):
    """Inside the scope Warp's device stream is torch's current one (here a side stream with a slow kernel queued
    first, which a launch and a staged host read must wait for); after it, Warp's own stream again."""
    device = torch.device(device)
    side = torch.cuda.Stream(device) if device.type == "cuda" else None
    before = wp.get_device(str(device)).stream if device.type == "cuda" else None
    with torch.cuda.stream(side) if side is not None else contextlib.nullcontext():
        values = torch.zeros(300, dtype=torch.int64, device=device)
        if side is not None:
            torch.cuda._sleep(50_000_000)  # ~25 ms of GPU time before the fill on the side stream
        values.fill_(7)
        with warp_scope(device) as wdev:
            if side is not None:
                assert wdev.stream.cuda_stream == side.cuda_stream
            out = _run(torch.ones(300, 3, device=device), values.double().float(), 1.0, 0)
            assert stage_host_values(values, wdev).values() == [7] * 300
        assert torch.equal(out.cpu(), torch.full((300,), 21.0))
    if before is not None:
        assert wp.get_device(str(device)).stream is before


@pytest.mark.parametrize("device", DEVICES)
def test_staged_host_read_waits_for_its_copy_only_and_is_invalidated_by_the_next(device):
    """A read staged before slow work is queued returns the values as they were when it was staged; on CUDA without
    waiting for the slow work, and a second staged read makes the first one an error (they share a buffer). A part
    of the tensor is read without a slice; a wrong dtype, layout or range is a typed error."""
    device = torch.device(device)
    values = torch.arange(5, dtype=torch.int64, device=device)
    with warp_scope(device) as wdev:
        assert stage_host_values(values, wdev, 1, 3).values() == [1, 2, 3]
        assert stage_host_values(values, wdev, 5).values() == []
        for bad in ((values, wdev, 3, 3), (values.int(), wdev), (values[::2], wdev)):
            with pytest.raises(InputError):
                stage_host_values(*bad)
        first = stage_host_values(values, wdev)
        if device.type == "cuda":
            torch.cuda._sleep(200_000_000)  # ~100 ms of GPU time queued after the copy
        values += 10
        assert first.values() == [0, 1, 2, 3, 4]
        if device.type == "cuda":
            assert not torch.cuda.current_stream(device).query()  # the slow work still runs
        second = stage_host_values(values, wdev)
        if device.type == "cuda":
            with pytest.raises(RuntimeError, match="reused the buffer"):
                first.values()
        assert second.values() == [10, 11, 12, 13, 14]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("count", [1, 7, 100_003])
def test_inclusive_scan_is_cumsum_in_int64(device, count):
    g = torch.Generator().manual_seed(count)
    values = torch.randint(0, 2**40, (count,), generator=g, dtype=torch.int64)  # sums far beyond int32
    out = torch.full_like(values, -1).to(device)
    with warp_scope(torch.device(device)):
        inclusive_scan(values.to(device), out)
    assert torch.equal(out.cpu(), torch.cumsum(values, 0))


def test_inclusive_scan_rejects_other_dtypes_and_lengths():
    with pytest.raises(InputError, match="values"):
        inclusive_scan(torch.zeros(4, dtype=torch.int32), torch.zeros(4, dtype=torch.int64))
    with pytest.raises(InputError, match="4 values into 3"):
        inclusive_scan(torch.zeros(4, dtype=torch.int64), torch.zeros(3, dtype=torch.int64))
