"""``codecsplat bench rdo`` on a tiny model and a procedural scene folder: the curve rows, the trajectory, the
profile's parts, and bad ``--set`` values."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from types import SimpleNamespace

import pytest
import torch

from codecsplat_warp.bench.options import RDO_PROFILE_PARTS
import codecsplat_warp.bench.rdo as bench_rdo
from codecsplat_warp.bench.rdo import parse_settings
from codecsplat_warp.errors import DataError, InputError
from codecsplat_warp.metrics.lpips import WEIGHTS_ENV
from codecsplat_warp.model import CodecSplat
from codecsplat_warp.model.pretrained import save_pretrained
from codecsplat_warp.nn.config import get_preset
from test_cli_commands import write_scene


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench-rdo")
    torch.manual_seed(0)
    model = CodecSplat(get_preset("tiny"), codec=True)
    model.codec.scale_posterior(30.0)
    save_pretrained(model, root / "tiny.safetensors")
    write_scene(root / "scenes" / "a", seed=4)
    return root


def bench(workspace, *args: str) -> dict:
    command = [sys.executable, "-m", "codecsplat_warp.cli", "bench", "rdo", "--device", "cpu", "--json",
               "--checkpoint", str(workspace / "tiny.safetensors"), "--data", str(workspace / "scenes"),
               "--protocol", "scene", *args]
    env = {k: v for k, v in os.environ.items() if k != WEIGHTS_ENV}
    done = subprocess.run(command, capture_output=True, text=True, cwd=workspace, env=env)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def test_the_curve_has_a_row_per_lambda_and_step_count_and_a_trajectory(workspace):
    result = bench(workspace, "--lambdas", "64", "--steps", "0,3", "--trajectory", "--set", "check_every=1",
                   "--plot", str(workspace / "curve.png"))
    coded = [r for r in result["rows"] if r["method"] == "codecsplat"]
    assert [(r["lambda"], r["steps"]) for r in coded] == [(64.0, 0), (64.0, 3)]
    assert "rdo" not in coded[0] and coded[1]["rdo"]["steps"] == 3
    assert [c["step"] for c in coded[1]["trajectory"]] == [0, 1, 2, 3]
    assert all("target_psnr" in c and "cross_psnr" in c for c in coded[1]["trajectory"])
    assert {r["method"] for r in result["rows"]} == {"copy nearest", "codec-free", "codecsplat"}
    assert (workspace / "curve.png").stat().st_size > 10_000
    assert result["settings"] == {"check_every": 1}


def test_the_profile_names_every_part(workspace):
    result = bench(workspace, "--profile", "--profile-steps", "2", "--lambdas", "64")
    profile = result["profile"]
    assert set(profile["parts_ms"]) == set(RDO_PROFILE_PARTS) and len(profile["step_ms_all"]) == 2
    assert profile["parts_ms"]["rasterize"]["forward"] > 0 and profile["parts_ms"]["rasterize"]["backward"] > 0
    assert profile["parts_ms"]["gs_head"]["forward"] > 0 and profile["clock"] == "CPU time"
    top = profile["top"]
    assert 0 < len(top) <= 15 and all(row["ms"] > 0 and row["calls"] >= 1 for row in top)
    assert [row["ms"] for row in top] == sorted((row["ms"] for row in top), reverse=True)


def _event(name: str, device_ms: float, device_type=torch.autograd.DeviceType.CPU, children=()):
    """A stand-in for a profiler event: its name, device kind, own GPU time (us) and host-side children."""
    return SimpleNamespace(name=name, device_type=device_type, self_device_time_total=1e3 * device_ms,
                           cpu_children=list(children), cpu_time_total=0.0)


def test_the_cuda_profile_counts_a_range_once_and_the_decoder_graphs_as_their_own_part():
    projection = _event("projection_kernel_launch", 1.5)
    events = [
        _event("rasterize", 0.0, children=[projection, _event("composite_launch", 2.5)]), projection,
        # the same range as an annotation on the GPU's timeline: its span, not more kernels
        _event("rasterize", 4.2, device_type=torch.autograd.DeviceType.CUDA),
        _event("_ReplayDecoder", 12.0),
        _event("autograd::engine::evaluate_function: _ReplayDecoderBackward", 13.0),
        _event("autograd::engine::evaluate_function: _RasterizeBackward", 9.0),
        _event("autograd::engine::evaluate_function: AddBackward0", 0.25),
    ]
    parts = bench_rdo._step_parts(events, torch.device("cuda"))
    assert parts["rasterize"] == {"forward": 4.0, "backward": 9.0}
    assert parts["decoder_graph"] == {"forward": 12.0, "backward": 13.0}
    assert parts["other"] == {"forward": 0.0, "backward": 0.25}
    assert sum(part["forward"] + part["backward"] for part in parts.values()) == 38.25


@pytest.mark.parametrize("text, match", [("steps=3", "key=value"), ("learning_rate", "key=value"),
                                         ("nonsense=1", "key=value"), ("learning_rate=fast", "not a float")])
def test_bad_settings_are_named(text, match):
    with pytest.raises(InputError, match=match):
        parse_settings(text)


def test_settings_take_their_fields_types():
    assert parse_settings("learning_rate=0.2, check_every=5,precision=bfloat16,cuda_graphs=off") == {
        "learning_rate": 0.2, "check_every": 5, "precision": "bfloat16", "cuda_graphs": False}
    assert parse_settings("cuda_graphs=True") == {"cuda_graphs": True}
    with pytest.raises(InputError, match="not a bool"):
        parse_settings("cuda_graphs=maybe")


def test_workers_give_the_rows_of_one_process(workspace):
    write_scene(workspace / "scenes" / "b", seed=5)
    try:
        args = ("--lambdas", "64,256", "--steps", "0,2")
        one, two = bench(workspace, *args), bench(workspace, *args, "--workers", "2")
    finally:
        import shutil
        shutil.rmtree(workspace / "scenes" / "b")
    # (sample, lambda) pairs are the units: 4 over 2 workers, so both samples' lambdas are split between workers
    assert two["workers"] == 2 and one["workers"] == 1
    order = [(r["scene"], r["method"], r.get("lambda"), r.get("steps")) for r in one["rows"]]
    assert order == [(scene, method, lam, steps) for scene in ("a", "b") for method, lam, steps in
                     [("copy nearest", None, None), ("codec-free", None, None),
                      *(("codecsplat", lam, n) for lam in (64.0, 256.0) for n in (0, 2))]]
    assert [(r["scene"], r["method"], r.get("lambda"), r.get("steps")) for r in two["rows"]] == order
    timing = two["worker_seconds"]
    assert sorted(w["units"] for w in timing) == [2, 2] and len(one["worker_seconds"]) == 1
    assert all(w[key] >= 0 for w in timing + one["worker_seconds"] for key in ("start_s", "load_s", "work_s"))
    assert two["wall_s"] >= max(w["start_s"] + w["load_s"] + w["work_s"] for w in timing) - 1e-3
    for a, b in zip(one["rows"], two["rows"]):
        assert a.get("bytes") == b.get("bytes") and a["psnr"] == pytest.approx(b["psnr"], abs=1e-4)


def _coded(method, lam, steps, seconds, psnr):
    return {"method": method, "lambda": lam, "steps": steps, "seconds": seconds, "psnr": psnr, "lpips_vgg": 0.5,
            "bytes": 4096}


def test_compare_draws_an_earlier_result_beside_this_runs_curves(tmp_path, monkeypatch):
    """Would catch: a compared result drawn without its label or in this run's style, a reference row of it drawn
    as a line of its own, or files that are not bench rdo results taken silently."""
    figures = []
    monkeypatch.setattr(bench_rdo, "save_figure", lambda fig, path: figures.append(fig))
    now = [_coded("codecsplat", 1024.0, k, 0.1 + k / 100, 17 + k / 100) for k in (0, 25)]
    earlier = [{"method": "codec-free", "psnr": 16.9}, *(_coded("codecsplat", 1024.0, k, 0.1 + k / 50, 16.5 + k / 200)
                                                         for k in (0, 25))]
    (tmp_path / "shipped.json").write_text(json.dumps({"summary": earlier}))
    compared = bench_rdo._compared_results(str(tmp_path / "shipped.json"), "curve.png")
    bench_rdo.plot_curve(now, tmp_path / "curve.png", compared)
    lines = {line.get_label(): line for line in figures[0].axes[0].get_lines()}
    assert set(lines) == {"λ=1024", "shipped: λ=1024"}
    assert lines["λ=1024"].get_linestyle() == "-" and lines["shipped: λ=1024"].get_linestyle() == ":"
    assert list(lines["shipped: λ=1024"].get_ydata()) == [16.5, 16.625]
    with pytest.raises(InputError, match="--plot"):
        bench_rdo._compared_results(str(tmp_path / "shipped.json"), None)
    (tmp_path / "other.json").write_text(json.dumps({"rows": []}))
    for bad in ("other.json", "missing.json"):
        with pytest.raises(DataError, match=f"--compare .*{bad}"):
            bench_rdo._compared_results(str(tmp_path / bad), "curve.png")
