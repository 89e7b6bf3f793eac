"""MVEnc's photometric cost volume: windowed-NCC features, their plane sweep, and the zero-started branch that
feeds it to the depth regressor (``ModelConfig.photometric_window``)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from train.stage1 import TrainConfig, stage1_model_config

from codecsplat_warp.data.procedural import ProceduralConfig, procedural_scene
from codecsplat_warp.errors import InputError
from codecsplat_warp.model import CodecSplat
from codecsplat_warp.nn.config import ModelConfig, get_preset
from codecsplat_warp.ops.geometry import inverse_depth_candidates
from codecsplat_warp.ops.mvs import photometric_cost_volume, window_ncc_features


def test_window_features_give_ncc_one_with_themselves_and_zero_on_flat_windows():
    images = torch.rand(1, 3, 12, 16)
    images[..., :6, :] = 0.5                                   # flat top half
    features, texture = window_ncc_features(images, 3)
    self_ncc = (features * features).sum(1) / 3.0              # the cost volume's dot product / sqrt(channels)
    assert features.shape == (1, 9, 12, 16) and texture.shape == (1, 12, 16)
    assert torch.allclose(self_ncc[0, 8:], torch.ones(4, 16), atol=1e-5)
    assert float(features[0, :, 1:4].abs().max()) == 0.0 and float(texture[0, 1:4].max()) == 0.0
    with pytest.raises(InputError, match="odd number >= 3"):
        window_ncc_features(images, 4)


def _winner_depth(scene, cameras) -> torch.Tensor:
    images = scene.images.float() / 255
    candidates = inverse_depth_candidates(cameras, 48).float()
    cost = photometric_cost_volume(images, candidates, cameras, 5)
    assert cost.shape == (2, 48, *images.shape[-2:]) and float(cost.abs().max()) <= 1.0 + 1e-5
    index = cost.argmax(1, keepdim=True)
    return torch.gather(candidates[:, :, None, None].expand(-1, -1, *cost.shape[2:]), 1, index)[:, 0]


def test_the_photometric_sweep_finds_the_depth_and_loses_it_with_wrong_cameras():
    scene = procedural_scene(5, ProceduralConfig(width=128, height=128, num_views=2, trajectory="forward"))
    error = (_winner_depth(scene, scene.cameras) - scene.depth).abs() / scene.depth
    w2c = scene.cameras.w2c.clone()
    w2c[1, 0, 3] += 0.2                                         # the second camera 20 cm off
    wrong = dataclasses.replace(scene.cameras, w2c=w2c)
    wrong_error = (_winner_depth(scene, wrong) - scene.depth).abs() / scene.depth
    assert float(error.median()) < 0.07 and float(wrong_error.median()) > 4 * float(error.median())


def test_the_branch_starts_at_zero_and_trains():
    torch.manual_seed(0)
    plain = CodecSplat(get_preset("tiny")).train()
    with_cost = CodecSplat(dataclasses.replace(get_preset("tiny"), photometric_window=3)).train()
    missing = with_cost.load_state_dict(plain.state_dict(), strict=False).missing_keys
    assert missing and all(key.startswith("mvenc.photometric_regressor.") for key in missing)
    scene = procedural_scene(3, ProceduralConfig(width=48, height=32, num_views=2))
    images = scene.images.float() / 255
    out = with_cost(images, scene.cameras)
    assert torch.equal(out["D_enc"], plain(images, scene.cameras)["D_enc"])
    out["D_enc"].log().mean().backward()
    assert float(with_cost.mvenc.photometric_regressor[-1].weight.grad.abs().sum()) > 0.0


def test_config_keeps_old_model_files_and_stage1_sets_the_window():
    assert "photometric_window" not in get_preset("re10k").to_dict()      # shipped ids unchanged
    config = dataclasses.replace(get_preset("re10k"), photometric_window=5)
    assert ModelConfig.from_dict(config.to_dict()) == config
    with pytest.raises(InputError, match="photometric_window"):
        dataclasses.replace(config, photometric_window=4)
    assert stage1_model_config(TrainConfig(preset="tiny", photometric_window=5)).photometric_window == 5
    assert stage1_model_config(TrainConfig(preset="tiny")).photometric_window == 0
