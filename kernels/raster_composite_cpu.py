"""Per-tile front-to-back alpha compositing laid out for the CPU, and its hand-written backward.

:mod:`.raster_composite` has the CUDA layout (one block of lanes per tile, rows staged in shared memory). Here one
thread composites a whole tile, image row by image row (*line* by line): a pass over the tile's depth-sorted rows
finds, for each row, the pixels of the line it can reach (a bit mask, see below) and lists the rows that reach any;
then each pixel of the line walks that list in place (``sorted_ids`` into ``splats``), with the constants, the
skipping and stopping rules and the arithmetic of :mod:`.raster_composite`. Tiles write disjoint pixels, so the host
splits the tiles into runs launched on several threads (``first_tile`` is a run's first tile), and a pixel's result
does not depend on that split.

Two tests leave out rows that cannot contribute, without changing which rows are composited (the bounds are
:mod:`.raster_reach`'s):

* Skip power: a row is skipped at a pixel before its ``exp`` when its power there exceeds its skip power ``S``
  (``skip_powers``, one per intersection), where its alpha is below the 1/255 threshold for certain.
* Line masks: the power along a line is a quadratic in the pixel's x, so the pixels where it can be at most ``S``
  form an interval, solved for in float64 (:func:`line_mask`) at the row's reach power (``line_powers``), which
  covers the rounding of the kernel's power; a conic too ill-conditioned for that gets every pixel of the line.

The backward walks each pixel's rows back to front from the index the forward saved, as the CUDA kernel does, and
adds the gradient of every (pixel, row) pair to that row's *intersection* with the tile: row ``grads`` of the
intersection buffer ``[M, 10]``, indexed by the position at which :func:`.raster_tiles.emit_intersections` wrote the
intersection (the binning sorts those positions beside the keys and gathers the row ids from them). Only the tile's
thread writes its intersections, pixel after pixel in a fixed order, without atomics.
:func:`sum_intersection_gradients` then adds the intersections of each row (consecutive positions) in a fixed order.
Renders and gradients are therefore bit-identical for any split of the tiles over threads. Sums are formed in
another order than the CUDA kernel's (which sums over a warp by shuffles, then across warps by atomics), so
gradients agree with it to float rounding, not bit for bit.
"""

from __future__ import annotations

from typing import Any

import warp as wp

from .raster_composite import blend_row, gaussian_power, pixel_upstream, row_alpha, row_gradient, write_pixel
from .raster_reach import reach_power, skip_power
from .raster_row import (
    ALPHA_THRESHOLD, CONIC_A, CONIC_B, CONIC_C, DEPTH, MAX_ALPHA, MEAN_X, MEAN_Y, OPACITY, ROW_WIDTH,
)  # fmt: skip

wp.set_module_options({"enable_backward": False})

LINE_SLACK = 1.0e-3
"""Pixels by which a line interval is widened on each side against the float64 rounding of its ends."""


@wp.func
def span_mask(first: int, last: int):
    """Bits ``first..last`` (0 <= first <= last < 32) set."""
    return wp.uint32((wp.uint64(1) << wp.uint64(last + 1)) - (wp.uint64(1) << wp.uint64(first)))


@wp.func
def line_mask(splats: wp.array2d(dtype=Any), row: int, threshold: wp.float64, py: int, x0: int, count: int):
    """Bit ``k`` set when pixel ``(x0 + k, py)`` (``k < count``) may see the row's power at or below its skip power:
    the pixels whose centre lies in the interval where the row's quadratic power along the line is at most
    ``threshold`` (the row's :func:`.raster_reach.reach_power`), widened by :data:`LINE_SLACK`; every pixel when
    ``threshold`` is inf."""
    if not wp.isfinite(threshold):
        return span_mask(0, count - 1)
    a = wp.float64(splats[row, CONIC_A])
    b = wp.float64(splats[row, CONIC_B])
    c = wp.float64(splats[row, CONIC_C])
    dy = wp.float64(splats[row, MEAN_Y]) - (wp.float64(py) + wp.float64(0.5))
    discriminant = wp.float64(2.0) * a * threshold - dy * dy * (a * c - b * b)
    if discriminant < wp.float64(0.0):
        return wp.uint32(0)
    half_width = wp.sqrt(discriminant) / a + wp.float64(LINE_SLACK)
    centre = wp.float64(splats[row, MEAN_X]) + b * dy / a - wp.float64(0.5)  # in pixel indices: centre x - 0.5
    left = wp.float64(x0)
    right = wp.float64(x0 + count - 1)
    low = wp.max(centre - half_width, left - wp.float64(1.0))
    high = wp.min(centre + half_width, right + wp.float64(1.0))
    first = wp.max(int(wp.ceil(low)), x0) - x0
    last = wp.min(int(wp.floor(high)), x0 + count - 1) - x0
    if first > last:
        return wp.uint32(0)
    return span_mask(first, last)


@wp.func
def list_line_rows(splats: wp.array2d(dtype=Any), sorted_ids: wp.array(dtype=wp.int32),
                   line_powers: wp.array(dtype=wp.float64), start: int, end: int, py: int, x0: int, count: int,
                   line_rows: wp.array(dtype=wp.int32), line_masks: wp.array(dtype=wp.uint32)):  # fmt: skip
    """List the sorted intersections ``[start, end)`` that may reach a pixel of line ``py`` (``count`` pixels from
    ``x0``) in ``line_rows[start:]``, in order, with their line masks in ``line_masks``; returns the list's end."""
    listed = start
    for t in range(start, end):
        mask = line_mask(splats, sorted_ids[t], line_powers[t], py, x0, count)
        if mask != wp.uint32(0):
            line_rows[listed] = t
            line_masks[listed] = mask
            listed += 1
    return listed


@wp.func
def tile_corner(tile: int, tile_size: int, tiles_x: int, tiles_per_image: int):
    """``vec3i(camera, tx, ty)``: the camera of flat tile ``tile`` and the tile's column and row in its image."""
    camera = tile // tiles_per_image
    in_image = tile - camera * tiles_per_image
    ty = in_image // tiles_x
    return wp.vec3i(camera, in_image - ty * tiles_x, ty)


@wp.kernel(enable_backward=False, module="unique")
def composite_forward_tiles(
    ranges: wp.array2d(dtype=wp.int32),
    sorted_ids: wp.array(dtype=wp.int32),
    splats: wp.array2d(dtype=Any),
    background: wp.array2d(dtype=Any),
    width: int,
    height: int,
    tile_size: int,
    tiles_x: int,
    tiles_per_image: int,
    first_tile: int,
    min_transmittance: Any,
    rounding: wp.float64,
    skip_powers: wp.array(dtype=Any),
    line_powers: wp.array(dtype=wp.float64),
    line_rows: wp.array(dtype=wp.int32),
    line_masks: wp.array(dtype=wp.uint32),
    out_color: wp.array2d(dtype=Any),
    out_depth: wp.array(dtype=Any),
    out_alpha: wp.array(dtype=Any),
    out_state: wp.array2d(dtype=Any),
    out_last: wp.array(dtype=wp.int32),
):
    """Composite every pixel of tile ``first_tile + tid`` front to back (one thread per tile).

    Args:
        ranges, sorted_ids, splats, background, min_transmittance, out_*: as in
            :func:`.raster_composite.composite_kernels`' ``composite_forward``.
        first_tile: the flat tile of thread 0; rounding: :data:`.raster_reach.POWER_ROUNDING` of the dtype.
        skip_powers, line_powers: ``[M]`` outputs, the skip power and the line-interval threshold of every sorted
            intersection of the tile (see the module docstring), which the backward reads.
        line_rows, line_masks: ``[M]`` scratch (int32, uint32), the list of :func:`list_line_rows`.
    """
    tile = first_tile + wp.tid()
    corner = tile_corner(tile, tile_size, tiles_x, tiles_per_image)
    camera = corner[0]
    start = ranges[tile, 0]
    end = ranges[tile, 1]
    for t in range(start, end):
        row = sorted_ids[t]
        skip_powers[t] = skip_power(splats[row, OPACITY])
        line_powers[t] = reach_power(splats[row, CONIC_A], splats[row, CONIC_B], splats[row, CONIC_C], skip_powers[t],
                                     rounding)
    zero = out_alpha.dtype(0.0)
    one = out_alpha.dtype(1.0)
    render_depth = out_depth.shape[0] > 0
    x0 = corner[1] * tile_size
    y0 = corner[2] * tile_size
    count = wp.min(x0 + tile_size, width) - x0
    for py in range(y0, wp.min(y0 + tile_size, height)):
        listed = list_line_rows(splats, sorted_ids, line_powers, start, end, py, x0, count, line_rows, line_masks)
        cy = out_alpha.dtype(float(py)) + out_alpha.dtype(0.5)
        for px in range(x0, x0 + count):
            cx = out_alpha.dtype(float(px)) + out_alpha.dtype(0.5)
            bit = wp.uint32(1) << wp.uint32(px - x0)
            T = one
            composited = wp.vector(zero, zero, zero, zero)
            last = start - 1
            for j in range(start, listed):
                if (line_masks[j] & bit) == wp.uint32(0):
                    continue
                t = line_rows[j]
                row = sorted_ids[t]
                power = gaussian_power(splats, row, cx, cy)
                if power > skip_powers[t]:
                    continue
                alpha = row_alpha(splats, row, power)
                if alpha == zero:
                    continue
                next_T = T * (one - alpha)
                if next_T <= min_transmittance:
                    break
                composited = blend_row(splats, row, alpha * T, composited, render_depth)
                last = t
                T = next_T
            write_pixel(out_color, out_depth, out_alpha, out_state, out_last, background,
                        (camera * height + py) * width + px, camera, composited, T, last)  # fmt: skip


@wp.kernel(enable_backward=False, module="unique")
def composite_backward_tiles(
    ranges: wp.array2d(dtype=wp.int32),
    sorted_ids: wp.array(dtype=wp.int32),
    splats: wp.array2d(dtype=Any),
    background: wp.array2d(dtype=Any),
    width: int,
    height: int,
    tile_size: int,
    tiles_x: int,
    tiles_per_image: int,
    first_tile: int,
    skip_powers: wp.array(dtype=Any),
    line_powers: wp.array(dtype=wp.float64),
    line_rows: wp.array(dtype=wp.int32),
    line_masks: wp.array(dtype=wp.uint32),
    positions: wp.array(dtype=wp.int32),
    state: wp.array2d(dtype=Any),
    last_index: wp.array(dtype=wp.int32),
    grad_color: wp.array2d(dtype=Any),
    grad_depth: wp.array(dtype=Any),
    grad_alpha: wp.array(dtype=Any),
    grad_intersections: wp.array2d(dtype=Any),
):
    """Add d loss / d row of every contributing (pixel, row) pair of tile ``first_tile + tid`` to the row's
    intersection with the tile, back to front (one thread per tile).

    Args:
        ranges, sorted_ids, splats, background, state, last_index, grad_*: as in
            :func:`.raster_composite.composite_kernels`' ``composite_backward``.
        skip_powers, line_powers: ``[M]`` as the forward wrote them; line_rows, line_masks: ``[M]`` scratch.
        positions: ``[M]`` int32, the position at which the binning emitted each sorted intersection.
        grad_intersections: ``[M, 10]`` zero-initialised, by emitted position; the depth column is left alone
            when ``grad_depth`` is empty.
    """
    tile = first_tile + wp.tid()
    corner = tile_corner(tile, tile_size, tiles_x, tiles_per_image)
    camera = corner[0]
    start = ranges[tile, 0]
    end = ranges[tile, 1]
    zero = grad_intersections.dtype(0.0)
    half = grad_intersections.dtype(0.5)
    columns = wp.where(grad_depth.shape[0] > 0, ROW_WIDTH, DEPTH)  # no depth gradient: the last column stays 0
    x0 = corner[1] * tile_size
    y0 = corner[2] * tile_size
    count = wp.min(x0 + tile_size, width) - x0
    for py in range(y0, wp.min(y0 + tile_size, height)):
        listed = list_line_rows(splats, sorted_ids, line_powers, start, end, py, x0, count, line_rows, line_masks)
        cy = grad_intersections.dtype(float(py)) + half
        for px in range(x0, x0 + count):
            cx = grad_intersections.dtype(float(px)) + half
            bit = wp.uint32(1) << wp.uint32(px - x0)
            pixel = (camera * height + py) * width + px
            last = last_index[pixel]
            T_final, upstream = pixel_upstream(state, grad_color, grad_depth, grad_alpha, background, pixel, camera)
            T = T_final
            behind = wp.vector(zero, zero, zero, zero)
            for step in range(listed - start):
                j = listed - 1 - step
                t = line_rows[j]
                if t > last or (line_masks[j] & bit) == wp.uint32(0):
                    continue
                row = sorted_ids[t]
                power = gaussian_power(splats, row, cx, cy)
                if power > skip_powers[t]:
                    continue
                vis = wp.exp(-power)
                alpha = wp.min(grad_intersections.dtype(MAX_ALPHA), splats[row, OPACITY] * vis)
                if power < zero or alpha < grad_intersections.dtype(ALPHA_THRESHOLD):
                    continue
                g, T, behind = row_gradient(splats, row, cx, cy, vis, alpha, T, behind, upstream, T_final)
                p = positions[t]
                for k in range(ROW_WIDTH):  # a constant range: unrolled
                    if k < columns:
                        grad_intersections[p, k] += g[k]


@wp.kernel(enable_backward=False, module="unique")
def sum_intersection_gradients(
    counts: wp.array(dtype=wp.int64),
    inclusive_offsets: wp.array(dtype=wp.int64),
    grad_intersections: wp.array2d(dtype=Any),
    first_row: int,
    grad_rows: wp.array2d(dtype=Any),
):
    """The gradient of projected row ``first_row + tid``: the sum of its intersections' gradients, in the order
    they were emitted (one thread per row; rows without intersections get zero).

    Args:
        counts, inclusive_offsets: ``[B*N]`` int64 intersections per row and their inclusive prefix sum.
        grad_intersections: ``[M, 10]`` by emitted position (see :func:`composite_backward_tiles`).
        grad_rows: ``[B*N, 10]`` output.
    """
    i = first_row + wp.tid()
    end = int(inclusive_offsets[i])
    zero = grad_rows.dtype(0.0)
    total = wp.vector(zero, zero, zero, zero, zero, zero, zero, zero, zero, zero)
    for p in range(end - int(counts[i]), end):
        for k in range(ROW_WIDTH):
            total[k] = total[k] + grad_intersections[p, k]
    for k in range(ROW_WIDTH):
        grad_rows[i, k] = total[k]
