"""Weight average (EMA) of training runs: the update rule, its checkpoints, and the runs' users (export,
validation, stage 2's warm starts) reading it in place of the raw weights; checkpoints without one."""

from __future__ import annotations

import json

import pytest
import torch
from safetensors.torch import load_file

from codecsplat_warp.errors import DataError, InputError
from codecsplat_warp.model import CodecSplat
from codecsplat_warp.nn.config import get_preset
from train import stage1, stage2
from train.checkpoint import latest_checkpoint, load_checkpoint, save_checkpoint
from train.export import export
from train.stage1 import TrainConfig, make_optimizer
from train.validate import load_run
from train.weight_average import WeightAverage, warmed_up_decay

TINY = get_preset("tiny")


def test_update_averages_only_trainable_parameters_with_the_warmed_up_decay():
    torch.manual_seed(0)
    model = torch.nn.Sequential(torch.nn.Linear(3, 2), torch.nn.Linear(2, 1)).double()
    model[1].requires_grad_(False)
    average = WeightAverage(model, decay=0.5)
    assert set(average.averages) == {"0.weight", "0.bias"}
    assert all(a.dtype == torch.float32 for a in average.averages.values())
    expected = model[0].weight.detach().float().clone()
    for n in range(12):
        with torch.no_grad():
            model[0].weight.add_(1.0)
        keep = min(0.5, (1 + n) / (10 + n))
        assert warmed_up_decay(0.5, n) == pytest.approx(keep)
        expected = keep * expected + (1 - keep) * model[0].weight.detach().float()
        average.update(model)
        torch.testing.assert_close(average.averages["0.weight"], expected)
    assert average.updates == 12 and warmed_up_decay(0.5, 11) == 0.5 and warmed_up_decay(0.999, 0) == 0.1
    with pytest.raises(InputError, match="decay"):
        WeightAverage(model, decay=1.0)
    with pytest.raises(InputError, match="ema-decay"):
        stage1.parse_args(["--ema-decay", "1"])
    assert stage1.parse_args([]).ema_decay == 0.999 and stage2.parse_args(["--ema-decay", "0"]).ema_decay == 0.0


def _run(folder, codec: bool, with_average: bool) -> tuple[CodecSplat, WeightAverage]:
    """A run folder (config.json + one checkpoint) whose weight average differs from its raw weights by 1;
    the checkpoint keeps the average only ``with_average`` (one written before the average existed)."""
    torch.manual_seed(5)
    model = CodecSplat(TINY, codec=codec)
    optimizer, scheduler = make_optimizer(model, TrainConfig(steps=1))
    average = WeightAverage(model, 0.9)
    with torch.no_grad():
        for parameter in model.parameters():
            parameter.add_(1.0)
    save_checkpoint(folder, 1, model, optimizer, scheduler, {}, average=average if with_average else None)
    (folder / "config.json").write_text(json.dumps({"train": {}, "model": TINY.to_dict()}))
    return model, average


@pytest.mark.parametrize("with_average", [True, False])
def test_export_and_validation_use_the_weight_average_where_the_checkpoint_keeps_one(tmp_path, with_average):
    model, average = _run(tmp_path / "run", codec=True, with_average=with_average)
    export(tmp_path / "run", tmp_path / "model.safetensors", half=False)
    exported = load_file(str(tmp_path / "model.safetensors"))
    loaded, step = load_run(tmp_path / "run", "cpu")
    assert step == 1
    for name, raw in model.state_dict().items():
        wanted = average.averages[name] if with_average and name in average.averages else raw
        assert torch.equal(exported[name].float(), wanted), name
        assert torch.equal(loaded.state_dict()[name], wanted), name


def test_stage2_warm_starts_read_the_weight_average(tmp_path):
    _, average = _run(tmp_path / "s1", codec=False, with_average=True)
    _, donor_average = _run(tmp_path / "donor", codec=True, with_average=True)
    config = stage2.Stage2Config(init=str(tmp_path / "s1"), out=str(tmp_path / "s2"), codec_init=str(tmp_path / "donor"))
    weights = stage2.build_stage2_model(TINY, config).state_dict()
    stage2_names = tuple(name + "." for name in CodecSplat.CODEC_MODULE_NAMES)
    for name, value in average.averages.items():  # --init: backbone and GS head
        if not name.startswith(stage2_names):
            assert torch.equal(weights[name], value), name
    from_donor = [name for name in donor_average.averages if name.startswith(stage2_names)]
    assert any(name.startswith("codec.") for name in from_donor)
    for name in from_donor:  # --codec-init: codec, depth head, R_post
        assert torch.equal(weights[name], donor_average.averages[name]), name


def test_resuming_a_checkpoint_without_average_starts_it_from_the_checkpoint_weights(tmp_path, capsys):
    model, _ = _run(tmp_path / "run", codec=False, with_average=False)
    clone = CodecSplat(TINY)
    optimizer, scheduler = make_optimizer(clone, TrainConfig(steps=1))
    average = WeightAverage(clone, 0.9)
    assert load_checkpoint(latest_checkpoint(tmp_path / "run"), clone, optimizer, scheduler, average) == 1
    assert "no weight average" in capsys.readouterr().out and average.updates == 0
    for name, value in average.averages.items():
        assert torch.equal(value, model.state_dict()[name]), name
    frozen = CodecSplat(TINY)
    frozen.depth_head.requires_grad_(False)  # other trainable parameters than the checkpoint's average
    _run(tmp_path / "new", codec=False, with_average=True)
    with pytest.raises(DataError, match="other parameters"):
        load_checkpoint(latest_checkpoint(tmp_path / "new"), frozen, *make_optimizer(frozen, TrainConfig(steps=1)),
                        WeightAverage(frozen, 0.9))
