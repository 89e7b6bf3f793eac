"""``codecsplat`` encode / decode / render / eval / demo end to end (subprocess), on a tiny random model and
tiny procedural scenes written to disk as codecsplat-scene-v1 folders; user errors exit 1 with one line."""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from codecsplat_warp.choices import RDO_PERCEPTUAL_WEIGHT
from codecsplat_warp.cli import BENCHMARKS, EXIT_USER, build_parser, main
from codecsplat_warp.data import ProceduralConfig, load_scene, procedural_scene
from codecsplat_warp.demo import DEMO_SCENE, DEMO_SEED, demo_sample, package_digest
from codecsplat_warp.export import read_ply, video
from codecsplat_warp.metrics import WEIGHTS_ENV, psnr
from codecsplat_warp.model import CodecSplat
from codecsplat_warp.model.pretrained import save_pretrained
from codecsplat_warp.nn.config import get_preset
from conftest import LPIPS_WEIGHTS, needs_lpips

WIDTH, HEIGHT = 48, 32


def write_scene(folder: pathlib.Path, seed: int, views: int = 6) -> pathlib.Path:
    """A procedural scene as a codecsplat-scene-v1 folder (PNG images + cameras.json)."""
    scene = procedural_scene(seed, ProceduralConfig(width=WIDTH, height=HEIGHT, num_views=views, texture_size=16))
    (folder / "images").mkdir(parents=True)
    frames = []
    for i in range(views):
        iio.imwrite(folder / "images" / f"{i:03d}.png", scene.images[i].permute(1, 2, 0).numpy())
        K, c2w = scene.cameras.K[i].double(), scene.cameras.c2w[i].double()
        frames.append({"file": f"images/{i:03d}.png", "w": WIDTH, "h": HEIGHT, "fx": float(K[0, 0]), "fy": float(K[1, 1]),
                       "cx": float(K[0, 2]), "cy": float(K[1, 2]), "c2w": c2w.tolist()})
    cameras = {"format": "codecsplat-scene-v1", "frames": frames, "near": float(scene.cameras.near.min()),
               "far": float(scene.cameras.far.max())}
    (folder / "cameras.json").write_text(json.dumps(cameras))
    return folder


def write_indexed_scenes(root: pathlib.Path, index: dict, views: int) -> pathlib.Path:
    """``root/data/<name>`` for every scene of ``index`` (procedural, seeds 1, 2, ... in its order, ``views`` views
    each) and ``root/index.json`` holding ``index``; returns ``root``."""
    for seed, name in enumerate(index, 1):
        write_scene(root / "data" / name, seed=seed, views=views)
    (root / "index.json").write_text(json.dumps(index))
    return root


@pytest.fixture(scope="module")
def workspace(tmp_path_factory) -> pathlib.Path:
    """A folder with ``tiny.safetensors`` (random tiny model with codec) and ``scenes/{a,b}``."""
    root = tmp_path_factory.mktemp("cli")
    torch.manual_seed(0)
    save_pretrained(CodecSplat(get_preset("tiny"), codec=True), root / "tiny.safetensors")
    write_scene(root / "scenes" / "a", seed=1)
    write_scene(root / "scenes" / "b", seed=2)
    return root


def codecsplat(workspace: pathlib.Path, *args: str) -> dict:
    """Run the console module with --json on the tiny model; the parsed stdout (exit code must be 0).

    LPIPS is left out (no weights in the environment) to keep the runs short; tests/test_metrics_image.py
    covers it."""
    command = [sys.executable, "-m", "codecsplat_warp.cli", *args, "--device", "cpu", "--json",
               "--checkpoint", str(workspace / "tiny.safetensors")]
    env = {k: v for k, v in os.environ.items() if k != WEIGHTS_ENV}
    done = subprocess.run(command, capture_output=True, text=True, cwd=workspace, env=env)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def test_encode_decode_render_pipeline(workspace):
    encoded = codecsplat(workspace, "encode", "scenes/a", "--views", "0,5", "--lambda", "64", "-o", "a.csplat")
    data = (workspace / "a.csplat").read_bytes()
    assert encoded["views"] == [0, 5] and encoded["bytes"]["total"] == len(data)
    assert set(encoded["bytes"]) == {"header", "cameras", "view0", "view1", "total"}
    assert encoded["lambda"] == 64 and encoded["seconds"]["encode"] > 0

    decoded = codecsplat(workspace, "decode", "a.csplat", "-o", "a.ply", "--prune")
    gaussians = read_ply(workspace / "a.ply")
    assert decoded["gaussians"] == len(gaussians) == 2 * WIDTH * HEIGHT - decoded["pruned"]
    assert decoded["lambda"] == 64 and bool((gaussians.opacities >= 1 / 255).all())

    orbit = codecsplat(workspace, "render", "a.csplat", "--orbit", "4", "-o", "orbit", "--format", "gif")
    gif = iio.imread(workspace / "orbit" / "render.gif", index=None)
    assert orbit["frames"] == 4 and gif.shape[:3] == (4, HEIGHT, WIDTH)

    posed = codecsplat(workspace, "render", "a.csplat", "--cameras", "scenes/a/cameras.json", "-o", "frames")
    assert posed["frames"] == 6 and len(list((workspace / "frames").glob("frame_*.png"))) == 6
    frame = iio.imread(workspace / "frames" / "frame_0003.png")
    assert frame.shape == (HEIGHT, WIDTH, 3) and frame.std() > 0


def test_eval_writes_both_tables_with_baselines_and_plots(workspace):
    result = codecsplat(workspace, "eval", "--data", "scenes", "--protocol", "scene", "--lambdas", "16,1024",
                        "--targets", "2", "--png-sh-clusters", "64", "--kmeans-iterations", "2", "--webp-qualities",
                        "20", "--jpeg-qualities", "20", "-o", "eval")
    methods = [(s["method"], s["setting"]) for s in result["summary"]]
    assert methods == [("Copy nearest context view", "no bitstream"), ("CodecSplat", "λ=16"), ("CodecSplat", "λ=1024"),
                       ("CodecSplat w/o codec→PLY", "float32"), ("CodecSplat w/o codec→PLY+Deflate", "16/8-bit"),
                       ("CodecSplat w/o codec→PNG", "K_SH=64"), ("CodecSplat w/ Deflate", "float16 features"),
                       ("WebP + codec-free", "q=20"), ("JPEG + codec-free", "q=20")]
    assert result["scenes"] == ["a", "b"] and len(result["rows"]) == 2 * 9
    floor, coded = result["summary"][0], result["summary"][1:]  # the zero-byte floor: no bitstream, no time
    assert floor["bytes"] == 0 and floor["gen_s"] == floor["compress_s"] == floor["decompress_s"] == 0
    assert 0 < floor["ssim"] <= 1 and floor["psnr"] > _grey_psnr(workspace / "scenes") + 1.0
    for row in coded:
        assert row["samples"] == 2 and row["bytes"] > 0 and 0 < row["ssim"] <= 1
        assert min(row["gen_s"], row["compress_s"], row["decompress_s"]) > 0
    raw_ply = coded[2]  # the codec-free Gaussians as float32: its compressed copies render (almost) the same
    assert all(s["bytes"] < raw_ply["bytes"] for s in coded if s is not raw_ply)
    # The tiny random model's renders change little with its Gaussians: the baselines' quantisation moves PSNR by
    # < 0.006 dB here, while scaling every PLY attribute by 1.05 after decoding moves it by 0.04 dB.
    assert all(abs(s["psnr"] - raw_ply["psnr"]) < 0.02 for s in coded[3:6]), [s["psnr"] for s in coded]
    for entry in result["summary"]:  # the summary is the mean of the per-scene rows
        rows = [r for r in result["rows"] if (r["method"], r["setting"]) == (entry["method"], entry["setting"])]
        assert entry["psnr"] == pytest.approx(sum(r["metrics"]["psnr"] for r in rows) / len(rows))
    markdown = (workspace / "eval" / "tables.md").read_text()
    assert "Table 1" in markdown and "Table 2" in markdown and "CodecSplat w/o codec→PNG" in markdown
    assert "λ=16,…,1024" in result["tables"]["table2"]
    for name in ("rate_distortion.png", "distortion_vs_time.png"):
        assert iio.imread(workspace / "eval" / name).shape[0] > 100
    assert json.loads((workspace / "eval" / "results.json").read_text())["summary"] == result["summary"]


def test_demo_writes_bitstreams_renders_ply_metrics_and_plots(workspace):
    summary = codecsplat(workspace, "demo", "--lambdas", "16,1024", "--rdo-steps", "2", "-o", "demo")
    out = workspace / "demo"
    assert summary["scene"] == DEMO_SCENE and [r["lam"] for r in summary["rows"]] == [16, 1024, 1024]
    assert [r["rdo_steps"] for r in summary["rows"]] == [0, 0, 2] and summary["rows"][2]["method"] == "CodecSplat RDO"
    truth = demo_sample(get_preset("tiny"), DEMO_SCENE, DEMO_SEED, 2).target_images
    for row in summary["rows"]:
        suffix = f"{row['lam']:g}" + ("-rdo" if row["rdo_steps"] else "")
        assert row["bytes"] == (out / f"scene-lambda{suffix}.csplat").stat().st_size
        renders = [iio.imread(out / "renders" / f"target{i}-lambda{suffix}.png") for i in range(2)]
        rendered = torch.from_numpy(np.stack(renders)).permute(0, 3, 1, 2).double() / 255
        assert row["psnr"] == pytest.approx(float(psnr(rendered, truth.double()).mean()), abs=0.05)  # uint8 renders
    assert len(read_ply(out / "scene.ply")) == summary["ply"]["gaussians"]
    for name in ("comparison.png", "rate_distortion.png", "renders/target1-lambda1024.png", "summary.json"):
        assert (out / name).is_file(), name
    assert all((workspace / f).is_file() for f in summary["files"])
    assert summary["package_digest"] == package_digest()  # which code and model wrote it (tests/test_demo_docs.py)


def test_the_shipped_demo_scene_has_its_context_views_around_targets_between_them():
    sample = demo_sample(get_preset("re10k"), DEMO_SCENE, DEMO_SEED, 2)
    assert sample.context_images.shape == sample.target_images.shape == (2, 3, 256, 256)
    centres = sample.context_cameras.centers.double()
    for target in sample.target_cameras.centers.double():  # each target lies between the two context cameras
        assert float((target - centres).norm(dim=-1).max()) < float((centres[0] - centres[1]).norm())


@pytest.mark.parametrize("scene", ["procedural", "scenes/b"])
def test_demo_runs_on_the_procedural_room_and_on_a_scene_folder(workspace, scene):
    summary = codecsplat(workspace, "demo", "--scene", scene, "--lambdas", "64", "--targets", "1", "-o", "demo-other")
    expected = demo_sample(get_preset("tiny"), str(workspace / scene) if "/" in scene else scene, DEMO_SEED, 1)
    assert summary["scene"] == expected.scene and summary["target_views"] == expected.target
    assert (workspace / "demo-other" / "comparison.png").is_file()


def _grey_psnr(scenes: pathlib.Path) -> float:
    """The best PSNR in dB of a flat mid-grey prediction of any frame of the scenes under ``scenes``: a floor
    that copying a nearby real view must beat."""
    frames = np.stack([iio.imread(path) for path in sorted(scenes.glob("*/images/*.png"))])
    images = torch.from_numpy(frames).permute(0, 3, 1, 2).double() / 255
    return float(psnr(torch.full_like(images, 0.5), images).max())


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("codecsplat: error:"), err
    return err[0]


def test_user_mistakes_exit_1_with_one_line(workspace, capsys):
    ckpt = ["--checkpoint", str(workspace / "tiny.safetensors"), "--device", "cpu"]
    assert main(["decode", str(workspace / "missing.csplat"), "-o", str(workspace / "x.ply"), *ckpt]) == EXIT_USER
    assert "does not exist" in _one_line_error(capsys)
    (workspace / "junk.csplat").write_bytes(b"CSPL" + bytes(40))
    assert main(["decode", str(workspace / "junk.csplat"), "-o", str(workspace / "x.ply"), *ckpt]) == EXIT_USER
    assert "bitstream" in _one_line_error(capsys)
    scene = str(workspace / "scenes" / "a")
    assert main(["encode", scene, "--views", "0,9", "-o", str(workspace / "x.csplat"), *ckpt]) == EXIT_USER
    assert "out of range" in _one_line_error(capsys)
    assert main(["encode", scene, "--lambda", "5000", "-o", str(workspace / "x.csplat"), *ckpt]) == EXIT_USER
    assert "5000" in _one_line_error(capsys)
    assert main(["encode", scene, "--size", "50x32", "-o", str(workspace / "x.csplat"), *ckpt]) == EXIT_USER
    assert "multiples of 4" in _one_line_error(capsys)
    assert main(["render", "x.csplat", "-o", "out", *ckpt]) == EXIT_USER
    assert "--cameras" in _one_line_error(capsys)
    assert main(["eval", "--data", scene, "--baselines", "zip", *ckpt]) == EXIT_USER
    assert "zip" in _one_line_error(capsys)
    assert main(["demo", "--scene", str(workspace / "no-such-scene"), "-o", str(workspace / "d"), *ckpt]) == EXIT_USER
    assert "nerd_mary_rose" in _one_line_error(capsys)  # the error names the built-in scenes
    assert not (workspace / "x.csplat").exists()


def test_demo_without_a_shipped_model_says_so(tmp_path, capsys, monkeypatch):
    from codecsplat_warp.model import pretrained

    monkeypatch.setattr(pretrained, "DEFAULT_CHECKPOINT", tmp_path / "codecsplat-default.safetensors")
    assert main(["demo", "--device", "cpu", "-o", str(tmp_path / "demo")]) == EXIT_USER
    assert "no model is shipped" in _one_line_error(capsys)


def test_mp4_without_a_video_plugin_names_the_extra(workspace, capsys, monkeypatch):
    monkeypatch.setattr(video, "MP4_PLUGINS", ())  # as if neither imageio-ffmpeg nor av were installed
    args = ["render", "a.csplat", "--orbit", "2", "-o", str(workspace / "mp4"), "--format", "mp4", "--device", "cpu"]
    assert main(args) == EXIT_USER
    assert "pip install imageio-ffmpeg" in _one_line_error(capsys)
    assert not (workspace / "mp4").exists()


def test_encode_default_views_are_spread_over_the_scene(workspace):
    result = codecsplat(workspace, "encode", "scenes/b", "-o", "b.csplat")
    assert result["views"] == [0, 5] and (result["width"], result["height"]) == (WIDTH, HEIGHT)
    assert load_scene(workspace / "scenes" / "b").num_views == 6


def test_every_benchmark_is_a_bench_subcommand():
    assert "codec" in BENCHMARKS
    for name in BENCHMARKS:
        assert build_parser().parse_args(["bench", name, "--device", "cpu"]).benchmark == name


def test_encode_with_rdo_steps_reports_the_optimisation(workspace):
    result = codecsplat(workspace, "encode", "scenes/a", "--views", "0,5", "--lambda", "256", "--steps", "3",
                        "-o", "rdo.csplat")
    assert result["rdo"]["steps"] == 3 and result["rdo"]["stopped"] == "steps"
    assert result["bytes"]["total"] == (workspace / "rdo.csplat").stat().st_size
    assert result["preset"] == "fast"  # the CPU's default preset; --steps overrides its count


def test_ctrl_c_during_rdo_writes_the_best_bitstream_so_far(workspace, monkeypatch, capsys):
    from codecsplat_warp.model import rdo

    real_step, calls = rdo.rdo_step, {"n": 0}

    def interrupted(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return real_step(*args, **kwargs)

    monkeypatch.setattr(rdo.loop, "rdo_step", interrupted)  # where the loop looks it up
    out = workspace / "interrupted.csplat"
    args = ["encode", "scenes/a", "--views", "0,5", "--preset", "slow", "-o", str(out), "--device", "cpu", "--json",
            "--checkpoint", str(workspace / "tiny.safetensors")]
    monkeypatch.chdir(workspace)
    assert main(args) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["rdo"]["stopped"] == "interrupted" and result["rdo"]["steps"] == 2
    assert out.stat().st_size == result["bytes"]["total"] and not list(workspace.glob(".interrupted*"))


@pytest.mark.parametrize("extra, message", [(["--perceptual", "-1"], "--perceptual must be a weight >= 0"),
                                            (["--perceptual", "nan", "--steps", "2"], "--perceptual must be"),
                                            (["--perceptual", "0.1", "--preset", "fast"], "give --preset medium"),
                                            (["--perceptual", "0.1", "--steps", "2", "--lpips-weights", "nowhere"],
                                             "lpips_vgg.safetensors does not exist")])
def test_a_perceptual_term_without_steps_or_weights_fails_before_any_work(workspace, capsys, extra, message):
    args = ["encode", "no-such-scene", "-o", str(workspace / "never.csplat"), *extra, "--device", "cpu"]
    assert main(args) == EXIT_USER
    assert message in _one_line_error(capsys) and not (workspace / "never.csplat").exists()


@needs_lpips
def test_encode_with_a_perceptual_term_optimises_with_the_lpips_network(workspace, monkeypatch, capsys):
    from codecsplat_warp.metrics.lpips import LPIPS

    seen = []
    unit_features = LPIPS.unit_features
    monkeypatch.setattr(LPIPS, "unit_features", lambda self, x: seen.append(x.shape) or unit_features(self, x))
    monkeypatch.chdir(workspace)
    args = ["encode", "scenes/a", "--views", "0,5", "--lambda", "256", "--steps", "2", "--lpips-weights",
            str(LPIPS_WEIGHTS), "-o", "perceptual.csplat", "--device", "cpu", "--json", "--checkpoint",
            str(workspace / "tiny.safetensors"), "--perceptual"]  # no value: the suggested weight
    assert main(args) == 0
    assert json.loads(capsys.readouterr().out)["perceptual"] == RDO_PERCEPTUAL_WEIGHT
    assert len(seen) >= 1 + 2 and all(shape[0] == 2 for shape in seen)  # the targets, then each step's renders
    assert (workspace / "perceptual.csplat").stat().st_size > 0


@pytest.mark.parametrize("option, value", [("--steps", "-2"), ("--time-budget", "0"), ("--time-budget", "nan")])
def test_bad_rdo_arguments_fail_before_any_work(workspace, capsys, option, value):
    args = ["encode", "no-such-scene", "-o", str(workspace / "never.csplat"), option, value, "--device", "cpu"]
    assert main(args) == EXIT_USER
    assert option in _one_line_error(capsys)
