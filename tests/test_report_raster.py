"""``codecsplat bench report`` rows of the rasterizer's early-stop transmittance: error against the default
render (the trade-off) and against the render at the row's own threshold (correctness)."""

from __future__ import annotations

import math

import torch

from codecsplat_warp.bench import report


def test_full_report_measures_early_stop_thresholds():
    rows = [e for e in report.entries(False, ["rasterize"]) if "min_transmittance" in dict(e.options)]
    assert {dict(e.options)["min_transmittance"] for e in rows} == set(report.RASTER_THRESHOLDS)
    assert {e.size for e in rows} == {"small", "re10k", "dl3dv"}
    assert "early-stop transmittance" in report.ERROR_LEGEND


def test_threshold_row_error_is_against_the_default_and_own_setting_error_is_small():
    options = (("tile_size", 16), ("mode", "classic"))
    default = report.Entry("rasterize", "tiny", torch.float32, options)
    early = report.Entry("rasterize", "tiny", torch.float32, (*options, ("min_transmittance", 0.1)))
    device = torch.device("cpu")
    default_rows = report.measure(default, device, reps=1)
    early_rows = report.measure(early, device, reps=1)
    assert all("err_same_setting" not in r for r in default_rows)
    for d, e in zip(default_rows, early_rows):
        assert e["phase"] == d["phase"] and e["reference"] == d["reference"] == "torch float64 (CPU)"
        assert e["err_same_setting"] < 1e-4 and d["error"] < 1e-4, (d, e)
        assert e["error"] > 100 * e["err_same_setting"], e  # stopping at T <= 0.1 changes the render
    assert math.isfinite(early_rows[0]["psnr_db"]) and early_rows[0]["psnr_db"] < default_rows[0]["psnr_db"] - 20
