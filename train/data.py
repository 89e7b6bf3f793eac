"""Training batches: several scenes' context and target views at one view count and image size per step.

A *batch source* is a function ``source(index) -> TrainingBatch`` that is deterministic in ``index`` (the
global batch counter ``(step * accumulate + micro) * world_size + rank``), so a resumed or multi-GPU run
draws exactly the batches it would have drawn without interruption and no sampler state needs checkpointing.

Each batch first draws its :class:`BatchShape` from a :class:`DataSpec`: a context view count (2-8 views
trains one model for both protocols), an image size (256x256 or 256x448) and as many scenes as fit the
context-view budget. Each scene of the batch is then a procedural scene or a real one:

* **real** scenes (folders with ``cameras.json``, e.g. packed by :mod:`train.pack_scenes`) are decoded once
  per worker at their stored size; a sample takes an anchor view and views around it with the targets
  between the context views (:func:`split_context_targets`, a random extra spread widens the baseline), resizes them to cover the batch size with a random zoom of up to
  :data:`MAX_ZOOM` and crops at a random position (intrinsics follow);
* **procedural** rooms and tabletops (:mod:`codecsplat_warp.data.procedural`, exact geometry) are textured
  with random crops of the real training photographs when ``DataSpec.photo_textures`` is set, next to the
  synthetic patterns;
* **chunk** scenes (``chunks:DIR``: RE10K / ACID / DL3DV ``.torch`` chunks with ``index.json``,
  :mod:`codecsplat_warp.data.chunks`) are read one chunk at a time (a few chunks cached per worker); a
  sample draws its context and targets with pixelSplat's / DepthSplat's bounded view sampler
  (:func:`~codecsplat_warp.data.views.sample_bounded_views`, ``DataSpec.view_sampler``; the context gap widens
  with the training step, ``BatchShape.step``) and is resized and cropped as real scenes are;
* with ``DataSpec.photometric`` every scene gets one random brightness, contrast, saturation and gamma
  change for all of its views (a camera's exposure, the same in context and targets);
* with ``DataSpec.mirror`` every scene is mirrored left-right with probability 1/2, all of its views together
  (images flipped, cameras :meth:`~codecsplat_warp.cameras.Cameras.mirrored`): a mirrored world that is just
  as consistent, which doubles the scenes a small training set offers.
"""

from __future__ import annotations

import dataclasses
import pathlib
from collections import OrderedDict
from dataclasses import dataclass
from typing import Callable

import torch
from torch.nn import functional as F

from codecsplat_warp.cameras import Cameras
from codecsplat_warp.data.chunks import load_index, read_chunk
from codecsplat_warp.data.depth_maps import INDEX_FILE, read_depth_maps
from codecsplat_warp.data.scene import Scene
from codecsplat_warp.data.views import (BoundedSamplerConfig, context_gap_bounds, sample_bounded_views,
                                        split_context_targets)
from codecsplat_warp.errors import DataError, InputError
from codecsplat_warp.nn.config import MODEL_STRIDE, ModelConfig

MAX_ZOOM = 1.15
"""Real scenes are resized to cover the batch size times a zoom drawn from [1, MAX_ZOOM], then cropped at random."""

PHOTOMETRIC = {"brightness": (0.8, 1.2), "contrast": (0.8, 1.2), "saturation": (0.7, 1.3), "gamma": (0.8, 1.25)}
"""Ranges of the per-scene photometric augmentation factors (each drawn uniformly; 1 is no change)."""

PHOTO_TEXTURES_PER_SCENE = 6
"""Photograph crops a procedural scene gets as extra textures (next to its 8 synthetic ones)."""

CHUNK_CACHE = 2
"""Chunks a :class:`ChunkScenes` keeps read (images still JPEG-encoded) per process, least recently used dropped."""

MAX_SCENE_DRAWS = 16
"""Chunk scenes a sample draws before giving up when each is too short for the context gap (pixelSplat skips them)."""


@dataclass(frozen=True)
class BatchShape:
    """What one training batch holds: ``scenes`` scenes of ``views`` context and ``targets`` target views,
    every image ``height`` x ``width`` pixels, drawn at optimiser step ``step`` (the context gap schedule of
    chunk scenes follows it)."""

    views: int
    targets: int
    height: int
    width: int
    scenes: int
    step: int = 0


@dataclass(frozen=True)
class DataSpec:
    """How batches are drawn.

    Attributes:
        views: context view counts a batch may have (one drawn uniformly per batch).
        sizes: image sizes (height, width) a batch may have (one drawn uniformly per batch).
        targets: target views per scene.
        batch_views: context views per batch: a batch holds ``max(1, batch_views // views)`` scenes.
        procedural_fraction: share of procedural scenes when real scenes are given too (``mix:``).
        photo_textures: texture procedural scenes with crops of the real training photographs.
        photometric: per-scene photometric augmentation.
        mirror: mirror half of the scenes left-right (world and images).
        view_sampler: the bounded view sampler of chunk scenes (gaps in frames; its context and target
            counts are replaced by each batch's); the default is DepthSplat's RE10K schedule.
        batches_per_step: batches per optimiser step (``accumulate * world_size``): batch ``index`` is drawn
            at step ``index // batches_per_step``.
    """

    views: tuple[int, ...]
    sizes: tuple[tuple[int, int], ...]
    targets: int = 4
    batch_views: int = 2
    procedural_fraction: float = 0.5
    photo_textures: bool = False
    photometric: bool = False
    mirror: bool = False
    view_sampler: BoundedSamplerConfig = BoundedSamplerConfig()
    batches_per_step: int = 1

    def __post_init__(self) -> None:
        if not self.views or any(v < 2 for v in self.views):
            raise InputError(f"context view counts must be >= 2, got {self.views}")
        if not self.sizes or any(h % MODEL_STRIDE or w % MODEL_STRIDE or h < 1 or w < 1 for h, w in self.sizes):
            raise InputError(f"image sizes must be positive multiples of {MODEL_STRIDE}, got {self.sizes}")
        if self.targets < 1 or self.batch_views < 1 or self.batches_per_step < 1:
            raise InputError("targets, batch_views and batches_per_step must be >= 1, got "
                             f"{self.targets}, {self.batch_views}, {self.batches_per_step}")
        if not 0.0 <= self.procedural_fraction <= 1.0:
            raise InputError(f"procedural_fraction must be in [0, 1], got {self.procedural_fraction}")

    @property
    def augmentation(self) -> "Augmentation":
        return Augmentation(photometric=self.photometric, mirror=self.mirror)

    @classmethod
    def of_model(cls, config: ModelConfig) -> "DataSpec":
        """One scene per batch at the preset's view count, size and target count (the stage-1 default)."""
        return cls(views=(config.num_views,), sizes=((config.height, config.width),),
                   targets=config.num_target_views, batch_views=config.num_views)


def parse_views(text: str) -> tuple[int, ...]:
    """``"2,4,8"`` -> (2, 4, 8); InputError on anything else."""
    try:
        return tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise InputError(f"view counts must be comma-separated integers, got {text!r}") from None


def parse_sizes(text: str) -> tuple[tuple[int, int], ...]:
    """``"256x256,256x448"`` (height x width) -> ((256, 256), (256, 448)); InputError on anything else."""
    try:
        return tuple((int(h), int(w)) for h, w in (s.lower().split("x") for s in text.split(",") if s.strip()))
    except ValueError:
        raise InputError(f"sizes must be comma-separated HEIGHTxWIDTH, got {text!r}") from None


def fixed_context_gap(text: str) -> BoundedSamplerConfig:
    """``"MIN,MAX"`` (frames) -> the default bounded sampler with the context gap drawn from [MIN, MAX] at
    every step (no warm-up); InputError on anything else."""
    try:
        low, high = (int(v) for v in text.split(","))
    except ValueError:
        raise InputError(f"a context gap must be MIN,MAX (frames), got {text!r}") from None
    if not 1 <= low <= high:
        raise InputError(f"a context gap needs 1 <= MIN <= MAX, got {text!r}")
    return BoundedSamplerConfig(min_distance_between_context_views=low, max_distance_between_context_views=high,
                                initial_min_distance_between_context_views=low,
                                initial_max_distance_between_context_views=high, warm_up_steps=0)


def batch_shape(spec: DataSpec, seed: int, index: int) -> BatchShape:
    """The shape of batch ``index``: a function of (seed, index) only."""
    generator = _generator(seed, index, -1)
    views = spec.views[int(torch.randint(len(spec.views), (), generator=generator))]
    height, width = spec.sizes[int(torch.randint(len(spec.sizes), (), generator=generator))]
    return BatchShape(views, spec.targets, height, width, max(1, spec.batch_views // views),
                      index // spec.batches_per_step)


@dataclass
class TrainingSample:
    """One scene's training example.

    Attributes:
        context_images: float32 [V,3,H,W] in [0,1]; context_cameras: V cameras at H x W.
        target_images: float32 [T,3,H,W] in [0,1]; target_cameras: T cameras at H x W.
        key: scene name (for logs).
        context_depth: float32 [V,H,W] reference depth of the context views (camera z, scene units; 0 where
            none is known): exact for procedural scenes, multi-view stereo for real scenes that have it
            (:data:`DEPTH_FOLDER`), all zero otherwise.
    """

    context_images: torch.Tensor
    context_cameras: Cameras
    target_images: torch.Tensor
    target_cameras: Cameras
    key: str
    context_depth: torch.Tensor


@dataclass
class TrainingBatch:
    """S scenes of one :class:`BatchShape`, stacked scene-major.

    Attributes:
        context_images: float32 [S*V,3,H,W] in [0,1]; context_cameras: the S*V cameras.
        target_images: float32 [S*T,3,H,W] in [0,1]; target_cameras: the S*T cameras.
        keys: the S scene names.
        context_depth: float32 [S*V,H,W] reference depth of the context views, 0 where unknown
            (:attr:`TrainingSample.context_depth`).
    """

    context_images: torch.Tensor
    context_cameras: Cameras
    target_images: torch.Tensor
    target_cameras: Cameras
    keys: tuple[str, ...]
    context_depth: torch.Tensor

    @property
    def scenes(self) -> int:
        return len(self.keys)

    @property
    def targets_per_scene(self) -> int:
        return self.target_cameras.num_views // self.scenes

    @classmethod
    def stack(cls, samples: list[TrainingSample]) -> "TrainingBatch":
        """The batch of ``samples`` (all of one view count and size)."""
        return cls(torch.cat([s.context_images for s in samples]), Cameras.concat([s.context_cameras for s in samples]),
                   torch.cat([s.target_images for s in samples]), Cameras.concat([s.target_cameras for s in samples]),
                   tuple(s.key for s in samples), torch.cat([s.context_depth for s in samples]))

    def scene_targets(self) -> list[Cameras]:
        """The target cameras of each scene."""
        T = self.targets_per_scene
        return [self.target_cameras.select(slice(s * T, (s + 1) * T)) for s in range(self.scenes)]

    def scene_contexts(self) -> list[Cameras]:
        """The context cameras of each scene."""
        V = self.context_cameras.num_views // self.scenes
        return [self.context_cameras.select(slice(s * V, (s + 1) * V)) for s in range(self.scenes)]

    def to(self, device, non_blocking: bool = False) -> "TrainingBatch":
        move = lambda t: t.to(device, non_blocking=non_blocking)  # noqa: E731
        return TrainingBatch(move(self.context_images), self.context_cameras.to(device), move(self.target_images),
                             self.target_cameras.to(device), self.keys, move(self.context_depth))

    def pin_memory(self) -> "TrainingBatch":
        """Images and depth in page-locked memory (the DataLoader calls this with ``pin_memory=True``)."""
        return TrainingBatch(self.context_images.pin_memory(), self.context_cameras, self.target_images.pin_memory(),
                             self.target_cameras, self.keys, self.context_depth.pin_memory())


BatchSource = Callable[[int], TrainingBatch]
SceneSampler = Callable[[torch.Generator, BatchShape], TrainingSample]
"""``sampler(generator, shape) -> TrainingSample``: one scene of ``shape``, all randomness from ``generator``."""


def _generator(seed: int, index: int, scene: int) -> torch.Generator:
    return torch.Generator().manual_seed(((seed * 1_000_003 + index) * 1009 + scene + 1) % (2**63))


def _uniform(generator: torch.Generator, low: float, high: float) -> float:
    return low + (high - low) * float(torch.rand((), generator=generator, dtype=torch.float64))


# --------------------------------------------------------------------------------------------------
# Augmentation
def photometric_jitter(images: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """float [N,3,H,W] in [0,1] -> the same exposure change applied to every image (ranges :data:`PHOTOMETRIC`):
    gamma, then brightness, contrast about the mean grey, saturation about the per-pixel grey; clipped."""
    factor = {name: _uniform(generator, *bounds) for name, bounds in PHOTOMETRIC.items()}
    out = images.clamp(0.0, 1.0) ** factor["gamma"] * factor["brightness"]
    grey = out.mean(dim=1, keepdim=True)
    out = (out - grey.mean()) * factor["contrast"] + grey.mean()
    grey = out.mean(dim=1, keepdim=True)
    return ((out - grey) * factor["saturation"] + grey).clamp(0.0, 1.0)


def random_mirror(images: torch.Tensor, cameras: Cameras, depth: torch.Tensor, generator: torch.Generator
                  ) -> tuple[torch.Tensor, Cameras, torch.Tensor]:
    """float [N,3,H,W] views of one scene, their cameras and depth [N,H,W] -> the same, or with probability 1/2
    all of them mirrored left-right (images and depth flipped, :meth:`Cameras.mirrored`)."""
    if _uniform(generator, 0.0, 1.0) < 0.5:
        return images, cameras, depth
    return images.flip(-1), cameras.mirrored(), depth.flip(-1)


@dataclass(frozen=True)
class Augmentation:
    """Per-scene augmentation of a sample's views (all views of a scene alike).

    Attributes:
        photometric: :func:`photometric_jitter`.
        mirror: :func:`random_mirror`.
    """

    photometric: bool = False
    mirror: bool = False

    def __call__(self, images: torch.Tensor, cameras: Cameras, depth: torch.Tensor, generator: torch.Generator
                 ) -> tuple[torch.Tensor, Cameras, torch.Tensor]:
        """float [N,3,H,W] in [0,1], their cameras and depth [N,H,W] -> augmented ones (random numbers drawn only
        for the augmentations that are on, so turning one off leaves the others' draws as they were)."""
        if self.photometric:
            images = photometric_jitter(images, generator)
        if self.mirror:
            images, cameras, depth = random_mirror(images, cameras, depth, generator)
        return images, cameras, depth


def random_resized_crop(images: torch.Tensor, cameras: Cameras, depth: torch.Tensor, height: int, width: int,
                        generator: torch.Generator) -> tuple[torch.Tensor, Cameras, torch.Tensor]:
    """uint8 [N,3,h,w] at the cameras' size and depth [N,h',w'] of the same views (any size covering the same
    image extent; 0 = unknown) -> float32 [N,3,height,width] in [0,1], cameras and float32 depth
    [N,height,width]: resized (images bilinear and antialiased, depth nearest, so that unknown pixels stay
    unknown) to cover the size times a zoom in [1, :data:`MAX_ZOOM`], cropped at a random position."""
    in_h, in_w = images.shape[-2:]
    scale = max(height / in_h, width / in_w) * _uniform(generator, 1.0, MAX_ZOOM)
    scaled_h, scaled_w = max(height, round(in_h * scale)), max(width, round(in_w * scale))
    top = int(torch.randint(scaled_h - height + 1, (), generator=generator))
    left = int(torch.randint(scaled_w - width + 1, (), generator=generator))
    resized = F.interpolate(images.float() / 255.0, size=(scaled_h, scaled_w), mode="bilinear", antialias=True,
                            align_corners=False)
    crop = resized[:, :, top:top + height, left:left + width].clamp(0.0, 1.0).contiguous()
    depth = F.interpolate(depth.float()[:, None], size=(scaled_h, scaled_w), mode="nearest-exact")[:, 0]
    return (crop, cameras.rescaled(scaled_w, scaled_h).cropped(left, top, width, height),
            depth[:, top:top + height, left:left + width].contiguous())


def cropped_sample(images: torch.Tensor, cameras: Cameras, depth: torch.Tensor, context: int, shape: BatchShape,
                   generator: torch.Generator, augmentation: Augmentation, key: str) -> TrainingSample:
    """uint8 [N,3,h,w] views (the first ``context`` of them context, the rest targets), their cameras and
    depth [N,h',w'] (0 = unknown) -> a :class:`TrainingSample` at the batch's size: :func:`random_resized_crop`,
    then ``augmentation``; float32 cameras."""
    pixels, cams, depth = random_resized_crop(images, cameras, depth, shape.height, shape.width, generator)
    pixels, cams, depth = augmentation(pixels, cams, depth, generator)
    cams = cams.to(dtype=torch.float32)
    return TrainingSample(pixels[:context], cams.select(slice(0, context)), pixels[context:],
                          cams.select(slice(context, None)), key, depth[:context])


# --------------------------------------------------------------------------------------------------
# Scene samplers
DEPTH_FOLDER = "mvs"
"""A real scene's reference depth, if any: ``<scene>/mvs/depth.json`` as ``codecsplat depth SCENE -o SCENE/mvs``
writes it (multi-view stereo depth of every view, 0 where no consistent depth was found)."""


def reference_depth(scene_folder: pathlib.Path, frame_names: list[str], height: int, width: int) -> torch.Tensor:
    """float32 [N,h,w] depth of a scene's frames (camera z, scene units; 0 = unknown) from its
    :data:`DEPTH_FOLDER`, at the depth maps' own size (they cover the photographs' extent, and
    :func:`random_resized_crop` samples them once, to the crop); all zero at the image size (``height`` x
    ``width``) when the scene has none.

    Raises:
        DataError: the depth folder exists but is unreadable, or lacks a depth map of one of the frames.
    """
    folder = scene_folder / DEPTH_FOLDER
    if not (folder / INDEX_FILE).is_file():
        return torch.zeros(len(frame_names), height, width)
    maps = read_depth_maps(folder)
    return maps.depth[[maps.frame_index(name) for name in frame_names]]


class RealScenes:
    """Real scenes under ``root`` (folders with ``cameras.json``), decoded once at their stored size (uint8),
    with the reference depth of :func:`reference_depth` (zero where a scene has none).

    Instances are picklable before first use, so DataLoader workers each build their own cache.
    """

    def __init__(self, root, names: list[str], augmentation: Augmentation):
        if not names:
            raise DataError(f"no scenes (*/cameras.json) under {root}")
        self.root = pathlib.Path(root)
        self.names = list(names)
        self.augmentation = augmentation
        self.view_counts = {name: _frame_count(self.root / name / "cameras.json") for name in self.names}
        self._cache: dict[str, tuple[torch.Tensor, Cameras, torch.Tensor]] = {}

    def scene(self, name: str) -> tuple[torch.Tensor, Cameras, torch.Tensor]:
        """uint8 [N,3,h,w] images and float64 cameras (scene's own near/far) of a scene at its stored size, and its
        float32 reference depth (:func:`reference_depth`; 0 = unknown)."""
        if name not in self._cache:
            from codecsplat_warp.data.scene_json import load_scene_json

            loaded = load_scene_json(self.root / name / "cameras.json")
            depth = reference_depth(self.root / name, loaded.frame_names, loaded.cameras.height, loaded.cameras.width)
            self._cache[name] = (loaded.decoded_images(), loaded.cameras, depth)
        return self._cache[name]

    def eligible(self, views: int) -> list[str]:
        """The scenes with at least ``views`` views; DataError when none has that many."""
        names = [name for name in self.names if self.view_counts[name] >= views]
        if not names:
            raise DataError(f"no scene under {self.root} has {views} views (most: {max(self.view_counts.values())})")
        return names

    def __call__(self, generator: torch.Generator, shape: BatchShape) -> TrainingSample:
        """One sample of a scene drawn among those with enough views for ``shape`` (context + targets)."""
        names = self.eligible(shape.views + shape.targets)
        name = names[int(torch.randint(len(names), (), generator=generator))]
        images, cameras, depth = self.scene(name)
        anchor = int(torch.randint(cameras.num_views, (), generator=generator))
        spread = int(torch.randint(shape.views + shape.targets + 1, (), generator=generator))
        context, targets = split_context_targets(cameras, anchor, shape.views, shape.targets, spread)
        views = context + targets
        return cropped_sample(images[views], cameras.select(views), depth[views], len(context), shape, generator,
                              self.augmentation, name)

    def photo_crops(self, generator: torch.Generator, count: int) -> list[torch.Tensor]:
        """``count`` random square crops (uint8 [3,s,s], s between 1/4 and all of the shorter side) of random
        training photographs."""
        crops = []
        for _ in range(count):
            images = self.scene(self.names[int(torch.randint(len(self.names), (), generator=generator))])[0]
            crops.append(random_square_crop(images[int(torch.randint(images.shape[0], (), generator=generator))],
                                            generator))
        return crops


def _frame_count(file: pathlib.Path) -> int:
    """Frames listed in a ``cameras.json`` (read without decoding any image); DataError if unreadable."""
    from codecsplat_warp.data.scene_json import read_json

    frames = read_json(file).get("frames")
    if not isinstance(frames, list):
        raise DataError(f"{file}: no frame list")
    return len(frames)


def random_square_crop(image: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """uint8 [3,h,w] -> uint8 [3,s,s] at a random position, s between 1/4 and all of the shorter side (>= 8)."""
    side = max(8, round(min(image.shape[-2:]) * _uniform(generator, 0.25, 1.0)))
    top = int(torch.randint(image.shape[-2] - side + 1, (), generator=generator))
    left = int(torch.randint(image.shape[-1] - side + 1, (), generator=generator))
    return image[:, top:top + side, left:left + side]


class ChunkScenes:
    """Scenes of a chunk folder (``.torch`` chunks and ``index.json``, :mod:`codecsplat_warp.data.chunks`), streamed.

    Only ``index.json`` is read up front; a draw reads the chunk holding its scene (the last :data:`CHUNK_CACHE`
    chunks stay in memory, images JPEG-encoded) and decodes only the frames it uses. Views come from the
    bounded sampler ``view_sampler`` at the batch's step (pixelSplat / DepthSplat training); a scene with
    too few frames for the step's smallest context gap is skipped for another draw, as pixelSplat does.
    Images are resized and cropped as real scenes are (:func:`random_resized_crop`). Cameras get the depth
    range ``near`` / ``far`` in scene units (chunks store none; the default is DepthSplat's RE10K one).
    Instances are picklable, so DataLoader workers each keep their own cache.
    """

    def __init__(self, root, keys: list[str], view_sampler: BoundedSamplerConfig, augmentation: Augmentation,
                 near: float = 0.5, far: float = 100.0):
        index = load_index(root)
        if not keys:
            raise DataError(f"no training scenes in {pathlib.Path(root) / 'index.json'}")
        self.root = pathlib.Path(root)
        self.chunk_of = {key: index[key] for key in keys}
        self.keys = list(keys)
        self.view_sampler = view_sampler
        self.augmentation = augmentation
        self.near, self.far = near, far
        self._cache: OrderedDict[pathlib.Path, dict[str, Scene]] = OrderedDict()

    def scene(self, key: str) -> Scene:
        """The scene ``key`` (images JPEG-encoded, float64 cameras), reading its chunk unless it is cached."""
        path = self.chunk_of[key]
        if path not in self._cache:
            self._cache[path] = {s.key: s for s in read_chunk(path, self.near, self.far)}
            while len(self._cache) > CHUNK_CACHE:
                self._cache.popitem(last=False)
        self._cache.move_to_end(path)
        scenes = self._cache[path]
        if key not in scenes:
            raise DataError(f"{path}: {self.root / 'index.json'} says it holds scene {key!r}, but it does not")
        return scenes[key]

    def _draw_key(self, generator: torch.Generator) -> str:
        return self.keys[int(torch.randint(len(self.keys), (), generator=generator))]

    def __call__(self, generator: torch.Generator, shape: BatchShape) -> TrainingSample:
        sampler = dataclasses.replace(self.view_sampler, num_context_views=shape.views, num_target_views=shape.targets)
        for _ in range(MAX_SCENE_DRAWS):
            key = self._draw_key(generator)
            scene = self.scene(key)
            try:
                views = sample_bounded_views(scene.num_views, sampler, shape.step, generator)
            except DataError:
                continue
            frames = list(views.context + views.target)
            unknown_depth = torch.zeros(len(frames), scene.cameras.height, scene.cameras.width)
            return cropped_sample(scene.decoded_images(frames), scene.cameras.select(frames), unknown_depth,
                                  len(views.context), shape, generator, self.augmentation, key)
        raise DataError(f"{self.root}: {MAX_SCENE_DRAWS} scenes drawn in a row are too short for {shape.views} "
                        f"context views at step {shape.step}'s context gap {context_gap_bounds(sampler, shape.step)}")

    def photo_crops(self, generator: torch.Generator, count: int) -> list[torch.Tensor]:
        """``count`` random square crops (uint8 [3,s,s], see :func:`random_square_crop`) of random frames."""
        crops = []
        for _ in range(count):
            scene = self.scene(self._draw_key(generator))
            frame = int(torch.randint(scene.num_views, (), generator=generator))
            crops.append(random_square_crop(scene.decoded_images([frame])[0], generator))
        return crops


class ProceduralScenes:
    """Procedural scenes (:func:`codecsplat_warp.data.procedural.procedural_scene`), one fresh scene per draw.

    Views along the scene's trajectory: context at evenly spaced positions (first and last included),
    targets in between. ``textures`` (:class:`RealScenes` or :class:`ChunkScenes`) adds crops of its
    photographs as textures.
    """

    def __init__(self, textures: RealScenes | ChunkScenes | None = None, augmentation: Augmentation = Augmentation()):
        self.textures = textures
        self.augmentation = augmentation

    def __call__(self, generator: torch.Generator, shape: BatchShape) -> TrainingSample:
        from codecsplat_warp.data.procedural import ProceduralConfig, procedural_scene

        config = ProceduralConfig(width=shape.width, height=shape.height, num_views=shape.views + shape.targets)
        photos = self.textures.photo_crops(generator, PHOTO_TEXTURES_PER_SCENE) if self.textures else None
        scene = procedural_scene(int(torch.randint(2**62, (), generator=generator)), config, photo_textures=photos)
        context, targets = split_context_targets(scene.cameras, 0, shape.views, shape.targets)
        pixels, cams, depth = self.augmentation(scene.images.float() / 255.0, scene.cameras, scene.depth, generator)
        cams = cams.to(dtype=torch.float32)
        return TrainingSample(pixels[context], cams.select(context), pixels[targets], cams.select(targets), scene.key,
                              depth[context])


def batch_source(spec: DataSpec, seed: int, real: SceneSampler | None, procedural: SceneSampler | None) -> BatchSource:
    """Batches of ``spec``'s shapes; each scene is procedural with probability ``spec.procedural_fraction``
    when both samplers are given, else from the one given."""
    if real is None and procedural is None:
        raise InputError("a batch source needs real or procedural scenes")

    def source(index: int) -> TrainingBatch:
        shape = batch_shape(spec, seed, index)
        samples = []
        for scene in range(shape.scenes):
            generator = _generator(seed, index, scene)
            use_procedural = real is None or (procedural is not None and
                                              _uniform(generator, 0.0, 1.0) < spec.procedural_fraction)
            samples.append((procedural if use_procedural else real)(generator, shape))
        return TrainingBatch.stack(samples)

    return source


MIX_PREFIX = "mix:"
"""``--data mix:DIR`` / ``mix:chunks:DIR``: procedural scenes (share ``DataSpec.procedural_fraction``) and the
real or chunk scenes of DIR."""

CHUNKS_PREFIX = "chunks:"
"""``--data chunks:DIR``: the scenes of a chunk folder (``.torch`` chunks and ``index.json``)."""


def make_source(data: str, spec: DataSpec, seed: int, holdout: list[str] | None = None) -> BatchSource:
    """``procedural``, a directory of real scenes, ``chunks:DIR`` (a chunk folder) or ``mix:`` before either
    of the last two (with procedural scenes) -> a :data:`BatchSource`.

    ``holdout`` names real scenes (or chunk scene keys) left out of training (kept for validation); their
    photographs are never used as procedural textures either.

    Raises:
        InputError: ``data`` is none of these forms, or a held-out name is not in the data.
        DataError: a chunk folder that does not exist or lacks a valid ``index.json``, or no scenes left.
    """
    if data == "procedural":
        return batch_source(spec, seed, None, ProceduralScenes(augmentation=spec.augmentation))
    mixed = data.startswith(MIX_PREFIX)
    body = data[len(MIX_PREFIX):] if mixed else data
    if body.startswith(CHUNKS_PREFIX):
        root = pathlib.Path(body[len(CHUNKS_PREFIX):])
        if not root.is_dir():
            raise DataError(f"chunk folder {root} (from --data {data!r}) does not exist")
        keys = without_holdout(root, sorted(load_index(root)), holdout or [])
        real = ChunkScenes(root, keys, spec.view_sampler, spec.augmentation)
    else:
        if not pathlib.Path(body).is_dir():
            raise InputError("data must be 'procedural', a directory of scenes, 'chunks:DIRECTORY' or either "
                             f"of the last two after 'mix:', got {data!r}")
        real = RealScenes(body, training_scenes(body, holdout or []), spec.augmentation)
    if not mixed:
        return batch_source(spec, seed, real, None)
    procedural = ProceduralScenes(real if spec.photo_textures else None, spec.augmentation)
    return batch_source(spec, seed, real, procedural)


def training_scenes(root, holdout: list[str]) -> list[str]:
    """Scene folders (with ``cameras.json``) under ``root`` minus ``holdout``; every held-out name must exist."""
    return without_holdout(root, sorted(p.parent.name for p in pathlib.Path(root).glob("*/cameras.json")), holdout)


def without_holdout(root, names: list[str], holdout: list[str]) -> list[str]:
    """``names`` (the scenes of ``root``) minus ``holdout``; InputError for a held-out name not among them,
    DataError when none is left."""
    missing = sorted(set(holdout) - set(names))
    if missing:
        raise InputError(f"held-out scenes not found under {root}: {', '.join(missing)}")
    kept = [n for n in names if n not in set(holdout)]
    if not kept:
        raise DataError(f"no training scenes left under {root} after holding out {len(holdout)}")
    return kept


class StepDataset(torch.utils.data.Dataset):
    """Map-style view of a batch source for a DataLoader (workers build batches in parallel)."""

    def __init__(self, source: BatchSource, length: int):
        self.source = source
        self.length = length

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, index: int) -> TrainingBatch:
        return self.source(int(index))

