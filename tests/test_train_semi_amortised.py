"""Semi-amortised training (train.semi_amortised): the encoder's optimisation inside each step, first-order
gradients into the decoder, the inner loop's metrics, resumption; on the tiny preset and procedural scenes."""

from __future__ import annotations

import json
import warnings

import pytest
import torch
from conftest import LPIPS_WEIGHTS as WEIGHTS
from conftest import needs_lpips

from codecsplat_warp.errors import DataError, InputError
from codecsplat_warp.metrics import LPIPS
from codecsplat_warp.model import CodecSplat
from codecsplat_warp.model.pretrained import save_pretrained
from codecsplat_warp.model.rdo import rdo_config, refine_latents, rdo_loss, latent_target
from codecsplat_warp.model.rdo.loop import STEP_SCALE_FLOOR, adam_step_scale
from codecsplat_warp.nn.config import get_preset
from train.checkpoint import latest_checkpoint, load_model_weights
from train.data import DataSpec, make_source
from train.semi_amortised import (INNER_LOGGED, SemiAmortisedConfig, build_model, draw_count, inner_count,
                                  lookahead_term, parse_args, run_model_config, semi_amortised_loss, train)
from train.stage1 import METRICS_FILE

TINY = get_preset("tiny")


def _model_file(path) -> CodecSplat:
    torch.manual_seed(5)
    model = CodecSplat(TINY, codec=True)
    save_pretrained(model, path)
    return model


def _batch(seed: int = 3):
    return make_source("procedural", DataSpec(views=(2,), sizes=((32, 48),), targets=1), seed=seed)(0)


def test_the_model_starts_from_the_init_file_with_only_the_named_modules_trainable(tmp_path):
    """Would catch: a start from other weights, or frozen modules that train (or the reverse)."""
    start = _model_file(tmp_path / "m.safetensors")
    config = SemiAmortisedConfig(init=str(tmp_path / "m.safetensors"), out=str(tmp_path / "run"),
                                 train_modules="codec,gs_head")
    assert run_model_config(config) == TINY
    model = build_model(TINY, config)
    for name, value in start.state_dict().items():
        assert torch.equal(model.state_dict()[name], value), name
    assert {n.split(".")[0] for n, p in model.named_parameters() if p.requires_grad} == {"codec", "gs_head"}
    decoder_side = build_model(TINY, SemiAmortisedConfig(init=str(tmp_path / "m.safetensors"),
                                                         out=str(tmp_path / "r1"),
                                                         train_modules="codec.synthesis,gs_head"))
    trained = {n for n, p in decoder_side.named_parameters() if p.requires_grad}
    assert trained and all(n.startswith(("codec.synthesis.", "gs_head.")) for n in trained)
    assert any(n.startswith("codec.synthesis.") for n in trained)
    for bad in ("codec,nothing", "codec.nothing", "codec.synthesis.out.weight", ""):
        with pytest.raises(InputError, match="not a module"):
            build_model(TINY, SemiAmortisedConfig(init=str(tmp_path / "m.safetensors"), out=str(tmp_path / "r2"),
                                                  train_modules=bad))
    (tmp_path / "bad.safetensors").write_bytes(b"not a model")
    with pytest.raises(DataError, match="not a CodecSplat model file"):
        run_model_config(SemiAmortisedConfig(init=str(tmp_path / "bad.safetensors"), out=str(tmp_path / "r3")))


def test_inner_step_counts_are_drawn_reproducibly_from_the_list_and_bad_options_fail():
    """Would catch: a draw that ignores the list or is not a function of (seed, step, rank, scene)."""
    counts = [0, 4, 9]
    drawn = [draw_count(counts, 1, step, 0, 0) for step in range(60)]
    assert set(drawn) == set(counts) and drawn == [draw_count(counts, 1, s, 0, 0) for s in range(60)]
    assert drawn != [draw_count(counts, 2, s, 0, 0) for s in range(60)]
    for argv, match in ((["--inner-steps", "3,-1"], "inner-steps"), (["--inner-steps", "a"], "inner-steps"),
                        (["--inner-preset", "fast"], "inner-preset"), (["--inner-precision", "fp8"], "precision"),
                        (["--encoder-gradient", "both"], "encoder-gradient"), (["--inner-draw", "rank"], "inner-draw"),
                        (["--inner-cuda-graphs", "2"], "inner-cuda-graphs"),
                        (["--lookahead-weight", "-1"], "lookahead-weight"),
                        (["--lookahead-epsilon", "0"], "lookahead-epsilon")):
        with pytest.raises(InputError, match=match):
            parse_args(argv)


def test_inner_draw_step_gives_every_rank_and_scene_of_a_step_one_count():
    """Would catch: ranks that wait on one another's longer inner loops under --inner-draw step, or scenes that all
    share one count under the default."""
    counts = [0, 4, 9, 25, 80]
    per_scene, per_step = SemiAmortisedConfig(seed=3), SemiAmortisedConfig(seed=3, inner_draw="step")
    assert parse_args(["--inner-draw", "step"]).inner_draw == "step" and per_scene.inner_draw == "scene"
    for step in range(20):
        shared = {inner_count(counts, per_step, step, rank, scene) for rank in range(4) for scene in range(2)}
        assert shared == {draw_count(counts, 3, step, 0, 0)}
    differing = [len({inner_count(counts, per_scene, step, rank, 0) for rank in range(4)}) for step in range(20)]
    assert max(differing) > 1


def test_refine_latents_lowers_the_context_loss_and_leaves_the_parameters_without_gradient(tmp_path):
    """The inner loop is the presets' optimisation: its loss falls over the steps, the latents move, and no
    gradient reaches the model's parameters even where they require one (training's case).
    Would catch: an inner loop that accumulates into the weights' gradients (which DDP would all-reduce)."""
    model = _model_file(tmp_path / "m.safetensors").train()
    batch = _batch()
    images, cameras = batch.context_images, batch.context_cameras
    with torch.no_grad():
        latents = model(images, cameras, lam=1024.0)["latents"]
    config = rdo_config("medium", steps=6, views=2, cuda_graphs=False, check_every=0)
    generator = torch.Generator().manual_seed(0)
    result = refine_latents(model, images, cameras, 1024.0, latents, config, generator)
    assert all(p.grad is None for p in model.parameters())
    assert any(not torch.equal(a, b) for a, b in zip(result.latents, latents))
    target = latent_target(model, images, cameras, 1024.0, latents, config)
    with torch.no_grad():
        before = float(rdo_loss(model, [z.clone() for z in latents], target, config,
                                torch.Generator().manual_seed(1))[0])
        after = float(rdo_loss(model, result.latents, target, config, torch.Generator().manual_seed(1))[0])
    assert after < before
    assert float(result.last["mse"]) < float(result.first["mse"])
    assert result.step_scale is None  # asked for by the look-ahead alone
    scaled = refine_latents(model, images, cameras, 1024.0, latents, config, torch.Generator().manual_seed(0),
                            step_scale=True)
    assert [p.shape for p in scaled.step_scale] == [z.shape for z in latents]
    assert all(bool((p > 0).all()) for p in scaled.step_scale)
    unchanged = refine_latents(model, images, cameras, 1024.0, latents, rdo_config("medium", steps=0, views=2))
    assert unchanged.first is None and all(torch.equal(a, b) for a, b in zip(unchanged.latents, latents))


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU visible to torch")
def test_on_cuda_the_inner_loop_replays_the_graphed_decoder_while_the_weights_are_trainable(tmp_path, monkeypatch):
    """Training's inner loop on CUDA takes the presets' CUDA graphs although the model's parameters require
    gradients. Would catch: a capture that fails there and falls back to eager (a warning), graphs that write into
    the weights' gradients, or graphed steps that move the latents elsewhere than the eager steps."""
    from codecsplat_warp.model.rdo import loop

    model = _model_file(tmp_path / "m.safetensors").cuda().train()
    batch = _batch()
    images = batch.context_images.cuda()
    cameras = batch.context_cameras.to(device="cuda", dtype=torch.float32)
    with torch.no_grad():
        latents = model(images, cameras, lam=1024.0)["latents"]
    decoders = []
    capture = loop.step_decoder
    monkeypatch.setattr(loop, "step_decoder", lambda *args: decoders.append(capture(*args)) or decoders[-1])

    def refined(graphs: bool) -> list[torch.Tensor]:
        config = rdo_config("medium", steps=20, views=2, cuda_graphs=graphs, check_every=0)
        generator = torch.Generator(device="cuda").manual_seed(0)
        return refine_latents(model, images, cameras, 1024.0, latents, config, generator).latents

    with warnings.catch_warnings():
        warnings.filterwarnings("error", message="RDO runs without CUDA graphs")
        graphed = refined(True)
    assert decoders[0] is not None and all(p.grad is None for p in model.parameters())
    assert all(p.requires_grad for p in model.parameters())
    eager = refined(False)
    assert decoders[1] is None
    moved = sum(float((e - z).abs().mean()) for e, z in zip(eager, latents))
    apart = sum(float((g - e).abs().mean()) for g, e in zip(graphed, eager))
    assert moved > 0 and apart < 0.05 * moved


def _training_model(tmp_path):
    """The tiny model with the default trained modules, in training mode, LPIPS and one 2-view batch."""
    _model_file(tmp_path / "m.safetensors")
    model = build_model(TINY, SemiAmortisedConfig(init=str(tmp_path / "m.safetensors"), out=str(tmp_path / "run")))
    return model.train(), LPIPS(weights_dir=WEIGHTS), _batch()


def _loss_and_gradients(model, lpips, batch, config: SemiAmortisedConfig) -> tuple[float, dict, dict]:
    """One step's loss (seeded alike for every call), its metrics, and the gradient of every parameter it reached."""
    torch.manual_seed(0)
    model.zero_grad(set_to_none=True)
    loss, metrics = semi_amortised_loss(model, lpips, batch, config, step=4)
    loss.backward()
    gradients = {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}
    return float(loss.detach()), metrics, gradients


@needs_lpips
def test_the_loss_decodes_the_refined_latents_and_its_gradient_reaches_decoder_and_encoder(tmp_path):
    """With K inner steps the loss is taken on the decode of the refined latents (another value than K = 0's
    with the same noise), the gradient reaches the decoder and, first-order, the codec's analysis and
    posterior, and the inner loop's metrics are there. Would catch: a loss on the amortised decode, or a
    straight-through that cuts the encoder off."""
    model, lpips, batch = _training_model(tmp_path)
    losses = {}
    for steps in ("0", "4"):
        losses[steps], metrics, _ = _loss_and_gradients(model, lpips, batch, SemiAmortisedConfig(inner_steps=steps))
        assert set(INNER_LOGGED) <= set(metrics)
        for part in ("codec.analysis", "codec.top_down", "codec.synthesis", "depth_head", "refine_post"):
            reached = [p.grad for n, p in model.named_parameters() if n.startswith(part) and p.grad is not None]
            assert reached and any(float(g.abs().sum()) > 0 for g in reached), (steps, part)
    assert metrics["inner_steps"] == 4.0 and float(metrics["context_gain"]) > 0
    assert losses["4"] != pytest.approx(losses["0"], rel=1e-6)


@needs_lpips
def test_with_the_encoder_gradient_amortised_only_the_decoder_learns_from_refined_latents(tmp_path):
    """``--encoder-gradient amortised``: with K inner steps the loss is the same as the straight-through one, the
    decoder's gradient is the same, and the encoder (the codec's analysis) gets exactly zero, while every trained
    parameter stays in the graph (DDP). Would catch: an encoder still pushed towards the refined latents, or a
    loss of another decode."""
    model, lpips, batch = _training_model(tmp_path)
    runs = {mode: _loss_and_gradients(model, lpips, batch, SemiAmortisedConfig(inner_steps="3", encoder_gradient=mode))
            for mode in ("refined", "amortised")}
    (refined_loss, _, refined), (amortised_loss, _, amortised) = runs["refined"], runs["amortised"]
    assert amortised_loss == pytest.approx(refined_loss, rel=1e-6)
    assert set(amortised) == {n for n, p in model.named_parameters() if p.requires_grad}
    analysis = [n for n in amortised if n.startswith("codec.analysis")]
    assert analysis and all(float(amortised[n].abs().sum()) == 0 for n in analysis)
    assert any(float(refined[n].abs().sum()) > 0 for n in analysis)
    for n in (n for n in amortised if n.startswith(("codec.synthesis", "depth_head"))):
        torch.testing.assert_close(amortised[n], refined[n], rtol=1e-4, atol=1e-7)


@needs_lpips
def test_a_resumed_run_gives_the_same_next_step_loss_and_logs_the_inner_loop(tmp_path):
    """Checkpoints carry the run across interruptions: two steps, resumed to three, match three straight.
    Would catch: an inner loop drawn from state that a checkpoint does not carry."""
    start = _model_file(tmp_path / "m.safetensors")
    common = dict(init=str(tmp_path / "m.safetensors"), data="procedural", device="cpu", workers=0,
                  warmup_steps=10, lpips_weights=str(WEIGHTS), checkpoint_every=2, log_every=1, seed=3,
                  coded_every=100, inner_steps="0,2")
    train(SemiAmortisedConfig(out=str(tmp_path / "a"), steps=2, **common), progress=False)
    resumed = train(SemiAmortisedConfig(out=str(tmp_path / "a"), steps=3, **common), progress=False)
    direct = train(SemiAmortisedConfig(out=str(tmp_path / "b"), steps=3, **common), progress=False)
    assert (resumed["resumed_from"], resumed["step"]) == (2, 3)
    assert resumed["loss"] == pytest.approx(direct["loss"], rel=1e-5)
    records = [json.loads(line) for line in (tmp_path / "a" / METRICS_FILE).read_text().splitlines()]
    assert [r["step"] for r in records] == [1, 2, 3]
    assert all(set(INNER_LOGGED) <= set(r) for r in records)
    trained = CodecSplat(TINY, codec=True)
    load_model_weights(latest_checkpoint(tmp_path / "a"), trained)
    for name, value in start.state_dict().items():
        if name.split(".")[0] not in ("codec", "depth_head", "refine_post"):
            assert torch.equal(trained.state_dict()[name], value), f"frozen {name} changed"


def test_adam_step_scale_is_the_steps_derivative_by_the_gradient_with_a_floor_where_moments_are_tiny():
    """Would catch: a scale without Adam's bias correction or (1 - beta1), or one unbounded where a latent's
    gradient has stayed near zero (there it would dwarf every other direction)."""
    torch.manual_seed(0)
    variable = torch.randn(200, requires_grad=True)
    optimiser = torch.optim.Adam([variable], lr=0.1)
    weights = torch.linspace(0.0, 2.0, 200)
    for _ in range(3):
        optimiser.zero_grad()
        (weights * variable).sum().backward()
        optimiser.step()
    scale = adam_step_scale(optimiser, [variable])[0]
    root = (optimiser.state[variable]["exp_avg_sq"] / (1 - 0.999**3)).sqrt()
    floor = STEP_SCALE_FLOOR * root.mean()
    assert torch.allclose(root, weights, rtol=1e-5)
    above = root > floor
    torch.testing.assert_close(scale[above], 0.1 / root[above])
    torch.testing.assert_close(scale[~above], torch.full_like(scale[~above], float(0.1 / floor)))
    assert bool((~above).any()) and float(scale.max()) <= float(0.1 / floor) * (1 + 1e-6)


@needs_lpips
def test_the_lookahead_term_is_the_context_losss_slope_along_the_preconditioned_target_gradient(tmp_path):
    """The look-ahead's central difference is the directional derivative of the presets' context loss (autograd's
    straight-through one, at the same noise) along ``u = P grad L_t``, its value is ``-w rms(u)`` times it, its
    gradient reaches the decoder, and it is zero without inner steps. Would catch: a wrong sign or scale, noise or
    rounding that differs between the two evaluations (the difference would be noise, or jumps of whole
    quantisation steps), or a term whose gradient never reaches the weights."""
    model, _, batch = _training_model(tmp_path)
    config = SemiAmortisedConfig(inner_steps="3", lookahead_weight=2.0, lookahead_epsilon=0.03)
    with torch.no_grad():
        latents = model(batch.context_images, batch.context_cameras, lam=512.0)["latents"]
    rdo = rdo_config("medium", steps=1, views=2, cuda_graphs=False, check_every=0)
    target = latent_target(model, batch.context_images, batch.context_cameras, 512.0, latents, rdo)
    moved = [z.clone().requires_grad_(True) for z in latents]
    loss, _ = rdo_loss(model, moved, target, rdo, torch.Generator().manual_seed((config.seed * 1_000_003 + 2) * 101 + 1))
    context_gradient = torch.autograd.grad(loss, moved)
    torch.manual_seed(1)
    # u: half the context loss's own gradient, half noise (a direction where the slope stands above the
    # rasterizer's small discontinuities, as a target gradient that a context step helps does)
    rms = torch.cat([g.flatten() for g in context_gradient]).square().mean().sqrt()
    u = [g / rms + torch.randn_like(g) for g in context_gradient]
    scales = [[torch.rand_like(z) + 0.5 for z in latents]]
    target_gradients = tuple(d / p for d, p in zip(u, scales[0]))
    term, slope = lookahead_term(model, batch, 512.0, latents, target_gradients, scales, config, step=2)
    size = torch.cat([d.flatten() for d in u]).square().mean().sqrt()
    derivative = sum(float((g * d / size).sum()) for g, d in zip(context_gradient, u))
    assert derivative > 0 and float(slope) == pytest.approx(derivative, rel=0.1)
    assert float(term) == pytest.approx(-2.0 * float(size) * float(slope), rel=1e-5)
    model.zero_grad(set_to_none=True)
    term.backward()
    reached = [p.grad for n, p in model.named_parameters() if n.startswith("codec.synthesis") and p.grad is not None]
    assert reached and any(float(g.abs().sum()) > 0 for g in reached)
    none, _ = lookahead_term(model, batch, 512.0, latents, target_gradients, [None], config, step=2)
    assert float(none) == 0.0


@needs_lpips
def test_with_the_lookahead_the_loss_gradient_changes_only_where_inner_steps_ran(tmp_path):
    """Would catch: a look-ahead that is never added, or one that changes the K = 0 draws (fast's objective)."""
    model, lpips, batch = _training_model(tmp_path)
    for steps, changes in (("0", False), ("3", True)):
        plain = _loss_and_gradients(model, lpips, batch, SemiAmortisedConfig(inner_steps=steps))
        ahead = _loss_and_gradients(model, lpips, batch, SemiAmortisedConfig(inner_steps=steps, lookahead_weight=5.0))
        differ = any(not torch.allclose(plain[2][n], ahead[2][n], rtol=1e-4, atol=1e-8) for n in plain[2])
        assert differ == changes, steps
        assert (float(ahead[1]["lookahead_alignment"]) != 0.0) == changes
