"""Differentiable 3D Gaussian splat rasterization on Warp kernels (CPU and CUDA), close to gsplat's API.

Pipeline (one kernel family per stage, see ``codecsplat_warp.kernels.raster_*``):

1. EWA projection, one thread per (camera, Gaussian): a packed row ``[x, y, conic(3), opacity, rgb, depth]``,
   pixel radii, tiles touched and input-validation flags.
2. Prefix sum of the tile counts; ONE host sync reads the intersection count and the flags, then the
   memory budget is checked before anything is allocated for sorting.
3. One 64-bit key ``[camera | tile | depth bits]`` per intersection, ``wp.utils.radix_sort_pairs`` on the
   used bits only, per-tile ranges from the sorted keys.
4. Front-to-back compositing per 16x16 tile (rows staged in shared memory), and a hand-written back-to-front
   backward. Projection gradients come from an adjoint launch of its straight-line twin kernel.

Gradients flow to ``means``, ``quats``, ``scales``, ``opacities``, ``colors`` (RGB or SH) and
``background``. ``viewmats`` and ``Ks`` are **not** differentiated (their gradient is None).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import warp as wp

from ..device import (
    FLOAT_DTYPES, check_finite, check_tensor, common_device, launch, matrices, to_warp, validation_enabled, vectors,
    warp_dtype, warp_scope,
)  # fmt: skip
from ..cameras import rigid_inverse
from ..errors import InputError, RasterMemoryError
from ..kernels import raster_composite, raster_project, raster_tiles

_LOW_PRECISION = (torch.float16, torch.bfloat16)

DEFAULT_MAX_INTERSECTION_BYTES = 4 << 30
"""Default budget for the intersection sort buffers (keys and values, double-buffered): 4 GiB."""

BYTES_PER_INTERSECTION = 2 * (8 + 4)
"""Sort buffer bytes per intersection: an int64 key and an int32 value, each twice (radix sort scratch)."""

LOW_PASS_PX2 = 0.3
"""Screen-space low-pass blur added to the 2D covariance diagonal, in px^2 (gsplat's eps2d)."""

MIN_ALPHA_FOR_DEPTH = 1e-10
"""Expected depth is ``sum w z / max(alpha, MIN_ALPHA_FOR_DEPTH)`` (gsplat's RGB+ED normalisation)."""

MODES = ("classic", "antialiased")

_ARGUMENT_OF_FLAG = {
    raster_project.BAD_MEANS: "means",
    raster_project.BAD_QUATS: "quats",
    raster_project.BAD_SCALES: "scales",
    raster_project.BAD_OPACITIES: "opacities",
    raster_project.BAD_COLORS: "colors",
    raster_project.BAD_VIEWMATS: "viewmats",
    raster_project.BAD_KS: "Ks",
}


@dataclass(frozen=True)
class RasterMeta:
    """Side outputs of :func:`rasterize`.

    Attributes:
        radii: ``[B, N, 2]`` int32 pixel half-extents (x, y) of each Gaussian's box per camera; 0 = culled.
        visible_counts: ``[B]`` int64 number of Gaussians with non-zero radii per camera.
        intersection_count: number of (camera, Gaussian, tile) intersections that were sorted.
        tile_size: tile edge in pixels.
    """

    radii: torch.Tensor
    visible_counts: torch.Tensor
    intersection_count: int
    tile_size: int


@dataclass(frozen=True)
class _Settings:
    width: int
    height: int
    near: float
    far: float
    sh_degree: int
    antialiased: bool
    render_depth: bool
    tile_size: int

    @property
    def tiles_x(self) -> int:
        return math.ceil(self.width / self.tile_size)

    @property
    def tiles_y(self) -> int:
        return math.ceil(self.height / self.tile_size)


def _projection_inputs(means, quats, scales, opacities, coeffs, viewmats, Ks) -> list:
    """The 3D-parameter and camera arguments of both projection kernels, in :func:`launch` form."""
    return [vectors(means), vectors(quats), vectors(scales), opacities, vectors(coeffs), matrices(viewmats),
            matrices(Ks)]  # fmt: skip


class _ProjectGaussians(torch.autograd.Function):
    """(means, quats, scales, opacities, coeffs) -> packed rows [B,N,10]; also radii, tile counts, flags."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, coeffs, viewmats, Ks, settings: _Settings):
        B, N = viewmats.shape[0], means.shape[0]
        device = means.device
        scalar = warp_dtype(means.dtype)
        splats = torch.zeros(B * N, raster_project.ROW_WIDTH, dtype=means.dtype, device=device)
        radii = torch.empty(B * N, 2, dtype=torch.int32, device=device)
        tile_counts = torch.empty(B * N, dtype=torch.int64, device=device)
        flags = torch.zeros(raster_project.NUM_FLAGS, dtype=torch.int32, device=device)
        with warp_scope(device) as wdev:
            launch(
                raster_project.project_gaussians,
                (B, N),
                [
                    *_projection_inputs(means, quats, scales, opacities, coeffs, viewmats, Ks),
                    settings.sh_degree,
                    settings.width,
                    settings.height,
                    scalar(settings.near),
                    scalar(settings.far),
                    scalar(LOW_PASS_PX2),
                    int(settings.antialiased),
                    settings.tile_size,
                    settings.tiles_x,
                    settings.tiles_y,
                    splats,
                    vectors(radii),
                    tile_counts,
                    flags,
                ],
                wdev,
            )
        ctx.settings = settings
        ctx.save_for_backward(means, quats, scales, opacities, coeffs, viewmats, Ks, radii)
        ctx.mark_non_differentiable(radii, tile_counts, flags)
        return splats.view(B, N, raster_project.ROW_WIDTH), radii.view(B, N, 2), tile_counts, flags

    @staticmethod
    def backward(ctx, grad_splats, _grad_radii, _grad_counts, _grad_flags):
        means, quats, scales, opacities, coeffs, viewmats, Ks, radii = ctx.saved_tensors
        settings: _Settings = ctx.settings
        B, N = viewmats.shape[0], means.shape[0]
        grads = [torch.zeros_like(t) for t in (means, quats, scales, opacities, coeffs)]
        if grad_splats is None or N == 0:
            return (*grads, None, None, None)
        scalar = warp_dtype(means.dtype)
        scratch = torch.zeros(B * N, raster_project.ROW_WIDTH, dtype=means.dtype, device=means.device)
        adj_args = [
            vectors(grads[0]),
            vectors(grads[1]),
            vectors(grads[2]),
            grads[3],
            vectors(grads[4]),
            None,
            None,
            None,
            0,
            0,
            0,
            scalar(0.0),
            0,
            grad_splats.reshape(B * N, raster_project.ROW_WIDTH).contiguous(),
        ]
        with warp_scope(means.device) as wdev:
            launch(
                raster_project.project_gaussians_differentiable,
                (B, N),
                [
                    *_projection_inputs(means, quats, scales, opacities, coeffs, viewmats, Ks),
                    vectors(radii.view(B * N, 2)),
                    settings.sh_degree,
                    settings.width,
                    settings.height,
                    scalar(LOW_PASS_PX2),
                    int(settings.antialiased),
                    scratch,
                ],
                wdev,
                adj_args=adj_args,
            )
        return (*grads, None, None, None)


CPU_BATCH = 16
"""Rows a one-pixel CPU block stages per step (CUDA blocks stage tile_size^2 rows, one per lane)."""


def _composite_launch_shape(device: torch.device, tile_size: int, num_tiles: int) -> tuple[int, int, int, tuple]:
    """(blocks, block_dim, blocks_per_tile, kernels): one lane per pixel on CUDA, one-lane blocks on the CPU."""
    pixels = tile_size * tile_size
    lanes = pixels if device.type == "cuda" else 1
    batch = pixels if device.type == "cuda" else CPU_BATCH
    return num_tiles * (pixels // lanes), lanes, pixels // lanes, raster_composite.composite_kernels(batch)


class _CompositeSplats(torch.autograd.Function):
    """Packed rows [B,N,10] (+ background) -> colour [B,H,W,3], accumulated depth [B,H,W,1], alpha [B,H,W,1]."""

    @staticmethod
    def forward(ctx, splats, background, ranges, sorted_ids, settings: _Settings):
        B = ranges.shape[0] // (settings.tiles_x * settings.tiles_y)
        H, W = settings.height, settings.width
        device, dtype = splats.device, splats.dtype
        color = torch.empty(B * H * W, 3, dtype=dtype, device=device)
        depth = torch.zeros(B * H * W, dtype=dtype, device=device)
        alpha = torch.empty(B * H * W, dtype=dtype, device=device)
        transmittance = torch.empty(B * H * W, dtype=dtype, device=device)
        last = torch.empty(B * H * W, dtype=torch.int32, device=device)
        blocks, block_dim, blocks_per_tile, kernels = _composite_launch_shape(device, settings.tile_size, len(ranges))
        rows = splats.reshape(-1, raster_project.ROW_WIDTH)
        with warp_scope(device) as wdev:
            launch(
                kernels[0],
                (blocks,),
                [
                    *_composite_common(ranges, sorted_ids, rows, background, settings, blocks_per_tile),
                    color,
                    depth,
                    alpha,
                    transmittance,
                    last,
                ],
                wdev,
                block_dim=block_dim,
            )
        ctx.settings = settings
        ctx.has_background = background is not None
        ctx.save_for_backward(rows, background, ranges, sorted_ids, transmittance, last)
        return color.view(B, H, W, 3), depth.view(B, H, W, 1), alpha.view(B, H, W, 1)

    @staticmethod
    def backward(ctx, grad_color, grad_depth, grad_alpha):
        rows, background, ranges, sorted_ids, transmittance, last = ctx.saved_tensors
        settings: _Settings = ctx.settings
        B, H, W = grad_color.shape[0], settings.height, settings.width
        device = rows.device
        grad_rows = torch.zeros_like(rows)
        blocks, block_dim, blocks_per_tile, kernels = _composite_launch_shape(device, settings.tile_size, len(ranges))
        with warp_scope(device) as wdev:
            launch(
                kernels[1],
                (blocks,),
                [
                    *_composite_common(ranges, sorted_ids, rows, background, settings, blocks_per_tile),
                    transmittance,
                    last,
                    grad_color.reshape(B * H * W, 3).contiguous(),
                    grad_depth.reshape(B * H * W).contiguous(),
                    grad_alpha.reshape(B * H * W).contiguous(),
                    grad_rows,
                ],
                wdev,
                block_dim=block_dim,
            )
        grad_background = None
        if ctx.has_background and ctx.needs_input_grad[1]:
            grad_background = (grad_color * transmittance.view(B, H, W, 1)).sum(dim=(1, 2))
        return grad_rows.view(B, -1, raster_project.ROW_WIDTH), grad_background, None, None, None


def _composite_common(ranges, sorted_ids, rows, background, settings: _Settings, blocks_per_tile: int) -> list:
    dummy_background = background if background is not None else rows.new_zeros(1, 3)
    return [
        ranges,
        sorted_ids,
        rows,
        dummy_background,
        int(background is not None),
        int(settings.render_depth),
        settings.width,
        settings.height,
        settings.tile_size,
        settings.tiles_x,
        settings.tiles_x * settings.tiles_y,
        blocks_per_tile,
    ]


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
    tile_size: int = 16,
    max_intersection_bytes: int = DEFAULT_MAX_INTERSECTION_BYTES,
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
        tile_size: tile edge in pixels (1..32; 16 is the tuned default).
        max_intersection_bytes: budget for the intersection sort buffers (24 bytes per intersection).

    Returns:
        ``(rgb [B,H,W,3], depth [B,H,W,1] or None, alpha [B,H,W,1], meta)`` in the dtype of ``means``
        (float32 or float64); see :class:`RasterMeta`.

    Raises:
        InputError: bad shape, dtype, mode, degree or size; NaN/Inf in any input; zero quaternion.
        DeviceMismatchError: inputs on different devices.
        RasterMemoryError: the intersections would need more than ``max_intersection_bytes``.
    """
    means, quats, scales, opacities, coeffs, viewmats, Ks, background, settings = _prepare(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height, near, far, background, mode,
        sh_degree, render_depth, tile_size,
    )  # fmt: skip
    B, N = viewmats.shape[0], means.shape[0]
    if N == 0:
        for name, tensor in (("viewmats", viewmats), ("Ks", Ks), ("background", background)):
            if tensor is not None:
                check_finite(name, tensor)
        return _empty_render(means, viewmats, background, settings)

    splats, radii, tile_counts, flags = _ProjectGaussians.apply(
        means, quats, scales, opacities, coeffs, viewmats, Ks, settings
    )
    offsets = _inclusive_scan(tile_counts, means.device)
    count, flag_values = _read_count_and_flags(offsets, flags, background)
    if validation_enabled():
        _raise_on_flags(flag_values)
    _check_budget(count, max_intersection_bytes)
    ranges, sorted_ids = _bin_intersections(splats, radii, tile_counts, offsets, count, B, settings)
    color, depth_sum, alpha = _CompositeSplats.apply(splats, background, ranges, sorted_ids, settings)
    depth = depth_sum / alpha.clamp_min(MIN_ALPHA_FOR_DEPTH) if settings.render_depth else None
    visible = (radii > 0).any(dim=-1).sum(dim=1)
    return color, depth, alpha, RasterMeta(radii, visible, count, settings.tile_size)


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
    means, quats, scales, opacities, coeffs, viewmats, Ks, _, settings = _prepare(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height, near, far, None, mode,
        sh_degree, True, 16,
    )  # fmt: skip
    splats, radii, _, flags = _ProjectGaussians.apply(means, quats, scales, opacities, coeffs, viewmats, Ks, settings)
    if validation_enabled() and means.shape[0]:
        _raise_on_flags([int(v) for v in flags.tolist()])
    return ProjectedGaussians(
        means2d=splats[..., 0:2], conics=splats[..., 2:5], opacities=splats[..., 5], colors=splats[..., 6:9],
        depths=splats[..., 9], radii=radii,
    )  # fmt: skip


def _prepare(means, quats, scales, opacities, colors, viewmats, Ks, width, height, near, far, background, mode,
             sh_degree, render_depth, tile_size):  # fmt: skip
    """Check every argument; return contiguous tensors (cameras in the dtype of ``means``), coeffs
    ``[N,K,3]`` and the settings."""
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
    dtype = means.dtype
    common_device(
        means=means, quats=quats, scales=scales, opacities=opacities, colors=colors, viewmats=viewmats, Ks=Ks,
        background=background,
    )  # fmt: skip
    settings = _make_settings(colors, width, height, near, far, mode, sh_degree, render_depth, tile_size)
    means, viewmats = _camera_relative(means, viewmats.detach())
    viewmats = viewmats.to(dtype).contiguous()
    Ks = Ks.detach().to(dtype).contiguous()
    coeffs = colors if colors.dim() == 3 else colors.unsqueeze(1)
    _check_key_bits(viewmats.shape[0], settings)
    return means, quats, scales, opacities, coeffs, viewmats, Ks, background, settings


def _camera_relative(means: torch.Tensor, viewmats: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Means and viewmats re-expressed about the mean camera centre ``o`` (rounded to the means' dtype), so that
    float32 positions are relative to the cameras: ``R x + t`` no longer cancels for a scene far from the world
    origin. ``means - o`` is one elementwise op (its gradient is the identity); ``viewmats @ T(o)`` is composed in
    float64. A pure translation of the world: images and gradients are unchanged."""
    if means.dtype == torch.float64 or means.shape[0] == 0:
        return means, viewmats
    with torch.autocast(means.device.type, enabled=False):
        origin = rigid_inverse(viewmats.to(torch.float64))[:, :3, 3].mean(dim=0).to(means.dtype)
        shift = torch.eye(4, dtype=torch.float64, device=viewmats.device)
        shift[:3, 3] = origin.to(torch.float64)
        return means - origin, viewmats.to(torch.float64) @ shift


def _make_settings(colors, width, height, near, far, mode, sh_degree, render_depth, tile_size) -> _Settings:
    for name, value in (("width", width), ("height", height)):
        if isinstance(value, bool) or int(value) != value or value < 1:
            raise InputError(f"{name} must be a positive integer, got {value!r}")
    if mode not in MODES:
        raise InputError(f"mode must be one of {MODES}, got {mode!r}")
    if isinstance(tile_size, bool) or int(tile_size) != tile_size or not 1 <= tile_size <= 32:
        raise InputError(f"tile_size must be an integer in 1..32, got {tile_size!r}")
    if not (math.isfinite(near) and near > 0 and far > near):
        raise InputError(f"near and far must satisfy 0 < near < far, got near={near}, far={far}")
    degree = _sh_degree(colors, sh_degree)
    return _Settings(int(width), int(height), float(near), float(far), degree, mode == "antialiased",
                     bool(render_depth), int(tile_size))  # fmt: skip


def _sh_degree(colors: torch.Tensor, sh_degree: int | None) -> int:
    """-1 for RGB colours, else the SH degree to evaluate (checked against K)."""
    if colors.dim() == 2:
        if sh_degree is not None:
            raise InputError("sh_degree is given but colors is [N,3] RGB; pass SH coefficients [N,K,3]")
        return -1
    K = colors.shape[1]
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


def _check_key_bits(num_cameras: int, settings: _Settings) -> None:
    if 32 + _tile_bits(settings) + _camera_bits(num_cameras) > 63:
        raise InputError(
            f"{num_cameras} cameras x {settings.tiles_x * settings.tiles_y} tiles do not fit the 31-bit "
            "camera|tile part of the sort key; render fewer cameras per call or use larger tiles"
        )


def _tile_bits(settings: _Settings) -> int:
    return max(1, (settings.tiles_x * settings.tiles_y - 1).bit_length())


def _camera_bits(num_cameras: int) -> int:
    return (num_cameras - 1).bit_length()


def _inclusive_scan(tile_counts: torch.Tensor, device: torch.device) -> torch.Tensor:
    """Inclusive prefix sum of the int64 tile counts by ``wp.utils.array_scan`` (on torch's stream)."""
    offsets = torch.empty_like(tile_counts)
    with warp_scope(device):
        wp.utils.array_scan(to_warp(tile_counts), to_warp(offsets), inclusive=True)
    return offsets


def _read_count_and_flags(offsets, flags, background) -> tuple[int, list[int]]:
    """The single host sync of a forward: intersection count, validation flags, non-finite background."""
    parts = [offsets[-1:], flags.to(torch.int64)]
    if background is not None:
        parts.append((~torch.isfinite(background)).sum().reshape(1))
    values = torch.cat(parts).tolist()
    return int(values[0]), [int(v) for v in values[1:]]


def _raise_on_flags(flag_values: list[int]) -> None:
    for slot, name in _ARGUMENT_OF_FLAG.items():
        if flag_values[slot]:
            raise InputError(f"{name} holds non-finite values (NaN or Inf) in {flag_values[slot]} row(s)")
    if flag_values[raster_project.HUGE_COVARIANCE]:
        raise InputError(
            f"scales: {flag_values[raster_project.HUGE_COVARIANCE]} (camera, Gaussian) pair(s) have a 2D covariance "
            "that overflows the float dtype (scales far too large); use float64 or smaller scales"
        )
    if flag_values[raster_project.ZERO_QUATS]:
        raise InputError(f"quats has {flag_values[raster_project.ZERO_QUATS]} zero quaternion(s) (no rotation)")
    if len(flag_values) > raster_project.NUM_FLAGS and flag_values[raster_project.NUM_FLAGS]:
        raise InputError(f"background holds {flag_values[raster_project.NUM_FLAGS]} non-finite value(s)")


def _check_budget(count: int, max_bytes: int) -> None:
    needed = count * BYTES_PER_INTERSECTION
    if needed > max_bytes or count >= 2**31:
        raise RasterMemoryError(
            f"{count:,} tile intersections need {needed:,} bytes ({needed / 2**30:.2f} GiB) of sort buffers, "
            f"over max_intersection_bytes={max_bytes:,}; render fewer or smaller Gaussians, or raise the budget"
        )


def _bin_intersections(splats, radii, tile_counts, offsets, count, num_cameras, settings: _Settings):
    """Sorted row ids ``[count]`` and per-tile ranges ``[B*tiles, 2]`` (int32)."""
    device = splats.device
    num_tiles = num_cameras * settings.tiles_x * settings.tiles_y
    ranges = torch.zeros(num_tiles, 2, dtype=torch.int32, device=device)
    keys = torch.empty(2 * count, dtype=torch.int64, device=device)
    values = torch.empty(2 * count, dtype=torch.int32, device=device)
    if count == 0:
        return ranges, values
    rows = splats.detach().reshape(-1, raster_project.ROW_WIDTH)
    tile_bits = _tile_bits(settings)
    with warp_scope(device) as wdev:
        launch(
            raster_tiles.emit_intersections,
            rows.shape[0],
            [
                rows,
                vectors(radii.reshape(-1, 2)),
                tile_counts,
                offsets,
                splats.shape[1],
                settings.tile_size,
                settings.tiles_x,
                settings.tiles_y,
                tile_bits,
                keys,
                values,
            ],
            wdev,
        )
        wp.utils.radix_sort_pairs(
            to_warp(keys), to_warp(values), count, 0, 32 + tile_bits + _camera_bits(num_cameras)
        )
        launch(
            raster_tiles.tile_ranges,
            count,
            [keys, count, tile_bits, settings.tiles_x * settings.tiles_y, ranges],
            wdev,
        )
    return ranges, values[:count]


def _empty_render(means, viewmats, background, settings: _Settings):
    """Output for N = 0: the background (or black), zero alpha and depth."""
    B, H, W = viewmats.shape[0], settings.height, settings.width
    zeros = means.new_zeros(B, H, W, 1)
    if background is not None:
        color = background[:, None, None, :].expand(B, H, W, 3).clone()
    else:
        color = means.new_zeros(B, H, W, 3)
    radii = torch.zeros(B, 0, 2, dtype=torch.int32, device=means.device)
    visible = torch.zeros(B, dtype=torch.int64, device=means.device)
    depth = zeros.clone() if settings.render_depth else None
    return color, depth, zeros, RasterMeta(radii, visible, 0, settings.tile_size)
