"""Tile binning of projected Gaussians: tile rectangles, 64-bit sort keys and per-tile ranges.

One intersection is one (camera, Gaussian, tile) triple. Its key is
``[camera | tile | float32 depth bits]``: the depth's 31 low bits (a positive float32 has sign bit 0, and
positive float32 values sort like their bit patterns), then the tile index in ``tile_bits`` bits, then
the camera, so one radix sort over ``DEPTH_BITS + tile_bits + camera bits`` bits orders intersections by
camera, then tile, then depth. The value is the flat index
``camera * N + gaussian`` of the Gaussian's projected row.
"""

from __future__ import annotations

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})

DEPTH_BITS = 31
"""Key bits below the tile index: a positive float32 depth without its (zero) sign bit."""

_DEPTH_SHIFT = wp.constant(wp.int64(DEPTH_BITS))

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
    tile_bits: int,
    keys: wp.array(dtype=wp.int64),
    values: wp.array(dtype=wp.int32),
):
    """Write the keys and values of every intersection of one projected Gaussian (one thread per row).

    Args:
        splats: projected rows ``[B*N, 10]`` (x, y, conic..., depth in column 9).
        radii: pixel radii ``[B*N]``; zero means culled.
        counts: int64 intersections per row ``[B*N]``; ``inclusive_offsets`` their inclusive prefix sum
            (the total is below 2^31, checked by the caller).
        keys, values: outputs, at least ``sum(counts)`` long.
    """
    i = wp.tid()
    count = counts[i]
    if count == wp.int64(0):
        return
    camera = i // num_gaussians
    rect = tile_rect(splats[i, 0], splats[i, 1], radii[i], tile_size, tiles_x, tiles_y)
    depth_bits = wp.int64(wp.cast(wp.float32(splats[i, DEPTH_COLUMN]), wp.int32))
    k = int(inclusive_offsets[i] - count)
    for ty in range(rect[1], rect[3]):
        for tx in range(rect[0], rect[2]):
            high = (wp.int64(camera) << wp.int64(tile_bits)) | wp.int64(ty * tiles_x + tx)
            keys[k] = (high << _DEPTH_SHIFT) | depth_bits
            values[k] = i
            k += 1


@wp.kernel
def tile_ranges(
    keys: wp.array(dtype=wp.int64),
    count: int,
    tile_bits: int,
    tiles_per_image: int,
    ranges: wp.array2d(dtype=wp.int32),
):
    """From sorted keys, the half-open range ``[start, end)`` of every tile (one thread per intersection).

    Args:
        keys: sorted keys, first ``count`` valid.
        ranges: ``[B * tiles_per_image, 2]`` zero-initialised; tiles without intersections stay (0, 0).
    """
    i = wp.tid()
    high = keys[i] >> _DEPTH_SHIFT
    mask = (wp.int64(1) << wp.int64(tile_bits)) - wp.int64(1)
    tile = int(high >> wp.int64(tile_bits)) * tiles_per_image + int(high & mask)
    if i == 0:
        ranges[tile, 0] = i
    elif (keys[i - 1] >> _DEPTH_SHIFT) != high:
        ranges[tile, 0] = i
    if i == count - 1:
        ranges[tile, 1] = i + 1
    elif (keys[i + 1] >> _DEPTH_SHIFT) != high:
        ranges[tile, 1] = i + 1
