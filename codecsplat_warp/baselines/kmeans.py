"""Lloyd's k-means in torch (CPU or CUDA), with distances computed in memory-bounded chunks."""

from __future__ import annotations

import torch

DISTANCE_CHUNK_ELEMENTS = 1 << 24
"""Largest point-to-centroid distance block held at once (64 MiB of float32)."""


def nearest_centroid(points: torch.Tensor, centroids: torch.Tensor) -> torch.Tensor:
    """int64 [N] index of the nearest (Euclidean) of centroids [K,D] for every point of points [N,D]."""
    rows = max(1, DISTANCE_CHUNK_ELEMENTS // max(1, centroids.shape[0]))
    centroid_norms = (centroids * centroids).sum(dim=1)[None]  # |x - c|^2 - |x|^2 = |c|^2 - 2 x.c
    labels = [torch.addmm(centroid_norms, chunk, centroids.T, alpha=-2.0).argmin(dim=1) for chunk in points.split(rows)]
    return torch.cat(labels)


def kmeans(points: torch.Tensor, clusters: int, iterations: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Cluster float points [N,D] into ``min(clusters, N)`` groups.

    Starts from distinct points drawn with ``seed``; each iteration assigns points to their nearest
    centroid and moves every non-empty cluster's centroid to its mean (empty clusters keep theirs).

    Returns:
        centroids float32 [K,D] and labels int64 [N] (the nearest centroid of each point).
    """
    points = points.float()
    n = points.shape[0]
    k = min(int(clusters), n)
    generator = torch.Generator().manual_seed(seed)
    centroids = points[torch.randperm(n, generator=generator)[:k].to(points.device)].clone()
    for _ in range(iterations):
        labels = nearest_centroid(points, centroids)
        sums = torch.zeros_like(centroids).index_add_(0, labels, points)
        counts = torch.bincount(labels, minlength=k)
        filled = counts > 0
        centroids[filled] = sums[filled] / counts[filled, None].to(points.dtype)
    return centroids, nearest_centroid(points, centroids)
