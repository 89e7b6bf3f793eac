"""The camera depth range outside which :meth:`~codecsplat_warp.model.CodecSplat.render` culls Gaussians."""

from __future__ import annotations

from ..cameras import Cameras

RENDER_NEAR_FRACTION = 0.5
"""Gaussians closer to a target camera than this fraction of its near bound are culled by the renderer."""

RENDER_FAR_FACTOR = 2.0
"""... and those farther than this multiple of its far bound."""


def render_depth_range(cameras: Cameras) -> tuple[float, float]:
    """(near, far) camera depth range :meth:`CodecSplat.render` culls with for target ``cameras``:
    :data:`RENDER_NEAR_FRACTION` x their smallest near and :data:`RENDER_FAR_FACTOR` x their largest far
    (world units). The range of any subset of the cameras lies inside it. Reads the bounds on the host."""
    return float(cameras.near.min()) * RENDER_NEAR_FRACTION, float(cameras.far.max()) * RENDER_FAR_FACTOR
