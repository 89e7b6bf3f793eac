"""The front door (issue 19): the package's main names import from ``codecsplat_warp`` itself, ``codecsplat_warp.ops``
exports the public ops, and every subpackage imports first in a fresh interpreter (no import-order dependence)."""

from __future__ import annotations

import inspect
import subprocess
import sys

import pytest

import codecsplat_warp
from codecsplat_warp import ops


def test_front_door_names_are_the_defining_objects():
    from codecsplat_warp import Cameras, CodecSplat, load_pretrained, load_scene, rasterize, reproject_average, unproject
    from codecsplat_warp.cameras import Cameras as cameras_def
    from codecsplat_warp.data import load_scene as load_scene_def
    from codecsplat_warp.model.codecsplat import CodecSplat as codecsplat_def
    from codecsplat_warp.model.pretrained import load_pretrained as load_pretrained_def
    from codecsplat_warp.ops.geometry import reproject_average as reproject_def, unproject as unproject_def
    from codecsplat_warp.ops.raster import rasterize as rasterize_def

    assert (Cameras, CodecSplat, load_pretrained, load_scene, rasterize, unproject, reproject_average) == (
        cameras_def, codecsplat_def, load_pretrained_def, load_scene_def, rasterize_def, unproject_def, reproject_def)
    assert sorted(codecsplat_warp.__all__) == sorted(
        ["CodecSplat", "Cameras", "load_pretrained", "load_scene", "rasterize", "unproject", "reproject_average"])


def test_ops_exports_the_public_ops():
    from codecsplat_warp.ops import geometry, mvs, raster

    modules = (geometry, mvs, raster)
    for name in ops.__all__:
        assert any(getattr(ops, name) is getattr(module, name, None) for module in modules), name
    public = {n for m in modules for n, v in vars(m).items()
              if inspect.isfunction(v) and not n.startswith("_") and getattr(v, "__module__", None) == m.__name__}
    assert public <= set(ops.__all__), f"public ops missing from codecsplat_warp.ops: {public - set(ops.__all__)}"


FIRST_IMPORTS = ("codecsplat_warp.codec", "codecsplat_warp.model", "codecsplat_warp.errors", "codecsplat_warp.kernels",
                 "codecsplat_warp.nn.config", "codecsplat_warp.gaussians")


@pytest.fixture(scope="module")
def fresh_interpreters():
    """One fresh interpreter per module of FIRST_IMPORTS that imports it first, then the front door; all started
    at once (each spends seconds importing torch and Warp), killed if a test leaves one running."""
    started = {}
    for first in FIRST_IMPORTS:
        code = f"import {first}; from codecsplat_warp import CodecSplat; from codecsplat_warp.codec import LatentCodec"
        started[first] = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                          text=True)
    yield started
    for process in started.values():
        if process.poll() is None:
            process.kill()
        process.communicate()


@pytest.mark.parametrize("first", FIRST_IMPORTS)
def test_any_module_imports_first(first, fresh_interpreters):
    process = fresh_interpreters[first]
    _, stderr = process.communicate(timeout=300)
    assert process.returncode == 0, stderr
