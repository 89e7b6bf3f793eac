"""The geometry measures of ``codecsplat eval`` and ``train.validate`` (issue 30): depth errors against reference MVS
depth (``--mvs-depth DIR``, ``DIR/<scene>/depth.json``), on the context views of a sample. Tiny CPU sizes on
procedural scene folders."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch
from PIL import Image

from codecsplat_warp.errors import DataError
from codecsplat_warp.eval.geometry import ReferenceDepth, depth_errors, read_depth_maps, to_sample_grid
from codecsplat_warp.eval.protocols import PROTOCOLS, Sample, find_scenes, index_samples
from test_cli_commands import HEIGHT, WIDTH, write_scene

INDEX = {"a": {"context": [0, 2], "target": [1]}, "b": {"context": [1, 3], "target": [2]}}
"""Two samples; the reference depth folder has scene a only."""


def test_depth_errors_are_exact_on_scaled_references():
    depth = 1.0 + torch.rand(3, 6, 8, dtype=torch.float64)
    reference = torch.zeros_like(depth)
    reference[0] = depth[0] * 1.1  # every pixel 10 % too far: |d - 1.1 d| / 1.1 d = 0.1 / 1.1, ratio 1/1.1 within 1.25
    reference[1, :2] = depth[1, :2] * 2.0  # 16 pixels at half the reference: error 0.5, outside 1.25
    errors = depth_errors(depth.float(), reference)  # view 2 has no reference
    pixels0, pixels1 = 48, 16
    assert errors["pixels"] == pixels0 + pixels1 and errors["views"] == 2
    assert errors["abs_rel"] == pytest.approx((pixels0 * 0.1 / 1.1 + pixels1 * 0.5) / (pixels0 + pixels1), rel=1e-6)
    assert errors["delta_1_25"] == pytest.approx(pixels0 / (pixels0 + pixels1))
    assert depth_errors(depth, depth) == {"abs_rel": 0.0, "delta_1_25": 1.0, "pixels": 144, "views": 3}
    assert depth_errors(-depth, depth)["delta_1_25"] == 0.0  # a negative depth is never within the threshold
    assert depth_errors(depth, torch.zeros_like(depth)) == {}


def test_reference_maps_follow_the_protocol_resize_and_centre_crop():
    columns = np.tile(np.arange(60, dtype=np.float64), (40, 1))  # value = stored column
    assert np.array_equal(to_sample_grid(columns, (60, 40), (60, 40)), columns)
    # 60x40 covering 40x40: no resize, 10 columns cropped on each side
    assert np.array_equal(to_sample_grid(columns, (60, 40), (40, 40))[0], np.arange(10, 50))
    # a half-size map of the same photograph: each map pixel covers 2x2 stored pixels
    half = np.arange(30 * 20, dtype=np.float64).reshape(20, 30)
    assert np.array_equal(to_sample_grid(half, (60, 40), (60, 40)), half.repeat(2, 0).repeat(2, 1))
    # down to 30x20: pixel centre i + 0.5 of the 30-wide grid lies at 2i + 1 on the 60-wide map
    assert np.array_equal(to_sample_grid(columns, (60, 40), (30, 20))[0], np.arange(30) * 2 + 1)
    assert to_sample_grid(columns, (60, 40), (30, 20)).shape == (20, 30)


def write_reference(folder, files: dict[str, np.ndarray], scale: float = 1e-3, extra: dict | None = None) -> None:
    """``folder/depth.json`` (codecsplat-depth-v1) with one 16-bit PNG per image file; depth in scene units."""
    (folder / "depth").mkdir(parents=True, exist_ok=True)
    frames = []
    for i, (file, depth) in enumerate(files.items()):
        Image.fromarray(np.round(depth / scale).astype(np.uint16)).save(folder / "depth" / f"{i}.png")
        frames.append({"file": file, "depth": f"depth/{i}.png", "mask": f"mask/{i}.png", "coverage": 1.0,
                       "sources": []})
    height, width = next(iter(files.values())).shape
    header = {"format": "codecsplat-depth-v1", "scale": scale, "width": width, "height": height, "near": 0.1,
              "far": 60.0, "frames": frames, **(extra or {})}
    (folder / "depth.json").write_text(json.dumps(header))


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """Scene folders a and b (4 views, 48x32) and the index of :data:`INDEX`."""
    root = tmp_path_factory.mktemp("geometry")
    write_scene(root / "data" / "a", seed=1, views=4)
    write_scene(root / "data" / "b", seed=2, views=4)
    (root / "index.json").write_text(json.dumps(INDEX))
    return root


def _samples(scenes) -> list[Sample]:
    return index_samples(find_scenes(scenes / "data"), scenes / "index.json", PROTOCOLS["scene"])


def test_reference_depth_of_the_context_views_on_the_sample_grid(scenes, tmp_path):
    first, second = _samples(scenes)
    assert first.context_files == ("images/000.png", "images/002.png") and first.stored_size == (WIDTH, HEIGHT)
    ramp = 1.0 + np.arange(2 * WIDTH, dtype=np.float64)[None].repeat(2 * HEIGHT, 0)  # a map at twice the size
    write_reference(tmp_path / "mvs" / "a", {"images/000.png": ramp, "images/001.png": ramp}, scale=2e-3)
    reference = ReferenceDepth(tmp_path / "mvs")
    depth = reference.context_depth(first)
    assert depth.shape == (2, HEIGHT, WIDTH) and depth.dtype == torch.float64
    assert torch.allclose(depth[0, 5], torch.arange(WIDTH, dtype=torch.float64) * 2 + 2)  # nearest: column 2i + 1
    assert float(depth[1].abs().max()) == 0.0  # frame 2 has no entry: no depth
    assert reference.context_depth(second) is None  # scene b has no depth.json
    assert reference.context_depth(replace(first, context_files=("images/003.png",))) is None
    with pytest.raises(DataError, match="does not exist"):
        ReferenceDepth(tmp_path / "nowhere")


@pytest.mark.parametrize("change,match", [
    ({"format": "codecsplat-depth-v0"}, "format must be 'codecsplat-depth-v1'"),
    ({"scale": -1.0}, "scale must be a positive number"), ({"scale": "1e-3"}, "scale must be a positive number"),
    ({"width": 0}, "width and height"), ({"frames": {"images/000.png": "depth/0.png"}}, "frames must be a list"),
    ({"width": 9}, r"depth/0.png: 8x4 pixels, depth.json says 9x4"),
])
def test_a_corrupt_depth_json_is_a_data_error(tmp_path, change, match):
    write_reference(tmp_path, {"images/000.png": np.ones((4, 8))}, extra=change)
    with pytest.raises(DataError, match=match):
        read_depth_maps(tmp_path)


def test_unreadable_depth_files_are_data_errors(tmp_path):
    (tmp_path / "depth.json").write_text("{not json")
    with pytest.raises(DataError, match="not a readable depth file"):
        read_depth_maps(tmp_path)
    write_reference(tmp_path, {"images/000.png": np.ones((4, 8))})
    Image.fromarray(np.ones((4, 8), dtype=np.uint8)).save(tmp_path / "depth" / "0.png")
    with pytest.raises(DataError, match="16-bit single-channel"):
        read_depth_maps(tmp_path)
    (tmp_path / "depth" / "0.png").unlink()
    with pytest.raises(DataError, match="0.png: cannot read the depth PNG"):
        read_depth_maps(tmp_path)
