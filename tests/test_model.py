"""CodecSplat codec-free network on the tiny preset: shapes, bounds, gradients, input checks, learning."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from codecsplat_warp.cameras import Cameras
from codecsplat_warp.data.procedural import ProceduralConfig, procedural_scene
from codecsplat_warp.errors import DeviceMismatchError, InputError
from codecsplat_warp.model import CodecSplat, DepthHead, normalized_from_depth
from codecsplat_warp.model.heads import append_channel
from codecsplat_warp.nn.config import FEATURE_STRIDE, MODEL_STRIDE, PRESETS, ModelConfig, get_preset

from conftest import DEVICES

TINY = get_preset("tiny")


@pytest.fixture(scope="module")
def scene():
    """A procedural scene of 4 views at the tiny size: views 0 and 3 are context, 1 and 2 targets."""
    s = procedural_scene(3, ProceduralConfig(width=TINY.width, height=TINY.height, num_views=4, texture_size=16))
    return s.images.float() / 255.0, s.cameras


def test_presets_match_the_paper_protocols():
    assert (PRESETS["re10k"].num_views, PRESETS["re10k"].height, PRESETS["re10k"].width) == (2, 256, 256)
    assert (PRESETS["dl3dv"].num_views, PRESETS["dl3dv"].height, PRESETS["dl3dv"].width) == (8, 256, 448)
    assert PRESETS["re10k"].sh_degree == 2
    with pytest.raises(InputError, match="preset"):
        get_preset("nope")
    with pytest.raises(InputError, match="multiples of 4"):
        ModelConfig(height=30)
    assert ModelConfig.from_dict(TINY.to_dict()) == TINY


@pytest.mark.parametrize("device", DEVICES)
def test_forward_shapes_bounds_and_finite_gradients(scene, device):
    images, cameras = scene
    model = CodecSplat(TINY).to(device)
    ctx = cameras.select([0, 3]).to(device)
    out = model(images[[0, 3]].to(device), ctx)
    V, H, W = 2, TINY.height, TINY.width
    h, w = H // FEATURE_STRIDE, W // FEATURE_STRIDE
    assert out["F_g"].shape == out["F_c"].shape == (V, TINY.feature_channels, h, w)
    assert out["F_mv"].shape == (V, TINY.cnn_channels, H // MODEL_STRIDE, W // MODEL_STRIDE)
    assert out["P_depth"].shape == (V, TINY.depth_candidates, H // MODEL_STRIDE, W // MODEL_STRIDE)
    torch.testing.assert_close(out["P_depth"].sum(1), torch.ones(V, H // 4, W // 4, device=device))
    depth, s = out["D_enc"], out["S_enc"]
    assert depth.shape == s.shape == (V, H, W)
    assert bool((depth >= ctx.near[:, None, None] * (1 - 1e-5)).all() and (depth <= ctx.far[:, None, None] * (1 + 1e-5)).all())
    torch.testing.assert_close(normalized_from_depth(depth, ctx.near, ctx.far), s, atol=1e-4, rtol=1e-4)
    g = out["gaussians"]
    assert g.means.shape == (V * H * W, 3) and g.sh.shape == (V * H * W, (TINY.sh_degree + 1) ** 2, 3)
    torch.testing.assert_close(g.quats.norm(dim=-1), torch.ones(V * H * W, device=device))
    assert bool((g.opacities > 0).all() and (g.opacities < 1).all() and (g.scales > 0).all())

    rgb = model.render(g, cameras.select([1, 2]).to(device))["rgb"]
    assert rgb.shape == (2, 3, H, W)
    assert out["S_aux"].shape == (V, H, W)  # training mode: the depth head's auxiliary on the detached F_c
    loss = ((rgb - images[[1, 2]].to(device)) ** 2).mean() + out["F_c"].square().mean()
    loss = loss + (out["S_aux"] - out["S_enc"].detach()).abs().mean()
    loss.backward()
    for name, p in model.named_parameters():
        assert p.grad is not None, f"{name} got no gradient"
        assert bool(torch.isfinite(p.grad).all()), f"{name} has a non-finite gradient"
    assert sum(float(p.grad.abs().sum()) for p in model.mvenc.parameters()) > 0


def test_refiner_starts_as_identity_and_gaussian_centres_lie_on_encoder_depth(scene):
    images, cameras = scene
    ctx = cameras.select([0, 3])
    out = CodecSplat(TINY)(images[[0, 3]], ctx)
    torch.testing.assert_close(out["F_c"], out["F_g"])
    # Camera-frame z of every Gaussian centre equals D_enc (offsets move points within the depth plane).
    means = out["gaussians"].means.reshape(2, -1, 3)
    w2c = ctx.w2c
    z = (means @ w2c[:, :3, :3].transpose(1, 2) + w2c[:, None, :3, 3])[..., 2]
    torch.testing.assert_close(z, out["D_enc"].reshape(2, -1), atol=1e-4, rtol=1e-5)


def test_more_views_than_neighbours_and_mono_slot(scene):
    images, cameras = scene
    config = ModelConfig(**{**TINY.to_dict(), "neighbours": 2})

    class Mono(nn.Module):
        out_channels = 5

        def __init__(self):
            super().__init__()
            self.conv = nn.Conv2d(3, 5, 3, stride=2, padding=1)

        def forward(self, x):
            return self.conv(x)

    model = CodecSplat(config, mono_backbone=Mono())
    out = model(images, cameras)  # 4 views, each uses its 2 nearest
    assert out["neighbours"].shape == (4, 2)
    centres = cameras.centers
    for v in range(4):
        dist = (centres - centres[v]).norm(dim=-1)
        dist[v] = float("inf")
        assert set(out["neighbours"][v].tolist()) == set(dist.argsort()[:2].tolist())
    out["F_c"].sum().backward()
    assert model.mvenc.mono_backbone.conv.weight.grad is not None
    with pytest.raises(InputError, match="out_channels"):
        CodecSplat(TINY, mono_backbone=nn.Identity())


def test_input_checks(scene):
    images, cameras = scene
    model = CodecSplat(TINY)
    ctx = cameras.select([0, 3])
    with pytest.raises(InputError, match="images"):
        model(images[[0, 3], :, :-4], ctx)
    with pytest.raises(InputError, match="images"):
        model(images[[0, 1, 3]], ctx)
    with pytest.raises(InputError, match=r"\[0, 1\]"):
        model(images[[0, 3]] * 2.0, ctx)
    with pytest.raises(InputError, match="non-finite"):
        model(images[[0, 3]].clone().fill_(float("nan")), ctx)
    with pytest.raises(InputError, match="at least 2"):
        model(images[[0]], cameras.select([0]))
    with pytest.raises(InputError, match="Cameras"):
        model(images[[0, 3]], "cams")
    with pytest.raises(InputError, match="multiples of 4"):
        odd = Cameras(ctx.K, ctx.w2c, ctx.near, ctx.far, TINY.width - 2, TINY.height)
        model(images[[0, 3], :, :, :-2], odd)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU visible to torch")
def test_device_mismatch_is_a_typed_error(scene):
    images, cameras = scene
    model = CodecSplat(TINY).cuda()
    with pytest.raises(DeviceMismatchError):
        model(images[[0, 3]], cameras.select([0, 3]))


def test_depth_head_range(scene):
    _, cameras = scene
    ctx = cameras.select([0, 3])
    feature = torch.randn(2, TINY.feature_channels, TINY.height // 2, TINY.width // 2)
    s, depth = DepthHead(TINY)(feature, ctx)
    assert s.shape == depth.shape == (2, TINY.height, TINY.width)
    assert bool((s > 0).all() and (s < 1).all())
    torch.testing.assert_close(normalized_from_depth(depth, ctx.near, ctx.far), s, atol=1e-4, rtol=1e-4)
    with pytest.raises(InputError, match="feature"):
        DepthHead(TINY)(feature[..., :-1], ctx)


def test_few_steps_on_one_scene_lower_the_loss(scene):
    images, cameras = scene
    torch.manual_seed(0)
    model = CodecSplat(TINY)
    optimizer = torch.optim.Adam(model.parameters(), lr=2e-3)
    ctx, tgt = cameras.select([0, 3]), cameras.select([1, 2])
    losses = []
    for _ in range(6):
        optimizer.zero_grad()
        rgb = model.render(model(images[[0, 3]], ctx)["gaussians"], tgt)["rgb"]
        loss = ((rgb - images[[1, 2]]) ** 2).mean()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    assert losses[-1] < 0.7 * losses[0], losses


def test_append_channel_keeps_a_channels_last_layout_and_the_values_and_gradients_of_cat():
    for channels_last in (False, True):
        x = torch.randn(2, 4, 5, 6)
        if channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        x.requires_grad_()
        extra = torch.randn(2, 5, 6, requires_grad=True)
        y = append_channel(x, extra)
        assert y.is_contiguous(memory_format=torch.channels_last if channels_last else torch.contiguous_format)
        assert torch.equal(y, torch.cat([x, extra[:, None]], dim=1))
        y.square().sum().backward()
        assert torch.equal(x.grad, 2 * x) and torch.equal(extra.grad, 2 * extra)
