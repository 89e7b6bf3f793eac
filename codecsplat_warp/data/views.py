"""Which views of a scene are context and which are targets.

* Testing: evaluation index files ``{"<key>": {"context": [i, j], "target": [...]}, "<key>": null}``
  (pixelSplat / MVSplat / DepthSplat ``assets/evaluation_index_*.json``); null entries are skipped.
* Training: pixelSplat's bounded sampler: pick a gap between the outer context views within bounds that
  widen linearly over ``warm_up_steps``, place the left view at random, put extra context views between
  the outer ones and draw targets between them.
"""

from __future__ import annotations

import json
import pathlib
from dataclasses import dataclass

import torch

from ..cameras import Cameras
from ..errors import DataError
from .scene import require_file


@dataclass(frozen=True)
class ViewSelection:
    """Context and target view indices into one scene."""

    context: tuple[int, ...]
    target: tuple[int, ...]


def load_evaluation_index(file) -> dict[str, ViewSelection]:
    """Parse an evaluation index file; scenes whose entry is null are left out.

    Raises:
        DataError: bad JSON, or an entry without integer ``context`` / ``target`` lists (naming the key).
    """
    file = pathlib.Path(file)
    require_file(file)
    try:
        entries = json.loads(file.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataError(f"{file}: not valid JSON: {exc}") from None
    if not isinstance(entries, dict):
        raise DataError(f"{file}: expected an object mapping scene keys to view selections")
    selections = {}
    for key, entry in entries.items():
        if entry is None:
            continue
        if not isinstance(entry, dict) or not all(_is_index_list(entry.get(k)) for k in ("context", "target")):
            raise DataError(f"{file}: scene {key!r}: expected {{'context': [int, ...], 'target': [int, ...]}}, got {entry!r}")
        selections[key] = ViewSelection(tuple(entry["context"]), tuple(entry["target"]))
    return selections


def _is_index_list(value) -> bool:
    return isinstance(value, list) and len(value) > 0 and all(isinstance(v, int) and v >= 0 for v in value)


@dataclass(frozen=True)
class BoundedSamplerConfig:
    """pixelSplat's ``bounded`` view sampler; defaults are DepthSplat's RE10K settings (frame units)."""

    num_context_views: int = 2
    num_target_views: int = 4
    min_distance_between_context_views: int = 45
    max_distance_between_context_views: int = 192
    min_distance_to_context_views: int = 0
    warm_up_steps: int = 150_000
    initial_min_distance_between_context_views: int = 25
    initial_max_distance_between_context_views: int = 45
    cameras_are_circular: bool = False

    def __post_init__(self) -> None:
        if self.num_context_views < 2 or self.num_target_views < 1:
            raise DataError(f"need >= 2 context and >= 1 target views, got {self.num_context_views}, {self.num_target_views}")
        if self.min_distance_between_context_views > self.max_distance_between_context_views:
            raise DataError("min_distance_between_context_views exceeds max_distance_between_context_views")


def context_gap_bounds(config: BoundedSamplerConfig, step: int) -> tuple[int, int]:
    """(min_gap, max_gap) between the outer context views at training ``step`` (before clamping to the scene)."""
    def schedule(initial: int, final: int) -> int:
        if config.warm_up_steps <= 0:
            return final
        return min(initial + int((final - initial) * step / config.warm_up_steps), final)

    return (schedule(config.initial_min_distance_between_context_views, config.min_distance_between_context_views),
            schedule(config.initial_max_distance_between_context_views, config.max_distance_between_context_views))


def sample_bounded_views(num_views: int, config: BoundedSamplerConfig, step: int,
                         generator: torch.Generator | None = None) -> ViewSelection:
    """Draw context and target views of a scene with ``num_views`` frames (pixelSplat's bounded sampler).

    Raises:
        DataError: the scene has too few frames for the smallest allowed gap.
    """
    min_gap, max_gap = context_gap_bounds(config, step)
    if not config.cameras_are_circular:
        max_gap = min(num_views - 1, max_gap)
    min_gap = max(2 * config.min_distance_to_context_views, min_gap, config.num_context_views - 1)
    if max_gap < min_gap:
        raise DataError(f"a scene with {num_views} views has no context gap in [{min_gap}, {max_gap}]")
    draw = lambda low, high, n=None: torch.randint(low, high, (n,) if n else (), generator=generator)  # noqa: E731
    gap = int(draw(min_gap, max_gap + 1))
    left = int(draw(0, num_views if config.cameras_are_circular else num_views - gap))
    right = left + gap
    margin = config.min_distance_to_context_views
    targets = draw(left + margin, right + 1 - margin, config.num_target_views)
    extra = _extra_context_views(left, right, config.num_context_views - 2, generator)
    context = [left, *extra, right]
    if config.cameras_are_circular:
        context = [c % num_views for c in context]
        targets = targets % num_views
    return ViewSelection(tuple(context), tuple(int(t) for t in targets))


def _extra_context_views(left: int, right: int, count: int, generator: torch.Generator | None) -> list[int]:
    """``count`` distinct sorted views strictly between ``left`` and ``right``."""
    if count == 0:
        return []
    order = torch.randperm(right - left - 1, generator=generator)[:count]
    return sorted(int(v) + left + 1 for v in order)


def split_context_targets(cameras: Cameras, anchor: int, num_context: int, num_target: int) -> tuple[list[int], list[int]]:
    """Context and target view indices among the ``num_context + num_target`` views nearest to ``anchor``.

    The views are ordered by camera-centre distance to the anchor; the context takes evenly spaced ranks
    including the nearest (the anchor) and the farthest, the targets the ranks in between, so targets
    lie among the context views rather than outside them.
    """
    total = num_context + num_target
    if cameras.num_views < total:
        raise DataError(f"scene has {cameras.num_views} views, need {total} ({num_context} context + {num_target} target)")
    centers = cameras.centers.double()
    order = torch.argsort((centers - centers[anchor]).norm(dim=-1), stable=True)[:total].tolist()
    ranks = torch.linspace(0, total - 1, num_context).round().long().tolist()
    context = [order[r] for r in ranks]
    targets = [order[r] for r in range(total) if r not in ranks]
    return context, targets
