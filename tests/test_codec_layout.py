"""Latent codec layouts (ModelConfig.codec_finest_stride, codec_latent_channels) and growing a codec by finer
levels (LatentCodec.grow_from): shapes, exact coding at a finer finest level, and a grown codec that starts
where its source was."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from codecsplat_warp.codec.latent import LatentCodec, latent_shapes, padding_multiple
from codecsplat_warp.errors import InputError
from codecsplat_warp.nn.config import ModelConfig, get_preset

TINY = get_preset("tiny")  # levels (4, 8) at feature strides 8, 4
FINER = dataclasses.replace(TINY, codec_latent_channels=(4, 8, 3), codec_finest_stride=2)


def test_finest_stride_sets_every_levels_grid_and_the_padding():
    assert latent_shapes(TINY, 16, 24) == [(4, 2, 3), (8, 4, 6)]
    assert latent_shapes(FINER, 16, 24) == [(4, 2, 3), (8, 4, 6), (3, 8, 12)]
    assert padding_multiple(TINY) == padding_multiple(FINER) == 8
    assert latent_shapes(dataclasses.replace(TINY, codec_finest_stride=2), 16, 24) == [(4, 4, 6), (8, 8, 12)]
    for bad in (1, 3, 6, 0, 2.0):
        with pytest.raises(InputError, match="codec_finest_stride"):
            dataclasses.replace(TINY, codec_finest_stride=bad)


def test_config_dict_leaves_out_the_layout_earlier_files_imply():
    assert "codec_finest_stride" not in TINY.to_dict()  # earlier model files keep their digest
    assert FINER.to_dict()["codec_finest_stride"] == 2
    assert ModelConfig.from_dict(FINER.to_dict()) == FINER
    assert ModelConfig.from_dict(TINY.to_dict()) == TINY


def _feature(seed: int = 0) -> torch.Tensor:
    return torch.randn(2, TINY.feature_channels, 12, 20, generator=torch.Generator().manual_seed(seed))


def test_a_finer_finest_level_codes_exactly():
    torch.manual_seed(3)
    codec = LatentCodec(FINER).eval()
    codec.scale_posterior(30.0)
    feature = _feature()
    out = codec(feature, 256.0)
    assert out.feature.shape == feature.shape and out.bits.shape == (2,)
    compressed = codec.compress(feature, 256.0)
    assert [tuple(s.shape[1:]) for s in compressed.symbols] == latent_shapes(FINER, 12, 20)
    assert int(compressed.symbols[-1].abs().sum()) > 0  # the finest level codes real symbols
    decoded, symbols = codec.decompress(compressed.streams, 12, 20, 256.0)
    assert all(torch.equal(a, b) for a, b in zip(symbols, compressed.symbols))
    torch.testing.assert_close(decoded, out.feature, rtol=1e-4, atol=1e-4)


def test_a_grown_codec_starts_where_its_source_was():
    torch.manual_seed(5)
    source = LatentCodec(TINY).eval()
    source.scale_posterior(30.0)
    torch.nn.init.zeros_(source.synthesis.blocks[0].conv2.weight)  # the block the grown codec drops: identity
    torch.nn.init.zeros_(source.synthesis.blocks[0].conv2.bias)
    grown = LatentCodec(FINER).eval()
    fresh = grown.grow_from(source.state_dict(), TINY)
    assert fresh and all(name.startswith("top_down.blocks.2.") for name in fresh)
    feature = _feature(1)
    for lam in (16.0, 1024.0):
        torch.testing.assert_close(grown(feature, lam).feature, source(feature, lam).feature)
        coded, before = grown.compress(feature, lam), source.compress(feature, lam)
        assert all(a.equal(b) for a, b in zip(coded.symbols, before.symbols))
        assert not coded.symbols[-1].any()  # the new level starts unused ...
        assert float(coded.bits.sum() - before.bits.sum()) < 0.01 * coded.symbols[-1].numel()  # ... and nearly free
        assert abs(sum(map(len, coded.streams)) - sum(map(len, before.streams))) <= 2 * len(coded.streams)
    grown.train()
    loss = grown(feature, 256.0).feature.square().mean()
    loss.backward()
    new_level = grown.top_down.blocks[2]
    assert new_level.posterior[-1].weight.grad.abs().sum() > 0  # the decoder's gradient reaches the new level


def test_growing_refuses_layouts_that_are_not_the_source_plus_finer_levels():
    state = LatentCodec(TINY).state_dict()
    others = [dataclasses.replace(TINY, codec_latent_channels=(4, 9, 3), codec_finest_stride=2),
              dataclasses.replace(TINY, codec_latent_channels=(4, 8, 3), codec_finest_stride=4),
              dataclasses.replace(FINER, codec_channels=12), TINY]
    for config in others:
        with pytest.raises(InputError, match="cannot grow"):
            LatentCodec(config).grow_from(state, TINY)
