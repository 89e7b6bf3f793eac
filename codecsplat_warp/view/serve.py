"""``codecsplat view`` from its arguments to a running server: every option and the input are checked, the port
too, and the scene is decoded (or encoded) and rendered once before the server starts, so a bad input ends the
command with its error and no server behind it."""

from __future__ import annotations

import contextlib
import io
import signal
import threading
import time
from dataclasses import dataclass
from typing import Callable

import viser

from ..codec import check_lambda
from ..errors import ViewerError
from ..model.pretrained import load_pretrained
from .app import Viewer
from .inputs import SceneSource, ViewScene, encode_source, input_kind, read_bitstream, read_gaussians, scene_source
from .options import DEFAULT_LAMBDA, DEFAULT_MAX_FRAME_SIDE, DEFAULT_PORT, MIN_FRAME_SIDE
from .ports import choose_port

SCENE_OPTIONS = {"lam": "--lambda", "preset": "--preset", "views": "--views", "size": "--size"}
"""The options that encode a scene folder (ViewConfig field -> flag): an error with another input."""

WARM_UP_SIDE = 64
"""Side (pixels) of the frame rendered before the server starts (the rasterizer's kernels load then, not while a
browser waits)."""

POLL_S = 0.5
"""How often the waiting command wakes up (seconds): Ctrl-C is handled at once either way."""


@dataclass(frozen=True)
class ViewConfig:
    """What ``codecsplat view`` was asked (see ``codecsplat view --help``).

    Attributes:
        input: a bitstream, a 3DGS PLY file, or a scene folder or pose file.
        host, port: where to serve (port 0: the first free port from :data:`~.options.DEFAULT_PORT` up).
        lam, preset, views, size: how to encode a scene folder (None: ``codecsplat encode``'s defaults); an error
            with any other input.
        cameras: a pose file of a PLY's views; an error with any other input.
        max_side: long side of a server frame, at most (pixels).
        progress: show the encoder's progress bar on a terminal.
    """

    input: str
    host: str
    port: int
    lam: float | None = None
    preset: str | None = None
    views: str | None = None
    size: tuple[int, int] | None = None
    cameras: str | None = None
    max_side: int = DEFAULT_MAX_FRAME_SIDE
    progress: bool = False


def check_config(config: ViewConfig) -> str:
    """The input's kind (:data:`~.inputs.KINDS`) once the options fit it. DataError for a missing input;
    ViewerError for an option that does not apply to it or a ``max_side`` below 16; InputError for a λ outside
    [16, 1024]."""
    if config.max_side < MIN_FRAME_SIDE:
        raise ViewerError(f"--max-frame-side must be at least {MIN_FRAME_SIDE} pixels, got {config.max_side}")
    kind = input_kind(config.input)
    given = [flag for name, flag in SCENE_OPTIONS.items() if getattr(config, name) is not None]
    if kind != "scene" and given:
        raise ViewerError(f"{', '.join(given)} encode a scene folder, but {config.input} is a "
                          f"{'scene bitstream' if kind == 'bitstream' else '3DGS PLY file'}: leave them out")
    if config.cameras is not None and kind != "ply":
        raise ViewerError(f"--cameras places the views of a PLY file, but {config.input} is a "
                          f"{'scene bitstream' if kind == 'bitstream' else 'scene folder'}, whose cameras come with it")
    if config.lam is not None:
        check_lambda(config.lam)
    return kind


def load_input(config: ViewConfig, kind: str, model, choose_views: Callable[[str | None, int, int], list[int]],
               preset: str) -> tuple[ViewScene, SceneSource | None]:
    """The scene to show first and, for a scene folder, its context views (which the page encodes again)."""
    if kind == "bitstream":
        return read_bitstream(model, config.input), None
    if kind == "ply":
        device = next(model.parameters()).device
        return read_gaussians(config.input, config.cameras, device), None
    source = scene_source(config.input, config.views, config.size, model, choose_views)
    lam = DEFAULT_LAMBDA if config.lam is None else config.lam
    return encode_source(model, source, lam, preset, progress=config.progress), source


def serve(config: ViewConfig, device, checkpoint: str | None,
          choose_views: Callable[[str | None, int, int], list[int]], default_preset: str,
          announce: Callable[[dict, list[str]], None]) -> None:
    """Check ``config``, load the model (``checkpoint``, None for the shipped one) on ``device``, read the input,
    then serve it until Ctrl-C (or SIGTERM). ``choose_views(views, available, model views)`` picks a scene folder's
    context views, ``default_preset`` is its preset without ``--preset``; ``announce(result, lines)`` reports the
    running server (URL, input, counts) once it listens. Every error is raised before the server starts."""
    kind = check_config(config)
    choose_port(config.host, config.port, DEFAULT_PORT)
    model = load_pretrained(checkpoint, device)
    scene, source = load_input(config, kind, model, choose_views, config.preset or default_preset)
    viewer = Viewer(model, scene, source, config.max_side)
    _, warm_up_s = viewer.render(viewer.opening_camera(WARM_UP_SIDE, WARM_UP_SIDE))
    port = choose_port(config.host, config.port, DEFAULT_PORT)
    with contextlib.redirect_stdout(io.StringIO()):  # viser's banner: the command prints its own line
        server = viser.ViserServer(host=config.host, port=port, label="codecsplat view", verbose=False)
    try:
        viewer.attach(server)
        url = _url(config.host, server.get_port())
        announce(_summary(url, config, scene, device, warm_up_s),
                 [f"codecsplat view: {scene.name} ({_describe(scene)}) on {device}",
                  f"open {url} in a browser; Ctrl-C stops the server"])
        _wait_for_interrupt()
    finally:
        viewer.stop()
        with contextlib.redirect_stdout(io.StringIO()):
            server.stop()


def _url(host: str, port: int) -> str:
    return f"http://[{host}]:{port}" if ":" in host else f"http://{host}:{port}"


def _describe(scene: ViewScene) -> str:
    """A few words on what is shown: its kind, splat count and, with a bitstream, its λ and bytes."""
    words = f"{scene.kind}, {len(scene.splats):,d} splats"
    if scene.bitstream is not None:
        words += f", λ={scene.lam:g}, {len(scene.bitstream):,d} B"
    return words


def _summary(url: str, config: ViewConfig, scene: ViewScene, device, warm_up_s: float) -> dict:
    """The ``--json`` object of a running viewer."""
    return {"url": url, "port": int(url.rsplit(":", 1)[1]), "host": config.host, "input": config.input,
            "kind": scene.kind, "gaussians": len(scene.gaussians), "splats": len(scene.splats), "model": scene.model,
            "lambda": scene.lam, "preset": scene.preset, "bytes": scene.parts, "context_psnr": scene.context_psnr,
            "device": str(device), "seconds": {**scene.seconds, "first_frame": warm_up_s}}


def _wait_for_interrupt() -> None:
    """Sleep until Ctrl-C, or SIGTERM (taken as Ctrl-C while waiting, in the main thread)."""
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, _interrupt)
    try:
        while True:
            time.sleep(POLL_S)
    except KeyboardInterrupt:
        return
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _interrupt(signum, frame) -> None:
    raise KeyboardInterrupt
