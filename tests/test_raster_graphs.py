"""Forward graphs of rasterize on CUDA (``codecsplat_warp.ops.raster.forward_graphs``): replays render as the eager
launches, keep nothing a caller holds in the graph's memory, and fall back to the eager launches when a guess does not
hold or a capture fails."""

from __future__ import annotations

import gc
import warnings

import pytest
import torch

import codecsplat_warp.ops.raster as raster_ops
from codecsplat_warp.ops.raster import forward_graphs, rasterize
from codecsplat_warp.synthetic import random_gaussians as make_scene

requires_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU visible to torch")

SIZE = 48


def cuda_scene(seed: int, spread: float = 1.0) -> list[torch.Tensor]:
    """300 float32 Gaussians before one camera (``spread`` scales them: more intersections), on CUDA."""
    scene = [t.cuda() for t in make_scene(300, SIZE, SIZE, dtype=torch.float32, seed=seed)]
    scene[2] = scene[2] * spread
    return scene


def forward(scene):
    """Leaves, the outputs of ``rasterize`` and a loss weighting them (fixed weights)."""
    leaves = [t.detach().clone().requires_grad_() for t in scene[:5]]
    rgb, depth, alpha, meta = rasterize(*leaves, *scene[5:], SIZE, SIZE)
    g = torch.Generator().manual_seed(3)
    loss = sum((o * torch.rand(o.shape, generator=g).cuda()).sum() for o in (rgb, depth, alpha))
    return leaves, [rgb, depth, alpha, meta.radii], meta.intersection_count, loss


def render(scene):
    """Images, radii and the gradients of :func:`forward`'s loss, and the intersection count."""
    leaves, outputs, count, loss = forward(scene)
    return [*outputs, *torch.autograd.grad(loss, leaves)], count


def assert_same(got, want):
    """Images and radii bit for bit; gradients to float32 rounding (CUDA's atomic sums run in no fixed order)."""
    for x, y in zip(got[:4], want[:4]):
        assert torch.equal(x, y)
    for x, y in zip(got[4:], want[4:]):
        assert ((x - y).norm() / y.norm().clamp_min(1e-30)).item() < 1e-5


@pytest.fixture
def fresh(monkeypatch):
    """No guesses or graphs from earlier tests; yields the number of times the stages before the binning ran
    (eagerly, or into a graph's warm-up and capture)."""
    monkeypatch.setattr(raster_ops, "_speculations", {})
    graphs, failed = raster_ops._thread_graphs()
    graphs.clear()
    failed.clear()
    stage = raster_ops._stage
    calls = [0]

    def counting(*args, **kwargs):
        calls[0] += 1
        return stage(*args, **kwargs)

    monkeypatch.setattr(raster_ops, "_stage", counting)
    with forward_graphs(True):
        yield calls
    graphs.clear()


@pytest.mark.cuda
@requires_cuda
def test_replays_render_as_the_eager_launches(fresh):
    """A call of a shape with a guess (here the eager calls') captures its graph (a warm-up and the capture), later
    ones replay it without running the stages again: images, radii and counts bit for bit as the eager launches,
    gradients to rounding, with new inputs at every call."""
    scenes = [cuda_scene(seed) for seed in (1, 2, 3)]
    with forward_graphs(False):
        eager = [render(scene) for scene in scenes]
    fresh[0] = 0
    for scene, (want, count) in zip(scenes * 2, eager * 2):
        got, got_count = render(scene)
        assert got_count == count
        assert_same(got, want)
    assert fresh[0] == 2
    assert len(raster_ops._thread_graphs()[0]) == 1


@pytest.mark.cuda
@requires_cuda
def test_outputs_and_gradients_survive_later_replays(fresh):
    """Two forwards of one shape before either backward: the second replay overwrites the graph's memory, not the
    first call's outputs or the state its backward reads."""
    scenes = [cuda_scene(seed) for seed in (4, 5)]
    with forward_graphs(False):
        eager = [render(scene) for scene in scenes]
    render(scenes[0])
    render(scenes[0])  # captured
    first, second = forward(scenes[0]), forward(scenes[1])
    for (leaves, outputs, _, loss), (want, _) in zip((second, first), (eager[1], eager[0])):
        assert_same([*outputs, *torch.autograd.grad(loss, leaves)], want)


@pytest.mark.cuda
@requires_cuda
def test_a_call_that_outgrows_the_graph_renders_eagerly_and_captures_again(fresh):
    """A call with several times the intersections of the captured guess renders eagerly (as without graphs); the
    next call of that size captures a larger graph."""
    small, large = cuda_scene(6), cuda_scene(6, spread=3.0)
    with forward_graphs(False):
        want, count = render(large)
    raster_ops._speculations.clear()
    render(small)  # eager: the first call of the shape
    render(small)  # captured
    captured = next(iter(raster_ops._thread_graphs()[0].values()))
    assert count > captured.guess.capacity
    got, got_count = render(large)
    assert got_count == count
    assert_same(got, want)
    render(large)
    grown = next(iter(raster_ops._thread_graphs()[0].values()))
    assert grown is not captured and grown.guess.capacity >= count


@pytest.mark.cuda
@requires_cuda
def test_a_failed_capture_warns_once_and_stays_eager(fresh, monkeypatch):
    """A capture that raises in its middle leaves the call shape eager, with one warning, the renders right and
    torch's CUDA generator usable."""
    scene = cuda_scene(7)
    with forward_graphs(False):
        want, _ = render(scene)
    launch = raster_ops._ForwardGraph._launch
    launches = [0]

    def failing_in_capture(self):
        launches[0] += 1
        if launches[0] == 2:  # the first is the warm-up, the second runs inside the capture
            raise RuntimeError("no capture here")
        return launch(self)

    monkeypatch.setattr(raster_ops._ForwardGraph, "_launch", failing_in_capture)
    with pytest.warns(RuntimeWarning, match="CUDA graph failed"):
        got, _ = render(scene)
    assert_same(got, want)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got, _ = render(scene)  # no second warning: the shape is eager from now on
    assert_same(got, want)
    assert not raster_ops._thread_graphs()[0] and launches[0] == 2
    assert torch.rand(4, device="cuda").shape == (4,)


@pytest.mark.cuda
@requires_cuda
def test_a_capture_neither_synchronises_nor_collects_nor_empties_the_caches(fresh, monkeypatch):
    """Capturing a graph (the second call of a shape) calls none of ``torch.cuda.synchronize``, ``gc.collect``,
    ``torch.cuda.empty_cache`` and torch's host cache emptying, and keeps the memory torch had reserved.

    Catches: captures through ``torch.cuda.graph`` (it synchronises and empties the caches) or a guard that
    collects Python's garbage first. In ``bench rdo`` of the held-out RE10K samples (H200) such a capture took
    223 ms (median of 55) against 3 ms, and a ``medium`` encode 1.14 s against 0.43 s."""
    scene = cuda_scene(8)
    render(scene)  # eager: the first call of the shape
    reserved = torch.cuda.memory_reserved()
    called = []
    capture = raster_ops._ForwardGraph.__init__

    def spied_capture(self, *args):
        with pytest.MonkeyPatch.context() as spies:
            for owner, name in ((torch.cuda, "synchronize"), (gc, "collect"), (torch.cuda, "empty_cache"),
                                (torch._C, "_host_emptyCache")):  # fmt: skip
                spies.setattr(owner, name, lambda *a, name=name, **k: called.append(name), raising=False)
            capture(self, *args)

    monkeypatch.setattr(raster_ops._ForwardGraph, "__init__", spied_capture)
    got, _ = render(scene)
    assert len(raster_ops._thread_graphs()[0]) == 1  # captured
    assert called == []
    assert torch.cuda.memory_reserved() >= reserved
    with forward_graphs(False):
        want, _ = render(scene)
    assert_same(got, want)


def test_forward_graphs_are_a_setting_of_the_thread_with_an_environment_default(monkeypatch):
    """``forward_graphs`` sets the calling thread's choice inside its block; a thread that sets none takes
    ``$CODECSPLAT_RASTER_GRAPHS`` (``0``: off), read once."""
    import threading

    seen = {}

    def choice(name):
        seen[name] = raster_ops._graphs_enabled()

    for value, name in (("0", "off"), ("1", "on")):
        monkeypatch.setenv(raster_ops.GRAPHS_VARIABLE, value)
        thread = threading.Thread(target=choice, args=(name,))
        thread.start()
        thread.join()
    assert seen == {"off": False, "on": True}
    with forward_graphs(False):
        assert not raster_ops._graphs_enabled()
        with forward_graphs(True):
            assert raster_ops._graphs_enabled()
        assert not raster_ops._graphs_enabled()
