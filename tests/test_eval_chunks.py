"""``codecsplat eval`` on RE10K/DL3DV-style ``.torch`` chunks with a pixelSplat evaluation index (issue 20): the
samples the index selects, DepthSplat's depth range, streaming one chunk at a time, resume, the errors, and the
command line end to end. The chunks are written in the test with ``write_chunks``: from procedural scenes (always)
and from real scenes under ``CODECSPLAT_DATA`` (skipped with the reason when unset). Nothing is written outside
pytest's temporary folders."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

import codecsplat_warp.eval.protocols as protocols
from codecsplat_warp.cli import main
from codecsplat_warp.data import ProceduralConfig, load_scene, procedural_scene, resize_and_crop, write_chunks
from codecsplat_warp.errors import DataError, InputError
from codecsplat_warp.eval.evaluate import EvalConfig, Evaluator, evaluate
from codecsplat_warp.eval.protocols import PROTOCOLS, chunk_plan, is_chunk_folder
from codecsplat_warp.eval.report import COPY_NEAREST, Row
from codecsplat_warp.model import CodecSplat
from codecsplat_warp.model.pretrained import save_pretrained
from codecsplat_warp.nn.config import get_preset

SIZE = (48, 32)
RE10K_SMALL = replace(PROTOCOLS["re10k"], width=SIZE[0], height=SIZE[1])
INDEX = {"s0": {"context": [0, 4], "target": [1, 2, 3]}, "s1": None, "s2": {"context": [1, 5], "target": [3]},
         "s3": {"context": [0, 2], "target": [1]}}
"""s1 is skipped (null); s0 and s2 share a chunk, s3 has one of its own."""


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    """Chunks of four procedural scenes (s0, s1, s2 in 000000.torch, s3 in 000001.torch) and the index file."""
    root = tmp_path_factory.mktemp("synthetic")
    scenes = [replace(procedural_scene(seed, ProceduralConfig(width=64, height=40, num_views=6, texture_size=16)),
                      key=f"s{seed}") for seed in range(4)]
    sizes = [sum(len(_jpeg(s, f)) for f in range(6)) for s in scenes]
    write_chunks(scenes, root / "test", max_chunk_bytes=sum(sizes[:3]), progress=False)
    (root / "index.json").write_text(json.dumps(INDEX))
    return root


def _jpeg(scene, frame: int) -> bytes:
    from codecsplat_warp.data.chunks import scene_to_record

    return bytes(scene_to_record(scene.select([frame]))["images"][0].numpy())


@pytest.fixture(scope="module")
def tiny_model():
    torch.manual_seed(0)
    return CodecSplat(get_preset("tiny"), codec=True).eval()


def test_the_index_selects_the_samples_in_chunk_order_with_depthsplat_depth_ranges(synthetic):
    data = synthetic / "test"
    assert is_chunk_folder(data) and not is_chunk_folder(synthetic)
    assert json.loads((data / "index.json").read_text()) == {"s0": "000000.torch", "s1": "000000.torch",
                                                            "s2": "000000.torch", "s3": "000001.torch"}
    plan = chunk_plan(data, synthetic / "index.json", RE10K_SMALL)
    assert plan.keys == [("s0", (0, 4), (1, 2, 3)), ("s2", (1, 5), (3,)), ("s3", (0, 2), (1,))]
    samples = list(plan.load(0))
    assert [(s.scene, s.context, s.target) for s in samples] == [(k[0], list(k[1]), list(k[2])) for k in plan.keys]
    first = samples[0]
    assert first.context_images.shape == (2, 3, 32, 48) and first.target_images.shape == (3, 3, 32, 48)
    assert first.context_images.dtype == torch.float32 and 0 <= float(first.context_images.min()) < 1
    assert torch.all(first.context_cameras.near == 0.5) and torch.all(first.target_cameras.far == 100.0)
    dl3dv = next(chunk_plan(data, synthetic / "index.json", replace(PROTOCOLS["dl3dv"], width=48, height=32)).load(0))
    assert torch.all(dl3dv.context_cameras.near == 0.5) and torch.all(dl3dv.context_cameras.far == 200.0)
    assert [k[0] for k in chunk_plan(data, synthetic / "index.json", RE10K_SMALL, scenes=("s3",)).keys] == ["s3"]


def test_scenes_stream_one_chunk_at_a_time(synthetic, monkeypatch):
    reads = []
    real_read = protocols.read_chunk
    monkeypatch.setattr(protocols, "read_chunk", lambda file, near, far: reads.append(file.name) or real_read(file, near, far))
    plan = chunk_plan(synthetic / "test", synthetic / "index.json", RE10K_SMALL)
    assert reads == []  # planning reads only the two index files
    stream = plan.load(0)
    next(stream)
    assert reads == ["000000.torch"]
    next(stream), next(stream)
    assert reads == ["000000.torch", "000001.torch"]  # each chunk once, the second only when its sample is due
    reads.clear()
    assert [s.scene for s in plan.load(2)] == ["s3"] and reads == ["000001.torch"]  # resuming skips finished chunks


def _write_index(path, entries) -> str:
    path.write_text(json.dumps(entries))
    return str(path)


def test_clear_errors_for_missing_scenes_frames_and_foreign_indices(synthetic, tmp_path):
    data = synthetic / "test"
    with pytest.raises(DataError, match=r"names none of the 4 scene\(s\) in .*index.json \(it names 5-abc, 5-def; "
                                        r"is it the index of another dataset\?\)"):
        chunk_plan(data, _write_index(tmp_path / "a.json", {"5-abc": {"context": [0, 1], "target": [2]},
                                                            "5-def": {"context": [0, 1], "target": [2]}}), RE10K_SMALL)
    with pytest.raises(DataError, match=r"scene\(s\) gone are not in .*index.json"):
        chunk_plan(data, _write_index(tmp_path / "b.json", {**INDEX, "gone": {"context": [0, 1], "target": [2]}}),
                   RE10K_SMALL)
    plan = chunk_plan(data, _write_index(tmp_path / "c.json", {"s0": {"context": [0, 1], "target": [2]},
                                                               "s2": {"context": [0, 9], "target": [7]}}), RE10K_SMALL)
    stream = plan.load(0)
    next(stream)  # the frames are checked when the scene is read
    with pytest.raises(DataError, match=r"scene 's2' has 6 frames \(0..5\), the index asks for frame\(s\) 7, 9"):
        next(stream)
    with pytest.raises(DataError, match="selects no scene s1"):  # null in the index
        chunk_plan(data, synthetic / "index.json", RE10K_SMALL, scenes=("s1",))
    with pytest.raises(InputError, match="use --protocol re10k or dl3dv"):
        chunk_plan(data, synthetic / "index.json", PROTOCOLS["scene"])
    moved = tmp_path / "moved"
    moved.mkdir()
    for name in ("000000.torch", "000001.torch"):
        (moved / name).write_bytes((data / name).read_bytes())
    (moved / "index.json").write_text(json.dumps({"s0": "000001.torch", "s2": "000000.torch", "s3": "000001.torch"}))
    with pytest.raises(DataError, match=r"puts scene 's0' in 000001.torch, which does not hold it"):
        list(chunk_plan(moved, _write_index(tmp_path / "d.json", {"s0": INDEX["s0"]}), RE10K_SMALL).load(0))


def _config(synthetic, out, **changes) -> EvalConfig:
    return EvalConfig(data=str(synthetic / "test"), index=str(synthetic / "index.json"), out=str(out), protocol="re10k",
                      size=SIZE, lambdas=(64.0,), baselines=(), progress=False, **changes)


def test_chunk_eval_runs_every_indexed_sample_with_the_floor(synthetic, tiny_model, tmp_path):
    result = evaluate(tiny_model, _config(synthetic, tmp_path / "out"), torch.device("cpu"))
    assert result["scenes"] == ["s0", "s2", "s3"] and (result["samples_done"], result["samples_total"]) == (3, 3)
    assert [r["scene"] for r in result["rows"] if r["method"] == COPY_NEAREST] == ["s0", "s2", "s3"]
    assert result["plan"][0] == ["s0", [0, 4], [1, 2, 3]]
    assert result["config"]["protocol"]["near"] == 0.5 and result["config"]["protocol"]["far"] == 100.0
    assert "| Copy nearest context view | no bitstream | 0.00 KiB |" in result["tables"]["table1"]
    with pytest.raises(InputError, match="chunk folder: give the evaluation index"):
        evaluate(tiny_model, replace(_config(synthetic, tmp_path / "x"), index=None), torch.device("cpu"))


def test_an_interrupted_chunk_eval_resumes_where_it_stopped(synthetic, tiny_model, tmp_path, monkeypatch):
    calls = []

    def run(self, sample, progress=None, groups=None):
        if len(calls) == 2 and interrupt:
            raise KeyboardInterrupt
        calls.append(sample.scene)
        return [Row(sample.scene, "CodecSplat", "λ=64", 100, {"psnr": 20.0 + len(calls)}, 1.0, 1.0, 1.0, lam=64.0)]

    monkeypatch.setattr(Evaluator, "run", run)
    monkeypatch.setattr(Evaluator, "warm_up", lambda self, sample: None)
    out = tmp_path / "out"
    interrupt = True
    with pytest.raises(KeyboardInterrupt):
        evaluate(tiny_model, _config(synthetic, out), torch.device("cpu"))
    assert json.loads((out / "results.json").read_text())["samples_done"] == 2
    interrupt = False
    result = evaluate(tiny_model, _config(synthetic, out), torch.device("cpu"))
    assert calls == ["s0", "s2", "s3"]  # the finished samples are not run again
    assert [r["metrics"]["psnr"] for r in result["rows"]] == [21.0, 22.0, 23.0] and result["samples_done"] == 3
    assert evaluate(tiny_model, _config(synthetic, out), torch.device("cpu"))["rows"] == result["rows"]  # all done
    assert calls == ["s0", "s2", "s3"]
    with pytest.raises(DataError, match=r"holds another evaluation \(options differ\).*--restart"):
        evaluate(tiny_model, replace(_config(synthetic, out), lambdas=(128.0,)), torch.device("cpu"))
    restarted = evaluate(tiny_model, replace(_config(synthetic, out), resume=False), torch.device("cpu"))
    assert calls[3:] == ["s0", "s2", "s3"] and [r["metrics"]["psnr"] for r in restarted["rows"]] == [24.0, 25.0, 26.0]


def test_eval_command_on_chunks_as_the_readme_shows(synthetic, tiny_model, tmp_path, capsys):
    save_pretrained(tiny_model, tmp_path / "tiny.safetensors")
    args = ["eval", "--data", str(synthetic / "test"), "--index", str(synthetic / "index.json"), "--protocol", "re10k",
            "--size", "48x32", "--lambdas", "64", "--baselines", "none", "-o", str(tmp_path / "out"), "--device", "cpu",
            "--checkpoint", str(tmp_path / "tiny.safetensors"), "--json"]
    assert main(args) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["samples_done"] == 3 and (tmp_path / "out" / "tables.md").is_file()
    assert main(args[:-1] + ["--size", "47x32"]) == 1
    assert "multiples of 4" in capsys.readouterr().err
    assert main([*args[:4], str(tmp_path / "nowhere.json"), *args[5:]]) == 1
    assert "nowhere.json" in capsys.readouterr().err


@pytest.fixture(scope="module")
def real_chunks(data_root, tmp_path_factory):
    """Two real scenes (their first 6 frames at 64x48) as chunks, and an index for them."""
    scenes = []
    for name in ("cap_milk", "llff_horns"):
        scene = load_scene(data_root / name)
        frames = list(range(6))
        images, cameras = resize_and_crop(scene.decoded_images(frames), scene.cameras.select(frames), 64, 48)
        scenes.append(replace(scene.select(frames), images=images, cameras=cameras, key=name))
    root = tmp_path_factory.mktemp("real")
    write_chunks(scenes, root / "test", max_chunk_bytes=1, progress=False)
    (root / "index.json").write_text(json.dumps({"cap_milk": {"context": [0, 5], "target": [2, 3]}, "llff_horns": None,
                                                 "cap_fox": None}))
    return root


@pytest.mark.data
def test_chunk_eval_on_real_scenes(real_chunks, tiny_model, tmp_path):
    result = evaluate(tiny_model, _config(real_chunks, tmp_path / "out"), torch.device("cpu"))
    assert result["scenes"] == ["cap_milk"] and result["plan"] == [["cap_milk", [0, 5], [2, 3]]]
    floor = next(s for s in result["summary"] if s["method"] == COPY_NEAREST)
    assert floor["bytes"] == 0 and 5.0 < floor["psnr"] < 60.0


def test_renders_picture_every_method_of_each_sample(synthetic, tiny_model, tmp_path):
    import imageio.v3 as iio

    config = _config(synthetic, tmp_path / "out", scenes=("s0",), renders=True)
    result = evaluate(tiny_model, config, torch.device("cpu"))
    assert [(r["method"], r["setting"]) for r in result["rows"]] == [
        (COPY_NEAREST, "no bitstream"), ("CodecSplat", "λ=64"), ("CodecSplat w/o codec→PLY", "float32")]
    picture = iio.imread(tmp_path / "out" / "renders" / "s0-1.png")
    assert picture.ndim == 3 and picture.shape[1] > picture.shape[0]  # 4 columns (truth + 3 methods), 3 target rows
    assert sorted(p.name for p in (tmp_path / "out" / "renders").iterdir()) == ["s0-1.png"]


def test_the_evaluator_keeps_one_render_per_row_when_asked(synthetic, tiny_model):
    from codecsplat_warp.metrics.image import ImageMetrics

    sample = next(iter(chunk_plan(synthetic / "test", synthetic / "index.json", RE10K_SMALL, ("s0",)).load(0)))
    metrics = ImageMetrics(None, torch.device("cpu"))
    keeping = Evaluator(tiny_model, metrics, (64.0,), (), torch.device("cpu"), keep_renders=True)
    rows = keeping.run(sample)
    targets, height, width = sample.target_images.shape[0], *sample.target_images.shape[-2:]
    assert len(keeping.renders) == len(rows) == 3
    assert all(r.shape == (targets, height, width, 3) and r.dtype == np.uint8 for r in keeping.renders)
    plain = Evaluator(tiny_model, metrics, (64.0,), (), torch.device("cpu"))
    plain.run(sample)
    assert plain.renders == []
