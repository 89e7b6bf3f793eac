"""The geometry measures of ``codecsplat eval`` and ``train.validate`` (issue 30): self-render (a method's Gaussians
in its own context views), depth errors against reference MVS depth (``--mvs-depth DIR``, ``DIR/<scene>/depth.json``),
and the LPIPS-VGG panel of the rate-distortion plot. Tiny CPU sizes on procedural scene folders."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch
from PIL import Image

import codecsplat_warp.eval.report as report
from codecsplat_warp.data import ProceduralConfig, procedural_scene, read_depth_maps
from codecsplat_warp.data.depth_maps import DEPTH_FORMAT, quantize_depth
from codecsplat_warp.errors import DataError
from codecsplat_warp.eval.evaluate import EvalConfig, Evaluator, evaluate
from codecsplat_warp.eval.geometry import ReferenceDepth, depth_errors, to_sample_grid
from codecsplat_warp.eval.protocols import PROTOCOLS, Sample, find_scenes, index_samples
from codecsplat_warp.eval.report import BACKBONE, CODECSPLAT, COPY_NEAREST, plot_rate_distortion
from codecsplat_warp.gaussians import SH_C0, Gaussians
from codecsplat_warp.metrics.image import ImageMetrics
from codecsplat_warp.model import CodecSplat
from codecsplat_warp.nn.config import get_preset
from codecsplat_warp.ops.geometry import unproject
from test_cli_commands import HEIGHT, WIDTH, write_indexed_scenes

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
        Image.fromarray(quantize_depth(torch.from_numpy(depth), scale)).save(folder / "depth" / f"{i}.png")
        frames.append({"file": file, "depth": f"depth/{i}.png", "mask": f"mask/{i}.png", "coverage": 1.0,
                       "sources": []})
    height, width = next(iter(files.values())).shape
    header = {"format": DEPTH_FORMAT, "scale": scale, "width": width, "height": height, "near": 0.1,
              "far": 60.0, "frames": frames, **(extra or {})}
    (folder / "depth.json").write_text(json.dumps(header))


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """Scene folders a and b (4 views, 48x32) and the index of :data:`INDEX`."""
    root = tmp_path_factory.mktemp("geometry")
    return write_indexed_scenes(root, INDEX, views=4)


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
    ({"scale": "a lot"}, "missing or malformed field"), ({"frames": {"images/000.png": "depth/0.png"}}, "malformed"),
    ({"width": 9}, r"depth/0.png is 8x4, depth.json says 9x4"), ({"frames": []}, "holds no frame"),
])
def test_a_corrupt_depth_json_is_a_data_error(tmp_path, change, match):
    write_reference(tmp_path / "mvs" / "a", {"images/000.png": np.ones((4, 8))}, extra=change)
    sample = Sample("a", [0, 1], [2], torch.rand(2, 3, 4, 8), None, torch.rand(1, 3, 4, 8), None,
                    ("images/000.png", "images/001.png"), (8, 4))
    with pytest.raises(DataError, match=match):
        ReferenceDepth(tmp_path / "mvs").context_depth(sample)


def test_unreadable_depth_files_are_data_errors(tmp_path):
    (tmp_path / "depth.json").write_text("{not json")
    with pytest.raises(DataError, match="cannot read JSON"):
        read_depth_maps(tmp_path)
    write_reference(tmp_path, {"images/000.png": np.ones((4, 8))})
    Image.fromarray(np.ones((4, 8), dtype=np.uint8)).save(tmp_path / "depth" / "0.png")
    with pytest.raises(DataError, match="must be a 16-bit grey PNG"):
        read_depth_maps(tmp_path)
    (tmp_path / "depth" / "0.png").unlink()
    with pytest.raises(DataError, match="0.png does not exist"):
        read_depth_maps(tmp_path)


def _pixel_gaussians(image: torch.Tensor, depth: torch.Tensor, cameras) -> Gaussians:
    """Opaque pixel-aligned Gaussians of one view (image [3,H,W] in [0,1], depth [H,W]) at its exact depth, 0.1 px
    wide (the rasterizer's 0.3 px^2 low-pass then spreads each over its neighbours: about 30 dB on a textured
    image, at any depth)."""
    means = unproject(depth[None].double(), cameras.to(dtype=torch.float64))[0].reshape(-1, 3).float()
    n = means.shape[0]
    sigma = 0.1 * depth.reshape(-1, 1).float() / float(cameras.K[0, 0, 0])
    return Gaussians(means=means, quats=torch.tensor([1.0, 0, 0, 0]).repeat(n, 1), scales=sigma.repeat(1, 3),
                     opacities=torch.full((n,), 0.99), sh=((image.reshape(3, -1).T - 0.5) / SH_C0)[:, None, :])


def test_self_render_gives_back_the_images_of_pixel_aligned_gaussians():
    scene = procedural_scene(3, ProceduralConfig(width=48, height=32, num_views=2, texture_size=16))
    images, cameras = scene.images.float() / 255.0, scene.cameras.to(dtype=torch.float32)
    gaussians = _pixel_gaussians(images[0], scene.depth[0], cameras.select([0]))
    evaluator = Evaluator(CodecSplat(get_preset("tiny")), ImageMetrics(None), (64.0,), (), torch.device("cpu"))
    own = Sample("s", [0], [1], images[[0]], cameras.select([0]), images[[1]], cameras.select([1]))
    wrong = replace(own, context_cameras=cameras.select([1]))  # view 0's image, view 1's camera
    right, moved = evaluator.self_render(gaussians, own), evaluator.self_render(gaussians, wrong)
    assert right["psnr"] > 27.0 and right["psnr"] > moved["psnr"] + 10.0, (right, moved)
    assert right["ssim"] > 0.95 > moved["ssim"]


@pytest.fixture(scope="module")
def tiny_model():
    torch.manual_seed(0)
    return CodecSplat(get_preset("tiny"), codec=True).eval()


def _reference_from(model, sample: Sample, folder, factor: float) -> None:
    """Reference depth of scene ``sample.scene``: the model's D_enc of the sample's context views times ``factor``,
    as maps at twice the stored size (each value 2x2)."""
    with torch.no_grad():
        d_enc = model(sample.context_images, sample.context_cameras)["D_enc"].double().numpy()
    maps = {file: (d * factor).repeat(2, 0).repeat(2, 1) for file, d in zip(sample.context_files, d_enc)}
    write_reference(folder / sample.scene, maps, scale=float(max(m.max() for m in maps.values())) / 60000)


def test_eval_reports_self_render_and_depth_errors(scenes, tiny_model, tmp_path, monkeypatch):
    first, _ = _samples(scenes)
    _reference_from(tiny_model, first, tmp_path / "mvs", 1.1)
    figures = []
    monkeypatch.setattr(report, "save_figure", lambda fig, path: figures.append((path.name, fig)))
    config = EvalConfig(data=str(scenes / "data"), index=str(scenes / "index.json"), out=str(tmp_path / "out"),
                        protocol="scene", lambdas=(64.0,), baselines=(), progress=False,
                        mvs_depth=str(tmp_path / "mvs"))
    result = evaluate(tiny_model, config, torch.device("cpu"))
    rows = {(r["scene"], r["method"]): r for r in result["rows"]}
    assert rows["a", COPY_NEAREST]["self_render"] is None and rows["a", COPY_NEAREST]["depth"] is None
    codec_free, coded = rows["a", BACKBONE + "→PLY"], rows["a", CODECSPLAT]
    assert codec_free["depth"]["abs_rel"] == pytest.approx(0.1 / 1.1, abs=2e-4)  # D_enc against D_enc * 1.1
    assert codec_free["depth"]["delta_1_25"] == 1.0 and codec_free["depth"]["views"] == 2
    assert codec_free["depth"]["pixels"] == 2 * WIDTH * HEIGHT and 0 <= coded["depth"]["abs_rel"] < 10
    assert rows["b", BACKBONE + "→PLY"]["depth"] == {} and rows["b", CODECSPLAT]["depth"] == {}  # no reference
    for row in (codec_free, coded):
        assert set(row["self_render"]) >= {"psnr", "ssim"} and 0 < row["self_render"]["psnr"] < 60
    entry = next(s for s in result["summary"] if s["method"] == BACKBONE + "→PLY")
    assert entry["depth_samples"] == 1 and entry["depth_abs_rel"] == codec_free["depth"]["abs_rel"]
    assert entry["self_psnr"] == pytest.approx((codec_free["self_render"]["psnr"]
                                                + rows["b", BACKBONE + "→PLY"]["self_render"]["psnr"]) / 2)
    assert (result["depth_reference"]["samples_scored"], result["depth_reference"]["views_scored"]) == (1, 2)
    assert "1 of 2 sample(s) scored, 2 of 4 context views" in result["depth_reference"]["text"]
    floor = next(line for line in result["tables"]["table1"].splitlines() if line.startswith(f"| {COPY_NEAREST}"))
    assert floor.endswith("| - | - | - |")
    assert "Self-render PSNR" in result["tables"]["table1"] and "Depth δ<1.25" in result["tables"]["table3"]
    markdown = (tmp_path / "out" / "tables.md").read_text()
    assert "## Table 3: self-render and depth" in markdown and "1 of 2 sample(s) scored" in markdown
    plot = dict(figures)["rate_distortion.png"]
    labels = [ax.get_ylabel() for ax in plot.axes]
    assert labels[:2] == ["PSNR (dB) ↑", "SSIM ↑"] and ("LPIPS-VGG ↓" in labels) == ("lpips_vgg" in entry)


def test_an_old_results_file_is_measured_again_and_says_so(scenes, tiny_model, tmp_path, monkeypatch):
    monkeypatch.delenv("CODECSPLAT_LPIPS_WEIGHTS", raising=False)  # no LPIPS: faster
    config = EvalConfig(data=str(scenes / "data"), index=str(scenes / "index.json"), out=str(tmp_path / "out"),
                        protocol="scene", lambdas=(64.0,), baselines=(), progress=False)
    first = evaluate(tiny_model, replace(config, scenes=("a",)), torch.device("cpu"))
    saved = json.loads((tmp_path / "out" / "results.json").read_text())
    del saved["config"]["mvs_depth"]  # as written before the option existed
    for row in saved["rows"]:
        del row["self_render"], row["depth"]
    (tmp_path / "out" / "results.json").write_text(json.dumps(saved))
    again = evaluate(tiny_model, replace(config, scenes=("a",)), torch.device("cpu"))
    assert len(again["notes"]) == 1 and "measured again" in again["notes"][0]
    assert all("self_render" in r for r in again["rows"]) and len(again["rows"]) == len(first["rows"])
    assert evaluate(tiny_model, replace(config, scenes=("a",)), torch.device("cpu"))["notes"] == []  # resumes


def test_rate_distortion_plot_has_an_lpips_vgg_panel_with_the_copy_floor(tmp_path, monkeypatch):
    figures = []
    monkeypatch.setattr(report, "save_figure", lambda fig, path: figures.append(fig))
    floor = {"method": COPY_NEAREST, "setting": "no bitstream", "lam": None, "bytes": 0, "psnr": 15.0, "ssim": 0.4,
             "lpips_vgg": 0.39, "lpips_alex": 0.3}
    summary = [floor] + [{"method": CODECSPLAT, "setting": f"λ={lam:g}", "lam": lam, "bytes": 1000.0 * lam,
                          "psnr": 17 + lam / 1024, "ssim": 0.5, "lpips_vgg": 0.5 - lam / 1e4, "lpips_alex": 0.4}
                         for lam in (16.0, 1024.0)]
    plot_rate_distortion(summary, tmp_path / "rd.png")
    (fig,) = figures
    panel = next(ax for ax in fig.axes if ax.get_ylabel() == "LPIPS-VGG ↓")
    assert panel.get_xlabel() == "KiB per scene" and len(fig.axes) == 4
    dashed = [line for line in panel.get_lines() if line.get_linestyle() == "--"]
    assert len(dashed) == 1 and list(dashed[0].get_ydata()) == [0.39, 0.39]


def _stage1_run(folder) -> CodecSplat:
    """A run folder (config.json + one checkpoint) of a tiny stage-1 model, without codec."""
    from train.checkpoint import save_checkpoint
    from train.stage1 import TrainConfig, make_optimizer

    torch.manual_seed(3)
    model = CodecSplat(get_preset("tiny"), codec=False)
    optimizer, scheduler = make_optimizer(model, TrainConfig(steps=1))
    save_checkpoint(folder, 1, model, optimizer, scheduler, {})
    (folder / "config.json").write_text(json.dumps({"train": {}, "model": get_preset("tiny").to_dict()}))
    return model.eval()


def test_validation_of_a_stage1_run_reports_self_render_and_encoder_depth(scenes, tmp_path, capsys):
    from train.validate import main, score_sample

    model = _stage1_run(tmp_path / "run")
    first, second = _samples(scenes)
    _reference_from(model, first, tmp_path / "mvs", 1.1)
    reference = ReferenceDepth(tmp_path / "mvs")
    score = score_sample(model, first, torch.device("cpu"), reference)
    assert score.depth_abs_rel == pytest.approx(0.1 / 1.1, abs=2e-4) and score.depth_delta_1_25 == 1.0
    assert 0 < score.self_render_psnr < 60 and score.model_psnr > 0
    assert score_sample(model, second, torch.device("cpu"), reference).depth_abs_rel is None  # no reference
    main(["--run", str(tmp_path / "run"), "--data", str(scenes / "data"), "--index", str(scenes / "index.json"),
          "--mvs-depth", str(tmp_path / "mvs"), "--device", "cpu"])  # re10k protocol: 256x256
    summary = json.loads((tmp_path / "run" / "validation-re10k.json").read_text())
    a, b = summary["scenes"]
    assert a["depth_abs_rel"] is not None and b["depth_abs_rel"] is None and summary["depth_samples"] == 1
    assert summary["depth_abs_rel"] == a["depth_abs_rel"] and summary["mvs_depth"] == str(tmp_path / "mvs")
    assert summary["self_render_psnr"] == pytest.approx((a["self_render_psnr"] + b["self_render_psnr"]) / 2)
    printed = capsys.readouterr().out.splitlines()
    assert printed[0].split() == ["scene", "model", "dB", "nearest", "dB", "self", "dB", "AbsRel", "δ<1.25"]
    assert printed[2].split()[-2:] == ["-", "-"] and "depth over 1 of 2 samples" in printed[3]
