"""Multi-view stereo depth of a posed scene: source view selection, a plane sweep with windowed NCC, and a
geometric consistency filter (the Warp kernels are in :mod:`codecsplat_warp.kernels.mvs`).

For every view r (the *reference*):

1. **Sources** (:func:`select_sources`): a grid of r's pixels at a few depths from its near to its far (uniform in
   log depth) is projected into every other view; the fraction that lands inside is the *overlap*. Views with enough overlap,
   a triangulation angle at the scene's middle depth (geometric mean of near and far) within a useful range and
   optical axes not too far apart are candidates; the best ``num_sources`` by overlap times a preference for
   angles near ``good_triangulation_deg`` are r's sources.
2. **Plane sweep**: ``num_planes`` fronto-parallel planes uniform in inverse depth from far to near. The cost of
   a plane is 1 - NCC of the grey-level window around the pixel (``2 * window_radius + 1`` samples a side,
   ``window_step`` pixels apart, each weighted by its likeness to the centre pixel: ``support_contrast``) with the
   source image warped by the plane's homography (bilinear sampling), aggregated over the sources as the mean of
   the best half (occlusion-robust). The winner is refined by a finer sweep around it, with fronto-parallel and
   slanted planes (``slant_degrees``), and a parabola fit in inverse depth.
3. **Photometric confidence**: a depth is dropped where the window's grey-level standard deviation is below
   ``min_texture`` or the aggregated NCC of the winner is below ``min_ncc``.
4. **Geometric consistency**: a depth is kept where at least ``min_consistent_views`` source views agree: the
   pixel unprojected at its depth, projected into the source, carried back with the source's depth there lands
   within ``max_reprojection_px`` pixels of the pixel and within ``max_relative_depth`` of its depth. The kept
   depth is the mean of the view's own and the agreeing views' depths.

No gradients. The same kernels run on CPU (launches split by image rows over threads) and CUDA (launches split
by views, ``views_per_launch`` at a time).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch

from ..cameras import Cameras, rigid_inverse
from ..checks import check_tensor, check_values
from ..errors import InputError, MVSError
from ..kernels import mvs as mvs_kernels
from ..mvs_config import MAX_SOURCES, MVSConfig
from .geometry import plane_sweep_cost_volume
from .primitives import launch_by_rows

GRAY_WEIGHTS = (0.299, 0.587, 0.114)
"""RGB -> grey level weights (ITU-R BT.601 luma)."""

FLAT_WINDOW_NORM = 1e-3
"""A window whose mean-free grey levels have a smaller norm is flat: :func:`window_ncc_features` leaves it near 0."""

SELECTION_GRID = 12
"""Pixels a side of the grid :func:`select_sources` projects into the candidate views."""

SELECTION_DEPTHS = 5
"""Depths (uniform in log depth from near to far) at which :func:`select_sources` projects the grid."""


@dataclass(frozen=True)
class SourceViews:
    """The source views of every reference view (:func:`select_sources`), best first.

    Attributes:
        index: int64 [V,K] source view indices, -1 after a view's last source (K = ``MVSConfig.num_sources``).
        overlap: float64 [V,K] fraction of the reference's pixel grid the source sees (0 where index is -1).
        angle_deg: float64 [V,K] median triangulation angle at the middle depth [degrees] (0 where index is -1).
    """

    index: torch.Tensor
    overlap: torch.Tensor
    angle_deg: torch.Tensor

    @property
    def count(self) -> torch.Tensor:
        """int64 [V] number of sources of each view."""
        return (self.index >= 0).sum(1)


@dataclass(frozen=True)
class MVSDepth:
    """Result of :func:`mvs_depth` (tensors on the images' device; float tensors in the images' dtype).

    Attributes:
        depth: [V,H,W] camera-z depth in scene units where kept, 0 elsewhere.
        mask: bool [V,H,W], True where the depth is kept (photometrically confident and consistent).
        sources: :class:`SourceViews` (on the CPU).
        ncc: [V,H,W] aggregated NCC of the winner plane (-1 where no plane is seen by any source).
        texture: [V,H,W] standard deviation of the window's grey levels (in [0,1]).
        raw_depth: [V,H,W] winner depth before the confidence and consistency filters (0 where no plane is seen).
        consistent_views: int32 [V,H,W] source views that agree with the confident depth.
    """

    depth: torch.Tensor
    mask: torch.Tensor
    sources: SourceViews
    ncc: torch.Tensor
    texture: torch.Tensor
    raw_depth: torch.Tensor
    consistent_views: torch.Tensor

    @property
    def coverage(self) -> torch.Tensor:
        """float64 [V] fraction of each view's pixels with a kept depth."""
        return self.mask.flatten(1).double().mean(1)


# --------------------------------------------------------------------------------------------------
# Public functions
def _gray_levels(images: torch.Tensor) -> torch.Tensor:
    """Grey levels [V,H,W] (contiguous, images' dtype) of RGB ``images`` [V,3,H,W] by :data:`GRAY_WEIGHTS`."""
    weights = images.new_tensor(GRAY_WEIGHTS)
    return torch.einsum("vchw,c->vhw", images, weights).contiguous()


def window_ncc_features(images: torch.Tensor, window: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Each pixel's grey-level window as a unit vector, so that a dot product of two is their NCC.

    Args:
        images: [V,3,H,W] RGB in [0,1] (float32 or float64).
        window: odd side of the square window in pixels (>= 3); border pixels are repeated outside the image.

    Returns:
        (features [V,window**2,H,W]: the window's grey levels minus their mean, scaled to norm
        sqrt(window) (so that :func:`~codecsplat_warp.ops.geometry.plane_sweep_cost_volume`, which divides the
        dot product by sqrt(channels), gives the NCC in [-1, 1]); 0 where the window is flat,
        texture [V,H,W]: the window's grey-level standard deviation).
    """
    images = check_tensor("images", images, ("V", 3, "H", "W"))
    if window < 3 or window % 2 == 0:
        raise InputError(f"window must be an odd number >= 3, got {window}")
    V, _, H, W = images.shape
    padded = torch.nn.functional.pad(_gray_levels(images)[:, None], (window // 2,) * 4, mode="replicate")
    patches = torch.nn.functional.unfold(padded, window).reshape(V, window * window, H, W)
    patches = patches - patches.mean(1, keepdim=True)
    norm = patches.norm(dim=1, keepdim=True)
    features = patches * (window ** 0.5 / norm.clamp_min(FLAT_WINDOW_NORM))
    return features, norm[:, 0] / window


def photometric_cost_volume(images: torch.Tensor, candidates: torch.Tensor, cameras: Cameras, window: int,
                            neighbours: torch.Tensor | None = None) -> torch.Tensor:
    """Plane sweep of windowed NCC: ``cost[r, k, y, x]`` is the mean over r's source views of the NCC of pixel
    (y, x)'s grey-level window with the source's window at the point where the pixel's ray meets depth
    ``candidates[r, k]`` (fronto-parallel windows, bilinear sampling: an approximation of the homography-warped
    window of :func:`mvs_depth` that holds for small baselines). No gradients (the images are inputs).

    Args:
        images: [V,3,H,W] RGB in [0,1], the cameras' size.
        candidates: [V,D] or [D] depths (camera z), > 0.
        cameras: the V cameras.
        window: odd window side in pixels (>= 3).
        neighbours: optional [V,M] source views of each view (default: every other view).

    Returns:
        [V,D,H,W] NCC in [-1, 1] (0 where no source sees the point or a window is flat), images' dtype.
    """
    with torch.no_grad():
        features, _ = window_ncc_features(images, window)
        return plane_sweep_cost_volume(features, candidates.to(features.dtype), cameras, neighbours)


def mvs_depth(images: torch.Tensor, cameras: Cameras, config: MVSConfig = MVSConfig(),
              progress: Callable[[int], None] | None = None) -> MVSDepth:  # fmt: skip
    """Semi-dense depth and a confidence mask of every view of a posed scene (see the module docstring).

    Args:
        images: [V,3,H,W] RGB in [0,1], float32 or float64 (the dtype the kernels run in), V >= 3.
        cameras: V cameras with near/far on the images' device; at any image size covering the same extent
            (intrinsics are rescaled to W x H).
        config: see :class:`MVSConfig`.
        progress: called with the number of reference views swept after each launch.

    Returns:
        :class:`MVSDepth`.

    Raises:
        MVSError: fewer than 3 views, or a view with no usable source view (naming it; unless
            ``config.allow_unmatched``).
        InputError: wrong shape, dtype, device or non-finite images; bad config.
    """
    if not isinstance(config, MVSConfig):
        raise InputError(f"config must be an MVSConfig, got {type(config).__name__}")
    if not isinstance(cameras, Cameras):
        raise InputError(f"cameras must be a codecsplat_warp.cameras.Cameras, got {type(cameras).__name__}")
    images = check_tensor("images", images, ("V", 3, "H", "W"), dims={"V": cameras.num_views})
    if cameras.device != images.device:
        raise InputError(f"cameras are on {cameras.device} but images are on {images.device}")
    check_values(finite={"images": images})
    V, _, H, W = images.shape
    sources = select_sources(cameras, config)
    grid = _SweepInputs.build(images, cameras.rescaled(W, H), sources, config)
    with torch.no_grad():
        raw_depth, ncc, texture = _sweep(grid, config, progress)
        confident = (raw_depth > 0) & (ncc >= config.min_ncc) & (texture >= config.min_texture)
        photometric = torch.where(confident, raw_depth, torch.zeros_like(raw_depth))
        agree, fused = _consistency(grid, photometric, config)
        mask = confident & (agree >= config.min_consistent_views) & _in_sweep_range(fused, cameras)
        depth = torch.where(mask, fused, torch.zeros_like(raw_depth))
    return MVSDepth(depth=depth, mask=mask, sources=sources, ncc=ncc, texture=texture, raw_depth=raw_depth,
                    consistent_views=agree)


def _in_sweep_range(depth: torch.Tensor, cameras: Cameras) -> torch.Tensor:
    """bool [V,H,W]: ``depth`` [V,H,W] within its view's [near, far], the range the sweep tested (refinement and the
    fusion of agreeing views can step past its ends, where no plane vouches for the depth)."""
    near = cameras.near.to(depth.dtype)[:, None, None]
    far = cameras.far.to(depth.dtype)[:, None, None]
    return (depth >= near) & (depth <= far)


def _plane_normals(config: MVSConfig) -> torch.Tensor:
    """float64 [1 + 4 * len(config.slant_degrees), 3] unit normals (camera frame) of the refinement planes: the
    fronto-parallel (0, 0, 1) first, then each slant towards +x, -x, +y and -y."""
    normals = [(0.0, 0.0, 1.0)]
    for angle in config.slant_degrees:
        tilt, facing = math.sin(math.radians(angle)), math.cos(math.radians(angle))
        normals += [(tilt, 0.0, facing), (-tilt, 0.0, facing), (0.0, tilt, facing), (0.0, -tilt, facing)]
    return torch.tensor(normals, dtype=torch.float64)


def select_sources(cameras: Cameras, config: MVSConfig = MVSConfig()) -> SourceViews:
    """The source views of every view of a posed scene (step 1 of the module docstring); deterministic.

    Raises:
        MVSError: fewer than 3 views, or a view without a candidate source (naming it, with its best overlap)
            unless ``config.allow_unmatched`` (its row of ``index`` is then all -1).
    """
    V = cameras.num_views
    if V < 3:
        raise MVSError(f"multi-view stereo needs at least 3 views, got {V}")
    cams = cameras.to("cpu", torch.float64)
    overlap, angle, view_angle = _pair_geometry(cams)
    eye = torch.eye(V, dtype=torch.bool)
    candidate = ((overlap >= config.min_overlap) & (angle >= config.min_triangulation_deg)
                 & (angle <= config.max_triangulation_deg) & (view_angle <= config.max_view_angle_deg) & ~eye)
    for r in range(V):
        if not bool(candidate[r].any()) and not config.allow_unmatched:
            raise MVSError(_no_source_message(r, overlap[r], angle[r], view_angle[r], eye[r], config))
    width = torch.where(angle < config.good_triangulation_deg, config.good_triangulation_deg / 3,
                        config.good_triangulation_deg)
    score = overlap * torch.exp(-0.5 * ((angle - config.good_triangulation_deg) / width) ** 2)
    score = torch.where(candidate, score, torch.full_like(score, -1.0))
    order = torch.sort(score, dim=1, descending=True, stable=True).indices[:, : config.num_sources]
    chosen = torch.gather(candidate, 1, order)
    index = torch.where(chosen, order, torch.full_like(order, -1))
    pick = lambda values: torch.where(chosen, torch.gather(values, 1, order), torch.zeros_like(order, dtype=values.dtype))  # noqa: E731
    return SourceViews(index=index, overlap=pick(overlap), angle_deg=pick(angle))


# --------------------------------------------------------------------------------------------------
# Steps
def _pair_geometry(cams: Cameras) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """float64 [V,V] overlap, median triangulation angle [deg] at the middle depth, and optical-axis angle [deg]
    of every (reference, candidate) pair (rows: reference)."""
    V = cams.num_views
    steps = (torch.arange(SELECTION_GRID, dtype=torch.float64) + 0.5) / SELECTION_GRID
    v_grid, u_grid = torch.meshgrid(steps * cams.height, steps * cams.width, indexing="ij")
    K = cams.K
    rays = torch.stack([(u_grid.reshape(1, -1) - K[:, 0, 2:3]) / K[:, 0, 0:1],
                        (v_grid.reshape(1, -1) - K[:, 1, 2:3]) / K[:, 1, 1:2],
                        torch.ones(V, u_grid.numel(), dtype=torch.float64)], dim=-1)  # [V,P,3]
    s = torch.linspace(0.0, 1.0, SELECTION_DEPTHS, dtype=torch.float64)
    depths = cams.near[:, None] * (cams.far / cams.near)[:, None] ** s[None]
    c2w, w2c = cams.c2w, cams.w2c
    points = (rays[:, None] * depths[:, :, None, None]).reshape(V, -1, 3)  # [V, depths * P, 3] camera frames
    world = points @ c2w[:, :3, :3].transpose(1, 2) + c2w[:, None, :3, 3]
    local = torch.einsum("sij,rnj->rsni", w2c[:, :3, :3], world) + w2c[None, :, None, :3, 3]  # [V,V,N,3]
    z = local[..., 2]
    u = K[None, :, None, 0, 0] * local[..., 0] / z + K[None, :, None, 0, 2]
    v = K[None, :, None, 1, 1] * local[..., 1] / z + K[None, :, None, 1, 2]
    inside = (z > 0) & (u >= 0) & (u <= cams.width) & (v >= 0) & (v <= cams.height)
    overlap = inside.double().mean(-1)
    middle = rays * torch.sqrt(cams.near * cams.far)[:, None, None]
    mid_world = middle @ c2w[:, :3, :3].transpose(1, 2) + c2w[:, None, :3, 3]  # [V,P,3]
    centres = c2w[:, :3, 3]
    to_ref = torch.nn.functional.normalize(mid_world - centres[:, None], dim=-1)  # [V,P,3]
    to_src = torch.nn.functional.normalize(mid_world[:, None] - centres[None, :, None], dim=-1)  # [V,V,P,3]
    cosine = (to_ref[:, None] * to_src).sum(-1).clamp(-1.0, 1.0)
    angle = torch.rad2deg(torch.acos(cosine)).median(-1).values
    axes = c2w[:, :3, 2]
    view_angle = torch.rad2deg(torch.acos((axes @ axes.T).clamp(-1.0, 1.0)))
    return overlap, angle, view_angle


def _no_source_message(r: int, overlap, angle, view_angle, self_mask, config: MVSConfig) -> str:
    """Why view r has no candidate source: its best overlap, and the angles of the best-overlapping view."""
    overlap = overlap.masked_fill(self_mask, -1.0)
    best = int(overlap.argmax())
    return (f"view {r} has no usable source view: the best overlap is {float(overlap[best]):.0%} with view {best} "
            f"(triangulation {float(angle[best]):.1f} deg, optical axes {float(view_angle[best]):.0f} deg apart); "
            f"a source needs overlap >= {config.min_overlap:.0%}, triangulation in [{config.min_triangulation_deg:g}, "
            f"{config.max_triangulation_deg:g}] deg and axes <= {config.max_view_angle_deg:g} deg apart")


@dataclass(frozen=True)
class _SweepInputs:
    """Kernel arrays of one scene (contiguous, on the images' device, in the images' dtype).

    gray [V,H,W]; intrinsics [V,4]; rel / back [V,K,4,4] reference-to-source transforms and their inverses;
    sources [V,K] int32 (a view's own index after its last source); count [V] int32; inv_range [V,2] (1/far,
    1/near); similarity [1] (``support_contrast``); normals [N,3] (:func:`_plane_normals`).
    """

    gray: torch.Tensor
    intrinsics: torch.Tensor
    rel: torch.Tensor
    back: torch.Tensor
    sources: torch.Tensor
    count: torch.Tensor
    inv_range: torch.Tensor
    similarity: torch.Tensor
    normals: torch.Tensor

    @staticmethod
    def build(images: torch.Tensor, cameras: Cameras, sources: SourceViews, config: MVSConfig) -> "_SweepInputs":
        dtype, device = images.dtype, images.device
        gray = _gray_levels(images)
        own = torch.arange(cameras.num_views)[:, None].expand_as(sources.index)
        padded = torch.where(sources.index >= 0, sources.index, own)
        cams64 = cameras.to(dtype=torch.float64)
        rel = cams64.relative_transforms(padded.to(cams64.device))
        to_kernel = lambda t: t.to(device=device, dtype=dtype).contiguous()  # noqa: E731
        return _SweepInputs(gray=gray, intrinsics=to_kernel(cams64.pixel_intrinsics()), rel=to_kernel(rel),
                            back=to_kernel(rigid_inverse(rel)),
                            sources=padded.to(device=device, dtype=torch.int32).contiguous(),
                            count=sources.count.to(device=device, dtype=torch.int32).contiguous(),
                            inv_range=to_kernel(torch.stack([1.0 / cams64.far, 1.0 / cams64.near], dim=-1)),
                            similarity=torch.tensor([config.support_contrast], dtype=dtype, device=device),
                            normals=to_kernel(_plane_normals(config)))


def _view_batches(num_views: int, device: torch.device, config: MVSConfig) -> list[tuple[int, int]]:
    """(first view, views) of each launch: one view at a time on the CPU, ``views_per_launch`` on CUDA."""
    per_launch = config.views_per_launch if device.type == "cuda" else 1
    return [(v, min(per_launch, num_views - v)) for v in range(0, num_views, per_launch)]


def _sweep(grid: _SweepInputs, config: MVSConfig, progress) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(raw depth, NCC, texture) [V,H,W] of every view by the plane-sweep kernel."""
    V, H, W = grid.gray.shape
    depth, ncc, texture = (torch.empty_like(grid.gray) for _ in range(3))
    done = 0
    for view0, views in _view_batches(V, grid.gray.device, config):
        launch_by_rows(mvs_kernels.plane_sweep_depth, (views, H, W),
                       [grid.gray, grid.intrinsics, grid.rel, grid.sources, grid.count, grid.inv_range, grid.similarity,
                        grid.normals, config.num_planes, config.refine_steps, config.window_radius, config.window_step,
                        depth, ncc, texture, view0], grid.gray.device)  # fmt: skip
        done += views
        if progress is not None:
            if grid.gray.is_cuda:
                torch.cuda.current_stream(grid.gray.device).synchronize()
            progress(done)
    return depth, ncc, texture


def _consistency(grid: _SweepInputs, depth: torch.Tensor, config: MVSConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """(int32 [V,H,W] number of source views that agree with ``depth``, [V,H,W] mean of ``depth`` and the
    agreeing views' depths) by the consistency kernel."""
    V, H, W = depth.shape
    tolerance = torch.tensor([config.max_reprojection_px, config.max_relative_depth], dtype=depth.dtype,
                             device=depth.device)
    agree = torch.empty(V, H, W, dtype=torch.int32, device=depth.device)
    fused = torch.empty_like(depth)
    launch_by_rows(mvs_kernels.consistent_views, (V, H, W),
                   [depth, grid.intrinsics, grid.rel, grid.back, grid.sources, grid.count, tolerance, agree, fused, 0],
                   depth.device)  # fmt: skip
    return agree, fused
