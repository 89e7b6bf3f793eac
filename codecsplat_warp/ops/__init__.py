"""Torch-facing differentiable ops over the Warp kernels (CPU and CUDA, zero-copy).

* :mod:`.geometry`: :func:`unproject` (depth [V,H,W] -> world points [V,H,W,3]), :func:`reproject_average`
  (paper Eq. 3), :func:`plane_sweep_cost_volume`, and the view-selection helpers :func:`inverse_depth_candidates`,
  :func:`all_other_views`, :func:`nearest_views`;
* :mod:`.mvs`: :func:`mvs_depth` (posed images [V,3,H,W] -> semi-dense depth, mask, :class:`MVSDepth`) with its
  :class:`MVSConfig`, :func:`select_sources` (each view's source views, :class:`SourceViews`), and the windowed-NCC
  plane sweep :func:`photometric_cost_volume` with its :func:`window_ncc_features`;
* :mod:`.raster`: :func:`rasterize` (3D Gaussians -> images, gsplat's conventions, with a backward) and
  :func:`project_gaussians` (the projection step alone, -> :class:`ProjectedGaussians`), :class:`RasterMeta`;
  :func:`cpu_layout` picks how CPU calls composite (benchmarks and tests), :func:`forward_graphs` whether CUDA calls
  replay their forward from CUDA graphs, :func:`default_tile_size` the tile edge a call uses when given none.

Shapes, dtypes and units are in each function's docstring.
"""

from .geometry import (
    all_other_views, inverse_depth_candidates, nearest_views, plane_sweep_cost_volume, reproject_average, unproject,
)
from .mvs import (
    MVSConfig, MVSDepth, SourceViews, mvs_depth, photometric_cost_volume, select_sources, window_ncc_features,
)
from .raster import (
    ProjectedGaussians, RasterMeta, cpu_layout, default_tile_size, forward_graphs, project_gaussians, rasterize,
)

__all__ = [
    "all_other_views", "inverse_depth_candidates", "nearest_views", "plane_sweep_cost_volume", "reproject_average",
    "unproject", "MVSConfig", "MVSDepth", "SourceViews", "mvs_depth", "photometric_cost_volume", "select_sources",
    "window_ncc_features", "ProjectedGaussians",
    "RasterMeta", "cpu_layout", "default_tile_size", "forward_graphs", "project_gaussians", "rasterize",
]
