"""Which views of a scene are context and which are targets.

* Testing: evaluation index files ``{"<key>": {"context": [i, j], "target": [...]}, "<key>": null}``
  (pixelSplat / MVSplat / DepthSplat ``assets/evaluation_index_*.json``); null entries are skipped.
* Training: pixelSplat's bounded sampler: pick a gap between the outer context views within bounds that
  widen linearly over ``warm_up_steps``, place the left view at random, put extra context views between
  the outer ones and draw targets between them.
"""

from __future__ import annotations

import json
import math
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


MAX_VIEW_ANGLE_DEGREES = 45.0
"""Views whose optical axis turns more than this from the anchor's are not candidates for its context or
targets (a hand-held outward capture passes close camera centres that look elsewhere)."""


def split_context_targets(cameras: Cameras, anchor: int, num_context: int, num_target: int,
                          spread: int = 0) -> tuple[list[int], list[int]]:
    """Context and target view indices around ``anchor``, with the targets between the context views.

    The candidates are the views looking within :data:`MAX_VIEW_ANGLE_DEGREES` of the anchor's direction
    (all views if fewer than ``num_context + num_target`` do), ordered by camera-centre distance to the
    anchor. A cluster of the nearest candidates is taken, ``num_context + num_target + spread`` of them to
    start with: the context is spread over it by farthest-point sampling from the anchor
    (for 2 views: the anchor and the cluster's farthest view), and the targets are the cluster's other views
    inside the context's bounding sphere (centred on the context centroid, through the farthest context view),
    those nearest the centroid first, so that the targets are interpolated, not extrapolated. When too few
    views lie inside, the cluster grows by one view at a time; a scene with no such split (e.g. targets only
    beyond the ends of a straight path) gets the last cluster's views in rank order.

    Args:
        spread: extra views in the first cluster (a wider context baseline; training draws it at random).
    Raises:
        DataError: the scene has fewer than ``num_context + num_target`` views.
    """
    total = num_context + num_target
    if cameras.num_views < total:
        raise DataError(f"scene has {cameras.num_views} views, need {total} ({num_context} context + {num_target} target)")
    centers = cameras.centers.double()
    axes = cameras.c2w[:, :3, 2].double()
    facing = (axes @ axes[anchor]).clamp(-1.0, 1.0) >= math.cos(math.radians(MAX_VIEW_ANGLE_DEGREES))
    if int(facing.sum()) < total:
        facing = torch.ones_like(facing)
    distance = (centers - centers[anchor]).norm(dim=-1).masked_fill(~facing, float("inf"))
    order = torch.argsort(distance, stable=True)[:int(facing.sum())].tolist()
    for size in range(min(total + max(spread, 0), len(order)), len(order) + 1):
        context, targets = _interpolating_split(centers, order[:size], num_context, num_target)
        if len(targets) == num_target:
            return context, targets
    ranks = torch.linspace(0, total - 1, num_context).round().long().tolist()
    return [order[r] for r in ranks], [order[r] for r in range(total) if r not in ranks]


def _interpolating_split(centers: torch.Tensor, cluster: list[int], num_context: int,
                         num_target: int) -> tuple[list[int], list[int]]:
    """Farthest-point context from ``cluster[0]`` and up to ``num_target`` targets inside its bounding sphere."""
    context = [cluster[0]]
    points = centers[cluster]
    nearest = (points - points[0]).norm(dim=-1)
    for _ in range(num_context - 1):
        nearest[[cluster.index(c) for c in context]] = -1.0
        pick = int(nearest.argmax())
        context.append(cluster[pick])
        nearest = torch.minimum(nearest, (points - points[pick]).norm(dim=-1))
    centroid = centers[context].mean(dim=0)
    radius = float((centers[context] - centroid).norm(dim=-1).max())
    inside = [(float((centers[v] - centroid).norm()), v) for v in cluster if v not in context]
    targets = [v for d, v in sorted(inside) if d <= radius * (1.0 + 1e-9)]
    return context, targets[:num_target]
