"""Baseline compressors for ``codecsplat eval``: the paper's (Tables 1, 2 and 4) on the codec-free model's output,
and an image codec on its input.

* :class:`PlyDeflate` (a): the Gaussians' PLY attributes, quantised, then Deflate.
* :class:`PngCompression` (b): gsplat-style PNG images of Morton-sorted attributes, k-means for higher SH.
* :class:`FeatureDeflate` (c): the intermediate feature F_c (and depth) in float16, then Deflate.
* :class:`ImageCodec`: not on the model's output but on its input, the context photographs as WebP or JPEG files
  (the receiver runs the codec-free model on the decoded photographs).

Gaussian compressors have ``encode(gaussians) -> bytes`` and ``decode(bytes, device) -> Gaussians``; the
feature compressor has ``encode(feature, depth, cameras) -> bytes`` and ``decode(bytes, device) ->
FeatureScene``; the image codec has ``encode(images) -> list[bytes]`` (one file per view) and ``decode(files,
device) -> images``. Each has a ``setting`` (its codec setting as the tables print it). Corrupt input raises
``BitstreamError``.
"""

from .feature_deflate import FeatureDeflate, FeatureScene
from .image_codec import ImageCodec
from .kmeans import kmeans
from .ply_deflate import PlyDeflate
from .png import PngCompression, morton_codes

__all__ = ["FeatureDeflate", "FeatureScene", "ImageCodec", "PlyDeflate", "PngCompression", "kmeans", "morton_codes"]
