"""CUDA warp-level helpers for Warp kernels (``wp.func_native`` snippets), each also correct on the CPU.

Warp's CPU backend runs a tiled launch with one lane per block and a plain launch one thread at a time, so on
the CPU every helper reduces over a single lane: :func:`warp_sum_row_add` adds its values, :func:`warp_max` returns
its argument, :func:`warp_count` whether it is non-zero, :func:`warp_append` is an atomic increment.
:func:`atomic_increment` counts atomically on both (Warp's own CPU atomics are plain adds, wrong for launches that
several CPU threads run at once). On CUDA they act on the lanes of the calling thread's 32-thread warp (a partial
last warp of a block included).
"""

from __future__ import annotations

import warp as wp

_WARP_MASK = """
const unsigned warp_lane = threadIdx.x & 31u;
const unsigned warp_lanes = min(32u, blockDim.x - (threadIdx.x & ~31u));
const unsigned warp_mask = warp_lanes == 32u ? 0xffffffffu : ((1u << warp_lanes) - 1u);
"""

_WARP_SUM_ROW_ADD = """
#if defined(__CUDA_ARCH__)
MASK
if (warp_lanes == 32u) {
    // reduce-scatter over the lane bits 4..0: 10 -> 5 -> 3 -> 2 -> 1 -> 1 sums per lane (zero-padded halves),
    // 12 shuffles instead of 50; then the lane pair that holds a column's total adds it, one atomic per column
    const bool b4 = (warp_lane & 16u) != 0u, b3 = (warp_lane & 8u) != 0u;
    const bool b2 = (warp_lane & 4u) != 0u, b1 = (warp_lane & 2u) != 0u;
    SCALAR a[5];
    #pragma unroll
    for (int k = 0; k < 5; ++k) {
        const SCALAR low = values.c[k], high = values.c[k + 5];
        a[k] = (b4 ? high : low) + __shfl_xor_sync(0xffffffffu, b4 ? low : high, 16);
    }
    SCALAR b[3];
    #pragma unroll
    for (int k = 0; k < 3; ++k) {
        const SCALAR low = a[k], high = k + 3 < 5 ? a[k + 3] : SCALAR(0);
        b[k] = (b3 ? high : low) + __shfl_xor_sync(0xffffffffu, b3 ? low : high, 8);
    }
    SCALAR c[2];
    #pragma unroll
    for (int k = 0; k < 2; ++k) {
        const SCALAR low = b[k], high = k + 2 < 3 ? b[k + 2] : SCALAR(0);
        c[k] = (b2 ? high : low) + __shfl_xor_sync(0xffffffffu, b2 ? low : high, 4);
    }
    SCALAR total = (b1 ? c[1] : c[0]) + __shfl_xor_sync(0xffffffffu, b1 ? c[0] : c[1], 2);
    total += __shfl_xor_sync(0xffffffffu, total, 1);
    const int of_b = (b2 ? 2 : 0) + (b1 ? 1 : 0);  // the entry of b, of a and the column this lane's total is
    const int of_a = (b3 ? 3 : 0) + of_b;
    const int column = (b4 ? 5 : 0) + of_a;
    if ((warp_lane & 1u) == 0u && of_b < 3 && of_a < 5 && column < columns)
        wp::atomic_add(out, row, column, total);
} else {
    #pragma unroll
    for (int k = 0; k < 10; ++k) {
        SCALAR total = values.c[k];
        for (unsigned offset = 16u; offset > 0u; offset >>= 1u) {
            const SCALAR other = __shfl_down_sync(warp_mask, total, offset);
            if (warp_lane + offset < warp_lanes) total += other;
        }
        if (warp_lane == 0u && k < columns) wp::atomic_add(out, row, k, total);
    }
}
#else
for (int k = 0; k < 10 && k < columns; ++k) wp::atomic_add(out, row, k, values.c[k]);
#endif
""".replace("MASK", _WARP_MASK)


@wp.func_native(_WARP_SUM_ROW_ADD.replace("SCALAR", "wp::float32"))
def warp_sum_row_add(out: wp.array2d(dtype=wp.float32), row: int, values: wp.types.vector(10, wp.float32),
                     columns: int):
    """Add the sums over this thread's CUDA warp of ``values`` (one 10-vector per lane: a projected row's
    gradient) to ``out[row, :columns]``, atomically. On a whole warp a reduce-scatter (lane pairs exchange half
    of what they hold: 12 shuffles, where ten tree reductions take 50) leaves each column's total on a lane
    of its own, and those lanes add at once: one atomic instruction for the warp instead of ten from one lane. A
    partial warp sums each column to its first lane, which adds them. On the CPU (one lane) ``values`` is added
    as it is. Every lane of the warp must call it with the same ``row`` (no divergence)."""
    ...


@wp.func_native(_WARP_SUM_ROW_ADD.replace("SCALAR", "wp::float64"))
def warp_sum_row_add(out: wp.array2d(dtype=wp.float64), row: int,  # noqa: F811 - the float64 overload
                     values: wp.types.vector(10, wp.float64), columns: int):
    ...


_WARP_MAX = f"""
#if defined(__CUDA_ARCH__)
{_WARP_MASK}
return __reduce_max_sync(warp_mask, value);
#else
return value;
#endif
"""


@wp.func_native(_WARP_MAX)
def warp_max(value: int) -> int:
    """Largest ``value`` over the lanes of this thread's CUDA warp, on every lane (on the CPU: ``value``); every
    lane of the warp must call it."""
    ...


_WARP_COUNT = f"""
#if defined(__CUDA_ARCH__)
{_WARP_MASK}
return __popc(__ballot_sync(warp_mask, flag));
#else
return flag != 0 ? 1 : 0;
#endif
"""


@wp.func_native(_WARP_COUNT)
def warp_count(flag: int) -> int:
    """How many lanes of this thread's CUDA warp have ``flag`` non-zero, on every lane (on the CPU: 1 when
    ``flag`` is non-zero, else 0); every lane of the warp must call it."""
    ...


_WARP_APPEND = """
#if defined(__CUDA_ARCH__)
const unsigned active = __activemask();
const unsigned lane = threadIdx.x & 31u;
const int leader = __ffs(active) - 1;
unsigned long long base = 0ull;
if (static_cast<int>(lane) == leader)
    base = atomicAdd(reinterpret_cast<unsigned long long*>(counters.data) + slot,
                     static_cast<unsigned long long>(__popc(active)));
base = __shfl_sync(active, base, leader);
return static_cast<wp::int32>(base + __popc(active & ((1u << lane) - 1u)));
#else
return static_cast<wp::int32>(__atomic_fetch_add(counters.data + slot, static_cast<wp::int64>(1), __ATOMIC_RELAXED));
#endif
"""


@wp.func_native(_WARP_APPEND)
def warp_append(counters: wp.array(dtype=wp.int64), slot: int) -> int:
    """Claim the next free index of a list whose length is ``counters[slot]``: returns the old count and adds 1.
    On CUDA the lanes of a warp that call it together claim consecutive indices with one atomic (a warp-aggregated
    append: the order within and between warps is unspecified); on the CPU it is one atomic increment. Lanes need
    not call it together."""
    ...


_ATOMIC_INCREMENT = """
#if defined(__CUDA_ARCH__)
atomicAdd(reinterpret_cast<unsigned long long*>(counters.data) + slot, 1ull);
#else
__atomic_fetch_add(counters.data + slot, static_cast<wp::int64>(1), __ATOMIC_RELAXED);
#endif
"""


@wp.func_native(_ATOMIC_INCREMENT)
def atomic_increment(counters: wp.array(dtype=wp.int64), slot: int):
    """Add 1 to ``counters[slot]`` atomically on the CPU too, where ``wp.atomic_add`` is a plain add (a CPU launch
    runs on one thread; launches that several threads run at once must not lose counts)."""
    ...


CACHE_LINE_INT64 = 16
"""int64 counters per 128-byte cache line: the stride between the lines of :func:`warp_fold_range`."""

_WARP_FOLD_RANGE = """
#if defined(__CUDA_ARCH__)
const unsigned active = __activemask();
const unsigned lane = threadIdx.x & 31u;
const int leader = __ffs(active) - 1;
const int low = __reduce_min_sync(active, value);
const int high = __reduce_max_sync(active, value);
if (static_cast<int>(lane) == leader) {
    const unsigned line = (blockIdx.x * (blockDim.x >> 5u) + (threadIdx.x >> 5u)) % static_cast<unsigned>(lines);
    long long* range = reinterpret_cast<long long*>(counters.data) + first + CACHE_LINE_INT64 * line;
    atomicMin(range, static_cast<long long>(low));
    atomicMax(range + 1, static_cast<long long>(high));
}
#else
wp::int64* low = counters.data + first;
wp::int64 seen = __atomic_load_n(low, __ATOMIC_RELAXED);
while (value < seen && !__atomic_compare_exchange_n(low, &seen, static_cast<wp::int64>(value), false,
                                                    __ATOMIC_RELAXED, __ATOMIC_RELAXED)) {}
wp::int64* high = counters.data + first + 1;
seen = __atomic_load_n(high, __ATOMIC_RELAXED);
while (value > seen && !__atomic_compare_exchange_n(high, &seen, static_cast<wp::int64>(value), false,
                                                    __ATOMIC_RELAXED, __ATOMIC_RELAXED)) {}
#endif
""".replace("CACHE_LINE_INT64", f"{CACHE_LINE_INT64}u")


@wp.func_native(_WARP_FOLD_RANGE)
def warp_fold_range(counters: wp.array(dtype=wp.int64), first: int, lines: int, value: int):
    """Fold ``value`` into a running range kept in ``lines`` cache lines of ``counters``: line ``k`` holds a
    minimum at ``first + 16 k`` and a maximum at ``first + 16 k + 1`` (:data:`CACHE_LINE_INT64` apart), and the
    range is the min and max over the lines. On CUDA the lanes of a warp that call it together reduce first and
    one lane adds two fire-and-forget atomics to its warp's line (warps spread over the lines, so that they do not
    all queue on one cache line); on the CPU every call folds into line 0 atomically. Lanes need not call it
    together."""
    ...
