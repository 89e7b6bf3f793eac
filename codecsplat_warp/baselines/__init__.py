"""Baseline compressors for the paper's Tables 1, 2 and 4, run on the codec-free model's output.

* :class:`PlyDeflate` (a): the Gaussians' PLY attributes, quantised, then Deflate.
* :class:`PngCompression` (b): gsplat-style PNG images of Morton-sorted attributes, k-means for higher SH.
* :class:`FeatureDeflate` (c): the intermediate feature F_c (and depth) in float16, then Deflate.

Gaussian compressors have ``encode(gaussians) -> bytes`` and ``decode(bytes, device) -> Gaussians``; the
feature compressor has ``encode(feature, depth, cameras) -> bytes`` and ``decode(bytes, device) ->
FeatureScene``. Each has a ``setting`` (its codec setting as the tables print it). Corrupt input raises
``BitstreamError``.
"""

from .feature_deflate import FeatureDeflate, FeatureScene
from .kmeans import kmeans
from .ply_deflate import PlyDeflate
from .png import PngCompression, morton_codes

__all__ = ["FeatureDeflate", "FeatureScene", "PlyDeflate", "PngCompression", "kmeans", "morton_codes"]
