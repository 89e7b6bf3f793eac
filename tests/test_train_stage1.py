"""Stage-1 trainer: checkpoint sharding, atomic/resumable checkpoints (same next-step loss), CLI."""

from __future__ import annotations

import pytest
import torch
from conftest import LPIPS_WEIGHTS as WEIGHTS
from conftest import assert_same_batches, needs_lpips

# `train` is a top-level folder of the repository (pytest's pythonpath = ["."]), not an installed package.
from train.checkpoint import (
    MAX_FILE_BYTES, join_tensors, latest_checkpoint, load_checkpoint, save_checkpoint, split_tensors,
)
from train.data import DataSpec, make_source, training_scenes
from codecsplat_warp.data import split_context_targets
from train.pack_scenes import pack_scene
from train.stage1 import METRICS_FILE, TrainConfig, _loader, lr_factor, make_optimizer, parse_args, to_device, train
from train.validate import plot_curve, read_metrics, SceneScore

from codecsplat_warp.errors import InputError  # noqa: E402
from codecsplat_warp.model import CodecSplat
from codecsplat_warp.nn.config import get_preset  # noqa: E402



def test_split_and_join_tensors_respect_the_file_limit():
    tensors = {"big": torch.arange(1000, dtype=torch.float32).reshape(10, 100), "a": torch.ones(3), "b": torch.zeros(50)}
    shards, cut = split_tensors(tensors, max_bytes=1024)
    assert all(sum(t.numel() * t.element_size() for t in s.values()) <= 1024 for s in shards)
    assert cut == {"big": [10, 100]}
    joined = join_tensors({k: v for s in shards for k, v in s.items()}, cut)
    assert set(joined) == set(tensors) and all(torch.equal(joined[k], tensors[k]) for k in tensors)


def test_checkpoint_round_trip_shards_and_ignores_partial_writes(tmp_path):
    config = TrainConfig(steps=10, warmup_steps=2)
    model = CodecSplat(get_preset("tiny"))
    optimizer, scheduler = make_optimizer(model, config)
    model(torch.rand(2, 3, 32, 48), _cameras())["F_c"].square().mean().backward()
    optimizer.step()
    scheduler.step()
    folder = save_checkpoint(tmp_path, 1, model, optimizer, scheduler, {"note": 1}, max_bytes=64 * 1024)
    assert len(list(folder.glob("model-*.safetensors"))) > 1
    assert all(f.stat().st_size <= 64 * 1024 for f in folder.iterdir() if f.suffix == ".safetensors")
    (tmp_path / "checkpoints" / "step-00000002.tmp").mkdir()  # a run killed while writing step 2
    assert latest_checkpoint(tmp_path) == folder
    (tmp_path / "checkpoints" / "latest").unlink()
    assert latest_checkpoint(tmp_path) == folder

    clone = CodecSplat(get_preset("tiny"))
    opt2, sched2 = make_optimizer(clone, config)
    assert load_checkpoint(folder, clone, opt2, sched2) == 1
    for (name, a), b in zip(model.state_dict().items(), clone.state_dict().values()):
        assert torch.equal(a, b), name
    s1, s2 = optimizer.state_dict()["state"], opt2.state_dict()["state"]
    assert all(torch.equal(s1[i]["exp_avg_sq"], s2[i]["exp_avg_sq"]) for i in s1)
    assert sched2.last_epoch == scheduler.last_epoch and MAX_FILE_BYTES == 16 * 1024 * 1024


@needs_lpips
def test_resumed_run_gives_the_same_next_step_loss(tmp_path):
    common = dict(preset="tiny", data="procedural", device="cpu", workers=0, warmup_steps=10, lpips_weights=str(WEIGHTS),
                  checkpoint_every=2, log_every=1, seed=3)
    train(TrainConfig(out=str(tmp_path / "a"), steps=2, **common), progress=False)
    resumed = train(TrainConfig(out=str(tmp_path / "a"), steps=3, **common), progress=False)
    direct = train(TrainConfig(out=str(tmp_path / "b"), steps=3, **common), progress=False)
    assert (resumed["resumed_from"], direct["resumed_from"], resumed["step"]) == (2, 0, 3)
    assert resumed["loss"] == pytest.approx(direct["loss"], rel=1e-5)
    assert (tmp_path / "a" / "checkpoints" / "step-00000003" / "checkpoint.json").is_file()
    assert list((tmp_path / "a" / "tensorboard").glob("events.*"))
    assert_same_weight_average(tmp_path / "a", tmp_path / "b", updates=3)


def assert_same_weight_average(resumed, direct, updates: int) -> None:
    """The newest checkpoints of a resumed and an uninterrupted run hold the same weight average (after
    ``updates`` updates), one that differs from the raw weights."""
    import json

    from safetensors.torch import load_file

    folders = [latest_checkpoint(run) for run in (resumed, direct)]
    indices = [json.loads((folder / "checkpoint.json").read_text()) for folder in folders]
    assert [index["ema"]["updates"] for index in indices] == [updates, updates]
    averages = [{k: v for f in folder.glob("ema-*.safetensors") for k, v in load_file(str(f)).items()}
                for folder in folders]
    assert averages[0] and averages[0].keys() == averages[1].keys()
    for name, value in averages[0].items():
        torch.testing.assert_close(value, averages[1][name], rtol=1e-6, atol=1e-7, msg=name)
    raw = {k: v for f in folders[0].glob("model-*.safetensors") for k, v in load_file(str(f)).items()}
    assert any(not torch.equal(value, raw[name]) for name, value in averages[0].items())


def test_lr_schedule_and_cli():
    assert lr_factor(0, 10, 100) == pytest.approx(0.1)
    assert lr_factor(10, 10, 100) == pytest.approx(1.0)
    assert lr_factor(100, 10, 100) == pytest.approx(0.1)
    config = parse_args(["--preset", "tiny", "--steps", "5", "--lr", "3e-4"])
    assert (config.preset, config.steps, config.lr) == ("tiny", 5, 3e-4)


def test_context_and_target_split_surrounds_targets():
    cams = _cameras(6)
    context, targets = split_context_targets(cams, 0, 2, 4)
    assert context == [0, 5] and sorted(targets) == [1, 2, 3, 4]


@needs_lpips
def test_time_limit_stops_cleanly_with_a_checkpoint_and_logged_steps(tmp_path):
    config = TrainConfig(preset="tiny", data="procedural", device="cpu", workers=0, warmup_steps=2, steps=50,
                         lpips_weights=str(WEIGHTS), checkpoint_every=100, log_every=1, time_limit_s=1e-3,
                         out=str(tmp_path))
    metrics = train(config, progress=False)
    assert metrics["step"] == 1
    assert latest_checkpoint(tmp_path).name == "step-00000001"
    assert [r["step"] for r in read_metrics(tmp_path)] == [1]
    plot_curve(read_metrics(tmp_path), [SceneScore("s", 1, 12.0, 11.0)], 1, tmp_path / "curve.png")
    assert (tmp_path / "curve.png").stat().st_size > 1000 and (tmp_path / METRICS_FILE).is_file()


def test_held_out_scenes_are_left_out_and_must_exist(data_root):
    names = training_scenes(data_root, ["llff_horns", "dtu_scan37"])
    assert "llff_horns" not in names and "dtu_scan37" not in names and len(names) >= 2
    with pytest.raises(InputError, match="no_such_scene"):
        training_scenes(data_root, ["no_such_scene"])


def test_mixed_source_draws_procedural_and_real_packed_scenes(data_root, tmp_path):
    """Catches: a held-out scene drawn, a mix without real or procedural scenes, or mixed batches that a second
    source of the same seed does not draw again (random state outside the seed and index)."""
    pack_scene(data_root / "llff_horns", tmp_path / "llff_horns", short_side=64)
    pack_scene(data_root / "dtu_scan37", tmp_path / "dtu_scan37", short_side=64)
    spec = DataSpec(views=(2,), sizes=((32, 48),), targets=2, batch_views=8, procedural_fraction=0.5)
    source = make_source(f"mix:{tmp_path}", spec, seed=0, holdout=["dtu_scan37"])
    batch = source(0)
    assert batch.scenes == 4 and batch.context_images.shape == (8, 3, 32, 48)
    assert batch.target_images.shape == (8, 3, 32, 48) and batch.target_cameras.num_views == 8
    keys = {key for index in range(4) for key in source(index).keys}
    assert "llff_horns" in keys and keys - {"llff_horns"} and "dtu_scan37" not in keys
    again = make_source(f"mix:{tmp_path}", spec, seed=0, holdout=["dtu_scan37"])
    assert_same_batches(again(3), source(3))  # deterministic in the seed and the index


def _cameras(n: int = 2):
    from codecsplat_warp.cameras import Cameras, intrinsics_matrix

    K = intrinsics_matrix(torch.full((n,), 40.0), torch.full((n,), 40.0), torch.full((n,), 24.0), torch.full((n,), 16.0))
    c2w = torch.eye(4).repeat(n, 1, 1)
    c2w[:, 0, 3] = 0.1 * torch.arange(n)
    return Cameras.from_c2w(K, c2w, torch.full((n,), 1.0), torch.full((n,), 10.0), 48, 32)


@needs_lpips
def test_two_process_ddp_matches_one_process_with_the_same_global_batch(tmp_path):
    """torchrun with 2 CPU (gloo) processes x 1 scene and 1 process x 2 accumulated scenes see the same scenes,
    log the same mean loss and end with the same weights."""
    import json
    import subprocess
    import sys

    from safetensors.torch import load_file

    common = ["--preset", "tiny", "--data", "procedural", "--device", "cpu", "--workers", "0", "--steps", "2",
              "--warmup-steps", "2", "--log-every", "1", "--checkpoint-every", "1", "--lpips-weights", str(WEIGHTS), "--seed", "5"]
    ddp = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--master_port", "29517",
           "-m", "train.stage1", *common, "--out", str(tmp_path / "ddp")]
    single = [sys.executable, "-m", "train.stage1", *common, "--accumulate", "2", "--out", str(tmp_path / "one")]
    for command in (ddp, single):
        done = subprocess.run(command, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr[-3000:]
    logs = {name: [json.loads(line) for line in (tmp_path / name / METRICS_FILE).read_text().splitlines()]
            for name in ("ddp", "one")}
    assert [r["scenes"] for r in logs["ddp"]] == [r["scenes"] for r in logs["one"]] == [2, 2]
    for a, b in zip(logs["ddp"], logs["one"]):
        assert a["loss"] == pytest.approx(b["loss"], rel=1e-4)
    # Adam turns float-rounding noise in near-zero gradients into full-size steps of single weights, so compare
    # the whole second update (step 1 -> 2) of both runs: rank-local gradients would make it differ by O(1).
    updates = []
    for name in ("ddp", "one"):
        steps = [load_file(next((tmp_path / name / "checkpoints" / f"step-0000000{k}").glob("model*.safetensors")))
                 for k in (1, 2)]
        updates.append(torch.cat([(steps[1][key] - steps[0][key]).flatten() for key in sorted(steps[0])]))
    assert updates[1].norm() > 0
    assert (updates[0] - updates[1]).norm() / updates[1].norm() < 0.02


def test_batches_are_pinned_in_the_training_thread_not_by_a_loader_thread():
    """The semi-amortised inner loop captures CUDA graphs in the training thread; a DataLoader pin-memory thread
    pinning meanwhile invalidates the capture and dies (two runs ended so). Would catch: a loader that pins in its
    own thread again, or a batch that does not reach the device whole."""
    source = make_source("procedural", DataSpec(views=(2,), sizes=((32, 48),), targets=1), seed=3)
    loader = _loader(source, 0, 2, 0, 1, 1, workers=1)
    assert loader.pin_memory is False and loader.num_workers == 1
    batch = next(iter(loader))
    moved = to_device(batch, torch.device("cpu"))
    assert torch.equal(moved.context_images, batch.context_images) and moved.keys == batch.keys
    if torch.cuda.is_available():
        on_gpu = to_device(batch, torch.device("cuda"))
        assert on_gpu.context_images.is_cuda and torch.equal(on_gpu.target_images.cpu(), batch.target_images)
