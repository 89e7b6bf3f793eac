"""``codecsplat bench report`` (codecsplat_warp.bench.report): Pareto fronts, the quick report's files, codec hook."""

from __future__ import annotations

import argparse
import json

import torch

from codecsplat_warp.bench import report
from codecsplat_warp.bench.options import report_arguments


def test_pareto_front_of_a_known_toy_set():
    points = [(1, 5), (2, 3), (3, 4), (2, 3), (4, 1), (5, 1), (0.5, 10), (3, 3), (6, 0.5)]
    assert report.pareto_front(points) == [True, True, False, True, True, False, True, False, True]


def test_pareto_fronts_are_per_kernel_phase_and_size():
    def row(kernel, size, time_ms, error):
        return {"kernel": kernel, "phase": "forward", "size": size, "time_ms": time_ms, "error": error}

    rows = [row("unproject", "tiny", 1.0, 1e-7), row("unproject", "tiny", 2.0, 1e-16),
            row("unproject", "tiny", 3.0, 1e-7), row("unproject", "small", 5.0, 1e-3),
            row("rasterize", "tiny", 9.0, 1e-2),
            {"kernel": "rasterize", "phase": "forward", "size": "tiny", "time_ms": 1.0, "error": None}]  # fmt: skip
    report.mark_pareto(rows)
    assert [r["pareto"] for r in rows] == [True, True, False, True, True, None]


def _dominated(row: dict, rows: list[dict]) -> bool:
    """Whether another row of ``row``'s kernel, phase and size is at least as fast and as accurate, and better in
    one of the two (a reference for ``row["pareto"]``, written out here rather than taken from the report)."""
    return any(other is not row and report.group_key(other) == report.group_key(row)
               and other["time_ms"] <= row["time_ms"] and other["error"] <= row["error"]
               and (other["time_ms"] < row["time_ms"] or other["error"] < row["error"]) for other in rows)


def _args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    parser.add_argument("--device", default="cpu")
    report_arguments(parser)
    return parser.parse_args(list(argv))


def test_quick_report_writes_json_markdown_and_png(tmp_path):
    """float32 only: the float64 rasterizer kernels would add ~25 s of compilation on a cold CPU cache."""
    out = tmp_path / "report"
    result = report.run(_args("--quick", "--out-dir", str(out), "--kernels", "unproject,rasterize", "--no-codec",
                              "--dtypes", "float32", "--reps", "1"))  # fmt: skip
    saved = json.loads((out / "report.json").read_text())
    assert saved["rows"] == json.loads(json.dumps(result["rows"]))
    rows = saved["rows"]
    assert not [r for r in rows if "failed" in r]
    assert {(r["kernel"], r["phase"]) for r in rows} == {(k, p) for k in ("unproject", "rasterize")
                                                          for p in ("forward", "backward")}  # fmt: skip
    for r in rows:
        assert r["time_ms"] > 0 and r["reference"] == "torch float64 (CPU)"
        assert r["dtype"] == "float32" and 0 < r["error"] < 1e-4, r
    assert all(r["psnr_db"] > 100 for r in rows if r["kernel"] == "rasterize" and r["phase"] == "forward")
    assert [r["pareto"] for r in rows] == [not _dominated(r, rows) for r in rows]
    text = (out / "report.md").read_text()
    assert "## unproject" in text and "## rasterize" in text and "tile_size=8" in text and "★" in text
    assert "early-stop transmittance" in text and "skipped (--no-codec)" in text
    png = (out / "pareto.png").read_bytes()
    assert png.startswith(b"\x89PNG\r\n\x1a\n") and len(png) > 10_000
    assert not list(out.glob("*.tmp*"))


def test_codec_hook_measures_psnr_against_encode_decode_time(tmp_path):
    from codecsplat_warp.model import CodecSplat
    from codecsplat_warp.nn.config import PRESETS

    assert report.codec_available()
    model = CodecSplat(PRESETS["tiny"], codec=True).eval()
    device = torch.device("cpu")
    context, targets, scene = report.codec_scene(model.config, device)
    rows = report.measure_codec(model, context, targets, [32.0, 512.0], device, reps=1, scene=scene)
    assert [r["config"] for r in rows] == ["copy nearest context view", "lambda=32", "lambda=512"]
    floor, coded = rows[0], rows[1:]
    for r in rows:
        assert r["kernel"] == "codec" and abs(r["error"] - 10 ** (-r["psnr_db"] / 10)) < 1e-12
    for r in coded:
        assert r["bytes"] > 0 and r["time_ms"] > 0
    images, cameras = context
    target_images, target_cameras = targets  # the floor: each target copies its nearest context view by centre distance
    nearest = (target_cameras.centers[:, None] - cameras.centers[None]).norm(dim=-1).argmin(dim=1)
    mse = float(((images[nearest] - target_images) ** 2).mean(dim=(1, 2, 3)).log10().mean())
    assert floor["bytes"] == 0 and "time_ms" not in floor and abs(floor["psnr_db"] + 10 * mse) < 1e-3
    result = report.finish({"quick": True, "commit": "test", "machines": {"cpu": "test machine"}, "rows": rows,
                            "not_exposed": {}, "codec": f"measured on {scene}"}, tmp_path)  # fmt: skip
    assert result["rows"][0]["pareto"] is None  # no run time: on no front
    assert [r["pareto"] for r in coded] == [not _dominated(r, coded) for r in coded]
    text = (tmp_path / "report.md").read_text()
    assert "## codec" in text and "| copy nearest context view |" in text and (tmp_path / "pareto.png").is_file()


def test_interleaved_rounds_alternate_their_order():
    """One warm-up call each, then rounds in order and in reverse order by turns; one sample per call per round."""
    from codecsplat_warp.measure import interleaved_medians

    ran = []
    calls = {name: (lambda name=name: ran.append(name)) for name in "abc"}
    medians = interleaved_medians(calls, torch.device("cpu"), reps=3)
    assert "".join(ran) == "abc" + "abc" + "cba" + "abc"
    assert set(medians) == set("abc")
