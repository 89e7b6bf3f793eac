"""Pieces of ``codecsplat eval``: view selection, scene discovery, option checks, summaries and the tables."""

from __future__ import annotations

import json

import pytest
import torch

from codecsplat_warp.cameras import Cameras, intrinsics_matrix
from codecsplat_warp.errors import DataError, InputError
from codecsplat_warp.data import split_context_targets
from codecsplat_warp.eval.evaluate import EvalConfig, evaluate
from codecsplat_warp.eval.protocols import PROTOCOLS, find_scenes, folder_index_plan, select_scenes
from codecsplat_warp.eval.report import Row, format_bytes, summarize, table1, table2, table3
from test_cli_commands import write_scene


def _line_of_cameras(count: int) -> Cameras:
    f = torch.full((count,), 20.0, dtype=torch.float64)
    c2w = torch.eye(4, dtype=torch.float64).repeat(count, 1, 1)
    c2w[:, 0, 3] = torch.arange(count, dtype=torch.float64)
    return Cameras.from_c2w(intrinsics_matrix(f, f, f * 0 + 8, f * 0 + 8), c2w, torch.full((count,), 0.1),
                            torch.full((count,), 10.0), 16, 16)


def test_evaluation_views_split_the_anchors_neighbourhood():
    cameras = _line_of_cameras(10)  # centres at x = 0..9: by distance to view 4 the order is 4, 3, 5, 2, 6, 1, ...
    # the cluster around the anchor grows until 3 views lie between the anchor and the context's far end
    assert split_context_targets(cameras, anchor=4, num_context=2, num_target=3) == ([4, 0], [2, 1, 3])
    context, target = split_context_targets(cameras, anchor=0, num_context=3, num_target=2)
    assert sorted(context) == [0, 2, 4] and target == [1, 3]
    assert split_context_targets(cameras, anchor=4, num_context=2, num_target=1) == ([4, 2], [3])
    assert split_context_targets(cameras, anchor=4, num_context=2, num_target=1, spread=3) == ([4, 1], [2])  # wider


def test_split_leaves_out_views_that_look_elsewhere():
    cameras = _line_of_cameras(10)
    c2w = cameras.c2w.clone()
    c2w[3, :3, :3] = torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]], dtype=torch.float64)  # turned 90°
    turned = Cameras.from_c2w(cameras.K, c2w, cameras.near, cameras.far, 16, 16)
    context, target = split_context_targets(turned, anchor=4, num_context=2, num_target=3)
    assert 3 not in context + target and (context, target) == ([4, 9], [6, 7, 5])
    with pytest.raises(DataError, match="need 11"):
        split_context_targets(cameras, 0, 8, 3)


def test_find_scenes(tmp_path):
    write_scene(tmp_path / "root" / "b", seed=1, views=3)
    write_scene(tmp_path / "root" / "a", seed=2, views=3)
    (tmp_path / "root" / "notes").mkdir()
    assert [p.name for p in find_scenes(tmp_path / "root")] == ["a", "b"]
    assert find_scenes(tmp_path / "root" / "a") == [tmp_path / "root" / "a"]
    with pytest.raises(DataError, match="does not exist"):
        find_scenes(tmp_path / "nowhere")
    with pytest.raises(DataError, match="no pose file"):
        find_scenes(tmp_path / "root" / "notes")
    found = find_scenes(tmp_path / "root")
    assert select_scenes(found, ()) == found
    assert [p.name for p in select_scenes(found, ("b",))] == ["b"]
    with pytest.raises(DataError, match="c not found; found a, b"):
        select_scenes(found, ("b", "c"))


def test_scenes_pick_entries_of_a_folder_index(tmp_path):
    write_scene(tmp_path / "root" / "a", seed=1, views=4)
    write_scene(tmp_path / "root" / "b", seed=2, views=4)
    index = tmp_path / "index.json"
    index.write_text(json.dumps({"a": {"context": [0, 2], "target": [1]}, "b": {"context": [0, 3], "target": [2]}}))
    found = find_scenes(tmp_path / "root")
    assert [k[0] for k in folder_index_plan(found, index, PROTOCOLS["scene"]).keys] == ["a", "b"]
    assert [k[0] for k in folder_index_plan(found, index, PROTOCOLS["scene"], ("b",)).keys] == ["b"]
    with pytest.raises(DataError, match="selects no scene"):
        folder_index_plan(found, index, PROTOCOLS["scene"], ("c",))
    with pytest.raises(DataError, match="not in the data"):  # without --scenes every indexed scene must exist
        folder_index_plan(found[:1], index, PROTOCOLS["scene"])


@pytest.mark.parametrize("changes,match", [({"protocol": "llff"}, "unknown protocol"),
                                           ({"baselines": ("zip",)}, "unknown baseline"),
                                           ({"lambdas": (8.0,)}, "lambda"), ({"lambdas": ()}, "at least one"),
                                           ({"target_views": 0}, "target views"), ({"samples_per_scene": 0}, "samples"),
                                           ({"png_sh_clusters": 70000}, "sh_clusters")])
def test_bad_options_are_input_errors_before_any_work(tmp_path, changes, match):
    config = EvalConfig(data=str(tmp_path / "nowhere"), out=str(tmp_path / "out"), **changes)
    with pytest.raises(InputError, match=match):
        evaluate(None, config, torch.device("cpu"))
    assert not (tmp_path / "out").exists()


def _row(scene, method, setting, size, psnr, lam=None, seconds=(1.0, 2.0, 3.0), self_psnr=None, depth=None):
    return Row(scene, method, setting, size, {"psnr": psnr, "ssim": 0.5}, *seconds, lam=lam,
               self_render=None if self_psnr is None else {"psnr": self_psnr, "ssim": 0.9}, depth=depth)


def test_summary_means_and_paper_tables():
    scored = {"abs_rel": 0.2, "delta_1_25": 0.5}
    rows = [_row("a", "CodecSplat", "λ=16", 1000, 20.0, 16.0, self_psnr=24.0, depth=scored),
            _row("b", "CodecSplat", "λ=16", 3000, 22.0, 16.0, self_psnr=26.0, depth={}),  # no reference depth
            _row("a", "CodecSplat", "λ=1024", 5000, 25.0, 1024.0, (1.0, 4.0, 5.0), self_psnr=30.0, depth={}),
            _row("a", "CodecSplat w/o codec→PNG", "K_SH=8192", 3 * 2**20, 26.0, self_psnr=31.0),
            _row("a", "Copy nearest context view", "no bitstream", 0, 15.0, seconds=(0.0, 0.0, 0.0))]
    summary = summarize(rows)
    assert [(s["method"], s["samples"]) for s in summary] == [("CodecSplat", 2), ("CodecSplat", 1),
                                                               ("CodecSplat w/o codec→PNG", 1),
                                                               ("Copy nearest context view", 1)]
    assert summary[0]["bytes"] == 2000 and summary[0]["psnr"] == 21.0 and summary[0]["self_psnr"] == 25.0
    assert (summary[0]["depth_samples"], summary[0]["depth_abs_rel"]) == (1, 0.2)  # the mean over scored samples
    assert summary[1]["depth_samples"] == 0 and "depth_abs_rel" not in summary[1]
    assert "depth_samples" not in summary[2] and not summary[3]["gaussians"]
    first = table1(summary).splitlines()
    assert first[0].startswith("| Method | Codec Setting | Bytes/scene") and "LPIPS-Alex" in first[0]
    assert first[0].endswith("| Self-render PSNR ↑ | Depth AbsRel ↓ | Depth δ<1.25 ↑ |")
    assert first[2] == ("| CodecSplat w/o codec→PNG | K_SH=8192 | 3.00 MiB | 26.00 | 0.500 | n/a | n/a | 31.00 | - "
                        "| - |")
    assert first[3] == "| Copy nearest context view | no bitstream | 0.00 KiB | 15.00 | 0.500 | n/a | n/a | - | - | - |"
    assert first[4] == "| CodecSplat | λ=16 | 1.95 KiB | 21.00 | 0.500 | n/a | n/a | 25.00 | 0.200 | 0.500 |"
    assert first[5].endswith("| 30.00 | n/a | n/a |")  # a depth map, but no sample had reference depth
    third = table3(summary).splitlines()
    assert third[4] == "| CodecSplat | λ=16 | 25.00 | 0.900 | n/a | n/a | 0.200 | 0.500 | 1 |"
    second = table2(summary).splitlines()
    assert second[-1] == "| CodecSplat | λ=16,…,1024 | 1.000 | 3.000 | 4.000 |"
    assert format_bytes(1536) == "1.50 KiB" and format_bytes(2**20) == "1.00 MiB"


def test_an_interrupted_eval_keeps_the_samples_it_finished(tmp_path, monkeypatch):
    from codecsplat_warp.eval.evaluate import Evaluator
    from codecsplat_warp.model import CodecSplat
    from codecsplat_warp.nn.config import get_preset

    for name, seed in (("a", 1), ("b", 2)):
        write_scene(tmp_path / "data" / name, seed=seed, views=3)

    def run_once(self, sample, progress=None, groups=None):
        if (tmp_path / "out" / "results.json").exists():
            raise KeyboardInterrupt
        return [_row(sample.scene, "CodecSplat", "λ=16", 100, 20.0, 16.0)]

    monkeypatch.setattr(Evaluator, "run", run_once)
    monkeypatch.setattr(Evaluator, "warm_up", lambda self, sample: None)
    config = EvalConfig(data=str(tmp_path / "data"), out=str(tmp_path / "out"), protocol="scene", target_views=1,
                        progress=False)
    with pytest.raises(KeyboardInterrupt):
        evaluate(CodecSplat(get_preset("tiny"), codec=True), config, torch.device("cpu"))
    saved = json.loads((tmp_path / "out" / "results.json").read_text())
    assert (saved["samples_done"], saved["samples_total"]) == (1, 2) and [r["scene"] for r in saved["rows"]] == ["a"]
    assert saved["summary"][0]["psnr"] == 20.0 and not (tmp_path / "out" / "tables.md").exists()
