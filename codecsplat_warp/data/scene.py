"""The :class:`Scene` every loader returns, lazily decoded images, and helpers shared by the loaders.

A scene is V posed RGB images sharing one size: ``images`` uint8 [V,3,H,W] (a tensor, or an
:class:`EncodedImages` sequence that decodes JPEG/PNG on access), ``cameras`` (:class:`Cameras` at the
stored image size; near/far live there), a ``key`` naming it and a ``source`` naming the format and file.
"""

from __future__ import annotations

import io
import os
import pathlib
import re
from dataclasses import dataclass, field
from typing import Callable, Sequence, Union

import numpy as np
import torch
from PIL import Image

from ..cameras import Cameras, intrinsics_matrix
from ..errors import CameraError, DataError

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp")
"""File endings treated as images when a loader lists an image folder."""

EncodedImage = Union[pathlib.Path, bytes]
"""One stored image: a file path, or the encoded bytes (JPEG/PNG) of a chunk."""


def decode_image(source: EncodedImage, frame: int) -> torch.Tensor:
    """Decode one image (file path or encoded bytes) to uint8 [3,H,W] RGB, EXIF orientation NOT applied.

    Raises:
        DataError: missing or undecodable file, naming the file (or chunk frame) and the frame index.
    """
    where = f"{source}" if isinstance(source, pathlib.Path) else "encoded bytes"
    try:
        with Image.open(source if isinstance(source, pathlib.Path) else io.BytesIO(source)) as img:
            array = np.asarray(img.convert("RGB"))
    except FileNotFoundError:
        raise DataError(f"frame {frame}: image file {where} does not exist") from None
    except (OSError, ValueError, Image.DecompressionBombError) as exc:
        raise DataError(f"frame {frame}: cannot decode image {where}: {exc}") from None
    return torch.from_numpy(array.copy()).permute(2, 0, 1).contiguous()


class EncodedImages(Sequence[torch.Tensor]):
    """A sequence of V encoded images that decodes each one when it is accessed.

    ``images[i]`` is uint8 [3,H,W]; ``images[slice or list]`` and :meth:`decode_all` are uint8 [n,3,H,W].
    Every decoded image is checked against the expected ``width`` x ``height`` (DataError naming the
    frame otherwise). Nothing is kept: caching is the caller's choice (see :mod:`.dataset`).
    """

    def __init__(self, sources: Sequence[EncodedImage], width: int, height: int):
        self.sources = list(sources)
        self.width = int(width)
        self.height = int(height)

    def __len__(self) -> int:
        return len(self.sources)

    @property
    def shape(self) -> tuple[int, int, int, int]:
        """(V, 3, H, W), as a decoded tensor would have."""
        return (len(self.sources), 3, self.height, self.width)

    def __getitem__(self, index):
        if isinstance(index, slice):
            return self.decode_many(range(*index.indices(len(self))))
        if isinstance(index, torch.Tensor):
            index = index.tolist()
        if isinstance(index, (list, tuple, range)):
            return self.decode_many(index)
        return self.decode(int(index))

    def decode(self, frame: int) -> torch.Tensor:
        """uint8 [3,H,W] of one frame."""
        if not -len(self) <= frame < len(self):
            raise IndexError(f"frame {frame} out of range for {len(self)} images")
        frame %= len(self)
        image = decode_image(self.sources[frame], frame)
        if tuple(image.shape[1:]) != (self.height, self.width):
            raise DataError(
                f"frame {frame}: image {_describe(self.sources[frame])} is {image.shape[2]}x{image.shape[1]}, "
                f"the cameras say {self.width}x{self.height}"
            )
        return image

    def decode_many(self, frames: Sequence[int]) -> torch.Tensor:
        """uint8 [n,3,H,W] of the given frames."""
        if len(frames) == 0:
            return torch.empty(0, 3, self.height, self.width, dtype=torch.uint8)
        return torch.stack([self.decode(int(f)) for f in frames])

    def decode_all(self) -> torch.Tensor:
        """uint8 [V,3,H,W] of every frame."""
        return self.decode_many(range(len(self)))


def _describe(source: EncodedImage) -> str:
    return str(source) if isinstance(source, pathlib.Path) else f"({len(source)} encoded bytes)"


@dataclass
class Scene:
    """V posed images of one scene.

    Attributes:
        images: uint8 [V,3,H,W] RGB tensor or an :class:`EncodedImages` that decodes on access.
        cameras: :class:`Cameras` at the stored image size (H, W), near/far included.
        key: short name of the scene (folder name, chunk key).
        source: where it came from, ``"<format>:<path>"``.
        frame_names: one name per view (image path relative to the scene folder, or ``"<key>/<index>"``).
        depth: optional float32 [V,H,W] ground-truth depth (camera z), e.g. from procedural scenes.
        metadata: free-form extra values of the format (chunk ``url`` and ``timestamps``, notes, ...).
    """

    images: torch.Tensor | EncodedImages
    cameras: Cameras
    key: str
    source: str
    frame_names: list[str]
    depth: torch.Tensor | None = None
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        V = self.cameras.num_views
        if len(self.images) != V or len(self.frame_names) != V:
            raise DataError(
                f"{self.source}: {len(self.images)} images, {len(self.frame_names)} frame names and {V} cameras "
                "must be equally many"
            )
        height, width = tuple(self.images.shape[-2:])
        if (width, height) != (self.cameras.width, self.cameras.height):
            raise DataError(
                f"{self.source}: images are {width}x{height}, cameras are {self.cameras.width}x{self.cameras.height}"
            )

    @property
    def num_views(self) -> int:
        return self.cameras.num_views

    def decoded_images(self, frames: Sequence[int] | None = None) -> torch.Tensor:
        """uint8 [n,3,H,W] of ``frames`` (all when None), decoding lazily stored images."""
        frames = list(range(self.num_views)) if frames is None else list(frames)
        if isinstance(self.images, EncodedImages):
            return self.images.decode_many(frames)
        return self.images[frames]

    def select(self, frames: Sequence[int]) -> "Scene":
        """The sub-scene of the given view indices (images decoded only if they already were)."""
        frames = [int(f) for f in frames]
        if isinstance(self.images, EncodedImages):
            images = EncodedImages([self.images.sources[f] for f in frames], self.images.width, self.images.height)
        else:
            images = self.images[frames]
        return Scene(
            images=images,
            cameras=self.cameras.select(frames),
            key=self.key,
            source=self.source,
            frame_names=[self.frame_names[f] for f in frames],
            depth=None if self.depth is None else self.depth[frames],
            metadata=dict(self.metadata),
        )


# --------------------------------------------------------------------------------------------------
# Helpers shared by the loaders
def natural_key(name: str) -> list:
    """Sort key that orders embedded numbers by value (``2.jpg`` before ``10.jpg``)."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name)]


def list_images(folder: pathlib.Path, natural: bool) -> list[str]:
    """Image file names in ``folder``, in natural order or in plain string order (as LLFF loaders sort).

    Raises:
        DataError: the folder is missing or holds no image.
    """
    if not folder.is_dir():
        raise DataError(f"image folder {folder} does not exist")
    names = [n for n in os.listdir(folder) if n.lower().endswith(IMAGE_EXTENSIONS)]
    if not names:
        raise DataError(f"image folder {folder} holds no image ({', '.join(IMAGE_EXTENSIONS)})")
    return sorted(names, key=natural_key) if natural else sorted(names)


def read_image_size(path: pathlib.Path | io.BytesIO, where: str) -> tuple[int, int]:
    """(width, height) from the header of an image file or buffer; DataError starting with ``where`` otherwise."""
    try:
        with Image.open(path) as img:
            return img.size
    except FileNotFoundError:
        raise DataError(f"{where}: image {path} does not exist") from None
    except OSError as exc:
        raise DataError(f"{where}: cannot read image {path}: {exc}") from None


def name_list(names: Sequence[str], shown: int = 5) -> str:
    """Up to ``shown`` names, comma separated, then how many more (``"none"`` when empty): for error messages."""
    more = f" and {len(names) - shown} more" if len(names) > shown else ""
    return ", ".join(names[:shown]) + more or "none"


def require_file(path: pathlib.Path) -> pathlib.Path:
    """``path`` when it is an existing file, else DataError naming it."""
    if not path.is_file():
        raise DataError(f"{path} does not exist")
    return path


def check_pose_values(file: pathlib.Path, frame: int, name: str, values) -> None:
    """DataError naming ``file`` and ``frame`` when ``values`` hold NaN or Inf."""
    if not np.all(np.isfinite(np.asarray(values, dtype=np.float64))):
        raise DataError(f"{file}: frame {frame}: {name} holds NaN or Inf")


def make_cameras(where: pathlib.Path | str, build: Callable[[], Cameras]) -> Cameras:
    """Run a Cameras constructor, re-raising CameraError as DataError that starts with ``where`` (message kept)."""
    try:
        return build()
    except CameraError as exc:
        raise DataError(f"{where}: {exc}") from None


def single_image_size(file: pathlib.Path, sizes: Sequence[tuple[int, int]]) -> tuple[int, int]:
    """The (width, height) all frames share; DataError naming the first frame that differs."""
    if not sizes:
        raise DataError(f"{file}: holds no frame")
    first = sizes[0]
    for frame, size in enumerate(sizes):
        if tuple(size) != tuple(first):
            raise DataError(
                f"{file}: frame {frame} is {size[0]}x{size[1]} but frame 0 is {first[0]}x{first[1]}; "
                "a scene must have one image size"
            )
    return int(first[0]), int(first[1])


def cameras_from_arrays(file: pathlib.Path, fx, fy, cx, cy, c2w, near, far, width: int, height: int) -> Cameras:
    """float64 Cameras from per-frame pixel intrinsics [V] and OpenCV c2w [V,4,4] (or [V,3,4]); errors name ``file``."""
    f64 = lambda x: torch.as_tensor(np.asarray(x, dtype=np.float64))  # noqa: E731
    K = intrinsics_matrix(f64(fx), f64(fy), f64(cx), f64(cy))
    V = K.shape[0]
    near_v = f64(near).expand(V).clone() if f64(near).dim() == 0 else f64(near)
    far_v = f64(far).expand(V).clone() if f64(far).dim() == 0 else f64(far)
    return make_cameras(file, lambda: Cameras.from_c2w(K, f64(c2w), near_v, far_v, width, height))


def bounds_from_focus(c2w: np.ndarray) -> tuple[float, float]:
    """Heuristic near/far for formats without depth bounds, from OpenCV c2w [V,4,4].

    Finds the point nearest (least squares) to all optical axes and returns 0.25 x the smallest and
    4 x the largest camera distance to it. When the axes are near-parallel (forward-facing captures)
    or the point lies behind the cameras, the mean optical axis is followed for 10 x the camera spread.
    """
    centres, axes = c2w[:, :3, 3], c2w[:, :3, 2]
    projectors = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
    A, b = projectors.sum(0), (projectors @ centres[:, :, None]).sum(0)[:, 0]
    eigen = np.linalg.eigvalsh(A)
    spread = max(float(np.linalg.norm(centres - centres.mean(0), axis=1).max()), 1e-6)
    focus = np.linalg.solve(A, b) if eigen[0] > 1e-3 * len(c2w) else None
    if focus is None or float(np.mean(((focus - centres) * axes).sum(1))) <= 0:
        focus = centres.mean(0) + axes.mean(0) * 10 * spread
    distances = np.linalg.norm(centres - focus, axis=1)
    near, far = 0.25 * float(distances.min()), 4.0 * float(distances.max())
    return max(near, 1e-3 * far), far


def depth_range(c2w: np.ndarray, near: float | None, far: float | None) -> tuple[float, float]:
    """(near, far): the given values, and :func:`bounds_from_focus` of OpenCV c2w [V,4,4] for those left None."""
    if near is None or far is None:
        guess_near, guess_far = bounds_from_focus(c2w)
        near, far = guess_near if near is None else near, guess_far if far is None else far
    return near, far


def shared_pinhole_scene(file: pathlib.Path, folder: pathlib.Path, frame_names: list[str], c2w: np.ndarray,
                         intrinsics: tuple[float, float, float, float], near: float | None, far: float | None,
                         source: str) -> Scene:
    """A scene of one pinhole camera (``intrinsics`` = fx, fy, cx, cy in pixels, centres at +0.5) at the poses
    ``c2w`` [V,4,4] (OpenCV camera-to-world), images ``folder/frame_names`` (their size read from the first);
    near/far from :func:`depth_range`. ``source`` names the format and file."""
    width, height = read_image_size(folder / frame_names[0], f"{file}: frame 0")
    near, far = depth_range(c2w, near, far)
    V = len(c2w)
    fx, fy, cx, cy = (np.full(V, value) for value in intrinsics)
    cameras = cameras_from_arrays(file, fx, fy, cx, cy, c2w, near, far, width, height)
    return Scene(images=EncodedImages([folder / n for n in frame_names], width, height), cameras=cameras,
                 key=folder.name, source=source, frame_names=frame_names)
