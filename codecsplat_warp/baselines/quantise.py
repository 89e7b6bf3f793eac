"""Uniform min/max quantisation of attribute columns, shared by the baseline compressors.

Each column c of values [N,C] is mapped to integers ``round((v - min_c) / (max_c - min_c) * (2^bits - 1))``
(0 for a constant column) and back to ``min_c + q / (2^bits - 1) * (max_c - min_c)``; the worst-case error
is half a step, ``(max_c - min_c) / (2 (2^bits - 1))``.
"""

from __future__ import annotations

import numpy as np

from ..errors import BitstreamError


def quantise(values: np.ndarray, bits: int) -> tuple[np.ndarray, list[float], list[float]]:
    """Columns of float ``values`` [N,C] as uint8 (bits <= 8) or uint16 (bits <= 16) [N,C], with their mins and maxs."""
    if not 1 <= bits <= 16:
        raise ValueError(f"bits must be 1..16, got {bits}")
    values = np.asarray(values, dtype=np.float64)
    mins, maxs = values.min(axis=0), values.max(axis=0)
    span = np.where(maxs > mins, maxs - mins, 1.0)
    levels = (1 << bits) - 1
    q = np.rint((values - mins) / span * levels)
    dtype = np.uint8 if bits <= 8 else np.uint16
    return q.astype(dtype), mins.tolist(), maxs.tolist()


def dequantise(q: np.ndarray, mins: list[float], maxs: list[float], bits: int) -> np.ndarray:
    """float32 [N,C] values of quantised columns ``q`` [N,C] (inverse of :func:`quantise`).

    Raises:
        BitstreamError: ``bits`` is not in 1..16 (0 would divide by zero levels), or ``mins`` / ``maxs`` do not have
            one finite entry per column.
    """
    if not 1 <= bits <= 16:
        raise BitstreamError(f"quantisation to {bits} bits: a stream holds 1 to 16 bits a value")
    mins, maxs = np.asarray(mins, dtype=np.float64), np.asarray(maxs, dtype=np.float64)
    if mins.shape != (q.shape[1],) or maxs.shape != (q.shape[1],) or not np.isfinite(mins).all() \
            or not np.isfinite(maxs).all():
        raise BitstreamError(f"quantisation ranges do not match {q.shape[1]} columns")
    levels = (1 << bits) - 1
    return (mins + q.astype(np.float64) / levels * (maxs - mins)).astype(np.float32)
