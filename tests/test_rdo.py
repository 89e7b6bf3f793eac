"""Encoder-side rate-distortion optimisation (codecsplat_warp.model.rdo) on the tiny preset: the optimised bitstream
decodes with the unchanged decoder, the measured loss never ends above the amortised one, the coded latents follow
the optimised ones, seeds repeat a run, budgets and interruptions keep the best, bad arguments fail at once."""

from __future__ import annotations

import gc
import math
import warnings

import pytest
import torch
from conftest import LPIPS_WEIGHTS, needs_lpips, tiny_coding_model

from codecsplat_warp.checks import validation
from codecsplat_warp.codec import parse_bitstream
from codecsplat_warp.data.procedural import ProceduralConfig, procedural_scene
from codecsplat_warp.errors import InputError
from codecsplat_warp.metrics.lpips import LPIPS
from codecsplat_warp.model import rdo
from codecsplat_warp.model.codecsplat import model_id

LAM = 1024.0


def _scene(seed: int = 3):
    s = procedural_scene(seed, ProceduralConfig(width=48, height=32, num_views=2, texture_size=16))
    return s.images.float() / 255.0, s.cameras.to(dtype=torch.float32)


@pytest.fixture(scope="module")
def optimised():
    model = tiny_coding_model(0)
    images, cameras = _scene()
    amortised = model.encode_scene(images, cameras, LAM)
    encoded = model.encode_scene(images, cameras, LAM, steps=12, seed=1)
    return model, images, cameras, amortised, encoded


def _context_mse(model, data: bytes, images, cameras) -> float:
    with torch.no_grad():
        rgb = model.render(model.decode(data), cameras)["rgb"]
    return float((rgb - images).square().mean())


def test_the_optimised_bitstream_decodes_with_the_unchanged_decoder_and_fits_the_context_better(optimised):
    model, images, cameras, amortised, encoded = optimised
    result = encoded.rdo
    assert result.steps == 12 and result.stopped == "steps" and result.best_step > 0, result.to_dict()
    assert parse_bitstream(encoded.data).header.model_id == model_id(model)
    scene = model.decode_scene(encoded.data)
    for coded, decoded in zip(encoded.latents, scene.latents):
        assert torch.equal(coded, decoded.cpu())
    assert encoded.data != amortised.data
    # the measured loss of the kept latents is below the amortised latents' (step 0 of the checks)
    checks = {c.step: c for c in result.checks}
    assert checks[result.best_step].loss < checks[0].loss
    assert _context_mse(model, encoded.data, images, cameras) < _context_mse(model, amortised.data, images, cameras)


def test_the_amortised_check_measures_the_amortised_bitstream(optimised):
    model, images, cameras, amortised, encoded = optimised
    first = encoded.rdo.checks[0]
    assert first.step == 0
    assert first.bits == pytest.approx(float(amortised.estimated_bits.sum()), rel=1e-9)
    expected = -10 * math.log10(_context_mse(model, amortised.data, images, cameras))
    assert first.psnr == pytest.approx(expected, abs=1e-3)


def test_a_seed_repeats_a_run_on_the_cpu(optimised):
    model, images, cameras, _, encoded = optimised
    again = model.encode_scene(images, cameras, LAM, steps=12, seed=1)
    assert again.data == encoded.data


def test_the_fast_preset_and_zero_steps_are_the_amortised_encoder(optimised):
    model, images, cameras, amortised, _ = optimised
    assert model.encode(images, cameras, LAM, preset="fast") == amortised.data
    assert model.encode(images, cameras, LAM, preset="slow", steps=0) == amortised.data
    assert amortised.rdo is None


class SteppingClock:
    """A stand-in for the ``time`` module whose ``perf_counter`` advances 0.05 s at every reading: a run's seconds
    are counted in readings, whatever the machine's load."""

    def __init__(self):
        self.now = 0.0

    def perf_counter(self) -> float:
        self.now += 0.05
        return self.now


def test_a_time_budget_alone_ends_the_run(monkeypatch):
    """Catches: a budget that does not end the run, or that ends it before any step. The loop's clock is scripted
    (a loaded machine once spent the whole 0.5 s before the first step)."""
    model = tiny_coding_model(1)
    images, cameras = _scene(5)
    monkeypatch.setattr(rdo.loop, "time", SteppingClock())
    encoded = model.encode_scene(images, cameras, 256.0, time_budget=0.5)
    assert encoded.rdo.stopped == "time" and encoded.rdo.steps >= 1
    model.decode(encoded.data)


def test_a_keyboard_interrupt_keeps_the_best_latents_so_far(monkeypatch):
    model = tiny_coding_model(2)
    images, cameras = _scene(7)
    calls = {"n": 0}
    real_loss = rdo.rdo_loss

    def interrupting(*args, **kwargs):
        if kwargs.get("compressed") is None:
            calls["n"] += 1
            if calls["n"] == 4:
                raise KeyboardInterrupt
        return real_loss(*args, **kwargs)

    monkeypatch.setattr(rdo.loop, "rdo_loss", interrupting)  # where the loop looks it up
    encoded = model.encode_scene(images, cameras, LAM, steps=50)
    assert encoded.rdo.stopped == "interrupted" and encoded.rdo.steps == 3
    assert [c.step for c in encoded.rdo.checks] == [0, 3]
    model.decode(encoded.data)


def test_non_finite_gradients_leave_the_latents_finite_and_the_bitstream_decodable(monkeypatch):
    model = tiny_coding_model(3)
    images, cameras = _scene(9)
    real_loss = rdo.rdo_loss

    def poisoned(model_, latents, *args, **kwargs):
        loss, parts = real_loss(model_, latents, *args, **kwargs)
        if kwargs.get("compressed") is None:
            loss = loss + (latents[0] * float("nan")).sum()
        return loss, parts

    monkeypatch.setattr(rdo.loop, "rdo_loss", poisoned)
    encoded = model.encode_scene(images, cameras, LAM, steps=4)
    assert encoded.rdo.steps == 4 and all(math.isfinite(c.loss) for c in encoded.rdo.checks)
    model.decode(encoded.data)


def test_runaway_latents_are_clamped_inside_the_coders_range():
    model = tiny_coding_model(4)
    images, cameras = _scene(11)
    start = model.codec.compress(model(images, cameras)["F_c"].detach(), LAM, reconstruct=True)
    start.latents = [torch.full_like(z, 1e12) for z in start.latents]  # past the escape range: uncodable as they are
    config = rdo.RDOConfig(steps=1, learning_rate=1e-3, check_every=0)
    with torch.enable_grad():
        result = rdo.optimise_latents(model, images, cameras, LAM, start, config)
    # the step-1 check coded the clamped latents (coding the start's raises InputError)
    assert [c.step for c in result.checks] == [0, 1] and math.isfinite(result.checks[1].loss)
    with pytest.raises(InputError, match="huge"):
        model.codec.compress_latents(start.latents, LAM, 16, 24)


@pytest.mark.parametrize("kwargs, match", [
    ({"steps": -1}, "steps"), ({"steps": 2.5}, "steps"), ({"time_budget": 0.0}, "budget"),
    ({"time_budget": -3.0}, "budget"), ({"time_budget": float("nan")}, "budget"), ({"preset": "fastest"}, "preset"),
])
def test_bad_arguments_get_a_typed_error_at_once(kwargs, match):
    model = tiny_coding_model(0)
    images, cameras = _scene()
    with pytest.raises(InputError, match=match):
        model.encode_scene(images, cameras, LAM, **kwargs)


def test_preset_configs():
    assert not rdo.rdo_config("fast").optimises
    assert rdo.rdo_config("medium", views=2).steps == rdo.preset_steps("medium", 2) == 25
    assert rdo.rdo_config("slow", views=8).steps == rdo.preset_steps("slow", 8) == 320
    assert rdo.preset_steps("slow", 1) == 5 and rdo.preset_steps("medium", 3) == 11
    assert rdo.preset_steps("medium", 8) * 4 == rdo.preset_steps("slow", 8) == 320, "a quarter of slow's steps"
    assert rdo.preset_steps("slow", 2) == 160, "with the cross-view term 2 views gain to 160 steps"
    assert rdo.rdo_config("fast", time_budget=3.0).steps is None
    assert rdo.rdo_config("slow", time_budget=3.0, views=2).steps == rdo.preset_steps("slow", 2)
    assert rdo.rdo_config("slow", steps=7).steps == 7


def test_the_cross_view_term_is_tuned_by_view_count_and_can_be_overridden():
    assert rdo.rdo_config("slow", views=2).cross_view_weight == 0.5
    assert rdo.rdo_config("fast", steps=7, views=2).cross_view_weight == 0.5, "explicit steps get the tuned loss too"
    assert rdo.rdo_config("slow", views=8).cross_view_weight == 0.0
    assert rdo.rdo_config("slow", views=1).cross_view_weight == 0.0
    assert rdo.rdo_config("slow", views=2, cross_view_weight=0.0).cross_view_weight == 0.0


def _cross_error(colour: torch.Tensor, alpha: torch.Tensor, images: torch.Tensor) -> float:
    """The cross-view error of renders of colour ``colour`` [V,3,H,W] at coverage ``alpha`` [V,H,W]."""
    return float(rdo.cross_view_error(colour * alpha[:, None], alpha, images))


def test_the_cross_view_error_is_the_covered_colour_error_and_transparency_does_not_lower_it():
    images, _ = _scene(5)
    gen = torch.Generator().manual_seed(0)
    colour = torch.rand(images.shape, generator=gen)
    alpha = 0.2 + 0.7 * torch.rand(images[:, 0].shape, generator=gen)
    error = _cross_error(colour, alpha, images)
    expected = torch.stack([(alpha[v] * (colour[v] - images[v]).square()).sum() / (3 * alpha[v].sum())
                            for v in range(2)]).mean()
    assert error == pytest.approx(float(expected), rel=1e-5)
    assert _cross_error(colour, alpha * 0.25, images) == pytest.approx(error, rel=1e-5), \
        "fainter Gaussians of the same colour must not predict the view better"
    assert _cross_error(images, alpha, images) == pytest.approx(0.0, abs=1e-10)


def test_the_cross_view_renders_come_from_the_other_views_gaussians_in_the_same_call(monkeypatch):
    model = tiny_coding_model(5)
    images, cameras = _scene(13)
    start = model.codec.compress(model(images, cameras)["F_c"].detach(), LAM, reconstruct=True)
    config = rdo.RDOConfig(steps=1, cross_view_weight=1.0)
    target = rdo.rdo_target(model, images, cameras, LAM, start, config)
    with torch.no_grad():
        gaussians = model.decode_feature(start.feature, cameras)[2]
        whole = model.render(gaussians, cameras, depth_range=target.depth_range)["rgb"]
        pieces = gaussians.split(2)
        others = [model.render(pieces[1 - v], cameras.select([v]), depth_range=target.depth_range) for v in range(2)]
        calls = []
        render = model.render
        monkeypatch.setattr(model, "render", lambda *a, **k: calls.append(1) or render(*a, **k))
        rgb, alpha = rdo.render_context_views(model, gaussians, target, cross_views=True)
    assert len(calls) == 1
    assert (rgb[:2] - whole).abs().max() < 1e-5
    assert (rgb[2:] - torch.cat([o["rgb"] for o in others])).abs().max() < 1e-5
    assert (alpha[2:] - torch.cat([o["alpha"] for o in others])).abs().max() < 1e-5
    assert float(alpha[2:].mean()) > 0.05, "the other view must cover some of each view"


def test_the_optional_terms_enter_the_loss_only_when_weighted():
    model = tiny_coding_model(5)
    images, cameras = _scene(13)
    start = model.codec.compress(model(images, cameras)["F_c"].detach(), LAM, reconstruct=True)
    plain = rdo.RDOConfig(steps=1)
    weighted = rdo.RDOConfig(steps=1, cross_view_weight=1.0, depth_weight=0.5, anchor_weight=0.1)
    with torch.no_grad():
        latents = [z + 0.5 for z in start.latents]
        base, parts = rdo.rdo_loss(model, latents, rdo.rdo_target(model, images, cameras, LAM, start, plain), plain,
                                   torch.Generator().manual_seed(0))
        more, extra = rdo.rdo_loss(model, latents, rdo.rdo_target(model, images, cameras, LAM, start, weighted),
                                   weighted, torch.Generator().manual_seed(0))
    assert set(parts) == {"mse", "bpp"} and {"cross", "depth", "anchor"} <= set(extra)
    assert float(extra["anchor"]) == pytest.approx(0.25) and float(extra["cross"]) > 0
    expected = base + LAM / 1024 * (extra["cross"] + 0.5 * extra["depth"]) + 0.1 * extra["anchor"]
    assert float(more) == pytest.approx(float(expected), rel=1e-5)


def test_a_cpu_run_has_the_heads_channels_last_and_gives_their_weights_back():
    model = tiny_coding_model(0)
    images, cameras = _scene()
    weight = next(t for t in model.gs_head.parameters() if t.dim() == 4 and t.shape[1] > 1 and t.shape[2] > 1)
    assert not weight.is_contiguous(memory_format=torch.channels_last)
    before = [(name, t.data_ptr(), t.stride()) for name, t in model.state_dict(keep_vars=True).items()]
    layouts = []

    def on_check(check, compressed):
        layouts.append(weight.is_contiguous(memory_format=torch.channels_last))
        assert all(t.is_contiguous() for t in model.codec.parameters()), "the codec keeps its layout"

    model.encode_scene(images, cameras, LAM, steps=3, seed=1, rdo_settings={"check_every": 1}, on_check=on_check)
    assert layouts and all(layouts), "channels-last during the run"
    assert [(name, t.data_ptr(), t.stride()) for name, t in model.state_dict(keep_vars=True).items()] == before
    start = _start(model, images, cameras)
    config = rdo.RDOConfig(steps=1)
    target = rdo.rdo_target(model, images, cameras, LAM, start, config)
    with torch.no_grad():
        plain = rdo.rdo_loss(model, start.latents, target, config, torch.Generator().manual_seed(0))[0]
        originals = rdo.heads_channels_last(model, torch.device("cpu"))
        try:
            last = rdo.rdo_loss(model, start.latents, target, config, torch.Generator().manual_seed(0))[0]
        finally:
            rdo.restore_weights(originals)
    assert originals and float(last) == pytest.approx(float(plain), rel=1e-5), "the same loss in either layout"
    assert rdo.heads_channels_last(model, torch.device("cuda")) == [], "nothing changes on CUDA"


@pytest.mark.parametrize("before", [False, True])
def test_a_cuda_run_searches_cudnns_algorithms_and_gives_the_flag_back(before, monkeypatch):
    monkeypatch.setattr(torch.backends.cudnn, "benchmark", before)
    model = tiny_coding_model(0)
    inside = []
    with pytest.raises(KeyboardInterrupt), rdo.decoder_fixed(model, torch.device("cuda")):
        inside.append(torch.backends.cudnn.benchmark)
        raise KeyboardInterrupt
    assert inside == [True], "cuDNN's algorithm search is on during a CUDA run"
    assert torch.backends.cudnn.benchmark is before, "and the flag is given back, however the run ends"
    with rdo.decoder_fixed(model, torch.device("cpu")):
        assert torch.backends.cudnn.benchmark is before, "the CPU leaves cuDNN's flag alone"


def _start(model, images, cameras):
    with torch.no_grad():
        return model.codec.compress(model(images, cameras)["F_c"], LAM, reconstruct=True)


def test_noise_given_to_the_quantiser_is_the_noise_it_would_draw():
    model = tiny_coding_model(5)
    images, cameras = _scene(13)
    start = _start(model, images, cameras)
    target = rdo.rdo_target(model, images, cameras, LAM, start, rdo.RDOConfig(steps=1))
    model.train()
    with torch.no_grad():
        drawn = rdo.decode_variables(model, start.latents, target, "latents", torch.Generator().manual_seed(4))
        generator = torch.Generator().manual_seed(4)
        noise = [torch.rand(z.shape, generator=generator) for z in start.latents]
        given = rdo.decode_variables(model, start.latents, target, "latents", noise=noise,
                                     lambda_embedding=model.codec.embedding(LAM))
        other = rdo.decode_variables(model, start.latents, target, "latents", torch.Generator().manual_seed(5))
    assert torch.equal(drawn[0], given[0]) and torch.equal(drawn[1], given[1])
    assert torch.equal(drawn[2].means, given[2].means) and torch.equal(drawn[2].sh, given[2].sh)
    assert not torch.equal(drawn[0], other[0])  # the noise reaches the rate


def test_the_cpu_runs_the_eager_decoder():
    model = tiny_coding_model(5)
    images, cameras = _scene(13)
    start = _start(model, images, cameras)
    config = rdo.RDOConfig(steps=1, cuda_graphs=True)
    target = rdo.rdo_target(model, images, cameras, LAM, start, config)
    assert rdo.step_decoder(model, target, start.latents, config) is None
    cuda = torch.device("cuda")
    assert not rdo.uses_cuda_graphs(config, torch.device("cpu"))
    assert rdo.uses_cuda_graphs(rdo.RDOConfig(steps=rdo.GRAPH_MIN_STEPS), cuda)
    assert rdo.uses_cuda_graphs(rdo.RDOConfig(steps=None, time_budget=5.0), cuda)
    assert not rdo.uses_cuda_graphs(rdo.RDOConfig(steps=rdo.GRAPH_MIN_STEPS - 1), cuda)  # capture would not pay
    assert not rdo.uses_cuda_graphs(rdo.RDOConfig(steps=100, cuda_graphs=False), cuda)
    assert rdo.uses_cuda_graphs(rdo.RDOConfig(steps=100, precision="bfloat16"), cuda)  # captured under autocast


def test_bfloat16_runs_the_networks_under_autocast_on_the_cpu_with_the_float32_gradient_direction():
    model = tiny_coding_model(5)
    images, cameras = _scene(13)
    start = _start(model, images, cameras)
    model.train()
    results = {}
    for precision in ("float32", "bfloat16"):
        config = rdo.RDOConfig(steps=1, precision=precision)
        target = rdo.rdo_target(model, images, cameras, LAM, start, config)
        latents = [z.clone().requires_grad_(True) for z in start.latents]
        loss, _ = rdo.rdo_loss(model, latents, target, config, torch.Generator().manual_seed(4))
        grads = torch.autograd.grad(loss, latents)
        results[precision] = loss.detach(), torch.cat([g.flatten() for g in grads])
    (loss32, grad32), (loss16, grad16) = results["float32"], results["bfloat16"]
    assert float(loss16) != float(loss32), "bf16 autocast reached the networks"
    assert float(loss16) == pytest.approx(float(loss32), rel=0.05)
    assert float(torch.nn.functional.cosine_similarity(grad16, grad32, dim=0)) >= 0.98


def test_optimising_the_feature_gives_a_decodable_bitstream_that_fits_the_context_better():
    model = tiny_coding_model(0)
    images, cameras = _scene()
    amortised = model.encode_scene(images, cameras, LAM)
    encoded = model.encode_scene(images, cameras, LAM, steps=12, seed=1,
                                 rdo_settings={"variable": "feature", "feature_step": 0.05})
    result = encoded.rdo
    assert result.steps == 12 and result.best_step > 0, result.to_dict()
    checks = {c.step: c for c in result.checks}
    assert checks[result.best_step].loss < checks[0].loss
    assert _context_mse(model, encoded.data, images, cameras) < _context_mse(model, amortised.data, images, cameras)


def test_annealed_rounding_stays_between_the_neighbours_and_becomes_rounding_when_cold():
    from codecsplat_warp.codec.latent import annealed_rounding

    residual = (torch.rand(4000, dtype=torch.float32) - 0.5) * 20
    uniform = torch.rand(4000)
    away = (residual - residual.floor() - 0.5).abs() > 0.1
    for temperature in (0.5, 0.2, 0.05):
        out = annealed_rounding(residual, uniform, torch.tensor(temperature))
        assert bool(((out >= residual.floor()) & (out <= residual.floor() + 1)).all())
    cold = annealed_rounding(residual, uniform, torch.tensor(0.02))
    torch.testing.assert_close(cold[away], torch.round(residual)[away], atol=1e-3, rtol=0)
    warm = annealed_rounding(residual, uniform, torch.tensor(0.5))
    assert float((warm - torch.round(residual)).abs().mean()) > 0.05  # soft while warm
    leaf = residual.clone().requires_grad_(True)
    annealed_rounding(leaf, uniform, torch.tensor(0.5)).sum().backward()
    assert bool(torch.isfinite(leaf.grad).all()) and float(leaf.grad.abs().sum()) > 0


def test_annealed_rounding_gives_a_decodable_bitstream_that_fits_the_context_better():
    model = tiny_coding_model(0)
    images, cameras = _scene()
    amortised = model.encode_scene(images, cameras, LAM)
    encoded = model.encode_scene(images, cameras, LAM, steps=12, seed=1, rdo_settings={"rounding": "annealed"})
    checks = {c.step: c for c in encoded.rdo.checks}
    assert encoded.rdo.best_step > 0 and checks[encoded.rdo.best_step].loss < checks[0].loss
    assert _context_mse(model, encoded.data, images, cameras) < _context_mse(model, amortised.data, images, cameras)
    assert rdo.annealing_temperature(rdo.RDOConfig(steps=10, rounding="annealed"), 0, 0.0) == pytest.approx(0.5)
    assert rdo.annealing_temperature(rdo.RDOConfig(steps=10, rounding="annealed"), 10, 0.0) == pytest.approx(0.05)
    assert rdo.annealing_temperature(rdo.RDOConfig(steps=10), 5, 0.0) is None
    with pytest.raises(InputError, match="rounding"):
        rdo.RDOConfig(steps=2, rounding="gumbel")


def test_the_feature_variable_needs_the_feature_and_no_latent_anchor():
    model = tiny_coding_model(0)
    images, cameras = _scene()
    start = _start(model, images, cameras)
    config = rdo.RDOConfig(steps=2, variable="feature")
    with pytest.raises(InputError, match="feature="):
        rdo.optimise_latents(model, images, cameras, LAM, start, config)
    with pytest.raises(InputError, match="anchor_weight"):
        rdo.RDOConfig(steps=2, variable="feature", anchor_weight=0.1)
    with pytest.raises(InputError, match="variable"):
        rdo.RDOConfig(steps=2, variable="weights")


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU visible to torch")
@pytest.mark.parametrize("variable, rounding, precision", [
    ("latents", "noise", "float32"), ("feature", "noise", "float32"), ("latents", "annealed", "float32"),
    ("latents", "noise", "bfloat16")])
def test_the_graphed_decoder_gives_the_eager_loss_and_gradients(variable, rounding, precision):
    model = tiny_coding_model(5).cuda()
    images, cameras = _scene(13)
    images, cameras = images.cuda(), cameras.to(device="cuda")
    with torch.no_grad():
        feature = model(images, cameras)["F_c"]
    start = model.codec.compress(feature, LAM, reconstruct=True)
    config = rdo.RDOConfig(steps=rdo.GRAPH_MIN_STEPS, variable=variable, rounding=rounding, precision=precision)
    target = rdo.rdo_target(model, images, cameras, LAM, start, config)
    model.requires_grad_(False)
    model.train()
    latents = rdo.start_variables(start, config, feature)
    with validation(False):
        # raises here when the capture fails
        decoder = rdo.GraphedDecoder(model, target, latents, variable, rounding == "annealed", precision)
    assert isinstance(rdo.step_decoder(model, target, latents, config), rdo.GraphedDecoder)
    for trial in range(3):  # replays with new latents, new noise and (annealed) a new temperature
        temperature = rdo.annealing_temperature(config, trial, 0.0)
        (eager, eager_grads), (graphed, graphed_grads) = [
            _loss_and_gradients(model, latents, target, config, trial, d, temperature) for d in (None, decoder)]
        if precision == "float32":
            assert float(graphed) == pytest.approx(float(eager), rel=1e-4)
            for a, b in zip(eager_grads, graphed_grads):
                assert float((a - b).norm()) <= 1e-3 * float(a.norm()) + 1e-9
        else:  # bf16 rounds each run differently (atomics in float32 feed bf16 convolutions): same direction
            assert float(graphed) == pytest.approx(float(eager), rel=1e-2)
            for a, b in zip(eager_grads, graphed_grads):
                assert float(torch.nn.functional.cosine_similarity(a.flatten(), b.flatten(), dim=0)) >= 0.98
        with torch.no_grad():
            for z in latents:
                z.add_(torch.randn_like(z))


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU visible to torch")
@pytest.mark.parametrize("cross_view_weight", [0.0, 0.5])
def test_the_graphed_context_loss_gives_the_eager_loss_and_gradients(cross_view_weight):
    torch.manual_seed(4)
    images = torch.rand(2, 3, 24, 40, device="cuda")
    config = rdo.RDOConfig(steps=rdo.GRAPH_MIN_STEPS, cross_view_weight=cross_view_weight)
    eager = rdo.context_loss(images, LAM, config, graphed=False)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        graphed = rdo.context_loss(images, LAM, config, graphed=True)
    # neither the fallback to eager nor torch's warning about the sample's accumulators (ACCUMULATE_GRAD_STREAM_WARNING)
    assert [str(w.message) for w in caught] == []
    assert "forward" in vars(graphed) and "forward" not in vars(eager)  # the graphs replace the module's forward
    views = 4 if cross_view_weight else 2
    for trial in range(3):  # replays with new renders, strided like the rasterizer's, and new bits
        inputs = [torch.rand(views, 24, 40, 3, device="cuda").permute(0, 3, 1, 2).requires_grad_(True),
                  torch.rand((), device="cuda").mul(1e4).requires_grad_(True)]
        if cross_view_weight:
            inputs.append(torch.rand(views, 24, 40, device="cuda").requires_grad_(True))
        results = []
        for loss in (eager, graphed):
            value, parts = loss(*inputs)
            results.append((float(value), parts.detach().clone(), torch.autograd.grad(value, inputs)))
        (a, a_parts, a_grads), (b, b_parts, b_grads) = results
        assert b == pytest.approx(a, rel=1e-6)
        assert torch.allclose(a_parts, b_parts, rtol=1e-6)
        assert (float(a_parts[1]) > 0) == bool(cross_view_weight)
        for x, y in zip(a_grads, b_grads):
            assert float((x - y).norm()) <= 1e-6 * float(x.norm())


def test_the_loss_needs_the_target_made_for_its_weights():
    model = tiny_coding_model(5)
    images, cameras = _scene(13)
    start = model.codec.compress(model(images, cameras)["F_c"].detach(), LAM, reconstruct=True)
    target = rdo.rdo_target(model, images, cameras, LAM, start, rdo.RDOConfig(steps=1, cross_view_weight=0.5))
    with pytest.raises(InputError, match="same cross-view and rate weights"):
        rdo.rdo_loss(model, [z.clone() for z in start.latents], target, rdo.RDOConfig(steps=1, cross_view_weight=1.0))


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU visible to torch")
@needs_lpips
def test_the_graphed_perceptual_distance_gives_the_eager_distance_and_gradient(monkeypatch):
    # TF32 convolutions alone move the gradient by ~3 % between any two algorithm choices; in float32 the graphs
    # and the eager network agree to ~1e-6
    monkeypatch.setattr(torch.backends.cudnn, "allow_tf32", False)
    network = LPIPS("vgg", LPIPS_WEIGHTS).cuda()
    torch.manual_seed(3)
    images = torch.rand(2, 3, 64, 96, device="cuda")
    target_units = network.unit_features(images)
    eager = rdo.perceptual_distance(network, target_units, images, graphed=False)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        graphed = rdo.perceptual_distance(network, target_units, images, graphed=True)
    assert [str(w.message) for w in caught] == []  # neither the fallback to eager nor torch's about accumulators
    assert "forward" in vars(graphed) and "forward" not in vars(eager)  # the graphs replace the module's forward
    for trial in range(3):  # replays with new renders, strided like the rasterizer's
        renders = torch.rand(2, 64, 96, 3, device="cuda").permute(0, 3, 1, 2).requires_grad_(True)
        values, grads = [], []
        for distance in (eager, graphed):
            value = distance(renders)
            values.append(float(value.detach()))
            grads.append(torch.autograd.grad(value, renders)[0].clone())
        assert values[1] == pytest.approx(values[0], rel=1e-5)
        assert float((grads[1] - grads[0]).norm()) <= 1e-4 * float(grads[0].norm())
    with torch.no_grad():  # a real coding's measure: no gradient
        assert float(graphed(images)) == pytest.approx(float(eager(images)), abs=1e-6)


def _graphed_run_inputs(seed: int = 5):
    """A tiny model on CUDA, frozen in training mode, with a run's target, config and start latents."""
    model = tiny_coding_model(seed).cuda()
    images, cameras = _scene(13)
    images, cameras = images.cuda(), cameras.to(device="cuda")
    with torch.no_grad():
        feature = model(images, cameras)["F_c"]
    start = model.codec.compress(feature, LAM, reconstruct=True)
    config = rdo.RDOConfig(steps=rdo.GRAPH_MIN_STEPS)
    target = rdo.rdo_target(model, images, cameras, LAM, start, config)
    model.requires_grad_(False)
    model.train()
    return model, target, config, rdo.start_variables(start, config)


def _on_the_captured_call(monkeypatch, action):
    """Make the graphed decoder's capture (its first decode after the warm-up) run ``action`` first."""
    calls = []

    def decode(*args, **kwargs):
        calls.append(None)
        if len(calls) == rdo.GraphedDecoder.WARMUP + 1:
            action()
        return decode_variables(*args, **kwargs)

    decode_variables = rdo.graphs.decode_variables
    monkeypatch.setattr(rdo.graphs, "decode_variables", decode)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU visible to torch")
def test_a_capture_survives_an_earlier_graph_that_the_garbage_collector_frees(monkeypatch):
    """An earlier run's CUDA graph that only the cyclic garbage collector can free (a reference cycle), with the
    collector due during the capture: the capture still succeeds, without a fallback warning.

    Catches: the capture invalidated by Python's collector freeing a graph mid-capture (``cuGraphExecDestroy`` is
    refused while a stream captures), what made ``pytest -m cuda``, run whole, fail the graphed tests after the
    first graphed test's decoders had become garbage."""
    model, target, config, latents = _graphed_run_inputs()
    scratch = torch.zeros(1, device="cuda")
    earlier = torch.cuda.CUDAGraph()
    with torch.cuda.graph(earlier):
        scratch.add_(1.0)
    box = {"graph": earlier}
    del earlier

    def drop_the_graph_into_a_cycle():
        cycle = [box.pop("graph")]
        cycle.append(cycle)  # only the cyclic collector can free the graph now
        del cycle
        for _ in range(64):  # allocations: the collector runs here unless it is held off
            [[] for _ in range(8)]

    _on_the_captured_call(monkeypatch, drop_the_graph_into_a_cycle)
    thresholds = gc.get_threshold()
    gc.set_threshold(1)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)  # the fallback to eager warns: fail instead
            decoder = rdo.step_decoder(model, target, latents, config)
    finally:
        gc.set_threshold(*thresholds)
    assert isinstance(decoder, rdo.GraphedDecoder)
    assert gc.isenabled()
    torch.rand(4, device="cuda")  # the generator still draws


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU visible to torch")
def test_a_failed_capture_falls_back_with_one_warning_and_leaves_the_generator_and_caches_as_they_were(monkeypatch):
    """A capture that fails (here: a synchronisation inside it) gives the eager decoder with one warning; the CUDA
    generator's state is the one before the attempt and it still draws; the eager loss and gradients are those of a
    run that never tried to capture (to the rounding of CUDA's atomics).

    Catches: the generator left in its capturing state ("Offset increment outside graph capture encountered
    unexpectedly" at every later draw) or advanced by the attempt, and caches filled inside the failed capture."""
    model, target, config, latents = _graphed_run_inputs()
    before_loss, before_grads = _loss_and_gradients(model, latents, target, config, 0, None, None)
    _on_the_captured_call(monkeypatch, torch.cuda.synchronize)
    rng_state = torch.cuda.get_rng_state()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        decoder = rdo.step_decoder(model, target, latents, config)
    assert decoder is None
    assert [str(w.message).startswith("RDO runs without CUDA graphs") for w in caught] == [True]
    assert torch.equal(torch.cuda.get_rng_state(), rng_state)
    assert gc.isenabled()
    drawn = torch.rand(4, device="cuda")
    torch.cuda.set_rng_state(rng_state)
    assert torch.equal(torch.rand(4, device="cuda"), drawn)
    after_loss, after_grads = _loss_and_gradients(model, latents, target, config, 0, None, None)
    assert float(after_loss) == pytest.approx(float(before_loss), rel=1e-5)  # CUDA's atomics: rounding apart
    for a, b in zip(before_grads, after_grads):
        assert float((a - b).norm()) <= 1e-4 * float(a.norm()) + 1e-9


def _loss_and_gradients(model, latents, target, config, seed, decoder, temperature):
    generator = torch.Generator(device="cuda").manual_seed(seed)
    loss, _ = rdo.rdo_loss(model, latents, target, config, generator, decoder=decoder, temperature=temperature)
    return loss.detach(), torch.autograd.grad(loss, latents)
