"""Learned refiner training (train.learned_refiner): the model frozen and the refiner trained with the target views
in the loss, its metrics, resumption, and the refiner file a run writes; on the tiny preset and procedural scenes."""

from __future__ import annotations

import json

import pytest
import torch
from conftest import LPIPS_WEIGHTS as WEIGHTS
from conftest import needs_lpips

from codecsplat_warp.errors import InputError, RefinerError
from codecsplat_warp.metrics import LPIPS
from codecsplat_warp.model import CodecSplat
from codecsplat_warp.model.codecsplat import model_id
from codecsplat_warp.model.pretrained import save_pretrained
from codecsplat_warp.model.rdo import LatentRefiner, Refinement, RefinerConfig, load_refiner, save_refiner
from codecsplat_warp.nn.config import get_preset
from train import learned_refiner
from train.checkpoint import latest_checkpoint, load_model_weights
from train.data import DataSpec, make_source
from train.learned_refiner import (REFINER_FILE, REFINER_LOGGED, LearnedRefinerConfig, RefinerTraining, build_model,
                                   parse_args, refiner_loss, train)
from train.semi_amortised import parse_counts
from train.stage1 import METRICS_FILE

TINY = get_preset("tiny")


def _model_file(path, seed: int = 5) -> CodecSplat:
    torch.manual_seed(seed)
    model = CodecSplat(TINY, codec=True)
    save_pretrained(model, path)
    return model


def test_the_model_is_frozen_and_the_refiner_starts_fresh_or_from_its_init(tmp_path):
    """Would catch: model weights that train, a start from other weights, or an --init refiner of another model."""
    start = _model_file(tmp_path / "m.safetensors")
    config = LearnedRefinerConfig(model=str(tmp_path / "m.safetensors"), out=str(tmp_path / "run"), hidden=4)
    built = build_model(TINY, config)
    for name, value in start.state_dict().items():
        assert torch.equal(built.model.state_dict()[name], value), name
    assert {n.split(".")[0] for n, p in built.named_parameters() if p.requires_grad} == {"refiner"}
    assert all(not cell.head.weight.detach().any() for cell in built.refiner.cells)
    refiner = LatentRefiner(RefinerConfig(TINY.codec_latent_channels, hidden=4))
    with torch.no_grad():
        refiner.log_step[0].fill_(0.5)
    save_refiner(refiner, tmp_path / "r.safetensors", model_id(start))
    warm = build_model(TINY, LearnedRefinerConfig(model=config.model, out=config.out, hidden=4,
                                                  init=str(tmp_path / "r.safetensors")))
    assert torch.equal(warm.refiner.log_step[0], refiner.log_step[0])
    save_refiner(refiner, tmp_path / "other.safetensors", model_id(_model_file(tmp_path / "o.safetensors", 6)))
    with pytest.raises(RefinerError, match="trained for model"):
        build_model(TINY, LearnedRefinerConfig(model=config.model, out=config.out, hidden=4,
                                               init=str(tmp_path / "other.safetensors")))
    assert parse_args([]).iterations == "8" and parse_counts("8, 25,8", "--iterations", 1) == [8, 25, 8]
    assert parse_counts(parse_args(["--iterations", "8,25,50,160"]).iterations, "--iterations", 1) == [8, 25, 50, 160]
    for argv, match in ((["--inner-preset", "fast"], "inner-preset"), (["--hidden", "0"], "hidden"),
                        *((["--iterations", bad], "--iterations must be a comma list of integers >= 1")
                          for bad in ("0", "8,0", "8,-1", "8,a", "2.5", ","))):
        with pytest.raises(InputError, match=match):
            parse_args(argv)


def test_one_iteration_count_is_drawn_per_step_for_every_scene_and_rank_and_logged(tmp_path, monkeypatch):
    """``--iterations 1,3`` over 12 steps of two scenes, as rank 0 and as rank 1 (the refinement itself stubbed
    out: only the counts it is asked for are recorded). Would catch: a count drawn per scene or per rank (DDP ranks
    out of step), a logged count that is not the one run, or one count run at every step."""
    _model_file(tmp_path / "m.safetensors")
    config = LearnedRefinerConfig(model=str(tmp_path / "m.safetensors"), out=str(tmp_path / "run"), hidden=4,
                                  iterations="1,3", seed=3)
    trained = build_model(TINY, config)
    batch = make_source("procedural", DataSpec(views=(2,), sizes=((32, 48),), targets=1, batch_views=4), seed=3)(0)
    assert batch.scenes == 2
    latents = [torch.zeros(4, c, 2, 3) for c in TINY.codec_latent_channels]
    ran = []

    def record(model, images, cameras, lam, start, refiner, rdo, generator):
        ran.append(rdo.steps)
        return Refinement([z.detach() for z in start], None, None)

    monkeypatch.setattr(learned_refiner, "learned_refine", record)
    monkeypatch.setattr(learned_refiner.dist, "is_initialized", lambda: True)
    logged = {}
    for rank in (0, 1):
        monkeypatch.setattr(learned_refiner.dist, "get_rank", lambda rank=rank: rank)
        logged[rank] = [trained(batch, 64.0, latents, config, step)[1]["iterations"] for step in range(12)]
    assert logged[0] == logged[1] and set(logged[0]) == {1.0, 3.0}
    assert ran[0::2] == ran[1::2] and [float(r) for r in ran[0::2]] == logged[0] + logged[1]


@needs_lpips
def test_the_target_loss_reaches_the_refiner_alone_and_logs_its_metrics(tmp_path):
    """Would catch: a loss on the amortised decode (no gradient to the refiner), gradients into the frozen model,
    or missing refiner metrics."""
    _model_file(tmp_path / "m.safetensors")
    config = LearnedRefinerConfig(model=str(tmp_path / "m.safetensors"), out=str(tmp_path / "run"), hidden=4,
                                  iterations="2")
    trained = build_model(TINY, config)
    assert isinstance(trained, RefinerTraining)
    batch = make_source("procedural", DataSpec(views=(2,), sizes=((32, 48),), targets=1), seed=3)(0)
    loss, metrics = refiner_loss(trained, LPIPS(weights_dir=WEIGHTS), batch, config, step=4)
    loss.backward()
    assert all(p.grad is None for p in trained.model.parameters())
    for cell, step in zip(trained.refiner.cells, trained.refiner.log_step):
        assert float(cell.head.weight.grad.abs().sum()) > 0 and float(step.grad.abs().sum()) > 0
    assert set(REFINER_LOGGED) <= set(metrics) and metrics["iterations"] == 2.0
    assert torch.isfinite(metrics["context_gain"]) and metrics["iterations_per_s"] > 0
    assert float(metrics["target_gain"]) == pytest.approx(float(metrics["psnr"] - metrics["target_psnr_amortised"]))


@needs_lpips
def test_a_resumed_run_gives_the_same_loss_and_writes_a_refiner_for_the_model(tmp_path):
    """One step, resumed to two, matches two straight; the run's refiner file names the model it was trained for
    and holds the checkpoint's refiner. Would catch: state a checkpoint does not carry, or a file tied to no model."""
    start = _model_file(tmp_path / "m.safetensors")
    common = dict(model=str(tmp_path / "m.safetensors"), data="procedural", device="cpu", workers=0, hidden=4,
                  warmup_steps=10, lpips_weights=str(WEIGHTS), checkpoint_every=1, log_every=1, seed=3,
                  iterations="2", ema_decay=0.0, sizes="32x48")
    train(LearnedRefinerConfig(out=str(tmp_path / "a"), steps=1, **common), progress=False)
    resumed = train(LearnedRefinerConfig(out=str(tmp_path / "a"), steps=2, **common), progress=False)
    direct = train(LearnedRefinerConfig(out=str(tmp_path / "b"), steps=2, **common), progress=False)
    assert (resumed["resumed_from"], resumed["step"]) == (1, 2)
    assert resumed["loss"] == pytest.approx(direct["loss"], rel=1e-5)
    records = [json.loads(line) for line in (tmp_path / "a" / METRICS_FILE).read_text().splitlines()]
    assert [r["step"] for r in records] == [1, 2] and all(set(REFINER_LOGGED) <= set(r) for r in records)
    refiner, meta = load_refiner(tmp_path / "a" / REFINER_FILE, model_id(start))
    assert resumed["refiner_id"] == meta["refiner_id"]
    saved = RefinerTraining(CodecSplat(TINY, codec=True), LatentRefiner(refiner.config))
    load_model_weights(latest_checkpoint(tmp_path / "a"), saved)
    for name, value in saved.refiner.state_dict().items():
        assert torch.equal(refiner.state_dict()[name], value), name
    assert any(float(cell.head.weight.abs().sum()) > 0 for cell in refiner.cells)
    for name, value in start.state_dict().items():
        assert torch.equal(saved.model.state_dict()[name], value), f"frozen {name} changed"
