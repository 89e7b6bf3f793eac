"""The README's Python quick-start runs as written: its ``python`` block, executed in a folder holding a small
procedural scene folder named ``my_scene`` (48x32, six views, written as codecsplat-scene-v1), with the shipped
model on the test machine's device."""

from __future__ import annotations

import re

import pytest
import torch

from conftest import ROOT
from test_cli_commands import write_scene


def readme_quick_start() -> str:
    """The first ``python`` code block under the README's "Python quick-start" heading."""
    text = (ROOT / "README.md").read_text()
    section = text.split("## Python quick-start", 1)[1].split("\n## ", 1)[0]
    match = re.search(r"```python\n(.*?)```", section, re.DOTALL)
    assert match, "README.md: no python block under '## Python quick-start'"
    return match.group(1)


@pytest.mark.slow
def test_readme_quick_start_runs_as_written(tmp_path, monkeypatch):
    """About 30 s on a shared 2-core CPU (the snippet codes and renders at 256x256, as a user would)."""
    write_scene(tmp_path / "my_scene", seed=5)
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(readme_quick_start(), "README.md (Python quick-start)", "exec"), namespace)
    data, rgb = namespace["data"], namespace["rgb"]
    assert isinstance(data, bytes) and 0 < len(data) < 64 * 1024
    assert rgb.shape == (1, 3, 256, 256) and rgb.dtype == torch.float32 and torch.isfinite(rgb).all()
    # the render shows the scene: closer to the true novel view than a flat grey image is
    target = namespace["images"][[1]]
    mse = lambda a: float(((a.clamp(0, 1) - target) ** 2).mean())  # noqa: E731
    assert mse(rgb) < mse(torch.full_like(target, 0.5)), (mse(rgb), mse(torch.full_like(target, 0.5)))
