"""Shared pytest setup: Warp kernel cache in the ignored build dir, device parametrisation, data path."""

from __future__ import annotations

import os
import pathlib

ROOT = pathlib.Path(__file__).resolve().parents[1]
os.environ.setdefault("WARP_CACHE_PATH", str(ROOT / "build" / "warp-cache"))

import pytest  # noqa: E402
import torch  # noqa: E402

from codecsplat_warp.model import CodecSplat  # noqa: E402
from codecsplat_warp.nn.config import get_preset  # noqa: E402

CUDA = torch.cuda.is_available()

DEVICES = [
    pytest.param("cpu", id="cpu"),
    pytest.param("cuda", id="cuda", marks=[pytest.mark.cuda, pytest.mark.skipif(not CUDA, reason="no CUDA GPU visible to torch")]),
]
"""Parametrise a test over every device: ``@pytest.mark.parametrize("device", DEVICES)``."""


def _warp_compiles_cpu_kernels() -> bool:
    import warp as wp

    return wp.is_cpu_available()


needs_warp_cpu = pytest.mark.skipif(
    not _warp_compiles_cpu_kernels(),
    reason="this Warp cannot compile CPU kernels (no warp-clang library, as in the GPU machines' kit); the test "
           "runs Warp kernels on the CPU beside CUDA")
"""Mark a CUDA test that also runs Warp kernels on the CPU (a CUDA bitstream decoded on the CPU, say)."""


@pytest.fixture(scope="session")
def data_root() -> pathlib.Path:
    """Root of the real scenes (``CODECSPLAT_DATA``); skips the test with the reason when unset or missing."""
    path = os.environ.get("CODECSPLAT_DATA")
    if not path:
        pytest.skip("CODECSPLAT_DATA is not set: real-scene tests need ../shared/data/scenes (set by .ci/run)")
    root = pathlib.Path(path)
    if not root.is_dir():
        pytest.skip(f"CODECSPLAT_DATA={path} is not a directory")
    return root


@pytest.fixture(autouse=True)
def _seed() -> None:
    torch.manual_seed(0)


LPIPS_WEIGHTS = pathlib.Path(os.environ.get("CODECSPLAT_LPIPS_WEIGHTS", "")).resolve() if os.environ.get("CODECSPLAT_LPIPS_WEIGHTS") else None
"""Folder with lpips_vgg.safetensors and lpips_alex.safetensors (``CODECSPLAT_LPIPS_WEIGHTS``; .ci/run sets it)."""

needs_lpips = pytest.mark.skipif(
    LPIPS_WEIGHTS is None or not (LPIPS_WEIGHTS / "lpips_vgg.safetensors").is_file(),
    reason="CODECSPLAT_LPIPS_WEIGHTS is unset or lacks lpips_vgg.safetensors (.ci/run sets ../shared/weights)",
)


POSTERIOR_GAIN = 30.0
"""An untrained codec's latents round to zero; scaling its posterior makes every test code real symbols."""


def tiny_coding_model(seed: int):
    """A ``tiny`` CodecSplat with its codec, seeded with ``seed``, in eval mode, on the CPU, with the codec's
    posterior scaled by :data:`POSTERIOR_GAIN` (:meth:`LatentCodec.scale_posterior`)."""
    torch.manual_seed(seed)
    model = CodecSplat(get_preset("tiny"), codec=True).eval()
    model.codec.scale_posterior(POSTERIOR_GAIN)
    return model


def assert_same_batches(got, expected) -> None:
    """Two training batches (``train.data.TrainingBatch``) are the same scenes, bit for bit: keys, images, depth and
    cameras."""
    assert got.keys == expected.keys
    for name in ("context_images", "target_images", "context_depth"):
        torch.testing.assert_close(getattr(got, name), getattr(expected, name), rtol=0, atol=0, msg=name)
    for views in ("context_cameras", "target_cameras"):
        for field in ("K", "w2c", "near", "far"):
            torch.testing.assert_close(getattr(getattr(got, views), field), getattr(getattr(expected, views), field),
                                       rtol=0, atol=0, msg=f"{views}.{field}")
