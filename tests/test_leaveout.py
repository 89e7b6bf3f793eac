"""``codecsplat bench leaveout`` (issue 8, "leave out what a scene does not need") and the pruning hooks of
``codecsplat decode`` / ``render``: the naive-layout arithmetic, the off-screen scene, the quick benchmark on
a real scene, and the CLI's pruning reports."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
import torch

from codecsplat_warp.bench.leaveout import (
    NAIVE_VIEW_SLOTS, RENDER_TOLERANCE, move_offscreen, naive_layout, visible_subset,
)  # fmt: skip
from codecsplat_warp.bench.raster import Workload, make_scene, ours_forward
from codecsplat_warp.cli import EXIT_OK, EXIT_USER, main
from codecsplat_warp.codec import bytes_report, pack_bitstream
from codecsplat_warp.export import read_ply
from codecsplat_warp.metrics import WEIGHTS_ENV
from codecsplat_warp.model import CodecSplat
from codecsplat_warp.nn.config import get_preset
from codecsplat_warp.model.pretrained import save_pretrained
from codecsplat_warp.synthetic import make_rig
from test_cli_commands import write_scene

FLOAT32_BYTES = 4
CRC_BYTES = 4


def test_naive_layout_counts_every_field_a_scene_does_not_use():
    rig = make_rig(2, 32, 32, dtype=torch.float32)
    shared = rig.K[:1].expand(2, 3, 3).contiguous()  # one set of intrinsics, one depth range (make_rig's)
    cameras = type(rig)(K=shared, w2c=rig.w2c, near=rig.near, far=rig.far, width=32, height=32)
    streams = [bytes(40), bytes(48)]
    data = pack_bitstream("0123456789abcdef", 64.0, cameras, streams)
    row = naive_layout(data)
    parts = bytes_report(data)
    record = lambda views, shared_fields: 5 + FLOAT32_BYTES * (  # noqa: E731  height, width u16, views u8
        (4 if shared_fields else 4 * views) + 7 * views + (2 if shared_fields else 2 * views))
    framed = lambda payload: (1 if payload < 128 else 2) + CRC_BYTES + payload  # noqa: E731
    assert row["views"] == 2 and row["bytes"] == len(data) == parts["total"]
    assert row["saved_flags"] == NAIVE_VIEW_SLOTS
    assert row["saved_shared"] == framed(record(2, False)) - framed(record(2, True)) == (4 + 2) * FLOAT32_BYTES
    assert row["saved_padding"] == framed(record(8, False)) - framed(record(2, False)) + 6 * framed(0)
    assert row["saved_deflate"] == framed(record(2, True)) - parts["cameras"]
    assert row["saved"] == row["naive_bytes"] - len(data) == sum(v for k, v in row.items() if k.startswith("saved_"))
    assert row["naive_header_cameras"] == 18 + NAIVE_VIEW_SLOTS + framed(record(8, False))


def test_offscreen_scene_culls_exactly_the_moved_gaussians():
    scene = make_scene(Workload("t", 2, 16, 16), torch.device("cpu"))
    full_radii = ours_forward(scene)[3].radii[0].any(dim=-1)
    for placement in ("behind", "beside"):
        moved_scene = move_offscreen(scene, placement, fraction=0.9, seed=1)
        moved = (moved_scene["means"] != scene["means"]).any(dim=-1)
        assert int(moved.sum()) == round(0.9 * len(moved))
        rgb, _, _, meta = ours_forward(moved_scene)
        radii = meta.radii[0].any(dim=-1)
        assert not bool(radii[moved].any()), placement
        assert torch.equal(radii[~moved], full_radii[~moved])
        subset = visible_subset(scene, fraction=0.9, seed=1)
        assert torch.equal(subset["means"], scene["means"][~moved])
        assert torch.equal(ours_forward(subset)[0], rgb), placement  # the moved Gaussians contribute nothing
    with pytest.raises(ValueError, match="placement"):
        move_offscreen(scene, "above")


@pytest.mark.data
@pytest.mark.slow
def test_quick_benchmark_on_a_real_scene(data_root):
    command = [sys.executable, "-m", "codecsplat_warp.cli", "bench", "leaveout", "--quick", "--device", "cpu",
               "--json", "--data", str(data_root), "--scenes", "llff_fortress"]
    done = subprocess.run(command, capture_output=True, text=True)
    assert done.returncode in (0, 1), done.stderr
    result = json.loads(done.stdout)
    assert done.returncode == (0 if result["passed"] else 1)
    assert result["passed"] == all(result["checks"].values())
    assert result["checks"]["pruned_renders_equal"] and result["checks"]["views_coded_without_padding"]
    (pruning,) = result["pruning"]
    assert pruning["scene"] == "llff_fortress" and pruning["max_abs_diff"] <= RENDER_TOLERANCE
    assert pruning["total"] == pruning["transparent"] + pruning["outside_frusta"] + pruning["kept"] == 2 * 32 * 32
    assert min(pruning["prune_ms"], pruning["render_ms"], pruning["render_pruned_ms"]) > 0
    assert [r["placement"] for r in result["offscreen"]] == ["behind", "beside"]
    for row in result["offscreen"]:
        assert row["visible"] <= 0.1 * row["gaussians"] + 1 and row["ratio_fwd"] > 0 and row["ratio_fwd_bwd"] > 0
        assert row["vs_visible_only_fwd"] > 0 and row["vs_visible_only_fwd_bwd"] > 0
    assert [r["case"] for r in result["sh_and_depth"]][1:3] == ["SH degree 3 (K=16)", "K=16 at sh_degree=0"]
    (bitstream,) = result["bitstream"]
    assert bitstream["saved"] == bitstream["naive_bytes"] - bitstream["bytes"] > NAIVE_VIEW_SLOTS
    assert [(r["views"], r["view_streams"]) for r in result["views"]] == [(2, 2), (3, 3)]
    assert set(result["tables"]) == {"a_pruning", "b_offscreen", "c_sh_and_depth", "d_bitstream", "d_views"}


@pytest.mark.slow
def test_decode_prunes_for_given_cameras_and_render_reports_its_pruning(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv(WEIGHTS_ENV, raising=False)
    torch.manual_seed(0)
    save_pretrained(CodecSplat(get_preset("tiny"), codec=True), tmp_path / "tiny.safetensors")
    scene = write_scene(tmp_path / "scene", seed=3)
    common = ["--checkpoint", str(tmp_path / "tiny.safetensors"), "--device", "cpu", "--json"]

    def run(*args: str) -> dict:
        assert main([*args, *common]) == EXIT_OK
        return json.loads(capsys.readouterr().out)

    run("encode", str(scene), "--views", "0,5", "-o", str(tmp_path / "a.csplat"))
    opacity_only = run("decode", str(tmp_path / "a.csplat"), "-o", str(tmp_path / "a.ply"), "--prune")
    assert opacity_only["prune"]["outside_frusta"] == 0
    cameras = str(scene / "cameras.json")
    framed = run("decode", str(tmp_path / "a.csplat"), "-o", str(tmp_path / "b.ply"), "--prune", "--cameras", cameras)
    report = framed["prune"]
    assert report["total"] == opacity_only["prune"]["total"] and report["transparent"] == opacity_only["pruned"]
    assert framed["gaussians"] == report["kept"] == len(read_ply(tmp_path / "b.ply"))
    assert report["kept"] == report["total"] - report["pruned"]
    rendered = run("render", str(tmp_path / "a.csplat"), "--cameras", cameras, "-o", str(tmp_path / "frames"))
    assert rendered["prune"] == report and rendered["seconds"]["prune"] > 0

    assert main(["decode", str(tmp_path / "a.csplat"), "-o", str(tmp_path / "c.ply"), "--cameras", cameras,
                 *common]) == EXIT_USER
    assert "--prune" in capsys.readouterr().err


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU visible to torch")
def test_kernel_times_name_our_kernels_on_cuda():
    """``bench raster --kernels``: per-kernel GPU times of ours, forward and forward+backward (no gsplat here)."""
    from codecsplat_warp.bench.raster import measure_kernels

    result = measure_kernels(Workload("tiny", 1, 32, 32), torch.device("cuda"), 2, 1.0, None, top=20)
    assert set(result) == {"ours fwd", "ours fwd+bwd"}
    for case, expected in (("ours fwd", "composite_forward"), ("ours fwd+bwd", "composite_backward")):
        assert result[case]["total_us"] > 0
        assert any(expected in name for name, _, _ in result[case]["kernels"]), case


def test_gradient_cosine_against_gsplat_is_the_worst_arguments_cosine():
    """``bench raster``'s gradient agreement with gsplat: the smallest cosine over the arguments, so one argument
    whose gradient turns away shows even when the others agree."""
    from codecsplat_warp.bench.raster import gradient_cosine

    ours = (torch.tensor([1.0, 0.0]), torch.tensor([[2.0, 1.0]], dtype=torch.float32))
    assert gradient_cosine(ours, ours) == pytest.approx(1.0, abs=1e-12)
    scaled = (torch.tensor([3.0, 0.0]), 0.5 * ours[1])
    assert gradient_cosine(ours, scaled) == pytest.approx(1.0, abs=1e-12)
    turned = (torch.tensor([3.0, 0.0]), torch.tensor([[1.0, -2.0]]))
    assert gradient_cosine(ours, turned) == pytest.approx(0.0, abs=1e-12)
    with pytest.raises(ValueError):
        gradient_cosine(ours, ours[:1])
