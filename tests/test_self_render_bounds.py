"""train.self_render_bounds: ideal pixel-aligned Gaussians at a procedural scene's exact depth render their own view
well, the colour fit improves on them, a wrong depth costs the all-views render, and the tool writes every variant."""

from __future__ import annotations

import json

import pytest
import torch
from conftest import tiny_coding_model
from test_cli_commands import write_scene

from codecsplat_warp.data.procedural import ProceduralConfig, procedural_scene
from codecsplat_warp.errors import InputError
from codecsplat_warp.model import CodecSplat, model_id
from codecsplat_warp.model.pretrained import save_pretrained
from codecsplat_warp.nn.config import get_preset
from train.self_render_bounds import VARIANTS, ideal_pixel_gaussians, main, optimise_colours, self_render_psnr


@pytest.fixture(scope="module")
def scene():
    """(images [2,3,32,48] in [0,1], exact depth [2,32,48], float32 cameras) of a procedural room."""
    s = procedural_scene(5, ProceduralConfig(width=48, height=32, num_views=2, texture_size=16))
    return s.images.float() / 255.0, s.depth, s.cameras.to(dtype=torch.float32)


@pytest.fixture(scope="module")
def model():
    return tiny_coding_model(0)


def test_ideal_gaussians_render_their_own_view_and_the_colour_fit_improves_them(scene, model):
    images, depth, cameras = scene
    ideal = ideal_pixel_gaussians(images, depth, cameras)
    assert len(ideal) == 2 * 32 * 48 and ideal.sh_degree == 0
    own = self_render_psnr(model, ideal, cameras, images, own_only=True)
    fitted = optimise_colours(model, ideal, cameras, images, steps=10)
    assert torch.equal(fitted.means, ideal.means) and not torch.equal(fitted.sh, ideal.sh)
    assert own > 22.0
    assert self_render_psnr(model, fitted, cameras, images, own_only=True) > own + 0.5


def test_a_wrong_depth_costs_the_render_of_all_views(scene, model):
    images, depth, cameras = scene
    exact = self_render_psnr(model, ideal_pixel_gaussians(images, depth, cameras), cameras, images, own_only=False)
    wrong = self_render_psnr(model, ideal_pixel_gaussians(images, depth * 1.5, cameras), cameras, images,
                             own_only=False)
    assert wrong < exact - 1.0


def test_the_tool_writes_every_variant_of_every_sample(tmp_path):
    torch.manual_seed(0)
    tiny = CodecSplat(get_preset("tiny"), codec=True)
    save_pretrained(tiny, tmp_path / "tiny.safetensors")
    write_scene(tmp_path / "scenes" / "a", seed=1, views=3)
    (tmp_path / "index.json").write_text(json.dumps({"a": {"context": [0, 2], "target": [1]}}))
    out = tmp_path / "bounds.json"
    main(["--checkpoint", str(tmp_path / "tiny.safetensors"), "--data", str(tmp_path / "scenes"),
          "--index", str(tmp_path / "index.json"), "--steps", "1", "--out", str(out)])
    summary = json.loads(out.read_text())
    assert summary["model_id"] == model_id(tiny) and summary["device"] == "cpu"
    assert [row["scene"] for row in summary["samples"]] == ["a"]
    assert set(summary["means"]) == set(VARIANTS) and set(summary["samples"][0]) == {"scene", *VARIANTS}


@pytest.mark.parametrize("option", [["--steps", "-1"], ["--samples", "-2"], ["--protocol", "llff"]])
def test_bad_options_raise_input_errors(tmp_path, option):
    with pytest.raises(InputError, match=option[0]):
        main(["--data", str(tmp_path), "--index", str(tmp_path / "index.json"), *option])
