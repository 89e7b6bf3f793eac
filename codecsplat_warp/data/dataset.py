"""torch ``Dataset`` / ``DataLoader`` path for training and evaluation.

Every item is a dict::

    {"key": str,
     "context": {"image": float32 [Vc,3,H,W] in [0,1], "K": [Vc,3,3], "w2c": [Vc,4,4], "near": [Vc], "far": [Vc],
                 "index": int64 [Vc]},
     "target":  {... the same with Vt views ...}}

(procedural items add ``"depth"`` float32 [V,H,W]). Cameras are float32, in pixels at the protocol size;
:func:`views_to_cameras` turns one (unbatched) view dict back into :class:`Cameras`.

Determinism: item i of epoch e draws its views from a generator seeded with (seed, e, i), so the result does
not depend on the number of workers or on which worker serves it. The context gap schedule follows the
training step set by :meth:`SceneDataset.set_step` (shared with worker processes through shared memory).
"""

from __future__ import annotations

import functools
import pathlib
from collections import OrderedDict
from dataclasses import dataclass, replace
from typing import Callable, Sequence

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset
from tqdm.auto import tqdm

from ..cameras import Cameras
from ..errors import DataError
from .chunks import load_index, read_chunk
from .formats import load_scene
from .preprocess import DatasetConfig, dataset_config, protocol_cameras, resize_and_crop
from .procedural import ProceduralConfig, procedural_scene
from .scene import Scene
from .views import BoundedSamplerConfig, ViewSelection, load_evaluation_index, sample_bounded_views

DEFAULT_CACHE_BYTES = 512 * 2**20
"""Per-process budget for decoded, preprocessed images kept between items."""


@dataclass(frozen=True)
class SceneRef:
    """A scene the dataset can load: its key, view count and a picklable loader."""

    key: str
    num_views: int
    load: Callable[[], Scene]


class ImageCache:
    """Least-recently-used store of uint8 [3,H,W] images keyed by (scene key, frame), bounded in bytes."""

    def __init__(self, max_bytes: int):
        self.max_bytes = int(max_bytes)
        self.bytes = 0
        self.entries: OrderedDict[tuple[str, int], torch.Tensor] = OrderedDict()

    def get(self, key: tuple[str, int]) -> torch.Tensor | None:
        image = self.entries.get(key)
        if image is not None:
            self.entries.move_to_end(key)
        return image

    def put(self, key: tuple[str, int], image: torch.Tensor) -> None:
        size = image.numel() * image.element_size()
        if size > self.max_bytes or key in self.entries:
            return
        self.entries[key] = image
        self.bytes += size
        while self.bytes > self.max_bytes:
            _, old = self.entries.popitem(last=False)
            self.bytes -= old.numel() * old.element_size()


class SceneDataset(Dataset):
    """Context/target samples from real scenes, preprocessed to a dataset protocol.

    Training (no ``evaluation_index``): one item per scene per epoch, views drawn by pixelSplat's bounded
    sampler. Evaluation: one item per scene listed (non-null) in the evaluation index, in its order.

    Args:
        scenes: the scenes (see :meth:`from_folders`, :meth:`from_chunks`).
        config: protocol (:class:`DatasetConfig` or ``re10k`` / ``acid`` / ``dl3dv``).
        sampler: bounded sampler settings for training.
        evaluation_index: path of an evaluation index file, or its parsed dict, for testing.
        seed: base seed of the view draws.
        use_config_depth_range: cameras get the config's near/far (True) or keep the scene's (False).
        cache_bytes: decoded-image cache budget per process.
    """

    def __init__(self, scenes: Sequence[SceneRef], config: DatasetConfig | str = "re10k",
                 sampler: BoundedSamplerConfig = BoundedSamplerConfig(), evaluation_index=None, seed: int = 0,
                 use_config_depth_range: bool = True, cache_bytes: int = DEFAULT_CACHE_BYTES):
        self.config = dataset_config(config) if isinstance(config, str) else config
        self.sampler = sampler
        self.seed = int(seed)
        self.use_config_depth_range = use_config_depth_range
        self.cache = ImageCache(cache_bytes)
        self.step = torch.zeros(2, dtype=torch.int64).share_memory_()  # [training step, epoch]
        self.selections: dict[str, ViewSelection] | None = None
        scenes = list(scenes)
        if evaluation_index is not None:
            index = evaluation_index if isinstance(evaluation_index, dict) else load_evaluation_index(evaluation_index)
            by_key = {s.key: s for s in scenes}
            scenes = [by_key[k] for k in index if k in by_key]
            self.selections = {k: index[k] for k in by_key if k in index}
            for ref in scenes:
                _check_selection(ref, self.selections[ref.key])
        self.scenes = scenes
        self._loaded: OrderedDict[str, Scene] = OrderedDict()

    # -- construction ---------------------------------------------------------------------------
    @classmethod
    def from_folders(cls, folders: Sequence, progress: bool = True, **kwargs) -> "SceneDataset":
        """Dataset of scene folders read with :func:`~codecsplat_warp.data.load_scene` (scanned once for view counts)."""
        refs = []
        for folder in tqdm(list(folders), desc="scanning scenes", unit="scene", disable=not progress):
            scene = load_scene(folder)
            refs.append(SceneRef(scene.key, scene.num_views, functools.partial(load_scene, pathlib.Path(folder))))
        return cls(refs, **kwargs)

    @classmethod
    def from_chunks(cls, root, progress: bool = True, **kwargs) -> "SceneDataset":
        """Dataset of a chunk folder (``index.json`` + ``*.torch``); every chunk is read once for view counts."""
        index = load_index(root)
        refs = []
        for chunk in tqdm(sorted(set(index.values())), desc="scanning chunks", unit="chunk", disable=not progress):
            for scene in _read_chunk_cached(chunk):
                refs.append(SceneRef(scene.key, scene.num_views, functools.partial(_chunk_scene, chunk, scene.key)))
        return cls(refs, **kwargs)

    # -- schedule -------------------------------------------------------------------------------
    def set_step(self, step: int) -> None:
        """Training step that drives the context-gap warm-up (visible to running workers)."""
        self.step[0] = int(step)

    def set_epoch(self, epoch: int) -> None:
        """Epoch mixed into the per-item seeds (visible to running workers)."""
        self.step[1] = int(epoch)

    # -- items ----------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.scenes)

    def __getitem__(self, index: int) -> dict:
        ref = self.scenes[index]
        if self.selections is not None:
            selection = self.selections[ref.key]
        else:
            generator = item_generator(self.seed, int(self.step[1]), index)
            try:
                selection = sample_bounded_views(ref.num_views, self.sampler, int(self.step[0]), generator)
            except DataError as exc:
                raise DataError(f"scene {ref.key!r}: {exc}") from None
        scene = self._scene(ref)
        return {"key": ref.key, "context": self._views(scene, selection.context),
                "target": self._views(scene, selection.target)}

    def _scene(self, ref: SceneRef) -> Scene:
        scene = self._loaded.get(ref.key)
        if scene is None:
            scene = ref.load()
            self._loaded[ref.key] = scene
            if len(self._loaded) > 64:
                self._loaded.popitem(last=False)
        return scene

    def _views(self, scene: Scene, frames: Sequence[int]) -> dict:
        frames = [int(f) for f in frames]
        images = []
        for frame in frames:
            image = self.cache.get((scene.key, frame))
            if image is None:
                image, _ = resize_and_crop(scene.decoded_images([frame]), scene.cameras.select([frame]),
                                           self.config.width, self.config.height)
                image = image[0]
                self.cache.put((scene.key, frame), image)
            images.append(image)
        cameras = protocol_cameras(scene.cameras.select(frames), self.config.width, self.config.height)
        if self.use_config_depth_range:
            cameras = cameras.with_depth_range(self.config.near, self.config.far)
        return _view_dict(torch.stack(images), cameras, frames)


class ProceduralDataset(Dataset):
    """Unlimited procedural training samples: item i renders scene seed (seed, i).

    The first and last views of each rendered trajectory (plus evenly spaced ones for more context views)
    are the context; the views in between are targets. Items carry exact ``depth``.
    """

    def __init__(self, length: int, config: ProceduralConfig = ProceduralConfig(), num_context_views: int = 2,
                 num_target_views: int = 2, seed: int = 0):
        if num_context_views < 1 or num_target_views < 0 or length < 1:
            raise DataError("need length >= 1, num_context_views >= 1 and num_target_views >= 0")
        self.length = length
        self.config = replace(config, num_views=num_context_views + num_target_views)
        self.num_context_views = num_context_views
        self.seed = seed

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, index: int) -> dict:
        scene_seed = int(np.random.SeedSequence([self.seed, index]).generate_state(1)[0])
        scene = procedural_scene(scene_seed, self.config)
        V = scene.num_views
        context = sorted({round(x) for x in np.linspace(0, V - 1, self.num_context_views)})
        target = [v for v in range(V) if v not in context]
        result = {"key": scene.key}
        for name, frames in (("context", context), ("target", target)):
            views = _view_dict(scene.images[frames], scene.cameras.select(frames), frames)
            views["depth"] = scene.depth[frames]
            result[name] = views
        return result


def make_dataloader(dataset: Dataset, batch_size: int = 1, num_workers: int = 0, shuffle: bool = True,
                    seed: int = 0, **kwargs) -> DataLoader:
    """DataLoader with a seeded shuffling order and persistent workers (when ``num_workers`` > 0)."""
    generator = torch.Generator().manual_seed(int(seed))
    return DataLoader(dataset, batch_size=batch_size, num_workers=num_workers, shuffle=shuffle, generator=generator,
                      persistent_workers=num_workers > 0, **kwargs)


def item_generator(seed: int, epoch: int, index: int) -> torch.Generator:
    """The torch generator of item ``index`` in ``epoch`` (independent of worker assignment)."""
    return torch.Generator().manual_seed(int(np.random.SeedSequence([seed, epoch, index]).generate_state(1)[0]))


def views_to_cameras(views: dict, width: int, height: int) -> Cameras:
    """:class:`Cameras` of one unbatched view dict (``K``, ``w2c``, ``near``, ``far``)."""
    return Cameras(K=views["K"], w2c=views["w2c"], near=views["near"], far=views["far"], width=width, height=height)


def _view_dict(images: torch.Tensor, cameras: Cameras, frames: Sequence[int]) -> dict:
    cameras = cameras.to(dtype=torch.float32)
    return {"image": images.float() / 255, "K": cameras.K, "w2c": cameras.w2c, "near": cameras.near,
            "far": cameras.far, "index": torch.tensor(list(frames), dtype=torch.int64)}


def _check_selection(ref: SceneRef, selection: ViewSelection) -> None:
    bad = [v for v in selection.context + selection.target if v >= ref.num_views]
    if bad:
        raise DataError(f"evaluation index: scene {ref.key!r} has {ref.num_views} views but selects {bad}")


@functools.lru_cache(maxsize=2)
def _read_chunk_cached(chunk: pathlib.Path) -> list[Scene]:
    return read_chunk(chunk)


def _chunk_scene(chunk: pathlib.Path, key: str) -> Scene:
    for scene in _read_chunk_cached(chunk):
        if scene.key == key:
            return scene
    raise DataError(f"{chunk}: scene {key!r} is not in this chunk")
