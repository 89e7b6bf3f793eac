"""Launch primitives of the ops on tensors' memory: Warp's native radix sort and scan, and concurrent CPU launches.

:func:`radix_sort_pairs` and :func:`inclusive_scan` call Warp's native sort and scan on the tensors' memory (no
``wp.array`` wrapping); on CUDA they run on Warp's current stream, so call them inside
:func:`~codecsplat_warp.device.warp_scope`. :func:`row_chunks` and :func:`weighted_chunks` split a CPU launch into
pieces, and :func:`run_concurrently` runs the pieces on :func:`~codecsplat_warp.device.cpu_threads` threads (a Warp CPU
launch runs on one thread and releases the GIL).
:func:`launch_by_rows` launches a row-parallel kernel that way.
"""

from __future__ import annotations

import functools
import threading
from typing import Sequence

import torch
from warp._src import context as warp_context  # the native sort and scan entry points

from ..device import cpu_threads, launch, warp_scope
from ..errors import InputError


def radix_sort_pairs(keys: torch.Tensor, values: torch.Tensor, count: int, end_bit: int) -> None:
    """Sort ``keys[:count]`` (uint32 or int64) and ``values[:count]`` (int32) in place by key bits ``[0, end_bit)``.

    ``wp.utils.radix_sort_pairs`` on the tensors' memory, without wrapping them as ``wp.array`` (the native call
    that function makes); both tensors are contiguous with at least ``2 * count`` elements, the second half being
    scratch. On CUDA it runs on Warp's current stream: call it inside :func:`~codecsplat_warp.device.warp_scope`.

    Raises:
        InputError: wrong dtype, too short or not contiguous.
    """
    if count == 0 or end_bit == 0:
        return
    for name, tensor, dtypes in (("keys", keys, _SORT_KEYS), ("values", values, (torch.int32,))):
        if tensor.dtype not in dtypes or tensor.numel() < 2 * count or not tensor.is_contiguous():
            raise InputError(f"radix sort {name} must be contiguous {' or '.join(map(str, dtypes))} with at least "
                             f"{2 * count} elements")  # fmt: skip
    sort = getattr(warp_context.runtime.core, _SORT_KEYS[keys.dtype] + ("_device" if keys.is_cuda else "_host"))
    sort(keys.data_ptr(), values.data_ptr(), count, 0, end_bit, 4)


def inclusive_scan(values: torch.Tensor, out: torch.Tensor) -> None:
    """``torch.cumsum(values, 0, out=out)`` for contiguous 1-D int64 tensors of equal length, by Warp's native scan on
    the tensors' memory (CUB on CUDA, on Warp's current stream: call it inside
    :func:`~codecsplat_warp.device.warp_scope`). One native call on the host, against 25 us for ``torch.cumsum`` on a
    lent H100's host.

    Raises:
        InputError: wrong dtype, shape or length, or not contiguous.
    """
    for name, tensor in (("values", values), ("out", out)):
        if tensor.dtype != torch.int64 or tensor.dim() != 1 or not tensor.is_contiguous():
            raise InputError(f"inclusive scan {name} must be a contiguous 1-D int64 tensor")
    if values.numel() != out.numel():
        raise InputError(f"inclusive scan of {values.numel()} values into {out.numel()}")
    if values.numel() == 0:
        return
    core = warp_context.runtime.core
    scan = core.wp_array_scan_int64_device if values.is_cuda else core.wp_array_scan_int64_host
    succeeded = scan(values.data_ptr(), out.data_ptr(), values.numel(), 8, 8, 1, True)
    if values.is_cuda and not succeeded:  # the host scan returns nothing
        raise RuntimeError(f"Warp's scan failed: {warp_context.runtime.get_error_string()}")


_SORT_KEYS = {torch.uint32: "wp_radix_sort_pairs_uint", torch.int64: "wp_radix_sort_pairs_int64"}
"""Key dtypes :func:`radix_sort_pairs` takes, and the stem of Warp's native sort for each."""


def row_chunks(rows: int, device: torch.device) -> list[tuple[int, int]]:
    """(first row, row count) pieces of a launch over ``rows`` image rows, one per CPU worker thread.

    Warp runs a CPU launch on a single thread; ops split their launches by rows and run the pieces with
    :func:`run_concurrently` (a Warp CPU launch releases the GIL), one piece per thread of
    :func:`~codecsplat_warp.device.cpu_threads`. On CUDA there is one piece.
    """
    pieces = 1 if device.type == "cuda" else max(1, min(cpu_threads(), rows))
    bounds = [rows * i // pieces for i in range(pieces + 1)]
    return [(lo, hi - lo) for lo, hi in zip(bounds, bounds[1:]) if hi > lo]


def weighted_chunks(weights: torch.Tensor, pieces: int) -> list[tuple[int, int]]:
    """(first item, item count) of at most ``pieces`` consecutive runs of items whose weights (a 1-D tensor of
    non-negative numbers, e.g. the work of each item) have about equal sums; every item is in one run."""
    count = weights.shape[0]
    if count == 0:
        return []
    pieces = max(1, min(pieces, count))
    cumulative = torch.cumsum(weights.to(torch.float64), 0)
    targets = cumulative[-1] * torch.arange(1, pieces, dtype=torch.float64) / pieces
    cuts = [0, *torch.searchsorted(cumulative, targets, right=True).tolist(), count]
    return [(lo, hi - lo) for lo, hi in zip(cuts, cuts[1:]) if hi > lo]


_pool = None
_pool_workers = 0
_pool_lock = threading.Lock()


def run_concurrently(tasks: Sequence) -> None:
    """Call every task (no arguments) on :func:`~codecsplat_warp.device.cpu_threads` threads at most: this one
    and the workers of a shared pool, each taking the next task in order when it is free (so that more tasks than
    threads balance uneven work). Returns when every task has finished; re-raises the first error.

    Tasks must not launch tiled kernels (``launch_tiled``): Warp's CPU kernels find their tile arena through one
    process-wide pointer on x86-64 (its JIT has no thread-local storage), which launches on several threads at
    once would share."""
    threads = min(cpu_threads(), len(tasks))
    if threads <= 1:
        for task in tasks:
            task()
        return
    queue = iter(tasks)
    queue_lock = threading.Lock()

    def work() -> None:
        while True:
            with queue_lock:
                task = next(queue, None)
            if task is None:
                return
            task()

    pool = _worker_pool(threads - 1)
    futures = [pool.submit(work) for _ in range(threads - 1)]
    try:
        work()
    finally:
        for future in futures:
            future.exception()  # waits: no task may still run on the tensors when this returns
    for future in futures:
        future.result()


PER_PIECE = object()
"""Stands, in the arguments given to :func:`launch_by_rows`, for the gradient buffer of each row piece."""


def launch_by_rows(kernel, dims: tuple[int, ...], args: list, device: torch.device,
                    scatter_like: torch.Tensor | None = None) -> torch.Tensor | None:  # fmt: skip
    """Launch a row-parallel kernel over ``dims = (*leading, H, W)`` in pieces of image rows (:func:`row_chunks`:
    one piece on CUDA, one per CPU thread on the CPU, run concurrently), each piece with the kernel arguments
    ``args`` followed by its first row (the kernel's last argument; its launch covers ``(*leading, rows, W)``).

    A backward kernel scatters (atomic adds) into a gradient buffer at places other pieces write too: given
    ``scatter_like``, each piece gets its own zeroed buffer of that tensor's shape and dtype where :data:`PER_PIECE`
    stands in ``args``, and the buffers' sum (into the first piece's) is returned; None without ``scatter_like``.
    """
    *leading, height, width = dims
    chunks = row_chunks(height, device)
    buffers = [None] * len(chunks) if scatter_like is None else [torch.zeros_like(scatter_like) for _ in chunks]
    with warp_scope(device) as wdev:
        run_concurrently([
            functools.partial(launch, kernel, (*leading, rows, width),
                              [buffer if arg is PER_PIECE else arg for arg in args] + [row0], wdev)  # fmt: skip
            for (row0, rows), buffer in zip(chunks, buffers)
        ])
    if scatter_like is None:
        return None
    total = buffers[0]
    for buffer in buffers[1:]:
        total += buffer
    return total


def _worker_pool(workers: int):
    """The shared pool, grown to at least ``workers`` threads."""
    global _pool, _pool_workers
    with _pool_lock:
        if _pool is None or _pool_workers < workers:
            from concurrent.futures import ThreadPoolExecutor

            if _pool is not None:
                _pool.shutdown(wait=False)
            _pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="codecsplat-cpu")
            _pool_workers = workers
        return _pool
