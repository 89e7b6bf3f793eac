"""The demo's numbers in docs/ are the ones the shipped model gives for the same sample (issue 9's "done when").

CI runs ``codecsplat demo`` (README command 1) before the tests, so its ./codecsplat-demo/summary.json is
checked when present; otherwise the demo runs here (about a minute on a 2-core CPU)."""

from __future__ import annotations

import json
import pathlib

import pytest
import torch

from codecsplat_warp.demo import DemoConfig, quality_table, run_demo
from codecsplat_warp.model.codecsplat import model_id
from codecsplat_warp.model.pretrained import load_pretrained

REPO = pathlib.Path(__file__).resolve().parents[1]
DOCUMENTED = REPO / "docs" / "demo" / "summary-cpu.json"
README_RUN = REPO / "codecsplat-demo" / "summary.json"


def _fresh_summary(tmp_path, documented: dict) -> dict:
    if README_RUN.is_file():
        summary = json.loads(README_RUN.read_text())
        if (summary["config"]["lambdas"] == documented["config"]["lambdas"] and summary["device"] == "cpu"
                and summary["model_id"] == documented["model_id"]):
            return summary
    model = load_pretrained(device=torch.device("cpu"))
    config = DemoConfig(out=str(tmp_path / "demo"), lpips_weights=documented["config"]["lpips_weights"],
                        progress=False)
    return run_demo(model, config, torch.device("cpu"))


def test_documented_demo_numbers_match_a_fresh_run(tmp_path):
    documented = json.loads(DOCUMENTED.read_text())
    assert documented["model_id"] == model_id(load_pretrained(device=torch.device("cpu")))
    fresh = _fresh_summary(tmp_path, documented)
    assert [r["lam"] for r in fresh["rows"]] == [r["lam"] for r in documented["rows"]]
    for got, want in zip(fresh["rows"], documented["rows"]):
        assert abs(got["bytes"] - want["bytes"]) <= 0.005 * want["bytes"], (got["lam"], got["bytes"], want["bytes"])
        assert got["psnr"] == pytest.approx(want["psnr"], abs=0.05)
        assert got["ssim"] == pytest.approx(want["ssim"], abs=0.005)
    assert [r["method"] for r in fresh["references"]] == [r["method"] for r in documented["references"]]
    for got, want in zip(fresh["references"], documented["references"]):  # copy-nearest floor, codec-free path
        assert got["psnr"] == pytest.approx(want["psnr"], abs=0.05), got["method"]


def test_the_documented_table_is_the_one_in_training_md():
    documented = json.loads(DOCUMENTED.read_text())
    assert quality_table(documented) in (REPO / "docs" / "training.md").read_text()
