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

# The basis's constants (Python floats: a kernel casts them to its scalar type, float64 without loss).
_BAND0 = 0.28209479177387814
_BAND1 = -0.48860251190292  # basis 1, 2, 3: _BAND1 y, -_BAND1 z, _BAND1 x
_BAND2_XY = 0.5462742152960395  # basis 4 and 8: _BAND2_XY 2xy, _BAND2_XY (x^2 - y^2)
_BAND2_Z = -1.092548430592079  # basis 5 and 7: _BAND2_Z z y, _BAND2_Z z x
_BAND2_ZZ = 0.9461746957575601  # basis 6: _BAND2_ZZ z^2 - _BAND2_ONE
_BAND2_ONE = 0.3153915652525201
_BAND3_A = -0.5900435899266435  # basis 9 and 15: _BAND3_A (3x^2 y - y^3), _BAND3_A (x^3 - 3xy^2)
_BAND3_B = 1.445305721320277  # basis 10 and 14: _BAND3_B z 2xy, _BAND3_B z (x^2 - y^2)
_BAND3_ZZ = -2.285228997322329  # basis 11 and 13: (_BAND3_ZZ z^2 + _BAND3_ONE) y, the same times x
_BAND3_ONE = 0.4570457994644658
_BAND3_ZZZ = 1.865881662950577  # basis 12: z (_BAND3_ZZZ z^2 + _BAND3_Z)
_BAND3_Z = -1.119528997770346


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
        a1 = type(x)(_BAND1)
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
        bz = type(x)(_BAND2_Z) * z
        a2 = type(x)(_BAND2_XY)
        b4 = a2 * s1
        b5 = bz * y
        b6 = type(x)(_BAND2_ZZ) * z2 - type(x)(_BAND2_ONE)
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
        c3 = type(x)(_BAND3_ZZ) * z2 + type(x)(_BAND3_ONE)
        bz3 = type(x)(_BAND3_B) * z
        a3 = type(x)(_BAND3_A)
        c2 = x * c1 - y * s1
        s2 = x * s1 + y * c1
        b9 = a3 * s2
        b10 = bz3 * s1
        b11 = c3 * y
        b12 = z * (type(x)(_BAND3_ZZZ) * z2 + type(x)(_BAND3_Z))
        b13 = c3 * x
        b14 = bz3 * c1
        b15 = a3 * c2
    return wp.vector(type(x)(_BAND0), b1, b2, b3, b4, b5, b6, b7, b8, b9, b10, b11, b12, b13, b14, b15)


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
        a1 = type(x)(_BAND1)
        gx = a1 * weights[3]
        gy = a1 * weights[1]
        gz = -a1 * weights[2]
    if degree >= 2:
        a2 = two * type(x)(_BAND2_XY)
        k5 = type(x)(_BAND2_Z)
        gx = gx + a2 * (y * weights[4] + x * weights[8]) + k5 * z * weights[7]
        gy = gy + a2 * (x * weights[4] - y * weights[8]) + k5 * z * weights[5]
        gz = gz + k5 * (y * weights[5] + x * weights[7]) + two * type(x)(_BAND2_ZZ) * z * weights[6]
    if degree >= 3:
        a3 = type(x)(_BAND3_A)
        k10 = type(x)(_BAND3_B)
        k11 = type(x)(_BAND3_ZZ)
        c3 = k11 * z * z + type(x)(_BAND3_ONE)
        c1 = x * x - y * y
        gx = gx + a3 * (two * three * x * y * weights[9] + three * c1 * weights[15]) + c3 * weights[13]
        gx = gx + two * k10 * z * (y * weights[10] + x * weights[14])
        gy = gy + a3 * (three * c1 * weights[9] - two * three * x * y * weights[15]) + c3 * weights[11]
        gy = gy + two * k10 * z * (x * weights[10] - y * weights[14])
        gz = gz + k10 * (two * x * y * weights[10] + c1 * weights[14])
        gz = gz + two * k11 * z * (y * weights[11] + x * weights[13])
        gz = gz + (three * type(x)(_BAND3_ZZZ) * z * z + type(x)(_BAND3_Z)) * weights[12]
    g = wp.vector(gx, gy, gz)
    return (g - d * wp.dot(d, g)) / length
