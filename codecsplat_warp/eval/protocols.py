"""Evaluation protocols and samples of ``codecsplat eval``: the image size and view counts of each protocol, the
scenes under ``--data``, the context/target frames of each sample (an evaluation index, or nearest-view splits
around evenly spread anchors) and the "copy the nearest context view" prediction."""

from __future__ import annotations

import pathlib
from dataclasses import dataclass

import torch

from ..cameras import Cameras
from ..data import detect_formats, load_evaluation_index, load_scene, split_context_targets
from ..data.preprocess import DatasetConfig, preprocess_scene
from ..errors import DataError


@dataclass(frozen=True)
class Protocol:
    """Image size and view counts of an evaluation protocol.

    Attributes:
        name: ``re10k``, ``dl3dv`` or ``scene``.
        width, height: protocol image size (resize to cover, centre-crop); None keeps each scene's stored
            size, cropped to multiples of 4.
        context_views: context views per sample; None uses the model's ``num_views``.
        target_views: target views rendered and scored per sample.
    """

    name: str
    width: int | None
    height: int | None
    context_views: int | None
    target_views: int = 3


PROTOCOLS = {
    "re10k": Protocol("re10k", 256, 256, 2),
    "dl3dv": Protocol("dl3dv", 448, 256, 8),
    "scene": Protocol("scene", None, None, None),
}
"""RE10K: 2 views at 256x256; DL3DV: 8 views at 256x448 (HxW); scene: stored size, the model's view count."""


@dataclass
class Sample:
    """One evaluation item: context and target views of a scene, images float32 [V,3,H,W] in [0,1]."""

    scene: str
    context: list[int]
    target: list[int]
    context_images: torch.Tensor
    context_cameras: Cameras
    target_images: torch.Tensor
    target_cameras: Cameras

    def to(self, device: torch.device) -> "Sample":
        return Sample(self.scene, self.context, self.target, self.context_images.to(device),
                      self.context_cameras.to(device), self.target_images.to(device), self.target_cameras.to(device))



# --------------------------------------------------------------------------------------------------
# Samples
def find_scenes(path) -> list[pathlib.Path]:
    """``path`` itself when it is a scene folder or pose file, else its sub-folders that hold a scene.

    Raises:
        DataError: ``path`` does not exist or holds no scene.
    """
    path = pathlib.Path(path)
    if not path.exists():
        raise DataError(f"{path} does not exist")
    if path.is_file() or detect_formats(path):
        return [path]
    scenes = sorted(p for p in path.iterdir() if p.is_dir() and detect_formats(p))
    if not scenes:
        raise DataError(f"{path} is neither a scene nor a folder of scenes (no pose file found)")
    return scenes


def select_scenes(paths: list[pathlib.Path], names: tuple[str, ...]) -> list[pathlib.Path]:
    """The ``paths`` whose folder name is in ``names``, in the order of ``names`` (all paths when it is empty).

    Raises:
        DataError: a name matches no path (the error lists the scenes found).
    """
    if not names:
        return paths
    by_name = {p.name: p for p in paths}
    missing = sorted(set(names) - set(by_name))
    if missing:
        raise DataError(f"scene(s) {', '.join(missing)} not found; found {', '.join(by_name)}")
    return [by_name[name] for name in names]


def scene_samples(path: pathlib.Path, protocol: Protocol, context_views: int, samples: int) -> list[Sample]:
    """``samples`` items of one scene, anchors evenly spread over its views, preprocessed to the protocol.

    The scene keeps its own near/far (real captures are not in the RE10K/DL3DV scale).
    """
    scene = load_scene(path)
    V = scene.num_views
    out = []
    for s in range(samples):
        anchor = min(V - 1, int((s + 0.5) * V / samples))
        context, target = split_context_targets(scene.cameras, anchor, context_views, protocol.target_views)
        out.append(protocol_sample(path.name, scene, protocol, context, target))
    return out


def index_samples(paths: list[pathlib.Path], index_file, protocol: Protocol) -> list[Sample]:
    """One item per entry of an evaluation index file (``{"<scene folder>": {"context": [...], "target":
    [...]}}``, see :func:`codecsplat_warp.data.load_evaluation_index`) among the scene folders ``paths``,
    preprocessed to the protocol, in the index's order.

    Raises:
        DataError: an entry names no scene folder of ``paths``, or a frame the scene does not have.
    """
    selections = load_evaluation_index(index_file)
    by_name = {p.name: p for p in paths}
    missing = [key for key in selections if key not in by_name]
    if missing:
        raise DataError(f"{index_file}: scene(s) {', '.join(missing)} are not in the data "
                        f"(found {', '.join(by_name) or 'none'})")
    out = []
    for key, selection in selections.items():
        scene = load_scene(by_name[key])
        frames = selection.context + selection.target
        if max(frames) >= scene.num_views:
            raise DataError(f"{index_file}: scene {key} has {scene.num_views} views, the index asks for frame "
                            f"{max(frames)}")
        out.append(protocol_sample(key, scene, protocol, list(selection.context), list(selection.target)))
    return out


def protocol_sample(name: str, scene, protocol: Protocol, context: list[int], target: list[int]) -> Sample:
    """The context and target frames of ``scene`` resized and centre-cropped to the protocol size (the stored
    size cropped to multiples of 4 when the protocol has none), keeping the scene's near/far."""
    width = protocol.width or scene.cameras.width // 4 * 4
    height = protocol.height or scene.cameras.height // 4 * 4
    frames = preprocess_scene(scene, DatasetConfig(width=width, height=height, near=0.0, far=0.0),
                              frames=context + target, use_config_depth_range=False)
    pixels = frames.images.float() / 255.0
    cameras = frames.cameras.to(dtype=torch.float32)
    n = len(context)
    return Sample(name, context, target, pixels[:n], cameras.select(list(range(n))), pixels[n:],
                  cameras.select(list(range(n, n + len(target)))))


def nearest_context_images(context_images: torch.Tensor, context_cameras: Cameras,
                           target_cameras: Cameras) -> torch.Tensor:
    """[T,3,H,W]: for each target camera, the context image [V,3,H,W] whose camera centre is nearest to its own
    (the "copy the nearest context view" prediction)."""
    distance = torch.cdist(target_cameras.centers.double(), context_cameras.centers.double())
    return context_images[distance.argmin(dim=1)]

