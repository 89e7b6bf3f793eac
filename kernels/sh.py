"""Real spherical harmonics (degrees 0-3) as Warp functions, with gsplat's basis order and constants.

The basis is the one of gsplat 1.5.3 / the Inria 3DGS code (Sloan, "Efficient Spherical Harmonic
Evaluation", JCGT 2013): index ``k`` in ``0 .. (degree+1)^2 - 1``, constant term 0.28209479177387814.
Only the bands up to ``degree`` are evaluated; higher coefficients present in the array are ignored.
Written as straight-line code with branches on ``degree`` so Warp's automatic adjoint is exact.
"""

from __future__ import annotations

from typing import Any

import warp as wp


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
    d = wp.normalize(direction)
    x = d[0]
    y = d[1]
    z = d[2]
    color = coeffs[n, 0] * type(x)(0.28209479177387814)
    if degree >= 1:
        a1 = type(x)(-0.48860251190292)
        color = color + coeffs[n, 1] * (a1 * y) + coeffs[n, 2] * (-a1 * z) + coeffs[n, 3] * (a1 * x)
    if degree >= 2:
        z2 = z * z
        b2 = type(x)(-1.092548430592079) * z
        a2 = type(x)(0.5462742152960395)
        c1 = x * x - y * y
        s1 = type(x)(2.0) * x * y
        color = (
            color
            + coeffs[n, 4] * (a2 * s1)
            + coeffs[n, 5] * (b2 * y)
            + coeffs[n, 6] * (type(x)(0.9461746957575601) * z2 - type(x)(0.3153915652525201))
            + coeffs[n, 7] * (b2 * x)
            + coeffs[n, 8] * (a2 * c1)
        )
        if degree >= 3:
            c3 = type(x)(-2.285228997322329) * z2 + type(x)(0.4570457994644658)
            b3 = type(x)(1.445305721320277) * z
            a3 = type(x)(-0.5900435899266435)
            c2 = x * c1 - y * s1
            s2 = x * s1 + y * c1
            color = (
                color
                + coeffs[n, 9] * (a3 * s2)
                + coeffs[n, 10] * (b3 * s1)
                + coeffs[n, 11] * (c3 * y)
                + coeffs[n, 12] * (z * (type(x)(1.865881662950577) * z2 - type(x)(1.119528997770346)))
                + coeffs[n, 13] * (c3 * x)
                + coeffs[n, 14] * (b3 * c1)
                + coeffs[n, 15] * (a3 * c2)
            )
    return color
