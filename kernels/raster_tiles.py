"""Tile binning of projected Gaussians: tile rectangles, sort keys and per-tile ranges.

One intersection is one (camera, Gaussian, tile) triple, for every tile of the Gaussian's bounding rectangle
(:func:`tile_rect`) that holds a pixel the Gaussian may reach (:func:`.raster_reach.tile_reached`); the others hold
no pixel where its alpha reaches the threshold. A row's intersections are written in the order of its rectangle's
tiles, row by row. The projection tests the tiles once: it counts them and, for a rectangle of at most
:data:`MASK_TILES` tiles, hands them to the emission as a bit mask (:func:`reached_tiles`). An intersection's key
is ``[flat tile | depth key]``: the flat tile index ``camera * tiles_per_image + tile`` above ``depth_bits`` bits of
depth key, so one radix sort over the key's used bits orders intersections by camera, then tile, then depth. The
depth key is ``(float32 bits of depth - depth_base) >> depth_shift``: a positive float32 sorts like its bit pattern, and
subtracting the smallest visible pattern (``depth_base``) keeps only the bits the depths of one call span. The
caller picks ``depth_shift`` so that the key fits the key dtype (uint32 or int64); with ``depth_shift = s``
depths within ``2^s`` float32 units in the last place of each other tie, and ties keep the order of the
rows (the sort is stable). The value is the flat index ``camera * N + gaussian`` of the Gaussian's projected
row.

The key's layout is computed on the device (:func:`sort_key_layout`), from the range of the visible depths that
the projection folds into the int64 flag buffer (:data:`DEPTH_RANGE`), by every thread of
:func:`emit_intersections`, whose first thread also writes it into the flag buffer (:data:`KEY_LAYOUT`) for the
host. So the keys can be emitted, sorted and ranged before the host has read the intersection count: into
buffers of a guessed capacity, which the host checks afterwards (see ``codecsplat_warp.ops.raster``). The int64
flag buffer's slots from :data:`KEY_LAYOUT` on are defined here; the projection's validation counters take the
slots below it.
"""

from __future__ import annotations

from typing import Any

import warp as wp

from .lanes import CACHE_LINE_INT64
from .raster_reach import reach_conic, row_reach, tile_reached
from .raster_row import CONIC_A, CONIC_B, CONIC_C, DEPTH, MEAN_X, MEAN_Y, OPACITY

wp.set_module_options({"enable_backward": False})

KEY_LAYOUT = 12
"""First of four int64 flag slots where :func:`emit_intersections` publishes the sort key layout of the call:
``depth_base, depth_shift, depth_bits, bits`` (see :func:`sort_key_layout`)."""

HOST_FLAGS = KEY_LAYOUT + 4
"""The flag slots the host reads after the projection: the validation counters and the key layout (the depth
range lines after them stay on the device)."""

DEPTH_RANGE = CACHE_LINE_INT64
"""First flag slot of the range of the visible depths' float32 bit patterns (what the sort key packs):
``DEPTH_RANGE_LINES`` lines of :func:`~.lanes.warp_fold_range`, folded by the projection."""

DEPTH_RANGE_LINES = 16
"""Cache lines the projection's warps spread their depth-range atomics over (one line: 55 -> 75 us for the
projection of 917,504 Gaussians on an H100, most of it queueing on the line)."""

NUM_FLAGS = DEPTH_RANGE + DEPTH_RANGE_LINES * CACHE_LINE_INT64
"""Length of the int64 flag buffer."""

NO_DEPTH_BITS = 2**31 - 1
"""Initial minimum of every depth-range line (larger than any float32 bit pattern of a positive depth); the
maxima start at 0."""

MAX_DEPTH_SHIFT = 8
"""Most low bits a 32-bit sort key may drop from the depth (see :func:`sort_key_layout`): depths within
``2^8 = 256`` float32 units in the last place (3.1e-5 relative at most) of each other then tie and keep row order.
That lets eight images of 8x8 tiles at 256x448 (14 tile bits; an 8-view RDO step) with depths spanning less than
eight octaves (26 bits) keep a 32-bit key: four sort passes over 8 bytes an intersection instead of five over 12.
A call drops only the bits it must: one such image with a 25-bit span (`bench raster`'s DL3DV workload) drops
four."""

PAD_KEY = wp.constant(wp.int64(2**63 - 1))
"""Key of the padding after the last intersection of a buffer longer than the count: every bit below bit 63 set
(as a uint32: every bit), so padding sorts after every intersection (after equal keys too: the sort is stable)."""


def key_layout(flag_values: list[int]) -> tuple[int, int, int, int]:
    """``(depth_base, depth_shift, depth_bits, bits)`` of the call's sort key as :func:`emit_intersections`
    published it, from the flag values (at least the first :data:`HOST_FLAGS`) read back after it ran."""
    return tuple(flag_values[KEY_LAYOUT : KEY_LAYOUT + 4])

@wp.func
def tile_rect(x: Any, y: Any, radius: wp.vec2i, tile_size: int, tiles_x: int, tiles_y: int):
    """Tiles covered by the pixel rectangle ``[x-rx, x+rx] x [y-ry, y+ry]`` (gsplat's rule).

    Returns ``vec4i(x0, y0, x1, y1)``: first tile inclusive, last tile exclusive, clamped to the grid.
    """
    ts = type(x)(float(tile_size))
    rx = type(x)(float(radius[0]))
    ry = type(x)(float(radius[1]))
    zero = type(x)(0.0)
    x0 = int(wp.min(wp.max(wp.floor((x - rx) / ts), zero), type(x)(float(tiles_x))))
    y0 = int(wp.min(wp.max(wp.floor((y - ry) / ts), zero), type(x)(float(tiles_y))))
    x1 = int(wp.min(wp.max(wp.ceil((x + rx) / ts), zero), type(x)(float(tiles_x))))
    y1 = int(wp.min(wp.max(wp.ceil((y + ry) / ts), zero), type(x)(float(tiles_y))))
    return wp.vec4i(x0, y0, x1, y1)


MASK_TILES = 64
"""Most tiles a row's rectangle may span for the projection to hand the tiles it reaches to the emission as a bit
mask (:func:`reached_tiles`); the emission tests the tiles of larger rectangles again."""


@wp.func
def rect_area(rect: wp.vec4i):
    """Tiles in a :func:`tile_rect` rectangle."""
    return (rect[2] - rect[0]) * (rect[3] - rect[1])


@wp.func
def reached_tiles(mean_x: Any, mean_y: Any, a: Any, b: Any, c: Any, reach: wp.float64, rect: wp.vec4i,
                  tile_size: int, width: int, height: int):  # fmt: skip
    """``(count, mask)``: how many tiles of ``rect`` (:func:`tile_rect`) the row reaches
    (:func:`.raster_reach.tile_reached`), and for a rectangle of at most :data:`MASK_TILES` tiles which ones (int64,
    bit ``j`` for the ``j``-th tile of the rectangle row by row; 0 for a larger one)."""
    conic = reach_conic(a, b, c, reach)
    count = int(0)
    mask = wp.int64(0)
    masked = rect_area(rect) <= MASK_TILES
    j = int(0)
    for ty in range(rect[1], rect[3]):
        for tx in range(rect[0], rect[2]):
            if tile_reached(mean_x, mean_y, conic, tx, ty, tile_size, width, height):
                count += 1
                if masked:
                    mask = mask | (wp.int64(1) << wp.int64(j))
            j += 1
    return count, mask


@wp.func
def depth_bits(depth: Any):
    """The float32 bit pattern of a positive depth, as an int32 (positive float32 values sort like it)."""
    return wp.cast(wp.float32(depth), wp.int32)


@wp.func
def depth_key(depth: Any, depth_base: int, depth_shift: int):
    """The depth part of a sort key (see the module docstring) as an int64."""
    return wp.int64((depth_bits(depth) - depth_base) >> depth_shift)


@wp.func
def bit_length(value: wp.int64):
    """Bits needed to write a non-negative ``value`` (Python's ``int.bit_length``: 0 for 0)."""
    bits = int(0)
    rest = value
    for halving in range(6):
        step = 32 >> halving
        if rest >> wp.int64(step) != wp.int64(0):
            rest = rest >> wp.int64(step)
            bits += step
    if rest != wp.int64(0):
        bits += 1
    return bits


@wp.func
def sort_key_layout(flags: wp.array(dtype=wp.int64), num_tiles: int):
    """The sort key of a call with ``num_tiles`` flat tiles (cameras x tiles per image), from the visible depths'
    bit range in ``flags`` (:data:`DEPTH_RANGE`): ``vec4i(depth_base, depth_shift, depth_bits, bits)``.

    The depth part keeps the bits the range spans (``depth_bits``, above the ``depth_shift`` dropped ones); the
    tile index goes above it. A key of ``bits <= 32`` is stored as a uint32: when tile and depth bits fit in 32
    after dropping at most :data:`MAX_DEPTH_SHIFT` low depth bits (half the sort passes of a 64-bit key, two thirds
    of the bytes). Otherwise nothing is dropped and ``bits > 32``: a lossless int64 key. An empty range (no visible
    depth) has no depth bits.
    """
    low = flags[DEPTH_RANGE]
    high = flags[DEPTH_RANGE + 1]
    lines = (flags.shape[0] - DEPTH_RANGE) // CACHE_LINE_INT64  # DEPTH_RANGE_LINES, known at run time: not unrolled
    for line in range(1, lines):
        low = wp.min(low, flags[DEPTH_RANGE + line * CACHE_LINE_INT64])
        high = wp.max(high, flags[DEPTH_RANGE + line * CACHE_LINE_INT64 + 1])
    tile_bits = bit_length(wp.int64(num_tiles - 1))
    span_bits = bit_length(wp.max(high - low, wp.int64(0)))
    shift = wp.max(0, tile_bits + span_bits - 32)
    if shift > MAX_DEPTH_SHIFT:
        shift = 0
    return wp.vec4i(int(low), shift, span_bits - shift, tile_bits + span_bits - shift)


@wp.kernel
def emit_intersections(
    splats: wp.array2d(dtype=Any),
    radii: wp.array(dtype=wp.vec2i),
    counts: wp.array(dtype=wp.int64),
    masks: wp.array(dtype=wp.int64),
    inclusive_offsets: wp.array(dtype=wp.int64),
    flags: wp.array(dtype=wp.int64),
    num_gaussians: int,
    tile_size: int,
    tiles_x: int,
    tiles_y: int,
    num_tiles: int,
    width: int,
    height: int,
    rounding: wp.float64,
    capacity: int,
    first_row: int,
    keys: wp.array(dtype=Any),
    values: wp.array(dtype=wp.int32),
):
    """Write the keys and values of every intersection of one projected Gaussian (one thread per row, from row
    ``first_row`` on: the CPU splits the rows over threads; the tiles it reaches, as the projection counted them),
    the first ``capacity`` of them, and pad the buffers from the intersection count up to ``capacity``; thread 0 also
    publishes the call's :func:`sort_key_layout` in ``flags`` at :data:`KEY_LAYOUT` (for the host).

    With ``capacity`` >= the count every intersection is written and the rest of the capacity holds
    :data:`PAD_KEY`, so a sort of ``capacity`` pairs orders the intersections as a sort of exactly the count would;
    with ``capacity`` < the count the buffers are incomplete (the host discards them). Launched with ``dim = 1``
    and ``capacity = 0`` it only publishes the layout.

    Args:
        splats: projected rows ``[B*N, 10]`` (x, y, conic..., depth in column 9).
        radii: pixel radii ``[B*N]``; zero means culled.
        counts: int64 intersections per row ``[B*N]``; ``inclusive_offsets`` their inclusive prefix sum; masks:
            ``[B*N]`` int64, the tiles of each row's rectangle it reaches (:func:`reached_tiles`, rectangles of at
            most :data:`MASK_TILES` tiles: the tiles are not tested again).
        flags: the int64 flag buffer with the visible depth range as the projection folded it.
        num_tiles: flat tiles ``B * tiles_x * tiles_y`` (below 2^31); width, height: the image in pixels;
            rounding: :data:`.raster_reach.POWER_ROUNDING` of the rows' dtype (the projection counted with it);
            capacity: intersections the buffers take (below 2^31).
        keys: uint32 (a layout of ``bits <= 32``) or int64 output, values: int32 output (row indices; 0 for
            padding), each at least ``capacity`` long.
    """
    i = first_row + wp.tid()
    total = int(inclusive_offsets[inclusive_offsets.shape[0] - 1])
    for p in range(total + i, capacity, inclusive_offsets.shape[0]):
        keys[p] = keys.dtype(PAD_KEY)
        values[p] = 0
    count = counts[i]
    if count == wp.int64(0) and i != 0:
        return
    layout = sort_key_layout(flags, num_tiles)
    if i == 0:
        for j in range(4):
            flags[KEY_LAYOUT + j] = wp.int64(layout[j])
        if count == wp.int64(0):
            return
    first_tile = (i // num_gaussians) * tiles_x * tiles_y
    mean_x = splats[i, MEAN_X]
    mean_y = splats[i, MEAN_Y]
    rect = tile_rect(mean_x, mean_y, radii[i], tile_size, tiles_x, tiles_y)
    low = depth_key(splats[i, DEPTH], layout[0], layout[1])
    depth_key_bits = wp.int64(layout[2])
    k = int(inclusive_offsets[i] - count)
    end = wp.min(int(inclusive_offsets[i]), capacity)
    rect_width = rect[2] - rect[0]
    area = rect_area(rect)
    if area <= MASK_TILES:
        mask = masks[i]
        for j in range(area):
            if k >= end:
                return
            if (mask >> wp.int64(j)) & wp.int64(1) != wp.int64(0):
                tile = wp.int64(first_tile + (rect[1] + j // rect_width) * tiles_x + rect[0] + j % rect_width)
                keys[k] = keys.dtype((tile << depth_key_bits) | low)
                values[k] = i
                k += 1
        return
    a = splats[i, CONIC_A]
    b = splats[i, CONIC_B]
    c = splats[i, CONIC_C]
    conic = reach_conic(a, b, c, row_reach(splats[i, OPACITY], a, b, c, rounding))
    # The reached tiles; then, only if the projection counted more (the same test compiled into another kernel),
    # unreached ones, which the compositing finds nothing to add from.
    for unreached in range(2):
        for ty in range(rect[1], rect[3]):
            for tx in range(rect[0], rect[2]):
                if k >= end:
                    return
                if tile_reached(mean_x, mean_y, conic, tx, ty, tile_size, width, height) == (unreached == 0):
                    tile = wp.int64(first_tile + ty * tiles_x + tx)
                    keys[k] = keys.dtype((tile << depth_key_bits) | low)
                    values[k] = i
                    k += 1


@wp.func
def key_tile(key: Any, depth_bits: int):
    """The flat tile index of a sort key."""
    return int(wp.int64(key) >> wp.int64(depth_bits))


@wp.kernel
def tile_ranges(
    keys: wp.array(dtype=Any),
    inclusive_offsets: wp.array(dtype=wp.int64),
    flags: wp.array(dtype=wp.int64),
    length: int,
    ranges: wp.array2d(dtype=wp.int32),
):
    """From sorted keys, the half-open range ``[start, end)`` of every flat tile (one thread per key).

    The intersection count (the last inclusive offset) and the key's depth bits (the layout that
    :func:`emit_intersections` published in ``flags``) are read here, so the host need not know them: the first
    ``min(count, length)`` keys are used, threads from there on do nothing. Keys of a guess the host later finds
    unusable (too short a buffer, a wrong key dtype, too few sorted bits) give wrong ranges, but only for tiles of
    the grid and inside ``[0, length]``.

    Args:
        keys: sorted uint32 or int64 keys; length: how many of them were sorted (the launch size).
        ranges: ``[B * tiles_per_image, 2]`` zero-initialised; tiles without intersections stay (0, 0).
    """
    i = wp.tid()
    used = wp.min(int(inclusive_offsets[inclusive_offsets.shape[0] - 1]), length)
    if i >= used:
        return
    shift = int(flags[KEY_LAYOUT + 2])
    tile = key_tile(keys[i], shift)
    if tile < 0 or tile >= ranges.shape[0]:
        return
    if i == 0:
        ranges[tile, 0] = i
    elif key_tile(keys[i - 1], shift) != tile:
        ranges[tile, 0] = i
    if i == used - 1:
        ranges[tile, 1] = i + 1
    elif key_tile(keys[i + 1], shift) != tile:
        ranges[tile, 1] = i + 1
