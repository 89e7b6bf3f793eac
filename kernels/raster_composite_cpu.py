"""Per-tile front-to-back alpha compositing laid out for the CPU, and its hand-written backward.

:mod:`.raster_composite` has the CUDA layout (one block of lanes per tile, rows staged in shared memory). Here one
thread composites a whole tile, image row by image row (*line* by line). A first pass over the tile's depth-sorted
intersections finds, for each intersection and each line of the tile, the pixels of the line it can reach (a bit
mask, see below; ``line_masks``, kept for the backward). Then the pixels of a line walk the tile's intersections
together, :data:`LANES` pixels at a time (a *chunk*): an intersection whose mask reaches no pixel of the chunk that
is still compositing costs one load and a test, and one that does is read once for all of them. Each pixel keeps
the constants, the skipping and stopping rules and the arithmetic of :mod:`.raster_composite`. Tiles write disjoint
pixels, so the host splits the tiles into runs launched on several threads (``first_tile`` is a run's first
tile), and a pixel's result does not depend on that split.

Two tests leave out rows that cannot contribute, without changing which rows are composited (the bounds are
:mod:`.raster_reach`'s):

* Skip power: a row is skipped at a pixel before its ``exp`` when its power there exceeds its skip power ``S``
  (``skip_powers``, one per intersection), where its alpha is below the 1/255 threshold for certain.
* Line masks: the power along a line is a quadratic in the pixel's x, so the pixels where it can be at most ``S``
  form an interval, solved for in float64 (:func:`line_mask`) at the row's reach power, which covers the rounding
  of the kernel's power; a conic too ill-conditioned for that gets every pixel of the line. Lines farther from
  the row's centre than its reach allows get an empty mask without the interval (:func:`line_span`).

The backward walks each chunk's intersections back to front from the largest index its pixels' forwards saved, as
the CUDA kernel walks a pixel's rows, and adds the gradient of every (pixel, row) pair of the chunk, summed over the
chunk's pixels in order, to that row's *intersection* with the tile: row ``grads`` of the intersection buffer
``[M, 10]``, indexed by the position at which :func:`.raster_tiles.emit_intersections` wrote the intersection (the
binning sorts those positions beside the keys and gathers the row ids from them). Only the tile's thread writes its
intersections, chunk after chunk in a fixed order, without atomics. :func:`sum_intersection_gradients` then adds the
intersections of each row (consecutive positions) in a fixed order. Renders and gradients are therefore
bit-identical for any split of the tiles over threads. Sums are formed in another order than the CUDA kernel's
(which sums over a warp by shuffles, then across warps by atomics), so gradients agree with it to float rounding,
not bit for bit.
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


line_conic = wp.types.vector(length=6, dtype=wp.float64)
"""A row's line-interval constants in float64 (:func:`row_line_conic`): ``(mean_x - 0.5, mean_y, 2 a R, a c - b^2,
1 / a, b / a)`` for its conic ``(a, b, c)`` and reach power ``R``."""


@wp.func
def row_line_conic(splats: wp.array2d(dtype=Any), row: int, threshold: wp.float64):
    """The :data:`line_conic` of row ``row`` at the finite reach power ``threshold`` (where ``a > 0`` and
    ``a c - b^2 > 0``: :func:`.raster_reach.reach_power`)."""
    a = wp.float64(splats[row, CONIC_A])
    b = wp.float64(splats[row, CONIC_B])
    c = wp.float64(splats[row, CONIC_C])
    inverse_a = wp.float64(1.0) / a
    return line_conic(wp.float64(splats[row, MEAN_X]) - wp.float64(0.5), wp.float64(splats[row, MEAN_Y]),
                      wp.float64(2.0) * a * threshold, a * c - b * b, inverse_a, b * inverse_a)  # fmt: skip


@wp.func
def line_mask(conic: line_conic, py: int, x0: int, count: int):
    """Bit ``k`` set when pixel ``(x0 + k, py)`` (``k < count``) may see the row's power at or below its skip power:
    the pixels whose centre lies in the interval where the row's quadratic power along the line, ``0.5 a dx^2 +
    b dx dy + 0.5 c dy^2``, is at most its reach power, widened by :data:`LINE_SLACK` (``conic``: the row's
    :func:`row_line_conic`)."""
    dy = conic[1] - (wp.float64(py) + wp.float64(0.5))
    discriminant = conic[2] - dy * dy * conic[3]
    if discriminant < wp.float64(0.0):
        return wp.uint32(0)
    half_width = wp.sqrt(discriminant) * conic[4] + wp.float64(LINE_SLACK)
    centre = conic[0] + conic[5] * dy  # in pixel indices: centre x - 0.5
    left = wp.float64(x0)
    right = wp.float64(x0 + count - 1)
    low = wp.max(centre - half_width, left - wp.float64(1.0))
    high = wp.min(centre + half_width, right + wp.float64(1.0))
    first = wp.max(int(wp.ceil(low)), x0) - x0
    last = wp.min(int(wp.floor(high)), x0 + count - 1) - x0
    if first > last:
        return wp.uint32(0)
    return span_mask(first, last)


LANES = wp.constant(16)
"""Pixels of a line that walk a tile's intersections together (a chunk; a line of a 32-pixel tile has two)."""


@wp.func
def line_span(conic: line_conic, y0: int, lines: int):
    """``vec2i(first, last)``: the lines ``y0 + first .. y0 + last`` (of ``lines`` from ``y0``) on which
    :func:`line_mask` may find pixels, where the interval's discriminant can be non-negative (``dy^2 <= 2 a R /
    (a c - b^2)``), widened by :data:`LINE_SLACK`; ``first > last`` when none."""
    reach = wp.sqrt(conic[2] / conic[3]) + wp.float64(LINE_SLACK)
    centre = conic[1] - wp.float64(0.5) - wp.float64(y0)  # in line indices from y0
    first = wp.max(int(wp.ceil(centre - reach)), 0)
    last = wp.min(int(wp.floor(centre + reach)), lines - 1)
    return wp.vec2i(first, last)


@wp.func
def line_base(start: int, end: int, line: int, tile_size: int):
    """Where line ``line`` of a tile with the intersections ``[start, end)`` keeps its masks in ``line_masks``
    (``[M * tile_size]``), less ``start``: intersection ``t``'s mask is at ``line_base + t``."""
    return start * tile_size + line * (end - start) - start


@wp.func
def tile_line_masks(splats: wp.array2d(dtype=Any), sorted_ids: wp.array(dtype=wp.int32), start: int, end: int,
                    rounding: wp.float64, x0: int, y0: int, count: int, lines: int, tile_size: int,
                    skip_powers: wp.array(dtype=Any), line_masks: wp.array(dtype=Any)):  # fmt: skip
    """The skip power of every intersection ``[start, end)`` of a tile and its mask on each of the tile's ``lines``
    lines (``count`` pixels from ``x0``): ``line_masks[line_base(...) + t]`` (:func:`line_base`)."""
    for t in range(start, end):
        row = sorted_ids[t]
        skip = skip_power(splats[row, OPACITY])
        skip_powers[t] = skip
        threshold = reach_power(splats[row, CONIC_A], splats[row, CONIC_B], splats[row, CONIC_C], skip, rounding)
        if not wp.isfinite(threshold):  # too ill-conditioned for an interval: every pixel of every line
            for line in range(lines):
                line_masks[line_base(start, end, line, tile_size) + t] = line_masks.dtype(span_mask(0, count - 1))
            continue
        conic = row_line_conic(splats, row, threshold)
        span = line_span(conic, y0, lines)
        for line in range(lines):
            mask = wp.uint32(0)
            if line >= span[0] and line <= span[1]:
                mask = line_mask(conic, y0 + line, x0, count)
            line_masks[line_base(start, end, line, tile_size) + t] = line_masks.dtype(mask)


@wp.func
def chunk_bits(lanes: int):
    """The bits of a chunk's first ``lanes`` pixels."""
    return span_mask(0, lanes - 1)


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
    line_masks: wp.array(dtype=Any),
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
        skip_powers: ``[M]`` output, the skip power of every sorted intersection; line_masks: ``[M * tile_size]``
            output (uint16 for tiles of at most 16 pixels a side, else uint32), its mask on every line of its tile
            (:func:`tile_line_masks`); the backward reads both.
    """
    tile = first_tile + wp.tid()
    corner = tile_corner(tile, tile_size, tiles_x, tiles_per_image)
    camera = corner[0]
    start = ranges[tile, 0]
    end = ranges[tile, 1]
    x0 = corner[1] * tile_size
    y0 = corner[2] * tile_size
    count = wp.min(x0 + tile_size, width) - x0
    lines = wp.min(y0 + tile_size, height) - y0
    tile_line_masks(splats, sorted_ids, start, end, rounding, x0, y0, count, lines, tile_size, skip_powers, line_masks)
    zero = out_alpha.dtype(0.0)
    one = out_alpha.dtype(1.0)
    half = out_alpha.dtype(0.5)
    render_depth = out_depth.shape[0] > 0
    for line in range(lines):
        base = line_base(start, end, line, tile_size)
        py = y0 + line
        cy = out_alpha.dtype(float(py)) + half
        for c0 in range(0, count, LANES):
            lanes = wp.min(LANES, count - c0)
            compositing = chunk_bits(lanes)  # pixels that have not stopped
            T = wp.vector(length=LANES, dtype=out_alpha.dtype)
            red = wp.vector(length=LANES, dtype=out_alpha.dtype)
            green = wp.vector(length=LANES, dtype=out_alpha.dtype)
            blue = wp.vector(length=LANES, dtype=out_alpha.dtype)
            depth = wp.vector(length=LANES, dtype=out_alpha.dtype)
            last = wp.vector(length=LANES, dtype=wp.int32)
            for k in range(LANES):
                T[k] = one
                last[k] = start - 1
            for t in range(start, end):
                reached = (wp.uint32(line_masks[base + t]) >> wp.uint32(c0)) & compositing
                if reached == wp.uint32(0):
                    continue
                row = sorted_ids[t]
                skip = skip_powers[t]
                for k in range(LANES):
                    if (reached >> wp.uint32(k)) & wp.uint32(1) != wp.uint32(0):
                        power = gaussian_power(splats, row, out_alpha.dtype(float(x0 + c0 + k)) + half, cy)
                        if power <= skip:
                            alpha = row_alpha(splats, row, power)
                            if alpha != zero:
                                next_T = T[k] * (one - alpha)
                                if next_T <= min_transmittance:
                                    compositing = compositing & ~(wp.uint32(1) << wp.uint32(k))
                                else:
                                    composited = blend_row(splats, row, alpha * T[k],
                                                           wp.vector(red[k], green[k], blue[k], depth[k]), render_depth)
                                    red[k] = composited[0]
                                    green[k] = composited[1]
                                    blue[k] = composited[2]
                                    depth[k] = composited[3]
                                    last[k] = t
                                    T[k] = next_T
                if compositing == wp.uint32(0):
                    break
            for k in range(LANES):
                if k < lanes:
                    write_pixel(out_color, out_depth, out_alpha, out_state, out_last, background,
                                (camera * height + py) * width + x0 + c0 + k, camera,
                                wp.vector(red[k], green[k], blue[k], depth[k]), T[k], last[k])  # fmt: skip


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
    line_masks: wp.array(dtype=Any),
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
        skip_powers, line_masks: as the forward wrote them.
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
    for line in range(wp.min(y0 + tile_size, height) - y0):
        base = line_base(start, end, line, tile_size)
        py = y0 + line
        cy = grad_intersections.dtype(float(py)) + half
        for c0 in range(0, count, LANES):
            lanes = wp.min(LANES, count - c0)
            # each pixel's walk: T in front of the rows walked, what they composite, the upstream gradients
            T = wp.vector(length=LANES, dtype=grad_intersections.dtype)
            behind = wp.matrix(shape=(LANES, 4), dtype=grad_intersections.dtype)
            upstream = wp.matrix(shape=(LANES, 5), dtype=grad_intersections.dtype)
            last = wp.vector(length=LANES, dtype=wp.int32)
            chunk_last = start - 1
            for k in range(LANES):
                last[k] = start - 1
                if k < lanes:
                    pixel = (camera * height + py) * width + x0 + c0 + k
                    last[k] = last_index[pixel]
                    chunk_last = wp.max(chunk_last, last[k])
                    pixel_T, pixel_upstream_grads = pixel_upstream(state, grad_color, grad_depth, grad_alpha,
                                                                   background, pixel, camera)
                    T[k] = pixel_T
                    upstream[k] = pixel_upstream_grads
            for step in range(chunk_last + 1 - start):
                t = chunk_last - step
                reached = (wp.uint32(line_masks[base + t]) >> wp.uint32(c0)) & chunk_bits(lanes)
                if reached == wp.uint32(0):
                    continue
                row = sorted_ids[t]
                skip = skip_powers[t]
                total = wp.vector(zero, zero, zero, zero, zero, zero, zero, zero, zero, zero)
                contributes = False
                for k in range(LANES):
                    if (reached >> wp.uint32(k)) & wp.uint32(1) != wp.uint32(0) and t <= last[k]:
                        cx = grad_intersections.dtype(float(x0 + c0 + k)) + half
                        power = gaussian_power(splats, row, cx, cy)
                        if power <= skip:
                            vis = wp.exp(-power)
                            alpha = wp.min(grad_intersections.dtype(MAX_ALPHA), splats[row, OPACITY] * vis)
                            if power >= zero and alpha >= grad_intersections.dtype(ALPHA_THRESHOLD):
                                g, front, composited = row_gradient(splats, row, cx, cy, vis, alpha, T[k], behind[k],
                                                                    upstream[k])  # fmt: skip
                                T[k] = front
                                behind[k] = composited
                                total = total + g
                                contributes = True
                if contributes:
                    p = positions[t]
                    for k in range(ROW_WIDTH):  # a constant range: unrolled
                        if k < columns:
                            grad_intersections[p, k] += total[k]


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
