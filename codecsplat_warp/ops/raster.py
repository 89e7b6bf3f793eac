"""Differentiable 3D Gaussian splat rasterization on Warp kernels (CPU and CUDA), close to gsplat's API.

Pipeline (one kernel family per stage, see ``codecsplat_warp.kernels.raster_*``), all inside one autograd
Function (or, when nothing needs a gradient, called without one) so that a call costs few host operations:

1. Camera preparation on one thread: validation flags of the cameras and background, the cameras cast to the
   Gaussians' dtype and made camera-relative (float32: the world is translated by the mean camera centre,
   composed in float64, so that a scene far from the world origin keeps its precision).
2. EWA projection, one thread per (camera, Gaussian): a packed row ``[x, y, conic(3), opacity, rgb, depth]``,
   pixel radii, tiles touched and input-validation flags.
3. Prefix sum of the tile counts; ONE host read of the intersection count and the flags (adjacent in one
   int64 buffer), then the memory budget is checked before buffers of the count's size are allocated (the guessed
   buffers of step 4 are cut to the budget).
4. One key ``[camera | tile | depth]`` per intersection, 32 bits when the call's depth range allows, else 64 (the
   layout is computed on the device, see :mod:`codecsplat_warp.kernels.raster_tiles`); Warp's radix sort
   (:func:`~codecsplat_warp.ops.primitives.radix_sort_pairs`) on the used bits only, per-tile ranges from the
   sorted keys.
   On CUDA, a call with the shape of an earlier one emits, sorts and composites *before* the host read, into
   buffers of a capacity guessed from that call (:class:`_Speculation`), so that neither the GPU nor the host waits
   for the other around the read; when the read shows the guess too small (or the key too wide), the keys are
   emitted, sorted and composited again into buffers of the exact size. Either way the sorted order, and so the
   render, is the same.
5. Front-to-back compositing per tile (expected depth normalised in the kernel), and a hand-written back-to-front
   backward. On CUDA a block of lanes per tile stages its rows in shared memory
   (:mod:`~codecsplat_warp.kernels.raster_composite`); on the CPU one thread per tile reads them in place, 16
   pixels of a line at a time, the tiles split over :func:`~codecsplat_warp.device.cpu_threads` threads
   (:mod:`~codecsplat_warp.kernels.raster_composite_cpu`, see :data:`CPU_LAYOUTS`), with the same results on any
   number of threads. Projection gradients come from an adjoint launch of its straight-line twin kernel.

On CUDA, once a call shape has a guess, stages 1 to 5 of its calls are replayed from a CUDA graph
(:class:`_ForwardGraph`, see :func:`forward_graphs`): the inputs are copied into the graph's, and the results out.

Gradients flow to ``means``, ``quats``, ``scales``, ``opacities``, ``colors`` (RGB or SH) and
``background``. ``viewmats`` and ``Ks`` are **not** differentiated (their gradient is None).
"""

from __future__ import annotations

import collections
import contextlib
import functools
import math
import numbers
import os
import threading
import warnings
from dataclasses import dataclass
from typing import Iterator, NamedTuple

import torch

from ..checks import FLOAT_DTYPES, check_finite, check_tensor, common_device, validation_enabled
from ..device import (
    PinnedRead, cpu_threads, cuda_graph_capture, launch, matrices, stage_host_values, vectors, warp_capture, warp_dtype,
    warp_scope,
)  # fmt: skip
from ..errors import InputError, RasterMemoryError
from ..kernels import raster_composite, raster_composite_cpu, raster_project, raster_reach, raster_row, raster_tiles
from .primitives import inclusive_scan, radix_sort_pairs, row_chunks, run_concurrently, weighted_chunks

_LOW_PRECISION = (torch.float16, torch.bfloat16)

DEFAULT_MAX_INTERSECTION_BYTES = 4 << 30
"""Default budget for the intersection sort buffers (keys and values, double-buffered): 4 GiB."""

LOW_PASS_PX2 = 0.3
"""Screen-space low-pass blur added to the 2D covariance diagonal, in px^2 (gsplat's eps2d)."""

DEFAULT_MIN_TRANSMITTANCE = 1e-4
"""A pixel stops compositing before the row that would take its transmittance to this or below (gsplat's)."""

MODES = ("classic", "antialiased")

GAUSSIAN_ARGUMENTS = ("means", "quats", "scales", "opacities", "colors")
"""The names of :func:`rasterize`'s per-Gaussian arguments, in order (the differentiable inputs besides the
background)."""

_ARGUMENT_OF_FLAG = {
    raster_project.BAD_MEANS: "means",
    raster_project.BAD_QUATS: "quats",
    raster_project.BAD_SCALES: "scales",
    raster_project.BAD_OPACITIES: "opacities",
    raster_project.BAD_COLORS: "colors",
    raster_project.BAD_VIEWMATS: "viewmats",
    raster_project.BAD_KS: "Ks",
    raster_project.BAD_BACKGROUND: "background",
}
_CAMERA_FLAGS = (raster_project.BAD_VIEWMATS, raster_project.BAD_KS, raster_project.BAD_BACKGROUND)
"""Flags that count non-finite values (the others count Gaussians)."""


# --------------------------------------------------------------------------------------------------
# Public ops
def rasterize(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    near: float = 0.01,
    far: float = 1e10,
    background: torch.Tensor | None = None,
    mode: str = "classic",
    sh_degree: int | None = None,
    render_depth: bool = True,
    tile_size: int | None = None,
    max_intersection_bytes: int = DEFAULT_MAX_INTERSECTION_BYTES,
    min_transmittance: float = DEFAULT_MIN_TRANSMITTANCE,
    leave_out: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor, RasterMeta]:
    """Render N 3D Gaussians into B pinhole cameras (differentiable, gsplat-compatible conventions).

    Args:
        means: ``[N,3]`` world positions.
        quats: ``[N,4]`` rotations as (w, x, y, z), need not be normalised (a zero quaternion is an error).
        scales: ``[N,3]`` standard deviations along the rotated axes (world units, >= 0).
        opacities: ``[N]`` in [0, 1].
        colors: ``[N,3]`` RGB, or ``[N,K,3]`` SH coefficients; SH colour is ``max(SH(dir) + 0.5, 0)`` with
            ``dir`` from the camera centre to the mean (gsplat's convention).
        viewmats: ``[B,4,4]`` world-to-camera (OpenCV axes). Not differentiated.
        Ks: ``[B,3,3]`` intrinsics in pixels, pixel centres at +0.5. Not differentiated.
        width, height: image size in pixels (any size >= 1).
        near, far: Gaussians with camera depth outside ``(near, far)`` are culled.
        background: ``[B,3]`` colour behind the splats, or None (black, no gradient).
        mode: ``"classic"`` or ``"antialiased"`` (opacity times ``sqrt(det(cov2d) / det(cov2d + 0.3 I))``).
        sh_degree: SH degree 0..3 to evaluate (SH colours only); None uses ``sqrt(K) - 1``.
        render_depth: also render expected depth ``sum w z / max(alpha, 1e-10)``; False skips that work.
        tile_size: tile edge in pixels (1..32); None: :func:`default_tile_size` of the inputs' device (8 on CUDA,
            16 on the CPU).
        max_intersection_bytes: budget for the intersection sort buffers (16 bytes per intersection with 32-bit
            sort keys, 24 with 64-bit ones; see :class:`SortKey`). On CUDA a call may hold sort buffers for up to
            1/8 more intersections than it has (see :class:`_Speculation`), never more than this budget.
        min_transmittance: early stop, in [0, 1): a pixel stops compositing before the first Gaussian that
            would take its transmittance ``T`` to this value or below (gsplat's 1e-4 by default). Larger
            values skip more of the hidden Gaussians (faster, a larger error against an exact render);
            0 composites every Gaussian until ``T`` underflows, where the backward, which rebuilds ``T`` by
            division from the final ``T``, loses accuracy behind nearly opaque stacks.
        leave_out: ``[B,2]`` integer: camera b renders without the Gaussians ``leave_out[b,0] <= n <
            leave_out[b,1]`` (an empty range leaves out none), e.g. each view predicted from the other views'
            pixel-aligned Gaussians in one call; None: every camera renders every Gaussian.

    Returns:
        ``(rgb [B,H,W,3], depth [B,H,W,1] or None, alpha [B,H,W,1], meta)`` in the dtype of ``means``
        (float32 or float64); see :class:`RasterMeta`.

    Raises:
        InputError: bad shape, dtype, mode, degree, size or threshold; NaN/Inf in any input; zero quaternion.
        DeviceMismatchError: inputs on different devices.
        RasterMemoryError: the intersections would need more than ``max_intersection_bytes``.
    """
    means, quats, scales, opacities, colors, viewmats, Ks, background, settings = _prepare(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height, near, far, background, mode,
        sh_degree, render_depth, tile_size, min_transmittance,
    )  # fmt: skip
    leave_out = _leave_out_ranges(leave_out, viewmats, means)
    if means.shape[0] == 0 or viewmats.shape[0] == 0:
        for name, tensor in (("viewmats", viewmats), ("Ks", Ks), ("background", background)):
            if tensor is not None:
                check_finite(name, tensor)
        return _empty_render(means, viewmats, background, settings)
    inputs = (means, quats, scales, opacities, colors, background, viewmats, Ks, leave_out, settings,
              max_intersection_bytes)
    if torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in inputs[:6]):
        color, depth, alpha, radii, count = _Rasterize.apply(*inputs)
    else:  # nothing to differentiate: no autograd bookkeeping
        color, depth, alpha, radii, count = _render(*inputs)[0]
    return color, depth, alpha, RasterMeta(radii, count, settings.tile_size)


@dataclass(frozen=True)
class RasterMeta:
    """Side outputs of :func:`rasterize`.

    Attributes:
        radii: ``[B, N, 2]`` int32 pixel half-extents (x, y) of each Gaussian's box per camera; 0 = culled.
        intersection_count: number of (camera, Gaussian, tile) intersections that were sorted.
        tile_size: tile edge in pixels.
        visible_counts: ``[B]`` int64 number of Gaussians with non-zero radii per camera (computed from
            ``radii`` on first access).
    """

    radii: torch.Tensor
    intersection_count: int
    tile_size: int

    @functools.cached_property
    def visible_counts(self) -> torch.Tensor:
        return (self.radii > 0).any(dim=-1).sum(dim=1)


def project_gaussians(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    near: float = 0.01,
    far: float = 1e10,
    mode: str = "classic",
    sh_degree: int | None = None,
) -> ProjectedGaussians:
    """The projection stage of :func:`rasterize` alone (same arguments, same checks and errors)."""
    means, quats, scales, opacities, colors, viewmats, Ks, _, settings = _prepare(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height, near, far, None, mode,
        sh_degree, True, 16, DEFAULT_MIN_TRANSMITTANCE,
    )  # fmt: skip
    coeffs = _sh_coefficients(colors)
    splats, radii, flags = _ProjectGaussians.apply(means, quats, scales, opacities, coeffs, viewmats, Ks, settings)
    if validation_enabled() and means.shape[0]:
        _raise_on_flags(flags.tolist())
    return ProjectedGaussians(
        means2d=splats[..., raster_row.MEAN_X : raster_row.MEAN_Y + 1],
        conics=splats[..., raster_row.CONIC_A : raster_row.CONIC_C + 1],
        opacities=splats[..., raster_row.OPACITY],
        colors=splats[..., raster_row.RED : raster_row.BLUE + 1],
        depths=splats[..., raster_row.DEPTH],
        radii=radii,
    )


@dataclass(frozen=True)
class ProjectedGaussians:
    """Per-camera 2D Gaussians (differentiable w.r.t. the 3D parameters); culled entries are zero.

    Attributes:
        means2d: ``[B,N,2]`` pixel positions; conics: ``[B,N,3]`` (a, b, c) of the inverse blurred 2D
        covariance; opacities: ``[B,N]`` (compensated in antialiased mode); colors: ``[B,N,3]``;
        depths: ``[B,N]`` camera z; radii: ``[B,N,2]`` int32 (0 = culled).
    """

    means2d: torch.Tensor
    conics: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor
    depths: torch.Tensor
    radii: torch.Tensor


# --------------------------------------------------------------------------------------------------
# Argument checks and the settings of a call
class _Settings(NamedTuple):
    """The checked settings of one call, and the tile grid they imply.

    Attributes:
        width, height: image size in pixels; near, far: depth range; sh_degree: -1 for RGB colours;
        antialiased, render_depth: flags; tile_size: tile edge in pixels; min_transmittance: early-stop threshold;
        tiles_x, tiles_y: tiles per image row and column.
    """

    width: int
    height: int
    near: float
    far: float
    sh_degree: int
    antialiased: bool
    render_depth: bool
    tile_size: int
    min_transmittance: float
    tiles_x: int
    tiles_y: int


CUDA_TILE_SIZE = 8
"""Tile edge of a CUDA call by default. Against 16 (H200, ``bench raster``'s workloads, interleaved, 2026-11-28): the
compositing kernels take about half the time (a pixel walks only the Gaussians that reach its 8x8 tile: backward 463
→ 272 us at RE10K, 783 → 433 us at DL3DV; a one-image call also fills the GPU with four times the blocks), the
sort about twice (more intersections), forward+backward 1.57 → 1.41 ms and 2.29 → 1.96 ms; 32 was slower."""

CPU_TILE_SIZE = 16
"""Tile edge of a CPU call by default (the tile layout's lines are tuned for it, see :data:`CPU_LAYOUTS`; 8 was
slower there: 733 against 692 ms forward+backward at the RE10K workload on the 2-core EPYC, 2026-11-28)."""


def default_tile_size(device: torch.device) -> int:
    """The tile edge that a call on ``device`` uses when given none: :data:`CUDA_TILE_SIZE` on CUDA, else
    :data:`CPU_TILE_SIZE`."""
    return CUDA_TILE_SIZE if device.type == "cuda" else CPU_TILE_SIZE


def _prepare(means, quats, scales, opacities, colors, viewmats, Ks, width, height, near, far, background, mode,
             sh_degree, render_depth, tile_size, min_transmittance):  # fmt: skip
    """Check every argument; return contiguous tensors (half-precision Gaussians as float32; cameras detached, in
    their float dtype) and the settings."""
    dims: dict[str, int] = {}
    means = check_tensor("means", means, ("N", 3), (*FLOAT_DTYPES, *_LOW_PRECISION), dims=dims)
    given = means.dtype
    quats = check_tensor("quats", quats, ("N", 4), (given,), dims)
    scales = check_tensor("scales", scales, ("N", 3), (given,), dims)
    opacities = check_tensor("opacities", opacities, ("N",), (given,), dims)
    if not isinstance(colors, torch.Tensor) or colors.dim() not in (2, 3):
        raise InputError("colors must be a tensor of shape [N,3] (RGB) or [N,K,3] (SH coefficients)")
    colors = check_tensor("colors", colors, ("N", 3) if colors.dim() == 2 else ("N", None, 3), (given,), dims)
    viewmats = check_tensor("viewmats", viewmats, ("B", 4, 4), dims=dims)
    Ks = check_tensor("Ks", Ks, ("B", 3, 3), dims=dims)
    if background is not None:
        background = check_tensor("background", background, ("B", 3), (given,), dims)
    if given in _LOW_PRECISION:  # half inputs (autocast) are computed in float32, like the geometry ops
        means, quats, scales, opacities, colors = (t.float() for t in (means, quats, scales, opacities, colors))
        background = None if background is None else background.float()
    common_device(
        means=means, quats=quats, scales=scales, opacities=opacities, colors=colors, viewmats=viewmats, Ks=Ks,
        background=background,
    )  # fmt: skip
    if tile_size is None:
        tile_size = default_tile_size(means.device)
    settings = _settings(colors.dim(), colors.shape[1], width, height, near, far, mode, sh_degree, render_depth,
                         tile_size, min_transmittance)  # fmt: skip
    _check_key_bits(viewmats.shape[0], settings)
    return means, quats, scales, opacities, colors, viewmats.detach(), Ks.detach(), background, settings


def _settings(*arguments) -> _Settings:
    """:func:`_make_settings` of the arguments, from a cache when they are hashable (settings are the same for most
    calls of a program)."""
    try:
        return _cached_settings(*arguments)
    except TypeError:  # an unhashable argument (or a TypeError of the checks): checked without the cache
        return _make_settings(*arguments)


def _make_settings(colors_rank, colors_width, width, height, near, far, mode, sh_degree, render_depth, tile_size,
                   min_transmittance) -> _Settings:  # fmt: skip
    """The checked settings of a call whose colours have rank ``colors_rank`` (2: RGB, 3: SH) and second size
    ``colors_width``; InputError for a bad one."""
    for name, value in (("width", width), ("height", height)):
        if isinstance(value, bool) or int(value) != value or value < 1:
            raise InputError(f"{name} must be a positive integer, got {value!r}")
    if mode not in MODES:
        raise InputError(f"mode must be one of {MODES}, got {mode!r}")
    if isinstance(tile_size, bool) or int(tile_size) != tile_size or not 1 <= tile_size <= 32:
        raise InputError(f"tile_size must be an integer in 1..32, got {tile_size!r}")
    if not (math.isfinite(near) and near > 0 and far > near):
        raise InputError(f"near and far must satisfy 0 < near < far, got near={near}, far={far}")
    degree = _sh_degree(colors_rank, colors_width, sh_degree)
    width, height, tile_size = int(width), int(height), int(tile_size)
    tiles_x, tiles_y = -(-width // tile_size), -(-height // tile_size)
    return _Settings(width, height, float(near), float(far), degree, mode == "antialiased", bool(render_depth),
                     tile_size, _transmittance_threshold(min_transmittance), tiles_x, tiles_y)  # fmt: skip


_cached_settings = functools.lru_cache(maxsize=256, typed=True)(_make_settings)
""":func:`_make_settings` cached (``typed``: ``True`` is not taken for 1); an error is raised again on every call."""


def _transmittance_threshold(value) -> float:
    """``min_transmittance`` as a float in [0, 1), else InputError."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not 0.0 <= value < 1.0:
        raise InputError(f"min_transmittance must be a real number in [0, 1), got {value!r}")
    return float(value)


def _sh_degree(colors_rank: int, K: int, sh_degree: int | None) -> int:
    """-1 for RGB colours (``colors_rank`` 2), else the SH degree to evaluate (checked against the K coefficients
    of ``[N,K,3]`` colours)."""
    if colors_rank == 2:
        if sh_degree is not None:
            raise InputError("sh_degree is given but colors is [N,3] RGB; pass SH coefficients [N,K,3]")
        return -1
    if sh_degree is None:
        root = math.isqrt(K)
        if root * root != K or not 1 <= root <= 4:
            raise InputError(f"colors has K={K} SH coefficients, not (d+1)^2 for d in 0..3; pass sh_degree")
        return root - 1
    if isinstance(sh_degree, bool) or int(sh_degree) != sh_degree or not 0 <= sh_degree <= 3:
        raise InputError(f"sh_degree must be 0, 1, 2 or 3, got {sh_degree!r}")
    if K < (sh_degree + 1) ** 2:
        raise InputError(f"sh_degree={sh_degree} needs K >= {(sh_degree + 1) ** 2} SH coefficients, colors has K={K}")
    return int(sh_degree)


MAX_TILE_BITS = 31
"""Bits of the flat tile index ``camera * tiles_per_image + tile``, an int32 in the kernels (a call has fewer than
2^31 flat tiles); a 64-bit key keeps its sign bit 0 with the 31 bits of a positive float32 depth beside it."""


def _check_key_bits(num_cameras: int, settings: _Settings) -> None:
    tiles = num_cameras * settings.tiles_x * settings.tiles_y
    if tiles >= 2**MAX_TILE_BITS:
        raise InputError(
            f"{num_cameras} cameras x {settings.tiles_x * settings.tiles_y} tiles do not fit the "
            f"{MAX_TILE_BITS}-bit tile part of the sort key; render fewer cameras per call or use larger tiles"
        )


# --------------------------------------------------------------------------------------------------
# Projection (stages 1 and 2)
class _Cameras(NamedTuple):
    """Cameras as the projection kernels take them, in the Gaussians' dtype (views of one buffer).

    Attributes:
        viewmats: ``[B,4,4]`` camera-relative world-to-camera; Ks: ``[B,3,3]`` pixels; origin: ``[3]`` the world
        translation (world units; 0 for float64 Gaussians); leave_out: ``[B,2]`` int32 Gaussian ranges the cameras
        cull (:func:`rasterize`), or ``[0,2]`` for none.
    """

    viewmats: torch.Tensor
    Ks: torch.Tensor
    origin: torch.Tensor
    leave_out: torch.Tensor


def _rows_and_cameras(means: torch.Tensor, num_cameras: int, leave_out: torch.Tensor
                      ) -> tuple[torch.Tensor, _Cameras]:  # fmt: skip
    """Uninitialised projected rows ``[B*N, 10]`` and prepared cameras (:class:`_Cameras`, with ``leave_out``) in
    the dtype of ``means`` ``[N,3]`` (separate allocations: fewer host operations than views of one buffer)."""
    B = num_cameras
    rows = means.new_empty(B * means.shape[0], raster_row.ROW_WIDTH)
    return rows, _Cameras(means.new_empty(B, 4, 4), means.new_empty(B, 3, 3), means.new_empty(3), leave_out)


def _leave_out_ranges(leave_out: torch.Tensor | None, viewmats: torch.Tensor, means: torch.Tensor) -> torch.Tensor:
    """:func:`rasterize`'s ``leave_out`` checked (``[B,2]`` integer, on the Gaussians' device) as int32 (other
    integer dtypes clamped to ``[-1, N]`` first; int32 is passed as it is, without a device op), or the zero-length
    ``[0,2]`` int32 array that means none."""
    if leave_out is None:
        return _zero_length(means.device, torch.int32, (2,))
    leave_out = check_tensor("leave_out", leave_out, (viewmats.shape[0], 2),
                             (torch.int8, torch.int16, torch.int32, torch.int64, torch.uint8))  # fmt: skip
    common_device(means=means, leave_out=leave_out)
    if leave_out.dtype == torch.int32:
        return leave_out
    return leave_out.clamp(-1, means.shape[0]).to(torch.int32)


class _Visible(NamedTuple):
    """The projection's list of visible rows, which the projection backward walks (uninitialised until the
    projection fills it). Its own allocations: the backward keeps it, not the forward's B*N int64 buffers.

    Attributes:
        count: ``[1]`` int64 length of the list; rows: ``[B*N]`` int32 flat row indices, the first ``count`` valid.
    """

    count: torch.Tensor
    rows: torch.Tensor


def _visible_list(means: torch.Tensor, rows: int) -> _Visible:
    return _Visible(means.new_empty(1, dtype=torch.int64), means.new_empty(rows, dtype=torch.int32))


def _prepare_cameras(viewmats, Ks, background, cameras: _Cameras, flags: torch.Tensor, visible: _Visible,
                     wdev) -> None:  # fmt: skip
    """Launch :func:`~codecsplat_warp.kernels.raster_project.prepare_cameras`; it also initialises ``flags`` and
    the length of the ``visible`` list.

    Args:
        viewmats: ``[B,4,4]``, Ks: ``[B,3,3]`` as given (float32 or float64); background: ``[B,3]`` or ``[0,3]``.
        cameras: the outputs, in the Gaussians' dtype; float32 Gaussians are made camera-relative.
        flags: ``[NUM_FLAGS]`` int64 validation counters.
    """
    dtype = cameras.origin.dtype
    launch(
        raster_project.prepare_cameras,
        1,
        [viewmats, Ks, background, int(dtype != torch.float64), cameras.viewmats, cameras.Ks, cameras.origin, flags,
         visible.count],  # fmt: skip
        wdev,
        layout=(viewmats.dtype, Ks.dtype, dtype),
    )


def _projection_inputs(means, quats, scales, opacities, coeffs, cameras: _Cameras) -> list:
    """The 3D-parameter and camera arguments of both projection kernels, in :func:`launch` form."""
    return [vectors(means), vectors(quats), vectors(scales), opacities, vectors(coeffs), matrices(cameras.viewmats),
            matrices(cameras.Ks), cameras.origin]  # fmt: skip


_LOW_PASS = {dtype: warp_dtype(dtype)(LOW_PASS_PX2) for dtype in FLOAT_DTYPES}
"""LOW_PASS_PX2 as a Warp scalar of each float dtype."""

_ZERO = {dtype: warp_dtype(dtype)(0.0) for dtype in FLOAT_DTYPES}
"""0 as a Warp scalar of each float dtype (the adjoint of a scalar argument)."""

_POWER_ROUNDING = {dtype: warp_dtype(torch.float64)(raster_reach.POWER_ROUNDING[name])
                   for dtype, name in ((torch.float32, "float32"), (torch.float64, "float64"))}  # fmt: skip
"""The bound on the rounding of a row's power, per Gaussian dtype (a Warp float64): the binning's reached tiles
and the CPU tile layout's line masks (:mod:`~codecsplat_warp.kernels.raster_reach`)."""


def _project(means, quats, scales, opacities, coeffs, cameras: _Cameras, settings: _Settings, splats: torch.Tensor,
             tile_counts: torch.Tensor, tile_masks: torch.Tensor, flags: torch.Tensor, visible: _Visible,
             ranges: torch.Tensor, wdev, zero_culled: bool = False) -> torch.Tensor:  # fmt: skip
    """Fill the projected rows ``splats [B*N, 10]`` (rows of culled Gaussians only with ``zero_culled``, else left
    as they were), ``tile_counts [B*N]``, ``tile_masks [B*N]`` (int64: which tiles of its rectangle a visible row
    reaches, :func:`~codecsplat_warp.kernels.raster_tiles.reached_tiles`), ``flags`` and the ``visible`` list, and
    zero the tile ``ranges`` ``[T, 2]`` int32 (``[0, 2]`` for none); return radii ``[B*N, 2]`` int32. On the CPU
    the Gaussians are split over the threads, and the ``visible`` list is then rewritten in row order
    (:func:`_list_visible_in_order`)."""
    dtype = means.dtype
    scalar = warp_dtype(dtype)
    radii = tile_counts.new_empty(splats.shape[0], 2, dtype=torch.int32)
    args = [
        *_projection_inputs(means, quats, scales, opacities, coeffs, cameras),
        settings.sh_degree,
        settings.width,
        settings.height,
        scalar(settings.near),
        scalar(settings.far),
        _LOW_PASS[dtype],
        int(settings.antialiased),
        settings.tile_size,
        settings.tiles_x,
        settings.tiles_y,
        _POWER_ROUNDING[dtype],
        int(zero_culled),
        vectors(cameras.leave_out),
    ]
    outputs = [splats, vectors(radii), tile_counts, tile_masks, flags, visible.count, visible.rows, vectors(ranges)]
    kernel = raster_project.projection_kernels(settings.sh_degree >= 0).project
    B = cameras.viewmats.shape[0]
    run_concurrently([
        functools.partial(launch, kernel, (B, count), [*args, first, *outputs], wdev, layout=dtype)
        for first, count in row_chunks(means.shape[0], means.device)
    ])  # fmt: skip
    if means.device.type == "cpu":
        _list_visible_in_order(radii, visible)
    return radii


def _list_visible_in_order(radii: torch.Tensor, visible: _Visible) -> None:
    """Rewrite the ``visible`` list as the visible rows (non-zero ``radii [B*N, 2]``) in increasing order, i.e.
    camera by camera: the order in which concurrent CPU launches appended them is not reproducible, and the
    projection backward walks the list camera by camera (:func:`_project_backward`)."""
    rows = torch.nonzero(radii.any(dim=1)).view(-1)
    visible.count[0] = rows.shape[0]
    visible.rows[: rows.shape[0]] = rows


def _project_backward(grad_rows, means, quats, scales, opacities, coeffs, cameras: _Cameras, visible: _Visible,
                      splats: torch.Tensor, radii: torch.Tensor, settings: _Settings,
                      wdev) -> list[torch.Tensor]:  # fmt: skip
    """Gradients of means ``[N,3]``, quats ``[N,4]``, scales ``[N,3]``, opacities ``[N]`` and coeffs ``[N,K,3]``
    from the gradient of the projected rows ``[B*N, 10]`` (views of one zero-initialised buffer), given the
    forward's rows ``splats [B*N, 10]`` and ``radii [B*N, 2]``; one thread per row of the ``visible`` list, and with
    SH colours first one per Gaussian for the colours' part (:func:`_sh_color_gradients`).

    On the CPU (where the list is in row order) the rows are taken camera after camera, each camera's split over
    the threads: a Gaussian has one row per camera, so no two threads add to its gradient at once (Warp's CPU
    atomics are plain adds), and its cameras' terms are added in camera order on any number of threads."""
    B, (N, K) = cameras.viewmats.shape[0], coeffs.shape[:2]
    dtype = means.dtype
    sizes = (3 * N, 4 * N, 3 * N, N, 3 * K * N)
    flat = means.new_zeros(sum(sizes)).split_with_sizes(sizes)
    grads = [flat[0].view(N, 3), flat[1].view(N, 4), flat[2].view(N, 3), flat[3], flat[4].view(N, K, 3)]
    zero = _ZERO[dtype]
    spherical_harmonics = settings.sh_degree >= 0
    if spherical_harmonics:
        _sh_color_gradients(grad_rows, means, coeffs, cameras, splats, radii, settings.sh_degree, grads[4], grads[0],
                            wdev)  # fmt: skip
    adj_coeffs = None if spherical_harmonics else vectors(grads[4])
    adj_args = [vectors(grads[0]), vectors(grads[1]), vectors(grads[2]), grads[3], adj_coeffs, None, None, None,
                None, None, 0, 0, 0, zero, 0, grad_rows]  # fmt: skip
    inputs = _projection_inputs(means, quats, scales, opacities, coeffs, cameras)
    settings_args = [settings.sh_degree, settings.width, settings.height, _LOW_PASS[dtype], int(settings.antialiased),
                     torch.empty_like(grad_rows)]  # fmt: skip
    kernel = raster_project.projection_kernels(spherical_harmonics).differentiable
    if means.device.type != "cpu":
        launch(kernel, B * N, [*inputs, visible.count, visible.rows, *settings_args], wdev, adj_args=adj_args,
               layout=dtype)  # fmt: skip
        return grads
    rows = visible.rows[: int(visible.count[0])]
    bounds = torch.searchsorted(rows, torch.arange(B + 1, dtype=rows.dtype) * N).tolist()
    for camera in range(B):
        pieces = [(bounds[camera] + first, count)
                  for first, count in row_chunks(bounds[camera + 1] - bounds[camera], means.device)]  # fmt: skip
        run_concurrently([
            functools.partial(launch, kernel, count, [*inputs, _length(count), rows[first : first + count],
                                                      *settings_args], wdev, adj_args=adj_args, layout=dtype)
            for first, count in pieces
        ])  # fmt: skip
    return grads


def _sh_color_gradients(grad_rows, means, coeffs, cameras: _Cameras, splats: torch.Tensor, radii: torch.Tensor,
                        sh_degree: int, grad_coeffs: torch.Tensor, grad_means: torch.Tensor, wdev) -> None:  # fmt: skip
    """Write the SH coefficients' gradient ``grad_coeffs [N,K,3]`` (up to ``sh_degree``) and add the colours'
    gradient through the view direction to ``grad_means [N,3]``, from the gradient of the projected rows
    ``[B*N, 10]``, one thread per Gaussian (split over the threads on the CPU)."""
    args = [vectors(means), vectors(coeffs), matrices(cameras.viewmats), cameras.origin, vectors(radii), splats,
            grad_rows, sh_degree]  # fmt: skip
    run_concurrently([
        functools.partial(launch, raster_project.sh_color_gradients, count,
                          [*args, first, vectors(grad_coeffs), vectors(grad_means)], wdev, layout=means.dtype)
        for first, count in row_chunks(means.shape[0], means.device)
    ])  # fmt: skip


def _length(count: int) -> torch.Tensor:
    """``[count]`` as the ``[1]`` int64 tensor a list length is passed as."""
    return torch.tensor([count], dtype=torch.int64)


class _ProjectGaussians(torch.autograd.Function):
    """The projection stage alone: (means, quats, scales, opacities, coeffs) -> rows [B,N,10]; radii, flags."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, coeffs, viewmats, Ks, settings: _Settings):
        B, N = viewmats.shape[0], means.shape[0]
        tile_counts, flags = means.new_empty(B * N + raster_tiles.NUM_FLAGS, dtype=torch.int64).split_with_sizes(
            (B * N, raster_tiles.NUM_FLAGS)
        )
        splats, cameras = _rows_and_cameras(means, B, _leave_out_ranges(None, viewmats, means))
        visible = _visible_list(means, B * N)
        with warp_scope(means.device) as wdev:
            _prepare_cameras(viewmats, Ks, _absent(means, 3), cameras, flags, visible, wdev)
            radii = _project(means, quats, scales, opacities, coeffs, cameras, settings, splats, tile_counts,
                             torch.empty_like(tile_counts), flags, visible,
                             tile_counts.new_empty(0, 2, dtype=torch.int32), wdev, zero_culled=True)  # fmt: skip
        ctx.settings = settings
        ctx.cameras = cameras
        ctx.visible = visible
        ctx.save_for_backward(means, quats, scales, opacities, coeffs, splats, radii)
        ctx.mark_non_differentiable(radii, flags)
        return splats.view(B, N, raster_row.ROW_WIDTH), radii.view(B, N, 2), flags

    @staticmethod
    def backward(ctx, grad_splats, _grad_radii, _grad_flags):
        means, quats, scales, opacities, coeffs, splats, radii = ctx.saved_tensors
        grad_rows = grad_splats.reshape(-1, raster_row.ROW_WIDTH).contiguous()
        with warp_scope(means.device) as wdev:
            grads = _project_backward(grad_rows, means, quats, scales, opacities, coeffs, ctx.cameras, ctx.visible,
                                      splats, radii, ctx.settings, wdev)  # fmt: skip
        return (*grads, None, None, None)


def _sh_coefficients(colors: torch.Tensor) -> torch.Tensor:
    """``colors`` as SH coefficients ``[N,K,3]``: RGB ``[N,3]`` becomes ``[N,1,3]`` (a view)."""
    return colors if colors.dim() == 3 else colors.unsqueeze(1)


def _absent(like: torch.Tensor, *inner: int) -> torch.Tensor:
    """A zero-length array ``[0, *inner]`` of the dtype and device of ``like``: how the kernels are told that an
    optional input or output is absent (one shared tensor per kind: it holds no data)."""
    return _zero_length(like.device, like.dtype, inner)


@functools.lru_cache(maxsize=64)
def _zero_length(device: torch.device, dtype: torch.dtype, inner: tuple[int, ...]) -> torch.Tensor:
    return torch.empty(0, *inner, dtype=dtype, device=device)


# --------------------------------------------------------------------------------------------------
# The render and its backward (the stages in order: _render)
CPU_BATCH = 16
"""Rows a one-pixel CPU block of the block layout stages per step (CUDA blocks stage block_dim rows, one per lane)."""

CPU_LAYOUTS = ("tiles", "blocks")
"""How a CPU call composites. ``"tiles"`` (the default): one thread per tile
(:mod:`~codecsplat_warp.kernels.raster_composite_cpu`), the tiles in runs of about equal work on
:func:`~codecsplat_warp.device.cpu_threads` threads. ``"blocks"``: the CUDA layout's kernels
(:mod:`~codecsplat_warp.kernels.raster_composite`) with one-lane blocks, on one thread, the CPU's layout before the
tile layout; kept so that CPU-only machines test the CUDA kernels' code, and to time the tile layout against (see
:func:`cpu_layout`). CUDA calls always use the block layout."""

TILE_RUNS_PER_THREAD = 4
"""Runs of tiles per thread in the tile layout: more runs than threads, so that a thread that finishes early takes
another run (tiles differ in work by orders of magnitude)."""

_layout_choice = threading.local()


@contextlib.contextmanager
def cpu_layout(name: str) -> Iterator[None]:
    """Composite the CPU calls this thread makes inside the block in layout ``name``, one of :data:`CPU_LAYOUTS`
    (benchmarks and tests; the default is ``"tiles"``). Raises InputError for another name."""
    if name not in CPU_LAYOUTS:
        raise InputError(f"CPU layout must be one of {CPU_LAYOUTS}, got {name!r}")
    previous = getattr(_layout_choice, "name", CPU_LAYOUTS[0])
    _layout_choice.name = name
    try:
        yield
    finally:
        _layout_choice.name = previous


def _composite_launch(device: torch.device, tile_size: int, num_tiles: int) -> _BlockComposite | _TileComposite:
    """The compositing layout of a call: blocks of one lane per pixel on CUDA (at most
    ``raster_composite.MAX_LANES`` a block); on the CPU the tile layout, or one-lane blocks (:func:`cpu_layout`)."""
    if device.type == "cpu" and getattr(_layout_choice, "name", CPU_LAYOUTS[0]) == "tiles":
        return _TILE_COMPOSITE
    return _block_composite(device.type, tile_size, num_tiles)


@functools.lru_cache(maxsize=64)
def _block_composite(device_type: str, tile_size: int, num_tiles: int) -> _BlockComposite:
    """The block layout of a call on a device of ``device_type`` (see :func:`_composite_launch`)."""
    pixels = tile_size * tile_size
    lanes = min(pixels, raster_composite.MAX_LANES) if device_type == "cuda" else 1
    batch = lanes if device_type == "cuda" else CPU_BATCH
    blocks_per_tile = -(-pixels // lanes)
    kernels = raster_composite.composite_kernels(batch)
    return _BlockComposite(num_tiles * blocks_per_tile, lanes, blocks_per_tile, kernels)


class _BlockComposite(NamedTuple):
    """The block layout (:mod:`~codecsplat_warp.kernels.raster_composite`): both kernels are launched as ``blocks``
    blocks of ``block_dim`` lanes, ``blocks_per_tile`` per tile; ``kernels`` = (forward, backward)."""

    blocks: int
    block_dim: int
    blocks_per_tile: int
    kernels: tuple
    uses_positions = False
    """Whether the binning hands this layout the emitted position of every sorted intersection (see
    :class:`_TileComposite`)."""

    def forward(self, binning: _Binning, ranges, colors_or_black, sorted_ids: torch.Tensor, positions: None,
                outputs: tuple, wdev) -> None:  # fmt: skip
        """Composite into ``outputs`` (see :func:`_composite_outputs`); nothing is kept for the backward."""
        splats, settings = binning.splats, binning.settings
        common = _composite_args(ranges, sorted_ids, splats, colors_or_black, settings) + [self.blocks_per_tile]
        threshold = warp_dtype(splats.dtype)(settings.min_transmittance)
        launch(self.kernels[0], self.blocks, [*common, threshold, *outputs], wdev, block_dim=self.block_dim,
               layout=splats.dtype)  # fmt: skip
        return None

    def backward(self, saved: _Saved, colors_or_black, settings: _Settings, output_grads: list, wdev) -> torch.Tensor:
        """The gradient of the projected rows ``[B*N, 10]`` from the gradients of the flat outputs."""
        grad_rows = torch.zeros_like(saved.splats)
        common = _composite_args(saved.ranges, saved.sorted_ids, saved.splats, colors_or_black, settings)
        launch(self.kernels[1], self.blocks, [*common, self.blocks_per_tile, saved.state, saved.last, *output_grads,
               grad_rows], wdev, block_dim=self.block_dim, layout=saved.splats.dtype)  # fmt: skip
        return grad_rows


class _TileState(NamedTuple):
    """What the tile layout's backward needs from its forward: ``skip_powers [count]`` (the Gaussians' dtype),
    ``line_masks [count * tile_size]`` (:func:`_line_mask_dtype`; every intersection's pixels on every line of its
    tile), and the binning's ``positions [count]`` int32 (where each sorted intersection was emitted),
    ``tile_counts`` and inclusive ``offsets`` ``[B*N]`` int64."""

    skip_powers: torch.Tensor
    line_masks: torch.Tensor
    positions: torch.Tensor
    tile_counts: torch.Tensor
    offsets: torch.Tensor


class _TileComposite:
    """The CPU tile layout (:mod:`~codecsplat_warp.kernels.raster_composite_cpu`); stateless (one instance,
    :data:`_TILE_COMPOSITE`). Its backward adds each intersection's gradient at the position the binning emitted
    it, so the binning sorts those positions (:func:`_bin` with ``positions``)."""

    uses_positions = True

    def forward(self, binning: _Binning, ranges, colors_or_black, sorted_ids: torch.Tensor, positions: torch.Tensor,
                outputs: tuple, wdev) -> _TileState:  # fmt: skip
        """Composite into ``outputs`` (see :func:`_composite_outputs`); returns what the backward needs
        (``positions``: where each of the ``sorted_ids`` was emitted)."""
        splats, settings = binning.splats, binning.settings
        count = sorted_ids.shape[0]
        skip_powers = splats.new_empty(count)
        line_masks = sorted_ids.new_empty(count * settings.tile_size, dtype=_line_mask_dtype(settings.tile_size))
        common = _composite_args(ranges, sorted_ids, splats, colors_or_black, settings)
        threshold = warp_dtype(splats.dtype)(settings.min_transmittance)
        run_concurrently([
            functools.partial(launch, raster_composite_cpu.composite_forward_tiles, tiles,
                              [*common, first, threshold, _POWER_ROUNDING[splats.dtype], skip_powers, line_masks,
                               *outputs], wdev, layout=(splats.dtype, line_masks.dtype))
            for first, tiles in _tile_runs(ranges)
        ])  # fmt: skip
        return _TileState(skip_powers, line_masks, positions, binning.tile_counts, binning.offsets)

    def backward(self, saved: _Saved, colors_or_black, settings: _Settings, output_grads: list, wdev) -> torch.Tensor:
        """The gradient of the projected rows ``[B*N, 10]`` from the gradients of the flat outputs: per
        intersection on the tiles' threads, then summed per row."""
        splats, tiles = saved.splats, saved.composite_state
        count = saved.sorted_ids.shape[0]
        grad_intersections = splats.new_zeros(count, raster_row.ROW_WIDTH)
        common = _composite_args(saved.ranges, saved.sorted_ids, splats, colors_or_black, settings)
        run_concurrently([
            functools.partial(launch, raster_composite_cpu.composite_backward_tiles, tiles_in_run,
                              [*common, first, tiles.skip_powers, tiles.line_masks, tiles.positions, saved.state,
                               saved.last, *output_grads, grad_intersections], wdev,
                              layout=(splats.dtype, tiles.line_masks.dtype))
            for first, tiles_in_run in _tile_runs(saved.ranges)
        ])  # fmt: skip
        grad_rows = torch.empty_like(splats)
        run_concurrently([
            functools.partial(launch, raster_composite_cpu.sum_intersection_gradients, rows,
                              [tiles.tile_counts, tiles.offsets, grad_intersections, first, grad_rows], wdev,
                              layout=splats.dtype)
            for first, rows in row_chunks(splats.shape[0], splats.device)
        ])  # fmt: skip
        return grad_rows


_TILE_COMPOSITE = _TileComposite()


def _line_mask_dtype(tile_size: int) -> torch.dtype:
    """The dtype of the tile layout's line masks (a bit per pixel of a tile's line): uint16 for tiles of at most 16
    pixels a side, else uint32."""
    return torch.uint16 if tile_size <= 16 else torch.uint32


def _tile_runs(ranges: torch.Tensor) -> list[tuple[int, int]]:
    """(first tile, tile count) runs of the tile layout: one run on one thread, else
    :data:`TILE_RUNS_PER_THREAD` runs per thread of about equal intersection counts."""
    threads = cpu_threads()
    if threads == 1:
        return [(0, ranges.shape[0])]
    work = (ranges[:, 1] - ranges[:, 0]) + 1  # + 1: a tile without intersections still writes its pixels
    return weighted_chunks(work, threads * TILE_RUNS_PER_THREAD)


def _composite_args(ranges, sorted_ids, rows, background, settings: _Settings) -> list:
    """The leading arguments shared by the compositing kernels of both layouts."""
    return [ranges, sorted_ids, rows, background, settings.width, settings.height, settings.tile_size,
            settings.tiles_x, settings.tiles_x * settings.tiles_y]  # fmt: skip


class _Saved(NamedTuple):
    """What the backward of a forward render needs besides its inputs (kept on the autograd context).

    Attributes:
        colors_or_black: ``[B,3]`` background or ``[0,3]``; cameras: the prepared cameras; splats: projected rows
        ``[B*N, 10]``; visible: the projection's list of visible rows; radii: ``[B*N, 2]`` int32 pixel radii (0 for a
        culled row); ranges: ``[B*tiles, 2]`` int32; sorted_ids: ``[count]`` int32; state: ``[P,2]`` (final T,
        accumulated depth); last: ``[P]`` int32; composite: the compositing layout; composite_state: what its forward
        kept for the backward (None in the block layout).
    """

    colors_or_black: torch.Tensor
    cameras: _Cameras
    splats: torch.Tensor
    visible: _Visible
    radii: torch.Tensor
    ranges: torch.Tensor
    sorted_ids: torch.Tensor
    state: torch.Tensor
    last: torch.Tensor
    composite: _BlockComposite | _TileComposite
    composite_state: _TileState | None


class _Staged(NamedTuple):
    """One call's projection stage, ready for its binning (:func:`_stage`): ``colors_or_black`` ``[B,3]`` or
    ``[0,3]``, the prepared ``cameras``, projected rows ``splats [B*N, 10]``, the ``visible`` list, ``radii
    [B*N, 2]`` int32, the zeroed tile ``ranges [B*tiles, 2]`` int32, the ``binning`` and the ``composite`` layout."""

    colors_or_black: torch.Tensor
    cameras: _Cameras
    splats: torch.Tensor
    visible: _Visible
    radii: torch.Tensor
    ranges: torch.Tensor
    binning: _Binning
    composite: _BlockComposite | _TileComposite


def _stage(means, quats, scales, opacities, colors, background, viewmats, Ks, leave_out, settings: _Settings,
           wdev) -> _Staged:  # fmt: skip
    """Stages 1 to 3 on checked inputs (inside :func:`~codecsplat_warp.device.warp_scope`): the cameras, the
    projection and the prefix sum of the tile counts."""
    B, N = viewmats.shape[0], means.shape[0]
    device = means.device
    coeffs = _sh_coefficients(colors)
    colors_or_black = _absent(means, 3) if background is None else background
    ints = means.new_empty(2 * B * N + raster_tiles.NUM_FLAGS, dtype=torch.int64)
    tile_counts, offsets, flags = ints.split_with_sizes((B * N, B * N, raster_tiles.NUM_FLAGS))
    tile_masks = torch.empty_like(tile_counts)
    splats, cameras = _rows_and_cameras(means, B, leave_out)
    visible = _visible_list(means, B * N)
    # the projection zeroes the ranges
    ranges = tile_counts.new_empty(B * settings.tiles_x * settings.tiles_y, 2, dtype=torch.int32)
    _prepare_cameras(viewmats, Ks, colors_or_black, cameras, flags, visible, wdev)
    radii = _project(means, quats, scales, opacities, coeffs, cameras, settings, splats, tile_counts, tile_masks,
                     flags, visible, ranges, wdev)  # fmt: skip
    inclusive_scan(tile_counts, offsets)
    binning = _Binning(splats, radii, ints, tile_counts, tile_masks, offsets, flags, B, settings)
    composite = _composite_launch(device, settings.tile_size, len(ranges))
    return _Staged(colors_or_black, cameras, splats, visible, radii, ranges, binning, composite)


def _render(means, quats, scales, opacities, colors, background, viewmats, Ks, leave_out, settings: _Settings,
            max_intersection_bytes: int) -> tuple[tuple, _Saved]:  # fmt: skip
    """The forward render on checked inputs: ``((rgb [B,H,W,3], depth [B,H,W,1] or None, alpha [B,H,W,1],
    radii [B,N,2] int32, intersection count), what the backward needs)``; on CUDA replayed from a
    :class:`_ForwardGraph` where one serves the call."""
    B, N = viewmats.shape[0], means.shape[0]
    device = means.device
    shape = (device, B, N, settings.width, settings.height, settings.tile_size)
    inputs = (means, quats, scales, opacities, colors, background, viewmats, Ks, leave_out)
    if device.type == "cuda" and device.type in SPECULATIVE_DEVICE_TYPES:  # a graph replays a speculative binning
        graphed = _graphed_render(inputs, settings, shape, max_intersection_bytes)
        if graphed is not None:
            return graphed
    with warp_scope(device) as wdev:
        staged = _stage(*inputs, settings, wdev)
        count, sorted_ids, outputs, composite_state = _bin_and_composite(
            staged.binning, staged.ranges, staged.colors_or_black, staged.composite,
            shape if device.type in SPECULATIVE_DEVICE_TYPES else None, max_intersection_bytes, wdev,
        )  # fmt: skip
    return _finish(staged, count, sorted_ids, outputs, composite_state)


def _finish(staged: _Staged, count: int, sorted_ids: torch.Tensor, outputs: tuple,
            composite_state: _TileState | None) -> tuple[tuple, _Saved]:  # fmt: skip
    """:func:`_render`'s result from the stage, the binning's count and sorted ids, and the compositing's outputs
    (:func:`_composite_outputs`) and state."""
    settings = staged.binning.settings
    B, H, W = staged.binning.num_cameras, settings.height, settings.width
    N = staged.splats.shape[0] // B
    color, depth, alpha, state, last = outputs
    depth = depth.view(B, H, W, 1) if settings.render_depth else None
    outputs = (color.view(B, H, W, 3), depth, alpha.view(B, H, W, 1), staged.radii.view(B, N, 2), count)
    return outputs, _Saved(staged.colors_or_black, staged.cameras, staged.splats, staged.visible, staged.radii,
                           staged.ranges, sorted_ids, state, last, staged.composite, composite_state)


class _Rasterize(torch.autograd.Function):
    """(means, quats, scales, opacities, colors, background) -> rgb [B,H,W,3], expected depth [B,H,W,1] or None,
    alpha [B,H,W,1], radii [B,N,2] (not differentiable) and the intersection count (an int).

    The inputs, the background array and the radii (an output the backward reads: changed in place, it raises
    autograd's error instead of changing the gradient) go through ``save_for_backward``; the forward's other
    intermediates (:class:`_Saved`) are kept on ``ctx`` directly."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, colors, background, viewmats, Ks, leave_out,
                settings: _Settings, max_intersection_bytes: int):  # fmt: skip
        outputs, saved = _render(means, quats, scales, opacities, colors, background, viewmats, Ks, leave_out,
                                 settings, max_intersection_bytes)  # fmt: skip
        ctx.settings, ctx.colors_shape = settings, colors.shape
        ctx.saved = saved._replace(colors_or_black=None, radii=None)
        ctx.save_for_backward(means, quats, scales, opacities, colors, saved.colors_or_black, saved.radii)
        ctx.mark_non_differentiable(outputs[3])
        ctx.set_materialize_grads(False)
        return outputs

    @staticmethod
    def backward(ctx, grad_color, grad_depth, grad_alpha, _grad_radii, _grad_count):
        means, quats, scales, opacities, colors, colors_or_black, radii = ctx.saved_tensors
        settings: _Settings = ctx.settings
        saved: _Saved = ctx.saved
        grads = [None] * 5
        if any(ctx.needs_input_grad[:5]):
            splats = saved.splats
            output_grads = [_flat_gradient(grad_color, splats, (3,)), _flat_gradient(grad_depth, splats, ()),
                            _flat_gradient(grad_alpha, splats, ())]  # fmt: skip
            with warp_scope(means.device) as wdev:
                grad_rows = saved.composite.backward(saved, colors_or_black, settings, output_grads, wdev)
                coeffs = _sh_coefficients(colors)  # after the compositing launch: its GPU work starts sooner
                grads = _project_backward(grad_rows, means, quats, scales, opacities, coeffs, saved.cameras,
                                          saved.visible, saved.splats, radii, settings, wdev)  # fmt: skip
            grads[4] = grads[4].view(ctx.colors_shape)
        grad_background = None
        if ctx.needs_input_grad[5] and grad_color is not None:
            B, H, W = grad_color.shape[:3]
            grad_background = (grad_color * saved.state[:, :1].view(B, H, W, 1)).sum(dim=(1, 2))
        return (*grads, grad_background, None, None, None, None, None)


def _composite_outputs(num_cameras: int, settings: _Settings, splats: torch.Tensor) -> tuple:
    """Uninitialised outputs of the forward compositing kernel for ``P = B*H*W`` pixels: flat ``color [P,3]``,
    expected ``depth [P]`` (``[0]`` without depth), ``alpha [P]``, ``state [P,2]`` (final T, accumulated depth),
    views of one buffer in the dtype of ``splats``, and ``last [P]`` int32."""
    P = num_cameras * settings.height * settings.width
    color, alpha, state, depth = splats.new_empty(6 * P + (P if settings.render_depth else 0)).split_with_sizes(
        (3 * P, P, 2 * P, P if settings.render_depth else 0)
    )
    last = torch.empty(P, dtype=torch.int32, device=splats.device)
    return color.view(P, 3), depth, alpha, state.view(P, 2), last


def _flat_gradient(grad: torch.Tensor | None, like: torch.Tensor, inner: tuple[int, ...]) -> torch.Tensor:
    """The gradient of a ``[B,H,W,*]`` output as a contiguous ``[B*H*W, *inner]`` array, or a zero-length one."""
    if grad is None:
        return _absent(like, *inner)
    return grad.reshape(-1, *inner).contiguous()


# --------------------------------------------------------------------------------------------------
# Tile binning: sort keys, speculation, the host read and the sort (stage 4)
class SortKey(NamedTuple):
    """How one call packs its intersection sort keys ``[flat tile | depth key]`` (computed on the device by
    :func:`codecsplat_warp.kernels.raster_tiles.sort_key_layout`).

    Attributes:
        depth_base: the smallest float32 bit pattern of a visible depth; depth_shift: low depth bits dropped (ties
        within ``2^depth_shift`` float32 ulps); depth_bits: key bits of the depth part; bits: key bits in use (the
        radix sort's end bit).
    """

    depth_base: int
    depth_shift: int
    depth_bits: int
    bits: int

    @property
    def dtype(self) -> torch.dtype:
        """``torch.uint32`` for a key of at most 32 bits, else ``torch.int64``."""
        return torch.uint32 if self.bits <= 32 else torch.int64

    @property
    def bytes_per_intersection(self) -> int:
        """Sort buffer bytes per intersection: the key and an int32 value, each twice (radix sort scratch)."""
        return _bytes_per_intersection(self.dtype)


def _bytes_per_intersection(key_dtype: torch.dtype) -> int:
    return 2 * (key_dtype.itemsize + 4)


class _Speculation(NamedTuple):
    """What a CUDA call guesses from the last call of its shape, to bin and composite before its host read.

    Attributes:
        capacity: intersections the sort buffers take; key_dtype: ``torch.uint32`` or ``torch.int64``; end_bit:
        key bits the sort orders (rounded up to a multiple of 8, the radix sort's digit: no extra pass).
    """

    capacity: int
    key_dtype: torch.dtype
    end_bit: int

    def covers(self, count: int, key: SortKey) -> bool:
        """Whether buffers and a sort set up by this guess hold the call's ``count`` intersections of ``key``."""
        return count <= self.capacity and key.dtype == self.key_dtype and key.bits <= self.end_bit


SPECULATIVE_DEVICE_TYPES = ("cuda",)
"""Device types on which a call bins and composites before its host read (:class:`_Speculation`); on the CPU the
read costs nothing, and a guessed capacity only sorts more."""

SPECULATION_SLACK = 1 / 8
"""The guessed capacity is the last count of the shape plus this fraction of it, plus
:data:`SPECULATION_MIN_SLACK`."""

SPECULATION_MIN_SLACK = 1024

_MAX_SPECULATIONS = 64
_speculations: dict[tuple, _Speculation] = {}
"""The guess for each call shape ``(device, B, N, width, height, tile_size)``; the least recent goes first."""
_speculations_lock = threading.Lock()


def _speculation(shape: tuple, max_bytes: int) -> _Speculation | None:
    """The guess for a call of ``shape``, its capacity cut to the sort budget ``max_bytes``; None before the first
    call of that shape."""
    guess = _speculations.get(shape)
    if guess is None:
        return None
    affordable = max_bytes // _bytes_per_intersection(guess.key_dtype)
    return guess if guess.capacity <= affordable else guess._replace(capacity=affordable)


def _remember(shape: tuple, count: int, key: SortKey) -> None:
    """Keep the guess for the next call of ``shape`` after one with ``count`` intersections of ``key`` (calls in
    several threads may share the store)."""
    capacity = min(count + int(count * SPECULATION_SLACK) + SPECULATION_MIN_SLACK, 2**31 - 1)
    end_bit = min(-(-key.bits // 8) * 8, 8 * key.dtype.itemsize)
    with _speculations_lock:
        _speculations.pop(shape, None)
        if len(_speculations) >= _MAX_SPECULATIONS:
            del _speculations[next(iter(_speculations))]
        _speculations[shape] = _Speculation(capacity, key.dtype, end_bit)


def _raise_on_flags(flag_values: list[int]) -> None:
    if not any(flag_values[: raster_project.VALIDATION_FLAGS]):
        return
    for slot, name in _ARGUMENT_OF_FLAG.items():
        if flag_values[slot]:
            unit = "value(s)" if slot in _CAMERA_FLAGS else "row(s)"
            raise InputError(f"{name} holds non-finite values (NaN or Inf) in {flag_values[slot]} {unit}")
    if flag_values[raster_project.HUGE_COVARIANCE]:
        raise InputError(
            f"scales: {flag_values[raster_project.HUGE_COVARIANCE]} (camera, Gaussian) pair(s) have a 2D covariance "
            "that overflows the float dtype (scales far too large); use float64 or smaller scales"
        )
    if flag_values[raster_project.ZERO_QUATS]:
        raise InputError(f"quats has {flag_values[raster_project.ZERO_QUATS]} zero quaternion(s) (no rotation)")


def _check_budget(count: int, key: SortKey, max_bytes: int) -> None:
    needed = count * key.bytes_per_intersection
    if needed > max_bytes or count >= 2**31:
        raise RasterMemoryError(
            f"{count:,} tile intersections need {needed:,} bytes ({needed / 2**30:.2f} GiB) of sort buffers, "
            f"over max_intersection_bytes={max_bytes:,}; render fewer or smaller Gaussians, or raise the budget"
        )


class _Binning(NamedTuple):
    """What the tile binning of one call reads: projected ``splats [B*N, 10]``, ``radii [B*N, 2]`` int32, the
    int64 buffer ``ints = [tile counts (B*N) | inclusive offsets (B*N) | flags]`` with its three parts, and the
    projection's ``tile_masks [B*N]`` int64."""

    splats: torch.Tensor
    radii: torch.Tensor
    ints: torch.Tensor
    tile_counts: torch.Tensor
    tile_masks: torch.Tensor
    offsets: torch.Tensor
    flags: torch.Tensor
    num_cameras: int
    settings: _Settings

    @property
    def num_tiles(self) -> int:
        """Flat tiles of the call: cameras x tiles per image."""
        return self.num_cameras * self.settings.tiles_x * self.settings.tiles_y


def _sort_buffers(like: torch.Tensor, capacity: int, key_dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """Uninitialised keys and int32 values for a sort of ``capacity`` pairs, each twice as long (sort scratch)."""
    return like.new_empty(2 * capacity, dtype=key_dtype), like.new_empty(2 * capacity, dtype=torch.int32)


def _emit(binning: _Binning, capacity: int, keys: torch.Tensor, values: torch.Tensor, wdev) -> None:
    """Launch :func:`~codecsplat_warp.kernels.raster_tiles.emit_intersections` over every row (on the CPU split over
    the threads: rows write disjoint intersections), or with ``capacity`` 0 on one thread (which publishes the key
    layout and writes nothing)."""
    splats, settings = binning.splats, binning.settings
    args = [
        splats,
        vectors(binning.radii),
        binning.tile_counts,
        binning.tile_masks,
        binning.offsets,
        binning.flags,
        splats.shape[0] // binning.num_cameras,
        settings.tile_size,
        settings.tiles_x,
        settings.tiles_y,
        binning.num_tiles,
        settings.width,
        settings.height,
        _POWER_ROUNDING[splats.dtype],
        capacity,
    ]
    pieces = row_chunks(splats.shape[0], splats.device) if capacity else [(0, 1)]
    run_concurrently([
        functools.partial(launch, raster_tiles.emit_intersections, rows, [*args, first, keys, values], wdev,
                          layout=(splats.dtype, keys.dtype))
        for first, rows in pieces
    ])  # fmt: skip


def _bin_and_composite(binning: _Binning, ranges: torch.Tensor, colors_or_black: torch.Tensor,
                       composite: _BlockComposite | _TileComposite, speculation_shape: tuple | None, max_bytes: int,
                       wdev) -> tuple[int, torch.Tensor, tuple, _TileState | None]:  # fmt: skip
    """Bin the projected rows into tiles and composite them: ``(intersection count, sorted row ids [count] int32,
    the outputs of :func:`_composite_outputs`, what the layout keeps for the backward)``; fills the tile ranges
    ``[B*tiles, 2]`` (zeroed by the projection). The call's one host read (count, validation flags, key layout)
    happens here.

    Without a guess for ``speculation_shape`` (None: no speculation) the host reads first, then bins exactly. With
    one, it bins into the guessed capacity and queues the compositing before it reads; when the read shows the
    guess unusable (:meth:`_Speculation.covers`), it bins exactly and composites again into the same outputs.
    Raises InputError on a validation flag and RasterMemoryError when the sort buffers would exceed ``max_bytes``.
    """
    splats, settings = binning.splats, binning.settings
    guess = None if speculation_shape is None else _speculation(speculation_shape, max_bytes)
    outputs = None
    if guess is not None:
        sorted_ids, outputs, state, read = _bin_and_composite_guessed(binning, ranges, colors_or_black, composite,
                                                                      guess, stage_host_values, wdev)  # fmt: skip
    else:
        no_keys, no_values = (_zero_length(splats.device, dtype, ()) for dtype in (torch.uint32, torch.int32))
        _emit(binning, 0, no_keys, no_values, wdev)  # only publishes the key layout
        read = stage_host_values(binning.ints, wdev, *_read_span(binning))
    count, key = _read_binning(read, max_bytes)
    if guess is not None and guess.covers(count, key):
        sorted_ids = sorted_ids[:count]
    else:
        if guess is not None:
            sorted_ids = None  # the failed guess's buffers go before the exact ones are allocated
            ranges.zero_()
        sorted_ids, positions, _ = _bin(binning, count, key.dtype, key.bits, ranges, wdev,
                                        positions=composite.uses_positions)
        if outputs is None:
            outputs = _composite_outputs(binning.num_cameras, settings, splats)
        state = composite.forward(binning, ranges, colors_or_black, sorted_ids, positions, outputs, wdev)
    if speculation_shape is not None:
        _remember(speculation_shape, count, key)
    return count, sorted_ids, outputs, state


def _bin_and_composite_guessed(binning: _Binning, ranges: torch.Tensor, colors_or_black: torch.Tensor,
                               composite: _BlockComposite | _TileComposite, guess: _Speculation, stage,
                               wdev) -> tuple[torch.Tensor, tuple, _TileState | None, object]:  # fmt: skip
    """The speculative half of :func:`_bin_and_composite`: bin into the ``guess``'s capacity, stage the host read
    with ``stage`` (:func:`~codecsplat_warp.device.stage_host_values` or a
    :meth:`~codecsplat_warp.device.PinnedRead.stage`) and composite, all before the read. Returns the sorted row ids
    ``[capacity]``, the outputs of :func:`_composite_outputs`, the layout's state and the staged read."""
    sorted_ids, positions, read = _bin(binning, guess.capacity, guess.key_dtype, guess.end_bit, ranges, wdev,
                                       stage=stage, positions=composite.uses_positions)
    outputs = _composite_outputs(binning.num_cameras, binning.settings, binning.splats)
    state = composite.forward(binning, ranges, colors_or_black, sorted_ids, positions, outputs, wdev)
    return sorted_ids, outputs, state, read


READ_VALUES = 1 + raster_tiles.HOST_FLAGS
"""Values of a call's host read: the intersection count, then the first
:data:`~codecsplat_warp.kernels.raster_tiles.HOST_FLAGS` flags."""


def _read_span(binning: _Binning) -> tuple[int, int]:
    """Where in ``binning.ints`` the host read starts and how many values it takes (:data:`READ_VALUES`): the last
    inclusive offset (the intersection count), then the flags."""
    return 2 * binning.splats.shape[0] - 1, READ_VALUES


def _read_binning(read, max_bytes: int) -> tuple[int, SortKey]:
    """Finish the call's one host read (staged over :func:`_read_span`): the intersection count and the sort key
    the emit kernel published. Raises InputError on a validation flag and RasterMemoryError when the sort buffers
    would exceed ``max_bytes``."""
    count, *flag_values = read.values()
    if validation_enabled():
        _raise_on_flags(flag_values)
    key = SortKey(*raster_tiles.key_layout(flag_values))
    _check_budget(count, key, max_bytes)
    return count, key


def _bin(binning: _Binning, capacity: int, key_dtype: torch.dtype, end_bit: int, ranges: torch.Tensor, wdev,
         stage=None, positions: bool = False) -> tuple[torch.Tensor, torch.Tensor | None, object]:
    """Emit up to ``capacity`` intersections with keys of ``key_dtype``, sort them by key bits ``[0, end_bit)`` and
    fill the per-tile ranges ``[B*tiles, 2]`` (int32, zero on entry). Returns the sorted row ids ``[capacity]``
    (int32; from the count on, padding); with ``positions`` the position at which each sorted intersection was
    emitted ``[capacity]`` (int32; the sort carries the positions and the row ids are gathered from them), else
    None; and with ``stage`` (a function with :func:`~codecsplat_warp.device.stage_host_values`' arguments) the host
    read staged by it after the emit launch (which publishes the key layout), else None."""
    keys, values = _sort_buffers(binning.ints, capacity, key_dtype)
    _emit(binning, capacity, keys, values, wdev)
    read = None if stage is None else stage(binning.ints, wdev, *_read_span(binning))
    emitted_rows = None
    if positions:
        emitted_rows = values[:capacity].clone()
        torch.arange(capacity, dtype=torch.int32, out=values[:capacity])
    radix_sort_pairs(keys, values, capacity, end_bit)
    launch(raster_tiles.tile_ranges, capacity, [keys, binning.offsets, binning.flags, capacity, ranges], wdev,
           layout=key_dtype)  # fmt: skip
    if emitted_rows is None:
        return values[:capacity], None, read
    order = values[:capacity]
    return emitted_rows[order.long()], order, read


def _empty_render(means, viewmats, background, settings: _Settings):
    """Output for N = 0 Gaussians or B = 0 cameras: the background (or black), zero alpha and depth."""
    B, H, W = viewmats.shape[0], settings.height, settings.width
    zeros = means.new_zeros(B, H, W, 1)
    if background is not None:
        color = background[:, None, None, :].expand(B, H, W, 3).clone()
    else:
        color = means.new_zeros(B, H, W, 3)
    radii = torch.zeros(B, means.shape[0], 2, dtype=torch.int32, device=means.device)
    depth = zeros.clone() if settings.render_depth else None
    return color, depth, zeros, RasterMeta(radii, 0, settings.tile_size)


# --------------------------------------------------------------------------------------------------
# Forward graphs: a CUDA call's stages 1 to 5 replayed from a CUDA graph
GRAPH_MAX_INTERSECTIONS = 1 << 22
"""A CUDA call replays its forward from a graph (:class:`_ForwardGraph`) only while its guessed intersection capacity
is at most this: such calls are bound by the host's launches (131,072 Gaussians into 256x256 take 0.5 ms of GPU time
and 1.7 ms of the host's, H200); larger ones by the GPU, where a graph's capacity headroom would only sort more."""

GRAPH_HEADROOM = 1 / 4
"""A graph is captured with this fraction more capacity than the call's guess, so that counts that drift up a little
(an optimisation's steps) do not capture it again; a guess that outgrows it, or shrinks to under half of it, does."""

MAX_FORWARD_GRAPHS = 4
"""Forward graphs a thread keeps (the least recently used goes first); each holds its call's buffers."""

GRAPHS_VARIABLE = "CODECSPLAT_RASTER_GRAPHS"
"""Environment variable: ``0`` turns forward graphs off by default (see :func:`forward_graphs`)."""

_graph_state = threading.local()
"""This thread's forward graphs: ``enabled`` (:func:`forward_graphs`), ``graphs`` (key -> :class:`_ForwardGraph`,
least recently used first) and ``failed`` (keys whose capture failed: they stay eager)."""


@contextlib.contextmanager
def forward_graphs(enabled: bool) -> Iterator[None]:
    """Let the CUDA calls this thread makes inside the block replay their forward from CUDA graphs, or not. By default
    they do, unless ``$CODECSPLAT_RASTER_GRAPHS`` is ``0``.

    A call of a shape, settings and dtypes seen before (whose sort the previous call sized, see :class:`_Speculation`)
    and with at most :data:`GRAPH_MAX_INTERSECTIONS` guessed intersections is captured once as a graph (cameras,
    projection, scan, emission, sort and compositing, up to the host read) and replayed from then on: its inputs are
    copied into the graph's, and its outputs and the backward's state copied out, so nothing a caller holds aliases
    the graph. The results are those of the eager launches, bit for bit. A graph keeps its call's buffers (on the
    order of the call's own memory) while the thread keeps it (:data:`MAX_FORWARD_GRAPHS`). A capture that fails
    warns once and leaves that call shape eager. Calls made while the current stream is being captured stay eager."""
    previous = _graphs_enabled()
    _graph_state.enabled = bool(enabled)
    try:
        yield
    finally:
        _graph_state.enabled = previous


def _graphs_enabled() -> bool:
    enabled = getattr(_graph_state, "enabled", None)
    if enabled is None:
        enabled = _graph_state.enabled = os.environ.get(GRAPHS_VARIABLE, "1").strip() != "0"
    return enabled


def _thread_graphs() -> tuple[collections.OrderedDict, set]:
    if not hasattr(_graph_state, "graphs"):
        _graph_state.graphs, _graph_state.failed = collections.OrderedDict(), set()
    return _graph_state.graphs, _graph_state.failed


class _ForwardGraph:
    """One call's :func:`_stage` and speculative binning and compositing (:func:`_bin_and_composite_guessed`, with
    the capacity ``guess``) captured as a CUDA graph on static copies of the call's tensor ``inputs`` (the order of
    :func:`_render`'s, None where absent), its host read staged into a :class:`~codecsplat_warp.device.PinnedRead`
    of its own. :meth:`replay` copies new inputs in and replays; the results stay in the graph's memory."""

    def __init__(self, inputs: tuple, settings: _Settings, guess: _Speculation):
        device = inputs[0].device
        self.settings, self.guess = settings, guess
        self.inputs = [None if t is None else t.clone() for t in inputs]
        self.present = [t for t in self.inputs if t is not None]
        self.read = PinnedRead(READ_VALUES)
        self._launch()  # warm-up: loads the kernels' modules and sizes Warp's sort scratch for the capacity
        self.graph = torch.cuda.CUDAGraph()
        with cuda_graph_capture(self.graph, device):
            with warp_capture(device) as self.warp_record:  # kept as long as the graph
                self.launched = self._launch()

    def _launch(self) -> tuple[_Staged, torch.Tensor, tuple]:
        with warp_scope(self.inputs[0].device) as wdev:
            staged = _stage(*self.inputs, self.settings, wdev)
            sorted_ids, outputs, _, _ = _bin_and_composite_guessed(
                staged.binning, staged.ranges, staged.colors_or_black, staged.composite, self.guess, self.read.stage,
                wdev,
            )  # fmt: skip
        return staged, sorted_ids, outputs

    def serves(self, guess: _Speculation) -> bool:
        """Whether this graph's capacity and key suit a call with ``guess`` (neither too small nor twice too large)."""
        mine = self.guess
        return (guess.key_dtype == mine.key_dtype and guess.end_bit <= mine.end_bit
                and guess.capacity <= mine.capacity <= 2 * guess.capacity)  # fmt: skip

    def replay(self, inputs: tuple) -> tuple[_Staged, torch.Tensor, tuple]:
        """Copy ``inputs`` (shaped as the captured ones) into the graph's and replay it; returns the graph's stage,
        sorted ids ``[capacity]`` and outputs."""
        torch._foreach_copy_(self.present, [t for t in inputs if t is not None])
        self.graph.replay()
        return self.launched


def _graphed_render(inputs: tuple, settings: _Settings, shape: tuple, max_bytes: int) -> tuple[tuple, _Saved] | None:
    """:func:`_render` of a CUDA call replayed from a :class:`_ForwardGraph` (captured here when none serves the
    call yet), or None when the call is not for a graph (see :func:`forward_graphs`) or the replay's guess did not
    cover its intersections (the caller then renders eagerly). Raises as :func:`_read_binning` does."""
    if not _graphs_enabled() or torch.cuda.is_current_stream_capturing():
        return None
    guess = _speculation(shape, max_bytes)
    if guess is None or guess.capacity > GRAPH_MAX_INTERSECTIONS:
        return None
    means, colors, background, viewmats, Ks, leave_out = (inputs[i] for i in (0, 4, 5, 6, 7, 8))
    stream = torch._C._cuda_getCurrentRawStream(means.device.index)  # a CUDA tensor's device has its index
    key = (shape, settings, stream, means.dtype, colors.shape, background is None, viewmats.dtype, Ks.dtype,
           leave_out.shape[0])  # with the shape and settings, every input's shape and dtype  # fmt: skip
    graph = _graph_for(key, guess, inputs, settings, max_bytes)
    if graph is None:
        return None
    staged, sorted_ids, outputs = graph.replay(inputs)
    staged, sorted_ids, outputs = _copy_out(staged, sorted_ids, outputs, inputs)  # queued before the host waits
    count, sort_key = _read_binning(graph.read, max_bytes)
    _remember(shape, count, sort_key)
    if not graph.guess.covers(count, sort_key):
        return None
    return _finish(staged, count, sorted_ids[:count], outputs, None)


def _graph_for(key: tuple, guess: _Speculation, inputs: tuple, settings: _Settings,
               max_bytes: int) -> _ForwardGraph | None:  # fmt: skip
    """This thread's graph under ``key`` when it serves ``guess`` (:meth:`_ForwardGraph.serves`), else one captured
    now from ``inputs`` with :data:`GRAPH_HEADROOM` more capacity than the guess (within the sort budget
    ``max_bytes``), the least recently used graph going first when the thread keeps :data:`MAX_FORWARD_GRAPHS`;
    None for a key whose capture failed (warned once, when it failed)."""
    graphs, failed = _thread_graphs()
    graph = graphs.get(key)
    if graph is not None and graph.serves(guess):
        graphs.move_to_end(key)
        return graph
    graphs.pop(key, None)
    if key in failed:
        return None
    while len(graphs) >= MAX_FORWARD_GRAPHS:
        graphs.popitem(last=False)
    affordable = max_bytes // _bytes_per_intersection(guess.key_dtype)
    roomy = guess._replace(capacity=min(guess.capacity + int(guess.capacity * GRAPH_HEADROOM), affordable))
    try:
        graph = _ForwardGraph(inputs, settings, roomy)
    except Exception as error:  # noqa: BLE001 -- any failure to capture leaves the call shape eager
        failed.add(key)
        cameras, gaussians = key[0][1], key[0][2]
        warnings.warn(f"rasterize: capturing the forward of {cameras} camera(s) x {gaussians:,} Gaussians as a "
                      f"CUDA graph failed; that call shape runs eagerly ({type(error).__name__}: {error})",
                      RuntimeWarning, stacklevel=2)  # fmt: skip
        return None
    graphs[key] = graph
    return graph


def _copy_out(staged: _Staged, sorted_ids: torch.Tensor, outputs: tuple,
              inputs: tuple) -> tuple[_Staged, torch.Tensor, tuple]:  # fmt: skip
    """Copies of a replay's results that :func:`_finish` and the backward keep (the next replay overwrites the
    graph's): one op per dtype (``x * 1``, exact), queued behind the replay. ``inputs`` are the call's own (its
    background and leave-out ranges are kept, as the eager path keeps them)."""
    color, depth, alpha, state, last = outputs
    cameras, visible = staged.cameras, staged.visible
    color, depth, alpha, state, splats, viewmats, Ks, origin = torch._foreach_mul(
        [color, depth, alpha, state, staged.splats, cameras.viewmats, cameras.Ks, cameras.origin], 1
    )
    last, radii, ranges, sorted_ids, rows = torch._foreach_mul(
        [last, staged.radii, staged.ranges, sorted_ids, visible.rows], 1
    )
    colors_or_black = staged.colors_or_black if inputs[5] is None else inputs[5]
    copied = _Staged(colors_or_black, _Cameras(viewmats, Ks, origin, inputs[8]), splats,
                     _Visible(visible.count.clone(), rows), radii, ranges, staged.binning,
                     staged.composite)  # fmt: skip
    return copied, sorted_ids, (color, depth, alpha, state, last)
