"""``codecsplat eval``'s image-codec rows (WebP / JPEG + codec-free) and RDO rows (CodecSplat RDO beside the
amortised CodecSplat): what each row runs and counts, the progress units, results.json and the tables, resuming,
and the plots. A tiny coding model on tiny procedural scene folders, on the CPU."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

import codecsplat_warp.eval.report as report
from codecsplat_warp.baselines import ImageCodec
from codecsplat_warp.cli import main
from codecsplat_warp.errors import DataError, InputError
from codecsplat_warp.eval.evaluate import (EvalConfig, Evaluator, RDOSetting, check_config, evaluate, layout_rows,
                                           row_layout)
from codecsplat_warp.eval.protocols import PROTOCOLS, find_scenes, index_samples
from codecsplat_warp.eval.report import (BACKBONE, CODECSPLAT, COPY_NEAREST, equal_bytes, plot_distortion_vs_time,
                                         plot_rate_distortion, table1, table2, table4)
from codecsplat_warp.export.video import to_uint8_frames
from codecsplat_warp.metrics.image import ImageMetrics
from codecsplat_warp.choices import RDO_CROSS_VIEW_MIN_STEPS, RDO_PRESETS
from codecsplat_warp.model.pretrained import save_pretrained
from conftest import LPIPS_WEIGHTS, needs_lpips, tiny_coding_model
from test_cli_commands import write_indexed_scenes

INDEX = {"a": {"context": [0, 2], "target": [1]}, "b": {"context": [0, 2], "target": [1]}}


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """Scene folders a and b (3 procedural views at 48x32) and an index with one sample each."""
    root = tmp_path_factory.mktemp("scenes")
    return write_indexed_scenes(root, INDEX, views=3)


@pytest.fixture(scope="module")
def model():
    return tiny_coding_model(0)


class _Counter:
    """Counts progress-bar units."""

    n = 0

    def update(self, n: int) -> None:
        self.n += n


def test_image_codec_and_rdo_rows_of_one_sample(scenes, model, monkeypatch):
    monkeypatch.setitem(RDO_PRESETS, "medium", 0.25)  # a preset's count, kept tiny (the least, 5 steps for 2 views)
    monkeypatch.setitem(RDO_CROSS_VIEW_MIN_STEPS, "medium", 5)
    sample = index_samples(find_scenes(scenes / "data"), scenes / "index.json", PROTOCOLS["scene"])[0]
    codecs = [ImageCodec("webp", 5), ImageCodec("webp", 90), ImageCodec("jpeg", 10)]
    rdo = [RDOSetting(preset="medium"), RDOSetting(steps=1)]
    evaluator = Evaluator(model, ImageMetrics(None), (64.0,), (), torch.device("cpu"), keep_renders=True,
                          image_codecs=codecs, rdo=rdo)
    inputs = []
    forward = model.forward
    monkeypatch.setattr(model, "forward", lambda images, cameras: inputs.append(images) or forward(images, cameras))
    progress = _Counter()
    rows = evaluator.run(sample, progress)
    assert [(r.method, r.setting) for r in rows] == [
        (COPY_NEAREST, "no bitstream"), (CODECSPLAT, "λ=64"), ("CodecSplat RDO (medium)", "λ=64"),
        ("CodecSplat RDO (1 step)", "λ=64"), (BACKBONE + "→PLY", "float32"), ("WebP + codec-free", "q=5"),
        ("WebP + codec-free", "q=90"), ("JPEG + codec-free", "q=10")]
    assert progress.n == len(rows) == len(evaluator.renders)
    assert row_layout((64.0,), (), codecs, rdo) == ["base", "base", "medium λ=64", "1 step λ=64"] + ["base"] * 4
    amortised, medium, one = rows[1:4]
    assert amortised.rdo is None and (medium.rdo["steps"], one.rdo["steps"]) == (5, 1)
    assert medium.compress_s > medium.rdo["seconds"] > 0  # the optimisation is compress time
    # every image row: the files plus the header and cameras of the CodecSplat bitstream; the model saw the decoded
    # photographs (the codec-free row saw the originals)
    photographs = to_uint8_frames(sample.context_images)
    assert torch.equal(inputs[0], sample.context_images)
    for row, codec, seen in zip(rows[5:], codecs, inputs[1:], strict=True):
        files = codec.encode(photographs)
        assert row.parts == {"header": amortised.parts["header"], "cameras": amortised.parts["cameras"],
                             "view0": len(files[0]), "view1": len(files[1]), "total": row.bytes}
        assert row.bytes == sum(map(len, files)) + amortised.parts["header"] + amortised.parts["cameras"]
        assert torch.equal(seen, codec.decode(files)) and not torch.equal(seen, sample.context_images)
        assert row.quality == codec.quality and row.self_render["psnr"] > 0 and row.depth == {}
        assert min(row.gen_s, row.compress_s, row.decompress_s) > 0
    assert rows[5].bytes < rows[6].bytes
    # one row group alone: its rows only, the others (the codec-free network of the base rows too) not run
    alone = evaluator.run(sample, progress, groups={"1 step λ=64"})
    assert len(inputs) == 1 + len(codecs) and progress.n == len(rows) + 1 and len(evaluator.renders) == 1
    assert [(r.method, r.setting, r.bytes, r.metrics) for r in alone] == [(one.method, one.setting, one.bytes,
                                                                          one.metrics)]


@needs_lpips
def test_perceptual_rdo_rows_optimise_with_the_lpips_vgg_term(scenes, model, monkeypatch):
    from codecsplat_warp.model import rdo as rdo_module

    sample = index_samples(find_scenes(scenes / "data"), scenes / "index.json", PROTOCOLS["scene"])[0]
    settings = check_config(replace(_config(scenes, "unused"), rdo_presets=(), rdo_steps=(1,),
                                    rdo_perceptual=(0.5,), lpips_weights=str(LPIPS_WEIGHTS))).rdo
    assert [s.name for s in settings] == ["1 step", "1 step, LPIPS 0.5"]
    evaluator = Evaluator(model, ImageMetrics(LPIPS_WEIGHTS), (64.0,), (), torch.device("cpu"), rdo=settings)
    terms = []
    loss = rdo_module.rdo_loss

    def spy(*args, **kwargs):
        value, parts = loss(*args, **kwargs)
        terms.append("perceptual" in parts)
        return value, parts

    monkeypatch.setattr(rdo_module.loop, "rdo_loss", spy)  # where the loop looks it up
    rows = evaluator.run(sample, groups={s.group(64.0) for s in settings})
    assert [r.method for r in rows] == ["CodecSplat RDO (1 step)", "CodecSplat RDO (1 step, LPIPS 0.5)"]
    # each run: the start measured, one step, the end measured; only the second with the perceptual term
    assert terms == [False] * 3 + [True] * 3
    assert all("lpips_vgg" in r.metrics for r in rows)


def _config(scenes, out, **changes) -> EvalConfig:
    config = EvalConfig(data=str(scenes / "data"), index=str(scenes / "index.json"), out=str(out), protocol="scene",
                        lambdas=(64.0,), baselines=("webp", "jpeg"), webp_qualities=(5, 50), jpeg_qualities=(5,),
                        rdo_presets=("medium",), rdo_steps=(3,), progress=False)
    return replace(config, **changes)


def _fake_run(calls: list, interrupt_at: str | None):
    """Evaluator.run that records the sample and returns one row per unit of work, raising KeyboardInterrupt
    at scene ``interrupt_at``."""

    def run(self, sample, progress=None, groups=None):
        if sample.scene == interrupt_at:
            raise KeyboardInterrupt
        calls.append(sample.scene)
        layout = row_layout(self.lambdas, self.baselines, self.image_codecs, self.rdo)
        return [report.Row(sample.scene, "m", str(i), 1, {"psnr": 20.0}, 1.0, 1.0, 1.0)
                for i in layout_rows(layout, groups)]

    return run


def test_the_new_options_belong_to_the_evaluation_a_run_resumes(scenes, model, tmp_path, monkeypatch):
    monkeypatch.delenv("CODECSPLAT_LPIPS_WEIGHTS", raising=False)  # no LPIPS: faster
    monkeypatch.setattr(Evaluator, "warm_up", lambda self, sample: None)
    calls: list[str] = []
    monkeypatch.setattr(Evaluator, "run", _fake_run(calls, interrupt_at="b"))
    with pytest.raises(KeyboardInterrupt):
        evaluate(model, _config(scenes, tmp_path), torch.device("cpu"))
    saved = json.loads((tmp_path / "results.json").read_text())
    assert saved["samples_done"] == 1 and len(saved["rows"]) == 2 + 2 + 1 + 2 + 1  # floor, λ x 3, PLY, images
    assert saved["rdo"] == [{"method": "CodecSplat RDO (medium)", "preset": "medium",
                             "steps": RDOSetting(preset="medium").resolved_steps, "seed": 0, "perceptual": 0.0},
                            {"method": "CodecSplat RDO (3 steps)", "preset": "fast", "steps": 3, "seed": 0,
                             "perceptual": 0.0}]
    monkeypatch.setattr(Evaluator, "run", _fake_run(calls, interrupt_at=None))
    assert evaluate(model, _config(scenes, tmp_path), torch.device("cpu"))["samples_done"] == 2
    assert calls == ["a", "b"]  # resumed: a is not run again
    for changes in ({"webp_qualities": (5,)}, {"jpeg_qualities": (5, 20)}, {"rdo_presets": ()}, {"rdo_steps": (4,)},
                    {"rdo_seed": 1}):
        with pytest.raises(DataError, match=r"\(options(, RDO steps)? differ\)"):
            evaluate(model, _config(scenes, tmp_path, **changes), torch.device("cpu"))
    monkeypatch.setitem(RDO_PRESETS, "medium", RDO_PRESETS["medium"] * 2)  # another version's preset
    with pytest.raises(DataError, match=r"\(RDO steps differ\)"):
        evaluate(model, _config(scenes, tmp_path), torch.device("cpu"))
    assert calls == ["a", "b"]


@pytest.mark.parametrize("changes,match", [({"webp_qualities": ()}, "at least one webp quality"),
                                           ({"jpeg_qualities": (0,)}, r"JPEG quality .*\[1, 100\]"),
                                           ({"webp_qualities": (5, 5)}, "once, got 5"),
                                           ({"rdo_presets": ("fast",)}, "takes no optimisation step"),
                                           ({"rdo_presets": ("fastest",)}, "unknown RDO preset"),
                                           ({"rdo_steps": (0,)}, "takes no optimisation step"),
                                           ({"rdo_steps": (-2,)}, "integer >= 0"),
                                           ({"rdo_perceptual": (0.0,)}, "must be > 0"),
                                           ({"rdo_perceptual": (0.1, 0.1)}, "once, got 0.1"),
                                           ({"rdo_presets": (), "rdo_steps": (), "rdo_perceptual": (0.1,)},
                                            "need an RDO preset or step count"),
                                           ({"rdo_perceptual": (0.1,), "lpips_weights": "nowhere"},
                                            "lpips_vgg.safetensors does not exist")])
def test_bad_image_qualities_and_rdo_settings_are_input_errors_before_any_work(tmp_path, changes, match):
    with pytest.raises(InputError, match=match):
        evaluate(None, _config(tmp_path / "nowhere", tmp_path / "out", **changes), torch.device("cpu"))
    assert not (tmp_path / "out").exists()


def test_eval_command_writes_the_new_rows_into_results_and_tables(scenes, model, tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("CODECSPLAT_LPIPS_WEIGHTS", raising=False)  # no LPIPS: faster
    save_pretrained(model, tmp_path / "tiny.safetensors")
    args = ["eval", "--data", str(scenes / "data"), "--index", str(scenes / "index.json"), "--protocol", "scene",
            "--scenes", "a", "--lambdas", "64", "--baselines", "jpeg,webp", "--webp-qualities", "5,50",
            "--jpeg-qualities", "20", "--rdo-steps", "1", "-o", str(tmp_path / "out"), "--device", "cpu",
            "--checkpoint", str(tmp_path / "tiny.safetensors"), "--json"]
    assert main(args) == 0
    result = json.loads(capsys.readouterr().out)
    assert [(s["method"], s["setting"]) for s in result["summary"]] == [
        (COPY_NEAREST, "no bitstream"), (CODECSPLAT, "λ=64"), ("CodecSplat RDO (1 step)", "λ=64"),
        (BACKBONE + "→PLY", "float32"), ("JPEG + codec-free", "q=20"), ("WebP + codec-free", "q=5"),
        ("WebP + codec-free", "q=50")]
    saved = json.loads((tmp_path / "out" / "results.json").read_text())
    assert saved["config"]["webp_qualities"] == [5, 50] and saved["config"]["rdo_steps"] == [1]
    assert [r["quality"] for r in saved["rows"]][-3:] == [20, 5, 50] and saved["rows"][2]["rdo"]["steps"] == 1
    markdown = (tmp_path / "out" / "tables.md").read_text()
    assert "## Table 4: at equal bytes" in markdown and result["tables"]["table4"] == "-"  # one lambda: no curve
    for line in ("| JPEG + codec-free | q=20 |", "| WebP + codec-free | q=5,…,50 |",
                 "| CodecSplat RDO (1 step) | λ=64 |", "GS generation of the image codecs runs at the receiver",
                 "CodecSplat RDO (1 step): 1 step;"):
        assert line in markdown, line
    assert main(args[:-1]) == 0  # everything done: resumes without running a sample
    assert main([*args[:-1], "--rdo-seed", "1"]) == 1
    assert "(options differ)" in capsys.readouterr().err
    assert main([*args[:-1], "--webp-qualities", "5,x"]) == 1
    assert "--webp-qualities must be a comma-separated list of numbers" in capsys.readouterr().err


def _entry(method, setting, size, psnr, lam=None, quality=None, seconds=(1.0, 2.0, 3.0)):
    return {"method": method, "setting": setting, "lam": lam, "quality": quality, "bytes": size, "psnr": psnr,
            "ssim": 0.5, "gen_s": seconds[0], "compress_s": seconds[1], "decompress_s": seconds[2]}


SUMMARY = [
    _entry(COPY_NEAREST, "no bitstream", 0, 15.0, seconds=(0.0, 0.0, 0.0)),
    _entry(CODECSPLAT, "λ=1024", 9000, 21.0, lam=1024.0), _entry(CODECSPLAT, "λ=16", 2000, 19.0, lam=16.0),
    _entry("CodecSplat RDO (slow)", "λ=16", 1900, 19.5, lam=16.0, seconds=(1.0, 40.0, 3.0)),
    _entry("CodecSplat RDO (slow)", "λ=1024", 8000, 21.5, lam=1024.0, seconds=(1.0, 60.0, 3.0)),
    _entry(BACKBONE + "→PLY+Deflate", "16/8-bit", 3 * 2**20, 22.0),
    _entry("WebP + codec-free", "q=50", 9500, 20.0, quality=50, seconds=(1.0, 0.01, 0.02)),
    _entry("WebP + codec-free", "q=5", 4000, 17.0, quality=5, seconds=(1.0, 0.01, 0.02)),
    _entry("JPEG + codec-free", "q=5", 3300, 16.0, quality=5), _entry("JPEG + codec-free", "q=50", 14000, 19.5,
                                                                      quality=50)]


def test_tables_order_and_average_each_curve():
    first = [line.split(" | ")[:2] for line in table1(SUMMARY).splitlines()[2:]]
    assert first == [[f"| {COPY_NEAREST}", "no bitstream"], [f"| {BACKBONE}→PLY+Deflate", "16/8-bit"],
                     ["| WebP + codec-free", "q=5"], ["| WebP + codec-free", "q=50"], ["| JPEG + codec-free", "q=5"],
                     ["| JPEG + codec-free", "q=50"], ["| CodecSplat", "λ=16"], ["| CodecSplat", "λ=1024"],
                     ["| CodecSplat RDO (slow)", "λ=16"], ["| CodecSplat RDO (slow)", "λ=1024"]]
    second = table2(SUMMARY).splitlines()[2:]
    assert second == [f"| {BACKBONE}→PLY+Deflate | 16/8-bit | 1.000 | 2.000 | 3.000 |",
                      "| WebP + codec-free | q=5,…,50 | 1.000 | 0.010 | 0.020 |",
                      "| JPEG + codec-free | q=5,…,50 | 1.000 | 2.000 | 3.000 |",
                      "| CodecSplat | λ=16,…,1024 | 1.000 | 2.000 | 3.000 |",
                      "| CodecSplat RDO (slow) | λ=16,…,1024 | 1.000 | 50.000 | 3.000 |"]


def test_equal_bytes_compares_each_codecsplat_curve_with_each_image_codec_over_their_shared_range():
    """Would catch: curves compared at their own settings instead of equal bytes, a sign that calls a higher LPIPS
    better, a range outside what both curves cover, or single settings taken for curves."""
    entries = {(e["method"], e["baseline"]): e for e in equal_bytes(SUMMARY)}
    assert set(entries) == {(m, b) for m in (CODECSPLAT, "CodecSplat RDO (slow)")
                            for b in ("WebP + codec-free", "JPEG + codec-free")}
    webp = entries[(CODECSPLAT, "WebP + codec-free")]
    assert (webp["from_bytes"], webp["to_bytes"]) == (4000, 9000)

    def at(points, size):  # linear in log bytes
        (b0, v0), (b1, v1) = points
        return v0 + (v1 - v0) * np.log(size / b0) / np.log(b1 / b0)

    ends = [at([(2000, 19.0), (9000, 21.0)], b) - at([(4000, 17.0), (9500, 20.0)], b) for b in (4000, 9000)]
    assert webp["psnr_least"] == pytest.approx(min(ends)) and webp["psnr_most"] == pytest.approx(max(ends))
    assert webp["lpips_vgg_least"] is None  # not measured
    lpips = [_entry(CODECSPLAT, "λ=16", 2000, 19.0, lam=16.0) | {"lpips_vgg": 0.40},
             _entry(CODECSPLAT, "λ=1024", 8000, 20.0, lam=1024.0) | {"lpips_vgg": 0.36},
             _entry("WebP + codec-free", "q=5", 2000, 18.0, quality=5) | {"lpips_vgg": 0.45},
             _entry("WebP + codec-free", "q=50", 8000, 18.5, quality=50) | {"lpips_vgg": 0.30},
             _entry("JPEG + codec-free", "q=5", 9000, 17.0, quality=5), _entry("JPEG + codec-free", "q=50", 20000,
                                                                               18.0, quality=50)]
    (crossing,) = equal_bytes(lpips)  # JPEG's sizes lie above CodecSplat's: nothing to compare
    assert crossing["lpips_vgg_least"] == pytest.approx(-0.06) and crossing["lpips_vgg_most"] == pytest.approx(0.05)
    assert crossing["psnr_least"] == pytest.approx(1.0) and crossing["psnr_most"] == pytest.approx(1.5)
    assert "| CodecSplat | WebP + codec-free | 1.95 KiB to 7.81 KiB | +1.000 / +1.500 | -0.060 / +0.050 |" in \
        table4(lpips)
    assert table4(lpips[:3]) == "-"  # a single image-codec setting is no curve


def test_plots_draw_a_line_per_curve_on_log_bytes_and_image_codecs_generate_at_the_receiver(tmp_path, monkeypatch):
    figures = {}
    monkeypatch.setattr(report, "save_figure", lambda fig, path: figures.update({path.name: fig}))
    plot_rate_distortion(SUMMARY, tmp_path / "rd.png")
    plot_distortion_vs_time(SUMMARY, tmp_path / "time.png")
    psnr = figures["rd.png"].axes[0]
    assert psnr.get_xscale() == "log" and psnr.get_xlabel() == "KiB per scene"
    lines = {line.get_label(): line for line in psnr.get_lines()}
    for method, kib in [(CODECSPLAT, [2000, 9000]), ("CodecSplat RDO (slow)", [1900, 8000]),
                        ("WebP + codec-free", [4000, 9500]), ("JPEG + codec-free", [3300, 14000])]:
        assert lines[method].get_linestyle() == "-" and list(lines[method].get_xdata()) == [k / 1024 for k in kib]
    assert lines[f"{BACKBONE}→PLY+Deflate (16/8-bit)"].get_linestyle() == "None"  # one setting: a marker
    assert lines[f"{COPY_NEAREST} (0 bytes)"].get_linestyle() == "--"
    sender, receiver = figures["time.png"].axes
    webp = {line.get_label(): line for line in sender.get_lines()}["WebP + codec-free"]
    assert list(webp.get_xdata()) == [0.01, 0.01] and webp.get_linestyle() == "None"  # image encoding alone
    webp = {line.get_label(): line for line in receiver.get_lines()}["WebP + codec-free"]
    assert np.allclose(webp.get_xdata(), [1.02, 1.02])  # decoding + the network on the decoded photographs
    slow = {line.get_label(): line for line in sender.get_lines()}["CodecSplat RDO (slow)"]
    assert list(slow.get_xdata()) == [41.0, 61.0]


def test_comparison_titles_wrap_to_their_panel_and_keep_every_word(tmp_path):
    title = f"{COPY_NEAREST} no bitstream\n0.00 KiB, 16.24 dB"
    fitted = report.fit_title(title, 256)
    chars = int(256 / (report.AVERAGE_CHAR_EM * report.TITLE_POINTS / 72 * report.FIGURE_DPI))
    assert max(len(line) for line in fitted.split("\n")) <= chars < len(title.split("\n")[0])
    assert fitted.split() == title.split() and fitted.count("\n") > title.count("\n")
    assert report.fit_title("ground truth", 256) == "ground truth"
    frames = np.zeros((1, 32, 256, 3), np.uint8)
    report.plot_comparison([frames, frames], ["ground truth", title], tmp_path / "c.png")
    assert (tmp_path / "c.png").stat().st_size > 0
