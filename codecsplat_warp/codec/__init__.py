"""The learned scene codec (paper §3.3-3.4): latent VAE, entropy coding, bitstream, decoded scenes.

* :mod:`.latent`: the lambda-conditioned hierarchical VAE on the feature F_c (:class:`LatentCodec`).
* :mod:`.entropy`: the quantised discrete Gaussian model and the range coder (``constriction``).
* :mod:`.bitstream`: header, camera stream, per-view feature streams (:func:`pack_bitstream`,
  :func:`parse_bitstream`, :func:`bytes_report`).
* :mod:`.scene`: :class:`EncodedScene` and :class:`DecodedScene`, what :meth:`CodecSplat.encode_scene` and
  :meth:`CodecSplat.decode_scene` return.

The encoder and decoder entry points are methods of :class:`codecsplat_warp.model.CodecSplat`.
"""

from .bitstream import (
    FORMAT_VERSION, MAX_PIXELS, MAX_SIDE, MAX_VIEWS, Bitstream, Header, bytes_report, pack_bitstream,
    parse_bitstream,
)
from .entropy import entropy_model_digest
from .latent import LAMBDA_MAX, LAMBDA_MIN, CodecOutput, CompressedLatents, LatentCodec, check_lambda
from .scene import DecodedScene, EncodedScene

__all__ = [
    "FORMAT_VERSION", "MAX_PIXELS", "MAX_SIDE", "MAX_VIEWS", "Bitstream", "Header", "bytes_report", "pack_bitstream",
    "parse_bitstream", "entropy_model_digest", "LAMBDA_MAX", "LAMBDA_MIN", "CodecOutput", "CompressedLatents",
    "LatentCodec", "check_lambda", "DecodedScene", "EncodedScene",
]
