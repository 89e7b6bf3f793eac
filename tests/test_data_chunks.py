"""RE10K-style chunks (write -> read), evaluation indices, view sampling, preprocessing and the Dataset path."""

from __future__ import annotations

import io
import json
from dataclasses import replace

import numpy as np
import pytest
import torch
from PIL import Image

from codecsplat_warp.data import (BoundedSamplerConfig, ProceduralConfig, SceneDataset, load_chunk_scene,
                                  load_evaluation_index, load_index, load_scene, make_dataloader, preprocess_scene,
                                  procedural_scene, read_chunk, resize_and_crop, sample_bounded_views, write_chunks)
from codecsplat_warp.data.views import context_gap_bounds
from codecsplat_warp.errors import DataError


def _downscaled(scene, frames, width, height):
    """The frames of ``scene`` as a decoded, downscaled scene (images re-encoded when chunked)."""
    images, cameras = resize_and_crop(scene.decoded_images(frames), scene.cameras.select(frames), width, height)
    return replace(scene.select(frames), images=images, cameras=cameras)


@pytest.fixture(scope="module")
def chunk_scenes(data_root, tmp_path_factory):
    """Two small scenes: one kept as its JPEG files (bytes stored verbatim), one downscaled (re-encoded)."""
    passthrough = load_scene(data_root / "llff_horns").select([0, 5, 10, 15])
    downscaled = _downscaled(load_scene(data_root / "cap_milk"), [0, 1, 2], 128, 96)
    downscaled.metadata.update(url="https://example.invalid/milk", timestamps=torch.tensor([10, 20, 30]))
    out = tmp_path_factory.mktemp("chunks")
    index = write_chunks([passthrough, downscaled], out, max_chunk_bytes=1, progress=False)
    return out, index, {passthrough.key: passthrough, downscaled.key: downscaled}


@pytest.mark.data
def test_chunk_round_trip(chunk_scenes):
    out, index, originals = chunk_scenes
    assert json.loads((out / "index.json").read_text()) == index
    assert len(set(index.values())) == 2  # max_chunk_bytes=1: one scene per chunk
    for key, original in originals.items():
        scene = load_chunk_scene(out, key, near=0.5, far=100.0)
        assert scene.num_views == original.num_views
        assert (scene.cameras.width, scene.cameras.height) == (original.cameras.width, original.cameras.height)
        torch.testing.assert_close(scene.cameras.w2c, original.cameras.w2c, atol=1e-5, rtol=0)
        torch.testing.assert_close(scene.cameras.K, original.cameras.K, atol=0, rtol=1e-6)
        assert torch.all(scene.cameras.near == 0.5) and torch.all(scene.cameras.far == 100.0)
        decoded, want = scene.decoded_images(), original.decoded_images()
        if key == "llff_horns":
            assert torch.equal(decoded, want)  # JPEG bytes stored verbatim
        else:
            assert (decoded.float() - want.float()).abs().mean() < 3.0  # re-encoded at quality 95
            assert scene.metadata["url"] == "https://example.invalid/milk"
            assert scene.metadata["timestamps"].tolist() == [10, 20, 30]
            assert scene.frame_names == ["cap_milk/10", "cap_milk/20", "cap_milk/30"]


@pytest.mark.data
def test_chunk_records_match_the_published_layout(chunk_scenes):
    out, index, originals = chunk_scenes
    records = torch.load(out / index["llff_horns"], weights_only=True)
    record = records[0]
    assert set(record) == {"key", "url", "timestamps", "cameras", "images"}
    assert record["cameras"].shape == (4, 18) and record["cameras"].dtype == torch.float32
    assert torch.all(record["cameras"][:, 4:6] == 0)
    cams = originals["llff_horns"].cameras
    fx_over_w = cams.K[:, 0, 0] / cams.width
    torch.testing.assert_close(record["cameras"][:, 0].double(), fx_over_w, atol=1e-6, rtol=0)
    w2c = record["cameras"][:, 6:].reshape(4, 3, 4).double()
    torch.testing.assert_close(w2c, cams.w2c[:, :3], atol=1e-5, rtol=0)
    assert Image.open(io.BytesIO(record["images"][0].numpy().tobytes())).format == "JPEG"


class ArbitraryObject:
    """A class a weights-only unpickler must refuse to construct."""


def test_chunk_errors(tmp_path):
    torch.save([{"key": "x", "obj": ArbitraryObject()}], tmp_path / "evil.torch")
    with pytest.raises(DataError, match=r"evil\.torch: not a weights-only torch chunk"):
        read_chunk(tmp_path / "evil.torch")
    record = {"key": "s", "url": "", "timestamps": torch.arange(2), "cameras": torch.zeros(2, 18),
              "images": [torch.zeros(3, dtype=torch.uint8)]}
    torch.save([record], tmp_path / "count.torch")
    with pytest.raises(DataError, match=r"count\.torch: scene 's': 2 camera rows but 1 images"):
        read_chunk(tmp_path / "count.torch")
    jpeg = io.BytesIO()
    Image.new("RGB", (8, 6)).save(jpeg, format="JPEG")
    rows = torch.tensor([[1.0, 1.0, 0.5, 0.5, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0]]).repeat(2, 1)
    rows[1, 7] = float("nan")
    record.update(cameras=rows, images=[torch.frombuffer(bytearray(jpeg.getvalue()), dtype=torch.uint8)] * 2)
    torch.save([record], tmp_path / "nan.torch")
    with pytest.raises(DataError, match=r"nan\.torch: scene 's': frame 1: camera row holds NaN or Inf"):
        read_chunk(tmp_path / "nan.torch")
    (tmp_path / "index.json").write_text(json.dumps({"s": "absent.torch"}))
    with pytest.raises(DataError, match=r"index\.json: scene 's' points to .*absent\.torch"):
        load_index(tmp_path)


def test_load_scene_reads_one_scene_of_a_chunk(tmp_path):
    scenes = [replace(procedural_scene(seed, ProceduralConfig(width=32, height=24, num_views=3, texture_size=8)),
                      key=f"scene{seed}") for seed in range(3)]
    write_chunks(scenes, tmp_path, progress=False)  # one chunk holds all three
    scene = load_scene(tmp_path / "000000.torch", key="scene1")
    assert scene.key == "scene1" and scene.num_views == 3 and scene.source == f"chunk:{tmp_path / '000000.torch'}"
    torch.testing.assert_close(scene.cameras.w2c, scenes[1].cameras.w2c.double(), atol=1e-5, rtol=0)
    assert torch.all(scene.cameras.near == 0.5) and torch.all(scene.cameras.far == 100.0)  # DepthSplat's RE10K range
    errors = [float((scene.decoded_images().float() - s.images.float()).abs().mean()) for s in scenes]
    assert errors[1] < 12.0 and errors[1] < min(errors[0], errors[2]) / 3  # its own images, through JPEG at quality 95
    assert load_scene(tmp_path, key="scene2").key == "scene2"  # a chunk folder, through its index.json
    with pytest.raises(DataError, match=r"000000\.torch holds no scene 'scene7'; it holds scene0, scene1, scene2"):
        load_scene(tmp_path / "000000.torch", key="scene7")
    with pytest.raises(DataError, match=r"holds 3 scenes: choose one with key= \(scene0, scene1, scene2\)"):
        load_scene(tmp_path / "000000.torch")
    write_chunks(scenes[:1], tmp_path / "one", progress=False)
    assert load_scene(tmp_path / "one" / "000000.torch").key == "scene0"  # a chunk of one scene needs no key
    with pytest.raises(DataError, match="key='scene0' selects a scene of a .torch chunk"):
        load_scene(tmp_path / "one" / "index.json", key="scene0")


def test_evaluation_index_skips_null(tmp_path):
    file = tmp_path / "evaluation_index_re10k.json"
    file.write_text(json.dumps({"a": {"context": [0, 10], "target": [3, 5, 7]}, "b": None, "c": {"context": [1, 2],
                                                                                                 "target": [1]}}))
    index = load_evaluation_index(file)
    assert list(index) == ["a", "c"]
    assert index["a"].context == (0, 10) and index["a"].target == (3, 5, 7)
    file.write_text(json.dumps({"a": {"context": [0, "x"], "target": [1]}}))
    with pytest.raises(DataError, match=r"scene 'a': expected"):
        load_evaluation_index(file)


def test_bounded_sampler_respects_bounds_and_schedule():
    config = BoundedSamplerConfig(num_context_views=3, num_target_views=4, min_distance_between_context_views=20,
                                  max_distance_between_context_views=40, min_distance_to_context_views=2,
                                  warm_up_steps=100, initial_min_distance_between_context_views=5,
                                  initial_max_distance_between_context_views=10)
    assert context_gap_bounds(config, 0) == (5, 10)
    assert context_gap_bounds(config, 50) == (12, 25)
    assert context_gap_bounds(config, 10**6) == (20, 40)
    generator = torch.Generator().manual_seed(0)
    for step, (low, high) in ((0, (5, 10)), (10**6, (20, 30))):
        for _ in range(200):
            sel = sample_bounded_views(31, config, step, generator)
            left, right = sel.context[0], sel.context[-1]
            assert low <= right - left <= high and 0 <= left and right <= 30
            assert list(sel.context) == sorted(set(sel.context)) and len(sel.context) == 3
            assert all(left + 2 <= t <= right - 2 for t in sel.target) and len(sel.target) == 4
    with pytest.raises(DataError, match="no context gap"):
        sample_bounded_views(4, config, 0, generator)


@pytest.mark.data
def test_preprocess_matches_manual_resize_and_crop(data_root):
    scene = load_scene(data_root / "cap_kangaroo")  # 230x512, portrait: width-limited
    out = preprocess_scene(scene, "dl3dv", frames=[0, 3])
    assert out.images.shape == (2, 3, 256, 448) and out.images.dtype == torch.uint8
    scale = 448 / 230
    scaled_h = round(512 * scale)
    top = (scaled_h - 256) // 2
    K = scene.cameras.K[0]
    np.testing.assert_allclose(out.cameras.K[0, 0, 0].item(), K[0, 0].item() * 448 / 230, rtol=1e-12)
    np.testing.assert_allclose(out.cameras.K[0, 1, 1].item(), K[1, 1].item() * scaled_h / 512, rtol=1e-12)
    np.testing.assert_allclose(out.cameras.K[0, 1, 2].item(), K[1, 2].item() * scaled_h / 512 - top, rtol=1e-12)
    assert torch.all(out.cameras.near == 0.5) and torch.all(out.cameras.far == 200.0)
    reference = Image.open(data_root / "cap_kangaroo" / scene.frame_names[3]).convert("RGB")
    reference = np.asarray(reference.resize((448, scaled_h), Image.Resampling.LANCZOS))[top:top + 256]
    assert np.array_equal(out.images[1].permute(1, 2, 0).numpy(), reference)


@pytest.mark.data
def test_dataset_from_chunks_evaluation_and_training(chunk_scenes, tmp_path):
    out, _, _ = chunk_scenes
    eval_file = tmp_path / "eval.json"
    eval_file.write_text(json.dumps({"cap_milk": {"context": [0, 2], "target": [1]}, "llff_horns": None}))
    evaluation = SceneDataset.from_chunks(out, evaluation_index=eval_file, progress=False)
    assert len(evaluation) == 1
    item = evaluation[0]
    assert item["key"] == "cap_milk" and item["context"]["image"].shape == (2, 3, 256, 256)
    assert item["context"]["index"].tolist() == [0, 2] and item["target"]["K"].shape == (1, 3, 3)
    assert item["context"]["image"].dtype == torch.float32 and 0 <= float(item["context"]["image"].min())

    sampler = BoundedSamplerConfig(num_target_views=1, min_distance_between_context_views=2,
                                   max_distance_between_context_views=3, warm_up_steps=0)
    training = SceneDataset.from_chunks(out, sampler=sampler, config="re10k", seed=7, progress=False)
    serial = [training[i] for i in range(len(training))]
    again = [training[i] for i in range(len(training))]  # second pass comes from the image cache
    assert all(torch.equal(a["context"]["image"], b["context"]["image"]) for a, b in zip(serial, again))
    loader = make_dataloader(training, batch_size=1, num_workers=2, shuffle=False)
    batches = list(loader)
    for batch, item in zip(batches, serial):
        assert batch["key"] == [item["key"]]
        assert torch.equal(batch["context"]["index"][0], item["context"]["index"])
        assert torch.equal(batch["context"]["image"][0], item["context"]["image"])
