"""Leaving out decoded Gaussians that contribute nothing to the views they will be rendered into (issue 8).

A Gaussian contributes no pixel when

* its opacity is below :data:`OPACITY_THRESHOLD` (1/255, the rasterizer's alpha threshold: its alpha never
  reaches 1/255 anywhere, so compositing skips it), or
* the rasterizer's projection culls it for **every** target camera: camera depth outside the render's
  ``(near, far)``, or its opacity-aware bounding box (``min(3.33, sqrt(2 ln(255 o)))`` standard deviations,
  see :mod:`codecsplat_warp.kernels.raster_project`) entirely off the image.

The frustum test is the rasterizer's own projection stage (:func:`codecsplat_warp.ops.raster.project_gaussians`,
radius 0 = culled), so it cannot disagree with the renderer beyond float32 rounding, and the rounding is
covered so that pruning never drops a Gaussian the renderer would draw, whatever cameras it renders together:

* the renderer works relative to the mean centre of the cameras of each call, so the camera depth it computes
  differs from the pruning pass's by a few float32 ulps of the distances involved. The depth range of the
  test is widened by :func:`depth_rounding_bound` (16 ulps of the largest such distance) on both sides;
* off-image culling is safe under rounding without a margin: a box edge lies where the Gaussian's alpha is
  below 1/255, and the nearest pixel centre beyond it lies half a pixel further, where the compositor
  skips it too.

When the rounding bound is not small against the near plane (a scene ``~10^5`` times larger than its near
distance), the frustum test is skipped rather than trusted: nothing but transparent Gaussians is pruned.

Pruned and unpruned Gaussians render the same images: the kept Gaussians keep their order, and the
rasterizer's depth sort is stable, so the composited rows are the same rows in the same order.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch

from ..cameras import Cameras
from ..gaussians import Gaussians
from ..kernels.raster_row import ALPHA_THRESHOLD
from ..ops.raster import project_gaussians
from .culling import render_depth_range

OPACITY_THRESHOLD = ALPHA_THRESHOLD
"""Gaussians with an opacity below this (1/255) contribute nothing visible: the rasterizer skips them."""

DEPTH_ROUNDING_ULPS = 16
"""The depth range of the frustum test is widened by this many float32 ulps of the scene's largest distance."""

ROWS_PER_PROJECTION = 1 << 22
"""(camera, Gaussian) pairs projected per call (about 230 MiB of projected rows); cameras go in chunks."""

_FLOAT32_EPS = float(torch.finfo(torch.float32).eps)


@dataclass(frozen=True)
class PruneReport:
    """How many Gaussians :func:`prune_gaussians` left out and why.

    Attributes:
        total: Gaussians given.
        transparent: left out for an opacity below :data:`OPACITY_THRESHOLD`.
        outside_frusta: left out (of the opaque ones) for being culled by every target camera.
        kept: Gaussians returned (``total - transparent - outside_frusta``).
    """

    total: int
    transparent: int
    outside_frusta: int
    kept: int

    @property
    def pruned(self) -> int:
        """Gaussians left out for either reason."""
        return self.transparent + self.outside_frusta

    def to_dict(self) -> dict[str, int]:
        """The counts as a JSON-able dict (``pruned`` included)."""
        return {**asdict(self), "pruned": self.pruned}


def prune_gaussians(gaussians: Gaussians, cameras: Cameras | None = None,
                    depth_range: tuple[float, float] | None = None) -> tuple[Gaussians, PruneReport]:
    """The Gaussians that contribute a pixel to some target view, and a :class:`PruneReport`.

    Args:
        gaussians: N Gaussians (any float dtype, on any device; the test runs in float32 like
            :meth:`CodecSplat.render`).
        cameras: the V target cameras the result will be rendered into (any subsets, any batching), on the
            Gaussians' device; None prunes by opacity only.
        depth_range: (near, far) the renderer culls camera depth with; None uses
            :func:`~codecsplat_warp.model.culling.render_depth_range` of ``cameras`` (what
            :meth:`CodecSplat.render` uses, also for any subset of the cameras).

    Returns:
        (kept Gaussians, same dtype and device, in their original order; the report).

    Raises:
        DeviceMismatchError: cameras and Gaussians on different devices.
        InputError: non-finite Gaussians or cameras (as the rasterizer).
    """
    opaque, transparent = prune_transparent(gaussians)
    if cameras is None or len(opaque) == 0:
        return opaque, PruneReport(len(gaussians), transparent, 0, len(opaque))
    near, far = depth_range if depth_range is not None else render_depth_range(cameras.to(dtype=torch.float32))
    seen = seen_by_any_camera(opaque, cameras, near, far)
    kept = _select(opaque, seen)
    return kept, PruneReport(len(gaussians), transparent, len(opaque) - len(kept), len(kept))


def prune_transparent(gaussians: Gaussians, threshold: float = OPACITY_THRESHOLD) -> tuple[Gaussians, int]:
    """The Gaussians whose opacity is at least ``threshold`` (default 1/255), and how many were left out.

    Opacities are compared in float32, as :meth:`CodecSplat.render` rasterizes them."""
    kept = _select(gaussians, gaussians.opacities.float() >= threshold)
    return kept, len(gaussians) - len(kept)


def seen_by_any_camera(gaussians: Gaussians, cameras: Cameras, near: float, far: float) -> torch.Tensor:
    """bool [N]: whether the rasterizer's projection keeps each Gaussian for at least one camera.

    Depths are tested against ``(near, far)`` widened by :func:`depth_rounding_bound`; if that bound is
    not below half of ``near``, every Gaussian counts as seen (see the module docstring).
    """
    slack = depth_rounding_bound(gaussians.means, cameras)
    if not slack < 0.5 * near:
        return torch.ones(len(gaussians), dtype=torch.bool, device=gaussians.means.device)
    means = gaussians.means.detach().float()
    quats, scales = gaussians.quats.detach().float(), gaussians.scales.detach().float()
    opacities = gaussians.opacities.detach().float()
    colors = means.new_zeros(len(gaussians), 3)  # colour plays no part in culling
    cams = cameras.to(dtype=torch.float32)
    seen = torch.zeros(len(gaussians), dtype=torch.bool, device=means.device)
    step = max(1, ROWS_PER_PROJECTION // len(gaussians))
    with torch.no_grad():
        for first in range(0, cams.num_views, step):
            chunk = cams.select(slice(first, first + step))
            projected = project_gaussians(means, quats, scales, opacities, colors, chunk.w2c, chunk.K, cams.width,
                                          cams.height, near=near - slack, far=far + slack)
            seen |= (projected.radii > 0).any(dim=-1).any(dim=0)
    return seen


def depth_rounding_bound(means: torch.Tensor, cameras: Cameras) -> float:
    """A bound on how far two float32 evaluations of a camera depth can differ (world units).

    The rasterizer computes camera depth relative to the mean centre ``o`` of the cameras it renders
    together; ``o`` lies within the target cameras' centres, so the distances entering the float32 sum are
    at most ``max |x - c| + 3 max |C - c|`` (``c`` the mean target centre, ``x`` a mean ``[N,3]``, ``C`` a
    camera centre). Returns :data:`DEPTH_ROUNDING_ULPS` float32 ulps of that distance.
    """
    centres = cameras.centers.detach().double()
    middle = centres.mean(dim=0)
    spread = float((centres - middle).norm(dim=-1).max())
    reach = float((means.detach().double() - middle.to(means.device)).norm(dim=-1).max()) if len(means) else 0.0
    return DEPTH_ROUNDING_ULPS * _FLOAT32_EPS * (reach + 3.0 * spread)


def _select(gaussians: Gaussians, keep: torch.Tensor) -> Gaussians:
    """The Gaussians where the bool mask ``keep`` [N] is set, in their order."""
    index = keep.nonzero()[:, 0]
    return Gaussians(*(t.index_select(0, index) for t in (gaussians.means, gaussians.quats, gaussians.scales,
                                                          gaussians.opacities, gaussians.sh)))
