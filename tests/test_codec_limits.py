"""train.codec_limits: its codec rows are what a user decodes from a bitstream, and the oracle rows exist."""

from __future__ import annotations

import pytest
import torch
from conftest import tiny_coding_model

from codecsplat_warp.data.procedural import ProceduralConfig, procedural_scene
from codecsplat_warp.eval.protocols import Sample
from codecsplat_warp.metrics.image import psnr
from train.codec_limits import sample_scores


def test_codec_row_matches_the_decoded_bitstream_and_every_swap_is_scored():
    model = tiny_coding_model(0)
    scene = procedural_scene(3, ProceduralConfig(width=48, height=32, num_views=3, texture_size=16))
    images, cameras = scene.images.float() / 255.0, scene.cameras.to(dtype=torch.float32)
    sample = Sample("procedural", [0, 2], [1], images[[0, 2]], cameras.select([0, 2]), images[[1]], cameras.select([1]))
    scores = sample_scores(model, sample, [16.0, 1024.0])
    per_lambda = ("codec λ={}", "codec λ={}, D_enc", "F_c with D^ of λ={}", "feature error λ={}")
    assert set(scores) == {"codec-free", "decoder on F_c"} | {k.format(lam) for lam in (16, 1024) for k in per_lambda}
    with torch.no_grad():
        decoded = model.decode(model.encode(sample.context_images, sample.context_cameras, 1024.0))
        coded = float(psnr(model.render(decoded, sample.target_cameras)["rgb"], sample.target_images).mean())
    assert scores["codec λ=1024"] == pytest.approx(coded, abs=1e-3)
    assert scores["feature error λ=1024"] < scores["feature error λ=16"]
