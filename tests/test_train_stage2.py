"""Stage-2 trainer: initialisation from stage 1, frozen backbone, lambda sampling, resumption, rate logging,
and rate control after brief training."""

from __future__ import annotations

import json
import math

import pytest
import torch
from conftest import LPIPS_WEIGHTS as WEIGHTS
from conftest import needs_lpips

from codecsplat_warp.codec import LAMBDA_MAX, LAMBDA_MIN
from codecsplat_warp.errors import DataError, InputError
from codecsplat_warp.metrics import LPIPS
from codecsplat_warp.model import CodecSplat
from codecsplat_warp.nn.config import get_preset
from codecsplat_warp.model.pretrained import save_pretrained
from train.checkpoint import latest_checkpoint, load_model_weights, save_checkpoint
from train.data import DataSpec, make_source
from train.stage1 import METRICS_FILE, TrainConfig, make_optimizer
from test_train_stage1 import assert_same_weight_average
from train.stage2 import (
    Stage2Config, build_stage2_model, parse_args, rate_ramp, rate_weight, run_model_config, sample_lambda,
    stage2_loss, train,
)

TINY = get_preset("tiny")


def _stage1_run(folder) -> CodecSplat:
    """A stage-1 run folder (config.json + one checkpoint) of a fresh tiny model, as stage 1 writes it."""
    torch.manual_seed(7)
    model = CodecSplat(TINY)
    optimizer, scheduler = make_optimizer(model, TrainConfig(steps=1))
    save_checkpoint(folder, 1, model, optimizer, scheduler, {})
    (folder / "config.json").write_text(json.dumps({"train": {}, "model": TINY.to_dict()}))
    return model


def test_stage2_model_starts_from_stage1_with_only_codec_modules_trainable(tmp_path):
    stage1 = _stage1_run(tmp_path / "s1")
    config = Stage2Config(init=str(tmp_path / "s1"), out=str(tmp_path / "s2"))
    assert run_model_config(config) == TINY
    model = build_stage2_model(TINY, config)
    for name, value in stage1.state_dict().items():
        assert torch.equal(model.state_dict()[name], value), name
    for name, value in stage1.refine_pre.state_dict().items():  # R_post starts as a copy of R_pre
        assert torch.equal(model.refine_post.state_dict()[name], value), name
    trainable = {n.split(".")[0] for n, p in model.named_parameters() if p.requires_grad}
    assert trainable == {"codec", "depth_head", "refine_post"}
    with pytest.raises(DataError, match="no checkpoint"):
        build_stage2_model(TINY, Stage2Config(init=str(tmp_path / "missing"), out=str(tmp_path / "s3")))
    with pytest.raises(InputError, match="--init"):
        run_model_config(Stage2Config(init="", out=str(tmp_path / "s4")))


def test_codec_init_copies_every_stage2_module_over_the_stage1_start(tmp_path):
    stage1 = _stage1_run(tmp_path / "s1")
    torch.manual_seed(11)
    donor = CodecSplat(TINY, codec=True)
    save_pretrained(donor, tmp_path / "donor.safetensors")
    config = Stage2Config(init=str(tmp_path / "s1"), out=str(tmp_path / "s2"),
                          codec_init=str(tmp_path / "donor.safetensors"))
    model = build_stage2_model(TINY, config)
    for name, value in model.state_dict().items():
        from_donor = name.split(".")[0] in CodecSplat.CODEC_MODULE_NAMES
        assert torch.equal(value, (donor if from_donor else stage1).state_dict()[name]), name
    with pytest.raises(DataError, match="holds no codec"):  # a stage-1 run has no codec to copy
        build_stage2_model(TINY, Stage2Config(init=str(tmp_path / "s1"), out=str(tmp_path / "s3"),
                                              codec_init=str(tmp_path / "s1")))


def test_codec_layout_options_grow_the_codec_init_codec_into_finer_levels(tmp_path):
    _stage1_run(tmp_path / "s1")
    torch.manual_seed(11)
    donor = CodecSplat(TINY, codec=True)
    save_pretrained(donor, tmp_path / "donor.safetensors")
    config = Stage2Config(init=str(tmp_path / "s1"), out=str(tmp_path / "s2"), codec_latent_channels="4,8,3",
                          codec_finest_stride=2, codec_init=str(tmp_path / "donor.safetensors"))
    model_config = run_model_config(config)
    assert (model_config.codec_latent_channels, model_config.codec_finest_stride) == ((4, 8, 3), 2)
    model = build_stage2_model(model_config, config)
    grown = model.state_dict()
    for name, value in donor.codec.top_down.blocks[1].state_dict().items():
        assert torch.equal(grown[f"codec.top_down.blocks.1.{name}"], value), name
    assert torch.equal(grown["codec.top_down.ups.1.conv.weight"], donor.codec.synthesis.ups[0].conv.weight)
    assert torch.equal(grown["codec.synthesis.ups.0.conv.weight"], donor.codec.synthesis.ups[1].conv.weight)
    assert not grown["codec.top_down.blocks.2.merge.weight"][:, :model_config.codec_channels].any()  # starts unused
    with pytest.raises(DataError, match="holds no codec"):  # levels that are not the donor's plus finer ones
        wrong = Stage2Config(**{**config.__dict__, "codec_latent_channels": "4,7,3", "out": str(tmp_path / "s3")})
        build_stage2_model(run_model_config(wrong), wrong)
    with pytest.raises(InputError, match="comma-separated"):
        run_model_config(Stage2Config(init=str(tmp_path / "s1"), out=str(tmp_path / "s4"), codec_latent_channels="4;8"))


def test_trainable_narrows_training_to_the_named_stage2_parameters(tmp_path):
    _stage1_run(tmp_path / "s1")
    config = Stage2Config(init=str(tmp_path / "s1"), out=str(tmp_path / "s2"),
                          trainable="codec.top_down.blocks.1,codec.synthesis,depth_head")
    model = build_stage2_model(TINY, config)
    trainable = {n for n, p in model.named_parameters() if p.requires_grad}
    assert trainable and all(n.startswith(("codec.top_down.blocks.1.", "codec.synthesis.", "depth_head."))
                             for n in trainable)
    assert any(n.startswith("depth_head.") for n in trainable)
    for wrong in ("codec.top_down.blocks.9", "backbone", "codec.top_down.blocks.1.pri"):
        with pytest.raises(InputError, match="names no stage-2 parameter"):
            build_stage2_model(TINY, Stage2Config(init=str(tmp_path / "s1"), out=str(tmp_path / "s3"), trainable=wrong))


def test_lambda_is_log_uniform_and_reproducible_per_step_and_rank():
    draws = [sample_lambda(0, step, 0) for step in range(400)]
    assert all(LAMBDA_MIN <= lam <= LAMBDA_MAX for lam in draws)
    logs = torch.tensor([math.log(lam) for lam in draws])
    middle = 0.5 * (math.log(LAMBDA_MIN) + math.log(LAMBDA_MAX))
    assert 0.4 < float((logs < middle).float().mean()) < 0.6
    assert sample_lambda(0, 5, 0) == sample_lambda(0, 5, 0) != sample_lambda(0, 5, 1)


def test_cli_and_rate_weight_defaults():
    config = parse_args(["--init", "runs/s1", "--steps", "7", "--gamma", "0.2"])
    assert (config.init, config.steps, config.gamma, config.beta) == ("runs/s1", 7, 0.2, None)
    assert rate_weight(config, get_preset("re10k")) == 4e-4 and rate_weight(config, get_preset("dl3dv")) == 1e-4
    assert rate_weight(parse_args(["--beta", "1e-3"]), TINY) == 1e-3
    with pytest.raises(InputError, match="coded-every"):
        parse_args(["--coded-every", "0"])
    assert [rate_ramp(s, 4) for s in range(5)] == [0.25, 0.5, 0.75, 1.0, 1.0] and rate_ramp(0, 0) == 1.0


@needs_lpips
def test_resumed_run_gives_the_same_next_step_loss_and_logs_coded_rate(tmp_path):
    stage1 = _stage1_run(tmp_path / "s1")
    common = dict(init=str(tmp_path / "s1"), data="procedural", device="cpu", workers=0, warmup_steps=10,
                  lpips_weights=str(WEIGHTS), checkpoint_every=2, log_every=1, seed=3, coded_every=2)
    train(Stage2Config(out=str(tmp_path / "a"), steps=2, **common), progress=False)
    resumed = train(Stage2Config(out=str(tmp_path / "a"), steps=3, **common), progress=False)
    direct = train(Stage2Config(out=str(tmp_path / "b"), steps=3, **common), progress=False)
    assert (resumed["resumed_from"], direct["resumed_from"], resumed["step"]) == (2, 0, 3)
    assert resumed["loss"] == pytest.approx(direct["loss"], rel=1e-5)
    assert_same_weight_average(tmp_path / "a", tmp_path / "b", updates=3)
    records = [json.loads(line) for line in (tmp_path / "a" / METRICS_FILE).read_text().splitlines()]
    assert [r["step"] for r in records] == [1, 2, 3]
    coded = records[1]
    assert coded["coded_bits"] > 0 and abs(coded["rate_gap"]) < 0.15  # tiny streams: 32-bit words weigh in
    assert "coded_bits" not in records[2]
    trained = CodecSplat(TINY, codec=True)
    load_model_weights(latest_checkpoint(tmp_path / "a"), trained)
    for name, value in stage1.state_dict().items():
        if not name.startswith("depth_head."):  # stage 1 trained it as an auxiliary; stage 2 goes on training it
            assert torch.equal(trained.state_dict()[name], value), f"frozen {name} changed"


@needs_lpips
@pytest.mark.parametrize("option, metric", [("self_render_weight", "self_psnr"), ("own_render_weight", "own_psnr")])
def test_context_render_weights_add_the_decoded_gaussians_render_loss_on_the_context_views(tmp_path, option, metric):
    _stage1_run(tmp_path / "s1")
    model = build_stage2_model(TINY, Stage2Config(init=str(tmp_path / "s1"), out=str(tmp_path / "s2"))).train()
    lpips = LPIPS(weights_dir=WEIGHTS)
    batch = make_source("procedural", DataSpec(views=(2,), sizes=((32, 48),), targets=1, batch_views=4), seed=3)(0)
    losses = {}
    for weight in (0.0, 0.5):
        torch.manual_seed(0)
        loss, metrics = stage2_loss(model, lpips, batch, Stage2Config(**{option: weight}), step=4)
        losses[weight] = float(loss.detach())
        assert (metric in metrics) == (weight > 0)
    assert 5.0 < float(metrics[metric]) < 60.0 and losses[0.5] > losses[0.0]


@pytest.mark.slow
def test_brief_codec_training_gives_more_bytes_and_less_distortion_at_higher_lambda():
    """Eq. 16's rate-distortion trade-off on the codec alone (tiny, a fixed random backbone's F_c of two
    procedural scenes, feature MSE as the distortion, stage 2's lambda sampling and rate warm-up): after a
    brief training the high-lambda operating point codes more bytes and reconstructs the features better
    than the low-lambda one. About 15 s on an idle 2-core CPU (a few hundred steps are needed)."""
    torch.manual_seed(0)
    model = CodecSplat(TINY, codec=True)
    source = make_source("procedural", DataSpec.of_model(TINY), seed=0)
    with torch.no_grad():
        features = [model(source(i).context_images, source(i).context_cameras)["F_c"] for i in range(2)]
    codec = model.codec
    optimizer = torch.optim.Adam(codec.parameters(), lr=RD_LEARNING_RATE)
    pixels = 2 * TINY.height * TINY.width
    for step in range(RD_STEPS):
        feature, lam = features[step % 2], sample_lambda(0, step, 0)
        out = codec(feature, lam)
        rate = RD_RATE_WEIGHT * rate_ramp(step, RD_STEPS // 2) * out.bits.sum() / pixels
        loss = lam / LAMBDA_MAX * (out.feature - feature).square().mean() + rate
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    codec.eval()
    points = {}
    for lam in (LAMBDA_MIN, LAMBDA_MAX):
        size, error = 0, 0.0
        for feature in features:
            coded = codec.compress(feature, lam)
            decoded, _ = codec.decompress(coded.streams, *feature.shape[-2:], lam)
            size += sum(len(s) for s in coded.streams)
            error += float((decoded - feature).square().mean())
        points[lam] = (size, error)
    (low_bytes, low_error), (high_bytes, high_error) = points[LAMBDA_MIN], points[LAMBDA_MAX]
    assert high_bytes > low_bytes and high_error < low_error, points


RD_STEPS = 400
RD_LEARNING_RATE = 3e-3
RD_RATE_WEIGHT = 4e-4
