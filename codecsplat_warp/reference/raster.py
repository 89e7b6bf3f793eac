"""Dense pure-torch reference of :func:`codecsplat_warp.ops.raster.rasterize`: every Gaussian at every pixel.

Same conventions and constants as the Warp rasterizer (and gsplat 1.5.3): EWA projection with the
frustum-clamped Jacobian, +0.3 px^2 blur, antialiasing compensation, opacity-aware radii and culling,
``alpha = min(0.999, o exp(-power))``, rows with ``alpha < 1/255`` skipped, a pixel stops before the first
row that would take its transmittance to ``<= min_transmittance`` (gsplat's 1e-4 by default). Gradients come
from torch autograd. Memory is ``O(B * H * W * N)``: for tests and small benchmarks only.

Depth order ties are broken like the rasterizer's stable sort: by float32 depth, then Gaussian index.
"""

from __future__ import annotations

import math

import torch

from ..kernels.raster_row import ALPHA_LEVELS, ALPHA_THRESHOLD, MAX_ALPHA

MIN_TRANSMITTANCE = 1e-4
"""Default early-stop transmittance (gsplat's)."""
LOW_PASS_PX2 = 0.3
MAX_EXTENT_SIGMAS = 3.33

SH_C0 = 0.28209479177387814


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """``[N,4]`` wxyz quaternions (any norm) -> ``[N,3,3]`` rotation matrices."""
    w, x, y, z = torch.nn.functional.normalize(quats, dim=-1).unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]  # fmt: skip
    return torch.stack(rows, dim=-1).reshape(quats.shape[:-1] + (3, 3))


def sh_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """``[..., (degree+1)^2]`` real SH basis (gsplat's order and constants) at normalised ``dirs``."""
    x, y, z = torch.nn.functional.normalize(dirs, dim=-1).unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        a = -0.48860251190292
        out += [a * y, -a * z, a * x]
    if degree >= 2:
        z2 = z * z
        b = -1.092548430592079 * z
        a = 0.5462742152960395
        c1 = x * x - y * y
        s1 = 2 * x * y
        out += [a * s1, b * y, 0.9461746957575601 * z2 - 0.3153915652525201, b * x, a * c1]
    if degree >= 3:
        c = -2.285228997322329 * z2 + 0.4570457994644658
        b = 1.445305721320277 * z
        a = -0.5900435899266435
        c2 = x * c1 - y * s1
        s2 = x * s1 + y * c1
        out += [a * s2, b * s1, c * y, z * (1.865881662950577 * z2 - 1.119528997770346), c * x, b * c1, a * c2]
    return torch.stack(out, dim=-1)


def project(means, quats, scales, opacities, viewmat, K, width, height, near, far, antialiased):
    """Projection of N Gaussians into one camera.

    Returns a dict of ``means2d [N,2]``, ``conics [N,3]`` (a, b, c), ``opacities [N]`` (compensated in
    antialiased mode), ``depths [N]``, ``radii [N,2]`` int32 (0 = culled) and ``visible [N]`` bool.
    """
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    p = means @ R.T + t
    x, y, z = p.unbind(-1)
    M = R @ quat_to_rotmat(quats) * scales[:, None, :]
    cov = M @ M.transpose(-1, -2)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    margin_x, margin_y = 0.3 * 0.5 * width / fx, 0.3 * 0.5 * height / fy
    safe_z = torch.where(z > near, z, torch.ones_like(z))
    tx = safe_z * torch.clamp(x / safe_z, -(cx / fx + margin_x), (width - cx) / fx + margin_x)
    ty = safe_z * torch.clamp(y / safe_z, -(cy / fy + margin_y), (height - cy) / fy + margin_y)
    zeros = torch.zeros_like(z)
    J = torch.stack(
        [fx / safe_z, zeros, -fx * tx / safe_z**2, zeros, fy / safe_z, -fy * ty / safe_z**2], dim=-1
    ).reshape(-1, 2, 3)
    cov2d = J @ cov @ J.transpose(-1, -2)
    det_orig = cov2d[:, 0, 0] * cov2d[:, 1, 1] - cov2d[:, 0, 1] * cov2d[:, 1, 0]
    blurred = cov2d + LOW_PASS_PX2 * torch.eye(2, dtype=means.dtype, device=means.device)
    det = blurred[:, 0, 0] * blurred[:, 1, 1] - blurred[:, 0, 1] * blurred[:, 1, 0]
    safe_det = torch.where(det > 0, det, torch.ones_like(det))
    conics = torch.stack([blurred[:, 1, 1], -blurred[:, 0, 1], blurred[:, 0, 0]], dim=-1) / safe_det[:, None]
    if antialiased:
        ratio = torch.clamp(det_orig / safe_det, min=0.0)
        opacities = opacities * ratio / torch.sqrt(torch.clamp(ratio, min=1e-12))
    means2d = torch.stack([fx * x / safe_z + cx, fy * y / safe_z + cy], dim=-1)
    with torch.no_grad():
        extent = torch.sqrt(2 * torch.log(torch.clamp(opacities * ALPHA_LEVELS, min=1.0)))
        extent = torch.clamp(extent, max=MAX_EXTENT_SIGMAS)
        diag = torch.stack([blurred[:, 0, 0], blurred[:, 1, 1]], dim=-1).clamp(min=0)
        radii = torch.ceil(extent[:, None] * torch.sqrt(diag))
        visible = (z > near) & (z < far) & (det > 0) & (opacities >= ALPHA_THRESHOLD) & (radii > 0).any(-1)
        visible &= (means2d[:, 0] + radii[:, 0] > 0) & (means2d[:, 0] - radii[:, 0] < width)
        visible &= (means2d[:, 1] + radii[:, 1] > 0) & (means2d[:, 1] - radii[:, 1] < height)
        visible &= torch.isfinite(means2d).all(-1) & torch.isfinite(conics).all(-1)
        radii = torch.where(visible[:, None], radii, torch.zeros_like(radii)).to(torch.int32)
    return {"means2d": means2d, "conics": conics, "opacities": opacities, "depths": z, "radii": radii,
            "visible": visible}  # fmt: skip


def gaussian_colors(means, colors, viewmat, sh_degree):
    """``[N,3]`` RGB per Gaussian for one camera: the colours, or ``max(SH + 0.5, 0)`` towards the mean."""
    if colors.dim() == 2:
        return colors
    center = -viewmat[:3, :3].T @ viewmat[:3, 3]
    basis = sh_basis(sh_degree, means - center)
    return torch.clamp_min((basis[..., None] * colors[:, : basis.shape[-1]]).sum(-2) + 0.5, 0.0)


def composite(means2d, conics, opacities, colors, depths, visible, width, height, background,
              min_transmittance=MIN_TRANSMITTANCE):  # fmt: skip
    """Dense front-to-back compositing of one camera: ``(rgb [H,W,3], depth_sum [H,W,1], alpha [H,W,1])``.

    Each pixel stops before the first used row whose transmittance after it is ``<= min_transmittance``."""
    order = torch.sort(depths.detach().float(), stable=True).indices
    order = order[visible[order]]
    mu, con, op, col, dep = means2d[order], conics[order], opacities[order], colors[order], depths[order]
    jj, ii = torch.meshgrid(
        torch.arange(height, dtype=means2d.dtype, device=means2d.device),
        torch.arange(width, dtype=means2d.dtype, device=means2d.device),
        indexing="ij",
    )
    pix = torch.stack([ii, jj], dim=-1).reshape(-1, 1, 2) + 0.5
    d = mu[None] - pix
    power = 0.5 * (con[None, :, 0] * d[..., 0] ** 2 + con[None, :, 2] * d[..., 1] ** 2) + con[None, :, 1] * d[
        ..., 0
    ] * d[..., 1]
    alpha = torch.clamp(op[None] * torch.exp(-power), max=MAX_ALPHA)
    used = (power >= 0) & (alpha >= ALPHA_THRESHOLD)
    alpha = torch.where(used, alpha, torch.zeros_like(alpha))
    with torch.no_grad():
        before = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1]], dim=1), dim=1)
        stop = used & (before * (1 - alpha) <= min_transmittance)
        keep = torch.cumsum(stop.to(torch.int64), dim=1) == 0
    alpha = alpha * keep
    T_before = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1]], dim=1), dim=1)
    weights = alpha * T_before
    T_final = torch.prod(1 - alpha, dim=1)
    rgb = weights @ col
    if background is not None:
        rgb = rgb + T_final[:, None] * background[None]
    depth_sum = weights @ dep[:, None]
    return rgb.reshape(height, width, 3), depth_sum.reshape(height, width, 1), (1 - T_final).reshape(height, width, 1)


def rasterize_dense(
    means, quats, scales, opacities, colors, viewmats, Ks, width, height, near=0.01, far=1e10,
    background=None, mode="classic", sh_degree=None, render_depth=True, min_transmittance=MIN_TRANSMITTANCE,
):  # fmt: skip
    """Reference of :func:`codecsplat_warp.ops.raster.rasterize` (same arguments and outputs).

    Returns ``(rgb [B,H,W,3], depth [B,H,W,1] or None, alpha [B,H,W,1], radii [B,N,2] int32)``.
    """
    if colors.dim() == 3 and sh_degree is None:
        sh_degree = math.isqrt(colors.shape[1]) - 1
    viewmats = viewmats.to(means.dtype)
    Ks = Ks.to(means.dtype)
    rgbs, depths, alphas, radii = [], [], [], []
    for b in range(viewmats.shape[0]):
        proj = project(means, quats, scales, opacities, viewmats[b], Ks[b], width, height, near, far,
                       mode == "antialiased")  # fmt: skip
        color = gaussian_colors(means, colors, viewmats[b], sh_degree)
        bg = None if background is None else background[b]
        rgb, depth_sum, alpha = composite(proj["means2d"], proj["conics"], proj["opacities"], color,
                                          proj["depths"], proj["visible"], width, height, bg,
                                          min_transmittance)  # fmt: skip
        rgbs.append(rgb)
        depths.append(depth_sum / alpha.clamp_min(1e-10))
        alphas.append(alpha)
        radii.append(proj["radii"])
    depth = torch.stack(depths) if render_depth else None
    return torch.stack(rgbs), depth, torch.stack(alphas), torch.stack(radii)
