"""Where a projected Gaussian can reach: the power beyond which it adds nothing, and which tiles hold a pixel it
may reach.

The compositing skips a row at a pixel where its alpha ``opacity * exp(-power)`` is below
:data:`.raster_row.ALPHA_THRESHOLD`. Two bounds follow from that, shared by the tile binning
(:mod:`.raster_tiles`: a Gaussian is binned only into the tiles it may reach) and the CPU compositing
(:mod:`.raster_composite_cpu`: a row is listed only on the lines it may reach):

* Skip power: ``S = log(ALPHA_LEVELS * opacity) + SKIP_MARGIN``. Beyond it ``opacity * exp(-power) <=
  exp(-SKIP_MARGIN) / 255``: alpha is below the threshold by a margin far larger than the rounding of ``exp``
  (fast-math ``exp`` on CUDA included), ``log`` and the product.
* Reach power: the power a kernel computes, ``0.5 (a dx^2 + c dy^2) + b dx dy`` in the row's dtype, differs from the
  exact quadratic by at most ``g k`` times itself, where ``k`` is the condition number of the conic and ``g`` bounds
  the relative rounding (:data:`POWER_ROUNDING`). So every pixel where the computed power is at most ``S`` has an
  exact power of at most ``R = S (1 + 4 g k) + g`` (:func:`reach_power`), evaluated in float64. A conic too
  ill-conditioned for that (``g k > MAX_CONDITIONED``) or not positive definite gets ``R = +inf``: it reaches every
  pixel of its bounding box.

A tile is reached when the exact quadratic's minimum over the rectangle spanned by the tile's pixel centres is at
most ``R`` (:func:`tile_reached`, in float64, with the row's conic prepared once by :func:`reach_conic`). Tiles
that fail the test hold no pixel where the row's alpha reaches the threshold, so leaving the row out of them changes
no render and no gradient; it leaves out the corners of the bounding box of a tilted or elongated Gaussian (about a
fifth of the intersections of the shipped model's Gaussians, 8 views at 256x448).
"""

from __future__ import annotations

from typing import Any

import warp as wp

from .raster_row import ALPHA_LEVELS

SKIP_MARGIN = 1.0 / 1024.0
"""Margin of the skip power above ``log(ALPHA_LEVELS * opacity)`` (see the module docstring): a skipped row's alpha
is at most ``exp(-1/1024) = 0.99902`` times the threshold, where float rounding moves it by about 1e-6."""

POWER_ROUNDING = {"float32": 1.0e-6, "float64": 1.0e-12}
"""Bound ``g`` on the relative rounding error of the kernel's power ``0.5 (a dx^2 + c dy^2) + b dx dy`` in each dtype,
relative to ``0.5 a dx^2 + 0.5 c dy^2 + |b dx dy|`` (about 16 units in the last place; float64 is given more, so
that it also covers the float64 rounding of the tests that use it)."""

MAX_CONDITIONED = 0.1
"""Largest ``g k`` (rounding bound times conic condition number) for which a row gets a finite reach power; rows
beyond reach every pixel of their bounding box (about 1e5 for float32: a Gaussian over 300 times longer than wide
on screen)."""


@wp.func
def skip_power(opacity: Any):
    """Power above which a row of this opacity has alpha below :data:`.raster_row.ALPHA_THRESHOLD` for certain."""
    return wp.log(type(opacity)(ALPHA_LEVELS) * opacity) + type(opacity)(SKIP_MARGIN)


@wp.func
def reach_power(a: Any, b: Any, c: Any, skip: Any, rounding: wp.float64):
    """The exact power (float64) below which every pixel lies where a row of conic ``(a, b, c)`` and skip power
    ``skip`` may be composited (see the module docstring), or +inf when the conic is too ill-conditioned."""
    a64 = wp.float64(a)
    b64 = wp.float64(b)
    c64 = wp.float64(c)
    det = a64 * c64 - b64 * b64
    if not (a64 > wp.float64(0.0) and det > wp.float64(0.0)):
        return wp.float64(wp.inf)
    largest = wp.float64(0.5) * (a64 + c64) + wp.sqrt(wp.float64(0.25) * (a64 - c64) * (a64 - c64) + b64 * b64)
    spread = rounding * largest * largest / det  # g k
    if spread > wp.float64(MAX_CONDITIONED):
        return wp.float64(wp.inf)
    return wp.float64(skip) * (wp.float64(1.0) + wp.float64(4.0) * spread) + rounding


@wp.struct
class ReachConic:
    """A row's conic in float64, with the reciprocals of its diagonal, and its reach power (:func:`reach_conic`):
    what :func:`tile_reached` tests every tile of the row's rectangle with."""

    a: wp.float64
    b: wp.float64
    c: wp.float64
    inverse_a: wp.float64
    inverse_c: wp.float64
    reach: wp.float64


@wp.func
def reach_conic(a: Any, b: Any, c: Any, reach: wp.float64):
    """The :class:`ReachConic` of a row with conic ``(a, b, c)`` and reach power ``reach`` (:func:`reach_power`;
    a finite reach implies ``a, c > 0``)."""
    conic = ReachConic()
    conic.a = wp.float64(a)
    conic.b = wp.float64(b)
    conic.c = wp.float64(c)
    conic.reach = reach
    conic.inverse_a = wp.float64(0.0)
    conic.inverse_c = wp.float64(0.0)
    if wp.isfinite(reach):
        conic.inverse_a = wp.float64(1.0) / conic.a
        conic.inverse_c = wp.float64(1.0) / conic.c
    return conic


@wp.func
def edge_minimum(a: wp.float64, b: wp.float64, c: wp.float64, inverse_a: wp.float64, low: wp.float64,
                 high: wp.float64, v: wp.float64):  # fmt: skip
    """Minimum over ``u`` in ``[low, high]`` of ``0.5 (a u^2 + c v^2) + b u v`` (``a > 0``, ``inverse_a = 1 / a``)."""
    u = wp.clamp(-b * v * inverse_a, low, high)
    return wp.float64(0.5) * (a * u * u + c * v * v) + b * u * v


@wp.func
def tile_reached(mean_x: Any, mean_y: Any, conic: ReachConic, tx: int, ty: int, tile_size: int, width: int,
                 height: int):  # fmt: skip
    """Whether tile ``(tx, ty)`` of a ``width`` x ``height`` image holds a pixel centre where the exact power of the
    row (mean in pixels, :func:`reach_conic`) is at most its reach power; always for an infinite reach. The test
    takes the quadratic's minimum over the rectangle of the tile's pixel centres; first, as a shortcut, its value at
    the rectangle's point nearest the mean (at most ``reach`` there: reached)."""
    if not wp.isfinite(conic.reach):
        return True
    half = wp.float64(0.5)
    left = wp.float64(tx * tile_size) + half - wp.float64(mean_x)
    right = wp.float64(wp.min((tx + 1) * tile_size, width)) - half - wp.float64(mean_x)
    top = wp.float64(ty * tile_size) + half - wp.float64(mean_y)
    bottom = wp.float64(wp.min((ty + 1) * tile_size, height)) - half - wp.float64(mean_y)
    zero = wp.float64(0.0)
    a = conic.a
    b = conic.b
    c = conic.c
    u = wp.clamp(zero, left, right)
    v = wp.clamp(zero, top, bottom)
    if half * (a * u * u + c * v * v) + b * u * v <= conic.reach:
        return True
    lowest = wp.min(edge_minimum(a, b, c, conic.inverse_a, left, right, top),
                    edge_minimum(a, b, c, conic.inverse_a, left, right, bottom))  # fmt: skip
    lowest = wp.min(lowest, edge_minimum(c, b, a, conic.inverse_c, top, bottom, left))
    lowest = wp.min(lowest, edge_minimum(c, b, a, conic.inverse_c, top, bottom, right))
    return lowest <= conic.reach


@wp.func
def row_reach(opacity: Any, a: Any, b: Any, c: Any, rounding: wp.float64):
    """:func:`reach_power` of a row from its opacity and conic."""
    return reach_power(a, b, c, skip_power(opacity), rounding)
