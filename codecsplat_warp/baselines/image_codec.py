"""The image-codec baseline: each context photograph coded on its own as a lossy WebP or JPEG file (Pillow).

``codecsplat eval`` decodes the files and runs the codec-free model on the decoded photographs ("WebP + codec-free",
"JPEG + codec-free"): the sender transmits photographs, the receiver generates the Gaussians. The settings are fixed
for every quality:

* WebP: lossy, ``quality=q`` (0-100), ``method=6`` (libwebp's slowest and smallest); the lossy format is 4:2:0.
* JPEG: ``quality=q`` (1-100), 4:2:0 chroma subsampling, optimised Huffman tables (``optimize=True``), baseline
  (not progressive), with the JFIF header Pillow writes.

Each file is a complete image file and its bytes are counted as they are; the files hold no cameras.
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import torch
from PIL import Image, UnidentifiedImageError

from ..errors import BitstreamError, InputError


@dataclass(frozen=True)
class ImageFormat:
    """One lossy image format: its ``label`` in tables, Pillow's ``pillow`` name, the quality range
    [``lowest``, 100] Pillow takes, and the Pillow save ``options`` besides the quality."""

    label: str
    pillow: str
    lowest: int
    options: dict = field(default_factory=dict)


FORMATS = {
    "webp": ImageFormat("WebP", "WEBP", 0, {"method": 6}),
    "jpeg": ImageFormat("JPEG", "JPEG", 1, {"subsampling": 2, "optimize": True, "progressive": False}),
}
"""The formats :class:`ImageCodec` codes, by the name ``--baselines`` uses (subsampling 2 is Pillow's 4:2:0)."""


@dataclass(frozen=True)
class ImageCodec:
    """Codes uint8 RGB photographs as one image file each, in ``format`` (a key of :data:`FORMATS`) at ``quality``.

    Raises:
        InputError: an unknown format, or a quality that is not an integer in the format's range.
    """

    format: str
    quality: int

    def __post_init__(self) -> None:
        if self.format not in FORMATS:
            raise InputError(f"unknown image format {self.format!r}; choose one of {', '.join(FORMATS)}")
        lowest = FORMATS[self.format].lowest
        if isinstance(self.quality, bool) or not isinstance(self.quality, int) or not lowest <= self.quality <= 100:
            raise InputError(f"{self.label} quality must be an integer in [{lowest}, 100], got {self.quality!r}")

    @property
    def label(self) -> str:
        """The format's name as the tables print it (``WebP``, ``JPEG``)."""
        return FORMATS[self.format].label

    @property
    def setting(self) -> str:
        """Codec setting as the tables print it."""
        return f"q={self.quality}"

    def encode(self, images: np.ndarray) -> list[bytes]:
        """One image file per view of ``images``, uint8 RGB [V,H,W,3].

        Raises:
            InputError: ``images`` is not a uint8 [V,H,W,3] array with V >= 1.
        """
        if not isinstance(images, np.ndarray) or images.dtype != np.uint8 or images.ndim != 4 \
                or images.shape[-1] != 3 or images.shape[0] < 1:
            described = f"{images.dtype} {images.shape}" if isinstance(images, np.ndarray) else type(images).__name__
            raise InputError(f"images must be a uint8 [V,H,W,3] array, got {described}")
        spec = FORMATS[self.format]
        files = []
        for image in images:
            buffer = io.BytesIO()
            Image.fromarray(np.ascontiguousarray(image)).save(buffer, format=spec.pillow, quality=self.quality,
                                                               **spec.options)
            files.append(buffer.getvalue())
        return files

    def decode(self, files: Sequence[bytes], device: torch.device | str = "cpu") -> torch.Tensor:
        """The photographs of files made by :meth:`encode`: float32 [V,3,H,W] in [0,1] (pixel / 255) on ``device``.

        Raises:
            BitstreamError: no file, a file that is not an RGB image in this format or is truncated or corrupt, or
                files of different sizes.
        """
        if not files:
            raise BitstreamError(f"no {self.label} file to decode")
        pixels = [self._read(data, view) for view, data in enumerate(files)]
        sizes = sorted({p.shape[:2] for p in pixels})
        if len(sizes) > 1:
            raise BitstreamError(f"corrupt {self.label} files: the views differ in size (HxW {sizes})")
        return torch.from_numpy(np.stack(pixels)).permute(0, 3, 1, 2).to(device, torch.float32) / 255

    def _read(self, data: bytes, view: int) -> np.ndarray:
        """uint8 [H,W,3] pixels of one file (BitstreamError naming ``view`` when it is not a good one)."""
        spec = FORMATS[self.format]
        try:
            with Image.open(io.BytesIO(bytes(data))) as image:
                if image.format != spec.pillow or image.mode != "RGB":
                    raise BitstreamError(f"view {view}: not an RGB {self.label} file ({image.format} {image.mode})")
                image.load()
                return np.asarray(image)
        except UnidentifiedImageError:
            raise BitstreamError(f"view {view}: not a {self.label} file") from None
        # Pillow raises OSError for truncated or broken files, SyntaxError for some broken headers and
        # DecompressionBombError for absurd sizes.
        except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as exc:
            raise BitstreamError(f"corrupt {self.label} file of view {view}: {exc}") from None
