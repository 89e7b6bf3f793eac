"""Tile binning of projected Gaussians: tile rectangles, sort keys and per-tile ranges.

One intersection is one (camera, Gaussian, tile) triple. Its key is ``[flat tile | depth key]``: the flat tile
index ``camera * tiles_per_image + tile`` above ``depth_bits`` bits of depth key, so one radix sort over the key's
used bits orders intersections by camera, then tile, then depth. The depth key is
``(float32 bits of depth - depth_base) >> depth_shift``: a positive float32 sorts like its bit pattern, and
subtracting the smallest visible pattern (``depth_base``) keeps only the bits the depths of one call span. The
caller picks ``depth_shift`` so that the key fits the key dtype (uint32 or int64); with ``depth_shift = s``
depths within ``2^s`` float32 units in the last place of each other tie, and ties keep the order of the
rows (the sort is stable). The value is the flat index ``camera * N + gaussian`` of the Gaussian's projected
row.
"""

from __future__ import annotations

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})

DEPTH_COLUMN = 9
"""Column of the projected row (see :mod:`codecsplat_warp.kernels.raster_project`) holding camera-space depth."""


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


@wp.func
def depth_bits(depth: Any):
    """The float32 bit pattern of a positive depth, as an int32 (positive float32 values sort like it)."""
    return wp.cast(wp.float32(depth), wp.int32)


@wp.func
def depth_key(depth: Any, depth_base: int, depth_shift: int):
    """The depth part of a sort key (see the module docstring) as an int64."""
    return wp.int64((depth_bits(depth) - depth_base) >> depth_shift)


@wp.kernel
def emit_intersections(
    splats: wp.array2d(dtype=Any),
    radii: wp.array(dtype=wp.vec2i),
    counts: wp.array(dtype=wp.int64),
    inclusive_offsets: wp.array(dtype=wp.int64),
    num_gaussians: int,
    tile_size: int,
    tiles_x: int,
    tiles_y: int,
    depth_base: int,
    depth_shift: int,
    depth_bits: int,
    keys: wp.array(dtype=Any),
    values: wp.array(dtype=wp.int32),
):
    """Write the keys and values of every intersection of one projected Gaussian (one thread per row).

    Args:
        splats: projected rows ``[B*N, 10]`` (x, y, conic..., depth in column 9).
        radii: pixel radii ``[B*N]``; zero means culled.
        counts: int64 intersections per row ``[B*N]``; ``inclusive_offsets`` their inclusive prefix sum
            (the total is below 2^31, checked by the caller).
        depth_base, depth_shift, depth_bits: the depth key (module docstring): the smallest float32 bit pattern
            of a visible depth, the bits dropped below it, and the key bits it occupies.
        keys: uint32 or int64 output, values: int32 output, each at least ``sum(counts)`` long.
    """
    i = wp.tid()
    count = counts[i]
    if count == wp.int64(0):
        return
    first_tile = (i // num_gaussians) * tiles_x * tiles_y
    rect = tile_rect(splats[i, 0], splats[i, 1], radii[i], tile_size, tiles_x, tiles_y)
    low = depth_key(splats[i, DEPTH_COLUMN], depth_base, depth_shift)
    k = int(inclusive_offsets[i] - count)
    for ty in range(rect[1], rect[3]):
        for tx in range(rect[0], rect[2]):
            tile = wp.int64(first_tile + ty * tiles_x + tx)
            keys[k] = keys.dtype((tile << wp.int64(depth_bits)) | low)
            values[k] = i
            k += 1


@wp.func
def key_tile(key: Any, depth_bits: int):
    """The flat tile index of a sort key."""
    return int(wp.int64(key) >> wp.int64(depth_bits))


@wp.kernel
def tile_ranges(keys: wp.array(dtype=Any), count: int, depth_bits: int, ranges: wp.array2d(dtype=wp.int32)):
    """From sorted keys, the half-open range ``[start, end)`` of every flat tile (one thread per intersection).

    Args:
        keys: sorted uint32 or int64 keys, first ``count`` valid; ``depth_bits``: key bits below the tile index.
        ranges: ``[B * tiles_per_image, 2]`` zero-initialised; tiles without intersections stay (0, 0).
    """
    i = wp.tid()
    tile = key_tile(keys[i], depth_bits)
    if i == 0:
        ranges[tile, 0] = i
    elif key_tile(keys[i - 1], depth_bits) != tile:
        ranges[tile, 0] = i
    if i == count - 1:
        ranges[tile, 1] = i + 1
    elif key_tile(keys[i + 1], depth_bits) != tile:
        ranges[tile, 1] = i + 1
