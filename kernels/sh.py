"""Real spherical harmonics (degrees 0-3) as Warp functions, with gsplat's basis order and constants.

The basis is the one of gsplat 1.5.3 / the Inria 3DGS code (Sloan, "Efficient Spherical Harmonic
Evaluation", JCGT 2013): index ``k`` in ``0 .. (degree+1)^2 - 1``, constant term 0.28209479177387814.
Only the bands up to ``degree`` are evaluated; higher coefficients present in the array are ignored.
Written as straight-line code (branches on ``degree``, loops unrolled at compile time) so Warp's automatic adjoint
is exact.
"""

from __future__ import annotations

from typing import Any

import warp as wp

MAX_COEFFICIENTS = 16
"""Basis functions up to degree 3, the highest supported."""


@wp.func
def sh_count(degree: int):
    """Number of basis functions up to ``degree``: ``(degree + 1)^2``."""
    return (degree + 1) * (degree + 1)


@wp.func
def sh_basis(direction: Any, degree: int):
    """The :data:`MAX_COEFFICIENTS` basis values towards ``direction`` (need not be normalised, must be non-zero),
    as a vector of its scalar type; the bands above ``degree`` are 0."""
    d = wp.normalize(direction)
    x = d[0]
    y = d[1]
    z = d[2]
    zero = type(x)(0.0)
    b1 = zero
    b2 = zero
    b3 = zero
    if degree >= 1:
        a1 = type(x)(-0.48860251190292)
        b1 = a1 * y
        b2 = -a1 * z
        b3 = a1 * x
    b4 = zero
    b5 = zero
    b6 = zero
    b7 = zero
    b8 = zero
    z2 = z * z
    c1 = x * x - y * y
    s1 = type(x)(2.0) * x * y
    if degree >= 2:
        bz = type(x)(-1.092548430592079) * z
        a2 = type(x)(0.5462742152960395)
        b4 = a2 * s1
        b5 = bz * y
        b6 = type(x)(0.9461746957575601) * z2 - type(x)(0.3153915652525201)
        b7 = bz * x
        b8 = a2 * c1
    b9 = zero
    b10 = zero
    b11 = zero
    b12 = zero
    b13 = zero
    b14 = zero
    b15 = zero
    if degree >= 3:
        c3 = type(x)(-2.285228997322329) * z2 + type(x)(0.4570457994644658)
        bz3 = type(x)(1.445305721320277) * z
        a3 = type(x)(-0.5900435899266435)
        c2 = x * c1 - y * s1
        s2 = x * s1 + y * c1
        b9 = a3 * s2
        b10 = bz3 * s1
        b11 = c3 * y
        b12 = z * (type(x)(1.865881662950577) * z2 - type(x)(1.119528997770346))
        b13 = c3 * x
        b14 = bz3 * c1
        b15 = a3 * c2
    return wp.vector(type(x)(0.28209479177387814), b1, b2, b3, b4, b5, b6, b7, b8, b9, b10, b11, b12, b13, b14, b15)


@wp.func
def sh_color(coeffs: wp.array2d(dtype=Any), n: int, degree: int, direction: Any):
    """Colour ``sum_k basis_k(d) * coeffs[n, k]`` (no +0.5 offset) for one Gaussian.

    Args:
        coeffs: SH coefficients, ``[N, K]`` of RGB vectors, ``K >= (degree+1)^2``.
        n: Gaussian index.
        degree: highest band evaluated, 0..3.
        direction: view direction (need not be normalised, must be non-zero), same scalar type.

    Returns:
        The RGB vector of the evaluated expansion.
    """
    basis = sh_basis(direction, degree)
    count = sh_count(degree)
    color = coeffs[n, 0] * basis[0]
    for k in range(1, wp.static(MAX_COEFFICIENTS)):
        if k < count:
            color = color + coeffs[n, k] * basis[k]
    return color


@wp.func
def sh_direction_gradient(direction: Any, degree: int, weights: Any):
    """Gradient with respect to ``direction`` (need not be normalised, must be non-zero) of
    ``sum_k weights[k] * basis_k(direction)`` over the bands up to ``degree`` (``weights``: a
    :data:`MAX_COEFFICIENTS` vector of the direction's scalar type; the constant band has no gradient).

    Written out by hand: the basis is a polynomial in the normalised direction ``d``, whose gradient ``g`` this
    sums; the normalisation then contributes ``(g - d (d . g)) / |direction|``."""
    length = wp.length(direction)
    d = direction / length
    x = d[0]
    y = d[1]
    z = d[2]
    zero = type(x)(0.0)
    two = type(x)(2.0)
    three = type(x)(3.0)
    gx = zero
    gy = zero
    gz = zero
    if degree >= 1:
        a1 = type(x)(-0.48860251190292)
        gx = a1 * weights[3]
        gy = a1 * weights[1]
        gz = -a1 * weights[2]
    if degree >= 2:
        a2 = two * type(x)(0.5462742152960395)
        k5 = type(x)(-1.092548430592079)
        gx = gx + a2 * (y * weights[4] + x * weights[8]) + k5 * z * weights[7]
        gy = gy + a2 * (x * weights[4] - y * weights[8]) + k5 * z * weights[5]
        gz = gz + k5 * (y * weights[5] + x * weights[7]) + two * type(x)(0.9461746957575601) * z * weights[6]
    if degree >= 3:
        a3 = type(x)(-0.5900435899266435)
        k10 = type(x)(1.445305721320277)
        k11 = type(x)(-2.285228997322329)
        c3 = k11 * z * z + type(x)(0.4570457994644658)
        c1 = x * x - y * y
        gx = gx + a3 * (two * three * x * y * weights[9] + three * c1 * weights[15]) + c3 * weights[13]
        gx = gx + two * k10 * z * (y * weights[10] + x * weights[14])
        gy = gy + a3 * (three * c1 * weights[9] - two * three * x * y * weights[15]) + c3 * weights[11]
        gy = gy + two * k10 * z * (x * weights[10] - y * weights[14])
        gz = gz + k10 * (two * x * y * weights[10] + c1 * weights[14])
        gz = gz + two * k11 * z * (y * weights[11] + x * weights[13])
        gz = gz + (three * type(x)(1.865881662950577) * z * z - type(x)(1.119528997770346)) * weights[12]
    g = wp.vector(gx, gy, gz)
    return (g - d * wp.dot(d, g)) / length
