"""Training samples for stage 1: context views, target views and their cameras, from procedural or real scenes.

A *source* is a function ``source(index) -> TrainingSample`` that is deterministic in ``index`` (a global
sample counter: step * world_size + rank), so a resumed or multi-GPU run draws exactly the samples it
would have drawn without interruption and no sampler state needs checkpointing.
"""

from __future__ import annotations

import pathlib
from dataclasses import dataclass
from typing import Callable

import torch

from codecsplat_warp.cameras import Cameras
from codecsplat_warp.data.views import split_context_targets
from codecsplat_warp.errors import DataError, InputError
from codecsplat_warp.model.config import ModelConfig


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

    def to(self, device) -> "TrainingSample":
        return TrainingSample(self.context_images.to(device), self.context_cameras.to(device),
                              self.target_images.to(device), self.target_cameras.to(device), self.key)


Source = Callable[[int], TrainingSample]


def _sample_from_scene(images: torch.Tensor, cameras: Cameras, key: str, context: list[int],
                       targets: list[int]) -> TrainingSample:
    pixels = images.float() / 255.0
    return TrainingSample(pixels[context], cameras.select(context).to(dtype=torch.float32),
                          pixels[targets], cameras.select(targets).to(dtype=torch.float32), key)


def procedural_source(config: ModelConfig, seed: int) -> Source:
    """Source of procedural scenes (:mod:`codecsplat_warp.data.procedural`), one fresh scene per index.

    Views along the scene's trajectory: context at evenly spaced positions (first and last included),
    targets in between.
    """
    from codecsplat_warp.data.procedural import ProceduralConfig, procedural_scene

    total = config.num_views + config.num_target_views
    proc = ProceduralConfig(width=config.width, height=config.height, num_views=total)

    def source(index: int) -> TrainingSample:
        scene = procedural_scene(seed * 1_000_003 + index, proc)
        context, targets = split_context_targets(scene.cameras, 0, config.num_views, config.num_target_views)
        return _sample_from_scene(scene.images, scene.cameras, scene.key, context, targets)

    return source


def real_scene_source(config: ModelConfig, root, seed: int, scene_names: list[str] | None = None) -> Source:
    """Source of real scenes under ``root`` (folders with ``cameras.json``; see the data README).

    Each scene is decoded, resized and centre-cropped to the preset size once and kept in memory (uint8).
    Index i picks a scene and an anchor view from a generator seeded by (seed, i); context and targets are
    the anchor's nearest views (:func:`split_context_targets`). The scenes keep their own near/far.
    """
    from codecsplat_warp.data.preprocess import DatasetConfig, preprocess_scene
    from codecsplat_warp.data.scene_json import load_scene_json

    root = pathlib.Path(root)
    names = scene_names if scene_names is not None else sorted(p.parent.name for p in root.glob("*/cameras.json"))
    if not names:
        raise DataError(f"no scenes (*/cameras.json) under {root}")
    protocol = DatasetConfig(width=config.width, height=config.height, near=0.0, far=0.0)
    cache: dict[str, tuple[torch.Tensor, Cameras]] = {}

    def scene(name: str) -> tuple[torch.Tensor, Cameras]:
        if name not in cache:
            loaded = preprocess_scene(load_scene_json(root / name / "cameras.json"), protocol,
                                      use_config_depth_range=False)
            cache[name] = (loaded.images, loaded.cameras)
        return cache[name]

    def source(index: int) -> TrainingSample:
        generator = torch.Generator().manual_seed(seed * 1_000_003 + index)
        name = names[int(torch.randint(len(names), (), generator=generator))]
        images, cameras = scene(name)
        anchor = int(torch.randint(cameras.num_views, (), generator=generator))
        context, targets = split_context_targets(cameras, anchor, config.num_views, config.num_target_views)
        return _sample_from_scene(images, cameras, name, context, targets)

    return source


MIX_PREFIX = "mix:"
"""``--data mix:DIR``: even sample indices are procedural scenes, odd ones real scenes under DIR."""


def make_source(data: str, config: ModelConfig, seed: int, holdout: list[str] | None = None) -> Source:
    """``procedural``, a directory of real scenes, or ``mix:DIR`` (both, alternating) -> a :data:`Source`.

    ``holdout`` names real scenes left out of training (kept for validation).
    """
    if data == "procedural":
        return procedural_source(config, seed)
    real_root = data[len(MIX_PREFIX):] if data.startswith(MIX_PREFIX) else data
    if not pathlib.Path(real_root).is_dir():
        raise InputError(f"data must be 'procedural', a directory of scenes or 'mix:DIRECTORY', got {data!r}")
    real = real_scene_source(config, real_root, seed, training_scenes(real_root, holdout or []))
    if not data.startswith(MIX_PREFIX):
        return real
    procedural = procedural_source(config, seed)
    return lambda index: procedural(index // 2) if index % 2 == 0 else real(index // 2)


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
    """Map-style view of a source for a DataLoader (workers build samples in parallel)."""

    def __init__(self, source: Source, length: int):
        self.source = source
        self.length = length

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, index: int) -> TrainingSample:
        return self.source(int(index))
