"""The stiff and extreme cases catalog (issue 8): ``python -m codecsplat_warp.bench.extreme --device cuda``.

Every :class:`Case` builds one small float64 problem on the CPU and names the op it exercises. A case either

* runs: the op on the chosen device in the case's dtype (float32 unless stated), forward and backward
  (gradient of a fixed random weighting of every output), and must give finite outputs, finite gradients,
  and a relative error against a float64 evaluation within the case's stated bound; or
* must raise a typed error (``error``): invalid input is refused, never turned into NaN output.

Rounding rule: the float64 evaluation runs on the *same* inputs as the op under test (rounded to the case's
dtype, then widened), so the error measures the op's arithmetic and not the rounding of its inputs. Camera
parameters (:class:`~codecsplat_warp.cameras.Cameras`, ``viewmats``, ``Ks``) stay float64 as loaders give
them; whatever the op does with them (casts, camera-relative composition) is part of what is measured.

Error: ``max |got - ref| / max |ref|`` per output and per gradient, the largest over them (absolute where
the reference is all zero); ``err fwd`` is over outputs, ``err bwd`` over gradients. The float64 evaluation
is the plain-torch reference of the op (:mod:`codecsplat_warp.reference`), on the CPU. Bounds come in tiers
(:data:`RASTER_F32`, :data:`GEOMETRY_F32`, :data:`POINTWISE_F32`, :data:`BF16_GRADIENT`), each about ten
times the largest error measured on well-conditioned float32 problems of its kind on the CPU, rounded up
to 1, 2 or 5 x 10^k; a case whose conditioning makes a larger error inherent states its own bound and why.

A case with ``known_bug`` documents a defect found by this catalog (in files this catalog may not change);
the test marks it ``xfail(strict=True)`` so the fix has to remove the mark. ``cuda_only`` cases are too slow
for the serial CPU backend; a smaller sibling covers the CPU.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from dataclasses import dataclass, field
from typing import Callable

import torch

from ..cameras import Cameras, intrinsics_matrix, rigid_inverse
from ..errors import CameraError, InputError
from ..export.files import write_json
from ..measure import format_table, machine_name
from ..model.heads import depth_from_normalized, normalized_from_depth
from ..ops.geometry import all_other_views, plane_sweep_cost_volume, reproject_average, unproject
from ..ops.raster import GAUSSIAN_ARGUMENTS, rasterize
from ..reference.geometry import cost_volume_reference, reproject_average_reference, unproject_reference
from ..reference.raster import rasterize_dense
from ..synthetic import make_rig, random_gaussians, rotation, smooth_depth
from .options import extreme_arguments

# --------------------------------------------------------------------------------------------------
# Catalog data structures
@dataclass(frozen=True)
class Problem:
    """One problem instance, float64 on the CPU.

    Attributes:
        inputs: tensors rounded to the case's dtype for the op under test (float64 widened for the reference).
        grad: names of the ``inputs`` that are differentiated.
        constants: camera parameters and index tensors, moved to the device but kept in their dtype.
        options: plain Python keyword arguments (image size, mode, ...).
    """

    inputs: dict[str, torch.Tensor]
    grad: tuple[str, ...] = ()
    constants: dict[str, object] = field(default_factory=dict)
    options: dict[str, object] = field(default_factory=dict)


@dataclass(frozen=True)
class Op:
    """An op under test and its float64 reference; both take the problem's arguments as keywords and
    return a tuple of float tensors (integer outputs such as counts converted, so they are compared too)."""

    name: str
    run: Callable[..., tuple[torch.Tensor, ...]]
    reference: Callable[..., tuple[torch.Tensor, ...]]


@dataclass(frozen=True)
class Case:
    """One catalog entry.

    Attributes:
        name: test id, ``<op>-<what is extreme>``.
        op: the op exercised.
        build: returns the float64 :class:`Problem`.
        bound: largest accepted relative error of the outputs (None for error cases).
        grad_bound: largest accepted relative error of the gradients (default: ``bound``).
        error: the typed exception the op must raise (then ``bound`` is None).
        match: regular expression the error message must contain (it names the bad argument).
        dtype: dtype the inputs are rounded to for the op under test.
        autocast: run the op's forward under ``torch.autocast(device, bfloat16)``.
        cuda_only: too slow for the serial CPU backend (a smaller sibling case runs there).
        known_bug: reason of a known defect (the test is ``xfail(strict=True)``).
        output_error: error function of the outputs (default :func:`relative_error`).
        note: why the case is hard, and why its bound is what it is.
    """

    name: str
    op: Op
    build: Callable[[], Problem]
    bound: float | None = None
    grad_bound: float | None = None
    error: type[Exception] | None = None
    match: str | None = None
    dtype: torch.dtype = torch.float32
    autocast: bool = False
    cuda_only: bool = False
    known_bug: str | None = None
    output_error: Callable[[torch.Tensor, torch.Tensor], float] | None = None
    note: str = ""

    @property
    def gradient_bound(self) -> float | None:
        return self.bound if self.grad_bound is None else self.grad_bound


# --------------------------------------------------------------------------------------------------
# Errors
def relative_error(got: torch.Tensor, ref: torch.Tensor) -> float:
    """``max |got - ref| / max |ref|`` (the absolute error where ``ref`` is all zero; 0 for empty tensors)."""
    if ref.numel() == 0:
        return 0.0
    diff = float((got.detach().cpu().double() - ref.detach().cpu().double()).abs().max())
    scale = float(ref.detach().abs().max())
    return diff / scale if scale > 0 else diff


def channel_relative_error(got: torch.Tensor, ref: torch.Tensor) -> float:
    """:func:`relative_error` per channel of ``[V,C,H,W]`` outputs, the largest over channels: for features
    whose channels differ by many orders of magnitude. Other outputs use :func:`relative_error`."""
    if got.dim() != 4:
        return relative_error(got, ref)
    return max(relative_error(got[:, c], ref[:, c]) for c in range(got.shape[1]))


# --------------------------------------------------------------------------------------------------
# Ops
def _reproject_outputs(avg_count) -> tuple[torch.Tensor, torch.Tensor]:
    avg, count = avg_count
    return avg, count.to(avg.dtype)


def _raster_outputs(result) -> tuple[torch.Tensor, ...]:
    return tuple(t for t in result[:3] if t is not None)


UNPROJECT = Op(
    "unproject",
    run=lambda depth, cameras: (unproject(depth, cameras),),
    reference=lambda depth, cameras: (unproject_reference(depth, cameras),),
)
REPROJECT = Op(
    "reproject_average",
    run=lambda feat, depth, cameras: _reproject_outputs(reproject_average(feat, depth, cameras)),
    reference=lambda feat, depth, cameras: _reproject_outputs(
        reproject_average_reference(feat, depth, cameras, all_other_views(feat.shape[0], feat.device))),
)  # fmt: skip
COST_VOLUME = Op(
    "plane_sweep_cost_volume",
    run=lambda feat, candidates, cameras: (plane_sweep_cost_volume(feat, candidates, cameras),),
    reference=lambda feat, candidates, cameras: (
        cost_volume_reference(feat, candidates, cameras, all_other_views(feat.shape[0], feat.device)),),
)  # fmt: skip
def _rasterize_dense_unit_quats(quats, tile_size: int = 16, **kw) -> tuple[torch.Tensor, ...]:
    """The dense reference on exactly normalised quaternions (its ``F.normalize`` clamps norms below 1e-12);
    ``tile_size`` only changes the rasterizer's binning, not its image."""
    unit = quats / torch.linalg.vector_norm(quats, dim=-1, keepdim=True)
    return _raster_outputs(rasterize_dense(quats=unit, **kw))


RASTERIZE = Op(
    "rasterize",
    run=lambda **kw: _raster_outputs(rasterize(**kw)),
    reference=_rasterize_dense_unit_quats,
)
DEPTH_FROM_NORMALIZED = Op(
    "depth_from_normalized",
    run=lambda s, near, far: (depth_from_normalized(s, near, far),),
    reference=lambda s, near, far: (depth_from_normalized(s, near, far),),
)
NORMALIZED_FROM_DEPTH = Op(
    "normalized_from_depth",
    run=lambda depth, near, far: (normalized_from_depth(depth, near, far),),
    reference=lambda depth, near, far: (normalized_from_depth(depth, near, far),),
)
DEPTH_HEAD_TO_POINTS = Op(
    "depth_from_normalized+unproject",
    run=lambda s, cameras: (unproject(depth_from_normalized(s, cameras.near, cameras.far), cameras),),
    reference=lambda s, cameras: (unproject_reference(depth_from_normalized(s, cameras.near, cameras.far), cameras),),
)
"""The decoder's path from the depth head's S to 3D points (Eq. 10, then unprojection)."""


# --------------------------------------------------------------------------------------------------
# Problem builders: cameras
def fov_focal(fov_degrees: float, size: int) -> float:
    """Focal length in pixels giving a field of view of ``fov_degrees`` across ``size`` pixels."""
    return size / 2 / math.tan(math.radians(fov_degrees) / 2)


def scaled_cameras(cameras: Cameras, scale: float) -> Cameras:
    """The same rig in a world ``scale`` times larger (translations, near and far scaled)."""
    w2c = cameras.w2c.clone()
    w2c[:, :3, 3] *= scale
    return Cameras(cameras.K, w2c, cameras.near * scale, cameras.far * scale, cameras.width, cameras.height)


def shifted_cameras(cameras: Cameras, offset: tuple[float, float, float]) -> Cameras:
    """The same rig with every camera centre moved by ``offset`` (world units)."""
    c2w = cameras.c2w.clone()
    c2w[:, :3, 3] += torch.tensor(offset, dtype=c2w.dtype)
    return Cameras.from_c2w(cameras.K, c2w, cameras.near, cameras.far, cameras.width, cameras.height)


def fov_cameras(num_views: int, width: int, height: int, fov_degrees: float) -> Cameras:
    """A :func:`make_rig` rig whose horizontal field of view is ``fov_degrees`` (square pixels)."""
    rig = make_rig(num_views, width, height)
    f = torch.full((num_views,), fov_focal(fov_degrees, width), dtype=torch.float64)
    K = intrinsics_matrix(f, f, rig.K[:, 0, 2], rig.K[:, 1, 2])
    return Cameras(K, rig.w2c, rig.near, rig.far, width, height)


def facing_away_rig(width: int, height: int) -> Cameras:
    """Two cameras back to back: every point in front of one is behind the other."""
    rig = make_rig(2, width, height)
    c2w = rig.c2w.clone()
    c2w[1, :3, :3] = rotation(math.pi, 0.0, 0.0)
    return Cameras.from_c2w(rig.K, c2w, rig.near, rig.far, width, height)


# --------------------------------------------------------------------------------------------------
# Problem builders: geometry
GRID = (3, 12, 16)
"""Views, rows and columns of the geometry problems (images twice the grid: intrinsics are rescaled)."""


def unproject_problem(cameras: Cameras | None = None, depth: torch.Tensor | None = None) -> Problem:
    """unproject inputs: the given ones, else a :data:`GRID` rig and smooth depths in [2, 4]."""
    V, H, W = GRID
    cameras = cameras if cameras is not None else make_rig(V, 2 * W, 2 * H)
    depth = depth if depth is not None else smooth_depth(cameras.num_views, H, W)
    return Problem({"depth": depth}, ("depth",), {"cameras": cameras})


def reproject_problem(cameras: Cameras | None = None, depth: torch.Tensor | None = None,
                      feat: torch.Tensor | None = None) -> Problem:  # fmt: skip
    """reproject_average inputs: the given tensors, else a :data:`GRID` rig, smooth depths, 4 random channels."""
    V, H, W = GRID
    cameras = cameras if cameras is not None else make_rig(V, 2 * W, 2 * H)
    V = cameras.num_views
    depth = depth if depth is not None else smooth_depth(V, H, W)
    g = torch.Generator().manual_seed(5)
    feat = feat if feat is not None else torch.randn(V, 4, *depth.shape[1:], generator=g, dtype=torch.float64)
    return Problem({"feat": feat, "depth": depth}, ("feat", "depth"), {"cameras": cameras})


def cost_volume_problem(candidates: torch.Tensor | None = None, feat: torch.Tensor | None = None,
                        num: int = 6) -> Problem:  # fmt: skip
    """plane_sweep_cost_volume inputs on a 2-view rig, 6x8 grid: the given tensors, else ``num`` candidates
    uniform in inverse depth over [0.5, 20] and 4 random channels."""
    V, H, W = 2, 6, 8
    cameras = make_rig(V, 4 * W, 4 * H)
    if candidates is None:
        inv = torch.linspace(1 / 20, 1 / 0.5, num, dtype=torch.float64)
        candidates = (1 / inv)[None].expand(cameras.num_views, -1).contiguous()
    g = torch.Generator().manual_seed(6)
    feat = feat if feat is not None else torch.randn(cameras.num_views, 4, H, W, generator=g, dtype=torch.float64)
    return Problem({"feat": feat, "candidates": candidates}, ("feat",), {"cameras": cameras})


def dynamic_range_features(V: int, H: int, W: int, exponents=(-18, -6, 0, 6, 18)) -> torch.Tensor:
    """[V,C,H,W] random features whose channel c has magnitude 10**exponents[c]."""
    g = torch.Generator().manual_seed(7)
    scale = torch.tensor([10.0**e for e in exponents], dtype=torch.float64)
    return torch.randn(V, len(exponents), H, W, generator=g, dtype=torch.float64) * scale[None, :, None, None]


def _rig_args() -> tuple[int, int, int]:
    """(views, image width, image height) of the geometry rigs: images twice the :data:`GRID`."""
    return GRID[0], 2 * GRID[2], 2 * GRID[1]


def with_value(problem: Problem, name: str, value: float, index=(0, 0, 0)) -> Problem:
    """A copy of ``problem`` with one element of input ``name`` set to ``value``."""
    inputs = {k: v.clone() for k, v in problem.inputs.items()}
    inputs[name][index] = value
    return Problem(inputs, problem.grad, problem.constants, problem.options)


# --------------------------------------------------------------------------------------------------
# Problem builders: rasterizer
def raster_problem(n: int = 24, width: int = 16, height: int = 16, sh_degree: int | None = None, seed: int = 0,
                   background: bool = True, edit: Callable[[dict], None] | None = None,
                   **options) -> Problem:  # fmt: skip
    """:func:`random_gaussians` (2-4 units in front of one camera) as a rasterize problem.

    ``edit`` changes the dict of tensors (``means ... colors, viewmats, Ks``) in place before the split.
    """
    generated = random_gaussians(n, width, height, 1, sh_degree, seed=seed)
    tensors = dict(zip((*GAUSSIAN_ARGUMENTS, "viewmats", "Ks"), generated))
    if background:
        tensors["background"] = torch.tensor([[0.2, 0.4, 0.6]], dtype=torch.float64)
    if edit is not None:
        edit(tensors)
    inputs = {k: tensors[k] for k in (*GAUSSIAN_ARGUMENTS, "background") if k in tensors}
    grad = tuple(k for k in inputs if inputs[k].numel())
    return Problem(inputs, grad, {"viewmats": tensors["viewmats"], "Ks": tensors["Ks"]},
                   {"width": width, "height": height, **options})  # fmt: skip


def _set_scales(values) -> Callable[[dict], None]:
    def edit(t: dict) -> None:
        t["scales"] = torch.as_tensor(values, dtype=torch.float64).expand_as(t["scales"]).clone()

    return edit


def _rank_deficient_scales(t: dict) -> None:
    patterns = torch.tensor([[0.1, 0.06, 0.0], [0.12, 0.0, 0.0], [0.0, 0.0, 0.0]], dtype=torch.float64)
    t["scales"] = patterns[torch.arange(t["scales"].shape[0]) % 3]


def _scaled_scene(scale: float) -> Callable[[dict], None]:
    def edit(t: dict) -> None:
        t["means"] = t["means"] * scale
        t["scales"] = t["scales"] * scale
        t["viewmats"][:, :3, 3] *= scale

    return edit


WORLD_OFFSET = (1.0e4, -1.0e4, 1.0e4)
"""Where the 'far from the origin' problems are moved (world units)."""


def _shifted_scene(t: dict) -> None:
    """Move means and camera rigidly: rotate (so the camera's R x + t mixes axes) and shift by WORLD_OFFSET."""
    move = torch.eye(4, dtype=torch.float64)
    move[:3, :3] = rotation(0.7, 0.3, 0.2)
    move[:3, 3] = torch.tensor(WORLD_OFFSET, dtype=torch.float64)
    t["means"] = t["means"] @ move[:3, :3].T + move[:3, 3]
    t["viewmats"] = t["viewmats"] @ rigid_inverse(move)


def _on_one_pixel(n: int) -> Callable[[], Problem]:
    """``n`` Gaussians exactly on the centre of a 1x1 image, opacities just above 1/255 up to 0.02: the pixel
    walks a couple of thousand rows before its transmittance reaches 1e-4 (and the rest are never read)."""

    def build() -> Problem:
        g = torch.Generator().manual_seed(8)
        quats = torch.zeros(n, 4, dtype=torch.float64)
        quats[:, 0] = 1.0
        inputs = {
            "means": torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64).expand(n, 3).clone(),
            "quats": quats,
            "scales": torch.full((n, 3), 0.01, dtype=torch.float64),
            "opacities": 0.0045 + 0.0155 * torch.rand(n, generator=g, dtype=torch.float64),
            "colors": torch.rand(n, 3, generator=g, dtype=torch.float64),
        }  # fmt: skip
        K = torch.tensor([[[10.0, 0.0, 0.5], [0.0, 10.0, 0.5], [0.0, 0.0, 1.0]]], dtype=torch.float64)
        return Problem(inputs, GAUSSIAN_ARGUMENTS, {"viewmats": torch.eye(4, dtype=torch.float64)[None], "Ks": K},
                       {"width": 1, "height": 1})  # fmt: skip

    return build


def _near_plane_depths(depths: list[float]) -> Callable[[dict], None]:
    """Move the first Gaussians to exactly these camera depths (float32 values) along their rays, so that they
    would project where they did (on screen) if they were not culled."""

    def edit(t: dict) -> None:
        k = len(depths)
        z = torch.tensor(depths, dtype=torch.float32).double()
        t["means"][:k, :2] *= (z / t["means"][:k, 2])[:, None]
        t["means"][:k, 2] = z

    return edit


def _f32_next(x: float, direction: float) -> float:
    """The float32 neighbour of ``x`` towards ``direction``."""
    return float(torch.nextafter(torch.tensor(x, dtype=torch.float32), torch.tensor(direction, dtype=torch.float32)))


def _fov_scene(fov_degrees: float, size: int) -> Callable[[dict], None]:
    """Gaussians spread over the whole frustum of a ``fov_degrees`` camera, footprints of a few pixels."""

    def edit(t: dict) -> None:
        n = t["means"].shape[0]
        g = torch.Generator().manual_seed(9)
        half = math.tan(math.radians(fov_degrees) / 2)
        z = 1.0 + 2.0 * torch.rand(n, generator=g, dtype=torch.float64)
        xy = (torch.rand(n, 2, generator=g, dtype=torch.float64) * 2 - 1) * half * z[:, None]
        t["means"] = torch.cat([xy, z[:, None]], dim=-1)
        f = fov_focal(fov_degrees, size)
        t["scales"] = (z / f)[:, None] * (1.0 + 2.0 * torch.rand(n, 3, generator=g, dtype=torch.float64))
        t["Ks"] = torch.tensor([[[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]]], dtype=torch.float64)

    return edit


ANISOTROPY = torch.tensor([1.0, 0.6, 0.8], dtype=torch.float64)
"""Per-axis scale factors that make a Gaussian's rotation matter (isotropic ones have zero quaternion gradient)."""


def _axis_directions(t: dict) -> None:
    """Means on the camera's axes and diagonals (view directions with exact zero components), some almost
    perpendicular to the optical axis (visible through a 170 degree field of view)."""
    points = [[0, 0, 3], [0, 0, 0.5], [1, 0, 3], [0, 1, 3], [-1, 0, 3], [0, -1, 3], [1, 1, 3], [-1, -1, 2],
              [10, 0, 1], [0, 10, 1], [-10, 0, 1], [0, -10, 1], [7, 7, 1], [20, 0, 2], [0, 0, 0.02],
              [3, 4, 5]]  # fmt: skip
    n = len(points)
    t["means"] = torch.tensor(points, dtype=torch.float64)
    for k in ("quats", "scales", "opacities", "colors"):
        t[k] = t[k][:n]
    t["scales"] = (t["means"][:, 2:3] * 0.2 / fov_focal(170, 32) + 0.01) * ANISOTROPY
    t["Ks"] = torch.tensor([[[fov_focal(170, 32), 0, 16], [0, fov_focal(170, 32), 16], [0, 0, 1]]], dtype=torch.float64)


def _opaque_stack(t: dict) -> None:
    """Opacity-1 Gaussians (alpha clamps at 0.999) stacked over the image centre at increasing depth."""
    n = t["means"].shape[0]
    t["means"] = torch.stack([torch.zeros(n), torch.zeros(n), torch.linspace(2, 4, n)], dim=-1).double()
    t["scales"] = 0.4 * ANISOTROPY.expand(n, 3).clone()
    t["opacities"] = torch.ones(n, dtype=torch.float64)


def _opacity_0_and_1(t: dict) -> None:
    t["opacities"][::2] = 0.0
    t["opacities"][1::2] = 1.0


def _scale_quats(factor: float) -> Callable[[dict], None]:
    def edit(t: dict) -> None:
        t["quats"] = torch.nn.functional.normalize(t["quats"], dim=-1) * factor

    return edit


def _first_scale(value: float) -> Callable[[dict], None]:
    def edit(t: dict) -> None:
        t["scales"][0] = value

    return edit


def _no_gaussians(t: dict) -> None:
    for k in GAUSSIAN_ARGUMENTS:
        t[k] = t[k][:0]


def _bad_value(name: str, value: float) -> Callable[[dict], None]:
    def edit(t: dict) -> None:
        t[name].view(-1)[-1] = value

    return edit


# --------------------------------------------------------------------------------------------------
# Problem builders: depth heads
def _s_problem(s: torch.Tensor, near: float, far: float) -> Problem:
    V = s.shape[0]
    return Problem({"s": s}, ("s",), {"near": torch.full((V,), near, dtype=torch.float64),
                                      "far": torch.full((V,), far, dtype=torch.float64)})  # fmt: skip


def _endpoints_s(V: int, H: int, W: int) -> torch.Tensor:
    """S in {0, 1} exactly on alternating pixels, random in between elsewhere."""
    g = torch.Generator().manual_seed(10)
    s = torch.rand(V, H, W, generator=g, dtype=torch.float64)
    s[:, ::2, ::2] = 0.0
    s[:, 1::2, 1::2] = 1.0
    return s


def _depth_problem(near: float, far: float) -> Problem:
    g = torch.Generator().manual_seed(11)
    depth = near + (far - near) * torch.rand(2, 8, 8, generator=g, dtype=torch.float64)
    return Problem({"depth": depth}, ("depth",), {"near": torch.full((2,), near, dtype=torch.float64),
                                                  "far": torch.full((2,), far, dtype=torch.float64)})  # fmt: skip


# --------------------------------------------------------------------------------------------------
# The catalog
MILLION = 1_000_000
CPU_PILE = 1 << 16
"""Gaussians on one pixel on the CPU (the serial backend and the dense float64 reference keep this to ~1 s)."""

RASTER_F32 = (5e-5, 1e-3)
"""(outputs, gradients) bound of float32 rasterization: ~10x the error of well-conditioned scenes on the CPU
(5e-6 and 1e-4: gradients sum many per-pixel terms of either sign)."""
GEOMETRY_F32 = (2e-5, 2e-4)
"""Bound of float32 bilinear reprojection and plane sweeps (measured up to 3e-6 and 5e-6)."""
POINTWISE_F32 = (2e-6, 2e-6)
"""Bound of float32 ops of a few flops per element (unprojection, Eq. 10): measured up to 2.3e-7, ~2 ulp."""
BF16_GRADIENT = 1e-2
"""Gradients of bfloat16 inputs come back in bfloat16: up to half an ulp (2^-9 = 2e-3) of rounding per value."""



def _raster(name: str, bounds: tuple[float, float], **kw) -> Case:
    """A rasterize case; keywords that are not :class:`Case` fields go to :func:`raster_problem`."""
    build_kw = {k: kw.pop(k) for k in list(kw) if k not in Case.__dataclass_fields__}
    return Case(name, RASTERIZE, lambda: raster_problem(**build_kw), *bounds, **kw)


def _raster_error(name: str, edit, match: str, error=InputError, **options) -> Case:
    return Case(name, RASTERIZE, lambda: raster_problem(edit=edit, **options), error=error, match=match)


def _geometry(name: str, op: Op, build: Callable[[], Problem], bounds: tuple[float, float], **kw) -> Case:
    return Case(name, op, build, *bounds, **kw)


CASES: list[Case] = [
    # ---------------------------------------------------------------------------------- rasterize
    _raster("rasterize-scale-ratio-1e6-discs", RASTER_F32, edit=_set_scales([0.1, 0.1, 1e-7]),
            note="flat discs (0.1, 0.1, 1e-7), random orientations: some seen edge-on (rank-1 2D covariance)"),
    _raster("rasterize-scale-ratio-1e6-needles", RASTER_F32, edit=_set_scales([0.15, 1e-7, 1e-7]),
            note="needles (0.15, 1e-7, 1e-7): 2D covariance of rank 1 before the 0.3 px^2 blur"),
    _raster("rasterize-scale-ratio-1e6-antialiased", RASTER_F32, edit=_set_scales([0.1, 0.1, 1e-7]),
            mode="antialiased",
            note="the compensation divides det(cov2d) = ac - b^2 (cancelling for edge-on discs) by det(cov2d + 0.3 I)"),
    _raster("rasterize-rank-deficient-scales", RASTER_F32, edit=_rank_deficient_scales,
            note="scales (s,s,0), (s,0,0), (0,0,0): only the 0.3 px^2 blur keeps the 2D covariance invertible"),
    _raster("rasterize-rank-deficient-scales-antialiased", RASTER_F32, edit=_rank_deficient_scales,
            mode="antialiased", note="compensation sqrt(det/det_blur) of singular covariances: 0 (culled) or tiny"),
    _raster("rasterize-exactly-at-near-plane", RASTER_F32, edit=_near_plane_depths([0.5] * 6), near=0.5,
            note="six means at z = near exactly: culled (the near plane is exclusive), no NaN in the gradient"),
    _raster("rasterize-just-behind-near-plane", RASTER_F32, edit=_near_plane_depths([_f32_next(0.5, 0.0)] * 6),
            near=0.5, note="six means one float32 ulp behind the near plane: culled"),
    _raster("rasterize-just-in-front-of-near-plane", RASTER_F32,
            edit=_near_plane_depths([_f32_next(0.01, 1.0)] * 3), near=0.01,
            note="three means one ulp in front of near = 0.01: footprints ~100x the image, clamped Jacobian"),
    _raster("rasterize-exactly-at-far-plane", RASTER_F32, edit=_near_plane_depths([4.0] * 6), far=4.0,
            note="six means at z = far exactly: culled (exclusive)"),
    _raster("rasterize-scene-scale-1e4", RASTER_F32, edit=_scaled_scene(1e4), near=100.0,
            note="every length x 1e4 (depths 2e4-4e4): projection is scale-invariant, so is the float32 error"),
    _raster("rasterize-scene-scale-1e-4", RASTER_F32, edit=_scaled_scene(1e-4), near=1e-6,
            note="every length x 1e-4 (depths 2e-4-4e-4, covariances ~1e-10)"),
    _raster("rasterize-world-offset-1e4", RASTER_F32, edit=_shifted_scene,
            note="scene and rotated camera 1.7e4 from the origin (float32 means, float64 viewmat)"),
    Case("rasterize-65536-gaussians-on-one-pixel", RASTERIZE, _on_one_pixel(CPU_PILE), *RASTER_F32,
         note=f"{CPU_PILE:,} Gaussians on one pixel: transmittance reaches 1e-4 after ~1,500 rows (no "
              "underflow: the early stop ends the walk); float32 sums over those rows"),
    Case("rasterize-million-gaussians-on-one-pixel", RASTERIZE, _on_one_pixel(MILLION), *RASTER_F32,
         cuda_only=True,
         note="1,000,000 Gaussians on one pixel: CUDA only (the dense float64 reference alone takes ~15 s on "
              "the CPU); the 65,536 case covers the CPU"),
    _raster("rasterize-opaque-stack", RASTER_F32, n=40, edit=_opaque_stack,
            note="opacity-1 Gaussians stacked (alpha clamps at 0.999): T falls 1e-3 per row, the backward "
                 "rebuilds T by dividing by 1 - alpha = 1e-3"),
    _raster("rasterize-opacity-0-and-1", RASTER_F32, edit=_opacity_0_and_1,
            note="opacities exactly 0 (culled) and 1 (alpha clamped at 0.999, zero opacity gradient there)"),
    _raster("rasterize-fov-5deg", RASTER_F32, width=32, height=32, edit=_fov_scene(5, 32),
            note="focal 366 px on a 32 px image: Jacobian entries f/z ~ 1e2"),
    _raster("rasterize-fov-170deg", RASTER_F32, width=32, height=32, edit=_fov_scene(170, 32),
            note="focal 1.4 px on a 32 px image, x/z up to tan(85 deg) = 11.4 (frustum clamp of the Jacobian)"),
    _raster("rasterize-sh3-extreme-directions", RASTER_F32, sh_degree=3, width=32, height=32,
            edit=_axis_directions,
            note="SH degree 3, view directions along axes (exact zeros), up to 87 deg off-axis, one mean 0.02 "
                 "from the camera centre; 170 degree field of view"),
    _raster("rasterize-antialiased-tiny-scales", RASTER_F32, edit=_set_scales([1e-8, 1e-8, 1e-8]),
            mode="antialiased", note="scales 1e-8: compensation ~1e-13, every Gaussian below 1/255 and culled"),
    _raster("rasterize-one-huge-gaussian", RASTER_F32, edit=_first_scale(1e3),
            note="one Gaussian of scale 1e3 (radius clamped by the frustum, covers every tile)"),
    _raster("rasterize-1x1-image", RASTER_F32, width=1, height=1, note="a single pixel"),
    _raster("rasterize-no-gaussians", (1e-6, 1e-6), edit=_no_gaussians,
            note="N = 0: the background, with its gradient (a float32 sum over 256 pixels)"),
    _raster("rasterize-bf16-autocast", RASTER_F32, autocast=True,
            note="float32 inputs under torch.autocast(bfloat16): no op inside may drop to bf16"),
    _raster("rasterize-bf16-inputs", (RASTER_F32[0], BF16_GRADIENT), dtype=torch.bfloat16,
            note="bfloat16 Gaussians (as a bf16 head gives them): computed in float32 like the geometry ops"),
    _raster("rasterize-tiny-quaternions", RASTER_F32, edit=_scale_quats(1e-22),
            note="|q| = 1e-22 ('need not be normalised', says the docstring)"),
    _raster("rasterize-huge-quaternions", RASTER_F32, edit=_scale_quats(1e20),
            note="|q| = 1e20"),
    Case("rasterize-covariance-overflow", RASTERIZE, lambda: raster_problem(edit=_first_scale(1e20)),
         error=InputError, match="scales",
         note="one Gaussian of scale 1e20: its float32 covariance overflows; must be refused, not dropped"),
    _raster_error("rasterize-empty-image", None, "width must be a positive integer", width=0),
    _raster_error("rasterize-nan-means", _bad_value("means", math.nan), "means holds non-finite"),
    _raster_error("rasterize-inf-scales", _bad_value("scales", math.inf), "scales holds non-finite"),
    _raster_error("rasterize-nan-opacities", _bad_value("opacities", math.nan), "opacities holds non-finite"),
    _raster_error("rasterize-inf-sh-coefficients", _bad_value("colors", -math.inf), "colors holds non-finite",
                  sh_degree=3),
    _raster_error("rasterize-nan-background", _bad_value("background", math.nan), "background holds"),
    _raster_error("rasterize-nan-viewmat", _bad_value("viewmats", math.nan), "viewmats holds non-finite"),
    # ---------------------------------------------------------------------------------- unproject
    _geometry("unproject-scene-scale-1e4", UNPROJECT,
              lambda: unproject_problem(scaled_cameras(make_rig(*_rig_args()), 1e4), smooth_depth(*GRID) * 1e4),
              POINTWISE_F32, note="depths 2e4-4e4, baselines 2.5e3"),
    _geometry("unproject-scene-scale-1e-4", UNPROJECT,
              lambda: unproject_problem(scaled_cameras(make_rig(*_rig_args()), 1e-4), smooth_depth(*GRID) * 1e-4),
              POINTWISE_F32, note="depths 2e-4-4e-4"),
    _geometry("unproject-world-offset-1e4", UNPROJECT,
              lambda: unproject_problem(shifted_cameras(make_rig(*_rig_args()), WORLD_OFFSET)), POINTWISE_F32,
              note="cameras 1.7e4 from the origin: the point is formed camera-relative, the centre added last"),
    _geometry("unproject-fov-5deg", UNPROJECT, lambda: unproject_problem(fov_cameras(3, 32, 24, 5)), POINTWISE_F32),
    _geometry("unproject-fov-170deg", UNPROJECT, lambda: unproject_problem(fov_cameras(3, 32, 24, 170)),
              POINTWISE_F32, note="rays up to tan(85 deg) = 11.4 off-axis"),
    _geometry("unproject-1x1-grid", UNPROJECT, lambda: unproject_problem(depth=smooth_depth(3, 1, 1)), POINTWISE_F32),
    _geometry("unproject-bf16-inputs", UNPROJECT, unproject_problem, (POINTWISE_F32[0], BF16_GRADIENT),
              dtype=torch.bfloat16, note="bfloat16 depth computed in float32; its gradient returns in bf16"),
    _geometry("unproject-bf16-autocast", UNPROJECT, unproject_problem, POINTWISE_F32, autocast=True, note="float32 depth, float64 cameras, under torch.autocast(bf16)"),
    Case("unproject-empty-depth", UNPROJECT, lambda: unproject_problem(depth=torch.ones(3, 0, 16, dtype=torch.float64)),
         error=InputError, match="depth is empty"),
    Case("unproject-zero-depth", UNPROJECT, lambda: with_value(unproject_problem(), "depth", 0.0), error=InputError,
         match="depth must be > 0"),
    Case("unproject-negative-depth", UNPROJECT, lambda: with_value(unproject_problem(), "depth", -1.0),
         error=InputError, match="depth must be > 0"),
    Case("unproject-nan-depth", UNPROJECT, lambda: with_value(unproject_problem(), "depth", math.nan),
         error=InputError, match="depth holds 1 non-finite"),
    Case("unproject-inf-depth", UNPROJECT, lambda: with_value(unproject_problem(), "depth", math.inf),
         error=InputError, match="depth holds 1 non-finite"),
    # ---------------------------------------------------------------------------------- depth heads (Eq. 10, 18)
    _geometry("depth-head-at-near-and-far", DEPTH_HEAD_TO_POINTS,
              lambda: Problem({"s": _endpoints_s(*GRID)}, ("s",), {"cameras": make_rig(*_rig_args())}), POINTWISE_F32,
              note="S = 0 and 1 exactly (depth = far and near) through Eq. 10 into unprojection"),
    _geometry("depth-from-normalized-near-almost-far", DEPTH_FROM_NORMALIZED,
              lambda: _s_problem(_endpoints_s(2, 8, 8), 1.0, 1.0 + 1e-6), POINTWISE_F32,
              note="near = 1, far = 1 + 1e-6 (float64 bounds, float32 S)"),
    _geometry("depth-from-normalized-wide-range", DEPTH_FROM_NORMALIZED,
              lambda: _s_problem(_endpoints_s(2, 8, 8), 1e-3, 1e6), POINTWISE_F32,
              note="near = 1e-3, far = 1e6 (nine decades of depth)"),
    _geometry("normalized-from-depth-near-almost-far", NORMALIZED_FROM_DEPTH, lambda: _depth_problem(1.0, 1.001),
              (1e-3, 1e-3),
              note="Eq. 18 with f/n = 1.001: 1/D - 1/f cancels to 1e-3 of its operands, so float32 loses "
                   "ulp/1e-3 = 6e-5 relative inherently (measured 5e-5)"),
    # ---------------------------------------------------------------------------------- reproject_average
    _geometry("reproject-all-sources-invalid", REPROJECT, lambda: reproject_problem(facing_away_rig(32, 24)),
              GEOMETRY_F32, note="two cameras back to back: every sample is behind its source; 0 and zero gradients"),
    _geometry("reproject-points-too-close", REPROJECT,
              lambda: reproject_problem(make_rig(3, 32, 24, baseline=0.6), torch.full(GRID, 1e-3, dtype=torch.float64)),
              GEOMETRY_F32, note="depth 1e-3 with 0.6 baselines: every projection leaves every source image"),
    _geometry("reproject-single-view", REPROJECT,
              lambda: reproject_problem(make_rig(1, 32, 24), smooth_depth(1, 12, 16)),
              GEOMETRY_F32, note="V = 1: no source view at all (M = 0)"),
    _geometry("reproject-feature-dynamic-range", REPROJECT,
              lambda: reproject_problem(feat=dynamic_range_features(*GRID[:1], *GRID[1:])), GEOMETRY_F32,
              output_error=channel_relative_error,
              note="channels of magnitude 1e-18 ... 1e18 (error per channel): no channel may leak into another"),
    _geometry("reproject-scene-scale-1e4", REPROJECT,
              lambda: reproject_problem(scaled_cameras(make_rig(*_rig_args()), 1e4), smooth_depth(*GRID) * 1e4),
              GEOMETRY_F32, note="depths 2e4-4e4, baselines 2.5e3"),
    _geometry("reproject-scene-scale-1e-4", REPROJECT,
              lambda: reproject_problem(scaled_cameras(make_rig(*_rig_args()), 1e-4), smooth_depth(*GRID) * 1e-4),
              GEOMETRY_F32, note="depths 2e-4-4e-4"),
    _geometry("reproject-world-offset-1e4", REPROJECT,
              lambda: reproject_problem(shifted_cameras(make_rig(*_rig_args()), WORLD_OFFSET)), GEOMETRY_F32,
              note="cameras 1.7e4 from the origin (float64 poses): reference-to-source transforms must not go "
                   "through float32 world coordinates"),
    _geometry("reproject-fov-170deg", REPROJECT, lambda: reproject_problem(fov_cameras(3, 32, 24, 170)), GEOMETRY_F32,
              note="rays up to 11.4 off-axis"),
    _geometry("reproject-fov-5deg", REPROJECT, lambda: reproject_problem(fov_cameras(3, 32, 24, 5)), GEOMETRY_F32,
              note="focal 366 px on a 32 px image: du/d(depth) is large"),
    _geometry("reproject-1x1-grid", REPROJECT, lambda: reproject_problem(depth=smooth_depth(3, 1, 1)), GEOMETRY_F32,
              note="one feature cell per view (a single bilinear tap)"),
    _geometry("reproject-bf16-autocast", REPROJECT, reproject_problem, GEOMETRY_F32, autocast=True),
    _geometry("reproject-bf16-inputs", REPROJECT, reproject_problem, (GEOMETRY_F32[0], BF16_GRADIENT),
              dtype=torch.bfloat16, note="bfloat16 feat and depth computed in float32; gradients return in bf16"),
    Case("reproject-nan-features", REPROJECT, lambda: with_value(reproject_problem(), "feat", math.nan, (0, 0, 0, 0)),
         error=InputError, match="feat holds 1 non-finite"),
    Case("reproject-inf-features", REPROJECT, lambda: with_value(reproject_problem(), "feat", math.inf, (1, 2, 3, 4)),
         error=InputError, match="feat holds 1 non-finite"),
    Case("reproject-negative-depth", REPROJECT, lambda: with_value(reproject_problem(), "depth", -2.0),
         error=InputError, match="depth must be > 0"),
    Case("reproject-empty-features", REPROJECT,
         lambda: reproject_problem(feat=torch.ones(3, 0, 12, 16, dtype=torch.float64)), error=InputError,
         match="feat is empty"),
    # ---------------------------------------------------------------------------------- plane sweep
    _geometry("cost-volume-128-candidates", COST_VOLUME, lambda: cost_volume_problem(num=128), GEOMETRY_F32,
              note="128 depth planes from 0.5 to 20"),
    _geometry("cost-volume-candidates-at-extremes", COST_VOLUME,
              lambda: cost_volume_problem(torch.tensor([[1e-6, 1e-3, 3.0, 1e6, 1e12]] * 2, dtype=torch.float64)),
              GEOMETRY_F32, note="planes at 1e-6 (nothing valid), 1e-3, 3, 1e6 and 1e12 (points at infinity)"),
    _geometry("cost-volume-feature-dynamic-range", COST_VOLUME,
              lambda: cost_volume_problem(feat=dynamic_range_features(2, 6, 8, (-9, -3, 0, 3, 9))), GEOMETRY_F32,
              note="channels of magnitude 1e-9 ... 1e9: the correlation is dominated by the largest channel"),
    _geometry("cost-volume-bf16-autocast", COST_VOLUME, cost_volume_problem, GEOMETRY_F32, autocast=True),
    Case("cost-volume-zero-candidate", COST_VOLUME,
         lambda: cost_volume_problem(candidates=torch.tensor([[0.0, 1.0], [1.0, 2.0]], dtype=torch.float64)),
         error=InputError, match="candidates must be > 0"),
    Case("cost-volume-inf-candidate", COST_VOLUME,
         lambda: cost_volume_problem(candidates=torch.tensor([[math.inf, 1.0], [1.0, 2.0]], dtype=torch.float64)),
         error=InputError, match="candidates holds 1 non-finite"),
    # ---------------------------------------------------------------------------------- cameras
    Case("cameras-near-equals-far", UNPROJECT,
         lambda: unproject_problem(make_rig(*_rig_args()).with_depth_range(2.0, 2.0)), error=CameraError,
         match="near < far"),
]
"""The catalog, in table order."""


# --------------------------------------------------------------------------------------------------
# Evaluation
def device_arguments(problem: Problem, dtype: torch.dtype, device: torch.device | str) -> dict:
    """Keyword arguments of the op under test: inputs rounded to ``dtype`` on ``device``, constants moved."""
    args = {k: v.to(device=device, dtype=dtype) for k, v in problem.inputs.items()}
    args.update({k: v.to(device=device) for k, v in problem.constants.items()})
    return {**args, **problem.options}


def reference_arguments(problem: Problem, dtype: torch.dtype) -> dict:
    """Keyword arguments of the float64 reference: the same rounded inputs, widened, on the CPU."""
    args = {k: v.to(dtype).to(torch.float64) for k, v in problem.inputs.items()}
    return {**args, **problem.constants, **problem.options}


def call(case: Case, device: torch.device | str) -> tuple[torch.Tensor, ...]:
    """Build the case's problem and run its op forward on ``device`` (what an error case must refuse)."""
    problem = case.build()
    return case.op.run(**device_arguments(problem, case.dtype, device))


Tensors = list[torch.Tensor]


def forward_backward(fn: Callable, args: dict, grad: tuple[str, ...], weights: Tensors | None,
                     autocast: bool = False) -> tuple[Tensors, Tensors, Tensors]:  # fmt: skip
    """Outputs, gradients of ``sum_k <weights_k, output_k>`` w.r.t. the ``grad`` inputs, and the weights.

    ``weights`` None draws fixed standard-normal float64 weights shaped like the outputs (seed 0).
    """
    leaves = {k: args[k].detach().requires_grad_() for k in grad}
    args = {**args, **leaves}
    device = next(iter(leaves.values())).device if leaves else torch.device("cpu")
    with torch.autocast(device.type, dtype=torch.bfloat16, enabled=autocast):
        outputs = fn(**args)
    if weights is None:
        g = torch.Generator().manual_seed(0)
        weights = [torch.randn(o.shape, generator=g, dtype=torch.float64) for o in outputs]
    loss = sum((o * w.to(device=o.device, dtype=o.dtype)).sum() for o, w in zip(outputs, weights))
    if isinstance(loss, torch.Tensor) and loss.requires_grad:
        grads = torch.autograd.grad(loss, list(leaves.values()), allow_unused=True)
    else:
        grads = [None] * len(leaves)
    grads = [torch.zeros_like(x) if g is None else g for x, g in zip(leaves.values(), grads)]
    return [o.detach() for o in outputs], grads, weights


def _all_finite(tensors) -> bool:
    return all(bool(torch.isfinite(t.float()).all()) for t in tensors)


def evaluate(case: Case, device: torch.device | str) -> dict:
    """Run one case on one device; returns its table row (see :data:`COLUMNS`)."""
    device = torch.device(device)
    row = {"case": case.name, "op": case.op.name, "device": str(device), "dtype": str(case.dtype).replace("torch.", ""),
           "bound": case.bound, "grad_bound": case.gradient_bound, "expected_error": _error_name(case.error),
           "known_bug": case.known_bug, "note": case.note}  # fmt: skip
    if case.cuda_only and device.type != "cuda":
        return {**row, "ok": None, "status": "skipped (CUDA only)"}
    try:
        row.update(_check_error(case, device) if case.error else measure_accuracy(case, device))
    except Exception as exc:  # noqa: BLE001 - a case that crashes is a failed row, not a crashed catalog
        row.update(ok=False, raised=type(exc).__name__, message=str(exc)[:200])
    row["status"] = _status(row, case)
    return row


def _check_error(case: Case, device: torch.device) -> dict:
    try:
        outputs = call(case, device)
    except case.error as exc:
        matched = case.match is None or re.search(case.match, str(exc)) is not None
        return {"ok": matched, "raised": type(exc).__name__, "message": str(exc)[:200]}
    return {"ok": False, "raised": "nothing", "finite_fwd": _all_finite(outputs)}


def measure_accuracy(case: Case, device: torch.device | str) -> dict:
    """Finiteness and errors of an accuracy case on ``device`` (exceptions propagate): ``finite_fwd``,
    ``finite_bwd``, ``err_fwd``, ``err_bwd`` and ``ok`` (all finite and both errors within the bounds)."""
    problem = case.build()
    ref_out, ref_grads, weights = forward_backward(case.op.reference, reference_arguments(problem, case.dtype),
                                                   problem.grad, None)  # fmt: skip
    out, grads, _ = forward_backward(case.op.run, device_arguments(problem, case.dtype, device), problem.grad,
                                     weights, case.autocast)  # fmt: skip
    output_error = case.output_error or relative_error
    result = {
        "finite_fwd": _all_finite(out),
        "finite_bwd": _all_finite(grads),
        "err_fwd": max((output_error(o, r) for o, r in zip(out, ref_out)), default=0.0),
        "err_bwd": max((relative_error(g, r) for g, r in zip(grads, ref_grads)), default=0.0),
        "raised": None,
    }
    result["ok"] = bool(result["finite_fwd"] and result["finite_bwd"] and result["err_fwd"] <= case.bound
                        and result["err_bwd"] <= case.gradient_bound)  # fmt: skip
    return result


def _error_name(error: type[Exception] | None) -> str | None:
    return None if error is None else error.__name__


def _status(row: dict, case: Case) -> str:
    if case.known_bug:
        return "known bug (fixed? remove known_bug)" if row["ok"] else "known bug"
    if row["ok"]:
        return f"ok ({row['raised']})" if case.error else "ok"
    return f"FAIL ({row['raised']})" if row.get("raised") else "FAIL"


def run_catalog(device: torch.device | str, cases: list[Case] | None = None, progress: bool = True) -> list[dict]:
    """Evaluate ``cases`` (default: the whole catalog) on ``device``; one row per case."""
    from tqdm import tqdm

    cases = CASES if cases is None else cases
    return [evaluate(c, device) for c in tqdm(cases, desc="extreme cases", disable=not progress, leave=False)]


def catalog_passed(rows: list[dict]) -> bool:
    """True when every case that ran is ok, except known bugs, which must still fail (strict expectation)."""
    return all((r["ok"] is not True) if r["known_bug"] else (r["ok"] is not False) for r in rows)


COLUMNS = [
    ("case", "case", "s"), ("dtype", "dtype", "s"), ("finite_fwd", "finite fwd", ""), ("finite_bwd", "finite bwd", ""),
    ("err_fwd", "err fwd", ".1e"), ("err_bwd", "err bwd", ".1e"), ("bound", "bound fwd", ".0e"),
    ("grad_bound", "bound bwd", ".0e"), ("expected_error", "expected error", "s"), ("status", "ok", "s"),
]  # fmt: skip


# --------------------------------------------------------------------------------------------------
# Command line (``python -m codecsplat_warp.bench.extreme``; also usable as a ``codecsplat bench`` module)
def run(args: argparse.Namespace) -> dict:
    device = torch.device(args.device)
    wanted = [w for w in args.cases.split(",") if w]
    cases = [c for c in CASES if not wanted or any(w in c.name for w in wanted)]
    if not cases:
        raise InputError(f"no case matches --cases {args.cases!r}")
    rows = run_catalog(device, cases, progress=not getattr(args, "json", False))
    table = format_table(rows, COLUMNS)
    machine = machine_name(device)
    passed = catalog_passed(rows)
    print(f"\nstiff and extreme cases on {device} ({machine})\n{table}\n", file=sys.stderr if args.json else sys.stdout)
    return {"benchmark": "extreme", "device": str(device), "machine": machine, "passed": passed, "rows": rows,
            "table": table}  # fmt: skip


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m codecsplat_warp.bench.extreme`` (``codecsplat bench extreme`` takes the
    same options)."""
    parser = argparse.ArgumentParser(prog="python -m codecsplat_warp.bench.extreme", description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="auto", help="cpu, cuda, cuda:N or auto: CUDA when available "
                        "(default %(default)s)")
    parser.add_argument("--out", help="write the JSON result to this file (default: none)")
    parser.add_argument("--json", action="store_true", help="print the JSON result on stdout, the table on stderr "
                        "(default off)")
    extreme_arguments(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    """``python -m codecsplat_warp.bench.extreme [--device cuda] [--cases ...] [--out FILE] [--json]``.

    Exit code 0 when every case is ok (known bugs still failing as documented), 1 otherwise.
    """
    from ..device import resolve_device

    parser = argparse.ArgumentParser(prog="python -m codecsplat_warp.bench.extreme", description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="auto", help="cpu, cuda, cuda:N or auto (CUDA when available)")
    parser.add_argument("--out", help="write the JSON result to this file")
    parser.add_argument("--json", action="store_true", help="print the JSON result on stdout (table on stderr)")
    extreme_arguments(parser)
    args = parser.parse_args(argv)
    args.device = str(resolve_device(args.device))
    result = run(args)
    if args.out:
        write_json(args.out, result)
    if args.json:
        print(json.dumps(result, indent=2))
    return 0 if result["passed"] else 1


if __name__ == "__main__":
    sys.exit(main())
