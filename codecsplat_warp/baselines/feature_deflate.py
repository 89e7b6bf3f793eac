"""Baseline (c), the paper's Table 4: the codec-free model's intermediate feature in float16, then Deflate.

The stream holds what the codec-free decoder path (:meth:`CodecSplat.decode_gaussians`) needs to rebuild the
Gaussians: the Gaussian-generation feature ``F_c`` [V,C_F,H/2,W/2] and the encoder depth ``D_enc`` [V,H,W],
both as float16 and Deflated, and the context cameras (K, the top three rows of w2c, near, far as float32,
Deflated; the image size in the header), so the stream describes the scene on its own as a CodecSplat
bitstream does.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np
import torch

from ..cameras import Cameras
from ..errors import BitstreamError
from .container import DEFLATE_LEVEL, pack, unpack

MAGIC = b"FF16"


@dataclass
class FeatureScene:
    """A decoded feature stream: ``feature`` [V,C_F,h,w] and ``depth`` [V,H,W] (float32) and the ``cameras``."""

    feature: torch.Tensor
    depth: torch.Tensor
    cameras: Cameras


@dataclass(frozen=True)
class FeatureDeflate:
    """float16 + Deflate of the intermediate feature (see the module docstring)."""

    setting: str = "float16 features"

    def encode(self, feature: torch.Tensor, depth: torch.Tensor, cameras: Cameras) -> bytes:
        """Compressed bytes of ``feature`` [V,C_F,h,w], ``depth`` [V,H,W] and the V context ``cameras``."""
        feature16 = feature.detach().to("cpu", torch.float16).contiguous()
        depth16 = depth.detach().to("cpu", torch.float16).contiguous()
        cams = cameras.to("cpu", torch.float32)
        camera_values = torch.cat([cams.K.reshape(-1), cams.w2c[:, :3, :].reshape(-1), cams.near, cams.far])
        header = {"feature": list(feature16.shape), "depth": list(depth16.shape),
                  "width": cameras.width, "height": cameras.height}
        parts = [zlib.compress(t.numpy().tobytes(), DEFLATE_LEVEL) for t in (feature16, depth16, camera_values)]
        return pack(MAGIC, header, parts)

    def decode(self, data: bytes, device: torch.device | str = "cpu") -> FeatureScene:
        """Feature, depth and cameras (float32, on ``device``) of bytes made by :meth:`encode`.

        Raises:
            BitstreamError: not such a stream, or corrupt.
        """
        header, parts = unpack(data, MAGIC)
        try:
            feature_shape, depth_shape = tuple(header["feature"]), tuple(header["depth"])
            arrays = [np.frombuffer(zlib.decompress(p), dtype=d) for p, d in zip(parts, ("<f2", "<f2", "<f4"))]
            feature = torch.from_numpy(arrays[0].reshape(feature_shape).astype(np.float32))
            depth = torch.from_numpy(arrays[1].reshape(depth_shape).astype(np.float32))
            views = feature_shape[0]
            values = torch.from_numpy(arrays[2].copy())
            K, rows, near, far = values.split([9 * views, 12 * views, views, views])
            w2c = torch.cat([rows.reshape(views, 3, 4), torch.tensor([[[0.0, 0.0, 0.0, 1.0]]]).expand(views, 1, 4)], 1)
            cameras = Cameras(K.reshape(views, 3, 3), w2c, near, far, int(header["width"]), int(header["height"]))
        except (KeyError, IndexError, TypeError, ValueError, RuntimeError, zlib.error) as exc:
            raise BitstreamError(f"corrupt feature stream: {exc}") from None
        return FeatureScene(feature.to(device), depth.to(device), cameras.to(device))
