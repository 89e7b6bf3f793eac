"""The rasterizer's CPU tile layout: the same renders and gradients on any number of threads, the block layout's
(CUDA's kernels, run on the CPU) within float32 rounding, the dense reference in float64; the thread-count and
freed-memory knobs and the helpers that split CPU launches."""

from __future__ import annotations

import platform

import pytest
import torch

from codecsplat_warp import cli, device
from codecsplat_warp.device import (FREED_MEMORY_VARIABLE, THREADS_VARIABLE, cpu_threads, freed_memory_wanted,
                                    set_cpu_threads)
from codecsplat_warp.errors import InputError
from codecsplat_warp.ops.primitives import run_concurrently, weighted_chunks
from codecsplat_warp.kernels.raster_reach import MAX_CONDITIONED, POWER_ROUNDING
from codecsplat_warp.ops.raster import cpu_layout, project_gaussians, rasterize
from codecsplat_warp.reference.raster import rasterize_dense
from codecsplat_warp.synthetic import random_gaussians


@pytest.fixture
def threads():
    """Set the CPU thread count inside a test (``threads(n)``); the count before is restored afterwards."""
    before = cpu_threads()
    yield set_cpu_threads
    set_cpu_threads(before)


def render_and_differentiate(scene, size, tile_size=16, **kwargs):
    """rgb, depth, alpha, radii and the gradients of a fixed random weighting of the three images (background
    included when given)."""
    leaves = [t.detach().clone().requires_grad_() for t in scene[:5]]
    background = kwargs.pop("background", None)
    wrt = leaves + ([background.detach().clone().requires_grad_()] if background is not None else [])
    rgb, depth, alpha, meta = rasterize(*leaves, *scene[5:], size, size, tile_size=tile_size,
                                        background=wrt[5] if background is not None else None, **kwargs)
    g = torch.Generator().manual_seed(5)
    loss = sum((o * torch.rand(o.shape, generator=g, dtype=o.dtype)).sum() for o in (rgb, depth, alpha))
    return [rgb, depth, alpha, meta.radii, *torch.autograd.grad(loss, wrt)]


def test_renders_and_gradients_are_bit_identical_on_1_2_and_3_threads(threads):
    """Two cameras, SH colours, a background, tiles of every size of work (partial tiles at the border): the tile
    layout splits the tiles over the threads in runs, and neither images nor gradients depend on the split."""
    scene = random_gaussians(300, width=52, height=52, cameras=2, dtype=torch.float32, sh_degree=2, seed=11)
    background = torch.rand(2, 3)
    results = []
    for count in (1, 2, 3):
        threads(count)
        results.append(render_and_differentiate(scene, 52, background=background))
    for other in results[1:]:
        for a, b in zip(results[0], other):
            assert torch.equal(a, b)


@pytest.mark.parametrize("tile_size", [1, 5, 16, 32])
def test_tile_layout_matches_the_block_layout(tile_size):
    """The block layout (the CUDA kernels with one-lane blocks) composites the same rows with the same arithmetic:
    images agree to float32 rounding (the two kernels are compiled apart, and the compiler may fuse multiply-adds
    differently); gradients are summed in another order (per tile then per row, against per pixel in atomics),
    so they agree to a few float32 ulps of the largest gradient."""
    scene = random_gaussians(120, width=40, height=40, cameras=2, dtype=torch.float32, seed=12)
    tiles = render_and_differentiate(scene, 40, tile_size)
    with cpu_layout("blocks"):
        blocks = render_and_differentiate(scene, 40, tile_size)
    for a, b in zip(tiles[:3], blocks[:3]):
        assert (a - b).abs().max() <= 1e-6
    assert torch.equal(tiles[3], blocks[3])
    for a, b in zip(tiles[4:], blocks[4:]):
        assert (a - b).abs().max() <= 1e-5 * b.abs().max()


def needles_and_faint_veils(dtype=torch.float32):
    """Random Gaussians (:func:`random_gaussians`, 2 cameras, 40x40) of which a few are needles, too ill-conditioned
    on screen for a line interval (a conic of condition number g * k > MAX_CONDITIONED), and a few faint veils that
    span many tiles: the two extremes of the tile layout's line masks."""
    scene = random_gaussians(60, width=40, height=40, cameras=2, dtype=dtype, seed=21)
    means, quats, scales, opacities = scene[:4]
    quats[:4] = torch.tensor([1.0, 0.0, 0.0, 0.2], dtype=dtype)  # a slight turn about the view axis
    scales[:4] = torch.tensor([20.0, 1e-4, 1e-4], dtype=dtype)
    scales[4:10] = torch.rand(6, 3, generator=torch.Generator().manual_seed(3), dtype=dtype) * 0.6 + 0.4
    opacities[4:10] = 0.02
    return scene


def test_needles_get_every_pixel_of_their_lines_and_faint_veils_their_intervals():
    """The needles' conics lie beyond the line intervals' conditioning (their lines are given whole), and with the
    veils the tile layout still composites what the block layout does: images to float32 rounding (a pixel the
    masks missed would be off by at least 1/255 of a colour), the gradients of opacities and colours to a few ulps
    of the largest (those of the needles' shapes pass through a near-singular covariance, where the two layouts'
    summation orders differ by more)."""
    scene = needles_and_faint_veils()
    conics = project_gaussians(*scene, 40, 40).conics.double()[:, :4]
    a, b, c = conics.unbind(-1)
    largest = 0.5 * (a + c) + (0.25 * (a - c) ** 2 + b * b).sqrt()
    condition = largest * largest / (a * c - b * b)
    assert (POWER_ROUNDING["float32"] * condition > MAX_CONDITIONED).all()
    for tile_size in (8, 32):
        tiles = render_and_differentiate(scene, 40, tile_size)
        with cpu_layout("blocks"):
            blocks = render_and_differentiate(scene, 40, tile_size)
        for a, b in zip(tiles[:3], blocks[:3]):
            assert (a - b).abs().max() <= 1e-6
        for a, b in zip(tiles[7:9], blocks[7:9]):  # opacities, colours
            assert (a - b).abs().max() <= 1e-5 * b.abs().max()


def test_block_layout_still_matches_the_dense_reference_in_float64():
    """The CUDA kernels' code, run on the CPU in the block layout, against the float64 dense reference (a CPU-only
    machine tests it this way)."""
    scene = random_gaussians(40, width=19, height=13, cameras=2, sh_degree=1, seed=13)
    leaves = [t.detach().clone().requires_grad_() for t in scene[:5]]
    with cpu_layout("blocks"):
        ours = rasterize(*leaves, *scene[5:], 19, 13)
    ref = rasterize_dense(*leaves, *scene[5:], 19, 13)
    for a, b in zip(ours[:3], ref[:3]):
        assert (a - b).abs().max() <= 1e-9
    grads = [torch.autograd.grad(sum(o.sum() for o in out[:3]), leaves) for out in (ours, ref)]
    for a, b in zip(*grads):
        assert (a - b).abs().max() <= 1e-7 * b.abs().max()


def test_unknown_cpu_layout_is_an_input_error():
    with pytest.raises(InputError, match="CPU layout"):
        with cpu_layout("rows"):
            pass


def test_thread_count_knob_sets_torch_too_and_rejects_nonsense(threads, monkeypatch):
    assert threads(3) == 3 and cpu_threads() == 3 and torch.get_num_threads() == 3
    for bad in (0, -2, 1.5, True):
        with pytest.raises(InputError, match="positive integer"):
            set_cpu_threads(bad)
    monkeypatch.setenv(THREADS_VARIABLE, "2")
    assert threads(None) == 2 and torch.get_num_threads() == 2
    monkeypatch.setenv(THREADS_VARIABLE, "all")
    with pytest.raises(InputError, match=THREADS_VARIABLE):
        set_cpu_threads(None)


def test_weighted_chunks_cover_every_item_once_in_runs_of_equal_weight():
    weights = torch.tensor([5, 0, 0, 1, 1, 1, 1, 1, 0, 5])
    chunks = weighted_chunks(weights, 3)
    assert [first for first, _ in chunks] == [0, 3, 9] and sum(count for _, count in chunks) == 10
    assert weighted_chunks(torch.zeros(0), 4) == [] and weighted_chunks(torch.ones(2), 8) == [(0, 1), (1, 1)]


def test_run_concurrently_runs_every_task_and_reraises_after_all_finished(threads):
    threads(2)
    done = []

    def fail():
        raise RuntimeError("task failed")

    tasks = [lambda k=k: done.append(k) for k in range(5)]
    run_concurrently(tasks)
    assert sorted(done) == list(range(5))
    done.clear()
    with pytest.raises(RuntimeError, match="task failed"):
        run_concurrently([fail, *tasks])
    assert sorted(done) == list(range(5))


def test_the_command_keeps_freed_memory_unless_its_variable_is_0(threads, monkeypatch):
    for text, wanted in (("", True), ("1", True), ("0", False), (" 0 ", False)):
        monkeypatch.setenv(FREED_MEMORY_VARIABLE, text)
        assert freed_memory_wanted() is wanted
    monkeypatch.setenv(FREED_MEMORY_VARIABLE, "yes")
    with pytest.raises(InputError, match=FREED_MEMORY_VARIABLE):
        freed_memory_wanted()
    calls = []
    monkeypatch.setattr(device, "keep_freed_memory", lambda: calls.append(1) or True)
    monkeypatch.setenv(FREED_MEMORY_VARIABLE, "0")
    cli._use_threads(None)
    assert calls == []
    monkeypatch.delenv(FREED_MEMORY_VARIABLE)
    cli._use_threads(None)
    assert calls == [1]


def test_keeping_freed_memory_applies_where_the_c_library_is_glibc():
    glibc = platform.libc_ver()[0] == "glibc"
    assert device.keep_freed_memory() is glibc and device.freed_memory_kept() is glibc
