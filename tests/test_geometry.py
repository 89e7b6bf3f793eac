"""Unprojection, reprojection averaging and plane sweeps against independent references (kornia, grid_sample)."""

from __future__ import annotations

import json

import kornia
import numpy as np
import pytest
import torch
from conftest import DEVICES
from codecsplat_warp.synthetic import make_rig, smooth_depth

from codecsplat_warp.cameras import Cameras
from codecsplat_warp.errors import CameraError, DeviceMismatchError, InputError
from codecsplat_warp.ops.geometry import (
    all_other_views,
    inverse_depth_candidates,
    nearest_views,
    plane_sweep_cost_volume,
    reproject_average,
    unproject,
)
from codecsplat_warp.reference.geometry import (
    cost_volume_reference,
    reproject_average_reference,
    unproject_reference,
)


# ---------------------------------------------------------------------------------------------- unproject
@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_unproject_matches_torch_reference(device, dtype):
    cams = make_rig(3, 20, 14, dtype=dtype, device=device, offset=(5.0, -3.0, 2.0))
    depth = smooth_depth(3, 7, 10, dtype=dtype, device=device)  # half-resolution grid: intrinsics rescaled
    got = unproject(depth, cams)
    want = unproject_reference(depth, cams)
    tol = 1e-12 if dtype == torch.float64 else 2e-5
    assert got.shape == (3, 7, 10, 3) and got.dtype == dtype
    torch.testing.assert_close(got, want, rtol=tol, atol=tol)


def test_unproject_matches_kornia_depth_to_3d():
    """kornia puts pixel centres at integers: the same camera there has cx - 0.5, cy - 0.5."""
    cams = make_rig(2, 16, 12)
    depth = smooth_depth(2, 12, 16)
    got = unproject(depth, cams)
    for v in range(2):
        K = cams.K[v].clone()
        K[0, 2] -= 0.5
        K[1, 2] -= 0.5
        cam_pts = kornia.geometry.depth.depth_to_3d_v2(depth[v:v + 1], K[None], normalize_points=False)[0]  # [H,W,3]
        world = kornia.geometry.linalg.transform_points(cams.c2w[v][None], cam_pts.reshape(1, -1, 3)).reshape(12, 16, 3)
        torch.testing.assert_close(got[v], world, rtol=1e-10, atol=1e-10)


def test_unproject_gradcheck():
    cams = make_rig(2, 6, 5)
    depth = smooth_depth(2, 5, 6).requires_grad_()
    assert torch.autograd.gradcheck(lambda d: unproject(d, cams), (depth,))


def test_unproject_half_precision_inputs_compute_in_float32():
    cams = make_rig(2, 8, 6, dtype=torch.float32)
    depth = smooth_depth(2, 6, 8, dtype=torch.float32)
    got = unproject(depth.to(torch.bfloat16), cams)
    assert got.dtype == torch.float32 and torch.isfinite(got).all()
    torch.testing.assert_close(got, unproject(depth.to(torch.bfloat16).float(), cams))


# ---------------------------------------------------------------------------------------------- reproject
@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_reproject_average_matches_grid_sample_reference(device, dtype):
    V, C, H, W = 3, 5, 9, 11
    cams = make_rig(V, 2 * W, 2 * H, dtype=dtype, device=device)  # feature grid at half the image size
    feat = torch.randn(V, C, H, W, dtype=dtype, device=device)
    depth = smooth_depth(V, H, W, dtype=dtype, device=device)
    avg, count = reproject_average(feat, depth, cams)
    ref_avg, ref_count = reproject_average_reference(feat, depth, cams, all_other_views(V, device))
    assert count.dtype == torch.int32
    assert torch.equal(count, ref_count)
    assert (count > 0).float().mean() > 0.5, "rig should give mostly valid samples"
    tol = 1e-10 if dtype == torch.float64 else 1e-5
    torch.testing.assert_close(avg, ref_avg, rtol=tol, atol=tol)


def test_reproject_average_with_neighbour_lists_and_zero_where_invalid():
    V, C, H, W = 4, 3, 8, 10
    cams = make_rig(V, W, H, baseline=0.6)
    feat = torch.randn(V, C, H, W, dtype=torch.float64)
    depth = smooth_depth(V, H, W)
    depth[0, :, :3] = 0.01  # points far too close: they leave every source image
    nbrs = nearest_views(cams, 2)
    avg, count = reproject_average(feat, depth, cams, nbrs)
    ref_avg, ref_count = reproject_average_reference(feat, depth, cams, nbrs)
    assert torch.equal(count, ref_count)
    torch.testing.assert_close(avg, ref_avg, rtol=1e-10, atol=1e-10)
    assert (count[0, :, :3] == 0).all() and (avg[0, :, :, :3] == 0).all()


def test_reproject_average_matches_kornia_warp_frame_depth_inside():
    """Two views: our average is view 1 warped into view 0; kornia's warp_frame_depth computes the same
    (integer pixel centres, align_corners=True), so interior pixels must agree."""
    H, W = 12, 16
    cams = make_rig(2, W, H)
    feat = torch.randn(2, 4, H, W, dtype=torch.float64)
    depth = smooth_depth(2, H, W)
    src_trans_dst = cams.w2c[1:2] @ cams.c2w[0:1]
    # kornia takes one intrinsics matrix for both views: give the rig a shared K
    cams_same = Cameras(cams.K[:1].repeat(2, 1, 1), cams.w2c, cams.near, cams.far, W, H)
    avg, count = reproject_average(feat, depth, cams_same)
    K_same = cams_same.K[:1].clone()
    K_same[:, :2, 2] -= 0.5
    warped = kornia.geometry.depth.warp_frame_depth(feat[1:2], depth[0:1, None], src_trans_dst, K_same)
    # interior: projection lands at least one pixel inside source image
    p = unproject(depth[:1], cams_same.select(0))[0]
    p_src = p @ cams_same.w2c[1, :3, :3].T + cams_same.w2c[1, :3, 3]
    uv = (p_src @ cams_same.K[1].T)[..., :2] / p_src[..., 2:]
    inside = (uv[..., 0] > 1.5) & (uv[..., 0] < W - 1.5) & (uv[..., 1] > 1.5) & (uv[..., 1] < H - 1.5)
    assert inside.float().mean() > 0.4
    torch.testing.assert_close(avg[0][:, inside], warped[0][:, inside], rtol=1e-9, atol=1e-9)
    assert (count[0][inside] == 1).all()


def test_reproject_average_gradcheck_feat_and_depth():
    V, C, H, W = 3, 2, 5, 6
    cams = make_rig(V, W, H)
    feat = torch.randn(V, C, H, W, dtype=torch.float64, requires_grad=True)
    depth = smooth_depth(V, H, W).requires_grad_()
    assert torch.autograd.gradcheck(lambda f, d: reproject_average(f, d, cams)[0], (feat, depth))


def test_reproject_average_gradients_match_reference():
    V, C, H, W = 3, 4, 7, 9
    cams = make_rig(V, W, H)
    feat = torch.randn(V, C, H, W, dtype=torch.float64, requires_grad=True)
    depth = smooth_depth(V, H, W).requires_grad_()
    weights = torch.randn(V, C, H, W, dtype=torch.float64)
    grads = torch.autograd.grad((reproject_average(feat, depth, cams)[0] * weights).sum(), (feat, depth))
    ref = reproject_average_reference(feat, depth, cams, all_other_views(V))[0]
    ref_grads = torch.autograd.grad((ref * weights).sum(), (feat, depth))
    for g, r in zip(grads, ref_grads):
        torch.testing.assert_close(g, r, rtol=1e-9, atol=1e-9)


def test_reproject_average_of_single_view_is_empty_average():
    cams = make_rig(1, 6, 5)
    avg, count = reproject_average(torch.ones(1, 2, 5, 6, dtype=torch.float64), smooth_depth(1, 5, 6), cams)
    assert (avg == 0).all() and (count == 0).all()


# ---------------------------------------------------------------------------------------------- plane sweep
@pytest.mark.parametrize("device", DEVICES)
def test_cost_volume_matches_reference(device):
    V, C, H, W, D = 3, 4, 6, 8, 5
    cams = make_rig(V, 4 * W, 4 * H, device=device)
    feat = torch.randn(V, C, H, W, dtype=torch.float64, device=device)
    candidates = inverse_depth_candidates(cams.with_depth_range(1.0, 10.0), D)
    got = plane_sweep_cost_volume(feat, candidates, cams)
    want = cost_volume_reference(feat, candidates, cams, all_other_views(V, device))
    assert got.shape == (V, D, H, W)
    torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-10)


def test_cost_volume_gradcheck():
    V, C, H, W = 2, 2, 4, 5
    cams = make_rig(V, W, H)
    feat = torch.randn(V, C, H, W, dtype=torch.float64, requires_grad=True)
    candidates = torch.tensor([2.0, 3.0, 5.0], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda f: plane_sweep_cost_volume(f, candidates, cams), (feat,))


def test_inverse_depth_candidates_are_uniform_in_inverse_depth():
    cams = make_rig(2, 8, 8).with_depth_range(1.0, 9.0)
    d = inverse_depth_candidates(cams, 5)
    torch.testing.assert_close(d[:, 0], cams.far)
    torch.testing.assert_close(d[:, -1], cams.near)
    inv = 1.0 / d
    torch.testing.assert_close(inv[:, 1:] - inv[:, :-1], (inv[:, 1:2] - inv[:, :1]).expand(-1, 4))


# ---------------------------------------------------------------------------------------------- bad input
def test_bad_inputs_raise_typed_errors_naming_the_argument():
    cams = make_rig(2, 8, 6)
    feat = torch.randn(2, 3, 6, 8, dtype=torch.float64)
    depth = smooth_depth(2, 6, 8)
    with pytest.raises(InputError, match="depth"):
        reproject_average(feat, depth[:, :5], cams)
    with pytest.raises(InputError, match="feat"):
        reproject_average(feat[:1], depth[:1], cams)
    with pytest.raises(InputError, match="depth must be > 0"):
        unproject(depth * 0, cams)
    with pytest.raises(InputError, match="non-finite"):
        reproject_average(feat.clone().index_fill_(0, torch.tensor([1]), float("nan")), depth, cams)
    with pytest.raises(InputError, match="depth is empty"):
        unproject(depth[:, :0], cams)
    with pytest.raises(InputError, match="dtype"):
        reproject_average(feat.float(), depth, cams)
    with pytest.raises(InputError, match="neighbours"):
        reproject_average(feat, depth, cams, torch.tensor([[1], [2]]))
    with pytest.raises(InputError, match="feat must have dtype"):
        reproject_average(feat.to(torch.int64), depth, cams)


def test_noncontiguous_inputs_are_made_contiguous():
    cams = make_rig(2, 8, 6)
    feat = torch.randn(2, 3, 8, 6, dtype=torch.float64).transpose(2, 3)
    depth = smooth_depth(2, 8, 6).transpose(1, 2)
    avg, _ = reproject_average(feat, depth, cams)
    ref, _ = reproject_average(feat.contiguous(), depth.contiguous(), cams)
    assert torch.equal(avg, ref)


def test_nan_camera_raises_camera_error_naming_the_view():
    cams = make_rig(3, 8, 6)
    w2c = cams.w2c.clone()
    w2c[2, 0, 3] = float("nan")
    with pytest.raises(CameraError, match="view 2"):
        Cameras(cams.K, w2c, cams.near, cams.far, 8, 6)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU to put tensors on two devices")
def test_tensors_on_different_devices_raise():
    cams = make_rig(2, 8, 6)
    with pytest.raises(DeviceMismatchError):
        reproject_average(torch.randn(2, 3, 6, 8, dtype=torch.float64).cuda(), smooth_depth(2, 6, 8), cams)


# ---------------------------------------------------------------------------------------------- real data
def _json_cameras(scene_dir, indices):
    """Parse cameras.json with plain numpy (independent of the Cameras class)."""
    meta = json.loads((scene_dir / "cameras.json").read_text())
    frames = [meta["frames"][i] for i in indices]
    K = np.stack([[[f["fx"], 0, f["cx"]], [0, f["fy"], f["cy"]], [0, 0, 1]] for f in frames]).astype(np.float64)
    c2w = np.stack([np.array(f["c2w"], dtype=np.float64) for f in frames])
    return K, c2w, frames[0]["w"], frames[0]["h"], meta["near"], meta["far"]


@pytest.mark.data
def test_real_scenes_points_land_where_cameras_json_says(data_root):
    """On every real scene: a plane of depth in view 0, reprojected into view 1 through a coordinate-valued
    feature map, lands at the pixel that cameras.json's matrices give, to 0.01 px (bilinear sampling of a
    linear map is exact; the slack covers rotations stored orthonormal only to ~1e-6)."""
    scenes = sorted(p.parent.name for p in data_root.glob("*/cameras.json"))
    assert scenes, f"no scenes with cameras.json under {data_root}"
    for scene in scenes:
        _check_scene_reprojection(data_root, scene)


def _check_scene_reprojection(data_root, scene):
    K, c2w, w, h, near, far = _json_cameras(data_root / scene, [0, 1])
    cams = Cameras.from_c2w(torch.from_numpy(K), torch.from_numpy(c2w), torch.full((2,), near, dtype=torch.float64),
                            torch.full((2,), far, dtype=torch.float64), w, h)
    gh, gw = h // 8, w // 8
    depth_value = float(np.sqrt(near * far))
    depth = torch.full((2, gh, gw), depth_value, dtype=torch.float64)
    # feature of view b = its own pixel coordinates (u, v) at the centres of the coarse grid
    ys, xs = torch.meshgrid(torch.arange(gh, dtype=torch.float64) + 0.5, torch.arange(gw, dtype=torch.float64) + 0.5, indexing="ij")
    coords = torch.stack([xs * w / gw, ys * h / gh])
    feat = torch.stack([coords, coords])
    avg, count = reproject_average(feat, depth, cams)
    # expected: numpy projection of the unprojected points (view 0 -> world -> view 1)
    u0 = (xs.numpy() * w / gw)
    v0 = (ys.numpy() * h / gh)
    rays = np.stack([(u0 - K[0, 0, 2]) / K[0, 0, 0], (v0 - K[0, 1, 2]) / K[0, 1, 1], np.ones_like(u0)], -1)
    world = (rays * depth_value) @ c2w[0, :3, :3].T + c2w[0, :3, 3]
    cam1 = (world - c2w[1, :3, 3]) @ c2w[1, :3, :3]
    uv1 = (cam1 @ K[1].T)[..., :2] / cam1[..., 2:]
    margin = (uv1[..., 0] > w / gw) & (uv1[..., 0] < w - w / gw) & (uv1[..., 1] > h / gh) & (uv1[..., 1] < h - h / gh)
    valid = count[0].numpy() == 1
    assert (valid & margin).sum() > 0, f"{scene}: no overlap between views 0 and 1 at depth {depth_value:.3g}"
    got = avg[0].permute(1, 2, 0).numpy()
    np.testing.assert_allclose(got[valid & margin], uv1[valid & margin], atol=1e-2, err_msg=scene)
    assert (valid[margin] == 1).all()


# ---------------------------------------------------------------------------------------------- host-side work
def test_cpu_row_pieces_give_the_same_results_as_one_launch():
    """CPU launches are split by rows over torch's threads; gradients scatter into per-piece buffers."""
    cams = make_rig(3, 24, 18)
    feat = torch.randn(3, 4, 9, 12, dtype=torch.float64)
    depth = smooth_depth(3, 9, 12)
    results = {}
    threads = torch.get_num_threads()
    try:
        for n in (1, 3):
            torch.set_num_threads(n)
            f, d = feat.clone().requires_grad_(), depth.clone().requires_grad_()
            avg, count = reproject_average(f, d, cams)
            cost = plane_sweep_cost_volume(f, inverse_depth_candidates(cams, 4), cams)
            (avg.square().sum() + cost.square().sum()).backward()
            results[n] = (avg, count, cost, f.grad, d.grad)
    finally:
        torch.set_num_threads(threads)
    for one, three in zip(results[1], results[3]):
        torch.testing.assert_close(one, three, rtol=1e-12, atol=1e-12)


def test_camera_arrays_are_memoized_and_follow_in_place_edits():
    cams = make_rig(2, 16, 12, dtype=torch.float64)
    feat = torch.randn(2, 3, 12, 16, dtype=torch.float64)
    depth = smooth_depth(2, 12, 16)
    first = reproject_average(feat, depth, cams)[0]
    assert len(cams.__dict__["_memo"]) == 2  # the version stamp and one entry
    held = cams.memo_values()
    assert len(held) == 1 and held[0] is next(v for k, v in cams.__dict__["_memo"].items() if k != "versions")
    torch.testing.assert_close(reproject_average(feat, depth, cams)[0], first, rtol=0, atol=0)
    with torch.no_grad():
        cams.w2c[1, 0, 3] += 0.5  # moves view 1: the memoized transforms must not be reused
    want = reproject_average_reference(feat, depth, cams, all_other_views(2))[0]
    torch.testing.assert_close(reproject_average(feat, depth, cams)[0], want, rtol=1e-10, atol=1e-10)
    for _ in range(20):  # fresh neighbour tensors every call: the memo stays bounded
        reproject_average(feat, depth, cams, neighbours=torch.tensor([[1], [0]]))
    assert len(cams.__dict__["_memo"]) <= 9
    assert all(value is not held[0] for value in cams.memo_values())  # dropped by the cache, still alive for whoever holds it
