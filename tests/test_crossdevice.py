"""A bitstream decodes to the same scene on every device: the fixture in tests/fixtures/crossdevice holds a bitstream
with the Gaussians and renders of its float32 decode on the machine that wrote it (regenerate it on a CUDA machine
with ``codecsplat bench crossdevice --device cuda --write tests/fixtures/crossdevice``, :data:`REGENERATE`); here it
is decoded on the CPU and compared. A fixture written with another model than the shipped one is a failure: a new
model comes with a new fixture."""

from __future__ import annotations

import json
import pathlib
import shlex

import pytest
import torch

from codecsplat_warp.bench.crossdevice import GAUSSIAN_TOLERANCE, RENDER_PSNR_DB, check_fixture
from codecsplat_warp.errors import InputError
from codecsplat_warp.model.codecsplat import model_id
from codecsplat_warp.model.pretrained import load_pretrained

FIXTURE = pathlib.Path(__file__).parent / "fixtures" / "crossdevice"
REGENERATE = "codecsplat bench crossdevice --device cuda --write tests/fixtures/crossdevice"
"""The command that writes the fixture, from the repository root on a machine with a CUDA GPU."""


@pytest.fixture(scope="module")
def shipped():
    return load_pretrained(None, "cpu")


def test_fixture_decodes_on_the_cpu_to_its_gaussians_and_renders_even_under_bf16_autocast(shipped):
    """The decode runs in float32 whatever autocast the caller runs under (a bf16 decode moves the Gaussians by
    about 1e-2 relative: far outside the tolerance). Catches: a decode that differs between CUDA and the CPU, or
    that follows the caller's autocast; and a new shipped model without a new fixture, which fails here (with the
    command that writes one) rather than being skipped."""
    record = json.loads((FIXTURE / "record.json").read_text())
    if record["model_id"] != model_id(shipped):
        pytest.fail(f"tests/fixtures/crossdevice was written with model {record['model_id']}, but the shipped model "
                    f"is {model_id(shipped)}: a new model needs a new cross-device fixture. Regenerate it on a "
                    f"machine with a CUDA GPU, from the repository root: `{REGENERATE}`, then commit the four files "
                    "it writes", pytrace=False)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        result = check_fixture(FIXTURE, torch.device("cpu"))
    assert max(result["relative_error"].values()) <= GAUSSIAN_TOLERANCE, result["table"]
    assert min(result["render_psnr_db"]) >= RENDER_PSNR_DB, result["table"]
    assert result["passed"]


def test_the_regenerate_command_writes_this_fixture_on_cuda():
    """Catches: a failure message that names a command or option the command line no longer has, or another folder."""
    from codecsplat_warp.cli import build_parser

    program, *argv = shlex.split(REGENERATE)
    args = build_parser().parse_args(argv)
    assert program == "codecsplat" and (args.command, args.benchmark, args.device) == ("bench", "crossdevice", "cuda")
    assert (FIXTURE.parents[2] / args.write).resolve() == FIXTURE.resolve() and args.check is None


def test_fixture_stays_small():
    assert sum(f.stat().st_size for f in FIXTURE.iterdir()) < 1 << 20


def test_unknown_decode_precision_is_an_input_error(shipped):
    with pytest.raises(InputError, match="precision"):
        shipped.decode_scene(b"", precision="float16")
