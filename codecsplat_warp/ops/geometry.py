"""Differentiable geometry ops over the Warp kernels: unprojection, reprojection averaging, plane sweeps.

All ops take their device from the input tensors (CPU or CUDA, launched on torch's current stream), accept
float32 or float64 (float16/bfloat16 inputs, e.g. under autocast, are computed in float32 and returned in
float32), and follow :mod:`codecsplat_warp.cameras` conventions. Camera parameters are treated as constants
(no gradient flows into ``Cameras``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..cameras import Cameras
from ..checks import check_same_dtype, check_tensor, check_values, common_device
from ..device import launch, warp_scope
from ..errors import DeviceMismatchError, InputError
from ..kernels import reproject as reproject_kernels
from ..kernels import unproject as unproject_kernels
from .primitives import PER_PIECE, launch_by_rows

_LOW_PRECISION = (torch.float16, torch.bfloat16)
_ACCEPTED = (torch.float32, torch.float64, torch.float16, torch.bfloat16)


# --------------------------------------------------------------------------------------------------
# Public ops
def unproject(depth: torch.Tensor, cameras: Cameras) -> torch.Tensor:
    """World-space points of every pixel centre at its depth.

    Args:
        depth: [V,H,W] camera-z depth per pixel, > 0 and finite. H, W may differ from the cameras' image size
            (intrinsics are rescaled to the depth grid).
        cameras: V cameras on the same device.

    Returns:
        points [V,H,W,3] in world coordinates, dtype of ``depth`` (float32 for half inputs). Differentiable
        with respect to ``depth``.
    """
    depth = _float_input("depth", depth, ("V", "H", "W"), {"V": cameras.num_views})
    check_values(positive={"depth": depth})
    grid = _kernel_cameras(cameras, depth, depth.shape[2], depth.shape[1], None)
    return _Unproject.apply(depth, grid.intrinsics, grid.c2w)


def reproject_average(
    feat: torch.Tensor,
    depth: torch.Tensor,
    cameras: Cameras,
    neighbours: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Geometry-aligned multi-view feature A(F, D) of paper Eq. 3.

    For each reference view r and pixel, back-project with ``depth[r]``, project into each source view
    (``neighbours[r]``, default every s != r), bilinearly sample ``feat[s]`` where the point is in front of the
    source camera and inside its image, and average the valid samples (zero where none is valid).

    Args:
        feat: [V,C,h,w] features; the grid may be smaller than the cameras' image (intrinsics are rescaled).
        depth: [V,h,w] reference depths (camera z), > 0.
        cameras: V cameras at image size, same device.
        neighbours: optional [V,M] integer source-view indices per reference view.

    Returns:
        (avg [V,C,h,w] in feat's dtype, count [V,h,w] int32 number of valid samples). ``avg`` is
        differentiable with respect to ``feat`` and ``depth`` (through the sampling coordinates).
    """
    dims = {"V": cameras.num_views}
    feat = _float_input("feat", feat, ("V", "C", "h", "w"), dims)
    depth = _float_input("depth", depth, ("V", "h", "w"), dims)
    common_device(feat=feat, depth=depth)
    check_same_dtype(feat=feat, depth=depth)
    check_values(finite={"feat": feat}, positive={"depth": depth})
    grid = _kernel_cameras(cameras, feat, feat.shape[3], feat.shape[2], neighbours)
    return _ReprojectAverage.apply(feat, depth, grid.intrinsics, grid.rel, grid.neighbours)


def plane_sweep_cost_volume(
    feat: torch.Tensor,
    candidates: torch.Tensor,
    cameras: Cameras,
    neighbours: torch.Tensor | None = None,
) -> torch.Tensor:
    """Plane-sweep correlation volume without materialising per-source warped copies.

    ``cost[r, k, y, x]`` is the mean over valid source views s of ``<feat[r,:,y,x], Warp_s->r(feat[s]; depth =
    candidates[r, k])> / sqrt(C)`` (validity and sampling as in :func:`reproject_average`; 0 where no source
    is valid).

    Args:
        feat: [V,C,h,w] matching features (grid may be smaller than the image).
        candidates: [V,D] or [D] constant depths of the sweep planes (camera z), > 0.
        cameras: V cameras at image size.
        neighbours: optional [V,M] source-view indices per reference view (default: every other view).

    Returns:
        cost [V,D,h,w], differentiable with respect to ``feat`` (reference and source features).
    """
    dims = {"V": cameras.num_views}
    feat = _float_input("feat", feat, ("V", "C", "h", "w"), dims)
    if isinstance(candidates, torch.Tensor) and candidates.dim() == 1:
        candidates = candidates[None].expand(cameras.num_views, -1)
    candidates = _float_input("candidates", candidates, ("V", "D"), dims)
    common_device(feat=feat, candidates=candidates)
    check_same_dtype(feat=feat, candidates=candidates)
    check_values(finite={"feat": feat}, positive={"candidates": candidates})
    grid = _kernel_cameras(cameras, feat, feat.shape[3], feat.shape[2], neighbours)
    return _CostVolume.apply(feat, candidates, grid.intrinsics, grid.rel, grid.neighbours)


def inverse_depth_candidates(cameras: Cameras, num: int) -> torch.Tensor:
    """[V,num] depths uniform in inverse depth from each view's far (index 0) to its near (index num-1)."""
    if num < 2:
        raise InputError(f"num depth candidates must be >= 2, got {num}")
    s = torch.linspace(0.0, 1.0, num, dtype=cameras.dtype, device=cameras.device)
    inv_near, inv_far = 1.0 / cameras.near[:, None], 1.0 / cameras.far[:, None]
    return 1.0 / (inv_far + s[None] * (inv_near - inv_far))


def all_other_views(num_views: int, device: torch.device | str = "cpu") -> torch.Tensor:
    """[V,V-1] int32: for each view r, every other view in increasing order."""
    idx = torch.arange(num_views, device=device)
    grid = idx[None].expand(num_views, -1)
    keep = grid != idx[:, None]
    return grid[keep].reshape(num_views, max(num_views - 1, 0)).to(torch.int32)


def nearest_views(cameras: Cameras, k: int, scenes: int = 1) -> torch.Tensor:
    """[V,k] int32: each view's k nearest other views by camera-centre distance (ties by index).

    With ``scenes`` > 1 the V views are that many scenes of V / scenes consecutive views each (a training
    batch), and a view's neighbours are taken from its own scene only (indices stay global).
    """
    V = cameras.num_views
    if scenes < 1 or V % scenes:
        raise InputError(f"scenes must divide the {V} views into equal groups, got scenes={scenes}")
    per_scene = V // scenes
    if not 0 < k < per_scene:
        raise InputError(f"k must be in [1, {per_scene - 1}] for {per_scene} views per scene, got {k}")
    centers = cameras.centers.to(torch.float64)
    dist = torch.cdist(centers, centers)
    scene = torch.arange(V, device=dist.device) // per_scene
    dist = dist.masked_fill(scene[:, None] != scene[None, :], float("inf"))
    dist.fill_diagonal_(float("inf"))
    return dist.topk(k, dim=1, largest=False).indices.to(torch.int32)


# --------------------------------------------------------------------------------------------------
# Autograd functions (tensors are already checked, contiguous and on one device)
class _Unproject(torch.autograd.Function):
    @staticmethod
    def forward(ctx, depth, intrinsics, c2w):
        V, H, W = depth.shape
        points = torch.empty(V, H, W, 3, dtype=depth.dtype, device=depth.device)
        with warp_scope(depth.device) as wdev:
            launch(unproject_kernels.unproject_forward, (V, H, W), [depth, intrinsics, c2w, points], wdev)
        ctx.save_for_backward(intrinsics, c2w)
        return points

    @staticmethod
    def backward(ctx, grad_points):
        intrinsics, c2w = ctx.saved_tensors
        grad_points = grad_points.contiguous()
        V, H, W, _ = grad_points.shape
        grad_depth = torch.empty(V, H, W, dtype=grad_points.dtype, device=grad_points.device)
        with warp_scope(grad_points.device) as wdev:
            launch(unproject_kernels.unproject_backward, (V, H, W), [grad_points, intrinsics, c2w, grad_depth], wdev)
        return grad_depth, None, None


class _ReprojectAverage(torch.autograd.Function):
    @staticmethod
    def forward(ctx, feat, depth, intrinsics, rel, neighbours):
        V, C, H, W = feat.shape
        avg = torch.zeros_like(feat)
        count = torch.empty(V, H, W, dtype=torch.int32, device=feat.device)
        launch_by_rows(reproject_kernels.reproject_average_forward, (V, H, W),
                       [feat, depth, intrinsics, rel, neighbours, avg, count], feat.device)
        ctx.save_for_backward(feat, depth, intrinsics, rel, neighbours, count)
        ctx.mark_non_differentiable(count)
        return avg, count

    @staticmethod
    def backward(ctx, grad_avg, _grad_count):
        feat, depth, intrinsics, rel, neighbours, count = ctx.saved_tensors
        grad_avg = grad_avg.contiguous()
        grad_depth = torch.empty_like(depth)
        V, _, H, W = feat.shape
        grad_feat = launch_by_rows(reproject_kernels.reproject_average_backward, (V, H, W),
                                   [grad_avg, feat, depth, intrinsics, rel, neighbours, count, PER_PIECE, grad_depth],
                                   feat.device, scatter_like=feat)  # fmt: skip
        return grad_feat, grad_depth, None, None, None


class _CostVolume(torch.autograd.Function):
    @staticmethod
    def forward(ctx, feat, candidates, intrinsics, rel, neighbours):
        V, _, H, W = feat.shape
        D = candidates.shape[1]
        cost = torch.empty(V, D, H, W, dtype=feat.dtype, device=feat.device)
        count = torch.empty(V, D, H, W, dtype=torch.int32, device=feat.device)
        launch_by_rows(reproject_kernels.cost_volume_forward, (V, D, H, W),
                       [feat, candidates, intrinsics, rel, neighbours, cost, count], feat.device)
        ctx.save_for_backward(feat, candidates, intrinsics, rel, neighbours, count)
        return cost

    @staticmethod
    def backward(ctx, grad_cost):
        feat, candidates, intrinsics, rel, neighbours, count = ctx.saved_tensors
        grad_cost = grad_cost.contiguous()
        grad_feat = launch_by_rows(reproject_kernels.cost_volume_backward, count.shape,
                                   [grad_cost, feat, candidates, intrinsics, rel, neighbours, count, PER_PIECE],
                                   feat.device, scatter_like=feat)  # fmt: skip
        return grad_feat, None, None, None, None


# --------------------------------------------------------------------------------------------------
# Helpers
def _float_input(name: str, t, shape, dims) -> torch.Tensor:
    t = check_tensor(name, t, shape, _ACCEPTED, dims)
    if t.numel() == 0:
        raise InputError(f"{name} is empty (shape {tuple(t.shape)})")
    return t.float() if t.dtype in _LOW_PRECISION else t


@dataclass(frozen=True)
class _KernelCameras:
    """Camera arrays in a kernel's form, for one feature grid and dtype (all contiguous, on the cameras' device).

    intrinsics [V,4] (fx, fy, cx, cy) in pixels of the grid; c2w [V,4,4]; rel [V,M,4,4] reference-to-source
    transforms composed in float64; neighbours [V,M] int32 (None for ops without sources).
    """

    intrinsics: torch.Tensor
    c2w: torch.Tensor
    rel: torch.Tensor | None
    neighbours: torch.Tensor | None


def _kernel_cameras(cameras: Cameras, like: torch.Tensor, width: int, height: int, neighbours) -> _KernelCameras:
    """Kernel-ready camera arrays for a width x height grid in ``like``'s dtype, memoized on ``cameras``.

    Building them takes a dozen small device ops and a host sync (neighbour index checks); an op called again
    with the same cameras object (and the same, unmodified ``neighbours`` tensor) reuses them.
    """
    if not isinstance(cameras, Cameras):
        raise InputError(f"cameras must be a codecsplat_warp.cameras.Cameras, got {type(cameras).__name__}")
    if cameras.device != like.device:
        raise DeviceMismatchError(f"cameras are on {cameras.device} but the tensors are on {like.device}")
    given = None if neighbours is None else (id(neighbours), getattr(neighbours, "_version", None))
    key = ("kernel", like.dtype, width, height, given)

    def build() -> tuple[_KernelCameras, object]:
        cams = cameras.to(dtype=like.dtype).rescaled(width, height)
        if neighbours is None:
            index = all_other_views(cams.num_views, like.device)
        else:
            index = _checked_neighbours(neighbours, cams.num_views, like.device)
        rel = cameras.to(dtype=torch.float64).relative_transforms(index).to(like.dtype).contiguous()
        # the given neighbours tensor is kept alive with the entry, so its id cannot be reused while cached
        return _KernelCameras(cams.pixel_intrinsics().contiguous(), cams.c2w.contiguous(), rel, index), neighbours

    with torch.autocast(like.device.type, enabled=False):  # camera algebra in full precision, cached as such
        return cameras.memoized(key, build)[0]


def _checked_neighbours(neighbours, num_views: int, device: torch.device) -> torch.Tensor:
    """[V,M] int32 contiguous copy of valid source-view indices (InputError otherwise)."""
    if not isinstance(neighbours, torch.Tensor) or neighbours.dim() != 2 or neighbours.shape[0] != num_views:
        got = tuple(neighbours.shape) if isinstance(neighbours, torch.Tensor) else type(neighbours).__name__
        raise InputError(f"neighbours must be a [V={num_views},M] integer tensor, got {got}")
    if neighbours.dtype.is_floating_point or neighbours.dtype == torch.bool:
        raise InputError(f"neighbours must hold integer view indices, got dtype {neighbours.dtype}")
    if neighbours.device != device:
        raise DeviceMismatchError(f"neighbours are on {neighbours.device} but feat is on {device}")
    if neighbours.numel() and bool(((neighbours < 0) | (neighbours >= num_views)).any()):
        raise InputError(f"neighbours must index views in [0, {num_views - 1}]")
    return neighbours.to(torch.int32).contiguous()
