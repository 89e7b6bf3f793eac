"""The ``codecsplat`` command line: exit codes, one-line user errors, selfcheck rows."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
import torch

from codecsplat_warp import selfcheck
from codecsplat_warp.cli import EXIT_USER, main


def test_user_error_is_one_line_and_exit_code_1(capsys):
    assert main(["bench", "geometry", "--device", "cpu", "--shapes", "nope"]) == EXIT_USER
    assert "unknown shape 'nope'" in capsys.readouterr().err
    assert main(["bogus-command"]) == EXIT_USER
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("codecsplat: error:") and "bogus-command" in err[0]


@pytest.mark.skipif(torch.cuda.is_available(), reason="a CUDA GPU is present, so --device cuda is not an error")
def test_cuda_request_without_gpu_is_a_user_error(capsys):
    assert main(["bench", "geometry", "--device", "cuda"]) == EXIT_USER
    assert "CUDA" in capsys.readouterr().err


def test_selfcheck_reports_a_failing_kernel_as_a_row_not_a_crash(monkeypatch):
    def broken(*_):
        raise RuntimeError("kernel exploded")

    check = selfcheck.KernelCheck("broken", broken, broken, lambda: (torch.zeros(1),), 1)
    monkeypatch.setattr(selfcheck, "CHECKS", [check])
    result = selfcheck.run_selfcheck([torch.device("cpu")], progress=False)
    assert not result["ok"]
    assert [r["status"] for r in result["rows"]] == ["ERROR: RuntimeError: kernel exploded"] * 2


def test_selfcheck_json_from_the_console_script():
    out = subprocess.run([sys.executable, "-m", "codecsplat_warp.cli", "selfcheck", "--device", "cpu", "--json"],
                         capture_output=True, text=True, check=True).stdout
    rows = json.loads(out)["rows"]
    assert {r["kernel"] for r in rows} >= {"unproject", "reproject_average", "plane_sweep_cost_volume", "rasterize (RGB)"}
    assert all(r["ok"] for r in rows)
