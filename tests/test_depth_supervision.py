"""Geometry supervision of training: the masked log-depth loss, reference depth in batches (exact for procedural
scenes), its gradient reaching the encoder, and the render loss on the context views themselves."""

from __future__ import annotations

import json
import math
import pathlib

import pytest
import torch
from conftest import LPIPS_WEIGHTS as WEIGHTS
from conftest import needs_lpips
from PIL import Image

from train.data import DEPTH_FOLDER, Augmentation, BatchShape, DataSpec, RealScenes, make_source
from train.stage1 import TrainConfig, reference_depth_loss, stage1_loss

from codecsplat_warp.data.depth_maps import DEPTH_FORMAT, INDEX_FILE, depth_scale, quantize_depth
from codecsplat_warp.data.procedural import ProceduralConfig, procedural_scene
from codecsplat_warp.errors import DataError, InputError
from codecsplat_warp.metrics import LPIPS
from codecsplat_warp.model import CodecSplat
from codecsplat_warp.nn.config import get_preset


def test_reference_depth_loss_is_the_mean_log_error_over_known_pixels():
    reference = torch.full((2, 4, 5), 2.0)
    reference[0, :2] = 0.0                                   # unknown pixels, whatever the prediction there
    depth = (reference * 1.1).clamp_min(0.5)
    depth[0, :2] = 100.0
    loss, share = reference_depth_loss(depth, reference)
    assert float(loss) == pytest.approx(math.log(1.1), rel=1e-5)
    assert float(share) == pytest.approx(30 / 40)


def test_reference_depth_loss_without_references_is_zero_with_a_zero_gradient():
    depth = torch.rand(1, 3, 3, requires_grad=True)
    loss, share = reference_depth_loss(depth + 0.5, torch.zeros(1, 3, 3))
    loss.backward()
    assert float(loss.detach()) == 0.0 and float(share) == 0.0 and torch.equal(depth.grad, torch.zeros_like(depth))


def test_procedural_batches_carry_their_exact_depth():
    spec = DataSpec(views=(2,), sizes=((32, 48),), targets=1, batch_views=4, mirror=True)
    batch = make_source("procedural", spec, seed=1)(0)
    assert batch.context_depth.shape == (4, 32, 48) and batch.context_depth.dtype == torch.float32
    near = batch.context_cameras.near.float()[:, None, None]
    far = batch.context_cameras.far.float()[:, None, None]
    assert bool((batch.context_depth >= near).all()) and bool((batch.context_depth <= far).all())


@needs_lpips
def test_depth_weight_sends_the_reference_depth_into_the_encoder_gradient():
    torch.manual_seed(0)
    model = CodecSplat(get_preset("tiny")).train()
    lpips = LPIPS(weights_dir=WEIGHTS)
    batch = make_source("procedural", DataSpec(views=(2,), sizes=((32, 48),), targets=1, batch_views=2), seed=2)(0)

    def encoder_gradient(weight: float) -> torch.Tensor:
        model.zero_grad(set_to_none=True)
        loss, metrics = stage1_loss(model, lpips, batch, TrainConfig(depth_weight=weight))
        loss.backward()
        assert float(metrics["depth_ref_pixels"]) == 1.0 and float(metrics["depth_ref"]) > 0.0
        return torch.cat([p.grad.flatten() for p in model.mvenc.parameters() if p.grad is not None])

    without, with_depth = encoder_gradient(0.0), encoder_gradient(1.0)
    assert not torch.allclose(without, with_depth)


def test_render_own_views_renders_each_views_gaussians_alone_into_its_own_camera():
    torch.manual_seed(0)
    model = CodecSplat(get_preset("tiny")).eval()
    batch = make_source("procedural", DataSpec(views=(2,), sizes=((32, 48),), targets=1, batch_views=4), seed=3)(0)
    with torch.no_grad():
        gaussians = model(batch.context_images, batch.context_cameras, scenes=batch.scenes)["gaussians"]
        own = model.render_own_views(gaussians, batch.context_cameras)
        second = gaussians.split(4)[1]
        alone = model.render(second, batch.context_cameras.select([1]))["rgb"]
        together = model.render(gaussians, batch.context_cameras.select([1]))["rgb"]
    assert own.shape == (4, 3, 32, 48)
    assert torch.equal(own[1:2], alone) and not torch.allclose(own[1:2], together)
    with pytest.raises(InputError, match="pixel-aligned Gaussians of the 3 views"):
        model.render_own_views(second, batch.context_cameras.select([0, 1, 2]))


@needs_lpips
@pytest.mark.parametrize("option, metric, other", [("self_render_weight", "self_psnr", "own_psnr"),
                                                   ("own_render_weight", "own_psnr", "self_psnr")])
def test_context_render_weights_score_the_context_views_and_add_their_render_loss(option, metric, other):
    """--self-render-weight: all Gaussians of a scene in its context views; --own-render-weight: each view's own
    Gaussians alone in its own camera."""
    torch.manual_seed(0)
    model = CodecSplat(get_preset("tiny")).train()
    lpips = LPIPS(weights_dir=WEIGHTS)
    batch = make_source("procedural", DataSpec(views=(2,), sizes=((32, 48),), targets=1, batch_views=4), seed=3)(0)
    plain, plain_metrics = stage1_loss(model, lpips, batch, TrainConfig())
    torch.manual_seed(0)
    both, metrics = stage1_loss(model, lpips, batch, TrainConfig(**{option: 0.5}))
    assert metric not in plain_metrics and other not in metrics and 5.0 < float(metrics[metric]) < 60.0
    assert float(both.detach()) > float(plain.detach())


def _write_reference_depth(scene: pathlib.Path, depth: torch.Tensor) -> None:
    """A depth map folder (codecsplat-depth-v1) at ``scene/mvs`` holding ``depth`` [V,h,w] (0 = none)."""
    folder = scene / DEPTH_FOLDER
    (folder / "depth").mkdir(parents=True)
    frames = json.loads((scene / "cameras.json").read_text())["frames"]
    scale = depth_scale(float(depth.max()) * 1.5)
    for frame, view in zip(frames, depth):
        name = pathlib.Path(frame["file"]).stem
        Image.fromarray(quantize_depth(view, scale)).save(folder / "depth" / f"{name}.png")
    index = {"format": DEPTH_FORMAT, "scale": scale, "width": depth.shape[2], "height": depth.shape[1], "near": 0.1,
             "far": 10.0, "frames": [{"file": f["file"], "depth": f"depth/{pathlib.Path(f['file']).stem}.png",
                                      "mask": "", "coverage": 0.5, "sources": []} for f in frames]}
    (folder / INDEX_FILE).write_text(json.dumps(index))


def test_real_scenes_bring_their_reference_depth_and_skip_scenes_too_short_for_the_batch(tmp_path):
    from test_cli_commands import HEIGHT, WIDTH, write_scene

    write_scene(tmp_path / "long", seed=1, views=6)
    write_scene(tmp_path / "short", seed=2, views=3)
    truth = procedural_scene(1, ProceduralConfig(width=WIDTH, height=HEIGHT, num_views=6, texture_size=16)).depth
    known = truth.clone()
    known[:, :, : WIDTH // 2] = 0.0                       # the left half has no reference depth
    _write_reference_depth(tmp_path / "long", known)
    scenes = RealScenes(tmp_path, ["long", "short"], Augmentation())
    torch.testing.assert_close(scenes.scene("long")[2], known, atol=2 * known.max() / 65535, rtol=0)
    assert not scenes.scene("short")[2].any()             # no mvs/ folder: all unknown
    assert scenes.eligible(5) == ["long"] and scenes.eligible(3) == ["long", "short"]
    with pytest.raises(DataError, match="has 7 views"):
        scenes.eligible(7)
    sample = scenes(torch.Generator().manual_seed(0), BatchShape(views=2, targets=3, height=HEIGHT, width=WIDTH, scenes=1))
    assert sample.key == "long" and sample.context_depth.shape == (2, HEIGHT, WIDTH)
    assert bool((sample.context_depth > 0).any()) and bool((sample.context_depth == 0).any())
