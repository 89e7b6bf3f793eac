"""Map 2D->3D (Eq. 12), rotations and SH rotation, against independent references (gsplat's torch SH, numpy)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from codecsplat_warp.cameras import Cameras, intrinsics_matrix
from codecsplat_warp.errors import InputError
from codecsplat_warp.gaussians import Gaussians, quat_multiply, quat_to_rotmat, rotate_sh, rotmat_to_quat, sh_basis
from codecsplat_warp.model import PixelGaussians, depth_from_normalized, map_to_world, normalized_from_depth

# gsplat 1.5.3's pure-torch rotation and SH code is the independent reference here (installed by the dev extra).
_gsplat = pytest.importorskip("gsplat.cuda._torch_impl", reason="gsplat 1.5.3 (dev extra) is not installed")
_quat_to_rotmat, _spherical_harmonics = _gsplat._quat_to_rotmat, _gsplat._spherical_harmonics


def random_rotations(n: int, generator: torch.Generator) -> torch.Tensor:
    q = torch.nn.functional.normalize(torch.randn(n, 4, generator=generator, dtype=torch.float64), dim=-1)
    return _quat_to_rotmat(q)


def axis_angle(axis, degrees) -> torch.Tensor:
    axis = torch.tensor(axis, dtype=torch.float64)
    axis = axis / axis.norm()
    half = math.radians(degrees) / 2
    return _quat_to_rotmat(torch.cat([torch.tensor([math.cos(half)]), math.sin(half) * axis]))


def make_pixels(V, H, W, K=4, quats=None, sh=None, offsets=None) -> PixelGaussians:
    g = torch.Generator().manual_seed(1)
    return PixelGaussians(
        opacities=torch.full((V, H, W), 0.5, dtype=torch.float64),
        offsets=torch.zeros(V, H, W, 2, dtype=torch.float64) if offsets is None else offsets,
        scales=torch.full((V, H, W, 3), 0.01, dtype=torch.float64),
        quats=torch.tensor([1.0, 0, 0, 0], dtype=torch.float64).expand(V, H, W, 4).clone() if quats is None else quats,
        sh=torch.randn(V, H, W, K, 3, generator=g, dtype=torch.float64) if sh is None else sh,
    )


def cameras_with_rotations(R: torch.Tensor, H=4, W=6) -> Cameras:
    V = R.shape[0]
    c2w = torch.eye(4, dtype=torch.float64).repeat(V, 1, 1)
    c2w[:, :3, :3] = R
    c2w[:, :3, 3] = torch.tensor([0.3, -0.2, 1.5], dtype=torch.float64)
    K = intrinsics_matrix(torch.full((V,), 5.0, dtype=torch.float64), torch.full((V,), 6.0, dtype=torch.float64),
                          torch.full((V,), W / 2, dtype=torch.float64), torch.full((V,), H / 2, dtype=torch.float64))
    return Cameras.from_c2w(K, c2w, torch.full((V,), 0.5), torch.full((V,), 10.0), W, H)


def test_identity_camera_space_rotation_becomes_camera_rotation_in_world():
    R = torch.stack([axis_angle([0, 1, 0], 90), axis_angle([1, 2, 3], 47)])
    cams = cameras_with_rotations(R)
    depth = torch.full((2, 4, 6), 2.0, dtype=torch.float64)
    g = map_to_world(make_pixels(2, 4, 6), depth, cams)
    world_R = _quat_to_rotmat(g.quats).reshape(2, 24, 3, 3)
    torch.testing.assert_close(world_R, R[:, None].expand(2, 24, 3, 3), atol=1e-9, rtol=0)


def test_world_rotation_composes_camera_and_local_rotation():
    gen = torch.Generator().manual_seed(0)
    R = random_rotations(3, gen)
    local = random_rotations(3 * 4 * 6, gen).reshape(3, 4, 6, 3, 3)
    cams = cameras_with_rotations(R)
    pixels = make_pixels(3, 4, 6, quats=rotmat_to_quat(local))
    g = map_to_world(pixels, torch.full((3, 4, 6), 1.0, dtype=torch.float64), cams)
    expected = (R[:, None, None] @ local).reshape(-1, 3, 3)
    torch.testing.assert_close(_quat_to_rotmat(g.quats), expected, atol=1e-9, rtol=0)


def test_rotmat_quat_round_trip_including_half_turns():
    gen = torch.Generator().manual_seed(2)
    R = torch.cat([random_rotations(50, gen), torch.stack([axis_angle([1, 0, 0], 180), axis_angle([0, 1, 1], 180),
                                                          axis_angle([0, 0, 1], 179.9)])])
    q = rotmat_to_quat(R)
    torch.testing.assert_close(q.norm(dim=-1), torch.ones(len(R), dtype=torch.float64))
    torch.testing.assert_close(_quat_to_rotmat(q), R, atol=1e-12, rtol=0)
    torch.testing.assert_close(quat_to_rotmat(q), R, atol=1e-12, rtol=0)


def test_quat_multiply_matches_matrix_product():
    gen = torch.Generator().manual_seed(3)
    a, b = (torch.nn.functional.normalize(torch.randn(10, 4, generator=gen, dtype=torch.float64), dim=-1) for _ in range(2))
    torch.testing.assert_close(_quat_to_rotmat(quat_multiply(a, b)), _quat_to_rotmat(a) @ _quat_to_rotmat(b))


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_basis_matches_gsplat(degree):
    gen = torch.Generator().manual_seed(4)
    dirs = torch.nn.functional.normalize(torch.randn(20, 3, generator=gen, dtype=torch.float64), dim=-1)
    K = (degree + 1) ** 2
    eye = torch.eye(K, dtype=torch.float64)
    # gsplat evaluates sum_k basis_k * coeff_k; unit coefficient vectors pick out each basis function.
    ref = torch.stack([_spherical_harmonics(degree, dirs, eye[k].expand(20, K)[..., None].expand(20, K, 3).contiguous())[:, 0]
                       for k in range(K)], dim=-1)
    torch.testing.assert_close(sh_basis(degree, dirs), ref)


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_rotated_sh_in_world_equals_camera_colour(degree):
    """Colour of the world-space SH seen along R d equals the camera-space SH along d (gsplat evaluation)."""
    gen = torch.Generator().manual_seed(5)
    R = random_rotations(2, gen)
    K = (degree + 1) ** 2
    sh = torch.randn(2, 7, K, 3, generator=gen, dtype=torch.float64)
    dirs = torch.nn.functional.normalize(torch.randn(2, 7, 3, generator=gen, dtype=torch.float64), dim=-1)
    rotated = rotate_sh(sh, R)
    world_dirs = torch.einsum("vij,vnj->vni", R, dirs)
    torch.testing.assert_close(_spherical_harmonics(degree, world_dirs, rotated), _spherical_harmonics(degree, dirs, sh))


def test_sh_rotation_fits_once_per_degree_and_device(monkeypatch):
    """The SH rotation's least-squares fit (a pseudo-inverse, i.e. an SVD and, on CUDA, a host sync) is made once;
    rotating again, as every decoded scene does, runs no pseudo-inverse."""
    R = random_rotations(2, torch.Generator().manual_seed(7))
    sh = torch.randn(2, 5, 9, 3, dtype=torch.float64)
    first = rotate_sh(sh, R)

    def no_pinv(*args, **kwargs):
        raise AssertionError("the SH fit was made again")

    monkeypatch.setattr(torch.linalg, "pinv", no_pinv)
    torch.testing.assert_close(rotate_sh(sh, R), first, rtol=0, atol=0)


def test_map_to_world_sh_and_centres_against_numpy():
    gen = torch.Generator().manual_seed(6)
    R = random_rotations(2, gen)
    cams = cameras_with_rotations(R)
    depth = 1.0 + torch.rand(2, 4, 6, generator=gen, dtype=torch.float64)
    offsets = 0.5 * (torch.rand(2, 4, 6, 2, generator=gen, dtype=torch.float64) - 0.5)
    g = map_to_world(make_pixels(2, 4, 6, K=9, offsets=offsets), depth, cams)
    # Independent numpy unprojection of the shifted pixel centres.
    K, c2w = cams.K.numpy(), cams.c2w.numpy()
    expected = np.zeros((2, 4, 6, 3))
    for v in range(2):
        for y in range(4):
            for x in range(6):
                u, w = x + 0.5 + offsets[v, y, x, 0].item(), y + 0.5 + offsets[v, y, x, 1].item()
                d = depth[v, y, x].item()
                p_cam = np.array([(u - K[v, 0, 2]) / K[v, 0, 0] * d, (w - K[v, 1, 2]) / K[v, 1, 1] * d, d])
                expected[v, y, x] = c2w[v, :3, :3] @ p_cam + c2w[v, :3, 3]
    np.testing.assert_allclose(g.means.numpy(), expected.reshape(-1, 3), atol=1e-6)
    assert g.sh.shape == (48, 9, 3) and g.sh_degree == 2


def test_depth_normalisation_round_trip_and_bounds():
    near, far = torch.tensor([0.5, 2.0]), torch.tensor([100.0, 5.0])
    s = torch.tensor([[0.0, 0.25, 1.0], [1.0, 0.5, 0.0]])
    d = depth_from_normalized(s, near, far)
    torch.testing.assert_close(d[:, 0], torch.tensor([100.0, 2.0]))
    torch.testing.assert_close(d[:, 2], torch.tensor([0.5, 5.0]))
    assert float(1.0 / d[1, 1]) == pytest.approx(0.5 * (1 / 2.0 + 1 / 5.0))
    torch.testing.assert_close(normalized_from_depth(d, near, far), s)
    with pytest.raises(InputError, match="near/far"):
        depth_from_normalized(s, near[:1], far[:1])


def test_gaussians_shape_checks():
    ok = dict(means=torch.zeros(3, 3), quats=torch.zeros(3, 4), scales=torch.zeros(3, 3), opacities=torch.zeros(3),
              sh=torch.zeros(3, 4, 3))
    assert Gaussians(**ok).sh_degree == 1
    with pytest.raises(InputError, match="quats"):
        Gaussians(**{**ok, "quats": torch.zeros(3, 3)})
    with pytest.raises(InputError, match="sh"):
        Gaussians(**{**ok, "sh": torch.zeros(3, 5, 3)})


def test_view_ranges_are_the_index_ranges_of_the_split_pieces():
    n = 12
    gaussians = Gaussians(torch.arange(3 * n, dtype=torch.float32).view(n, 3), torch.zeros(n, 4), torch.zeros(n, 3),
                          torch.zeros(n), torch.zeros(n, 1, 3))
    ranges = gaussians.view_ranges(3)
    assert ranges.tolist() == [[0, 4], [4, 8], [8, 12]]
    for (first, end), piece in zip(ranges.tolist(), gaussians.split(3)):
        assert torch.equal(gaussians.means[first:end], piece.means)
    with pytest.raises(InputError, match="5 equal parts"):
        gaussians.view_ranges(5)
