"""Multi-view stereo depth (ops.mvs, kernels/mvs.py), ``codecsplat depth`` and depth map folders.

Accuracy is measured on a procedural room with exact depth, 6 views at 128x106 on a 45-degree orbit, whose
surfaces carry band-limited random textures (16x16 random colour cells per texture tile, so that the images
are not aliased at this size). A pixel is *textured* when the standard deviation of its grey level over the
5x5 pixels around it is at least :data:`TEXTURED_STD` (grey levels in [0, 1]).
"""

from __future__ import annotations

import json
import math
import pathlib
from dataclasses import replace

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from PIL import Image

from conftest import DEVICES, needs_warp_cpu
from codecsplat_warp.cameras import Cameras
from codecsplat_warp.cli import EXIT_USER, main
from codecsplat_warp.data import ProceduralConfig, procedural_scene
from codecsplat_warp.data.depth_maps import (
    DEPTH_FORMAT, depth_scale, dequantize_depth, quantization_error, quantize_depth, read_depth_maps,
)
from codecsplat_warp.errors import DataError, InputError, MVSError
from codecsplat_warp.ops import MVSConfig, mvs_depth, select_sources
from codecsplat_warp.ops.mvs import GRAY_WEIGHTS

TEXTURED_STD = 0.03
"""Grey-level standard deviation over 5x5 pixels from which a pixel counts as textured."""

CONFIG = MVSConfig(num_planes=48, num_sources=4)
"""The accuracy run: fewer planes than the default (the refinement recovers the precision), 4 sources of 5."""


def textured_scene(seed: int = 0, width: int = 128, height: int = 106, views: int = 6, arc: float = 45.0):
    """A procedural room on an orbit whose surfaces carry band-limited random photo textures."""
    generator = torch.Generator().manual_seed(seed)
    photos = [(torch.rand(3, 16, 16, generator=generator) * 255).to(torch.uint8) for _ in range(64)]
    config = ProceduralConfig(width=width, height=height, num_views=views, layout="room", trajectory="orbit",
                              texture_size=64, orbit_arc_degrees=(arc, arc))
    return procedural_scene(seed, config, photo_textures=photos)


def as_input(scene, dtype=torch.float32, device="cpu"):
    return (scene.images.to(device, dtype) / 255, scene.cameras.to(device, dtype))


def textured_pixels(images: torch.Tensor) -> torch.Tensor:
    """bool [V,H,W]: grey-level standard deviation over the 5x5 pixels around >= TEXTURED_STD."""
    gray = torch.einsum("vchw,c->vhw", images.double(), torch.tensor(GRAY_WEIGHTS, dtype=torch.float64))[:, None]
    mean = torch.nn.functional.avg_pool2d(gray, 5, 1, 2, count_include_pad=False)
    square = torch.nn.functional.avg_pool2d(gray**2, 5, 1, 2, count_include_pad=False)
    return (square - mean**2).clamp(min=0).sqrt()[:, 0] >= TEXTURED_STD


def rotated(cameras: Cameras, degrees: float, seed: int) -> Cameras:
    """The cameras each turned by ``degrees`` about its own random axis through its centre."""
    generator = torch.Generator().manual_seed(seed)
    w2c = cameras.w2c.double().clone()
    for v in range(cameras.num_views):
        axis = torch.nn.functional.normalize(torch.randn(3, generator=generator, dtype=torch.float64), dim=0)
        skew = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        turn = torch.linalg.matrix_exp(math.radians(degrees) * skew)
        w2c[v, :3, :3] = turn @ w2c[v, :3, :3]
        w2c[v, :3, 3] = turn @ w2c[v, :3, 3]
    return Cameras(K=cameras.K, w2c=w2c.to(cameras.dtype), near=cameras.near, far=cameras.far, width=cameras.width,
                   height=cameras.height)


@pytest.fixture(scope="module")
def scene():
    return textured_scene()


@pytest.fixture(scope="module")
def result(scene):
    return mvs_depth(*as_input(scene), CONFIG)


# ---------------------------------------------------------------------------------------------- accuracy
def test_kept_depths_are_within_one_percent(scene, result):
    kept = result.mask
    assert result.depth.shape == scene.depth.shape and result.depth.dtype == torch.float32
    assert bool((result.depth[~kept] == 0).all()) and bool((result.depth[kept] > 0).all())
    error = (result.depth[kept] - scene.depth[kept]).abs() / scene.depth[kept]
    assert kept.sum() > 0.3 * kept.numel()
    assert float((error < 0.01).float().mean()) >= 0.90, float((error < 0.01).float().mean())


def test_no_depth_is_kept_outside_the_swept_range(scene):
    """Surfaces beyond a view's far bound (cut to the middle of the room's depths here) get no depth, even where the
    refinement or the fusion of agreeing views would step past the last plane; the writer relies on it (its 16-bit
    scale ends at far)."""
    images, cameras = as_input(scene)
    far = scene.depth.flatten(1).median(dim=1).values.to(cameras.dtype)
    cut = Cameras(K=cameras.K, w2c=cameras.w2c, near=cameras.near, far=far, width=cameras.width, height=cameras.height)
    out = mvs_depth(images, cut, CONFIG)
    assert bool(out.mask.any())
    kept = out.depth.masked_fill(~out.mask, float("nan"))
    assert bool((kept.nan_to_num(0.0) <= far[:, None, None]).all())
    assert bool((kept.nan_to_num(float("inf")) >= cut.near[:, None, None]).all())


def test_textured_surfaces_are_covered(scene, result):
    textured = textured_pixels(scene.images.float() / 255)
    assert textured.float().mean() > 0.5  # the scene is mostly textured: the measure is about matching
    coverage = float((result.mask & textured).sum() / textured.sum())
    assert coverage >= 0.5, coverage


def test_perturbed_cameras_lose_most_coverage(scene, result):
    """Cameras turned by 1.5 degrees each: the views no longer agree, and the consistency check drops them."""
    images, cameras = as_input(scene)
    perturbed = mvs_depth(images, rotated(cameras, 1.5, seed=1), CONFIG)
    before, after = float(result.coverage.mean()), float(perturbed.coverage.mean())
    assert after < 0.25 * before, (before, after)


def test_the_consistency_check_is_what_drops_them(scene):
    """With the perturbed cameras, photometric winners remain on most pixels; without the consistency check
    (0 agreeing views needed) they would be kept."""
    images, cameras = as_input(scene)
    small = torch.nn.functional.interpolate(images, size=(53, 64), mode="area")
    config = MVSConfig(num_planes=24, num_sources=4, refine_steps=2, slant_degrees=())
    loose = mvs_depth(small, rotated(cameras, 1.5, seed=1), replace(config, min_consistent_views=0))
    strict = mvs_depth(small, rotated(cameras, 1.5, seed=1), config)
    assert float(loose.coverage.mean()) > 4 * float(strict.coverage.mean())


# ---------------------------------------------------------------------------------------------- sources and errors
def test_sources_are_other_views_with_a_baseline(scene):
    sources = select_sources(scene.cameras, MVSConfig(num_sources=3))
    assert sources.index.shape == (6, 3) and sources.index.dtype == torch.int64
    for v in range(6):
        chosen = [int(s) for s in sources.index[v] if s >= 0]
        assert chosen and v not in chosen and len(set(chosen)) == len(chosen)
    valid = sources.index >= 0
    assert bool((sources.angle_deg[valid] >= 1.0).all()) and bool((sources.angle_deg[valid] <= 30.0).all())
    again = select_sources(scene.cameras, MVSConfig(num_sources=3))
    assert torch.equal(sources.index, again.index)


def tiny_scene(views: int = 5, seed: int = 0):
    return textured_scene(seed=seed, width=48, height=40, views=views, arc=36.0)


TINY = MVSConfig(num_planes=16, num_sources=3, refine_steps=2, slant_degrees=(45.0,))


def test_too_few_views_raise():
    scene = tiny_scene()
    images, cameras = as_input(scene)
    with pytest.raises(MVSError, match="at least 3 views, got 2"):
        mvs_depth(images[:2], cameras.select([0, 1]), TINY)


def test_a_view_without_overlap_is_named():
    scene = tiny_scene()
    w2c = scene.cameras.w2c.clone()
    w2c[2, :3, :3] = torch.diag(torch.tensor([-1.0, 1.0, -1.0])) @ w2c[2, :3, :3]  # view 2 turned around
    w2c[2, :3, 3] = torch.diag(torch.tensor([-1.0, 1.0, -1.0])) @ w2c[2, :3, 3]
    cameras = Cameras(K=scene.cameras.K, w2c=w2c, near=scene.cameras.near, far=scene.cameras.far, width=48,
                      height=40)
    images = scene.images.float() / 255
    with pytest.raises(MVSError, match="view 2 has no usable source view"):
        mvs_depth(images, cameras, TINY)
    lenient = mvs_depth(images, cameras, replace(TINY, allow_unmatched=True))
    assert bool((lenient.sources.index[2] == -1).all()) and float(lenient.coverage[2]) == 0.0
    assert float(lenient.coverage.sum()) > 0


def test_bad_inputs_raise_input_errors():
    scene = tiny_scene()
    images, cameras = as_input(scene)
    bad = images.clone()
    bad[1, 0, 3, 4] = float("nan")
    with pytest.raises(InputError, match="images holds 1 non-finite"):
        mvs_depth(bad, cameras, TINY)
    with pytest.raises(InputError, match="images must have shape"):
        mvs_depth(images[:, :2], cameras, TINY)
    with pytest.raises(InputError, match="images has V=4"):
        mvs_depth(images[:4], cameras, TINY)
    with pytest.raises(InputError, match="dtype"):
        mvs_depth(scene.images, cameras, TINY)
    for field, value in (("num_planes", 1), ("num_sources", 9), ("window_step", 0), ("min_ncc", 2.0),
                         ("max_relative_depth", float("nan")), ("min_consistent_views", 6), ("slant_degrees", (90,))):
        with pytest.raises(InputError, match=field):
            MVSConfig(**{field: value})
    with pytest.raises(InputError, match="MVSConfig"):
        mvs_depth(images, cameras, {"num_planes": 8})


@pytest.mark.parametrize("device", DEVICES)
def test_float64_agrees_with_float32(device):
    scene = tiny_scene()
    single = mvs_depth(*as_input(scene, torch.float32, device), TINY)
    double = mvs_depth(*as_input(scene, torch.float64, device), TINY)
    assert double.depth.dtype == torch.float64 and single.depth.device.type == device
    both = single.mask & double.mask
    either = single.mask | double.mask
    assert float(both.sum()) >= 0.9 * float(either.sum()) and float(both.sum()) > 0.1 * both.numel()
    relative = (single.depth[both].double() - double.depth[both]).abs() / double.depth[both]
    assert float((relative < 1e-3).double().mean()) > 0.95
    assert torch.equal(single.sources.index, double.sources.index)


def test_launches_of_several_views_give_the_same_depth(monkeypatch):
    """CUDA sweeps ``views_per_launch`` views per launch; the same batching on the CPU changes nothing."""
    from codecsplat_warp.ops import mvs

    scene = tiny_scene()
    one_by_one = mvs_depth(*as_input(scene), TINY)
    monkeypatch.setattr(mvs, "_view_batches", lambda views, device, config: [(0, 2), (2, 3)])
    done = []
    batched = mvs_depth(*as_input(scene), TINY, progress=done.append)
    assert done == [2, 5]
    assert torch.equal(one_by_one.raw_depth, batched.raw_depth) and torch.equal(one_by_one.depth, batched.depth)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU visible to torch")
@needs_warp_cpu
def test_cuda_agrees_with_cpu():
    scene = tiny_scene()
    cpu = mvs_depth(*as_input(scene), TINY)
    gpu = mvs_depth(*as_input(scene, device="cuda"), TINY)
    both = cpu.mask & gpu.mask.cpu()
    assert float(both.sum()) >= 0.9 * float((cpu.mask | gpu.mask.cpu()).sum())
    relative = (cpu.depth[both] - gpu.depth.cpu()[both]).abs() / cpu.depth[both]
    assert float((relative < 1e-3).float().mean()) > 0.95


# ---------------------------------------------------------------------------------------------- files
def write_scene_folder(folder: pathlib.Path, scene) -> pathlib.Path:
    """``scene`` as a codecsplat-scene-v1 folder (PNG images + cameras.json)."""
    (folder / "images").mkdir(parents=True)
    frames = []
    for i in range(scene.num_views):
        iio.imwrite(folder / "images" / f"{i:03d}.png", scene.images[i].permute(1, 2, 0).numpy())
        K, c2w = scene.cameras.K[i].double(), scene.cameras.c2w[i].double()
        frames.append({"file": f"images/{i:03d}.png", "w": scene.cameras.width, "h": scene.cameras.height,
                       "fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
                       "c2w": c2w.tolist()})
    cameras = {"format": "codecsplat-scene-v1", "frames": frames, "near": float(scene.cameras.near.min()),
               "far": float(scene.cameras.far.max())}
    (folder / "cameras.json").write_text(json.dumps(cameras))
    return folder


def test_cli_writes_depth_maps_that_read_back(tmp_path, capsys):
    scene = textured_scene(seed=0, width=64, height=54, views=5, arc=36.0)
    folder = write_scene_folder(tmp_path / "scene", scene)
    out = tmp_path / "depth"
    code = main(["depth", str(folder), "-o", str(out), "--device", "cpu", "--planes", "16", "--sources", "3",
                 "--max-size", "48", "--json"])
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    index = json.loads((out / "depth.json").read_text())
    assert index["format"] == DEPTH_FORMAT and (index["width"], index["height"]) == (48, 40)
    assert index["config"]["num_planes"] == 16 and index["device"] == "cpu" and index["seconds"] > 0
    assert summary["scenes"][0]["output"] == str(out) and len(index["frames"]) == 5 and summary["views"] == 5
    maps = read_depth_maps(out)
    assert maps.depth.shape == (5, 40, 48) and maps.depth.dtype == torch.float32
    assert maps.frames == [f"images/{i:03d}.png" for i in range(5)]
    assert maps.frame_index("images/003.png") == 3
    for v, frame in enumerate(index["frames"]):
        mask = np.asarray(Image.open(out / frame["mask"]))
        assert mask.dtype == np.uint8 and set(np.unique(mask)) <= {0, 255}
        assert np.array_equal(mask == 255, maps.mask[v].numpy())
        assert abs(frame["coverage"] - float(maps.mask[v].double().mean())) < 1e-12
        assert frame["sources"] and v not in frame["sources"]
        preview = Image.open(out / frame["preview"])
        assert preview.size == (96, 40) and preview.mode == "RGB"
    assert float(maps.mask.float().mean()) > 0.2
    # the same computation in memory: the files hold it up to the quantisation
    from codecsplat_warp.data import load_scene
    from codecsplat_warp.data.preprocess import resize_to_max_side

    loaded = load_scene(folder)
    images, cameras = resize_to_max_side(loaded.decoded_images(), loaded.cameras, 48)
    direct = mvs_depth(images.float() / 255, cameras.to(dtype=torch.float32),
                       MVSConfig(num_planes=16, num_sources=3))
    assert torch.equal(direct.mask, maps.mask)
    assert float((direct.depth - maps.depth).abs().max()) <= quantization_error(index["scale"]) * (1 + 1e-5)


def test_cli_runs_several_scenes_and_keeps_finished_ones(tmp_path, capsys):
    folders = [write_scene_folder(tmp_path / name, tiny_scene(seed=seed)) for name, seed in (("a", 0), ("b", 1))]
    args = ["depth", *map(str, folders), "-o", str(tmp_path / "out"), "--device", "cpu", "--planes", "12",
            "--sources", "3", "--json"]
    assert main(args) == 0
    first = json.loads(capsys.readouterr().out)
    assert [pathlib.Path(r["output"]).name for r in first["scenes"]] == ["a", "b"] and first["views"] == 10
    assert not any(r["resumed"] for r in first["scenes"])
    for name in "ab":
        assert read_depth_maps(tmp_path / "out" / name).depth.shape == (5, 40, 48)
    assert main(args) == 0
    assert all(r["resumed"] for r in json.loads(capsys.readouterr().out)["scenes"])
    assert main([*args, "--planes", "13"]) == 0  # another config: computed again
    assert not any(r["resumed"] for r in json.loads(capsys.readouterr().out)["scenes"])


def test_cli_user_errors_exit_1(tmp_path, capsys):
    scene = tiny_scene(views=2)
    folder = write_scene_folder(tmp_path / "two", scene)
    assert main(["depth", str(folder), "-o", str(tmp_path / "out"), "--device", "cpu"]) == EXIT_USER
    assert "at least 3 views" in capsys.readouterr().err
    assert main(["depth", str(folder), "-o", str(tmp_path / "out"), "--max-size", "8"]) == EXIT_USER
    assert main(["depth", str(folder), "-o", str(tmp_path / "out"), "--planes", "1"]) == EXIT_USER
    assert not (tmp_path / "out" / "depth.json").exists()


def test_quantisation_round_trip_loses_at_most_half_a_level(tmp_path):
    far = 37.5
    scale = depth_scale(far)
    depth = torch.rand(30, 40, dtype=torch.float64) * (far - 0.2) + 0.2
    depth[::3] = 0
    levels = quantize_depth(depth, scale)
    Image.fromarray(levels).save(tmp_path / "d.png")
    back = dequantize_depth(np.asarray(Image.open(tmp_path / "d.png")), scale)
    assert back.dtype == torch.float32 and levels.dtype == np.uint16
    assert bool(((back == 0) == (depth == 0)).all())
    assert float((back.double() - depth).abs().max()) <= quantization_error(scale) + 1e-6 * far
    with pytest.raises(DataError, match="exceeds"):
        quantize_depth(torch.tensor([[2 * far]]), scale)


def test_reading_a_broken_folder_raises_data_errors(tmp_path):
    with pytest.raises(DataError, match="does not exist"):
        read_depth_maps(tmp_path / "missing")
    folder = tmp_path / "maps"
    (folder / "depth").mkdir(parents=True)
    with pytest.raises(DataError, match="depth.json does not exist"):
        read_depth_maps(folder)
    index = {"format": DEPTH_FORMAT, "scale": 0.001, "width": 4, "height": 3, "near": 1.0, "far": 60.0,
             "frames": [{"file": "images/a.jpg", "depth": "depth/a.png", "mask": "mask/a.png", "coverage": 0.5,
                         "sources": [1, 2]}]}
    (folder / "depth.json").write_text(json.dumps({**index, "format": "something-else"}))
    with pytest.raises(DataError, match="format must be"):
        read_depth_maps(folder)
    (folder / "depth.json").write_text("{not json")
    with pytest.raises(DataError, match="cannot read JSON"):
        read_depth_maps(folder)
    (folder / "depth.json").write_text(json.dumps({k: v for k, v in index.items() if k != "scale"}))
    with pytest.raises(DataError, match="scale"):
        read_depth_maps(folder)
    (folder / "depth.json").write_text(json.dumps(index))
    with pytest.raises(DataError, match="a.png does not exist"):
        read_depth_maps(folder)
    (folder / "depth" / "a.png").write_bytes(b"\x89PNG broken")
    with pytest.raises(DataError, match="cannot decode"):
        read_depth_maps(folder)
    Image.fromarray(np.zeros((3, 4), np.uint8)).save(folder / "depth" / "a.png")
    with pytest.raises(DataError, match="16-bit"):
        read_depth_maps(folder)
    Image.fromarray(np.zeros((5, 4), np.uint16)).save(folder / "depth" / "a.png")
    with pytest.raises(DataError, match="4x5, depth.json says 4x3"):
        read_depth_maps(folder)
    Image.fromarray(np.full((3, 4), 1000, np.uint16)).save(folder / "depth" / "a.png")
    maps = read_depth_maps(folder)
    assert torch.allclose(maps.depth, torch.full((1, 3, 4), 1.0)) and maps.sources == [[1, 2]]
    with pytest.raises(DataError, match="no depth map for frame"):
        maps.frame_index("images/b.jpg")


# ---------------------------------------------------------------------------------------------- real data
@pytest.mark.data
@pytest.mark.slow
def test_a_real_scene_gets_depth_within_its_bounds(data_root):
    from codecsplat_warp.data import load_scene
    from codecsplat_warp.data.preprocess import resize_to_max_side

    scene = load_scene(data_root / "strecha_fountain_p11")
    images, cameras = resize_to_max_side(scene.decoded_images(), scene.cameras, 96)
    out = mvs_depth(images.float() / 255, cameras.to(dtype=torch.float32), MVSConfig(num_planes=48))
    kept = out.depth[out.mask]
    assert float(out.coverage.mean()) > 0.3, out.coverage
    assert float(kept.min()) >= float(cameras.near.min()) * 0.999 and float(kept.max()) <= float(cameras.far.max())


def test_the_config_module_and_the_kernels_agree_on_the_source_limit():
    """MVSConfig lives in a module without torch or Warp (the command line's --help shows its defaults at once);
    its source limit must be the kernels' vector length."""
    from codecsplat_warp import mvs_config
    from codecsplat_warp.kernels import mvs as mvs_kernels

    assert mvs_config.MAX_SOURCES == int(mvs_kernels.MAX_SOURCES)
    with pytest.raises(InputError, match="num_sources"):
        MVSConfig(num_sources=mvs_config.MAX_SOURCES + 1, min_consistent_views=2)
