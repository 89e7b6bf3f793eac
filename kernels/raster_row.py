"""The projected row: the record the rasterizer's stages hand on, and the alpha threshold they share.

The projection (:mod:`.raster_project`) writes one row of :data:`ROW_WIDTH` scalars (the Gaussians' float dtype)
per (camera, Gaussian); the tile binning (:mod:`.raster_tiles`) reads its position and depth, and the compositing
(:mod:`.raster_composite`) stages whole rows in shared memory. Columns:

    0, 1  MEAN_X, MEAN_Y               mean2d (pixels)
    2..4  CONIC_A, CONIC_B, CONIC_C    conic of the blurred 2D covariance: power = 0.5 (a dx^2 + c dy^2) + b dx dy
    5     OPACITY                      opacity (times the antialiasing compensation in antialiased mode)
    6..8  RED, GREEN, BLUE             colour (SH evaluated towards the Gaussian, + 0.5, clamped at 0; or the given RGB)
    9     DEPTH                        camera-space depth z (the last column)

Plain Python numbers (no Warp, no torch): the kernels read them as compile-time constants.
"""

ROW_WIDTH = 10
"""Scalars per projected row."""

MEAN_X, MEAN_Y = 0, 1
CONIC_A, CONIC_B, CONIC_C = 2, 3, 4
OPACITY = 5
RED, GREEN, BLUE = 6, 7, 8
DEPTH = 9
"""Columns of the projected row (see the module docstring); depth is the last one."""

ALPHA_LEVELS = 255.0
"""The alpha threshold is one level of 8-bit alpha, ``1 / ALPHA_LEVELS``; a Gaussian's opacity-aware extent,
``sqrt(2 ln(ALPHA_LEVELS * opacity))`` standard deviations, is where its alpha falls to it."""

ALPHA_THRESHOLD = 1.0 / ALPHA_LEVELS
"""Opacity/alpha below which a Gaussian contributes nothing (gsplat's ALPHA_THRESHOLD, 1/255): the projection culls
a Gaussian whose opacity is below it, and the compositing skips a row whose alpha at a pixel is below it."""

MAX_ALPHA = 0.999
"""Largest alpha one Gaussian takes at a pixel (gsplat's clamp), so that transmittance never reaches zero."""
