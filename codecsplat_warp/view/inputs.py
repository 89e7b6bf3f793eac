"""What ``codecsplat view`` shows, read from its input: a scene bitstream, a 3DGS PLY file, or a scene folder that it
encodes (and encodes again at another λ or preset from the page).

Every input error is raised here, before a server starts: a missing path (:class:`~codecsplat_warp.errors.DataError`),
a corrupt, truncated or foreign bitstream (:class:`~codecsplat_warp.errors.BitstreamError`, from the decoder), a PLY
without the 3DGS properties (``DataError``, from :func:`~codecsplat_warp.export.ply.read_ply`), an unreadable scene
folder (``DataError``, from :func:`~codecsplat_warp.data.load_scene`).
"""

from __future__ import annotations

import pathlib
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch

from ..cameras import Cameras
from ..codec import bytes_report, check_lambda
from ..codec.bitstream import MAGIC
from ..data import load_scene
from ..data.preprocess import DatasetConfig, preprocess_scene, resize_to_max_side
from ..errors import DataError
from ..export.ply import read_ply
from ..gaussians import Gaussians
from ..metrics import psnr
from ..model.codecsplat import model_id
from ..model.prune import prune_transparent
from .geometry import framing_camera

KINDS = ("bitstream", "ply", "scene")
"""The inputs ``codecsplat view`` takes: a scene bitstream, a 3DGS PLY file, a scene folder (or pose file)."""

PLY_MAGIC = b"ply"
"""The first bytes of every PLY file."""

PHOTOGRAPH_SIDE = 256
"""A PLY's photographs (from ``--cameras``) are sent to the browser at most this many pixels on their long side."""

ENCODE_PHASES = ("encode", "decode", "score")
"""The phases of :func:`encode_source`, in order, as its ``on_phase`` callback names them."""


@dataclass(frozen=True)
class ViewScene:
    """One set of Gaussians the viewer shows, and what it came from.

    Attributes:
        kind: one of :data:`KINDS`.
        name: the input's file or folder name.
        gaussians: every Gaussian of the input (what ``codecsplat decode`` writes), on the model's device.
        splats: the Gaussians with an opacity of at least 1/255 (the others draw nothing): drawn and rendered.
        reference: the camera the page opens at, float64 on the CPU: the first context camera, or for a PLY without
            cameras one that frames the Gaussians (:func:`~codecsplat_warp.view.geometry.framing_camera`).
        context: the context cameras (float64, CPU), drawn as frustums; None for a PLY without cameras.
        photographs: uint8 [V,H,W,3] photographs of the context views when the input had them, else None.
        bitstream: the scene bitstream (None for a PLY).
        parts: bytes per part of the bitstream (:func:`~codecsplat_warp.codec.bytes_report`), None for a PLY.
        model: the id of the model that wrote the bitstream, None for a PLY.
        lam: the bitstream's λ, None for a PLY.
        preset: the encoder preset a scene folder was encoded with, else None.
        context_psnr: per context view, the PSNR (dB) of the decoded scene rendered into it against its photograph
            (a scene folder), else None.
        seconds: what reading the input took, by phase.
    """

    kind: str
    name: str
    gaussians: Gaussians
    splats: Gaussians
    reference: Cameras
    context: Cameras | None
    photographs: np.ndarray | None
    bitstream: bytes | None
    parts: dict[str, int] | None
    model: str | None
    lam: float | None
    preset: str | None = None
    context_psnr: list[float] | None = None
    seconds: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class SceneSource:
    """The context views of a scene folder, ready to encode.

    Attributes:
        name: the folder (or pose file) name.
        images: [V,3,H,W] float32 in [0,1] on the model's device (resized and centre-cropped).
        cameras: the V context cameras at that size (float32, the model's device).
    """

    name: str
    images: torch.Tensor
    cameras: Cameras


def input_kind(path: str) -> str:
    """Which of :data:`KINDS` the input ``path`` is: a folder is a scene; a file is a bitstream when it starts with
    the bitstream magic or ends in ``.csplat``, a PLY when it starts with ``ply`` or ends in ``.ply``, else a pose
    file. DataError when ``path`` does not exist."""
    file = pathlib.Path(path)
    if not file.exists():
        raise DataError(f"{path} does not exist: codecsplat view takes a scene bitstream (.csplat), a 3DGS PLY file "
                        "or a scene folder")
    if file.is_dir():
        return "scene"
    with open(file, "rb") as handle:
        head = handle.read(len(MAGIC))
    if head == MAGIC or file.suffix.lower() == ".csplat":
        return "bitstream"
    if head.startswith(PLY_MAGIC) or file.suffix.lower() == ".ply":
        return "ply"
    return "scene"


def read_bitstream(model, path: str) -> ViewScene:
    """The decoded scene of the bitstream file ``path``. BitstreamError when it is truncated, corrupt, of a newer
    format or written by another model than ``model``."""
    data = pathlib.Path(path).read_bytes()
    start = time.perf_counter()
    decoded = model.decode_scene(data)
    seconds = {"decode": time.perf_counter() - start}
    context = decoded.cameras.to("cpu", torch.float64)
    return ViewScene(kind="bitstream", name=pathlib.Path(path).name, gaussians=decoded.gaussians,
                     splats=prune_transparent(decoded.gaussians)[0], reference=context.select([0]), context=context,
                     photographs=None, bitstream=data, parts=bytes_report(data), model=decoded.header.model_id,
                     lam=decoded.lam, seconds=seconds)


def read_gaussians(path: str, cameras: str | None, device: torch.device) -> ViewScene:
    """The Gaussians of the 3DGS PLY file ``path`` on ``device``; ``cameras``: a pose file of views in the PLY's
    world (drawn as frustums, with their photographs when its image files are there; the page opens at its first
    view), else the page opens at a camera that frames the Gaussians. DataError for a file without the 3DGS
    properties or an unreadable pose file."""
    start = time.perf_counter()
    gaussians = read_ply(path, device)
    seconds = {"read": time.perf_counter() - start}
    if len(gaussians) == 0:
        raise DataError(f"{path} holds no Gaussian")
    context, photographs = None, None
    if cameras is not None:
        posed = load_scene(cameras)
        context = posed.cameras.to("cpu", torch.float64)
        photographs = _photographs(posed)
    reference = context.select([0]) if context is not None else framing_camera(gaussians.means)
    return ViewScene(kind="ply", name=pathlib.Path(path).name, gaussians=gaussians,
                     splats=prune_transparent(gaussians)[0], reference=reference, context=context,
                     photographs=photographs, bitstream=None, parts=None, model=None, lam=None, seconds=seconds)


def _photographs(scene) -> np.ndarray | None:
    """uint8 [V,h,w,3] images of a loaded scene, resized to at most :data:`PHOTOGRAPH_SIDE` pixels on their long side;
    None when its image files cannot be read."""
    try:
        images = scene.decoded_images()
    except DataError:
        return None
    return resize_to_max_side(images, scene.cameras, PHOTOGRAPH_SIDE)[0].permute(0, 2, 3, 1).numpy()


def scene_source(path: str, views: str | None, size: tuple[int, int] | None, model,
                 choose_views: Callable[[str | None, int, int], list[int]]) -> SceneSource:
    """The context views of the scene folder or pose file ``path`` as ``codecsplat encode`` takes them:
    ``choose_views(views, available, model views)`` picks the indices (``--views``, or the model's view count evenly
    spread), resized and centre-cropped to ``size`` (width, height; None: the model's training size), the scene's
    own depth range kept."""
    scene = load_scene(path)
    chosen = choose_views(views, scene.num_views, model.config.num_views)
    width, height = size or (model.config.width, model.config.height)
    config = DatasetConfig(width=width, height=height, near=0.0, far=0.0)
    scene = preprocess_scene(scene, config, frames=chosen, use_config_depth_range=False)
    device = next(model.parameters()).device
    return SceneSource(name=pathlib.Path(path).name, images=(scene.images.float() / 255.0).to(device),
                       cameras=scene.cameras.to(device, torch.float32))


def encode_source(model, source: SceneSource, lam: float, preset: str,
                  on_phase: Callable[[str], None] = lambda phase: None, progress: bool = False) -> ViewScene:
    """Encode the context views of ``source`` at ``lam`` with the encoder ``preset`` (as ``codecsplat encode``),
    decode the bitstream and score its Gaussians in the context views. ``on_phase`` is called with each of
    :data:`ENCODE_PHASES` as it starts; ``progress`` shows the optimisation's progress bar on a terminal. InputError
    for a λ outside [16, 1024] or an unknown preset."""
    lam = check_lambda(lam)
    seconds = {}
    on_phase("encode")
    start = time.perf_counter()
    data = model.encode_scene(source.images, source.cameras, lam, preset=preset, progress=progress).data
    seconds["encode"] = time.perf_counter() - start
    on_phase("decode")
    start = time.perf_counter()
    decoded = model.decode_scene(data)
    seconds["decode"] = time.perf_counter() - start
    on_phase("score")
    with torch.no_grad():
        rendered = model.render(decoded.gaussians, source.cameras)["rgb"]
    scores = psnr(rendered, source.images).tolist()
    context = source.cameras.to("cpu", torch.float64)
    photographs = (source.images * 255.0).round().to("cpu", torch.uint8).permute(0, 2, 3, 1).numpy()
    return ViewScene(kind="scene", name=source.name, gaussians=decoded.gaussians,
                     splats=prune_transparent(decoded.gaussians)[0], reference=context.select([0]), context=context,
                     photographs=photographs, bitstream=data, parts=bytes_report(data), model=model_id(model),
                     lam=decoded.lam, preset=preset, context_psnr=scores, seconds=seconds)
