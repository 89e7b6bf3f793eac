"""Entropy coding of latent symbols: exact round trips, escapes, code length against the ideal, quantised priors."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from codecsplat_warp.codec import entropy
from codecsplat_warp.errors import InputError


def _round_trip(symbols: np.ndarray, indices: np.ndarray) -> tuple[np.ndarray, bytes]:
    encoder = entropy.new_encoder()
    entropy.encode_symbols(encoder, symbols, indices)
    data = entropy.encoder_bytes(encoder)
    return entropy.decode_symbols(entropy.new_decoder(data), indices), data


def test_symbols_round_trip_exactly_over_every_scale_and_several_calls():
    rng = np.random.default_rng(0)
    indices = rng.integers(0, entropy.SCALE_LEVELS, 5000)
    scales = entropy.scale_table().numpy()[indices]
    symbols = np.round(rng.normal(size=5000) * scales).astype(np.int64)
    encoder = entropy.new_encoder()
    entropy.encode_symbols(encoder, symbols[:3000], indices[:3000])
    entropy.encode_symbols(encoder, symbols[3000:], indices[3000:])
    decoder = entropy.new_decoder(entropy.encoder_bytes(encoder))
    first = entropy.decode_symbols(decoder, indices[:3000])
    second = entropy.decode_symbols(decoder, indices[3000:])
    np.testing.assert_array_equal(np.concatenate([first, second]), symbols)


def test_out_of_range_symbols_are_escaped_exactly():
    tails = entropy.discrete_models().tails
    indices = np.array([0, 0, 0, 5, 63, 63, 10, 0, 0])
    symbols = np.array([tails[0] + 1, -(tails[0] + 1), 2**20, -(2**31), tails[63] + 7, -(tails[63] + 2**32),
                        0, 1, -1], dtype=np.int64)
    decoded, _ = _round_trip(symbols, indices)
    np.testing.assert_array_equal(decoded, symbols)


def test_residuals_beyond_the_escape_range_are_a_typed_error():
    tail = int(entropy.discrete_models().tails[0])
    with pytest.raises(InputError, match="codable range"):
        _round_trip(np.array([tail + 2**32 + 1], dtype=np.int64), np.array([0]))


def test_coded_length_matches_the_ideal_code_length():
    rng = np.random.default_rng(1)
    n = 20000
    indices = rng.integers(0, 40, n)
    scales = entropy.scale_table()[torch.from_numpy(indices)]
    symbols = torch.round(torch.randn(n, dtype=torch.float64, generator=torch.Generator().manual_seed(2)) * scales)
    ideal = float(entropy.gaussian_bits(symbols, scales).sum())
    _, data = _round_trip(symbols.long().numpy(), indices)
    assert abs(8 * len(data) / ideal - 1) < 0.01, (8 * len(data), ideal)


def test_prior_quantisation_grid_and_scale_index():
    table = entropy.scale_table()
    assert table.shape == (entropy.SCALE_LEVELS,)
    assert table[0] == pytest.approx(entropy.SCALE_MIN) and table[-1] == pytest.approx(entropy.SCALE_MAX)
    torch.testing.assert_close(entropy.scale_index(table.log()), torch.arange(entropy.SCALE_LEVELS))
    assert int(entropy.scale_index(torch.tensor(-50.0))) == 0
    assert int(entropy.scale_index(torch.tensor(50.0))) == entropy.SCALE_LEVELS - 1
    means = torch.tensor([0.0, 1.0 / 200, -0.3, 5.0078125], dtype=torch.float64)
    q = entropy.quantize_mean(means)
    assert bool(((q / entropy.MEAN_GRID).round() == q / entropy.MEAN_GRID).all())
    assert float((q - means).abs().max()) <= entropy.MEAN_GRID / 2
    assert q.float().double().equal(q)  # grid values are exact in float32 too


def test_rate_estimate_is_bounded_and_matches_the_gaussian_mass():
    bits = entropy.gaussian_bits(torch.tensor([0.0, 1e6]), torch.tensor([1.0, 0.11]))
    p0 = math.erf(0.5 / math.sqrt(2))
    assert float(bits[0]) == pytest.approx(-math.log2(p0), rel=1e-5)
    assert float(bits[1]) == pytest.approx(-math.log2(entropy.LIKELIHOOD_MIN), rel=1e-5)


def test_table_digest_is_stable_and_tables_cover_their_tails():
    models = entropy.discrete_models()
    assert entropy.entropy_model_digest() == models.digest and len(models.digest) == 64
    assert models.tails[0] >= 1 and all(np.diff(models.tails) >= 0)


def test_feature_stream_must_hold_whole_words():
    from codecsplat_warp.errors import BitstreamError

    with pytest.raises(BitstreamError, match="32-bit words"):
        entropy.new_decoder(b"\x00" * 5)


def test_rate_estimate_bounds_its_value_but_keeps_the_outliers_gradient():
    residual = torch.tensor([3.0, 50.0], requires_grad=True)
    scale = torch.tensor([0.11, 0.11], requires_grad=True)
    bits = entropy.gaussian_bits(residual, scale)
    torch.testing.assert_close(bits.detach(), torch.full((2,), -math.log2(entropy.LIKELIHOOD_MIN)))
    bits.sum().backward()
    assert bool((residual.grad > 0).all()), "the rate must still pull an outlier towards the mean"
    assert bool((scale.grad < 0).all()), "the rate must still widen the scale of an outlier"


def test_rate_estimate_matches_the_probability_form_inside_its_bound():
    r = torch.linspace(0.0, 4.0, 41, dtype=torch.float64)[:, None]
    s = torch.logspace(math.log10(entropy.SCALE_MIN), math.log10(entropy.SCALE_MAX), 17, dtype=torch.float64)[None]
    p = torch.special.ndtr((0.5 - r) / s) - torch.special.ndtr((-0.5 - r) / s)
    inside = p > entropy.LIKELIHOOD_MIN
    expected = -torch.log2(p)
    bits = entropy.gaussian_bits(r.expand_as(p), s.expand_as(p))
    assert bits.dtype == torch.float64
    torch.testing.assert_close(bits[inside], expected[inside], rtol=1e-9, atol=1e-9)
