"""Reader of KITTI odometry scenes: ``poses.txt`` + ``calib.txt`` (+ optional ``images.txt``).

``poses.txt`` holds one line per frame: 12 numbers, the row-major 3x4 camera-to-world matrix of the
left grey camera (OpenCV axes: x right, y down, z forward; metres), as in KITTI's ground-truth pose files.
``calib.txt`` holds lines ``P0: p11 ... p34`` (row-major 3x4 projection matrices of the rectified
cameras); ``P0`` = K [I | 0] is the camera the poses belong to. KITTI puts pixel centres at integers, so
cx, cy are read +0.5 (our convention: pixel centres at +0.5). Line k of ``poses.txt`` belongs to line k
of ``images.txt`` (image paths relative to the folder) when that file exists, else to the k-th image of
``images/`` in natural order. The format has no depth bounds: near/far come from the arguments or from
:func:`~codecsplat_warp.data.scene.bounds_from_focus`.
"""

from __future__ import annotations

import pathlib

import numpy as np

from ..errors import DataError
from .scene import Scene, check_pose_values, list_images, require_file, shared_pinhole_scene

CALIB_FILE = "calib.txt"
IMAGE_LIST_FILE = "images.txt"
CAMERA = "P0"
"""The calib.txt projection the poses belong to (the left grey camera, KITTI ``image_0``)."""
PIXEL_CENTRE_SHIFT = 0.5
"""Added to KITTI's principal point (pixel centres at integers) to reach ours (pixel centres at +0.5)."""


def load_kitti(file, near: float | None = None, far: float | None = None) -> Scene:
    """Scene from a KITTI ``poses.txt`` with ``calib.txt`` next to it; ``near``/``far`` override the heuristic bounds.

    Raises:
        DataError: missing files, unparsable or non-finite numbers, a P0 that is not K [I | 0], pose and
            image counts that differ, invalid cameras (naming the file and the frame).
    """
    file = pathlib.Path(file)
    c2w = read_poses(file)
    fx, fy, cx, cy = read_calibration(file.parent / CALIB_FILE)
    folder = file.parent
    frame_names = _frame_names(folder)
    if len(frame_names) != len(c2w):
        raise DataError(f"{file}: {len(c2w)} pose lines but {len(frame_names)} images "
                        f"({folder / IMAGE_LIST_FILE if (folder / IMAGE_LIST_FILE).is_file() else folder / 'images'})")
    return shared_pinhole_scene(file, folder, frame_names, c2w, (fx, fy, cx, cy), near, far, f"kitti:{file}")


def read_poses(file: pathlib.Path) -> np.ndarray:
    """float64 [N,4,4] OpenCV camera-to-world matrices, one per non-empty line of a KITTI pose file.

    Raises:
        DataError: no pose, a line without exactly 12 numbers, NaN or Inf (naming the file and the frame).
    """
    lines = [line.split() for line in require_file(file).read_text().splitlines() if line.strip()]
    if not lines:
        raise DataError(f"{file}: holds no pose line")
    poses = np.tile(np.eye(4), (len(lines), 1, 1))
    for frame, fields in enumerate(lines):
        if len(fields) != 12:
            raise DataError(f"{file}: frame {frame}: expected 12 numbers (row-major 3x4 c2w), got {len(fields)} fields")
        try:
            poses[frame, :3] = np.array([float(x) for x in fields]).reshape(3, 4)
        except ValueError:
            raise DataError(f"{file}: frame {frame}: not a number in {fields}") from None
        check_pose_values(file, frame, "pose", poses[frame])
    return poses


def read_calibration(file: pathlib.Path, camera: str = CAMERA) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) in pixels, pixel centres at +0.5, from the ``camera`` line of a KITTI ``calib.txt``.

    Raises:
        DataError: missing file or line, not 12 numbers, NaN or Inf, or a projection that is not
            [[fx, 0, cx, 0], [0, fy, cy, 0], [0, 0, 1, 0]] (naming the file).
    """
    rows = {}
    for line in require_file(file).read_text().splitlines():
        name, _, values = line.partition(":")
        if values:
            rows[name.strip()] = values.split()
    if camera not in rows:
        raise DataError(f"{file}: no '{camera}:' line (found {', '.join(rows) or 'none'})")
    fields = rows[camera]
    try:
        P = np.array([float(x) for x in fields], dtype=np.float64)
    except ValueError:
        raise DataError(f"{file}: {camera}: not a number in {fields}") from None
    if P.shape != (12,):
        raise DataError(f"{file}: {camera}: expected 12 numbers (row-major 3x4 projection), got {len(fields)}")
    if not np.all(np.isfinite(P)):
        raise DataError(f"{file}: {camera} holds NaN or Inf")
    P = P.reshape(3, 4)
    zero = [P[0, 1], P[0, 3], P[1, 0], P[1, 3], P[2, 0], P[2, 1], P[2, 3]]
    if any(v != 0 for v in zero) or P[2, 2] != 1:
        raise DataError(f"{file}: {camera} must be [[fx, 0, cx, 0], [0, fy, cy, 0], [0, 0, 1, 0]] (the camera the "
                        f"poses belong to), got {P.tolist()}")
    return float(P[0, 0]), float(P[1, 1]), float(P[0, 2]) + PIXEL_CENTRE_SHIFT, float(P[1, 2]) + PIXEL_CENTRE_SHIFT


def _frame_names(folder: pathlib.Path) -> list[str]:
    """Image paths relative to ``folder``: the lines of ``images.txt``, else ``images/`` in natural order."""
    listing = folder / IMAGE_LIST_FILE
    if listing.is_file():
        names = [line.strip() for line in listing.read_text().splitlines() if line.strip()]
        if not names:
            raise DataError(f"{listing}: lists no image")
        return names
    return [f"images/{n}" for n in list_images(folder / "images", natural=True)]
