"""Scene-batched training: block-diagonal neighbours, batches of several scenes, augmentation, warm starts,
the mono prior and the held-out index."""

from __future__ import annotations

import json

import pytest
import torch
from conftest import LPIPS_WEIGHTS, assert_same_batches, needs_lpips

from codecsplat_warp.cameras import Cameras, intrinsics_matrix
from codecsplat_warp.errors import CameraError, DataError, InputError
from codecsplat_warp.eval.protocols import PROTOCOLS, find_scenes, index_samples
from codecsplat_warp.model import CodecSplat
from codecsplat_warp.nn.config import ModelConfig, get_preset
from codecsplat_warp.nn.mono import VGGMono
from codecsplat_warp.ops.geometry import nearest_views
from train.checkpoint import load_matching_weights, read_weights
from train.data import (Augmentation, DataSpec, TrainingBatch, batch_shape, make_source, photometric_jitter,
                        random_resized_crop)
from train.heldout import HELD_OUT, INDEX_FILES, SEEN, SEEN_INDEX_FILES

TINY = get_preset("tiny")


def _cameras(n: int, offset: float = 0.0, width: int = 48, height: int = 32) -> Cameras:
    f = torch.full((n,), 40.0)
    c2w = torch.eye(4).repeat(n, 1, 1)
    c2w[:, 0, 3] = offset + 0.1 * torch.arange(n)
    return Cameras.from_c2w(intrinsics_matrix(f, f, f * 0 + width / 2, f * 0 + height / 2), c2w,
                            torch.full((n,), 1.0), torch.full((n,), 10.0), width, height)


def test_nearest_views_stay_inside_each_scene():
    cameras = Cameras.concat([_cameras(3), _cameras(3, offset=0.05)])  # the second scene interleaves the first
    neighbours = nearest_views(cameras, 2, scenes=2)
    assert all(set(neighbours[v].tolist()) <= set(range(3 * (v // 3), 3 * (v // 3) + 3)) for v in range(6))
    assert set(nearest_views(cameras, 2)[0].tolist()) == {3, 1}  # one scene: the nearest views overall
    with pytest.raises(InputError, match="equal groups"):
        nearest_views(cameras, 1, scenes=4)
    with pytest.raises(CameraError, match="image size"):
        Cameras.concat([_cameras(2), _cameras(2, width=64)])


def test_a_batch_of_scenes_renders_each_scene_as_alone():
    """Views attend to, match against and refine with their own scene only: the Gaussians of two stacked scenes
    are those of each scene on its own."""
    torch.manual_seed(0)
    model = CodecSplat(TINY).eval()
    cameras = [_cameras(2), _cameras(2, offset=0.03)]
    images = [torch.rand(2, 3, 32, 48), torch.rand(2, 3, 32, 48)]
    with torch.no_grad():
        alone = [model(i, c)["gaussians"] for i, c in zip(images, cameras)]
        together = model(torch.cat(images), Cameras.concat(cameras), scenes=2)["gaussians"].split(2)
    for a, b in zip(alone, together):
        torch.testing.assert_close(b.means, a.means, atol=1e-4, rtol=1e-4)
        torch.testing.assert_close(b.sh, a.sh, atol=1e-4, rtol=1e-4)


def test_batches_are_deterministic_and_follow_the_spec():
    """Batches are a function of the seed and the index: a second source of the same seed draws the same batch,
    another seed another one. Catches: batches drawn from global or per-source random state (a worker or a resumed
    run would see other scenes), which a source asked twice for a cached batch would not show."""
    spec = DataSpec(views=(2, 3), sizes=((32, 48), (32, 64)), targets=2, batch_views=6)
    source = make_source("procedural", spec, seed=1)
    for index in range(3):
        shape = batch_shape(spec, 1, index)
        batch = source(index)
        assert batch.scenes == 6 // shape.views and batch.targets_per_scene == 2
        assert batch.context_images.shape == (batch.scenes * shape.views, 3, shape.height, shape.width)
        assert [c.num_views for c in batch.scene_targets()] == [2] * batch.scenes
    batch = source(2)
    assert_same_batches(make_source("procedural", spec, seed=1)(2), batch)
    assert not torch.equal(make_source("procedural", spec, seed=2)(2).context_images, batch.context_images)
    with pytest.raises(InputError, match="multiples"):
        DataSpec(views=(2,), sizes=((30, 48),))


def test_photometric_jitter_is_one_change_for_all_views_and_stays_in_range():
    images = torch.rand(1, 3, 8, 8).expand(3, 3, 8, 8)
    out = photometric_jitter(images, torch.Generator().manual_seed(4))
    assert out.min() >= 0 and out.max() <= 1 and not torch.equal(out, images)
    torch.testing.assert_close(out[0], out[2])


def test_mirror_flips_half_of_the_scenes_with_their_cameras_and_leaves_the_other_draws_alone():
    images, cameras, depth = torch.rand(3, 3, 8, 12), _cameras(3, width=12, height=8), torch.rand(3, 8, 12)
    flipped = 0
    for seed in range(40):
        out, cams, out_depth = Augmentation(mirror=True)(images, cameras, depth, torch.Generator().manual_seed(seed))
        if torch.equal(out, images):
            assert cams is cameras and out_depth is depth
        else:
            flipped += 1
            torch.testing.assert_close(out, images.flip(-1))
            torch.testing.assert_close(out_depth, depth.flip(-1))
            torch.testing.assert_close(cams.w2c, cameras.mirrored().w2c)
            torch.testing.assert_close(cams.K, cameras.mirrored().K)
    assert 10 <= flipped <= 30
    jittered, _, same_depth = Augmentation(photometric=True)(images, cameras, depth, torch.Generator().manual_seed(5))
    both = Augmentation(photometric=True, mirror=True)(images, cameras, depth, torch.Generator().manual_seed(5))[0]
    assert torch.equal(both, jittered) or torch.equal(both, jittered.flip(-1))
    assert same_depth is depth and Augmentation()(images, cameras, depth, torch.Generator())[0] is images


def test_random_crop_keeps_the_principal_ray():
    """A pixel of the crop and the ray its camera gives it come from the same place of the source image."""
    cameras = _cameras(1, width=96, height=64)
    images = (torch.arange(96 * 64) % 251).reshape(1, 1, 64, 96).expand(1, 3, 64, 96).to(torch.uint8)
    crop, cropped, _ = random_resized_crop(images, cameras, images[:, 0].float(), 32, 48, torch.Generator().manual_seed(0))
    scale = cropped.K[0, 0, 0] / cameras.K[0, 0, 0]
    centre_in_source = (cameras.K[0, :2, 2] - (cropped.K[0, :2, 2] - torch.tensor([24.0, 16.0])) / scale)
    assert crop.shape == (1, 3, 32, 48) and 0 <= float(centre_in_source[0]) <= 96 and 0 <= float(centre_in_source[1]) <= 64


def test_random_crop_takes_the_depth_along_without_blending_it():
    """Depth is cropped where the image is (a ramp image and the same ramp as depth agree after the crop),
    nearest-sampled: every value is one of the source's, so an unknown (0) pixel never bleeds into its neighbours."""
    cameras = _cameras(1, width=96, height=64)
    ramp = (torch.arange(96, dtype=torch.float32) * 2.5).expand(64, 96)
    images = ramp.round().to(torch.uint8).expand(1, 3, 64, 96).contiguous()
    depth = ramp[None].clone()
    depth[:, :, 40:] = 0.0
    crop, _, crop_depth = random_resized_crop(images, cameras, depth, 32, 48, torch.Generator().manual_seed(0))
    assert crop_depth.shape == (1, 32, 48) and set(crop_depth.unique().tolist()) <= set(depth.unique().tolist())
    known = crop_depth > 0
    assert bool(known.any()) and bool((~known).any())
    assert float((crop_depth - crop[:, 0] * 255.0)[known].abs().max()) < 4.0


def test_warm_start_copies_matching_tensors_and_reports_the_rest(tmp_path):
    from codecsplat_warp.model.pretrained import round_to_half, save_pretrained

    source = round_to_half(CodecSplat(TINY, codec=True))
    path = save_pretrained(source, tmp_path / "m.safetensors", half=True)
    target = CodecSplat(ModelConfig(**{**TINY.to_dict(), "mono": "vgg16"}))
    kept, unused = load_matching_weights(target, read_weights(path))
    assert kept and all(k.startswith("mvenc.mono") for k in kept)
    assert unused and all(k.startswith(("codec.", "refine_post.")) for k in unused)
    torch.testing.assert_close(target.feat_head.state_dict()["net.0.weight"], source.feat_head.state_dict()["net.0.weight"])
    with pytest.raises(DataError, match="neither"):
        read_weights(tmp_path / "missing")


@needs_lpips
def test_vgg_mono_prior_loads_imagenet_weights_and_is_frozen(tmp_path):
    mono = VGGMono().load_imagenet(LPIPS_WEIGHTS / "lpips_vgg.safetensors")
    features = mono(torch.rand(2, 3, 32, 48))
    assert features.shape == (2, 256, 8, 12) and not any(p.requires_grad for p in mono.parameters())
    model = CodecSplat(ModelConfig(**{**TINY.to_dict(), "mono": "vgg16"}))
    assert model.mvenc.mono_backbone is not None and "mvenc.mono_backbone.trunk.2.14.weight" in model.state_dict()
    with pytest.raises(InputError, match="does not exist"):
        mono.load_imagenet(tmp_path / "none.safetensors")
    with pytest.raises(InputError, match="mono"):
        ModelConfig(**{**TINY.to_dict(), "mono": "resnet"})


def test_held_out_index_files_name_the_held_out_scenes():
    for protocol, views in (("re10k", 2), ("dl3dv", 8)):
        entries = json.loads(INDEX_FILES[protocol].read_text())
        assert tuple(entries) == HELD_OUT
        assert all(len(e["context"]) == views and len(e["target"]) == 3 for e in entries.values())


def test_the_seen_scenes_are_training_scenes_with_index_files():
    assert not set(SEEN) & set(HELD_OUT) and len(SEEN) == len(HELD_OUT)
    for protocol, views in (("re10k", 2), ("dl3dv", 8)):
        entries = json.loads(SEEN_INDEX_FILES[protocol].read_text())
        assert tuple(entries) == SEEN
        assert all(len(e["context"]) == views and len(e["target"]) == 3 for e in entries.values())


def test_index_samples_and_their_errors(data_root, tmp_path):
    index = tmp_path / "index.json"
    index.write_text(json.dumps({"cap_fox": {"context": [25, 29], "target": [28]}}))
    (sample,) = index_samples(find_scenes(data_root), index, PROTOCOLS["re10k"])
    assert sample.context == [25, 29] and sample.context_images.shape == (2, 3, 256, 256)
    index.write_text(json.dumps({"no_such_scene": {"context": [0, 1], "target": [2]}}))
    with pytest.raises(DataError, match="no_such_scene"):
        index_samples(find_scenes(data_root), index, PROTOCOLS["re10k"])
    index.write_text(json.dumps({"cap_fox": {"context": [0, 1], "target": [999]}}))
    with pytest.raises(DataError, match="999"):
        index_samples(find_scenes(data_root), index, PROTOCOLS["re10k"])


def test_a_training_batch_stacks_scenes():
    from train.data import TrainingSample

    samples = [TrainingSample(torch.rand(2, 3, 8, 8), _cameras(2, width=8, height=8), torch.rand(1, 3, 8, 8),
                              _cameras(1, width=8, height=8), key, torch.rand(2, 8, 8)) for key in ("a", "b")]
    batch = TrainingBatch.stack(samples)
    assert batch.keys == ("a", "b") and batch.context_cameras.num_views == 4 and batch.targets_per_scene == 1
