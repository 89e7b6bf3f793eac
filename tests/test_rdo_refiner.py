"""The learned latent refiner (codecsplat_warp.model.rdo.refiner) on the tiny preset: a fresh one is the presets'
Adam, the target gradient reaches its weights through the iterations and never the model's, a trained one reads the
run's lambda, its file round-trips and refuses another model or an older format, the encoder runs it, and ``bench
rdo --refiner`` adds its rows and times its iteration."""

from __future__ import annotations

import json

import pytest
import torch
from conftest import tiny_coding_model
from safetensors.torch import save_file
from test_cli_commands import write_scene

from codecsplat_warp.bench import rdo as bench_rdo
from codecsplat_warp.cli import build_parser
from codecsplat_warp.codec import parse_bitstream
from codecsplat_warp.data.procedural import ProceduralConfig, procedural_scene
from codecsplat_warp.errors import InputError, RefinerError
from codecsplat_warp.metrics.lpips import WEIGHTS_ENV
from codecsplat_warp.model.codecsplat import model_id
from codecsplat_warp.model.pretrained import save_pretrained
from codecsplat_warp.model.rdo import (LatentRefiner, RefinerConfig, latent_target, learned_refine, load_refiner,
                                       rdo_config, rdo_loss, refine_latents, refiner_id, refiner_step, save_refiner)

LAM = 1024.0


def _scene_on(device: str):
    """The tiny coding model, a 2-view procedural scene (48x32) and its amortised latents, all on ``device``."""
    model = tiny_coding_model(0).to(device)
    s = procedural_scene(3, ProceduralConfig(width=48, height=32, num_views=2, texture_size=16))
    images, cameras = s.images.float().to(device) / 255.0, s.cameras.to(device=device, dtype=torch.float32)
    with torch.no_grad():
        latents = model(images, cameras, lam=LAM)["latents"]
    return model, images, cameras, latents


@pytest.fixture(scope="module")
def scene():
    return _scene_on("cpu")


def _refiner(latents, seed: int | None = None) -> LatentRefiner:
    """A fresh refiner for ``latents``; with a ``seed``, its output convolutions and step sizes perturbed (as a
    trained one's are)."""
    refiner = LatentRefiner(RefinerConfig(tuple(z.shape[1] for z in latents), hidden=4))
    if seed is not None:
        torch.manual_seed(seed)
        with torch.no_grad():
            for cell, step in zip(refiner.cells, refiner.log_step):
                cell.head.weight.normal_(std=0.05)
                step.normal_(std=0.1)
    return refiner


def test_a_fresh_refiner_takes_the_presets_adam_steps_and_lowers_the_context_loss(scene):
    """Would catch: an output layer or step size that does not start at Adam's step, another schedule or loss than
    the presets', or moves of the wrong shape."""
    model, images, cameras, latents = scene
    config = rdo_config("medium", steps=3, views=2, cuda_graphs=False, check_every=0)
    adam = refine_latents(model, images, cameras, LAM, latents, config, torch.Generator().manual_seed(0))
    refiner = _refiner(latents)
    learned = learned_refine(model, images, cameras, LAM, latents, refiner, config, torch.Generator().manual_seed(0))
    for a, b, z in zip(adam.latents, learned.latents, latents):
        assert b.shape == z.shape and b.dtype == torch.float32
        torch.testing.assert_close(b.detach(), a, rtol=0, atol=1e-5)
        assert not torch.equal(b.detach(), z)
    target = latent_target(model, images, cameras, LAM, latents, config)
    with torch.no_grad():
        before = float(rdo_loss(model, [z.clone() for z in latents], target, config, torch.Generator().manual_seed(1))[0])
        after = float(rdo_loss(model, [z.detach() for z in learned.latents], target, config,
                               torch.Generator().manual_seed(1))[0])
    assert after < before
    with pytest.raises(InputError, match="channels"):
        LatentRefiner(RefinerConfig((3, 5))).start(latents)


def test_the_loss_at_the_last_iteration_reaches_every_refiner_weight_and_no_model_weight(scene):
    """The gradient input is detached, the path through the refiner is not. Would catch: a gradient taken with
    backward() into the model's weights, or a refiner move cut from the graph."""
    model, images, cameras, latents = scene
    model.requires_grad_(True)
    try:
        refiner = _refiner(latents, seed=2)
        config = rdo_config("medium", steps=2, views=2, cuda_graphs=False, check_every=0)
        result = learned_refine(model, images, cameras, LAM, latents, refiner, config,
                                torch.Generator().manual_seed(0))
        sum(z.square().sum() for z in result.latents).backward()
        assert all(p.grad is None for p in model.parameters())
        for name, p in refiner.named_parameters():
            assert p.grad is not None and float(p.grad.abs().sum()) > 0, name
    finally:
        model.requires_grad_(False)


def test_a_trained_refiner_reads_the_runs_lambda(scene, monkeypatch):
    """The same latents, gradient and progress at lambda 16 and 1024 give other moves (at one lambda, the same),
    and a step hands the refiner its target's lambda. Would catch: a lambda channel left out of the inputs or
    constant, or a step that passes the refiner another lambda than the run's."""
    model, images, cameras, latents = scene
    refiner = _refiner(latents, seed=7)
    torch.manual_seed(8)
    grads = [torch.randn_like(z) for z in latents]

    def moves(lam: float) -> list[torch.Tensor]:
        with torch.no_grad():
            return refiner([z.clone() for z in latents], grads, refiner.start(latents), 0.1, 0.5, lam)

    low, again, high = moves(16.0), moves(16.0), moves(1024.0)
    for a, b, c in zip(low, again, high):
        assert torch.equal(a, b) and float((a - c).abs().max()) > 1e-4
    seen = []
    forward = refiner.forward
    monkeypatch.setattr(refiner, "forward", lambda *args: seen.append(args[-1]) or forward(*args))
    config = rdo_config("medium", steps=1, views=2, cuda_graphs=False, check_every=0)
    target = latent_target(model, images, cameras, 64.0, latents, config)
    with torch.no_grad():
        refiner_step(model, refiner, latents, refiner.start(latents), target, config, torch.Generator().manual_seed(0),
                     0.1, 0.0)
    assert seen == [64.0]


def test_a_refiner_file_round_trips_and_refuses_another_model_or_format(scene, tmp_path):
    """The older format is a file of format 1 as it was written (no lambda channel: each cell's input projection one
    channel narrower). Would catch: weights or config lost on the way, an id that ignores the weights, a refiner
    applied to a model it was not trained for, or an old file read as a new one."""
    model, _, _, latents = scene
    refiner = _refiner(latents, seed=3)
    identity = save_refiner(refiner, tmp_path / "r.safetensors", model_id(model))
    loaded, meta = load_refiner(tmp_path / "r.safetensors", model_id(model))
    assert meta == {"refiner_id": identity, "model_id": model_id(model)} and refiner_id(loaded) == identity
    assert loaded.config == refiner.config and not loaded.training
    assert all(not p.requires_grad for p in loaded.parameters())
    for name, value in refiner.state_dict().items():
        assert torch.equal(loaded.state_dict()[name], value), name
    assert refiner_id(_refiner(latents, seed=4)) != identity
    other = model_id(tiny_coding_model(1))
    with pytest.raises(RefinerError, match=f"{identity}.*{model_id(model)}.*{other}"):
        load_refiner(tmp_path / "r.safetensors", other)
    save_pretrained(model, tmp_path / "model.safetensors")
    with pytest.raises(RefinerError, match="not a latent refiner file"):
        load_refiner(tmp_path / "model.safetensors")
    with pytest.raises(RefinerError, match="not found"):
        load_refiner(tmp_path / "missing.safetensors")
    old = {name: value[:, :-1].contiguous() if name.endswith("project.weight") else value.contiguous()
           for name, value in refiner.state_dict().items()}
    save_file(old, str(tmp_path / "old.safetensors"),
              metadata={"format": "codecsplat-latent-refiner/1", "config": json.dumps(refiner.config.to_dict()),
                        "refiner_id": identity, "model_id": model_id(model)})
    with pytest.raises(RefinerError, match="format codecsplat-latent-refiner/1, this version reads "
                                           "codecsplat-latent-refiner/2 only"):
        load_refiner(tmp_path / "old.safetensors", model_id(model))


def test_the_encoder_runs_the_refiner_and_its_bitstream_decodes(scene):
    """``encode_scene(refiner=...)``: a fresh refiner's iterations code what Adam's steps code, and a changed one
    codes its last iterate. Would catch: an encoder that ignores the refiner or keeps another coding than the
    refiner's last."""
    model, images, cameras, latents = scene
    adam = model.encode_scene(images, cameras, LAM, steps=2, seed=1)
    assert adam.rdo.best_step == 2
    fresh = model.encode_scene(images, cameras, LAM, steps=2, seed=1, refiner=_refiner(latents))
    assert fresh.data == adam.data and fresh.rdo.steps == 2
    changed = model.encode_scene(images, cameras, LAM, steps=2, seed=1, refiner=_refiner(latents, seed=5))
    assert changed.data != adam.data and changed.rdo.best_step == 2
    assert parse_bitstream(changed.data).header.model_id == model_id(model)
    for coded, decoded in zip(changed.latents, model.decode_scene(changed.data).latents):
        assert torch.equal(coded, decoded.cpu())
    with pytest.raises(InputError, match="variable='latents'"):
        model.encode_scene(images, cameras, LAM, steps=1, refiner=_refiner(latents),
                           rdo_settings={"variable": "feature"})


def test_bench_rdo_adds_the_refiner_rows_and_times_its_iteration(scene, tmp_path, monkeypatch):
    """Would catch: refiner rows missing or run as Adam, a profile without the refiner's iteration, or a refiner
    of another model accepted."""
    model, _, _, latents = scene
    monkeypatch.delenv(WEIGHTS_ENV, raising=False)
    save_pretrained(model, tmp_path / "tiny.safetensors")
    write_scene(tmp_path / "scenes" / "a", seed=4)
    save_refiner(_refiner(latents, seed=6), tmp_path / "r.safetensors", model_id(model))
    common = ["bench", "rdo", "--device", "cpu", "--json", "--checkpoint", str(tmp_path / "tiny.safetensors"),
              "--data", str(tmp_path / "scenes"), "--protocol", "scene", "--lambdas", "64",
              "--refiner", str(tmp_path / "r.safetensors")]
    result = bench_rdo.run(build_parser().parse_args(common + ["--steps", "0,1", "--refiner-steps", "1"]))
    coded = [(r["method"], r["steps"], r.get("rdo", {}).get("steps")) for r in result["rows"] if "lambda" in r]
    assert coded == [("codecsplat", 0, None), ("codecsplat", 1, 1), ("refiner", 1, 1)]
    adam, refined = [r for r in result["rows"] if r.get("steps") == 1]
    assert refined["context_psnr"] != adam["context_psnr"]
    assert {s["method"] for s in result["summary"]} == {"copy nearest", "codec-free", "codecsplat", "refiner"}
    profile = bench_rdo.run(build_parser().parse_args(common + ["--profile", "--profile-steps", "1"]))["profile"]
    assert profile["refiner_step_ms"] > 0 and len(profile["refiner_step_ms_all"]) == 1
    assert "x the Adam step" in bench_rdo.format_profile(profile)
    save_refiner(_refiner(latents), tmp_path / "other.safetensors", model_id(tiny_coding_model(1)))
    with pytest.raises(RefinerError, match="trained for model"):
        bench_rdo.run(build_parser().parse_args(common[:-1] + [str(tmp_path / "other.safetensors"), "--steps", "0",
                                                               "--refiner-steps", "1"]))


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU visible to torch")
def test_on_cuda_the_graphed_encoder_runs_a_fresh_refiner_as_adams_steps_and_a_changed_one_decodes():
    """The encoder on CUDA with its decoder and loss as CUDA graphs (the default there), every Warp kernel on CUDA
    (the GPU machines' Warp compiles no CPU kernels). Would catch: a refiner iteration that misses the graphed
    decoder's gradient or reads stale static tensors, or a refiner left on the CPU while the latents are on the
    GPU."""
    model, images, cameras, latents = _scene_on("cuda")
    device = torch.device("cuda")
    amortised = model.encode_scene(images, cameras, LAM, steps=0, seed=1)
    adam = model.encode_scene(images, cameras, LAM, steps=3, seed=1)
    fresh = model.encode_scene(images, cameras, LAM, steps=3, seed=1, refiner=_refiner(latents).to(device))
    assert fresh.rdo.steps == 3

    def share_moved(a, b) -> float:
        return float(sum((x != y).sum() for x, y in zip(a.latents, b.latents))) / sum(x.numel() for x in a.latents)

    # Adam's arithmetic on the GPU may round a few latents the other way: the same moves, up to a few ties
    assert share_moved(fresh, adam) <= 0.01 < share_moved(fresh, amortised)
    changed = model.encode_scene(images, cameras, LAM, steps=3, seed=1,
                                 refiner=_refiner(latents, seed=5).to(device))
    assert changed.data != adam.data
    for coded, decoded in zip(changed.latents, model.decode_scene(changed.data).latents):
        assert torch.equal(coded.cpu(), decoded.cpu())
