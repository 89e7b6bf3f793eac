"""Reader of Microsoft 7-Scenes style scenes: ``camera-intrinsics.txt`` + ``poses/<frame>.pose.txt``.

``camera-intrinsics.txt`` is a 3x3 pinhole matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` (pixels at the
stored image size, pixel centres at +0.5), shared by every frame. Each ``<frame>.pose.txt`` is a 4x4
camera-to-world matrix (OpenCV axes: x right, y down, z forward; metres), and belongs to the colour image
``<frame>.color.<ext>`` in ``images/`` (or next to the pose file, as the original dataset stores them).
Frames are in natural order of the pose file names. The format has no depth bounds (the depth maps are
not read): near/far come from the arguments or from :func:`~codecsplat_warp.data.scene.bounds_from_focus`.
"""

from __future__ import annotations

import pathlib

import numpy as np

from ..errors import DataError
from .scene import IMAGE_EXTENSIONS, Scene, natural_key, require_file, shared_pinhole_scene

INTRINSICS_FILE = "camera-intrinsics.txt"
POSE_FOLDER = "poses"
POSE_SUFFIX = ".pose.txt"
COLOR_SUFFIX = ".color"


def load_7scenes(file, near: float | None = None, far: float | None = None) -> Scene:
    """Scene from a ``camera-intrinsics.txt`` with its ``poses/`` folder next to it; ``near``/``far`` override
    the heuristic bounds.

    Raises:
        DataError: missing or malformed files, a pose without its colour image, invalid cameras (naming
            the file and the frame).
    """
    file = pathlib.Path(file)
    folder = file.parent
    fx, fy, cx, cy = read_intrinsics(file)
    pose_files = pose_files_of(folder)
    c2w = np.stack([read_pose(path, frame) for frame, path in enumerate(pose_files)])
    frame_names = [_color_image(folder, frame, path) for frame, path in enumerate(pose_files)]
    return shared_pinhole_scene(file, folder, frame_names, c2w, (fx, fy, cx, cy), near, far, f"7scenes:{file}")


def pose_files_of(folder: pathlib.Path) -> list[pathlib.Path]:
    """The ``*.pose.txt`` files of a scene, natural order: in ``poses/`` when it holds any, else in ``folder``."""
    for where in (folder / POSE_FOLDER, folder):
        files = sorted(where.glob(f"*{POSE_SUFFIX}"), key=lambda p: natural_key(p.name))
        if files:
            return files
    raise DataError(f"{folder}: no *{POSE_SUFFIX} file in {folder / POSE_FOLDER} or {folder}")


def read_intrinsics(file: pathlib.Path) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) in pixels from ``camera-intrinsics.txt``.

    Raises:
        DataError: not a 3x3 matrix of numbers, NaN or Inf, skew or a last row other than [0, 0, 1].
    """
    K = _read_matrix(file, (3, 3), f"{file}")
    if K[0, 1] != 0 or K[1, 0] != 0 or not np.array_equal(K[2], [0.0, 0.0, 1.0]):
        raise DataError(f"{file}: expected a pinhole matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}")
    return float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])


def read_pose(file: pathlib.Path, frame: int) -> np.ndarray:
    """float64 [4,4] camera-to-world matrix of one ``*.pose.txt`` (the last row must be [0, 0, 0, 1]).

    Raises:
        DataError: not a 4x4 matrix of numbers, NaN or Inf, or a bad last row (naming the file and frame).
    """
    c2w = _read_matrix(file, (4, 4), f"{file}: frame {frame}")
    if not np.array_equal(c2w[3], [0.0, 0.0, 0.0, 1.0]):
        raise DataError(f"{file}: frame {frame}: last row must be [0, 0, 0, 1], got {c2w[3].tolist()}")
    return c2w


def _read_matrix(file: pathlib.Path, shape: tuple[int, int], where: str) -> np.ndarray:
    """float64 matrix of ``shape`` from a whitespace-separated text file (one row per line); errors start
    with ``where``."""
    rows = [line.split() for line in require_file(file).read_text().splitlines() if line.strip()]
    try:
        matrix = np.array([[float(x) for x in row] for row in rows], dtype=np.float64)
    except ValueError:
        raise DataError(f"{where}: expected {shape[0]} rows of {shape[1]} numbers, found text that is not a "
                        "number") from None
    if matrix.shape != shape:
        raise DataError(f"{where}: expected {shape[0]} rows of {shape[1]} numbers, got {len(rows)} rows of "
                        f"{', '.join(sorted({str(len(r)) for r in rows})) or 'nothing'}")
    if not np.all(np.isfinite(matrix)):
        raise DataError(f"{where}: holds NaN or Inf")
    return matrix


def _color_image(folder: pathlib.Path, frame: int, pose_file: pathlib.Path) -> str:
    """Path (relative to ``folder``) of the colour image of a pose file: ``<stem>.color.<ext>``."""
    stem = pose_file.name[:-len(POSE_SUFFIX)] + COLOR_SUFFIX
    for where in (folder / "images", pose_file.parent):
        for ext in IMAGE_EXTENSIONS:
            if (where / (stem + ext)).is_file():
                return (where / (stem + ext)).relative_to(folder).as_posix()
    raise DataError(f"{pose_file}: frame {frame}: no colour image {stem}.* in {folder / 'images'} or {pose_file.parent}")
