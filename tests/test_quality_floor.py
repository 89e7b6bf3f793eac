"""A quality floor for the shipped model: on held-out real scenes it must beat copying the nearest context view.

The samples are entries of the fixed held-out index (``train/heldout_index/index-re10k.json``: 2 context
views, 3 targets between them) at 256x256, the RE10K protocol size; no training run has seen these scenes.
Both the codec-free path and the decoded bitstream at lambda = 1024 must beat the copy-nearest floor by
:data:`MARGIN_DB` on the mean PSNR of the samples. The shipped model 554cc15fd43d1f3e on the 2-core EPYC:
codec-free 21.36 dB and lambda = 1024 20.45 dB against 16.91 dB for copying the nearest view (+4.45, +3.55). The
test can fail: model 4946ca55d1d390a0 (2026-11-21) scored +0.56 dB at lambda = 1024.

Two more floors, on the geometry and on what a person sees (same samples, same CPU): the codec-free Gaussians
rendered back into their own context views must score at least :data:`SELF_RENDER_FLOOR_DB` (the shipped model:
22.32 dB; pixel-aligned Gaussians on a right geometry would approach the photographs), and the codec-free LPIPS-VGG
of the targets may exceed copy-nearest's by at most :data:`LPIPS_SLACK` (the shipped model: 0.327 against 0.311).
"""

from __future__ import annotations

import json
import pathlib

import pytest
import torch
from conftest import LPIPS_WEIGHTS, needs_lpips

from codecsplat_warp.eval.protocols import PROTOCOLS, find_scenes, index_samples, nearest_context_images
from codecsplat_warp.metrics import LPIPS
from codecsplat_warp.metrics.image import psnr
from codecsplat_warp.model.pretrained import load_pretrained

ROOT = pathlib.Path(__file__).resolve().parents[1]
INDEX = ROOT / "train" / "heldout_index" / "index-re10k.json"
SCENES = ("cap_fox", "llff_horns", "other_kitti06")
"""Held-out scenes of the floor (a small subset of the index, for CPU time): inward, forward-facing, driving."""

MARGIN_DB = 1.0
"""How far above the copy-nearest floor (mean PSNR, dB) both paths of the shipped model must be."""

SELF_RENDER_FLOOR_DB = 20.0
"""Least mean PSNR (dB) of the codec-free Gaussians rendered into their own context views."""

LPIPS_SLACK = 0.05
"""How far the codec-free targets' mean LPIPS-VGG may lie above copy-nearest's."""


@pytest.fixture(scope="module")
def samples(data_root, tmp_path_factory):
    entries = json.loads(INDEX.read_text())
    index = tmp_path_factory.mktemp("floor") / "index.json"
    index.write_text(json.dumps({name: entries[name] for name in SCENES}))
    return index_samples(find_scenes(data_root), index, PROTOCOLS["re10k"])


@pytest.mark.data
@pytest.mark.slow
@needs_lpips
def test_shipped_model_beats_copying_the_nearest_view_codec_free_and_at_lambda_1024(samples):
    model = load_pretrained(device="cpu")
    lpips = LPIPS(weights_dir=LPIPS_WEIGHTS)
    scores = {"copy nearest": [], "codec-free": [], "lambda 1024": [], "self-render": [], "lpips copy nearest": [],
              "lpips codec-free": []}
    with torch.no_grad():
        for sample in samples:
            nearest = nearest_context_images(sample.context_images, sample.context_cameras, sample.target_cameras)
            free = model(sample.context_images, sample.context_cameras)["gaussians"]
            free_targets = model.render(free, sample.target_cameras)["rgb"]
            decoded = model.decode(model.encode(sample.context_images, sample.context_cameras, 1024.0))
            for name, prediction in (("copy nearest", nearest), ("codec-free", free_targets),
                                     ("lambda 1024", model.render(decoded, sample.target_cameras)["rgb"])):
                scores[name].append(float(psnr(prediction, sample.target_images).mean()))
            own = model.render(free, sample.context_cameras)["rgb"]
            scores["self-render"].append(float(psnr(own, sample.context_images).mean()))
            scores["lpips copy nearest"].append(float(lpips(nearest, sample.target_images).mean()))
            scores["lpips codec-free"].append(float(lpips(free_targets, sample.target_images).mean()))
    mean = {name: sum(values) / len(values) for name, values in scores.items()}
    floor = mean["copy nearest"] + MARGIN_DB
    assert mean["codec-free"] >= floor and mean["lambda 1024"] >= floor, mean
    assert mean["self-render"] >= SELF_RENDER_FLOOR_DB, mean
    assert mean["lpips codec-free"] <= mean["lpips copy nearest"] + LPIPS_SLACK, mean
