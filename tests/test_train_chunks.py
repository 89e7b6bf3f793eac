"""Training from chunk folders (``--data chunks:DIR``): determinism by batch index, mixes, the bounded view
sampler's step schedule, typed errors and exact resume of stage 1."""

from __future__ import annotations

import json
import pickle

import pytest
import torch
from conftest import LPIPS_WEIGHTS as WEIGHTS
from conftest import needs_lpips

from codecsplat_warp.data import ProceduralConfig, procedural_scene, write_chunks
from codecsplat_warp.errors import DataError, InputError
from codecsplat_warp.nn.config import get_preset
from train.data import CHUNK_CACHE, Augmentation, ChunkScenes, DataSpec, batch_shape, fixed_context_gap, make_source
from train.stage1 import METRICS_FILE, TrainConfig, data_spec, parse_args, train
from train.stage2 import parse_args as stage2_args

TINY = get_preset("tiny")
GAP = "2,6"
"""Context gap (frames) of the tests: the 12-frame test scenes are far too short for DepthSplat's 25-192."""


@pytest.fixture(scope="module")
def chunk_root(tmp_path_factory):
    """Three 12-frame procedural scenes at 32x48 and one of 2 frames (too short for any gap >= 2), one or two
    scenes per chunk."""
    scenes = [procedural_scene(seed, ProceduralConfig(width=48, height=32, num_views=12)) for seed in (1, 2, 3)]
    scenes.append(procedural_scene(4, ProceduralConfig(width=48, height=32, num_views=2)))
    root = tmp_path_factory.mktemp("chunks")
    write_chunks(scenes, root, max_chunk_bytes=12 * 1000, progress=False)
    return root


def _index(root) -> dict[str, str]:
    return json.loads((root / "index.json").read_text())


def _spec(**overrides) -> DataSpec:
    return DataSpec(**{**dict(views=(2, 3), sizes=((32, 48),), targets=2, batch_views=4,
                              view_sampler=fixed_context_gap(GAP)), **overrides})


def _assert_same(a, b) -> None:
    assert a.keys == b.keys
    assert torch.equal(a.context_images, b.context_images) and torch.equal(a.target_images, b.target_images)
    assert torch.equal(a.context_cameras.w2c, b.context_cameras.w2c)
    assert torch.equal(a.target_cameras.K, b.target_cameras.K)


def test_chunk_source_gives_the_same_batch_for_the_same_index(chunk_root):
    assert len(set(_index(chunk_root).values())) > 1  # several chunks: a draw streams one, not the folder
    first, second = (make_source(f"chunks:{chunk_root}", _spec(), seed=5) for _ in range(2))
    short = next(k for k in _index(chunk_root) if k.endswith("-4"))
    for index in (0, 3, 7):
        batch = first(index)
        _assert_same(batch, second(index))
        shape = batch_shape(_spec(), 5, index)
        assert batch.context_images.shape == (shape.scenes * shape.views, 3, 32, 48)
        assert batch.target_images.shape == (shape.scenes * 2, 3, 32, 48)
        assert batch.context_images.dtype == torch.float32 and short not in batch.keys
        assert set(batch.keys) <= set(_index(chunk_root))
    assert not torch.equal(first(0).context_images, first(1).context_images)
    # reading the batches in another order (as a resumed run does) changes none of them
    _assert_same(make_source(f"chunks:{chunk_root}", _spec(), seed=5)(7), first(7))


def test_chunk_scenes_keep_a_few_chunks_and_pickle_for_workers(chunk_root):
    keys = sorted(_index(chunk_root))
    scenes = ChunkScenes(chunk_root, keys, fixed_context_gap(GAP), Augmentation())
    shape = batch_shape(_spec(views=(2,)), 0, 0)
    for seed in range(6):
        sample = scenes(torch.Generator().manual_seed(seed), shape)
        assert len(scenes._cache) <= CHUNK_CACHE
        centres = sample.context_cameras.centers
        assert sample.context_images.shape == (2, 3, 32, 48) and centres.shape == (2, 3)
        assert sample.key in keys and not sample.key.endswith("-4")
    copy = pickle.loads(pickle.dumps(scenes))  # as a DataLoader worker gets it
    again = copy(torch.Generator().manual_seed(5), shape)
    assert again.key == sample.key and torch.equal(again.target_images, sample.target_images)


def test_context_gap_follows_the_step_of_the_batch_index(chunk_root):
    spec = _spec(batches_per_step=2, view_sampler=DataSpec.of_model(TINY).view_sampler)
    assert [batch_shape(spec, 0, i).step for i in (0, 1, 2, 5)] == [0, 0, 1, 2]
    # DepthSplat's RE10K schedule starts at gaps of 25-45 frames: 12-frame scenes are all too short
    with pytest.raises(DataError, match="too short .* context gap"):
        make_source(f"chunks:{chunk_root}", spec, seed=0)(0)
    config = parse_args(["--preset", "tiny", "--context-gap", GAP, "--accumulate", "3"])
    assert data_spec(config, TINY, world=2).batches_per_step == 6
    assert data_spec(config, TINY).view_sampler == fixed_context_gap(GAP)
    stage2 = stage2_args(["--data", f"mix:chunks:{chunk_root}", "--context-gap", GAP])  # stage 2 shares the flags
    assert data_spec(stage2, TINY).view_sampler == fixed_context_gap(GAP)
    with pytest.raises(InputError, match="MIN,MAX"):
        fixed_context_gap("45")
    with pytest.raises(InputError, match="MIN <= MAX"):
        fixed_context_gap("9,3")


def test_mix_draws_procedural_and_chunk_scenes(chunk_root):
    chunk_keys = set(_index(chunk_root))
    source = make_source(f"mix:chunks:{chunk_root}", _spec(photo_textures=True, photometric=True), seed=0)
    keys = [k for i in range(6) for k in source(i).keys]
    assert any(k in chunk_keys for k in keys) and any(k not in chunk_keys for k in keys)
    held = sorted(chunk_keys)[0]
    kept = make_source(f"chunks:{chunk_root}", _spec(), seed=0, holdout=[held])
    assert held not in {k for i in range(6) for k in kept(i).keys}


def test_chunk_data_errors_name_the_problem(chunk_root, tmp_path):
    with pytest.raises(DataError, match="chunk folder .*nowhere.* does not exist"):
        make_source(f"chunks:{tmp_path / 'nowhere'}", _spec(), seed=0)
    with pytest.raises(DataError, match="index.json does not exist"):
        make_source(f"mix:chunks:{tmp_path}", _spec(), seed=0)
    with pytest.raises(InputError, match="held-out scenes not found .*no_such_key"):
        make_source(f"chunks:{chunk_root}", _spec(), seed=0, holdout=["no_such_key"])
    with pytest.raises(InputError, match="chunks:DIRECTORY"):
        make_source(f"chunk:{chunk_root}", _spec(), seed=0)


@needs_lpips
def test_resumed_chunk_run_gives_the_same_next_step_loss(chunk_root, tmp_path):
    common = dict(preset="tiny", data=f"chunks:{chunk_root}", context_gap=GAP, views="2,3", batch_views=4,
                  device="cpu", workers=0, warmup_steps=10, lpips_weights=str(WEIGHTS), checkpoint_every=2,
                  log_every=1, seed=3)
    train(TrainConfig(out=str(tmp_path / "a"), steps=2, **common), progress=False)
    resumed = train(TrainConfig(out=str(tmp_path / "a"), steps=3, **common), progress=False)
    direct = train(TrainConfig(out=str(tmp_path / "b"), steps=3, **common), progress=False)
    assert (resumed["resumed_from"], direct["resumed_from"], resumed["step"]) == (2, 0, 3)
    for name in ("loss", "mse", "psnr"):
        assert resumed[name] == pytest.approx(direct[name], rel=1e-5), name
    logged = [json.loads(line) for line in (tmp_path / "a" / METRICS_FILE).read_text().splitlines()]
    assert [r["step"] for r in logged] == [1, 2, 3] and logged[-1]["scenes"] == resumed["scenes"]
