"""Torch-facing differentiable ops over the Warp kernels (CPU and CUDA, zero-copy).

* :mod:`.geometry`: :func:`unproject` (depth [V,H,W] -> world points [V,H,W,3]), :func:`reproject_average`
  (paper Eq. 3), :func:`plane_sweep_cost_volume`, and the view-selection helpers :func:`inverse_depth_candidates`,
  :func:`all_other_views`, :func:`nearest_views`;
* :mod:`.mvs`: :func:`mvs_depth` (posed images [V,3,H,W] -> semi-dense depth, mask, :class:`MVSDepth`) with its
  :class:`MVSConfig`, and :func:`select_sources` (each view's source views, :class:`SourceViews`);
* :mod:`.raster`: :func:`rasterize` (3D Gaussians -> images, gsplat's conventions, with a backward) and
  :func:`project_gaussians` (the projection step alone, -> :class:`ProjectedGaussians`), :class:`RasterMeta`;
  :func:`cpu_layout` picks how CPU calls composite (benchmarks and tests).

Shapes, dtypes and units are in each function's docstring.
"""

from .geometry import (
    all_other_views, inverse_depth_candidates, nearest_views, plane_sweep_cost_volume, reproject_average, unproject,
)
from .mvs import MVSConfig, MVSDepth, SourceViews, mvs_depth, select_sources
from .raster import ProjectedGaussians, RasterMeta, cpu_layout, project_gaussians, rasterize

__all__ = [
    "all_other_views", "inverse_depth_candidates", "nearest_views", "plane_sweep_cost_volume", "reproject_average",
    "unproject", "MVSConfig", "MVSDepth", "SourceViews", "mvs_depth", "select_sources", "ProjectedGaussians",
    "RasterMeta", "cpu_layout", "project_gaussians", "rasterize",
]
