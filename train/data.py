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
* with ``DataSpec.photometric`` every scene gets one random brightness, contrast, saturation and gamma
  change for all of its views (a camera's exposure, the same in context and targets).
"""

from __future__ import annotations

import pathlib
from dataclasses import dataclass
from typing import Callable

import torch
from torch.nn import functional as F

from codecsplat_warp.cameras import Cameras
from codecsplat_warp.data.views import split_context_targets
from codecsplat_warp.errors import DataError, InputError
from codecsplat_warp.nn.config import MODEL_STRIDE, ModelConfig

MAX_ZOOM = 1.15
"""Real scenes are resized to cover the batch size times a zoom drawn from [1, MAX_ZOOM], then cropped at random."""

PHOTOMETRIC = {"brightness": (0.8, 1.2), "contrast": (0.8, 1.2), "saturation": (0.7, 1.3), "gamma": (0.8, 1.25)}
"""Ranges of the per-scene photometric augmentation factors (each drawn uniformly; 1 is no change)."""

PHOTO_TEXTURES_PER_SCENE = 6
"""Photograph crops a procedural scene gets as extra textures (next to its 8 synthetic ones)."""


@dataclass(frozen=True)
class BatchShape:
    """What one training batch holds: ``scenes`` scenes of ``views`` context and ``targets`` target views,
    every image ``height`` x ``width`` pixels."""

    views: int
    targets: int
    height: int
    width: int
    scenes: int


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
    """

    views: tuple[int, ...]
    sizes: tuple[tuple[int, int], ...]
    targets: int = 4
    batch_views: int = 2
    procedural_fraction: float = 0.5
    photo_textures: bool = False
    photometric: bool = False

    def __post_init__(self) -> None:
        if not self.views or any(v < 2 for v in self.views):
            raise InputError(f"context view counts must be >= 2, got {self.views}")
        if not self.sizes or any(h % MODEL_STRIDE or w % MODEL_STRIDE or h < 1 or w < 1 for h, w in self.sizes):
            raise InputError(f"image sizes must be positive multiples of {MODEL_STRIDE}, got {self.sizes}")
        if self.targets < 1 or self.batch_views < 1:
            raise InputError(f"targets and batch_views must be >= 1, got {self.targets}, {self.batch_views}")
        if not 0.0 <= self.procedural_fraction <= 1.0:
            raise InputError(f"procedural_fraction must be in [0, 1], got {self.procedural_fraction}")

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


def batch_shape(spec: DataSpec, seed: int, index: int) -> BatchShape:
    """The shape of batch ``index``: a function of (seed, index) only."""
    generator = _generator(seed, index, -1)
    views = spec.views[int(torch.randint(len(spec.views), (), generator=generator))]
    height, width = spec.sizes[int(torch.randint(len(spec.sizes), (), generator=generator))]
    return BatchShape(views, spec.targets, height, width, max(1, spec.batch_views // views))


@dataclass
class TrainingSample:
    """One scene's training example.

    Attributes:
        context_images: float32 [V,3,H,W] in [0,1]; context_cameras: V cameras at H x W.
        target_images: float32 [T,3,H,W] in [0,1]; target_cameras: T cameras at H x W.
        key: scene name (for logs).
    """

    context_images: torch.Tensor
    context_cameras: Cameras
    target_images: torch.Tensor
    target_cameras: Cameras
    key: str


@dataclass
class TrainingBatch:
    """S scenes of one :class:`BatchShape`, stacked scene-major.

    Attributes:
        context_images: float32 [S*V,3,H,W] in [0,1]; context_cameras: the S*V cameras.
        target_images: float32 [S*T,3,H,W] in [0,1]; target_cameras: the S*T cameras.
        keys: the S scene names.
    """

    context_images: torch.Tensor
    context_cameras: Cameras
    target_images: torch.Tensor
    target_cameras: Cameras
    keys: tuple[str, ...]

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
                   tuple(s.key for s in samples))

    def scene_targets(self) -> list[Cameras]:
        """The target cameras of each scene."""
        T = self.targets_per_scene
        return [self.target_cameras.select(slice(s * T, (s + 1) * T)) for s in range(self.scenes)]

    def to(self, device, non_blocking: bool = False) -> "TrainingBatch":
        move = lambda t: t.to(device, non_blocking=non_blocking)  # noqa: E731
        return TrainingBatch(move(self.context_images), self.context_cameras.to(device), move(self.target_images),
                             self.target_cameras.to(device), self.keys)

    def pin_memory(self) -> "TrainingBatch":
        """Images in page-locked memory (the DataLoader calls this with ``pin_memory=True``)."""
        return TrainingBatch(self.context_images.pin_memory(), self.context_cameras, self.target_images.pin_memory(),
                             self.target_cameras, self.keys)


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


def random_resized_crop(images: torch.Tensor, cameras: Cameras, height: int, width: int,
                        generator: torch.Generator) -> tuple[torch.Tensor, Cameras]:
    """uint8 [N,3,h,w] at the cameras' size -> float32 [N,3,height,width] in [0,1]: resized (bilinear,
    antialiased) to cover the size times a zoom in [1, :data:`MAX_ZOOM`], cropped at a random position."""
    in_h, in_w = images.shape[-2:]
    scale = max(height / in_h, width / in_w) * _uniform(generator, 1.0, MAX_ZOOM)
    scaled_h, scaled_w = max(height, round(in_h * scale)), max(width, round(in_w * scale))
    top = int(torch.randint(scaled_h - height + 1, (), generator=generator))
    left = int(torch.randint(scaled_w - width + 1, (), generator=generator))
    resized = F.interpolate(images.float() / 255.0, size=(scaled_h, scaled_w), mode="bilinear", antialias=True,
                            align_corners=False)
    crop = resized[:, :, top:top + height, left:left + width].clamp(0.0, 1.0).contiguous()
    return crop, cameras.rescaled(scaled_w, scaled_h).cropped(left, top, width, height)


# --------------------------------------------------------------------------------------------------
# Scene samplers
class RealScenes:
    """Real scenes under ``root`` (folders with ``cameras.json``), decoded once at their stored size (uint8).

    Instances are picklable before first use, so DataLoader workers each build their own cache.
    """

    def __init__(self, root, names: list[str], photometric: bool):
        if not names:
            raise DataError(f"no scenes (*/cameras.json) under {root}")
        self.root = pathlib.Path(root)
        self.names = list(names)
        self.photometric = photometric
        self._cache: dict[str, tuple[torch.Tensor, Cameras]] = {}

    def scene(self, name: str) -> tuple[torch.Tensor, Cameras]:
        """uint8 [N,3,h,w] images and float64 cameras of a scene at its stored size (scene's own near/far)."""
        if name not in self._cache:
            from codecsplat_warp.data.scene_json import load_scene_json

            loaded = load_scene_json(self.root / name / "cameras.json")
            self._cache[name] = (loaded.decoded_images(), loaded.cameras)
        return self._cache[name]

    def __call__(self, generator: torch.Generator, shape: BatchShape) -> TrainingSample:
        name = self.names[int(torch.randint(len(self.names), (), generator=generator))]
        images, cameras = self.scene(name)
        anchor = int(torch.randint(cameras.num_views, (), generator=generator))
        spread = int(torch.randint(shape.views + shape.targets + 1, (), generator=generator))
        context, targets = split_context_targets(cameras, anchor, shape.views, shape.targets, spread)
        views = context + targets
        pixels, cams = random_resized_crop(images[views], cameras.select(views), shape.height, shape.width, generator)
        if self.photometric:
            pixels = photometric_jitter(pixels, generator)
        cams = cams.to(dtype=torch.float32)
        V = len(context)
        return TrainingSample(pixels[:V], cams.select(slice(0, V)), pixels[V:], cams.select(slice(V, None)), name)

    def photo_crops(self, generator: torch.Generator, count: int) -> list[torch.Tensor]:
        """``count`` random square crops (uint8 [3,s,s], s between 1/4 and all of the shorter side) of random
        training photographs."""
        crops = []
        for _ in range(count):
            images, _ = self.scene(self.names[int(torch.randint(len(self.names), (), generator=generator))])
            image = images[int(torch.randint(images.shape[0], (), generator=generator))]
            side = max(8, round(min(image.shape[-2:]) * _uniform(generator, 0.25, 1.0)))
            top = int(torch.randint(image.shape[-2] - side + 1, (), generator=generator))
            left = int(torch.randint(image.shape[-1] - side + 1, (), generator=generator))
            crops.append(image[:, top:top + side, left:left + side])
        return crops


class ProceduralScenes:
    """Procedural scenes (:func:`codecsplat_warp.data.procedural.procedural_scene`), one fresh scene per draw.

    Views along the scene's trajectory: context at evenly spaced positions (first and last included),
    targets in between. ``textures`` (a :class:`RealScenes`) adds crops of its photographs as textures.
    """

    def __init__(self, textures: RealScenes | None = None, photometric: bool = False):
        self.textures = textures
        self.photometric = photometric

    def __call__(self, generator: torch.Generator, shape: BatchShape) -> TrainingSample:
        from codecsplat_warp.data.procedural import ProceduralConfig, procedural_scene

        config = ProceduralConfig(width=shape.width, height=shape.height, num_views=shape.views + shape.targets)
        photos = self.textures.photo_crops(generator, PHOTO_TEXTURES_PER_SCENE) if self.textures else None
        scene = procedural_scene(int(torch.randint(2**62, (), generator=generator)), config, photo_textures=photos)
        context, targets = split_context_targets(scene.cameras, 0, shape.views, shape.targets)
        pixels = scene.images.float() / 255.0
        if self.photometric:
            pixels = photometric_jitter(pixels, generator)
        cams = scene.cameras.to(dtype=torch.float32)
        return TrainingSample(pixels[context], cams.select(context), pixels[targets], cams.select(targets), scene.key)


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
"""``--data mix:DIR``: procedural scenes (share ``DataSpec.procedural_fraction``) and real scenes under DIR."""


def make_source(data: str, spec: DataSpec, seed: int, holdout: list[str] | None = None) -> BatchSource:
    """``procedural``, a directory of real scenes, or ``mix:DIR`` (both) -> a :data:`BatchSource`.

    ``holdout`` names real scenes left out of training (kept for validation); their photographs are never
    used as procedural textures either.
    """
    if data == "procedural":
        return batch_source(spec, seed, None, ProceduralScenes(photometric=spec.photometric))
    real_root = data[len(MIX_PREFIX):] if data.startswith(MIX_PREFIX) else data
    if not pathlib.Path(real_root).is_dir():
        raise InputError(f"data must be 'procedural', a directory of scenes or 'mix:DIRECTORY', got {data!r}")
    real = RealScenes(real_root, training_scenes(real_root, holdout or []), spec.photometric)
    if not data.startswith(MIX_PREFIX):
        return batch_source(spec, seed, real, None)
    procedural = ProceduralScenes(real if spec.photo_textures else None, spec.photometric)
    return batch_source(spec, seed, real, procedural)


def training_scenes(root, holdout: list[str]) -> list[str]:
    """Scene folders (with ``cameras.json``) under ``root`` minus ``holdout``; every held-out name must exist."""
    names = sorted(p.parent.name for p in pathlib.Path(root).glob("*/cameras.json"))
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

