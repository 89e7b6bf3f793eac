"""3D Gaussians in world space, and the rotation (quaternion) and spherical-harmonics helpers they use.

Shared by the network (:mod:`codecsplat_warp.model`, whose Eq. 12 map :func:`codecsplat_warp.model.heads.map_to_world`
builds :class:`Gaussians` from pixel-aligned camera-space predictions), the codec's bitstream (camera
rotations as quaternions), the exporters and the baselines.

Conventions:

* rotations: unit quaternions (w,x,y,z), Gaussian frame -> world; ``q_world = q(R_c2w) * q_cam``
  (:func:`quat_multiply`), forgetting which is a known bug in exported feed-forward PLYs;
* SH colours are those of 3DGS / gsplat: colour = sum_k sh[k] * Y_k(dir) (+0.5 added by the renderer),
  real basis ordered as in :func:`sh_basis`; :func:`rotate_sh` re-expresses them in a rotated frame.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from functools import lru_cache

import torch

from .checks import check_tensor
from .errors import InputError

_ANY_FLOAT = (torch.float32, torch.float64, torch.float16, torch.bfloat16)
"""Float dtypes a Gaussians field may hold (half types appear under autocast); only shapes are constrained."""

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
         1.445305721320277, -0.5900435899266435)


@dataclass
class Gaussians:
    """N 3D Gaussians in world space (OpenCV-world of the cameras).

    Attributes:
        means: [N,3] centres.
        quats: [N,4] unit quaternions (w,x,y,z), Gaussian frame -> world.
        scales: [N,3] standard deviations along the Gaussian's axes (world units).
        opacities: [N] in (0,1).
        sh: [N,K,3] SH colour coefficients, K = (degree+1)^2, w.r.t. world-space view directions.
    """

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    sh: torch.Tensor

    def __post_init__(self) -> None:
        dims: dict[str, int] = {}
        expected = {"means": ("N", 3), "quats": ("N", 4), "scales": ("N", 3), "opacities": ("N",), "sh": ("N", "K", 3)}
        for name, shape in expected.items():
            check_tensor(f"Gaussians.{name}", getattr(self, name), shape, _ANY_FLOAT, dims)
        k = dims["K"]
        if round(k**0.5) ** 2 != k:
            raise InputError(f"Gaussians.sh must have shape [N,K,3] with K a square, got {tuple(self.sh.shape)}")

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        """Degree of the SH colours (K = (degree+1)^2)."""
        return round(self.sh.shape[1] ** 0.5) - 1

    def split(self, parts: int) -> "list[Gaussians]":
        """``parts`` consecutive, equally long pieces (e.g. the Gaussians of each scene of a training batch,
        whose views are stacked view-major). InputError unless ``parts`` divides the count."""
        self._piece_length(parts)
        pieces = {f.name: getattr(self, f.name).chunk(parts) for f in fields(self)}
        return [Gaussians(**{name: chunks[i] for name, chunks in pieces.items()}) for i in range(parts)]

    def view_ranges(self, views: int) -> torch.Tensor:
        """``[views, 2]`` int64 on the Gaussians' device: the index range ``[first, end)`` of each of the ``views``
        consecutive, equally long pieces of :meth:`split` (the pixel-aligned Gaussians of each view, view-major),
        e.g. for :func:`~codecsplat_warp.ops.raster.rasterize`'s ``leave_out``. InputError unless ``views`` divides
        the count."""
        length = self._piece_length(views)
        first = torch.arange(views, device=self.means.device) * length
        return torch.stack([first, first + length], dim=1)

    def _piece_length(self, parts: int) -> int:
        """The length of each of ``parts`` equal consecutive pieces; InputError unless ``parts`` divides the count."""
        if parts < 1 or len(self) % parts:
            raise InputError(f"cannot split {len(self)} Gaussians into {parts} equal parts")
        return len(self) // parts

    def detach(self) -> "Gaussians":
        """A copy without autograd history."""
        return Gaussians(**{f.name: getattr(self, f.name).detach() for f in fields(self)})


# --------------------------------------------------------------------------------------------------
# Rotations
def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """[...,3,3] rotation matrices of unit quaternions [...,4] (w,x,y,z)."""
    w, x, y, z = quats.unbind(-1)
    rows = (
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    )
    return torch.stack(rows, dim=-1).reshape(*quats.shape[:-1], 3, 3)


def rotmat_to_quat(R: torch.Tensor) -> torch.Tensor:
    """Unit quaternions [...,4] (w,x,y,z, w >= 0) of rotation matrices [...,3,3] (Shepperd's method).

    The largest of the four ``4 q_i^2`` candidates picks the numerically stable formula per matrix.
    """
    m = R.reshape(-1, 3, 3)
    m00, m11, m22 = m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]
    squares = torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    candidates = torch.stack([
        torch.stack([squares[:, 0], m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]], -1),
        torch.stack([m[:, 2, 1] - m[:, 1, 2], squares[:, 1], m[:, 1, 0] + m[:, 0, 1], m[:, 0, 2] + m[:, 2, 0]], -1),
        torch.stack([m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] + m[:, 0, 1], squares[:, 2], m[:, 2, 1] + m[:, 1, 2]], -1),
        torch.stack([m[:, 1, 0] - m[:, 0, 1], m[:, 0, 2] + m[:, 2, 0], m[:, 2, 1] + m[:, 1, 2], squares[:, 3]], -1),
    ], dim=1)
    best = squares.argmax(dim=-1)
    q = candidates[torch.arange(m.shape[0], device=m.device), best]
    q = q / (2.0 * squares.gather(1, best[:, None]).clamp_min(1e-12).sqrt())
    q = torch.where(q[:, :1] < 0, -q, q)
    return q.reshape(*R.shape[:-2], 4)


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a * b of quaternions [...,4] (w,x,y,z): the rotation b followed by a."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], dim=-1)


# --------------------------------------------------------------------------------------------------
# Spherical harmonics
def sh_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """[...,(degree+1)^2] real SH basis of 3DGS (gsplat ordering and signs) at unit directions [...,3]."""
    if not 0 <= degree <= 3:
        raise InputError(f"SH degree must be 0..3, got {degree}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [SH_C2[0] * x * y, SH_C2[1] * y * z, SH_C2[2] * (2 * zz - xx - yy), SH_C2[3] * x * z,
                SH_C2[4] * (xx - yy)]
    if degree >= 3:
        out += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * x * y * z, SH_C3[2] * y * (4 * zz - xx - yy),
                SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), SH_C3[4] * x * (4 * zz - xx - yy),
                SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3 * yy)]
    return torch.stack(out, dim=-1)


def _fibonacci_directions(count: int) -> torch.Tensor:
    """[count,3] float64 unit directions spread evenly over the sphere."""
    i = torch.arange(count, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / count
    phi = i * torch.pi * (3.0 - 5.0**0.5)
    r = (1.0 - z * z).sqrt()
    return torch.stack([r * phi.cos(), r * phi.sin(), z], dim=-1)


SH_FIT_DIRECTIONS = 64
"""Directions the SH rotation blocks are fitted on (far more than the 16 coefficients of degree 3)."""


@lru_cache(maxsize=16)
def sh_rotation_fit(degree: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The rotation-independent part of :func:`sh_rotation_matrices`, made once per (degree, device):
    the fit directions [P,3], the pseudo-inverse of their SH basis [K,P] and the block-diagonal mask [K,K]
    (float64, on ``device``). Computed on the CPU and moved once, so that decoding a scene runs no SVD
    and no host-to-device copy for it."""
    dirs = _fibonacci_directions(SH_FIT_DIRECTIONS)
    fit = torch.linalg.pinv(sh_basis(degree, dirs))
    mask = torch.block_diag(*[torch.ones(2 * l + 1, 2 * l + 1, dtype=torch.float64) for l in range(degree + 1)])
    return dirs.to(device), fit.to(device), mask.to(device)


def sh_rotation_matrices(R: torch.Tensor, degree: int) -> torch.Tensor:
    """[V,K,K] block-diagonal matrices M with ``sh_rotated = M @ sh`` for rotations R [V,3,3].

    ``f'(d) = f(R^T d)``: evaluating the rotated coefficients at ``R d`` equals the original at ``d``.
    Each degree's block is solved by least squares over 64 well-spread directions (exact, since the
    degree-l basis spans a rotation-invariant space; :func:`sh_rotation_fit`); computed in float64.
    """
    dirs, fit, mask = sh_rotation_fit(degree, R.device)
    rotated = sh_basis(degree, dirs @ R.to(torch.float64))  # [V,P,K]: Y(R^T d) as rows d^T R
    M = fit @ rotated  # [V,K,K]: least-squares solution of basis @ M = rotated
    return (M * mask).to(R.dtype)


def rotate_sh(sh: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """SH coefficients [V,...,K,3] expressed in frames rotated by R [V,3,3] (camera -> world for R = R_c2w)."""
    degree = round(sh.shape[-2] ** 0.5) - 1
    if degree == 0:
        return sh
    M = sh_rotation_matrices(R, degree).to(sh.dtype)
    # one matrix product per view (not a broadcast product: one tiny K x K product per Gaussian, 5 ms of an
    # 8-view RDO step on an H200)
    return torch.einsum("vkl,v...lc->v...kc", M, sh)
