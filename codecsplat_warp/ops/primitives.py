"""Launch primitives of the ops on tensors' memory: Warp's native radix sort and scan, and concurrent CPU launches.

:func:`radix_sort_pairs` and :func:`inclusive_scan` call Warp's native sort and scan on the tensors' memory (no
``wp.array`` wrapping); on CUDA they run on Warp's current stream, so call them inside
:func:`~codecsplat_warp.device.warp_scope`. :func:`row_chunks` and :func:`run_concurrently` split a CPU launch over
image rows and run the pieces on a shared thread pool (a Warp CPU launch runs on one thread and releases the GIL);
:func:`launch_by_rows` launches a row-parallel kernel that way.
"""

from __future__ import annotations

import functools
import os
from typing import Sequence

import torch
from warp._src import context as warp_context  # the native sort and scan entry points

from ..device import launch, warp_scope
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
    :func:`run_concurrently` (a Warp CPU launch releases the GIL), using ``torch.get_num_threads()``
    threads like torch's own CPU ops. On CUDA there is one piece.
    """
    pieces = 1 if device.type == "cuda" else max(1, min(torch.get_num_threads(), rows))
    bounds = [rows * i // pieces for i in range(pieces + 1)]
    return [(lo, hi - lo) for lo, hi in zip(bounds, bounds[1:]) if hi > lo]


_cpu_pool = None


def run_concurrently(tasks: Sequence) -> None:
    """Call every task (no arguments); more than one run on a shared thread pool. Re-raises the first error."""
    global _cpu_pool
    if len(tasks) <= 1:
        for task in tasks:
            task()
        return
    if _cpu_pool is None:
        from concurrent.futures import ThreadPoolExecutor

        _cpu_pool = ThreadPoolExecutor(max_workers=os.cpu_count() or 1, thread_name_prefix="codecsplat-cpu")
    futures = [_cpu_pool.submit(task) for task in tasks[1:]]
    tasks[0]()
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
