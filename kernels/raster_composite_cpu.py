"""Per-tile front-to-back alpha compositing laid out for the CPU, and its hand-written backward.

:mod:`.raster_composite` has the CUDA layout (one block of lanes per tile, rows staged in shared memory). Here one
thread composites a whole tile: its pixels one after another, each walking the tile's depth-sorted rows in place
(``sorted_ids`` into ``splats``), with the constants, the skipping and stopping rules and the arithmetic of
:mod:`.raster_composite`. Tiles write disjoint pixels, so the host splits the tiles into runs launched on several
threads (``first_tile`` is a run's first tile), and a pixel's result does not depend on that split.

Skip power: a row is skipped before its ``exp`` when its power at the pixel exceeds
``log(ALPHA_LEVELS * opacity) + SKIP_MARGIN`` (computed once per intersection into ``skip_powers``). There
``opacity * exp(-power) <= exp(-SKIP_MARGIN) / 255``, so alpha is below the 1/255 threshold by a margin far
larger than the rounding of ``exp``, ``log`` and the product: the same rows are composited as without the test.

The backward walks each pixel's rows back to front from the index the forward saved, as the CUDA kernel does, and
adds the gradient of every (pixel, row) pair to that row's *intersection* with the tile: row ``grads`` of the
intersection buffer ``[M, 10]``, indexed by the position at which :func:`.raster_tiles.emit_intersections` wrote the
intersection (:func:`.raster_tiles.intersection_position`). Only the tile's thread writes its intersections, pixel
after pixel in a fixed order, without atomics. :func:`sum_intersection_gradients` then adds the intersections of each
row (consecutive positions) in a fixed order. Renders and gradients are therefore bit-identical for any split of
the tiles over threads. Sums are formed in another order than the CUDA kernel's (which sums over a warp by
shuffles, then across warps by atomics), so gradients agree with it to float rounding, not bit for bit.
"""

from __future__ import annotations

from typing import Any

import warp as wp

from .raster_composite import MIN_ALPHA_FOR_DEPTH, gaussian_power
from .raster_row import (
    ALPHA_LEVELS, ALPHA_THRESHOLD, BLUE, CONIC_A, CONIC_B, CONIC_C, DEPTH, GREEN, MAX_ALPHA, MEAN_X, MEAN_Y,
    OPACITY, RED, ROW_WIDTH,
)  # fmt: skip
from .raster_tiles import intersection_position

wp.set_module_options({"enable_backward": False})

SKIP_MARGIN = 1.0 / 1024.0
"""Margin of the skip power above ``log(ALPHA_LEVELS * opacity)`` (see the module docstring): a skipped row's alpha
is at most ``exp(-1/1024) = 0.99902`` times the threshold, where float rounding moves it by about 1e-6."""


@wp.func
def skip_power(opacity: Any):
    """Power above which a row of this opacity has alpha below :data:`.raster_row.ALPHA_THRESHOLD` for certain."""
    return wp.log(type(opacity)(ALPHA_LEVELS) * opacity) + type(opacity)(SKIP_MARGIN)


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
    skip_powers: wp.array(dtype=Any),
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
        first_tile: the flat tile of thread 0.
        skip_powers: ``[M]`` output, the skip power of every sorted intersection of the tile (see the module
            docstring), which the backward reads.
    """
    tile = first_tile + wp.tid()
    corner = tile_corner(tile, tile_size, tiles_x, tiles_per_image)
    camera = corner[0]
    start = ranges[tile, 0]
    end = ranges[tile, 1]
    for t in range(start, end):
        skip_powers[t] = skip_power(splats[sorted_ids[t], OPACITY])
    zero = out_alpha.dtype(0.0)
    one = out_alpha.dtype(1.0)
    render_depth = out_depth.shape[0] > 0
    x0 = corner[1] * tile_size
    y0 = corner[2] * tile_size
    for py in range(y0, wp.min(y0 + tile_size, height)):
        cy = out_alpha.dtype(float(py)) + out_alpha.dtype(0.5)
        for px in range(x0, wp.min(x0 + tile_size, width)):
            cx = out_alpha.dtype(float(px)) + out_alpha.dtype(0.5)
            T = one
            r = zero
            g = zero
            b = zero
            depth = zero
            last = start - 1
            for t in range(start, end):
                row = sorted_ids[t]
                power = gaussian_power(splats, row, cx, cy)
                if power > skip_powers[t]:
                    continue
                alpha = wp.min(out_alpha.dtype(MAX_ALPHA), splats[row, OPACITY] * wp.exp(-power))
                if power < zero or alpha < out_alpha.dtype(ALPHA_THRESHOLD):
                    continue
                next_T = T * (one - alpha)
                if next_T <= min_transmittance:
                    break
                weight = alpha * T
                r += weight * splats[row, RED]
                g += weight * splats[row, GREEN]
                b += weight * splats[row, BLUE]
                if render_depth:
                    depth += weight * splats[row, DEPTH]
                last = t
                T = next_T
            pixel = (camera * height + py) * width + px
            if background.shape[0] > 0:
                r += T * background[camera, 0]
                g += T * background[camera, 1]
                b += T * background[camera, 2]
            out_color[pixel, 0] = r
            out_color[pixel, 1] = g
            out_color[pixel, 2] = b
            out_alpha[pixel] = one - T
            if render_depth:
                out_depth[pixel] = depth / wp.max(one - T, out_alpha.dtype(MIN_ALPHA_FOR_DEPTH))
            out_state[pixel, 0] = T
            out_state[pixel, 1] = depth
            out_last[pixel] = last


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
    radii: wp.array(dtype=wp.vec2i),
    counts: wp.array(dtype=wp.int64),
    inclusive_offsets: wp.array(dtype=wp.int64),
    state: wp.array2d(dtype=Any),
    last_index: wp.array(dtype=wp.int32),
    grad_color: wp.array2d(dtype=Any),
    grad_depth: wp.array(dtype=Any),
    grad_alpha: wp.array(dtype=Any),
    positions: wp.array(dtype=wp.int32),
    grad_intersections: wp.array2d(dtype=Any),
):
    """Add d loss / d row of every contributing (pixel, row) pair of tile ``first_tile + tid`` to the row's
    intersection with the tile, back to front (one thread per tile).

    Args:
        ranges, sorted_ids, splats, background, state, last_index, grad_*: as in
            :func:`.raster_composite.composite_kernels`' ``composite_backward``.
        skip_powers: ``[M]`` as the forward wrote them.
        radii, counts, inclusive_offsets: the binning's inputs (``[B*N]``), to find where each intersection was
            emitted.
        positions: ``[M]`` int32 scratch: the emitted position of each sorted intersection of the tile.
        grad_intersections: ``[M, 10]`` zero-initialised, by emitted position; the depth column is left alone
            when ``grad_depth`` is empty.
    """
    tile = first_tile + wp.tid()
    corner = tile_corner(tile, tile_size, tiles_x, tiles_per_image)
    camera = corner[0]
    start = ranges[tile, 0]
    end = ranges[tile, 1]
    for t in range(start, end):
        row = sorted_ids[t]
        positions[t] = intersection_position(splats, radii, counts, inclusive_offsets, row, corner[1], corner[2],
                                             tile_size, tiles_x, tiles_per_image // tiles_x)  # fmt: skip
    zero = grad_intersections.dtype(0.0)
    one = grad_intersections.dtype(1.0)
    half = grad_intersections.dtype(0.5)
    with_depth = grad_depth.shape[0] > 0
    x0 = corner[1] * tile_size
    y0 = corner[2] * tile_size
    for py in range(y0, wp.min(y0 + tile_size, height)):
        cy = grad_intersections.dtype(float(py)) + half
        for px in range(x0, wp.min(x0 + tile_size, width)):
            cx = grad_intersections.dtype(float(px)) + half
            pixel = (camera * height + py) * width + px
            last = last_index[pixel]
            T_final = state[pixel, 0]
            v_r = zero
            v_g = zero
            v_b = zero
            v_depth = zero
            v_alpha_out = zero
            background_dot = zero
            if grad_color.shape[0] > 0:
                v_r = grad_color[pixel, 0]
                v_g = grad_color[pixel, 1]
                v_b = grad_color[pixel, 2]
            if grad_alpha.shape[0] > 0:
                v_alpha_out = grad_alpha[pixel]
            if with_depth:
                # as in the CUDA kernel: E = D / max(alpha, eps), dE/dalpha = -E / max(alpha, eps) where alpha >= eps
                alpha_out = one - T_final
                denominator = wp.max(alpha_out, grad_intersections.dtype(MIN_ALPHA_FOR_DEPTH))
                v_depth = grad_depth[pixel] / denominator
                if alpha_out >= grad_intersections.dtype(MIN_ALPHA_FOR_DEPTH):
                    v_alpha_out -= grad_depth[pixel] * ((state[pixel, 1] / denominator) / denominator)
            if background.shape[0] > 0:
                background_dot = background[camera, 0] * v_r + background[camera, 1] * v_g + background[camera, 2] * v_b
            T = T_final
            acc_r = zero
            acc_g = zero
            acc_b = zero
            acc_depth = zero
            for step in range(last + 1 - start):
                t = last - step
                row = sorted_ids[t]
                power = gaussian_power(splats, row, cx, cy)
                if power > skip_powers[t]:
                    continue
                vis = wp.exp(-power)
                opacity = splats[row, OPACITY]
                alpha = wp.min(grad_intersections.dtype(MAX_ALPHA), opacity * vis)
                if power < zero or alpha < grad_intersections.dtype(ALPHA_THRESHOLD):
                    continue
                ra = one / (one - alpha)
                T = T * ra
                weight = alpha * T
                c_r = splats[row, RED]
                c_g = splats[row, GREEN]
                c_b = splats[row, BLUE]
                z = splats[row, DEPTH]
                v_alpha = (c_r * T - acc_r * ra) * v_r + (c_g * T - acc_g * ra) * v_g + (c_b * T - acc_b * ra) * v_b
                v_alpha += (z * T - acc_depth * ra) * v_depth
                v_alpha += T_final * ra * v_alpha_out - T_final * ra * background_dot
                p = positions[t]
                grad_intersections[p, RED] += weight * v_r
                grad_intersections[p, GREEN] += weight * v_g
                grad_intersections[p, BLUE] += weight * v_b
                if with_depth:
                    grad_intersections[p, DEPTH] += weight * v_depth
                if opacity * vis <= grad_intersections.dtype(MAX_ALPHA):
                    v_power = -opacity * vis * v_alpha
                    dx = splats[row, MEAN_X] - cx
                    dy = splats[row, MEAN_Y] - cy
                    grad_intersections[p, MEAN_X] += v_power * (splats[row, CONIC_A] * dx + splats[row, CONIC_B] * dy)
                    grad_intersections[p, MEAN_Y] += v_power * (splats[row, CONIC_B] * dx + splats[row, CONIC_C] * dy)
                    grad_intersections[p, CONIC_A] += half * v_power * dx * dx
                    grad_intersections[p, CONIC_B] += v_power * dx * dy
                    grad_intersections[p, CONIC_C] += half * v_power * dy * dy
                    grad_intersections[p, OPACITY] += vis * v_alpha
                acc_r += c_r * weight
                acc_g += c_g * weight
                acc_b += c_b * weight
                acc_depth += z * weight


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
