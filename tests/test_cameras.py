"""Camera conventions, constructors and validation."""

from __future__ import annotations

import pytest
import torch
from codecsplat_warp.synthetic import make_rig, rotation

from codecsplat_warp.cameras import Cameras, intrinsics_matrix, rigid_inverse
from codecsplat_warp.checks import check_tensor, common_device
from codecsplat_warp.errors import CameraError, DeviceMismatchError, InputError


def _K(n=1, f=100.0, w=64, h=48):
    return intrinsics_matrix(torch.full((n,), f, dtype=torch.float64), torch.full((n,), f, dtype=torch.float64),
                             torch.full((n,), w / 2, dtype=torch.float64), torch.full((n,), h / 2, dtype=torch.float64))


def test_c2w_is_the_rigid_inverse_and_centres_are_column_three():
    cams = make_rig(3, 32, 24, offset=(10.0, -2.0, 3.0))
    eye = torch.eye(4, dtype=torch.float64).expand(3, 4, 4)
    torch.testing.assert_close(cams.c2w @ cams.w2c, eye)
    torch.testing.assert_close(cams.centers, torch.linalg.inv(cams.w2c)[:, :3, 3])


def test_principal_point_projects_the_optical_axis_to_the_image_centre():
    """cx = W/2 with +0.5 pixel centres: a point on the optical axis lands between the two middle pixels."""
    cams = Cameras.from_c2w(_K(w=64, h=48), torch.eye(4, dtype=torch.float64)[None], [0.1], [10.0], 64, 48)
    p = torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64)
    uv = cams.K[0] @ p / p[2]
    assert uv[:2].tolist() == [32.0, 24.0]  # = pixel index 31.5 + 0.5: the image centre


def test_opengl_constructor_flips_y_and_z():
    c2w_gl = torch.eye(4, dtype=torch.float64)[None]
    cams = Cameras.from_opengl_c2w(_K(), c2w_gl, [0.1], [10.0], 64, 48)
    # an OpenGL camera looks down -z: the world point (0,0,-2) is in front of it (OpenCV z = +2)
    p_cam = cams.w2c[0] @ torch.tensor([0.0, 0.0, -2.0, 1.0], dtype=torch.float64)
    assert p_cam[2] == 2.0
    p_cam = cams.w2c[0] @ torch.tensor([0.0, 1.0, -2.0, 1.0], dtype=torch.float64)
    assert p_cam[1] == -1.0  # OpenGL up is OpenCV -y


def test_normalized_intrinsics_round_trip():
    cams = make_rig(2, 40, 30)
    again = Cameras.from_normalized_intrinsics(cams.normalized_intrinsics(), cams.w2c, cams.near, cams.far, 40, 30)
    torch.testing.assert_close(again.K, cams.K)
    half = Cameras.from_normalized_intrinsics(cams.normalized_intrinsics(), cams.w2c, 0.5, 100.0, 20, 15)
    torch.testing.assert_close(half.K, cams.rescaled(20, 15).K)
    assert half.near.tolist() == [0.5, 0.5]


def test_rescale_and_crop_keep_pixel_edge_convention():
    cams = make_rig(1, 40, 30)
    small = cams.rescaled(10, 15)
    # the image corner (0,0) and (W,H) map to the same rays before and after rescaling
    Kinv, Kinv_small = torch.linalg.inv(cams.K[0]), torch.linalg.inv(small.K[0])
    for corner, corner_small in (([0.0, 0.0], [0.0, 0.0]), ([40.0, 30.0], [10.0, 15.0])):
        ray = Kinv @ torch.tensor(corner + [1.0], dtype=torch.float64)
        ray_small = Kinv_small @ torch.tensor(corner_small + [1.0], dtype=torch.float64)
        torch.testing.assert_close(ray, ray_small)
    crop = cams.cropped(4, 3, 30, 20)
    assert crop.K[0, 0, 2] == cams.K[0, 0, 2] - 4 and (crop.width, crop.height) == (30, 20)
    with pytest.raises(CameraError, match="crop"):
        cams.cropped(20, 0, 30, 10)


def _project(cams: Cameras, points: torch.Tensor) -> torch.Tensor:
    """[V,2] pixel positions (u, v) of one world point per view."""
    cam = (cams.w2c @ torch.cat([points, torch.ones(len(points), 1, dtype=points.dtype)], 1)[..., None])[:, :3, 0]
    pix = (cams.K @ cam[..., None])[..., 0]
    return pix[:, :2] / pix[:, 2:]


def test_mirrored_cameras_see_the_mirrored_world_in_the_flipped_image():
    cams = make_rig(3, 40, 30, offset=(0.3, -0.2, 0.1))
    mirror = cams.mirrored()
    Cameras(mirror.K, mirror.w2c, mirror.near, mirror.far, 40, 30)  # validates: still proper rotations, no skew
    points = torch.tensor([[0.1, 0.2, 4.0], [-0.5, 0.3, 3.0], [0.7, -0.4, 5.0]], dtype=torch.float64)
    uv = _project(cams, points)
    uv_mirror = _project(mirror, points * torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64))
    torch.testing.assert_close(uv_mirror[:, 0], 40.0 - uv[:, 0])
    torch.testing.assert_close(uv_mirror[:, 1], uv[:, 1])
    torch.testing.assert_close(mirror.mirrored().w2c, cams.w2c)
    torch.testing.assert_close(mirror.mirrored().K, cams.K)


def test_relative_transforms_map_reference_camera_points_to_source_camera():
    cams = make_rig(3, 16, 12, offset=(100.0, 0.0, 0.0))
    nbrs = torch.tensor([[1, 2], [0, 2], [0, 1]])
    rel = cams.relative_transforms(nbrs)
    p_ref = torch.tensor([0.1, -0.2, 3.0, 1.0], dtype=torch.float64)
    for r in range(3):
        world = cams.c2w[r] @ p_ref
        for m in range(2):
            torch.testing.assert_close(rel[r, m] @ p_ref, cams.w2c[nbrs[r, m]] @ world)


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda K, T, n, f: K.__setitem__((1, 0, 0), -5.0), "view 1: focal"),
        (lambda K, T, n, f: T.__setitem__((0, 0, 0), 1.5), "view 0: w2c rotation"),
        (lambda K, T, n, f: T.__setitem__((1, slice(None, 3), 0), -T[1, :3, 0]), "view 1: w2c rotation"),  # reflection
        (lambda K, T, n, f: T.__setitem__((1, 3, 0), 0.5), "view 1: w2c bottom row"),
        (lambda K, T, n, f: n.__setitem__(0, 0.0), "view 0: need 0 < near < far"),
        (lambda K, T, n, f: f.__setitem__(1, 0.1), "view 1: need 0 < near < far"),
        (lambda K, T, n, f: K.__setitem__((0, 0, 2), float("inf")), "view 0: K holds NaN or Inf"),
        (lambda K, T, n, f: K.__setitem__((0, 0, 1), 3.0), "view 0: K must be"),
    ],
)
def test_invalid_cameras_raise_camera_error_naming_the_view(mutate, message):
    base = make_rig(2, 16, 12)
    K, T, n, f = base.K.clone(), base.w2c.clone(), base.near.clone(), base.far.clone()
    mutate(K, T, n, f)
    with pytest.raises(CameraError, match=message):
        Cameras(K, T, n, f, 16, 12)


def test_camera_shape_dtype_and_size_errors():
    base = make_rig(2, 16, 12)
    with pytest.raises(CameraError, match="w2c"):
        Cameras(base.K, base.w2c[:1], base.near, base.far, 16, 12)
    with pytest.raises(CameraError, match="dtype"):
        Cameras(base.K.float(), base.w2c, base.near, base.far, 16, 12)
    with pytest.raises(CameraError, match="image size"):
        Cameras(base.K, base.w2c, base.near, base.far, 0, 12)
    with pytest.raises(CameraError, match="pose matrices"):
        Cameras.from_c2w(base.K, torch.eye(3, dtype=torch.float64)[None].repeat(2, 1, 1), base.near, base.far, 16, 12)


def test_rigid_inverse_matches_general_inverse():
    T = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    T[0, :3, :3] = rotation(0.3, -0.2, 1.0)
    T[:, :3, 3] = torch.tensor([[1.0, 2.0, 3.0], [-4.0, 0.5, 7.0]], dtype=torch.float64)
    torch.testing.assert_close(rigid_inverse(T), torch.linalg.inv(T))


def test_select_and_to_keep_values():
    cams = make_rig(3, 16, 12)
    sub = cams.select([2, 0])
    assert torch.equal(sub.K, cams.K[[2, 0]]) and len(sub) == 2
    f32 = cams.to(dtype=torch.float32)
    assert f32.dtype == torch.float32 and f32.w2c.dtype == torch.float32


def test_device_helpers_name_arguments():
    with pytest.raises(DeviceMismatchError, match="a on cpu, b on meta"):
        common_device(a=torch.zeros(1), b=torch.zeros(1, device="meta"))
    with pytest.raises(InputError, match=r"x must have shape \[V,3\]"):
        check_tensor("x", torch.zeros(2, 4), ("V", 3))
    with pytest.raises(InputError, match="x must be a torch.Tensor"):
        check_tensor("x", [1.0], ("V",))
