"""The options of ``codecsplat view`` (argparse only: ``--help`` imports neither torch nor viser)."""

from __future__ import annotations

import argparse

DEFAULT_HOST = "127.0.0.1"
"""The viewer listens on this machine only unless ``--host`` says otherwise."""

DEFAULT_PORT = 8080
"""viser's default port; ``--port 0`` takes the first free port from here up."""

DEFAULT_LAMBDA = 128.0
"""λ of a scene folder's first encode without ``--lambda`` (``codecsplat encode``'s default)."""

DEFAULT_MAX_FRAME_SIDE = 960
"""Long side (pixels) of the frames the server renders at most; the browser stretches them over its canvas."""

MIN_FRAME_SIDE = 16
"""The smallest ``--max-frame-side`` accepted (pixels)."""


def add_arguments(parser: argparse.ArgumentParser, presets: tuple[str, ...]) -> None:
    """The arguments of ``codecsplat view`` (besides the common ``--device``, ``--json``, ``--threads`` and
    ``--checkpoint``); ``presets`` are the encoder's preset names."""
    parser.add_argument("input", metavar="INPUT", help="a scene bitstream (.csplat), a 3DGS PLY file, or a scene "
                        "folder or pose file (encoded first, as codecsplat encode does)")
    parser.add_argument("--host", default=DEFAULT_HOST, help="address to serve the page on (default %(default)s: this "
                        "machine only)")
    parser.add_argument("--port", type=int, default=DEFAULT_PORT, help="port to serve the page on; 0 takes the first "
                        f"free port from {DEFAULT_PORT} up (default %(default)s)")
    parser.add_argument("--lambda", dest="lam", type=float, default=None, help="a scene folder's rate trade-off in "
                        f"[16, 1024] (default {DEFAULT_LAMBDA:g}); the page's slider encodes it again at another")
    parser.add_argument("--preset", choices=list(presets), default=None, help="a scene folder's encoder preset, as "
                        "codecsplat encode takes it (default: medium on a CUDA GPU, fast on the CPU)")
    parser.add_argument("--views", help="a scene folder's context view indices, e.g. 0,5 (default: the model's view "
                        "count, evenly spread)")
    parser.add_argument("--size", help="WIDTHxHEIGHT a scene folder's views are resized and centre-cropped to "
                        "(default: the model's training size)")
    parser.add_argument("--cameras", help="with a PLY: a pose file of views in the PLY's world, drawn as frustums "
                        "(with their photographs when the image files are there); the page opens at its first view "
                        "(default: a view along the PLY's +z axis that frames the Gaussians)")
    parser.add_argument("--max-frame-side", type=int, default=DEFAULT_MAX_FRAME_SIDE, metavar="PX",
                        help="long side of the frames the server renders, at most, in pixels (default %(default)s)")
