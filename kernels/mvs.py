"""Multi-view stereo: a plane sweep with windowed NCC, refinement between planes, and a geometric consistency count.

Conventions (``codecsplat_warp.cameras``): OpenCV axes, pixel centres at +0.5, depth = camera z. The sweep planes
are fronto-parallel in the reference camera, the refinement also tries slanted ones: the window pixel
(x + i*step, y + j*step) lies where its ray meets the plane through the centre pixel's point, so its position in a
source view is the plane-induced homography of that pixel (:func:`source_ncc`).

Array arguments (all scalar arrays so one kernel serves float32 and float64):

* ``gray`` [V,H,W] grey levels in [0,1]; ``depth`` [V,H,W] camera-z depth (0 = none);
* ``intrinsics`` [V,4] fx, fy, cx, cy in pixels of the grid;
* ``rel`` [V,K,4,4] reference-to-source transforms ``w2c[s] @ c2w[r]``, ``back`` [V,K,4,4] their inverses;
* ``sources`` [V,K] int32 source view indices, of which the first ``source_count[r]`` are used;
* ``inv_range`` [V,2] inverse depth of the far and of the near plane per view;
* ``similarity`` [1] grey-level difference at which a window sample's support weight halves (0: uniform);
* ``normals`` [N,3] unit plane normals (reference camera frame) tried when refining, row 0 fronto-parallel;
* ``view0``, ``row0``: first view and first image row of the launch (launches are split by views and, on
  the CPU, by rows over threads).

Source pixels are sampled bilinearly with the coordinates clamped to the border pixels; a source counts for a
(pixel, plane) only where the window centre lands in front of it and inside its image.
"""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})

from .reproject import lower_tap, rotate_to_source, to_source_frame
from .unproject import pixel_ray

MAX_SOURCES = wp.constant(8)
"""Most source views per reference view (the per-plane costs are sorted in a local vector of this length)."""


@wp.func
def no_match_cost(like: Any):
    """Cost of a plane that no source sees (1 - NCC lies in [0, 2]), in ``like``'s type.

    A function rather than a ``wp.constant``: Warp 1.19 folds ``float64(CONSTANT)`` into the constant's own
    variable, so a variable initialised that way and updated in a loop changes every later read of the constant.
    """
    return type(like)(2.0)


@wp.func
def gray_at(gray: wp.array(dtype=Any, ndim=3), v: int, x: int, y: int):
    """gray[v] at integer pixel (x, y), clamped to the image."""
    return gray[v, wp.clamp(y, 0, gray.shape[1] - 1), wp.clamp(x, 0, gray.shape[2] - 1)]


@wp.func
def sample_bilinear(gray: wp.array(dtype=Any, ndim=3), v: int, u: Any, w: Any):
    """Bilinear sample of gray[v] at image point (u, w) (pixel-edge units), clamped to the border pixels."""
    one = type(u)(1.0)
    half = type(u)(0.5)
    sx = wp.clamp(u - half, type(u)(0.0), type(u)(gray.shape[2] - 1))
    sy = wp.clamp(w - half, type(u)(0.0), type(u)(gray.shape[1] - 1))
    x0 = lower_tap(sx, gray.shape[2])
    y0 = lower_tap(sy, gray.shape[1])
    x1 = wp.min(x0 + 1, gray.shape[2] - 1)
    y1 = wp.min(y0 + 1, gray.shape[1] - 1)
    ax = sx - type(u)(x0)
    ay = sy - type(u)(y0)
    top = (one - ax) * gray[v, y0, x0] + ax * gray[v, y0, x1]
    bottom = (one - ax) * gray[v, y1, x0] + ax * gray[v, y1, x1]
    return (one - ay) * top + ay * bottom


@wp.func
def project(intrinsics: wp.array(dtype=Any, ndim=2), v: int, p: Any):
    """Image point (u, w) of camera-frame point p (z > 0) in view v."""
    return intrinsics[v, 0] * p[0] / p[2] + intrinsics[v, 2], intrinsics[v, 1] * p[1] / p[2] + intrinsics[v, 3]


@wp.func
def inside_image(u: Any, w: Any, width: int, height: int):
    """Whether image point (u, w) lies in [0, width] x [0, height]."""
    zero = type(u)(0.0)
    return u >= zero and u <= type(u)(width) and w >= zero and w <= type(u)(height)


@wp.func
def support_weight(g: Any, centre: Any, similarity: Any):
    """Weight of a window sample of grey level g around a centre of grey level ``centre``:
    1 / (1 + ((g - centre) / similarity)^2), so samples unlike the centre (likely another surface) count less;
    1 when ``similarity`` <= 0."""
    w = type(g)(1.0)
    if similarity > type(g)(0.0):
        t = (g - centre) / similarity
        w = type(g)(1.0) / (type(g)(1.0) + t * t)
    return w


@wp.func
def reference_window(gray: wp.array(dtype=Any, ndim=3), r: int, x: int, y: int, radius: int, step: int,
                     similarity: Any):  # fmt: skip
    """Statistics of the reference window of pixel (x, y): (ref, std) with ref = (sum of weights, weighted sum,
    weighted sum of squared deviations, similarity) of the grey levels (:func:`support_weight`), and std the
    plain standard deviation of the window's grey levels."""
    zero = type(similarity)(0.0)
    centre = gray_at(gray, r, x, y)
    weights = zero
    total = zero
    squares = zero
    plain = zero
    plain_squares = zero
    for j in range(-radius, radius + 1):
        for i in range(-radius, radius + 1):
            g = gray_at(gray, r, x + i * step, y + j * step)
            w = support_weight(g, centre, similarity)
            weights += w
            total += w * g
            squares += w * g * g
            plain += g
            plain_squares += g * g
    n = type(similarity)((2 * radius + 1) * (2 * radius + 1))
    deviation = wp.max(squares - total * total / weights, zero)
    std = wp.sqrt(wp.max(plain_squares / n - (plain / n) * (plain / n), zero))
    return wp.vector(weights, total, deviation, similarity), std


@wp.func
def source_ncc(
    gray: wp.array(dtype=Any, ndim=3),
    intrinsics: wp.array(dtype=Any, ndim=2),
    rel: wp.array(dtype=Any, ndim=4),
    r: int,
    m: int,
    x: int,
    y: int,
    d: Any,
    normal: Any,
    radius: int,
    step: int,
    ref: Any,
    s: int,
):
    """(valid, NCC) of the reference window of pixel (x, y) with source m = view s on the plane through the
    pixel's point at depth d with unit ``normal`` (reference camera frame; (0, 0, 1) is fronto-parallel).

    Window pixel (i, j) steps along the pixel ray r_ij = ray + (i step / fx, j step / fy, 0) to the plane, at
    depth d (n . ray) / (n . r_ij). Weighted NCC with the reference's support weights (``ref`` from
    :func:`reference_window`); 0 where either window is flat. Not valid where the plane is seen nearly edge-on.
    """
    zero = type(d)(0.0)
    ray = pixel_ray(intrinsics, r, x, y)
    dx = type(d)(step) / intrinsics[r, 0]
    dy = type(d)(step) / intrinsics[r, 1]
    origin = to_source_frame(rel, r, m, wp.vector(zero, zero, zero))
    a = rotate_to_source(rel, r, m, ray)
    bx = rotate_to_source(rel, r, m, wp.vector(dx, zero, zero))
    by = rotate_to_source(rel, r, m, wp.vector(zero, dy, zero))
    facing = wp.dot(normal, ray)
    nx = normal[0] * dx
    ny = normal[1] * dy
    p = a * d + origin
    width = gray.shape[2]
    height = gray.shape[1]
    valid = int(0)
    if p[2] > zero and facing > type(d)(0.1) * wp.length(ray):  # plane at most ~84 deg from facing the pixel
        u, w = project(intrinsics, s, p)
        valid = int(inside_image(u, w, width, height))
    centre = gray_at(gray, r, x, y)
    src_sum = zero
    src_squares = zero
    cross = zero
    if valid == 1:
        for j in range(-radius, radius + 1):
            for i in range(-radius, radius + 1):
                along = facing + nx * type(d)(i) + ny * type(d)(j)
                q = (a + bx * type(d)(i) + by * type(d)(j)) * (d * facing / wp.max(along, type(d)(1.0e-6))) + origin
                if q[2] > zero and along > type(d)(0.5) * facing:
                    qu, qw = project(intrinsics, s, q)
                    g = sample_bilinear(gray, s, qu, qw)
                else:
                    valid = 0
                    g = zero
                reference = gray_at(gray, r, x + i * step, y + j * step)
                w = support_weight(reference, centre, ref[3])
                src_sum += w * g
                src_squares += w * g * g
                cross += w * g * reference
    ncc = zero
    if valid == 1:
        src_deviation = src_squares - src_sum * src_sum / ref[0]
        covariance = cross - ref[1] * src_sum / ref[0]
        tiny = type(d)(1.0e-10) * ref[0]
        if src_deviation > tiny and ref[2] > tiny:
            ncc = wp.clamp(covariance / wp.sqrt(src_deviation * ref[2]), type(d)(-1.0), type(d)(1.0))
    return valid, ncc


@wp.func
def plane_normal(normals: wp.array(dtype=Any, ndim=2), n: int):
    """Row n of ``normals`` [N,3] as a vector."""
    return wp.vector(normals[n, 0], normals[n, 1], normals[n, 2])


@wp.func
def plane_cost(
    gray: wp.array(dtype=Any, ndim=3),
    intrinsics: wp.array(dtype=Any, ndim=2),
    rel: wp.array(dtype=Any, ndim=4),
    sources: wp.array(dtype=wp.int32, ndim=2),
    count: int,
    r: int,
    x: int,
    y: int,
    inv_d: Any,
    normal: Any,
    radius: int,
    step: int,
    ref: Any,
):
    """Occlusion-robust matching cost of pixel (x, y) of view r on the plane through its point at inverse depth
    ``inv_d`` with ``normal`` (see :func:`source_ncc`).

    The mean of the best (lowest) half, rounded up, of the costs 1 - NCC of the sources that see the window
    centre; :func:`no_match_cost` where none does.
    """
    costs = wp.vector(length=MAX_SOURCES, dtype=type(inv_d))
    d = type(inv_d)(1.0) / inv_d
    n = int(0)
    for m in range(count):
        valid, ncc = source_ncc(gray, intrinsics, rel, r, m, x, y, d, normal, radius, step, ref, sources[r, m])
        if valid == 1:
            c = type(inv_d)(1.0) - ncc
            k = n
            while k > 0:  # insertion into the sorted costs
                if costs[k - 1] <= c:
                    break
                costs[k] = costs[k - 1]
                k -= 1
            costs[k] = c
            n += 1
    result = no_match_cost(inv_d)
    if n > 0:
        best = (n + 1) // 2
        total = type(inv_d)(0.0)
        for k in range(best):
            total += costs[k]
        result = total / type(inv_d)(best)
    return result


@wp.kernel
def plane_sweep_depth(
    gray: wp.array(dtype=Any, ndim=3),
    intrinsics: wp.array(dtype=Any, ndim=2),
    rel: wp.array(dtype=Any, ndim=4),
    sources: wp.array(dtype=wp.int32, ndim=2),
    source_count: wp.array(dtype=wp.int32, ndim=1),
    inv_range: wp.array(dtype=Any, ndim=2),
    similarity: wp.array(dtype=Any, ndim=1),
    normals: wp.array(dtype=Any, ndim=2),
    num_planes: int,
    refine_steps: int,
    radius: int,
    step: int,
    depth: wp.array(dtype=Any, ndim=3),
    ncc: wp.array(dtype=Any, ndim=3),
    texture: wp.array(dtype=Any, ndim=3),
    view0: int,
    row0: int,
):
    """Winner-take-all depth of each pixel over ``num_planes`` fronto-parallel planes uniform in inverse depth,
    refined with slanted planes.

    Around the winner, every plane normal of ``normals`` [N,3] (row 0 must be fronto-parallel, (0, 0, 1)) is
    tried at ``refine_steps`` - 1 inverse depths on either side, 1/``refine_steps`` of the plane spacing apart;
    the best (normal, inverse depth) is refined by a parabola through it and its two neighbours in inverse depth.
    Writes depth (0 where no plane is seen by any source), the aggregated NCC of the best refined plane (-1
    there) and the standard deviation of the reference window's grey levels. Launch dim: (views, rows, W) from
    view ``view0``, row ``row0``.
    """
    t, row, x = wp.tid()
    r = view0 + t
    y = row0 + row
    ref, std = reference_window(gray, r, x, y, radius, step, similarity[0])
    texture[r, y, x] = std
    count = source_count[r]
    inv_far = inv_range[r, 0]
    inv_near = inv_range[r, 1]
    spacing = (inv_near - inv_far) / type(inv_far)(num_planes - 1)
    fronto = plane_normal(normals, 0)
    best = no_match_cost(inv_far)
    best_inv = inv_far
    for k in range(num_planes):
        inv_d = inv_far + spacing * type(inv_far)(k)
        c = plane_cost(gray, intrinsics, rel, sources, count, r, x, y, inv_d, fronto, radius, step, ref)
        if c < best:
            best = c
            best_inv = inv_d
    fine = spacing / type(inv_far)(refine_steps)
    centre = best_inv
    best_normal = fronto
    for n in range(normals.shape[0]):
        normal = plane_normal(normals, n)
        for j in range(1 - refine_steps, refine_steps):
            inv_d = centre + fine * type(inv_far)(j)
            if (n > 0 or j != 0) and inv_d >= inv_far and inv_d <= inv_near:
                c = plane_cost(gray, intrinsics, rel, sources, count, r, x, y, inv_d, normal, radius, step, ref)
                if c < best:
                    best = c
                    best_inv = inv_d
                    best_normal = normal
    if best < no_match_cost(inv_far):
        below = best_inv - fine
        above = best_inv + fine
        if below >= inv_far and above <= inv_near:
            c_below = plane_cost(gray, intrinsics, rel, sources, count, r, x, y, below, best_normal, radius, step, ref)
            c_above = plane_cost(gray, intrinsics, rel, sources, count, r, x, y, above, best_normal, radius, step, ref)
            curvature = c_below - type(inv_far)(2.0) * best + c_above
            if curvature > type(inv_far)(0.0):
                offset = type(inv_far)(0.5) * fine * (c_below - c_above) / curvature
                best_inv += wp.clamp(offset, -fine, fine)
        depth[r, y, x] = type(inv_far)(1.0) / best_inv
        ncc[r, y, x] = type(inv_far)(1.0) - best
    else:
        depth[r, y, x] = type(inv_far)(0.0)
        ncc[r, y, x] = type(inv_far)(-1.0)


@wp.func
def sample_depth(depth: wp.array(dtype=Any, ndim=3), v: int, u: Any, w: Any):
    """depth[v] at image point (u, w): bilinear where all four taps hold a depth, else the nearest pixel's."""
    half = type(u)(0.5)
    zero = type(u)(0.0)
    width = depth.shape[2]
    height = depth.shape[1]
    sx = wp.clamp(u - half, zero, type(u)(width - 1))
    sy = wp.clamp(w - half, zero, type(u)(height - 1))
    x0 = lower_tap(sx, width)
    y0 = lower_tap(sy, height)
    x1 = wp.min(x0 + 1, width - 1)
    y1 = wp.min(y0 + 1, height - 1)
    d00 = depth[v, y0, x0]
    d01 = depth[v, y0, x1]
    d10 = depth[v, y1, x0]
    d11 = depth[v, y1, x1]
    result = depth[v, wp.min(int(w), height - 1), wp.min(int(u), width - 1)]
    if d00 > zero and d01 > zero and d10 > zero and d11 > zero:
        one = type(u)(1.0)
        ax = sx - type(u)(x0)
        ay = sy - type(u)(y0)
        result = (one - ay) * ((one - ax) * d00 + ax * d01) + ay * ((one - ax) * d10 + ax * d11)
    return result


@wp.kernel
def consistent_views(
    depth: wp.array(dtype=Any, ndim=3),
    intrinsics: wp.array(dtype=Any, ndim=2),
    rel: wp.array(dtype=Any, ndim=4),
    back: wp.array(dtype=Any, ndim=4),
    sources: wp.array(dtype=wp.int32, ndim=2),
    source_count: wp.array(dtype=wp.int32, ndim=1),
    tolerance: wp.array(dtype=Any, ndim=1),
    agree: wp.array(dtype=wp.int32, ndim=3),
    fused: wp.array(dtype=Any, ndim=3),
    view0: int,
    row0: int,
):
    """agree[r, y, x] = number of source views whose depth agrees with depth[r, y, x] (0 where it is 0), and
    fused[r, y, x] = the mean of depth[r, y, x] and the agreeing views' depths carried into r.

    The pixel is unprojected at its depth into source s, s's depth is sampled there (:func:`sample_depth`),
    and that point is carried back into r: it agrees when it lands within ``tolerance[0]`` pixels of the pixel
    centre and its depth is within ``tolerance[1]`` (relative) of depth[r, y, x]. Launch dim: (views, rows, W)
    from view ``view0``, row ``row0``.
    """
    t, row, x = wp.tid()
    r = view0 + t
    y = row0 + row
    d = depth[r, y, x]
    zero = type(d)(0.0)
    n = int(0)
    total = d
    if d > zero:
        point = pixel_ray(intrinsics, r, x, y) * d
        width = depth.shape[2]
        height = depth.shape[1]
        for m in range(source_count[r]):
            s = sources[r, m]
            p = to_source_frame(rel, r, m, point)
            if p[2] <= zero:
                continue
            u, w = project(intrinsics, s, p)
            if not inside_image(u, w, width, height):
                continue
            ds = sample_depth(depth, s, u, w)
            if ds <= zero:
                continue
            seen = wp.vector((u - intrinsics[s, 2]) / intrinsics[s, 0], (w - intrinsics[s, 3]) / intrinsics[s, 1],
                             type(d)(1.0)) * ds
            q = to_source_frame(back, r, m, seen)
            if q[2] <= zero:
                continue
            back_u, back_w = project(intrinsics, r, q)
            du = back_u - (type(d)(x) + type(d)(0.5))
            dv = back_w - (type(d)(y) + type(d)(0.5))
            if du * du + dv * dv < tolerance[0] * tolerance[0] and wp.abs(q[2] - d) < tolerance[1] * d:
                n += 1
                total += q[2]
    agree[r, y, x] = n
    fused[r, y, x] = total / type(d)(n + 1)
