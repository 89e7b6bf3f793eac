"""CodecSplat encode/decode on the tiny preset: exact symbols, device/dtype/thread independence, rate
estimate against coded bytes, foreign bitstreams, pretrained files, and the differentiable codec path."""

from __future__ import annotations

import copy
import json

import pytest
import torch
from safetensors import safe_open
from conftest import needs_warp_cpu, tiny_coding_model
from safetensors.torch import save_file

from codecsplat_warp.codec import LAMBDA_MAX, LAMBDA_MIN, DecodedScene, bytes_report, parse_bitstream
from codecsplat_warp.data.procedural import ProceduralConfig, procedural_scene
from codecsplat_warp.errors import BitstreamError, DataError, DeviceMismatchError, InputError
from codecsplat_warp.model import CodecSplat
from codecsplat_warp.nn.config import get_preset
from codecsplat_warp.model.codecsplat import model_id
from codecsplat_warp.model.pretrained import DEFAULT_CHECKPOINT, load_pretrained, round_to_half, save_pretrained

TINY = get_preset("tiny")


def _scene(height: int = 32, width: int = 48, seed: int = 3):
    s = procedural_scene(seed, ProceduralConfig(width=width, height=height, num_views=2, texture_size=16))
    return s.images.float() / 255.0, s.cameras.to(dtype=torch.float32)


@pytest.fixture(scope="module")
def coded():
    model = tiny_coding_model(0)
    images, cameras = _scene()
    return model, images, cameras, model.encode_scene(images, cameras, 64.0)


def test_decoded_symbols_equal_the_coded_ones_and_the_scene_is_complete(coded):
    model, images, cameras, encoded = coded
    assert sum(int((l != 0).sum()) for l in encoded.latents) > 50, "the test must code non-trivial symbols"
    scene = model.decode_scene(encoded.data)
    assert isinstance(scene, DecodedScene)
    assert len(scene.latents) == len(encoded.latents)
    for a, b in zip(encoded.latents, scene.latents):
        assert torch.equal(a, b.cpu())
    V, H, W = 2, TINY.height, TINY.width
    assert len(scene.gaussians) == V * H * W and scene.depth.shape == (V, H, W)
    near, far = scene.cameras.near[:, None, None], scene.cameras.far[:, None, None]
    assert bool((scene.depth >= near * (1 - 1e-4)).all() and (scene.depth <= far * (1 + 1e-4)).all())
    torch.testing.assert_close(scene.cameras.K, cameras.K)
    torch.testing.assert_close(scene.cameras.w2c, cameras.w2c, atol=1e-5, rtol=1e-5)
    assert scene.lam == 64.0 and scene.header.model_id == model_id(model)
    assert model.encode(images, cameras, 64.0) == encoded.data, "encoding is deterministic"
    assert len(model.decode(encoded.data)) == V * H * W
    report = bytes_report(encoded.data)
    assert report["total"] == len(encoded.data)
    assert [report[f"view{v}"] - 5 for v in range(V)] == encoded.feature_bytes  # 1 length byte + CRC32


def test_decoding_in_float64_and_with_other_thread_counts_gives_the_same_symbols(coded):
    model, _, _, encoded = coded
    reference = model.decode_scene(encoded.data)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        single = model.decode_scene(encoded.data)
    finally:
        torch.set_num_threads(threads)
    double = tiny_coding_model(0).double()
    assert model_id(double) == model_id(model), "the identifier names float32 weights, whatever the compute dtype"
    in_float64 = double.decode_scene(encoded.data)
    for other in (single, in_float64):
        for a, b in zip(reference.latents, other.latents):
            assert torch.equal(a, b)
    torch.testing.assert_close(in_float64.depth.float(), reference.depth, atol=1e-3, rtol=1e-3)


def test_estimated_rate_matches_coded_bytes():
    model = tiny_coding_model(0)
    images, cameras = _scene(64, 96, seed=5)
    for lam in (LAMBDA_MIN, LAMBDA_MAX):
        encoded = model.encode_scene(images, cameras, lam)
        coded_bits = 8 * sum(encoded.feature_bytes)
        estimate = float(encoded.estimated_bits.sum())
        assert estimate > 2000
        assert abs(coded_bits / estimate - 1) < 0.03, (coded_bits, estimate)
        forward = float(model(images, cameras, lam=lam)["rate_bits"])  # eval mode: the coder's discrete model
        assert forward == pytest.approx(estimate, rel=1e-3)


def test_foreign_and_corrupt_bitstreams_are_refused(coded):
    model, _, _, encoded = coded
    other = tiny_coding_model(seed=1)
    with pytest.raises(BitstreamError, match=f"{model_id(model)}.*{model_id(other)}"):
        other.decode_scene(encoded.data)
    corrupted = bytearray(encoded.data)
    corrupted[-3] ^= 0x10
    with pytest.raises(BitstreamError, match="CRC"):
        model.decode(bytes(corrupted))
    with pytest.raises(BitstreamError, match="truncated"):
        model.decode(encoded.data[:-4])


def test_model_id_follows_the_weights():
    """The id names the weights, whatever object holds them. Catches: an id tied to the object (another model with
    the same weights must have it, one with other weights must not), and a cached id that outlives an in-place
    change of a weight or does not come back when the weight does."""
    model = tiny_coding_model(0)
    before = model_id(model)
    assert len(before) == 16 and model_id(tiny_coding_model(0)) == before != model_id(tiny_coding_model(1))
    bias = model.codec.synthesis.out.bias
    saved = bias.detach().clone()
    with torch.no_grad():
        bias.add_(1.0)
    assert model_id(model) != before
    with torch.no_grad():
        bias.copy_(saved)
    assert model_id(model) == before


def test_encoder_input_checks():
    model = tiny_coding_model(0)
    images, cameras = _scene()
    with pytest.raises(InputError, match="lambda"):
        model.encode(images, cameras, 8.0)
    with pytest.raises(InputError, match="lambda"):
        model.encode(images, cameras, float("nan"))
    with pytest.raises(InputError, match="no codec"):
        CodecSplat(TINY).encode(images, cameras, 64.0)
    with pytest.raises(InputError, match="no codec"):
        CodecSplat(TINY)(images, cameras, lam=64.0)


def test_training_pass_gives_a_rate_and_gradients_to_every_codec_module():
    model = tiny_coding_model(0).train()
    images, cameras = _scene()
    out = model(images, cameras, lam=100.0)
    assert out["F_hat"].shape == out["F_c"].shape and out["S"].shape == out["D_hat"].shape == (2, 32, 48)
    assert out["rate_bits"].ndim == 0 and float(out["rate_bits"].detach()) > 0
    loss = out["rate_bits"] * 1e-3 + out["gaussians"].means.square().mean() + (out["S"] - out["S_enc"]).abs().mean()
    loss.backward()
    for module in model.codec_modules():
        for name, p in module.named_parameters():
            assert p.grad is not None and bool(torch.isfinite(p.grad).all()), name


def test_held_rounding_offsets_make_the_decoder_input_linear_in_the_latents():
    """The noisy quantiser's held offsets (finite differences along the latents, train.semi_amortised): at the
    point they were recorded the pass is the plain one; a move of the finest level (on which no other level's mean
    depends) by whole quantisation steps moves the feature as the plain rounding does there (its offsets are
    periodic in its latents); half a step does not snap. Would catch:
    offsets recorded or held per the wrong level, or held ones that still round."""
    model = tiny_coding_model(0).train()
    images, cameras = _scene()
    with torch.no_grad():
        latents = model(images, cameras, lam=100.0)["latents"]
        h, w = cameras.height // 2, cameras.width // 2
        run = lambda zs, held=None: model.codec.forward_latents(  # noqa: E731
            zs, 100.0, h, w, torch.Generator().manual_seed(4), held_offsets=held)
        plain = run(latents)
        assert len(plain.rounding_offsets) == len(latents)
        assert all(float(o.abs().max()) <= 0.5 for o in plain.rounding_offsets)
        held = run(latents, plain.rounding_offsets)
        torch.testing.assert_close(held.feature, plain.feature)
        torch.testing.assert_close(held.bits, plain.bits)
        finest = [*latents[:-1], latents[-1] + 1.0]
        torch.testing.assert_close(run(finest, plain.rounding_offsets).feature, run(finest).feature)
        halfway = [*latents[:-1], latents[-1] + 0.5]
        assert not torch.allclose(run(halfway, plain.rounding_offsets).feature, run(halfway).feature)
    with pytest.raises(InputError, match="training mode"):
        model.eval().codec.forward_latents(latents, 100.0, h, w, held_offsets=plain.rounding_offsets)


def test_pretrained_round_trip_and_missing_files(tmp_path, coded):
    model, _, _, encoded = coded
    path = save_pretrained(model, tmp_path / "m.safetensors")
    loaded = load_pretrained(path, device="cpu")
    assert not loaded.training and model_id(loaded) == model_id(model)
    for a, b in zip(loaded.decode_scene(encoded.data).latents, encoded.latents):
        assert torch.equal(a, b)
    with safe_open(str(path), framework="pt") as f:
        metadata = f.metadata()
        tensors = {k: f.get_tensor(k) for k in f.keys()}
    assert json.loads(metadata["config"]) == json.loads(json.dumps(TINY.to_dict()))
    assert metadata["model_id"] == model_id(model)

    tampered = dict(tensors)
    tampered["codec.synthesis.out.bias"] = tampered["codec.synthesis.out.bias"] + 1
    save_file(tampered, str(tmp_path / "bad.safetensors"), metadata=metadata)
    with pytest.raises(DataError, match="SHA-256"):
        load_pretrained(tmp_path / "bad.safetensors", device="cpu")
    with pytest.raises(DataError, match="nope.safetensors"):
        load_pretrained(tmp_path / "nope.safetensors")
    if not DEFAULT_CHECKPOINT.is_file():
        with pytest.raises(DataError, match="codecsplat-default.safetensors"):
            load_pretrained()
    with pytest.raises(InputError, match="codec"):
        save_pretrained(CodecSplat(TINY), tmp_path / "stage1.safetensors")


def test_half_storage_round_trips_exactly_and_refuses_unrounded_weights(tmp_path, coded):
    model = copy.deepcopy(coded[0])
    with pytest.raises(InputError, match="round_to_half"):
        save_pretrained(model, tmp_path / "h.safetensors", half=True)
    path = save_pretrained(round_to_half(model), tmp_path / "h.safetensors", half=True)
    full = save_pretrained(model, tmp_path / "f.safetensors")
    assert path.stat().st_size < 0.6 * full.stat().st_size
    assert model_id(load_pretrained(path, device="cpu")) == model_id(model)


def test_shipped_model_loads_and_fits_in_16_mb():
    assert DEFAULT_CHECKPOINT.stat().st_size <= 16_000_000
    model = load_pretrained(device="cpu")
    assert model.has_codec and model.config.name == "re10k"
    with safe_open(str(DEFAULT_CHECKPOINT), framework="pt") as f:  # stored by save_pretrained(half=True)
        assert {f.get_slice(name).get_dtype() for name in f.keys()} == {"F16"}
    assert {t.dtype for t in model.state_dict().values()} == {torch.float32}


def test_re10k_pretrained_file_fits_in_16_mib(tmp_path):
    path = save_pretrained(CodecSplat(get_preset("re10k"), codec=True), tmp_path / "re10k.safetensors")
    assert path.stat().st_size <= 16 * 1024 * 1024, path.stat().st_size


def test_decode_refuses_another_device_than_the_models(coded):
    model, _, _, encoded = coded
    with pytest.raises(DeviceMismatchError, match="model.to"):
        model.decode(encoded.data, device="meta")
    assert parse_bitstream(encoded.data).header.lam == 64.0


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU visible to torch")
@needs_warp_cpu
def test_bitstream_encoded_on_cuda_decodes_on_cpu_to_the_same_symbols():
    images, cameras = _scene(64, 96, seed=5)
    gpu = tiny_coding_model(0).cuda()
    encoded = gpu.encode_scene(images.cuda(), cameras.to("cuda"), 300.0)
    on_cpu = tiny_coding_model(0).decode_scene(encoded.data)
    on_gpu = gpu.decode_scene(encoded.data)
    for coded, cpu, cuda in zip(encoded.latents, on_cpu.latents, on_gpu.latents):
        assert torch.equal(coded, cpu) and torch.equal(coded, cuda.cpu())


def test_bounded_log_scale_passes_gradients_only_back_into_its_range():
    from codecsplat_warp.codec import entropy, latent

    lo, hi = entropy.log_scale_bounds()
    for upstream, expected in (([1.0, 1.0, -1.0], [0.0, 1.0, 0.0]), ([-1.0, 1.0, 1.0], [-1.0, 1.0, 1.0])):
        x = torch.tensor([lo - 8.0, 0.0, hi + 8.0], requires_grad=True)
        y = latent.bounded_log_scale(x)
        torch.testing.assert_close(y.detach(), torch.tensor([lo, 0.0, hi]))
        (y * torch.tensor(upstream)).sum().backward()
        torch.testing.assert_close(x.grad, torch.tensor(expected))


def test_rate_cannot_push_a_log_scale_far_below_the_smallest_scale():
    """Zero residuals under training noise cost fewer bits at smaller scales; past the smallest scale that
    push must stop, or the log-scale drifts where no gradient brings it back (stage 2 diverged that way)."""
    from codecsplat_warp.codec import entropy, latent

    lo, _ = entropy.log_scale_bounds()
    raw = torch.full((256,), lo + 0.5, requires_grad=True)
    optimiser = torch.optim.SGD([raw], lr=1.0)
    noise = torch.rand(256, generator=torch.Generator().manual_seed(0)) - 0.5
    for _ in range(200):
        optimiser.zero_grad()
        entropy.gaussian_bits(noise, latent.bounded_log_scale(raw).exp()).sum().backward()
        optimiser.step()
    assert float(raw.detach().min()) > lo - 1.0  # a plain straight-through clamp ends 84 below here
