"""Reader of Strecha et al. scenes (EPFL dense multi-view stereo benchmark): ``gt_dense_cameras/<image>.camera``.

One text file per image: ``gt_dense_cameras/<name>.camera`` belongs to ``images/<name>`` (e.g. ``0000.jpg.camera``
to ``images/0000.jpg``), both folders in the scene folder. Nine lines of numbers:

======  =====================================================================================================
line    holds
======  =====================================================================================================
1-3     K, the 3x3 pinhole matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` in pixels at the stored image size
        (used as given: pixel centres at +0.5)
4       three lens distortion terms (ignored: pinhole; kept in ``Scene.metadata["distortion"]``)
5-7     R, camera-to-world rotation with OpenCV axes (x right, y down, z forward): its columns are the camera
        axes in world coordinates
8       C, the camera centre in world coordinates
9       ``w h``, the image size in pixels
======  =====================================================================================================

OpenCV c2w = [[R, C], [0, 1]]: a world point X projects to x ~ K Rᵀ (X − C). Frames are in natural order of
the file names. The format has no depth bounds: near/far come from the arguments or from
:func:`~codecsplat_warp.data.scene.bounds_from_focus`.
"""

from __future__ import annotations

import pathlib
from dataclasses import dataclass

import numpy as np

from ..errors import DataError
from .scene import (EncodedImages, Scene, cameras_from_arrays, depth_range, natural_key, require_file,
                    single_image_size)

CAMERA_FOLDER = "gt_dense_cameras"
CAMERA_SUFFIX = ".camera"
IMAGE_FOLDER = "images"
LINES = (("K", 3), ("K", 3), ("K", 3), ("distortion", 3), ("R", 3), ("R", 3), ("R", 3), ("camera centre", 3),
         ("w h", 2))
"""What each of the nine lines of a ``.camera`` file holds, and how many numbers."""


@dataclass(frozen=True)
class StrechaCamera:
    """One parsed ``.camera`` file: K float64 [3,3] (pixels), distortion float64 [3], c2w float64 [4,4]
    (OpenCV axes, world units), size (width, height) in pixels."""

    K: np.ndarray
    distortion: np.ndarray
    c2w: np.ndarray
    size: tuple[int, int]


def load_strecha(folder, near: float | None = None, far: float | None = None) -> Scene:
    """Scene from a Strecha ``gt_dense_cameras/`` folder, images in ``images/`` next to it; ``near``/``far``
    override the heuristic bounds.

    Raises:
        DataError: no ``*.camera`` file, a malformed file (naming the file and line), frames of different
            sizes, invalid cameras.
    """
    folder = pathlib.Path(folder)
    files = camera_files_of(folder)
    cameras = [read_camera(file) for file in files]
    root = folder.parent
    frame_names = [f"{IMAGE_FOLDER}/{file.name[:-len(CAMERA_SUFFIX)]}" for file in files]
    width, height = single_image_size(folder, [camera.size for camera in cameras])
    K = np.stack([camera.K for camera in cameras])
    c2w = np.stack([camera.c2w for camera in cameras])
    near, far = depth_range(c2w, near, far)
    return Scene(
        images=EncodedImages([root / name for name in frame_names], width, height),
        cameras=cameras_from_arrays(folder, K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], c2w, near, far,
                                    width, height),
        key=root.name,
        source=f"strecha:{folder}",
        frame_names=frame_names,
        metadata={"distortion": [camera.distortion.tolist() for camera in cameras]},
    )


def camera_files_of(folder: pathlib.Path) -> list[pathlib.Path]:
    """The ``*.camera`` files of a ``gt_dense_cameras/`` folder, natural order of their names.

    Raises:
        DataError: the folder is missing or holds no ``*.camera`` file.
    """
    files = sorted(folder.glob(f"*{CAMERA_SUFFIX}"), key=lambda p: natural_key(p.name)) if folder.is_dir() else []
    if not files:
        raise DataError(f"{folder}: no *{CAMERA_SUFFIX} file (Strecha gt_dense_cameras folder)")
    return files


def is_strecha_folder(folder: pathlib.Path) -> bool:
    """Whether ``folder`` is a folder holding ``*.camera`` files."""
    return folder.is_dir() and any(folder.glob(f"*{CAMERA_SUFFIX}"))


def read_camera(file: pathlib.Path) -> StrechaCamera:
    """Parse one ``.camera`` file (nine lines of numbers; trailing blank lines allowed).

    Raises:
        DataError: another line count, a line with the wrong count of numbers, text that is not a number,
            NaN or Inf, a K that is not a pinhole matrix, an image size that is not two positive whole numbers
            (naming the file and the line).
    """
    lines = require_file(file).read_text().rstrip().splitlines()
    if len(lines) != len(LINES):
        raise DataError(f"{file}: expected {len(LINES)} lines (K, distortion, R, camera centre, w h), got {len(lines)}")
    rows = [_numbers(file, number, line) for number, line in enumerate(lines, start=1)]
    K = np.array(rows[0:3])
    if K[0, 1] != 0 or K[1, 0] != 0 or not np.array_equal(K[2], [0.0, 0.0, 1.0]):
        raise DataError(f"{file}: lines 1-3 (K): expected a pinhole matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], "
                        f"got {K.tolist()}")
    c2w = np.eye(4)
    c2w[:3, :3] = rows[4:7]
    c2w[:3, 3] = rows[7]
    width, height = rows[8]
    if width != int(width) or height != int(height) or width <= 0 or height <= 0:
        raise DataError(f"{file}: line 9 (w h): expected two positive whole numbers, got {rows[8].tolist()}")
    return StrechaCamera(K=K, distortion=rows[3], c2w=c2w, size=(int(width), int(height)))


def _numbers(file: pathlib.Path, number: int, line: str) -> np.ndarray:
    """float64 values of line ``number`` (1-based) of a ``.camera`` file, checked against :data:`LINES`."""
    name, count = LINES[number - 1]
    fields = line.split()
    where = f"{file}: line {number} ({name})"
    if len(fields) != count:
        raise DataError(f"{where}: expected {count} numbers, got {len(fields)} fields")
    try:
        values = np.array([float(x) for x in fields], dtype=np.float64)
    except ValueError:
        raise DataError(f"{where}: not a number in {fields}") from None
    if not np.all(np.isfinite(values)):
        raise DataError(f"{where}: holds NaN or Inf")
    return values
