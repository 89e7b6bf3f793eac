"""The shipped models by identifier: a bitstream of the first shipped model (a stored fixture) decodes while that
model ships, and once it no longer does, decoding it fails with an error that names the model and says where to
get it (``codecsplat_warp.model.releases``)."""

from __future__ import annotations

import pathlib

import pytest

from codecsplat_warp.cli import main
from codecsplat_warp.codec.bitstream import parse_bitstream
from codecsplat_warp.errors import BitstreamError
from codecsplat_warp.model import releases
from codecsplat_warp.model.codecsplat import model_id
from codecsplat_warp.model.pretrained import load_pretrained
from conftest import tiny_coding_model

FIRST_MODEL = "554cc15fd43d1f3e"
FIRST_RELEASE = "0.1.0"
FIXTURE = pathlib.Path(__file__).parent / "fixtures" / f"model-{FIRST_MODEL}" / "scene.csplat"
"""A 2-view 64x64 procedural scene at λ=16 written by the first shipped model (354 bytes, 8,192 Gaussians)."""


@pytest.fixture(scope="module")
def shipped():
    return load_pretrained(None, "cpu")


def test_the_default_model_id_is_the_shipped_files(shipped):
    """Would catch: a new shipped model without its identifier in the releases (decode errors would send users to
    the wrong model)."""
    assert model_id(shipped) == releases.DEFAULT_MODEL_ID
    assert releases.DEFAULT_MODEL_ID not in releases.EARLIER_DEFAULTS


def test_a_bitstream_of_the_first_shipped_model_decodes_or_says_where_that_model_is(shipped):
    """Would catch: a new default that cannot decode the first model's bitstreams and does not say which release
    can, or an error that names no model."""
    data = FIXTURE.read_bytes()
    assert parse_bitstream(data).header.model_id == FIRST_MODEL
    if model_id(shipped) == FIRST_MODEL:
        assert shipped.decode_scene(data).gaussians.means.shape == (8192, 3)
    else:
        assert releases.EARLIER_DEFAULTS.get(FIRST_MODEL) == FIRST_RELEASE
        with pytest.raises(BitstreamError, match=f"codecsplat-warp=={FIRST_RELEASE}"):
            shipped.decode_scene(data)
    with pytest.raises(BitstreamError, match=f"written by model {FIRST_MODEL}, but this model is [0-9a-f]{{16}}; "
                                             f"{FIRST_MODEL} (is the model shipped with this package|was the default)"):
        tiny_coding_model(0).decode_scene(data)


def test_where_to_get_names_the_release_or_the_users_own_file(monkeypatch):
    assert "decode without --checkpoint" in releases.where_to_get(releases.DEFAULT_MODEL_ID)
    monkeypatch.setitem(releases.EARLIER_DEFAULTS, "0123456789abcdef", "0.0.9")
    earlier = releases.where_to_get("0123456789abcdef")
    assert "pip install codecsplat-warp==0.0.9" in earlier and releases.DEFAULT_FILE in earlier
    assert "the model file that encoded it (--checkpoint FILE" in releases.where_to_get("fedcba9876543210")


def test_the_decode_command_prints_where_to_get_the_model_in_one_line(tmp_path, capsys):
    from codecsplat_warp.model.pretrained import save_pretrained

    save_pretrained(tiny_coding_model(0), tmp_path / "tiny.safetensors")
    code = main(["decode", str(FIXTURE), "--checkpoint", str(tmp_path / "tiny.safetensors"), "--device", "cpu",
                 "-o", str(tmp_path / "out.ply")])
    err = capsys.readouterr().err.strip()
    assert code != 0 and len(err.splitlines()) == 1 and FIRST_MODEL in err and "--checkpoint" in err
