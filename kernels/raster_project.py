"""EWA projection of 3D Gaussians into pinhole cameras (forward with culling, and a differentiable twin).

Conventions (those of :mod:`codecsplat_warp.cameras` and of gsplat 1.5.3): ``viewmat`` is world-to-camera
with OpenCV axes (x right, y down, z forward), ``K`` is in pixels, pixel ``(i, j)`` has its centre at
``(i + 0.5, j + 0.5)``; quaternions are ``(w, x, y, z)`` and need not be normalised.

One thread per (camera, Gaussian) writes one *projected row* of 10 scalars (the packed record the
compositing kernels stage through shared memory; its columns are named in :mod:`.raster_row`).

:func:`prepare_cameras` runs first, on one thread: it validates the cameras (and background) and makes
them camera-relative. A float32 position far from the world origin loses its digits in ``R x + t`` (the two
terms cancel); so the world is translated by the mean camera centre ``o`` (computed in float64 and rounded
to the Gaussians' dtype): the projection kernels use ``x - o`` and viewmats ``V T(o)`` composed in float64.
A pure translation: images are unchanged and the gradient of ``x - o`` is the identity.

The ``project_gaussians`` kernel (see :func:`projection_kernels`) also culls (non-finite, z outside
(near, far), det <= 0 after the blur, opacity < 1/255 (:data:`.raster_row.ALPHA_THRESHOLD`), off-screen), writes
integer pixel radii from the opacity-aware extent ``min(3.33, sqrt(2 ln(255 opacity)))`` sigma, the number of tiles
each row reaches (:mod:`.raster_reach`), input validation flags and the list of visible rows. Its twin
``project_gaussians_differentiable`` recomputes only the differentiable row of the listed visible Gaussians and is
launched with ``adjoint=True`` for the backward pass (straight-line code, so Warp's automatic adjoint is exact; a
float64 gradcheck covers it); with SH colours :func:`sh_color_gradients` gives the colours' gradient (of the
coefficients, and of the means through the view direction), one thread per Gaussian.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import warp as wp

from .lanes import CACHE_LINE_INT64, atomic_increment, warp_append, warp_fold_range
from .raster_row import (
    ALPHA_LEVELS, ALPHA_THRESHOLD, BLUE, CONIC_A, CONIC_B, CONIC_C, DEPTH, GREEN, MEAN_X, MEAN_Y, OPACITY, RED,
)  # fmt: skip
from .raster_reach import row_reach
from .raster_tiles import (
    DEPTH_RANGE, DEPTH_RANGE_LINES, NO_DEPTH_BITS, NUM_FLAGS, depth_bits, reached_tiles, tile_rect,
)  # fmt: skip
from .sh import MAX_COEFFICIENTS, sh_basis, sh_color, sh_count, sh_direction_gradient

MAX_EXTENT_SIGMAS = 3.33
"""Largest bounding extent in standard deviations (gsplat's default)."""

(BAD_MEANS, BAD_QUATS, BAD_SCALES, BAD_OPACITIES, BAD_COLORS, BAD_VIEWMATS, BAD_KS, BAD_BACKGROUND, ZERO_QUATS,
 HUGE_COVARIANCE) = range(10)
"""Slots of the int64 flag array: non-finite rows per Gaussian argument, non-finite entries per camera argument,
zero quaternions, covariances that overflow (the validation flags; the buffer's other slots, from
:data:`.raster_tiles.KEY_LAYOUT` on, belong to the sort key, see :mod:`.raster_tiles`)."""

VALIDATION_FLAGS = HUGE_COVARIANCE + 1
"""Number of validation flag slots (the first ones of the flag buffer)."""

_NO_DEPTH_BITS = wp.constant(wp.int64(NO_DEPTH_BITS))


@wp.func
def world_to_camera(viewmat: Any, point: Any):
    """Camera-space position of a world point (``viewmat`` is a 4x4 world-to-camera matrix)."""
    return wp.vector(
        viewmat[0, 0] * point[0] + viewmat[0, 1] * point[1] + viewmat[0, 2] * point[2] + viewmat[0, 3],
        viewmat[1, 0] * point[0] + viewmat[1, 1] * point[1] + viewmat[1, 2] * point[2] + viewmat[1, 3],
        viewmat[2, 0] * point[0] + viewmat[2, 1] * point[1] + viewmat[2, 2] * point[2] + viewmat[2, 3],
    )


@wp.func
def camera_center(viewmat: Any):
    """World position of the camera centre, ``-R^T t``."""
    return wp.vector(
        -(viewmat[0, 0] * viewmat[0, 3] + viewmat[1, 0] * viewmat[1, 3] + viewmat[2, 0] * viewmat[2, 3]),
        -(viewmat[0, 1] * viewmat[0, 3] + viewmat[1, 1] * viewmat[1, 3] + viewmat[2, 1] * viewmat[2, 3]),
        -(viewmat[0, 2] * viewmat[0, 3] + viewmat[1, 2] * viewmat[1, 3] + viewmat[2, 2] * viewmat[2, 3]),
    )


@wp.func
def quat_scale(quat: Any):
    """Largest absolute component of a quaternion (0 only for the zero quaternion)."""
    return wp.max(wp.max(wp.abs(quat[0]), wp.abs(quat[1])), wp.max(wp.abs(quat[2]), wp.abs(quat[3])))


@wp.func
def camera_covariance(viewmat: Any, quat: Any, scale: Any):
    """Camera-space 3x3 covariance ``R_cam (R_q S)(R_q S)^T R_cam^T`` from a wxyz quaternion and scales.

    The quaternion is divided by its largest component before normalising, so |q|^2 neither underflows nor
    overflows for any non-zero finite q (float32 |q| < 1e-19 or > 1e19)."""
    q = wp.normalize(quat / quat_scale(quat))
    w = q[0]
    x = q[1]
    y = q[2]
    z = q[3]
    one = type(w)(1.0)
    two = type(w)(2.0)
    rot = wp.matrix(
        one - two * (y * y + z * z), two * (x * y - w * z), two * (x * z + w * y),
        two * (x * y + w * z), one - two * (x * x + z * z), two * (y * z - w * x),
        two * (x * z - w * y), two * (y * z + w * x), one - two * (x * x + y * y),
        shape=(3, 3),
    )  # fmt: skip
    m = rot * wp.diag(scale)
    view_rot = wp.matrix(
        viewmat[0, 0], viewmat[0, 1], viewmat[0, 2],
        viewmat[1, 0], viewmat[1, 1], viewmat[1, 2],
        viewmat[2, 0], viewmat[2, 1], viewmat[2, 2],
        shape=(3, 3),
    )  # fmt: skip
    vm = view_rot * m
    return vm * wp.transpose(vm)


@wp.func
def projected_covariance(p: Any, cov: Any, K: Any, width: int, height: int):
    """EWA 2x2 image covariance ``J cov J^T`` (no blur), with x/z and y/z clamped to the frustum + 30 %.

    The clamp follows gsplat: limits ``(W - cx)/fx + 0.3 tan_fovx`` and ``cx/fx + 0.3 tan_fovx``
    (same in y); the gradient through a clamped coordinate is zero.
    """
    fx = K[0, 0]
    fy = K[1, 1]
    cx = K[0, 2]
    cy = K[1, 2]
    zero = type(fx)(0.0)
    w = type(fx)(float(width))
    h = type(fx)(float(height))
    margin = type(fx)(0.3 * 0.5)
    lim_x_pos = (w - cx) / fx + margin * w / fx
    lim_x_neg = cx / fx + margin * w / fx
    lim_y_pos = (h - cy) / fy + margin * h / fy
    lim_y_neg = cy / fy + margin * h / fy
    z = p[2]
    tx = z * wp.clamp(p[0] / z, -lim_x_neg, lim_x_pos)
    ty = z * wp.clamp(p[1] / z, -lim_y_neg, lim_y_pos)
    jac = wp.matrix(
        fx / z, zero, -fx * tx / (z * z),
        zero, fy / z, -fy * ty / (z * z),
        shape=(2, 3),
    )  # fmt: skip
    return jac * cov * wp.transpose(jac)


@wp.func
def projected_mean(p: Any, K: Any):
    """Pixel position of a camera-space point (pixel centres at +0.5 are implied by K's convention)."""
    return wp.vector(K[0, 0] * p[0] / p[2] + K[0, 2], K[1, 1] * p[1] / p[2] + K[1, 2])


@wp.func
def blur_compensation(det_orig: Any, det_blur: Any):
    """``sqrt(max(det_orig / det_blur, 0))`` with a finite derivative at 0 (r / sqrt(max(r, 1e-12)))."""
    r = wp.max(det_orig / det_blur, type(det_orig)(0.0))
    return r / wp.sqrt(wp.max(r, type(det_orig)(1.0e-12)))


@wp.func
def sh_row_color(coeffs: wp.array2d(dtype=Any), n: int, sh_degree: int, mean: Any, viewmat: Any):
    """RGB of Gaussian ``n`` from its SH coefficients: ``max(SH(mean - centre) + 0.5, 0)``."""
    c = sh_color(coeffs, n, sh_degree, mean - camera_center(viewmat))
    half = type(c[0])(0.5)
    zero = type(c[0])(0.0)
    return wp.vector(wp.max(c[0] + half, zero), wp.max(c[1] + half, zero), wp.max(c[2] + half, zero))


@wp.func
def write_row(
    splats: wp.array2d(dtype=Any), i: int, mean2d: Any, conic: Any, opacity: Any, color: Any, depth: Any
):
    """Store one projected row (layout in :mod:`.raster_row`)."""
    splats[i, MEAN_X] = mean2d[0]
    splats[i, MEAN_Y] = mean2d[1]
    splats[i, CONIC_A] = conic[0]
    splats[i, CONIC_B] = conic[1]
    splats[i, CONIC_C] = conic[2]
    splats[i, OPACITY] = opacity
    splats[i, RED] = color[0]
    splats[i, GREEN] = color[1]
    splats[i, BLUE] = color[2]
    splats[i, DEPTH] = depth


@wp.func
def flag_non_finite3(v: Any, flags: wp.array(dtype=wp.int64), slot: int):
    if not (wp.isfinite(v[0]) and wp.isfinite(v[1]) and wp.isfinite(v[2])):
        atomic_increment(flags, slot)


@wp.func
def validate_gaussian(
    n: int, mean: Any, quat: Any, scale: Any, opacity: Any, coeffs: wp.array2d(dtype=Any),
    flags: wp.array(dtype=wp.int64),
):  # fmt: skip
    """Count the non-finite rows per argument of Gaussian ``n``, and a zero quaternion."""
    flag_non_finite3(mean, flags, BAD_MEANS)
    flag_non_finite3(scale, flags, BAD_SCALES)
    if not (wp.isfinite(quat[0]) and wp.isfinite(quat[1]) and wp.isfinite(quat[2]) and wp.isfinite(quat[3])):
        atomic_increment(flags, BAD_QUATS)
    elif quat_scale(quat) == type(opacity)(0.0):
        atomic_increment(flags, ZERO_QUATS)
    if not wp.isfinite(opacity):
        atomic_increment(flags, BAD_OPACITIES)
    for k in range(coeffs.shape[1]):
        flag_non_finite3(coeffs[n, k], flags, BAD_COLORS)


@wp.func
def non_finite_count(values: wp.array3d(dtype=Any), b: int):
    """Number of NaN/Inf entries of matrix ``values[b]``."""
    count = wp.int64(0)
    for r in range(values.shape[1]):
        for c in range(values.shape[2]):
            if not wp.isfinite(values[b, r, c]):
                count += wp.int64(1)
    return count


@wp.kernel(enable_backward=False, module="unique")
def prepare_cameras(
    viewmats: wp.array3d(dtype=Any),
    Ks: wp.array3d(dtype=Any),
    background: wp.array2d(dtype=Any),
    camera_relative: int,
    out_viewmats: wp.array3d(dtype=Any),
    out_Ks: wp.array3d(dtype=Any),
    origin: wp.array(dtype=Any),
    flags: wp.array(dtype=wp.int64),
    visible_count: wp.array(dtype=wp.int64),
):
    """Validate the cameras, cast them to the Gaussians' dtype and make them camera-relative (``dim=1``).

    Args:
        viewmats: ``[B,4,4]`` world-to-camera, any float dtype; Ks: ``[B,3,3]`` intrinsics in pixels.
        background: ``[B,3]`` colours, or ``[0,3]`` for none (only validated here).
        camera_relative: 1 to translate the world by the mean camera centre (float32 Gaussians), 0 for none.
        out_viewmats: ``[B,4,4]`` ``viewmats T(origin)`` composed in float64, in the output dtype;
        out_Ks: ``[B,3,3]`` the intrinsics in the output dtype; origin: ``[3]`` the mean camera centre rounded
            to the output dtype (world units), or 0.
        flags: ``[NUM_FLAGS]`` counters: camera and background slots set, Gaussian slots zeroed, every depth-range
            line empty (``NO_DEPTH_BITS``, 0).
        visible_count: ``[1]`` int64, zeroed (the length of the projection's visible-row list).
    """
    num = viewmats.shape[0]
    for slot in range(NUM_FLAGS):
        flags[slot] = wp.int64(0)
    for line in range(DEPTH_RANGE_LINES):
        flags[DEPTH_RANGE + line * CACHE_LINE_INT64] = _NO_DEPTH_BITS
    visible_count[0] = wp.int64(0)
    bad_background = wp.int64(0)
    for b in range(background.shape[0]):
        for c in range(3):
            if not wp.isfinite(background[b, c]):
                bad_background += wp.int64(1)
    flags[BAD_BACKGROUND] = bad_background
    centre_sum = wp.vec3d()
    for b in range(num):
        flags[BAD_VIEWMATS] = flags[BAD_VIEWMATS] + non_finite_count(viewmats, b)
        flags[BAD_KS] = flags[BAD_KS] + non_finite_count(Ks, b)
        centre = wp.vec3d()
        for j in range(3):
            for r in range(3):
                centre[j] = centre[j] + wp.float64(viewmats[b, r, j]) * wp.float64(viewmats[b, r, 3])
        centre_sum = centre_sum - centre
    shift = wp.vec3d()
    for j in range(3):
        origin[j] = origin.dtype(0.0)
        if camera_relative != 0 and num > 0:
            origin[j] = origin.dtype(centre_sum[j] / wp.float64(num))
        shift[j] = wp.float64(origin[j])
    for b in range(num):
        for r in range(4):
            for c in range(3):
                out_viewmats[b, r, c] = origin.dtype(viewmats[b, r, c])
            translation = wp.float64(viewmats[b, r, 3])
            if camera_relative != 0:
                translation = (wp.float64(viewmats[b, r, 0]) * shift[0] + wp.float64(viewmats[b, r, 1]) * shift[1]
                               + wp.float64(viewmats[b, r, 2]) * shift[2] + translation)  # fmt: skip
            out_viewmats[b, r, 3] = origin.dtype(translation)
        for r in range(3):
            for c in range(3):
                out_Ks[b, r, c] = origin.dtype(Ks[b, r, c])


@wp.func
def row_is_finite(mean2d: Any, conic: Any, opacity: Any, color: Any):
    return (
        wp.isfinite(mean2d[0])
        and wp.isfinite(mean2d[1])
        and wp.isfinite(conic[0])
        and wp.isfinite(conic[1])
        and wp.isfinite(conic[2])
        and wp.isfinite(opacity)
        and wp.isfinite(color[0])
        and wp.isfinite(color[1])
        and wp.isfinite(color[2])
    )


DIFFERENTIABLE_LAUNCH_BOUNDS = (256, 3)
"""CUDA ``__launch_bounds__`` of the differentiable projection: three blocks of 256 threads resident per
multiprocessor, i.e. at most 85 registers per thread for its adjoint (128 unbounded, float32 RGB). Measured on an
H200 at the DL3DV workload: 180 us per backward launch against 197 us unbounded."""


class ProjectionKernels(NamedTuple):
    """The projection kernels of one colour kind (see :func:`projection_kernels`)."""

    project: Any
    differentiable: Any


@functools.cache
def projection_kernels(spherical_harmonics: bool) -> ProjectionKernels:
    """:func:`project_gaussians` and its differentiable twin for RGB colours (``spherical_harmonics=False``:
    ``coeffs`` is ``[N, 1]`` and ``sh_degree`` is ignored) or for SH coefficients. Separate kernels, because the
    SH code (and its adjoint) would otherwise claim registers in the RGB kernels too: fewer registers, more
    threads in flight per multiprocessor."""

    @wp.func
    def row_color(coeffs: wp.array2d(dtype=Any), n: int, sh_degree: int, mean: Any, viewmat: Any):
        """RGB of Gaussian ``n``: SH evaluated towards it, or the given colour (``coeffs[n, 0]``)."""
        if wp.static(spherical_harmonics):
            return sh_row_color(coeffs, n, sh_degree, mean, viewmat)
        return coeffs[n, 0]

    @wp.func
    def differentiated_color(coeffs: wp.array2d(dtype=Any), n: int, like: Any):
        """The colour the differentiable twin writes: the given colour (``coeffs[n, 0]``), or with SH colours zero
        (``like`` gives the scalar type), whose gradient :func:`sh_color_gradients` takes instead."""
        if wp.static(spherical_harmonics):
            zero = type(like)(0.0)
            return wp.vector(zero, zero, zero)
        return coeffs[n, 0]

    @wp.kernel(enable_backward=False, module="unique")
    def project_gaussians(
        means: wp.array(dtype=Any),
        quats: wp.array(dtype=Any),
        scales: wp.array(dtype=Any),
        opacities: wp.array(dtype=Any),
        coeffs: wp.array2d(dtype=Any),
        viewmats: wp.array(dtype=Any),
        Ks: wp.array(dtype=Any),
        origin: wp.array(dtype=Any),
        sh_degree: int,
        width: int,
        height: int,
        near: Any,
        far: Any,
        eps2d: Any,
        antialiased: int,
        tile_size: int,
        tiles_x: int,
        tiles_y: int,
        rounding: wp.float64,
        zero_culled: int,
        leave_out: wp.array(dtype=wp.vec2i),
        first_gaussian: int,
        splats: wp.array2d(dtype=Any),
        radii: wp.array(dtype=wp.vec2i),
        tile_counts: wp.array(dtype=wp.int64),
        tile_masks: wp.array(dtype=wp.int64),
        flags: wp.array(dtype=wp.int64),
        visible_count: wp.array(dtype=wp.int64),
        visible_rows: wp.array(dtype=wp.int32),
        tile_ranges: wp.array(dtype=wp.vec2i),
    ):
        """Project, cull and bin-count every (camera b, Gaussian n); launch with ``dim=(B, count)`` for the Gaussians
        ``first_gaussian .. first_gaussian + count - 1`` (the CPU splits the Gaussians over threads).

        Args:
            means, scales: ``[N]`` 3-vectors (world units); quats: ``[N]`` wxyz 4-vectors; opacities: ``[N]`` in [0, 1].
            coeffs: ``[N, K]`` RGB vectors: SH coefficients (``sh_degree`` 0..3) or the colour (``sh_degree = -1``, K = 1).
            viewmats: ``[B]`` 4x4 camera-relative world-to-camera, Ks: ``[B]`` 3x3 intrinsics in pixels, origin:
                ``[3]`` the world translation, all from :func:`prepare_cameras`.
            near, far: depth range (exclusive); eps2d: low-pass blur in px^2 (0.3); antialiased: 1 to scale
                opacity by the blur compensation ``sqrt(det / det_blur)``.
            rounding: :data:`.raster_reach.POWER_ROUNDING` of the dtype (for the tiles a row reaches).
            zero_culled: 1 to write zero rows for culled Gaussians; 0 leaves them unwritten (the rasterizer reads
                only visible rows, and ten scattered stores per culled Gaussian cost more than the projection).
            leave_out: ``[B]`` int32 pairs: camera b culls the Gaussians ``leave_out[b][0] <= n < leave_out[b][1]``
                (e.g. a view's own pixel-aligned Gaussians); ``[0]`` culls none.
            first_gaussian: the Gaussian of thread ``(b, 0)``.
            splats: output rows ``[B*N, 10]``; radii: ``[B*N]`` pixel radii (0 = culled);
            tile_counts: ``[B*N]`` int64 tiles reached (0 for a culled row), tile_masks: ``[B*N]`` int64 which ones
                (:func:`.raster_tiles.reached_tiles`; unwritten for a culled row);
            flags: ``[NUM_FLAGS]`` counters (initialised by :func:`prepare_cameras`): validation counts and the range
                of the visible depths' float32 bits.
            visible_count: ``[1]`` int64 (zeroed by :func:`prepare_cameras`), visible_rows: ``[B*N]`` int32: the
                first ``visible_count[0]`` entries receive the flat index of every visible row, in no particular
                order (the list the differentiable twin walks, so that its work follows the visible Gaussians).
            tile_ranges: ``[T]`` int32 pairs set to zero (the tile binning's output, zeroed here because this is the
                one parallel launch before the binning; it saves a fill launch), or ``[0]``.
        """
        b, local = wp.tid()
        n = first_gaussian + local
        num = means.shape[0]
        i = b * num + n
        for j in range(i, tile_ranges.shape[0], viewmats.shape[0] * num):
            tile_ranges[j] = wp.vec2i(0, 0)
        quat = quats[n]
        scale = scales[n]
        opacity = opacities[n]
        viewmat = viewmats[b]
        K = Ks[b]
        if b == 0:
            validate_gaussian(n, means[n], quat, scale, opacity, coeffs, flags)
        mean = means[n] - wp.vector(origin[0], origin[1], origin[2])

        zero = type(opacity)(0.0)
        if zero_culled != 0:
            write_row(splats, i, wp.vector(zero, zero), wp.vector(zero, zero, zero), zero, wp.vector(zero, zero, zero), zero)
        radii[i] = wp.vec2i(0, 0)
        tile_counts[i] = wp.int64(0)
        if leave_out.shape[0] > 0:
            if n >= leave_out[b][0] and n < leave_out[b][1]:
                return
        p = world_to_camera(viewmat, mean)
        if not (p[2] > near and p[2] < far and wp.isfinite(p[0]) and wp.isfinite(p[1])):
            return
        cov2d = projected_covariance(p, camera_covariance(viewmat, quat, scale), K, width, height)
        if not (wp.isfinite(cov2d[0, 0]) and wp.isfinite(cov2d[0, 1]) and wp.isfinite(cov2d[1, 1])):
            if wp.isfinite(scale[0]) and wp.isfinite(scale[1]) and wp.isfinite(scale[2]):
                atomic_increment(flags, HUGE_COVARIANCE)
            return
        det_orig = wp.determinant(cov2d)
        blurred = cov2d + wp.identity(n=2, dtype=type(opacity)) * eps2d
        det = wp.determinant(blurred)
        if not (det > zero):
            return
        conic = wp.vector(blurred[1, 1] / det, -blurred[0, 1] / det, blurred[0, 0] / det)
        effective_opacity = opacity
        if antialiased != 0:
            effective_opacity = opacity * blur_compensation(det_orig, det)
        if not (effective_opacity >= type(opacity)(ALPHA_THRESHOLD)):
            return
        extent = wp.min(
            type(opacity)(MAX_EXTENT_SIGMAS),
            wp.sqrt(type(opacity)(2.0) * wp.log(effective_opacity * type(opacity)(ALPHA_LEVELS))),
        )
        radius = wp.vec2i(int(wp.ceil(extent * wp.sqrt(blurred[0, 0]))), int(wp.ceil(extent * wp.sqrt(blurred[1, 1]))))
        if radius[0] <= 0 and radius[1] <= 0:
            return
        mean2d = projected_mean(p, K)
        rx = type(opacity)(float(radius[0]))
        ry = type(opacity)(float(radius[1]))
        if mean2d[0] + rx <= zero or mean2d[0] - rx >= type(opacity)(float(width)):
            return
        if mean2d[1] + ry <= zero or mean2d[1] - ry >= type(opacity)(float(height)):
            return
        color = row_color(coeffs, n, sh_degree, mean, viewmat)
        if not row_is_finite(mean2d, conic, effective_opacity, color):
            return
        write_row(splats, i, mean2d, conic, effective_opacity, color, p[2])
        rect = tile_rect(mean2d[0], mean2d[1], radius, tile_size, tiles_x, tiles_y)
        radii[i] = radius
        reach = row_reach(effective_opacity, conic[0], conic[1], conic[2], rounding)
        reached, mask = reached_tiles(mean2d[0], mean2d[1], conic[0], conic[1], conic[2], reach, rect, tile_size,
                                      width, height)  # fmt: skip
        tile_counts[i] = wp.int64(reached)
        tile_masks[i] = mask
        visible_rows[warp_append(visible_count, 0)] = i
        warp_fold_range(flags, DEPTH_RANGE, DEPTH_RANGE_LINES, depth_bits(p[2]))

    @wp.kernel(module="unique", launch_bounds=DIFFERENTIABLE_LAUNCH_BOUNDS)
    def project_gaussians_differentiable(
        means: wp.array(dtype=Any),
        quats: wp.array(dtype=Any),
        scales: wp.array(dtype=Any),
        opacities: wp.array(dtype=Any),
        coeffs: wp.array2d(dtype=Any),
        viewmats: wp.array(dtype=Any),
        Ks: wp.array(dtype=Any),
        origin: wp.array(dtype=Any),
        visible_count: wp.array(dtype=wp.int64),
        visible_rows: wp.array(dtype=wp.int32),
        sh_degree: int,
        width: int,
        height: int,
        eps2d: Any,
        antialiased: int,
        splats: wp.array2d(dtype=Any),
    ):
        """The differentiable part of :func:`project_gaussians` for the visible rows it listed (``dim=B*N``: thread
        ``t < visible_count[0]`` takes row ``visible_rows[t]``, the others return at once).

        Launch with ``adjoint=True``, ``adj_outputs`` = gradient of the rows, to get gradients of means,
        quats, scales, opacities and RGB colours (accumulated over cameras). Culled rows get no gradient. Walking
        the list instead of all ``(b, n)`` keeps a warp from running the adjoint because one of its 32 Gaussians is
        visible: with 90 % of the Gaussians off-screen nearly every warp would. With SH colours the twin leaves
        the colour out (it writes zero), and :func:`sh_color_gradients` gives the coefficients' gradient and the
        means' through the view direction, one thread per Gaussian: here the coefficients would cost 3 (degree
        + 1)^2 atomic adds per row, and their uncoalesced loads and the basis's spilled registers took 1.8 of the
        3.0 ms of an 8-view RDO step's adjoint (H200; Nsight Compute: 85 % of its L2 sectors excessive, 84 M
        spill requests).
        """
        t = wp.tid()
        if wp.int64(t) >= visible_count[0]:
            return
        i = visible_rows[t]
        b = i // means.shape[0]
        n = i - b * means.shape[0]
        mean = means[n] - wp.vector(origin[0], origin[1], origin[2])
        opacity = opacities[n]
        viewmat = viewmats[b]
        K = Ks[b]
        p = world_to_camera(viewmat, mean)
        cov2d = projected_covariance(p, camera_covariance(viewmat, quats[n], scales[n]), K, width, height)
        blurred = cov2d + wp.identity(n=2, dtype=type(opacity)) * eps2d
        det = wp.determinant(blurred)
        conic = wp.vector(blurred[1, 1] / det, -blurred[0, 1] / det, blurred[0, 0] / det)
        effective_opacity = opacity
        if antialiased != 0:
            effective_opacity = opacity * blur_compensation(wp.determinant(cov2d), det)
        color = differentiated_color(coeffs, n, opacity)
        write_row(splats, i, projected_mean(p, K), conic, effective_opacity, color, p[2])

    return ProjectionKernels(project_gaussians, project_gaussians_differentiable)


@wp.kernel(enable_backward=False, module="unique")
def sh_color_gradients(
    means: wp.array(dtype=Any),
    coeffs: wp.array2d(dtype=Any),
    viewmats: wp.array(dtype=Any),
    origin: wp.array(dtype=Any),
    radii: wp.array(dtype=wp.vec2i),
    splats: wp.array2d(dtype=Any),
    grad_rows: wp.array2d(dtype=Any),
    sh_degree: int,
    first_gaussian: int,
    grad_coeffs: wp.array2d(dtype=Any),
    grad_means: wp.array(dtype=Any),
):
    """Write the gradient of the SH coefficients of Gaussian ``n = first_gaussian + t`` (thread ``t``,
    ``dim=count``) into ``grad_coeffs``, and add the colours' gradient through the view direction to
    ``grad_means[n]``, both summed over the cameras that see it.

    A row's colour is ``max(sum_k basis_k(d) c_k + 0.5, 0)`` per channel, ``d`` the direction from the camera
    centre to the Gaussian. Where the projected colour is above 0, channel ``j`` of coefficient ``k`` gets
    ``basis_k(d) * grad[j]`` (the colour is linear in the coefficients), and the mean gets the gradient of
    ``sum_k (c_k . grad) basis_k(d)`` with respect to ``d`` (:func:`~.sh.sh_direction_gradient`). The thread loads
    the coefficients once, sums its cameras' terms in registers, in camera order, writes each coefficient once and
    adds to its own mean (no atomics; launched before the projection adjoint, whose atomic adds follow).

    Args:
        means: ``[N]`` 3-vectors; coeffs: ``[N, K]`` RGB vectors, ``K >= (sh_degree + 1)^2``.
        viewmats: ``[B]`` 4x4 and origin: ``[3]`` from :func:`prepare_cameras`.
        radii: ``[B*N]`` pixel radii from :func:`project_gaussians` (0: culled, no gradient).
        splats: ``[B*N, 10]`` the projected rows; grad_rows: ``[B*N, 10]`` their gradient.
        sh_degree: 0..3; grad_coeffs: ``[N, K]`` RGB vectors (the coefficients above the degree are left as they
            are); grad_means: ``[N]`` 3-vectors, added to.
    """
    n = first_gaussian + wp.tid()
    num = means.shape[0]
    mean = means[n] - wp.vector(origin[0], origin[1], origin[2])
    count = sh_count(sh_degree)
    zero = splats.dtype(0.0)
    own = wp.matrix(shape=(MAX_COEFFICIENTS, 3), dtype=splats.dtype)
    for k in range(wp.static(MAX_COEFFICIENTS)):
        if k < count:
            own[k] = coeffs[n, k]
    total = wp.matrix(shape=(MAX_COEFFICIENTS, 3), dtype=splats.dtype)
    grad_mean = wp.vector(zero, zero, zero)
    for b in range(viewmats.shape[0]):
        i = b * num + n
        radius = radii[i]
        if radius[0] != 0 or radius[1] != 0:
            g = wp.vector(
                wp.where(splats[i, RED] > zero, grad_rows[i, RED], zero),
                wp.where(splats[i, GREEN] > zero, grad_rows[i, GREEN], zero),
                wp.where(splats[i, BLUE] > zero, grad_rows[i, BLUE], zero),
            )
            direction = mean - camera_center(viewmats[b])
            basis = sh_basis(direction, sh_degree)
            weights = own * g
            for k in range(wp.static(MAX_COEFFICIENTS)):
                if k < count:
                    total[k] = total[k] + g * basis[k]
            grad_mean = grad_mean + sh_direction_gradient(direction, sh_degree, weights)
    for k in range(wp.static(MAX_COEFFICIENTS)):
        if k < count:
            grad_coeffs[n, k] = total[k]
    grad_means[n] = grad_means[n] + grad_mean
