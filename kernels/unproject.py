"""Per-pixel 2D-to-3D unprojection (forward and hand-written backward), generic over float32/float64.

Conventions are those of ``codecsplat_warp.cameras``: OpenCV axes, pixel centres at +0.5, depth = camera z.
Camera parameters arrive as plain scalar arrays so one kernel serves both float widths:

* ``intrinsics`` [V,4]: fx, fy, cx, cy in pixels of the depth grid;
* ``c2w`` [V,4,4]: camera-to-world.

The point is formed in the camera frame, rotated into world axes, and the camera centre is added last, so
the float32 error stays relative to the camera distance rather than to the world origin.
"""

from typing import Any

import warp as wp

# Backward passes are hand-written kernels: skip Warp's adjoint code generation (compiles ~2.6x faster).
wp.set_module_options({"enable_backward": False})


@wp.func
def pixel_ray(intrinsics: wp.array(dtype=Any, ndim=2), v: int, x: int, y: int):
    """Camera-frame ray (z = 1) through the centre of pixel (column x, row y) of view v."""
    one = intrinsics.dtype(1.0)
    half = intrinsics.dtype(0.5)
    u = intrinsics.dtype(x) + half
    w = intrinsics.dtype(y) + half
    return wp.vector((u - intrinsics[v, 2]) / intrinsics[v, 0], (w - intrinsics[v, 3]) / intrinsics[v, 1], one)


@wp.func
def rotate_to_world(c2w: wp.array(dtype=Any, ndim=3), v: int, p: Any):
    """``R_c2w @ p`` for a camera-frame vector p of view v (no translation)."""
    return wp.vector(
        c2w[v, 0, 0] * p[0] + c2w[v, 0, 1] * p[1] + c2w[v, 0, 2] * p[2],
        c2w[v, 1, 0] * p[0] + c2w[v, 1, 1] * p[1] + c2w[v, 1, 2] * p[2],
        c2w[v, 2, 0] * p[0] + c2w[v, 2, 1] * p[1] + c2w[v, 2, 2] * p[2],
    )


@wp.kernel
def unproject_forward(
    depth: wp.array(dtype=Any, ndim=3),
    intrinsics: wp.array(dtype=Any, ndim=2),
    c2w: wp.array(dtype=Any, ndim=3),
    points: wp.array(dtype=Any, ndim=4),
):
    """points[v, y, x, :] = c2w[v] applied to depth[v, y, x] * ray(x, y). Launch dim: (V, H, W)."""
    v, y, x = wp.tid()
    offset = rotate_to_world(c2w, v, pixel_ray(intrinsics, v, x, y) * depth[v, y, x])
    for k in range(3):
        points[v, y, x, k] = offset[k] + c2w[v, k, 3]


@wp.kernel
def unproject_backward(
    grad_points: wp.array(dtype=Any, ndim=4),
    intrinsics: wp.array(dtype=Any, ndim=2),
    c2w: wp.array(dtype=Any, ndim=3),
    grad_depth: wp.array(dtype=Any, ndim=3),
):
    """grad_depth[v, y, x] = <grad_points[v, y, x], R_c2w ray(x, y)>. Launch dim: (V, H, W)."""
    v, y, x = wp.tid()
    direction = rotate_to_world(c2w, v, pixel_ray(intrinsics, v, x, y))
    g = wp.vector(grad_points[v, y, x, 0], grad_points[v, y, x, 1], grad_points[v, y, x, 2])
    grad_depth[v, y, x] = wp.dot(g, direction)
