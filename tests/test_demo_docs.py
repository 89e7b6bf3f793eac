"""The demo's numbers in docs/ are the ones the shipped model gives for the same sample, and the model beats copying
the nearest photograph on the demo's real scene.

The demo scene is ``nerd_mary_rose``, four photographs shipped with the package (a held-out scene: no training run
has seen it). CI runs ``codecsplat demo`` (README command 1) before the tests, so its ./codecsplat-demo/summary.json
is checked when the code and model that wrote it are the ones here (its ``package_digest``) and it ran the documented
demo; otherwise the demo runs here (about a minute on a 2-core CPU).

The floor: every decoded bitstream and the codec-free path must score :data:`MARGIN_DB` above copying the nearest
context photograph (mean PSNR of the two targets). Model 554cc15fd43d1f3e on the 2-core EPYC: copy-nearest 16.29 dB,
codec-free 21.30 dB (+5.02), λ = 16 / 128 / 1024 19.24 / 19.71 / 19.90 dB (+2.95 / +3.42 / +3.62).
"""

from __future__ import annotations

import json
import pathlib

import pytest
import torch

from codecsplat_warp.demo import DEMO_SCENE, DemoConfig, package_digest, package_folders, quality_table, run_demo
from codecsplat_warp.eval.report import COPY_NEAREST
from codecsplat_warp.model.codecsplat import model_id
from codecsplat_warp.model.pretrained import load_pretrained

REPO = pathlib.Path(__file__).resolve().parents[1]
DOCUMENTED = REPO / "docs" / "results" / "demo-summary-cpu.json"
DOCUMENTED_PAGE = REPO / "docs" / "getting-started.md"
README_RUN = REPO / "codecsplat-demo" / "summary.json"

MARGIN_DB = 2.0
"""How far above the copy-nearest floor (mean PSNR, dB) every path of the shipped model must be on the demo scene."""


@pytest.fixture(scope="module")
def documented() -> dict:
    return json.loads(DOCUMENTED.read_text())


RUN_SETTINGS = ("scene", "lambdas", "seed", "target_views", "rdo_steps")
"""The demo options that decide its numbers (``out``, ``progress`` and the LPIPS folder do not)."""


def reusable(summary: dict, documented: dict, digest: str) -> bool:
    """Whether a demo ``summary`` found on disk may stand for a fresh run: written on the CPU by this package's
    code and model (``digest``, :func:`package_digest`) with the documented settings and model."""
    settings = lambda s: [s["config"].get(key) for key in RUN_SETTINGS]  # noqa: E731
    return (summary.get("package_digest") == digest and summary.get("device") == "cpu"
            and summary.get("model_id") == documented["model_id"] and settings(summary) == settings(documented))


@pytest.fixture(scope="module")
def fresh(documented, tmp_path_factory) -> dict:
    """A summary of ``codecsplat demo --device cpu`` with the documented settings, by the code and model here: the
    README run's when :func:`reusable`, else a run of the demo now."""
    if README_RUN.is_file():
        summary = json.loads(README_RUN.read_text())
        if reusable(summary, documented, package_digest()):
            return summary
    model = load_pretrained(device=torch.device("cpu"))
    config = DemoConfig(out=str(tmp_path_factory.mktemp("demo")), lpips_weights=documented["config"]["lpips_weights"],
                        progress=False)
    return run_demo(model, config, torch.device("cpu"))


def test_a_summary_on_disk_stands_for_a_run_only_of_this_code_model_and_settings(documented):
    """Catches: a stale ./codecsplat-demo/summary.json passing for a fresh run after the package's code or model
    changed (or from before summaries named their code), or one run with other settings or on another device."""
    digest = package_digest()
    summary = {**documented, "device": "cpu", "package_digest": digest}
    assert reusable(summary, documented, digest)
    assert not reusable(summary, documented, "0" * 64)  # other code or another model
    assert not reusable({key: value for key, value in summary.items() if key != "package_digest"}, documented, digest)
    assert not reusable({**summary, "device": "cuda"}, documented, digest)
    assert not reusable({**summary, "model_id": "0" * 16}, documented, digest)
    for key, other in (("rdo_steps", 0), ("lambdas", [16.0]), ("target_views", 1), ("seed", 4), ("scene", "procedural")):
        assert not reusable({**summary, "config": {**summary["config"], key: other}}, documented, digest), key


def test_the_package_digest_follows_every_file_of_the_code_and_model(tmp_path):
    """Catches: a digest blind to a source file, a kernel, the model or a file's name (a stale summary would be
    reused), or one that moves with compiled caches (a fresh summary would never be)."""
    code, kernels = tmp_path / "codecsplat_warp", tmp_path / "kernels"
    for path, data in ((code / "model.py", b"x = 1\n"), (code / "assets" / "model.safetensors", b"\0" * 64),
                       (kernels / "raster.py", b"y = 2\n")):
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
    digest = lambda: package_digest([code, kernels])  # noqa: E731
    first = digest()
    (code / "__pycache__").mkdir()
    (code / "__pycache__" / "model.cpython-312.pyc").write_bytes(b"compiled")
    assert digest() == first
    for path, data in ((code / "model.py", b"x = 2\n"), (kernels / "raster.py", b"y = 3\n"),
                       (code / "assets" / "model.safetensors", b"\0" * 63 + b"\1")):
        before = digest()
        path.write_bytes(data)
        assert digest() != before, path.name
    before = digest()
    (kernels / "raster.py").rename(kernels / "composite.py")
    assert digest() != before
    folders = package_folders()
    assert {folder.name for folder in folders} >= {"codecsplat_warp"} and any(
        (folder / "raster_composite_cpu.py").is_file() for folder in folders)


def test_documented_demo_numbers_match_a_fresh_run(documented, fresh):
    """Catches: numbers in docs/ that the shipped model no longer gives on the demo scene, checked against a run of
    this package's code and model (the README run's summary only when its package digest is this one's)."""
    assert documented["model_id"] == model_id(load_pretrained(device=torch.device("cpu")))
    assert fresh["package_digest"] == package_digest()
    assert documented["scene"] == fresh["scene"] == DEMO_SCENE
    assert [r["lam"] for r in fresh["rows"]] == [r["lam"] for r in documented["rows"]]
    for got, want in zip(fresh["rows"], documented["rows"]):
        assert abs(got["bytes"] - want["bytes"]) <= 0.005 * want["bytes"], (got["lam"], got["bytes"], want["bytes"])
        assert got["psnr"] == pytest.approx(want["psnr"], abs=0.05)
        assert got["ssim"] == pytest.approx(want["ssim"], abs=0.005)
    assert [r["method"] for r in fresh["references"]] == [r["method"] for r in documented["references"]]
    for got, want in zip(fresh["references"], documented["references"]):  # copy-nearest floor, codec-free path
        assert got["psnr"] == pytest.approx(want["psnr"], abs=0.05), got["method"]


def test_the_shipped_model_beats_copying_the_nearest_photograph_on_the_demo_scene(fresh):
    references = {r["method"]: r["psnr"] for r in fresh["references"]}
    floor = references.pop(COPY_NEAREST) + MARGIN_DB
    scores = {**references, **{row["setting"]: row["psnr"] for row in fresh["rows"]}}
    assert all(psnr >= floor for psnr in scores.values()), (floor, scores)


def test_the_documented_table_is_the_one_in_the_guide(documented):
    assert quality_table(documented) in DOCUMENTED_PAGE.read_text()
