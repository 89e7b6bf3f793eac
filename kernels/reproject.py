"""Multi-view reprojection: warped-feature averaging (paper Eq. 3) and plane-sweep cost volumes.

Both share one geometric step, :func:`warp_to_source`: back-project pixel (x, y) of reference view r at depth
d, move the point into source view s with the relative transform ``rel[r, m] = w2c[s] @ c2w[r]`` (never
through world coordinates), project it, and turn the projection into bilinear taps of the source grid.

Conventions (``codecsplat_warp.cameras``): OpenCV axes, pixel centres at +0.5, depth = camera z. A sample is
*valid* when the point is in front of the source camera (z > 0) and its projection lies inside the source
image, 0 <= u <= W and 0 <= v <= H. The sampling position is (u - 0.5, v - 0.5) in grid units, clamped to
the border pixels: the same as ``torch.nn.functional.grid_sample(align_corners=False,
padding_mode="border")``, including a zero coordinate gradient where the clamp is active.

Array arguments (all scalar arrays so one kernel serves float32 and float64):

* ``feat`` [V,C,H,W] features; ``depth`` [V,H,W] reference depths; ``candidates`` [V,D] sweep depths;
* ``intrinsics`` [V,4] fx, fy, cx, cy in pixels *of the feature grid*;
* ``rel`` [V,M,4,4] reference-to-source transforms; ``neighbours`` [V,M] int32 source view indices;
* ``row0``: first image row of the launch (CPU ops split a launch by rows over threads; 0 on CUDA).

Backward kernels are hand-written (the forward loops run a data-dependent number of samples).
"""

from typing import Any

import warp as wp

# Backward passes are hand-written kernels: skip Warp's adjoint code generation (compiles ~2.6x faster).
wp.set_module_options({"enable_backward": False})

from .unproject import pixel_ray


@wp.func
def to_source_frame(rel: wp.array(dtype=Any, ndim=4), r: int, m: int, p: Any):
    """``R_rel @ p + t_rel`` for the reference-to-source transform rel[r, m]."""
    return wp.vector(
        rel[r, m, 0, 0] * p[0] + rel[r, m, 0, 1] * p[1] + rel[r, m, 0, 2] * p[2] + rel[r, m, 0, 3],
        rel[r, m, 1, 0] * p[0] + rel[r, m, 1, 1] * p[1] + rel[r, m, 1, 2] * p[2] + rel[r, m, 1, 3],
        rel[r, m, 2, 0] * p[0] + rel[r, m, 2, 1] * p[1] + rel[r, m, 2, 2] * p[2] + rel[r, m, 2, 3],
    )


@wp.func
def rotate_to_source(rel: wp.array(dtype=Any, ndim=4), r: int, m: int, p: Any):
    """``R_rel @ p`` (direction only) for the reference-to-source transform rel[r, m]."""
    return wp.vector(
        rel[r, m, 0, 0] * p[0] + rel[r, m, 0, 1] * p[1] + rel[r, m, 0, 2] * p[2],
        rel[r, m, 1, 0] * p[0] + rel[r, m, 1, 1] * p[1] + rel[r, m, 1, 2] * p[2],
        rel[r, m, 2, 0] * p[0] + rel[r, m, 2, 1] * p[1] + rel[r, m, 2, 2] * p[2],
    )


@wp.func
def clamped_coordinate(pos: Any, du_dd: Any, size: int):
    """Grid coordinate ``pos - 0.5`` clamped to [0, size-1], and its derivative (0 where clamped)."""
    zero = type(pos)(0.0)
    raw = pos - type(pos)(0.5)
    top = type(pos)(size - 1)
    if raw <= zero:
        return zero, zero
    if raw >= top:
        return top, zero
    return raw, du_dd


@wp.func
def lower_tap(coord: Any, size: int):
    """Index of the lower bilinear tap (so that the upper tap min(i0+1, size-1) stays inside)."""
    return wp.min(int(wp.floor(coord)), wp.max(size - 2, 0))


@wp.func
def warp_to_source(
    intrinsics: wp.array(dtype=Any, ndim=2),
    rel: wp.array(dtype=Any, ndim=4),
    r: int,
    m: int,
    s: int,
    x: int,
    y: int,
    d: Any,
    width: int,
    height: int,
):
    """Bilinear taps in source view s for pixel (x, y) of view r at depth d.

    Returns (valid, x0, y0, ax, ay, dsx_dd, dsy_dd): the lower taps, the fractional weights towards the upper
    taps (x0+1, y0+1, clamped), and the derivatives of the sampling coordinates with respect to d.
    """
    zero = type(d)(0.0)
    ray = pixel_ray(intrinsics, r, x, y)
    p = to_source_frame(rel, r, m, ray * d)
    q = rotate_to_source(rel, r, m, ray)  # dp/dd
    valid = int(0)
    x0 = int(0)
    y0 = int(0)
    sx = zero
    sy = zero
    dsx = zero
    dsy = zero
    if p[2] > zero:
        inv_z = type(d)(1.0) / p[2]
        u = intrinsics[s, 0] * p[0] * inv_z + intrinsics[s, 2]
        v = intrinsics[s, 1] * p[1] * inv_z + intrinsics[s, 3]
        if u >= zero and u <= type(d)(width) and v >= zero and v <= type(d)(height):
            du = intrinsics[s, 0] * (q[0] * p[2] - p[0] * q[2]) * inv_z * inv_z
            dv = intrinsics[s, 1] * (q[1] * p[2] - p[1] * q[2]) * inv_z * inv_z
            sx, dsx = clamped_coordinate(u, du, width)
            sy, dsy = clamped_coordinate(v, dv, height)
            x0 = lower_tap(sx, width)
            y0 = lower_tap(sy, height)
            valid = 1
    return valid, x0, y0, sx - type(d)(x0), sy - type(d)(y0), dsx, dsy


@wp.func
def bilinear(feat: wp.array(dtype=Any, ndim=4), s: int, c: int, x0: int, y0: int, ax: Any, ay: Any):
    """Bilinear sample of feat[s, c] at lower taps (x0, y0) with weights (ax, ay) towards the upper taps."""
    one = type(ax)(1.0)
    x1 = wp.min(x0 + 1, feat.shape[3] - 1)
    y1 = wp.min(y0 + 1, feat.shape[2] - 1)
    top = (one - ax) * feat[s, c, y0, x0] + ax * feat[s, c, y0, x1]
    bottom = (one - ax) * feat[s, c, y1, x0] + ax * feat[s, c, y1, x1]
    return (one - ay) * top + ay * bottom


@wp.func
def bilinear_coordinate_grad(feat: wp.array(dtype=Any, ndim=4), s: int, c: int, x0: int, y0: int, ax: Any, ay: Any):
    """(d sample / d sx, d sample / d sy) of :func:`bilinear`."""
    one = type(ax)(1.0)
    x1 = wp.min(x0 + 1, feat.shape[3] - 1)
    y1 = wp.min(y0 + 1, feat.shape[2] - 1)
    f00 = feat[s, c, y0, x0]
    f01 = feat[s, c, y0, x1]
    f10 = feat[s, c, y1, x0]
    f11 = feat[s, c, y1, x1]
    return (one - ay) * (f01 - f00) + ay * (f11 - f10), (one - ax) * (f10 - f00) + ax * (f11 - f01)


@wp.func
def scatter_bilinear(grad_feat: wp.array(dtype=Any, ndim=4), s: int, c: int, x0: int, y0: int, ax: Any, ay: Any, g: Any):
    """Adjoint of :func:`bilinear`: atomically add g times each tap weight into grad_feat[s, c]."""
    one = type(ax)(1.0)
    x1 = wp.min(x0 + 1, grad_feat.shape[3] - 1)
    y1 = wp.min(y0 + 1, grad_feat.shape[2] - 1)
    wp.atomic_add(grad_feat, s, c, y0, x0, g * (one - ax) * (one - ay))
    wp.atomic_add(grad_feat, s, c, y0, x1, g * ax * (one - ay))
    wp.atomic_add(grad_feat, s, c, y1, x0, g * (one - ax) * ay)
    wp.atomic_add(grad_feat, s, c, y1, x1, g * ax * ay)


@wp.kernel
def reproject_average_forward(
    feat: wp.array(dtype=Any, ndim=4),
    depth: wp.array(dtype=Any, ndim=3),
    intrinsics: wp.array(dtype=Any, ndim=2),
    rel: wp.array(dtype=Any, ndim=4),
    neighbours: wp.array(dtype=wp.int32, ndim=2),
    avg: wp.array(dtype=Any, ndim=4),
    count: wp.array(dtype=wp.int32, ndim=3),
    row0: int,
):
    """avg[r, :, y, x] = mean over valid sources of the warped source features; count = number valid.

    ``avg`` must be zero-initialised. Launch dim: (V, rows, W) covering rows row0.. of the image.
    """
    r, row, x = wp.tid()
    y = row0 + row
    d = depth[r, y, x]
    n = int(0)
    for m in range(neighbours.shape[1]):
        s = neighbours[r, m]
        valid, x0, y0, ax, ay, dsx, dsy = warp_to_source(intrinsics, rel, r, m, s, x, y, d, feat.shape[3], feat.shape[2])
        if valid == 1:
            n += 1
            for c in range(feat.shape[1]):
                avg[r, c, y, x] = avg[r, c, y, x] + bilinear(feat, s, c, x0, y0, ax, ay)
    count[r, y, x] = n
    if n > 0:
        inv_n = feat.dtype(1.0) / feat.dtype(n)
        for c in range(feat.shape[1]):
            avg[r, c, y, x] = avg[r, c, y, x] * inv_n


@wp.kernel
def reproject_average_backward(
    grad_avg: wp.array(dtype=Any, ndim=4),
    feat: wp.array(dtype=Any, ndim=4),
    depth: wp.array(dtype=Any, ndim=3),
    intrinsics: wp.array(dtype=Any, ndim=2),
    rel: wp.array(dtype=Any, ndim=4),
    neighbours: wp.array(dtype=wp.int32, ndim=2),
    count: wp.array(dtype=wp.int32, ndim=3),
    grad_feat: wp.array(dtype=Any, ndim=4),
    grad_depth: wp.array(dtype=Any, ndim=3),
    row0: int,
):
    """Adjoint of :func:`reproject_average_forward` (count treated as constant: it is piecewise constant).

    ``grad_feat`` must be zero-initialised (atomic scatter). Launch dim: (V, rows, W) from row row0.
    """
    r, row, x = wp.tid()
    y = row0 + row
    n = count[r, y, x]
    gd = feat.dtype(0.0)
    if n > 0:
        inv_n = feat.dtype(1.0) / feat.dtype(n)
        d = depth[r, y, x]
        for m in range(neighbours.shape[1]):
            s = neighbours[r, m]
            valid, x0, y0, ax, ay, dsx, dsy = warp_to_source(intrinsics, rel, r, m, s, x, y, d, feat.shape[3], feat.shape[2])
            if valid == 1:
                for c in range(feat.shape[1]):
                    g = grad_avg[r, c, y, x] * inv_n
                    scatter_bilinear(grad_feat, s, c, x0, y0, ax, ay, g)
                    gx, gy = bilinear_coordinate_grad(feat, s, c, x0, y0, ax, ay)
                    gd += g * (gx * dsx + gy * dsy)
    grad_depth[r, y, x] = gd


@wp.kernel
def cost_volume_forward(
    feat: wp.array(dtype=Any, ndim=4),
    candidates: wp.array(dtype=Any, ndim=2),
    intrinsics: wp.array(dtype=Any, ndim=2),
    rel: wp.array(dtype=Any, ndim=4),
    neighbours: wp.array(dtype=wp.int32, ndim=2),
    cost: wp.array(dtype=Any, ndim=4),
    count: wp.array(dtype=wp.int32, ndim=4),
    row0: int,
):
    """cost[r, k, y, x] = mean over valid sources s of <feat[r,:,y,x], warp_s(feat[s]) at depth candidates[r,k]> / sqrt(C).

    Zero where no source is valid; count[r, k, y, x] = number of valid sources. Launch dim: (V, D, rows, W)
    from row row0.
    """
    r, k, row, x = wp.tid()
    y = row0 + row
    d = candidates[r, k]
    total = feat.dtype(0.0)
    n = int(0)
    for m in range(neighbours.shape[1]):
        s = neighbours[r, m]
        valid, x0, y0, ax, ay, dsx, dsy = warp_to_source(intrinsics, rel, r, m, s, x, y, d, feat.shape[3], feat.shape[2])
        if valid == 1:
            n += 1
            for c in range(feat.shape[1]):
                total += feat[r, c, y, x] * bilinear(feat, s, c, x0, y0, ax, ay)
    count[r, k, y, x] = n
    if n > 0:
        total = total / (feat.dtype(n) * wp.sqrt(feat.dtype(feat.shape[1])))
    cost[r, k, y, x] = total


@wp.kernel
def cost_volume_backward(
    grad_cost: wp.array(dtype=Any, ndim=4),
    feat: wp.array(dtype=Any, ndim=4),
    candidates: wp.array(dtype=Any, ndim=2),
    intrinsics: wp.array(dtype=Any, ndim=2),
    rel: wp.array(dtype=Any, ndim=4),
    neighbours: wp.array(dtype=wp.int32, ndim=2),
    count: wp.array(dtype=wp.int32, ndim=4),
    grad_feat: wp.array(dtype=Any, ndim=4),
    row0: int,
):
    """Adjoint of :func:`cost_volume_forward` with respect to ``feat`` (both the reference and the sources).

    ``grad_feat`` must be zero-initialised (atomic scatter). Launch dim: (V, D, rows, W) from row row0.
    """
    r, k, row, x = wp.tid()
    y = row0 + row
    n = count[r, k, y, x]
    if n > 0:
        g = grad_cost[r, k, y, x] / (feat.dtype(n) * wp.sqrt(feat.dtype(feat.shape[1])))
        d = candidates[r, k]
        for m in range(neighbours.shape[1]):
            s = neighbours[r, m]
            valid, x0, y0, ax, ay, dsx, dsy = warp_to_source(intrinsics, rel, r, m, s, x, y, d, feat.shape[3], feat.shape[2])
            if valid == 1:
                for c in range(feat.shape[1]):
                    wp.atomic_add(grad_feat, r, c, y, x, g * bilinear(feat, s, c, x0, y0, ax, ay))
                    scatter_bilinear(grad_feat, s, c, x0, y0, ax, ay, g * feat[r, c, y, x])
