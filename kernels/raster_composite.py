"""Per-tile front-to-back alpha compositing of projected Gaussians and its hand-written backward.

Both kernels are launched with :func:`warp.launch_tiled`. Each thread owns at most one pixel; a tile of
``tile_size^2`` pixels is covered by ``blocks_per_tile = ceil(tile_size^2 / block_dim)`` blocks (on CUDA
``block_dim = min(tile_size^2, 256)``, so one block per tile up to 16x16 tiles; on the CPU blocks have one
lane and a tile has ``tile_size^2`` of them). Lanes of a tile's last block beyond its pixels own none. Every
block stages ``batch`` projected rows of its tile's depth-sorted list in shared memory (``tile_load`` of the
ids, then ``tile_load_indexed`` of the rows) and each thread walks the staged rows for its pixel. ``batch``
is a compile-time constant of :func:`composite_kernels` (``block_dim`` on CUDA, small on the CPU where every
one-pixel block stages its own copy). In the backward the lanes of a CUDA warp walk the rows in step. A row
that more than :data:`DIRECT_ATOMIC_LANES` lanes of the warp reach has its gradient summed over the warp
(:func:`~codecsplat_warp.kernels.lanes.warp_sum_row_add`, a ``wp.func_native`` snippet: a reduce-scatter of the ten
columns over the lanes, after which ten lanes add a column's total each, at once) instead of up to 320 atomics. A
row that fewer lanes reach (the common case for the model's pixel-sized Gaussians) gets their atomics directly.

Constants are gsplat's: ``alpha = min(0.999, opacity * exp(-power))``; rows with ``power < 0`` or
``alpha < 1/255`` (:data:`.raster_row.ALPHA_THRESHOLD`) are skipped; a pixel stops (exclusively) at the first row whose
``T * (1 - alpha) <= min_transmittance`` (a kernel argument; gsplat's constant is 1e-4). The forward
saves the final transmittance ``T``, the accumulated depth and the sorted index of the last contributing
row; the backward walks that pixel's rows back to front from that index, rebuilding ``T`` by division
from the final ``T`` (Warp's automatic adjoint cannot differentiate this early-exit loop). The saved index
*is* the stopping point, so the backward needs no threshold. Rebuilding ``T`` by division is accurate while
the final ``T`` stays far from underflow, which a threshold such as 1e-4 guarantees (a threshold of 0 does
not: behind a nearly opaque stack a float32 ``T`` underflows after about a dozen layers).

Expected depth is normalised in the kernels, ``sum w z / max(alpha, MIN_ALPHA_FOR_DEPTH)`` (gsplat's
RGB+ED), with its gradient. An absent output is a zero-length array: no background (``[0, 3]``), no depth
(``[0]``), no gradient for an output (``[0]`` or ``[0, 3]``). Row layout: see :mod:`.raster_row`.
"""

from __future__ import annotations

import functools
from typing import Any

import warp as wp

from .lanes import warp_count, warp_max, warp_sum_row_add
from .raster_row import (
    ALPHA_THRESHOLD, BLUE, CONIC_A, CONIC_B, CONIC_C, DEPTH, GREEN, MAX_ALPHA, MEAN_X, MEAN_Y, OPACITY, RED,
    ROW_WIDTH,
)  # fmt: skip

wp.set_module_options({"enable_backward": False})

OUTSIDE_ROW = wp.constant(1 << 30)
"""Pixel row given to lanes that own no pixel (larger than any image height)."""
MIN_ALPHA_FOR_DEPTH = 1.0e-10
"""Expected depth is ``sum w z / max(alpha, MIN_ALPHA_FOR_DEPTH)`` (gsplat's RGB+ED normalisation)."""


MAX_LANES = 256
"""Most CUDA threads a compositing block has: a 16x16 tile is one block; larger tiles take several (a 32x32 block of
1,024 threads would ask for more registers than a multiprocessor has)."""

@wp.func
def tile_pixel(block: int, lane: int, blocks_per_tile: int, tile_size: int, tiles_x: int, tiles_per_image: int):
    """``vec4i(tile, camera, px, py)`` of the pixel owned by this thread; a lane past the tile's last pixel gets
    ``py = OUTSIDE_ROW``, below every image, so it owns no pixel."""
    tile = block // blocks_per_tile
    local = (block - tile * blocks_per_tile) * wp.block_dim() + lane
    camera = tile // tiles_per_image
    if local >= tile_size * tile_size:
        return wp.vec4i(tile, camera, 0, OUTSIDE_ROW)
    in_image = tile - camera * tiles_per_image
    ty = in_image // tiles_x
    tx = in_image - ty * tiles_x
    return wp.vec4i(tile, camera, tx * tile_size + local % tile_size, ty * tile_size + local // tile_size)


@wp.func
def gaussian_power(rows: Any, t: int, px: Any, py: Any):
    """``0.5 (a dx^2 + c dy^2) + b dx dy`` of staged row ``t`` at pixel centre (px, py)."""
    dx = rows[t, MEAN_X] - px
    dy = rows[t, MEAN_Y] - py
    return type(px)(0.5) * (rows[t, CONIC_A] * dx * dx + rows[t, CONIC_C] * dy * dy) + rows[t, CONIC_B] * dx * dy


@wp.func
def row_alpha(rows: Any, t: int, power: Any):
    """Alpha of row ``t`` of ``rows`` at a pixel where its power is ``power``: ``min(MAX_ALPHA, opacity exp(-power))``,
    or 0 where the row is skipped (``power < 0``, or alpha below ALPHA_THRESHOLD: a composited alpha is never 0)."""
    alpha = wp.min(type(power)(MAX_ALPHA), rows[t, OPACITY] * wp.exp(-power))
    if power < type(power)(0.0) or alpha < type(power)(ALPHA_THRESHOLD):
        return type(power)(0.0)
    return alpha


@wp.func
def blend_row(rows: Any, t: int, weight: Any, composited: Any, render_depth: bool):
    """``composited`` (``vector(r, g, b, sum w z)``) with row ``t`` of ``rows`` added at ``weight`` (its depth only
    with ``render_depth``)."""
    depth = composited[3]
    if render_depth:
        depth += weight * rows[t, DEPTH]
    return wp.vector(composited[0] + weight * rows[t, RED], composited[1] + weight * rows[t, GREEN],
                     composited[2] + weight * rows[t, BLUE], depth)  # fmt: skip


@wp.func
def write_pixel(out_color: wp.array2d(dtype=Any), out_depth: wp.array(dtype=Any), out_alpha: wp.array(dtype=Any),
                out_state: wp.array2d(dtype=Any), out_last: wp.array(dtype=wp.int32), background: wp.array2d(dtype=Any),
                pixel: int, camera: int, composited: Any, T: Any, last: int):  # fmt: skip
    """Write a composited pixel (arrays as in the forward kernels): colour over the camera's background, alpha
    ``1 - T``, the normalised expected depth, the state the backward reads and the last contributing row."""
    one = type(T)(1.0)
    r = composited[0]
    g = composited[1]
    b = composited[2]
    if background.shape[0] > 0:
        r += T * background[camera, 0]
        g += T * background[camera, 1]
        b += T * background[camera, 2]
    out_color[pixel, 0] = r
    out_color[pixel, 1] = g
    out_color[pixel, 2] = b
    out_alpha[pixel] = one - T
    if out_depth.shape[0] > 0:
        out_depth[pixel] = composited[3] / wp.max(one - T, type(T)(MIN_ALPHA_FOR_DEPTH))
    out_state[pixel, 0] = T
    out_state[pixel, 1] = composited[3]
    out_last[pixel] = last


@wp.func
def pixel_upstream(state: wp.array2d(dtype=Any), grad_color: wp.array2d(dtype=Any), grad_depth: wp.array(dtype=Any),
                   grad_alpha: wp.array(dtype=Any), background: wp.array2d(dtype=Any), pixel: int, camera: int):  # fmt: skip
    """The gradients that reach flat pixel ``pixel`` (of camera ``camera``) for the backward walk over its rows:
    ``(T_final, vector(d/dr, d/dg, d/db, d/d(sum w z), T_final (d/dalpha - background . d/drgb)))``, zero for an
    absent output gradient (arrays as in the backward kernels). The last entry is what the final transmittance
    passes to every row in front of it (times the row's ``1 / (1 - alpha)``): one number, so that the walk keeps
    fewer registers."""
    zero = state.dtype(0.0)
    one = state.dtype(1.0)
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
    if grad_depth.shape[0] > 0:
        # expected depth E = D / max(alpha, eps): dE/dD = 1 / max(alpha, eps); dE/dalpha = -E / max(alpha, eps)
        # where alpha >= eps (torch's clamp_min gradient), else 0
        alpha_out = one - T_final
        denominator = wp.max(alpha_out, state.dtype(MIN_ALPHA_FOR_DEPTH))
        v_depth = grad_depth[pixel] / denominator
        if alpha_out >= state.dtype(MIN_ALPHA_FOR_DEPTH):
            v_alpha_out -= grad_depth[pixel] * ((state[pixel, 1] / denominator) / denominator)
    if background.shape[0] > 0:
        background_dot = background[camera, 0] * v_r + background[camera, 1] * v_g + background[camera, 2] * v_b
    return T_final, wp.vector(v_r, v_g, v_b, v_depth, T_final * (v_alpha_out - background_dot))


@wp.func
def row_gradient(rows: Any, t: int, cx: Any, cy: Any, vis: Any, alpha: Any, T: Any, behind: Any, upstream: Any):
    """The gradient of row ``t`` of ``rows`` at pixel centre (cx, cy), one step of the back-to-front walk: the row
    has ``vis = exp(-power)`` and ``alpha`` there, ``T`` is the transmittance behind it and ``behind`` the
    ``vector(r, g, b, depth)`` composited behind it (from the pixel's last row on), ``upstream`` as
    :func:`pixel_upstream` gives it. Returns ``(gradient of the row's 10 columns, T in front of the row,
    behind with the row added)``; the geometry and opacity entries are 0 where alpha is clamped at MAX_ALPHA."""
    zero = type(T)(0.0)
    one = type(T)(1.0)
    ra = one / (one - alpha)
    T = T * ra
    weight = alpha * T
    c_r = rows[t, RED]
    c_g = rows[t, GREEN]
    c_b = rows[t, BLUE]
    z = rows[t, DEPTH]
    v_alpha = ((c_r * T - behind[0] * ra) * upstream[0] + (c_g * T - behind[1] * ra) * upstream[1]
               + (c_b * T - behind[2] * ra) * upstream[2])  # fmt: skip
    v_alpha += (z * T - behind[3] * ra) * upstream[3]
    v_alpha += ra * upstream[4]
    g = wp.vector(zero, zero, zero, zero, zero, zero, zero, zero, zero, zero)
    g[RED] = weight * upstream[0]
    g[GREEN] = weight * upstream[1]
    g[BLUE] = weight * upstream[2]
    g[DEPTH] = weight * upstream[3]
    opacity = rows[t, OPACITY]
    if opacity * vis <= type(T)(MAX_ALPHA):
        v_power = -opacity * vis * v_alpha
        dx = rows[t, MEAN_X] - cx
        dy = rows[t, MEAN_Y] - cy
        g[MEAN_X] = v_power * (rows[t, CONIC_A] * dx + rows[t, CONIC_B] * dy)
        g[MEAN_Y] = v_power * (rows[t, CONIC_B] * dx + rows[t, CONIC_C] * dy)
        g[CONIC_A] = type(T)(0.5) * v_power * dx * dx
        g[CONIC_B] = v_power * dx * dy
        g[CONIC_C] = type(T)(0.5) * v_power * dy * dy
        g[OPACITY] = vis * v_alpha
    return g, T, behind + wp.vector(c_r * weight, c_g * weight, c_b * weight, z * weight)


DIRECT_ATOMIC_LANES = 4
"""In the compositing backward, a row that this many lanes of a warp or fewer reach gets their atomic adds
directly; more lanes sum over the warp first and add one atomic per column (:func:`.lanes.warp_sum_row_add`)."""

FORWARD_BLOCKS_PER_SM = 4
BACKWARD_BLOCKS_PER_SM = 4
"""CUDA blocks of 256 lanes that each compositing kernel is compiled to keep resident per multiprocessor
(``__launch_bounds__``), which caps the compiler at 65,536 / (256 x 4) = 64 registers per thread. Measured on an
H200 at the DL3DV workload (float32, fast math): forward 373 us at 4 blocks, 382 at 5, 384 at 6, 416 at 3 and
451 unbounded (113 registers, two blocks); backward 913 us at 4, 997 at 5, 1,125 at 3 and 1,664 unbounded."""


def _cuda_options(blocks_per_sm: int) -> dict:
    """Kernel options of a compositing kernel: launch bounds, CUDA fast math (``exp`` and division; gsplat builds
    with ``--use_fast_math`` too; no effect on float64 or on the CPU), no grid-stride loop (one block per tile)."""
    return {"launch_bounds": (MAX_LANES, blocks_per_sm), "module_options": {"fast_math": True}, "grid_stride": False}


@functools.cache
def composite_kernels(batch: int):
    """The ``(composite_forward, composite_backward)`` kernels staging ``batch`` rows per step."""
    BATCH = batch

    @wp.kernel(enable_backward=False, module="unique", **_cuda_options(FORWARD_BLOCKS_PER_SM))
    def composite_forward(
        ranges: wp.array2d(dtype=wp.int32),
        sorted_ids: wp.array(dtype=wp.int32),
        splats: wp.array2d(dtype=Any),
        background: wp.array2d(dtype=Any),
        width: int,
        height: int,
        tile_size: int,
        tiles_x: int,
        tiles_per_image: int,
        blocks_per_tile: int,
        min_transmittance: Any,
        out_color: wp.array2d(dtype=Any),
        out_depth: wp.array(dtype=Any),
        out_alpha: wp.array(dtype=Any),
        out_state: wp.array2d(dtype=Any),
        out_last: wp.array(dtype=wp.int32),
    ):
        """Composite every pixel front to back.

        Args:
            ranges: ``[B * tiles_per_image, 2]`` half-open ranges into ``sorted_ids``.
            sorted_ids: ``[M]`` flat row indices sorted by (camera, tile, depth).
            splats: projected rows ``[B*N, 10]``; background: ``[B, 3]``, or ``[0, 3]`` for black.
            min_transmittance: a pixel stops before the first row that takes ``T`` to this or below, in [0, 1).
            out_color: ``[B*H*W, 3]`` colour incl. background; out_depth: ``[B*H*W]`` expected depth, or ``[0]``
                to skip depth; out_alpha: ``1 - T``; out_state: ``[B*H*W, 2]`` final ``T`` and accumulated depth
                ``sum w z``; out_last: sorted index of the last contributing row (``range start - 1`` when none).
        """
        block, lane = wp.tid()
        where = tile_pixel(block, lane, blocks_per_tile, tile_size, tiles_x, tiles_per_image)
        tile = where[0]
        px = where[2]
        py = where[3]
        inside = px < width and py < height
        start = ranges[tile, 0]
        end = ranges[tile, 1]
        zero = out_alpha.dtype(0.0)
        one = out_alpha.dtype(1.0)
        cx = out_alpha.dtype(float(px)) + out_alpha.dtype(0.5)
        cy = out_alpha.dtype(float(py)) + out_alpha.dtype(0.5)
        render_depth = out_depth.shape[0] > 0
        T = one
        composited = wp.vector(zero, zero, zero, zero)
        last = start - 1
        done = not inside
        for batch_start in range(start, end, BATCH):
            ids = wp.tile_load(sorted_ids, shape=BATCH, offset=batch_start, storage="shared")
            rows = wp.tile_load_indexed(splats, indices=ids, shape=(BATCH, ROW_WIDTH), offset=(0, 0), axis=0,
                                        storage="shared")
            count = wp.min(BATCH, end - batch_start)
            if not done:
                for t in range(count):
                    alpha = row_alpha(rows, t, gaussian_power(rows, t, cx, cy))
                    if alpha == zero:
                        continue
                    next_T = T * (one - alpha)
                    if next_T <= min_transmittance:
                        done = True
                        break
                    composited = blend_row(rows, t, alpha * T, composited, render_depth)
                    last = batch_start + t
                    T = next_T
            finished = wp.tile_sum(wp.tile(wp.where(done, 1, 0)))
            if finished[0] == wp.block_dim():
                break
        if inside:
            camera = where[1]
            pixel = (camera * height + py) * width + px
            write_pixel(out_color, out_depth, out_alpha, out_state, out_last, background, pixel, camera, composited, T,
                        last)  # fmt: skip

    @wp.kernel(enable_backward=False, module="unique", **_cuda_options(BACKWARD_BLOCKS_PER_SM))
    def composite_backward(
        ranges: wp.array2d(dtype=wp.int32),
        sorted_ids: wp.array(dtype=wp.int32),
        splats: wp.array2d(dtype=Any),
        background: wp.array2d(dtype=Any),
        width: int,
        height: int,
        tile_size: int,
        tiles_x: int,
        tiles_per_image: int,
        blocks_per_tile: int,
        state: wp.array2d(dtype=Any),
        last_index: wp.array(dtype=wp.int32),
        grad_color: wp.array2d(dtype=Any),
        grad_depth: wp.array(dtype=Any),
        grad_alpha: wp.array(dtype=Any),
        grad_splats: wp.array2d(dtype=Any),
    ):
        """Accumulate d loss / d row for every contributing (pixel, row) pair, back to front.

        Args:
            ranges, sorted_ids, splats, background, ...: as in :func:`composite_forward`.
            state, last_index: saved by the forward, ``[B*H*W, 2]`` and ``[B*H*W]``.
            grad_color: ``[B*H*W, 3]``; grad_depth: ``[B*H*W]`` (of the expected depth); grad_alpha: ``[B*H*W]``;
                each ``[0]`` (``[0, 3]``) when that output has no gradient.
            grad_splats: ``[B*N, 10]`` zero-initialised, accumulated with atomics.
        """
        block, lane = wp.tid()
        where = tile_pixel(block, lane, blocks_per_tile, tile_size, tiles_x, tiles_per_image)
        tile = where[0]
        px = where[2]
        py = where[3]
        inside = px < width and py < height
        start = ranges[tile, 0]
        end = ranges[tile, 1]
        zero = grad_splats.dtype(0.0)
        one = grad_splats.dtype(1.0)
        cx = grad_splats.dtype(float(px)) + grad_splats.dtype(0.5)
        cy = grad_splats.dtype(float(py)) + grad_splats.dtype(0.5)

        last = start - 1
        T = one  # the walk starts behind the last row, at the final transmittance
        upstream = wp.vector(zero, zero, zero, zero, zero)
        if inside:
            camera = where[1]
            pixel = (camera * height + py) * width + px
            last = last_index[pixel]
            T, upstream = pixel_upstream(state, grad_color, grad_depth, grad_alpha, background, pixel, camera)
        # Rows after the block's largest last index contribute to no pixel of the block: the block stages none of
        # them, and a warp walks only the rows up to its own largest last index. The lanes of a warp walk the
        # same rows (so that they meet at each row's shuffle reduction); a lane past its own last row, or
        # outside the image, contributes zero.
        block_last = wp.tile_max(wp.tile(last))[0]
        warp_last = warp_max(last)
        columns = wp.where(grad_depth.shape[0] > 0, ROW_WIDTH, DEPTH)  # no depth gradient: the last column stays 0
        behind = wp.vector(zero, zero, zero, zero)
        batch_end = block_last + 1
        while batch_end > start:
            batch_start = wp.max(start, batch_end - BATCH)
            ids = wp.tile_load(sorted_ids, shape=BATCH, offset=batch_start, storage="shared")
            rows = wp.tile_load_indexed(splats, indices=ids, shape=(BATCH, ROW_WIDTH), offset=(0, 0), axis=0,
                                        storage="shared")
            count = wp.min(batch_end, warp_last + 1) - batch_start
            for step in range(count):
                t = count - 1 - step
                power = gaussian_power(rows, t, cx, cy)
                vis = wp.exp(-power)
                opacity = rows[t, OPACITY]
                alpha = wp.min(grad_splats.dtype(MAX_ALPHA), opacity * vis)
                valid = batch_start + t <= last and power >= zero and alpha >= grad_splats.dtype(ALPHA_THRESHOLD)
                lanes = warp_count(int(valid))
                if lanes > 0:
                    g = wp.vector(zero, zero, zero, zero, zero, zero, zero, zero, zero, zero)
                    if valid:
                        g, T, behind = row_gradient(rows, t, cx, cy, vis, alpha, T, behind, upstream)
                    if lanes > DIRECT_ATOMIC_LANES:  # warp-uniform: sum over the warp, a lane per column adds
                        warp_sum_row_add(grad_splats, ids[t], g, columns)
                    elif valid:
                        row = ids[t]
                        for k in range(ROW_WIDTH):
                            if k < columns:
                                wp.atomic_add(grad_splats, row, k, g[k])
            batch_end = batch_start

    return composite_forward, composite_backward
