"""Evaluation protocols and samples of ``codecsplat eval``: the image size, view counts and depth range of each
protocol, the scenes under ``--data``, the context/target frames of each sample (an evaluation index, or
nearest-view splits around evenly spread anchors) and the "copy the nearest context view" prediction.

``--data`` is a scene folder, a folder of scene folders, or a folder of RE10K/ACID/DL3DV ``.torch`` chunks
with their ``index.json`` (:func:`is_chunk_folder`). A :class:`SamplePlan` lists every sample's
(scene, context, target) before any image is decoded and then produces the samples one at a time, in order: a
chunk folder is read one chunk at a time (:func:`chunk_plan`), never whole.
"""

from __future__ import annotations

import itertools
import pathlib
from dataclasses import dataclass, replace
from typing import Callable, Collection, Iterator

import torch

from ..cameras import Cameras
from ..data import detect_formats, load_evaluation_index, load_scene, split_context_targets
from ..data.chunks import load_index, read_chunk
from ..data.preprocess import DATASET_CONFIGS, DatasetConfig, preprocess_scene
from ..data.scene import name_list
from ..data.views import ViewSelection
from ..errors import DataError, InputError


@dataclass(frozen=True)
class Protocol:
    """Image size and view counts of an evaluation protocol.

    Attributes:
        name: ``re10k``, ``dl3dv`` or ``scene``.
        width, height: protocol image size (resize to cover, centre-crop); None keeps each scene's stored
            size, cropped to multiples of 4.
        context_views: context views per sample; None uses the model's ``num_views``.
        target_views: target views rendered and scored per sample.
        near, far: depth range (scene units) given to every camera of a chunk dataset, which stores none
            (DepthSplat's per dataset, :data:`~codecsplat_warp.data.preprocess.DATASET_CONFIGS`); None for the
            ``scene`` protocol. Scene folders keep their own bounds (real captures are not in RE10K/DL3DV scale).
    """

    name: str
    width: int | None
    height: int | None
    context_views: int | None
    target_views: int = 3
    near: float | None = None
    far: float | None = None


PROTOCOLS = {
    "re10k": Protocol("re10k", 256, 256, 2, near=DATASET_CONFIGS["re10k"].near, far=DATASET_CONFIGS["re10k"].far),
    "dl3dv": Protocol("dl3dv", 448, 256, 8, near=DATASET_CONFIGS["dl3dv"].near, far=DATASET_CONFIGS["dl3dv"].far),
    "scene": Protocol("scene", None, None, None),
}
"""RE10K: 2 views at 256x256, depth 0.5-100; DL3DV: 8 views at 256x448 (HxW), depth 0.5-200 (DepthSplat's
``config/experiment/{re10k,dl3dv}.yaml``, which set RE10K's near to 0.5 where pixelSplat's dataset config has 1);
scene: stored size, the model's view count."""


@dataclass
class Sample:
    """One evaluation item: context and target views of a scene, images float32 [V,3,H,W] in [0,1].

    ``context_files`` (the context views' frame names, e.g. ``images/x.jpg`` as in the scene's
    ``cameras.json``) and ``stored_size`` (the scene's stored (width, height) before the protocol's resize and
    centre crop) let reference data of the stored views be brought to the sample's grid
    (:mod:`~codecsplat_warp.eval.geometry`); empty / None where the sample does not come from a stored scene.
    """

    scene: str
    context: list[int]
    target: list[int]
    context_images: torch.Tensor
    context_cameras: Cameras
    target_images: torch.Tensor
    target_cameras: Cameras
    context_files: tuple[str, ...] = ()
    stored_size: tuple[int, int] | None = None

    def to(self, device: torch.device) -> "Sample":
        return replace(self, context_images=self.context_images.to(device),
                       context_cameras=self.context_cameras.to(device), target_images=self.target_images.to(device),
                       target_cameras=self.target_cameras.to(device))



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


SampleKey = tuple[str, tuple[int, ...], tuple[int, ...]]
"""(scene, context frames, target frames): what names a sample in ``results.json`` (and lets a run resume)."""


@dataclass
class SamplePlan:
    """The samples of one evaluation, named before any image is decoded, produced one at a time.

    Attributes:
        keys: every sample's (scene, context frames, target frames), in evaluation order.
        skipped: scenes left out, as ``{"scene": name, "reason": text}``.
        load: ``load(start)`` yields the :class:`Sample` of ``keys[start:]``, in order, loading each scene
            (or chunk) only when its first sample is due.
    """

    keys: list[SampleKey]
    skipped: list[dict]
    load: Callable[[int], Iterator[Sample]]


def sample_key(sample: Sample) -> SampleKey:
    """The :data:`SampleKey` of a sample."""
    return sample.scene, tuple(sample.context), tuple(sample.target)


def eager_plan(samples: list[Sample], skipped: list[dict]) -> SamplePlan:
    """A plan of samples already in memory."""
    return SamplePlan([sample_key(s) for s in samples], skipped, lambda start: iter(samples[start:]))


def index_samples(paths: list[pathlib.Path], index_file, protocol: Protocol) -> list[Sample]:
    """Every sample of :func:`folder_index_plan`, loaded."""
    return list(folder_index_plan(paths, index_file, protocol).load(0))


def index_selections(index_file, scenes: Collection[str] = ()) -> dict[str, ViewSelection]:
    """The entries of an evaluation index file (:func:`codecsplat_warp.data.load_evaluation_index`), only those of
    ``scenes`` when given. Raises DataError when ``scenes`` names a key the index does not select."""
    selections = load_evaluation_index(index_file)
    if scenes:
        unknown = sorted(set(scenes) - set(selections))
        if unknown:
            raise DataError(f"{index_file} selects no scene {name_list(unknown)}")
        selections = {k: v for k, v in selections.items() if k in set(scenes)}
    return selections


def folder_index_plan(paths: list[pathlib.Path], index_file, protocol: Protocol,
                      scenes: Collection[str] = ()) -> SamplePlan:
    """One sample per entry of an evaluation index file (``{"<scene folder>": {"context": [...], "target":
    [...]}}``, null entries skipped, see :func:`codecsplat_warp.data.load_evaluation_index`) among the scene
    folders ``paths``, preprocessed to the protocol, in the index's order; each scene is loaded when its sample
    is due. ``scenes`` keeps only those entries of the index (all when empty).

    Raises:
        DataError: ``scenes`` names a key the index does not select; the index names no scene of ``paths``, or
            some it names are missing (checked at once); a frame the scene does not have (when that scene is loaded).
    """
    selections = index_selections(index_file, scenes)
    by_name = {p.name: p for p in paths}
    _check_index_scenes(index_file, selections, by_name, "the data")
    keys = [(key, sel.context, sel.target) for key, sel in selections.items()]

    def load(start: int) -> Iterator[Sample]:
        for key, context, target in keys[start:]:
            scene = load_scene(by_name[key])
            check_frames(index_file, key, scene.num_views, context + target)
            yield protocol_sample(key, scene, protocol, list(context), list(target))

    return SamplePlan(keys, [], load)


def is_chunk_folder(path) -> bool:
    """Whether ``path`` is a folder of ``.torch`` chunks with their ``index.json``."""
    path = pathlib.Path(path)
    return path.is_dir() and (path / "index.json").is_file() and any(path.glob("*.torch"))


def chunk_plan(root, index_file, protocol: Protocol, scenes: Collection[str] = ()) -> SamplePlan:
    """The samples an evaluation index (pixelSplat / DepthSplat ``evaluation_index_*.json``: per scene key its
    ``context`` and ``target`` frames, null to skip) selects from a chunk folder, streamed one chunk at a time.

    Samples are ordered by chunk file, then by their order in the index, so each chunk is read once; a
    chunk's images stay JPEG-encoded until their frames are preprocessed. Every camera gets the protocol's
    depth range (chunks store none).

    Args:
        root: the chunk folder (``index.json`` mapping scene keys to chunk files, ``*.torch``).
        index_file: the evaluation index.
        protocol: a protocol with a depth range (``re10k``, ``dl3dv``).
        scenes: keep only these scene keys of the index (all when empty).
    Raises:
        InputError: the protocol has no depth range (``scene``).
        DataError: malformed ``index.json`` or evaluation index; ``scenes`` names a key the index does not
            select; the index names no scene of the data, or some it names are missing (checked at once); a
            chunk without a scene ``index.json`` puts there, or a frame a scene does not have (when loaded).
    """
    if protocol.near is None or protocol.far is None:
        raise InputError(f"the {protocol.name} protocol has no depth range, and chunks store none: "
                         "use --protocol re10k or dl3dv")
    root = pathlib.Path(root)
    chunks = load_index(root)
    selections = index_selections(index_file, scenes)
    _check_index_scenes(index_file, selections, chunks, f"{root / 'index.json'}")
    order = {key: i for i, key in enumerate(selections)}
    keys = sorted(((key, sel.context, sel.target) for key, sel in selections.items()),
                  key=lambda k: (chunks[k[0]].name, order[k[0]]))

    def load(start: int) -> Iterator[Sample]:
        for chunk, group in itertools.groupby(keys[start:], key=lambda k: chunks[k[0]]):
            found = {scene.key: scene for scene in read_chunk(chunk, protocol.near, protocol.far)}
            for key, context, target in group:
                if key not in found:
                    raise DataError(f"{root / 'index.json'} puts scene {key!r} in {chunk.name}, which does not hold it")
                check_frames(index_file, key, found[key].num_views, context + target)
                yield protocol_sample(key, found[key], protocol, list(context), list(target))

    return SamplePlan(keys, [], load)


def check_frames(index_file, key: str, num_views: int, frames: Collection[int]) -> None:
    """DataError naming the index, the scene and the frames when ``frames`` asks for one beyond ``num_views``."""
    bad = sorted(f for f in set(frames) if f >= num_views)
    if bad:
        raise DataError(f"{index_file}: scene {key!r} has {num_views} frames (0..{num_views - 1}), the index asks "
                        f"for frame(s) {', '.join(map(str, bad))}")


def _check_index_scenes(index_file, selections: dict[str, ViewSelection], available: Collection[str],
                        where: str) -> None:
    """DataError when the index names no scene of ``available``, or names some that are missing."""
    missing = [key for key in selections if key not in available]
    if selections and len(missing) == len(selections):
        raise DataError(f"{index_file} names none of the {len(available)} scene(s) in {where} "
                        f"(it names {name_list(missing)}; is it the index of another dataset?)")
    if missing:
        raise DataError(f"{index_file}: scene(s) {name_list(missing)} are not in {where}")


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
                  cameras.select(list(range(n, n + len(target)))), tuple(scene.frame_names[f] for f in context),
                  (scene.cameras.width, scene.cameras.height))


def nearest_context_images(context_images: torch.Tensor, context_cameras: Cameras,
                           target_cameras: Cameras) -> torch.Tensor:
    """[T,3,H,W]: for each target camera, the context image [V,3,H,W] whose camera centre is nearest to its own
    (the "copy the nearest context view" prediction)."""
    distance = torch.cdist(target_cameras.centers.double(), context_cameras.centers.double())
    return context_images[distance.argmin(dim=1)]

