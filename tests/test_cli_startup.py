"""The command line answers at once: ``--help`` of every command and benchmark, and a bad argument, without
importing torch or Warp; ``--threads``; no Warp CUDA driver warning on a machine without a GPU."""

from __future__ import annotations

import subprocess
import sys

import pytest

from codecsplat_warp.bench.options import ARGUMENTS
from codecsplat_warp.choices import PROTOCOL_NAMES
from codecsplat_warp.cli import BENCHMARKS, COMMANDS, EXIT_USER, main

_LIGHT_PARSE = """
import sys
from codecsplat_warp.cli import main
for argv in {argvs!r}:
    try:
        code = main(argv)
    except SystemExit as exit:
        code = exit.code
    print("exit code:", code)
print("heavy modules:", sorted(name for name in ("torch", "warp", "numpy") if name in sys.modules))
"""


def test_help_and_bad_arguments_import_neither_torch_nor_warp():
    argvs = [["--help"], *([command, "--help"] for command in COMMANDS),
             *(["bench", name, "--help"] for name in BENCHMARKS), ["demo", "--bogus"], ["bench", "raster", "--reps"]]
    result = subprocess.run([sys.executable, "-c", _LIGHT_PARSE.format(argvs=argvs)], capture_output=True, text=True,
                            timeout=120)  # fmt: skip
    lines = result.stdout.strip().splitlines()
    assert lines[-1] == "heavy modules: []", result.stdout + result.stderr
    codes = [int(line.split(": ")[1]) for line in lines if line.startswith("exit code: ")]
    assert codes == [0] * (len(argvs) - 2) + [EXIT_USER, EXIT_USER]
    assert "unrecognized arguments: --bogus" in result.stderr


def test_every_benchmark_has_its_options_and_the_protocol_names_are_the_protocols():
    from codecsplat_warp.eval.protocols import PROTOCOLS

    assert set(BENCHMARKS) == set(ARGUMENTS)
    assert tuple(PROTOCOLS) == PROTOCOL_NAMES


@pytest.mark.parametrize("threads", ["0", "-1"])
def test_threads_must_be_positive(threads, capsys):
    assert main(["selfcheck", "--device", "cpu", "--threads", threads]) == EXIT_USER
    assert "--threads must be a positive integer" in capsys.readouterr().err


def test_a_cpu_run_prints_no_cuda_warning():
    code = "from codecsplat_warp.device import cuda_driver_missing, init_warp; init_warp(); print(cuda_driver_missing())"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "CUDA warning" not in result.stderr and "NVIDIA CUDA driver" not in result.stderr
